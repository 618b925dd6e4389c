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
        #: the same bank on measured momenta (a twist measured: :class:`MomentumBlocks`)
        self.blocks = MomentumBlocks(n, self.windows)

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
        if measured:
            if not self.blocks.active:
                self._threshold_period = 0.0  # two tests now share the rate
            for item in measured:
                self.blocks.add(*item)
        found = self._filtered(stamp_ns, mu, cov)
        if not self.blocks.active or self._period is None:
            return found if wanted else None
        best = self.blocks.update(stamp_ns, self.floor_ns)
        if not wanted:
            # The fit below costs ~ points^2 x the window's samples (MomentumBlocks.locate):
            # once per sample it was most of the node's time while a push lasted.
            return None
        if best < 0 or not self.blocks.statistics[best] > self.threshold:
            return found
        block = self.blocks.locate(stamp_ns, best, self.floor_ns)
        return ImpulseDetection(block.start_ns, block.window, block.statistic,
                                block.mu_before, block.cov_before, True)

    def measured_mean(self, lo_ns: int, hi_ns: int
                      ) -> Optional[tuple[np.ndarray, np.ndarray]]:
        """Return the mean measured momentum over (lo_ns, hi_ns] (None: no twist)."""
        return self.blocks.mean(lo_ns, hi_ns) if self.blocks.active else None

    def _filtered(self, stamp_ns: int, mu: np.ndarray,
                  cov: np.ndarray) -> Optional[ImpulseDetection]:
        """Run the test on the filtered momentum (module doc)."""
        if self._end > self._start:
            dt = (stamp_ns - int(self._stamps[self._end - 1])) * 1e-9
            if dt > 0.0:
                self._period = dt if self._period is None else \
                    self._period + 0.01 * (dt - self._period)
        self._store(stamp_ns, mu, cov)
        if self._period is None:
            return None
        if abs(self._period - self._threshold_period) > \
                PERIOD_TOLERANCE * self._threshold_period or not self._threshold_period:
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
    to_world = ad_inverse.T
    white = to_world @ locked @ (twist_cov + joint_cov) @ locked.T @ to_world.T
    w = to_world @ kirillov(pi)
    return to_world @ pi, white, w @ pose_cov @ w.T


