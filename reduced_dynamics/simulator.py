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
rate, ``/joint_states`` (robots with shape joints), ``/odom`` (or ``/base_pose``) and
the noise-free ground truth ``/ground_truth/momentum``,
``/ground_truth/external_wrench`` and ``/ground_truth/base_pose``. A joint that
leaves its URDF limits stops the run with a clear message (as a near-singular
shape does), never a bag that replay rejects. The measured topics go through a sensor model
(noise, quantisation, stamp jitter and bunching, latency, dropouts:
:mod:`reduced_dynamics.sensor_model`); binary thrusters
(:mod:`reduced_dynamics.thrusters`) add ``/commanded_wrench``. Torque holds, thruster
pulses and firings are discontinuities, so the run is integrated piecewise between
them; every sample comes from the integrator's dense output. Messages are written in
record-time order chunk by chunk, so memory stays flat for long runs.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass, field
import functools
import heapq
import json
import math
from pathlib import Path
import shutil
import time
from typing import Any, Callable, Iterator, Optional, Sequence, Union

import numpy as np
import pinocchio as pin

from reduced_dynamics.bag.writer import BagWriter
from reduced_dynamics.estimator.config import EstimatorConfig
from reduced_dynamics.estimator.plausibility import JointBounds
from reduced_dynamics.full_dynamics import FullDynamics, FullTrajectory, PrescribedShapeDynamics
from reduced_dynamics.geometry.isotropy import MomentumClass
from reduced_dynamics.geometry.quaternion import matrix_to_unit_xyzw
from reduced_dynamics.messages.convert import (
    base_state_to_odometry,
    base_state_to_pose_stamped,
    base_state_to_pose_with_covariance_stamped,
    header_to_ros,
    joint_state_to_ros,
    joint_trajectory_to_ros,
    wrench_to_ros,
)
from reduced_dynamics.messages.samples import (BaseStateSample, JointStateSample,
                                               JointTrajectorySample, WrenchSample)
from reduced_dynamics.messages.types import RosbagsTypes
from reduced_dynamics.robot.model import RobotModel
from reduced_dynamics.robot.momentum import (
    body_momentum,
    body_momentum_from_spatial,
    momentum_map,
)
from reduced_dynamics.robot.state import FreeFloatingState, TorqueLaw
from reduced_dynamics.sensor_model import (
    QUANTIZE_FIELDS, quantize, TimingOptions, TopicStatistics, TopicTiming)
from reduced_dynamics.thrusters import (
    LAYOUT_FORCE, LAYOUTS, ThrusterFiring, ThrusterSet)
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
#: the true base pose (geometry_msgs/PoseStamped, world frame, every sample)
TOPIC_TRUE_POSE = '/ground_truth/base_pose'
TOPIC_STATUS = '/simulator/status'
TOPIC_COMMAND = '/commanded_wrench'
#: the planned trajectory of ``--trajectory`` (what the estimator's planned mode follows)
TOPIC_TRAJECTORY = '/joint_trajectory'
#: Measured topics, in the order that numbers their random streams (never reorder).
SENSOR_TOPICS = (TOPIC_JOINT_STATES, TOPIC_ODOM, TOPIC_BASE_POSE)

