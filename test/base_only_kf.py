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
A base-only filter for comparison (docs/mechanics_case.md): not a product feature.

What a user without the mechanics would build, as the freeflyer2 data README's
reference filter: per axis of the base pose (world x, y, z and the world attitude
angles) an independent linear Kalman filter of (position, velocity, acceleration)
with the acceleration a random walk (constant force), the whole robot treated as
one rigid body of its total mass and its locked inertia at the first measured
shape. The reported external force is mass x acceleration, the torque inertia x
angular acceleration. Measurements: the base pose and, from an Odometry, the base
twist (turned into the world frame).
"""

from __future__ import annotations

from typing import NamedTuple, Optional

import numpy as np
from scipy.spatial.transform import Rotation

from reduced_dynamics.bag.reader import open_bag


class BaseTrack(NamedTuple):
    """Measured base states in stamp order; twist rows are NaN where there is none."""

    stamps_ns: np.ndarray
    #: (K, 6): world position and the world attitude angles (unwrapped rotation vector)
    pose: np.ndarray
    #: (K, 6): world linear and angular velocity, or NaN (pose-only input)
    twist: np.ndarray
    #: attitude at the first sample (for the inertia's world frame)
    first_rotation: Rotation


def _stamp(msg) -> int:
    return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec


def read_base_track(bag: str, topic: str) -> BaseTrack:
    """Read an Odometry or PoseStamped topic as a :class:`BaseTrack`."""
    rows = []
    with open_bag(bag) as reader:
        for message in reader.messages([topic]):
            msg = message.msg
            pose = msg.pose.pose if hasattr(msg.pose, 'pose') else msg.pose
            p, q = pose.position, pose.orientation
            twist = np.full(6, np.nan)
            if hasattr(msg, 'twist'):
                lin, ang = msg.twist.twist.linear, msg.twist.twist.angular
                twist = np.array([lin.x, lin.y, lin.z, ang.x, ang.y, ang.z])
            rows.append((_stamp(msg), np.array([p.x, p.y, p.z]),
                         np.array([q.x, q.y, q.z, q.w]), twist))
    rows.sort(key=lambda row: row[0])
    rotations = Rotation.from_quat(np.array([row[2] for row in rows]))
    # World-frame increments R_k R_{k-1}^T summed: angles that never wrap, whose second
    # difference is the world angular acceleration for small steps.
    steps = (rotations[1:] * rotations[:-1].inv()).as_rotvec()
    angles = np.vstack((np.zeros(3), np.cumsum(steps, axis=0)))
    body = np.array([row[3] for row in rows])
    # nav_msgs/Odometry's twist is in the child (base) frame.
    twist = np.hstack((rotations.apply(np.nan_to_num(body[:, :3])),
                       rotations.apply(np.nan_to_num(body[:, 3:]))))
    twist[np.isnan(body)] = np.nan
    pose = np.hstack((np.array([row[1] for row in rows]), angles))
    return BaseTrack(np.array([row[0] for row in rows], dtype=np.int64), pose, twist,
                     rotations[0])


class BaseOnlyEstimate(NamedTuple):
    """Per-sample estimate of the base-only filter."""

    stamps_ns: np.ndarray
    #: (K, 6): world force [N] and torque [N m] (rigid-body mass x acceleration)
    wrench: np.ndarray
    #: (K, 6): their standard deviations
    sigma: np.ndarray


def _transition(dt: float, jerk: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return F and Q of (p, v, a) with white jerk of density ``jerk`` (per axis)."""
    f = np.array([[1.0, dt, 0.5 * dt * dt], [0.0, 1.0, dt], [0.0, 0.0, 1.0]])
    q = np.array([[dt ** 5 / 20, dt ** 4 / 8, dt ** 3 / 6],
                  [dt ** 4 / 8, dt ** 3 / 3, dt ** 2 / 2],
                  [dt ** 3 / 6, dt ** 2 / 2, dt]])
    return f, q[None] * (jerk ** 2)[:, None, None]


