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

"""Test helper: full-dynamics runs turned into estimator input samples."""

import numpy as np
import pinocchio as pin

from reduced_dynamics.full_dynamics import FullDynamics
from reduced_dynamics.messages.samples import BaseStateSample, JointStateSample


#: Estimator settings for noise-free simulated sensors: the filter is told the sensors are
#: exact (1e-10 m, rad, m/s, rad/s), so it follows them; the innovation gate is off.
NOISE_FREE = {'pose_position_noise': 1e-10, 'pose_angle_noise': 1e-10,
              'twist_linear_noise': 1e-10, 'twist_angular_noise': 1e-10,
              'joint_velocity_noise': 0.0, 'innovation_gate': 0.0, 'pose_stamp_noise': 0.0}


def simulate(robot, state, torque, times, pulse=None):
    """
    Run full dynamics, piecewise around an optional base-frame wrench pulse.

    ``pulse`` = (start, duration, wrench6). Returns (poses, xi, qbar, qbar_dot, mu) arrays.
    """
    pieces = []
    breaks = [times[0], times[-1]]
    if pulse is not None:
        breaks = sorted({times[0], pulse[0], pulse[0] + pulse[1], times[-1]})
    current = state
    for a, b in zip(breaks[:-1], breaks[1:]):
        inside = pulse is not None and pulse[0] <= a < pulse[0] + pulse[1]
        wrench = (lambda t, w=np.asarray(pulse[2], float): w) if inside else None
        sample_times = [t for t in times if a <= t < b] + [b]
        if sample_times[0] != a:
            sample_times = [a] + sample_times
        run = FullDynamics(robot, torque, wrench).simulate(current, np.array(sample_times))
        keep = [i for i, t in enumerate(sample_times) if t in set(times)
                and (t < b or b == times[-1])]
        pieces.append((run, keep))
        current = run.state(len(sample_times) - 1)
    poses, xi, qbar, qbar_dot, mu = [], [], [], [], []
    for run, keep in pieces:
        for i in keep:
            poses.append(run.poses[i])
            xi.append(run.xi[i])
            qbar.append(run.qbar[i])
            qbar_dot.append(run.qbar_dot[i])
            mu.append(run.mu[i])
    return (np.array(poses), np.array(xi), np.array(qbar), np.array(qbar_dot),
            np.array(mu))


def samples(robot, times, poses, xi, qbar, qbar_dot, torque=None, odometry=True):
    """Return (joint-state samples, base samples) for a run."""
    joints, bases = [], []
    for i, t in enumerate(times):
        stamp = int(round(t * 1e9))
        tau = np.zeros(robot.m) if torque is None else torque(t, qbar[i], qbar_dot[i])
        joints.append(JointStateSample(stamp, '', robot.shape_joint_names, qbar[i],
                                       qbar_dot[i], tau))
        g = pin.SE3(poses[i])
        quat = pin.Quaternion(g.rotation).coeffs()
        twist = robot.group.twist(xi[i])
        bases.append(BaseStateSample(stamp, 'world', robot.base_link, g.translation, quat,
                                     twist[:3] if odometry else None,
                                     twist[3:] if odometry else None))
    return joints, bases


def feed(estimator, joints, bases):
    """Feed interleaved samples; return all outputs including the flush."""
    outputs = []
    for joint, base in zip(joints, bases):
        outputs += estimator.add_joint_state(joint)
        outputs += estimator.add_base_state(base)
    return outputs + estimator.flush()


def feed_stream(estimator, stream):
    """Feed joint state and base samples in stream order; return all outputs and the flush."""
    outputs = []
    for sample in stream:
        if isinstance(sample, JointStateSample):
            outputs += estimator.add_joint_state(sample)
        else:
            outputs += estimator.add_base_state(sample)
    return outputs + estimator.flush()
