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
Fixed-layout CDR encoders and decoders for the messages the replay writes and reads.

Encoders turn sample dataclasses straight into the bytes that
``typestore.serialize_cdr(<x>_to_ros(sample, RosbagsTypes()), msgtype)`` gives
(little-endian CDR, header ``00 01 00 00``, no trailing padding), without
building message objects. Decoders turn input bytes straight into the samples
that ``<x>_from_ros(typestore.deserialize_cdr(data, msgtype))`` gives.

Layout rules: offsets align relative to the end of the 4-byte header; a
string is a uint32 length (NUL included), the bytes and a NUL; a sequence is
a uint32 count, then its elements, aligned (an empty primitive sequence adds
no padding, as rosbags and Fast-CDR do).

Everything assumes the ROS 2 definitions of :data:`ENCODERS` and
:data:`DECODERS` (identical from Humble to Jazzy) and a little-endian host;
:func:`fast_path_applies` checks both. Decoders are strict: anything they do
not accept (big-endian data, bad lengths, trailing bytes, invalid UTF-8,
negative stamps, inconsistent arrays) raises, and the caller falls back to
the typestore, which then decides what is wrong and says so.
"""

from __future__ import annotations

import functools
import struct
import sys
from typing import Any, Callable, Optional, Union

import numpy as np

from reduced_dynamics.messages.samples import (
    BaseStateSample,
    CommandSample,
    Diagnostics,
    EVENT_FIELDS,
    EventSample,
    JointStateSample,
    message_covariance,
    PosePath,
    ShapePrediction,
    trusted_sample,
    TwistSample,
    WrenchSample,
)
from reduced_dynamics.messages.stamps import NS_PER_S
from reduced_dynamics.messages.typestore import jazzy_hash, rihs01

Buffer = Union[bytes, bytearray, memoryview]

HEADER = b'\x00\x01\x00\x00'
_INT32_MAX = 2**31 - 1
_INT32_MIN = -(2**31)
_F8 = np.dtype('<f8')
_U32 = struct.Struct('<I')
_TIME = struct.Struct('<iI')
_HEAD = struct.Struct('<iII')  # Header stamp (sec, nanosec) and frame_id length
_ZEROS = b'\x00' * 8
_CACHE_LIMIT = 256  # memory stays flat whatever the bag: caches reset when full


class CdrError(ValueError):
    """Bytes the fixed-layout decoder does not accept (the generic path decides)."""


def _cached(cache: dict, key: Any, make: Callable[[], Any]) -> Any:
    """Return ``cache[key]``, computing it on a miss (bounded size)."""
    value = cache.get(key)
    if value is None:
        if len(cache) >= _CACHE_LIMIT:
            cache.clear()
        value = cache[key] = make()
    return value


def _f64(values: np.ndarray) -> bytes:
    """Return the little-endian float64 bytes of an array (or sequence) of numbers."""
    if getattr(values, 'dtype', None) is not _F8:
        values = np.asarray(values, dtype=_F8)
    return values.tobytes()


def _time(stamp_ns: int) -> bytes:
    """Encode builtin_interfaces/Time (the checks of ``time_to_ros``)."""
    sec, nanosec = divmod(int(stamp_ns), NS_PER_S)
    if sec < 0:
        raise ValueError(f'ROS Time cannot be negative, got {stamp_ns} ns')
    if sec > _INT32_MAX:
        raise ValueError(f'ROS Time sec overflows int32: {stamp_ns} ns')
    return _TIME.pack(sec, nanosec)


def _duration(duration_ns: int) -> bytes:
    """Encode builtin_interfaces/Duration (the checks of ``duration_to_ros``)."""
    sec, nanosec = divmod(int(duration_ns), NS_PER_S)
    if not _INT32_MIN <= sec <= _INT32_MAX:
        raise ValueError(f'ROS Duration sec overflows int32: {duration_ns} ns')
    return _TIME.pack(sec, nanosec)


class CdrBuilder:
    """Append CDR fields to a message, tracking the alignment offset."""

    __slots__ = ('parts', 'pos')

    def __init__(self) -> None:
        """Start a message after its encapsulation header."""
        self.parts: list[bytes] = [HEADER]
        self.pos = 0

    def align(self, size: int) -> None:
        """Pad to a multiple of ``size`` (1, 2, 4 or 8)."""
        pad = -self.pos & (size - 1)
        if pad:
            self.parts.append(_ZEROS[:pad])
            self.pos += pad

    def raw(self, data: bytes) -> None:
        """Append bytes that need no alignment (or were aligned by the caller)."""
        self.parts.append(data)
        self.pos += len(data)

    def uint32(self, value: int) -> None:
        """Append an aligned 32-bit unsigned integer, e.g. a sequence count."""
        self.align(4)
        self.raw(_U32.pack(value))

    def string(self, text: str) -> None:
        """Append a text: length with NUL, UTF-8 bytes, NUL."""
        data = text.encode()
        self.uint32(len(data) + 1)
        self.raw(data + b'\x00')

    def strings(self, texts: tuple[str, ...]) -> None:
        """Append a sequence of texts; the encoded block is cached as names repeat."""
        self.uint32(len(texts))
        self.raw(_cached(_STRINGS, texts, lambda: _string_block(texts)))

    def stamp(self, stamp_ns: int) -> None:
        """Append builtin_interfaces/Time."""
        self.align(4)
        self.raw(_time(stamp_ns))

    def header(self, stamp_ns: int, frame_id: str) -> None:
        """Append std_msgs/Header."""
        self.stamp(stamp_ns)
        self.string(str(frame_id))

    def float64s(self, values: np.ndarray) -> None:
        """Append a float64 sequence (no element padding when empty)."""
        data = _f64(values)
        self.uint32(len(data) >> 3)
        if data:
            self.align(8)
            self.raw(data)

    def getvalue(self) -> bytes:
        """Return the serialized message, header included."""
        return b''.join(self.parts)


_STRINGS: dict = {}
_FRAMES: dict = {}
_FRAMES4: dict = {}


def _string_block(texts: tuple[str, ...]) -> bytes:
    """Encode strings back to back from a 4-aligned offset (no count)."""
    builder = CdrBuilder()
    for text in texts:
        builder.string(text)
    return b''.join(builder.parts[1:])


def _frame_block(frame_id: str, alignment: int) -> bytes:
    """Encode a Header's frame_id (at offset 8) plus the padding to ``alignment``."""
    data = frame_id.encode()
    end = 12 + len(data) + 1
    return _U32.pack(len(data) + 1) + data + _ZEROS[:1 + (-end & (alignment - 1))]


