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

"""The batched update equals the streaming one sample for sample (bit for bit)."""

from dataclasses import fields, is_dataclass
import os

import numpy as np
import pinocchio as pin
import pytest

from conftest_robots import paper_robot, planar_robot, tree_robot
from reduced_dynamics.bag.reader import open_bag
from reduced_dynamics.estimator import Estimator, EstimatorConfig
from reduced_dynamics.estimator.kernel import rotations, UpdateKernel
from reduced_dynamics.geometry.isotropy import MomentumClass
from reduced_dynamics.messages.convert import (
    joint_state_from_ros, odometry_from_ros, pose_stamped_from_ros)
from reduced_dynamics.messages.samples import (BaseStateSample, JointStateSample,
                                               with_receive_time)
from reduced_dynamics.replay import choose_inputs, ReplayOptions
from reduced_dynamics.resources import config_path
from reduced_dynamics.robot.model import load_robot
from reduced_dynamics.validation import random_scenario
from sim_samples import feed_stream, samples, simulate

DATA = os.path.join(os.path.dirname(__file__), 'data')
MS = 1_000_000


# --- helpers -------------------------------------------------------------------------
def _same(a, b, where='output'):
    """Assert two outputs (dataclasses, arrays, lists, scalars) are identical."""
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        assert isinstance(a, np.ndarray) and isinstance(b, np.ndarray), where
        assert a.shape == b.shape and np.array_equal(a, b), where
    elif is_dataclass(a):
        assert type(a) is type(b), where
        for item in fields(a):
            _same(getattr(a, item.name), getattr(b, item.name), f'{where}.{item.name}')
    elif isinstance(a, (list, tuple)):
        assert isinstance(b, (list, tuple)) and len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b)):
            _same(x, y, f'{where}[{i}]')
    elif isinstance(a, dict):
        assert a.keys() == b.keys(), where
        for key in a:
            _same(a[key], b[key], f'{where}[{key!r}]')
    else:
        assert a == b, f'{where}: {a!r} != {b!r}'


def _batched(estimator, stream, size):
    outputs, columns = [], []
    for start in range(0, len(stream), size or len(stream) or 1):
        batch = estimator.add_samples(stream[start:start + (size or len(stream))])
        outputs += batch.outputs()
        columns.append(batch)
    final = estimator.flush_batch()
    columns.append(final)
    mu = np.concatenate([b.column('mu') for b in columns if len(b)] or [np.zeros((0, 1))])
    assert np.array_equal(mu, np.array([o.mu for o in outputs + final.outputs()]))
    return outputs + final.outputs()


def _state(estimator):
    """Return what must agree besides the outputs (mean and spread: to rounding)."""
    summary = estimator.summary()
    moments = summary.pop('mu_mean'), summary.pop('mu_spread')
    events = [(e.start_ns, e.end_ns, e.peak_wrench, e.mu_before, e.mu_after)
              for e in estimator.events]
    return summary, moments, events, estimator.last_rejection, dict(estimator.rejected)


def _compare_paths(make, stream, sizes=(1, 3, 64, None)):
    """Run the stream sample by sample, then batched in slices of each size."""
    reference = make()
    expected = feed_stream(reference, stream)
    expected_state = _state(reference)
    for size in sizes:
        estimator = make()
        got = _batched(estimator, stream, size)
        assert len(got) == len(expected), size
        _same(got, expected, f'size {size}')
        state = _state(estimator)
        _same(state[0], expected_state[0], f'summary, size {size}')
        for got_moment, moment in zip(state[1], expected_state[1]):
            # Chunks merge their running moments (Chan et al.): equal to rounding.
            scale = max(1.0, float(np.abs(expected_state[1][0]).max()))
            assert np.allclose(got_moment, moment, rtol=1e-12, atol=1e-12 * scale), size
        _same(state[2:], expected_state[2:], f'events/rejections, size {size}')
    return expected, reference


def _bag_stream(name, robot):
    path = os.path.join(DATA, name)
    with open_bag(path) as reader:
        joint_topic, base_topic, is_odom = choose_inputs(reader.topics(), ReplayOptions())
        stream = []
        for message in reader.messages([t for t in (joint_topic, base_topic) if t]):
            if message.topic == joint_topic:
                stream.append(joint_state_from_ros(message.msg))
            elif is_odom:
                stream.append(odometry_from_ros(message.msg))
            else:
                stream.append(pose_stamped_from_ros(message.msg, robot.base_link))
    return stream, is_odom, joint_topic is None or robot.m == 0


# --- the estimator on shipped bags and simulated runs ------------------------------------
@pytest.mark.parametrize('name, make_robot', [('paper_thruster', paper_robot),
                                              ('paper_constant', paper_robot),
                                              ('planar_pose_only', planar_robot)])
