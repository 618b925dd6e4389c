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
How well an estimated external wrench follows commanded binary thrust (freeflyer2 judging).

The procedure of ../shared/data/freeflyer2/README.md: per axis (world-frame Fx,
Fy and Mz about the body's centre of mass), the Pearson correlation between the
replay's ``~/drift/momentum_rate`` and the commanded wrench, both taken at the
estimate's stamps (the command held from its last message, its body force
rotated by the measured yaw), both smoothed by the same Savitzky-Golay filter
(window 61, order 3), 61 samples dropped at each end.

The commands are ``ff_msgs/msg/ThrusterCommand`` (``std_msgs/Header header``,
``bool[8] switches``), whose definition is not in the bags: their CDR bytes are
read directly (:func:`decode_thruster_command`). :func:`write_command_bag`
turns them into the body-frame geometry_msgs/WrenchStamped the estimator's
commanded-wrench input takes (README "Commanded wrench").
"""

from __future__ import annotations

from bisect import bisect_right
import struct
from typing import NamedTuple, Optional

import numpy as np
from scipy.signal import savgol_filter

from reduced_dynamics.bag.reader import open_bag
from reduced_dynamics.bag.writer import BagWriter
from reduced_dynamics.messages.cdr import encode_wrench_stamped
from reduced_dynamics.messages.samples import WrenchSample
from reduced_dynamics.thrusters import FREEFLYER_FORCE, LAYOUTS

COMMAND_TOPIC = '/robot/commands/binary_thrust'
#: The commands as body wrenches in :func:`write_command_bag`'s output.
WRENCH_COMMAND_TOPIC = '/robot/commands/wrench'
POSE_TOPIC = '/vrpn_mocap/robot/pose'
RATE_TOPIC = '/reduced_dynamics/drift/momentum_rate'
WINDOW = 61
ORDER = 3


class Correlation(NamedTuple):
    """Pearson correlation per axis (world Fx, Fy; Mz about the centre of mass)."""

    fx: float
    fy: float
    mz: float
    samples: int


def decode_thruster_command(data: bytes) -> tuple[int, tuple[bool, ...]]:
    """Return (header stamp [ns], 8 switches) of a CDR ff_msgs/msg/ThrusterCommand."""
    little = data[1] == 1  # CDR encapsulation: 0x0001 little endian, 0x0000 big
    order = '<' if little else '>'
    sec, nanosec, length = struct.unpack_from(order + 'iII', data, 4)
    offset = 16 + length  # the frame_id string, its terminating zero included
    switches = struct.unpack_from('8?', data, offset)
    return sec * 1_000_000_000 + nanosec, switches


def _commands(bag: str) -> tuple[np.ndarray, np.ndarray]:
    """Return command stamps [ns] (the record time where the header stamp is 0) and wrenches."""
    units = np.array(LAYOUTS['freeflyer'])[:, [0, 1, 5]] * FREEFLYER_FORCE
    stamps, wrenches = [], []
    with open_bag(bag) as reader:
        for message in reader.raw_messages([COMMAND_TOPIC]):
            stamp, switches = decode_thruster_command(message.data)
            stamps.append(stamp or message.timestamp_ns)
            wrenches.append(np.array(switches, dtype=float) @ units)
    order = np.argsort(stamps, kind='stable')
    return np.array(stamps)[order], np.array(wrenches)[order]


def _poses(bag: str, topic: str) -> tuple[list[int], np.ndarray]:
    """Return pose stamps and (x, y, yaw) rows, in stamp order."""
    rows = []
    with open_bag(bag) as reader:
        for message in reader.messages([topic]):
            pose = message.msg.pose
            q = pose.orientation
            yaw = np.arctan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))
            stamp = message.msg.header.stamp.sec * 1_000_000_000 \
                + message.msg.header.stamp.nanosec
            rows.append((stamp, pose.position.x, pose.position.y, yaw))
    rows.sort(key=lambda row: row[0])
    return [row[0] for row in rows], np.array([row[1:] for row in rows])


def _estimates(out_bag: str) -> tuple[list[int], np.ndarray]:
    """Return the estimate stamps and (Fx, Fy, Tz about the origin) rows."""
    rows = []
    with open_bag(out_bag) as reader:
        for message in reader.messages([RATE_TOPIC]):
            msg = message.msg
            stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
            rows.append((stamp, msg.wrench.force.x, msg.wrench.force.y, msg.wrench.torque.z))
    return [row[0] for row in rows], np.array([row[1:] for row in rows])


def _held(stamps: list[int], source_stamps, values: np.ndarray) -> np.ndarray:
    """Return the values held from their last stamp at or before each stamp (first before)."""
    source = list(source_stamps)
    index = [max(bisect_right(source, stamp) - 1, 0) for stamp in stamps]
    return values[index]


def thrust_correlation(bag: str, out_bag: str, pose_topic: str = POSE_TOPIC,
                       window: int = WINDOW, order: int = ORDER) -> Correlation:
    """Return the README's correlation of ``out_bag``'s wrench estimate with ``bag``'s commands."""
    stamps, estimate = _estimates(out_bag)
    command_stamps, commands = _commands(bag)
    pose_stamps, poses = _poses(bag, pose_topic)
    state = _held(stamps, pose_stamps, poses)
    x, y, yaw = state[:, 0], state[:, 1], state[:, 2]
    body = _held(stamps, command_stamps, commands)
    c, s = np.cos(yaw), np.sin(yaw)
    commanded = np.column_stack((c * body[:, 0] - s * body[:, 1],
                                 s * body[:, 0] + c * body[:, 1], body[:, 2]))
    fx, fy, tz = estimate[:, 0], estimate[:, 1], estimate[:, 2]
    # Torque about the centre of mass: about the origin minus r x F.
    about_com = np.column_stack((fx, fy, tz - (x * fy - y * fx)))
    smooth_est = savgol_filter(about_com, window, order, axis=0)[window:-window]
    smooth_cmd = savgol_filter(commanded, window, order, axis=0)[window:-window]
    values = [float(np.corrcoef(smooth_est[:, i], smooth_cmd[:, i])[0, 1]) for i in range(3)]
    return Correlation(*values, len(smooth_est))