def _header8(stamp_ns: int, frame_id: str) -> bytes:
    """Encode a leading std_msgs/Header padded for a float64 that follows."""
    return HEADER + _time(stamp_ns) + _cached(
        _FRAMES, frame_id, lambda: _frame_block(str(frame_id), 8))


# ------------------------------------------------------------------ encoders


def encode_wrench_stamped(sample: WrenchSample) -> bytes:
    """Encode geometry_msgs/msg/WrenchStamped."""
    body = _f64(sample.force) + _f64(sample.torque)
    if len(body) != 48:
        raise ValueError('force and torque must have 3 entries each')
    return _header8(sample.stamp_ns, sample.frame_id) + body


def encode_twist_stamped(sample: TwistSample) -> bytes:
    """Encode geometry_msgs/msg/TwistStamped."""
    body = _f64(sample.linear) + _f64(sample.angular)
    if len(body) != 48:
        raise ValueError('linear and angular must have 3 entries each')
    return _header8(sample.stamp_ns, sample.frame_id) + body


def encode_joint_state(sample: JointStateSample) -> bytes:
    """Encode sensor_msgs/msg/JointState."""
    # Unrolled CdrBuilder calls: this message goes out with every sample.
    frame = _cached(_FRAMES4, sample.frame_id, lambda: _frame_block(str(sample.frame_id), 4))
    names = sample.names
    block = _cached(_STRINGS, names, lambda: _string_block(names))
    parts = [HEADER, _time(sample.stamp_ns), frame, _U32.pack(len(names)), block]
    pos = 12 + len(frame) + len(block)
    for values in (sample.position, sample.velocity, sample.effort):
        data = _f64(values)
        pad = -pos & 3
        parts.append(_ZEROS[:pad] + _U32.pack(len(data) >> 3))
        pos += pad + 4
        if data:
            pad = pos & 4  # pos is 4-aligned: 0 or 4 bytes to 8
            parts.append(_ZEROS[:pad] + data)
            pos += pad + len(data)
    return b''.join(parts)


