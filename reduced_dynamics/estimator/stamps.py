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
Stamp policy of one input stream: accept, drop an outlier, or follow a clock jump.

A header stamp is trusted when it is consistent with the stream's clock so far:
it advances by at most the stream's cadence (4 local periods: 4 x the larger of
the upper quartile and the mean of its last 16 accepted steps, so that bursts do
not shrink it; ``stamp_outlier_tolerance`` until they are known), or, with a
receive time (the bag's record time, rclpy's ``received_timestamp``) on both
this sample and the reference, it advances further while it runs ahead of its
receive time by at most half the step, against the stream's smallest recent
latency (the stream paused; a reference that itself arrived late does not make
the next sample look ahead). With receive times the offset
``stamp - receive`` must also stay within the tolerance of the reference's
offset (transport latency varies by milliseconds, a wrong clock by much more). The tolerance is
``max(stamp_outlier_tolerance, cadence)``. A stamp running ahead of the
cadence alone is suspect even when small: accepted, it would turn the valid
samples after it into ``backwards`` ones.

A consistent stamp that does not advance (a duplicate or a reordered message)
is rejected as ``backwards``. An inconsistent stamp is held as a candidate, and
its stream decides what it was:

* a later sample consistent with the old clock proves the candidates isolated
  outliers: they are dropped (``outlier``) and the sample accepted; those whose
  stamps lie in order between the old clock's last one and the sample's were a
  gap in the stream that their receive times did not show (a publisher that
  sent a burst, then stalled): they are accepted first, in order;
* ``jump_samples`` consecutive candidates consistent among themselves prove a
  clock jump (simulator restart, ``ros2 bag play --loop``): the gate
  re-synchronises to them and releases them all, so no sample after a jump is
  lost (their outputs come ``jump_samples - 1`` samples late);
* a stamp that jumps together with its receive time (both moved: a bag recorded
  on sim time, looped) is a jump at once.

Candidates still held at the end of the input are dropped as outliers.
The gate holds opaque items (what the caller wants back); it never looks at them.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import Any, Optional

NS = 1_000_000_000
#: Accepted steps kept for the local period (median).
PERIOD_WINDOW = 16
#: The tolerance is at least this many local periods.
PERIOD_FACTOR = 4


@dataclass
class ClockJump:
    """A confirmed re-synchronisation: the stream's clock moved from ``from_ns`` to ``to_ns``."""

    stream: str
    from_ns: int
    to_ns: int
    to_receive_ns: Optional[int]
    receive_moved: bool

    @property
    def backwards(self) -> bool:
        """Return True when time went back (the estimator must restart its clock)."""
        return self.to_ns < self.from_ns


@dataclass
class StampResult:
    """
    What a non-trivial :meth:`StampGate.offer` decided.

    ``dropped``: (item, reason, detail) rejected, reason ``outlier`` or
    ``backwards``; ``jump``: a confirmed clock jump, to handle before
    ``accepted`` (items to process now, in order).
    """

    accepted: list = field(default_factory=list)
    dropped: list = field(default_factory=list)
    jump: Optional[ClockJump] = None


#: :meth:`StampGate.offer`'s answer when the offered item is accepted and nothing else
#: happened (the hot path: no allocation).
ACCEPTED = StampResult()


