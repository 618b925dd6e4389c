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
filter step (mean only, the gains cached). Memory is the steps of that window
(one d x d gain, two poses and two states a step; the buffer drops every step
before the oldest waiting row). A restart step (no transition) makes the past
independent of what follows: everything waiting is emitted at once. At lag 0
each row is emitted at its own step (the causal estimate); with a lag beyond
the run, :meth:`FixedLagSmoother.flush` at the end gives the full smoother.
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple, Optional

import numpy as np
import pinocchio as pin

from reduced_dynamics.estimator.core.smoother import backward_mean, smoother_gain
from reduced_dynamics.estimator.core.state import FilterStep
from reduced_dynamics.geometry.lie_group import BaseGroup
from reduced_dynamics.messages.samples import trusted_sample, WrenchSample

NS = 1_000_000_000
#: A backward pass at most once per this fraction of the lag (stamp time).
PASS_FRACTION = 0.5
#: Initial buffer capacity in steps (it doubles when the window needs more).
INITIAL_CAPACITY = 256

#: (smoothed pose 4 x 4, x, command held or None) -> the momentum rate (n,)
RateOf = Callable[[np.ndarray, np.ndarray, Optional[np.ndarray]], np.ndarray]


class FixedLagRow(NamedTuple):
    """A row's fixed-lag estimate: its stamp, mu and momentum rate (algebra and samples)."""

    stamp_ns: int
    mu: np.ndarray
    rate: np.ndarray
    momentum: WrenchSample
    momentum_rate: WrenchSample


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
        self._ready: list[FixedLagRow] = []
        self._first_waiting: Optional[int] = None  # buffer index of the oldest waiting row
        self._last_p: Optional[np.ndarray] = None  # the newest step's filtered covariance
        #: backward passes run, and the most steps the buffer held (memory bound)
        self.passes = 0
        self.peak_steps = 0
        self._allocate(INITIAL_CAPACITY)

    # --- the buffer ---------------------------------------------------------------------
    def _allocate(self, capacity: int) -> None:
        d, xd, n = self.dim, self.dim - self.n, self.n
        old = getattr(self, '_arrays', None)
        arrays = {'stamp': np.zeros(capacity, np.int64), 'output': np.zeros(capacity, bool),
                  'restart': np.zeros(capacity, bool), 'gain': np.zeros((capacity, d, d)),
                  'pose_pred': np.zeros((capacity, 4, 4)), 'x_pred': np.zeros((capacity, xd)),
                  'pose': np.zeros((capacity, 4, 4)), 'x': np.zeros((capacity, xd)),
                  'command': np.zeros((capacity, n))}
        count = self._end - self._start
        if old is not None:
            for name, array in arrays.items():
                array[:count] = old[name][self._start:self._end]
        self._arrays = arrays
        self._out = (np.zeros((capacity, 4, 4)), np.zeros((capacity, xd)))
        if self._first_waiting is not None:
            self._first_waiting -= self._start
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
            self._run_pass(now - self.lag_ns)

    def _run_pass(self, until_ns: Optional[int]) -> None:
        """Smooth back to the oldest waiting row; emit the rows stamped <= ``until_ns``."""
        first, end = self._first_waiting, self._end
        a = self._arrays
        count = end - first
        pose_out, x_out = (o[:count] for o in self._out)
        backward_mean(a['restart'][first:end], a['gain'][first:end],
                      a['pose_pred'][first:end], a['x_pred'][first:end], a['pose'][first:end],
                      a['x'][first:end], self._basis, self._pinv, self._whole, pose_out, x_out)
        self.passes += 1
        if count:
            self._last_pass_ns = int(a['stamp'][end - 1])
        rows = a['output'][first:end].copy()
        if until_ns is not None:
            rows &= a['stamp'][first:end] <= until_ns
        chosen = np.flatnonzero(rows)
        self._emit(chosen, first, pose_out, x_out)
        waiting = np.flatnonzero(a['output'][first:end] & ~rows)
        if len(waiting):
            self._first_waiting = first + int(waiting[0])
            self._start = self._first_waiting
        else:
            self._first_waiting = None
            self._start = end

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
        momentum, wrench = self.wrenches(mu), self.wrenches(rate)
        world, sample = self.world, WrenchSample
        for j, i in enumerate(chosen.tolist()):
            stamp = int(a['stamp'][first + i])
            self._ready.append(FixedLagRow(
                stamp, mu[j], rate[j],
                trusted_sample(sample, stamp, world, momentum[j, :3], momentum[j, 3:]),
                trusted_sample(sample, stamp, world, wrench[j, :3], wrench[j, 3:])))

    # --- the estimator's side -----------------------------------------------------------
    def take(self) -> list[FixedLagRow]:
        """Return the rows emitted since the last call (oldest first)."""
        if not self._ready:
            return []
        ready, self._ready = self._ready, []
        return ready

    def flush(self) -> list[FixedLagRow]:
        """Emit every waiting row from the newest step (end of data); return what is ready."""
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

    def flush_fixed_lag(self) -> list[FixedLagRow]:
        """Emit every row still waiting for its lag (end of data); [] when off."""
        return [] if self.fixed_lag is None else self.fixed_lag.flush()
