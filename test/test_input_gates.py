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

"""Input gates: the stamp policy (outliers, clock jumps) and the plausibility bounds."""

import os

from hypothesis import given, settings, strategies as st
import numpy as np
import pytest

from reduced_dynamics.bag.reader import open_bag
from reduced_dynamics.bag.writer import BagWriter
from reduced_dynamics.estimator import Estimator
from reduced_dynamics.estimator.config import EstimatorConfig
from reduced_dynamics.estimator.plausibility import BaseBounds, JointBounds
from reduced_dynamics.estimator.stamps import ACCEPTED, StampGate
from reduced_dynamics.messages.samples import BaseStateSample, JointStateSample
from reduced_dynamics.params import defaults
from reduced_dynamics.replay import replay, ReplayOptions
from reduced_dynamics.robot.model import load_robot, RobotModel
from sim_samples import feed_stream

DATA = os.path.join(os.path.dirname(__file__), 'data')
MS = 1_000_000
S = 1_000_000_000
#: A header stamp in 2038 (just below the int32 seconds limit).
FAR_FUTURE_S = 2_147_000_000
#: Replay settings for the noise-free simulated bags: the filter follows the sensors.
NOISE_FREE = {**defaults(), 'pose_position_noise': 1e-10, 'pose_angle_noise': 1e-10,
              'twist_linear_noise': 1e-10, 'twist_angular_noise': 1e-10,
              'joint_velocity_noise': 0.0, 'innovation_gate': 0.0, 'pose_stamp_noise': 0.0}


def _run_gate(gate, stamps, receives=None):
    """Offer stamps in order; return (accepted stamps in processing order, drops, jumps)."""
    accepted, dropped, jumps = [], [], []
    receives = receives or [None] * len(stamps)
    for stamp, receive in zip(stamps, receives):
        result = gate.offer(stamp, receive, stamp)
        if result is ACCEPTED:
            accepted.append(stamp)
            continue
        dropped += [(item, reason) for item, reason, _ in result.dropped]
        if result.jump is not None:
            jumps.append(result.jump)
        accepted += result.accepted
    dropped += [(item, reason) for item, reason, _ in gate.finish()]
    return accepted, dropped, jumps


def test_isolated_future_outlier_is_dropped_alone():
    stamps = [k * 10 * MS for k in range(50)]
    for receives in (None, list(stamps)):
        bad = list(stamps)
        bad[20] = FAR_FUTURE_S * S
        accepted, dropped, jumps = _run_gate(StampGate('j', S, 3), bad, receives)
        assert accepted == stamps[:20] + stamps[21:]
        assert dropped == [(bad[20], 'outlier')] and not jumps


def test_a_stamp_slightly_ahead_is_an_outlier_not_a_new_clock():
    # Half a second ahead: within the tolerance, but 100 periods ahead of the cadence.
    stamps = [k * 5 * MS for k in range(60)]
    for receives in (None, [s + 2 * MS for s in stamps]):
        bad = list(stamps)
        bad[30] += S // 2
        accepted, dropped, jumps = _run_gate(StampGate('j', S, 3), bad, receives)
        assert accepted == stamps[:30] + stamps[31:]
        assert dropped == [(bad[30], 'outlier')] and not jumps


def test_outlier_in_the_past_and_at_the_end():
    stamps = [100 * S + k * 10 * MS for k in range(30)]
    bad = list(stamps)
    bad[5] = 0
    bad[-1] = FAR_FUTURE_S * S
    accepted, dropped, _ = _run_gate(StampGate('j', S, 3), bad)
    assert accepted == stamps[:5] + stamps[6:-1]
    assert dropped == [(0, 'outlier'), (bad[-1], 'outlier')]


def test_clock_jump_backwards_is_followed_without_loss():
    before = [100 * S + k * 10 * MS for k in range(30)]
    after = [5 * S + k * 10 * MS for k in range(30)]
    accepted, dropped, jumps = _run_gate(StampGate('j', S, 3), before + after)
    assert accepted == before + after and not dropped
    assert len(jumps) == 1 and jumps[0].backwards and jumps[0].to_ns == after[0]


def test_jump_with_the_receive_time_is_followed_at_once():
    # A looped bag recorded on sim time: record time and header stamp jump together.
    stamps = [100 * S + k * 10 * MS for k in range(10)] + [k * 10 * MS for k in range(10)]
    gate = StampGate('j', S, 3)
    results = [gate.offer(s, s + 3 * MS, s) for s in stamps]
    assert all(r is ACCEPTED for r in results[:10] + results[11:])
    assert results[10].jump.backwards and results[10].jump.receive_moved
    assert results[10].accepted == [stamps[10]]


