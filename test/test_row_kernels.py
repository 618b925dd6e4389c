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
The per-row Python around the compiled kernels, trimmed: the same numbers, fewer calls.

Each compiled routine that fuses kernels equals the calls it replaces bit for bit, and
the counts of per-row calls show what left the row (issue 19, docs/row_kernels.md).
"""

from unittest import mock

import numpy as np
import pinocchio as pin
import pytest

from reduced_dynamics.estimator import multiscale
from reduced_dynamics.estimator.core import impulse


@pytest.fixture(scope='module')
def bench_run():
    """Return (robot, the bench's messages of 400 samples) (1 kHz, joints and Odometry)."""
    from reduced_dynamics.bench import update_samples
    from reduced_dynamics.robot.model import load_robot
    robot = load_robot()
    joints, bases = update_samples(robot, 400)
    return robot, [m for pair in zip(joints, bases) for m in pair]


def _estimator(robot):
    from reduced_dynamics.estimator.config import EstimatorConfig
    from reduced_dynamics.estimator.pipeline import Estimator
    return Estimator(robot, EstimatorConfig(prediction_rate=0.0))


def test_measured_momentum_se3_equals_the_two_kernels_it_fuses() -> None:
    """Poses from Pinocchio, the filter covariance's block as a strided view (as the filter)."""
    from reduced_dynamics.geometry.lie_group import SUBGROUPS
    rng = np.random.default_rng(11)
    group = SUBGROUPS['SE(3)']
    for _ in range(300):
        g, pose = pin.SE3.Random(), pin.SE3.Random()
        root = rng.standard_normal((6, 6))
        locked = root @ root.T + 6.0 * np.eye(6)
        interpolated = locked + 0.01 * rng.standard_normal((6, 6))
        p = rng.standard_normal((18, 18))
        p = p @ p.T
        twist, connection = rng.standard_normal(6), rng.standard_normal(6)
        twist_cov = np.diag(rng.uniform(0.1, 1.0, 6))
        joint_cov, pose_noise = np.diag(rng.uniform(0.1, 1.0, 6)), np.diag(rng.uniform(0.1, 1, 6))
        expected = multiscale.twist_momentum(g.actionInverse, locked, connection, twist,
                                             twist_cov, joint_cov, p[:6, :6],
                                             group.coadjoint_form) \
            + multiscale.centre_of_mass('SE(3)', pose, interpolated, pose_noise)[:3]
        pi = locked @ (twist + connection)
        fused = impulse.measured_momentum_se3(
            g.actionInverse, locked, pi, twist_cov, joint_cov, p[:6, :6],
            group.coadjoint_form(pi), interpolated, pose.rotation, pose.translation,
            pose_noise)
        assert len(fused) == len(expected)
        for mine, want in zip(fused, expected):
            np.testing.assert_array_equal(mine, want)


def test_a_measured_twist_is_one_compiled_call_per_row(bench_run) -> None:
    """An SE(3) row with a twist: its momentum and centre of mass come from one call."""
    robot, messages = bench_run
    calls = {'fused': 0, 'twist_momentum': 0, 'centre_of_mass_se3': 0}

    def counted(name, function):
        def wrapper(*args):
            calls[name] += 1
            return function(*args)
        return wrapper

    estimator = _estimator(robot)
    with mock.patch.object(impulse, 'measured_momentum_se3',
                           counted('fused', impulse.measured_momentum_se3)), \
            mock.patch.object(impulse, 'twist_momentum',
                              counted('twist_momentum', impulse.twist_momentum)), \
            mock.patch.object(impulse, 'centre_of_mass_se3',
                              counted('centre_of_mass_se3', impulse.centre_of_mass_se3)):
        estimator.add_samples(messages)
    assert estimator.processed == 400
    # Every row measures a twist (the first one's starts the filter and is one too).
    assert calls == {'fused': 400, 'twist_momentum': 0, 'centre_of_mass_se3': 0}


def test_the_event_windows_lookups_are_done_once_per_window_length() -> None:
    """still_moving and window_statistic: the direct formulas' answers, bank scans once."""
    from reduced_dynamics.chi_square import chi2
    rng = np.random.default_rng(3)
    test = multiscale.MultiScaleTest(6, 1.0)
    test.blocks.active = True
    lengths = [0.3, 0.05, 1.7, 0.3, 3.0, 1.7]
    with mock.patch.object(multiscale.np, 'argmin', wraps=np.argmin) as argmin:
        for _ in range(50):
            test.statistics[:] = rng.chisquare(6, len(test.windows))
            test.blocks.statistics[:] = rng.chisquare(6, len(test.windows)) * 2.0
            for window in lengths:
                short = test.windows <= max(window, test.windows[0]) * (1 + 1e-9)
                threshold = float(chi2.isf(0.01 / int(short.sum()), 6))
                assert test.still_moving(window) == bool(
                    np.any(test.blocks.statistics[short] > threshold))
                nearest = int(np.argmin(np.abs(test.windows - window)))
                assert test.window_statistic(window) == float(test.statistics[nearest])
        # 50 x 6 direct lookups above, and one per distinct length in the test itself.
        assert argmin.call_count == 50 * len(lengths) + len(set(lengths))
