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
Issue 10's events on the realistic simulated bags, through the documented workflow.

Settings per bag: the replay defaults, the sensor figures the simulation used
(``test/data/*_realistic.sensors.yaml``) and ``reduced-dynamics tune BAG`` with its
defaults (``test/data/*_realistic.tuned.yaml``, scripts/make_test_bags.sh). Event
latencies are compared with the information bound of the bag's own sensor figures
(``estimator/detectability.py``). Measured values are in docs/events.md "Events on the
realistic simulated bags".
"""

import json
import math
from pathlib import Path

import numpy as np
import pytest

from reduced_dynamics.bag.reader import open_bag
from reduced_dynamics.estimator.detectability import detection_bound, step_information
from reduced_dynamics.params import defaults, load_params_file
from reduced_dynamics.replay import replay, ReplayOptions
from reduced_dynamics.resources import config_path
from reduced_dynamics.robot.model import load_robot

from filter_helpers import wrench_series

DATA = Path(__file__).parent / 'data'
SETTINGS = ('defaults', 'sensors', 'tuned')
#: The free-flyer's pose noise: 0.5 mm plus the 0.1 mm quantisation (step^2 / 12), 2 mrad.
FREEFLYER_POSE_SIGMA = (math.hypot(5e-4, 1e-4 / math.sqrt(12)),) * 2 + (2e-3,)
#: freeflyer_testbed's: the frame-to-frame noise measured on the freeflyer2 recordings.
TESTBED_POSE_SIGMA = (2.5e-5, 2.5e-5, 2e-4)


def _params(bag: str, setting: str) -> dict:
    params = defaults()
    if setting == 'spacecraft':
        # The shipped spacecraft settings (config/spacecraft.yaml), not tuned on the bag.
        params.update(load_params_file(str(config_path('spacecraft.yaml'))))
    elif setting != 'defaults':
        params.update(load_params_file(str(DATA / f'{bag}.{setting}.yaml')))
    return params


def _robot(bag: str):
    if bag.startswith('freeflyer'):
        robot = load_robot(str(config_path('robots/freeflyer.urdf')))
        return robot, {'base_pose_topic': '/base_pose'}
    return load_robot(), {}


def _relative_error(robot, estimate, truth) -> float:
    """Planar: the linear impulse of a push, the angular one of a pure torque firing."""
    estimate, truth = np.asarray(estimate, float), np.asarray(truth, float)
    if robot.n == 3:
        estimate = estimate[[0, 1, 5]] if len(estimate) == 6 else estimate
        truth = truth[[0, 1, 5]]
        part = slice(0, 2) if np.linalg.norm(truth[:2]) > 0.1 else slice(2, 3)
        estimate, truth = estimate[part], truth[part]
    return float(np.linalg.norm(estimate - truth) / np.linalg.norm(truth))


def _run(tmp_path, bag: str, setting: str, smooth: bool) -> tuple[list[dict], list[dict]]:
    """Replay; return per firing (latency, errors) and the events outside every firing."""
    truth = json.loads((DATA / f'{bag}.summary.json').read_text())
    robot, topics = _robot(bag)
    out = tmp_path / f'{bag}-{setting}-{smooth}'
    summary = replay(str(DATA / bag), str(out), robot,
                     ReplayOptions(params=_params(bag, setting), smooth=smooth, **topics))
    origin = truth['start_time_ns']
    rate = wrench_series(out, '/reduced_dynamics/drift/momentum_rate')
    seconds = (rate[:, 0] - origin) * 1e-9
    events = list(summary['events'])
    firings = []
    for firing in truth['firings'] or truth['pulses']:
        start, end = firing['start'], firing['start'] + firing['duration']
        window = (seconds >= start - 0.5) & (seconds <= end + 1.0)
        integral = np.trapezoid(rate[window, 1:], seconds[window], axis=0)
        mine = [e for e in events
                if start - 0.5 <= (e['start_stamp_ns'] - origin) * 1e-9 <= end]
        for event in mine:
            events.remove(event)
        first = mine[0] if mine else None
        firings.append({
            # Detection latency (what the information bound limits); the start a
            # multi-scale detection dates back to its window is 'start_error'.
            'latency': None if first is None else
            (first['detected_stamp_ns'] - origin) * 1e-9 - start,
            'start_error': None if first is None else
            (first['start_stamp_ns'] - origin) * 1e-9 - start,
            'event_error': None if first is None or first['impulse'] is None else
            _relative_error(robot, first['impulse'], firing['world_impulse']),
            'rate_error': _relative_error(robot, integral, firing['world_impulse'])})
    return firings, events


def _freeflyer_bounds(bag: str = 'freeflyer_realistic',
                      sigma=FREEFLYER_POSE_SIGMA) -> list[float]:
    """Information bound of each firing of a free-flyer bag (120 Hz poses, pose only)."""
    robot, _ = _robot(bag)
    inertia = robot.metric_blocks(np.zeros(0)).locked_inertia
    truth = json.loads((DATA / f'{bag}.summary.json').read_text())
    return [detection_bound(np.linalg.solve(inertia, np.array(f['body_delivered'])[[0, 1, 5]]),
                            120.0, sigma) for f in truth['firings']]


def _paper_bound(bag: str = 'paper_realistic', pose_sigma=(1e-3,) * 3 + (5e-4,) * 3,
                 twist_sigma=(2e-3,) * 6, joint_rate_sigma: float = 5e-3) -> float:
    """Information bound of a paper-robot bag's pulse (100 Hz odometry, its own figures)."""
    robot = load_robot()
    truth = json.loads((DATA / f'{bag}.summary.json').read_text())
    pulse = truth['pulses'][0]
    with open_bag(DATA / bag) as reader:
        for message in reader.messages(['/joint_states']):
            stamp = message.msg.header.stamp
            if stamp.sec * 10**9 + stamp.nanosec >= truth['start_time_ns'] + 3 * 10**9:
                qbar = np.array(message.msg.position)
                break
    blocks = robot.metric_blocks(qbar)
    acceleration = np.linalg.solve(blocks.locked_inertia, pulse['body_wrench'])
    # The twist noise plus the tachometers' through the connection A.
    twist = np.sqrt(np.asarray(twist_sigma) ** 2 +
                    joint_rate_sigma ** 2 * np.sum(blocks.connection ** 2, axis=1))
    return detection_bound(acceleration, 100.0, pose_sigma, twist)


#: paper_spacecraft's figures (paper_spacecraft.sensors.yaml): 0.1 m, 5e-5 rad; 1e-3 m/s,
#: 1e-4 rad/s; joint rates 1e-3 rad/s.
SPACECRAFT_FIGURES = ((0.1,) * 3 + (5e-5,) * 3, (1e-3,) * 3 + (1e-4,) * 3, 1e-3)


def test_information_bound_matches_its_continuous_limits():
    """Sums over samples against a^2 f tau^5 / (20 sigma^2) and a^2 f tau^3 / (3 sigma_v^2)."""
    a, f, tau = 0.3, 2000.0, 0.2
    assert step_information([a], tau, f, [1e-3]) == pytest.approx(
        a ** 2 * f * tau ** 5 / (20 * 1e-6), rel=0.01)
    assert step_information([a], tau, f, [1e9], [1e-2]) == pytest.approx(
        a ** 2 * f * tau ** 3 / (3 * 1e-4), rel=0.01)
    # The colleague's figures: 0.36 N on 16 kg at 120 Hz, 0.5 mm, chi2_3(1e-6) = 30.7,
    # needs ~0.3 s; flagging within 0.1 s needs ~5.7 N.
    assert detection_bound([0.36 / 16, 0, 0], 120.0, [5e-4, 5e-4, 2e-3]) == \
        pytest.approx(0.30, abs=0.01)
    assert detection_bound([5.7 / 16, 0, 0], 120.0, [5e-4, 5e-4, 2e-3]) == \
        pytest.approx(0.1, abs=0.01)


def test_bounds_of_the_shipped_bags():
    """No test can flag the free-flyer's pushes within 100 ms; the paper pulse just about."""
    bounds = _freeflyer_bounds()
    # pushes 0.36 / 0.34 / 0.36 N on 16 kg; the torque firing 0.087 N m on 0.18 kg m^2
    assert bounds == pytest.approx([0.300, 0.308, 0.158, 0.300], abs=0.005)
    assert _paper_bound() == pytest.approx(0.10, abs=0.005)
    # With the noise measured on the real testbed (25 um, 0.2 mrad) the pushes' bound
    # is 0.092 s, the torque firing's 0.058 s.
    assert _freeflyer_bounds('freeflyer_testbed', TESTBED_POSE_SIGMA) == \
        pytest.approx([0.092, 0.092, 0.058, 0.092], abs=0.005)


def test_paper_realistic_tuned_flags_the_pulse(tmp_path):
    """`tune` then replay: the 0.5 s, 20 N pulse flagged, its impulse within 10 %."""
    bound = _paper_bound()
    rate_errors = []
    for smooth in (False, True):
        (pulse,), others = _run(tmp_path, 'paper_realistic', 'tuned', smooth)
        assert others == []
        # Measured 0.140 s (bound 0.10 s): the statistic at 0.1 s fell short of its
        # median in this noise realisation (chi2_6 at 1e-6 is 38.3).
        assert pulse['latency'] is not None and 0.0 <= pulse['latency'] <= 1.5 * bound
        assert pulse['event_error'] <= 0.10       # measured 5.0 %
        rate_errors.append(pulse['rate_error'])
    # The integrated momentum rate: measured 10.6 % causal, 7.4 % smoothed (12.3 and
    # 2.7 % with the tuned file of before, tuned from the 1 mm default). The causal
    # figure moves with the phase of the 25 ms onset grid (9.8 % when the grid started
    # at the filter's first sample rather than 1 s later): the step's size is estimated
    # from the hypothesis nearest the true onset.
    assert rate_errors[0] <= 0.13 and rate_errors[1] <= 0.10


def test_freeflyer_realistic_tuned_events_against_the_bound(tmp_path):
    """The torque firing is flagged within 2x its bound; the pushes are not flagged."""
    bounds = _freeflyer_bounds()
    firings, others = _run(tmp_path, 'freeflyer_realistic', 'tuned', False)
    assert others == []
    torque = firings[2]
    # Measured 0.232 s against a bound of 0.158 s; event impulse 6.0 % (1.4 % before the
    # multi-scale test, whose window dates the start 0.115 s after the firing).
    assert bounds[2] <= torque['latency'] <= 2.0 * bounds[2]
    assert torque['event_error'] <= 0.10
    # The pushes (bounds 0.30-0.31 s), absorbed by the tuned random walk before the
    # step test has the evidence, are flagged by the multi-scale test (they were not
    # before it): measured 0.51 / 0.47 / 0.46 s, event impulse 37 / 4.6 / 8.7 % (the
    # first ends early and its impulse is short), impulses integrated 1.0-2.0 % causal.
    for push, bound in zip((firings[0], firings[1], firings[3]), bounds[:2] + bounds[3:]):
        assert push['latency'] is not None and bound <= push['latency'] <= 2.0 * bound
        assert push['rate_error'] <= 0.10
    assert firings[1]['event_error'] <= 0.10 and firings[3]['event_error'] <= 0.10
    smoothed, _ = _run(tmp_path, 'freeflyer_realistic', 'tuned', True)
    assert all(f['rate_error'] <= 0.10 for f in smoothed)  # measured 0.2-2.5 %


def test_freeflyer_testbed_tuned_flags_every_firing(tmp_path):
    """
    The free-flyer with the real testbed's mocap noise, `tune` then replay.

    Every firing is flagged and its impulse recovered; the torque firing within
    100 ms, the 0.34-0.36 N pushes after 2-3x their 0.092 s bound (the tuned random
    walk, 0.012 m/s^3/sqrt(Hz), absorbs part of each push before the step test has
    the evidence).
    """
    bounds = _freeflyer_bounds('freeflyer_testbed', TESTBED_POSE_SIGMA)
    firings, others = _run(tmp_path, 'freeflyer_testbed', 'tuned', False)
    assert others == []
    # Measured latency 0.108 / 0.133 / 0.074 / 0.133 s (0.201 / 0.224 / 0.074 / 0.275
    # before the multi-scale test); event impulse 1.8 / 0.7 / 2.2 / 2.5 %; rate
    # integral 0.6 / 3.6 / 4.4 / 1.5 % causal.
    for firing, bound in zip(firings, bounds):
        assert firing['latency'] is not None and bound <= firing['latency'] <= 1.5 * bound
        assert firing['event_error'] <= 0.10 and firing['rate_error'] <= 0.10
    assert firings[2]['latency'] <= 0.1
    smoothed, others = _run(tmp_path, 'freeflyer_testbed', 'tuned', True)
    assert others == []
    assert all(f['rate_error'] <= 0.02 for f in smoothed)   # measured 0.1-0.5 %


def test_paper_spacecraft_flags_the_pulse_within_100_ms(tmp_path):
    """
    The same pulse seen by a spacecraft's navigation, replayed with config/spacecraft.yaml.

    The velocity (1e-3 m/s) and attitude-rate (1e-4 rad/s) figures bring the information
    bound from 0.10 s (paper_realistic) to 0.02 s; the step test flags within 100 ms.
    """
    bound = _paper_bound('paper_spacecraft', *SPACECRAFT_FIGURES)
    assert bound == pytest.approx(0.02, abs=0.005)
    rate_errors = []
    for smooth in (False, True):
        (pulse,), others = _run(tmp_path, 'paper_spacecraft', 'spacecraft', smooth)
        assert others == []                       # no event while coasting
        # Measured 0.020 s causal (the multi-scale test at the 2nd odometry sample; the
        # bound is at the nominal sample time, the stamp jitters by 0.3 ms).
        assert pulse['latency'] is not None and bound - 1e-3 <= pulse['latency'] <= 0.1
        assert pulse['event_error'] <= 0.10       # measured 3.0 %
        rate_errors.append(pulse['rate_error'])
    # The integrated momentum rate: measured 2.7 % causal, 1.3 % smoothed.
    assert rate_errors[0] <= 0.10 and rate_errors[1] <= 0.10


@pytest.mark.parametrize('bag', ['paper_realistic', 'freeflyer_realistic', 'freeflyer_testbed'])
@pytest.mark.parametrize('setting', SETTINGS)
def test_no_events_while_coasting(tmp_path, bag, setting):
    """Every event starts within a firing, whatever the settings (causal)."""
    _, others = _run(tmp_path, bag, setting, False)
    assert others == []


@pytest.mark.parametrize('params', ['defaults', 'paper_realistic.tuned',
                                    'paper_realistic.sensors'])
def test_no_events_on_paper_constant(tmp_path, params):
    """A coasting bag (torques only, no wrench): no event with any of the settings."""
    values = defaults()
    if params != 'defaults':
        values.update(load_params_file(str(DATA / f'{params}.yaml')))
    summary = replay(str(DATA / 'paper_constant'), str(tmp_path / 'out'), load_robot(),
                     ReplayOptions(params=values, smooth=False))
    assert summary['events'] == [] and summary['filter']['steps_taken'] == 0
