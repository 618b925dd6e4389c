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
Second-stage reduction by the cyclic joints N at their momenta theta (Theorem 57).

The cyclic joints of :mod:`reduced_dynamics.robot.symmetry` (reaction wheels,
rotors) form an abelian group ``N``, so ``N_theta = N`` and the theta-shape space
is ``Q^ = (Q1/G_mu) x Q^shape`` with the cyclic angles removed. Reducing in two
stages equals reducing once by ``G x N`` at ``(mu, theta)`` (both groups act on
different factors and commute), which gives the computable form used here, with
the joint-space inertia split as base+cyclic ("locked", e) and kept joints (k):

    I_e = [[I, B_w], [B_w^T, M_ww]]     locked inertia of G x N
    A_e = I_e^-1 B_e                    connection of G x N (5.29)
    K^  = M_kk - B_e^T I_e^-1 B_e       the metric K^ of Theorem 57 (horizontal lift)
    pi_e = [pi(q~1); theta]             theta = M_w. v: the wheels' axial momenta
    H^  = 1/2 pi_e^T I_e^-1 pi_e + 1/2 p^^T K^-1 p^ (+ V)        (5.47)

``theta`` enters the amended potential and, through ``d(A_e^T pi_e)``, the
magnetic term: the curvature block is ``Xi^_mu + Xi_theta`` (5.37 for N). Wheel
motor torques ``tau_w`` change the momenta, ``theta_dot = tau_w``, and the kept
momentum picks up ``-A_w^T tau_w`` (the reaction on the rest of the robot). The
cyclic angles are reconstructed from ``[xi; theta_dot_angles] = I_e^-1 pi_e -
A_e q^_dot``, like the base pose.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Optional, Sequence, Union

import numpy as np
import pinocchio as pin

from reduced_dynamics.geometry.chart import CosetChart
from reduced_dynamics.geometry.isotropy import isotropy_algebra, IsotropyAlgebra, RANK_RTOL
from reduced_dynamics.integrators import Budget, integrate_adaptive
from reduced_dynamics.reduction.hamiltonian import kinetic_shape_derivatives
from reduced_dynamics.reduction.magnetic import magnetic_form
from reduced_dynamics.robot.model import ModelError, RobotModel
from reduced_dynamics.robot.momentum import momentum_map
from reduced_dynamics.robot.state import FreeFloatingState, TorqueLaw, zero_torque

#: Shape torques on all joints (kept and cyclic): an array or tau(qbar, qbar_dot).
Torque = Union[np.ndarray, Callable[[np.ndarray, np.ndarray], np.ndarray]]


class CyclicSplit:
    """Index bookkeeping: shape joints split into kept joints and cyclic joints (N)."""

    def __init__(self, robot: RobotModel, cyclic_joints: Sequence[str]) -> None:
        """
        Split the robot's shape joints.

        Unknown or repeated names, and joints that are not cyclic (the kinetic
        energy depends on them: :func:`reduced_dynamics.robot.symmetry.detect_symmetries`),
        raise ModelError with the reason: reducing by them would be silently wrong.
        """
        names = list(robot.shape_joint_names)
        unknown = [name for name in cyclic_joints if name not in names]
        if unknown:
            raise ModelError(f'unknown cyclic joint(s) {", ".join(unknown)}; the shape joints '
                             f'are {", ".join(names)}')
        if len(set(cyclic_joints)) != len(cyclic_joints):
            raise ModelError('cyclic joints listed twice')
        report = robot.symmetry_report()
        for joint in report.joints:
            if joint.name in cyclic_joints and not joint.cyclic:
                raise ModelError(f'joint {joint.name} cannot be reduced: {joint.explanation}')
        chosen = set(cyclic_joints)
        self.names = tuple(name for name in names if name in chosen)
        self.kept_names = tuple(name for name in names if name not in chosen)
        self.cyclic = np.array([names.index(name) for name in self.names], dtype=int)
        self.kept = np.array([names.index(name) for name in self.kept_names], dtype=int)
        n = robot.n
        self.n = n
        self.c = len(self.cyclic)
        self.mk = len(self.kept)
        #: rows/columns of M for the locked group G x N, and for the kept joints
        self.locked_rows = np.concatenate([np.arange(n), n + self.cyclic])
        self.kept_rows = n + self.kept
        self.order = np.concatenate([self.locked_rows, self.kept_rows])

    def full_shape(self, qhat: np.ndarray, cyclic: np.ndarray) -> np.ndarray:
        """Return qbar with the kept joints ``qhat`` and the cyclic joints ``cyclic``."""
        qbar = np.empty(self.mk + self.c)
        qbar[self.kept] = qhat
        qbar[self.cyclic] = cyclic
        return qbar


