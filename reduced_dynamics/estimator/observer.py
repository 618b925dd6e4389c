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
Momentum drift: an observer of mu_dot = w and a detector of thruster/contact events.

Without external wrench mu is constant (Noether); an external wrench w (world
frame, about the world origin) gives ``mu_dot = w``. The observer is the
momentum-observer filter ``dr/dt = K (w - r)``, i.e. ``r = K (mu - mu_0 -
int r)``, discretised exactly for a wrench constant between samples:
``r_k = e^{-K dt} r_{k-1} + (1 - e^{-K dt}) (mu_k - mu_{k-1}) / dt``. Its
integral tends to the impulse; a step in w is followed with time constant 1/K.

An event starts when |r| exceeds the threshold and ends after ``hold`` seconds
below half of it; the reduced model is then re-reduced at the new momentum.
Between events the momentum level is the running mean of mu since the last
event, which averages sensor noise out.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import math
from typing import Callable, Optional

import numpy as np


@dataclass
class MomentumEvent:
    """A detected external-wrench event and the momentum change across it."""

    start_ns: int
    end_ns: Optional[int] = None
    mu_before: Optional[np.ndarray] = None
    mu_after: Optional[np.ndarray] = None
    peak_wrench: float = 0.0

    @property
    def impulse(self) -> Optional[np.ndarray]:
        """Return mu_after - mu_before (world frame), once the event has ended."""
        if self.mu_before is None or self.mu_after is None:
            return None
        return self.mu_after - self.mu_before


