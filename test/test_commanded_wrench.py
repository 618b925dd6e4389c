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
The commanded wrench (issue 10 item 4): gain, bias and the disturbance beyond the command.

Against the simulator's truth on test/data/freeflyer_realistic (binary thrusters
delivering 0.9 / 0.85 / 0.95 of the commanded Fx / Fy / Mz, no bias) and on a
bag simulated here with a bias; Jacobians against finite differences; the
zero-order hold; input hygiene (a bad command is counted and ignored: the
outputs equal those without it), batched == streaming.
"""

import json
import os
import subprocess
import sys

from hypothesis import given, HealthCheck, note, settings, strategies as st
import numpy as np
import pytest

from reduced_dynamics.bag.reader import open_bag
from reduced_dynamics.estimator import command_gain, Estimator
from reduced_dynamics.estimator.config import EstimatorConfig
from reduced_dynamics.estimator.filter import Linearisation, MomentumFilter, NoiseModel
from reduced_dynamics.geometry.lie_group import SUBGROUPS
from reduced_dynamics.messages import cdr
from reduced_dynamics.messages.samples import CommandSample, with_receive_time
from reduced_dynamics.params import defaults
from reduced_dynamics.replay import replay, ReplayOptions
from reduced_dynamics.resources import config_path
from reduced_dynamics.robot.model import load_robot
from reduced_dynamics.topics import active_topics, EVENTS_TOPIC, resolved_name

from filter_helpers import minus, plus

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
DATA = os.path.join(REPO, 'test', 'data')
FREEFLYER_BAG = os.path.join(DATA, 'freeflyer_realistic')
FREEFLYER = load_robot(str(config_path('robots/freeflyer.urdf')))
NS = 1_000_000_000
#: The simulator's truth of freeflyer_realistic (scripts/make_test_bags.sh): per axis
#: of SE(2)'s dual (fx, fy, tz).
TRUE_GAIN = np.array([0.9, 0.85, 0.95])
#: Largest |gain - truth| accepted. Measured on the shipped bag (seed 5): 0.0027,
#: 0.0058, 0.0013; over the same simulation with seeds 11-18 the largest errors were
#: 0.018 (fx), 0.011 (fy), 0.0064 (tz), against reported sigmas of 0.028, 0.031,
#: 0.0091 (the sigmas are conservative: the disturbance random walk allows more
#: than the simulation has). 0.025 covers the seeds with margin and is below the
#: 0.05 to 0.15 gain losses a thruster-health check has to see.
GAIN_TOLERANCE = 0.025


def _command_filter(name: str):
    group = SUBGROUPS[name]
    n = group.dim
    rng = np.random.default_rng(7)
    root = rng.normal(size=(n, n))
    locked = root @ root.T + n * np.eye(n)
    joint = rng.normal(size=(n, 2)) * 0.1
    lin = Linearisation(locked, np.linalg.inv(locked), rng.normal(size=n) * 0.3,
                        joint @ joint.T)
    flt = MomentumFilter(group, NoiseModel(), 0.0, command=True)
    g = group.exp(rng.normal(size=n))
    x = np.concatenate((rng.normal(size=2 * n), 1.0 + 0.2 * rng.normal(size=n),
                        0.3 * rng.normal(size=n)))
    return group, flt, lin, g, x, rng.normal(size=n)


@pytest.mark.parametrize('name', ['SE(3)', 'SE(2)'])
def test_commanded_transition_matches_finite_differences(name):
    group, flt, lin, g, x, u = _command_filter(name)
    n, dim = group.dim, 5 * group.dim
    dt = 1e-3
    phi, q = flt._transition(g, x, lin, dt, u)
    g1, x1 = flt.propagate_mean(g, x, lin, dt, u)
    numeric = np.zeros((dim, dim))
    eps = 1e-6
    for j in range(dim):
        d = np.zeros(dim)
        d[j] = eps
        gp, xp = flt.propagate_mean(*plus(group, g, x, d), lin, dt, u)
        gm, xm = flt.propagate_mean(*plus(group, g, x, -d), lin, dt, u)
        numeric[:, j] = (minus(group, gp, xp, g1, x1) - minus(group, gm, xm, g1, x1)) \
            / (2 * eps)
    # exp(F dt) at the step's start against the discrete map: O(dt^2).
    assert np.abs(phi - numeric).max() < 1e-5
    # The gain and bias blocks themselves (mu rows, ~1e-3): the same O(dt^2).
    assert np.allclose(phi[n:2 * n, 3 * n:], numeric[n:2 * n, 3 * n:], atol=1e-6)
    assert np.abs(phi[n:2 * n, 3 * n:]).max() > 1e-4
    eig = np.linalg.eigvalsh(q)
    assert eig.min() > -1e-12 * eig.max()


@pytest.mark.parametrize('name', ['SE(3)', 'SE(2)'])
def test_total_wrench_jacobian_matches_finite_differences(name):
    group, flt, lin, g, x, u = _command_filter(name)
    dim = 5 * group.dim
    p = np.eye(dim)
    _, cov = flt._total(g, x, p, u)
    jac = np.zeros((group.dim, dim))
    eps = 1e-6
    for j in range(dim):
        d = np.zeros(dim)
        d[j] = eps
        forward, _ = flt._total(*plus(group, g, x, d), p, u)
        backward, _ = flt._total(*plus(group, g, x, -d), p, u)
        jac[:, j] = (forward - backward) / (2 * eps)
    # P = identity: the covariance is J J^T.
    assert np.allclose(cov, jac @ jac.T, atol=1e-7)


def test_command_hold_is_integrated_exactly_over_a_step():
    estimator = Estimator(FREEFLYER, commanded_wrench=True)
    estimator._command_from_ns = 0
    assert estimator._command_input(100).mean.tolist() == [0.0, 0.0, 0.0]
    for stamp, fx in ((120, 1.0), (150, 3.0), (260, -2.0)):
        estimator._accept_command((stamp, np.array([fx, 0.0, 0.0])))
    # Step 100 -> 200: zero for 20, 1 for 30, 3 for 50 ns.
    step = estimator._command_input(200)
    assert step.mean[0] == pytest.approx((0 * 20 + 1 * 30 + 3 * 50) / 100)
    assert step.now.tolist() == [3.0, 0.0, 0.0]
    step = estimator._command_input(300)
    assert step.mean[0] == pytest.approx((3 * 60 - 2 * 40) / 100)
    assert step.now[0] == -2.0
    # Past commands are forgotten, the held one stays.
    assert estimator._command_stamps == [260]
    assert np.array_equal(estimator._command_input(400).mean, [-2.0, 0.0, 0.0])


# --- the shipped bag ------------------------------------------------------------------
def _replay(tmp_path, bag=FREEFLYER_BAG, smooth=False, command=True, name='out'):
    options = ReplayOptions(base_pose_topic='/base_pose', smooth=smooth,
                            commanded_wrench_topic='/commanded_wrench' if command else None)
    out = tmp_path / name
    summary = replay(bag, str(out), FREEFLYER, options)
    return summary, out


def _wrenches(path, topic):
    with open_bag(path) as reader:
        samples = [cdr.decode_wrench_stamped(bytes(m.data)) for m in reader.raw_messages([topic])]
    return (np.array([s.stamp_ns for s in samples]),
            np.array([np.r_[s.force, s.torque] for s in samples]))


def _statuses(path, name):
    from rosbags.typesys import get_typestore, Stores
    store = get_typestore(Stores.ROS2_JAZZY)
    out = []
    with open_bag(path) as reader:
        for message in reader.raw_messages(['/diagnostics']):
            msg = store.deserialize_cdr(bytes(message.data),
                                        'diagnostic_msgs/msg/DiagnosticArray')
            out += [s for s in msg.status if s.name == name]
    return out


@pytest.fixture(scope='module')
def causal(tmp_path_factory):
    return _replay(tmp_path_factory.mktemp('causal'))


def test_freeflyer_gain_and_bias_match_the_simulator(causal):
    summary, _ = causal
    command = summary['commanded_wrench']
    assert command['topic'] == '/commanded_wrench'
    assert command['axes'] == ['fx', 'fy', 'tz']
    assert command['samples'] == 122 and summary['messages_in']['/commanded_wrench'] == 122
    # Well excited: every gain identified, a number.
    assert all(isinstance(g, float) for g in command['gain']), command['gain']
    gain, gain_sigma = np.array(command['gain']), np.array(command['gain_sigma'])
    bias, bias_sigma = np.array(command['bias_estimate']), np.array(command['bias_sigma'])
    # The planar torque bias equals a world torque: not separable (below), so reported so.
    assert command['bias'][2] == 'unidentified'
    assert command['gain_projections'] == 0
    error = np.abs(gain - TRUE_GAIN)
    assert np.all(error < 3 * gain_sigma), (gain, gain_sigma)
    assert np.all(error < GAIN_TOLERANCE), gain
    # The data pinned the gains: far below the 0.5 prior.
    assert np.all(gain_sigma < [0.04, 0.04, 0.015])
    # No bias in this simulation: consistent with zero.
    assert np.all(np.abs(bias) < 3 * bias_sigma), (bias, bias_sigma)
    assert not summary['events']  # every firing was commanded
    assert not summary['rejected']


def test_total_wrench_tracks_the_thrust_and_the_disturbance_stays_at_zero(causal, tmp_path):
    summary, out = causal
    stamps, total = _wrenches(out, '/reduced_dynamics/drift/momentum_rate')
    dstamps, disturbance = _wrenches(out, '/reduced_dynamics/drift/disturbance')
    assert np.array_equal(stamps, dstamps)
    truth_stamps, truth = _wrenches(FREEFLYER_BAG, '/ground_truth/external_wrench')
    truth = truth[np.clip(np.searchsorted(truth_stamps, stamps), 0, len(truth) - 1)]
    axes = [0, 1, 5]
    # After the filter's start (its wrench prior is 1 m/s^2).
    late = stamps - stamps[0] > 1.5 * NS
    error = (total - truth)[late][:, axes]
    scale = np.sqrt((truth[late][:, axes] ** 2).mean(axis=0))
    # Measured: RMS error 0.015 N, 0.025 N, 0.0037 N m against RMS thrust 0.092 N,
    # 0.143 N, 0.022 N m; correlation 0.988, 0.986, 0.986 (without the command,
    # the same causal filter: 0.65, 0.72, 0.61).
    assert np.all(np.sqrt((error ** 2).mean(axis=0)) < 0.25 * scale)
    for i in axes:
        assert np.corrcoef(total[late, i], truth[late, i])[0, 1] > 0.97
    # The disturbance beyond the command is consistent with zero: at the
    # diagnostics (1 Hz), (d / sigma)^2 averages about 1 (chi-square per axis).
    statuses = _statuses(out, 'reduced_dynamics: commanded wrench')
    assert len(statuses) >= 13
    ratios = []
    for status in statuses:
        values = {v.key: v.value for v in status.values}
        d = np.array(values['disturbance'].split(), dtype=float)
        sigma = np.array(values['disturbance_sigma'].split(), dtype=float)
        ratios.append(d / sigma)
    ratios = np.array(ratios)
    assert np.all(np.abs(ratios) < 3.5), ratios
    assert (ratios ** 2).mean() < 1.5
    # ... and small against the thrust it no longer has to carry.
    assert np.all(np.sqrt((disturbance[late][:, axes] ** 2).mean(axis=0)) < 0.1 * scale)


def test_without_the_option_nothing_changes(causal, tmp_path):
    summary, out = _replay(tmp_path, command=False)
    assert 'commanded_wrench' not in summary
    assert '/commanded_wrench' not in summary['messages_in']
    with open_bag(out) as reader:
        topics = set(reader.topics())
    assert topics == {resolved_name(t) for t in active_topics(False) + (EVENTS_TOPIC,)}
    assert '/reduced_dynamics/drift/disturbance' not in topics
    # The momentum estimate differs only through the wrench model, not the inputs.
    _, with_command = causal
    assert _wrenches(out, '/reduced_dynamics/momentum')[0].tolist() == \
        _wrenches(with_command, '/reduced_dynamics/momentum')[0].tolist()


def test_smoothed_replay_reports_the_same_gain_and_a_closer_wrench(causal, tmp_path):
    options = ReplayOptions(base_pose_topic='/base_pose', plots_dir=str(tmp_path / 'plots'),
                            commanded_wrench_topic='/commanded_wrench')
    out = tmp_path / 'out'
    summary = replay(FREEFLYER_BAG, str(out), FREEFLYER, options)
    assert summary['commanded_wrench'] == causal[0]['commanded_wrench']
    assert str(tmp_path / 'plots' / 'disturbance.png') in summary['plots']
    stamps, total = _wrenches(out, '/reduced_dynamics/drift/momentum_rate')
    truth_stamps, truth = _wrenches(FREEFLYER_BAG, '/ground_truth/external_wrench')
    truth = truth[np.clip(np.searchsorted(truth_stamps, stamps), 0, len(truth) - 1)]
    for i in (0, 1, 5):
        # Measured 0.991, 0.988, 0.993.
        assert np.corrcoef(total[:, i], truth[:, i])[0, 1] > 0.98


def test_cli_option_and_summary_json(tmp_path):
    summary_path = tmp_path / 'summary.json'
    result = subprocess.run(
        [sys.executable, '-m', 'reduced_dynamics.cli', 'replay', FREEFLYER_BAG,
         '-o', str(tmp_path / 'out'), '--urdf', str(config_path('robots/freeflyer.urdf')),
         '--base-pose-topic', '/base_pose', '--commanded-wrench-topic', '/commanded_wrench',
         '--no-smooth', '--quiet', '--summary-json', str(summary_path)],
        capture_output=True, text=True, cwd=REPO, check=False)
    assert result.returncode == 0, result.stderr
    assert 'commanded wrench /commanded_wrench (122 commands): fx gain 0.89' in result.stdout
    command = json.loads(summary_path.read_text())['commanded_wrench']
    assert set(command) == {'topic', 'axes', 'samples', 'gain', 'gain_sigma', 'bias',
                            'bias_sigma', 'gain_estimate', 'bias_estimate',
                            'gain_projections'}
    missing = subprocess.run(
        [sys.executable, '-m', 'reduced_dynamics.cli', 'replay', FREEFLYER_BAG,
         '-o', str(tmp_path / 'out2'), '--urdf', str(config_path('robots/freeflyer.urdf')),
         '--base-pose-topic', '/base_pose', '--commanded-wrench-topic', '/thrust', '--quiet'],
        capture_output=True, text=True, cwd=REPO, check=False)
    assert missing.returncode == 2
    assert 'no geometry_msgs/msg/WrenchStamped topic /thrust' in missing.stderr


#: The freeflyer's simulated 15 s thruster runs (poses only, 120 Hz, gains off one), without
#: their firings and bias.
FREEFLYER_SIMULATION = [
    '--urdf', str(config_path('robots/freeflyer.urdf')), '--duration', '15', '--rate', '120',
    '--seed', '5', '--torque', 'zero', '--base-pose-only', '--noise-pose', '0.0005',
    '--noise-orientation', '0.002', '--thruster-layout', 'freeflyer',
    '--thrust-gain', '0.9', '0.85', '1', '1', '1', '0.95', '--command-rate', '8']


def _simulate(path, *args):
    """Write ``reduced-dynamics simulate`` with ``args`` to ``path`` (it must succeed)."""
    subprocess.run([sys.executable, '-m', 'reduced_dynamics.cli', 'simulate', '-o', str(path),
                    *args], check=True, capture_output=True, cwd=REPO)


def test_a_body_force_bias_is_recovered(tmp_path):
    """The bias of the delivered body force: 0.02 N on Fx (and 2 mN m on Mz)."""
    bag = tmp_path / 'biased'
    _simulate(bag, *FREEFLYER_SIMULATION, '--fire', '2,1,2,5', '--fire', '5,1.5,4,7',
              '--fire', '9,0.8,1,3,5,7', '--fire', '12,1,6,1',
              '--thrust-bias', '0.02', '0', '0', '0', '0', '0.002')
    summary, _ = _replay(tmp_path, bag=str(bag))
    command = summary['commanded_wrench']
    bias, sigma = np.array(command['bias_estimate']), np.array(command['bias_sigma'])
    truth = np.array([0.02, 0.0, 0.002])
    assert np.all(np.abs(bias - truth) < 3 * sigma), (bias, sigma)
    # A body-fixed force is told from a world-fixed disturbance as the base turns
    # (measured: 0.0198 +- 0.0098 N). A body torque on a planar base is not: it
    # equals a world torque, so the Mz bias stays at its prior (sigma 0.0045 N m)
    # and the disturbance carries it (docs/commanded_wrench.md).
    assert abs(bias[0] - 0.02) < 0.005 and sigma[0] < 0.5 * 0.005 * 16.0
    assert sigma[2] > 0.9 * 0.025 * 0.18  # the prior: 0.025 rad/s^2 on 0.18 kg m^2
    gain = np.array(command['gain'])
    assert np.all(np.abs(gain - TRUE_GAIN) < GAIN_TOLERANCE)


#: The paper robot (SE(3) base, a 6-joint arm, Odometry and joint states with the noise of
#: test/data/paper_realistic) with six 20 N binary thrusters, one per body axis (the
#: torque ones on a 0.2 m arm), fired in pairs, and their delivered gains.
PAPER_GAIN = np.array([0.9, 0.8, 1.1, 0.95, 0.85, 1.05])
PAPER_SIMULATION = [
    '--duration', '6', '--rate', '100', '--seed', '4', '--torque', 'sinusoid',
    '--noise-position', '1e-4', '--noise-velocity', '0.005', '--noise-effort', '0.05',
    '--noise-pose', '0.001', '--noise-orientation', '0.0005', '--noise-twist', '0.002',
    '--stamp-jitter', '0.0003', '--latency', '0.004', '--latency-jitter', '0.001',
    '--thruster-unit', '1,0,0,0,0,0', '--thruster-unit', '0,1,0,0,0,0',
    '--thruster-unit', '0,0,1,0,0,0', '--thruster-unit', '0,0,0,0.2,0,0',
    '--thruster-unit', '0,0,0,0,0.2,0', '--thruster-unit', '0,0,0,0,0,0.2',
    '--thruster-force', '20', '--fire', '1,1,0,4', '--fire', '2.5,1,1,5', '--fire', '4,1,2,3',
    '--thrust-gain', *[str(g) for g in PAPER_GAIN], '--command-rate', '10']


def simulate_paper_thrusters(path):
    """Write the paper robot's thruster bag (PAPER_SIMULATION) to ``path``."""
    _simulate(path, *PAPER_SIMULATION)


