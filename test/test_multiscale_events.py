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

"""Multi-scale event detection (estimator/multiscale.py, docs/multiscale_events.md)."""

import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from reduced_dynamics.cli import main as cli_main
from reduced_dynamics.chi_square import chi2
from reduced_dynamics.estimator.multiscale import (EXCESS_MINIMUM, MomentumBlocks,
                                                   MultiScaleTest, window_bank)

URDF = str(Path(__file__).parent / 'data' / 'freeflyer_arm.urdf')


def test_window_bank_is_geometric_from_50_ms_to_3_s():
    windows = window_bank()
    assert windows[0] == pytest.approx(0.05) and windows[-1] == pytest.approx(3.0)
    assert np.all(windows[1:] / windows[:-1] <= 1.5 + 1e-9)


def test_threshold_follows_the_false_alarm_rate_and_the_update_rate():
    test = MultiScaleTest(3, 1.0)
    cov = np.eye(3) * 1e-4
    for k in range(300):
        test.update(k * 10_000_000, np.zeros(3), cov)
    windows = len(test.windows)
    assert test.threshold == pytest.approx(chi2.isf(1.0 * 0.01 / 3600 / windows, 3), rel=1e-3)


def test_a_momentum_change_is_found_and_dated_by_its_window():
    test = MultiScaleTest(3, 1.0)
    cov = np.eye(3) * 1e-4
    rng = np.random.default_rng(1)
    found = None
    for k in range(400):
        mu = rng.normal(0.0, 0.005, 3)
        if k >= 200:   # a constant wrench from 2 s: mu ramps at 0.1 per second
            mu[0] += 0.1 * (k - 200) * 0.01
        detection = test.update(k * 10_000_000, mu, cov)
        if detection is not None:
            found = (k, detection)
            break
    assert found is not None
    k, detection = found
    assert 2.0 < k * 0.01 < 3.0   # measured 2.78 s: d^2 / 2e-4 reaches ~35 at 0.8 s
    assert abs(detection.start_ns * 1e-9 - 2.0) <= 0.3


NS = 1_000_000_000
#: A measured momentum's white noise (n = 3), 100 Hz.
NOISE = np.diag([0.05, 0.05, 0.02]) ** 2


class Normal:
    """
    ``rng.multivariate_normal(zeros, cov)`` for one ``cov``: the same draws, the factor once.

    numpy's Generator (method 'svd') factors and checks ``cov`` on every call (~0.1 ms,
    most of these tests' data); here the factor is formed once as it forms it, and
    a draw is ``standard_normal(n) @ factor + 0``: the same bits
    (:func:`test_normal_draws_are_multivariate_normals`).
    """

    def __init__(self, cov):
        _, s, vh = np.linalg.svd(cov)
        self.factor = np.sqrt(s)[:, None] * vh
        self.zeros = np.zeros(cov.shape[0])

    def __call__(self, rng):
        x = rng.standard_normal(self.zeros.shape[0])[None] @ self.factor
        x += self.zeros
        return x[0]


def test_normal_draws_are_multivariate_normals():
    for cov in (NOISE, 4.0 * NOISE, 0.05 * NOISE, np.eye(3) * 0.05 ** 2, np.eye(3),
                np.diag([5.0, 5.0, 0.5]) ** 2, np.eye(2) * 1e-3 ** 2):
        draw, theirs, ours = Normal(cov), np.random.default_rng(4), np.random.default_rng(4)
        expected = np.array([theirs.multivariate_normal(np.zeros(len(cov)), cov)
                             for _ in range(300)])
        # Bytes, not values: a -0.0 for a 0.0 would be a different draw.
        assert np.array([draw(ours) for _ in range(300)]).tobytes() == expected.tobytes()


