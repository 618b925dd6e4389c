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

"""Tests of ``reduced-dynamics simulate``: bag contents, ground truth, noise, errors."""

import dataclasses
import json
from pathlib import Path
import shlex
import tracemalloc
from typing import Any

from mcap.reader import make_reader
import numpy as np
import pinocchio as pin
import pytest
from rosbags.rosbag2 import Reader as RosbagsReader
from rosbags.typesys import get_typestore, Stores
from scipy.integrate import simpson
import yaml

from conftest_robots import paper_robot, planar_robot
from reduced_dynamics.bag import open_bag
from reduced_dynamics.cli import main
from reduced_dynamics.estimator.config import EstimatorConfig
from reduced_dynamics.estimator.plausibility import JointBounds
from reduced_dynamics.full_dynamics import FullDynamics
from reduced_dynamics.simulator import (
    initial_state,
    make_excitation,
    SimulationOptions,
    simulate_bag,
    STATUS_MSGTYPE,
    ThrusterPulse,
)

REPO_ROOT = Path(__file__).resolve().parent.parent
DATA = REPO_ROOT / 'test' / 'data'
SCRIPT = REPO_ROOT / 'scripts' / 'make_test_bags.sh'
SHIPPED = ('paper_thruster', 'planar_pose_only', 'paper_constant')
#: Bags with realistic sensors (jitter, latency, bunching: stamps off the grid); see
#: test_simulated_sensors.py for their contents.
REALISTIC = ('paper_realistic', 'freeflyer_realistic', 'paper_spacecraft', 'freeflyer_testbed')
TRUE_POSE = '/ground_truth/base_pose'


# --------------------------------------------------------------------------- helpers
def wrench6(msg: Any) -> np.ndarray:
    """Return (force, torque) of a WrenchStamped."""
    w = msg.wrench
    return np.array([w.force.x, w.force.y, w.force.z, w.torque.x, w.torque.y, w.torque.z])


def read_topic(path: Path, topic: str) -> tuple[np.ndarray, list]:
    """Return (log times in s from the first sample, messages) of one topic."""
    with open_bag(path) as bag:
        start = bag.start_ns
        items = [(m.timestamp_ns, m.msg) for m in bag.messages([topic])]
    return np.array([(t - start) * 1e-9 for t, _ in items]), [msg for _, msg in items]


def pose_of(msg: Any) -> pin.SE3:
    """Return the base pose of an Odometry or PoseStamped."""
    pose = msg.pose.pose if hasattr(msg, 'child_frame_id') else msg.pose
    q = pose.orientation
    quat = pin.Quaternion(q.w, q.x, q.y, q.z)
    return pin.SE3(quat.toRotationMatrix(), np.array([pose.position.x, pose.position.y,
                                                      pose.position.z]))


def flatten(value: Any) -> list:
    """Return every leaf of a rosbags message, depth first."""
    if dataclasses.is_dataclass(value):
        return [leaf for f in dataclasses.fields(value) if not f.name.startswith('__')
                for leaf in flatten(getattr(value, f.name))]
    if isinstance(value, np.ndarray):
        return value.ravel().tolist()
    if isinstance(value, (list, tuple)):
        return [leaf for item in value for leaf in flatten(item)]
    return [value]


def script_commands() -> dict[str, list[str]]:
    """Return the ``simulate`` argument lists of scripts/make_test_bags.sh by bag name."""
    commands = {}
    for line in SCRIPT.read_text().splitlines():
        if line.startswith('simulate '):
            argv = shlex.split(line)[1:]
            name = Path(argv[argv.index('-o') + 1]).name
            commands[name] = argv
    return commands


def summary_of(name: str) -> dict:
    """Return the shipped JSON summary of bag ``name``."""
    return json.loads((DATA / f'{name}.summary.json').read_text())


