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
The batched path's validation by columns accepts and rejects what the per-message path does.

Every message of a stream with bad input of each kind (NaN, inf, limits, unknown and
reordered joints, zero and off-norm quaternions, missing twists, message covariances)
and bad time (duplicates, backwards stamps, outliers, clock jumps both ways, bursts)
goes through ``add_samples`` in batches of several sizes and one by one; the two must
count the same rejections with the same texts, in the same order, accept the same
items (bit for bit) and give the same outputs.
"""

import numpy as np
import pytest

from reduced_dynamics.estimator import Estimator
from reduced_dynamics.estimator.config import EstimatorConfig
from reduced_dynamics.estimator.plausibility import BaseBounds, JointBounds
from reduced_dynamics.messages.samples import BaseStateSample, JointStateSample
from reduced_dynamics.robot.model import RobotModel

MS = 1_000_000
S = 1_000_000_000
#: Kinds of bad joint states and of bad base states the streams mix in.
BAD_JOINT = ('nan_position', 'inf_velocity', 'position_limit', 'velocity_limit',
             'effort_limit', 'no_effort', 'no_velocity', 'unknown_joint', 'reordered',
             'duplicate_joint')
BAD_BASE = ('nan_position', 'inf_twist', 'zero_quaternion', 'off_norm', 'near_norm',
            'far_position', 'fast_twist', 'spinning', 'no_twist', 'covariance',
            'bad_covariance')


def _joint(robot, rng, stamp, receive, kind=None):
    m = robot.m
    names = robot.shape_joint_names
    t = stamp * 1e-9
    position = 0.2 * np.sin(t + np.arange(m)) + rng.normal(0.0, 1e-4, m)
    velocity = 0.2 * np.cos(t + np.arange(m)) + rng.normal(0.0, 1e-3, m)
    effort = rng.uniform(-0.1, 0.1, m)
    k = int(rng.integers(m))
    if kind == 'nan_position':
        position[k] = np.nan
    elif kind == 'inf_velocity':
        velocity[k] = -np.inf
    elif kind == 'position_limit':
        position[k] = 1e4
    elif kind == 'velocity_limit':
        velocity[k] = 1e5
    elif kind == 'effort_limit':
        effort[k] = -1e9
    elif kind == 'no_effort':
        effort = np.zeros(0)
    elif kind == 'no_velocity':
        velocity = np.zeros(0)
    elif kind == 'unknown_joint':
        names = names[:-1] + ('not_a_joint',)
    elif kind == 'reordered':
        order = rng.permutation(m)
        names = tuple(names[i] for i in order)
        position, velocity, effort = position[order], velocity[order], effort[order]
    elif kind == 'duplicate_joint' and m > 1:
        names = names[:-1] + names[:1]
    return JointStateSample(stamp, '', tuple(names), position, velocity, effort,
                            receive_ns=receive)


def _base(robot, rng, stamp, receive, kind=None):
    t = stamp * 1e-9
    position = np.array([0.01 * t, 0.0, 0.0]) + rng.normal(0.0, 1e-4, 3)
    quaternion = np.array([0.0, 0.0, np.sin(0.025 * t), np.cos(0.025 * t)])
    quaternion += rng.normal(0.0, 1e-4, 4)
    quaternion /= np.linalg.norm(quaternion)
    linear = np.array([0.01, 0.0, 0.0]) + rng.normal(0.0, 1e-3, 3)
    angular = np.array([0.0, 0.0, 0.05]) + rng.normal(0.0, 1e-3, 3)
    covariance = None
    if kind == 'nan_position':
        position[1] = np.nan
    elif kind == 'inf_twist':
        angular[2] = np.inf
    elif kind == 'zero_quaternion':
        quaternion[:] = 0.0
    elif kind == 'off_norm':
        quaternion *= 1.5
    elif kind == 'near_norm':
        quaternion *= 1.0 + 1e-9  # inside the tolerance: normalised
    elif kind == 'far_position':
        position[0] = 1e7
    elif kind == 'fast_twist':
        linear[0] = 1e4
    elif kind == 'spinning':
        angular[1] = -1e4
    elif kind == 'covariance':
        covariance = np.diag([1e-6] * 3 + [1e-5] * 3).ravel()
    elif kind == 'bad_covariance':
        covariance = np.diag([1e-6] * 3 + [-1e-5] * 3).ravel()  # a counted fallback
    twist = (None, None) if kind == 'no_twist' else (linear, angular)
    return BaseStateSample(stamp, 'world', robot.base_link, position, quaternion, *twist,
                           receive_ns=receive, pose_covariance=covariance,
                           twist_covariance=covariance)


def _stream(robot, seed: int, count: int = 400, receive: bool = True,
            bad_rate: float = 0.08) -> list:
    """Joint and base states at 10 ms with bad values and bad time mixed in."""
    rng = np.random.default_rng(seed)
    stamps = [10 * S + k * 10 * MS for k in range(count)]
    # Bad time: a duplicate, a stamp back, a lone outlier ahead, a burst of near-equal
    # base stamps, and from 60 % on a clock 7 s back (a restart), 3 s ahead at 80 %.
    stamps[40] = stamps[39]
    stamps[70] = stamps[68]
    stamps[100] += 3 * S
    for k in range(130, 138):
        stamps[k] = stamps[130] + (k - 130) * 1000
    for k in range(int(0.6 * count), count):
        stamps[k] -= 7 * S
    for k in range(int(0.8 * count), count):
        stamps[k] += 3 * S
    stream = []
    for k, stamp in enumerate(stamps):
        rx = stamp + 2 * MS + int(rng.integers(0, MS)) if receive else None
        joint_kind = BAD_JOINT[int(rng.integers(len(BAD_JOINT)))] \
            if rng.random() < bad_rate else None
        base_kind = BAD_BASE[int(rng.integers(len(BAD_BASE)))] \
            if rng.random() < bad_rate else None
        pair = [_joint(robot, rng, stamp, rx, joint_kind),
                _base(robot, rng, stamp + (300_000 if k % 3 == 0 else 0), rx, base_kind)]
        if rng.random() < 0.1:
            pair.reverse()  # the base state first now and then
        stream += pair
    return stream


def _recording(robot, config, use_odometry):
    """Return an estimator that records its rejections, accepted items and per-message takes."""
    estimator = Estimator(robot, config, use_odometry=use_odometry)
    log = {'rejected': [], 'joints': [], 'bases': [], 'take_joint': 0, 'take_base': 0}
    reject, accept_joint, accept_base = (estimator._reject, estimator._accept_joint,
                                         estimator._accept_base)
    take_joint, take_base = estimator._take_joint, estimator._take_base

    def _reject(reason, detail):
        log['rejected'].append((reason, detail))
        return reject(reason, detail)

    def _accept_joint(item):
        stamp, qbar, qbar_dot, tau = item
        log['joints'].append((stamp, qbar.tobytes(), qbar_dot.tobytes(), tau.tobytes()))
        accept_joint(item)

    def _accept_base(item):
        stamp, row = item
        log['bases'].append((stamp, np.array(list(row)).tobytes(),
                             repr(getattr(row, 'noise', None))))
        accept_base(item)

    def _take_joint(sample):
        log['take_joint'] += 1
        take_joint(sample)

    def _take_base(sample):
        log['take_base'] += 1
        take_base(sample)

    estimator._reject, estimator._accept_joint = _reject, _accept_joint
    estimator._accept_base, estimator._take_joint = _accept_base, _take_joint
    estimator._take_base = _take_base
    return estimator, log


def _per_message(estimator, stream):
    outputs = []
    for sample in stream:
        if isinstance(sample, JointStateSample):
            outputs += estimator.add_joint_state(sample)
        else:
            outputs += estimator.add_base_state(sample)
    return outputs + estimator.flush()


def _batched(estimator, stream, size):
    outputs = []
    for start in range(0, len(stream), size):
        outputs += estimator.add_samples(stream[start:start + size]).outputs()
        yield estimator.rejected.copy(), estimator.last_rejection
    outputs += estimator.flush()
    yield outputs


def _output_bits(outputs):
    return [(o.stamp_ns, o.mu.tobytes(), o.momentum_rate.force.tobytes(),
             o.momentum_rate.torque.tobytes()) for o in outputs]


def _needs_message_path(sample, use_odometry, robot) -> bool:
    """Return whether a sample fails a column check (or is not taken by columns)."""
    if isinstance(sample, JointStateSample):
        if sample.names != robot.shape_joint_names or not sample.velocity.size:
            return True
        bounds = JointBounds(robot, EstimatorConfig(), sample.names)
        values = [sample.position, sample.velocity, sample.effort]
        if not all(np.isfinite(v).all() for v in values):
            return True
        return bounds.check(*(v.tolist() for v in values)) is not None
    if (sample.twist_linear is not None) != use_odometry:
        return True
    twist = [] if sample.twist_linear is None else \
        sample.twist_linear.tolist() + sample.twist_angular.tolist()
    values = sample.position.tolist() + sample.orientation_xyzw.tolist() + twist
    if not np.isfinite(values).all():
        return True
    norm = float(np.linalg.norm(sample.orientation_xyzw))
    return norm < 1e-6 or BaseBounds(EstimatorConfig()).check(
        sample.position.tolist(), float(np.sqrt(np.sum(sample.orientation_xyzw ** 2))),
        twist) is not None


@pytest.mark.parametrize('seed, use_odometry, receive',
                         [(1, True, True), (2, True, False), (3, False, True)])
def test_batches_accept_and_reject_what_messages_one_by_one_do(seed, use_odometry, receive):
    robot = RobotModel()
    config = EstimatorConfig(prediction_rate=0.0, diagnostics_rate=5.0,
                             use_message_covariance=True)
    stream = _stream(robot, seed, receive=receive)
    if not use_odometry:
        stream = [s if isinstance(s, JointStateSample) or s.twist_linear is None
                  or s.pose_covariance is not None
                  else BaseStateSample(s.stamp_ns, s.frame_id, s.child_frame_id, s.position,
                                       s.orientation_xyzw, receive_ns=s.receive_ns)
                  for s in stream]
    reference, expected = _recording(robot, config, use_odometry)
    reference_outputs = _per_message(reference, stream)
    assert expected['rejected'] and reference.clock_resets >= 1
    assert reference.covariance_fallbacks or not use_odometry
    reasons = {reason for reason, _ in expected['rejected']}
    assert {'non_finite', 'unknown_joint', 'non_finite_base', 'stamp_backwards',
            'missing_velocity'} <= reasons, reasons
    for size in (len(stream), 250, 37):
        estimator, log = _recording(robot, config, use_odometry)
        *steps, outputs = _batched(estimator, stream, size)
        assert log['rejected'] == expected['rejected']
        assert log['joints'] == expected['joints'] and log['bases'] == expected['bases']
        assert _output_bits(outputs) == _output_bits(reference_outputs)
        assert estimator.rejected == reference.rejected
        assert estimator.last_rejection == reference.last_rejection
        assert estimator.received == reference.received
        assert estimator.clock_resets == reference.clock_resets
        assert estimator.covariance_fallbacks == reference.covariance_fallbacks
        assert estimator.last_covariance_fallback == reference.last_covariance_fallback
        # Only what fails a column check (or is not taken by columns) goes one by one.
        message_path = [s for s in stream if _needs_message_path(s, use_odometry, robot)]
        assert log['take_joint'] == sum(isinstance(s, JointStateSample) for s in message_path)
        assert log['take_base'] == len(message_path) - log['take_joint']


def test_counters_between_batches_equal_those_of_the_same_messages_one_by_one():
    # Diagnostics close a chunk mid-batch: the counters they report, and the rejections
    # after each batch, are those of the per-message path at the same message. (Not
    # last_rejection between batches: the innovation gate rejects as rows are processed,
    # at the chunk's end on the batched path, after the intake's rejections of the batch;
    # so it was before the columns too.)
    robot = RobotModel()
    config = EstimatorConfig(prediction_rate=0.0, diagnostics_rate=20.0)
    stream = _stream(robot, 4, count=300, bad_rate=0.2)
    reference = Estimator(robot, config)
    expected = []
    size = 61
    for start in range(0, len(stream), size):
        for sample in stream[start:start + size]:
            if isinstance(sample, JointStateSample):
                reference.add_joint_state(sample)
            else:
                reference.add_base_state(sample)
        expected.append(reference.rejected.copy())
    estimator = Estimator(robot, config)
    *steps, _ = _batched(estimator, stream, size)
    assert [counts for counts, _ in steps] == expected
    diagnostics = [o.diagnostics for o in _per_message(Estimator(robot, config), stream)
                   if o.diagnostics is not None]
    batched = [o.diagnostics for o in list(_batched(Estimator(robot, config), stream,
                                                    size))[-1] if o.diagnostics is not None]
    # (Their counters and levels; their text names the last rejection: see above.)
    assert diagnostics and _statuses(batched) == _statuses(diagnostics)


def _statuses(diagnostics: list) -> list:
    return [[(status.name, status.level, status.values) for status in d.statuses]
            for d in diagnostics]


def test_column_bounds_pass_exactly_where_the_per_message_checks_pass():
    robot = RobotModel()
    config = EstimatorConfig()
    rng = np.random.default_rng(9)
    joint = JointBounds(robot, config)
    base = BaseBounds(config)
    m = robot.m
    scale = np.array([[1.0, 10.0, 1e3]])
    position = rng.standard_normal((500, m)) * scale[:, rng.integers(0, 3, 500)].T
    velocity = rng.standard_normal((500, m)) * scale[:, rng.integers(0, 3, 500)].T * 10
    effort = rng.standard_normal((500, m)) * scale[:, rng.integers(0, 3, 500)].T * 100
    no_effort = rng.random(500) < 0.2
    got = joint.passes(position, velocity, effort, no_effort).tolist()
    want = [joint.check(p.tolist(), v.tolist(), [] if skip else e.tolist()) is None
            for p, v, e, skip in zip(position, velocity, effort, no_effort)]
    assert got == want and 0 < sum(got) < 500
    where = rng.standard_normal((500, 3)) * 10.0 ** rng.integers(-1, 6, (500, 1))
    norm = 1.0 + rng.standard_normal(500) * 10.0 ** rng.integers(-9, 0, 500)
    twist = rng.standard_normal((500, 6)) * 10.0 ** rng.integers(-1, 4, (500, 1))
    got = base.passes(where, norm, twist).tolist()
    want = [base.check(p.tolist(), float(n), t.tolist()) is None
            for p, n, t in zip(where, norm, twist)]
    assert got == want and 0 < sum(got) < 500
    got = base.passes(where, norm, None).tolist()
    assert got == [base.check(p.tolist(), float(n), []) is None for p, n in zip(where, norm)]


def test_rows_keep_the_prediction_inputs_only_when_predictions_run():
    # processing.py: the per-row poses, states and quiet flags (in_event) serve the
    # predictions; without them the row reads in_event only inside the detector. With
    # predictions the outputs (estimates and predictions) are those of the messages
    # one by one.
    import sys

    from reduced_dynamics.estimator.events import EventDetector

    class Counting(EventDetector):
        reads = 0

        @property
        def in_event(self):
            if sys._getframe(1).f_code.co_filename.endswith('processing.py'):
                Counting.reads += 1
            return EventDetector.in_event.fget(self)

    robot = RobotModel()
    rng = np.random.default_rng(5)
    stream = [sample for k in range(200) for sample in (
        _joint(robot, rng, 10 * S + k * 10 * MS, None), _base(robot, rng, 10 * S + k * 10 * MS,
                                                              None))]
    for rate, per_row in ((0.0, 0), (20.0, 1)):
        config = EstimatorConfig(prediction_rate=rate, diagnostics_rate=0.0)
        estimator = Estimator(robot, config)
        estimator.add_samples(stream[:20])
        estimator.detector.__class__ = Counting
        Counting.reads = 0
        before = estimator.processed
        estimator.add_samples(stream[20:])
        assert estimator.processed - before > 150
        assert Counting.reads == per_row * (estimator.processed - before)
    outputs = list(_batched(Estimator(robot, config), stream, 64))[-1]
    reference = _per_message(Estimator(robot, config), stream)
    assert _output_bits(outputs) == _output_bits(reference)
    paths = [(o.stamp_ns, o.prediction_path.positions.tobytes(),
              o.prediction_path.orientations_xyzw.tobytes()) for o in outputs
             if o.prediction_path is not None]
    assert len(paths) > 10 and paths == [
        (o.stamp_ns, o.prediction_path.positions.tobytes(),
         o.prediction_path.orientations_xyzw.tobytes()) for o in reference
        if o.prediction_path is not None]