@dataclass
class SecondStageBlocks:
    """Blocks of M split by G x N (Theorem 57): I_e, B_e, M_kk, A_e and K^."""

    locked_inertia: np.ndarray
    coupling: np.ndarray
    shape_inertia: np.ndarray
    locked_inverse: np.ndarray
    connection: np.ndarray
    reduced_metric: np.ndarray

    @classmethod
    def from_mass(cls, split: CyclicSplit, mass: np.ndarray) -> 'SecondStageBlocks':
        """Split a joint-space inertia M (Pinocchio order) by G x N."""
        order = split.order
        permuted = mass[order][:, order]
        ne = split.n + split.c
        locked, coupling = permuted[:ne, :ne], permuted[:ne, ne:]
        shape = permuted[ne:, ne:]
        inverse = np.linalg.inv(locked)
        connection = inverse @ coupling
        reduced = shape - coupling.T @ connection
        return cls(locked, coupling, shape, inverse, connection, 0.5 * (reduced + reduced.T))

    def locked_momentum(self, locked_velocity: np.ndarray,
                        shape_rate: np.ndarray) -> np.ndarray:
        """pi_e = I_e [xi; theta_dot] + B_e q^_dot: [pi; theta] (rows of M v)."""
        return self.locked_inertia @ locked_velocity + self.coupling @ shape_rate


def second_stage_blocks(robot: RobotModel, split: CyclicSplit,
                        qbar: np.ndarray) -> SecondStageBlocks:
    """Return I_e, B_e, M_kk, I_e^-1, A_e = I_e^-1 B_e and K^ at qbar."""
    return SecondStageBlocks.from_mass(split, robot.mass_matrix(qbar))


@dataclass
class SecondStageTerms:
    """H^ (5.47) and its kept-shape derivatives at (pi_e, q^, p^), pi_e held fixed."""

    blocks: SecondStageBlocks
    locked_velocity: np.ndarray
    qhat_dot: np.ndarray
    locked_twist: np.ndarray
    energy: float
    dH_dqhat: np.ndarray
    curvature: np.ndarray


def second_stage_terms(robot: RobotModel, split: CyclicSplit, pi_e: np.ndarray,
                       qhat: np.ndarray, phat: np.ndarray) -> SecondStageTerms:
    """
    Evaluate H^, dH^/dq^, q^_dot = K^-1 p^, the locked twist and the curvature.

    The cyclic angles are set to zero: M does not depend on them (that is what
    makes them cyclic). The derivatives use the RNEA identities of
    REDUCED_MODEL.md 8 with the locked group G x N in place of G.
    """
    qbar = split.full_shape(qhat, np.zeros(split.c))
    blocks = second_stage_blocks(robot, split, qbar)
    u = blocks.locked_inverse @ pi_e
    qhat_dot = np.linalg.solve(blocks.reduced_metric, phat)
    # The curvature with pi_e = [pi; theta] fixed is Xi^_mu + Xi_theta together.
    dH, curvature = kinetic_shape_derivatives(robot, qbar, split.locked_rows, split.kept_rows,
                                              split.kept, blocks.connection, u, qhat_dot)
    energy = 0.5 * float(pi_e @ u) + 0.5 * float(phat @ qhat_dot)
    if robot.has_potential:
        dH += robot.potential_gradient(qbar)[split.kept]
        energy += robot.potential_energy(qbar)
    return SecondStageTerms(blocks, u, qhat_dot, u - blocks.connection @ qhat_dot, energy, dH,
                            curvature)


