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
The plots of ``replay --plots DIR``, fitted to the robot.

Only the wrench components the base group moves in are drawn (a planar base:
Fx, Fy and Tz; the other three are zero by construction and would flatten the
axes). Torques and angular momenta are taken about the system's centre of mass
when the base poses can be read from the input bag (about the world origin they
grow with the lever arm of the base's position). The commanded wrench is drawn
beside the estimate when the bag has one: the replay's commanded-wrench input
(geometry_msgs/WrenchStamped, body frame) or a thruster command by a command
mapping (:mod:`reduced_dynamics.command_mapping`; the shipped freeflyer2 one is
used when the bag has its topic). Residuals on a log axis leave out the zeros
(the legend counts them); legends sit outside the axes.
"""

from __future__ import annotations

from dataclasses import dataclass
import os
from typing import Any, NamedTuple, Optional, Sequence

import numpy as np
import pinocchio as pin

from reduced_dynamics.bag.reader import open_bag
from reduced_dynamics.command_mapping import CommandMapping, freeflyer2_mapping
from reduced_dynamics.plot_marks import draw_marks
from reduced_dynamics.robot.model import RobotModel

#: Wrench component names, in the order (fx, fy, fz, tx, ty, tz).
COMPONENTS = ('x', 'y', 'z')
#: Base pose messages whose position and orientation the centre of mass is found from.
POSE_TYPES = ('geometry_msgs/msg/PoseStamped', 'nav_msgs/msg/Odometry',
              'geometry_msgs/msg/PoseWithCovarianceStamped')
WRENCH_TYPE = 'geometry_msgs/msg/WrenchStamped'
#: Legend outside the axes, to their right: it never covers data.
LEGEND = {'loc': 'upper left', 'bbox_to_anchor': (1.01, 1.0), 'borderaxespad': 0.0,
          'fontsize': 8}


@dataclass(frozen=True)
class PlotInputs:
    """Where the plots find the base poses and the command (all optional)."""

    bag: Optional[str] = None
    base_topic: Optional[str] = None
    #: the replay's commanded-wrench input (WrenchStamped, body frame)
    command_topic: Optional[str] = None
    #: a thruster command mapping file (default: freeflyer2's if the bag has its topic)
    thruster_map: Optional[str] = None


def shown_axes(robot: RobotModel) -> tuple[list[int], list[int]]:
    """Return the force and torque components (0..2 each) the base group moves in."""
    moved = np.any(np.abs(robot.group.algebra_basis) > 0.0, axis=1)
    return [i for i in range(3) if moved[i]], [i for i in range(3) if moved[3 + i]]


def _held(stamps: np.ndarray, source: np.ndarray) -> np.ndarray:
    """Return the index of the last source stamp at or before each stamp (first before)."""
    return np.maximum(np.searchsorted(source, stamps, side='right') - 1, 0)


def _stamp(msg: Any, record_ns: int) -> int:
    stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
    return stamp or record_ns


def read_poses(bag: str, topic: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return stamps [ns], positions (n, 3) and rotations (n, 3, 3) of a base pose topic."""
    rows = []
    with open_bag(bag) as reader:
        if reader.topics().get(topic) not in POSE_TYPES:
            return np.zeros(0, dtype=np.int64), np.zeros((0, 3)), np.zeros((0, 3, 3))
        for message in reader.messages([topic]):
            pose = message.msg.pose
            pose = getattr(pose, 'pose', pose)  # Odometry, PoseWithCovarianceStamped
            q = pose.orientation
            quat = np.array([q.x, q.y, q.z, q.w])
            if not np.all(np.isfinite(quat)) or np.linalg.norm(quat) == 0.0:
                continue  # the replay rejected it too
            rotation = pin.Quaternion(quat / np.linalg.norm(quat)).toRotationMatrix()
            rows.append((_stamp(message.msg, message.timestamp_ns),
                         np.array([pose.position.x, pose.position.y, pose.position.z]),
                         rotation))
    rows.sort(key=lambda row: row[0])
    if not rows:
        return np.zeros(0, dtype=np.int64), np.zeros((0, 3)), np.zeros((0, 3, 3))
    return (np.array([r[0] for r in rows], dtype=np.int64), np.array([r[1] for r in rows]),
            np.array([r[2] for r in rows]))


class Table(NamedTuple):
    """A series' rows: stamps [ns] as integers (a float64 rounds them to 256 ns), values."""

    stamps: np.ndarray
    values: np.ndarray

    @classmethod
    def of(cls, rows: Sequence[tuple]) -> 'Table':
        """Return the table of ``(stamp, value, ...)`` rows."""
        stamps = np.array([row[0] for row in rows], dtype=np.int64)
        width = len(rows[0]) - 1 if len(rows) else 0
        values = np.array([row[1:] for row in rows], dtype=float).reshape(len(rows), width)
        return cls(stamps, values)


def centre_of_mass(robot: RobotModel, stamps: np.ndarray, poses: tuple,
                   shape: Table) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """
    Return the system's centre of mass (world, (n, 3)) and the base pose at ``stamps``.

    ``poses``: :func:`read_poses`; ``shape``: the shape state qbar. Each is held
    from its last sample at or before the stamp.
    """
    pose_stamps, positions, rotations = poses
    index = _held(stamps, pose_stamps)
    data = robot.model.createData()
    if len(shape.stamps) and shape.values.shape[1] == robot.m:
        qbars = shape.values[_held(stamps, shape.stamps)]
    else:
        qbars = np.zeros((len(stamps), robot.m))
    local = np.empty((len(stamps), 3))
    cache: dict[bytes, np.ndarray] = {}
    for k, qbar in enumerate(qbars):
        key = qbar.tobytes()
        if key not in cache:  # a jointless base: one centre of mass for all rows
            q = robot.identity_configuration(qbar).copy()
            cache[key] = pin.centerOfMass(robot.model, data, q).copy()
        local[k] = cache[key]
    rotation, position = rotations[index], positions[index]
    if robot.base_joint_type != 'floating':
        # A planar base: the pose's projection onto SE(2) (RobotModel.project_pose), as
        # the estimator takes it; a tilt of the mocap frame is not the body's.
        yaw = np.arctan2(rotation[:, 1, 0], rotation[:, 0, 0])
        c, s = np.cos(yaw), np.sin(yaw)
        rotation = np.zeros_like(rotation)
        rotation[:, 0, 0], rotation[:, 0, 1], rotation[:, 1, 0], rotation[:, 1, 1] = c, -s, s, c
        rotation[:, 2, 2] = 1.0
        position = np.column_stack([position[:, :2], np.zeros(len(position))])
    return position + np.einsum('nij,nj->ni', rotation, local), position, rotation


def _command_body(bag: str, inputs: PlotInputs) -> Optional[tuple[np.ndarray, np.ndarray, str]]:
    """Return the command's stamps, body wrenches (n, 6) about the base origin and source."""
    with open_bag(bag) as reader:
        topics = reader.topics()
    if inputs.command_topic and topics.get(inputs.command_topic) == WRENCH_TYPE:
        stamps, rows = [], []
        with open_bag(bag) as reader:
            for message in reader.messages([inputs.command_topic]):
                w = message.msg.wrench
                stamps.append(_stamp(message.msg, message.timestamp_ns))
                rows.append((w.force.x, w.force.y, w.force.z, w.torque.x, w.torque.y,
                             w.torque.z))
        order = np.argsort(stamps, kind='stable')
        return (np.array(stamps, dtype=np.int64)[order], np.array(rows).reshape(-1, 6)[order],
                inputs.command_topic)
    mapping = CommandMapping.load(inputs.thruster_map) if inputs.thruster_map \
        else freeflyer2_mapping()
    if topics.get(mapping.topic) != mapping.msgtype:
        return None
    stamps, wrenches = mapping.read_commands(bag)
    return stamps, wrenches, f'{mapping.topic} ({mapping.name or "thruster map"})'


def commanded_world(bag: str, inputs: PlotInputs, stamps: np.ndarray, position: np.ndarray,
                    rotation: np.ndarray, com: np.ndarray
                    ) -> Optional[tuple[np.ndarray, str]]:
    """
    Return the nominal commanded wrench (n, 6), world frame, torque about ``com``.

    None when the bag has no command. Held from its last message; the body wrench
    (about the base origin) is turned into the world by the base pose.
    """
    found = _command_body(bag, inputs)
    if found is None or not len(found[0]):
        return None
    command_stamps, body, source = found
    held = body[_held(stamps, command_stamps)]
    force = np.einsum('nij,nj->ni', rotation, held[:, :3])
    torque = np.einsum('nij,nj->ni', rotation, held[:, 3:]) \
        + np.cross(position - com, force)
    return np.hstack([force, torque]), source


def _wrench_figure(plt: Any, t: np.ndarray, rows: np.ndarray, robot: RobotModel,
                   names: tuple, units: tuple, title: str, marks: dict, t0: int,
                   command: Optional[tuple[np.ndarray, str]] = None) -> Any:
    """Return a figure of the moved components of (n, 6) ``rows``, one axes per half."""
    halves = [h for h in zip(shown_axes(robot), (0, 3), names, units) if h[0]]
    fig, axes = plt.subplots(len(halves), 1, figsize=(10, 3 * len(halves) + 0.6),
                             sharex=True, squeeze=False, layout='constrained')
    for ax, (components, offset, name, unit) in zip(axes[:, 0], halves):
        draw_marks(ax, marks, t0)
        for i in components:
            line, = ax.plot(t, rows[:, offset + i], label=f'{name}_{COMPONENTS[i]}',
                            zorder=3)
            if command is not None:
                # Binary thrusters switch at the command rate: thin and light, under
                # the estimate, so that it stays readable.
                ax.plot(t, command[0][:, offset + i], color=line.get_color(), alpha=0.35,
                        linewidth=0.7, zorder=2, label=f'{name}_{COMPONENTS[i]} commanded')
        ax.set_ylabel(unit)
        ax.legend(**LEGEND)
        ax.grid(True, alpha=0.3)
    axes[-1, 0].set_xlabel('time [s]')
    axes[0, 0].set_title(title + (f'\ncommanded (nominal): {command[1]}' if command else ''))
    return fig


def _positive(values: np.ndarray) -> tuple[np.ndarray, int]:
    """Return the values with the non-positive ones masked (NaN), and how many they were."""
    values = np.asarray(values, dtype=float)
    keep = values > 0.0
    return np.where(keep, values, np.nan), int(np.count_nonzero(~keep))


def _residual_figure(plt: Any, residual: Table, start: int, marks: dict, t0: int) -> Any:
    fig, ax = plt.subplots(figsize=(10, 4), layout='constrained')
    draw_marks(ax, marks, t0)
    ax.set_yscale('log')
    drawn = 0
    notes = []
    if len(residual.stamps):
        t = (residual.stamps - start) * 1e-9
        for column, marker, name in ((0, 'o-', 'shape [rad]'), (1, 's-', 'base position [m]')):
            values, zeros = _positive(residual.values[:, column])
            if zeros == len(values):
                notes.append(f'{name.split(" [")[0]} residual 0 throughout (not drawn)')
                continue
            label = name + (f' ({zeros} of {len(values)} zero, not drawn)' if zeros else '')
            ax.plot(t, values, marker, label=label)
            drawn += 1
    if drawn:
        ax.legend(**LEGEND)
    else:
        ax.text(0.5, 0.5, 'no finished prediction' if not len(residual.stamps)
                else 'no nonzero residual', ha='center', transform=ax.transAxes)
    ax.set_xlabel('prediction start [s]')
    ax.set_ylabel('max error over horizon (log; zeros left out)')
    ax.set_title('prediction residual (reduced model vs. measured)'
                 + (f'\n{"; ".join(notes)}' if notes and drawn else ''))
    ax.grid(True, which='both', alpha=0.3)
    return fig


def _pyplot() -> Any:
    """Return matplotlib.pyplot on the Agg backend (files only, no display needed)."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    return plt


def make_figures(series: dict, robot: RobotModel, marks: Optional[dict] = None,
                 inputs: Optional[PlotInputs] = None) -> dict[str, Any]:
    """Return ``{file name: matplotlib Figure}`` of a replay's series (see write_plots)."""
    plt = _pyplot()
    marks = marks or {}
    inputs = inputs or PlotInputs()
    figures: dict[str, Any] = {}
    mu, rate, shape = (Table.of(series[name].rows) for name in ('mu', 'rate', 'shape'))
    disturbance = Table.of(series['disturbance'].rows if 'disturbance' in series else [])
    t0 = int(mu.stamps[0]) if len(mu.stamps) else 0
    # The base pose and the centre of mass at the estimate stamps, when the bag has them.
    about, com = 'origin', None
    position = rotation = None
    if inputs.bag and inputs.base_topic and len(mu.stamps):
        poses = read_poses(inputs.bag, inputs.base_topic)
        if len(poses[0]):
            com, position, rotation = centre_of_mass(robot, mu.stamps, poses, shape)
            about = 'centre of mass'

    def moved_about_com(table: Table) -> np.ndarray:
        """World (n, 6) rows about the origin -> about the centre of mass."""
        values = table.values.copy()
        if com is not None:
            # Every series is added per output: the stamps are mu's.
            values[:, 3:] -= np.cross(com[_held(table.stamps, mu.stamps)], values[:, :3])
        return values

    def seconds(table: Table) -> np.ndarray:
        return (table.stamps - t0) * 1e-9

    if len(mu.stamps):
        lifted = Table(mu.stamps, np.array([robot.group.dual_to_wrench(row)
                                            for row in mu.values]))
        figures['momentum.png'] = _wrench_figure(
            plt, seconds(mu), moved_about_com(lifted), robot, ('p', 'L'),
            ('linear momentum [kg m/s]', f'angular momentum about {about} [kg m²/s]'),
            f'momentum map μ (world frame, angular about the {about})', marks, t0)
    if len(rate.stamps):
        command, title = None, 'momentum drift: estimated external wrench dμ/dt'
        if com is not None and inputs.bag:
            held = _held(rate.stamps, mu.stamps)
            try:
                command = commanded_world(inputs.bag, inputs, rate.stamps, position[held],
                                          rotation[held], com[held])
            except (ValueError, OSError) as error:  # a bad thruster map: the plot says so
                title += f'\ncommanded wrench not drawn: {error}'
        figures['drift.png'] = _wrench_figure(
            plt, seconds(rate), moved_about_com(rate), robot, ('F', 'T'),
            ('force [N]', f'torque about {about} [N m]'), title, marks, t0, command)
    if len(disturbance.stamps):
        figures['disturbance.png'] = _wrench_figure(
            plt, seconds(disturbance), moved_about_com(disturbance), robot, ('F', 'T'),
            ('force [N]', f'torque about {about} [N m]'),
            'disturbance beyond the commanded wrench', marks, t0)
    if len(shape.stamps) and shape.values.shape[1]:
        fig, ax = plt.subplots(figsize=(10, 4), layout='constrained')
        draw_marks(ax, marks, t0)
        for i, name in enumerate(robot.shape_joint_names):
            ax.plot(seconds(shape), shape.values[:, i], label=name)
        ax.set_xlabel('time [s]')
        ax.set_ylabel('shape q̄ [rad or m]')
        ax.set_title('shape state')
        ax.legend(**LEGEND)
        ax.grid(True, alpha=0.3)
        figures['shape.png'] = fig
    residual = Table.of(series['residual'].rows)
    start = t0 if len(mu.stamps) else (int(residual.stamps[0]) if len(residual.stamps) else 0)
    figures['prediction_residual.png'] = _residual_figure(plt, residual, start, marks, start)
    return figures


def write_plots(directory: str, series: dict, robot: RobotModel,
                marks: Optional[dict] = None, inputs: Optional[PlotInputs] = None
                ) -> list[str]:
    """
    Write PNG plots of mu, drift, shape state and prediction residual; return paths.

    ``marks`` (:func:`reduced_dynamics.plot_marks.read_marks`): thruster pulses are
    shaded and joint-torque changes drawn on every plot. ``inputs``: the input bag
    and its topics, for the centre of mass and the commanded wrench.
    """
    plt = _pyplot()
    os.makedirs(directory, exist_ok=True)
    paths = []
    for name, fig in make_figures(series, robot, marks, inputs).items():
        path = os.path.join(directory, name)
        fig.savefig(path, dpi=100)
        plt.close(fig)
        paths.append(path)
    return paths