def test_batched_equals_streaming_on_shipped_bags(name, make_robot):
    robot = make_robot()
    stream, is_odom, base_driven = _bag_stream(name, robot)
    # Default settings: predictions and diagnostics on, so chunks close at them. No
    # wall-time budget: two paths must make the same predictions on a loaded machine too.
    config = EstimatorConfig(prediction_horizon=0.5, diagnostics_rate=2.0, innovation_gate=0.0,
                             prediction_max_wall_time=0.0)
    expected, reference = _compare_paths(
        lambda: Estimator(robot, config, use_odometry=is_odom, base_driven=base_driven),
        stream, sizes=(1, 7, 200, None))
    assert len(expected) > 250 and reference.predictor.made >= 1
    assert any(o.diagnostics is not None for o in expected)


@pytest.mark.parametrize('make_robot, odometry', [(paper_robot, True), (tree_robot, True),
                                                  (planar_robot, True), (paper_robot, False)])
def test_batched_equals_streaming_on_simulated_pulse(make_robot, odometry):
    robot = make_robot()
    scenario = random_scenario(robot, MomentumClass.GENERIC, 5, drift_speed=0.1,
                               shape_speed=0.2)
    times = np.arange(401) / 200.0
    wrench = np.array([20.0, -10.0, 0.0, 0.0, 0.0, -3.0])  # in the plane: any base group
    run = simulate(robot, scenario.state, scenario.torque, times, (0.8, 0.1, wrench))
    joints, bases = samples(robot, times, *run[:4], torque=scenario.torque, odometry=odometry)
    # Base samples a little late and jittered: the joint states wait, then interpolate.
    rng = np.random.default_rng(0)
    stream = []
    for joint, base in zip(joints, bases):
        stamp = base.stamp_ns + int(rng.integers(0, 2 * MS))
        stream += [joint, BaseStateSample(stamp, base.frame_id, base.child_frame_id,
                                          base.position, base.orientation_xyzw,
                                          base.twist_linear, base.twist_angular)]
    # Noise-free samples, filtered as from a precise sensor: the pulse is an event.
    config = EstimatorConfig(prediction_rate=2.0, prediction_horizon=0.3,
                             diagnostics_rate=5.0, event_hold=0.05, pose_position_noise=1e-5,
                             pose_angle_noise=1e-5, twist_linear_noise=1e-5,
                             twist_angular_noise=1e-5, pose_stamp_noise=1e-3,
                             prediction_max_wall_time=0.0)
    expected, reference = _compare_paths(
        lambda: Estimator(robot, config, use_odometry=odometry), stream)
    assert len(expected) >= 395 and len(reference.events) >= 1


def test_batched_equals_streaming_with_the_second_stage():
    robot = load_robot(str(config_path('robots/paper_robot_wheels.urdf')))
    scenario = random_scenario(robot, MomentumClass.GENERIC, 5, drift_speed=0.1,
                               shape_speed=0.2, rotors=[6, 7, 8])
    times = np.arange(301) / 200.0
    run = simulate(robot, scenario.state, scenario.torque, times, None)
    joints, bases = samples(robot, times, *run[:4], torque=scenario.torque)
    stream = [item for pair in zip(bases, joints) for item in pair]
    config = EstimatorConfig(prediction_rate=2.0, prediction_horizon=0.3, diagnostics_rate=5.0,
                             prediction_mode='held_torque', prediction_max_wall_time=0.0)
    reference = Estimator(robot, config, cyclic_joints='auto')
    expected = feed_stream(reference, stream)
    assert len(expected) == 301 and reference.predictor.made >= 2
    assert all(o.cyclic_state.names == ('wheel_x', 'wheel_y', 'wheel_z') for o in expected)
    assert all(len(o.shape_state.names) == 6 for o in expected)
    for size in (3, 64, None):
        got = _batched(Estimator(robot, config, cyclic_joints='auto'), stream, size)
        assert len(got) == len(expected)
        for a, b in zip(got, expected):
            # First-stage fields to the bit; the second-stage solve (p^, theta) goes
            # through BLAS, whose rounding depends on memory alignment: to 1e-12.
            _same(a.momentum, b.momentum)
            _same(a.shape_state.position, b.shape_state.position)
            for x, y in ((a.shape_state.effort, b.shape_state.effort),
                         (a.cyclic_state.effort, b.cyclic_state.effort)):
                np.testing.assert_allclose(x, y, rtol=1e-12, atol=1e-12 * np.abs(y).max())
            _same(a.cyclic_state.position, b.cyclic_state.position)
            assert (a.prediction is None) == (b.prediction is None)
            if a.prediction is not None:
                np.testing.assert_allclose(a.prediction.positions, b.prediction.positions,
                                           rtol=1e-9, atol=1e-12)


