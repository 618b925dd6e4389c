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
Simulated sensor bags: full free-floating dynamics written as a rosbag2 (MCAP) bag.

``reduced-dynamics simulate`` (and :func:`simulate_bag`) integrates the full
dynamics (Pinocchio ``aba``, DOP853 at rtol = atol = 1e-13) and writes, at a fixed
rate, ``/joint_states``, ``/odom`` (or ``/base_pose``) and the noise-free
ground truth ``/ground_truth/momentum`` and ``/ground_truth/external_wrench``.
Torque holds and thruster pulses are discontinuities, so the run is integrated
piecewise between them; every sample comes from the integrator's dense output.
Messages are written chunk by chunk, so memory stays flat for long runs.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass, field
import json
import math
from pathlib import Path
import shutil
import time
from typing import Any, Callable, Iterator, Optional, Sequence, Union

import numpy as np
import pinocchio as pin

from reduced_dynamics.bag.writer import BagWriter
from reduced_dynamics.full_dynamics import FullDynamics, FullTrajectory
from reduced_dynamics.geometry.isotropy import MomentumClass
from reduced_dynamics.messages.convert import (
    base_state_to_odometry,
    base_state_to_pose_stamped,
    header_to_ros,
    joint_state_to_ros,
    wrench_to_ros,
)
from reduced_dynamics.messages.samples import BaseStateSample, JointStateSample, WrenchSample
from reduced_dynamics.messages.types import RosbagsTypes
from reduced_dynamics.robot.model import RobotModel
from reduced_dynamics.robot.momentum import (
    body_momentum,
    body_momentum_from_spatial,
    momentum_map,
)
from reduced_dynamics.robot.state import FreeFloatingState, TorqueLaw
from reduced_dynamics.validation import random_scenario

PathLike = Union[str, Path]

NS_PER_S = 1_000_000_000
#: Default bag start time (2023-11-14): a realistic epoch; stamp 0 means "unset" to many tools.
DEFAULT_START_NS = 1_700_000_000 * NS_PER_S
WORLD_FRAME = 'world'

TOPIC_JOINT_STATES = '/joint_states'
TOPIC_ODOM = '/odom'
TOPIC_BASE_POSE = '/base_pose'
TOPIC_MOMENTUM = '/ground_truth/momentum'
TOPIC_EXTERNAL_WRENCH = '/ground_truth/external_wrench'
TOPIC_STATUS = '/simulator/status'

TORQUE_MODES = ('zero', 'constant', 'sinusoid', 'pd')
MOMENTUM_CLASSES = {
    'generic': MomentumClass.GENERIC,
    'pure_angular': MomentumClass.PURE_ANGULAR,
    'pure_linear': MomentumClass.PURE_LINEAR,
    'zero': MomentumClass.ZERO,
}

#: Custom message of the optional status topic; it is registered in the writer's
#: typestore only, so bag readers must take the definition embedded in the bag.
STATUS_MSGTYPE = 'reduced_dynamics_msgs/msg/SimulatorStatus'
STATUS_DEFINITION = """\
std_msgs/Header header
string torque_mode
bool thruster_active
float64[6] base_wrench
float64 kinetic_energy
float64 potential_energy
"""
STATUS_RATE = 10.0

# Shape accelerations the excitations aim at (rad/s^2), as in validation.random_scenario.
_SHAPE_ACCEL = 0.1
# PD tracking: natural frequency (rad/s), damping ratio, reference amplitude (rad).
_PD_OMEGA = 3.0
_PD_ZETA = 1.0
_PD_AMPLITUDE = 0.2
# A sample whose mass-matrix condition number grew by this factor over the initial
# one is near a singular shape (e.g. the gimbal lock of a spherical joint as 3 revolutes).
_SINGULAR_GROWTH = 100.0
_GAUSS_NODES, _GAUSS_WEIGHTS = np.polynomial.legendre.leggauss(16)
# Random streams: [seed, stream] so each option draws independently of the others.
_STREAM_POSE, _STREAM_TORQUE, _STREAM_JOINT_NOISE, _STREAM_BASE_NOISE = 1, 2, 3, 4
_STREAM_DROP = 10