def test_paper_robot_gains_with_joint_states_and_odometry(tmp_path):
    """SE(3), the joint-state-driven path: six gains against the simulator's."""
    bag = tmp_path / 'paper'
    simulate_paper_thrusters(bag)
    # The simulated 1 mm position noise (the default is a motion capture's 0.5 mm).
    params = {**defaults(), 'pose_position_noise': 1e-3}
    options = ReplayOptions(params=params, smooth=False,
                            commanded_wrench_topic='/commanded_wrench')
    summary = replay(str(bag), str(tmp_path / 'out'), load_robot(), options)
    command = summary['commanded_wrench']
    assert command['axes'] == ['fx', 'fy', 'fz', 'tx', 'ty', 'tz']
    gain, sigma = np.array(command['gain']), np.array(command['gain_sigma'])
    # Measured: 0.8962 +- 0.027, 0.8142 +- 0.022, 1.1007 +- 0.028, 0.9826 +- 0.15,
    # 0.8725 +- 0.091, 1.0252 +- 0.15 (the torques are pinned less: 4 N m on the
    # paper robot's inertia, with 0.5 mrad attitude noise).
    assert np.all(np.abs(gain - PAPER_GAIN) < 3 * sigma), (gain, sigma)
    assert np.all(sigma[:3] < 0.05) and np.all(sigma[3:] < 0.3)
    assert np.all(np.abs(command['bias_estimate']) < 3 * np.array(command['bias_sigma']))
    assert not summary['events'] and not summary['rejected']


