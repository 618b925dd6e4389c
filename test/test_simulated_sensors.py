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

"""Realistic simulated sensors: noise, quantisation, stamps, latency, dropouts, thrusters."""

import dataclasses
import functools
import json
from pathlib import Path
from typing import Any

from mcap.reader import make_reader
import numpy as np
import pinocchio as pin
import pytest
from rosbags.rosbag2 import Reader as RosbagsReader

from conftest_robots import paper_robot
from reduced_dynamics.bag import open_bag
from reduced_dynamics.cli import main
from reduced_dynamics.resources import config_path
from reduced_dynamics.robot.model import load_robot
from reduced_dynamics.simulator import SimulationOptions, simulate_bag, ThrusterPulse
from reduced_dynamics.thrusters import (
    FREEFLYER_ARM, LAYOUTS, ThrusterFiring, ThrusterSet)

REPO_ROOT = Path(__file__).resolve().parent.parent
DATA = REPO_ROOT / 'test' / 'data'
START = SimulationOptions().start_time_ns
GROUND_TRUTH = ('/ground_truth/momentum', '/ground_truth/external_wrench')


@functools.lru_cache(maxsize=None)
def freeflyer():
    """Return the planar one-body free-flyer (16 kg, 0.18 kg m^2)."""
    return load_robot(config_path('robots/freeflyer.urdf'))


def read(path: Path, topic: str) -> list[tuple[int, Any]]:
    """Return (log time ns, message) of one topic with the project's reader."""
    with open_bag(path) as bag:
        return [(m.timestamp_ns, m.msg) for m in bag.messages([topic])]


def stamp_ns(msg: Any) -> int:
    """Return a message's header stamp in ns."""
    return msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec


def wrench6(msg: Any) -> np.ndarray:
    """Return (force, torque) of a WrenchStamped."""
    w = msg.wrench
    return np.array([w.force.x, w.force.y, w.force.z, w.torque.x, w.torque.y, w.torque.z])


def pose_of(msg: Any) -> pin.SE3:
    """Return the base pose of an Odometry or PoseStamped."""
    pose = msg.pose.pose if hasattr(msg, 'child_frame_id') else msg.pose
    q = pose.orientation
    quat = pin.Quaternion(q.w, q.x, q.y, q.z)
    return pin.SE3(quat.normalized().toRotationMatrix(),
                   np.array([pose.position.x, pose.position.y, pose.position.z]))


def simulate(tmp_path: Path, name: str, robot: Any = None, **fields: Any) -> Any:
    """Simulate into tmp_path/name and return the summary."""
    return simulate_bag(robot or freeflyer(), tmp_path / name, SimulationOptions(**fields))


def nominal_index(stamp: int, rate: float) -> np.ndarray:
    """Return the sample index k of a header stamp on the nominal grid."""
    return np.rint((np.asarray(stamp) - START) * rate / 1e9).astype(int)


# --------------------------------------------------------------------------- shipped bags
@pytest.mark.parametrize('name', ['paper_realistic', 'freeflyer_realistic', 'paper_spacecraft',
                                  'freeflyer_testbed'])
def test_shipped_realistic_bags_read_back(name: str) -> None:
    path = DATA / name
    summary = json.loads((DATA / f'{name}.summary.json').read_text())
    counts = summary['message_counts']
    assert (path / f'{name}.mcap').stat().st_size < 1_000_000
    with RosbagsReader(path) as reader:
        assert reader.message_count == sum(counts.values())
    with open(path / f'{name}.mcap', 'rb') as stream:
        log_times = [m.log_time for _, _, m in
                     make_reader(stream, validate_crcs=True).iter_messages()]
    # Written in record-time order, whatever the latency did.
    assert len(log_times) == sum(counts.values()) and np.all(np.diff(log_times) >= 0)
    with open_bag(path) as bag:
        read_counts: dict[str, int] = {}
        for message in bag.messages(list(counts)):
            read_counts[message.topic] = read_counts.get(message.topic, 0) + 1
        assert read_counts == counts
        assert not bag.skipped
    for topic, stats in summary['sensors'].items():
        assert stats['written'] == counts[topic]
        assert stats['written'] + stats['dropped_random'] + stats['dropped_outage'] \
            == summary['samples']