def base_only_filter(track: BaseTrack, inertia: np.ndarray, pose_sigma: np.ndarray,
                     twist_sigma: Optional[np.ndarray], jerk: np.ndarray,
                     axes: Optional[list[int]] = None,
                     smooth: bool = False) -> BaseOnlyEstimate:
    """
    Run the per-axis constant-force Kalman filter over ``track``.

    ``inertia``: the whole robot's 6x6 locked inertia (mass first) in the base frame at
    the first sample; its diagonal in the world frame of the first attitude scales the
    accelerations. ``pose_sigma``/``twist_sigma`` (6 each): measurement noise;
    ``twist_sigma`` None: poses only. ``jerk`` (6): random-walk density of the
    acceleration [m/s^3/sqrt(Hz), rad/s^3/sqrt(Hz)], the densities this package's filter
    is given (wrench_jerk_linear, wrench_jerk_angular). ``axes``: the axes to run
    (planar: 0, 1, 5); the others are reported as zero. ``smooth``: the fixed-interval
    (Rauch-Tung-Striebel) smoother's estimate instead of the causal one.
    """
    axes = list(range(6)) if axes is None else axes
    rotation = track.first_rotation.as_matrix()
    world = np.zeros((6, 6))
    world[:3, :3] = world[3:, 3:] = rotation
    scale = np.diag(world @ inertia @ world.T)[axes]
    jerk = np.asarray(jerk, float)[axes]
    count, m = len(track.stamps_ns), len(axes)
    x = np.zeros((m, 3))
    x[:, 0] = track.pose[0, axes]
    if twist_sigma is not None and not np.isnan(track.twist[0, axes]).any():
        x[:, 1] = track.twist[0, axes]
    p = np.zeros((m, 3, 3))
    # A diffuse prior on velocity and acceleration: the first samples set them.
    p[:, 0, 0] = np.asarray(pose_sigma, float)[axes] ** 2
    p[:, 1, 1], p[:, 2, 2] = 1.0, 10.0
    r_pose = np.asarray(pose_sigma, float)[axes] ** 2
    r_twist = None if twist_sigma is None else np.asarray(twist_sigma, float)[axes] ** 2
    # Per step: predicted and updated state and covariance, transition into the step.
    x_pred, p_pred = np.zeros((count, m, 3)), np.zeros((count, m, 3, 3))
    x_post, p_post = np.zeros((count, m, 3)), np.zeros((count, m, 3, 3))
    transitions = np.zeros((count, 3, 3))
    for k in range(count):
        if k:
            f, q = _transition((track.stamps_ns[k] - track.stamps_ns[k - 1]) * 1e-9, jerk)
            x = x @ f.T
            p = f @ p @ f.T + q
            transitions[k] = f
        x_pred[k], p_pred[k] = x, p
        rows = [(0, track.pose[k, axes], r_pose)]
        if r_twist is not None and not np.isnan(track.twist[k, axes]).any():
            rows.append((1, track.twist[k, axes], r_twist))
        for index, z, r in rows:
            # Sequential scalar updates per axis (independent measurements).
            s = p[:, index, index] + r
            gain = p[:, :, index] / s[:, None]
            x = x + gain * (z - x[:, index])[:, None]
            p = p - gain[:, :, None] * p[:, index, None, :]
        x_post[k], p_post[k] = x, p
    if smooth:
        for k in range(count - 2, -1, -1):
            f = transitions[k + 1]
            # C = P_k F^T P_pred(k+1)^-1, per axis (the covariances are symmetric).
            c = np.linalg.solve(p_pred[k + 1], f @ p_post[k]).transpose(0, 2, 1)
            x_post[k] = x_post[k] + np.einsum('aij,aj->ai', c, x_post[k + 1] - x_pred[k + 1])
            p_post[k] = p_post[k] + c @ (p_post[k + 1] - p_pred[k + 1]) @ c.transpose(0, 2, 1)
    accel, accel_var = x_post[:, :, 2], p_post[:, :, 2, 2]
    wrench = np.zeros((count, 6))
    sigma = np.zeros((count, 6))
    wrench[:, axes] = accel * scale
    sigma[:, axes] = np.sqrt(accel_var) * scale
    return BaseOnlyEstimate(track.stamps_ns, wrench, sigma)