# --- input hygiene ------------------------------------------------------------------------
def _freeflyer_samples(start_s=1.5, end_s=4.0):
    """Poses and commands of the shipped bag in record order (receive time = record time)."""
    samples = []
    with open_bag(FREEFLYER_BAG) as reader:
        begin = reader.start_ns
        for message in reader.raw_messages(['/base_pose', '/commanded_wrench']):
            if not begin + start_s * NS <= message.timestamp_ns < begin + end_s * NS:
                continue
            data = bytes(message.data)
            sample = cdr.decode_wrench_stamped(data) if message.topic == '/commanded_wrench' \
                else cdr.decode_pose_stamped(data, FREEFLYER.base_link)
            samples.append(with_receive_time(sample, message.timestamp_ns))
    return samples


SAMPLES = _freeflyer_samples()
CONFIG = EstimatorConfig.from_mapping({'prediction_rate': 0.0, 'diagnostics_rate': 0.0})


def _run(samples, batched):
    estimator = Estimator(FREEFLYER, CONFIG, use_odometry=False, commanded_wrench=True)
    if batched:
        outputs = estimator.add_samples(samples).outputs()
    else:
        outputs = []
        for sample in samples:
            outputs += estimator.add_command(sample) if isinstance(sample, CommandSample) \
                else estimator.add_base_state(sample)
    return estimator, outputs + estimator.flush()


