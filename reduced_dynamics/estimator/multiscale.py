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
Multi-scale test of an impulse: the filtered momentum's change over a bank of windows.

Without external wrench mu is constant (Noether), so over any window L the change
of the filtered momentum ``d_L = mu(t) - mu(t - L)`` is only the filter's error
change. With the errors at both ends positively correlated (the same sensors,
the same filter) its covariance is at most ``V_L = P_mu(t) + P_mu(t - L)``, and

    T_L = d_L^T V_L^-1 d_L

is at most chi2_n under no wrench. A constant wrench pulse over the window moves
d_L by its impulse: T_L is the GLR statistic of that pulse against no wrench (the
maximum-likelihood impulse is d_L itself). The random-walk wrench of the filter
is no nuisance here: the test is against *no* wrench, where the per-sample step
test (:mod:`.step_test`) weighs a step against the random walk, which explains
a slow push almost as well (docs/multiscale_events.md).

Windows form a geometric bank from ``shortest`` to ``longest`` (0.05-3 s, ratio
1.5, and 3 s itself: 12 windows). The user's false-alarm rate R per hour is spread over the
windows and the updates (union bound): each T_L at an update dt after the last
is compared with the chi2_n quantile of ``R dt / 3600 / windows``. That is
conservative twice (the bound; V_L above the true variance), which the measured
rates in the docs show.

