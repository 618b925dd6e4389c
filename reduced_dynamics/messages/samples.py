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
ROS-free sample dataclasses exchanged between bag I/O, nodes and the estimator.

All times are integer nanoseconds (``stamp_ns``).  Arrays are coerced to
contiguous ``float64`` numpy arrays and shape-checked on construction.  The
dataclasses are frozen (fields cannot be rebound) and compare by identity,
because element-wise numpy comparison has no single truth value.
"""

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
import math
from typing import Optional, Union

import numpy as np

#: Diagnostic levels (diagnostic_msgs/msg/DiagnosticStatus constants).
DIAG_OK = 0
DIAG_WARN = 1
DIAG_ERROR = 2
DIAG_STALE = 3

KeyValues = Union[Mapping[str, str], Iterable[tuple[str, str]]]


def _stamp(value: int, name: str = 'stamp_ns') -> int:
    """Validate a non-negative integer nanosecond timestamp."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise TypeError(f'{name} must be an integer number of nanoseconds, got {value!r}')
    if value < 0:
        raise ValueError(f'{name} must be >= 0, got {value}')
    return int(value)


def _array(value: object, shape: tuple[Optional[int], ...], name: str) -> np.ndarray:
    """Coerce to a contiguous float64 array and check its shape (None = any size)."""
    arr = np.ascontiguousarray(value, dtype=np.float64)
    if arr.ndim != len(shape) or any(
        want is not None and have != want for have, want in zip(arr.shape, shape)
    ):
        pretty = tuple('*' if s is None else s for s in shape)
        raise ValueError(f'{name} must have shape {pretty}, got {arr.shape}')
    return arr


def _optional_array(value: object, shape: tuple[int, ...], name: str) -> Optional[np.ndarray]:
    """Like _array but passes None through."""
    return None if value is None else _array(value, shape, name)


def trusted_sample(cls: type, *values: object) -> object:
    """
    Build a sample dataclass from fields the caller guarantees valid, skipping checks.

    For hot paths that construct samples from arrays they own: every array must
    already be a contiguous float64 array of the right shape and ``stamp_ns`` a
    non-negative int, exactly what ``__post_init__`` would produce. Fields are
    given positionally, all of them.
    """
    sample = object.__new__(cls)
    sample.__dict__.update(zip(cls.__dataclass_fields__, values))
    return sample


def _validate_stamps(sample: object) -> None:
    """Normalise an input sample's header stamp and optional receive time (in place)."""
    object.__setattr__(sample, 'stamp_ns', _stamp(sample.stamp_ns))
    with_receive_time(sample, sample.receive_ns)


def with_receive_time(sample: object, receive_ns: Optional[int]) -> object:
    """Set the receive time of a freshly decoded (caller-owned) input sample; return it."""
    object.__setattr__(sample, 'receive_ns', None if receive_ns is None
                       else _stamp(receive_ns, 'receive_ns'))
    return sample


def message_covariance(values: np.ndarray) -> Optional[np.ndarray]:
    """
    Return a copy of a message's 36 covariance values, None when all are zero.

    All zeros is what a driver that fills no covariance sends (and what this
    package wrote before it wrote covariances): no information, not certainty.
    """
    return values.copy() if values.any() else None


def _times_from_start(value: object) -> np.ndarray:
    """Return trajectory point times [ns] as int64, checked >= 0 and strictly increasing."""
    times = np.asarray(value)
    if times.ndim != 1 or (times.size and not np.issubdtype(times.dtype, np.integer)):
        raise ValueError('times_from_start_ns must be a 1-D integer array (nanoseconds)')
    times = np.ascontiguousarray(times, dtype=np.int64)
    if times.size and (times[0] < 0 or np.any(np.diff(times) <= 0)):
        raise ValueError('times_from_start_ns must be >= 0 and strictly increasing')
    return times


@dataclass(frozen=True, eq=False)
class JointStateSample:
    """
    Joint state; velocity and effort may be empty (size 0).

    ``receive_ns``: when the message arrived (a bag's record time, rclpy's
    received timestamp), None when unknown; the estimator's stamp policy uses it.
    """

    stamp_ns: int
    frame_id: str
    names: tuple[str, ...]
    position: np.ndarray
    velocity: np.ndarray = field(default_factory=lambda: np.zeros(0))
    effort: np.ndarray = field(default_factory=lambda: np.zeros(0))
    receive_ns: Optional[int] = None

    def __post_init__(self) -> None:
        """Validate and normalize fields."""
        _validate_stamps(self)
        names = tuple(str(n) for n in self.names)
        object.__setattr__(self, 'names', names)
        n = len(names)
        object.__setattr__(self, 'position', _array(self.position, (n,), 'position'))
        for key in ('velocity', 'effort'):
            arr = np.ascontiguousarray(getattr(self, key), dtype=np.float64).reshape(-1)
            if arr.size not in (0, n):
                raise ValueError(f'{key} must be empty or have {n} entries, got {arr.size}')
            object.__setattr__(self, key, arr)


