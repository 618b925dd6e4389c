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

"""Online fixed-lag smoothing: its limits, its stamps, its memory, node and replay."""

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from reduced_dynamics.bag.reader import open_bag
from reduced_dynamics.estimator.config import EstimatorConfig
from reduced_dynamics.estimator import fixed_lag
from reduced_dynamics.estimator.fixed_lag import FixedLagRows, FixedLagSmoother, PASS_FRACTION
from reduced_dynamics.estimator.pipeline import Estimator
from reduced_dynamics.messages import cdr
from reduced_dynamics.messages.convert import joint_state_from_ros, odometry_from_ros
from reduced_dynamics.messages.samples import CommandSample, with_receive_time
from reduced_dynamics.replay import replay, ReplayOptions
from reduced_dynamics.resources import config_path, paper_robot_urdf
from reduced_dynamics.robot.model import load_robot
from reduced_dynamics.simulator import TOPIC_JOINT_STATES, TOPIC_ODOM
from reduced_dynamics.topics import active_topics, FIXED_LAG_TOPICS, resolved_name

REPO = Path(__file__).resolve().parent.parent
DATA = REPO / 'test' / 'data'
NS = 1_000_000_000
ROBOT = load_robot()
QUIET = {'prediction_rate': 0.0, 'diagnostics_rate': 0.0}


def _bag_samples(bag: Path) -> list:
    with open_bag(str(bag)) as reader:
        return [joint_state_from_ros(m.msg) if m.topic == TOPIC_JOINT_STATES
                else odometry_from_ros(m.msg)
                for m in reader.messages([TOPIC_JOINT_STATES, TOPIC_ODOM])]


SAMPLES = _bag_samples(DATA / 'paper_realistic')  # 6 s, 100 Hz joint states + odometry


def _run(lag: float, samples=SAMPLES, smooth: bool = False, robot=ROBOT, **kwargs):
    """Return (estimator, causal outputs, fixed-lag rows with the stamp they went out at)."""
    estimator = Estimator(robot, EstimatorConfig.from_mapping(
        {**QUIET, 'smoothing_lag': lag}), **kwargs)
    if smooth:
        estimator.enable_smoothing()
    outputs = estimator.add_samples(samples).outputs() + estimator.flush()
    emitted = [(output.stamp_ns, row) for output in outputs for row in output.fixed_lag or ()]
    end = outputs[-1].stamp_ns
    emitted += [(end, row) for row in estimator.flush_fixed_lag()]
    return estimator, outputs, emitted


def test_a_lag_beyond_the_run_gives_the_full_smoother():
    # 6 s of data, lag 10 s: every row waits to the end, then one backward pass from the
    # last step, the full smoother's (the same compiled backward step).
    estimator, outputs, emitted = _run(10.0, smooth=True)
    smoothed = list(estimator.smoothed_rows())
    assert len(emitted) == len(smoothed) == len(outputs) > 500
    n = ROBOT.n
    for (_, row), fields in zip(emitted, smoothed):
        assert row.stamp_ns == fields['momentum'].stamp_ns
        np.testing.assert_allclose(row.mu, fields['mu'], rtol=0, atol=1e-12)
        rate = fields['momentum_rate']
        np.testing.assert_allclose(row.momentum_rate.force, rate.force, rtol=0, atol=1e-12)
        np.testing.assert_allclose(row.momentum_rate.torque, rate.torque, rtol=0, atol=1e-12)
        assert row.rate.shape == (n,)


def test_lag_zero_is_the_causal_estimate():
    # The estimator's 0 is "off"; the smoother itself at lag 0 emits each row at its own
    # step, i.e. the filtered state the causal outputs carry.
    estimator = Estimator(ROBOT, EstimatorConfig.from_mapping({**QUIET, 'smoothing_lag': 0.0}))
    assert estimator.fixed_lag is None and not estimator.filter.record
    smoother = FixedLagSmoother(ROBOT.group, 0.0, estimator.filter.dim, False,
                                estimator.kernel.wrenches, 'world')
    estimator.filter.record, estimator.filter.steps = True, smoother
    outputs = estimator.add_samples(SAMPLES).outputs() + estimator.flush()
    rows = smoother.take()
    assert smoother.flush() == []  # nothing waits at lag 0
    assert len(rows) == len(outputs) > 500
    for row, output in zip(rows, outputs):
        assert row.stamp_ns == output.stamp_ns
        assert np.array_equal(row.mu, output.mu)
        assert cdr.encode_wrench_stamped(row.momentum) == \
            cdr.encode_wrench_stamped(output.momentum)
        assert cdr.encode_wrench_stamped(row.momentum_rate) == \
            cdr.encode_wrench_stamped(output.momentum_rate)


