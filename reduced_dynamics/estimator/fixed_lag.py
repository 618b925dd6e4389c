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
Online fixed-lag smoothing: the RTS backward pass over the last ``lag`` seconds of steps.

The filter's recorded steps (:class:`~.core.state.FilterStep`) go into a ring
buffer of stacked arrays, each with its smoother gain C_k (computed once, when
step k + 1 comes: it depends on filtered quantities alone). Once a row's stamp
is ``lag`` behind the newest step, the compiled backward pass of the means
(:func:`~.core.smoother.backward_mean`, the full smoother's arithmetic) runs
from the newest step back to the oldest row still waiting, and every row at
least ``lag`` old is emitted with its smoothed momentum and momentum rate,
stamped with the row's own time. The topics carry no covariance, so none is
propagated.

The pass runs at most once per ``PASS_FRACTION * lag`` of stamp time, so a row
is smoothed over between ``lag`` and ``(1 + PASS_FRACTION) lag`` of later data
and the pass costs ``(1 + PASS_FRACTION) / PASS_FRACTION`` backward steps per
filter step (mean only, the gains cached). A pass longer than ``SLICE_STEPS`` is
spread over the next filter steps, ``SLICE_STEPS`` backward steps each (the same
arithmetic: the same bits), and its rows go out when it is done: a live estimator
(the node) then pays no pass at once in one input callback. Its rows are kept
as columns (:class:`FixedLagRows`), a row object only when read. Memory is the
steps of that window (one d x d gain, two poses and two states a step; the buffer
drops every step before the oldest waiting row). A restart step (no transition) makes the past
independent of what follows: everything waiting is emitted at once. At lag 0
each row is emitted at its own step (the causal estimate); with a lag beyond
the run, :meth:`FixedLagSmoother.flush` at the end gives the full smoother.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, Callable, NamedTuple, Optional, Union

import numpy as np
import pinocchio as pin

from reduced_dynamics.estimator.core.smoother import backward_mean, smoother_gain
from reduced_dynamics.estimator.core.state import FilterStep
from reduced_dynamics.geometry.lie_group import BaseGroup
from reduced_dynamics.messages.cdr_columns import stamp_columns, vector6_records
from reduced_dynamics.messages.samples import trusted_sample, WrenchSample

NS = 1_000_000_000
#: A backward pass at most once per this fraction of the lag (stamp time).
PASS_FRACTION = 0.5
#: Initial buffer capacity in steps (it doubles when the window needs more).
INITIAL_CAPACITY = 256
#: Backward steps a pass runs per filter step appended: a pass over more is spread over
#: the next steps (the same arithmetic, so the same bits), and its rows go out when it
#: reaches them. At 1 kHz and a 0.5 s lag a pass is ~750 steps (~1.3 ms at once, the
#: node's largest latency spike after its rows' publication; docs/fixed_lag.md,
#: "Latency in the node").
SLICE_STEPS = 32

#: (smoothed pose 4 x 4, x, command held or None) -> the momentum rate (n,)
RateOf = Callable[[np.ndarray, np.ndarray, Optional[np.ndarray]], np.ndarray]


class FixedLagRow(NamedTuple):
    """A row's fixed-lag estimate: its stamp, mu and momentum rate (algebra and samples)."""

    stamp_ns: int
    mu: np.ndarray
    rate: np.ndarray
    momentum: WrenchSample
    momentum_rate: WrenchSample


class FixedLagRows(Sequence):
    """
    The rows one or more backward passes emitted, as columns; a :class:`FixedLagRow` when read.

    A pass emits a quarter second of rows at once (250 at 1 kHz, lag 0.5 s): built
    row by row as objects and encoded message by message they took ~5 ms of the node's
    input callback, the largest spike in its latency (docs/fixed_lag.md, "Latency in
    the node").
    Here a pass keeps its columns; the node encodes each topic's messages at once
    (:meth:`records`, the bytes of ``cdr.encode_wrench_stamped``), and a reader of the
    rows (replay, the tests) gets each row with the values and arrays it had before.
    """

    __slots__ = ('stamps_ns', 'mu', 'rate', 'momentum', 'momentum_rate', 'world')

    def __init__(self, stamps_ns: np.ndarray, mu: np.ndarray, rate: np.ndarray,
                 momentum: np.ndarray, momentum_rate: np.ndarray, world: str) -> None:
        """Rows k of: stamps (K,) int64, mu and rate (K, n), their wrenches (K, 6)."""
        self.stamps_ns, self.mu, self.rate = stamps_ns, mu, rate
        self.momentum, self.momentum_rate, self.world = momentum, momentum_rate, world

    def __len__(self) -> int:
        return len(self.stamps_ns)

    def __getitem__(self, index: Union[int, slice]) -> Any:
        if isinstance(index, slice):
            return [self[k] for k in range(*index.indices(len(self)))]
        stamp = int(self.stamps_ns[index])
        momentum, rate, world = self.momentum[index], self.momentum_rate[index], self.world
        return FixedLagRow(stamp, self.mu[index], self.rate[index],
                           trusted_sample(WrenchSample, stamp, world, momentum[:3], momentum[3:]),
                           trusted_sample(WrenchSample, stamp, world, rate[:3], rate[3:]))

    def records(self) -> Optional[dict[str, np.ndarray]]:
        """
        Return each topic field's messages (FixedLagRow field -> (K, size) uint8), or None.

        Row k is ``cdr.encode_wrench_stamped`` of row k's sample (messages/cdr_columns.py).
        None when a stamp is not a ROS Time: the per-message encoder then says why.
        """
        stamps = stamp_columns(self.stamps_ns)
        if stamps is None:
            return None
        return {'momentum': vector6_records(stamps, self.world, self.momentum),
                'momentum_rate': vector6_records(stamps, self.world, self.momentum_rate)}

    @classmethod
    def joined(cls, parts: list['FixedLagRows']) -> 'FixedLagRows':
        """Return the rows of ``parts`` (oldest first) as one."""
        if len(parts) == 1:
            return parts[0]
        return cls(*(np.concatenate([getattr(part, name) for part in parts])
                     for name in cls.__slots__[:5]), parts[0].world)


class _Pass:
    """A backward pass under way over buffer steps [first, end): its slices reached ``top``."""

    __slots__ = ('first', 'end', 'top', 'until_ns', 'pose_out', 'x_out')

    def __init__(self, first: int, end: int, top: int, until_ns: Optional[int],
                 pose_out: np.ndarray, x_out: np.ndarray) -> None:
        self.first, self.end, self.top, self.until_ns = first, end, top, until_ns
        self.pose_out, self.x_out = pose_out, x_out

    def shifted(self, by: int) -> '_Pass':
        """Return the pass with its buffer indices moved down by ``by`` (a compaction)."""
        return _Pass(self.first - by, self.end - by, self.top - by, self.until_ns,
                     self.pose_out, self.x_out)


class FixedLagSmoother:
    """
    A fixed-lag RTS smoother fed with the filter's steps (its ``steps`` sink).

    ``downstream``: a second sink (the full smoother's store) every step also goes
    to. ``wrenches``: algebra covectors (K, n) -> wrenches (K, 6) (the update
    kernel's); ``rate_of``: the momentum rate from a smoothed state (default
    ``x[n:2n]``, the wrench w; with a commanded wrench, the total).
    """

    def __init__(self, group: BaseGroup, lag: float, dim: int, command: bool,
                 wrenches: Callable[[np.ndarray], np.ndarray], world: str,
                 rate_of: Optional[RateOf] = None, downstream: Any = None) -> None:
        """Start empty for a filter of error dimension ``dim`` (x has dim - n entries)."""
        if not lag >= 0.0:
            raise ValueError(f'fixed lag must be >= 0 s, got {lag}')
        self.group, self.n, self.dim, self.command = group, group.dim, dim, command
        self.lag_ns = int(round(lag * NS))
        self.pass_ns = int(PASS_FRACTION * self.lag_ns)
        self.wrenches, self.world, self.rate_of = wrenches, world, rate_of
        self.downstream = downstream
        self._basis, self._pinv, self._whole = (group.algebra_basis, group.algebra_pinv,
                                                group.is_whole)
        self._start = self._end = 0
        self._last_pass_ns: Optional[int] = None
        self._ready: list[FixedLagRows] = []
        self._first_waiting: Optional[int] = None  # buffer index of the oldest waiting row
        self._last_p: Optional[np.ndarray] = None  # the newest step's filtered covariance
        #: the pass under way (:class:`_Pass`), None when none is
        self._pass: Optional[_Pass] = None
        #: backward passes run, and the most steps the buffer held (memory bound)
        self.passes = 0
        self.peak_steps = 0
        self._allocate(INITIAL_CAPACITY)

    # --- the buffer ---------------------------------------------------------------------
    def _allocate(self, capacity: int) -> None:
        """Hold the live steps in new arrays of ``capacity`` (or, at the same, in place)."""
        d, xd, n = self.dim, self.dim - self.n, self.n
        old = getattr(self, '_arrays', None)
        count = self._end - self._start
        if old is not None and capacity == self.capacity and self._start >= count:
            # Compaction in place: the live steps to the front of the same arrays (the two
            # ranges do not overlap). New zeroed arrays of the whole capacity took 1.6-5 ms
            # at 1 kHz, once or twice a second: a latency spike in the node's callback.
            for array in old.values():
                array[:count] = array[self._start:self._end]
            arrays = old
        else:
            arrays = {'stamp': np.zeros(capacity, np.int64),
                      'output': np.zeros(capacity, bool),
                      'restart': np.zeros(capacity, bool), 'gain': np.zeros((capacity, d, d)),
                      'pose_pred': np.zeros((capacity, 4, 4)),
                      'x_pred': np.zeros((capacity, xd)), 'pose': np.zeros((capacity, 4, 4)),
                      'x': np.zeros((capacity, xd)), 'command': np.zeros((capacity, n))}
            if old is not None:
                for name, array in arrays.items():
                    array[:count] = old[name][self._start:self._end]
        self._arrays = arrays
        if self._first_waiting is not None:
            self._first_waiting -= self._start
        if self._pass is not None:
            self._pass = self._pass.shifted(self._start)
        self._start, self._end = 0, count
        self.capacity = capacity

    def _make_room(self) -> None:
        count = self._end - self._start
        # Compact when at most half is live (amortised O(1) a step), else grow.
        self._allocate(self.capacity if 2 * count <= self.capacity else 2 * self.capacity)

    def __len__(self) -> int:
        """Return the number of steps held (the window)."""
        return self._end - self._start

    # --- the filter's sink --------------------------------------------------------------
    def append(self, step: FilterStep) -> None:
        """Take the filter's next step; emit the rows whose lag has passed."""
        if self.downstream is not None:
            self.downstream.append(step)
        if step.transition is None and self._first_waiting is not None:
            # A restart: what waits no longer depends on anything to come.
            self._finish_pass()
            if self._first_waiting is not None:
                self._run_pass(None)
        if self._end == self.capacity:
            self._make_room()
        k, a = self._end, self._arrays
        a['stamp'][k] = step.stamp_ns
        a['output'][k] = step.output
        a['restart'][k] = step.transition is None
        if step.transition is not None and k > self._start:
            # C of the step before (still needed: it is in the window).
            a['gain'][k - 1] = smoother_gain(
                np.ascontiguousarray(self._last_p), np.ascontiguousarray(step.transition),
                np.ascontiguousarray(step.p_pred))
        self._last_p = step.p
        a['pose_pred'][k], a['x_pred'][k] = step.pose_pred, step.x_pred
        a['pose'][k], a['x'][k] = step.pose, step.x
        if self.command:
            a['command'][k] = step.command
        self._end += 1
        self.peak_steps = max(self.peak_steps, self._end - self._start)
        if self._pass is not None:
            self._continue_pass(SLICE_STEPS)
            return
        if step.output and self._first_waiting is None:
            self._first_waiting = k
        if self._first_waiting is None:
            # No row waits: no step before the next row is ever needed.
            self._start = self._end
            return
        now = step.stamp_ns
        # A clock restarted backwards (last pass in the future) must not stop the passes:
        # the window would grow until the new clock caught up (issue 27).
        if a['stamp'][self._first_waiting] <= now - self.lag_ns and (
                self._last_pass_ns is None or now - self._last_pass_ns >= self.pass_ns
                or now < self._last_pass_ns):
            self._start_pass(now - self.lag_ns)
            self._continue_pass(SLICE_STEPS)

    def _run_pass(self, until_ns: Optional[int]) -> None:
        """Smooth back to the oldest waiting row at once; emit the rows stamped <= ``until_ns``."""
        self._start_pass(until_ns)
        self._finish_pass()

    def _start_pass(self, until_ns: Optional[int]) -> None:
        """Start a backward pass from the newest step; its slices run in :meth:`_continue_pass`."""
        first, end = self._first_waiting, self._end
        count = end - first
        self._pass = _Pass(first, end, end, until_ns, np.empty((count, 4, 4)),
                           np.empty((count, self.dim - self.n)))
        self.passes += 1
        if count:
            self._last_pass_ns = int(self._arrays['stamp'][end - 1])

    def _finish_pass(self) -> None:
        """Run what is left of the pass under way (if any) and emit its rows."""
        if self._pass is not None:
            self._continue_pass(self._pass.top - self._pass.first)

    def _continue_pass(self, steps: int) -> None:
        """
        Run the pass's next ``steps`` backward steps; at its oldest step, emit its rows.

        A slice [lo, top) continues from step ``top``, whose smoothed mean the slice
        before wrote: for the call that step's filtered mean is replaced by it (restored
        after), so each step's arithmetic is a whole pass's (backward_mean starts from
        the last step's mean).
        """
        run, a = self._pass, self._arrays
        first, top = run.first, run.top
        lo = max(first, top - steps)
        if run.top == run.end:
            pose_out, x_out = run.pose_out, run.x_out
            backward_mean(a['restart'][lo:top], a['gain'][lo:top], a['pose_pred'][lo:top],
                          a['x_pred'][lo:top], a['pose'][lo:top], a['x'][lo:top],
                          self._basis, self._pinv, self._whole, pose_out[lo - first:],
                          x_out[lo - first:])
        elif lo < top:
            pose, x = a['pose'][top].copy(), a['x'][top].copy()
            a['pose'][top], a['x'][top] = run.pose_out[top - first], run.x_out[top - first]
            try:
                backward_mean(a['restart'][lo:top + 1], a['gain'][lo:top + 1],
                              a['pose_pred'][lo:top + 1], a['x_pred'][lo:top + 1],
                              a['pose'][lo:top + 1], a['x'][lo:top + 1], self._basis,
                              self._pinv, self._whole, run.pose_out[lo - first:],
                              run.x_out[lo - first:])
            finally:
                a['pose'][top], a['x'][top] = pose, x
        run.top = lo
        if lo > first:
            return
        self._pass = None
        end, until_ns = run.end, run.until_ns
        rows = a['output'][first:end].copy()
        if until_ns is not None:
            rows &= a['stamp'][first:end] <= until_ns
        chosen = np.flatnonzero(rows)
        self._emit(chosen, first, run.pose_out, run.x_out)
        waiting = np.flatnonzero(a['output'][first:end] & ~rows)
        if len(waiting):
            self._first_waiting = first + int(waiting[0])
            self._start = self._first_waiting
        elif a['output'][end:self._end].any():
            # Rows came during the pass: the oldest of them waits now.
            self._first_waiting = end + int(np.flatnonzero(a['output'][end:self._end])[0])
            self._start = self._first_waiting
        else:
            self._first_waiting = None
            self._start = self._end

    def _emit(self, chosen: np.ndarray, first: int, pose_out: np.ndarray,
              x_out: np.ndarray) -> None:
        if not len(chosen):
            return
        n, a = self.n, self._arrays
        mu = np.ascontiguousarray(x_out[chosen, :n])
        if self.rate_of is None:
            rate = np.ascontiguousarray(x_out[chosen, n:2 * n])
        else:
            rate = np.array([self.rate_of(pose_out[i], x_out[i],
                                          a['command'][first + i] if self.command else None)
                             for i in chosen])
        stamps = a['stamp'][first + chosen]
        self._ready.append(FixedLagRows(stamps, mu, rate, self.wrenches(mu),
                                        self.wrenches(rate), self.world))

    # --- the estimator's side -----------------------------------------------------------
    def take(self) -> Union[FixedLagRows, list]:
        """Return the rows emitted since the last call (oldest first; [] when none)."""
        if not self._ready:
            return []
        ready, self._ready = self._ready, []
        return FixedLagRows.joined(ready)

    def flush(self) -> Union[FixedLagRows, list]:
        """Emit every waiting row from the newest step (end of data); return what is ready."""
        self._finish_pass()
        if self._first_waiting is not None:
            self._run_pass(None)
        return self.take()


class FixedLagSmoothing:
    """Fixed-lag smoothing of the running estimate (a part of :class:`~.pipeline.Estimator`)."""

    #: the smoother while ``smoothing_lag`` > 0 (None: off)
    fixed_lag: Optional[FixedLagSmoother] = None

    def _attach_fixed_lag(self) -> None:
        """Put the fixed-lag smoother (``config.smoothing_lag``) behind the filter's steps."""
        lag, current, flt = self.config.smoothing_lag, self.fixed_lag, self.filter
        store = getattr(self, 'step_store', None)
        if lag <= 0.0:
            if current is not None:
                self.fixed_lag = None
                flt.steps = store if store is not None else []
                flt.record = self.record_steps
            return
        if current is None or current.lag_ns != int(round(lag * NS)):
            # A new lag starts afresh (rows waiting under the old one are dropped).
            estimator = self

            unknown = np.zeros((flt.dim, flt.dim))  # the mean does not depend on P

            def total(pose: np.ndarray, x: np.ndarray, held: Optional[np.ndarray]) -> np.ndarray:
                return estimator.filter._total(pin.SE3(pose), x, unknown, held)[0]

            self.fixed_lag = FixedLagSmoother(
                self.robot.group, lag, flt.dim, self.commanded_wrench, self.kernel.wrenches,
                self.config.world_frame, total if self.commanded_wrench else None, store)
        flt.steps, flt.record = self.fixed_lag, True

    def flush_fixed_lag(self) -> Union[FixedLagRows, list]:
        """Emit every row still waiting for its lag (end of data); [] when off."""
        return [] if self.fixed_lag is None else self.fixed_lag.flush()
