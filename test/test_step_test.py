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

"""The anchored wrench-step test against the explicit GLR bank (docs/step_test.md)."""

import numpy as np
import pinocchio as pin
import pytest

from reduced_dynamics.estimator.filter import Linearisation, MomentumFilter, NoiseModel
from reduced_dynamics.estimator.step_reference import ExplicitStepTest
from reduced_dynamics.estimator.step_test import GLR_HYPOTHESES, WrenchStepTest
from reduced_dynamics.geometry.lie_group import SUBGROUPS


class _Recorder:
    """Stands in for a filter's step test: forwards every call and keeps a copy of it."""

    #: the filter's compiled row step (step_row.py) would run the test without these
    #: calls: the recorded runs take the calls it replaces (tested equal in test_step_row)
    active = False

    def __init__(self, test: WrenchStepTest) -> None:
        self.test, self.calls = test, []

    def __getattr__(self, name: str):
        return getattr(self.test, name)

    def reset(self, settle_from_ns=None) -> None:
        self.calls.append(('reset', settle_from_ns))
        self.test.reset(settle_from_ns)

    def propagate(self, stamp_ns: int, transition: np.ndarray) -> None:
        self.calls.append(('propagate', stamp_ns, transition.copy()))
        self.test.propagate(stamp_ns, transition)

    def update(self, h, s, gain, nu):
        self.calls.append(('update', h.copy(), s.copy(), gain.copy(), nu.copy()))
        return self.test.update(h, s, gain, nu)


def _replay(test, calls: list) -> list:
    """Feed recorded calls to ``test``; return its answer per update (None or a detection)."""
    answers = []
    for call in calls:
        if call[0] == 'reset':
            test.reset(call[1])
        elif call[0] == 'propagate':
            test.propagate(call[1], call[2])
        else:
            answers.append(test.update(*call[1:]))
    return answers


def _record(group_name: str, twist: bool, rate: float, force: float, seconds: float,
            seed: int) -> tuple[MomentumFilter, list]:
    """
    Run a body whose wrench steps on at 1.5 s and off at 3 s; return its step-test calls.

    Planar: 16 kg, pose only, 1 mm / 2 mrad. SE(3): a rigid body with pose and twist
    (the paper robot's measurement layout), 1 mm / 0.5 mrad, 2e-3 m/s and rad/s. The
    wrench random walk is slow (0.002): a fast one absorbs a step before the test sees it.
    """
    group = SUBGROUPS[group_name]
    n = group.dim
    rng = np.random.default_rng(seed)
    diagonal = [16.0, 16.0, 0.18] if n == 3 else [16.0] * 3 + [0.2, 0.25, 0.18]
    locked = np.diag(diagonal)
    lin = Linearisation(locked, np.linalg.inv(locked), np.zeros(n), np.zeros((n, n)))
    noise = NoiseModel(pose_position=1e-3, pose_angle=2e-3 if n == 3 else 5e-4,
                       twist_linear=2e-3, twist_angular=2e-3, jerk_linear=0.002,
                       jerk_angular=0.002)
    flt = MomentumFilter(group, noise, 1e-6, step_significance=1e-6)
    recorder = _Recorder(flt.step_test)
    flt.step_test = recorder
    g, x = group.exp(np.zeros(n)), np.zeros(2 * n)
    direction = np.ones(n) / np.sqrt(n)
    sub, dt = 10, 1.0 / rate
    for k in range(int(seconds * rate)):
        t = k * dt
        x = x.copy()
        x[n:] = force * direction * np.array(diagonal) / 16.0 if 1.5 <= t < 3.0 else 0.0
        for _ in range(sub):
            g, x = flt.propagate_mean(g, x, lin, dt / sub)
        pose = g * group.exp(np.sqrt(flt._pose_var) * rng.normal(size=n))
        meas = None
        if twist:
            meas = flt.twist(g, x[:n], lin) + np.sqrt(flt._twist_var) * rng.normal(size=n)
        flt.step(int(round(t * 1e9)), lin, pose, meas)
    return flt, recorder.calls


