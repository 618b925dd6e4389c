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

"""Bag replay end to end: shipped and generated bags in, output bags read independently."""

import json
import os
import shutil

from mcap.reader import make_reader
import numpy as np
import pytest

from reduced_dynamics.bag.reader import open_bag
from reduced_dynamics.cli import main
from reduced_dynamics.estimator import Estimator, EstimatorConfig
from reduced_dynamics.messages.convert import joint_state_from_ros, odometry_from_ros
from reduced_dynamics.params import defaults
from reduced_dynamics.replay import replay, ReplayOptions
from reduced_dynamics.resources import config_path
from reduced_dynamics.robot.model import load_robot
from reduced_dynamics.simulator import simulate_bag, SimulationOptions, ThrusterPulse
from reduced_dynamics.topics import active_topics, EVENTS_TOPIC, resolved_name

from filter_helpers import bag_contents

DATA = os.path.join(os.path.dirname(__file__), 'data')


def _read_all(path, topics):
    with open_bag(path) as reader:
        return [(m.topic, m.timestamp_ns, m.msg) for m in reader.messages(topics)]


def _wrenches(messages, topic):
    return np.array([[m.wrench.force.x, m.wrench.force.y, m.wrench.force.z,
                      m.wrench.torque.x, m.wrench.torque.y, m.wrench.torque.z]
                     for t, _, m in messages if t == topic])


@pytest.fixture(scope='module')
def thruster_replay(tmp_path_factory):
    out = tmp_path_factory.mktemp('replay') / 'out'
    # Causal (--no-smooth): the outputs the node publishes, compared bit for bit below.
    summary = replay(os.path.join(DATA, 'paper_thruster'), str(out), load_robot(),
                     ReplayOptions(params=_noise_free_params(), smooth=False))
    return summary, str(out)


def test_output_bag_read_independently_with_counts_of_summary(thruster_replay):
    summary, out = thruster_replay
    mcap_file = [f for f in os.listdir(out) if f.endswith('.mcap')][0]
    counts = {}
    with open(os.path.join(out, mcap_file), 'rb') as stream:
        reader = make_reader(stream, validate_crcs=True)
        for _, channel, _ in reader.iter_messages():
            counts[channel.topic] = counts.get(channel.topic, 0) + 1
    assert counts == summary['messages_out']
    # Default prediction mode (planned, held_velocity without a plan): no shape prediction.
    assert set(counts) == {resolved_name(t) for t in active_topics(False) + (EVENTS_TOPIC,)
                           if t.name != 'prediction/shape'}
    with open_bag(out) as reader:
        assert {t: reader.message_count(t) for t in reader.topics()
                if reader.message_count(t)} == counts
        assert reader.topics() == {resolved_name(t): t.msgtype
                                   for t in active_topics(False) + (EVENTS_TOPIC,)}


def test_replayed_momentum_matches_ground_truth_and_stamps(thruster_replay):
    summary, out = thruster_replay
    outputs = _read_all(out, ['/reduced_dynamics/momentum', '/reduced_dynamics/drift/'
                              'momentum_rate'])
    truth = _read_all(os.path.join(DATA, 'paper_thruster'), ['/ground_truth/momentum'])
    mu = _wrenches(outputs, '/reduced_dynamics/momentum')
    mu_truth = _wrenches(truth, '/ground_truth/momentum')
    assert mu.shape == mu_truth.shape
    assert np.abs(mu - mu_truth).max() <= 1e-9 * np.linalg.norm(mu_truth[0])
    stamps = [m.header.stamp.sec * 10**9 + m.header.stamp.nanosec
              for t, _, m in outputs if t == '/reduced_dynamics/momentum']
    assert stamps == [ts for _, ts, _ in truth]
    # Impulse recovered from the published drift estimate, and flagged within 50 ms.
    rate = _wrenches(outputs, '/reduced_dynamics/drift/momentum_rate')
    seconds = (np.array(stamps) - stamps[0]) * 1e-9
    impulse = np.trapezoid(rate, seconds, axis=0)
    jump = mu_truth[-1] - mu_truth[0]
    assert np.linalg.norm(impulse - jump) <= 0.05 * np.linalg.norm(jump)
    (event,) = summary['events']
    assert 0.0 <= event['start_s'] - 1.5 <= 0.05