def _bytes(outputs):
    return [(cdr.encode_wrench_stamped(o.momentum), cdr.encode_wrench_stamped(o.momentum_rate),
             cdr.encode_wrench_stamped(o.disturbance)) for o in outputs]


def test_batched_equals_streaming_with_commands():
    _, batched = _run(SAMPLES, True)
    estimator, streamed = _run(SAMPLES, False)
    assert _bytes(batched) == _bytes(streamed)
    assert estimator.received['command'] == sum(isinstance(s, CommandSample) for s in SAMPLES)
    assert not estimator.rejected


def test_an_estimator_without_the_option_ignores_commands_and_counts_them():
    plain = [s for s in SAMPLES if not isinstance(s, CommandSample)]
    reference = Estimator(FREEFLYER, CONFIG, use_odometry=False)
    expected = reference.add_samples(plain).outputs() + reference.flush()
    estimator = Estimator(FREEFLYER, CONFIG, use_odometry=False)
    outputs = estimator.add_samples(SAMPLES).outputs() + estimator.flush()
    assert [(cdr.encode_wrench_stamped(o.momentum_rate)) for o in outputs] == \
        [(cdr.encode_wrench_stamped(o.momentum_rate)) for o in expected]
    assert all(o.disturbance is None for o in outputs)
    assert estimator.rejected == {'command_unused': len(SAMPLES) - len(plain)}