# --------------------------------------------------------------------------- options
@dataclass(frozen=True)
class ThrusterPulse:
    """A constant base-frame wrench (fx, fy, fz, tx, ty, tz) on the base during [start, end)."""

    start: float
    duration: float
    wrench: tuple[float, float, float, float, float, float]

    def __post_init__(self) -> None:
        """Validate the pulse."""
        wrench = tuple(float(w) for w in self.wrench)
        object.__setattr__(self, 'wrench', wrench)
        object.__setattr__(self, 'start', float(self.start))
        object.__setattr__(self, 'duration', float(self.duration))
        if len(wrench) != 6:
            raise ValueError(f'thruster wrench needs 6 values (fx fy fz tx ty tz), got {wrench}')
        if not all(math.isfinite(v) for v in (self.start, self.duration) + wrench):
            raise ValueError('thruster pulse values must be finite')
        if self.start < 0.0:
            raise ValueError(f'thruster pulse start must be >= 0, got {self.start:g}')
        if self.duration <= 0.0:
            raise ValueError(f'thruster pulse duration must be > 0, got {self.duration:g}')

    @property
    def end(self) -> float:
        """End time of the pulse (exclusive)."""
        return self.start + self.duration

    @classmethod
    def parse(cls, spec: str) -> 'ThrusterPulse':
        """Parse ``T,DURATION,FX,FY,FZ,TX,TY,TZ``."""
        parts = [p.strip() for p in spec.split(',')]
        if len(parts) != 8:
            raise ValueError(f'thruster spec {spec!r} must be T,DURATION,FX,FY,FZ,TX,TY,TZ '
                             f'(8 comma-separated numbers, got {len(parts)})')
        try:
            values = [float(p) for p in parts]
        except ValueError:
            raise ValueError(f'thruster spec {spec!r} holds a value that is not a number') \
                from None
        return cls(values[0], values[1], tuple(values[2:]))


@dataclass(frozen=True)
class SimulationOptions:
    """
    What to simulate and how to write it; see ``reduced-dynamics simulate --help``.

    ``rtol``/``atol`` are DOP853's tolerances: at 1e-13 the dense output keeps the
    momentum constant to ~1e-11 relative (1e-12 gives occasional 2e-10 spikes between
    steps) at no noticeable cost. Noise standard deviations: ``noise_position`` on joint positions,
    ``noise_velocity`` on joint velocities and the base twist, ``noise_pose`` on
    the base position (m) and orientation (a small rotation, rad). ``torque_scale``
    scales the excitation (the reference amplitude for ``pd``); ``torque_hold``
    is how long ``constant`` torques are held before they flip sign.
    """

    duration: float = 10.0
    rate: float = 200.0
    seed: int = 0
    torque: str = 'sinusoid'
    torque_scale: float = 1.0
    torque_hold: float = 2.0
    thrusters: tuple[ThrusterPulse, ...] = ()
    noise_position: float = 0.0
    noise_velocity: float = 0.0
    noise_pose: float = 0.0
    drop_rate: float = 0.0
    base_pose_only: bool = False
    momentum_class: str = 'generic'
    status: bool = False
    overwrite: bool = False
    start_time_ns: int = DEFAULT_START_NS
    rtol: float = 1e-13
    atol: float = 1e-13
    chunk_seconds: float = 1.0

    def __post_init__(self) -> None:
        """Validate every field (ValueError with the offending option)."""
        object.__setattr__(self, 'thrusters', tuple(self.thrusters))
        _check_positive('duration', self.duration)
        _check_positive('rate', self.rate)
        _check_positive('torque_hold', self.torque_hold)
        _check_positive('chunk_seconds', self.chunk_seconds)
        _check_positive('rtol', self.rtol)
        _check_positive('atol', self.atol)
        for name in ('torque_scale', 'noise_position', 'noise_velocity', 'noise_pose'):
            _check_nonnegative(name, getattr(self, name))
        if not 0.0 <= self.drop_rate < 1.0:
            raise ValueError(f'drop_rate must be in [0, 1), got {self.drop_rate!r}')
        if isinstance(self.seed, bool) or not isinstance(self.seed, (int, np.integer)) \
                or self.seed < 0:
            raise ValueError(f'seed must be a non-negative integer, got {self.seed!r}')
        if self.torque not in TORQUE_MODES:
            raise ValueError(f'unknown torque mode {self.torque!r}; choose from {TORQUE_MODES}')
        if self.momentum_class not in MOMENTUM_CLASSES:
            raise ValueError(f'unknown momentum class {self.momentum_class!r}; choose from '
                             f'{tuple(MOMENTUM_CLASSES)}')
        if not isinstance(self.start_time_ns, (int, np.integer)) or self.start_time_ns < 0:
            raise ValueError(f'start_time_ns must be a non-negative integer, '
                             f'got {self.start_time_ns!r}')
        if self.duration * self.rate > 1e8:
            raise ValueError('duration * rate exceeds 1e8 samples')
        for pulse in self.thrusters:
            if not isinstance(pulse, ThrusterPulse):
                raise ValueError(f'thrusters must be ThrusterPulse objects, got {pulse!r}')
            if pulse.start >= self.duration:
                raise ValueError(f'thruster pulse at {pulse.start:g} s starts after the end of '
                                 f'the run ({self.duration:g} s)')

    @property
    def samples(self) -> int:
        """Return the number of sample instants k / rate in [0, duration]."""
        return int(math.floor(self.duration * self.rate + 1e-9)) + 1


