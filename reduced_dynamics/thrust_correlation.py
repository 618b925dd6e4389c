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
``bool[8] switches``), whose definition is not in the bags. What they push with
is data, not code: a command mapping (:mod:`reduced_dynamics.command_mapping`;
default the shipped ``config/thrusters/freeflyer2.yaml``) gives the message's
definition and each thruster's direction, position and force, so any thruster
vehicle's command is judged the same way. :func:`write_command_bag` turns them
into the body-frame geometry_msgs/WrenchStamped the estimator's commanded-wrench
input takes (README "Commanded wrench").

:func:`write_command_twin` writes a recording's **command twin**: the same pose
stamps (receive times and all), the recording's own measured mocap noise
(:func:`mocap_noise`), but a body whose only force is the command. The estimator's
correlation on the twin is what the sensors allow; on the recording it is also
bounded by how well the command describes the force the body felt (README
"freeflyer2 correlations").
"""

from __future__ import annotations

from bisect import bisect_right
import struct
from typing import NamedTuple, Optional, Sequence

import numpy as np

from reduced_dynamics.bag.reader import open_bag
from reduced_dynamics.bag.writer import BagWriter
from reduced_dynamics.command_mapping import CommandMapping, freeflyer2_mapping
from reduced_dynamics.estimator.retiming import FrameRetimer
from reduced_dynamics.messages.cdr import encode_wrench_stamped
from reduced_dynamics.messages.samples import WrenchSample
from reduced_dynamics.resources import config_path
from reduced_dynamics.robot.model import load_robot

COMMAND_TOPIC = '/robot/commands/binary_thrust'
#: The commands as body wrenches in :func:`write_command_bag`'s output.
WRENCH_COMMAND_TOPIC = '/robot/commands/wrench'
POSE_TOPIC = '/vrpn_mocap/robot/pose'
RATE_TOPIC = '/reduced_dynamics/drift/momentum_rate'
WINDOW = 61
ORDER = 3
#: Delivered / nominal thrust of the twin: the freeflyer2 thrusters deliver about half
#: their nominal 0.2 N (torque gain 0.58 and 0.66 with the commanded-wrench input).
TWIN_GAIN = 0.5
#: Integration step [s] of the twin's motion under the held command.
TWIN_STEP = 1e-3


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


def _commands(bag: str, mapping: Optional[CommandMapping] = None
              ) -> tuple[np.ndarray, np.ndarray]:
    """Return command stamps [ns] (the record time where the header stamp is 0), (Fx, Fy, Mz)."""
    stamps, wrenches = (mapping or freeflyer2_mapping()).read_commands(bag)
    return stamps, wrenches[:, [0, 1, 5]]


def _planar(pose) -> tuple[float, float, float]:
    """Return (x, y, yaw) of a geometry_msgs/Pose."""
    q = pose.orientation
    yaw = np.arctan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))
    return pose.position.x, pose.position.y, float(yaw)


def _poses(bag: str, topic: str) -> tuple[list[int], np.ndarray]:
    """Return pose stamps and (x, y, yaw) rows, in stamp order."""
    rows = []
    with open_bag(bag) as reader:
        for message in reader.messages([topic]):
            stamp = message.msg.header.stamp.sec * 1_000_000_000 \
                + message.msg.header.stamp.nanosec
            pose = message.msg.pose  # PoseStamped's pose, Odometry's PoseWithCovariance
            rows.append((stamp, *_planar(getattr(pose, 'pose', pose))))
    rows.sort(key=lambda row: row[0])
    return [row[0] for row in rows], np.array([row[1:] for row in rows])


def _estimates(out_bag: str, topic: str = RATE_TOPIC) -> tuple[list[int], np.ndarray]:
    """Return the estimate stamps and (Fx, Fy, Tz about the origin) rows, in stamp order."""
    rows = []
    with open_bag(out_bag) as reader:
        for message in reader.messages([topic]):
            msg = message.msg
            stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
            rows.append((stamp, msg.wrench.force.x, msg.wrench.force.y, msg.wrench.torque.z))
    rows.sort(key=lambda row: row[0])  # a fixed-lag topic is recorded after the fact
    return [row[0] for row in rows], np.array([row[1:] for row in rows])


def _held(stamps: list[int], source_stamps, values: np.ndarray) -> np.ndarray:
    """Return the values held from their last stamp at or before each stamp (first before)."""
    source = list(source_stamps)
    index = [max(bisect_right(source, stamp) - 1, 0) for stamp in stamps]
    return values[index]


class CommandFit(NamedTuple):
    """Per axis (world Fx, Fy; Mz about the centre of mass): correlation and linear fit."""

    correlation: Correlation
    #: Slope of the estimate against the command (delivered / commanded).
    gain: tuple[float, float, float]
    #: The estimate where the command is zero [N, N, N m].
    bias: tuple[float, float, float]


def commanded_world(bag: str, stamps: Sequence[int], pose_topic: str = POSE_TOPIC,
                    poses_bag: Optional[str] = None,
                    mapping: Optional[CommandMapping] = None
                    ) -> tuple[np.ndarray, np.ndarray]:
    """
    Return the commanded (Fx, Fy, Mz) in the world frame at ``stamps``, and (x, y, yaw).

    The command is held from its last message, its body force rotated by the pose
    (of ``poses_bag``, default ``bag``) held from its last message.
    """
    command_stamps, commands = _commands(bag, mapping)
    if not len(command_stamps):
        raise ValueError(f'{bag}: no thruster command to correlate with')
    pose_stamps, poses = _poses(poses_bag or bag, pose_topic)
    if not pose_stamps:
        raise ValueError(f'{poses_bag or bag}: no pose on {pose_topic}')
    state = _held(list(stamps), pose_stamps, poses)
    body = _held(list(stamps), command_stamps, commands)
    c, s = np.cos(state[:, 2]), np.sin(state[:, 2])
    return np.column_stack((c * body[:, 0] - s * body[:, 1],
                            s * body[:, 0] + c * body[:, 1], body[:, 2])), state


def about_centre_of_mass(estimate: np.ndarray, position: np.ndarray) -> np.ndarray:
    """Return (Fx, Fy, Tz about the origin) rows as (Fx, Fy, Tz about ``position``)."""
    fx, fy, tz = estimate[:, 0], estimate[:, 1], estimate[:, 2]
    # Torque about the centre of mass: about the origin minus r x F.
    return np.column_stack((fx, fy, tz - (position[:, 0] * fy - position[:, 1] * fx)))


def command_fit(bag: str, out_bag: str, pose_topic: str = POSE_TOPIC,
                window: int = WINDOW, order: int = ORDER, poses_bag: Optional[str] = None,
                mapping: Optional[CommandMapping] = None,
                rate_topic: str = RATE_TOPIC) -> CommandFit:
    """
    Return the README's correlation and the gain of ``out_bag``'s estimate with the command.

    The arguments are :func:`thrust_correlation`'s. The gain and bias are the
    least-squares line estimate = gain * command + bias through the same smoothed
    samples the correlation is taken over.
    """
    stamps, estimate = _estimates(out_bag, rate_topic)
    if len(stamps) <= 2 * window:
        raise ValueError(f'{out_bag}: {len(stamps)} wrench estimates on {rate_topic}, the '
                         f'correlation needs more than {2 * window} (the smoothing window '
                         'dropped at each end)')
    commanded, state = commanded_world(bag, stamps, pose_topic, poses_bag, mapping)
    about_com = about_centre_of_mass(estimate, state[:, :2])
    smooth_est = savitzky_golay_inner(about_com, window, order)
    smooth_cmd = savitzky_golay_inner(commanded, window, order)
    values = [float(np.corrcoef(smooth_est[:, i], smooth_cmd[:, i])[0, 1]) for i in range(3)]
    lines = [np.polyfit(smooth_cmd[:, i], smooth_est[:, i], 1) for i in range(3)]
    return CommandFit(Correlation(*values, len(smooth_est)),
                      tuple(float(line[0]) for line in lines),
                      tuple(float(line[1]) for line in lines))


def savitzky_golay_inner(values: np.ndarray, window: int, order: int) -> np.ndarray:
    """
    Return the Savitzky-Golay smoothing of ``values``' columns, ``window`` rows cut at each end.

    The rows scipy.signal.savgol_filter(values, window, order, axis=0)[window:-window]
    holds (equal to rounding, test_correlate.py): there every point's window lies inside
    the series, so the filter is one convolution with the least-squares coefficients and
    the edge fits do not enter. Here rather than scipy.signal, whose import alone took
    3.8 s of CPU on this project's machine (measured), longer than the rest of a
    ``reduced-dynamics correlate`` run on the shipped recordings.
    """
    if window % 2 == 0 or not 0 <= order < window:
        raise ValueError(f'the Savitzky-Golay window must be odd and longer than the '
                         f'order: window {window}, order {order}')
    values = np.asarray(values, dtype=float)
    if values.shape[0] <= 2 * window:
        raise ValueError(f'{values.shape[0]} samples: the Savitzky-Golay smoothing keeps '
                         f'none with {window} cut at each end')
    half = window // 2
    # Offsets scaled to [-1, 1] (a better conditioned fit; the value at the centre, the
    # polynomial's constant term, is the same): row 0 of pinv(A) gives it.
    offsets = np.arange(-half, half + 1, dtype=float) / max(half, 1)
    design = offsets[:, None] ** np.arange(order + 1)
    coefficients = np.linalg.pinv(design)[0]
    inner = values[window - half:values.shape[0] - window + half]
    out = np.zeros((values.shape[0] - 2 * window,) + values.shape[1:])
    for k, coefficient in enumerate(coefficients):
        out += coefficient * inner[k:k + out.shape[0]]
    return out


def thrust_correlation(bag: str, out_bag: str, pose_topic: str = POSE_TOPIC,
                       window: int = WINDOW, order: int = ORDER,
                       poses_bag: Optional[str] = None,
                       mapping: Optional[CommandMapping] = None,
                       rate_topic: str = RATE_TOPIC) -> Correlation:
    """
    Return the README's correlation of ``out_bag``'s wrench estimate with ``bag``'s commands.

    ``poses_bag``: the bag whose poses (PoseStamped or Odometry) turn the command into
    the world frame (default ``bag``; a command twin's own, :func:`write_command_twin`).
    ``mapping``: the command message and thrusters (default freeflyer2's).
    ``rate_topic``: the estimate (e.g. the fixed-lag ``drift/momentum_rate_smoothed``).
    """
    return command_fit(bag, out_bag, pose_topic, window, order, poses_bag, mapping,
                       rate_topic).correlation


def momentum_spread(out_bag: str) -> Optional[np.ndarray]:
    """Return the standard deviation of each published momentum component (x, y, z)."""
    rows = []
    with open_bag(out_bag) as reader:
        for message in reader.messages(['/reduced_dynamics/momentum']):
            wrench = message.msg.wrench
            rows.append((wrench.force.x, wrench.force.y, wrench.torque.z))
    return np.array(rows).std(axis=0) if rows else None


def write_command_bag(bag: str, out: str, pose_topic: str = POSE_TOPIC,
                      frame_id: str = 'robot', mapping: Optional[CommandMapping] = None) -> int:
    """
    Copy ``bag``'s poses and write its thruster switches as body wrenches; return the count.

    Each command message (``mapping``, default freeflyer2's ff_msgs/msg/ThrusterCommand)
    becomes a geometry_msgs/msg/WrenchStamped on :data:`WRENCH_COMMAND_TOPIC` at the
    same record time: the nominal body wrench of its values by the mapping (freeflyer2:
    the data README's map, 0.2 N per thruster, 0.11461 m lever arm), stamped with the
    header stamp (the record time where it is 0), ``frame_id`` the base link.
    The poses are copied byte for byte.
    """
    mapping = mapping or freeflyer2_mapping()
    count = 0
    topics = {pose_topic: 'geometry_msgs/msg/PoseStamped',
              WRENCH_COMMAND_TOPIC: 'geometry_msgs/msg/WrenchStamped'}
    with open_bag(bag) as reader, BagWriter(out, topics, overwrite=True) as writer:
        decode = mapping.decoder(reader)
        for message in reader.raw_messages([pose_topic, mapping.topic]):
            if message.topic == pose_topic:
                writer.write_raw(pose_topic, message.timestamp_ns, bytes(message.data))
                continue
            msg = decode(bytes(message.data))
            if msg is None:  # undecodable: counted by the reader
                continue
            stamp = mapping.stamp(msg, message.timestamp_ns)
            wrench = mapping.wrench(getattr(msg, mapping.field))
            sample = WrenchSample(stamp, frame_id, wrench[:3],
                                  wrench[3:])
            writer.write_raw(WRENCH_COMMAND_TOPIC, message.timestamp_ns,
                             encode_wrench_stamped(sample))
            count += 1
    return count


class CommandTwin(NamedTuple):
    """What :func:`write_command_twin` wrote: poses and the noise it measured and used."""

    poses: int
    position_noise: float
    angle_noise: float


def _frame_times(stamps_ns: list[int]) -> np.ndarray:
    """Return the frame times [ns] of receive-stamped poses (arrival order; retiming.py)."""
    retimer = FrameRetimer('on')
    return np.array([retimer.retime(stamp)[0] for stamp in stamps_ns], dtype=np.int64)


def mocap_noise(frame_ns: np.ndarray, poses: np.ndarray) -> tuple[float, float]:
    """
    Return the frame-to-frame noise (position [m], yaw [rad]) of (x, y, yaw) poses.

    Over every run of five consecutive frames (steps within half a period of the
    median) the 4th difference of a smooth motion is negligible at 120 Hz and that
    of white noise has variance 70 sigma^2. x and y are pooled.
    """
    steps = np.diff(frame_ns)
    period = np.median(steps)
    regular = np.abs(steps - period) < 0.5 * period
    runs = np.flatnonzero(np.convolve(regular, np.ones(4, dtype=int), 'valid') == 4)

    def sigma(values: np.ndarray) -> float:
        fourth = values[4:] - 4 * values[3:-1] + 6 * values[2:-2] - 4 * values[1:-3] \
            + values[:-4]
        return float(np.sqrt(np.mean(fourth[runs] ** 2) / 70.0))

    position = float(np.hypot(sigma(poses[:, 0]), sigma(poses[:, 1])) / np.sqrt(2.0))
    return position, sigma(np.unwrap(poses[:, 2]))


def write_command_twin(bag: str, out: str, pose_topic: str = POSE_TOPIC,
                       gain: float = TWIN_GAIN, seed: int = 0) -> CommandTwin:
    """
    Write the command twin of the freeflyer2 recording ``bag`` to ``out``; return its figures.

    Every pose message of ``bag`` is copied with its record time and header stamp;
    its pose is replaced by that of a body (the data README's 16 kg, 0.18 kg m^2;
    config/robots/freeflyer.urdf) pushed by ``gain`` times the commanded wrench
    alone, taken at the message's frame time (the lower envelope of the stamps,
    estimator/retiming.py), plus Gaussian noise of the recording's own
    :func:`mocap_noise`. The twin starts at rest at the first measured pose; the
    command's mean world force and torque are taken out (a tilted table), so that
    it stays on the table as the closed-loop robot did.
    """
    messages = []
    with open_bag(bag) as reader:
        for message in reader.messages([pose_topic]):
            stamp = message.msg.header.stamp
            messages.append((message.timestamp_ns, stamp.sec * 1_000_000_000 + stamp.nanosec,
                             message.msg))
    frames = _frame_times([header for _, header, _ in messages])
    measured = np.array([_planar(msg.pose) for _, _, msg in messages])
    position_noise, angle_noise = mocap_noise(np.sort(frames), measured[np.argsort(frames)])
    inertia = load_robot(str(config_path('robots/freeflyer.urdf'))) \
        .metric_blocks(np.zeros(0)).locked_inertia
    mass, yaw_inertia = inertia[0, 0], inertia[2, 2]
    grid = np.arange(frames.min(), frames.max() + 1, int(TWIN_STEP * 1e9), dtype=np.int64)
    command_stamps, commands = _commands(bag)
    body = _held(list(grid), command_stamps, commands) * gain
    first = measured[np.argmin(frames)]
    angular = body[:, 2] / yaw_inertia
    yaw = first[2] + np.cumsum(np.cumsum(angular - angular.mean()) * TWIN_STEP) * TWIN_STEP
    c, s = np.cos(yaw), np.sin(yaw)
    linear = np.column_stack((c * body[:, 0] - s * body[:, 1],
                              s * body[:, 0] + c * body[:, 1])) / mass
    linear -= linear.mean(axis=0)
    path = first[:2] + np.cumsum(np.cumsum(linear, axis=0) * TWIN_STEP, axis=0) * TWIN_STEP
    rng = np.random.default_rng(seed)
    count = len(messages)
    x = np.interp(frames, grid, path[:, 0]) + rng.normal(0.0, position_noise, count)
    y = np.interp(frames, grid, path[:, 1]) + rng.normal(0.0, position_noise, count)
    heading = np.interp(frames, grid, yaw) + rng.normal(0.0, angle_noise, count)
    with BagWriter(out, {pose_topic: 'geometry_msgs/msg/PoseStamped'},
                   overwrite=True) as writer:
        for k, (record_ns, _, msg) in enumerate(messages):
            msg.pose.position.x, msg.pose.position.y = float(x[k]), float(y[k])
            q = msg.pose.orientation
            q.x, q.y, q.z, q.w = 0.0, 0.0, float(np.sin(0.5 * heading[k])), \
                float(np.cos(0.5 * heading[k]))
            writer.write(pose_topic, record_ns, msg)
    return CommandTwin(count, position_noise, angle_noise)