Cost per update: one ``searchsorted`` over the ring of past estimates and a
stacked n x n solve per window.
"""

from __future__ import annotations

import math
from typing import NamedTuple, Optional

import numpy as np
from reduced_dynamics.chi_square import chi2

#: Shortest and longest window [s] and the ratio between successive windows.
SHORTEST = 0.05
LONGEST = 3.0
RATIO = 1.5
#: Relative change of the update period after which the threshold is recomputed.
PERIOD_TOLERANCE = 0.2


def window_bank(shortest: float = SHORTEST, longest: float = LONGEST,
                ratio: float = RATIO) -> np.ndarray:
    """Return the geometric bank of window lengths [s], ``longest`` included."""
    count = int(math.floor(math.log(longest / shortest) / math.log(ratio) + 1e-9)) + 1
    windows = shortest * ratio ** np.arange(count)
    if windows[-1] < longest * (1 - 1e-9):
        windows = np.append(windows, longest)
    return windows


class ImpulseDetection(NamedTuple):
    """A window whose momentum change is significant."""

    #: the pulse's estimated start [ns] and the length [s] of the window whose
    #: statistic is largest
    start_ns: int
    window: float
    statistic: float
    #: the momentum before the pulse (at the longest significant window's start)
    #: and its covariance
    mu_before: np.ndarray
    cov_before: np.ndarray


class MultiScaleTest:
    """GLR of a constant-wrench pulse over each window of a geometric bank (module doc)."""

    def __init__(self, n: int, false_alarm_rate: float,
                 windows: Optional[np.ndarray] = None) -> None:
        """Set up for momenta of dimension ``n``; ``false_alarm_rate`` [1/h], 0: off."""
        self.n = n
        self.rate = false_alarm_rate
        self.windows = window_bank() if windows is None else np.asarray(windows, float)
        self._lags_ns = np.round(self.windows * 1e9).astype(np.int64)
        self._capacity = 256
        self._stamps = np.zeros(self._capacity, dtype=np.int64)
        self._mu = np.zeros((self._capacity, n))
        self._cov = np.zeros((self._capacity, n, n))
        self._start = 0
        self._end = 0
        self._period: Optional[float] = None
        self._threshold_period = 0.0
        self.threshold = math.inf
        #: no window reaches back before this stamp (the last event's end or a reset)
        self.floor_ns: Optional[int] = None
        #: per-window statistics at the last update (0 where the window is not covered)
        self.statistics = np.zeros(len(self.windows))

    @property
    def active(self) -> bool:
        """Return whether the test runs (a positive false-alarm rate)."""
        return self.rate > 0.0

    def significance(self, period: float) -> float:
        """Return the per-window, per-update false-alarm probability at update ``period`` s."""
        return min(0.5, self.rate * period / 3600.0 / len(self.windows))

    def reset(self, from_ns: Optional[int]) -> None:
        """Let no window reach back before ``from_ns`` (an event's end, a restart)."""
        self.floor_ns = from_ns

    def _store(self, stamp_ns: int, mu: np.ndarray, cov: np.ndarray) -> None:
        if self._end == self._capacity:
            oldest = stamp_ns - self._lags_ns[-1]
            keep = max(self._start, int(np.searchsorted(
                self._stamps[self._start:self._end], oldest, 'right')) + self._start - 1)
            count = self._end - keep
            if count > self._capacity // 2:
                self._capacity *= 2
                for name in ('_stamps', '_mu', '_cov'):
                    old = getattr(self, name)
                    new = np.zeros((self._capacity,) + old.shape[1:], old.dtype)
                    new[:count] = old[keep:self._end]
                    setattr(self, name, new)
            else:
                for array in (self._stamps, self._mu, self._cov):
                    array[:count] = array[keep:self._end]
            self._start, self._end = 0, count
        self._stamps[self._end] = stamp_ns
        self._mu[self._end] = mu
        self._cov[self._end] = cov
        self._end += 1

    def update(self, stamp_ns: int, mu: np.ndarray,
               cov: np.ndarray) -> Optional[ImpulseDetection]:
        """Take one filtered momentum and its covariance; return the detecting window."""
        if not self.active:
            return None
        if self._end > self._start:
            dt = (stamp_ns - int(self._stamps[self._end - 1])) * 1e-9
            if dt > 0.0:
                self._period = dt if self._period is None else \
                    self._period + 0.01 * (dt - self._period)
        self._store(stamp_ns, mu, cov)
        if self._period is None:
            return None
        if abs(self._period - self._threshold_period) > \
                PERIOD_TOLERANCE * self._threshold_period:
            # chi2.isf is ~50 us: recomputed only when the update rate changes.
            self._threshold_period = self._period
            self.threshold = float(chi2.isf(self.significance(self._period), self.n))
        stamps = self._stamps[self._start:self._end]
        targets = stamp_ns - self._lags_ns
        # The newest sample at or before t - L: the window is at least L long.
        index = np.searchsorted(stamps, targets, 'right') - 1
        floor = self.floor_ns
        covered = (index >= 0) & (stamps[np.maximum(index, 0)] >= (
            stamps[0] if floor is None else max(floor, int(stamps[0]))))
        self.statistics[:] = 0.0
        if not covered.any():
            return None
        rows = index[covered] + self._start
        d = mu - self._mu[rows]
        v = cov + self._cov[rows]
        try:
            solved = np.linalg.solve(v, d[..., None])[..., 0]
        except np.linalg.LinAlgError:
            return None
        values = np.einsum('ij,ij->i', d, solved)
        self.statistics[covered] = values
        best = int(np.argmax(values))
        if not values[best] > self.threshold:
            return None
        # A weak pulse is crossed first by a long window reaching back well before it.
        # A constant wrench since theta makes T_L grow as min(L, t - theta)^2: the
        # shortest window with half the largest statistic dates the start (the
        # "knee"), the longest significant one, starting before the pulse, gives the
        # momentum before it (the impulse is then whole).
        knee = int(np.flatnonzero(values >= 0.5 * values[best])[0])
        longest = int(np.flatnonzero(values > self.threshold)[-1])
        return ImpulseDetection(int(self._stamps[rows[knee]]),
                                float(self.windows[np.flatnonzero(covered)[best]]),
                                float(values[best]), self._mu[rows[longest]].copy(),
                                self._cov[rows[longest]].copy())

    def window_statistic(self, window: float) -> float:
        """Return the last statistic of the bank window nearest ``window`` s."""
        return float(self.statistics[int(np.argmin(np.abs(self.windows - window)))])