def _check_positive(name: str, value: float) -> None:
    if not (isinstance(value, (int, float, np.floating)) and math.isfinite(value)
            and value > 0.0):
        raise ValueError(f'{name} must be a finite number > 0, got {value!r}')


def _check_nonnegative(name: str, value: float) -> None:
    if not (isinstance(value, (int, float, np.floating)) and math.isfinite(value)
            and value >= 0.0):
        raise ValueError(f'{name} must be a finite number >= 0, got {value!r}')


# --------------------------------------------------------------------------- summary
@dataclass
class PulseSummary:
    """A thruster pulse and its impulse, world frame about the origin (force; torque)."""

    start: float
    duration: float
    body_wrench: np.ndarray
    world_impulse: np.ndarray


@dataclass
class SimulationSummary:
    """What :func:`simulate_bag` wrote; momenta are 6-D (linear; angular), world frame."""

    path: Path
    robot: str
    base_link: str
    base_group: str
    joint_names: tuple[str, ...]
    duration: float
    rate: float
    samples: int
    torque: str
    seed: int
    start_time_ns: int
    message_counts: dict[str, int]
    topic_types: dict[str, str]
    initial_momentum: np.ndarray
    final_momentum: np.ndarray
    pulses: list[PulseSummary] = field(default_factory=list)
    wall_seconds: float = 0.0

    def text(self) -> str:
        """Return the one-paragraph summary printed by the CLI."""
        counts = ', '.join(f'{t} {c}' for t, c in self.message_counts.items())
        mu = self.initial_momentum
        parts = [
            f'Simulated {self.robot} (base {self.base_group}, link {self.base_link!r}, '
            f'{len(self.joint_names)} shape joints) for {self.duration:g} s at '
            f'{self.rate:g} Hz ({self.samples} samples, {self.torque} torques, seed '
            f'{self.seed}) into {self.path} in {self.wall_seconds:.2f} s.',
            f'Messages: {counts}.',
            f'Initial momentum (world): linear {_vec(mu[:3])}, angular {_vec(mu[3:])}.',
        ]
        for index, pulse in enumerate(self.pulses, 1):
            parts.append(
                f'Pulse {index} at {pulse.start:g} s for {pulse.duration:g} s: world impulse '
                f'linear {_vec(pulse.world_impulse[:3])}, '
                f'angular {_vec(pulse.world_impulse[3:])}.')
        return ' '.join(parts)

    def to_dict(self) -> dict[str, Any]:
        """Return a JSON-ready dict (no wall time, so it is reproducible)."""
        return {
            'bag': str(self.path), 'robot': self.robot, 'base_link': self.base_link,
            'base_group': self.base_group, 'joint_names': list(self.joint_names),
            'duration': self.duration, 'rate': self.rate, 'samples': self.samples,
            'torque': self.torque, 'seed': self.seed, 'start_time_ns': self.start_time_ns,
            'message_counts': dict(self.message_counts), 'topic_types': dict(self.topic_types),
            'initial_momentum': self.initial_momentum.tolist(),
            'final_momentum': self.final_momentum.tolist(),
            'pulses': [{'start': p.start, 'duration': p.duration,
                        'body_wrench': p.body_wrench.tolist(),
                        'world_impulse': p.world_impulse.tolist()} for p in self.pulses],
        }

    def write_json(self, path: PathLike) -> None:
        """Write :meth:`to_dict` as indented JSON."""
        Path(path).write_text(json.dumps(self.to_dict(), indent=2) + '\n')


def _vec(values: np.ndarray) -> str:
    return '(' + ', '.join(f'{v:.4g}' for v in values) + ')'


# --------------------------------------------------------------------------- excitation
class Excitation:
    """Joint torques of a run: a law per smooth piece and the times the law jumps."""

    def __init__(self, law: Callable[[float], TorqueLaw], breakpoints: Sequence[float] = ()):
        """Wrap ``law(t_mid)``: the torque law on the piece holding ``t_mid``."""
        self._law = law
        self.breakpoints = tuple(breakpoints)

    def law(self, t_mid: float) -> TorqueLaw:
        """Return the smooth torque law on the piece containing ``t_mid``."""
        return self._law(t_mid)