@dataclass(frozen=True, eq=False)
class BaseStateSample:
    """
    Floating-base pose in ``frame_id`` (world) with twist in ``child_frame_id`` (base).

    The twist follows REP 105 / nav_msgs/Odometry: expressed in the child
    (base) frame.  ``twist_linear``/``twist_angular`` are None when the
    source carries no twist (e.g. geometry_msgs/PoseStamped). ``receive_ns``:
    when the message arrived, None when unknown (as for joint states).
    ``pose_covariance`` / ``twist_covariance``: the message's row-major 6 x 6
    covariances (36 values, order x y z roll pitch yaw; the pose's in
    ``frame_id``, the twist's in ``child_frame_id``, REP 103/105), None when the
    message carries none or only zeros (:func:`message_covariance`).
    """

    stamp_ns: int
    frame_id: str
    child_frame_id: str
    position: np.ndarray
    orientation_xyzw: np.ndarray
    twist_linear: Optional[np.ndarray] = None
    twist_angular: Optional[np.ndarray] = None
    receive_ns: Optional[int] = None
    pose_covariance: Optional[np.ndarray] = None
    twist_covariance: Optional[np.ndarray] = None

    def __post_init__(self) -> None:
        """Validate and normalize fields."""
        _validate_stamps(self)
        for key in ('pose_covariance', 'twist_covariance'):
            value = getattr(self, key)
            if value is not None:
                value = np.reshape(np.asarray(value, dtype=np.float64), -1)
            object.__setattr__(self, key, _optional_array(value, (36,), key))
        object.__setattr__(self, 'position', _array(self.position, (3,), 'position'))
        object.__setattr__(
            self, 'orientation_xyzw', _array(self.orientation_xyzw, (4,), 'orientation_xyzw'))
        if (self.twist_linear is None) != (self.twist_angular is None):
            raise ValueError('twist_linear and twist_angular must both be set or both be None')
        object.__setattr__(
            self, 'twist_linear', _optional_array(self.twist_linear, (3,), 'twist_linear'))
        object.__setattr__(
            self, 'twist_angular', _optional_array(self.twist_angular, (3,), 'twist_angular'))

    @property
    def has_twist(self) -> bool:
        """Return True when the sample carries a base twist."""
        return self.twist_linear is not None


@dataclass(frozen=True, eq=False)
class WrenchSample:
    """Force/torque pair (also used for momenta: force=linear, torque=angular)."""

    stamp_ns: int
    frame_id: str
    force: np.ndarray
    torque: np.ndarray

    def __post_init__(self) -> None:
        """Validate and normalize fields."""
        object.__setattr__(self, 'stamp_ns', _stamp(self.stamp_ns))
        object.__setattr__(self, 'force', _array(self.force, (3,), 'force'))
        object.__setattr__(self, 'torque', _array(self.torque, (3,), 'torque'))


@dataclass(frozen=True, eq=False)
class CommandSample:
    """
    A commanded wrench (geometry_msgs/WrenchStamped as an input), base (body) frame.

    What the thrusters or actuators were told to deliver; ``receive_ns`` as for
    the other inputs (the stamp policy uses it).
    """

    stamp_ns: int
    frame_id: str
    force: np.ndarray
    torque: np.ndarray
    receive_ns: Optional[int] = None

    def __post_init__(self) -> None:
        """Validate and normalize fields."""
        _validate_stamps(self)
        object.__setattr__(self, 'force', _array(self.force, (3,), 'force'))
        object.__setattr__(self, 'torque', _array(self.torque, (3,), 'torque'))


@dataclass(frozen=True, eq=False)
class TwistSample:
    """Linear/angular velocity pair expressed in ``frame_id``."""

    stamp_ns: int
    frame_id: str
    linear: np.ndarray
    angular: np.ndarray

    def __post_init__(self) -> None:
        """Validate and normalize fields."""
        object.__setattr__(self, 'stamp_ns', _stamp(self.stamp_ns))
        object.__setattr__(self, 'linear', _array(self.linear, (3,), 'linear'))
        object.__setattr__(self, 'angular', _array(self.angular, (3,), 'angular'))


