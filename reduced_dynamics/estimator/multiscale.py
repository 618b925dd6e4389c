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

Cost per update: one compiled call for both banks (core/bank_step.py; with a
measured twist its momentum too:
:class:`~reduced_dynamics.estimator.measured_momentum.TwistSample`;
docs/multiscale_events.md, "Cost").

The filtered momentum's covariance is set mostly by the filter's random-walk
wrench, so this test cannot see a slow push below ~sqrt(threshold 2 P_mu)
whatever its length. Where a twist is measured, :class:`.MomentumBlocks` runs
the same bank on the momenta each twist gives
(:func:`~reduced_dynamics.estimator.measured_momentum.twist_momentum`): block
means of every sample, chi2_n exactly under no wrench (docs/multiscale_events.md).
"""

from __future__ import annotations

import math
from typing import Any, Optional

import numpy as np
from reduced_dynamics.chi_square import chi2
from reduced_dynamics.estimator.core import bank_step, impulse
# Re-exported: the names this module held before it was split (stop 26).
from reduced_dynamics.estimator.block_pulse import (  # noqa: F401
    BlockDetection, FIT_SCRATCH)
from reduced_dynamics.estimator.measured_momentum import (  # noqa: F401
    LINEAR, TwistSample, centre_of_mass, twist_momenta, twist_momentum)
from reduced_dynamics.estimator.momentum_blocks import (  # noqa: F401
    EXCESS_MINIMUM, EXCESS_SAMPLES, MomentumBlocks)
from reduced_dynamics.estimator.multiscale_bank import (  # noqa: F401
    CALIBRATION_EVERY, CALIBRATION_MEMORY, ImpulseDetection, LONGEST, PERIOD_TOLERANCE,
    RATIO, SHORTEST, window_bank)
from reduced_dynamics.estimator.multiscale_twist import TwistUpdate, _UNCOMMON


class MultiScaleTest(TwistUpdate):
    """GLR of a constant-wrench pulse over each window of a geometric bank (module doc)."""

    def __init__(self, n: int, false_alarm_rate: float,
                 windows: Optional[np.ndarray] = None,
                 calibration_memory: float = CALIBRATION_MEMORY) -> None:
        """Set up for momenta of dimension ``n``; ``false_alarm_rate`` [1/h], 0: off."""
        self.n = n
        self.rate = false_alarm_rate
        self.windows = window_bank() if windows is None else np.asarray(windows, float)
        # The state and per-window arrays bank_step.twist_step takes (TwistUpdate).
        self._twist_arrays(n, len(self.windows))
        self.calibration_memory = calibration_memory
        self._lags_ns[:] = np.round(self.windows * 1e9).astype(np.int64)
        self._capacity = 256
        self._stamps = np.zeros(self._capacity, dtype=np.int64)
        self._mu = np.zeros((self._capacity, n))
        self._cov = np.zeros((self._capacity, n, n))
        self._start = 0
        self._end = 0
        self.threshold = math.inf
        #: per-window statistics at the last update (0 where the window is not covered)
        self.statistics = self._window_values[0]
        #: the same bank on measured momenta (a twist measured: :class:`.MomentumBlocks`)
        self.blocks = MomentumBlocks(n, self.windows)
        self._moving_thresholds: dict[int, float] = {}
        # Per window length asked for: the bank windows it covers and their threshold
        # (still_moving), the nearest bank window (window_statistic).
        self._moving_windows: dict[float, tuple[Any, float]] = {}
        self._nearest: dict[float, int] = {}
        #: per test (filtered momentum, blocks) and window: the running fraction of
        #: quiet updates above the chi2_n median, and the inflation of T it implies
        self._above = self._window_values[1:3]
        self._above[:] = 0.5
        self.inflation = self._window_values[3:5]
        self.inflation[:] = 1.0
        self._median = float(chi2.isf(0.5, n))
        self._updates = 0
        # The compiled update's arrays (core/bank_step.py): each window's ring row, the
        # Cholesky work space, and the block bank's grid (stride [ns], last slot, quiet
        # updates since its last evaluation).
        self._rows = self._window_ints[0]
        self._rows[:] = -1
        self._scratch = self._stack[:14]
        self._grid = self._window_ints[1:4]
        self._grid[0] = np.maximum(1, self._lags_ns // bank_step.GRID)
        self._grid[1] = -1
        self._share_with_blocks()
        #: whether no event is open (the detector sets it): only then is the null learnt
        self.quiet = True

    @property
    def active(self) -> bool:
        """Return whether the test runs (a positive false-alarm rate)."""
        return self.rate > 0.0

    def significance(self, period: float) -> float:
        """Return the per-window, per-update false-alarm probability at update ``period`` s."""
        tests = 2 if self.blocks.active else 1
        return min(0.5, self.rate * period / 3600.0 / len(self.windows) / tests)

    def reset(self, from_ns: Optional[int]) -> None:
        """Let no window reach back before ``from_ns`` (an event's end, a restart)."""
        self.floor_ns = from_ns

    def _store(self, stamp_ns: int, mu: np.ndarray, cov: np.ndarray) -> None:
        if self._end == self._capacity:
            self._make_room(stamp_ns)
        self._stamps[self._end] = stamp_ns
        self._mu[self._end] = mu
        self._cov[self._end] = cov
        self._end += 1

    def _make_room(self, stamp_ns: int) -> None:
        """Drop the samples no window reaches (or double the ring) before storing one."""
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

    def update(self, stamp_ns: int, mu: np.ndarray, cov: np.ndarray,
               measured: Optional[list[tuple]] = None,
               wanted: bool = True) -> Optional[ImpulseDetection]:
        """
        Take one filtered momentum and its covariance; return the detecting window.

        ``measured``: (stamp, mu, covariance) the measured twists since the last
        update give (:func:`~reduced_dynamics.estimator.measured_momentum.twist_momenta`;
        None or empty: none). The block test on them runs beside the test on the
        filtered momentum, each at half the rate.
        ``wanted`` False: the caller has no use for a detection now (an event is
        open); the statistics are updated, nothing is located, None is returned.
        """
        if not self.rate > 0.0:  # not self.active (a property call per sample)
            return None
        if measured is not None and len(measured) == 1 and \
                measured[0].__class__ is TwistSample:
            out = self._update_twist(stamp_ns, mu, cov, measured[0], wanted)
            if out is not _UNCOMMON:
                return out
        # Not the common update: the next one is checked before its call (_update_twist).
        self._next_common = False
        sample = None
        if measured:
            if not self.blocks.active:
                self._threshold_period = 0.0  # two tests now share the rate
            measured = [item.momentum() if item.__class__ is TwistSample else item
                        for item in measured]
            if len(measured) == 1 and self._period is not None:
                # The common case: the sample and both banks in one compiled call.
                sample = self.blocks.prepare(*measured[0])
            if sample is None:
                for item in measured:
                    self.blocks.add(*item)
        # The update count in its state array (its attribute is a property).
        state = self._state
        state[bank_step.UPDATES] += 1
        if not state[bank_step.UPDATES] % CALIBRATION_EVERY:
            self._inflate()
        # Both banks (the block test's as MomentumBlocks.update, then calibrated).
        found, best = self._filtered(stamp_ns, mu, cov, wanted, sample)
        if not self.blocks.active or self._period is None:
            return found if wanted else None
        if not wanted:
            # The fit below costs ~ points^2 x the window's samples (MomentumBlocks.locate):
            # once per sample it was most of the node's time while a push lasted.
            return None
        return self._block_detection(stamp_ns, found, best)

    def _block_detection(self, stamp_ns: int, found: Optional[ImpulseDetection],
                         best: int) -> Optional[ImpulseDetection]:
        """Return the block test's detection (its best window ``best``), or ``found``."""
        if best < 0 or not self.blocks.statistics[best] > self.threshold:
            return found
        # Between its evaluations a window's statistic is held (bank_step.update): the
        # detection reads every window at this sample, as the knee of the filtered test
        # does, so the window that dates the pulse is the one that fits it now.
        best = self.blocks.update(stamp_ns, self.floor_ns)
        if best < 0:
            return found
        self.blocks.statistics /= self.inflation[1]
        best = int(np.argmax(self.blocks.statistics))
        if not self.blocks.statistics[best] > self.threshold:
            return found
        block = self.blocks.locate(stamp_ns, best, self.floor_ns)
        return ImpulseDetection(block.start_ns, block.window, block.statistic,
                                block.mu_before, block.cov_before, True)

    def measured_mean(self, lo_ns: int, hi_ns: int
                      ) -> Optional[tuple[np.ndarray, np.ndarray]]:
        """Return the mean measured momentum over (lo_ns, hi_ns] (None: no twist)."""
        return self.blocks.mean(lo_ns, hi_ns) if self.blocks.active else None

    def _filtered(self, stamp_ns: int, mu: np.ndarray, cov: np.ndarray,
                  wanted: bool = True,
                  sample: Optional[tuple] = None) -> tuple[Optional[ImpulseDetection], int]:
        """
        Run the test on the filtered momentum (module doc) and the block test's update.

        Return the filtered test's detection (or None; None too when not ``wanted``:
        the caller would drop it) and the block test's best window (-1: none),
        calibrated: one compiled call (core/bank_step.update) on preallocated arrays;
        with ``sample`` (MomentumBlocks.prepare's arguments: the period is known, so the
        call is made) the measured momentum is taken in the same call (a twist too:
        :meth:`_update_twist`).
        """
        # The state read once (its attributes are properties: TwistUpdate).
        state, values = self._state, self._values
        end, start = state.tolist()[:2]
        period = float(values[bank_step.PERIOD])
        period = None if math.isnan(period) else period
        if end > start:
            dt = (stamp_ns - int(self._stamps[end - 1])) * 1e-9
            if dt > 0.0:
                period = dt if period is None else period + 0.01 * (dt - period)
                values[bank_step.PERIOD] = period
        if period is None:
            self._store(stamp_ns, mu, cov)
            return None, -1
        if end == self._capacity:
            self._make_room(stamp_ns)
            end, start = self._end, self._start
        threshold_period = float(values[bank_step.THRESHOLD_PERIOD])
        if abs(period - threshold_period) > PERIOD_TOLERANCE * threshold_period or \
                not threshold_period:
            # chi2.isf is ~50 us: recomputed only when the update rate changes.
            self._threshold_period = period
            self.threshold = float(chi2.isf(self.significance(period), self.n))
        floor = int(state[bank_step.FLOOR]) if state[bank_step.HAS_FLOOR] else None
        measured = self.blocks
        # MomentumBlocks.update's conditions: it runs with a twist measured, and tests
        # from four samples with its excess noise known.
        # MomentumBlocks.update's conditions but its four samples (the kernel counts them,
        # this update's sample included).
        ready = measured.active and measured._differences >= EXCESS_MINIMUM
        first, block_end = 0, measured._end
        if block_end:
            first = int(measured._stamps[0])
            first = first if floor is None else max(floor, first)
        # _calibration, inlined (called per sample).
        learn = self.quiet
        rate = min(1.0, period / float(values[bank_step.MEMORY])) if learn else 0.0
        if sample is None:
            # One compiled call: the sample stored, both banks' statistics, calibrated.
            best, value, block_best = bank_step.update(
                self._stamps, self._mu, self._cov, start, end, self._lags_ns,
                stamp_ns, 0 if floor is None else floor, floor is not None, mu, cov,
                self._rows, self.statistics, self._above, self.inflation, self._scratch,
                self._median, rate, learn, measured.active, ready, *measured._arrays(),
                measured._common, measured._stamps, block_end, measured._lags_ns, first,
                measured.mass, measured.linear, measured.statistics, self._grid)
        else:
            added, best, value, block_best = bank_step.update_with_sample(
                *sample, self._stamps, self._mu, self._cov, start, end,
                self._lags_ns, stamp_ns, 0 if floor is None else floor, floor is not None,
                mu, cov, self._rows, self.statistics, self._above, self.inflation,
                self._scratch, self._median, rate, learn, ready, *measured._arrays(),
                measured._common, measured._stamps, measured._lags_ns, first, measured.mass,
                measured.linear, measured.statistics, self._grid)
            if added:  # measured.added(), inlined (called per sample)
                measured._end = block_end + 1
                measured.active = True
        state[bank_step.END] = end + 1
        if not wanted or best < 0 or not value > self.threshold:
            return None, block_best
        return self._detection(best), block_best

    def _detection(self, best: int) -> ImpulseDetection:
        """Return the filtered test's detection, its window ``best`` among those covered."""
        rows = self._rows
        covered = rows >= 0
        rows = rows[covered]
        values = self.statistics[covered]
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

    def _calibration(self) -> tuple[float, bool]:
        """Return the null calibration's learning rate per update and whether it learns."""
        learn = self.quiet and self._period is not None
        return (min(1.0, self._period / self.calibration_memory) if learn else 0.0), learn

    def _calibrate(self, test: int, raw: np.ndarray) -> np.ndarray:
        """
        Learn test ``test``'s null from quiet updates; return ``raw`` / its inflation.

        The union bound holds if T_L is chi2_n without a wrench. Noise the model does
        not know (a moving arm's model error, coloured noise the excess from
        successive differences misses) scales T_L up, most at long windows. Its scale
        comes from the test's own median (robust: a push is a small part of the
        time), learnt over ``calibration_memory`` s while no event is open.
        """
        rate, learn = self._calibration()
        return impulse.calibrate(raw, self._above[test], self.inflation[test], self._median,
                                 rate, learn)

    def still_moving(self, window: float) -> bool:
        """
        Return whether the measured momenta still move over windows of up to ``window`` s.

        True when a block window that short is beyond its 99 % quantile (Bonferroni
        over those windows): a push goes on. Ends an event where the push does, not
        where the wrench estimate's chi-square happens to dip (a long push's events
        integrated half of its impulse otherwise).
        """
        if not self.blocks.active:
            return False
        known = self._moving_windows.get(window)
        if known is None:
            # Called per sample while an event is open, with a few window lengths.
            short = self.windows <= max(window, self.windows[0]) * (1 + 1e-9)
            count = int(short.sum())
            if count not in self._moving_thresholds:
                self._moving_thresholds[count] = float(chi2.isf(0.01 / count, self.n))
            # An ascending bank (the default): those windows are its first ``count``,
            # a slice (no boolean indexing per call).
            selector = slice(0, count) if short[:count].all() else short
            known = self._moving_windows[window] = (selector, self._moving_thresholds[count])
        short, threshold = known
        if short.__class__ is slice:
            # The first windows: one compiled scan (numpy's slice, compare and any
            # were ~3 us a sample while an event is open).
            return bank_step.any_above(self.blocks.statistics, short.stop, threshold)
        return bool((self.blocks.statistics[short] > threshold).any())

    def window_statistic(self, window: float) -> float:
        """Return the last statistic of the bank window nearest ``window`` s."""
        index = self._nearest.get(window)
        if index is None:
            index = self._nearest[window] = int(np.argmin(np.abs(self.windows - window)))
        return float(self.statistics[index])