COMMAND_INDICES = [i for i, s in enumerate(SAMPLES) if isinstance(s, CommandSample)]


def _damaged(sample, kind, previous):
    if kind == 'nan':
        return CommandSample(sample.stamp_ns, sample.frame_id, [np.nan, 0, 0], sample.torque,
                             sample.receive_ns), 'non_finite_command'
    if kind == 'inf':
        return CommandSample(sample.stamp_ns, sample.frame_id, sample.force, [0, 0, -np.inf],
                             sample.receive_ns), 'non_finite_command'
    if kind == 'huge':
        # 1e5 N on 16 kg: 6250 m/s^2, beyond the 1000 m/s^2 bound.
        return CommandSample(sample.stamp_ns, sample.frame_id, [0, 1e5, 0], sample.torque,
                             sample.receive_ns), 'command_bound'
    if kind == 'duplicate':
        return CommandSample(previous.stamp_ns, sample.frame_id, sample.force, sample.torque,
                             sample.receive_ns), 'command_stamp_backwards'
    # A stamp from another clock (2038): held, then dropped as an outlier.
    return CommandSample(sample.stamp_ns + 400_000_000 * NS, sample.frame_id, sample.force,
                         sample.torque, sample.receive_ns), 'command_stamp_outlier'


@settings(max_examples=40, deadline=None, derandomize=True, database=None,
          suppress_health_check=list(HealthCheck))