# --------------------------------------------------------------------------- shipped bags
@pytest.mark.parametrize('name', SHIPPED)
def test_shipped_bag_reads_back(name: str) -> None:
    path = DATA / name
    summary = summary_of(name)
    types = summary['topic_types']
    counts = summary['message_counts']
    metadata = yaml.safe_load((path / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    assert metadata['storage_identifier'] == 'mcap'
    assert {t['topic_metadata']['name']: t['message_count']
            for t in metadata['topics_with_message_count']} == counts
    # rosbags' own reader.
    with RosbagsReader(path) as reader:
        assert {c.topic: c.msgtype for c in reader.connections} == types
        assert reader.message_count == sum(counts.values())
    # The mcap reference reader, validating chunk and data CRCs.
    with open(path / f'{name}.mcap', 'rb') as stream:
        mcap_counts: dict[str, int] = {}
        for schema, channel, message in make_reader(stream, validate_crcs=True).iter_messages():
            assert schema.encoding == 'ros2msg' and channel.message_encoding == 'cdr'
            assert schema.name == types[channel.topic]
            assert message.log_time == message.publish_time
            mcap_counts[channel.topic] = mcap_counts.get(channel.topic, 0) + 1
    assert mcap_counts == counts
    # Stamps: header stamp = log time, on the sample grid, strictly increasing per topic.
    period_ns = round(1e9 / summary['rate'])
    with open_bag(path) as bag:
        assert bag.start_ns == summary['start_time_ns']
        assert bag.duration == pytest.approx(summary['duration'])
        for topic in types:
            stamps = []
            for message in bag.messages([topic]):
                header = message.msg.header
                assert header.stamp.sec * 10**9 + header.stamp.nanosec == message.timestamp_ns
                stamps.append(message.timestamp_ns - summary['start_time_ns'])
            assert np.all(np.diff(stamps) > 0)
            assert all(s % period_ns == 0 for s in stamps)
        assert not bag.skipped
    assert counts['/ground_truth/momentum'] == summary['samples']


def test_shipped_paper_bag_fields() -> None:
    summary = summary_of('paper_thruster')
    robot = paper_robot()
    _, joints = read_topic(DATA / 'paper_thruster', '/joint_states')
    assert all(tuple(m.name) == robot.shape_joint_names and m.header.frame_id == ''
               for m in joints)
    assert all(len(m.position) == len(m.velocity) == len(m.effort) == robot.m for m in joints)
    _, odom = read_topic(DATA / 'paper_thruster', '/odom')
    assert {(m.header.frame_id, m.child_frame_id) for m in odom} == {('world', 'spacecraft')}
    _, momenta = read_topic(DATA / 'paper_thruster', '/ground_truth/momentum')
    assert {m.header.frame_id for m in momenta} == {'world'}
    assert wrench6(momenta[0]) == pytest.approx(summary['initial_momentum'], rel=1e-12)
    assert wrench6(momenta[-1]) == pytest.approx(summary['final_momentum'], rel=1e-12)


def test_custom_status_topic_is_self_described() -> None:
    path = DATA / 'planar_pose_only'
    assert STATUS_MSGTYPE not in get_typestore(Stores.ROS2_JAZZY).types
    times, status = read_topic(path, '/simulator/status')  # type from the bag's definition
    assert len(status) == 31 and np.allclose(np.diff(times), 0.1)
    assert {m.torque_mode for m in status} == {'pd'}
    assert all(m.kinetic_energy > 0.0 and len(m.base_wrench) == 6 for m in status)
    assert not any(m.thruster_active for m in status)


@pytest.mark.parametrize('name', SHIPPED + REALISTIC)
def test_shipped_bags_are_reproducible(name: str, tmp_path: Path,
                                       monkeypatch: pytest.MonkeyPatch) -> None:
    argv = [a.replace('$OUT', str(tmp_path)) for a in script_commands()[name]]
    monkeypatch.chdir(REPO_ROOT)  # the script's URDF paths are relative to the root
    assert main(['simulate'] + argv) == 0
    fresh, shipped = summary_of(name), json.loads((tmp_path / f'{name}.summary.json').read_text())
    for key in ('bag', 'initial_momentum', 'final_momentum', 'pulses', 'firings'):
        fresh.pop(key), shipped.pop(key)
    # The shipped bags predate the ground-truth pose; a fresh run writes it every sample.
    assert shipped['message_counts'].pop(TRUE_POSE) == shipped['samples']
    assert shipped['topic_types'].pop(TRUE_POSE) == 'geometry_msgs/msg/PoseStamped'
    assert fresh == shipped
    with open_bag(DATA / name) as old, open_bag(tmp_path / name) as new:
        topics = sorted(old.topics())
        assert sorted(set(new.topics()) - {TRUE_POSE}) == topics
        pairs = zip(old.messages(topics), new.messages(topics), strict=True)
        for (topic_a, _, t_a, msg_a), (topic_b, _, t_b, msg_b) in pairs:
            assert (topic_a, t_a) == (topic_b, t_b)
            leaves_a, leaves_b = flatten(msg_a), flatten(msg_b)
            assert len(leaves_a) == len(leaves_b)
            for a, b in zip(leaves_a, leaves_b):
                if isinstance(a, float):
                    # Allow for floating-point differences between platforms.
                    assert b == pytest.approx(a, rel=1e-7, abs=1e-9)
                else:
                    assert a == b


# --------------------------------------------------------------------------- ground truth
def test_momentum_constant_without_thrusters(tmp_path: Path) -> None:
    options = SimulationOptions(duration=3.0, rate=50.0, seed=4, torque='sinusoid')
    simulate_bag(paper_robot(), tmp_path / 'bag', options)
    _, momenta = read_topic(tmp_path / 'bag', '/ground_truth/momentum')
    _, external = read_topic(tmp_path / 'bag', '/ground_truth/external_wrench')
    mu = np.array([wrench6(m) for m in momenta])
    assert np.max(np.linalg.norm(mu - mu[0], axis=1)) <= 1e-10 * np.linalg.norm(mu[0])
    assert not np.any([wrench6(m) for m in external])


def test_thruster_jump_equals_impulse() -> None:
    path = DATA / 'paper_thruster'
    summary = summary_of('paper_thruster')
    pulse = summary['pulses'][0]
    start, end = pulse['start'], pulse['start'] + pulse['duration']
    times, momenta = read_topic(path, '/ground_truth/momentum')
    _, external = read_topic(path, '/ground_truth/external_wrench')
    _, odom = read_topic(path, '/odom')
    mu = np.array([wrench6(m) for m in momenta])
    wrench = np.array([wrench6(m) for m in external])
    before, after = times < start - 1e-9, times >= end - 1e-9
    on = ~before & ~after
    scale = np.linalg.norm(mu[0])
    assert np.max(np.linalg.norm(mu[before] - mu[0], axis=1)) <= 1e-10 * scale
    assert np.max(np.linalg.norm(mu[after] - mu[-1], axis=1)) <= 1e-10 * scale
    assert not np.any(wrench[before | after])
    jump = mu[-1] - mu[0]
    # The world wrench, independently: the base-frame wrench moved to the world origin.
    body = pin.Force(np.array(pulse['body_wrench']))
    for index in np.flatnonzero(on):
        assert wrench[index] == pytest.approx(pose_of(odom[index]).act(body).vector, abs=1e-9)
    # Integral of the sampled wrench: Simpson on the open pulse, plus its left limit at
    # the end time (the sample at the end already reads zero) by extrapolation.
    t_on, w_on = times[on], wrench[on]
    tail = np.array([np.polyval(np.polyfit(t_on[-5:], w_on[-5:, j], 4), end) for j in range(6)])
    integral = simpson(np.vstack([w_on, tail]), x=np.r_[t_on, end], axis=0)
    assert np.linalg.norm(integral - jump) <= 1e-6 * np.linalg.norm(jump)
    assert np.linalg.norm(np.array(pulse['world_impulse']) - jump) <= 1e-9 * np.linalg.norm(jump)


def test_constant_torques_are_held() -> None:
    path = DATA / 'paper_constant'
    times, joints = read_topic(path, '/joint_states')
    effort = np.array([m.effort for m in joints])
    hold = np.searchsorted([0.5, 1.5, 2.5], times + 1e-9, side='right')
    for index in range(4):
        block = effort[hold == index]
        assert np.all(block == block[0])
        if index:
            assert block[0] == pytest.approx(-effort[hold == index - 1][0])
    _, momenta = read_topic(path, '/ground_truth/momentum')
    mu = np.array([wrench6(m) for m in momenta])
    assert np.max(np.linalg.norm(mu - mu[0], axis=1)) <= 1e-10 * np.linalg.norm(mu[0])
    assert np.linalg.norm(mu[0, :3]) <= 1e-12 * np.linalg.norm(mu[0])  # pure angular


def test_matches_direct_full_dynamics(tmp_path: Path) -> None:
    robot = paper_robot()
    options = SimulationOptions(duration=1.0, rate=50.0, seed=5, torque='pd')
    simulate_bag(robot, tmp_path / 'bag', options)
    state, scenario_torque = initial_state(robot, 'generic', 5)
    law = make_excitation(robot, state, scenario_torque, options).law(0.5)
    times = np.arange(51) / 50.0
    full = FullDynamics(robot, law).simulate(state, times, 1e-12, 1e-12)
    _, joints = read_topic(tmp_path / 'bag', '/joint_states')
    _, odom = read_topic(tmp_path / 'bag', '/odom')
    assert np.array([m.position for m in joints]) == pytest.approx(full.qbar, abs=1e-9)
    assert np.array([m.velocity for m in joints]) == pytest.approx(full.qbar_dot, abs=1e-9)
    effort = [law(t, q, qd) for t, q, qd in zip(times, full.qbar, full.qbar_dot)]
    assert np.array([m.effort for m in joints]) == pytest.approx(np.array(effort), abs=1e-8)
    for index, msg in enumerate(odom):
        assert np.allclose(pose_of(msg).homogeneous, full.poses[index], atol=1e-9)
        twist = msg.twist.twist
        assert [twist.linear.x, twist.linear.y, twist.linear.z, twist.angular.x,
                twist.angular.y, twist.angular.z] == pytest.approx(full.xi[index], abs=1e-9)


def test_planar_odometry_is_embedded_in_3d(tmp_path: Path) -> None:
    options = SimulationOptions(duration=0.5, rate=20.0, seed=6, torque='sinusoid',
                                thrusters=(ThrusterPulse(0.1, 0.2, (1, 2, 3, 4, 5, 6)),))
    summary = simulate_bag(planar_robot(), tmp_path / 'bag', options)
    _, odom = read_topic(tmp_path / 'bag', '/odom')
    for msg in odom:
        pose, twist = msg.pose.pose, msg.twist.twist
        assert pose.position.z == 0.0 and pose.orientation.x == pose.orientation.y == 0.0
        assert twist.linear.z == twist.angular.x == twist.angular.y == 0.0
    # Only the in-plane part (fx, fy, tz) of the pulse acts on an SE(2) base.
    impulse = summary.pulses[0].world_impulse
    assert impulse[2] == impulse[3] == impulse[4] == 0.0 and np.linalg.norm(impulse) > 0.0
    _, momenta = read_topic(tmp_path / 'bag', '/ground_truth/momentum')
    jump = wrench6(momenta[-1]) - wrench6(momenta[0])
    assert np.linalg.norm(jump - impulse) <= 1e-9 * np.linalg.norm(impulse)


def test_memory_stays_flat(tmp_path: Path) -> None:
    robot = paper_robot()
    simulate_bag(robot, tmp_path / 'warm', SimulationOptions(duration=0.1, rate=20.0))
    peaks = []
    for duration in (4.0, 8.0):
        tracemalloc.start()
        # PD torques: the default sinusoid leaves j5's URDF limits at 3.9 s (a stop).
        simulate_bag(robot, tmp_path / f'bag{duration:g}',
                     SimulationOptions(duration=duration, torque='pd'))
        peaks.append(tracemalloc.get_traced_memory()[1])
        tracemalloc.stop()
    # Twice the messages (about 1.3 MB more) but the same peak: only a chunk is held.
    assert peaks[1] < peaks[0] + 300_000


# --------------------------------------------------------------------------- noise, drops
def test_noise_and_drops_have_requested_statistics(tmp_path: Path) -> None:
    robot = paper_robot()
    base = dict(duration=2.0, rate=200.0, seed=7, torque='sinusoid')
    simulate_bag(robot, tmp_path / 'clean', SimulationOptions(**base))
    noisy = SimulationOptions(**base, noise_position=0.01, noise_velocity=0.02, noise_pose=0.005,
                              drop_rate=0.3)
    summary = simulate_bag(robot, tmp_path / 'noisy', noisy)
    counts = summary.message_counts
    assert counts['/ground_truth/momentum'] == counts['/ground_truth/external_wrench'] == 401
    for topic in ('/joint_states', '/odom'):
        assert abs(counts[topic] / 401 - 0.7) < 0.06
    clean_t, clean_j = read_topic(tmp_path / 'clean', '/joint_states')
    noisy_t, noisy_j = read_topic(tmp_path / 'noisy', '/joint_states')
    _, noisy_o = read_topic(tmp_path / 'noisy', '/odom')
    index = np.searchsorted(clean_t, noisy_t)
    assert np.allclose(clean_t[index], noisy_t)
    # Drops are independent per topic: the two topics keep different samples.
    odom_t, _ = read_topic(tmp_path / 'noisy', '/odom')
    assert not np.array_equal(noisy_t, odom_t)
    dq = np.array([n.position for n in noisy_j]) - np.array([clean_j[i].position for i in index])
    dv = np.array([n.velocity for n in noisy_j]) - np.array([clean_j[i].velocity for i in index])
    assert np.std(dq) == pytest.approx(0.01, rel=0.1) and abs(np.mean(dq)) < 0.002
    assert np.std(dv) == pytest.approx(0.02, rel=0.1)
    assert np.all(np.array([n.effort for n in noisy_j])
                  == np.array([clean_j[i].effort for i in index]))
    _, clean_o = read_topic(tmp_path / 'clean', '/odom')
    index = np.searchsorted(clean_t, odom_t)
    errors, twist_errors = [], []
    for msg, i in zip(noisy_o, index):
        error = pose_of(clean_o[i]).inverse() * pose_of(msg)
        errors.append(np.r_[pose_of(msg).translation - pose_of(clean_o[i]).translation,
                            pin.log3(error.rotation)])
        a, b = msg.twist.twist, clean_o[i].twist.twist
        twist_errors.append([a.linear.x - b.linear.x, a.angular.z - b.angular.z])
    assert np.std(np.array(errors)) == pytest.approx(0.005, rel=0.1)
    assert np.std(np.array(twist_errors)) == pytest.approx(0.02, rel=0.15)
    covariance = np.array(noisy_o[0].pose.covariance).reshape(6, 6)
    assert np.allclose(covariance, 0.005 ** 2 * np.eye(6))


# --------------------------------------------------------------------------- errors
def test_refuses_to_overwrite(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    out = tmp_path / 'bag'
    options = SimulationOptions(duration=0.1, rate=20.0)
    simulate_bag(paper_robot(), out, options)
    before = (out / 'bag.mcap').read_bytes()
    with pytest.raises(ValueError, match='exists already'):
        simulate_bag(paper_robot(), out, options)
    assert main(['simulate', '-o', str(out), '--duration', '0.1']) == 2
    assert '--overwrite' in capsys.readouterr().err
    assert (out / 'bag.mcap').read_bytes() == before
    summary = tmp_path / 'summary.json'
    assert main(['simulate', '-o', str(out), '--duration', '0.1', '--rate', '20',
                 '--overwrite', '--summary', str(summary)]) == 0
    assert 'Simulated paper_robot' in capsys.readouterr().out
    assert json.loads(summary.read_text())['samples'] == 3
    foreign = tmp_path / 'notes'
    foreign.mkdir()
    (foreign / 'keep.txt').write_text('x')
    with pytest.raises(ValueError, match='refusing to overwrite'):
        simulate_bag(paper_robot(), foreign, dataclasses.replace(options, overwrite=True))
    assert (foreign / 'keep.txt').exists()


@pytest.mark.parametrize('spec', ['1,2,3', '1,0.5,a,0,0,0,0,0', '1,-0.5,0,0,0,0,0,0',
                                  '-1,0.5,0,0,0,0,0,0', '1,0.5,0,0,0,0,0,0,0',
                                  'nan,1,0,0,0,0,0,0'])
def test_malformed_thruster_specs(spec: str, capsys: pytest.CaptureFixture) -> None:
    with pytest.raises(ValueError):
        ThrusterPulse.parse(spec)
    with pytest.raises(SystemExit) as exit_info:
        main(['simulate', '-o', 'unused', '--thruster', spec])
    assert exit_info.value.code == 2
    assert 'argument --thruster' in capsys.readouterr().err


@pytest.mark.parametrize('argv, message', [
    (['--duration', '-1'], 'argument --duration: must be > 0'),
    (['--duration', '0'], 'argument --duration: must be > 0'),
    (['--rate', '0'], 'argument --rate: must be > 0'),
    (['--rate', 'fast'], 'argument --rate: not a number'),
    (['--drop-rate', '1'], 'argument --drop-rate: must be in [0, 1)'),
    (['--noise-pose', '-0.1'], 'argument --noise-pose: must be >= 0'),
    (['--seed', '-3'], 'argument --seed: must be >= 0'),
    (['--torque', 'random'], 'argument --torque: invalid choice'),
])
def test_bad_cli_options(argv: list, message: str, capsys: pytest.CaptureFixture) -> None:
    with pytest.raises(SystemExit) as exit_info:
        main(['simulate', '-o', 'unused'] + argv)
    assert exit_info.value.code == 2
    assert message in capsys.readouterr().err


@pytest.mark.parametrize('fields, message', [
    (dict(duration=-1.0), 'duration'), (dict(rate=0.0), 'rate'),
    (dict(drop_rate=1.0), 'drop_rate'), (dict(torque='random'), 'torque mode'),
    (dict(seed=-1), 'seed'), (dict(momentum_class='spin'), 'momentum class'),
    (dict(noise_velocity=float('nan')), 'noise_velocity'),
    (dict(duration=1.0, thrusters=(ThrusterPulse(2.0, 0.1, (0,) * 6),)), 'after the end'),
])
def test_bad_options(fields: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        SimulationOptions(**fields)


def test_pulse_after_the_end_from_cli(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    assert main(['simulate', '-o', str(tmp_path / 'bag'), '--duration', '1',
                 '--thruster', '2,1,1,0,0,0,0,0']) == 2
    assert 'after the end of the run' in capsys.readouterr().err
    assert not (tmp_path / 'bag').exists()


# --------------------------------------------------------------------------- issue 26 item 6
def test_ground_truth_pose_is_the_true_base_pose(tmp_path: Path) -> None:
    """Every sample carries the true base pose: the noise-free /odom pose, world frame."""
    options = SimulationOptions(duration=1.0, rate=50.0, seed=2, torque='constant',
                                torque_scale=0.05)
    summary = simulate_bag(paper_robot(), tmp_path / 'bag', options)
    assert summary.message_counts[TRUE_POSE] == summary.samples == 51
    assert summary.topic_types[TRUE_POSE] == 'geometry_msgs/msg/PoseStamped'
    times, truth = read_topic(tmp_path / 'bag', TRUE_POSE)
    _, odom = read_topic(tmp_path / 'bag', '/odom')
    assert np.allclose(np.diff(times), 0.02)
    assert {m.header.frame_id for m in truth} == {'world'}
    for a, b in zip(truth, odom, strict=True):
        assert (pose_of(a).inverse() * pose_of(b)).isIdentity(1e-12)
    # With pose noise, /odom moves off the truth and the truth stays put.
    noisy = dataclasses.replace(options, noise_pose=0.01)
    simulate_bag(paper_robot(), tmp_path / 'noisy', noisy)
    _, truth_noisy = read_topic(tmp_path / 'noisy', TRUE_POSE)
    _, odom_noisy = read_topic(tmp_path / 'noisy', '/odom')
    assert all((pose_of(a).inverse() * pose_of(b)).isIdentity(1e-12)
               for a, b in zip(truth, truth_noisy))
    offsets = [np.linalg.norm(pose_of(a).translation - pose_of(b).translation)
               for a, b in zip(truth_noisy, odom_noisy)]
    assert 0.005 < float(np.median(offsets)) < 0.05


def test_leaving_the_joint_limits_stops_with_a_message(
        tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """The issue's seed 3 leaves j4's range: a clear message, no bag replay would reject."""
    argv = ['simulate', '-o', str(tmp_path / 'bag'), '--rate', '100', '--seed', '3',
            '--torque', 'constant', '--torque-scale', '0.05', '--duration', '12']
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert 'a joint left its URDF limits at t = 7.82 s (joint_position_limit: j4 at ' in err
    assert 'outside [-2, 2]' in err
    assert not (tmp_path / 'bag').exists()
    # The same run, stopped before it leaves them, passes replay's gate at every sample.
    assert main(argv[:-1] + ['7', '--overwrite']) == 0
    bounds = JointBounds(paper_robot(), EstimatorConfig())
    _, joints = read_topic(tmp_path / 'bag', '/joint_states')
    assert len(joints) == 701
    assert all(bounds.check(list(m.position), list(m.velocity), list(m.effort)) is None
               for m in joints)
    # Explicitly ignored, the run goes on and replay's gate rejects what left the range.
    assert main(argv + ['--joint-limits', 'ignore', '--overwrite']) == 0
    _, joints = read_topic(tmp_path / 'bag', '/joint_states')
    assert len(joints) == 1201
    assert any(bounds.check(list(m.position), list(m.velocity), list(m.effort)) is not None
               for m in joints)