def _seconds(stamps_ns: np.ndarray, low: int, what: str) -> tuple[list, list]:
    """Split integer nanoseconds into (sec, nanosec) lists, sec within [low, int32 max]."""
    sec, nanosec = np.divmod(np.asarray(stamps_ns, dtype=np.int64), NS_PER_S)
    if sec.size and (sec.min() < low or sec.max() > _INT32_MAX):
        raise ValueError(f'{what} sec outside [{low}, {_INT32_MAX}] in {stamps_ns}')
    return sec.tolist(), nanosec.tolist()


_LAYOUTS: dict = {}


def _points_layout(count: int, m: int, velocities: bool, start: int) -> struct.Struct:
    """Return the struct of ``count`` JointTrajectoryPoints from (4-aligned) offset ``start``."""
    fmt, pos = ['<'], start
    for _ in range(count):
        for size in (m, m if velocities else 0, 0, 0):  # positions ... effort
            fmt.append('I')
            pos += 4
            if size:
                pad = -pos & 7
                fmt.append(f'{pad}x{size}d')
                pos += pad + 8 * size
        fmt.append('iI')  # time_from_start, 4-aligned after a count or float64 values
        pos += 8
    return struct.Struct(''.join(fmt))


def encode_joint_trajectory(sample: ShapePrediction) -> bytes:
    """Encode trajectory_msgs/msg/JointTrajectory like ``shape_prediction_to_ros``."""
    out = CdrBuilder()
    out.header(sample.stamp_ns, sample.frame_id)
    out.strings(sample.joint_names)
    count = len(sample.times_from_start_ns)
    out.uint32(count)
    sec, nanosec = _seconds(sample.times_from_start_ns, _INT32_MIN, 'ROS Duration')
    m = len(sample.joint_names)
    positions = np.asarray(sample.positions, dtype=_F8).reshape(count, m)
    velocities = sample.velocities
    # One struct.pack for all points: their layout depends on m and alignment only.
    layout = _cached(_LAYOUTS, ('points', count, m, velocities is not None, out.pos & 7),
                     lambda: _points_layout(count, m, velocities is not None, out.pos & 7))
    values: list = []
    rows = positions.tolist()
    if velocities is None:
        for i in range(count):
            values += (m, *rows[i], 0, 0, 0, sec[i], nanosec[i])
    else:
        speeds = np.asarray(velocities, dtype=_F8).reshape(count, m).tolist()
        for i in range(count):
            values += (m, *rows[i], m, *speeds[i], 0, 0, sec[i], nanosec[i])
    out.raw(layout.pack(*values))
    return out.getvalue()


def _poses_layout(count: int, frame_size: int, start: int) -> struct.Struct:
    """Return the struct of ``count`` PoseStamped with one frame_id, from offset ``start``."""
    fmt, pos = ['<'], start
    for _ in range(count):
        pos += 12 + frame_size  # stamp, frame_id length and bytes (4-aligned start)
        pad = -pos & 7
        fmt.append(f'iII{frame_size}s{pad}x7d')
        pos += pad + 56
    return struct.Struct(''.join(fmt))


def encode_path(sample: PosePath) -> bytes:
    """Encode nav_msgs/msg/Path like ``pose_path_to_ros`` (each pose in the path frame)."""
    out = CdrBuilder()
    out.header(sample.stamp_ns, sample.frame_id)
    count = len(sample.stamps_ns)
    out.uint32(count)
    sec, nanosec = _seconds(sample.stamps_ns, 0, 'ROS Time')
    poses = np.hstack((np.asarray(sample.positions, dtype=_F8).reshape(-1, 3),
                       np.asarray(sample.orientations_xyzw, dtype=_F8).reshape(-1, 4)))
    if poses.shape[0] != count:
        raise ValueError('one position and orientation per stamp expected')
    frame = str(sample.frame_id).encode() + b'\x00'
    layout = _cached(_LAYOUTS, ('poses', count, len(frame), out.pos & 7),
                     lambda: _poses_layout(count, len(frame), out.pos & 7))
    values: list = []
    for i, pose in enumerate(poses.tolist()):
        values += (sec[i], nanosec[i], len(frame), frame, *pose)
    out.raw(layout.pack(*values))
    return out.getvalue()