def make_excitation(robot: RobotModel, state: FreeFloatingState, scenario_torque: TorqueLaw,
                    options: SimulationOptions) -> Excitation:
    """Build the joint-torque excitation ``options.torque`` asks for."""
    m = robot.m
    scale = options.torque_scale
    rng = np.random.default_rng([options.seed, _STREAM_TORQUE])
    # Gains and amplitudes follow the reduced metric's diagonal, so each joint gets about
    # the same acceleration whatever inertia it drives.
    inertia = np.diag(robot.metric_blocks(state.qbar).reduced_metric).copy()
    if options.torque == 'zero':
        zeros = np.zeros(m)
        return Excitation(lambda _t: lambda t, q, qd: zeros)
    if options.torque == 'sinusoid':
        def scaled(t: float, q: np.ndarray, qd: np.ndarray) -> np.ndarray:
            return scale * scenario_torque(t, q, qd)
        return Excitation(lambda _t: scaled)
    if options.torque == 'constant':
        # Bang-bang: a half hold, then holds of alternating sign, so the shape rate
        # oscillates about its initial value and the shape stays bounded.
        amplitude = scale * _SHAPE_ACCEL * inertia * rng.uniform(0.5, 1.0, m) \
            * rng.choice([-1.0, 1.0], m)
        hold = options.torque_hold
        edges = np.arange(0.5 * hold, options.duration, hold)

        def piece(t_mid: float) -> TorqueLaw:
            sign = -1.0 if int(np.searchsorted(edges, t_mid, side='right')) % 2 else 1.0
            value = sign * amplitude
            return lambda t, q, qd: value
        return Excitation(piece, edges.tolist())
    q0 = state.qbar.copy()
    amplitude = scale * _PD_AMPLITUDE * rng.uniform(0.5, 1.0, m)
    omega = rng.uniform(0.5, 2.0, m)
    kp = inertia * _PD_OMEGA ** 2
    kd = inertia * 2.0 * _PD_ZETA * _PD_OMEGA

    def pd(t: float, q: np.ndarray, qd: np.ndarray) -> np.ndarray:
        # Reference q0 + A sin(w t), with feedforward of its acceleration.
        s, c = np.sin(omega * t), np.cos(omega * t)
        q_ref = q0 + amplitude * s
        qd_ref = amplitude * omega * c
        qdd_ref = -amplitude * omega ** 2 * s
        return kp * (q_ref - q) + kd * (qd_ref - qd) + inertia * qdd_ref
    return Excitation(lambda _t: pd)


# --------------------------------------------------------------------------- initial state
def initial_state(robot: RobotModel, momentum_class: str, seed: int
                  ) -> tuple[FreeFloatingState, TorqueLaw]:
    """
    Return a gentle initial state with momentum in ``momentum_class`` and its sinusoid torques.

    Shape, shape rate, momentum direction and torques come from
    :func:`reduced_dynamics.validation.random_scenario`; the base pose is redrawn
    from ``seed`` (random_scenario's comes from Pinocchio's unseeded C RNG) and the
    momentum rescaled so the drift twist keeps the scenario's speed.
    """
    scenario = random_scenario(robot, MOMENTUM_CLASSES[momentum_class], seed)
    state = scenario.state
    blocks = robot.metric_blocks(state.qbar)
    pi_old = body_momentum(blocks, state.xi, state.qbar_dot)
    mu = momentum_map(robot.group, state.g, pi_old)
    drift_old = float(np.linalg.norm(blocks.solve_locked(pi_old)))
    rng = np.random.default_rng([seed, _STREAM_POSE])
    quat = rng.standard_normal(4)
    quat /= np.linalg.norm(quat)
    rotation = pin.Quaternion(quat[3], quat[0], quat[1], quat[2]).toRotationMatrix()
    g = robot.project_pose(pin.SE3(rotation, rng.uniform(-1.0, 1.0, 3)))
    pi = body_momentum_from_spatial(robot.group, g, mu)
    drift = float(np.linalg.norm(blocks.solve_locked(pi)))
    if drift > 0.0:
        mu = mu * (drift_old / drift)
        pi = body_momentum_from_spatial(robot.group, g, mu)
    xi = blocks.solve_locked(pi - blocks.coupling @ state.qbar_dot)
    return FreeFloatingState(g, xi, state.qbar.copy(), state.qbar_dot.copy()), scenario.torque


# --------------------------------------------------------------------------- pieces
@dataclass
class _Piece:
    """A time interval on which torques and base wrench are smooth."""

    start: float
    end: float
    first: int
    stop: int
    pulses: tuple[int, ...]


def _first_sample_at_or_after(t: float, rate: float) -> int:
    """Smallest k with k / rate >= t (exact in the floats used for sample times)."""
    k = max(0, int(math.ceil(t * rate)))
    while k > 0 and (k - 1) / rate >= t:
        k -= 1
    while k / rate < t:
        k += 1
    return k