@given(st.lists(st.tuples(st.integers(1, len(COMMAND_INDICES) - 2),
                          st.sampled_from(['nan', 'inf', 'huge', 'duplicate', 'outlier'])),
                min_size=1, max_size=4, unique_by=lambda t: t[0]),
       st.booleans())
def test_fuzz_bad_commands_are_counted_and_ignored(damage, batched):
    """A rejected command changes nothing: the outputs equal those without it."""
    note(repr(damage))
    samples = list(SAMPLES)
    expected_reasons: dict = {}
    dropped = set()
    for k, kind in sorted(damage):
        index = COMMAND_INDICES[k]
        previous = samples[COMMAND_INDICES[k - 1]]
        if COMMAND_INDICES[k - 1] in dropped and kind == 'duplicate':
            kind = 'nan'  # the reference of a duplicate must itself be valid
        samples[index], reason = _damaged(samples[index], kind, previous)
        expected_reasons[reason] = expected_reasons.get(reason, 0) + 1
        dropped.add(index)
    estimator, outputs = _run(samples, batched)
    assert dict(estimator.rejected) == expected_reasons
    for output in outputs:
        for wrench in (output.momentum, output.momentum_rate, output.disturbance):
            assert np.isfinite(wrench.force).all() and np.isfinite(wrench.torque).all()
    clean = [s for i, s in enumerate(SAMPLES) if i not in dropped]
    _, expected = _run(clean, batched)
    assert _bytes(outputs) == _bytes(expected)