def test_shipped_paper_realistic_has_jitter_latency_and_a_pulse() -> None:
    summary = json.loads((DATA / 'paper_realistic.summary.json').read_text())
    odom = read(DATA / 'paper_realistic', '/odom')
    stamps = np.array([stamp_ns(m) for _, m in odom])
    records = np.array([t for t, _ in odom])
    nominal = START + np.rint(nominal_index(stamps, 100.0) * 1e7).astype(np.int64)
    assert np.std(stamps - nominal) * 1e-9 == pytest.approx(3e-4, rel=0.15)
    assert np.mean(records - nominal) * 1e-9 == pytest.approx(4e-3, abs=3e-4)
    assert len(summary['pulses']) == 1 and summary['sensors']['/odom']['dropped_random'] > 0
    joints = read(DATA / 'paper_realistic', '/joint_states')
    position = np.array([m.position for _, m in joints])
    assert np.allclose(position / 1e-5, np.rint(position / 1e-5), atol=1e-6)


def test_shipped_freeflyer_realistic_has_bunches_and_commands() -> None:
    summary = json.loads((DATA / 'freeflyer_realistic.summary.json').read_text())
    poses = read(DATA / 'freeflyer_realistic', '/base_pose')
    gaps = np.diff([stamp_ns(m) for _, m in poses]) * 1e-9
    stats = summary['sensors']['/base_pose']
    assert stats['bunched'] >= 10
    assert np.count_nonzero(gaps < 1e-4) == stats['bunched']
    assert np.all(gaps[gaps < 1e-4] >= 0.0)
    commands = read(DATA / 'freeflyer_realistic', '/commanded_wrench')
    assert len(commands) == summary['message_counts']['/commanded_wrench']
    assert {m.header.frame_id for _, m in commands} == {'robot'}
    assert len(summary['firings']) == 4


