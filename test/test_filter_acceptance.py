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

"""The filter on realistic simulated bags and on the shared real freeflyer2 recordings."""

import json
import os
from pathlib import Path
import struct

import numpy as np
import pytest

from reduced_dynamics.chi_square import chi2
from reduced_dynamics.params import defaults, load_params_file
from reduced_dynamics.replay import replay, ReplayOptions
from reduced_dynamics.resources import config_path
from reduced_dynamics.robot.model import load_robot
from reduced_dynamics.thrust_correlation import (decode_thruster_command, momentum_spread,
                                                 thrust_correlation, write_command_twin)

from filter_helpers import wrench_series

DATA = Path(__file__).parent / 'data'
#: The real freeflyer2 recordings: the PD one is shipped (test/data/freeflyer2, MIT), the
#: longer trajectory-optimisation one only in the shared data set beside the clone.
SHARED = Path(__file__).resolve().parent.parent.parent / 'shared' / 'data' / 'freeflyer2'
TRAJECTORY_BAG = SHARED / 'rosbag2_2024_03_15-15_45_20'
PD_BAG = DATA / 'freeflyer2' / 'rosbag2_2024_03_14-14_17_23'
REAL_BAGS = [
    pytest.param(TRAJECTORY_BAG, id=TRAJECTORY_BAG.name, marks=pytest.mark.skipif(
        not TRAJECTORY_BAG.is_dir(), reason=f'shared real data absent ({SHARED})')),
    pytest.param(PD_BAG, id=PD_BAG.name),
]
#: A 16 kg body pushed by at most two 0.2 N thrusters per axis (0.025 m/s^2) over a
#: table a few metres wide cannot exceed ~0.5 m/s: 8 N s bounds the momentum's spread.
SPREAD_BOUND = 16.0 * 0.5


def _firing_impulses(out, summary):
    """Integrate the published wrench over each firing (0.5 s before to 1 s after)."""
    rate = wrench_series(out, '/reduced_dynamics/drift/momentum_rate')
    seconds = (rate[:, 0] - summary['start_time_ns']) * 1e-9
    for firing in summary['firings'] or summary['pulses']:
        start, end = firing['start'], firing['start'] + firing['duration']
        window = (seconds >= start - 0.5) & (seconds <= end + 1.0)
        yield (np.trapezoid(rate[window, 1:], seconds[window], axis=0),
               np.array(firing['world_impulse']))


@pytest.mark.parametrize('smooth', [False, True])
def test_freeflyer_realistic_firings_recover_the_impulse(tmp_path, smooth):
    """Planar free-flyer, pose only, mocap-like noise, bunched stamps, an outage."""
    robot = load_robot(str(config_path('robots/freeflyer.urdf')))
    summary = json.loads((DATA / 'freeflyer_realistic.summary.json').read_text())
    out = tmp_path / 'out'
    replay(str(DATA / 'freeflyer_realistic'), str(out), robot,
           ReplayOptions(base_pose_topic='/base_pose', smooth=smooth))
    for estimate, truth in _firing_impulses(out, summary):
        linear, angular = np.linalg.norm(truth[:2]), abs(truth[5])
        if linear > 0.1:  # a push: measured 1-4 % (causal and smoothed)
            assert np.linalg.norm(estimate[:2] - truth[:2]) <= 0.1 * linear
        else:  # the pure torque firing: its angular impulse (measured 1-2 %)
            assert abs(estimate[5] - truth[5]) <= 0.1 * angular


@pytest.mark.parametrize('smooth,bound', [(False, 0.15), (True, 0.1)])
def test_paper_realistic_pulse_impulse(tmp_path, smooth, bound):
    """The paper robot with noisy odometry and joint states: the 0.5 s, 20 N pulse."""
    summary = json.loads((DATA / 'paper_realistic.summary.json').read_text())
    out = tmp_path / 'out'
    replay(str(DATA / 'paper_realistic'), str(out), load_robot(),
           ReplayOptions(smooth=smooth))
    (estimate, truth), = _firing_impulses(out, summary)
    # Measured: 10.4 % causal (just above the 10 %), 6.7 % smoothed.
    assert np.linalg.norm(estimate - truth) <= bound * np.linalg.norm(truth)


def test_smoothing_beats_the_causal_filter_on_momentum(tmp_path):
    robot = load_robot(str(config_path('robots/freeflyer.urdf')))
    truth = wrench_series(DATA / 'freeflyer_realistic', '/ground_truth/momentum')
    errors = []
    # One pass writes both (causal_out: the bag replay --no-smooth writes).
    replay(str(DATA / 'freeflyer_realistic'), str(tmp_path / 'outTrue'), robot,
           ReplayOptions(base_pose_topic='/base_pose', causal_out=str(tmp_path / 'outFalse')))
    for smooth in (False, True):
        out = tmp_path / f'out{smooth}'
        mu = wrench_series(out, '/reduced_dynamics/momentum')
        index = np.searchsorted(truth[:, 0], mu[:, 0])
        keep = (index < len(truth)) & (mu[:, 0] - mu[0, 0] > 1e9)  # after 1 s
        matched = truth[np.minimum(index, len(truth) - 1)]
        error = np.abs(mu[keep, 1:] - matched[keep, 1:])[:, [0, 1, 5]]
        errors.append(np.sqrt(np.mean(error ** 2, axis=0)))
    assert np.all(errors[1] < errors[0]), errors