def momentum_spread(out_bag: str) -> Optional[np.ndarray]:
    """Return the standard deviation of each published momentum component (x, y, z)."""
    rows = []
    with open_bag(out_bag) as reader:
        for message in reader.messages(['/reduced_dynamics/momentum']):
            wrench = message.msg.wrench
            rows.append((wrench.force.x, wrench.force.y, wrench.torque.z))
    return np.array(rows).std(axis=0) if rows else None


def write_command_bag(bag: str, out: str, pose_topic: str = POSE_TOPIC,
                      frame_id: str = 'robot') -> int:
    """
    Copy ``bag``'s poses and write its thruster switches as body wrenches; return the count.

    Each ff_msgs/msg/ThrusterCommand becomes a geometry_msgs/msg/WrenchStamped on
    :data:`WRENCH_COMMAND_TOPIC` at the same record time: the nominal body wrench of
    the switches by the data README's thruster map (0.2 N per thruster, 0.11461 m
    lever arm; :data:`reduced_dynamics.thrusters.LAYOUTS`), stamped with the
    header stamp (the record time where it is 0), ``frame_id`` the base link.
    The poses are copied byte for byte.
    """
    units = np.array(LAYOUTS['freeflyer']) * FREEFLYER_FORCE
    count = 0
    topics = {pose_topic: 'geometry_msgs/msg/PoseStamped',
              WRENCH_COMMAND_TOPIC: 'geometry_msgs/msg/WrenchStamped'}
    with open_bag(bag) as reader, BagWriter(out, topics, overwrite=True) as writer:
        for message in reader.raw_messages([pose_topic, COMMAND_TOPIC]):
            if message.topic == pose_topic:
                writer.write_raw(pose_topic, message.timestamp_ns, bytes(message.data))
                continue
            stamp, switches = decode_thruster_command(bytes(message.data))
            wrench = np.array(switches, dtype=float) @ units
            sample = WrenchSample(stamp or message.timestamp_ns, frame_id, wrench[:3],
                                  wrench[3:])
            writer.write_raw(WRENCH_COMMAND_TOPIC, message.timestamp_ns,
                             encode_wrench_stamped(sample))
            count += 1
    return count