def encode_diagnostic_array(sample: Diagnostics) -> bytes:
    """Encode diagnostic_msgs/msg/DiagnosticArray."""
    out = CdrBuilder()
    out.header(sample.stamp_ns, sample.frame_id)
    out.uint32(len(sample.statuses))
    for status in sample.statuses:
        level = int(status.level)
        if not 0 <= level <= 255:
            raise ValueError(f'byte value must be in 0..255, got {level}')
        out.raw(bytes((level,)))
        out.string(status.name)
        out.string(status.message)
        out.string(status.hardware_id)
        out.uint32(len(status.values))
        for key, value in status.values:
            out.string(key)
            out.string(value)
    return out.getvalue()


def _event_layout() -> bytes:
    """Encode the ``~/events`` MultiArrayLayout (always the same) and data's count."""
    out = CdrBuilder()
    out.uint32(len(EVENT_FIELDS))
    for name, size in EVENT_FIELDS:
        out.string(name)
        out.uint32(size)
        out.uint32(size)
    out.uint32(0)  # data_offset
    out.uint32(sum(size for _, size in EVENT_FIELDS))
    out.align(8)
    return out.getvalue()


_EVENT_LAYOUT: list = []


def encode_event(sample: EventSample) -> bytes:
    """Encode the ``~/events`` record, std_msgs/msg/Float64MultiArray."""
    if not _EVENT_LAYOUT:
        _EVENT_LAYOUT.append(_event_layout())
    return _EVENT_LAYOUT[0] + _f64(sample.values())


#: Message type -> encoder of the sample type its ``*_to_ros`` converter takes.
ENCODERS: dict[str, Callable[[Any], bytes]] = {
    'geometry_msgs/msg/WrenchStamped': encode_wrench_stamped,
    'geometry_msgs/msg/TwistStamped': encode_twist_stamped,
    'sensor_msgs/msg/JointState': encode_joint_state,
    'trajectory_msgs/msg/JointTrajectory': encode_joint_trajectory,
    'nav_msgs/msg/Path': encode_path,
    'diagnostic_msgs/msg/DiagnosticArray': encode_diagnostic_array,
    'std_msgs/msg/Float64MultiArray': encode_event,
}


# ------------------------------------------------------------------ decoders

def _strict(decode: Callable[..., Any]) -> Callable[..., Any]:
    """Turn every failure of ``decode`` into CdrError (one exception for the caller)."""
    @functools.wraps(decode)
    def wrapper(data: Buffer, *args: Any, **kwargs: Any) -> Any:
        try:
            return decode(data, *args, **kwargs)
        except CdrError:
            raise
        except (struct.error, ValueError, IndexError, TypeError) as error:
            raise CdrError(f'{type(error).__name__}: {error}') from error
    return wrapper


def _check_header(data: Buffer) -> None:
    """Accept little-endian plain CDR only."""
    if data[:2] != b'\x00\x01':
        raise CdrError('not little-endian CDR')


def _stamp_frame(data: Buffer) -> tuple[int, str, int]:
    """Decode the leading Header; return (stamp_ns, frame_id, offset after it)."""
    sec, nanosec, length = _HEAD.unpack_from(data, 4)
    stamp_ns = sec * NS_PER_S + nanosec
    if stamp_ns < 0:
        raise CdrError('negative stamp')
    end = 16 + length
    if length < 1 or end > len(data) or data[end - 1] != 0:
        raise CdrError('bad frame_id')
    return stamp_ns, bytes(data[16:end - 1]).decode(), end - 4


def _string_at(data: Buffer, pos: int) -> tuple[str, int]:
    """Decode the string at (4-aligned) ``pos``; return it and the offset after it."""
    (length,) = _U32.unpack_from(data, 4 + pos)
    end = pos + 8 + length
    if length < 1 or end > len(data) or data[end - 1] != 0:
        raise CdrError('bad string')
    return bytes(data[pos + 8:end - 1]).decode(), end - 4