@dataclass(frozen=True, eq=False)
class ShapePrediction:
    """
    Predicted shape trajectory starting at ``stamp_ns``.

    ``times_from_start_ns`` (N,) must be non-negative and strictly increasing;
    ``positions`` is (N, m); ``velocities`` is (N, m) or None.
    """

    stamp_ns: int
    frame_id: str
    joint_names: tuple[str, ...]
    times_from_start_ns: np.ndarray
    positions: np.ndarray
    velocities: Optional[np.ndarray] = None

    def __post_init__(self) -> None:
        """Validate and normalize fields."""
        object.__setattr__(self, 'stamp_ns', _stamp(self.stamp_ns))
        names = tuple(str(n) for n in self.joint_names)
        object.__setattr__(self, 'joint_names', names)
        times = _times_from_start(self.times_from_start_ns)
        object.__setattr__(self, 'times_from_start_ns', times)
        shape = (times.size, len(names))
        object.__setattr__(self, 'positions', _array(self.positions, shape, 'positions'))
        object.__setattr__(
            self, 'velocities', _optional_array(self.velocities, shape, 'velocities'))


@dataclass(frozen=True, eq=False)
class JointTrajectorySample:
    """
    A planned joint trajectory (trajectory_msgs/JointTrajectory as an input).

    Times count from ``stamp_ns`` (0: start on arrival, as joint_trajectory_controller
    does); ``times_from_start_ns`` (N,) non-negative and strictly increasing;
    ``positions`` (N, m); ``velocities`` / ``accelerations`` (N, m) or None
    (accelerations only with velocities).
    """

    stamp_ns: int
    frame_id: str
    joint_names: tuple[str, ...]
    times_from_start_ns: np.ndarray
    positions: np.ndarray
    velocities: Optional[np.ndarray] = None
    accelerations: Optional[np.ndarray] = None
    receive_ns: Optional[int] = None

    def __post_init__(self) -> None:
        """Validate and normalize fields."""
        _validate_stamps(self)
        names = tuple(str(n) for n in self.joint_names)
        object.__setattr__(self, 'joint_names', names)
        times = _times_from_start(self.times_from_start_ns)
        object.__setattr__(self, 'times_from_start_ns', times)
        shape = (times.size, len(names))
        object.__setattr__(self, 'positions', _array(self.positions, shape, 'positions'))
        object.__setattr__(
            self, 'velocities', _optional_array(self.velocities, shape, 'velocities'))
        object.__setattr__(
            self, 'accelerations', _optional_array(self.accelerations, shape, 'accelerations'))
        if self.accelerations is not None and self.velocities is None:
            raise ValueError('accelerations need velocities')


@dataclass(frozen=True, eq=False)
class PosePath:
    """Sequence of stamped poses in ``frame_id`` (e.g. a drift-integrated base path)."""

    stamp_ns: int
    frame_id: str
    stamps_ns: np.ndarray
    positions: np.ndarray
    orientations_xyzw: np.ndarray

    def __post_init__(self) -> None:
        """Validate and normalize fields."""
        object.__setattr__(self, 'stamp_ns', _stamp(self.stamp_ns))
        stamps = np.asarray(self.stamps_ns)
        if stamps.ndim != 1 or (stamps.size and not np.issubdtype(stamps.dtype, np.integer)):
            raise ValueError('stamps_ns must be a 1-D integer array (nanoseconds)')
        stamps = np.ascontiguousarray(stamps, dtype=np.int64)
        if stamps.size and stamps.min() < 0:
            raise ValueError('stamps_ns must be >= 0')
        object.__setattr__(self, 'stamps_ns', stamps)
        n = stamps.size
        object.__setattr__(self, 'positions', _array(self.positions, (n, 3), 'positions'))
        object.__setattr__(
            self,
            'orientations_xyzw',
            _array(self.orientations_xyzw, (n, 4), 'orientations_xyzw'),
        )


@dataclass(frozen=True, eq=False)
class DiagnosticStatusSample:
    """One diagnostic status; ``values`` accepts a dict or (key, value) pairs."""

    level: int
    name: str
    message: str = ''
    hardware_id: str = ''
    values: tuple[tuple[str, str], ...] = ()

    def __post_init__(self) -> None:
        """Validate and normalize fields."""
        level = int(self.level)
        if level not in (DIAG_OK, DIAG_WARN, DIAG_ERROR, DIAG_STALE):
            raise ValueError(f'diagnostic level must be 0 (OK)..3 (STALE), got {self.level!r}')
        object.__setattr__(self, 'level', level)
        raw = self.values.items() if isinstance(self.values, Mapping) else self.values
        pairs = tuple((str(k), str(v)) for k, v in raw)
        object.__setattr__(self, 'values', pairs)

    def values_dict(self) -> dict[str, str]:
        """Return the key/value pairs as a dict (later duplicates win)."""
        return dict(self.values)