# --- real data: the freeflyer2 PD recording's ThrusterCommand as a body wrench ----------
#: Shipped with the tests (test/data/freeflyer2, MIT): runs from a clone with nothing beside it.
PD_BAG = os.path.join(DATA, 'freeflyer2', 'rosbag2_2024_03_14-14_17_23')


def test_real_freeflyer2_thruster_switches_as_commanded_wrench(tmp_path):
    """Measured figures, not a fit: the defaults are not tuned to these bags."""
    from reduced_dynamics.thrust_correlation import (decode_thruster_command,
                                                     WRENCH_COMMAND_TOPIC, write_command_bag)
    from reduced_dynamics.thrusters import FREEFLYER_ARM, FREEFLYER_FORCE
    converted = tmp_path / 'pd'
    assert write_command_bag(PD_BAG, str(converted)) == 3535
    with open_bag(PD_BAG) as source, open_bag(converted) as target:
        switches = [decode_thruster_command(bytes(m.data))[1] for m in
                    source.raw_messages(['/robot/commands/binary_thrust'])]
        wrenches = [cdr.decode_wrench_stamped(bytes(m.data))
                    for m in target.raw_messages([WRENCH_COMMAND_TOPIC])]
    for s, w in zip(switches, wrenches):
        # The data README's map: Fx = s2 + s5 - s1 - s6, Fy = s4 + s7 - s0 - s3,
        # Mz / arm = s1 + s3 + s5 + s7 - s0 - s2 - s4 - s6 (0.2 N each).
        assert w.force[0] == pytest.approx(FREEFLYER_FORCE * (s[2] + s[5] - s[1] - s[6]))
        assert w.force[1] == pytest.approx(FREEFLYER_FORCE * (s[4] + s[7] - s[0] - s[3]))
        assert w.torque[2] == pytest.approx(FREEFLYER_FORCE * FREEFLYER_ARM * (
            s[1] + s[3] + s[5] + s[7] - s[0] - s[2] - s[4] - s[6]))
    options = ReplayOptions(base_pose_topic='/vrpn_mocap/robot/pose', smooth=False,
                            commanded_wrench_topic=WRENCH_COMMAND_TOPIC)
    summary = replay(str(converted), str(tmp_path / 'out'), FREEFLYER, options)
    command = summary['commanded_wrench']
    # Measured (docs/commanded_wrench.md): gain 0.565 +- 0.023, 0.637 +- 0.025,
    # 0.657 +- 0.011; the Mz gain is the stable figure (0.68 and 0.64 on the two
    # halves of this bag, 0.53 and 0.59 on the other bag's), the force gains are not
    # (the table's position-dependent tilt enters them).
    assert 0.5 < command['gain'][2] < 0.8 and command['gain_sigma'][2] < 0.05
    assert all(0.0 < g < 1.0 for g in command['gain'])
    # No push in this recording, yet events (measured: 2, at 9.5 s and 12.8 s): the
    # chi-square test of w, not the step test, with every gain identified (multiple
    # correlation <= 0.8): the delivered wrench beyond k u + b changes by ~0.1 N within
    # seconds, more than the default disturbance density (1e-3 m/s^3/sqrt(Hz)) allows.
    # At 0.01 (a table whose tilt varies with position) none (docs/commanded_wrench.md).
    assert 1 <= len(summary['events']) <= 3
    params = {**defaults(), 'disturbance_jerk_linear': 0.01}
    options = ReplayOptions(params=params, base_pose_topic='/vrpn_mocap/robot/pose',
                            smooth=False, commanded_wrench_topic=WRENCH_COMMAND_TOPIC)
    looser = replay(str(converted), str(tmp_path / 'looser'), FREEFLYER, options)
    assert not looser['events']
    assert all(isinstance(g, float) for g in looser['commanded_wrench']['gain'])