def test_tune_recovers_the_simulated_pose_noise(tmp_path):
    """The realistic freeflyer bag has 0.5 mm position noise (plus 0.1 mm quantisation)."""
    from reduced_dynamics.cli import main
    out = tmp_path / 'tuned.yaml'
    # Start 4x off (the default, 0.5 mm, is the simulated figure itself).
    start = tmp_path / 'start.yaml'
    start.write_text('/**/reduced_dynamics:\n  ros__parameters:\n'
                     '    pose_position_noise: 0.002\n')
    assert main(['tune', str(DATA / 'freeflyer_realistic'), '-o', str(out), '--urdf',
                 str(config_path('robots/freeflyer.urdf')), '--base-joint', 'planar',
                 '--base-pose-topic', '/base_pose', '--parameters', 'pose_position_noise',
                 '--params', str(start), '--max-evaluations', '12', '--quiet']) == 0
    params = load_params_file(str(out))
    assert 2e-4 <= params['pose_position_noise'] <= 8e-4
    header = out.read_text().splitlines()[1]
    before, after = (float(v) for v in header.split('log-likelihood ')[1].split(';')[0]
                     .split(' -> '))
    assert after > before


def test_thruster_command_cdr_decoding():
    frame = b'body\x00'
    data = b'\x00\x01\x00\x00' + struct.pack('<iII', 12, 345, len(frame)) + frame \
        + bytes([1, 0, 1, 0, 0, 1, 0, 0])
    stamp, switches = decode_thruster_command(data)
    assert stamp == 12 * 10**9 + 345
    assert switches == (True, False, True, False, False, True, False, False)


@pytest.mark.parametrize('path', REAL_BAGS)
def test_real_freeflyer2_bags_correlate_with_the_commanded_thrust(tmp_path, path):
    """The data README's judging procedure, replay defaults, no command input."""
    robot = load_robot(str(config_path('robots/freeflyer.urdf')))
    bag = str(path)
    figures = {}
    # One pass writes both (causal_out: the bag replay --no-smooth writes).
    summary = replay(bag, str(tmp_path / 'outTrue'), robot, ReplayOptions(
        params=defaults(), base_pose_topic='/vrpn_mocap/robot/pose',
        causal_out=str(tmp_path / 'outFalse')))
    assert summary['processed'] >= 6000
    for smooth in (False, True):
        out = str(tmp_path / f'out{smooth}')
        figures[smooth] = thrust_correlation(bag, out)
        assert np.all(momentum_spread(out) <= SPREAD_BOUND)
    causal, smoothed = figures[False], figures[True]
    # Measured (docs/real_data.md): causal 0.831/0.724/0.753 and 0.733/0.755/0.913, smoothed
    # 0.907/0.891/0.969 and 0.761/0.781/0.956 (pose_position_noise 0.5 mm; with 1 mm the
    # trajectory bag's causal Fy was 0.696). The poses are re-timed to their frames
    # (pose_retiming auto; off, at 1 mm: causal 0.81/0.68/0.74 and 0.72/0.75/0.91). The PD
    # bag's causal figures were 0.45/0.45/0.77 before the pose stamp noise (its mocap
    # client stamps on receipt, 100 Hz polling). The floors (0.7 causal, 0.8
    # smoothed) hold on 10 of 12 figures; the PD bag's smoothed Fx and Fy are bounded
    # by the recording, not the sensors (test_command_twin_...).
    summary_filter = summary['filter']
    assert summary_filter['poses_retimed'] > 0.95 * summary['processed']
    assert min(causal[:3]) >= 0.7
    if path == TRAJECTORY_BAG:
        assert min(smoothed[:3]) >= 0.8
        assert causal.fx >= 0.82 and causal.fy >= 0.715 and causal.mz >= 0.745
    else:
        assert smoothed.fx >= 0.755 and smoothed.fy >= 0.775 and smoothed.mz >= 0.95
        assert causal.fx >= 0.725 and causal.fy >= 0.745 and causal.mz >= 0.905
    assert os.path.isdir(out)