def test_replay_equals_pipeline_on_same_bag(thruster_replay):
    _, out = thruster_replay
    robot = load_robot()
    estimator = Estimator(robot, EstimatorConfig.from_mapping(_noise_free_params()))
    direct = []
    for message in _read_all(os.path.join(DATA, 'paper_thruster'), ['/joint_states', '/odom']):
        if message[0] == '/joint_states':
            direct += estimator.add_joint_state(joint_state_from_ros(message[2]))
        else:
            direct += estimator.add_base_state(odometry_from_ros(message[2]))
    direct += estimator.flush()
    replayed = _wrenches(_read_all(out, ['/reduced_dynamics/body_momentum']),
                         '/reduced_dynamics/body_momentum')
    expected = np.array([np.r_[o.body_momentum.force, o.body_momentum.torque] for o in direct])
    assert np.array_equal(replayed, expected)


def test_constant_torque_bag_prediction_residual(tmp_path):
    bag = os.path.join(DATA, 'paper_constant')
    # Noise-free efforts, and the held-torque estimate is told so (its change test then
    # takes every flip at once; issue 26: the estimate, not the last sample, is held).
    params = {**_params(), 'prediction_rate': 2.0, 'prediction_horizon': 0.4,
              'prediction_mode': 'held_torque', 'joint_effort_noise': 1e-9}
    summary = replay(bag, str(tmp_path / 'out'), load_robot(), ReplayOptions(params=params))
    assert summary['predictions'] >= 4
    # Torques are held for 1 s: predictions that do not straddle a flip are exact.
    assert summary['prediction_shape_residual_median'] <= 1e-6


def _params():
    return defaults()


def _noise_free_params():
    """Return the defaults for noise-free simulated sensors (the filter is told so)."""
    params = defaults()
    params.update(pose_position_noise=1e-10, pose_angle_noise=1e-10, twist_linear_noise=1e-10,
                  twist_angular_noise=1e-10, joint_velocity_noise=0.0, innovation_gate=0.0,
                  pose_stamp_noise=0.0)
    return params


def test_planar_puck_from_poses_only_with_custom_topic(tmp_path):
    urdf = """<robot name="puck"><link name="puck"><inertial><mass value="12"/>
      <inertia ixx="0.3" ixy="0" ixz="0" iyy="0.3" iyz="0" izz="0.5"/></inertial></link>
      </robot>"""
    robot = load_robot(urdf, 'planar')
    bag = tmp_path / 'puck'
    pulse = ThrusterPulse(1.0, 0.2, (3.0, -2.0, 0.0, 0.0, 0.0, 0.4))
    simulate_bag(robot, bag, SimulationOptions(duration=3.0, rate=100.0, seed=4,
                                               base_pose_only=True, status=True,
                                               thrusters=(pulse,)))
    with open_bag(bag) as reader:
        assert '/simulator/status' in reader.topics()
        assert '/joint_states' not in reader.topics() or robot.m == 0
    # Causal: a smoother spreads the pulse's onset over its time constant both ways.
    summary = replay(str(bag), str(tmp_path / 'out'), robot, ReplayOptions(smooth=False))
    assert summary['base_driven'] and not summary['rejected']
    outputs = _read_all(tmp_path / 'out', ['/reduced_dynamics/momentum'])
    truth = _read_all(bag, ['/ground_truth/momentum'])
    mu = _wrenches(outputs, '/reduced_dynamics/momentum')
    mu_truth = _wrenches(truth, '/ground_truth/momentum')
    stamps = np.array([ts for _, ts, _ in truth])
    # Pose-only: the filter starts at mu = 0 and rings ~1.5 s after the pulse.
    seconds = (stamps - stamps[0]) * 1e-9
    quiet = (seconds >= 0.3) & ((seconds < 0.95) | (seconds > 2.7))
    # Mocap-grade noise is assumed (1 mm): within 2e-3 N s, 0.17 mm/s on 12 kg.
    assert np.abs(mu - mu_truth)[quiet].max() <= 2e-3
    assert len(summary['events']) == 1
    impulse = np.array(summary['events'][0]['impulse'])
    jump = (mu_truth[-1] - mu_truth[0])[[0, 1, 5]]
    assert np.linalg.norm(impulse - jump) <= 0.2 * np.linalg.norm(jump)


def test_cli_replay_with_params_window_and_plots(tmp_path, capsys):
    out = tmp_path / 'out'
    code = main(['replay', os.path.join(DATA, 'planar_pose_only'), '-o', str(out),
                 '--urdf', str(config_path('robots/planar_testbed.urdf')),
                 '--base-joint', 'planar',
                 '--gravity', '0', '0', '-9.81', '--params', str(config_path('params.yaml')),
                 '--start', '0.5', '--end', '2.5', '--plots', str(tmp_path / 'plots'),
                 '--quiet', '--summary-json', str(tmp_path / 'summary.json')])
    assert code == 0
    text = capsys.readouterr().out
    assert 'messages out' in text and 'rejected' in text
    assert sorted(os.listdir(tmp_path / 'plots')) == ['drift.png', 'momentum.png',
                                                      'prediction_residual.png', 'shape.png']
    with open_bag(out) as reader:
        stamps = [m.timestamp_ns for m in reader.messages(['/reduced_dynamics/momentum'])]
    with open_bag(os.path.join(DATA, 'planar_pose_only')) as reader:
        start = reader.start_ns
    assert (stamps[0] - start) * 1e-9 >= 0.5 - 1e-9
    assert (stamps[-1] - start) * 1e-9 < 2.5