# --- physical gains (issue 20 item 6) -------------------------------------------------
def _spd(rng, dim):
    root = rng.normal(size=(dim, dim))
    return root @ root.T + 0.1 * np.eye(dim)


def test_gain_projection_is_the_covariance_weighted_one():
    """Simon & Chia's projection: k on the floor, the correlated states moved with it."""
    n, rng = 3, np.random.default_rng(3)
    p = _spd(rng, 5 * n)
    x = np.concatenate((rng.normal(size=2 * n), [-0.3, 0.8, 0.9], rng.normal(size=n)))
    assert command_gain.project_gains(np.r_[x[:2 * n], [0.5, 0.8, 0.9], x[3 * n:]], p, n) \
        is None
    correction = command_gain.project_gains(x, p, n)
    k = 3 * n
    expected = -p[:, k] * (x[2 * n] - command_gain.GAIN_FLOOR) / p[k, k]
    if np.all(x[2 * n:3 * n] + expected[3 * n:4 * n] >= command_gain.GAIN_FLOOR):
        assert np.allclose(correction, expected)
    gains = x[2 * n:3 * n] + correction[3 * n:4 * n]
    assert np.all(gains >= command_gain.GAIN_FLOOR - 1e-12)
    assert gains[0] == pytest.approx(command_gain.GAIN_FLOOR)
    # Among corrections putting the active gains on the floor, the least in P^-1.
    active = np.flatnonzero(np.isclose(gains, command_gain.GAIN_FLOOR))
    null = np.delete(np.eye(5 * n), 3 * n + active, axis=0).T
    step = null @ np.linalg.lstsq(null.T @ np.linalg.solve(p, null),
                                  -null.T @ np.linalg.solve(p, correction), rcond=None)[0]
    assert np.abs(step).max() < 1e-9


def test_active_set_takes_a_gain_pushed_below_the_floor():
    n = 3
    p = np.eye(5 * n)
    # k0 and k1 strongly correlated: raising k0 to the floor pushes k1 below it.
    p[3 * n, 3 * n + 1] = p[3 * n + 1, 3 * n] = -0.99
    x = np.concatenate((np.zeros(2 * n), [-0.5, 0.2, 1.0], np.zeros(n)))
    correction = command_gain.project_gains(x, p, n)
    gains = x[2 * n:3 * n] + correction[3 * n:4 * n]
    assert np.allclose(gains[:2], command_gain.GAIN_FLOOR) and gains[2] == 1.0


def test_an_unidentified_gain_on_the_command_does_not_read_as_a_disturbance():
    group, flt, lin, g, x, u = _command_filter('SE(2)')
    n = group.dim
    flt.initialise(0, g, lin, None)
    assert not flt.command_identified()[0].any()  # the prior: nothing identified
    flt.x = np.concatenate((x[:n], [0.05, 0.0, 0.0], x[2 * n:]))
    plain = float(flt.wrench_significance())
    flt._command = np.array([0.4, 0.0, 0.0])
    widened = flt.wrench_significance()
    to_world = flt._adjoint_inverse(flt.g).T
    cov = flt.wrench_cov + 0.16 * np.outer(to_world[:, 0], to_world[:, 0]) * flt.p[3 * n, 3 * n]
    assert widened == pytest.approx(flt.wrench @ np.linalg.solve(cov, flt.wrench))
    assert widened < plain


#: A still robot: both +x thrusters fire for the whole recording against a body force that
#: cancels them (0.36 N), so only k u + b + w is pinned, never k apart from b and w.
STILL = ['--fire', '0,16,2,5', '--thrust-bias', '-0.36', '0', '0', '0', '0', '0']


def test_a_still_robot_gives_an_unidentified_gain(tmp_path):
    bag = tmp_path / 'still'
    _simulate(bag, *FREEFLYER_SIMULATION, *STILL)
    summary, _ = _replay(tmp_path, bag=str(bag))
    command = summary['commanded_wrench']
    # Measured: fx gain 0.26 +- 0.25 (truth 0.9), its multiple correlation with the bias
    # and the disturbance 0.99; fy and tz never fired (their prior).
    assert command['gain'] == ['unidentified'] * 3
    assert command['bias'][0] == 'unidentified'
    assert all(k >= command_gain.GAIN_FLOOR for k in command['gain_estimate'])
    assert not summary['events']
