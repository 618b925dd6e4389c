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
The block test of the multi-scale bank: measured momenta before a gap against after it.

Block means of every measured momentum (information-weighted prefix sums,
estimator/core/blocks.py), chi2_n exactly under no wrench, the noise the model
misses learnt from successive differences (docs/multiscale_events.md).
"""

from __future__ import annotations

from typing import Optional

import numpy as np
from reduced_dynamics.estimator import block_pulse
from reduced_dynamics.estimator.block_pulse import BlockDetection
from reduced_dynamics.estimator.core import blocks
from reduced_dynamics.estimator.core.bank_step import (BLOCK_END, DIFFERENCES, EXCESS_SAMPLES,
                                                       ORIGIN)
from reduced_dynamics.estimator.multiscale_bank import state_slot

#: Successive differences before the block test runs (the memory of the excess noise's
#: running mean, EXCESS_SAMPLES, is core/bank_step.py's).
EXCESS_MINIMUM = 200


class MomentumBlocks:
    """
    GLR of a momentum change from measured momenta: before a gap against after it.

    With a twist measured, every sample gives mu
    (:func:`~reduced_dynamics.estimator.measured_momentum.twist_momentum`) with its
    own, independent noise C_k. Without a wrench mu is constant, so the
    information-weighted mean of a block of samples, m = (sum C^-1)^-1 sum C^-1 y,
    has covariance (sum C^-1)^-1, and for window L (before (t-3L, t-2L], gap
    (t-2L, t-L], after (t-L, t])

        T_L = (m_after - m_before)^T (V_after + V_before)^-1 (m_after - m_before)

    is exactly chi2_n. A push inside the gap moves the difference by its impulse.
    Unlike the filtered momentum (whose covariance holds the filter's random-walk
    wrench, :class:`.MultiScaleTest`), a block of L seconds averages every sample in
    it: a 3 s block of 62.5 Hz twists is ~14 times as precise as one. Where the
    base pose comes with the twist, the measured centre of mass joins each block
    (its line fit's slope times the mass is the linear momentum:
    estimator/core/blocks.py), which on a heavy base with noisy velocities carries
    most of a slow push's evidence.
    """

    # The ring's end, the successive differences taken and the origin of the times [ns]:
    # elements of ``_state`` (bank_step.twist_step advances them in place).
    _end = state_slot('_state', BLOCK_END)
    _differences = state_slot('_state', DIFFERENCES)
    _origin_ns = state_slot('_state', ORIGIN)

    def __init__(self, n: int, windows: np.ndarray) -> None:
        """Set up for momenta of dimension ``n`` and the bank's ``windows`` [s]."""
        self.n = n
        self._state = np.zeros(3, dtype=np.int64)
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
        (:func:`~reduced_dynamics.estimator.measured_momentum.centre_of_mass`; None: none).
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
        """Return the pulse that best explains window ``window``'s change (block_pulse.py)."""
        return block_pulse.locate(self, stamp_ns, window, floor_ns, points)

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
