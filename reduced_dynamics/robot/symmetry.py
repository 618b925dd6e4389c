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
Further symmetries of the shape space: which joints are cyclic (section 5.1).

Every shape joint here is one-dimensional, so the only candidate subgroup of its
group ``Q_i`` is the whole joint group (rotation about, or translation along, its
axis). A joint is *cyclic* when the kinetic energy, and the potential if any, do
not change when it moves, for every configuration: condition (5.43) for left
translation (the moving joint carries its subtree), (5.46) for right translation at
an extremity (an axisymmetric rotor). For one-dimensional groups both say
``dM/dq_i = 0`` (and ``dV/dq_i = 0``), which is what :func:`detect_symmetries`
tests numerically at seeded random configurations, relative to the inertias.
Two closed-form certificates explain the result in words:

* (5.46) at an extremity: ``Y ad_rho + ad_rho^T Y = 0`` for the body's spatial
  inertia ``Y`` in the joint frame and the joint twist ``rho`` (centre of mass on
  the axis, inertia axisymmetric about it);
* Proposition 56 for a joint on the base: ``ad_varpi(tau_1) = 0`` for every base
  motion ``tau_1`` (sufficient, not necessary).

The cyclic joints form the group ``N`` of the second-stage reduction (Theorem 57).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple, Optional

import numpy as np
import pinocchio as pin

from reduced_dynamics.robot.model import RobotModel

#: Relative tolerance of the invariance tests (round-off is ~1e-15; a 0.1 mm offset
#: of a 5 kg rotor's centre of mass on the example robot is ~1e-6).
SYMMETRY_RTOL = 1e-9
#: Seeded random configurations at which (5.43) is tested, besides the home pose.
SAMPLE_CONFIGURATIONS = 12


@dataclass
class JointSymmetry:
    """The verdict on one shape joint and why."""

    name: str
    kind: str
    extremity: bool
    cyclic: bool
    invariance_residual: float
    potential_residual: float
    rotor_residual: Optional[float]
    proposition56: Optional[bool]
    explanation: str
    rtol: float = SYMMETRY_RTOL

    @property
    def certificate(self) -> str:
        """Which condition of the paper establishes the symmetry ('' if none)."""
        if not self.cyclic:
            return ''
        if self.rotor_residual is not None and self.rotor_residual <= self.rtol:
            return '(5.46)'
        if self.proposition56:
            return 'Proposition 56'
        return '(5.43)'


@dataclass
class SymmetryReport:
    """Symmetry analysis of a robot: one :class:`JointSymmetry` per shape joint."""

    robot_name: str
    base_group: str
    joints: list[JointSymmetry] = field(default_factory=list)
    configurations: int = 0
    rtol: float = SYMMETRY_RTOL

    @property
    def cyclic_joints(self) -> tuple[str, ...]:
        """Names of the cyclic joints (the generators of N), in shape order."""
        return tuple(joint.name for joint in self.joints if joint.cyclic)

    @property
    def group(self) -> str:
        """Name the symmetry group N of the second stage (e.g. SO(2)^3, or trivial)."""
        rotations = sum(1 for j in self.joints if j.cyclic and j.kind == 'revolute')
        translations = sum(1 for j in self.joints if j.cyclic and j.kind == 'prismatic')
        factors = [f'SO(2)^{rotations}' if rotations > 1 else 'SO(2)'] if rotations else []
        if translations:
            factors.append(f'R^{translations}' if translations > 1 else 'R')
        return ' x '.join(factors) or 'trivial'

    def format(self) -> str:
        """Human-readable report, one line per joint."""
        lines = [f'robot {self.robot_name}: base group {self.base_group}, '
                 f'{len(self.joints)} shape joints, invariance tested at '
                 f'{self.configurations} configurations (relative tolerance '
                 f'{self.rtol:g})']
        width = max([len(j.name) for j in self.joints] + [5])
        lines.append(f'  {"joint":<{width}}  {"verdict":<10}  {"|dM/dq|":>8}  (5.43)  '
                     'Prop56  (5.46)  why')
        for joint in self.joints:
            verdict = 'cyclic' if joint.cyclic else 'not cyclic'
            left = 'holds' if joint.invariance_residual <= self.rtol else 'fails'
            prop56 = 'n/a' if joint.proposition56 is None else \
                ('holds' if joint.proposition56 else 'fails')
            right = 'n/a' if joint.rotor_residual is None else \
                ('holds' if joint.rotor_residual <= self.rtol else 'fails')
            lines.append(f'  {joint.name:<{width}}  {verdict:<10}  '
                         f'{joint.invariance_residual:8.1e}  {left:<6}  {prop56:<6}  '
                         f'{right:<6}  {joint.explanation}')
        cyclic = ', '.join(self.cyclic_joints)
        lines.append(f'second-stage group N = {self.group}'
                     + (f' (cyclic joints: {cyclic}; Theorem 57 applies)' if cyclic
                        else ': no further reduction'))
        return '\n'.join(lines)