class StampGate:
    """
    The stamp policy of one stream (see the module docstring).

    ``tolerance_ns``: ``stamp_outlier_tolerance`` in ns; ``jump_samples``:
    consecutive consistent candidates that confirm a clock jump.
    """

    def __init__(self, stream: str, tolerance_ns: int, jump_samples: int) -> None:
        """Start without a reference: the first sample is accepted."""
        self.stream = stream
        self.tolerance_ns = int(tolerance_ns)
        self.jump_samples = max(1, int(jump_samples))
        self.last_ns: Optional[int] = None
        self.last_receive_ns: Optional[int] = None
        self._steps: deque[int] = deque(maxlen=PERIOD_WINDOW)
        # Latencies (receive - stamp) of the last accepted samples: the smallest is the
        # transport's own; a sample that arrived late has a larger one, never a smaller.
        self._latencies: deque[int] = deque(maxlen=PERIOD_WINDOW)
        # PERIOD_FACTOR local periods (tolerance_ns until the period is known), refreshed
        # every few accepted steps: the per-sample check compares with it.
        self._cadence = self.tolerance_ns
        self._since_cadence = 0
        self._held: list[tuple[int, Optional[int], Any]] = []
        # After another stream's jump: the new clock, before this stream has a reference.
        self._anchor: Optional[tuple[int, Optional[int]]] = None
        #: The gate of the other stream on the same clock: its last stamp judges this
        #: stream's first one (set by the owner).
        self.peer: Optional['StampGate'] = None

    def configure(self, tolerance_ns: int, jump_samples: int) -> None:
        """Adopt new settings; the state is kept."""
        self.tolerance_ns = int(tolerance_ns)
        self.jump_samples = max(1, int(jump_samples))
        self._refresh_cadence()

    def _refresh_cadence(self) -> None:
        steps = self._steps
        self._since_cadence = 0
        if not steps:
            self._cadence = self.tolerance_ns
            return
        ordered = sorted(steps)
        # The upper quartile or the mean step (1 / rate), whichever is larger: bursts of
        # near-equal stamps (motion-capture packets) must not shrink the cadence.
        self._cadence = PERIOD_FACTOR * max(ordered[(3 * len(ordered)) // 4],
                                            sum(ordered) // len(ordered))

    def _step(self, step: int) -> None:
        self._steps.append(step)
        self._since_cadence += 1
        if self._since_cadence >= 4 or len(self._steps) < 4:
            self._refresh_cadence()

    @property
    def held(self) -> int:
        """Return the number of candidate samples held."""
        return len(self._held)

    def tolerance(self) -> int:
        """Return the effective tolerance [ns]: the parameter or 4 local periods."""
        return max(self.tolerance_ns, self._cadence)

    def _relation(self, ref_ns: int, ref_rx: Optional[int], stamp: int,
                  receive: Optional[int], tolerance: int, mode: str = 'stream') -> str:
        """
        Classify ``stamp`` against a reference: 'forward', 'backwards', 'jump' or 'far'.

        'jump': consistent in offset, but the stamp moved by more than the
        tolerance together with the receive time. In 'stream' mode a step ahead
        of the stream's cadence (PERIOD_FACTOR local periods) is 'forward' only
        when the receive time moved at least half as far (a pause of the
        stream); a stamp that runs ahead alone would make the samples after it
        look backwards. 'chain' mode (held candidates among themselves) and
        'window' mode (either direction; re-anchoring on another stream's clock)
        allow steps up to the tolerance.
        """
        step = stamp - ref_ns
        if receive is not None and ref_rx is not None:
            deviation = abs(step - (receive - ref_rx))
            if deviation > tolerance:
                return 'far'
            if mode in ('window', 'chain') and step > 0 or mode == 'window':
                return 'forward'
            if step > 0:
                if mode == 'chain' or step <= self._cadence or \
                        2 * self._ahead(stamp, receive, deviation) <= step:
                    return 'forward'
                return 'far'
            return 'jump' if -step > tolerance else 'backwards'
        if mode == 'window':
            return 'forward' if abs(step) <= tolerance else 'far'
        if 0 < step <= (tolerance if mode == 'chain' else self._cadence):
            return 'forward'
        if -tolerance <= step <= 0:
            return 'backwards'
        return 'far'

    def _ahead(self, stamp: int, receive: int, deviation: int) -> int:
        """
        Return how far [ns] a stamp runs ahead of its receive time, beyond the stream's.

        Against the smallest latency of the recent accepted samples, not the
        reference's: a reference that arrived late (a loaded machine) must not make
        a sample that arrived on time look ahead. ``deviation`` without latencies.
        """
        if not self._latencies:
            return deviation
        return min(self._latencies) - (receive - stamp)

    def offer(self, stamp: int, receive: Optional[int], item: Any) -> StampResult:
        """
        Judge one sample's stamp; return :data:`ACCEPTED` or what to do instead.

        On :data:`ACCEPTED` the caller processes ``item`` now. Otherwise the
        result lists what to drop, a jump to handle, and what to process.
        """
        last = self.last_ns
        if last is not None and not self._held:
            # Hot path: the stream goes on.
            step = stamp - last
            rx = self.last_receive_ns
            if 0 < step <= self._cadence and (
                    receive is None or rx is None
                    or abs(step - (receive - rx)) <= self.tolerance_ns):
                # _step, inlined (every accepted message passes here).
                self._steps.append(step)
                self._since_cadence += 1
                if self._since_cadence >= 4 or len(self._steps) < 4:
                    self._refresh_cadence()
                self.last_ns, self.last_receive_ns = stamp, receive
                if receive is not None:
                    self._latencies.append(receive - stamp)
                return ACCEPTED
        result = self._judge(stamp, receive, item)
        if result.jump is None and not result.dropped and len(result.accepted) == 1 \
                and result.accepted[0] is item:
            return ACCEPTED
        return result

    def _accept(self, stamp: int, receive: Optional[int]) -> None:
        last = self.last_ns
        if last is not None and stamp > last:
            self._step(stamp - last)
        self.last_ns, self.last_receive_ns = stamp, receive
        if receive is not None:
            self._latencies.append(receive - stamp)

    def _judge(self, stamp: int, receive: Optional[int], item: Any) -> StampResult:
        last = self.last_ns
        result = StampResult()
        if last is None:
            anchor = self._reference_anchor()
            if anchor is None or self._relation(anchor[0], anchor[1], stamp, receive,
                                                self.tolerance(), 'window') == 'forward':
                self._anchor = None
                self._accept(stamp, receive)
                result.accepted.append(item)
                return result
            return self._candidate(stamp, receive, item, result)
        tolerance = self.tolerance()
        relation = self._relation(last, self.last_receive_ns, stamp, receive, tolerance)
        if relation == 'forward':
            # Candidates between two samples of the old clock, in order, were a gap the
            # receive times did not show (a publisher that burst, then stalled).
            held = self._held
            between = 0
            while between < len(held) and last < held[between][0] < stamp:
                between += 1
            self._held = held[between:]
            self._release(held[:between], result)
            result.dropped = self._drop_held()
            self._accept(stamp, receive)
            result.accepted.append(item)
            return result
        if relation == 'backwards':
            result.dropped.append((item, 'backwards',
                                   f'{self.stream} stamp {stamp} <= previous {last}'))
            return result
        if relation == 'jump':
            # Stamp and receive time moved together: the source's clock really jumped.
            result.dropped = self._drop_held()
            result.jump = ClockJump(self.stream, last, stamp, receive, True)
            self.last_ns, self.last_receive_ns = stamp, receive
            self._latencies.clear()
            result.accepted.append(item)
            return result
        return self._candidate(stamp, receive, item, result)

    def _candidate(self, stamp: int, receive: Optional[int], item: Any,
                   result: StampResult) -> StampResult:
        held = self._held
        if held:
            ref_ns, ref_rx, _ = held[-1]
            # Candidates only need to be in order and within the tolerance of each other:
            # held after a gap in a bursty stream, they must not be dropped one by one.
            tolerance, mode = self.tolerance(), 'chain'
            if not self._steps:
                # No local period yet: the candidates' own spacing (or the gap before
                # the first) scales the tolerance, so that a stream slower than the
                # tolerance can start.
                spacing = ref_ns - held[-2][0] if len(held) > 1 else \
                    ref_ns - (self.last_ns if self.last_ns is not None else ref_ns)
                tolerance = max(tolerance, PERIOD_FACTOR * spacing)
            relation = self._relation(ref_ns, ref_rx, stamp, receive, tolerance, mode)
            if relation != 'forward':
                if len(held) == 1:
                    # One candidate against another: the older one is dropped, and this
                    # one is held in its place (in the new list: it must not vanish).
                    result.dropped = self._drop_held()
                    held = self._held
                else:
                    # A chain is establishing itself: this one is the odd one out.
                    result.dropped.append((item, 'outlier',
                                           self._outlier_text(stamp, receive)))
                    return result
        held.append((stamp, receive, item))
        if len(held) >= self.jump_samples:
            self._held = []
            first = held[0][0]
            anchor = self._reference_anchor()
            origin = self.last_ns if self.last_ns is not None else \
                (anchor[0] if anchor is not None else first)
            result.jump = ClockJump(self.stream, origin, first, held[0][1], False)
            self._anchor = None
            # The stream's rate is unchanged: its local period stays.
            self.last_ns = None
            self._latencies.clear()
            self._release(held, result)
        return result

    def _release(self, held: list, result: StampResult) -> None:
        """Accept held candidates (stamp, receive, item) in order, into ``result``."""
        for stamp, receive, item in held:
            self._accept(stamp, receive)
            result.accepted.append(item)

    def _reference_anchor(self) -> Optional[tuple[int, Optional[int]]]:
        """Return the clock a stream without a reference is judged by, if any."""
        if self._anchor is not None:
            return self._anchor
        peer = self.peer
        if peer is not None and peer.last_ns is not None:
            return peer.last_ns, peer.last_receive_ns
        return None

    def _outlier_text(self, stamp: int, receive: Optional[int]) -> str:
        """Say why a stamp is an outlier: the rule that fired, with its numbers."""
        anchor = self._reference_anchor()
        if self.last_ns is not None:
            reference, ref_rx = self.last_ns, self.last_receive_ns
        elif anchor is not None:
            reference, ref_rx = anchor
        else:
            return f'{self.stream} stamp {stamp} inconsistent with its neighbours'
        step = stamp - reference
        head = f'{self.stream} stamp {stamp} is {step * 1e-9:+.6g} s from its stream'
        tolerance = self.tolerance()
        if receive is not None and ref_rx is not None:
            moved = receive - ref_rx
            if abs(step - moved) > tolerance:
                return (f'{head} while its receive time moved {moved * 1e-9:+.6g} s '
                        f'(offset rule: stamp and receive time apart by more than the '
                        f'tolerance {tolerance * 1e-9:.3g} s)')
            if step > self._cadence:
                ahead = self._ahead(stamp, receive, abs(step - moved))
                return (f'{head} (cadence rule: ahead of the cadence {self._cadence * 1e-9:.3g}'
                        f' s, 4 local periods, and ahead of its receive time by '
                        f'{ahead * 1e-9:.3g} s, more than half the step)')
        elif step > self._cadence:
            return (f'{head} (cadence rule: ahead of the cadence {self._cadence * 1e-9:.3g} s, '
                    '4 local periods, without a receive time to show a pause)')
        return f'{head} (tolerance {tolerance * 1e-9:.3g} s)'

    def _drop_held(self) -> list:
        held, self._held = self._held, []
        return [(item, 'outlier', self._outlier_text(stamp, receive))
                for stamp, receive, item in held]

    def follow(self, stamp: int, receive: Optional[int]) -> StampResult:
        """
        Re-anchor on another stream's new clock after its jump (see :class:`ClockJump`).

        Held candidates that fit the new clock are released in order; the rest
        are dropped as outliers.
        """
        held, self._held = self._held, []
        self.last_ns = self.last_receive_ns = None
        self._latencies.clear()
        self._anchor = (stamp, receive)
        result = StampResult()
        for stamp_k, receive_k, item_k in held:
            step = self._judge(stamp_k, receive_k, item_k)
            result.dropped += step.dropped
            result.accepted += step.accepted
            result.jump = step.jump or result.jump
        return result

    def finish(self) -> list:
        """End of input: drop the candidates still held (unconfirmed) as outliers."""
        return self._drop_held()

    def restart(self) -> list[tuple[int, Optional[int], Any]]:
        """Forget the clock (the estimator restarted); return the held (stamp, receive, item)."""
        held, self._held = self._held, []
        self.last_ns = self.last_receive_ns = None
        self._steps.clear()
        self._latencies.clear()
        self._refresh_cadence()
        self._anchor = None
        return held
