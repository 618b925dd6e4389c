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
Fixed-layout CDR of many messages at once, from columns (one row per message).

A chunk of estimator outputs is column-wise (stamps (K,), wrenches (K, 6),
joint values (K, m)); the per-message encoders of :mod:`.cdr` would take them
row by row through sample objects. Here every message of a topic has the same
size (one frame id, one set of joint names), so the K messages are one
``uint8`` array (K, size): a template row (header, frame id, names, counts and
padding, as :mod:`.cdr` lays them out) copied K times, then the stamps and the
float64 columns written through ``ndarray.view`` of their byte ranges. The
bytes are those of the per-message encoders (test_cdr_columns.py); row k is
message k (``records[k].tobytes()``, or :func:`split`).
"""

from __future__ import annotations

from typing import Optional

import numpy as np

from reduced_dynamics.messages.cdr import (_cached, _frame_block, _header8, _string_block,
                                           _U32, encode_joint_state, encode_twist_stamped,
                                           encode_wrench_stamped, HEADER)
from reduced_dynamics.messages.stamps import NS_PER_S

#: The first stamp [ns] whose seconds overflow builtin_interfaces/Time's int32.
_TIME_END_NS = 2**31 * NS_PER_S
_LAYOUTS: dict = {}

#: The per-message encoders whose bytes these columns reproduce.
COLUMN_ENCODERS = (encode_wrench_stamped, encode_twist_stamped, encode_joint_state)


def stamp_columns(stamps_ns: np.ndarray) -> Optional[np.ndarray]:
    """
    Return builtin_interfaces/Time of integer nanosecond stamps, packed, or None.

    Each stamp as the int64 whose little-endian bytes are its ``sec`` (int32) and
    ``nanosec`` (uint32). None (a negative stamp or sec beyond int32): the caller goes
    message by message, where the per-message encoder raises its own error.
    """
    stamps = np.asarray(stamps_ns, dtype=np.int64)
    if stamps.size and (stamps.min() < 0 or stamps.max() >= _TIME_END_NS):
        return None
    sec, nanosec = np.divmod(stamps, NS_PER_S)
    nanosec <<= 32
    nanosec |= sec
    return nanosec


def _rows(template: np.ndarray, count: int) -> np.ndarray:
    """Return ``count`` copies of the uint8 row ``template`` as a (count, len) array."""
    out = np.empty((count, len(template)), np.uint8)
    out[:] = template
    return out


def _put_stamps(out: np.ndarray, stamps: np.ndarray) -> None:
    """Write each row's builtin_interfaces/Time at byte 4 (after the CDR header)."""
    out[:, 4:12].view('<i8')[:, 0] = stamps


def _put_f64(out: np.ndarray, offset: int, values: np.ndarray) -> None:
    """Write float64 columns (K, w) from byte ``offset`` of each row (bits unchanged)."""
    width = values.shape[1]
    if width:
        out[:, offset:offset + 8 * width].view('<f8')[:] = values


def _vector6_template(frame_id: str) -> tuple[np.ndarray, int]:
    """Return a zero WrenchStamped/TwistStamped as uint8 and its values' byte offset."""
    prefix = _header8(0, frame_id)
    return np.frombuffer(prefix + bytes(48), np.uint8), len(prefix)


def vector6_records(stamps: np.ndarray, frame_id: str,
                    values: np.ndarray) -> np.ndarray:
    """
    Return WrenchStamped or TwistStamped messages (the same layout), one per row.

    ``values`` (K, 6): force then torque, or linear then angular, float64, as
    ``cdr.encode_wrench_stamped`` / ``encode_twist_stamped`` write them.
    """
    if values.ndim != 2 or values.shape[1] != 6:
        raise ValueError(f'expected (K, 6) values, got shape {values.shape}')
    template, offset = _cached(_LAYOUTS, ('vector6', frame_id),
                               lambda: _vector6_template(frame_id))
    out = _rows(template, len(values))
    _put_stamps(out, stamps)
    _put_f64(out, offset, values)
    return out


def _joint_state_layout(frame_id: str, names: tuple[str, ...]) -> tuple[np.ndarray, tuple]:
    """Return a JointState's template (zeros) and its three arrays' byte offsets."""
    # The arithmetic of cdr.encode_joint_state, positions relative to the CDR header.
    frame = _frame_block(str(frame_id), 4)
    block = _string_block(names) if names else b''
    m = len(names)
    parts = [HEADER, bytes(8), frame, _U32.pack(m), block]
    pos = 12 + len(frame) + len(block)
    offsets = []
    for _ in range(3):
        pad = -pos & 3
        parts.append(bytes(pad) + _U32.pack(m))
        pos += pad + 4
        if m:
            pad = pos & 4
            parts.append(bytes(pad + 8 * m))
            offsets.append(4 + pos + pad)
            pos += pad + 8 * m
    return np.frombuffer(b''.join(parts), np.uint8), tuple(offsets)


def joint_state_records(stamps: np.ndarray, frame_id: str,
                        names: tuple[str, ...], position: np.ndarray, velocity: np.ndarray,
                        effort: np.ndarray) -> np.ndarray:
    """
    Return sensor_msgs/JointState messages, one per row, as ``cdr.encode_joint_state``.

    ``position``, ``velocity``, ``effort``: (K, m) float64 each, m = len(names)
    (the estimator's shape states: the three arrays always full).
    """
    m = len(names)
    for values in (position, velocity, effort):
        if values.ndim != 2 or values.shape[1] != m:
            raise ValueError(f'expected (K, {m}) joint values, got shape {values.shape}')
    template, offsets = _cached(_LAYOUTS, ('joint_state', frame_id, names),
                                lambda: _joint_state_layout(frame_id, names))
    out = _rows(template, len(position))
    _put_stamps(out, stamps)
    for offset, values in zip(offsets, (position, velocity, effort)):
        _put_f64(out, offset, values)
    return out


def split(records: np.ndarray) -> list[bytes]:
    """Return the rows of ``records`` (K, size) as K ``bytes`` messages."""
    size = records.shape[1]
    data = records.tobytes()
    return [data[i:i + size] for i in range(0, len(data), size)]