def _blocks(seconds: float, rng, scale: float = 1.0, push=None) -> list:
    """Measured momenta at 100 Hz: N(0, scale^2 NOISE), plus a ramp (start, duration, J)."""
    out, noise = [], Normal(scale ** 2 * NOISE)
    for k in range(int(seconds * 100)):
        t = k / 100
        mu = noise(rng)
        if push is not None:
            start, duration, impulse = push
            mu += np.asarray(impulse) * min(max((t - start) / duration, 0.0), 1.0)
        out.append((k * NS // 100, mu))
    return out


def test_block_statistics_are_chi_square_without_a_wrench():
    # T_L of measured momenta with their own white noise is chi2_n: at the 1 % quantile
    # each window exceeds 1 % of the time (the excess noise learnt is ~0, at most
    # slightly positive, which makes the test a little conservative).
    blocks = MomentumBlocks(3, window_bank())
    rng = np.random.default_rng(5)
    quantile = chi2.isf(0.01, 3)
    above, counted = np.zeros(len(blocks.windows)), np.zeros(len(blocks.windows))
    for stamp, mu in _blocks(300.0, rng):
        blocks.add(stamp, mu, NOISE)
        if blocks.update(stamp, None) >= 0:
            covered = blocks.statistics > 0
            counted += covered
            above += covered & (blocks.statistics > quantile)
    short = blocks.windows <= 0.5  # many independent blocks in 300 s
    fraction = above[short] / counted[short]
    assert np.all((fraction > 0.004) & (fraction < 0.016)), fraction
    assert np.all(np.abs(np.diag(blocks.excess)) < 0.05 * np.diag(NOISE))


def test_the_excess_noise_is_learnt_from_successive_differences():
    # Noise twice as large as reported: the excess (3 NOISE) is learnt within 15 %, and
    # the statistics are chi2 again.
    blocks = MomentumBlocks(3, window_bank())
    rng = np.random.default_rng(6)
    quantile = chi2.isf(0.01, 3)
    above = counted = 0
    for stamp, mu in _blocks(200.0, rng, scale=2.0):
        blocks.add(stamp, mu, NOISE)
        if blocks.update(stamp, None) >= 0:
            counted += 1
            above += blocks.statistics[2] > quantile
    assert np.allclose(np.diag(blocks.excess), 3 * np.diag(NOISE), rtol=0.15)
    assert 0.004 < above / counted < 0.02
    assert not MomentumBlocks(3, window_bank()).ready and EXCESS_MINIMUM >= 100


def test_a_long_weak_push_is_found_by_the_measured_momenta():
    # A 3 s push of 0.12 (2.4 sigma of one sample, 30 of the difference of two 3 s
    # blocks) the filtered momentum cannot show (its covariance, like a random-walk
    # filter's, is 0.05^2):
    # without measured momenta nothing is found; with them the first detection is
    # dated near the push, mu before within 3 sigma of 0.
    rng = np.random.default_rng(7)
    push = (20.0, 3.0, [0.12, 0.0, 0.0])
    samples = _blocks(30.0, rng, push=push)
    filtered = np.eye(3) * 0.05 ** 2
    plain, measured = MultiScaleTest(3, 1.0), MultiScaleTest(3, 1.0)
    found, draw = [], Normal(filtered)
    for stamp, mu in samples:
        mu_hat = draw(rng) + \
            np.array(push[2]) * min(max((stamp / NS - 20.0) / 3.0, 0.0), 1.0)
        assert plain.update(stamp, mu_hat, filtered) is None
        detection = measured.update(stamp, mu_hat, filtered, [(stamp, mu, NOISE)])
        if detection is not None:
            found.append((stamp, detection))
            measured.reset(stamp)
    (stamp, detection) = found[0]  # the rest of the push after the reset follows it
    assert detection.measured
    # Measured: dated 19.42 s, flagged at 21.49 s with 1.5 s of a weak ramp seen: the
    # fitted ramp's start is loose then (the table's 3 s pushes: -0.24 s median).
    assert abs(detection.start_ns / NS - 20.0) <= 0.75
    assert 20.0 < stamp / NS <= 26.0  # measured 21.49 s: while it pushes
    assert np.all(np.abs(detection.mu_before) <= 3 * np.sqrt(np.diag(detection.cov_before)))


def _free_flyer_push(tmp_path, duration: float, seed: int, thruster: str) -> tuple:
    """Simulate the arm-carrying free-flyer with a push, replay it causally; (summary, truth)."""
    bag, truth = tmp_path / 'bag', tmp_path / 'truth.json'
    assert cli_main(['simulate', '-o', str(bag), '--summary', str(truth), '--urdf', URDF,
                     '--duration', str(duration), '--rate', '62.5', '--seed', str(seed),
                     '--torque', 'pd', '--momentum-class', 'zero', '--thruster', thruster,
                     '--noise-position', '1e-3', '--noise-velocity', '0.005',
                     '--noise-pose', '0.001', '--noise-orientation', '0.001',
                     '--noise-twist', '0.003']) == 0
    params = tmp_path / 'params.yaml'
    params.write_text(yaml.safe_dump({'/**/reduced_dynamics': {'ros__parameters': {
        'pose_position_noise': 1e-3, 'pose_angle_noise': 1e-3, 'twist_linear_noise': 3e-3,
        'twist_angular_noise': 3e-3, 'joint_velocity_noise': 5e-3}}}))
    summary_file = tmp_path / 'summary.json'
    assert cli_main(['replay', str(bag), '-o', str(tmp_path / 'out'), '--quiet',
                     '--no-smooth', '--params', str(params), '--summary-json',
                     str(summary_file), '--urdf', URDF]) == 0
    return json.loads(summary_file.read_text()), truth


def test_a_light_push_on_a_small_free_flyer_with_a_moving_arm(tmp_path):
    """
    The issue's case: a 0.37 N, 1 s push on a free-flyer (16 kg) whose arm moves.

    Base pose 1 mm / 1 mrad and twist 3 mm/s at 62.5 Hz. Before the multi-scale test
    no event was flagged (the per-sample chi-square and the step test weigh a step
    against the random walk). Now one event, starting within 0.5 s of the push, its
    impulse within 10 % and within 3 sigma of its reported covariance; none while only
    the arm moves.
    """
    summary, truth = _free_flyer_push(tmp_path, 12, 3, '6,1,0.37,0,0,0,0,0')
    pulse = json.loads(truth.read_text())['pulses'][0]
    (event,) = summary['events']
    origin = json.loads(truth.read_text())['start_time_ns']
    start = (event['start_stamp_ns'] - origin) * 1e-9
    # Measured: start 6.18 s, detected at 6.35 s by the 1.9 s window.
    assert abs(start - 6.0) <= 0.5
    impulse = np.array(event['impulse'])
    true = np.array(pulse['world_impulse'])[[0, 1, 5]]
    sigma = np.sqrt(np.diag(event['impulse_cov']))
    # Measured (3a3a89e) error 0.003 / 0.011 / 0.001 against sigma 0.008 / 0.008 / 0.006:
    # 3.1 % of the linear impulse (both ends from the measured twists' momenta; before,
    # from the filtered momentum: 14-17 %).
    assert np.all(np.abs(impulse - true) <= 3.0 * sigma)
    assert np.linalg.norm(impulse[:2] - true[:2]) <= 0.10 * np.linalg.norm(true[:2])
    assert event['window_s'] is not None


def test_the_last_event_is_in_the_diagnostics():
    from reduced_dynamics.estimator.events import EventDetector
    from reduced_dynamics.estimator.reporting import _last_event
    detector = EventDetector(3, 1e-6, 0.1, 1.0)
    cov = np.eye(3) * 1e-4
    for k in range(600):
        mu = np.array([0.1 * max(0, min(k - 200, 100)) * 0.01, 0.0, 0.0])
        detector.update(k * 10_000_000, mu, 0.0, 0.0, False, cov)
    (event,) = detector.events
    fields = _last_event(detector.events)
    assert event.window is not None and fields['last_event_window'] == f'{event.window:.3g}'
    assert float(fields['last_event_impulse'].split()[0]) == pytest.approx(0.1, abs=0.01)
    assert fields['last_event_impulse_sigma'].split()[0] == f'{np.sqrt(2e-4):.3g}'


def _linear_error(estimate, truth) -> float:
    estimate, truth = np.asarray(estimate, float)[:3], np.asarray(truth, float)[:3]
    return float(np.linalg.norm(estimate - truth) / np.linalg.norm(truth))


def test_a_short_pulse_on_a_humanoid_on_a_bus(tmp_path):
    """
    The issue's second case: a 20 N, 0.3 s pulse at 5 s on a 500 kg bus with a humanoid.

    The humanoid: 29 joints, 70 kg (robot/humanoid_bus.py), under PD tracking. 500 Hz,
    pose 1 mm / 1 mrad, velocities 0.01. Measured (3a3a89e): one event, dated 4.958 s,
    detected at 5.264 s (the block test's 0.57 s window); its linear impulse 2.6 % off
    (0.70 / -5.17 / -2.83 N s against 0.59 / -5.27 / -2.80; both ends of the impulse
    from the measured momenta; 7.8 % before the centre of mass joined the blocks).
    Before the measured momenta (a 29-joint random tree stood in): 21 %.
    """
    from reduced_dynamics.robot.humanoid_bus import humanoid_on_bus_urdf
    urdf = tmp_path / 'humanoid_on_bus.urdf'
    urdf.write_text(humanoid_on_bus_urdf())
    bag, truth = tmp_path / 'bag', tmp_path / 'truth.json'
    assert cli_main(['simulate', '-o', str(bag), '--summary', str(truth), '--urdf', str(urdf),
                     '--duration', '10', '--rate', '500', '--seed', '4', '--torque', 'pd',
                     '--momentum-class', 'zero', '--thruster', '5,0.3,20,0,0,0,0,0',
                     '--noise-position', '1e-4', '--noise-velocity', '0.01',
                     '--noise-pose', '0.001', '--noise-orientation', '0.001',
                     '--noise-twist', '0.01']) == 0
    params = tmp_path / 'params.yaml'
    params.write_text(yaml.safe_dump({'/**/reduced_dynamics': {'ros__parameters': {
        'pose_position_noise': 1e-3, 'pose_angle_noise': 1e-3, 'twist_linear_noise': 0.01,
        'twist_angular_noise': 0.01, 'joint_velocity_noise': 0.01}}}))
    summary_file = tmp_path / 'summary.json'
    assert cli_main(['replay', str(bag), '-o', str(tmp_path / 'out'), '--quiet',
                     '--no-smooth', '--params', str(params), '--summary-json',
                     str(summary_file), '--urdf', str(urdf)]) == 0
    summary = json.loads(summary_file.read_text())
    truth = json.loads(truth.read_text())
    origin = truth['start_time_ns']
    (event,) = summary['events']
    assert abs((event['start_stamp_ns'] - origin) * 1e-9 - 5.0) <= 0.5
    assert 0.0 <= (event['detected_stamp_ns'] - origin) * 1e-9 - 5.0 <= 0.5
    assert _linear_error(event['impulse'], truth['pulses'][0]['world_impulse']) <= 0.10


def test_the_measured_momentum_bound_is_where_the_block_statistic_reaches_its_threshold():
    # Noise-free measured momenta with a step of the bound's impulse inside the gap of
    # one window: that window's statistic is the chi2_n quantile the bound was set at.
    from reduced_dynamics.estimator.detectability import measured_momentum_bound
    blocks = MomentumBlocks(3, window_bank())
    window = 7
    length = blocks.windows[window]
    significance = 1e-9
    impulse = measured_momentum_bound(NOISE, [1.0, 0.0, 0.0], length, 100.0, significance)
    step_at = 5.0
    end = step_at + 1.5 * length  # the step in the middle of the gap (t - 2L, t - L]
    for k in range(int(end * 100) + 1):
        mu = np.array([impulse if k / 100 >= step_at else 0.0, 0.0, 0.0])
        blocks.add(k * NS // 100, mu, NOISE)
    assert blocks.ready and not blocks.excess.any()
    blocks.update(int(end * 100) * NS // 100, None)
    # The blocks hold floor(L f) samples, not L f: within 2 %.
    assert blocks.statistics[window] == pytest.approx(chi2.isf(significance, 3), rel=0.02)


def test_a_lasting_push_is_located_once_not_at_every_sample(monkeypatch):
    # Issue 27: a push that goes on (in the soak, twists that disagree with the arm's
    # motion) keeps the block statistic above its threshold at every sample. The fit
    # that dates a pulse (MomentumBlocks.locate, ~points^2 x the window's samples) is
    # needed only to open an event; run at every sample it cost the node ~10 ms each.
    from reduced_dynamics.estimator.events import EventDetector
    calls = []
    locate = MomentumBlocks.locate

    def counted(self, *args, **kwargs):
        calls.append(args[0])
        return locate(self, *args, **kwargs)
    monkeypatch.setattr(MomentumBlocks, 'locate', counted)
    detector = EventDetector(3, 1e-6, 0.1, 1.0)
    rng = np.random.default_rng(11)
    filtered = np.eye(3) * 0.05 ** 2
    samples = 0
    for stamp, mu in _blocks(40.0, rng, push=(10.0, 1000.0, [3000.0, 0.0, 0.0])):
        drift = np.array([3000.0 * max(stamp / NS - 10.0, 0.0) / 1000.0, 0.0, 0.0])
        detector.update(stamp, drift, 0.0, 0.0, False, filtered, [(stamp, mu, NOISE)])
        samples += 1
    assert detector.in_event and len(detector.events) >= 1
    # Before: located at every sample from the detection on (2 991 of 4 000).
    assert len(calls) <= len(detector.events) < 5, (len(calls), samples)


#: A heavy base (500 kg) with noisy velocities: the measured momenta's white noise
#: (5 N s linear per sample), and its 1 mm positions at 100 Hz.
MASS = 500.0
HEAVY = np.diag([5.0, 5.0, 0.5]) ** 2
POSITION = np.eye(2) * 1e-3 ** 2


def _heavy(seconds: float, rng, push=None, velocity=(0.02, -0.01)) -> list:
    """Measured momenta and centre-of-mass positions of a coasting heavy base (push: J)."""
    out, c = [], np.zeros(2)
    p = MASS * np.asarray(velocity, float)
    heavy, position = Normal(HEAVY), Normal(POSITION)
    for k in range(int(seconds * 100)):
        t = k / 100
        momentum = np.array([*p, 0.0])
        if push is not None:
            start, duration, impulse = push
            momentum[0] += impulse * min(max((t - start) / duration, 0.0), 1.0)
        if k:
            c = c + momentum[:2] / MASS * 0.01
        mu = momentum + heavy(rng)
        measured = c + position(rng)
        out.append((k * NS // 100, mu, (measured, POSITION, MASS, (0, 1))))
    return out


def test_block_statistics_with_positions_are_chi_square_without_a_wrench():
    # The centre of mass on a line joins each block (its slope times the mass): T_L
    # stays chi2_n, each window above the 1 % quantile 1 % of the time.
    blocks = MomentumBlocks(3, window_bank())
    rng = np.random.default_rng(8)
    quantile = chi2.isf(0.01, 3)
    above, counted = np.zeros(len(blocks.windows)), np.zeros(len(blocks.windows))
    for stamp, mu, position in _heavy(200.0, rng):
        blocks.add(stamp, mu, HEAVY, None, position)
        if blocks.update(stamp, None) >= 0:
            covered = blocks.statistics > 0
            counted += covered
            above += covered & (blocks.statistics > quantile)
    short = blocks.windows <= 0.5
    fraction = above[short] / counted[short]
    assert np.all((fraction > 0.004) & (fraction < 0.02)), fraction


def test_a_slow_push_on_a_heavy_base_is_found_by_the_measured_positions():
    # A 3 s push of 1.5 N s on 500 kg: the twists' 3 s blocks know the momentum to
    # 0.41 N s (their difference: non-centrality ~7, under the threshold of ~50); the
    # 1 mm positions' line fits to 0.03 N s. Without positions nothing is found; with
    # them one detection while it pushes, dated within 0.75 s.
    rng = np.random.default_rng(9)
    push = (20.0, 3.0, 1.5)
    filtered = np.eye(3) * 1.0
    twists, fused = MultiScaleTest(3, 1.0), MultiScaleTest(3, 1.0)
    found, draw = [], Normal(filtered)
    for stamp, mu, position in _heavy(32.0, rng, push=push):
        mu_hat = draw(rng)
        assert twists.update(stamp, mu_hat, filtered, [(stamp, mu, HEAVY)]) is None
        detection = fused.update(stamp, mu_hat, filtered, [(stamp, mu, HEAVY, None, position)])
        if detection is not None:
            found.append((stamp, detection))
            fused.reset(stamp)
    stamp, detection = found[0]
    assert detection.measured
    assert 20.0 < stamp / NS <= 26.0
    assert abs(detection.start_ns / NS - 20.0) <= 0.75


def test_a_push_that_goes_on_after_its_event_ended_continues_it():
    """
    A 3 s push of 12 N s on 500 kg (4 N): one event with its whole impulse.

    Its event ends while it goes on (the still-moving windows, up to half the detecting
    0.85 s, miss 4 N on 500 kg). No window reaches back before an end, so the detecting
    window finds the push again only once its blocks are covered: measured 1.7 s after
    the end, dated 0.1 s after it. The re-opening of a just-ended event lasted SETTLE
    (1 s): two events, the first with 48 % of the impulse (the bus's 3 s push at 30x
    the bound, docs/multiscale_events.md). Now it lasts the event's horizon, SETTLE +
    3 windows. Seeds 1-20 here: 5 split before, none now (none either since a continued
    stretch ends by its continuing window's criteria: the end 12.73 s, 13.44 s before).
    """
    from reduced_dynamics.estimator.events import EventDetector
    rng = np.random.default_rng(4)
    detector = EventDetector(3, 1e-6, 0.1, 1.0)
    notices = []
    for stamp, mu, position in _heavy(22.0, rng, push=(10.0, 3.0, 12.0)):
        # The filtered momentum flat: only the block test runs.
        detector.update(stamp, np.zeros(3), 0.0, 0.0, False, np.eye(3),
                        [(stamp, mu, HEAVY, None, position)])
        notices += [(stamp, n) for n in detector.take_notices()]
    (event,) = detector.events
    assert abs(event.start_ns / NS - 10.0) <= 0.5
    assert 12.5 <= event.end_ns / NS <= 13.0 + 3 * event.window  # measured 12.73 s
    assert event.impulse[0] == pytest.approx(12.0, rel=0.05)  # measured 11.93
    # Announced once, final once: after the horizon in which the push could go on.
    assert [n.final for _, n in notices] == [False, True]
    assert notices[1][0] > event.end_ns + event.horizon(True) * NS


def test_an_events_horizon_without_a_continuation_pauses_nothing():
    """
    After an event's end, nothing pauses predictions while its horizon runs.

    The horizon (SETTLE + 3 windows) only keeps the event's record open for a
    continuation (and its final notice waiting); an event is under way, which pauses
    predictions (processing.py: a row is quiet when no event is), from its detection
    to its end. A 0.3 s push of 6 N s on 500 kg, nothing after it: one event, no
    continuation, every row from its end to its final notice quiet (measured: found
    by the 0.57 s window, ended at 10.8 s, final at 13.51 s).
    """
    from reduced_dynamics.estimator.events import EventDetector, SETTLE
    rng = np.random.default_rng(4)
    detector = EventDetector(3, 1e-6, 0.1, 1.0)
    rows, final_at = [], None
    for stamp, mu, position in _heavy(20.0, rng, push=(10.0, 0.3, 6.0)):
        detector.update(stamp, np.zeros(3), 0.0, 0.0, False, np.eye(3),
                        [(stamp, mu, HEAVY, None, position)])
        rows.append((stamp, detector.in_event))
        if any(n.final for n in detector.take_notices()):
            final_at = stamp
    (event,) = detector.events
    assert event.end_ns is not None and final_at is not None
    horizon = [paused for stamp, paused in rows if event.end_ns <= stamp <= final_at]
    # The record waited beyond SETTLE for a continuation that did not come ...
    assert final_at > event.end_ns + SETTLE * NS
    assert final_at > event.end_ns + event.horizon(True) * NS
    # ... and no row of that wait was paused.
    assert len(horizon) > 100 and not any(horizon)


def test_warm_up_loads_the_block_kernels():
    # The block test is compiled (estimator/core/blocks.py) and the node's warm-up
    # loads it with the argument types replay passes (a fresh process: nothing loaded).
    from filter_helpers import fresh_process_words
    code = ('from reduced_dynamics.estimator.core.warmup import warm_up; warm_up(); '
            'from reduced_dynamics.estimator.core import blocks as b; '
            'import numpy as np; '
            'from reduced_dynamics.estimator.multiscale import MomentumBlocks, window_bank; '
            'kernels = (b.bank_statistics, b.block_mean, b.accumulate, '
            'b.accumulate_position, b.learn_excess, b.sample_information, b.add_sample); '
            'before = [len(k.signatures) for k in kernels]; '
            'm = MomentumBlocks(3, window_bank()); m._differences = 10 ** 6; '
            '[m.add(k * 10 ** 7, np.zeros(3), np.eye(3), np.zeros((3, 3)), '
            '(np.zeros(2), np.eye(2), 5.0, (0, 1))) for k in range(400)]; '
            'm.update(399 * 10 ** 7, None); '
            'print(min(before) > 0, before == [len(k.signatures) for k in kernels])')
    assert fresh_process_words(code) == ['True', 'True']


def test_a_long_push_is_one_event_with_its_whole_impulse(tmp_path):
    """
    A 3 s push at 30x the bound on the small free-flyer: one event, the whole impulse.

    Before, the event ended when the wrench estimate's chi-square dipped while the
    push went on: 40 % of the impulse missed (the detection table's 3 s, 30x row). Now
    it goes on while the measured momenta still move (multiscale.still_moving).
    """
    summary, truth = _free_flyer_push(tmp_path, 16, 100, '5,3,0.113,0,0,0,0,0')
    truth = json.loads(truth.read_text())
    origin = truth['start_time_ns']
    (event,) = summary['events']
    assert 4.5 <= (event['start_stamp_ns'] - origin) * 1e-9 <= 8.5
    assert event['end_s'] is not None and event['end_s'] >= 8.0 - 0.5
    assert _linear_error(event['impulse'][:2] + [0.0],
                         truth['pulses'][0]['world_impulse'][:2] + [0.0]) <= 0.10


def test_the_null_is_calibrated_from_the_tests_own_median():
    # Measured momenta with a slow error the noise model does not know (an AR(1) of 2 s,
    # which successive differences do not see): the 3 s blocks' T_L is then ~6 chi2_n
    # and the union bound no longer holds (measured: 3 false detections in the first
    # 83 s). The median of the quiet updates' T_L gives the inflation (measured 5.8 at
    # 3 s, 1.0 at 50 ms); after 5 calibration memories (60 s here) none.
    rng = np.random.default_rng(11)
    test = MultiScaleTest(3, 1.0, calibration_memory=60.0)
    filtered = np.eye(3) * 1e-2
    slow, keep = np.zeros(3), np.exp(-0.02 / 2.0)
    late, slow_noise, noise = 0, Normal(0.05 * NOISE), Normal(NOISE)
    for k in range(50 * 600):
        stamp = k * NS // 50
        slow = keep * slow + np.sqrt(1 - keep ** 2) * slow_noise(rng)
        mu = noise(rng) + slow
        detection = test.update(stamp, np.zeros(3), filtered, [(stamp, mu, NOISE)])
        if detection is not None:
            test.reset(stamp)
            late += k >= 50 * 300
    assert test.inflation[1, -1] > 3.0 and test.inflation[1, 0] < 1.5
    assert late == 0