@pytest.mark.parametrize('name, argv', [
    ('paper_realistic', []),
    ('freeflyer_realistic', ['--urdf', 'config/robots/freeflyer.urdf', '--base-joint', 'planar',
                             '--base-pose-topic', '/base_pose']),
])
def test_replay_reads_realistic_bags(name: str, argv: list, tmp_path: Path,
                                     monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(REPO_ROOT)
    code = main(['replay', str(DATA / name), '-o', str(tmp_path / 'out'),
                 '--summary-json', str(tmp_path / 's.json')] + argv)
    assert code in (0, 3)
    written = json.loads((tmp_path / 's.json').read_text())
    counts = json.loads((DATA / f'{name}.summary.json').read_text())['message_counts']
    base = '/base_pose' if name.startswith('freeflyer') else '/odom'
    assert written['messages_in'][base] == counts[base]


# --------------------------------------------------------------------------- noise
def test_noise_per_field_and_ground_truth_unchanged(tmp_path: Path) -> None:
    robot = paper_robot()
    base = dict(duration=2.0, rate=200.0, seed=8, torque='sinusoid',
                thrusters=(ThrusterPulse(0.5, 0.3, (5, 0, 0, 0, 1, 0)),))
    simulate(tmp_path, 'clean', robot, **base)
    noisy = dict(noise_position=0.01, noise_velocity=0.02, noise_effort=0.3, noise_pose=0.004,
                 noise_orientation=0.002, noise_twist=0.05,
                 quantize=(('joint_velocity', 1e-3),),
                 stamp_jitter=1e-4, latency=2e-3, latency_jitter=5e-4)
    simulate(tmp_path, 'noisy', robot, **base, **noisy)
    # Sensor options never touch the ground truth (same messages, same times).
    for topic in GROUND_TRUTH:
        clean, other = read(tmp_path / 'clean', topic), read(tmp_path / 'noisy', topic)
        assert [t for t, _ in clean] == [t for t, _ in other]
        assert np.array_equal([wrench6(m) for _, m in clean], [wrench6(m) for _, m in other])
    clean_j = [m for _, m in read(tmp_path / 'clean', '/joint_states')]
    noisy_j = [m for _, m in read(tmp_path / 'noisy', '/joint_states')]
    assert len(clean_j) == len(noisy_j) == 401
    dq = np.array([n.position for n in noisy_j]) - np.array([c.position for c in clean_j])
    de = np.array([n.effort for n in noisy_j]) - np.array([c.effort for c in clean_j])
    assert np.std(dq) == pytest.approx(0.01, rel=0.1)
    assert np.std(de) == pytest.approx(0.3, rel=0.1) and abs(np.mean(de)) < 0.05
    clean_o = [m for _, m in read(tmp_path / 'clean', '/odom')]
    noisy_o = [m for _, m in read(tmp_path / 'noisy', '/odom')]
    position, rotation, linear, angular = [], [], [], []
    for a, b in zip(noisy_o, clean_o):
        position.append(pose_of(a).translation - pose_of(b).translation)
        rotation.append(pin.log3(pose_of(b).rotation.T @ pose_of(a).rotation))
        ta, tb = a.twist.twist, b.twist.twist
        linear.append([ta.linear.x - tb.linear.x, ta.linear.y - tb.linear.y])
        angular.append([ta.angular.x - tb.angular.x, ta.angular.z - tb.angular.z])
    assert np.std(position) == pytest.approx(0.004, rel=0.1)
    assert np.std(rotation) == pytest.approx(0.002, rel=0.1)
    assert np.std(linear) == pytest.approx(0.05, rel=0.1)
    assert np.std(angular) == pytest.approx(0.05, rel=0.1)
    covariance = np.array(noisy_o[0].pose.covariance).reshape(6, 6)
    assert np.allclose(np.diag(covariance), [0.004 ** 2] * 3 + [0.002 ** 2] * 3)
    velocity = np.array([n.velocity for n in noisy_j])
    assert np.allclose(velocity / 1e-3, np.rint(velocity / 1e-3), rtol=0, atol=1e-9)


def test_angular_twist_noise_of_its_own(tmp_path: Path) -> None:
    """--noise-twist-angular: a gyro's figure on the angular velocity, the linear one kept."""
    robot = paper_robot()
    base = dict(duration=2.0, rate=200.0, seed=8, torque='sinusoid')
    simulate(tmp_path, 'clean', robot, **base)
    simulate(tmp_path, 'gyro', robot, **base, noise_twist=0.05, noise_twist_angular=0.002)
    linear, angular = [], []
    for (_, a), (_, b) in zip(read(tmp_path / 'gyro', '/odom'), read(tmp_path / 'clean', '/odom')):
        ta, tb = a.twist.twist, b.twist.twist
        linear.append([ta.linear.x - tb.linear.x, ta.linear.z - tb.linear.z])
        angular.append([ta.angular.x - tb.angular.x, ta.angular.z - tb.angular.z])
    assert np.std(linear) == pytest.approx(0.05, rel=0.1)
    assert np.std(angular) == pytest.approx(0.002, rel=0.1)
    covariance = np.array(a.twist.covariance).reshape(6, 6)
    assert np.allclose(np.diag(covariance), [0.05 ** 2] * 3 + [0.002 ** 2] * 3)


@pytest.mark.parametrize('field, step', [('joint_position', 0.01), ('joint_effort', 0.5),
                                         ('base_position', 0.002),
                                         ('base_orientation', 1e-3),
                                         ('base_linear_velocity', 0.01),
                                         ('base_angular_velocity', 0.004)])
def test_quantisation_step(field: str, step: float, tmp_path: Path) -> None:
    robot = paper_robot()
    base = dict(duration=0.5, rate=100.0, seed=9, torque='sinusoid')
    simulate(tmp_path, 'clean', robot, **base)
    simulate(tmp_path, 'q', robot, **base, quantize=((field, step),))

    def values(name: str) -> np.ndarray:
        if field.startswith('joint'):
            attribute = field.split('_')[1]
            joints = read(tmp_path / name, '/joint_states')
            return np.array([getattr(m, attribute) for _, m in joints])
        rows = []
        for _, m in read(tmp_path / name, '/odom'):
            p, q, t = m.pose.pose.position, m.pose.pose.orientation, m.twist.twist
            rows.append({'base_position': [p.x, p.y, p.z],
                         'base_orientation': [q.x, q.y, q.z, q.w],
                         'base_linear_velocity': [t.linear.x, t.linear.y, t.linear.z],
                         'base_angular_velocity': [t.angular.x, t.angular.y, t.angular.z]
                         }[field])
        return np.array(rows)
    clean, quantised = values('clean'), values('q')
    ratio = quantised / step
    assert np.allclose(ratio, np.rint(ratio), rtol=0, atol=1e-6)
    error = quantised - clean
    assert np.max(np.abs(error)) <= 0.5 * step * (1 + 1e-9)
    assert np.max(np.abs(error)) > 0.3 * step  # it did round something


# --------------------------------------------------------------------------- stamps
def test_stamp_jitter_distribution(tmp_path: Path) -> None:
    simulate(tmp_path, 'bag', duration=10.0, rate=200.0, seed=3, torque='zero',
             base_pose_only=True, stamp_jitter=5e-4)
    poses = read(tmp_path / 'bag', '/base_pose')
    stamps = np.array([stamp_ns(m) for _, m in poses])
    records = np.array([t for t, _ in poses])
    errors = (stamps - records) * 1e-9  # no latency: the record time is the sample time
    assert len(errors) == 2001 and np.all(records == START + np.arange(2001) * 5_000_000)
    assert np.std(errors) == pytest.approx(5e-4, rel=0.05)
    assert abs(np.mean(errors)) < 4 * 5e-4 / np.sqrt(2001)
    # Gaussian: 68 % within one sigma, 95 % within two.
    assert np.mean(np.abs(errors) < 5e-4) == pytest.approx(0.683, abs=0.03)
    assert np.mean(np.abs(errors) < 1e-3) == pytest.approx(0.954, abs=0.015)


def test_bunched_stamps_come_in_pairs(tmp_path: Path) -> None:
    summary = simulate(tmp_path, 'bag', duration=20.0, rate=120.0, seed=4, torque='zero',
                       base_pose_only=True, bunch_fraction=0.02, bunch_gap=3e-5)
    poses = read(tmp_path / 'bag', '/base_pose')
    stamps = np.array([stamp_ns(m) for _, m in poses])
    records = np.array([t for t, _ in poses])
    gaps = np.diff(stamps) * 1e-9
    bunched = np.flatnonzero(gaps < 1e-4)
    count = summary.sensors['/base_pose'].bunched
    assert len(bunched) == count
    # About 2 % of the samples (binomial: 2401 * 0.02 = 48 +- 7), never two in a row.
    assert 30 <= count <= 70 and np.all(np.diff(bunched) > 1)
    assert np.all((gaps[bunched] >= 1.5e-5 - 1e-9) & (gaps[bunched] <= 4.5e-5 + 1e-9))
    # A bunched message keeps its contents (sampled at its own instant), only its stamp moved.
    simulate(tmp_path, 'clean', duration=20.0, rate=120.0, seed=4, torque='zero',
             base_pose_only=True)
    clean = read(tmp_path / 'clean', '/base_pose')
    for index in bunched:
        assert stamps[index] == stamps[index + 1] - round(gaps[index] * 1e9)
        assert records[index] == stamp_ns(clean[index][1])
        assert pose_of(poses[index][1]).isApprox(pose_of(clean[index][1]))
    others = np.setdiff1d(np.arange(len(stamps)), bunched)
    assert np.all(stamps[others] == records[others])


def test_latency_distribution_and_record_order(tmp_path: Path) -> None:
    simulate(tmp_path, 'bag', duration=10.0, rate=200.0, seed=5, torque='zero',
             base_pose_only=True, latency=0.01, latency_jitter=0.004)
    poses = read(tmp_path / 'bag', '/base_pose')
    stamps = np.array([stamp_ns(m) for _, m in poses])
    records = np.array([t for t, _ in poses])
    delay = (records - stamps) * 1e-9  # no stamp jitter: the stamp is the sample time
    assert np.all(np.sort(stamps) == START + np.arange(2001) * 5_000_000)
    assert np.all(delay >= 0.0)
    assert np.mean(delay) == pytest.approx(0.01, abs=3e-4)
    assert np.std(delay) == pytest.approx(0.004, rel=0.06)
    # Records are in order in the file although delays reorder some messages: the reader
    # returns them in log-time order, so their stamps are not monotonic.
    assert np.all(np.diff(records) >= 0) and np.any(np.diff(stamps) < 0)
    truth = read(tmp_path / 'bag', '/ground_truth/momentum')
    assert [t for t, _ in truth] == [stamp_ns(m) for _, m in truth]


# --------------------------------------------------------------------------- dropouts
def test_random_drops_and_outages_are_counted(tmp_path: Path) -> None:
    rate = 100.0
    summary = simulate(tmp_path, 'bag', paper_robot(), duration=10.0, rate=rate, seed=6,
                       torque='zero', drop_rate=0.05, outage_rate=0.5, outage_duration=0.1)
    samples = summary.samples
    for topic in ('/joint_states', '/odom'):
        stats = summary.sensors[topic]
        messages = read(tmp_path / 'bag', topic)
        assert len(messages) == stats.written == summary.message_counts[topic]
        assert stats.written + stats.dropped_random + stats.dropped_outage == samples
        kept = set(nominal_index([stamp_ns(m) for _, m in messages], rate).tolist())
        in_outage = {k for k in range(samples)
                     if any(a <= k / rate < b for a, b in stats.outages)}
        # Every sample inside an outage is lost; the others are lost at random.
        assert not kept & in_outage and len(in_outage) == stats.dropped_outage
        assert 2 <= len(stats.outages) <= 12  # Poisson(5)
        random_lost = samples - len(kept) - len(in_outage)
        assert random_lost == stats.dropped_random
        # Binomial(samples outside outages, 0.05): within 4 sigma.
        trials = samples - len(in_outage)
        assert abs(random_lost - 0.05 * trials) <= 4 * np.sqrt(trials * 0.05 * 0.95)
    lengths = [b - a for a, b in summary.sensors['/odom'].outages]
    assert 0.01 < np.mean(lengths) < 0.4
    # The two topics lose different messages (independent streams).
    assert summary.sensors['/odom'].outages != summary.sensors['/joint_states'].outages


def test_timing_options_are_reproducible_and_independent(tmp_path: Path) -> None:
    fields = dict(duration=2.0, rate=120.0, seed=11, torque='zero', base_pose_only=True,
                  noise_pose=1e-3)
    simulate(tmp_path, 'a', **fields, stamp_jitter=1e-3, latency=0.005)
    simulate(tmp_path, 'b', **fields, stamp_jitter=1e-3, latency=0.005)
    simulate(tmp_path, 'c', **fields, stamp_jitter=1e-3)
    a, b, c = (read(tmp_path / n, '/base_pose') for n in 'abc')
    assert [(t, stamp_ns(m)) for t, m in a] == [(t, stamp_ns(m)) for t, m in b]
    # Adding latency changes record times only: the stamps and the noise stay.
    assert sorted(stamp_ns(m) for _, m in a) == sorted(stamp_ns(m) for _, m in c)
    by_stamp = {stamp_ns(m): pose_of(m).translation for _, m in c}
    assert all(np.array_equal(by_stamp[stamp_ns(m)], pose_of(m).translation) for _, m in a)


# --------------------------------------------------------------------------- thrusters
def test_freeflyer_layout_matches_the_switch_table() -> None:
    units = np.array(LAYOUTS['freeflyer'])
    for bits in range(256):
        s = [(bits >> i) & 1 for i in range(8)]
        expected = [s[2] + s[5] - s[1] - s[6], s[4] + s[7] - s[0] - s[3], 0, 0, 0,
                    FREEFLYER_ARM * (s[1] + s[3] + s[5] + s[7] - s[0] - s[2] - s[4] - s[6])]
        on = [i for i in range(8) if s[i]]
        assert ThrusterSet(units, 0.2).command(on) == pytest.approx(0.2 * np.array(expected))


def test_binary_thrusters_command_and_delivered_wrench(tmp_path: Path) -> None:
    gain, bias = (0.8, 1.1, 1.0, 1.0, 1.0, 0.9), (0.01, -0.02, 0.0, 0.0, 0.0, 0.001)
    firings = (ThrusterFiring(0.5, 0.7, (2, 5)), ThrusterFiring(0.9, 0.5, (4, 7, 5)),
               ThrusterFiring(2.0, 0.25, (1,)))
    summary = simulate(tmp_path, 'bag', duration=3.0, rate=100.0, seed=2, torque='zero',
                       base_pose_only=True, thruster_layout='freeflyer', firings=firings,
                       thrust_gain=gain, thrust_bias=bias, command_rate=4.0)
    thrusters = ThrusterSet(np.array(LAYOUTS['freeflyer']), 0.2, np.array(gain),
                            np.array(bias))
    commands = read(tmp_path / 'bag', '/commanded_wrench')
    times = [(t - START) * 1e-9 for t, _ in commands]
    # The 4 Hz grid (0, 0.25, ..., 3) plus every switch: 13 + {0.9, 1.2, 1.4, 2.25}.
    assert times == pytest.approx(sorted(set(np.arange(13) * 0.25) | {0.9, 1.2, 1.4, 2.25}))
    for t, (_, msg) in zip(times, commands):
        on = {0.5: (2, 5), 0.75: (2, 5), 0.9: (2, 4, 5, 7), 1.0: (2, 4, 5, 7),
              1.2: (4, 5, 7), 1.25: (4, 5, 7), 2.0: (1,)}.get(round(t, 3), ())
        assert wrench6(msg) == pytest.approx(thrusters.command(on), abs=1e-15)
        assert msg.header.frame_id == 'robot' and stamp_ns(msg) == START + round(t * 1e9)
    # Ground truth: the delivered body wrench (gain * command + bias, the bias always on)
    # rotated into the world frame, torque about the origin.
    external = read(tmp_path / 'bag', '/ground_truth/external_wrench')
    poses = read(tmp_path / 'bag', '/base_pose')
    for (t_ns, wrench), (_, pose) in zip(external, poses):
        t = (t_ns - START) * 1e-9
        body = thrusters.delivered(thrusters.command(thrusters.on(firings, t)))
        body[2:5] = 0.0  # only fx, fy, tz act on an SE(2) base
        world = pose_of(pose).act(pin.Force(body)).vector
        assert wrench6(wrench) == pytest.approx(world, abs=1e-9)
    # Firing summaries: the commanded and delivered body wrench of each firing's set.
    for firing, record in zip(firings, summary.firings):
        assert record.body_command == pytest.approx(thrusters.command(firing.thrusters))
        assert record.body_delivered == pytest.approx(
            np.array(gain) * thrusters.command(firing.thrusters) + np.array(bias))


def test_firing_impulse_equals_momentum_jump(tmp_path: Path) -> None:
    firings = (ThrusterFiring(0.3, 0.4, (2, 5, 1)), ThrusterFiring(1.2, 0.6, (7, 4)))
    summary = simulate(tmp_path, 'bag', duration=2.0, rate=100.0, seed=3, torque='zero',
                       base_pose_only=True, thruster_layout='freeflyer', firings=firings,
                       thrust_gain=(0.9, 0.9, 1, 1, 1, 0.8))
    momenta = read(tmp_path / 'bag', '/ground_truth/momentum')
    t = np.array([(s - START) * 1e-9 for s, _ in momenta])
    mu = np.array([wrench6(m) for _, m in momenta])
    for firing, record in zip(firings, summary.firings):
        before = mu[np.searchsorted(t, firing.start) - 1]
        after = mu[np.searchsorted(t, firing.end - 1e-9)]
        jump = after - before
        assert np.linalg.norm(jump - record.world_impulse) <= 1e-9 * np.linalg.norm(jump)
    coasting = (t < 0.3) | ((t >= 0.7) & (t < 1.2)) | (t >= 1.8)
    segments = np.split(mu[coasting], np.flatnonzero(np.diff(np.flatnonzero(coasting)) > 1) + 1)
    for segment in segments:
        assert np.max(np.abs(segment - segment[0])) <= 1e-12


def test_custom_thruster_units_on_the_paper_robot(tmp_path: Path) -> None:
    units = ((1, 0, 0, 0, 0.5, 0), (0, 0, 1, 0.2, 0, 0))
    summary = simulate(tmp_path, 'bag', paper_robot(), duration=1.0, rate=50.0, seed=1,
                       thruster_units=units, thruster_force=10.0,
                       firings=(ThrusterFiring(0.23, 0.3, (0, 1)),))
    assert summary.firings[0].body_command == pytest.approx([10, 0, 10, 2, 5, 0])
    # The 10 Hz grid (11 messages) and the two switches.
    assert summary.message_counts['/commanded_wrench'] == 11 + 2


def test_freeflyer_has_no_joint_states(tmp_path: Path) -> None:
    summary = simulate(tmp_path, 'bag', duration=0.2, rate=50.0, base_pose_only=True)
    assert '/joint_states' not in summary.topic_types
    assert summary.robot == 'freeflyer' and summary.base_group == 'SE(2)'
    robot = freeflyer()
    assert robot.m == 0
    assert robot.model.inertias[1].mass == pytest.approx(16.0)
    assert robot.model.inertias[1].inertia[2, 2] == pytest.approx(0.18)


# --------------------------------------------------------------------------- errors
@pytest.mark.parametrize('fields, message', [
    (dict(firings=(ThrusterFiring(0.1, 0.1, (0,)),)), 'need a thruster layout'),
    (dict(thrust_bias=(1, 0, 0, 0, 0, 0)), 'need a thruster layout'),
    (dict(thruster_layout='freeflyer', firings=(ThrusterFiring(0.1, 0.1, (8,)),)),
     'layout has 8'),
    (dict(thruster_layout='freeflyer', thruster_units=((1, 0, 0, 0, 0, 0),)), 'not both'),
    (dict(thruster_layout='hovercraft'), 'unknown thruster layout'),
    (dict(thruster_units=((1, 0, 0),)), '6 values'),
    (dict(thruster_layout='freeflyer', firings=(ThrusterFiring(20.0, 0.1, (1,)),)),
     'after the end'),
    (dict(quantize=(('joint_angle', 0.1),)), 'unknown quantize field'),
    (dict(quantize=(('joint_position', 0.0),)), 'quantize step'),
    (dict(bunch_fraction=1.0), 'bunch_fraction'), (dict(latency=-1.0), 'latency'),
    (dict(outage_duration=0.0), 'outage_duration'), (dict(noise_twist=-1.0), 'noise_twist'),
    (dict(noise_twist_angular=-1.0), 'noise_twist_angular'),
    (dict(thruster_layout='freeflyer', thruster_force=0.0), 'thruster_force'),
])
def test_bad_sensor_options(fields: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        SimulationOptions(**fields)


@pytest.mark.parametrize('argv, message', [
    (['--fire', '1,2'], 'argument --fire'), (['--fire', '1,2,x'], 'argument --fire'),
    (['--quantize', 'pose=1'], 'argument --quantize'),
    (['--quantize', 'joint_position=0'], 'argument --quantize'),
    (['--thruster-unit', '1,2,3'], 'argument --thruster-unit'),
    (['--bunch-fraction', '1.5'], 'argument --bunch-fraction'),
    (['--thruster-layout', 'hovercraft'], 'argument --thruster-layout'),
])
def test_bad_sensor_cli_options(argv: list, message: str, capsys: pytest.CaptureFixture) -> None:
    with pytest.raises(SystemExit) as exit_info:
        main(['simulate', '-o', 'unused'] + argv)
    assert exit_info.value.code == 2
    assert message in capsys.readouterr().err


def test_cli_options_reach_the_simulation(tmp_path: Path, capsys: pytest.CaptureFixture,
                                          monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(REPO_ROOT)
    out = tmp_path / 'bag'
    assert main(['simulate', '-o', str(out), '--urdf', 'config/robots/freeflyer.urdf',
                 '--duration', '1', '--rate', '50', '--base-pose-only', '--torque', 'zero',
                 '--thruster-layout', 'freeflyer', '--fire', '0.2,0.3,2,5',
                 '--thrust-gain', '0.5', '1', '1', '1', '1', '1', '--command-rate', '5',
                 '--stamp-jitter', '1e-4', '--latency', '0.002', '--bunch-fraction', '0.1',
                 '--outage-rate', '1', '--outage-duration', '0.05',
                 '--quantize', 'base_position=0.001', '--summary', str(tmp_path / 's.json')]
                ) == 0
    summary = json.loads((tmp_path / 's.json').read_text())
    assert summary['firings'][0]['body_delivered'][0] == pytest.approx(0.2)
    assert summary['message_counts']['/commanded_wrench'] == 6 + 1  # 0.2 s is on the grid
    assert 'Firing 1 of thrusters [2, 5]' in capsys.readouterr().out
    options = dataclasses.fields(SimulationOptions)
    assert {'stamp_jitter', 'bunch_fraction', 'latency', 'outage_rate', 'quantize',
            'firings'} <= {f.name for f in options}


def test_topics_at_their_own_rates(tmp_path: Path) -> None:
    summary = simulate(tmp_path, 'bag', paper_robot(), duration=1.0, rate=200.0, seed=3,
                       torque='sinusoid', joint_rate=100.0, base_rate=50.0,
                       bunch_fraction=0.2, noise_pose=1e-3)
    joints = read(tmp_path / 'bag', '/joint_states')
    odom = read(tmp_path / 'bag', '/odom')
    assert [t - START for t, _ in joints] == [k * 10_000_000 for k in range(101)]
    assert [t - START for t, _ in odom] == [k * 20_000_000 for k in range(51)]
    assert summary.message_counts['/ground_truth/momentum'] == 201
    # A bunched base message is stamped just before the next *base* message.
    stamps = np.array([stamp_ns(m) for _, m in odom])
    gaps = np.diff(stamps)
    assert summary.sensors['/odom'].bunched == np.count_nonzero(gaps < 100_000) > 0
    assert np.all((gaps == 20_000_000) | (gaps < 100_000) | (gaps > 20_000_000))
    with pytest.raises(ValueError, match='whole number'):
        SimulationOptions(rate=200.0, base_rate=120.0)