def _float64s_at(data: Buffer, pos: int) -> tuple[int, int, int]:
    """Locate the float64 sequence at ``pos``; return (data offset, count, next offset)."""
    pos = (pos + 3) & -4
    (count,) = _U32.unpack_from(data, 4 + pos)
    pos += 4
    if count:
        pos = (pos + 7) & -8
    return pos, count, pos + 8 * count


def _check_end(data: Buffer, pos: int) -> None:
    """Reject a message that is short or has trailing bytes (rosbags allows 3 of padding)."""
    if not len(data) - 3 <= 4 + pos <= len(data):
        raise CdrError('message length disagrees with its content')


#: The last joint-name block seen, as one tuple (count, bytes, names) so that
#: threads read a consistent triple: recorded names repeat in every message.
_LAST_NAMES: list = [(-1, b'', ())]


def _names_at(data: Buffer, pos: int) -> tuple[tuple[str, ...], int]:
    """Decode the string sequence at (4-aligned) ``pos``; return it and the next offset."""
    (count,) = _U32.unpack_from(data, 4 + pos)
    pos += 4
    last_count, last_data, last_names = _LAST_NAMES[0]
    # The same bytes parse to the same names: compare instead of parsing again.
    if count == last_count and data[4 + pos:4 + pos + len(last_data)] == last_data:
        return last_names, pos + len(last_data)
    if 5 * count > len(data):
        raise CdrError('string count beyond the data')
    start, decoded = pos, []
    for _ in range(count):
        name, pos = _string_at(data, (pos + 3) & -4)
        decoded.append(name)
    names = tuple(decoded)
    _LAST_NAMES[0] = (count, bytes(data[4 + start:4 + pos]), names)
    return names, pos


@_strict
def decode_joint_state(data: Buffer) -> JointStateSample:
    """Decode sensor_msgs/msg/JointState into the sample ``joint_state_from_ros`` gives."""
    _check_header(data)
    stamp_ns, frame_id, pos = _stamp_frame(data)
    names, pos = _names_at(data, (pos + 3) & -4)
    p_at, p_count, pos = _float64s_at(data, pos)
    v_at, v_count, pos = _float64s_at(data, pos)
    e_at, e_count, pos = _float64s_at(data, pos)
    _check_end(data, pos)
    n = len(names)
    if p_count != n or v_count not in (0, n) or e_count not in (0, n):
        raise CdrError('array sizes disagree with the names')
    # One copy of the float region; the arrays are slices of it. Non-empty
    # sequences start 8-aligned, so their offsets from p_at are multiples of 8.
    values = np.frombuffer(data, _F8, (pos - p_at) >> 3, 4 + p_at).copy()
    v, e = (v_at - p_at) >> 3, (e_at - p_at) >> 3
    return trusted_sample(JointStateSample, stamp_ns, frame_id, names, values[:p_count],
                          values[v:v + v_count], values[e:e + e_count])


_ODOMETRY = np.r_[0:7, 43:49]  # pose, then twist, among the 85 float64 of Odometry
_ZERO_COVARIANCE = bytes(36 * 8)


def _covariance(data: Buffer, raw: np.ndarray, start: int, first: int) -> Optional[np.ndarray]:
    """Return the 36 covariance values from float ``first`` of ``raw`` (None: all zeros)."""
    # Comparing the bytes is ten times cheaper than ndarray.any(): most drivers send zeros.
    at = start + 8 * first
    zeros = data.startswith(_ZERO_COVARIANCE, at) if isinstance(data, bytes) \
        else data[at:at + 288] == _ZERO_COVARIANCE
    if zeros:
        return None
    return message_covariance(raw[first:first + 36])