TORQUE_MODES = ('zero', 'constant', 'sinusoid', 'pd', 'multisine')
JOINT_LIMIT_POLICIES = ('stop', 'ignore')
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
#: ``multisine``: sines per joint and their angular frequencies' range (rad/s): several
#: incommensurate frequencies per joint turn the links about varied axes (payload
#: identification needs that, docs/payload.md).
_MULTISINE_COUNT = 4
_MULTISINE_OMEGA = (1.0, 5.0)
# A sample whose mass-matrix condition number grew by this factor over the initial
# one is near a singular shape (e.g. the gimbal lock of a spherical joint as 3 revolutes).
_SINGULAR_GROWTH = 100.0
_GAUSS_NODES, _GAUSS_WEIGHTS = np.polynomial.legendre.leggauss(16)
# Random streams: [seed, stream] so each option draws independently of the others.
_STREAM_POSE, _STREAM_TORQUE, _STREAM_JOINT_NOISE, _STREAM_BASE_NOISE = 1, 2, 3, 4
_STREAM_EFFORT_NOISE = 5


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
    ``noise_velocity`` on joint velocities and the base twist (``noise_twist`` when
    given; ``noise_twist_angular`` on its angular part when given), ``noise_effort`` on
    joint efforts, ``noise_pose`` on the base position (m)
    and orientation (a small rotation, rad; ``noise_orientation`` when given).
    ``quantize`` holds (field, step) pairs of :data:`QUANTIZE_FIELDS`. The timing
    fields (``stamp_jitter`` ... ``outage_duration``) apply to every measured topic,
    each with its own random streams (:class:`reduced_dynamics.sensor_model.TimingOptions`).
    Binary thrusters: ``thruster_layout`` (a name of
    :data:`reduced_dynamics.thrusters.LAYOUTS`) or ``thruster_units`` (body-frame unit
    wrenches), ``thruster_force`` (nominal N, default the layout's or 1), ``firings``,
    the delivered wrench ``thrust_gain * command + thrust_bias`` and the command topic's
    ``command_rate``. ``torque_scale`` scales the excitation (the reference amplitude
    for ``pd`` and ``multisine``); ``torque_hold`` is how long ``constant`` torques
    are held before they flip sign.
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
    noise_effort: float = 0.0
    noise_twist: Optional[float] = None
    noise_twist_angular: Optional[float] = None
    noise_orientation: Optional[float] = None
    quantize: tuple[tuple[str, float], ...] = ()
    stamp_jitter: float = 0.0
    bunch_fraction: float = 0.0
    bunch_gap: float = 3e-5
    latency: float = 0.0
    latency_jitter: float = 0.0
    outage_rate: float = 0.0
    outage_duration: float = 0.04
    poll_period: float = 0.0
    poll_late_fraction: float = 0.0
    poll_late_delay: float = 0.05
    thruster_layout: str = ''
    thruster_units: tuple[tuple[float, ...], ...] = ()
    thruster_force: Optional[float] = None
    firings: tuple[ThrusterFiring, ...] = ()
    thrust_gain: tuple[float, ...] = (1.0,) * 6
    thrust_bias: tuple[float, ...] = (0.0,) * 6
    command_rate: float = 10.0
    joint_rate: Optional[float] = None
    base_rate: Optional[float] = None
    base_pose_only: bool = False
    #: with ``base_pose_only``: PoseWithCovarianceStamped carrying the noise it adds
    base_pose_covariance: bool = False
    momentum_class: str = 'generic'
    status: bool = False
    overwrite: bool = False
    start_time_ns: int = DEFAULT_START_NS
    rtol: float = 1e-13
    atol: float = 1e-13
    chunk_seconds: float = 1.0
    #: a planned joint trajectory file (YAML/CSV, :mod:`reduced_dynamics.trajectory_file`):
    #: the shape follows it exactly, the base by the full dynamics (no torque law)
    trajectory: str = ''
    #: a joint leaving what replay accepts of its URDF limits: ``stop`` the run with a
    #: message, or ``ignore`` (explicitly: replay then rejects those samples)
    joint_limits: str = 'stop'

    def __post_init__(self) -> None:
        """Validate every field (ValueError with the offending option)."""
        object.__setattr__(self, 'thrusters', tuple(self.thrusters))
        object.__setattr__(self, 'firings', tuple(self.firings))
        object.__setattr__(self, 'quantize', tuple((str(f), float(v)) for f, v in self.quantize))
        object.__setattr__(self, 'thruster_units',
                           tuple(tuple(float(x) for x in u) for u in self.thruster_units))
        object.__setattr__(self, 'thrust_gain', tuple(float(x) for x in self.thrust_gain))
        object.__setattr__(self, 'thrust_bias', tuple(float(x) for x in self.thrust_bias))
        _check_positive('duration', self.duration)
        if self.trajectory and (self.thrusters or self.firings):
            raise ValueError('--trajectory prescribes the shape with no external wrench: '
                             'thrusters are not supported with it')
        _check_positive('bunch_gap', self.bunch_gap)
        _check_positive('outage_duration', self.outage_duration)
        _check_positive('command_rate', self.command_rate)
        for name in ('joint_rate', 'base_rate'):
            if getattr(self, name) is not None:
                _check_positive(name, getattr(self, name))
                self.decimation(getattr(self, name), name)
        for name in ('noise_effort', 'stamp_jitter', 'latency', 'latency_jitter',
                     'outage_rate', 'poll_period', 'poll_late_delay'):
            _check_nonnegative(name, getattr(self, name))
        for name in ('noise_twist', 'noise_twist_angular', 'noise_orientation'):
            if getattr(self, name) is not None:
                _check_nonnegative(name, getattr(self, name))
        if not 0.0 <= self.poll_late_fraction < 1.0:
            raise ValueError('poll_late_fraction must be in [0, 1), got '
                             f'{self.poll_late_fraction!r}')
        if not 0.0 <= self.bunch_fraction < 1.0:
            raise ValueError(f'bunch_fraction must be in [0, 1), got {self.bunch_fraction!r}')
        for name, step in self.quantize:
            if name not in QUANTIZE_FIELDS:
                raise ValueError(f'unknown quantize field {name!r}; choose from '
                                 f'{QUANTIZE_FIELDS}')
            _check_positive(f'quantize step of {name}', step)
        self._check_thrusters()
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
        if self.joint_limits not in JOINT_LIMIT_POLICIES:
            raise ValueError(f'unknown joint_limits {self.joint_limits!r}; choose from '
                             f'{JOINT_LIMIT_POLICIES}')
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

    def _check_thrusters(self) -> None:
        if self.thruster_layout and self.thruster_units:
            raise ValueError('give thruster_layout or thruster_units, not both')
        if self.thruster_layout and self.thruster_layout not in LAYOUTS:
            raise ValueError(f'unknown thruster layout {self.thruster_layout!r}; choose from '
                             f'{tuple(LAYOUTS)}')
        if any(len(u) != 6 for u in self.thruster_units):
            raise ValueError('each thruster unit wrench needs 6 values (fx fy fz tx ty tz)')
        if len(self.thrust_gain) != 6 or len(self.thrust_bias) != 6:
            raise ValueError('thrust_gain and thrust_bias need 6 values (fx fy fz tx ty tz)')
        if not all(math.isfinite(v) for v in self.thrust_gain + self.thrust_bias):
            raise ValueError('thrust_gain and thrust_bias must be finite')
        if self.thruster_force is not None:
            _check_positive('thruster_force', self.thruster_force)
        thrusters = self.thruster_set()
        if thrusters is None and (self.firings or any(self.thrust_bias)):
            raise ValueError('firings and thrust_bias need a thruster layout '
                             '(thruster_layout or thruster_units)')
        for firing in self.firings:
            if not isinstance(firing, ThrusterFiring):
                raise ValueError(f'firings must be ThrusterFiring objects, got {firing!r}')
            if max(firing.thrusters) >= thrusters.count:
                raise ValueError(f'firing at {firing.start:g} s names thruster '
                                 f'{max(firing.thrusters)}, but the layout has '
                                 f'{thrusters.count} (indices from 0)')
            if firing.start >= self.duration:
                raise ValueError(f'thruster firing at {firing.start:g} s starts after the end '
                                 f'of the run ({self.duration:g} s)')

    def thruster_set(self) -> Optional[ThrusterSet]:
        """Return the binary thrusters, or None when there are none."""
        if not (self.thruster_layout or self.thruster_units):
            return None
        units = LAYOUTS[self.thruster_layout] if self.thruster_layout else self.thruster_units
        force = self.thruster_force
        if force is None:
            force = LAYOUT_FORCE.get(self.thruster_layout, 1.0)
        return ThrusterSet(np.array(units), force, np.array(self.thrust_gain),
                           np.array(self.thrust_bias))

    def decimation(self, topic_rate: Optional[float], name: str = 'rate') -> int:
        """Return how many samples apart a topic at ``topic_rate`` publishes (rate / it)."""
        if topic_rate is None:
            return 1
        ratio = self.rate / topic_rate
        every = int(round(ratio))
        if every < 1 or abs(ratio - every) > 1e-9 * ratio:
            raise ValueError(f'{name} ({topic_rate:g} Hz) must divide the sample rate '
                             f'({self.rate:g} Hz) a whole number of times')
        return every

    def timing(self) -> TimingOptions:
        """Return the timing effects of every measured topic."""
        return TimingOptions(self.stamp_jitter, self.bunch_fraction, self.bunch_gap,
                             self.latency, self.latency_jitter, self.drop_rate,
                             self.outage_rate, self.outage_duration,
                             poll_period=self.poll_period,
                             poll_late_fraction=self.poll_late_fraction,
                             poll_late_delay=self.poll_late_delay)

    def step(self, name: str) -> float:
        """Return the quantisation step of field ``name`` (0: not quantised)."""
        return dict(self.quantize).get(name, 0.0)

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
class FiringSummary:
    """A binary-thruster firing: its body-frame command, what was delivered, the impulse."""

    start: float
    duration: float
    thrusters: tuple[int, ...]
    body_command: np.ndarray
    body_delivered: np.ndarray
    #: world impulse (force; torque about the origin) of the delivered wrench over the firing
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
    firings: list[FiringSummary] = field(default_factory=list)
    sensors: dict[str, TopicStatistics] = field(default_factory=dict)
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
        for index, firing in enumerate(self.firings, 1):
            parts.append(
                f'Firing {index} of thrusters {list(firing.thrusters)} at {firing.start:g} s '
                f'for {firing.duration:g} s: world impulse linear '
                f'{_vec(firing.world_impulse[:3])}, angular {_vec(firing.world_impulse[3:])}.')
        for topic, stats in self.sensors.items():
            lost = stats.dropped_random + stats.dropped_outage
            if lost or stats.bunched:
                parts.append(f'{topic}: {stats.dropped_random} dropped, {stats.dropped_outage} '
                             f'lost in {len(stats.outages)} outages, {stats.bunched} bunched.')
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
            'firings': [{'start': f.start, 'duration': f.duration,
                         'thrusters': list(f.thrusters),
                         'body_command': f.body_command.tolist(),
                         'body_delivered': f.body_delivered.tolist(),
                         'world_impulse': f.world_impulse.tolist()} for f in self.firings],
            'sensors': {t: stats.to_dict() for t, stats in self.sensors.items()},
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
    kp = inertia * _PD_OMEGA ** 2
    kd = inertia * 2.0 * _PD_ZETA * _PD_OMEGA
    if options.torque == 'multisine':
        # Reference q0 + sum_h A_h sin(w_h t + p_h) per joint, the amplitudes summing
        # to the pd mode's, with random frequencies and phases.
        count = _MULTISINE_COUNT
        weights = rng.uniform(0.5, 1.0, (m, count))
        amplitudes = (scale * _PD_AMPLITUDE * rng.uniform(0.5, 1.0, m))[:, None] \
            * weights / weights.sum(axis=1, keepdims=True)
        omegas = rng.uniform(*_MULTISINE_OMEGA, (m, count))
        phases = rng.uniform(0.0, 2.0 * np.pi, (m, count))

        # The products of constants once (the same bits as formed per call: each
        # product is evaluated left to right), and one sine per call: the integrator
        # calls this at every stage.
        rate_amplitudes = amplitudes * omegas
        acceleration_amplitudes = amplitudes * omegas ** 2

        def multisine(t: float, q: np.ndarray, qd: np.ndarray) -> np.ndarray:
            arg = omegas * t + phases
            sine = np.sin(arg)
            q_ref = q0 + (amplitudes * sine).sum(axis=1)
            qd_ref = (rate_amplitudes * np.cos(arg)).sum(axis=1)
            qdd_ref = -(acceleration_amplitudes * sine).sum(axis=1)
            return kp * (q_ref - q) + kd * (qd_ref - qd) + inertia * qdd_ref
        return Excitation(lambda _t: multisine)
    amplitude = scale * _PD_AMPLITUDE * rng.uniform(0.5, 1.0, m)
    omega = rng.uniform(0.5, 2.0, m)

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
    firings: tuple[int, ...] = ()


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
    for pulse in options.thrusters + options.firings:
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
        firing = tuple(i for i, f in enumerate(options.firings) if f.start <= mid < f.end)
        yield _Piece(a, b, first, min(stop, last + 1), active, firing)


# --------------------------------------------------------------------------- simulation
class _Noise:
    """Sensor noise and quantisation, one random stream per purpose."""

    def __init__(self, robot: RobotModel, options: SimulationOptions) -> None:
        self.robot = robot
        self.options = options
        seed = options.seed
        self.joint_rng = np.random.default_rng([seed, _STREAM_JOINT_NOISE])
        self.base_rng = np.random.default_rng([seed, _STREAM_BASE_NOISE])
        self.effort_rng = np.random.default_rng([seed, _STREAM_EFFORT_NOISE])
        # Standard deviations per algebra coordinate (linear ones: m, angular ones: rad).
        basis = robot.group.algebra_basis
        angular = np.abs(basis[3:]).sum(axis=0) > 0.0
        twist = options.noise_velocity if options.noise_twist is None else options.noise_twist
        orientation = options.noise_pose if options.noise_orientation is None \
            else options.noise_orientation
        self.pose_sigma = np.where(angular, orientation, options.noise_pose)
        # A gyro and a velocity solution differ by orders of magnitude (config/spacecraft.yaml).
        twist_angular = twist if options.noise_twist_angular is None \
            else options.noise_twist_angular
        self.twist_sigma = np.where(angular, float(twist_angular), float(twist))
        self.steps = {name: options.step(name) for name in QUANTIZE_FIELDS}

    def joints(self, qbar: np.ndarray, qbar_dot: np.ndarray, tau: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Return measured joint positions, velocities and efforts."""
        # Always draw, so turning one noise on does not change the other's sequence.
        draw = self.joint_rng.standard_normal((2, self.robot.m))
        options, steps = self.options, self.steps
        position = qbar + options.noise_position * draw[0]
        velocity = qbar_dot + options.noise_velocity * draw[1]
        effort = tau
        if options.noise_effort > 0.0:
            effort = tau + options.noise_effort * self.effort_rng.standard_normal(self.robot.m)
        return (quantize(position, steps['joint_position']),
                quantize(velocity, steps['joint_velocity']),
                quantize(effort, steps['joint_effort']))

    def base(self, g: pin.SE3, twist6: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Return the measured position, quaternion (x, y, z, w) and body twist."""
        basis = self.robot.group.algebra_basis
        draw = self.base_rng.standard_normal((2, self.robot.n))
        pose_noise = basis @ (self.pose_sigma * draw[0])
        noisy = pin.SE3(g.rotation @ pin.exp3(pose_noise[3:]), g.translation + pose_noise[:3])
        twist6 = twist6 + basis @ (self.twist_sigma * draw[1])
        steps = self.steps
        position = quantize(noisy.translation, steps['base_position'])
        quaternion = quantize(_quaternion_xyzw(noisy.rotation), steps['base_orientation'])
        twist6 = np.concatenate([quantize(twist6[:3], steps['base_linear_velocity']),
                                 quantize(twist6[3:], steps['base_angular_velocity'])])
        return position, quaternion, twist6

    def covariances(self) -> tuple[np.ndarray, np.ndarray]:
        """Return the row-major 6x6 pose and twist covariances an Odometry reports."""
        basis = self.robot.group.algebra_basis
        mask = np.diag(basis @ basis.T)
        # The quantisation error, uniform on a step, has variance step^2 / 12.
        steps = self.steps
        q_pose = np.r_[[steps['base_position'] ** 2 / 12.0] * 3,
                       [steps['base_orientation'] ** 2 / 3.0] * 3]
        q_twist = np.r_[[steps['base_linear_velocity'] ** 2 / 12.0] * 3,
                        [steps['base_angular_velocity'] ** 2 / 12.0] * 3]
        pose_var = (basis ** 2) @ (self.pose_sigma ** 2) + q_pose * mask
        twist_var = (basis ** 2) @ (self.twist_sigma ** 2) + q_twist * mask
        return np.diag(mask * pose_var).ravel(), np.diag(mask * twist_var).ravel()


def bag_topics(options: SimulationOptions, robot: Optional[RobotModel] = None
               ) -> dict[str, str]:
    """Return ``{topic: type}`` of the bag ``options`` describe (no joint states if m = 0)."""
    topics = {}
    if robot is None or robot.m > 0:
        topics[TOPIC_JOINT_STATES] = 'sensor_msgs/msg/JointState'
    if options.base_pose_only:
        topics[TOPIC_BASE_POSE] = 'geometry_msgs/msg/PoseWithCovarianceStamped' \
            if options.base_pose_covariance else 'geometry_msgs/msg/PoseStamped'
    else:
        topics[TOPIC_ODOM] = 'nav_msgs/msg/Odometry'
    topics[TOPIC_MOMENTUM] = 'geometry_msgs/msg/WrenchStamped'
    topics[TOPIC_EXTERNAL_WRENCH] = 'geometry_msgs/msg/WrenchStamped'
    topics[TOPIC_TRUE_POSE] = 'geometry_msgs/msg/PoseStamped'
    if options.thruster_set() is not None:
        topics[TOPIC_COMMAND] = 'geometry_msgs/msg/WrenchStamped'
    if options.status:
        topics[TOPIC_STATUS] = STATUS_MSGTYPE
    if options.trajectory:
        topics[TOPIC_TRAJECTORY] = 'trajectory_msgs/msg/JointTrajectory'
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
    return matrix_to_unit_xyzw(rotation)


def command_times(options: SimulationOptions) -> list[float]:
    """Return the times [s] of the command messages: the command grid plus every switch."""
    grid = np.arange(0.0, options.duration + 1e-9, 1.0 / options.command_rate)
    edges = [t for f in options.firings for t in (f.start, f.end) if t <= options.duration]
    return sorted({round(float(t), 9) for t in list(grid) + edges})


class _Recorder:
    """Turn trajectory samples into messages; write them in record-time order."""

    def __init__(self, robot: RobotModel, options: SimulationOptions, bag: BagWriter) -> None:
        self.robot = robot
        self.options = options
        self.bag = bag
        self.types = RosbagsTypes(bag.typestore)
        self.noise = _Noise(robot, options)
        self.names = tuple(robot.shape_joint_names)
        self.pose_cov, self.twist_cov = self.noise.covariances()
        self.status_every = max(1, int(round(options.rate / STATUS_RATE)))
        self.reference_cond: Optional[float] = None
        self.bounds = JointBounds(robot, EstimatorConfig()) \
            if options.joint_limits == 'stop' else None
        self.base_topic = TOPIC_BASE_POSE if options.base_pose_only else TOPIC_ODOM
        timing = options.timing()
        # Each measured topic publishes every `every` samples; its timing model counts
        # the topic's own messages (its "next message" is `every` samples later).
        self.every = {TOPIC_JOINT_STATES: options.decimation(options.joint_rate),
                      self.base_topic: options.decimation(options.base_rate)}
        self.timing = {
            topic: TopicTiming(timing, options.seed, SENSOR_TOPICS.index(topic),
                               functools.partial(self._topic_stamp, self.every[topic]),
                               options.duration)
            for topic in bag.topics if topic in SENSOR_TOPICS}
        self.thrusters = options.thruster_set()
        self.commands = command_times(options) if self.thrusters is not None else []
        self.next_command = 0
        # (record time, order, topic, message): messages wait here until no later
        # sample can be recorded before them (delays are >= 0).
        self.queue: list[tuple[int, int, str, Any]] = []
        self.order = 0

    def stamp(self, k: int) -> int:
        """Return the bag time of sample k."""
        return self.options.start_time_ns + int(round(k * NS_PER_S / self.options.rate))

    def _topic_stamp(self, every: int, j: int) -> int:
        return self.stamp(j * every)

    def _push(self, record_ns: int, topic: str, msg: Any) -> None:
        heapq.heappush(self.queue, (record_ns, self.order, topic, msg))
        self.order += 1

    def _flush(self, before_ns: Optional[int]) -> None:
        queue = self.queue
        while queue and (before_ns is None or queue[0][0] < before_ns):
            record_ns, _, topic, msg = heapq.heappop(queue)
            self.bag.write(topic, record_ns, msg)

    def _commands(self, until_s: Optional[float]) -> None:
        """Queue the command messages up to ``until_s`` (all when None)."""
        thrusters, times = self.thrusters, self.commands
        while self.next_command < len(times) and (until_s is None
                                                  or times[self.next_command] <= until_s):
            t = times[self.next_command]
            stamp = self.options.start_time_ns + int(round(t * NS_PER_S))
            wrench6 = thrusters.command(thrusters.on(self.options.firings, t))
            sample = WrenchSample(stamp, self.robot.base_link, wrench6[:3], wrench6[3:])
            self._push(stamp, TOPIC_COMMAND, wrench_to_ros(sample, self.types))
            self.next_command += 1

    def record(self, k: int, state: FreeFloatingState, mu: np.ndarray, tau: np.ndarray,
               external: np.ndarray, body_wrench: np.ndarray) -> None:
        """Queue every topic for sample k and write what can no longer be overtaken."""
        robot, options, types = self.robot, self.options, self.types
        self._check_regular(k, state.qbar)
        self._check_limits(k, state.qbar, state.qbar_dot, tau)
        stamp = self.stamp(k)
        t = k / options.rate
        self._commands(t)
        self._flush(stamp)
        timing = self.timing.get(TOPIC_JOINT_STATES)
        every = self.every[TOPIC_JOINT_STATES]
        if timing is not None and k % every == 0:
            position, velocity, effort = self.noise.joints(state.qbar, state.qbar_dot, tau)
            times = timing.message(k // every, t)
            if times is not None:
                sample = JointStateSample(times[0], '', self.names, position, velocity, effort)
                self._push(times[1], TOPIC_JOINT_STATES, joint_state_to_ros(sample, types))
        every = self.every[self.base_topic]
        times = None
        if k % every == 0:
            position, quaternion, twist6 = self.noise.base(state.g,
                                                           robot.group.twist(state.xi))
            times = self.timing[self.base_topic].message(k // every, t)
        if times is not None:
            base = BaseStateSample(times[0], WORLD_FRAME, robot.base_link, position,
                                   quaternion, twist6[:3], twist6[3:])
            if options.base_pose_only and options.base_pose_covariance:
                msg = base_state_to_pose_with_covariance_stamped(base, types, self.pose_cov)
            elif options.base_pose_only:
                msg = base_state_to_pose_stamped(base, types)
            else:
                msg = base_state_to_odometry(base, types, self.pose_cov, self.twist_cov)
            self._push(times[1], self.base_topic, msg)
        self._push(stamp, TOPIC_MOMENTUM, wrench_to_ros(_wrench(mu, robot, stamp), types))
        self._push(stamp, TOPIC_EXTERNAL_WRENCH,
                   wrench_to_ros(_wrench(external, robot, stamp), types))
        truth = BaseStateSample(stamp, WORLD_FRAME, robot.base_link, state.g.translation,
                                _quaternion_xyzw(state.g.rotation), np.zeros(3), np.zeros(3))
        self._push(stamp, TOPIC_TRUE_POSE, base_state_to_pose_stamped(truth, types))
        if options.status and k % self.status_every == 0:
            self._status(stamp, state, body_wrench)

    def finish(self) -> None:
        """Write every queued message."""
        self._commands(None)
        self._flush(None)

    def _status(self, stamp: int, state: FreeFloatingState, body_wrench: np.ndarray) -> None:
        robot = self.robot
        velocity = np.concatenate([state.xi, state.qbar_dot])
        kinetic = 0.5 * float(velocity @ robot.mass_matrix(state.qbar) @ velocity)
        msg = self.types.create(
            STATUS_MSGTYPE, header=header_to_ros(stamp, robot.base_link, self.types),
            torque_mode=self.options.torque, thruster_active=bool(np.any(body_wrench != 0.0)),
            base_wrench=np.asarray(body_wrench, dtype=np.float64),
            kinetic_energy=kinetic, potential_energy=robot.potential_energy(state.qbar))
        self._push(stamp, TOPIC_STATUS, msg)

    def _check_limits(self, k: int, qbar: np.ndarray, qbar_dot: np.ndarray,
                      tau: np.ndarray) -> None:
        """
        Stop when a joint leaves what replay accepts of its URDF ``<limit>``.

        The true state goes through replay's own plausibility gate at its
        defaults (:class:`~reduced_dynamics.estimator.plausibility.JointBounds`:
        limits plus ``joint_limit_margin``, ``limit_factor`` times the velocity
        and effort limits): a bag past it would have its samples rejected.
        """
        if self.bounds is None:
            return
        verdict = self.bounds.check(qbar.tolist(), qbar_dot.tolist(), list(tau))
        if verdict is not None:
            raise ValueError(
                f'a joint left its URDF limits at t = {k / self.options.rate:g} s '
                f'({verdict[0]}: {verdict[1]}); replay would reject these samples: use a '
                f'smaller --torque-scale, --torque pd, a shorter --duration or another --seed '
                f'(--joint-limits ignore writes the bag anyway)')

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
    planned = _planned_start(robot, state, options) if options.trajectory else None
    excitation = None if planned else make_excitation(robot, state, scenario_torque, options)
    topics = bag_topics(options, robot)
    store = status_typestore() if options.status else None
    bag = BagWriter(out, topics, typestore=store, overwrite=options.overwrite)
    bag.open()
    try:
        recorder = _Recorder(robot, options, bag)
        if planned:
            initial_mu, final_mu, pulses, firings = _run_planned(robot, planned, options,
                                                                 recorder)
        else:
            initial_mu, final_mu, pulses, firings = _run(robot, state, excitation, options,
                                                         recorder)
        recorder.finish()
        bag.close()
    except BaseException:
        bag.abort()
        shutil.rmtree(out, ignore_errors=True)
        raise
    thrusters = options.thruster_set()
    firing_summaries = []
    for firing, impulse in zip(options.firings, firings):
        command = thrusters.command(firing.thrusters)
        firing_summaries.append(FiringSummary(
            firing.start, firing.duration, firing.thrusters, command,
            thrusters.delivered(command), robot.group.dual_to_wrench(impulse)))
    return SimulationSummary(
        path=out, robot=robot.model.name, base_link=robot.base_link,
        base_group=robot.group.name, joint_names=tuple(robot.shape_joint_names),
        duration=options.duration, rate=options.rate, samples=options.samples,
        torque='trajectory' if options.trajectory else options.torque, seed=int(options.seed),
        start_time_ns=int(options.start_time_ns),
        message_counts=dict(bag.message_counts), topic_types=topics,
        initial_momentum=robot.group.dual_to_wrench(initial_mu),
        final_momentum=robot.group.dual_to_wrench(final_mu),
        pulses=[PulseSummary(p.start, p.duration, np.array(p.wrench),
                             robot.group.dual_to_wrench(impulse))
                for p, impulse in zip(options.thrusters, pulses)],
        firings=firing_summaries,
        sensors={topic: timing.stats for topic, timing in recorder.timing.items()},
        wall_seconds=time.perf_counter() - started)


def _piece_wrench(options: SimulationOptions, piece: _Piece) -> np.ndarray:
    """Return the body wrench on the base during ``piece``: pulses plus delivered thrust."""
    body_wrench = np.zeros(6)
    for index in piece.pulses:
        body_wrench += np.asarray(options.thrusters[index].wrench)
    thrusters = options.thruster_set()
    if thrusters is not None:
        on = thrusters.on(options.firings, 0.5 * (piece.start + piece.end))
        body_wrench = body_wrench + thrusters.delivered(thrusters.command(on))
    return body_wrench


def _run(robot: RobotModel, state: FreeFloatingState, excitation: Excitation,
         options: SimulationOptions, recorder: _Recorder
         ) -> tuple[np.ndarray, np.ndarray, list[np.ndarray], list[np.ndarray]]:
    """Integrate piece by piece, writing each piece's samples; return mu0, mu_end, impulses."""
    impulses = [np.zeros(robot.n) for _ in options.thrusters]
    firing_impulses = [np.zeros(robot.n) for _ in options.firings]
    dynamics = FullDynamics(robot)
    mu_first = mu_last = np.zeros(robot.n)
    for piece in _pieces(options, excitation.breakpoints):
        torque = excitation.law(0.5 * (piece.start + piece.end))
        body_wrench = _piece_wrench(options, piece)
        pushed = bool(np.any(body_wrench != 0.0))
        dynamics.torque = torque
        dynamics.base_wrench = _constant_wrench(body_wrench) if pushed else None
        samples = np.arange(piece.first, piece.stop) / options.rate
        half = 0.5 * (piece.end - piece.start)
        nodes = piece.start + half * (1.0 + _GAUSS_NODES) if pushed else np.zeros(0)
        times = np.unique(np.concatenate([[piece.start, piece.end], samples, nodes]))
        trajectory = dynamics.simulate(state, times, options.rtol, options.atol)
        where = np.searchsorted(times, samples)
        for k, index in zip(range(piece.first, piece.stop), where):
            sample_state = trajectory.state(index)
            tau = np.asarray(torque(times[index], sample_state.qbar, sample_state.qbar_dot),
                             dtype=float)
            external = dynamics.world_wrench(times[index], sample_state.g)
            recorder.record(k, sample_state, trajectory.mu[index], tau, external, body_wrench)
        if pushed:
            where_nodes = np.searchsorted(times, nodes)
            for pulse_index in piece.pulses:
                _add_impulse(robot, options.thrusters[pulse_index].wrench, trajectory,
                             where_nodes, half, impulses[pulse_index])
            for firing_index in piece.firings:
                _add_impulse(robot, body_wrench - _pulse_wrench(options, piece), trajectory,
                             where_nodes, half, firing_impulses[firing_index])
        if piece.start == 0.0:
            mu_first = trajectory.mu[0].copy()
        mu_last = trajectory.mu[-1].copy()
        state = trajectory.state(len(times) - 1)
    return mu_first, mu_last, impulses, firing_impulses


def _planned_start(robot: RobotModel, state: FreeFloatingState,
                   options: SimulationOptions) -> tuple:
    """
    Return (trajectory sample, shape path, g0, xi0) of a ``--trajectory`` run.

    The shape starts on the plan (joints it leaves out at the scenario's
    shape, at rest); the base at the scenario's pose and momentum mu (so
    ``--momentum-class`` still chooses the class): xi0 = I^-1 (pi - B qbar_dot0).
    """
    from reduced_dynamics.estimator.base_motion import plan_of
    from reduced_dynamics.trajectory_file import load_trajectory
    trajectory = load_trajectory(options.trajectory, robot.shape_joint_names)
    plan = plan_of(robot, trajectory, 0)
    qbar0 = state.qbar.copy()
    if trajectory.times_from_start_ns[0] == 0:
        qbar0[plan.index] = trajectory.positions[0]
    path = plan.path_from(0, qbar0, np.zeros(robot.m))
    if path is None:
        raise ValueError(f'trajectory {options.trajectory} has a single point at time 0')
    n = robot.n
    pi = robot.mass_matrix(state.qbar)[:n] @ np.concatenate([state.xi, state.qbar_dot])
    q0, qd0, _ = path(0.0)
    mass = robot.mass_matrix(q0)
    xi0 = np.linalg.solve(mass[:n, :n], pi - mass[:n, n:] @ qd0)
    return trajectory, path, state.g, xi0


def _run_planned(robot: RobotModel, planned: tuple, options: SimulationOptions,
                 recorder: _Recorder) -> tuple:
    """Play the plan with the exact shape path (full dynamics for the base); record it."""
    trajectory, path, g0, xi0 = planned
    sample = JointTrajectorySample(options.start_time_ns, '', trajectory.joint_names,
                                   trajectory.times_from_start_ns, trajectory.positions,
                                   trajectory.velocities, trajectory.accelerations)
    recorder.bag.write(TOPIC_TRAJECTORY, options.start_time_ns,
                       joint_trajectory_to_ros(sample, recorder.types))
    times = np.arange(options.samples) / options.rate
    run = PrescribedShapeDynamics(robot, path).simulate(g0, xi0, times, options.rtol,
                                                        options.atol)
    zero = np.zeros(robot.n)
    for k in range(len(times)):
        recorder.record(k, run.state(k), run.mu[k], run.torques[k], zero, np.zeros(6))
    return run.mu[0].copy(), run.mu[-1].copy(), [], []


def _pulse_wrench(options: SimulationOptions, piece: _Piece) -> np.ndarray:
    return sum((np.asarray(options.thrusters[i].wrench) for i in piece.pulses), np.zeros(6))


def _add_impulse(robot: RobotModel, body_wrench: Sequence[float], trajectory: FullTrajectory,
                 where: np.ndarray, half: float, impulse: np.ndarray) -> None:
    """Add the Gauss-Legendre quadrature of a body wrench's world wrench over the piece."""
    body = robot.group.dual_coordinates(np.asarray(body_wrench, dtype=float))
    for weight, index in zip(_GAUSS_WEIGHTS, where):
        ad = robot.group.Ad(trajectory.pose(index).inverse())
        impulse += half * weight * (ad.T @ body)


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


def _firing(text: str) -> ThrusterFiring:
    try:
        return ThrusterFiring.parse(text)
    except ValueError as error:
        raise argparse.ArgumentTypeError(str(error)) from None


def _unit_wrench(text: str) -> tuple[float, ...]:
    parts = text.split(',')
    if len(parts) != 6:
        raise argparse.ArgumentTypeError(f'{text!r} must be FX,FY,FZ,TX,TY,TZ (6 numbers)')
    return tuple(_number(p) for p in parts)


def _quantize(text: str) -> tuple[str, float]:
    name, _, step = text.partition('=')
    if name not in QUANTIZE_FIELDS:
        raise argparse.ArgumentTypeError(f'{text!r}: FIELD must be one of '
                                         f'{", ".join(QUANTIZE_FIELDS)}')
    return name, _positive(step)


def register_command(subparsers: Any) -> None:
    """Add the ``simulate`` subcommand to the ``reduced-dynamics`` parser."""
    from reduced_dynamics.cli import add_robot_arguments
    parser = subparsers.add_parser(
        'simulate', help='simulate full dynamics and write a rosbag2 (MCAP) bag',
        description='Integrate the full free-floating dynamics (Pinocchio aba, DOP853) and '
                    'write /joint_states, /odom (or /base_pose) and the ground truth '
                    '/ground_truth/momentum, /ground_truth/external_wrench and '
                    '/ground_truth/base_pose as a rosbag2 bag with MCAP storage. A joint '
                    'that leaves its URDF limits stops the run with a message.')
    add_robot_arguments(parser)
    parser.add_argument('-o', '--output', required=True, metavar='OUT',
                        help='bag directory to create')
    parser.add_argument('--overwrite', action='store_true',
                        help='replace OUT (and --summary) if they exist')
    parser.add_argument('--duration', type=_positive, default=10.0, help='seconds (default 10)')
    parser.add_argument('--rate', type=_positive, default=200.0,
                        help='sample rate of every topic, Hz (default 200)')
    parser.add_argument('--joint-rate', type=_positive, default=None,
                        help='rate of /joint_states, Hz: --rate divided by a whole number '
                             '(default --rate)')
    parser.add_argument('--base-rate', type=_positive, default=None,
                        help='rate of /odom or /base_pose, Hz: --rate divided by a whole '
                             'number (default --rate)')
    parser.add_argument('--seed', type=_seed, default=0, help='random seed (default 0)')
    parser.add_argument('--torque', choices=TORQUE_MODES, default='sinusoid',
                        help='joint torques: zero, constant (held --torque-hold s, alternating '
                             'sign), sinusoid, pd (PD tracking of a sinusoidal reference '
                             'about the initial shape) or multisine (PD tracking of a sum of '
                             'four sines of random frequencies per joint) (default sinusoid)')
    parser.add_argument('--torque-scale', type=_nonnegative, default=1.0,
                        help='scale of the torques (of the reference amplitude for pd and '
                             'multisine)')
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
    parser.add_argument('--noise-effort', type=_nonnegative, default=0.0,
                        help='std of joint effort noise (N m or N)')
    parser.add_argument('--noise-twist', type=_nonnegative, default=None,
                        help='std of base twist noise (m/s, rad/s; default --noise-velocity)')
    parser.add_argument('--noise-twist-angular', type=_nonnegative, default=None,
                        help='std of the base angular velocity noise (rad/s; default '
                             '--noise-twist)')
    parser.add_argument('--noise-orientation', type=_nonnegative, default=None,
                        help='std of base orientation noise (rad; default --noise-pose)')
    parser.add_argument('--quantize', type=_quantize, action='append', default=[],
                        metavar='FIELD=STEP',
                        help='round FIELD to multiples of STEP after the noise; FIELD one of '
                             + ', '.join(QUANTIZE_FIELDS) + '; repeatable')
    parser.add_argument('--drop-rate', type=_fraction, default=0.0,
                        help='fraction of sensor messages dropped at random, per topic')
    parser.add_argument('--outage-rate', type=_nonnegative, default=0.0,
                        help='sensor outages per second, per topic (Poisson; default 0)')
    parser.add_argument('--outage-duration', type=_positive, default=0.04,
                        help='mean outage length, s (exponential; default 0.04)')
    parser.add_argument('--stamp-jitter', type=_nonnegative, default=0.0,
                        help='std of the header stamp error of sensor messages, s')
    parser.add_argument('--bunch-fraction', type=_fraction, default=0.0,
                        help='fraction of sensor messages stamped --bunch-gap before the next '
                             'one (pairs of packets stamped together, as mocap does)')
    parser.add_argument('--bunch-gap', type=_positive, default=3e-5,
                        help='mean stamp gap of a bunched pair, s (uniform in [0.5, 1.5] '
                             'times it; default 3e-5)')
    parser.add_argument('--stamp-on-receipt', type=_nonnegative, default=0.0,
                        metavar='POLL_PERIOD', dest='poll_period',
                        help='stamp sensor messages on receipt by a client polling every '
                             'POLL_PERIOD s (vrpn_mocap: 0.01): stamps at the next poll, '
                             'bursts after late polls (instead of --stamp-jitter and '
                             'bunching; 0: off)')
    parser.add_argument('--poll-late-fraction', type=_fraction, default=0.0,
                        help='fraction of polls that run late (default 0)')
    parser.add_argument('--poll-late-delay', type=_positive, default=0.05,
                        help='mean delay of a late poll, s (uniform in [0.5, 1.5] times it; '
                             'default 0.05)')
    parser.add_argument('--latency', type=_nonnegative, default=0.0,
                        help='mean delay from a sample to its record (bag log) time, s')
    parser.add_argument('--latency-jitter', type=_nonnegative, default=0.0,
                        help='std of that delay, s (the delay is clipped at 0)')
    parser.add_argument('--thruster-layout', choices=tuple(LAYOUTS), default='',
                        help='binary thrusters of a known robot (freeflyer: the 8 thrusters '
                             'of the freeflyer2 testbed, 0.2 N each)')
    parser.add_argument('--thruster-unit', type=_unit_wrench, action='append', default=[],
                        metavar='FX,FY,FZ,TX,TY,TZ',
                        help='body-frame wrench of one binary thruster per newton; '
                             'repeatable, numbered from 0 (instead of --thruster-layout)')
    parser.add_argument('--thruster-force', type=_positive, default=None,
                        help='nominal force of each binary thruster, N (default: the '
                             "layout's, else 1)")
    parser.add_argument('--fire', type=_firing, action='append', default=[],
                        metavar='T,DURATION,I[,J...]',
                        help='binary thrusters I, J, ... on during [T, T+DURATION); repeatable')
    parser.add_argument('--thrust-gain', type=float, nargs=6, default=[1.0] * 6,
                        metavar=('FX', 'FY', 'FZ', 'TX', 'TY', 'TZ'),
                        help='delivered = gain * commanded + bias, per body axis (default 1)')
    parser.add_argument('--thrust-bias', type=float, nargs=6, default=[0.0] * 6,
                        metavar=('FX', 'FY', 'FZ', 'TX', 'TY', 'TZ'),
                        help='constant body wrench added to the delivered thrust (N, N m; '
                             'acts also when no thruster fires; default 0)')
    parser.add_argument('--command-rate', type=_positive, default=10.0,
                        help=f'rate of {TOPIC_COMMAND} (geometry_msgs/WrenchStamped, the '
                             'commanded body wrench), Hz, plus one message at every switch '
                             '(default 10)')
    parser.add_argument('--base-pose-only', action='store_true',
                        help='write /base_pose (PoseStamped) instead of /odom')
    parser.add_argument('--base-pose-covariance', action='store_true',
                        help='with --base-pose-only: write PoseWithCovarianceStamped, '
                             'carrying the covariance of the noise added')
    parser.add_argument('--momentum-class', choices=tuple(MOMENTUM_CLASSES), default='generic',
                        help='class of the initial momentum (default generic)')
    parser.add_argument('--trajectory', metavar='FILE',
                        help='play a planned joint trajectory (YAML/CSV, see reduced-dynamics '
                             'predict): the shape follows it exactly, the base by the full '
                             f'dynamics; the plan is recorded on {TOPIC_TRAJECTORY}')
    parser.add_argument('--joint-limits', choices=JOINT_LIMIT_POLICIES, default='stop',
                        help='a joint that leaves what replay accepts of its URDF limits: '
                             'stop the run with a message (default), or ignore it (replay '
                             'then rejects those samples)')
    parser.add_argument('--payload', metavar='LINK,MASS,CX,CY,CZ,IXX,IYY,IZZ[,IXY,IXZ,IYZ]',
                        help='the robot holds a rigid payload on LINK: mass (kg), centre of '
                             'mass in the link frame (m), inertia about it (kg m^2); the bag '
                             'is the truth a replay with the nominal URDF does not know')
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
        base_pose_covariance=args.base_pose_covariance,
        noise_effort=args.noise_effort, noise_twist=args.noise_twist,
        noise_twist_angular=args.noise_twist_angular,
        noise_orientation=args.noise_orientation, quantize=tuple(args.quantize),
        stamp_jitter=args.stamp_jitter, bunch_fraction=args.bunch_fraction,
        bunch_gap=args.bunch_gap, latency=args.latency, latency_jitter=args.latency_jitter,
        outage_rate=args.outage_rate, outage_duration=args.outage_duration,
        poll_period=args.poll_period, poll_late_fraction=args.poll_late_fraction,
        poll_late_delay=args.poll_late_delay, thruster_layout=args.thruster_layout,
        thruster_units=tuple(args.thruster_unit),
        thruster_force=args.thruster_force, firings=tuple(args.fire),
        thrust_gain=tuple(args.thrust_gain), thrust_bias=tuple(args.thrust_bias),
        command_rate=args.command_rate, trajectory=args.trajectory or '',
        joint_limits=args.joint_limits,
        joint_rate=args.joint_rate, base_rate=args.base_rate,
        momentum_class=args.momentum_class, status=args.status, overwrite=args.overwrite,
        start_time_ns=int(round(args.start_time * NS_PER_S)))


def run_command(args: argparse.Namespace) -> int:
    """Run ``reduced-dynamics simulate``."""
    from reduced_dynamics.cli import load_robot_from_args
    options = options_from_args(args)
    if args.summary and Path(args.summary).exists() and not args.overwrite:
        raise ValueError(f'summary {args.summary} exists already (pass --overwrite to replace)')
    robot = load_robot_from_args(args)
    if args.payload:
        from reduced_dynamics.payload import Payload, with_payload
        robot = with_payload(robot, Payload.parse(args.payload))
    summary = simulate_bag(robot, args.output, options)
    if args.summary:
        summary.write_json(args.summary)
    print(summary.text())
    return 0