@dataclass(frozen=True, eq=False)
class Diagnostics:
    """A diagnostic array: several statuses sharing one stamp."""

    stamp_ns: int
    statuses: tuple[DiagnosticStatusSample, ...]
    frame_id: str = ''

    def __post_init__(self) -> None:
        """Validate and normalize fields."""
        object.__setattr__(self, 'stamp_ns', _stamp(self.stamp_ns))
        statuses = tuple(self.statuses)
        for status in statuses:
            if not isinstance(status, DiagnosticStatusSample):
                raise TypeError(f'statuses must be DiagnosticStatusSample, got {status!r}')
        object.__setattr__(self, 'statuses', statuses)


#: The ``~/events`` record (std_msgs/Float64MultiArray): its fields in order, with
#: their number of values. The message's layout names them (one dimension per field,
#: label = name, size = stride = number of values), so a reader can find them by name.
EVENT_FIELDS: tuple[tuple[str, int], ...] = (
    ('start', 2),               # the push's estimated start: sec, nanosec
    ('end', 2),                 # its end: sec, nanosec (NaN while under way)
    ('detected', 2),            # when it was flagged: sec, nanosec
    ('window', 1),              # the multi-scale window [s] that found it (NaN: per sample)
    ('peak_wrench', 1),         # largest |w| during the event [N, N m mixed as |w|]
    ('impulse', 6),             # mu after - mu before: fx fy fz tx ty tz [N s, N m s], world
    ('impulse_covariance', 36),  # its covariance (an upper bound), row-major
    ('final', 1),               # 1: the impulse has settled; 0: announced at detection
)


@dataclass(frozen=True, eq=False)
class EventSample:
    """
    An external-wrench event as the ``~/events`` topic carries it (world frame).

    ``end_ns`` None while under way, ``window`` None when the per-sample chi-square
    or the step test found it; ``impulse`` (6,) and ``impulse_covariance`` (6, 6) in
    the wrench order of ``~/momentum``, NaN where unknown.
    """

    start_ns: int
    end_ns: Optional[int]
    detected_ns: int
    window: Optional[float]
    peak_wrench: float
    impulse: np.ndarray
    impulse_covariance: np.ndarray
    final: bool

    def __post_init__(self) -> None:
        """Validate and normalize fields."""
        object.__setattr__(self, 'start_ns', _stamp(self.start_ns, 'start_ns'))
        object.__setattr__(self, 'detected_ns', _stamp(self.detected_ns, 'detected_ns'))
        if self.end_ns is not None:
            object.__setattr__(self, 'end_ns', _stamp(self.end_ns, 'end_ns'))
        object.__setattr__(self, 'window', None if self.window is None else float(self.window))
        object.__setattr__(self, 'peak_wrench', float(self.peak_wrench))
        object.__setattr__(self, 'impulse', _array(self.impulse, (6,), 'impulse'))
        object.__setattr__(self, 'impulse_covariance',
                           _array(self.impulse_covariance, (6, 6), 'impulse_covariance'))
        object.__setattr__(self, 'final', bool(self.final))

    def values(self) -> np.ndarray:
        """Return the record's values in the order of :data:`EVENT_FIELDS`."""
        def stamp(ns: Optional[int]) -> tuple[float, float]:
            return (math.nan, math.nan) if ns is None else \
                tuple(float(v) for v in divmod(ns, 1_000_000_000))
        return np.concatenate([
            stamp(self.start_ns), stamp(self.end_ns), stamp(self.detected_ns),
            [math.nan if self.window is None else self.window, self.peak_wrench],
            self.impulse, self.impulse_covariance.reshape(-1), [float(self.final)]])

    @classmethod
    def from_values(cls, values: np.ndarray) -> 'EventSample':
        """Return the event a record's values describe (the inverse of :meth:`values`)."""
        values = np.asarray(values, dtype=float)
        if values.shape != (sum(size for _, size in EVENT_FIELDS),):
            raise ValueError(f'an event record has {sum(s for _, s in EVENT_FIELDS)} '
                             f'values, got {values.shape}')

        def stamp(pair: np.ndarray) -> Optional[int]:
            return None if np.isnan(pair).any() else \
                int(pair[0]) * 1_000_000_000 + int(pair[1])
        return cls(stamp(values[0:2]), stamp(values[2:4]), stamp(values[4:6]),
                   None if np.isnan(values[6]) else float(values[6]), values[7],
                   values[8:14], values[14:50].reshape(6, 6), values[50] > 0.5)