def test_paused_stream_resumes_at_once_with_receive_times_and_late_without():
    stamps = [k * 10 * MS for k in range(10)] + [5 * S + k * 10 * MS for k in range(10)]
    accepted, dropped, jumps = _run_gate(StampGate('j', S, 3), stamps, list(stamps))
    assert accepted == stamps and not dropped and not jumps
    gate = StampGate('j', S, 3)
    late = [len(r.accepted) if r is not ACCEPTED else 1
            for r in (gate.offer(s, None, s) for s in stamps)]
    # Without receive times the first two after the gap wait for the third, then all go.
    assert late[10:13] == [0, 0, 3] and sum(late) == len(stamps)


def test_duplicates_and_reordering_are_backwards_not_outliers():
    stamps = [k * 10 * MS for k in range(10)]
    bad = stamps[:5] + [stamps[4], stamps[3]] + stamps[5:]
    accepted, dropped, jumps = _run_gate(StampGate('j', S, 3), bad)
    assert accepted == stamps and dropped == [(stamps[4], 'backwards'),
                                              (stamps[3], 'backwards')]


def test_bursty_stream_without_receive_time_loses_nothing():
    # Motion capture at 100 Hz whose packets sometimes come in bursts stamped tens of
    # microseconds apart (as in the freeflyer2 recordings): the cadence must not shrink.
    stamps, t = [], 0
    for k in range(400):
        burst = 40 <= k % 100 < 60
        t += 20_000 if burst else 10 * MS
        stamps.append(t)
    accepted, dropped, jumps = _run_gate(StampGate('j', S, 3), stamps)
    # After a long burst the first regular step is held until two more confirm it
    # (a forward re-synchronisation): late, not lost.
    assert accepted == stamps and not dropped and all(not j.backwards for j in jumps)


def test_slow_stream_without_receive_time_loses_nothing():
    stamps = [k * 2 * S for k in range(20)]  # 0.5 Hz, slower than the 1 s tolerance
    accepted, dropped, _ = _run_gate(StampGate('j', S, 3), stamps)
    assert accepted == stamps and not dropped
    assert StampGate('j', S, 3).tolerance() == S


def test_jump_chain_survives_an_outlier_inside_it():
    before = [100 * S + k * 10 * MS for k in range(10)]
    after = [5 * S + k * 10 * MS for k in range(10)]
    stream = before + after[:2] + [FAR_FUTURE_S * S] + after[2:]
    accepted, dropped, jumps = _run_gate(StampGate('j', S, 3), stream)
    assert accepted == before + after and dropped == [(FAR_FUTURE_S * S, 'outlier')]


def test_follow_releases_the_other_streams_new_clock():
    gate = StampGate('base', S, 3)
    for k in range(10):
        assert gate.offer(100 * S + k * 10 * MS, None, k) is ACCEPTED
    held = gate.offer(5 * S, None, 'new0')
    assert held.accepted == [] and gate.held == 1
    result = gate.follow(5 * S + 2 * MS, None)
    assert result.accepted == ['new0'] and not result.dropped
    assert gate.offer(5 * S + 10 * MS, None, 'new1') is ACCEPTED


def _details(gate, stamps, receives):
    """Offer stamps in order; return (accepted stamps, [(stamp, reason, detail)] dropped)."""
    accepted, dropped = [], []
    for stamp, receive in zip(stamps, receives):
        result = gate.offer(stamp, receive, stamp)
        if result is ACCEPTED:
            accepted.append(stamp)
            continue
        dropped += result.dropped
        accepted += result.accepted
    return accepted, dropped + gate.finish()


def test_a_sample_after_a_late_one_is_not_an_outlier():
    """Issue 21.2: on a loaded machine the reference arrived late; the next is on time."""
    period, latency, late = 5 * MS, 2 * MS, 80 * MS
    stamps = [k * period for k in range(40)]
    receives = [s + latency for s in stamps]
    a = stamps[-1] + period                 # taken 80 ms late
    b = a + 85 * MS                         # the publisher stalled; taken on time
    stamps += [a, b] + [b + k * period for k in range(1, 30)]
    receives += [a + late, b + latency] + [b + k * period + late for k in range(1, 30)]
    accepted, dropped = _details(StampGate('joint state', S, 3), stamps, receives)
    assert dropped == [] and accepted == stamps