def _joint_twist(model: pin.Model, data: pin.Data, joint_id: int) -> np.ndarray:
    """Return the joint motion subspace (6,) in its own frame (after forward kinematics)."""
    return np.asarray(data.joints[joint_id].S).reshape(6, -1)[:, 0].copy()


def rotor_residual(inertia: pin.Inertia, twist: np.ndarray) -> float:
    """
    Residual of (5.46) for a body at an extremity: ``|Y ad_rho + ad_rho^T Y| / |Y|``.

    ``h(ad_rho V, V) = 0`` for all twists V is the skew-symmetry of ``Y ad_rho``.
    """
    matrix = inertia.matrix()
    scale = float(np.linalg.norm(matrix))
    if scale == 0.0:
        return 0.0
    ad = pin.Motion(twist).action
    product = matrix @ ad
    return float(np.linalg.norm(product + product.T)) / scale


def _rotor_explanation(inertia: pin.Inertia, twist: np.ndarray, kind: str,
                       rtol: float) -> str:
    """Say in words why a body at an extremity is not an axisymmetric rotor."""
    if kind == 'prismatic':
        return ('not cyclic: sliding its body along the axis changes how base rotations '
                'move it (5.46 fails for a translation)')
    axis = twist[3:] / np.linalg.norm(twist[3:])
    com = inertia.lever
    offset = com - (com @ axis) * axis
    reasons = []
    length_scale = np.sqrt(max(np.trace(inertia.inertia), 1e-300) / max(inertia.mass, 1e-300))
    if np.linalg.norm(offset) > rtol * length_scale:
        reasons.append(f'its centre of mass is {1e3 * np.linalg.norm(offset):.3g} mm off '
                       'the joint axis')
    rotational = inertia.inertia
    cross = rotational @ axis - (axis @ rotational @ axis) * axis
    basis = np.linalg.svd(axis.reshape(1, 3))[2][1:]
    transverse = np.linalg.eigvalsh(basis @ rotational @ basis.T)
    size = max(np.trace(rotational), 1e-300)
    if np.linalg.norm(cross) > rtol * size or transverse[1] - transverse[0] > rtol * size:
        reasons.append('its inertia is not axisymmetric about the axis (transverse moments '
                       f'{transverse[0]:.4g} and {transverse[1]:.4g} kg m^2)')
    if not reasons:
        reasons.append('its body inertia changes under rotation about the axis')
    return 'not cyclic: ' + ' and '.join(reasons) + ' (5.46 fails)'


def _proposition56(robot: RobotModel, joint_id: int, twist: np.ndarray,
                   rtol: float) -> Optional[bool]:
    """Whether the joint's twist commutes with every base motion (joints on the base)."""
    model = robot.model
    if model.parents[joint_id] != 1:
        return None
    varpi = model.jointPlacements[joint_id].act(pin.Motion(twist)).vector
    brackets = pin.Motion(varpi).action @ robot.group.algebra_basis
    return bool(np.linalg.norm(brackets) <= rtol * np.linalg.norm(varpi))


class JointScales(NamedTuple):
    """What makes the residuals dimensionless: slides are measured in radii of gyration."""

    slides: np.ndarray
    radius: float
    per_joint: np.ndarray

    @classmethod
    def of(cls, robot: RobotModel) -> 'JointScales':
        """Return the scales of a robot (one ccrba at the home pose)."""
        model = robot.model
        slides = np.array([model.joints[j].shortname().startswith('JointModelP')
                           for j in range(2, model.njoints)], dtype=bool)
        data = model.createData()
        pin.ccrba(model, data, pin.neutral(model), np.zeros(model.nv))
        radius = float(np.sqrt(np.trace(data.Ig.inertia) / robot.total_mass))
        return cls(slides, radius, np.where(slides, radius, 1.0))


def _sample_configurations(robot: RobotModel, slides: np.ndarray, count: int,
                           seed: int) -> list[np.ndarray]:
    """Home plus seeded random shapes (angles in [-pi, pi], slides in [-0.5, 0.5] m)."""
    rng = np.random.default_rng(seed)
    samples = [np.zeros(robot.m)]
    for _ in range(count):
        sample = rng.uniform(-np.pi, np.pi, robot.m)
        sample[slides] = rng.uniform(-0.5, 0.5, int(slides.sum()))
        samples.append(sample)
    return samples