@pytest.mark.parametrize('group_name,twist,rate,force', [
    ('SE(2)', False, 120.0, 5.0), ('SE(3)', True, 100.0, 2.0)])
def test_anchored_test_takes_the_explicit_banks_steps(group_name, twist, rate, force) -> None:
    """The same detections at the same updates, with the same step, correction and P."""
    flt, calls = _record(group_name, twist, rate, force, 4.0, seed=3)
    assert flt.steps_taken >= 2     # on and off (more: the filter's own overshoot)
    n, dim = flt.n, flt.dim
    explicit = _replay(ExplicitStepTest(n, 1e-6, dim), calls)
    anchored = _replay(WrenchStepTest(n, 1e-6, dim), calls)
    found = [k for k, a in enumerate(explicit) if a is not None]
    assert found == [k for k, a in enumerate(anchored) if a is not None]
    assert len(found) == flt.steps_taken
    for k in found:
        a, b = explicit[k], anchored[k]
        assert b.statistic == pytest.approx(a.statistic, rel=1e-9)
        for left, right in zip(a[1:], b[1:]):
            assert np.allclose(left, right, rtol=1e-8, atol=1e-12 * np.abs(left).max())


def test_few_onsets_are_evaluated_exactly() -> None:
    """
    On noise, the bound of (S8) rules out almost every onset without forming its J.

    60 s of pose-only samples at 120 Hz, no step: the 40 onsets' information is
    formed exactly for 1.5 of them per update (measured; the newest onset, whose J0
    is zero, is always one): the cost per update does not scale with the onsets.
    """
    group = SUBGROUPS['SE(2)']
    locked = np.diag([16.0, 16.0, 0.18])
    lin = Linearisation(locked, np.linalg.inv(locked), np.zeros(3), np.zeros((3, 3)))
    flt = MomentumFilter(group, NoiseModel(pose_position=1e-3, pose_angle=2e-3), 1e-6,
                         step_significance=1e-6)
    rng = np.random.default_rng(2)
    updates = 7200
    for k in range(updates):
        pose = pin.SE3(pin.utils.rotate('z', rng.normal(0.0, 2e-3)),
                       np.r_[rng.normal(0.0, 1e-3, 2), 0.0])
        flt.step(int(round(k / 120.0 * 1e9)), lin, pose, None)
    test = flt.step_test
    assert flt.steps_taken == 0 and test.onsets == GLR_HYPOTHESES
    assert test.evaluated / updates < 3.0, test.evaluated / updates


def test_false_alarms_far_below_the_union_bound() -> None:
    """
    Noise only, at a significance of 1e-3 so that false alarms are frequent enough to count.

    3 x 2 min of 120 Hz poses (1 mm / 2 mrad, as assumed): the union bound over the 40
    onsets allows 40 x 1e-3 per update; measured k = steps / (updates x 1e-3) = 0.32
    (14 steps: 2, 4 and 8), as on simulated coasting with realistic sensors (0.23-0.38,
    docs/step_test.md): the onsets' statistics share most of their innovations.
    """
    group = SUBGROUPS['SE(2)']
    locked = np.diag([16.0, 16.0, 0.18])
    lin = Linearisation(locked, np.linalg.inv(locked), np.zeros(3), np.zeros((3, 3)))
    steps, updates, significance = 0, 0, 1e-3
    for seed in (1, 2, 3):
        flt = MomentumFilter(group, NoiseModel(pose_position=1e-3, pose_angle=2e-3), 1e-6,
                             step_significance=significance)
        rng = np.random.default_rng(seed)
        for k in range(14400):
            pose = pin.SE3(pin.utils.rotate('z', rng.normal(0.0, 2e-3)),
                           np.r_[rng.normal(0.0, 1e-3, 2), 0.0])
            flt.step(int(round(k / 120.0 * 1e9)), lin, pose, None)
        steps += flt.steps_taken
        updates += 14400
    k = steps / (updates * significance)
    assert 0.0 < k <= 1.0, k