def test_a_gap_sent_in_a_burst_then_a_stall_loses_nothing():
    """
    A mocap gap (83 ms) in a stream published faster than real time, then a stall.

    CI (stop 38): a bag replayed over DDS as fast as the node takes it; the two samples
    after the bag's gap arrived 2 ms apart (the gap not in their receive times: held as
    candidates), the third after the publisher stalled 60 ms (consistent with the old
    clock again). The two were dropped as outliers; replay, with the bag's record times,
    kept them. Between two samples of the old clock, in order, they are a gap.
    """
    period = 8_333_333
    stamps = [k * period for k in range(40)]
    stamps += [stamps[-1] + 83 * MS + k * period for k in range(40)]
    receives, t = [], 0
    for k in range(len(stamps)):
        t += 60 * MS if k == 42 else 2 * MS
        receives.append(t)
    accepted, dropped = _details(StampGate('base', S, 3), stamps, receives)
    assert dropped == [] and accepted == stamps
    # A candidate ahead of the sample that proves the old clock is still an outlier;
    # the one before it, in order, is kept.
    bad = list(stamps)
    bad[41] = stamps[42] + 10 * MS
    accepted, dropped = _details(StampGate('base', S, 3), bad, receives)
    assert [(item, reason) for item, reason, _ in dropped] == [(bad[41], 'outlier')]
    assert accepted == stamps[:41] + stamps[42:]


@settings(max_examples=300, deadline=None, derandomize=True)
@given(steps=st.lists(st.one_of(st.integers(1, 20 * MS), st.integers(20 * MS, 300 * MS)),
                      min_size=30, max_size=120),
       pacing=st.lists(st.one_of(st.integers(0, 3 * MS), st.integers(3 * MS, 400 * MS)),
                       min_size=121, max_size=121))
def test_a_clean_stream_loses_nothing_whatever_its_pacing(steps, pacing):
    """
    Increasing stamps with gaps up to 0.3 s, taken at any pace (bursts, stalls up to 0.4 s).

    A publisher faster or slower than real time, a loaded machine: no sample may be dropped,
    but for the last two, which may still be held as candidates when the input ends.
    """
    stamps = list(np.cumsum([5 * S] + steps))
    receives = list(np.cumsum(pacing[:len(stamps)]) + 7 * S)
    stamps, receives = [int(s) for s in stamps], [int(r) for r in receives]
    accepted, dropped = _details(StampGate('base', S, 3), stamps, receives)
    assert accepted == stamps[:len(accepted)] and len(accepted) >= len(stamps) - 2
    assert [item for item, _, _ in dropped] == stamps[len(accepted):]


@pytest.mark.parametrize('with_receive', [True, False])
def test_an_outlier_names_the_rule_that_fired(with_receive):
    """Issue 21.2: a stamp 85 ms ahead is refused by the cadence rule, and says so."""
    stamps = [k * 5 * MS for k in range(60)]
    bad = list(stamps)
    bad[30] += 85 * MS
    receives = [s + 2 * MS for s in stamps] if with_receive else [None] * len(stamps)
    accepted, dropped = _details(StampGate('joint state', S, 3), bad, receives)
    assert accepted == stamps[:30] + stamps[31:]
    (item, reason, detail), = dropped
    assert (item, reason) == (bad[30], 'outlier')
    assert detail.startswith(f'joint state stamp {bad[30]} is +0.09 s from its stream')
    assert 'cadence rule' in detail and 'tolerance' not in detail
    assert '0.02 s, 4 local periods' in detail
    # A stamp an hour ahead of its receive time breaks the offset rule instead.
    if with_receive:
        bad[30] = stamps[30] + 3600 * S
        _, dropped = _details(StampGate('joint state', S, 3), bad, receives)
        assert 'offset rule' in dropped[0][2] and 'tolerance 1 s' in dropped[0][2]


# --- the estimator with the gates ---------------------------------------------------------
def _good(robot, stamp, receive=None, q=None):
    joint = JointStateSample(stamp, '', robot.shape_joint_names,
                             np.full(robot.m, 0.1) if q is None else q,
                             np.full(robot.m, 0.2), np.zeros(robot.m), receive_ns=receive)
    base = BaseStateSample(stamp, 'world', robot.base_link, [0.1, 0.2, 0.3],
                           [0.0, 0.0, 0.0, 1.0], [0.01, 0.0, 0.0], [0.0, 0.0, 0.02],
                           receive_ns=receive)
    return joint, base


