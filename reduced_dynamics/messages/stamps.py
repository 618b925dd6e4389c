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
Conversions between integer nanoseconds and builtin_interfaces Time/Duration.

Time (``sec: int32, nanosec: uint32``) must be non-negative; negative times
are rejected.  Duration may be negative and uses the rclpy normalization
``sec = floor(ns / 1e9)``, ``0 <= nanosec < 1e9``.
"""

from typing import Any

import numpy as np

from reduced_dynamics.messages.types import MessageTypes

NS_PER_S = 1_000_000_000
_INT32_MAX = 2**31 - 1
_INT32_MIN = -(2**31)


def _as_int(value: Any, name: str) -> int:
    """Accept Python/numpy integers only (no floats, no bools)."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise TypeError(f'{name} must be an integer number of nanoseconds, got {value!r}')
    return int(value)


def split_ns(ns: int) -> tuple[int, int]:
    """Split nanoseconds into ``(sec, nanosec)`` with ``0 <= nanosec < 1e9``."""
    ns = _as_int(ns, 'ns')
    return ns // NS_PER_S, ns % NS_PER_S


def time_to_ros(stamp_ns: int, types: MessageTypes) -> Any:
    """Build builtin_interfaces/msg/Time from non-negative nanoseconds."""
    sec, nanosec = split_ns(stamp_ns)
    if sec < 0:
        raise ValueError(f'ROS Time cannot be negative, got {stamp_ns} ns')
    if sec > _INT32_MAX:
        raise ValueError(f'ROS Time sec overflows int32: {stamp_ns} ns')
    return types.create('builtin_interfaces/msg/Time', sec=sec, nanosec=nanosec)


def time_from_ros(msg: Any) -> int:
    """
    Convert builtin_interfaces/msg/Time to nanoseconds (rejects negative times).

    Like rclpy's ``Time.from_msg``, a non-normalized ``nanosec >= 1e9`` is
    accepted and simply added.
    """
    ns = int(msg.sec) * NS_PER_S + int(msg.nanosec)
    if ns < 0:
        raise ValueError(f'ROS Time cannot be negative (sec={msg.sec}, nanosec={msg.nanosec})')
    return ns


def duration_to_ros(duration_ns: int, types: MessageTypes) -> Any:
    """Build builtin_interfaces/msg/Duration (negative allowed, floor-normalized)."""
    sec, nanosec = split_ns(duration_ns)
    if not _INT32_MIN <= sec <= _INT32_MAX:
        raise ValueError(f'ROS Duration sec overflows int32: {duration_ns} ns')
    return types.create('builtin_interfaces/msg/Duration', sec=sec, nanosec=nanosec)


def duration_from_ros(msg: Any) -> int:
    """Convert builtin_interfaces/msg/Duration to (possibly negative) nanoseconds."""
    return int(msg.sec) * NS_PER_S + int(msg.nanosec)
