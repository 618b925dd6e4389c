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
The multi-scale test's two banks per update in two compiled calls (core/bank_step.py).

:class:`_Separate` is MultiScaleTest's update as it was (main 0fcd9f2): the filtered
test's store_window_changes and calibrated_best, then MomentumBlocks.update
(bank_statistics), calibrate and np.argmax, each dispatched from Python. The fused
update must give the same detections, statistics and calibration, bit for bit,
through pushes, resets, events (not wanted), an unquiet null and singular
covariances.
"""

import math
from typing import Optional

import numpy as np
import pytest
from reduced_dynamics.chi_square import chi2
from scipy.special import chdtri

from reduced_dynamics.estimator import multiscale
from reduced_dynamics.estimator.core import impulse
from reduced_dynamics.estimator.multiscale import (CALIBRATION_EVERY, ImpulseDetection,
                                                   MultiScaleTest, PERIOD_TOLERANCE)


class _Separate(MultiScaleTest):
    """MultiScaleTest.update and _filtered as they were: five dispatched calls."""

    def update(self, stamp_ns: int, mu: np.ndarray, cov: np.ndarray,
               measured: Optional[list] = None,
               wanted: bool = True) -> Optional[ImpulseDetection]:
        if not self.active:
            return None
        if measured:
            if not self.blocks.active:
                self._threshold_period = 0.0
            for item in measured:
                self.blocks.add(*item)
        self._updates += 1
        if not self._updates % CALIBRATION_EVERY:
            p = np.clip(self._above, 0.5, 1.0 - 1e-3)
            self.inflation = np.maximum(1.0, self._median / chdtri(self.n, p))
        found = self._filtered_separately(stamp_ns, mu, cov)
        if not self.blocks.active or self._period is None:
            return found if wanted else None
        best = self.blocks.update(stamp_ns, self.floor_ns)
        if best >= 0:
            self.blocks.statistics[:] = self._calibrate(1, self.blocks.statistics)
            best = int(np.argmax(self.blocks.statistics))
        if not wanted:
            return None
        if best < 0 or not self.blocks.statistics[best] > self.threshold:
            return found
        block = self.blocks.locate(stamp_ns, best, self.floor_ns)
        return ImpulseDetection(block.start_ns, block.window, block.statistic,
                                block.mu_before, block.cov_before, True)

    def _filtered_separately(self, stamp_ns: int, mu: np.ndarray,
                             cov: np.ndarray) -> Optional[ImpulseDetection]:
        if self._end > self._start:
            dt = (stamp_ns - int(self._stamps[self._end - 1])) * 1e-9
            if dt > 0.0:
                self._period = dt if self._period is None else \
                    self._period + 0.01 * (dt - self._period)
        if self._period is None:
            self._store(stamp_ns, mu, cov)
            return None
        if self._end == self._capacity:
            self._make_room(stamp_ns)
        if abs(self._period - self._threshold_period) > \
                PERIOD_TOLERANCE * self._threshold_period or not self._threshold_period:
            self._threshold_period = self._period
            self.threshold = float(chi2.isf(self.significance(self._period), self.n))
        floor = self.floor_ns
        try:
            rows, d, solved = impulse.store_window_changes(
                self._stamps, self._mu, self._cov, self._start, self._end, self._lags_ns,
                stamp_ns, 0 if floor is None else floor, floor is not None, mu, cov)
        except np.linalg.LinAlgError:
            self._end += 1
            self.statistics[:] = 0.0
            return None
        self._end += 1
        if not len(d):
            self.statistics[:] = 0.0
            return None
        rate, learn = self._calibration()
        best, value = impulse.calibrated_best(
            rows, np.einsum('ij,ij->i', d, solved), self.statistics, self._above[0],
            self.inflation[0], self._median, rate, learn)
        if not value > self.threshold:
            return None
        covered = rows >= 0
        rows = rows[covered]
        values = self.statistics[covered]
        knee = int(np.flatnonzero(values >= 0.5 * values[best])[0])
        longest = int(np.flatnonzero(values > self.threshold)[-1])
        return ImpulseDetection(int(self._stamps[rows[knee]]),
                                float(self.windows[np.flatnonzero(covered)[best]]),
                                float(values[best]), self._mu[rows[longest]].copy(),
                                self._cov[rows[longest]].copy())


def _inputs(n: int, d: int, seconds: float, rate: float, seed: int) -> list:
    """Return per update (stamp, mu, cov, measured, wanted, quiet, reset, singular)."""
    rng = np.random.default_rng(seed)
    out = []
    mu_true = np.zeros(n)
    noise = np.diag(np.linspace(1.0, 2.0, n)) * 2.5e-3
    root = rng.standard_normal((n, n)) * 1e-3
    fixed = root @ root.T + 1e-6 * np.eye(n)
    for k in range(int(seconds * rate)):
        stamp = 10 ** 9 + int(round(k * 1e9 / rate))
        t = k / rate
        if 2.0 <= t < 2.6 or 5.0 <= t < 5.1:
            mu_true = mu_true + 0.15 / rate  # pushes: a long one and a short one
        cov = fixed
        mu = mu_true + rng.standard_normal(n) * 1e-3
        measured_mu = mu_true + rng.standard_normal(n) * 5e-2
        position = None
        if d:
            position = (rng.standard_normal(d) * 1e-3 + t * 0.01, 1e-6 * np.eye(d), 5.0,
                        tuple(range(d)))
        common = 1e-7 * np.eye(n)
        measured = [(stamp, measured_mu, noise, common, position)] if k % 3 else None
        singular = k in (700, 701)
        if singular:
            cov = -fixed  # V_L = 0 for every window reaching it: its solve raises
        out.append((stamp, mu, cov, measured, k % 50 < 35, (k // 200) % 3 != 1,
                    k in (450, 900), singular))
    return out


def _state(test: MultiScaleTest) -> list:
    blocks = test.blocks
    return [test.statistics.copy(), test._above.copy(), test.inflation.copy(),
            blocks.statistics.copy(), test._stamps[:test._end].copy(),
            test._mu[:test._end].copy(), np.array([test._start, test._end, test.threshold,
                                                   test._period or 0.0])]


@pytest.mark.parametrize('n,d', [(6, 3), (3, 2), (3, 0)])
def test_the_fused_update_equals_the_separate_calls(n, d, monkeypatch) -> None:
    """Detections of both banks, statistics, calibration and rings: the same bits."""
    monkeypatch.setattr(multiscale, 'EXCESS_MINIMUM', 50)
    fused, separate = MultiScaleTest(n, 50.0), _Separate(n, 50.0)
    found = {'filtered': 0, 'blocks': 0}
    formed = multiscale.bank_step.changes
    unformed = []

    def changes(*args):
        out = formed(*args)
        unformed.append(not out[0])
        return out
    monkeypatch.setattr(multiscale.bank_step, 'changes', changes)
    for stamp, mu, cov, measured, wanted, quiet, reset, _ in _inputs(n, d, 8.0, 100.0, n):
        for test in (fused, separate):
            test.quiet = quiet
            if reset:
                test.reset(stamp - 10 ** 8)
        mine = fused.update(stamp, mu, cov, measured, wanted)
        expected = separate.update(stamp, mu, cov, measured, wanted)
        assert (mine is None) == (expected is None), stamp
        if expected is not None:
            found['blocks' if expected.measured else 'filtered'] += 1
            for a, b in zip(mine, expected):
                np.testing.assert_array_equal(a, b)
        for a, b in zip(_state(fused), _state(separate)):
            np.testing.assert_array_equal(a, b)
    assert found['filtered'] and found['blocks'], found
    assert sum(unformed) >= 2  # the singular V_L, caught as the Python caught it
    assert fused.blocks.active and fused.blocks.ready
    assert math.isfinite(fused.threshold)


def test_no_detection_is_formed_when_the_caller_has_no_use_for_it(monkeypatch) -> None:
    """An event open (not wanted): statistics updated, the pulse's dating not computed."""
    formed = []
    real = multiscale.ImpulseDetection

    def counted(*args, **kwargs):
        formed.append(1)
        return real(*args, **kwargs)
    monkeypatch.setattr(multiscale, 'ImpulseDetection', counted)
    test = MultiScaleTest(6, 50.0)
    above = 0
    for stamp, mu, cov, measured, _, _, _, _ in _inputs(6, 3, 8.0, 100.0, 6):
        assert test.update(stamp, mu, cov, measured, wanted=False) is None
        above += bool(test.statistics.max() > test.threshold)
    assert above > 10 and not formed