@pytest.mark.parametrize('damage', ['truncate', 'garbage', 'no_base_topic', 'missing'])
def test_hostile_bags_give_clear_errors(tmp_path, capsys, damage):
    bag = tmp_path / 'bag'
    shutil.copytree(os.path.join(DATA, 'paper_constant'), bag)
    mcap_file = bag / 'paper_constant.mcap'
    args = ['replay', str(bag), '-o', str(tmp_path / 'out'), '--quiet']
    if damage == 'truncate':
        data = mcap_file.read_bytes()
        mcap_file.write_bytes(data[:len(data) // 2])
        args.append('--strict')  # without it the intact half is replayed (exit 3)
    elif damage == 'garbage':
        mcap_file.write_bytes(os.urandom(4096))
    elif damage == 'no_base_topic':
        args += ['--odom-topic', '/nonexistent']
    else:
        args[1] = str(tmp_path / 'nothing_here')
    assert main(args) == 2
    err = capsys.readouterr().err
    assert err.startswith('reduced-dynamics replay: error:') and len(err.splitlines()) == 1


def test_output_is_not_overwritten(tmp_path, capsys):
    out = tmp_path / 'out'
    out.mkdir()
    (out / 'keep.txt').write_text('precious')
    assert main(['replay', os.path.join(DATA, 'paper_constant'), '-o', str(out),
                 '--quiet']) == 2
    assert (out / 'keep.txt').read_text() == 'precious'


def _raw_outputs(path):
    names = [resolved_name(t) for t in active_topics(False)]
    with open_bag(path) as reader:
        return [(m.topic, m.timestamp_ns, bytes(m.data)) for m in reader.raw_messages(names)]


def test_fixed_layout_codecs_change_no_output_byte(tmp_path, monkeypatch):
    # Same bag, prediction and diagnostics on: fast codecs against rosbags' generic
    # (de)serialization through the *_to_ros / *_from_ros converters.
    from reduced_dynamics.messages import cdr
    bag = os.path.join(DATA, 'paper_constant')
    fast_path = cdr.fast_path_applies
    written = set()
    for mode in ('held_torque', 'held_velocity'):
        params = {**_params(), 'prediction_rate': 2.0, 'prediction_horizon': 0.4,
                  'prediction_mode': mode}
        monkeypatch.setattr(cdr, 'fast_path_applies', fast_path)
        fast = replay(bag, str(tmp_path / f'fast_{mode}'), load_robot(),
                      ReplayOptions(params=params))
        monkeypatch.setattr(cdr, 'fast_path_applies', lambda store, msgtype: False)
        slow = replay(bag, str(tmp_path / f'slow_{mode}'), load_robot(),
                      ReplayOptions(params=params))
        assert fast['messages_out'] == slow['messages_out']
        written |= set(fast['messages_out'])
        assert _raw_outputs(tmp_path / f'fast_{mode}') == _raw_outputs(tmp_path / f'slow_{mode}')
    assert written == {resolved_name(t) for t in active_topics(False)}  # no event here


def test_bad_input_messages_are_counted_and_change_no_output(tmp_path):
    from rosbags.typesys import get_typestore, Stores
    from reduced_dynamics.bag.writer import BagWriter
    store = get_typestore(Stores.ROS2_JAZZY)
    clean = os.path.join(DATA, 'paper_constant')
    with open_bag(clean) as reader:
        topics = {t: m for t, m in reader.topics().items() if t in ('/joint_states', '/odom')}
        items = [(m.topic, m.msgtype, m.timestamp_ns, bytes(m.data))
                 for m in reader.raw_messages(list(topics))]
    joint = next(i for i in items if i[0] == '/joint_states')
    odom = next(i for i in items if i[0] == '/odom')
    bad_sizes = store.deserialize_cdr(joint[3], joint[1])
    bad_sizes.position = bad_sizes.position[:1]
    negative = bytearray(odom[3])
    negative[4:8] = (-5).to_bytes(4, 'little', signed=True)
    junk = [('/joint_states', joint[3][:20]),  # undecodable
            ('/odom', odom[3][:50]),  # undecodable
            ('/joint_states', bytes(store.serialize_cdr(bad_sizes, joint[1]))),  # malformed
            ('/odom', bytes(negative))]  # malformed: negative stamp
    damaged = tmp_path / 'damaged'
    with BagWriter(damaged, topics) as writer:
        for index, (topic, msgtype, stamp, data) in enumerate(items):
            if index == 40:  # valid big-endian CDR: the generic decoder takes it
                data = bytes(store.serialize_cdr(store.deserialize_cdr(data, msgtype), msgtype,
                                                 little_endian=False))
            writer.write_raw(topic, stamp, data)
            if index % 97 == 5 and junk:
                bad_topic, bad = junk.pop()
                writer.write_raw(bad_topic, stamp, bad)
    assert not junk
    good = replay(clean, str(tmp_path / 'good'), load_robot())
    summary = replay(str(damaged), str(tmp_path / 'out'), load_robot())
    assert summary['undecodable_skipped'] == {
        'deserialization failed: /joint_states (sensor_msgs/msg/JointState)': 1,
        'deserialization failed: /odom (nav_msgs/msg/Odometry)': 1}
    assert summary['rejected'] == {'malformed': 2}
    assert {t: n - good['messages_in'][t] for t, n in summary['messages_in'].items()} == \
        {'/joint_states': 1, '/odom': 1}
    # Diagnostics count the rejections; every estimate is the same.
    assert summary['messages_out'] == good['messages_out']
    estimates = [m for m in _raw_outputs(tmp_path / 'out') if m[0] != '/diagnostics']
    assert estimates == [m for m in _raw_outputs(tmp_path / 'good') if m[0] != '/diagnostics']


def test_replay_base_joint_auto_follows_the_urdf_world_joint(tmp_path) -> None:
    """A URDF declaring a planar world joint loads with the default parameters (auto)."""
    from reduced_dynamics.params import ALL_PARAMETERS
    from reduced_dynamics.replay import load_robot_from_params
    from reduced_dynamics.resources import config_path
    defaults = {name: spec.default for name, spec in ALL_PARAMETERS.items()}
    robot = load_robot_from_params(defaults, str(config_path('robots/freeflyer.urdf')))
    assert robot.base_joint_type == 'planar'
    assert load_robot_from_params(defaults).base_joint_type == 'floating'


def test_causal_output_of_a_smoothed_replay_is_the_no_smooth_replay(tmp_path, capsys):
    """``--causal-output``: from one pass, the smoothed bag and ``--no-smooth``'s bag, bytewise."""
    bag = os.path.join(DATA, 'paper_thruster')
    common = ['replay', bag, '--quiet', '--fixed-lag', '0.5']
    assert main([*common, '-o', str(tmp_path / 'causal'), '--no-smooth']) == 0
    assert main([*common, '-o', str(tmp_path / 'smoothed')]) == 0
    capsys.readouterr()
    summary = tmp_path / 'summary.json'
    assert main([*common, '-o', str(tmp_path / 'both'), '--causal-output',
                 str(tmp_path / 'both_causal'), '--summary-json', str(summary)]) == 0
    assert f'causal outputs (as --no-smooth writes them): {tmp_path / "both_causal"}' \
        in capsys.readouterr().out
    topics, causal = bag_contents(tmp_path / 'causal')
    # Events and fixed-lag rows (written as they happen, smoothed or not) are in both bags.
    written = {topic for topic, _, _ in causal}
    assert resolved_name(EVENTS_TOPIC) in written and '/reduced_dynamics/momentum_smoothed' \
        in written
    assert bag_contents(tmp_path / 'both_causal') == (topics, causal)
    assert bag_contents(tmp_path / 'both') == bag_contents(tmp_path / 'smoothed')
    assert json.loads(summary.read_text())['causal_output_bag'] == str(tmp_path / 'both_causal')


def test_causal_output_refusals_name_the_flag(tmp_path, capsys):
    bag = os.path.join(DATA, 'paper_constant')
    out, causal = str(tmp_path / 'out'), str(tmp_path / 'causal')
    assert main(['replay', bag, '-o', out, '--quiet', '--no-smooth',
                 '--causal-output', causal]) == 2
    assert 'error: --causal-output: without smoothing the output bag holds the causal ' \
        'outputs already' in capsys.readouterr().err
    assert main(['replay', bag, '-o', out, '--quiet', '--causal-output', out]) == 2
    assert f'error: --causal-output: {out} is the output bag itself' in capsys.readouterr().err
    os.mkdir(causal)
    assert main(['replay', bag, '-o', out, '--quiet', '--causal-output', causal]) == 2
    assert f'error: output {causal} exists already' in capsys.readouterr().err
    assert not os.path.exists(out)
    with pytest.raises(ValueError, match='without smoothing'):
        replay(bag, out, load_robot(), ReplayOptions(smooth=False, causal_out=causal))