def test_estimator_follows_a_backwards_clock_jump_of_both_streams():
    robot = RobotModel()
    config = EstimatorConfig(prediction_rate=0.0, diagnostics_rate=0.0)
    stamps = [100 * S + k * 10 * MS for k in range(40)] + [5 * S + k * 10 * MS
                                                           for k in range(40)]
    stream = [s for stamp in stamps for s in _good(robot, stamp)]
    estimator = Estimator(robot, config)
    outputs = feed_stream(estimator, stream)
    assert [o.stamp_ns for o in outputs] == stamps
    assert not estimator.rejected and estimator.clock_resets == 1
    assert all(np.isfinite(o.momentum_rate.force).all() for o in outputs)
    # The batched path decides the same.
    batched = Estimator(robot, config)
    columns = batched.add_samples(stream)
    assert list(columns.column('stamps_ns')) + [o.stamp_ns for o in batched.flush()] \
        == stamps
    assert batched.clock_resets == 1


def test_reset_restarts_the_clock_and_keeps_counts():
    robot = RobotModel()
    estimator = Estimator(robot, EstimatorConfig(prediction_rate=0.0, diagnostics_rate=0.0))
    first = feed_stream(estimator,
                        [s for k in range(10) for s in _good(robot, 50 * S + k * 10 * MS)])
    assert len(first) == 10
    estimator.reset('ROS time jumped back')
    again = feed_stream(estimator, [s for k in range(10) for s in _good(robot, S + k * 10 * MS)])
    assert len(again) == 10 and not estimator.rejected
    assert estimator.clock_resets == 1 and estimator.last_reset == 'ROS time jumped back'
    assert estimator.summary()['processed'] == 20


def test_plausibility_bounds_from_the_urdf():
    robot = RobotModel()
    config = EstimatorConfig()
    bounds = JointBounds(robot, config)
    names = robot.shape_joint_names
    j4 = names.index('j4')
    assert bounds.lower[j4] == -1.5 - config.joint_limit_margin
    assert bounds.velocity[j4] == 2.0 * config.limit_factor
    assert bounds.effort[j4] == 20.0 * config.limit_factor
    j2 = names.index('j2_x')  # continuous, no limit: the configured bounds
    assert bounds.upper[j2] == config.joint_position_bound
    assert bounds.velocity[j2] == config.joint_velocity_bound
    zeros = [0.0] * robot.m
    assert bounds.check(zeros, zeros, zeros) is None
    beyond = list(zeros)
    beyond[j4] = 1.5 + config.joint_limit_margin + 1e-6
    assert bounds.check(beyond, zeros, [])[0] == 'joint_position_limit'
    fast = list(zeros)
    fast[j4] = -2.0 * config.limit_factor * (1 + 1e-9)
    assert bounds.check(zeros, fast, [])[0] == 'joint_velocity_limit'
    assert bounds.check(zeros, zeros, [1e300] * robot.m)[0] == 'joint_effort_limit'
    base = BaseBounds(config)
    assert base.check([0.0, 0.0, 0.0], 1.0 + 0.5 * config.quaternion_norm_tolerance,
                      [0.0] * 6) is None
    assert base.check([0.0, 0.0, 0.0], 1e3, [])[0] == 'quaternion_norm'
    assert base.check([1e300, 0.0, 0.0], 1.0, [])[0] == 'base_position_bound'
    assert base.check([0.0, 0.0, 0.0], 1.0, [1e5, 0, 0, 0, 0, 0])[0] == 'base_twist_bound'
    assert base.check([0.0, 0.0, 0.0], 1.0, [0, 0, 0, 0, 0, 50.0])[0] == 'base_twist_bound'


def test_urdf_limits_are_kept():
    robot = RobotModel()
    limit = robot.shape_joint_limits['j4']
    assert (limit.lower, limit.upper, limit.velocity, limit.effort) == (-1.5, 1.5, 2.0, 20.0)
    assert 'j2_x' not in robot.shape_joint_limits  # continuous without <limit>