@dataclass
class SecondStageEvaluation:
    """One evaluation of the Theorem 57 vector field."""

    z_dot: np.ndarray
    xi: np.ndarray
    cyclic_rate: np.ndarray
    pi: np.ndarray
    energy: float
    terms: SecondStageTerms


class SecondStageSystem:
    """
    The robot reduced by G at mu and by its cyclic joints N at theta (Theorem 57).

    State ``z = (q~1, q^, p^, theta)``: chart of Q1/G_mu, kept shape, its
    reduced momentum, and the cyclic momenta theta (constant without wheel torques).
    """

    def __init__(self, robot: RobotModel, cyclic_joints: Sequence[str], mu: np.ndarray,
                 g_ref: pin.SE3, rank_rtol: float = RANK_RTOL) -> None:
        """Set up G_mu, the chart of Q1/G_mu at ``g_ref`` and the split of the shape."""
        self.robot = robot
        self.group = robot.group
        self.split_indices = CyclicSplit(robot, cyclic_joints)
        if self.split_indices.c == 0:
            raise ModelError('second-stage reduction needs at least one cyclic joint')
        self.mu = np.asarray(mu, dtype=float)
        self.isotropy: IsotropyAlgebra = isotropy_algebra(self.group, self.mu, rank_rtol)
        self.chart = CosetChart(self.group, self.isotropy.complement, pin.SE3(g_ref))
        self.k = self.isotropy.orbit_dim
        self.mk = self.split_indices.mk
        self.c = self.split_indices.c
        self.nz = self.k + 2 * self.mk + self.c

    @property
    def cyclic_joints(self) -> tuple[str, ...]:
        """Names of the cyclic joints (generators of N), in shape order."""
        return self.split_indices.names

    @property
    def kept_joints(self) -> tuple[str, ...]:
        """Names of the joints of the theta-shape space."""
        return self.split_indices.kept_names

    @classmethod
    def from_full_state(cls, robot: RobotModel, state: FreeFloatingState,
                        cyclic_joints: Sequence[str], rank_rtol: float = RANK_RTOL
                        ) -> tuple['SecondStageSystem', np.ndarray]:
        """Return the system through a full state and its z (q~1 = 0 at g)."""
        split = CyclicSplit(robot, cyclic_joints)
        blocks = second_stage_blocks(robot, split, state.qbar)
        velocity = np.concatenate([state.xi, state.qbar_dot])
        qhat_dot = velocity[split.kept_rows]
        pi_e = blocks.locked_momentum(velocity[split.locked_rows], qhat_dot)
        mu = momentum_map(robot.group, state.g, pi_e[:robot.n])
        system = cls(robot, cyclic_joints, mu, state.g, rank_rtol)
        z = np.concatenate([np.zeros(system.k), state.qbar[split.kept],
                            blocks.reduced_metric @ qhat_dot, pi_e[robot.n:]])
        return system, z

    def split(self, z: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(q~1, q^, p^, theta) views of z."""
        k, mk = self.k, self.mk
        return z[:k], z[k:k + mk], z[k + mk:k + 2 * mk], z[k + 2 * mk:]

    def body_momentum(self, q1: np.ndarray) -> np.ndarray:
        """pi(q~1) = Ad_chi(q~1)^T mu."""
        return self.group.Ad(self.chart.point(q1)).T @ self.mu

    def kinematics(self, z: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        """
        Return (pi, locked twist [xi; cyclic rates], q^_dot, H^) at z, no derivatives.

        ``[xi; theta_dot] = I_e^-1 pi_e - A_e q^_dot``, ``q^_dot = K^-1 p^`` and H^ (5.47).
        """
        pi, pi_e, qbar, blocks, u, qhat_dot = self._momenta(z)
        energy = 0.5 * float(pi_e @ u) + 0.5 * float(self.split(z)[2] @ qhat_dot) \
            + self.robot.potential_energy(qbar)
        return pi, u - blocks.connection @ qhat_dot, qhat_dot, energy

    def _momenta(self, z: np.ndarray) -> tuple:
        """(pi, pi_e, qbar, blocks, u = I_e^-1 pi_e, q^_dot = K^-1 p^) at z."""
        q1, qhat, phat, theta = self.split(z)
        pi = self.body_momentum(q1)
        pi_e = np.concatenate([pi, theta])
        qbar = self.split_indices.full_shape(qhat, np.zeros(self.c))
        blocks = second_stage_blocks(self.robot, self.split_indices, qbar)
        return (pi, pi_e, qbar, blocks, blocks.locked_inverse @ pi_e,
                np.linalg.solve(blocks.reduced_metric, phat))

    def _torques(self, tau: Torque, qhat: np.ndarray, qhat_dot: np.ndarray,
                 cyclic_rate: np.ndarray, cyclic_angles: Optional[np.ndarray]
                 ) -> tuple[np.ndarray, np.ndarray]:
        """Return (torques on the kept joints, wheel-motor torques) from an array or a law."""
        split = self.split_indices
        if callable(tau):
            angles = np.zeros(self.c) if cyclic_angles is None else cyclic_angles
            tau = tau(split.full_shape(qhat, angles), split.full_shape(qhat_dot, cyclic_rate))
        tau = np.asarray(tau, dtype=float)
        return tau[split.kept], tau[split.cyclic]

    def hamiltonian(self, z: np.ndarray) -> float:
        """H^ (5.47): amended potential of G x N plus the kept-shape kinetic energy."""
        return self.kinematics(z)[3]

    def evaluate(self, z: np.ndarray, tau: Torque,
                 cyclic_angles: Optional[np.ndarray] = None) -> SecondStageEvaluation:
        """
        Return the vector field of Theorem 57 at z with joint torques tau (all joints).

        ``tau`` is an array over the full shape or tau(qbar, qbar_dot); the cyclic
        angles (reconstructed separately) only matter to a torque law.
        """
        k = self.k
        split = self.split_indices
        q1, qhat, phat, theta = self.split(z)
        pi = self.body_momentum(q1)
        pi_e = np.concatenate([pi, theta])
        terms = second_stage_terms(self.robot, split, pi_e, qhat, phat)
        n = self.robot.n
        connection = terms.blocks.connection
        jac = self.chart.body_jacobian(q1)
        form, kirillov_jac = magnetic_form(self.group, pi, jac, connection[:n],
                                           terms.curvature)
        dH_dq1 = -(kirillov_jac.T @ terms.locked_velocity[:n])
        qhat_dot = terms.qhat_dot
        if k:
            q1_dot = np.linalg.solve(form[:k, :k].T, -dH_dq1 - form[k:, :k].T @ qhat_dot)
        else:
            q1_dot = np.zeros(0)
        cyclic_rate = terms.locked_twist[n:]
        kept_torque, wheel_torque = self._torques(tau, qhat, qhat_dot, cyclic_rate,
                                                  cyclic_angles)
        x_dot = np.concatenate([q1_dot, qhat_dot])
        phat_dot = -terms.dH_dqhat - form[:, k:].T @ x_dot + kept_torque \
            - connection[n:].T @ wheel_torque
        z_dot = np.concatenate([q1_dot, qhat_dot, phat_dot, wheel_torque])
        return SecondStageEvaluation(z_dot, terms.locked_twist[:n], cyclic_rate, pi,
                                     terms.energy, terms)

    def vector_field(self, z: np.ndarray, tau: Torque,
                     cyclic_angles: Optional[np.ndarray] = None
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """
        Return (z_dot, xi, cyclic rates): :meth:`evaluate` by the Coriolis route.

        As for the first stage (``ReducedSystem.vector_field``): with ``u~`` the
        locked velocity ``I_e^-1 pi_e`` on the locked rows, ``w = [-A_e q^_dot;
        q^_dot]`` and Pinocchio's C(q, v), ``M_dot = C + C^T`` and
        ``p_dot = C^T v + tau`` give ``p^_dot = [-A_e; 1]^T (C^T w - C u~) + tau_k
        - A_w^T tau_w - dV/dq^``; the orbit equation is ``L^T W^T L q~1_dot =
        L^T W^T xi``. No derivative tensor, no magnetic matrix.
        """
        k, mk = self.k, self.mk
        split = self.split_indices
        q1, qhat = z[:k], z[k:k + mk]
        pi, _, qbar, blocks, u, qhat_dot = self._momenta(z)
        nv = self.robot.model.nv
        drift = np.zeros(nv)
        drift[split.locked_rows] = u
        w = np.empty(nv)
        w[split.locked_rows] = -blocks.connection @ qhat_dot
        w[split.kept_rows] = qhat_dot
        v = drift + w
        coriolis = self.robot.coriolis_matrix(qbar, v)
        h = w @ coriolis - coriolis @ drift
        n = self.robot.n
        locked_twist = v[split.locked_rows]
        xi, cyclic_rate = locked_twist[:n], locked_twist[n:]
        kept_torque, wheel_torque = self._torques(tau, qhat, qhat_dot, cyclic_rate,
                                                  cyclic_angles)
        phat_dot = h[split.kept_rows] - blocks.connection.T @ h[split.locked_rows] \
            + kept_torque - blocks.connection[n:].T @ wheel_torque
        if self.robot.has_potential:
            phat_dot -= self.robot.potential_gradient(qbar)[split.kept]
        z_dot = np.empty(self.nz)
        z_dot[k:k + mk] = qhat_dot
        z_dot[k + mk:k + 2 * mk] = phat_dot
        z_dot[k + 2 * mk:] = wheel_torque
        if k:
            jac = self.chart.body_jacobian(q1)
            kirillov_t = jac.T @ self.group.coadjoint_form(pi).T
            z_dot[:k] = np.linalg.solve(kirillov_t @ jac, kirillov_t @ xi)
        return z_dot, xi, cyclic_rate

    def recentre(self, z: np.ndarray) -> np.ndarray:
        """Move the chart centre to chi(q~1); returns z with q~1 = 0."""
        self.chart = self.chart.recentred(z[:self.k])
        out = z.copy()
        out[:self.k] = 0.0
        return out

    def full_state(self, z: np.ndarray, g: pin.SE3,
                   cyclic_angles: np.ndarray) -> FreeFloatingState:
        """Return the full state at z with base pose g and cyclic angles (reconstructed)."""
        _, twist, qhat_dot, _ = self.kinematics(z)
        split = self.split_indices
        n = self.robot.n
        return FreeFloatingState(pin.SE3(g), twist[:n].copy(),
                                 split.full_shape(self.split(z)[1], cyclic_angles),
                                 split.full_shape(qhat_dot, twist[n:]))


class SecondStagePropagator:
    """
    Theorem 57 plus reconstruction of the cyclic angles and of the base pose.

    y = (z, cyclic angles, eta) with g = g_seg exp(eta).
    """

    def __init__(self, system: SecondStageSystem, g0: pin.SE3,
                 cyclic_angles: np.ndarray, torque: Optional[TorqueLaw] = None) -> None:
        """Propagate from base pose g0 and cyclic angles under a joint-torque law."""
        self.system = system
        self.group = system.group
        self.torque = torque or zero_torque(system.robot.m)
        self.g_seg = pin.SE3(g0)
        self.angles0 = np.asarray(cyclic_angles, dtype=float).copy()
        self.nz = system.nz
        self.c = system.c

    @classmethod
    def from_full_state(cls, robot: RobotModel, state: FreeFloatingState,
                        cyclic_joints: Sequence[str], torque: Optional[TorqueLaw] = None
                        ) -> tuple['SecondStagePropagator', np.ndarray]:
        """Return the propagator through a full state and its initial y."""
        system, z = SecondStageSystem.from_full_state(robot, state, cyclic_joints)
        angles = state.qbar[system.split_indices.cyclic]
        return (cls(system, state.g, angles, torque),
                np.concatenate([z, angles, np.zeros(robot.n)]))

    def pose(self, y: np.ndarray) -> pin.SE3:
        """Reconstructed base pose of y."""
        return self.g_seg * self.group.exp(y[self.nz + self.c:])

    def rhs(self, t: float, y: np.ndarray) -> np.ndarray:
        """dy/dt: Theorem 57, cyclic angle rates and g_dot = g xi."""
        angles = y[self.nz:self.nz + self.c]
        z_dot, xi, cyclic_rate = self.system.vector_field(
            y[:self.nz], lambda qbar, qbar_dot: self.torque(t, qbar, qbar_dot), angles)
        eta_dot = self.group.right_jacobian_inverse(y[self.nz + self.c:]) @ xi
        return np.concatenate([z_dot, cyclic_rate, eta_dot])

    def chart_size(self, y: np.ndarray) -> float:
        """Largest of the orbit-chart and base-chart coordinate norms."""
        return max(float(np.linalg.norm(y[:self.system.k])),
                   float(np.linalg.norm(y[self.nz + self.c:])))

    def recentre(self, y: np.ndarray) -> np.ndarray:
        """Re-centre the chart of Q1/G_mu and the base-pose chart."""
        self.g_seg = self.pose(y)
        out = y.copy()
        out[:self.nz] = self.system.recentre(y[:self.nz])
        out[self.nz + self.c:] = 0.0
        return out

    def observe(self, t: float, y: np.ndarray) -> np.ndarray:
        """[g (16), pi(q~1), qbar, qbar_dot, theta, H^]: qbar with reconstructed angles."""
        z = y[:self.nz]
        system, split = self.system, self.system.split_indices
        pi, twist, qhat_dot, energy = system.kinematics(z)
        n = system.robot.n
        qbar = split.full_shape(system.split(z)[1], y[self.nz:self.nz + self.c])
        qbar_dot = split.full_shape(qhat_dot, twist[n:])
        return np.concatenate([self.pose(y).homogeneous.ravel(), pi, qbar, qbar_dot,
                               system.split(z)[3], [energy]])

    def propagate(self, y0: np.ndarray, times: Sequence[float], rtol: float = 1e-11,
                  atol: float = 1e-12, budget: Optional[Budget] = None
                  ) -> 'SecondStageTrajectory':
        """Integrate with adaptive DOP853 from times[0] and sample at ``times``."""
        times = np.asarray(times, dtype=float)
        records = integrate_adaptive(self, y0, times, 'DOP853', rtol, atol, budget=budget)
        return SecondStageTrajectory(self.system, times, records)


class SecondStageTrajectory:
    """Samples of a second-stage run: poses, pi, full shape and rates, theta, H^."""

    def __init__(self, system: SecondStageSystem, times: np.ndarray,
                 records: np.ndarray) -> None:
        """Split observe() records into named arrays."""
        n, m, c = system.group.dim, system.robot.m, system.c
        self.times = times
        self.poses = records[:, :16].reshape(-1, 4, 4)
        self.pi = records[:, 16:16 + n]
        self.qbar = records[:, 16 + n:16 + n + m]
        self.qbar_dot = records[:, 16 + n + m:16 + n + 2 * m]
        self.theta = records[:, 16 + n + 2 * m:16 + n + 2 * m + c]
        self.energy = records[:, -1]

    def pose(self, index: int) -> pin.SE3:
        """Reconstructed base pose at sample ``index``."""
        return pin.SE3(self.poses[index])
