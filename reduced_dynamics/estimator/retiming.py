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
Causal re-timing of a periodic pose source stamped on receipt (``pose_retiming``).

A motion-capture or camera stream delivers consecutive frames of a fixed-rate clock,
but a polling client (ROS 2 ``vrpn_mocap``: ``update_freq`` 100 Hz,
``use_vrpn_timestamps`` false) stamps each message when its poll received it. Model:
frame n is taken at ``t_n = t0 + n T`` and stamped ``s = t_n + d`` with a latency
``d >= 0`` (the wait for the next poll, a late poll, transport). The frame clock is
then the **lower envelope** of the stamps over the frame index: as in clock-skew
estimation from one-way delays (Moon, Skelly, Towsley 1999), the line
``a + b n`` below every point (n, s) of a sliding window that maximises
``sum(s - a - b n)`` (a linear programme whose optimum is the edge of the lower
convex hull above the window's mean index) estimates t0 and T; a sample is
re-timed to ``min(s, a + b n)``: never later than its receipt, always a frame of
the estimated clock.

Frame indices: consecutive messages are consecutive frames. Where that is unsure,
the stamp sigma says so (:meth:`FrameRetimer.retime`), and no sample is lost or
moved after its receipt:

* a latency under 3/4 period admits only the counted frame: its frame time, with
  the re-timed sigma (``pose_retimed_stamp_noise``);
* a latency of 3/4 period or more could also be a later frame, with frames lost
  before it: such samples make a run; in it a sample gets its counted frame time
  with the stream's ``pose_stamp_noise``, the first sample of a new poll whose
  latency is beyond the stream's own range (99th percentile of its window) a sigma
  spanning frame time to receipt (a late poll's oldest frame, or an outage);
* a run longer than twice the longest run this stream ended by itself keeps its
  stamps; one of twice that (at least ``LEVEL_SAMPLES``) proves lost frames (every
  poll delivers a frame younger than a period): the count moves on by the largest
  number every sample of the run allows;
* a latency below -T/2 (the count or the clock is wrong) or beyond ``MAX_LATENCY``
  (a stall), or a window no longer consistent, restarts the estimate; it re-times
  again after ``LOCK_SAMPLES`` samples.

``auto`` re-times only a stream that shows the receive-stamp signature in its
window: the consecutive-frame envelope holds (every latency within
[-T/2, ``MAX_LATENCY``]) and at least 1 % of its steps (3 or more) are under
``BURST_STEP`` periods (two frames delivered by one poll, stamped microseconds
apart: a clock that stamps its own samples does that only by rare chance).
Hardware-stamped navigation, a simulator's jittered Odometry, and a polling client
faster than its source (no bursts) keep their stamps. ``on`` skips the burst test
(a stream known to be stamped on receipt); ``off`` never re-times.

The re-timer sees the samples the stamp policy
(:mod:`reduced_dynamics.estimator.stamps`) accepted, one at a time, in arrival order:
streaming and batched paths give the same stamps.
"""

from __future__ import annotations

from collections import deque
import math
from typing import Optional

import numpy as np

from reduced_dynamics.estimator.core import envelope

NS = 1_000_000_000
#: Samples in the sliding window of the envelope: 2 s at 120 Hz, many beats of a
#: 100 Hz poll against a 120 Hz camera (the envelope is touched every 50 ms there),
#: short against the drift of a crystal's rate (its skew is estimated, not assumed).
WINDOW = 256
#: Samples a fresh estimate needs before it re-times: 0.5 s at 120 Hz.
LOCK_SAMPLES = 64
#: The envelope is refitted every this many samples (the period is stable; each
#: sample is still checked against the current line).
REFIT = 16
#: The largest latency [s] of a frame that is still counted as the next one: a
#: polling client's delay is its poll period plus how late a poll runs (tens of ms);
#: a longer gap may hide lost frames, whose count the stamps cannot tell.
MAX_LATENCY = 0.2
#: The fewest samples in a row at least 3/4 period above the envelope that prove
#: frames were lost (a lost frame shifts every later latency by T; at least twice
#: the suspect length, see :meth:`FrameRetimer._fit`). Each on-time poll delivers a
#: frame younger than one period (the newest it found), so runs end by themselves.
LEVEL_SAMPLES = 8
#: Two frames one poll delivered are stamped microseconds apart: a step under this
#: fraction of the period (167 us at 120 Hz; the freeflyer2 bags: 19-20 % of their
#: steps). A clock stamping its own samples with jitter sigma makes one with
#: probability Phi(-T / (sqrt(2) sigma)): 4e-4 for 1 ms on 200 Hz.
BURST_STEP = 0.05
#: Such steps needed in the window (at least this many and this fraction of it), so
#: that chance does not make the signature.
BURST_COUNT = 3
BURST_FRACTION = 0.01
#: The modes of ``pose_retiming``.
MODES = ('auto', 'on', 'off')


class FrameRetimer:
    """
    The re-timing of one pose stream (see the module docstring).

    :meth:`retime` takes each accepted stamp in order and returns the stamp the
    filter uses and whether it was re-timed; :meth:`restart` forgets the clock
    (the estimator's clock restarted).
    """

    def __init__(self, mode: str = 'auto', retimed_sigma: float = 5e-4) -> None:
        """Start without an estimate; ``retimed_sigma`` [s]: a frame time's stamp sigma."""
        self.mode = mode
        self.retimed_sigma = retimed_sigma
        self._previous: Optional[int] = None
        self._points: deque[tuple[int, int]] = deque(maxlen=WINDOW)
        # The same points as interleaved int64 (index, stamp), written as they come: a
        # fit reads its window from here (converting 2 x WINDOW Python ints at every
        # refit cost more than the rest of the per-sample re-timing). Its last
        # len(_points) pairs end at _end.
        self._flat = np.empty(4 * WINDOW, np.int64)
        self._end = 0
        self._line: Optional[tuple[int, int, float]] = None
        self._index = 0
        self._last_out: Optional[int] = None
        self._since_fit = 0
        self._above = 0
        self._run = 0
        self._suspect_after = 0
        self._natural = 0.0
        self._locked = False
        #: samples re-timed, kept (not re-timed) and estimate restarts so far
        self.retimed = 0
        self.kept = 0
        self.restarts = 0
        #: index corrections for frames lost within a poll delay
        self.shifts = 0
        #: the latest period estimate [ns], or None
        self.period_ns: Optional[float] = None

    def configure(self, mode: str, retimed_sigma: float) -> None:
        """Adopt a mode and sigma; a new mode forgets the estimate."""
        self.retimed_sigma = retimed_sigma
        if mode != self.mode:
            self.mode = mode
            self._forget()

    def restart(self) -> None:
        """Forget the estimate and the last stamp (the estimator's clock restarted)."""
        self._forget()
        self._last_out = self._previous = None

    def _push(self, index: int, stamp: int) -> None:
        """Append a point to the window (both copies)."""
        self._points.append((index, stamp))
        end = self._end
        flat = self._flat
        if 2 * end == flat.size:
            # Full: the held points move to the front (once every WINDOW points or more).
            held = len(self._points) - 1
            flat[:2 * held] = flat[2 * (end - held):2 * end]
            end = held
        flat[2 * end] = index
        flat[2 * end + 1] = stamp
        self._end = end + 1

    def _window_arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """Return the window's (index, stamp) columns (envelope.window_arrays' layout)."""
        end = self._end
        flat = self._flat[2 * (end - len(self._points)):2 * end]
        return flat[0::2], flat[1::2]

    def _forget(self) -> None:
        self._points.clear()
        self._end = 0
        self._line = None
        self._index = 0
        self._since_fit = 0
        self._above = 0
        self._run = 0
        self._locked = False
        self.period_ns = None

    def _fit(self) -> None:
        self._since_fit = 0
        points = self._points
        index, stamp = self._window_arrays()
        line = envelope.optional_line(*envelope.lower_line(index, stamp))
        if line is None or line[2] <= 0.0:
            self._line, self._locked, self.period_ns = None, False, None
            return
        self._line = line
        self.period_ns = period = line[2]
        if len(points) < LOCK_SAMPLES:
            self._locked = False
            return
        n0, s0, _ = line
        consistent, bursts, longest, p99 = envelope.scan(index, stamp, n0, s0, period,
                                                         MAX_LATENCY * NS, BURST_STEP)
        # A run of late samples (d >= 3/4 period) twice as long as any this stream ended
        # on its own is suspect (frames may have been lost in it).
        self._suspect_after = 2 * int(longest) + 2
        # The stream's latency range: its 99th percentile (late polls' oldest frames are
        # rarer), at least a period, with the envelope's quarter-period slack.
        self._natural = max(float(p99), period) + 0.25 * period
        if not consistent:
            # The count of frames is contradicted (a lost frame miscounted, a clock
            # that is not periodic): start again from the newest sample.
            newest = points[-1]
            self._forget()
            self.restarts += 1
            self._push(0, newest[1])
            return
        self._locked = self.mode == 'on' or int(bursts) >= max(BURST_COUNT,
                                                               BURST_FRACTION * len(points))

    def retime(self, stamp: int) -> tuple[int, Optional[float]]:
        """
        Return the stamp for the filter and its standard deviation [s].

        ``stamp``: the accepted header stamp (strictly after the previous one).
        The result is strictly increasing and never after ``stamp``. The
        deviation is None where the stream's ``pose_stamp_noise`` applies (a kept
        stamp, or a frame time whose count a run of late samples leaves open), the
        re-timed sigma for a frame time, or wider for the first frame after a gap
        that may have lost frames.
        """
        if self.mode == 'off':
            return stamp, None
        points = self._points
        line = self._line
        index = self._index + 1 if points else 0
        previous, self._previous = self._previous, stamp
        new_poll = previous is None or line is None or stamp - previous >= 0.25 * line[2]
        far = False
        if line is not None and len(points) >= LOCK_SAMPLES:
            # (A line from fewer samples has not seen enough beats of the poll against
            # the frame clock to judge a sample by.)
            n0, s0, period = line
            d = stamp - s0 - period * (index - n0)
            if d < -0.5 * period or d > MAX_LATENCY * NS:
                # The frame count is unknown (lost frames, a stall) or contradicted (a
                # clock jump): start again from this sample.
                self._forget()
                self.restarts += 1
                index, line = 0, None
            elif d >= 0.75 * period:
                # As late as the next frame could be: frames may have been lost. How many
                # at most, if every sample of this run had latency >= 0 (a quarter period
                # of slack for the envelope's error).
                lost = int((d + 0.25 * period) // period)
                self._run = min(self._run, lost) if self._above else lost
                self._above += 1
                # A new poll's frame later than the stream's latencies go: either a late
                # poll's oldest frame (the rest of its burst follows within microseconds)
                # or frames were lost. Its stamp sigma spans both.
                far = new_poll and d > self._natural
                if self._above >= max(2 * self._suspect_after, LEVEL_SAMPLES):
                    # No sample of the run came within 3/4 period of its frame: every poll
                    # delivers one that fresh, so frames were lost during the run. Count
                    # them: the largest number every sample of the run allows (re-timed
                    # stamps stay at or before their receipt). Where in the run they were
                    # lost is unknown: its earlier samples leave the window.
                    self._drop_last(self._above - 1)
                    index += self._run
                    self.shifts += 1
                    self._above = 0
                    far = False
            else:
                self._above = 0
        elif points and stamp - points[-1][1] > MAX_LATENCY * NS + (
                0 if line is None else line[2]):
            self._forget()
            index = 0
        self._index = index
        self._push(index, stamp)
        self._since_fit += 1
        if self._line is None or self._since_fit >= REFIT:
            self._fit()
            line = self._line
        out: int = stamp
        sigma: Optional[float] = None
        if self._locked and line is not None and self._above <= self._suspect_after:
            n0, s0, period = line
            frame = s0 + int(round(period * (index - n0)))
            last = self._last_out
            if frame <= stamp and (last is None or frame > last):
                out = frame
                if far:
                    # Uniform between this frame time and the receipt.
                    sigma = (stamp - frame) / (NS * math.sqrt(12.0))
                elif not self._above:
                    sigma = self.retimed_sigma
                # (Otherwise in a run of late samples the count may miss lost frames,
                # found only at the run's end: the stream's stamp noise.)
            elif frame > stamp and (last is None or stamp > last):
                # Slightly below the envelope (within half a period): the frame was
                # taken no later than its receipt.
                sigma = self.retimed_sigma
        if out != stamp or sigma is not None:
            self.retimed += 1
        else:
            self.kept += 1
        self._last_out = out
        return out, sigma

    def _drop_last(self, count: int) -> None:
        """Remove the last ``count`` window points; refit at this sample."""
        points = self._points
        for _ in range(min(count, len(points) - 1)):
            points.pop()
            self._end -= 1
        self._since_fit = REFIT