def _pieces(options: SimulationOptions, breakpoints: Sequence[float]) -> Iterator[_Piece]:
    """Yield the pieces: split at discontinuities, then at chunk boundaries."""
    end = options.duration
    jumps = {0.0, end}
    for pulse in options.thrusters:
        jumps.update(t for t in (pulse.start, pulse.end) if 0.0 < t < end)
    jumps.update(t for t in breakpoints if 0.0 < t < end)
    edges = sorted(jumps)
    # Chunk boundaries only bound memory; skip those that nearly hit a discontinuity.
    chunks = np.arange(options.chunk_seconds, end, options.chunk_seconds)
    edges = sorted(set(edges) | {float(c) for c in chunks
                                 if np.min(np.abs(np.asarray(edges) - c)) > 1e-9})
    last = options.samples - 1
    for a, b in zip(edges[:-1], edges[1:]):
        first = _first_sample_at_or_after(a, options.rate)
        stop = last + 1 if b == end else _first_sample_at_or_after(b, options.rate)
        mid = 0.5 * (a + b)
        active = tuple(i for i, p in enumerate(options.thrusters) if p.start <= mid < p.end)
        yield _Piece(a, b, first, min(stop, last + 1), active)


# --------------------------------------------------------------------------- simulation
class _Noise:
    """Sensor noise and message drops, one random stream per purpose."""

    def __init__(self, robot: RobotModel, options: SimulationOptions, topics: Sequence[str]):
        self.robot = robot
        self.options = options
        seed = options.seed
        self.joint_rng = np.random.default_rng([seed, _STREAM_JOINT_NOISE])
        self.base_rng = np.random.default_rng([seed, _STREAM_BASE_NOISE])
        self.drop_rngs = {t: np.random.default_rng([seed, _STREAM_DROP + i])
                          for i, t in enumerate(topics)}

    def joints(self, qbar: np.ndarray, qbar_dot: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Return noisy joint positions and velocities."""
        # Always draw, so turning one noise on does not change the other's sequence.
        draw = self.joint_rng.standard_normal((2, self.robot.m))
        return (qbar + self.options.noise_position * draw[0],
                qbar_dot + self.options.noise_velocity * draw[1])

    def base(self, g: pin.SE3, twist6: np.ndarray) -> tuple[pin.SE3, np.ndarray]:
        """Return a noisy pose and body twist (noise only along the base group)."""
        basis = self.robot.group.algebra_basis
        draw = self.base_rng.standard_normal((2, self.robot.n))
        pose_noise = basis @ (self.options.noise_pose * draw[0])
        noisy = pin.SE3(g.rotation @ pin.exp3(pose_noise[3:]), g.translation + pose_noise[:3])
        return noisy, twist6 + basis @ (self.options.noise_velocity * draw[1])

    def keep(self, topic: str) -> bool:
        """Whether the message on ``topic`` survives the random drops."""
        return bool(self.drop_rngs[topic].random() >= self.options.drop_rate)


def bag_topics(options: SimulationOptions) -> dict[str, str]:
    """Return ``{topic: type}`` of the bag ``options`` describe."""
    topics = {TOPIC_JOINT_STATES: 'sensor_msgs/msg/JointState'}
    if options.base_pose_only:
        topics[TOPIC_BASE_POSE] = 'geometry_msgs/msg/PoseStamped'
    else:
        topics[TOPIC_ODOM] = 'nav_msgs/msg/Odometry'
    topics[TOPIC_MOMENTUM] = 'geometry_msgs/msg/WrenchStamped'
    topics[TOPIC_EXTERNAL_WRENCH] = 'geometry_msgs/msg/WrenchStamped'
    if options.status:
        topics[TOPIC_STATUS] = STATUS_MSGTYPE
    return topics


def status_typestore() -> Any:
    """Return a Jazzy typestore that also knows :data:`STATUS_MSGTYPE`."""
    from rosbags.typesys import get_types_from_msg, get_typestore, Stores
    store = get_typestore(Stores.ROS2_JAZZY)
    store.register(get_types_from_msg(STATUS_DEFINITION, STATUS_MSGTYPE))
    return store


def _wrench(mu: np.ndarray, robot: RobotModel, stamp: int) -> WrenchSample:
    wrench6 = robot.group.dual_to_wrench(mu)
    return WrenchSample(stamp, WORLD_FRAME, wrench6[:3], wrench6[3:])


def _quaternion_xyzw(rotation: np.ndarray) -> np.ndarray:
    return pin.Quaternion(rotation).normalized().coeffs().copy()


class _Recorder:
    """Turn trajectory samples into messages and write those that are not dropped."""

    def __init__(self, robot: RobotModel, options: SimulationOptions, bag: BagWriter) -> None:
        self.robot = robot
        self.options = options
        self.bag = bag
        self.types = RosbagsTypes(bag.typestore)
        self.noise = _Noise(robot, options, [TOPIC_JOINT_STATES, TOPIC_ODOM, TOPIC_BASE_POSE])
        self.names = tuple(robot.shape_joint_names)
        mask = np.diag(robot.group.algebra_basis @ robot.group.algebra_basis.T)
        self.pose_cov = np.diag(mask * options.noise_pose ** 2).ravel()
        self.twist_cov = np.diag(mask * options.noise_velocity ** 2).ravel()
        self.status_every = max(1, int(round(options.rate / STATUS_RATE)))
        self.reference_cond: Optional[float] = None

    def stamp(self, k: int) -> int:
        """Return the bag time of sample k."""
        return self.options.start_time_ns + int(round(k * NS_PER_S / self.options.rate))

    def record(self, k: int, state: FreeFloatingState, mu: np.ndarray, tau: np.ndarray,
               external: np.ndarray, body_wrench: np.ndarray) -> None:
        """Write every topic for sample k."""
        robot, options, types = self.robot, self.options, self.types
        self._check_regular(k, state.qbar)
        stamp = self.stamp(k)
        position, velocity = self.noise.joints(state.qbar, state.qbar_dot)
        twist6 = robot.group.twist(state.xi)
        pose, twist6 = self.noise.base(state.g, twist6)
        if self.noise.keep(TOPIC_JOINT_STATES):
            sample = JointStateSample(stamp, '', self.names, position, velocity, tau)
            self.bag.write(TOPIC_JOINT_STATES, stamp, joint_state_to_ros(sample, types))
        topic = TOPIC_BASE_POSE if options.base_pose_only else TOPIC_ODOM
        if self.noise.keep(topic):
            base = BaseStateSample(stamp, WORLD_FRAME, robot.base_link, pose.translation,
                                   _quaternion_xyzw(pose.rotation), twist6[:3], twist6[3:])
            if options.base_pose_only:
                self.bag.write(topic, stamp, base_state_to_pose_stamped(base, types))
            else:
                self.bag.write(topic, stamp, base_state_to_odometry(
                    base, types, self.pose_cov, self.twist_cov))
        self.bag.write(TOPIC_MOMENTUM, stamp, wrench_to_ros(_wrench(mu, robot, stamp), types))
        self.bag.write(TOPIC_EXTERNAL_WRENCH, stamp,
                       wrench_to_ros(_wrench(external, robot, stamp), types))
        if options.status and k % self.status_every == 0:
            self._status(stamp, state, body_wrench)

    def _status(self, stamp: int, state: FreeFloatingState, body_wrench: np.ndarray) -> None:
        robot = self.robot
        velocity = np.concatenate([state.xi, state.qbar_dot])
        kinetic = 0.5 * float(velocity @ robot.mass_matrix(state.qbar) @ velocity)
        msg = self.types.create(
            STATUS_MSGTYPE, header=header_to_ros(stamp, robot.base_link, self.types),
            torque_mode=self.options.torque, thruster_active=bool(np.any(body_wrench != 0.0)),
            base_wrench=np.asarray(body_wrench, dtype=np.float64),
            kinetic_energy=kinetic, potential_energy=robot.potential_energy(state.qbar))
        self.bag.write(TOPIC_STATUS, stamp, msg)

    def _check_regular(self, k: int, qbar: np.ndarray) -> None:
        cond = float(np.linalg.cond(self.robot.mass_matrix(qbar)))
        if self.reference_cond is None:
            self.reference_cond = cond
        elif cond > _SINGULAR_GROWTH * self.reference_cond:
            raise ValueError(
                f'the shape reached a near-singular configuration at t = '
                f'{k / self.options.rate:g} s (mass matrix condition number {cond:.2e}, '
                f'e.g. the gimbal lock of a spherical joint); use --torque pd, a shorter '
                f'--duration or another --seed')


def _constant_wrench(wrench: np.ndarray) -> Callable[[float], np.ndarray]:
    return lambda t: wrench


def simulate_bag(robot: RobotModel, out_path: PathLike,
                 options: Optional[SimulationOptions] = None) -> SimulationSummary:
    """
    Simulate ``robot`` with full dynamics and write the bag at ``out_path``.

    Raises ValueError (BagError) before integrating if ``out_path`` exists and
    ``options.overwrite`` is false; a failed run removes its partial bag.
    """
    options = options or SimulationOptions()
    started = time.perf_counter()
    out = Path(out_path)
    if out.exists() and not options.overwrite:
        raise ValueError(f'output {out} exists already (pass --overwrite / overwrite=True '
                         f'to replace it)')
    state, scenario_torque = initial_state(robot, options.momentum_class, options.seed)
    excitation = make_excitation(robot, state, scenario_torque, options)
    topics = bag_topics(options)
    store = status_typestore() if options.status else None
    bag = BagWriter(out, topics, typestore=store, overwrite=options.overwrite)
    bag.open()
    try:
        recorder = _Recorder(robot, options, bag)
        initial_mu, final_mu, pulses = _run(robot, state, excitation, options, recorder)
        bag.close()
    except BaseException:
        bag.abort()
        shutil.rmtree(out, ignore_errors=True)
        raise
    return SimulationSummary(
        path=out, robot=robot.model.name, base_link=robot.base_link,
        base_group=robot.group.name, joint_names=tuple(robot.shape_joint_names),
        duration=options.duration, rate=options.rate, samples=options.samples,
        torque=options.torque, seed=int(options.seed), start_time_ns=int(options.start_time_ns),
        message_counts=dict(bag.message_counts), topic_types=topics,
        initial_momentum=robot.group.dual_to_wrench(initial_mu),
        final_momentum=robot.group.dual_to_wrench(final_mu),
        pulses=[PulseSummary(p.start, p.duration, np.array(p.wrench),
                             robot.group.dual_to_wrench(impulse))
                for p, impulse in zip(options.thrusters, pulses)],
        wall_seconds=time.perf_counter() - started)


def _run(robot: RobotModel, state: FreeFloatingState, excitation: Excitation,
         options: SimulationOptions, recorder: _Recorder
         ) -> tuple[np.ndarray, np.ndarray, list[np.ndarray]]:
    """Integrate piece by piece, writing each piece's samples; return mu0, mu_end, impulses."""
    impulses = [np.zeros(robot.n) for _ in options.thrusters]
    dynamics = FullDynamics(robot)
    mu_first = mu_last = np.zeros(robot.n)
    for piece in _pieces(options, excitation.breakpoints):
        torque = excitation.law(0.5 * (piece.start + piece.end))
        body_wrench = np.zeros(6)
        for index in piece.pulses:
            body_wrench += np.asarray(options.thrusters[index].wrench)
        dynamics.torque = torque
        dynamics.base_wrench = _constant_wrench(body_wrench) if piece.pulses else None
        samples = np.arange(piece.first, piece.stop) / options.rate
        half = 0.5 * (piece.end - piece.start)
        nodes = piece.start + half * (1.0 + _GAUSS_NODES) if piece.pulses else np.zeros(0)
        times = np.unique(np.concatenate([[piece.start, piece.end], samples, nodes]))
        trajectory = dynamics.simulate(state, times, options.rtol, options.atol)
        where = np.searchsorted(times, samples)
        for k, index in zip(range(piece.first, piece.stop), where):
            sample_state = trajectory.state(index)
            tau = np.asarray(torque(times[index], sample_state.qbar, sample_state.qbar_dot),
                             dtype=float)
            external = dynamics.world_wrench(times[index], sample_state.g)
            recorder.record(k, sample_state, trajectory.mu[index], tau, external, body_wrench)
        if piece.pulses:
            _add_impulses(robot, options, piece, trajectory, np.searchsorted(times, nodes),
                          half, impulses)
        if piece.start == 0.0:
            mu_first = trajectory.mu[0].copy()
        mu_last = trajectory.mu[-1].copy()
        state = trajectory.state(len(times) - 1)
    return mu_first, mu_last, impulses


def _add_impulses(robot: RobotModel, options: SimulationOptions, piece: _Piece,
                  trajectory: FullTrajectory, where: np.ndarray, half: float,
                  impulses: list[np.ndarray]) -> None:
    """Gauss-Legendre quadrature of each active pulse's world wrench over the piece."""
    for pulse_index in piece.pulses:
        body = robot.group.dual_coordinates(np.asarray(options.thrusters[pulse_index].wrench))
        for weight, index in zip(_GAUSS_WEIGHTS, where):
            ad = robot.group.Ad(trajectory.pose(index).inverse())
            impulses[pulse_index] += half * weight * (ad.T @ body)


# --------------------------------------------------------------------------- CLI
def _positive(text: str) -> float:
    value = _number(text)
    if not value > 0.0:
        raise argparse.ArgumentTypeError(f'must be > 0, got {text}')
    return value


def _nonnegative(text: str) -> float:
    value = _number(text)
    if not value >= 0.0:
        raise argparse.ArgumentTypeError(f'must be >= 0, got {text}')
    return value


def _fraction(text: str) -> float:
    value = _number(text)
    if not 0.0 <= value < 1.0:
        raise argparse.ArgumentTypeError(f'must be in [0, 1), got {text}')
    return value


def _number(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f'not a number: {text!r}') from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f'must be finite, got {text}')
    return value


