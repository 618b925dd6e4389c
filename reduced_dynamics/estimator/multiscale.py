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
measured twist its momentum too: :class:`TwistSample`; docs/multiscale_events.md,
"Cost").

The filtered momentum's covariance is set mostly by the filter's random-walk
wrench, so this test cannot see a slow push below ~sqrt(threshold 2 P_mu)
whatever its length. Where a twist is measured, :class:`MomentumBlocks` runs
the same bank on the momenta each twist gives (:func:`twist_momentum`): block
means of every sample, chi2_n exactly under no wrench (docs/multiscale_events.md).
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple, Optional

import numpy as np
from reduced_dynamics.chi_square import chi2
from scipy.special import chdtri
from reduced_dynamics.estimator.core import bank_step, blocks, impulse

#: Shortest and longest window [s] and the ratio between successive windows.
SHORTEST = 0.05
LONGEST = 3.0
RATIO = 1.5
#: Relative change of the update period after which the threshold is recomputed.
PERIOD_TOLERANCE = 0.2
#: Successive differences before the block test runs, and the memory of the excess
#: noise's running mean (samples).
EXCESS_MINIMUM = 200
EXCESS_SAMPLES = 2000
#: Memory [s] of the null calibration (the running fraction of quiet updates whose
#: statistic is above the chi2_n median), and updates between its inflation's updates.
CALIBRATION_MEMORY = 600.0
CALIBRATION_EVERY = 256
#: Elements [float64] of the work space MomentumBlocks.locate keeps between detections
#: (8 MiB, allocated at the first): the pulse fits' ramps of windows up to ~0.15 s at 1 kHz.
FIT_SCRATCH = 1 << 20


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
    #: whether the block test on measured momenta found it (mu before is then theirs)
    measured: bool = False


#: MultiScaleTest._update_twist's answer when the update is not its common one.
_UNCOMMON = object()


