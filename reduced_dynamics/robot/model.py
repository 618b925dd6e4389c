# Copyright 2026 reduced_dynamics developers
#
# Licensed under the Apache License, Version 2.0 (the "License");
# you may not use this file except in compliance with the License.
# You may obtain a copy of the License at
#
#     http://www.apache.org/licenses/LICENSE-2.0
#
# Unless required by applicable law or agreed to in writing, software
# distributed under the License is distributed on an "AS IS" BASIS,
# WITHOUT WARRANTIES OR CONDITIONS OF ANY KIND, either express or implied.
# See the License for the specific language governing permissions and
# limitations under the License.

"""
The free-floating robot: Pinocchio model, base group, shape space and metric blocks.

Theorem 51 / Lemma 52: the kinetic energy is left-invariant in the base pose, so
the joint-space inertia evaluated with the base at identity,
``M(qbar) = crba(e, qbar) = [[I, B], [B^T, Mr]]``, gives the metric everywhere
(REDUCED_MODEL.md section 2).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping, Optional

import numpy as np
import pinocchio as pin

from reduced_dynamics.geometry.lie_group import BaseGroup, SUBGROUPS
from reduced_dynamics.robot.urdf import build_pinocchio_model, parse_urdf, UrdfError

BASE_GROUP_OF_JOINT = {'floating': 'SE(3)', 'planar': 'SE(2)'}


class ModelError(ValueError):
    """A robot model the reduction does not apply to."""


@dataclass
class MetricBlocks:
    """
    Blocks of M(qbar) and what follows from them (5.28, 5.29, Corollary 55).

    ``locked_inertia`` I (n x n, base frame), ``coupling`` B (n x m),
    ``shape_inertia`` Mr (m x m), ``connection`` A = I^-1 B (5.29) and
    ``reduced_metric`` S = Mr - B^T I^-1 B.
    """

    mass_matrix: np.ndarray
    locked_inertia: np.ndarray
    coupling: np.ndarray
    shape_inertia: np.ndarray
    connection: np.ndarray
    reduced_metric: np.ndarray
    locked_inverse: np.ndarray

    def solve_locked(self, covector: np.ndarray) -> np.ndarray:
        """I^-1 covector (e.g. the drift twist I^-1 pi)."""
        return self.locked_inverse @ covector


@dataclass
class KineticWorkspace:
    """
    Pinocchio handles for hot loops: M and C at the base identity without wrappers.

    ``q`` is a private configuration buffer (base at identity; write the shape
    into ``q[nq_base:]``); ``kinetic_model`` has zero gravity (Coriolis terms).
    The Data objects are the robot's own (one thread at a time, as everywhere).
    """

    model: pin.Model
    data: pin.Data
    kinetic_model: pin.Model
    kinetic_data: pin.Data
    q: np.ndarray
    nq_base: int


class RobotModel:
    """A free-floating open-chain robot with base group G = Q1 and shape Q2 x ... x QN."""

    def __init__(self, urdf: str = '', base_joint: Optional[str] = None,
                 gravity: Optional[np.ndarray] = None) -> None:
        """
        Load a URDF (path or XML text; default: the paper robot).

        ``gravity`` (world frame, m/s^2) defaults to zero. It must leave the
        potential invariant under the base group: zero for a floating base,
        normal to the plane (along z) for a planar base.
        """
        if not urdf:
            from reduced_dynamics.resources import paper_robot_urdf
            urdf = paper_robot_urdf()
        parsed = parse_urdf(urdf, base_joint)
        built = build_pinocchio_model(parsed)
        self.urdf = parsed
        self.model: pin.Model = built.model
        self.base_joint_type: str = parsed.base_joint_type
        self.base_link: str = parsed.base_link
        self.group: BaseGroup = SUBGROUPS[BASE_GROUP_OF_JOINT[parsed.base_joint_type]]
        self.shape_joint_names: tuple[str, ...] = built.shape_joint_names
        self.shape_joint_sources = built.shape_joint_sources
        #: URDF <limit> of the shape joints that declare one (plausibility gates)
        self.shape_joint_limits = built.shape_joint_limits
        self.gravity = np.zeros(3) if gravity is None else np.asarray(gravity, dtype=float)
        self._check_invariant_potential()
        self.model.gravity = pin.Motion(np.r_[self.gravity, 0.0, 0.0, 0.0])
        self.data = self.model.createData()
        # RNEA derivatives of M w need zero gravity; a copy avoids toggling the shared model.
        self._kinetic_model = pin.Model(self.model)
        self._kinetic_model.gravity = pin.Motion.Zero()
        self._kinetic_data = self._kinetic_model.createData()
        self.n = self.group.dim
        self.m = self.model.nv - self.n
        self.nq_base = self.model.joints[1].nq
        self._lower = np.tril_indices(self.model.nv, -1)
        self._has_potential = bool(np.any(self.gravity != 0.0))
        self._zero_v = np.zeros(self.model.nv)
        self._q_work = pin.neutral(self.model)
        self._base_identity_q = self._q_work[:self.nq_base].copy()
        self.total_mass = float(pin.computeTotalMass(self.model))
        if self.total_mass <= 0.0:
            raise ModelError('the robot has no mass')

    def worker_copy(self) -> 'RobotModel':
        """
        Return a copy sharing the (read-only) model but owning its Pinocchio Data.

        For computations in another thread (deferred predictions): every
        method writes only into Data objects and work buffers, which the copy
        has to itself.
        """
        copy = object.__new__(RobotModel)
        copy.__dict__.update(self.__dict__)
        copy.data = self.model.createData()
        copy._kinetic_data = self._kinetic_model.createData()
        copy._q_work = self._q_work.copy()
        copy._zero_v = self._zero_v.copy()
        return copy

    def _check_invariant_potential(self) -> None:
        norm = float(np.linalg.norm(self.gravity))
        if norm == 0.0:
            return
        if self.base_joint_type == 'floating':
            raise ModelError(
                'gravity with a floating base: the potential is not invariant under SE(3), '
                'so the momentum is not conserved and the reduction does not apply '
                '(use zero gravity, or a planar base with gravity normal to the plane)')
        if np.linalg.norm(self.gravity[:2]) > 1e-12 * norm:
            raise ModelError('planar base: gravity must be normal to the plane (along z) for '
                             'the potential to be invariant under SE(2)')

    @property
    def has_potential(self) -> bool:
        """Whether a (G-invariant) gravitational potential is present."""
        return self._has_potential

    def symmetry_report(self):
        """Return the cyclic-joint analysis of section 5.1 (computed once, then cached)."""
        if getattr(self, '_symmetry_report', None) is None:
            from reduced_dynamics.robot.symmetry import detect_symmetries
            self._symmetry_report = detect_symmetries(self)
        return self._symmetry_report

    # --- configurations -------------------------------------------------------------
    def full_configuration(self, g: pin.SE3, qbar: np.ndarray) -> np.ndarray:
        """Pinocchio q for base pose g and shape qbar."""
        q = np.empty(self.model.nq)
        q[:self.nq_base] = self.base_configuration(g)
        q[self.nq_base:] = qbar
        return q

    def base_configuration(self, g: pin.SE3) -> np.ndarray:
        """Pinocchio coordinates of the base joint for pose g."""
        if self.base_joint_type == 'floating':
            return pin.SE3ToXYZQUAT(g)
        yaw = float(np.arctan2(g.rotation[1, 0], g.rotation[0, 0]))
        return np.array([g.translation[0], g.translation[1], np.cos(yaw), np.sin(yaw)])

    def base_pose(self, q: np.ndarray) -> pin.SE3:
        """Return base pose g from Pinocchio q."""
        if self.base_joint_type == 'floating':
            return pin.XYZQUATToSE3(q[:7])
        yaw = float(np.arctan2(q[3], q[2]))
        return pin.SE3(pin.utils.rotate('z', yaw), np.array([q[0], q[1], 0.0]))

    def project_pose(self, g: pin.SE3) -> pin.SE3:
        """Return the closest element of the base group (x, y, yaw for a planar base)."""
        if self.base_joint_type == 'floating':
            return g
        return self.base_pose(self.base_configuration(g))

    def identity_configuration(self, qbar: np.ndarray) -> np.ndarray:
        """Compute q with the base at identity (a shared work buffer: copy if you keep it)."""
        self._q_work[:self.nq_base] = self._base_identity_q
        self._q_work[self.nq_base:] = qbar
        return self._q_work

    # --- metric -----------------------------------------------------------------------
    def mass_matrix(self, qbar: np.ndarray) -> np.ndarray:
        """M(qbar) = crba(e, qbar), symmetric (Lemma 52)."""
        # crba fills the upper triangle of a fresh array: mirror it in place.
        mass = pin.crba(self.model, self.data, self.identity_configuration(qbar))
        lower = self._lower
        mass[lower] = mass.T[lower]
        return mass

    def mass_matrix_upper(self, qbar: np.ndarray) -> np.ndarray:
        """
        M(qbar) = crba(e, qbar) with only its upper triangle guaranteed (Lemma 52).

        For LAPACK routines that read one triangle (``dposv``): mirroring costs
        as much as the call, and Pinocchio versions differ in what they put below.
        """
        return pin.crba(self.model, self.data, self.identity_configuration(qbar))

    def kinetic_workspace(self) -> KineticWorkspace:
        """Return handles for :meth:`mass_matrix_upper` / :meth:`coriolis_matrix` in a loop."""
        return KineticWorkspace(self.model, self.data, self._kinetic_model, self._kinetic_data,
                                pin.neutral(self.model), self.nq_base)

    def coriolis_matrix(self, qbar: np.ndarray, v: np.ndarray) -> np.ndarray:
        """
        Pinocchio's Coriolis matrix C(q, v) at the base identity, velocity v = [xi; qbar_dot].

        It satisfies ``M_dot = C + C^T`` (M_dot the derivative of M(qbar) along
        qbar_dot) and ``dT/dqbar = (C^T v)[n:]`` at fixed v (REDUCED_MODEL.md 8;
        checked against finite differences in the tests).
        """
        return pin.computeCoriolisMatrix(self._kinetic_model, self._kinetic_data,
                                         self.identity_configuration(qbar), v)

    def metric_blocks(self, qbar: np.ndarray) -> MetricBlocks:
        """Blocks I, B, Mr of M(qbar), the connection A (5.29) and reduced metric S."""
        mass = self.mass_matrix(qbar)
        n = self.n
        locked = mass[:n, :n]
        coupling = mass[:n, n:]
        shape = mass[n:, n:]
        # numpy on these small blocks: scipy's cho_factor/cho_solve wrappers cost more
        # than the factorisation. inv raises LinAlgError for a singular I.
        inverse = np.linalg.inv(locked)
        connection = inverse @ coupling
        reduced = shape - coupling.T @ connection
        return MetricBlocks(mass, locked, coupling, shape, connection,
                            0.5 * (reduced + reduced.T), inverse)

    def potential_energy(self, qbar: np.ndarray) -> float:
        """V(e, qbar): G-invariant gravitational potential (0 without gravity)."""
        if not self.has_potential:
            return 0.0
        return float(pin.computePotentialEnergy(self.model, self.data,
                                                self.identity_configuration(qbar)))

    def potential_gradient(self, qbar: np.ndarray) -> np.ndarray:
        """dV/dqbar at the base identity."""
        if not self.has_potential:
            return np.zeros(self.m)
        grav = pin.computeGeneralizedGravity(self.model, self.data,
                                             self.identity_configuration(qbar))
        return grav[self.n:].copy()

    def mass_matrix_derivative_action(self, qbar: np.ndarray,
                                      vectors: np.ndarray) -> np.ndarray:
        """
        d(M(qbar) w)/dqbar for each column w of ``vectors`` (REDUCED_MODEL.md 8).

        Returns an array (len(vectors), nv, m): RNEA derivatives with zero velocity,
        acceleration w and zero gravity. Base columns are dropped: M does not
        depend on the base pose (Theorem 51).
        """
        q = self.identity_configuration(qbar)
        zero, n = self._zero_v, self.n
        out = np.empty((len(vectors), self.model.nv, self.m))
        derivatives = pin.computeRNEADerivatives
        model, data = self._kinetic_model, self._kinetic_data
        for index, w in enumerate(vectors):
            out[index] = derivatives(model, data, q, zero, w)[0][:, n:]
        return out


#: ``base_joint`` value meaning "as the URDF declares it (floating if it does not)".
AUTO_BASE_JOINT = 'auto'


def load_robot(urdf: str = '', base_joint: Optional[str] = None,
               gravity: Optional[np.ndarray] = None,
               xacro_args: Optional[Mapping[str, str]] = None) -> RobotModel:
    """
    Load a robot model; URDF problems raise :class:`ModelError` with the reason.

    ``base_joint`` ``'auto'`` or None: the URDF's own world joint, else floating.
    A path ending in ``.xacro`` is expanded first, with ``xacro_args``
    (:mod:`reduced_dynamics.robot.xacro_file`).
    """
    from reduced_dynamics.robot.xacro_file import expand_xacro, is_xacro, XacroError
    try:
        if is_xacro(urdf):
            urdf = expand_xacro(urdf, xacro_args)
        elif xacro_args:
            raise ModelError(f'xacro arguments {sorted(xacro_args)} given, but the robot '
                             'description is not a .xacro file')
    except XacroError as error:
        raise ModelError(str(error)) from error
    try:
        return RobotModel(urdf, None if base_joint == AUTO_BASE_JOINT else base_joint, gravity)
    except UrdfError as error:
        raise ModelError(str(error)) from error