def mass_matrix_sensitivity(robot: RobotModel, qbar: np.ndarray,
                            scales: Optional[JointScales] = None) -> np.ndarray:
    """
    Return ``max_kl |dM_kl/dq_i| / sqrt(M_kk M_ll)`` for each shape joint i.

    Slides are scaled by the robot's radius of gyration so the residual is
    dimensionless for both joint kinds.
    """
    scales = scales or JointScales.of(robot)
    mass = robot.mass_matrix(qbar)
    identity = np.eye(robot.model.nv)
    derivative = robot.mass_matrix_derivative_action(qbar, identity)  # (k, nv, i)
    scale = np.sqrt(np.diag(mass))
    normalised = np.abs(derivative) / (scale[:, None, None] * scale[None, :, None])
    return normalised.max(axis=(0, 1)) * scales.per_joint


def _potential_sensitivity(robot: RobotModel, qbar: np.ndarray,
                           scales: JointScales) -> np.ndarray:
    """``|dV/dq_i|`` relative to ``m g L`` (zero without gravity)."""
    if not robot.has_potential:
        return np.zeros(robot.m)
    weight = robot.total_mass * float(np.linalg.norm(robot.gravity))
    return np.abs(robot.potential_gradient(qbar)) * scales.per_joint / (weight * scales.radius)


def detect_symmetries(robot: RobotModel, rtol: float = SYMMETRY_RTOL,
                      configurations: int = SAMPLE_CONFIGURATIONS,
                      seed: int = 0) -> SymmetryReport:
    """
    Decide for every shape joint whether it is cyclic, and explain why (5.43-5.46).

    ``rtol`` bounds ``|dM/dq_i|`` relative to the inertias (and ``|dV/dq_i|``
    relative to ``m g L``) at every sampled configuration.
    """
    model = robot.model
    data = model.createData()
    pin.forwardKinematics(model, data, pin.neutral(model))
    invariance = np.zeros(robot.m)
    potential = np.zeros(robot.m)
    scales = JointScales.of(robot)
    samples = _sample_configurations(robot, scales.slides, configurations, seed)
    for qbar in samples:
        invariance = np.maximum(invariance, mass_matrix_sensitivity(robot, qbar, scales))
        potential = np.maximum(potential, _potential_sensitivity(robot, qbar, scales))
    report = SymmetryReport(model.name, robot.group.name, configurations=len(samples),
                            rtol=rtol)
    for index, name in enumerate(robot.shape_joint_names):
        joint_id = index + 2
        twist = _joint_twist(model, data, joint_id)
        kind = 'prismatic' if scales.slides[index] else 'revolute'
        extremity = len(model.subtrees[joint_id]) == 1
        rotor = rotor_residual(model.inertias[joint_id], twist) if extremity else None
        prop56 = _proposition56(robot, joint_id, twist, rtol)
        cyclic = bool(invariance[index] <= rtol and potential[index] <= rtol)
        explanation = _explain(kind, cyclic, rotor, prop56, invariance[index],
                               potential[index], model.inertias[joint_id], twist, rtol)
        report.joints.append(JointSymmetry(name, kind, extremity, cyclic,
                                           float(invariance[index]), float(potential[index]),
                                           rotor, prop56, explanation, rtol))
    return report


def _explain(kind: str, cyclic: bool, rotor: Optional[float], prop56: Optional[bool],
             invariance: float, potential: float, inertia: pin.Inertia, twist: np.ndarray,
             rtol: float) -> str:
    """One sentence on the verdict, citing the condition that decides it."""
    motion = 'axis' if kind == 'revolute' else 'slide axis'
    if cyclic:
        if rotor is not None and rotor <= rtol:
            return (f'cyclic: its body is axisymmetric about the joint {motion} with the '
                    'centre of mass on it (5.46, right translation at an extremity)')
        if prop56:
            return ('cyclic: its axis commutes with every base motion (Proposition 56, '
                    'left translation)')
        return ('cyclic: moving it with its subtree leaves the kinetic energy unchanged '
                '(5.43, left translation)')
    if potential > rtol and invariance <= rtol:
        return 'not cyclic: the kinetic energy is invariant but gravity depends on it'
    if rotor is not None and rotor > rtol:
        return _rotor_explanation(inertia, twist, kind, rtol)
    return (f'not cyclic: moving it changes the inertia the rest of the robot sees '
            f'(5.43 fails, |dM/dq| {invariance:.2g} of the inertias)')