class MultiScaleTest:
    """GLR of a constant-wrench pulse over each window of a geometric bank (module doc)."""

    def __init__(self, n: int, false_alarm_rate: float,
                 windows: Optional[np.ndarray] = None,
                 calibration_memory: float = CALIBRATION_MEMORY) -> None:
        """Set up for momenta of dimension ``n``; ``false_alarm_rate`` [1/h], 0: off."""
        self.n = n
        self.calibration_memory = calibration_memory
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
        #: the same bank on measured momenta (a twist measured: :class:`MomentumBlocks`)
        self.blocks = MomentumBlocks(n, self.windows)
        self._moving_thresholds: dict[int, float] = {}
        # Per window length asked for: the bank windows it covers and their threshold
        # (still_moving), the nearest bank window (window_statistic).
        self._moving_windows: dict[float, tuple[Any, float]] = {}
        self._nearest: dict[float, int] = {}
        #: per test (filtered momentum, blocks) and window: the running fraction of
        #: quiet updates above the chi2_n median, and the inflation of T it implies
        self._above = np.full((2, len(self.windows)), 0.5)
        self.inflation = np.ones((2, len(self.windows)))
        self._median = float(chi2.isf(0.5, n))
        self._updates = 0
        # The compiled update's arrays (core/bank_step.py): each window's ring row, the
        # Cholesky work space, and the block bank's grid (stride [ns], last slot, quiet
        # updates since its last evaluation).
        self._rows = np.full(len(self.windows), -1, dtype=np.int64)
        self._scratch = np.zeros((14, n, n))
        self._grid = np.zeros((3, len(self.windows)), dtype=np.int64)
        self._grid[0] = np.maximum(1, self._lags_ns // bank_step.GRID)
        self._grid[1] = -1
        #: whether no event is open (the detector sets it): only then is the null learnt
        self.quiet = True
        # bank_step.twist_step's arrays that stay between updates (_kept_arrays).
        self._kept: Optional[tuple] = None

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
        update give (:func:`twist_momenta`; None or empty: none). The block test on
        them runs beside the test on the filtered momentum, each at half the rate.
        ``wanted`` False: the caller has no use for a detection now (an event is
        open); the statistics are updated, nothing is located, None is returned.
        """
        if not self.active:
            return None
        if measured is not None and len(measured) == 1 and \
                measured[0].__class__ is TwistSample:
            out = self._update_twist(stamp_ns, mu, cov, measured[0], wanted)
            if out is not _UNCOMMON:
                return out
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
        self._updates += 1
        if not self._updates % CALIBRATION_EVERY:
            # T ~ lambda chi2_n above the median a fraction p of the time: lambda =
            # median / isf(p). Never below 1 (never looser than the noise model).
            p = np.clip(self._above, 0.5, 1.0 - 1e-3)
            self.inflation[:] = np.maximum(1.0, self._median / chdtri(self.n, p))
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

    def _update_twist(self, stamp_ns: int, mu: np.ndarray, cov: np.ndarray,
                      sample: 'TwistSample', wanted: bool) -> Any:
        """
        Run :meth:`update` on the common update in one compiled call; _UNCOMMON: not common.

        Common: the update period known, the block test running on positions, and
        ``sample`` a common sample (:meth:`MomentumBlocks.prepare`'s conditions, no
        excess decomposition due; checked before anything moves). The same steps as
        :meth:`update` with :meth:`_filtered`, in the same order: the period, the block
        test's first stamp and the calibration's rate in the call
        (core/bank_step.twist_step), the arrays that stay passed as one kept tuple.
        """
        blocks, period, end = self.blocks, self._period, self._end
        last, k = blocks._last, blocks._end
        differences = blocks._differences + 1
        if period is None or last is None or not k or k == blocks._capacity or \
                len(blocks.linear) != 3 or sample[0] <= blocks._stamps[k - 1] or \
                differences % 16 == 1 or differences == EXCESS_MINIMUM or \
                not blocks.active or end <= self._start:
            return _UNCOMMON
        # MomentumBlocks.prepare's state, advanced (called per sample).
        blocks._last = blocks._keep
        blocks._differences = differences
        self._updates += 1
        if not self._updates % CALIBRATION_EVERY:
            # As in update.
            p = np.clip(self._above, 0.5, 1.0 - 1e-3)
            self.inflation[:] = np.maximum(1.0, self._median / chdtri(self.n, p))
        if end == self._capacity:
            # (_filtered takes the period from the last stamp first: it stays the last.)
            self._make_room(stamp_ns)
            end = self._end
        floor = self.floor_ns
        added, period, best, value, block_best = bank_step.twist_step(
            *sample, stamp_ns, mu, cov, 0 if floor is None else floor, floor is not None,
            self.quiet, period, self.calibration_memory, differences >= EXCESS_MINIMUM,
            float(min(differences, EXCESS_SAMPLES)), last[0], last[1], self._start, end, k,
            blocks._origin_ns, *self._kept_arrays())
        # _filtered: the threshold when the period moved (the call does not read it).
        self._period = period
        threshold_period = self._threshold_period
        if abs(period - threshold_period) > PERIOD_TOLERANCE * threshold_period or \
                not threshold_period:
            self._threshold_period = period
            self.threshold = float(chi2.isf(self.significance(period), self.n))
        if added:
            blocks._end = k + 1
        self._end = end + 1
        found = None
        if wanted and best >= 0 and value > self.threshold:
            found = self._detection(best)
        if not wanted:
            return None
        return self._block_detection(stamp_ns, found, block_best)

    def _kept_arrays(self) -> tuple:
        """
        Return the arrays bank_step.twist_step takes that stay between updates, as one tuple.

        Built again when one of them was replaced (a ring grown or compacted, the block
        test's positions started, a new excess): the identities checked are those.
        """
        blocks = self.blocks
        kept = self._kept
        if kept is not None and kept[0] is self._stamps and kept[1] is blocks._stamps and \
                kept[2] is blocks._positions and kept[3] is blocks.excess:
            return kept[4]
        arrays = (blocks._excess_raw, *blocks._keep, blocks.excess, self._stamps, self._mu,
                  self._cov, self._lags_ns, self._rows, self.statistics, self._above,
                  self.inflation, self._scratch, self._median, blocks._info, blocks._score,
                  *blocks._positions, blocks._common, blocks._stamps, blocks._lags_ns,
                  blocks.mass, blocks.linear, blocks.statistics, self._grid)
        self._kept = (self._stamps, blocks._stamps, blocks._positions, blocks.excess, arrays)
        return arrays

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
        if self._end > self._start:
            dt = (stamp_ns - int(self._stamps[self._end - 1])) * 1e-9
            if dt > 0.0:
                self._period = dt if self._period is None else \
                    self._period + 0.01 * (dt - self._period)
        if self._period is None:
            self._store(stamp_ns, mu, cov)
            return None, -1
        if self._end == self._capacity:
            self._make_room(stamp_ns)
        if abs(self._period - self._threshold_period) > \
                PERIOD_TOLERANCE * self._threshold_period or not self._threshold_period:
            # chi2.isf is ~50 us: recomputed only when the update rate changes.
            self._threshold_period = self._period
            self.threshold = float(chi2.isf(self.significance(self._period), self.n))
        floor = self.floor_ns
        measured = self.blocks
        # MomentumBlocks.update's conditions: it runs with a twist measured, and tests
        # from four samples with its excess noise known.
        # MomentumBlocks.update's conditions but its four samples (the kernel counts them,
        # this update's sample included).
        ready = measured.active and measured._differences >= EXCESS_MINIMUM
        first = 0
        if measured._end:
            first = int(measured._stamps[0])
            first = first if floor is None else max(floor, first)
        # _calibration, inlined (called per sample).
        learn = self.quiet
        rate = min(1.0, self._period / self.calibration_memory) if learn else 0.0
        if sample is None:
            # One compiled call: the sample stored, both banks' statistics, calibrated.
            best, value, block_best = bank_step.update(
                self._stamps, self._mu, self._cov, self._start, self._end, self._lags_ns,
                stamp_ns, 0 if floor is None else floor, floor is not None, mu, cov,
                self._rows, self.statistics, self._above, self.inflation, self._scratch,
                self._median, rate, learn, measured.active, ready, *measured._arrays(),
                measured._common, measured._stamps, measured._end, measured._lags_ns, first,
                measured.mass, measured.linear, measured.statistics, self._grid)
        else:
            added, best, value, block_best = bank_step.update_with_sample(
                *sample, self._stamps, self._mu, self._cov, self._start, self._end,
                self._lags_ns, stamp_ns, 0 if floor is None else floor, floor is not None,
                mu, cov, self._rows, self.statistics, self._above, self.inflation,
                self._scratch, self._median, rate, learn, ready, *measured._arrays(),
                measured._common, measured._stamps, measured._lags_ns, first, measured.mass,
                measured.linear, measured.statistics, self._grid)
            if added:  # measured.added(), inlined (called per sample)
                measured._end += 1
                measured.active = True
        self._end += 1
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
        return bool((self.blocks.statistics[short] > threshold).any())

    def window_statistic(self, window: float) -> float:
        """Return the last statistic of the bank window nearest ``window`` s."""
        index = self._nearest.get(window)
        if index is None:
            index = self._nearest[window] = int(np.argmin(np.abs(self.windows - window)))
        return float(self.statistics[index])


def twist_momentum(ad_inverse: np.ndarray, locked: np.ndarray, connection_qd: np.ndarray,
                   twist: np.ndarray, twist_cov: np.ndarray, joint_cov: np.ndarray,
                   pose_cov: np.ndarray, kirillov: Any
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """
    Return the momentum one measured body twist gives, and two covariances.

    mu = Ad_{g^-1}^T pi with pi = I (xi + A qbar_dot) (REDUCED_MODEL.md, the twist
    measurement h = I^-1 Ad_g^T mu - A qbar_dot turned around), g the filter's pose.
    Its noise: the twist's and the joint velocities' (``joint_cov``, body twist
    coordinates) through I, white; and the filter's pose error (``pose_cov``)
    through Ad, Ad_{(g exp d)^-1}^T pi = Ad_{g^-1}^T (pi + W(pi) d) (``kirillov``:
    pi -> W(pi), BaseGroup.coadjoint_form), which changes slowly: averaging does
    not reduce it.
    """
    pi = locked @ (twist + connection_qd)
    # The products in one compiled call, in numpy's order (core/impulse.py).
    return impulse.twist_momentum(ad_inverse, locked, pi, twist_cov, joint_cov, pose_cov,
                                  kirillov(pi))


class TwistSample(NamedTuple):
    """
    One measured twist of an SE(3) base at its row, not yet turned into a momentum.

    The arguments of :func:`.impulse.measured_momentum_se3` (the row's locked inertia
    for the momentum and the centre of mass). :class:`MultiScaleTest` turns it into
    the momentum inside the banks' compiled call (core/bank_step.twist_step);
    :meth:`momentum` gives the (stamp, mu, white, common, position) tuple
    :func:`twist_momenta` gives for other samples, the same bits.
    """

    stamp_ns: int
    ad_inverse: np.ndarray
    locked: np.ndarray
    twist: np.ndarray
    connection_qd: np.ndarray
    twist_cov: np.ndarray
    joint_cov: np.ndarray
    pose_cov: np.ndarray
    structure: np.ndarray
    rotation: np.ndarray
    translation: np.ndarray
    com_pose_cov: np.ndarray

    def momentum(self) -> tuple:
        """Return (stamp, mu, white covariance, common covariance, position)."""
        mu, white, common, world, cov, mass = impulse.measured_momentum_se3(
            self.ad_inverse, self.locked, self.twist, self.connection_qd, self.twist_cov,
            self.joint_cov, self.pose_cov, self.structure, self.locked, self.rotation,
            self.translation, self.com_pose_cov)
        return self.stamp_ns, mu, white, common, (world, cov, mass, _LINEAR_SE3)


def twist_momenta(flt: Any, before: Any, lin: Any, start_ns: Optional[int], stamp_ns: int,
                  measurements: list, gated: list, g: Any = None) -> list[tuple]:
    """
    Return (stamp, mu, covariance) of a row's accepted twist measurements.

    The common one (an SE(3) base, at the row, the filter's noise) as a
    :class:`TwistSample`: the multi-scale test computes its momentum in its own
    compiled call.

    ``before``, ``lin``: the linearisations of the previous row (at ``start_ns``)
    and of this one (at ``stamp_ns``); A qbar_dot is interpolated to each
    measurement's stamp, as the filter does (a moving arm's A qbar_dot changes within
    a row interval by more than a precise twist's noise). ``gated``: stamps the
    filter refused. The filter's pose maps them to the world (``g``: that pose as a
    pin.SE3 when the caller has it; None: taken from the filter).
    """
    if flt._g is None:
        return []
    # To the world with the filter's pose, not each sample's: a measured pose's noise
    # would weigh the samples by their own error (C depends on it), biasing the means.
    n = lin.locked.shape[0]
    ad_inverse = flt._adjoint_inverse(flt.g if g is None else g)
    pose_cov = flt.p[:n, :n]
    out = []
    span = None if start_ns is None or before is None else stamp_ns - start_ns
    se3 = flt.group.name == 'SE(3)'
    for measurement in measurements:
        if measurement is None or measurement.twist is None or \
                measurement.stamp_ns in gated:
            continue
        if se3 and measurement.noise is None and \
                not (span and measurement.stamp_ns < stamp_ns):
            # The common sample (at the row, the filter's noise): the general case
            # below with nothing to interpolate and no noise of its own, its momentum
            # computed in the banks' compiled call (TwistSample).
            pose = measurement.pose
            # tuple.__new__: the fields as they are (the NamedTuple's own __new__ is a
            # Python function, ~0.5 us a row).
            out.append(tuple.__new__(TwistSample, (
                measurement.stamp_ns, ad_inverse, lin.locked, measurement.twist,
                lin.connection_qd, flt._r_twist, lin.joint_cov, pose_cov,
                flt.group.structure_constants, pose.rotation, pose.translation,
                flt._r_pose)))
            continue
        connection = lin.connection_qd
        if span and measurement.stamp_ns < stamp_ns:
            fraction = (measurement.stamp_ns - start_ns) / span
            connection = before.connection_qd + fraction * (lin.connection_qd
                                                            - before.connection_qd)
        own = None if measurement.noise is None else measurement.noise[1]
        locked = lin.locked
        if span and measurement.stamp_ns < stamp_ns:
            locked = before.locked + fraction * (lin.locked - before.locked)
        own_pose = None if measurement.noise is None else measurement.noise[0]
        twist_cov = flt._r_twist if own is None else own
        com_cov = flt._r_pose if own_pose is None else own_pose
        if se3:
            # twist_momentum and centre_of_mass below, in one compiled call.
            pose = measurement.pose
            mu, white, common, world, cov, mass = impulse.measured_momentum_se3(
                ad_inverse, lin.locked, measurement.twist, connection, twist_cov,
                lin.joint_cov, pose_cov, flt.group.structure_constants, locked,
                pose.rotation, pose.translation, com_cov)
            out.append((measurement.stamp_ns, mu, white, common,
                        (world, cov, mass, LINEAR['SE(3)'])))
            continue
        out.append((measurement.stamp_ns, *twist_momentum(
            ad_inverse, lin.locked, connection, measurement.twist, twist_cov,
            lin.joint_cov, pose_cov, flt.group.coadjoint_form), centre_of_mass(
                flt.group.name, measurement.pose, locked, com_cov)))
    return out


#: The algebra coordinates of the linear momentum, per base group whose measured
#: centre of mass the block test reads (world x, y, z; x, y in the plane).
LINEAR = {'SE(3)': (0, 1, 2), 'SE(2)': (0, 1)}
_LINEAR_SE3 = LINEAR['SE(3)']


def centre_of_mass(group: str, pose: Any, locked: np.ndarray, pose_cov: np.ndarray
                   ) -> Optional[tuple]:
    """
    Return the measured centre of mass in the world, its covariance, the mass, the axes.

    The locked inertia holds the first moment: its linear-angular block is -M [c]x
    for SE(3) (c in the base frame), -M c_y, M c_x in the plane for SE(2). With the
    measured pose g = (R, p): c_world = p + R c, and a pose error exp(d) (body
    coordinates: translation d_v, rotation d_w) moves it by R (d_v - [c]x d_w).
    None for other base groups (the linear momentum is not the slope of a point).
    """
    axes = LINEAR.get(group)
    if axes is None:
        return None
    if group == 'SE(3)':
        # Compiled (core/impulse.py); SE(2) below.
        world, cov, mass = impulse.centre_of_mass_se3(locked, pose.rotation, pose.translation,
                                                      pose_cov)
        return world, cov, mass, axes
    mass = float(locked[0, 0])
    c = np.array([locked[1, 2], -locked[0, 2]]) / mass
    rotation = pose.rotation[:2, :2]
    jacobian = np.zeros((2, 3))
    jacobian[:, :2] = rotation
    jacobian[:, 2] = rotation @ np.array([-c[1], c[0]])
    world = pose.translation[:2] + rotation @ c
    return world, jacobian @ pose_cov @ jacobian.T, mass, axes


class BlockDetection(NamedTuple):
    """A momentum change between two blocks of measured momenta."""

    #: the change's start and end [ns] (the gap between the blocks that fits it best)
    start_ns: int
    end_ns: int
    window: float
    statistic: float
    #: the mean measured momentum before the change and its covariance
    mu_before: np.ndarray
    cov_before: np.ndarray


class MomentumBlocks:
    """
    GLR of a momentum change from measured momenta: before a gap against after it.

    With a twist measured, every sample gives mu (:func:`twist_momentum`) with its
    own, independent noise C_k. Without a wrench mu is constant, so the
    information-weighted mean of a block of samples, m = (sum C^-1)^-1 sum C^-1 y,
    has covariance (sum C^-1)^-1, and for window L (before (t-3L, t-2L], gap
    (t-2L, t-L], after (t-L, t])

        T_L = (m_after - m_before)^T (V_after + V_before)^-1 (m_after - m_before)

    is exactly chi2_n. A push inside the gap moves the difference by its impulse.
    Unlike the filtered momentum (whose covariance holds the filter's random-walk
    wrench, :class:`MultiScaleTest`), a block of L seconds averages every sample in
    it: a 3 s block of 62.5 Hz twists is ~14 times as precise as one. Where the
    base pose comes with the twist, the measured centre of mass joins each block
    (its line fit's slope times the mass is the linear momentum:
    estimator/core/blocks.py), which on a heavy base with noisy velocities carries
    most of a slow push's evidence.
    """

    def __init__(self, n: int, windows: np.ndarray) -> None:
        """Set up for momenta of dimension ``n`` and the bank's ``windows`` [s]."""
        self.n = n
        self.windows = np.asarray(windows, float)
        self._lags_ns = np.round(self.windows * 1e9).astype(np.int64)
        self._capacity = 256
        self._stamps = np.zeros(self._capacity, dtype=np.int64)
        # Prefix sums of C^-1 and C^-1 y (row k: samples 0..k of the ring).
        self._info = np.zeros((self._capacity, n, n))
        self._score = np.zeros((self._capacity, n))
        self._common = np.zeros((self._capacity, n, n))
        # Prefix moments of the measured centre of mass (estimator/core/blocks.py), times
        # from ``_origin_ns`` [s]; d = 0 until a position comes in.
        self.linear = np.zeros(0, dtype=np.int64)
        self.mass = 0.0
        self._origin_ns = 0
        self._positions = self._position_arrays(self._capacity, 0)
        self._end = 0
        self.statistics = np.zeros(len(self.windows))
        #: whether any measured momentum came in (the test then runs)
        self.active = False
        #: noise beyond the modelled one (stamp jitter between joints and twist, model
        #: error), from successive differences; added to every sample's covariance
        self.excess = np.zeros((n, n))
        self._excess_raw = np.zeros((n, n))
        self._differences = 0
        self._last: Optional[tuple[np.ndarray, np.ndarray]] = None
        # Where bank_step.twist_step leaves its sample's momentum and white
        # covariance (the next successive difference's last sample).
        self._keep = (np.zeros(n), np.zeros((n, n)))
        self._no_position = np.zeros((0, 0))
        self._no_common = np.zeros((n, n))
        self._no_centre = np.zeros(0)
        self._fit_scratch: Optional[np.ndarray] = None

    @staticmethod
    def _position_arrays(capacity: int, d: int) -> list[np.ndarray]:
        """Return empty prefix arrays s0, s1, s2, y0, t1, counts for ``capacity`` rows."""
        return [np.zeros((capacity, d, d)), np.zeros((capacity, d, d)),
                np.zeros((capacity, d, d)), np.zeros((capacity, d)), np.zeros((capacity, d)),
                np.zeros(capacity, dtype=np.int64)]

    def _arrays(self) -> tuple:
        """Return the prefix arrays the kernels take (estimator/core/blocks.py)."""
        return (self._info, self._score, *self._positions)

    @property
    def ready(self) -> bool:
        """Return whether the excess noise is known well enough for the test to run."""
        return self._differences >= EXCESS_MINIMUM

    def _learn_excess(self, mu: np.ndarray, cov: np.ndarray) -> None:
        """
        Update the excess noise from this sample and the last.

        Under no wrench successive measured momenta differ by their noise only (a
        push moves them by F dt, nothing at these rates): E[d d^T] = C_k + C_k-1 +
        2 Q. Q is their running mean (then exponential over EXCESS_SAMPLES), made
        positive semi-definite. Myers & Tapley's noise estimation on differences.
        """
        last, self._last = self._last, (mu, cov)
        if last is None:
            return
        self._differences += 1
        blocks.learn_excess(self._excess_raw, mu, cov, last[0], last[1],
                            float(min(self._differences, EXCESS_SAMPLES)))
        if self._differences % 16 == 1 or self._differences == EXCESS_MINIMUM:
            values, vectors = np.linalg.eigh(self._excess_raw)
            self.excess = (vectors * np.maximum(values, 0.0)) @ vectors.T

    def add(self, stamp_ns: int, mu: np.ndarray, cov: np.ndarray,
            common: Optional[np.ndarray] = None,
            position: Optional[tuple] = None) -> None:
        """
        Take one measured momentum, its white noise's covariance (stamps increasing).

        ``common``: the covariance of its slowly changing error (the filter pose's),
        which a block's mean keeps whole. ``position``: the measured centre of mass
        at the same stamp, (c, its covariance, total mass, linear coordinates)
        (:func:`centre_of_mass`; None: none).
        """
        if self._end and stamp_ns <= self._stamps[self._end - 1]:
            return
        if self._add_compiled(stamp_ns, mu, cov, common, position):
            return
        self._learn_excess(mu, cov)
        try:
            info, lam = blocks.sample_information(
                cov, self.excess, self._no_position if position is None else position[1])
        except np.linalg.LinAlgError:
            return
        if position is None:
            lam = None
        if lam is not None and not len(self.linear):
            self.linear = np.asarray(position[3], dtype=np.int64)
            self.mass = float(position[2])
            self._positions = self._position_arrays(self._capacity, len(self.linear))
        if self._end == self._capacity:
            self._compact(stamp_ns)
        k = self._end
        if not k:
            self._origin_ns = stamp_ns
        self._stamps[k] = stamp_ns
        self._common[k] = 0.0 if common is None else common
        blocks.accumulate(self._info, self._score, k, info, mu)
        if len(self.linear):
            present = lam is not None and len(position[0]) == len(self.linear)
            d = len(self.linear)
            blocks.accumulate_position(
                *self._positions, k, lam if present else np.zeros((d, d)),
                (stamp_ns - self._origin_ns) * 1e-9,
                np.asarray(position[0], float) if present else np.zeros(d), present)
        self._end += 1
        self.active = True

    def _add_compiled(self, stamp_ns: int, mu: np.ndarray, cov: np.ndarray,
                      common: Optional[np.ndarray], position: Optional[tuple]) -> bool:
        """
        Take the common sample in one compiled call (blocks.add_sample); False: not common.

        Common: see :meth:`prepare` (all of :meth:`add` otherwise).
        """
        args = self.prepare(stamp_ns, mu, cov, common, position)
        if args is None:
            return False
        try:
            blocks.add_sample(*args[:8], self._info, self._score, self._common, args[8],
                              self._stamps, args[9], args[10], *self._positions, *args[11:])
        except np.linalg.LinAlgError:
            return True
        self.added()
        return True

    def prepare(self, stamp_ns: int, mu: np.ndarray, cov: np.ndarray,
                common: Optional[np.ndarray] = None,
                position: Optional[tuple] = None) -> Optional[tuple]:
        """
        Return blocks.add_sample's per-sample arguments for a common sample; None: not common.

        Common: a stamp after the last, a sample after the first with a last one to
        difference against, room in the ring, and a position exactly when the test reads
        positions. The excess noise's state is advanced (the sample is then differenced,
        and the excess decomposed when due): the caller makes the
        compiled call and, when it did not raise, calls :meth:`added`. Returns (raw,
        mu, cov, last mu, last cov, divisor, excess, position covariance, common,
        stamp, row, time, centre, with positions).
        """
        last, k, d = self._last, self._end, len(self.linear)
        differences = self._differences + 1
        if last is None or not k or k == self._capacity or (position is None) != (not d) \
                or (d and len(position[0]) != d) or stamp_ns <= self._stamps[k - 1]:
            return None
        self._last = (mu, cov)
        self._differences = differences
        divisor = float(min(differences, EXCESS_SAMPLES))
        if differences % 16 == 1 or differences == EXCESS_MINIMUM:
            # The excess noise's eigen-decomposition is due (_learn_excess): of the raw
            # mean as the compiled call will leave it (the same kernel on a copy), so
            # that call takes the sample with this excess, as add does.
            raw = self._excess_raw.copy()
            blocks.learn_excess(raw, mu, cov, last[0], last[1], divisor)
            values, vectors = np.linalg.eigh(raw)
            self.excess = (vectors * np.maximum(values, 0.0)) @ vectors.T
        return (self._excess_raw, mu, cov, last[0], last[1], divisor, self.excess,
                self._no_position if position is None else position[1],
                self._no_common if common is None else common, stamp_ns, k,
                (stamp_ns - self._origin_ns) * 1e-9,
                self._no_centre if position is None else np.asarray(position[0], float),
                position is not None)

    def added(self) -> None:
        """Count the sample :meth:`prepare` gave, now in the ring."""
        self._end += 1
        self.active = True

    def _compact(self, stamp_ns: int) -> None:
        """Drop samples older than three longest windows (and re-base the prefix sums)."""
        oldest = stamp_ns - 3 * self._lags_ns[-1] - 1
        keep = max(0, int(np.searchsorted(self._stamps[:self._end], oldest, 'right')) - 1)
        count = self._end - keep
        if count > self._capacity // 2:
            self._capacity *= 2
        old = [self._stamps, self._info, self._score, self._common, *self._positions]
        new = [np.zeros((self._capacity,) + array.shape[1:], array.dtype) for array in old]
        for source, target in zip(old, new):
            target[:count] = source[keep:self._end]
        # Prefix sums from the first kept sample (common and stamps are per sample).
        for index in [1, 2] + list(range(4, len(new))):
            if keep:
                new[index][:count] -= old[index][keep - 1]
        self._stamps, self._info, self._score, self._common = new[:4]
        positions = new[4:]
        if len(self.linear) and count:
            # Times from the first kept sample: the moments stay small numbers.
            shift = (int(self._stamps[0]) - self._origin_ns) * 1e-9
            s0, s1, s2, y0, t1, _ = positions
            s2[:count] += -2.0 * shift * s1[:count] + shift * shift * s0[:count]
            s1[:count] -= shift * s0[:count]
            t1[:count] -= shift * y0[:count]
            self._origin_ns = int(self._stamps[0])
        self._positions = positions
        self._end = count

    def _mean(self, lo: int, hi: int) -> tuple[np.ndarray, np.ndarray]:
        """Return the mean over prefix rows (lo, hi] and its covariance (without common)."""
        return blocks.block_mean(*self._arrays(), int(lo), int(hi), self.mass, self.linear)

    def update(self, stamp_ns: int, floor_ns: Optional[int]) -> int:
        """Compute every window's statistic at ``stamp_ns``; return the best window's index."""
        self.statistics[:] = 0.0
        if self._end < 4 or not self.ready:
            return -1
        first = int(self._stamps[0])
        first = first if floor_ns is None else max(floor_ns, first)
        try:
            # Both blocks hold samples, and the before block starts within the data.
            found, values = blocks.bank_statistics(
                *self._arrays(), self._common, self._stamps, self._end, self._lags_ns,
                stamp_ns, first, self.mass, self.linear)
        except np.linalg.LinAlgError:
            return -1
        if not found:
            return -1
        self.statistics[:] = values
        return int(np.argmax(self.statistics))

    def locate(self, stamp_ns: int, window: int, floor_ns: Optional[int],
               points: int = 40) -> BlockDetection:
        """
        Return the constant-force pulse that best explains the change the window found.

        Over the window's span (t-3L, t], the measured momenta are fitted by
        y_k = mu0 + J r_k, r_k = clip((t_k - s) / (e - s), 0, 1): constant before s,
        a ramp (a constant force) to e, constant after (e = t: still pushing). The
        start s and end e (on a grid of ``points``) maximise the GLR of J with mu0 a
        nuisance (with the measured centre of mass: :meth:`_position_rows`); mu0 and
        its covariance are the momentum before. The detecting
        window may hold the push in its after block (a strong push is flagged while it
        goes on), so its gap does not date it. Done at a detection only.
        """
        stamps = self._stamps[:self._end]
        lag = int(self._lags_ns[window])
        lo_ns = stamp_ns - 3 * lag
        if floor_ns is not None:
            lo_ns = max(lo_ns, floor_ns)
        lo = max(int(np.searchsorted(stamps, lo_ns, 'right')) - 1, -1)
        hi = self._end - 1
        index = np.arange(lo + 1, hi + 1)
        previous = np.concatenate(([lo], index[:-1]))
        info_k = self._info[index] - np.where(
            (previous < 0)[:, None, None], 0.0, self._info[np.maximum(previous, 0)])
        score_k = self._score[index] - np.where(
            (previous < 0)[:, None], 0.0, self._score[np.maximum(previous, 0)])
        n = self.n
        times = (stamps[index] - stamps[hi]) * 1e-9
        grid = np.unique(np.linspace(0, len(index) - 1, points).round().astype(int))
        starts, ends = np.meshgrid(times[grid], times[grid], indexing='ij')
        keep = ends > starts
        starts, ends = starts[keep], ends[keep]
        # clip((t - s) / (e - s), 0, 1) and its square, compiled (numpy's bits).
        ramp, ramp_square = self._work((len(starts), len(times)), (len(starts), len(times)))
        blocks.pulse_ramps(times, starts, ends, ramp, ramp_square)
        flat_info = info_k.reshape(len(index), n * n)
        # sum r Lambda and sum r Lambda y in one product (BLAS reads the ramps once; each
        # column the bits of its own product: test_multiscale_kernels.py), sum r^2 Lambda.
        both = ramp @ np.hstack((flat_info, score_k))
        cross, score_j = both[:, :n * n], both[:, n * n:]
        square = ramp_square @ flat_info
        # Unknowns (mu0, c0, J): the twists' rows, then the positions' (_position_rows).
        # The (mu0, c0) block and its right-hand side are the same in every fit.
        size = 2 * n + len(self.linear)
        nuisance, jj = slice(0, size - n), slice(size - n, size)
        block = np.zeros((size - n, size - n))
        rhs_block = np.zeros(size - n)
        block[:n, :n] = flat_info.sum(axis=0).reshape(n, n)
        rhs_block[:n] = score_k.sum(axis=0)
        sums = self._position_rows(index, previous, times, starts, ends, block, rhs_block)
        normal, rhs = self._work((len(starts), size, size), (len(starts), size))
        empty = np.zeros((0, 0))
        blocks.pulse_normals(block, rhs_block, cross, square, score_j,
                             *(sums if sums is not None else (empty,) * 4), self.linear,
                             self.mass, self.mass ** 2, sums is not None, normal, rhs)
        # The GLR of J with (mu0, c0) a nuisance: J^T S J, S the Schur complement;
        # the nuisance block, the same in every fit, is inverted once (numpy's inv per
        # matrix: the bits of the stacked call).
        try:
            inverse = np.linalg.inv(block)
            couple = normal[:, jj, nuisance]
            schur = normal[:, jj, jj] - couple @ inverse @ couple.transpose(0, 2, 1)
            residual = rhs[:, jj] - (couple @ (inverse @ rhs[:, nuisance, None]))[..., 0]
            impulse = np.linalg.solve(schur, residual[..., None])[..., 0]
        except np.linalg.LinAlgError:
            impulse = residual = np.zeros((len(starts), n))
        values = np.einsum('ij,ij->i', residual, impulse)
        best = int(np.argmax(values))
        try:
            joint = np.linalg.inv(normal[best])
        except np.linalg.LinAlgError:
            joint = np.linalg.pinv(normal[best])
        cov = joint[:n, :n]
        before = (joint @ rhs[best])[:n]
        start = int(stamps[hi] + round(starts[best] * 1e9))
        end = int(stamps[hi] + round(ends[best] * 1e9))
        return BlockDetection(start, end, float(self.windows[window]), float(values[best]),
                              before, cov + self._common[max(lo, 0)])

    def _work(self, *shapes: tuple) -> list[np.ndarray]:
        """
        Return arrays of ``shapes`` for a pulse fit's work (contents undefined).

        Fresh arrays of a few MB cost mostly their page faults (~0.5 ms per MB here, more
        than filling them): up to FIT_SCRATCH elements in all they are views of one
        buffer kept between detections; larger fits (long windows) allocate as numpy did.
        """
        sizes = [int(np.prod(shape)) for shape in shapes]
        if sum(sizes) > FIT_SCRATCH:
            return [np.empty(shape) for shape in shapes]
        if self._fit_scratch is None:
            self._fit_scratch = np.empty(FIT_SCRATCH)
        offsets = np.cumsum([0] + sizes)
        return [self._fit_scratch[offsets[k]:offsets[k + 1]].reshape(shape)
                for k, shape in enumerate(shapes)]

    def _position_rows(self, index: np.ndarray, previous: np.ndarray, times: np.ndarray,
                       starts: np.ndarray, ends: np.ndarray, block: np.ndarray,
                       rhs: np.ndarray) -> Optional[tuple[np.ndarray, ...]]:
        """
        Add the measured centre of mass to the pulse fits of :meth:`locate`.

        A pulse from s to e moves c by J R(t) / M, R the ramp's integral (0 before s,
        (t - s)^2 / 2 (e - s) during it, (e - s) / 2 + t - e after), so
        c_k = c0 + t_k E mu0 / M + R_k E J / M (E: the linear coordinates), with the
        sample's information P_k. Adds the (mu0, c0) part, the same in every fit, to
        ``block`` and ``rhs``; returns the per-fit sums blocks.pulse_normals takes
        (sum R P, sum R t P, sum R^2 P, sum R P c), None without positions.
        """
        d = len(self.linear)
        if not d:
            return None
        s0, _, _, y0, _, counts = self._positions
        low = np.maximum(previous, 0)
        first = (previous < 0)[:, None, None]
        lam = s0[index] - np.where(first, 0.0, s0[low])
        weighted = y0[index] - np.where(first[..., 0], 0.0, y0[low])
        present = (counts[index] - np.where(previous < 0, 0, counts[low])) > 0
        if present.sum() < 2:
            return None
        lam, weighted, t = lam[present], weighted[present], times[present]
        c = np.linalg.solve(lam, weighted[..., None])[..., 0]
        c = c - c.mean(axis=0)
        # R, R t and R^2 per fit and sample, compiled (numpy's expressions' bits), in
        # the work space locate's ramps used (no longer needed).
        ramp, timed, squared = self._work(*[(len(starts), len(t))] * 3)
        blocks.position_ramps(t, starts, ends, ramp, timed, squared)
        flat = lam.reshape(len(t), d * d)
        pc = np.einsum('kij,kj->ki', lam, c)
        mass, n = self.mass, self.n
        both = ramp @ np.hstack((flat, pc))  # sum R P, sum R P c: one product, as above
        sums = [both[:, :d * d]] + [weights @ flat for weights in (timed, squared)]
        p0, p1, p2 = (((t ** j)[None, :] @ flat).reshape(d, d) for j in range(3))
        select = np.zeros((d, n))
        select[np.arange(d), self.linear] = 1.0
        st = select.T
        mu0, c0 = slice(0, n), slice(n, n + d)
        block[mu0, mu0] += st @ p2 @ select / mass ** 2
        block[mu0, c0] += st @ p1 / mass
        block[c0, mu0] += p1 @ select / mass
        block[c0, c0] += p0
        rhs[mu0] += (st @ (t @ pc)) / mass
        rhs[c0] += pc.sum(axis=0)
        return (*sums, both[:, d * d:])

    def mean(self, lo_ns: int, hi_ns: int) -> Optional[tuple[np.ndarray, np.ndarray]]:
        """Return the mean measured momentum over (lo_ns, hi_ns] and its covariance."""
        if not self._end:
            return None
        stamps = self._stamps[:self._end]
        lo, hi = np.searchsorted(stamps, [lo_ns, hi_ns], 'right') - 1
        if hi <= lo or lo < -1:
            return None
        try:
            mean, cov = self._mean(lo, hi)
        except np.linalg.LinAlgError:
            return None
        return mean, cov + self._common[hi]
