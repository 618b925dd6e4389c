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
Synchronisation and re-timing: accepted samples to rows of the filter, in stamp order.

Part of :class:`~.pipeline.Estimator` (its state is set up there). A joint-state
sample becomes a row once a base sample at or after its stamp has come
(:mod:`.sync`; base stamps only increase, so every base sample up to the row is
then known, whatever the order in which the two inputs arrived). The row carries
the base samples stamped since the previous row, with the frame times and stamp
sigmas of re-timed poses (:mod:`.retiming`), and, with a commanded wrench, the
held command over each filter step (a zero-order hold). Clock jumps the stamp
policy confirms (:mod:`~reduced_dynamics.estimator.stamps`) restart the clock here.
"""

from __future__ import annotations

from bisect import bisect_right
from typing import Optional

import numpy as np

from reduced_dynamics.estimator.events import EventDetector
from reduced_dynamics.estimator.filter import Command, MomentumFilter
from reduced_dynamics.estimator.outputs import EstimatorOutput
from reduced_dynamics.estimator.stamps import ACCEPTED, ClockJump, StampResult
from reduced_dynamics.estimator.sync import BaseBuffer

#: Re-timed stamps held until their measurement is resolved: far more than the base
#: buffer holds (older ones are no longer measured anyway).
RETIMED_KEEP = 4096


class Timing:
    """
    Synchronisation, re-timing and clock restarts (a part of :class:`~.pipeline.Estimator`).

    Accepted samples queue here (``_pending``, the base buffer, the held
    commands) until a row is resolved; resolved rows go to the open chunk
    (:mod:`.processing`).
    """

    def _accept_joint(self, pending: tuple) -> None:
        """Queue a joint sample whose stamp the stamp policy accepted."""
        stamp = self._last_joint_ns = pending[0]
        if self.base_driven:
            self._held, self._have_shape = pending, True
            return
        waiting = self._pending
        waiting.append(pending)
        if len(waiting) == 1:
            latest = self._buffer.latest_ns
            if latest is None or latest < stamp:
                # Alone and newer than every base state: it waits (as _drain would find).
                return
        self._drain(final=False)

    def _accept_base(self, item: tuple) -> None:
        """Buffer a base sample whose stamp the stamp policy accepted."""
        stamp, row = item
        odometry = self.use_odometry
        if self._retimer.mode != 'off':
            # The filter takes the frame time of a re-timed pose (estimator/retiming.py).
            stamp, sigma = self._retimer.retime(stamp)
            if sigma is not None:
                self._retimed_ns.append((stamp, sigma))
        self._last_base_ns = stamp
        self._buffer.append(stamp, row)
        pending = self._pending
        if self.base_driven:
            pending.append((stamp,) + self._held[1:])
        if odometry and len(pending) == 1 and pending[0][0] == stamp:
            # The one waiting shape sample has this very stamp (simulators, drivers on
            # one clock tick): _drain would find gap 0, ready, and this row. Skip it.
            self._resolve(pending.popleft() + (row, self._measurements(stamp)))
            return
        self._drain(final=False)

    def _accept_command(self, item: tuple) -> None:
        """Hold a command whose stamp the stamp policy accepted (stamps ascend)."""
        stamp, u = item
        self._accepted_commands += 1
        if self._command_stamps and stamp <= self._command_stamps[-1]:
            # The command stream's own clock jumped back (its gate followed it): the
            # held commands are of the old time.
            self._command_stamps, self._command_values = [], []
        self._command_stamps.append(stamp)
        self._command_values.append(u)

    def _command_at(self, index: int) -> np.ndarray:
        """Return the command held at entry ``index - 1`` (zero before the first)."""
        return self._command_values[index - 1] if index > 0 else self._command_zero

    def _command_input(self, stamp: int) -> Command:
        """
        Return the command over the step that ends at ``stamp`` (zero-order hold).

        ``mean``: its exact mean over [previous sample, stamp]; ``now``: the value
        held at ``stamp``. Commands before the step's start are forgotten.
        """
        stamps, values = self._command_stamps, self._command_values
        start, self._command_from_ns = self._command_from_ns, stamp
        end_index = bisect_right(stamps, stamp)
        now = self._command_at(end_index)
        if start is None or stamp <= start:
            mean = now
        else:
            index = bisect_right(stamps, start)
            mean = now
            if index < end_index:
                # Piecewise constant over [start, stamp]: the switches in between.
                total = self._command_at(index) * float(stamps[index] - start)
                for k in range(index, end_index):
                    until = stamps[k + 1] if k + 1 < end_index else stamp
                    total = total + values[k] * float(until - stamps[k])
                mean = total / float(stamp - start)
        if end_index > 1:
            del stamps[:end_index - 1], values[:end_index - 1]
        return Command(mean, now)

    def _stamp_result(self, result: StampResult, joint: Optional[bool]) -> None:
        """
        Apply a stamp decision of the joint (or base) stream: drops, a jump, accepts.

        ``joint`` None: the command stream, whose jumps restart nothing (its
        commands are held by stamp; the sensor streams own the clock).
        """
        if joint is None:
            prefix, accept = 'command_stamp_', self._accept_command
        else:
            prefix, accept = ('stamp_', self._accept_joint) if joint \
                else ('base_stamp_', self._accept_base)
        for _, reason, detail in result.dropped:
            self._reject(prefix + reason, detail)
        if result.jump is not None and joint is not None:
            self._clock_jump(result.jump, joint)
        for item in result.accepted:
            accept(item)

    def _clock_jump(self, jump: ClockJump, joint: bool) -> None:
        """
        Follow a confirmed clock jump of one stream.

        Forward, nothing restarts (a gap; the other stream confirms its own
        jump). Backwards, the estimator restarts its clock and the other
        stream re-anchors on the new time, releasing what it held.
        """
        if not jump.backwards:
            return
        self._restart_clock(f'{jump.stream} clock jumped back '
                            f'{(jump.from_ns - jump.to_ns) * 1e-9:.6g} s')
        other = self._base_gate if joint else self._joint_gate
        self._stamp_result(other.follow(jump.to_ns, jump.to_receive_ns), not joint)

    def reset(self, reason: str) -> list[EstimatorOutput]:
        """
        Restart the estimator's clock (e.g. ROS time jumped back); return ready outputs.

        What waits at the old time is processed first; then every time-dependent
        state is forgotten (base buffer, last stamps, the filter's state, open
        predictions, prediction and diagnostics times). The momentum level,
        events and counters stay. Samples the stamp policy held are re-judged
        against the new clock.
        """
        held = [(self._joint_gate.restart(), True), (self._base_gate.restart(), False)]
        if self.commanded_wrench:
            held.append((self._command_gate.restart(), None))
        self._restart_clock(reason)
        accepts = {True: self._accept_joint, False: self._accept_base,
                   None: self._accept_command}
        gates = {True: self._joint_gate, False: self._base_gate, None: self._command_gate}
        for items, joint in held:
            gate = gates[joint]
            for stamp, receive, item in items:
                result = gate.offer(stamp, receive, item)
                if result is ACCEPTED:
                    accepts[joint](item)
                else:
                    self._stamp_result(result, joint)
        return self._close_streaming()

    def _restart_clock(self, reason: str) -> None:
        self._drain(final=True)
        self._process_chunk()
        self.predictor.finish()
        self.predictor.forget_history()
        self._buffer = BaseBuffer()
        self._measured_ns = None
        self._retimer.restart()
        self._retimed_ns.clear()
        self._last_joint_ns = self._last_base_ns = None
        self._last_prediction_ns = self._last_diagnostics_ns = None
        # The filter restarts from the next sample (its recorded steps stay, the
        # smoother sees the restart); detected events stay reported.
        old = self.filter
        config = self.config
        self.filter = MomentumFilter(self.robot.group, self.noise, config.innovation_gate,
                                     record=self.record_steps, command=self.commanded_wrench,
                                     step_significance=self._step_significance())
        if self.commanded_wrench:
            # The held commands belong to the old clock; the command stream re-anchors.
            self._command_stamps, self._command_values = [], []
            self._command_from_ns = None
            self._command_gate.restart()
        for name in ('steps', 'gated', 'log_likelihood', 'nis_sum', 'nis_dof', 'diverged',
                     'restart_causes', 'burst_skipped'):
            setattr(self.filter, name, getattr(old, name))
        self.filter.record = old.record  # the fixed-lag smoother's steps too
        events = self.detector.events
        self.detector = EventDetector(self.robot.n, config.event_significance,
                                      config.event_hold, config.event_false_alarm_rate)
        self.detector.events = events
        self.clock_resets += 1
        self.last_reset = reason

    def _drain(self, final: bool) -> None:
        pending = self._pending
        if not pending:
            return
        buffer, tolerance_ns = self._buffer, self._tolerance_ns
        needs_successor = False
        while pending:
            head = pending[0]
            stamp = head[0]
            gap, ready, index = buffer.status(stamp, needs_successor)
            if not ready and not final:
                newest_joint = self._last_joint_ns or stamp
                waited = max(newest_joint, buffer.latest_ns or 0) - stamp
                if waited <= 4 * tolerance_ns:
                    break
            pending.popleft()
            if gap is None:
                self._reject('no_base_state', f'no base pose near {stamp}')
            elif gap > tolerance_ns:
                detail = f'nearest base pose {gap * 1e-9:.3f} s from joint state {stamp}'
                self._reject('stale_base_state', detail)
            else:
                self._resolve(head + (buffer.query(stamp, index), self._measurements(stamp)))

    def _measurements(self, stamp_ns: int) -> tuple:
        """
        Return the base samples (stamp_ns, row) stamped after the previous row, up to ``stamp_ns``.

        Called when the row is resolved, i.e. when the buffer holds a base sample
        at or after ``stamp_ns`` (base stamps only increase): every sample up to the
        row has arrived, whatever the order in which the two streams came in.
        """
        after, self._measured_ns = self._measured_ns, stamp_ns
        samples = self._buffer.between(after, stamp_ns)
        queue = self._retimed_ns
        if not queue or queue[0][0] > stamp_ns:
            return samples
        # Re-timed samples carry their stamp sigma as a third entry (resolved per sample
        # in arrival order: the same in the streaming and batched paths).
        sigmas = {}
        while queue and queue[0][0] <= stamp_ns:
            retimed, sigma = queue.popleft()
            sigmas[retimed] = sigma
        return tuple((s, row, sigmas[s]) if s in sigmas else (s, row) for s, row in samples)

    def _resolve(self, row: tuple) -> None:
        """Queue a synchronised sample for the update (processing it where it must be)."""
        chunk = self._chunk
        chunk.rows.append(row)
        if self.commanded_wrench:
            # The commands known now (arrival order), whatever the chunk's length: one per
            # filter step of the row (to each base measurement before it, then to it).
            stamp = row[0]
            command_input = self._command_input
            chunk.commands.append([command_input(sample[0]) for sample in row[5]
                                   if sample[0] < stamp] + [command_input(stamp)])
        period = self._diagnostics_period_ns
        if period is not None:
            # Diagnostics report the counters at their sample: close the chunk there.
            last = self._last_diagnostics_ns
            if last is None:
                self._last_diagnostics_ns = row[0]
            elif row[0] - last >= period:
                chunk.diagnose = True
                self._process_chunk()
                return
        if len(chunk.rows) >= self._chunk_limit:
            self._process_chunk()
