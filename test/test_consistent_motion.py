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

"""The soak's feed is a free-floating motion: no external wrench, predictions at their rate."""

import numpy as np
import pinocchio as pin
import pytest

from reduced_dynamics.consistent_motion import ConsistentMotion
from reduced_dynamics.estimator import Estimator, EstimatorConfig
from reduced_dynamics.robot.model import load_robot
from reduced_dynamics.robot.momentum import body_momentum, momentum_map
from reduced_dynamics.soak import soak_messages


@pytest.fixture(scope='module')
def robot():
    return load_robot()


def _pose_after(robot, seconds: float, dt: float) -> pin.SE3:
    motion = ConsistentMotion(robot)
    for _ in range(int(round(seconds / dt))):
        motion.advance(dt)
    return motion.pose


def test_the_pose_is_the_integral_of_the_twist_to_second_order(robot):
    reference = _pose_after(robot, 1.0, 1e-4)
    errors = [np.linalg.norm(pin.log6(_pose_after(robot, 1.0, dt).inverse() * reference).vector)
              for dt in (4e-3, 2e-3)]
    assert errors[1] < 1e-6
    # Halving the step quarters the error: the midpoint rule, not a drifting pose.
    assert 3.0 < errors[0] / errors[1] < 5.0


def test_the_spatial_momentum_stays_what_it_was_at_the_start(robot):
    motion = ConsistentMotion(robot)
    for _ in range(500):
        motion.advance(1e-3)
    qbar, qbar_dot = motion.shape(motion.t)
    xi = robot.group.coordinates(motion.twist6())
    pi = body_momentum(robot.metric_blocks(qbar), xi, qbar_dot)
    np.testing.assert_allclose(momentum_map(robot.group, motion.pose, pi), motion.mu,
                               atol=1e-12 * np.linalg.norm(motion.mu))


def test_the_soak_feed_opens_no_event_and_predictions_run_at_their_rate(robot):
    # With a base that moved on its own the block test saw a lasting push: an event
    # stayed open and predictions paused (4 in 20 s at 1 Hz).
    config = EstimatorConfig()
    estimator = Estimator(robot, config, use_odometry=True, defer_predictions=True)
    jobs = 0
    messages = soak_messages(robot, 6000)
    for _, kind, sample in messages:
        for output in (estimator.add_base_state if kind else estimator.add_joint_state)(sample):
            if output.prediction_job is not None:
                jobs += 1
                output.prediction_job.run()
    seconds = (messages[-1][0] - messages[0][0]) * 1e-9
    assert list(estimator.events) == []
    assert jobs >= int(seconds * config.prediction_rate) - 1