@_strict
def decode_odometry(data: Buffer) -> BaseStateSample:
    """Decode nav_msgs/msg/Odometry into the sample ``odometry_from_ros`` gives."""
    _check_header(data)
    stamp_ns, frame_id, pos = _stamp_frame(data)
    child, pos = _string_at(data, (pos + 3) & -4)
    pos = (pos + 7) & -8
    # pose (7), covariance (36), twist (6), covariance (36)
    _check_end(data, pos + 85 * 8)
    raw = np.frombuffer(data, _F8, 85, 4 + pos)
    values = raw[_ODOMETRY]
    pose_cov, twist_cov = _covariance(data, raw, 4 + pos, 7), _covariance(data, raw, 4 + pos, 49)
    if pose_cov is None and twist_cov is None:
        # The fields left out keep their defaults (None).
        return trusted_sample(BaseStateSample, stamp_ns, frame_id, child, values[:3],
                              values[3:7], values[7:10], values[10:])
    return trusted_sample(BaseStateSample, stamp_ns, frame_id, child, values[:3],
                          values[3:7], values[7:10], values[10:], None, pose_cov, twist_cov)


@_strict
def decode_pose_stamped(data: Buffer, child_frame_id: str = '') -> BaseStateSample:
    """Decode geometry_msgs/msg/PoseStamped like ``pose_stamped_from_ros``."""
    _check_header(data)
    stamp_ns, frame_id, pos = _stamp_frame(data)
    pos = (pos + 7) & -8
    _check_end(data, pos + 7 * 8)
    pose = np.frombuffer(data, _F8, 7, 4 + pos).copy()
    return trusted_sample(BaseStateSample, stamp_ns, frame_id, str(child_frame_id), pose[:3],
                          pose[3:], None, None)


@_strict
def decode_pose_with_covariance_stamped(data: Buffer,
                                        child_frame_id: str = '') -> BaseStateSample:
    """Decode geometry_msgs/msg/PoseWithCovarianceStamped like its ``*_from_ros``."""
    _check_header(data)
    stamp_ns, frame_id, pos = _stamp_frame(data)
    pos = (pos + 7) & -8
    # pose (7), covariance (36)
    _check_end(data, pos + 43 * 8)
    raw = np.frombuffer(data, _F8, 43, 4 + pos)
    pose = raw[:7].copy()
    return trusted_sample(BaseStateSample, stamp_ns, frame_id, str(child_frame_id), pose[:3],
                          pose[3:], None, None, None, _covariance(data, raw, 4 + pos, 7), None)


@_strict
def decode_wrench_stamped(data: Buffer) -> CommandSample:
    """Decode geometry_msgs/msg/WrenchStamped like ``command_from_ros`` (an input)."""
    _check_header(data)
    stamp_ns, frame_id, pos = _stamp_frame(data)
    pos = (pos + 7) & -8
    _check_end(data, pos + 6 * 8)
    wrench = np.frombuffer(data, _F8, 6, 4 + pos).copy()
    return trusted_sample(CommandSample, stamp_ns, frame_id, wrench[:3], wrench[3:])


#: Message type -> decoder into the sample its ``*_from_ros`` converter returns.
DECODERS: dict[str, Callable[..., Any]] = {
    'geometry_msgs/msg/WrenchStamped': decode_wrench_stamped,
    'sensor_msgs/msg/JointState': decode_joint_state,
    'nav_msgs/msg/Odometry': decode_odometry,
    'geometry_msgs/msg/PoseStamped': decode_pose_stamped,
    'geometry_msgs/msg/PoseWithCovarianceStamped': decode_pose_with_covariance_stamped,
}


def fast_path_applies(typestore: Optional[Any], msgtype: str) -> bool:
    """
    Tell whether the fixed layouts here match ``typestore``'s ``msgtype``.

    True when the host is little-endian (rosbags serializes in host order),
    this module has a codec for ``msgtype`` and the store's definition hashes
    like the standard one (a bag may carry another definition under the same
    name). ``typestore`` None means the standard definitions.
    """
    if sys.byteorder != 'little' or (msgtype not in ENCODERS and msgtype not in DECODERS):
        return False
    if typestore is None:
        return True
    try:
        if getattr(typestore, 'max_sequence_length', 2**32 - 1) < 2**32 - 1:
            return False  # the store rejects long sequences the decoders would accept
        return rihs01(typestore, msgtype) == jazzy_hash(msgtype)
    except Exception:  # noqa: B902 - unknown or unhashable definition: no fast path
        return False