@dataclass
class MomentumObserver:
    """
    External-wrench observer, event detector and momentum level.

    :meth:`update_many` takes a chunk of samples: the filter inputs are formed
    for the whole chunk at once and only the scalar recursion and the event
    logic loop in Python. The running level sum is folded lazily (one
    accumulate per run of quiet samples). :meth:`update` is a chunk of one.
    """

    bandwidth: float
    threshold: float
    hold: float
    rate: Optional[np.ndarray] = None
    events: list[MomentumEvent] = field(default_factory=list)
    _last_mu: Optional[np.ndarray] = None
    _last_ns: Optional[int] = None
    _level_sum: Optional[np.ndarray] = None
    _level_count: int = 0
    _quiet_since: Optional[int] = None
    _changed: bool = False
    # Rows of the current chunk accumulated into the level but not yet summed.
    _run: Optional[np.ndarray] = None
    _run_start: int = 0
    _run_stop: int = 0

    @property
    def in_event(self) -> bool:
        """Return whether an event is under way."""
        return bool(self.events) and self.events[-1].end_ns is None

    @property
    def has_level(self) -> bool:
        """Return whether a momentum level exists (without computing it)."""
        return self._level_count > 0 or self._run_stop > self._run_start

    @property
    def level(self) -> Optional[np.ndarray]:
        """Return the momentum level the reduced model uses (mean since the last event)."""
        self._fold()
        if self._level_count == 0:
            return None
        return self._level_sum / self._level_count

    def take_level_change(self) -> bool:
        """Return True once after the level was reset (an event ended: re-reduce)."""
        changed, self._changed = self._changed, False
        return changed

    def update(self, stamp_ns: int, mu: np.ndarray) -> np.ndarray:
        """Feed mu at a stamp; return the external-wrench estimate r."""
        self.update_many(np.array([stamp_ns], dtype=np.int64), np.asarray(mu)[None, :])
        return self.rate

    def update_many(self, stamps_ns: np.ndarray, mus: np.ndarray,
                    after: Optional[Callable[[int], None]] = None) -> np.ndarray:
        """
        Feed a chunk of mu (K, n) at increasing stamps; return the estimates r (K, n).

        ``after(k)`` is called once sample k is taken, with the observer in the
        state a sample-by-sample run would have there (for predictions). The
        rows are bit-identical to feeding the samples one at a time.
        """
        count = len(stamps_ns)
        if count == 0:
            return np.empty_like(mus)
        stamps = stamps_ns.tolist()
        rates = self._filter(stamps_ns, mus)
        # |r| row by row with a fixed summation order (independent of the chunk length).
        sizes = np.sqrt(np.matmul(rates[:, None, :], rates[:, :, None])[:, 0, 0]).tolist()
        self._detect_many(stamps, mus, rates, sizes, after)
        self.rate = rates[-1].copy()
        self._last_mu, self._last_ns = mus[-1].copy(), stamps[-1]
        self._fold()
        self._run = None
        return rates

    def _filter(self, stamps_ns: np.ndarray, mus: np.ndarray) -> np.ndarray:
        """
        Run r_k = d_k r_{k-1} + (1 - d_k) (mu_k - mu_{k-1}) / dt_k, d_k = exp(-K dt_k).

        The inputs are formed for the whole chunk; only the scalar recursion
        loops, one column at a time. A sample without a usable predecessor
        (the first, or a stamp not after the previous) keeps r: d = 1 and a
        zero input. math.exp, not np.exp: numpy's SIMD exp may round
        differently depending on the chunk length.
        """
        count, n = mus.shape
        if count == 1:
            return self._filter_one(int(stamps_ns[0]), mus)
        previous = np.empty_like(stamps_ns)
        previous[1:] = stamps_ns[:-1]
        # Without a predecessor the first "previous" is the sample itself: invalid.
        previous[0] = stamps_ns[0] if self._last_mu is None else self._last_ns
        valid = stamps_ns > previous
        steps = np.where(valid, (stamps_ns - previous) * 1e-9, 1.0)
        decays = np.array(list(map(math.exp, (-self.bandwidth * steps).tolist())))
        decays[~valid] = 1.0
        gains = np.where(valid, 1.0 - decays, 0.0)
        last_mu = mus[0] if self._last_mu is None else self._last_mu
        differences = mus - np.concatenate((last_mu[None, :], mus[:-1]))
        terms = (gains[:, None] * differences) / steps[:, None]
        start = [0.0] * n if self.rate is None else self.rate.tolist()
        decay_list = decays.tolist()
        columns = []
        for rate, column in zip(start, terms.T.tolist()):
            out = []
            append = out.append
            for decay, term in zip(decay_list, column):
                rate = decay * rate + term
                append(rate)
            columns.append(out)
        return np.array(columns).T.copy()

    def _filter_one(self, stamp: int, mus: np.ndarray) -> np.ndarray:
        """Do :meth:`_filter` for one sample: the same operations, fewer numpy calls."""
        rate = [0.0] * mus.shape[1] if self.rate is None else self.rate.tolist()
        if self._last_mu is not None and stamp > self._last_ns:
            dt = (stamp - self._last_ns) * 1e-9
            decay = math.exp(-self.bandwidth * dt)
            terms = ((1.0 - decay) * (mus[0] - self._last_mu) / dt).tolist()
            rate = [decay * r + t for r, t in zip(rate, terms)]
        else:
            # No usable predecessor: d = 1 and a zero input, exactly as the chunked
            # form computes them (down to the sign of a zero).
            last_mu = mus[0] if self._last_mu is None else self._last_mu
            terms = ((0.0 * (mus[0] - last_mu)) / 1.0).tolist()
            rate = [1.0 * r + t for r, t in zip(rate, terms)]
        return np.array([rate])

    def _detect_many(self, stamps: list, mus: np.ndarray, rates: np.ndarray, sizes: list,
                     after: Optional[Callable[[int], None]]) -> None:
        """Start and end events sample by sample; quiet samples join the level."""
        threshold, half, hold = self.threshold, 0.5 * self.threshold, self.hold
        events = self.events
        event = events[-1] if self.in_event else None
        quiet_since = self._quiet_since
        # Quiet rows are not summed here: rows run_start.. of this chunk join the
        # level when _fold runs (when the level is read, and at the chunk's end).
        self._run = mus
        run_start = None if event is not None else 0
        for k, size in enumerate(sizes):
            stamp = stamps[k]
            if event is None:
                if size > threshold:
                    self._run_start, self._run_stop = run_start, k
                    level = self.level
                    before = level if level is not None else \
                        (mus[k - 1] if k else self._last_mu)
                    event = MomentumEvent(stamp, mu_before=None if before is None
                                          else before.copy(), peak_wrench=size)
                    events.append(event)
                    quiet_since = run_start = None
            else:
                if size > event.peak_wrench:
                    event.peak_wrench = size
                if size > half:
                    quiet_since = None
                else:
                    if quiet_since is None:
                        quiet_since = stamp
                    if (stamp - quiet_since) * 1e-9 >= hold:
                        event.end_ns = stamp
                        event.mu_after = mus[k].copy()
                        self._changed = True
                        # The level restarts from this sample.
                        self._level_sum, self._level_count = None, 0
                        event = None
                        run_start = k
            if after is not None:
                # Leave the observer as a one-by-one run would, for predictions.
                self._run_start, self._run_stop = \
                    (k + 1, k + 1) if run_start is None else (run_start, k + 1)
                self._quiet_since = quiet_since
                self.rate = rates[k]
                self._last_mu, self._last_ns = mus[k], stamp
                after(k)
                if run_start is not None:
                    run_start = self._run_start  # the level may have been folded
        count = len(sizes)
        self._run_start, self._run_stop = (count, count) if run_start is None \
            else (run_start, count)
        self._quiet_since = quiet_since

    def _fold(self) -> None:
        """Add the pending run of quiet rows to the level sum, in order."""
        start, stop = self._run_start, self._run_stop
        if stop <= start:
            return
        rows = self._run[start:stop]
        total = self._level_sum
        if total is None:
            total, rows = rows[0].copy(), rows[1:]
        if len(rows) == 1:
            total = total + rows[0]
        elif len(rows):
            # accumulate adds row after row: the same sums as one sample at a time.
            total = np.add.accumulate(np.concatenate((total[None, :], rows)), axis=0)[-1]
        self._level_sum = total
        self._level_count += stop - start
        self._run_start = stop