def _good(robot, stamp):
    return (JointStateSample(stamp, '', robot.shape_joint_names, np.full(robot.m, 0.1),
                             np.full(robot.m, 0.2), np.full(robot.m, 0.3)),
            BaseStateSample(stamp, 'world', robot.base_link, np.array([1.0, 2.0, 3.0]),
                            [0, 0, np.sin(0.1), np.cos(0.1)], np.array([0.1, 0, 0]),
                            np.array([0, 0, 0.2])))


def _hostile_stream(robot):
    """Good samples with every kind of bad one in between, in one batch."""
    names = robot.shape_joint_names
    stream = []
    for k in range(12):
        stamp = (k + 1) * 10 * MS
        joint, base = _good(robot, stamp)
        nan = np.full(robot.m, 0.1)
        nan[k % robot.m] = np.nan if k % 2 else np.inf
        huge = np.full(robot.m, 1e308)  # finite, though their sum overflows
        stream += [
            joint,
            JointStateSample(stamp + MS, '', names, nan, np.zeros(robot.m)),
            JointStateSample(stamp + 2 * MS, '', names[:-1] + ('ghost',), np.zeros(robot.m),
                             np.zeros(robot.m)),
            JointStateSample(stamp + 3 * MS, '', names[:-1], np.zeros(robot.m - 1),
                             np.zeros(robot.m - 1)),
            JointStateSample(stamp + 4 * MS, '', names, np.zeros(robot.m)),
            JointStateSample(stamp - 5 * MS, '', names, np.zeros(robot.m), np.zeros(robot.m)),
            base,
            BaseStateSample(stamp + MS, 'world', 'b', np.zeros(3), np.zeros(4), np.zeros(3),
                            np.zeros(3)),
            BaseStateSample(stamp - MS, 'world', 'b', np.zeros(3), [0, 0, 0, 1.0],
                            np.zeros(3), np.zeros(3)),
            BaseStateSample(stamp + MS, 'world', 'b', [np.nan, 0, 0], [0, 0, 0, 1.0],
                            np.zeros(3), np.zeros(3)),
        ]
        if k == 5:
            # Reversed joint order (a permutation), then finite values whose sum overflows.
            stream.append(JointStateSample(stamp + 6 * MS, '', names[::-1],
                                           np.full(robot.m, 0.1), np.full(robot.m, 0.2)))
            stream.append(_good(robot, stamp + 6 * MS)[1])
            stream.append(JointStateSample(stamp + 7 * MS, '', names, huge, np.zeros(robot.m),
                                           huge))
            stream.append(_good(robot, stamp + 7 * MS)[1])
    # A joint state far from any base state: stale once the base stream moves on.
    stream.append(JointStateSample(500 * MS, '', names, np.zeros(robot.m), np.zeros(robot.m)))
    stream.append(_good(robot, 900 * MS)[1])
    # Received at their stamps (as a bag records them): the stamp policy then sees the
    # streams pause before the last two samples, rather than jump ahead of their cadence.
    return [with_receive_time(sample, sample.stamp_ns) for sample in stream]


def test_bad_input_inside_a_batch_is_rejected_like_one_by_one():
    robot = paper_robot()
    # The innovation gate off: the permuted joint state moves the joints of a base at
    # rest, a momentum jump the gate would (rightly) refuse; here the intake is tested.
    config = EstimatorConfig(prediction_rate=0.0, diagnostics_rate=30.0, innovation_gate=0.0)
    expected, reference = _compare_paths(lambda: Estimator(robot, config),
                                         _hostile_stream(robot), sizes=(1, 2, 5, 40, None))
    # Nothing valid lost: 12 good samples and the permuted one; the huge one (1e308, far
    # beyond the URDF limits) is implausible.
    assert len(expected) == 13
    assert reference.rejected == {
        'non_finite': 12, 'unknown_joint': 12, 'missing_joint': 12, 'missing_velocity': 12,
        'stamp_backwards': 12, 'invalid_quaternion': 12, 'base_stamp_backwards': 12,
        'non_finite_base': 12, 'joint_position_limit': 1, 'stale_base_state': 1}
    assert reference.last_rejection.startswith('stale_base_state')