def test_passes_keep_columns_whose_messages_are_their_rows_bytes():
    # A pass's rows stay columns (FixedLagRows); the node publishes each topic's messages
    # from them at once. Every message must be the per-message encoder's bytes of the row
    # a reader gets, and the outputs' per-sample lists the same rows.
    estimator = Estimator(ROBOT, EstimatorConfig.from_mapping({**QUIET, 'smoothing_lag': 0.5}))
    outputs = estimator.add_samples(SAMPLES).outputs()
    passes = [output.fixed_lag for output in outputs if output.fixed_lag]
    tail = estimator.flush_fixed_lag()
    assert isinstance(tail, FixedLagRows) and len(passes) >= 8
    assert all(isinstance(rows, list) and rows for rows in passes)
    assert sorted(len(rows) for rows in passes)[len(passes) // 2] > 10
    assert estimator.flush_fixed_lag() == []  # nothing left
    records = tail.records()
    assert {field: part.shape[0] for field, part in records.items()} == \
        {'momentum': len(tail), 'momentum_rate': len(tail)}
    for k, row in enumerate(tail):
        assert row.stamp_ns == int(tail.stamps_ns[k]) and row.momentum.frame_id == 'world'
        assert np.array_equal(row.mu, tail.mu[k]) and np.array_equal(row.rate, tail.rate[k])
        for field, part in records.items():
            assert part[k].tobytes() == cdr.encode_wrench_stamped(getattr(row, field))
    assert tail[-1].stamp_ns == int(tail.stamps_ns[-1])
    assert [row.stamp_ns for row in tail[1:3]] == tail.stamps_ns[1:3].tolist()
    # Passes taken together (take() between two rows): one set of columns, in order.
    halves = FixedLagRows(tail.stamps_ns[:5], tail.mu[:5], tail.rate[:5], tail.momentum[:5],
                          tail.momentum_rate[:5], 'world'), \
        FixedLagRows(tail.stamps_ns[5:], tail.mu[5:], tail.rate[5:], tail.momentum[5:],
                     tail.momentum_rate[5:], 'world')
    joined = FixedLagRows.joined(list(halves))
    for name in ('stamps_ns', 'mu', 'rate', 'momentum', 'momentum_rate'):
        assert np.array_equal(getattr(joined, name), getattr(tail, name))
    # A stamp that is no ROS Time: no columns (the per-message encoder says why).
    early = FixedLagRows(np.array([-1]), tail.mu[:1], tail.rate[:1], tail.momentum[:1],
                         tail.momentum_rate[:1], 'world')
    assert early.records() is None


def test_a_pass_in_slices_gives_the_bits_of_a_whole_pass(monkeypatch):
    # A pass runs SLICE_STEPS backward steps per appended step, each slice starting from
    # the smoothed mean the one before left: the rows must be those of one whole pass,
    # bit for bit, also when the buffer is compacted or grown while a pass is under way.
    def rows(slice_steps):
        monkeypatch.setattr(fixed_lag, 'SLICE_STEPS', slice_steps)
        moved = []
        allocate = FixedLagSmoother._allocate

        def watched(self, capacity):
            moved.append(getattr(self, '_pass', None) is not None)
            allocate(self, capacity)

        monkeypatch.setattr(FixedLagSmoother, '_allocate', watched)
        estimator, _, emitted = _run(0.5)
        return emitted, estimator.fixed_lag.passes, sum(moved)

    whole, passes, _ = rows(10 ** 9)
    sliced, sliced_passes, moved_mid_pass = rows(7)
    assert passes == sliced_passes > 15 and moved_mid_pass >= 1
    assert len(whole) == len(sliced) > 500
    late = 0
    for (out_a, a), (out_b, b) in zip(whole, sliced):
        assert a.stamp_ns == b.stamp_ns and out_b >= out_a
        late += out_b > out_a
        for name in ('mu', 'rate'):
            assert getattr(a, name).tobytes() == getattr(b, name).tobytes()
        assert cdr.encode_wrench_stamped(a.momentum_rate) == \
            cdr.encode_wrench_stamped(b.momentum_rate)
    assert late > 0  # the slices did spread the passes


@pytest.mark.parametrize('lag', [0.1, 0.5])
def test_rows_are_stamped_with_their_time_and_go_out_after_their_lag(lag):
    _, outputs, emitted = _run(lag)
    stamps = [o.stamp_ns for o in outputs]
    # Every row once, in order, stamped with the time it describes.
    assert [row.stamp_ns for _, row in emitted] == stamps
    assert all(row.momentum.stamp_ns == row.momentum_rate.stamp_ns == row.stamp_ns
               for _, row in emitted)
    gap = max(np.diff(stamps))
    end = stamps[-1]
    for out_ns, row in emitted:
        if out_ns == end and row.stamp_ns > end - lag * NS:
            continue  # flushed at the end of the data, before its lag
        waited = out_ns - row.stamp_ns
        assert lag * NS <= waited <= (1 + PASS_FRACTION) * lag * NS + 2 * gap, row.stamp_ns
    # A lag of data later the estimate differs from the causal one (it is smoothed).
    causal = np.array([o.mu for o in outputs])
    lagged = np.array([row.mu for _, row in emitted])
    assert np.abs(lagged - causal).max() > 0.0


def test_memory_is_bounded_by_the_lag_not_the_run():
    lag = 0.2
    short, _, _ = _run(lag, SAMPLES[:len(SAMPLES) // 3])
    whole, outputs, _ = _run(lag)
    # Two filter steps per row here (joint states and odometry on their own stamps).
    per_second = 2 * len(outputs) / ((outputs[-1].stamp_ns - outputs[0].stamp_ns) / NS)
    bound = (1 + PASS_FRACTION) * lag * per_second + 4
    assert whole.fixed_lag.peak_steps <= bound
    assert whole.fixed_lag.peak_steps <= short.fixed_lag.peak_steps + 4
    assert whole.fixed_lag.capacity <= 2 * max(bound, 256)
    assert len(whole.fixed_lag) <= bound


def _freeflyer_command_samples() -> list:
    robot = load_robot(str(config_path('robots/freeflyer.urdf')))
    samples = []
    with open_bag(str(DATA / 'freeflyer_realistic')) as reader:
        begin = reader.start_ns
        for message in reader.raw_messages(['/base_pose', '/commanded_wrench']):
            if message.timestamp_ns >= begin + 3 * NS:
                break
            data = bytes(message.data)
            sample = cdr.decode_wrench_stamped(data) if message.topic == '/commanded_wrench' \
                else cdr.decode_pose_stamped(data, robot.base_link)
            samples.append(with_receive_time(sample, message.timestamp_ns))
    assert any(isinstance(s, CommandSample) for s in samples)
    return robot, samples


def test_with_a_commanded_wrench_the_rate_is_the_smoothed_total():
    robot, samples = _freeflyer_command_samples()
    estimator, outputs, emitted = _run(10.0, samples, smooth=True, robot=robot,
                                       use_odometry=False, commanded_wrench=True)
    smoothed = list(estimator.smoothed_rows())
    assert len(emitted) == len(smoothed) == len(outputs) > 100
    for (_, row), fields in zip(emitted, smoothed):
        rate = fields['momentum_rate']
        np.testing.assert_allclose(row.momentum_rate.force, rate.force, rtol=0, atol=1e-12)
        np.testing.assert_allclose(row.momentum_rate.torque, rate.torque, rtol=0, atol=1e-12)


def _raw(path, topic):
    with open_bag(str(path)) as reader:
        return [(m.timestamp_ns, bytes(m.data)) for m in reader.raw_messages([topic])]


def test_replay_writes_the_fixed_lag_topics_only_when_asked(tmp_path):
    bag = DATA / 'paper_realistic'
    plain = replay(str(bag), str(tmp_path / 'plain'), ROBOT, ReplayOptions(smooth=False))
    lagged = replay(str(bag), str(tmp_path / 'lagged'), ROBOT,
                    ReplayOptions(smooth=False, fixed_lag=0.5))
    names = [resolved_name(t) for t in FIXED_LAG_TOPICS]
    assert not set(names) & set(plain['messages_out'])
    rows = plain['messages_out']['/reduced_dynamics/momentum']
    assert all(lagged['messages_out'][name] == rows for name in names)
    # The causal topics stay bit for bit.
    for topic in active_topics(False):
        name = resolved_name(topic)
        assert _raw(tmp_path / 'plain', name) == _raw(tmp_path / 'lagged', name), name
    # Header stamps: the rows' own; record times: when the lag had passed (or the end).
    momentum = [cdr.decode_wrench_stamped(d).stamp_ns
                for _, d in _raw(tmp_path / 'plain', '/reduced_dynamics/momentum')]
    smoothed = _raw(tmp_path / 'lagged', '/reduced_dynamics/momentum_smoothed')
    assert [cdr.decode_wrench_stamped(d).stamp_ns for _, d in smoothed] == momentum
    assert all(record >= cdr.decode_wrench_stamped(d).stamp_ns for record, d in smoothed)


def test_replay_cli_refuses_a_bad_lag(tmp_path, capsys):
    from reduced_dynamics.cli import main
    code = main(['replay', str(DATA / 'paper_realistic'), '-o', str(tmp_path / 'out'),
                 '--fixed-lag', '-1'])
    assert code == 2
    assert '--fixed-lag' in capsys.readouterr().err
    assert not (tmp_path / 'out').exists()


def test_node_publishes_what_replay_fixed_lag_writes(tmp_path):
    # The node at its default smoothing_lag (0.5 s) against replay --fixed-lag 0.5: the
    # same bytes on both fixed-lag topics (the node never reaches the end of the data, so
    # it lacks the rows replay flushes there), and the causal topics as before.
    try:
        from ros_harness import real_ros, Ros
    except ImportError:  # test/ imported as a package
        from test.ros_harness import real_ros, Ros
    from reduced_dynamics.node import ReducedDynamicsNode
    from rclpy.parameter import Parameter
    bag = DATA / 'paper_realistic'
    replay(str(bag), str(tmp_path / 'out'), ROBOT, ReplayOptions(smooth=False, fixed_lag=0.5))
    with real_ros() as ros:
        node = ReducedDynamicsNode(parameter_overrides=[
            Parameter('urdf_path', value=str(paper_robot_urdf())),
            # replay has no wall-time prediction budget: bit equality under any load
            Parameter('prediction_max_wall_time', value=0.0)])
        Ros.record_logs(node)
        try:
            assert node.get_parameter('smoothing_lag').value == 0.5
            with open_bag(bag) as reader:
                for message in reader.raw_messages(['/joint_states', '/odom']):
                    ros.deliver(node, message.topic, bytes(message.data),
                                message.timestamp_ns)
            node.wait_for_predictions()
            topics = active_topics(False) + FIXED_LAG_TOPICS
            names = {t.name: node.resolve_topic_name(
                t.name if t.name.startswith('/') else '~/' + t.name) for t in topics}
            published = {t.name: ros.published_raw(names[t.name]) for t in topics}
        finally:
            node.destroy_node()
    for topic in topics:
        replayed = [data for _, data in _raw(tmp_path / 'out', resolved_name(topic))]
        mine = published[topic.name]
        if topic in FIXED_LAG_TOPICS:
            assert 0.8 * len(replayed) < len(mine) < len(replayed), topic.name
            assert mine == replayed[:len(mine)], topic.name
        else:
            assert mine == replayed, topic.name


def test_node_publishes_columns_and_rows_through_its_worker_in_order():
    # A pass's columns and a list of rows (the per-output path) go through the one
    # fixed-lag worker: each topic gets the per-message encoder's bytes, in order.
    try:
        from ros_harness import real_ros, Ros
    except ImportError:  # test/ imported as a package
        from test.ros_harness import real_ros, Ros
    from reduced_dynamics.node import ReducedDynamicsNode
    from rclpy.parameter import Parameter
    k = np.arange(6, dtype=float)[:, None]
    rows = FixedLagRows(np.arange(6, dtype=np.int64) * 10 ** 6 + NS, np.tile(k, 6),
                        -np.tile(k, 6), np.tile(k, 6) * 0.5, np.tile(k, 6) * -0.25, 'world')
    with real_ros() as ros:
        node = ReducedDynamicsNode(parameter_overrides=[
            Parameter('urdf_path', value=str(paper_robot_urdf()))])
        Ros.record_logs(node)
        try:
            node._publish_fixed_lag(FixedLagRows(*(getattr(rows, name)[:3] for name in (
                'stamps_ns', 'mu', 'rate', 'momentum', 'momentum_rate')), 'world'))
            node._publish_fixed_lag(rows[3:])  # a list of FixedLagRow, after the columns
            node.wait_for_predictions()
            published = {t.field: ros.published_raw(node.resolve_topic_name('~/' + t.name))
                         for t in FIXED_LAG_TOPICS}
        finally:
            node.destroy_node()
    for field, messages in published.items():
        assert messages == [cdr.encode_wrench_stamped(getattr(row, field)) for row in rows]


def test_changing_the_lag_at_run_time_starts_afresh_and_zero_stops_recording():
    estimator, outputs, emitted = _run(0.2)
    assert estimator.filter.record and estimator.filter.steps is estimator.fixed_lag
    estimator.apply_config(estimator.config.replaced(smoothing_lag=0.0))
    assert estimator.fixed_lag is None and not estimator.filter.record
    assert estimator.filter.steps == []
    estimator.apply_config(estimator.config.replaced(smoothing_lag=0.3))
    smoother = estimator.fixed_lag
    assert smoother is not None and smoother.lag_ns == int(0.3 * NS) and len(smoother) == 0
    # The same motion again, 10 ms after the first run's end.
    shift = outputs[-1].stamp_ns - SAMPLES[0].stamp_ns + 10_000_000
    later = [replace(sample, stamp_ns=sample.stamp_ns + shift) for sample in SAMPLES[:200]]
    more = estimator.add_samples(later).outputs()
    rows = [row for output in more for row in output.fixed_lag or ()]
    assert rows and all(row.stamp_ns > outputs[-1].stamp_ns for row in rows)