# --- acceptance on the shipped bag -------------------------------------------------------
def _mutated_bag(tmp_path, mutate):
    """Copy paper_thruster's inputs into a new bag, message by message through ``mutate``."""
    from rosbags.typesys import get_typestore, Stores
    store = get_typestore(Stores.ROS2_JAZZY)
    with open_bag(os.path.join(DATA, 'paper_thruster')) as reader:
        topics = {t: m for t, m in reader.topics().items() if t in ('/joint_states', '/odom')}
        items = [(m.topic, m.msgtype, m.timestamp_ns, bytes(m.data))
                 for m in reader.raw_messages(list(topics))]
    path = tmp_path / 'mutated'
    changed = []
    with BagWriter(path, topics) as writer:
        counters = {'/joint_states': 0, '/odom': 0}
        for topic, msgtype, stamp, data in items:
            msg = store.deserialize_cdr(data, msgtype)
            if mutate(topic, counters[topic], msg):
                data = bytes(store.serialize_cdr(msg, msgtype))
                changed.append((topic, counters[topic], stamp))
            counters[topic] += 1
            writer.write_raw(topic, stamp, data)
    return str(path), changed


@pytest.fixture(scope='module')
def clean_replay(tmp_path_factory):
    out = tmp_path_factory.mktemp('clean') / 'out'
    return replay(os.path.join(DATA, 'paper_thruster'), str(out), load_robot(),
                  ReplayOptions(params=NOISE_FREE, smooth=False)), out


def _momenta(path):
    with open_bag(path) as reader:
        return {m.timestamp_ns: np.array([m.msg.wrench.force.x, m.msg.wrench.force.y,
                                          m.msg.wrench.force.z, m.msg.wrench.torque.x,
                                          m.msg.wrench.torque.y, m.msg.wrench.torque.z])
                for m in reader.messages(['/reduced_dynamics/momentum'])}


def test_one_future_stamp_loses_exactly_that_sample(tmp_path, clean_replay):
    clean, clean_out = clean_replay

    def future(topic, index, msg):
        if topic == '/joint_states' and index == 300:
            msg.header.stamp.sec = FAR_FUTURE_S
            return True
        return False

    bag, changed = _mutated_bag(tmp_path, future)
    summary = replay(bag, str(tmp_path / 'out'), load_robot(),
                     ReplayOptions(params=NOISE_FREE, smooth=False))
    assert summary['rejected'] == {'stamp_outlier': 1}
    assert summary['processed'] == clean['processed'] - 1
    lost = changed[0][2]  # simulated bags record at the header stamp
    reference = _momenta(clean_out)
    mutated = _momenta(tmp_path / 'out')
    assert set(reference) - set(mutated) == {lost} and not set(mutated) - set(reference)
    # Up to the lost sample bit for bit; after it the filter steps over a longer gap.
    assert all(np.array_equal(mutated[t], reference[t]) for t in mutated if t < lost)
    assert all(np.allclose(mutated[t], reference[t], rtol=1e-8) for t in mutated)


def test_implausible_values_are_rejected_and_counted(tmp_path, clean_replay):
    clean, _ = clean_replay

    def hostile(topic, index, msg):
        if topic == '/joint_states' and index % 50 == 7:
            values = np.array(msg.position)
            values[index % len(values)] = 1e300
            msg.position = values
            return True
        if topic == '/joint_states' and index % 50 == 9:
            msg.effort = np.full(len(msg.effort), -1e300)
            return True
        if topic == '/odom' and index % 50 == 11:
            q = msg.pose.pose.orientation
            q.x, q.y, q.z, q.w = 1e3 * q.x, 1e3 * q.y, 1e3 * q.z, 1e3 * q.w
            return True
        return False

    bag, changed = _mutated_bag(tmp_path, hostile)
    summary = replay(bag, str(tmp_path / 'out'), load_robot(),
                     ReplayOptions(params=NOISE_FREE, smooth=False))
    per_topic = {t: sum(1 for c in changed if c[0] == t) for t in ('/joint_states', '/odom')}
    rejected = summary['rejected']
    assert rejected.get('joint_position_limit', 0) + rejected.get('joint_effort_limit', 0) \
        == per_topic['/joint_states']
    assert rejected['quaternion_norm'] == per_topic['/odom']
    # Momentum stays physical: below ten times the clean run's largest.
    reference = _momenta(clean['output_bag'])
    mutated = np.array(list(_momenta(tmp_path / 'out').values()))
    bound = 10 * max(np.abs(v).max() for v in reference.values())
    assert np.isfinite(mutated).all() and np.abs(mutated).max() <= bound