def _seed(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f'not an integer: {text!r}') from None
    if value < 0:
        raise argparse.ArgumentTypeError(f'must be >= 0, got {text}')
    return value


def _thruster(text: str) -> ThrusterPulse:
    try:
        return ThrusterPulse.parse(text)
    except ValueError as error:
        raise argparse.ArgumentTypeError(str(error)) from None


def register_command(subparsers: Any) -> None:
    """Add the ``simulate`` subcommand to the ``reduced-dynamics`` parser."""
    from reduced_dynamics.cli import add_robot_arguments
    parser = subparsers.add_parser(
        'simulate', help='simulate full dynamics and write a rosbag2 (MCAP) bag',
        description='Integrate the full free-floating dynamics (Pinocchio aba, DOP853) and '
                    'write /joint_states, /odom (or /base_pose) and the ground truth '
                    '/ground_truth/momentum and /ground_truth/external_wrench as a rosbag2 '
                    'bag with MCAP storage.')
    add_robot_arguments(parser)
    parser.add_argument('-o', '--output', required=True, metavar='OUT',
                        help='bag directory to create')
    parser.add_argument('--overwrite', action='store_true',
                        help='replace OUT (and --summary) if they exist')
    parser.add_argument('--duration', type=_positive, default=10.0, help='seconds (default 10)')
    parser.add_argument('--rate', type=_positive, default=200.0,
                        help='sample rate of every topic, Hz (default 200)')
    parser.add_argument('--seed', type=_seed, default=0, help='random seed (default 0)')
    parser.add_argument('--torque', choices=TORQUE_MODES, default='sinusoid',
                        help='joint torques: zero, constant (held --torque-hold s, alternating '
                             'sign), sinusoid, or pd (PD tracking of a sinusoidal reference '
                             'about the initial shape) (default sinusoid)')
    parser.add_argument('--torque-scale', type=_nonnegative, default=1.0,
                        help='scale of the torques (of the reference amplitude for pd)')
    parser.add_argument('--torque-hold', type=_positive, default=2.0,
                        help='seconds each constant torque is held (default 2)')
    parser.add_argument('--thruster', type=_thruster, action='append', default=[],
                        metavar='T,DURATION,FX,FY,FZ,TX,TY,TZ',
                        help='base-frame wrench (N, N m) on the base during [T, T+DURATION); '
                             'repeatable')
    parser.add_argument('--noise-position', type=_nonnegative, default=0.0,
                        help='std of joint position noise (rad or m)')
    parser.add_argument('--noise-velocity', type=_nonnegative, default=0.0,
                        help='std of joint velocity and base twist noise')
    parser.add_argument('--noise-pose', type=_nonnegative, default=0.0,
                        help='std of base position (m) and orientation (rad) noise')
    parser.add_argument('--drop-rate', type=_fraction, default=0.0,
                        help='fraction of sensor messages dropped at random, per topic')
    parser.add_argument('--base-pose-only', action='store_true',
                        help='write /base_pose (PoseStamped) instead of /odom')
    parser.add_argument('--momentum-class', choices=tuple(MOMENTUM_CLASSES), default='generic',
                        help='class of the initial momentum (default generic)')
    parser.add_argument('--status', action='store_true',
                        help=f'also write {TOPIC_STATUS} ({STATUS_MSGTYPE}, a custom type '
                             f'embedded in the bag) at {STATUS_RATE:g} Hz')
    parser.add_argument('--start-time', type=_nonnegative, default=DEFAULT_START_NS / NS_PER_S,
                        help='bag time of the first sample, s since the epoch')
    parser.add_argument('--summary', default=None, metavar='JSON',
                        help='also write the summary as JSON to this file')
    parser.set_defaults(func=run_command)


def options_from_args(args: argparse.Namespace) -> SimulationOptions:
    """Return the :class:`SimulationOptions` of parsed ``simulate`` arguments."""
    return SimulationOptions(
        duration=args.duration, rate=args.rate, seed=args.seed, torque=args.torque,
        torque_scale=args.torque_scale, torque_hold=args.torque_hold,
        thrusters=tuple(args.thruster), noise_position=args.noise_position,
        noise_velocity=args.noise_velocity, noise_pose=args.noise_pose,
        drop_rate=args.drop_rate, base_pose_only=args.base_pose_only,
        momentum_class=args.momentum_class, status=args.status, overwrite=args.overwrite,
        start_time_ns=int(round(args.start_time * NS_PER_S)))


def run_command(args: argparse.Namespace) -> int:
    """Run ``reduced-dynamics simulate``."""
    from reduced_dynamics.cli import load_robot_from_args
    options = options_from_args(args)
    if args.summary and Path(args.summary).exists() and not args.overwrite:
        raise ValueError(f'summary {args.summary} exists already (pass --overwrite to replace)')
    robot = load_robot_from_args(args)
    summary = simulate_bag(robot, args.output, options)
    if args.summary:
        summary.write_json(args.summary)
    print(summary.text())
    return 0