def test_a_failed_prediction_and_a_later_rejection_keep_their_order(monkeypatch):
    robot = paper_robot()
    stream = []
    for k in range(60):
        joint, base = _good(robot, (k + 1) * 10 * MS)
        stream += [joint, base]
        if k in (20, 41):
            stream.append(JointStateSample(joint.stamp_ns - MS, '', robot.shape_joint_names,
                                           np.zeros(robot.m), np.zeros(robot.m)))

    def fail(*args, **kwargs):
        raise ArithmeticError('no prediction today')

    # Events and the gate off: the samples (a pose at rest with a twist) are not
    # consistent dynamics, and this test is about the order of rejections.
    config = EstimatorConfig(prediction_rate=10.0, event_significance=0.0,
                             innovation_gate=0.0)
    last = []
    for cut in (len(stream), 45):
        results = []
        for size in (0, 1, cut):
            estimator = Estimator(robot, config)
            monkeypatch.setattr(estimator.predictor, 'predict', fail)
            if size:
                _batched(estimator, stream[:cut], size)
            else:
                feed_stream(estimator, stream[:cut])
            results.append((estimator.last_rejection, dict(estimator.prediction_failures)))
        assert results[0] == results[1] == results[2]
        last.append(results[0][0])
    # A prediction failed after the last rejection in the whole stream, not in the first
    # 45 samples (a failure at 210 ms, then the stamp going back).
    assert last[0].startswith('prediction failed') and last[1].startswith('stamp_backwards')


def test_add_samples_keeps_waiting_samples_between_calls():
    robot = paper_robot()
    joints, bases = zip(*(_good(robot, (k + 1) * 10 * MS) for k in range(5)))
    estimator = Estimator(robot, EstimatorConfig(prediction_rate=0.0))
    assert len(estimator.add_samples(list(joints))) == 0  # no base state yet: all wait
    batch = estimator.add_samples(list(bases))
    assert len(batch) == 5 and len(batch.outputs()) == 5
    assert estimator.processed == 5 and not estimator.rejected
    assert batch.column('stamps_ns').tolist() == [j.stamp_ns for j in joints]


# --- parts -------------------------------------------------------------------------------
@pytest.mark.parametrize('make_robot', [paper_robot, tree_robot, planar_robot])
def test_kernel_matches_metric_blocks_and_is_chunk_invariant(make_robot):
    robot = make_robot()
    kernel = UpdateKernel(robot)
    rng = np.random.default_rng(2)
    count = 40
    qbar = rng.normal(size=(count, robot.m))
    qbar_dot = rng.normal(size=(count, robot.m))
    xi = rng.normal(size=(count, robot.n))
    # From the test's own generator (pin.SE3.Random draws from a global state that other
    # tests advance: the result then depended on the test order).
    poses = [robot.project_pose(pin.exp6(pin.Motion(rng.normal(size=6)))) for _ in range(count)]
    bases = np.array([np.r_[pin.SE3ToXYZQUAT(g), robot.group.twist(x)]
                      for g, x in zip(poses, xi)])
    result = kernel.evaluate(qbar, qbar_dot, bases)
    for k in range(count):
        blocks = robot.metric_blocks(qbar[k])
        velocity = np.r_[xi[k], qbar_dot[k]]
        momentum = blocks.mass_matrix @ velocity
        pi = momentum[:robot.n]
        expected = {'pi': pi, 'mu': robot.group.Ad(poses[k].inverse()).T @ pi,
                    'pbar': blocks.reduced_metric @ qbar_dot[k],
                    'drift': blocks.solve_locked(pi),
                    'energy': 0.5 * velocity @ momentum + robot.potential_energy(qbar[k])}
        for name, value in expected.items():
            got = getattr(result, name)[k]
            assert np.allclose(got, value, rtol=1e-12, atol=1e-12 * np.abs(value).max()), name
        single = kernel.evaluate(qbar[k:k + 1], qbar_dot[k:k + 1], bases[k:k + 1])
        for got, chunk in zip(single, result):
            assert np.array_equal(got[0], chunk[k])
    assert np.allclose(result.rotation, [g.rotation for g in poses], rtol=0, atol=1e-15)


def test_rotation_formula_scalar_and_vector_branches_agree():
    rng = np.random.default_rng(3)
    quaternions = rng.normal(size=(50, 4))
    quaternions /= np.linalg.norm(quaternions, axis=1)[:, None]
    stacked = rotations(quaternions)
    one_by_one = np.array([rotations(q[None, :])[0] for q in quaternions])
    assert np.array_equal(stacked, one_by_one)
    assert np.allclose(stacked, [pin.Quaternion(q[3], *q[:3]).toRotationMatrix()
                                 for q in quaternions], rtol=0, atol=1e-15)


def test_singular_locked_inertia_fails_alike_on_both_paths():
    kernel = UpdateKernel(paper_robot())
    locked = np.zeros((3, 6, 6))
    locked[:, :3, :3] = 2.0 * np.eye(3)  # mass, no rotational inertia at all
    for count in (1, 3):
        with pytest.raises(np.linalg.LinAlgError, match='positive definite'):
            kernel.solve_locked(locked[:count], np.ones((count, 6)))