@pytest.mark.parametrize('path', REAL_BAGS)
def test_command_twin_of_a_real_bag_correlates_near_one(tmp_path, path):
    """
    The recording's stamps and mocap noise, a body pushed by the command alone.

    The same estimator and defaults that reach 0.76-0.91 (Fx) on the recordings reach
    0.99 on their command twins (thrust_correlation.write_command_twin): the sensors
    and the stamps allow near 1; what bounds the recordings' figures is how well the
    command describes the force the body felt.
    """
    robot = load_robot(str(config_path('robots/freeflyer.urdf')))
    bag, twin = str(path), str(tmp_path / 'twin')
    figures = write_command_twin(bag, twin)
    # Measured: 22 / 26 um and 0.22 / 0.19 mrad frame to frame (0.5 mm and 2 mrad are
    # the defaults: re-fits of the mocap body and slow errors come on top).
    assert 1.5e-5 <= figures.position_noise <= 3.5e-5
    assert 1e-4 <= figures.angle_noise <= 3e-4
    assert figures.poses >= 6000
    correlations = {}
    # One pass writes both (causal_out: the bag replay --no-smooth writes).
    summary = replay(twin, str(tmp_path / 'outTrue'), robot, ReplayOptions(
        params=defaults(), base_pose_topic='/vrpn_mocap/robot/pose',
        causal_out=str(tmp_path / 'outFalse')))
    # The twin's body is pushed (by the command, not given to the filter here): the
    # multi-scale test flags those pushes as events; no wrench step is taken.
    assert summary['filter']['steps_taken'] == 0
    for smooth in (False, True):
        correlations[smooth] = thrust_correlation(bag, str(tmp_path / f'out{smooth}'),
                                                  poses_bag=twin)
    # Measured smoothed 0.995/0.994/0.993 and 0.998/0.998/0.997; causal 0.922/0.916/0.826
    # and 0.991/0.985/0.975 (the trajectory bag's 8 Hz commands switch whole thrusters).
    assert min(correlations[True][:3]) >= 0.99
    assert min(correlations[False][:3]) >= 0.8


def _ground_truth(bag: str, topic: str) -> tuple[np.ndarray, np.ndarray]:
    """Return a ground-truth topic's header stamps and (force, torque) rows."""
    rows = wrench_series(DATA / bag, topic)
    return rows[:, 0].astype(np.int64), rows[:, 1:]


@pytest.mark.parametrize('bag', ['paper_realistic', 'paper_spacecraft', 'freeflyer_realistic',
                                 'freeflyer_testbed'])
def test_nees_on_the_simulated_bags_within_the_chi_square_bound(bag):
    """
    The causal estimate of mu and w against the simulator's truth, sample by sample.

    With the sensor figures the bag was simulated with (``*.sensors.yaml``), the
    normalised estimation error squared e^T P^-1 e of mu and of w (the published
    momentum rate and its covariance) stays within the chi2_n 95 % quantile on at
    least 95 % of the samples after the first 1.5 s (the prior being forgotten).
    """
    from sim_samples import feed_stream
    from test_estimator_batch import _bag_stream
    from reduced_dynamics.estimator import Estimator, EstimatorConfig
    robot = load_robot(str(config_path('robots/freeflyer.urdf'))) \
        if bag.startswith('freeflyer') else load_robot()
    params = {**defaults(), **load_params_file(str(DATA / f'{bag}.sensors.yaml')),
              'prediction_rate': 0.0}
    stream, is_odom, base_driven = _bag_stream(bag, robot)
    estimator = Estimator(robot, EstimatorConfig.from_mapping(params), use_odometry=is_odom,
                          base_driven=base_driven)
    outputs = feed_stream(estimator, stream)
    mu_stamps, mu_truth = _ground_truth(bag, '/ground_truth/momentum')
    w_stamps, w_truth = _ground_truth(bag, '/ground_truth/external_wrench')
    axes = [0, 1, 5] if robot.n == 3 else list(range(6))
    nees_mu, nees_w = [], []
    for output in outputs:
        if output.stamp_ns < mu_stamps[0] + 1_500_000_000:
            continue
        true_mu = [np.interp(output.stamp_ns, mu_stamps, mu_truth[:, i]) for i in axes]
        held = max(np.searchsorted(w_stamps, output.stamp_ns, side='right') - 1, 0)
        rate = np.r_[output.momentum_rate.force, output.momentum_rate.torque][axes]
        error_mu, error_w = output.mu - true_mu, rate - w_truth[held, axes]
        nees_mu.append(error_mu @ np.linalg.solve(output.momentum_covariance, error_mu))
        nees_w.append(error_w @ np.linalg.solve(output.wrench_covariance, error_w))
    bound = chi2.isf(0.05, robot.n)  # the 95 % quantile (scipy.stats's import: 3.3 s)
    inside_mu = np.mean(np.array(nees_mu) <= bound)
    inside_w = np.mean(np.array(nees_w) <= bound)
    # Measured (inside mu, w; mean NEES mu, w): paper_realistic 0.989, 0.987 (4.4, 1.8 for
    # n = 6); paper_spacecraft 0.975, 0.987 (5.4, 1.7); freeflyer_realistic 0.975, 0.970
    # (1.9, 1.0 for n = 3); freeflyer_testbed 0.976, 0.983 (2.2, 1.2). The wrench's is
    # below n: the random-walk model is wider than the piecewise-constant thrust.
    assert len(nees_mu) > 400
    assert inside_mu >= 0.95 and inside_w >= 0.95, (inside_mu, inside_w)
    assert np.mean(nees_mu) <= robot.n and np.mean(nees_w) <= robot.n