def twist_momenta(flt: Any, before: Any, lin: Any, start_ns: Optional[int], stamp_ns: int,
                  measurements: list, gated: list) -> list[tuple]:
    """
    Return (stamp, mu, covariance) of a row's accepted twist measurements.

    ``before``, ``lin``: the linearisations of the previous row (at ``start_ns``)
    and of this one (at ``stamp_ns``); A qbar_dot is interpolated to each
    measurement's stamp, as the filter does (a moving arm's A qbar_dot changes within
    a row interval by more than a precise twist's noise). ``gated``: stamps the
    filter refused. The filter's pose maps them to the world.
    """
    if flt.g is None:
        return []
    # To the world with the filter's pose, not each sample's: a measured pose's noise
    # would weigh the samples by their own error (C depends on it), biasing the means.
    n = lin.locked.shape[0]
    ad_inverse, pose_cov = flt._adjoint_inverse(flt.g), flt.p[:n, :n]
    out = []
    span = None if start_ns is None or before is None else stamp_ns - start_ns
    for measurement in measurements:
        if measurement is None or measurement.twist is None or \
                measurement.stamp_ns in gated:
            continue
        connection = lin.connection_qd
        if span and measurement.stamp_ns < stamp_ns:
            fraction = (measurement.stamp_ns - start_ns) / span
            connection = before.connection_qd + fraction * (lin.connection_qd
                                                            - before.connection_qd)
        own = None if measurement.noise is None else measurement.noise[1]
        out.append((measurement.stamp_ns, *twist_momentum(
            ad_inverse, lin.locked, connection, measurement.twist,
            flt._r_twist if own is None else own, lin.joint_cov, pose_cov,
            flt.group.coadjoint_form)))
    return out


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
    it: a 3 s block of 62.5 Hz twists is ~14 times as precise as one.
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
        d = mu - last[0]
        sample = 0.5 * (np.outer(d, d) - cov - last[1])
        self._differences += 1
        self._excess_raw += (sample - self._excess_raw) / min(self._differences,
                                                              EXCESS_SAMPLES)
        if self._differences % 16 == 1 or self._differences == EXCESS_MINIMUM:
            values, vectors = np.linalg.eigh(self._excess_raw)
            self.excess = (vectors * np.maximum(values, 0.0)) @ vectors.T

    def add(self, stamp_ns: int, mu: np.ndarray, cov: np.ndarray,
            common: Optional[np.ndarray] = None) -> None:
        """
        Take one measured momentum, its white noise's covariance (stamps increasing).

        ``common``: the covariance of its slowly changing error (the filter pose's),
        which a block's mean keeps whole.
        """
        if self._end and stamp_ns <= self._stamps[self._end - 1]:
            return
        self._learn_excess(mu, cov)
        try:
            info = np.linalg.inv(cov + self.excess)
        except np.linalg.LinAlgError:
            return
        if self._end == self._capacity:
            self._compact(stamp_ns)
        k = self._end
        self._stamps[k] = stamp_ns
        self._common[k] = 0.0 if common is None else common
        if k:
            self._info[k] = self._info[k - 1] + info
            self._score[k] = self._score[k - 1] + info @ mu
        else:
            self._info[k], self._score[k] = info, info @ mu
        self._end += 1
        self.active = True

    def _compact(self, stamp_ns: int) -> None:
        """Drop samples older than three longest windows (and re-base the prefix sums)."""
        oldest = stamp_ns - 3 * self._lags_ns[-1] - 1
        keep = max(0, int(np.searchsorted(self._stamps[:self._end], oldest, 'right')) - 1)
        count = self._end - keep
        base_info = self._info[keep - 1].copy() if keep else 0.0
        base_score = self._score[keep - 1].copy() if keep else 0.0
        if count > self._capacity // 2:
            self._capacity *= 2
        stamps = np.zeros(self._capacity, dtype=np.int64)
        info = np.zeros((self._capacity, self.n, self.n))
        score = np.zeros((self._capacity, self.n))
        common = np.zeros((self._capacity, self.n, self.n))
        common[:count] = self._common[keep:self._end]
        self._common = common
        stamps[:count] = self._stamps[keep:self._end]
        info[:count] = self._info[keep:self._end] - base_info
        score[:count] = self._score[keep:self._end] - base_score
        self._stamps, self._info, self._score, self._end = stamps, info, score, count

    def _sums(self, after: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Return the prefix sums up to index ``after`` (-1: none)."""
        index = np.maximum(after, 0)
        empty = (after < 0)[..., None]
        return (np.where(empty[..., None], 0.0, self._info[index]),
                np.where(empty, 0.0, self._score[index]))

    def _statistics(self, lo: np.ndarray, split0: np.ndarray, split1: np.ndarray,
                    hi: np.ndarray) -> tuple[np.ndarray, ...]:
        """Return T, the before mean and its covariance for blocks (lo, split0], (split1, hi]."""
        info0, score0 = self._sums(lo)
        info1, score1 = self._sums(split0)
        info2, score2 = self._sums(split1)
        info3, score3 = self._sums(hi)
        cov_before = np.linalg.inv(info1 - info0)
        cov_after = np.linalg.inv(info3 - info2)
        before = np.matmul(cov_before, (score1 - score0)[..., None])[..., 0]
        after = np.matmul(cov_after, (score3 - score2)[..., None])[..., 0]
        # The filter pose's error is not averaged: each block keeps its last one.
        cov_before = cov_before + self._common[split0]
        cov_after = cov_after + self._common[hi]
        d = after - before
        solved = np.linalg.solve(cov_before + cov_after, d[..., None])[..., 0]
        return np.einsum('ij,ij->i', d, solved), before, cov_before

    def update(self, stamp_ns: int, floor_ns: Optional[int]) -> int:
        """Compute every window's statistic at ``stamp_ns``; return the best window's index."""
        self.statistics[:] = 0.0
        if self._end < 4 or not self.ready:
            return -1
        stamps = self._stamps[:self._end]
        first = int(stamps[0]) if floor_ns is None else max(floor_ns, int(stamps[0]))
        bounds = stamp_ns - np.outer(self._lags_ns, np.arange(3, -1, -1))
        index = np.searchsorted(stamps, bounds, 'right') - 1
        # Both blocks hold samples, and the before block starts within the data.
        covered = (bounds[:, 0] >= first) & (index[:, 1] > index[:, 0]) & \
            (index[:, 3] > index[:, 2])
        if not covered.any():
            return -1
        rows = index[covered]
        try:
            values = self._statistics(rows[:, 0], rows[:, 1], rows[:, 2], rows[:, 3])[0]
        except np.linalg.LinAlgError:
            return -1
        self.statistics[covered] = values
        return int(np.argmax(self.statistics))

    def locate(self, stamp_ns: int, window: int, floor_ns: Optional[int],
               points: int = 40) -> BlockDetection:
        """
        Return the constant-force pulse that best explains the change the window found.

        Over the window's span (t-3L, t], the measured momenta are fitted by
        y_k = mu0 + J r_k, r_k = clip((t_k - s) / (e - s), 0, 1): constant before s,
        a ramp (a constant force) to e, constant after (e = t: still pushing). The
        start s and end e (on a grid of ``points``) maximise the GLR of J with mu0 a
        nuisance; mu0 and its covariance are the momentum before. The detecting
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
        ramp = np.clip((times[None, :] - starts[:, None]) / (ends - starts)[:, None], 0.0, 1.0)
        flat_info = info_k.reshape(len(index), n * n)
        total = flat_info.sum(axis=0).reshape(n, n)
        cross = (ramp @ flat_info).reshape(-1, n, n)           # sum r Lambda
        square = ((ramp ** 2) @ flat_info).reshape(-1, n, n)   # sum r^2 Lambda
        score_j = ramp @ score_k                                 # sum r Lambda y
        score_mu = score_k.sum(axis=0)
        inverse = np.linalg.inv(total)
        schur = square - cross @ inverse @ cross.transpose(0, 2, 1)
        residual = score_j - (cross @ (inverse @ score_mu))
        try:
            impulse = np.linalg.solve(schur, residual[..., None])[..., 0]
        except np.linalg.LinAlgError:
            impulse = np.zeros_like(residual)
        values = np.einsum('ij,ij->i', residual, impulse)
        best = int(np.argmax(values))
        joint = np.block([[total, cross[best].T], [cross[best], square[best]]])
        cov = np.linalg.inv(joint)[:n, :n]
        before = inverse @ (score_mu - cross[best].T @ impulse[best])
        start = int(stamps[hi] + round(starts[best] * 1e9))
        end = int(stamps[hi] + round(ends[best] * 1e9))
        return BlockDetection(start, end, float(self.windows[window]), float(values[best]),
                              before, cov + self._common[max(lo, 0)])

    def mean(self, lo_ns: int, hi_ns: int) -> Optional[tuple[np.ndarray, np.ndarray]]:
        """Return the mean measured momentum over (lo_ns, hi_ns] and its covariance."""
        if not self._end:
            return None
        stamps = self._stamps[:self._end]
        lo, hi = np.searchsorted(stamps, [lo_ns, hi_ns], 'right') - 1
        if hi <= lo or lo < -1:
            return None
        info0, score0 = self._sums(np.array([lo]))
        info1, score1 = self._sums(np.array([hi]))
        try:
            cov = np.linalg.inv(info1[0] - info0[0])
        except np.linalg.LinAlgError:
            return None
        return cov @ (score1[0] - score0[0]), cov + self._common[hi]
