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
Thruster/contact events from the filter's own statistics.

Without external wrench mu is constant (Noether) and the filter's wrench
estimate w is consistent with zero: its significance ``s = w^T P_ww^-1 w`` is
then chi-square with n degrees of freedom. An event starts when s exceeds the
chi2_n quantile at the false-alarm probability ``event_significance``; it ends
after ``hold`` seconds with s below the 99 % quantile, and the reduced model
is then re-reduced at the new momentum. The test is dimensionless: the same
default works for a 16 kg testbed and a 500 kg spacecraft.

The random-walk w needs time to grow after a thruster switches, so the test on
w alone lags. :class:`~reduced_dynamics.estimator.step_test.WrenchStepTest`, a
generalised-likelihood-ratio test of a *step* in w on the filter's own
innovations (Willsky & Jones 1976; docs/step_test.md), flags it at once; a
step it finds starts an event as s above its threshold does.

Neither sees a weak push of a second or more: the step test weighs a step
against the filter's random walk, which explains a slow push almost as well.
:class:`~reduced_dynamics.estimator.multiscale.MultiScaleTest` tests the
filtered momentum's change over windows of 0.05-3 s against no wrench at the
user's false-alarm rate per hour (``event_false_alarm_rate``); a window it finds
starts an event at the window's start (docs/multiscale_events.md).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple, Optional

import numpy as np
from reduced_dynamics.chi_square import chi2
from reduced_dynamics.estimator.event_log import EventLog
from reduced_dynamics.estimator.multiscale import ImpulseDetection, MultiScaleTest

# The step test's names stay importable from here (filter.py and older callers).
from reduced_dynamics.estimator.step_test import StepDetection, WrenchStepTest

__all__ = ['EventDetector', 'EventNotice', 'MomentumEvent', 'SETTLE', 'StepDetection',
           'WrenchStepTest']

#: Seconds after an event's end during which its mu_after follows the filter.
SETTLE = 1.0
#: Longest block window [s] whose change keeps an event that no window started open
#: (its end comes at most three such windows after the push's).
MOVING_WINDOW = 0.3


@dataclass
class MomentumEvent:
    """A detected external-wrench event and the momentum change across it."""

    start_ns: int
    end_ns: Optional[int] = None
    mu_before: Optional[np.ndarray] = None
    mu_after: Optional[np.ndarray] = None
    peak_wrench: float = 0.0
    peak_significance: float = 0.0
    #: the window [s] of the multi-scale test that detected it (None: the per-sample
    #: chi-square or the step test)
    window: Optional[float] = None
    #: covariances of mu_before and mu_after (None: not given to the detector)
    cov_before: Optional[np.ndarray] = None
    cov_after: Optional[np.ndarray] = None
    #: when it was detected (the start is where the multi-scale test dates it)
    detected_ns: Optional[int] = None
    #: whether mu_after is fixed (SETTLE s after the end; a re-opened event clears it)
    settled: bool = False
    #: once a detection continued it, the window [s] that found the continuation: the
    #: open stretch ends by its criteria (None: by ``window``'s)
    stretch_window: Optional[float] = None

    def horizon(self, blocks: bool) -> float:
        """
        Return the seconds after the end during which a detection may continue the event.

        SETTLE; with the block test on measured momenta (``blocks``), for an event a
        window found, 3 such windows more: no window reaches back before the end, so
        that window, which sees a push going on at the force it found undiminished (a
        constant force moves its blocks' difference by 2 L F, its largest value), is
        blind until it is covered again, 3 L after the end (docs/multiscale_events.md,
        "One push, one event").
        """
        return SETTLE + (3.0 * self.window if blocks and self.window is not None else 0.0)

    @property
    def impulse_cov(self) -> Optional[np.ndarray]:
        """
        Return the impulse's covariance, P_mu before + P_mu after.

        An upper bound: the two estimates' errors are positively correlated.
        """
        if self.cov_before is None or self.cov_after is None or self.impulse is None:
            return None
        return self.cov_before + self.cov_after

    @property
    def impulse(self) -> Optional[np.ndarray]:
        """Return mu_after - mu_before (world frame), once the event has ended."""
        if self.mu_before is None or self.mu_after is None:
            return None
        return self.mu_after - self.mu_before


class EventNotice(NamedTuple):
    """
    A snapshot of an event for the ``~/events`` topic (algebra coordinates, world frame).

    Issued twice per event: at its detection (``final`` False, ``end_ns`` None, the
    impulse so far: mu now - mu before) and once its impulse is settled (``final``
    True: its horizon after its end (:meth:`MomentumEvent.horizon`), or when the next
    event starts, or at the end of the data).
    """

    start_ns: int
    end_ns: Optional[int]
    detected_ns: int
    window: Optional[float]
    peak_wrench: float
    impulse: Optional[np.ndarray]
    impulse_cov: Optional[np.ndarray]
    final: bool


def notice(event: 'MomentumEvent', final: bool, mu: Optional[np.ndarray] = None,
           cov: Optional[np.ndarray] = None) -> EventNotice:
    """Return the event's notice; before its end ``mu``, ``cov`` give the impulse so far."""
    impulse, impulse_cov = event.impulse, event.impulse_cov
    if impulse is None and mu is not None and event.mu_before is not None:
        impulse = mu - event.mu_before
        impulse_cov = None if cov is None or event.cov_before is None \
            else event.cov_before + cov
    return EventNotice(event.start_ns, event.end_ns,
                       event.start_ns if event.detected_ns is None else event.detected_ns,
                       event.window, float(event.peak_wrench),
                       None if impulse is None else impulse.copy(),
                       None if impulse_cov is None else impulse_cov.copy(), final)


@dataclass
class EventDetector:
    """Chi-square test of the wrench estimate with hysteresis and a hold time."""

    dim: int
    significance: float
    hold: float
    #: false alarms per hour of the multi-scale test (0: off)
    false_alarm_rate: float = 0.0
    #: the last EVENTS_KEEP events (estimator/event_log.py: memory bound)
    events: EventLog = field(default_factory=EventLog)
    _quiet_mu: Optional[np.ndarray] = None
    _quiet_since: Optional[int] = None
    _changed: bool = False
    _quiet_cov: Optional[np.ndarray] = None
    #: notices not yet taken (:meth:`take_notices`) and the last event not yet final
    notices: list[EventNotice] = field(default_factory=list)
    _settling: Optional[MomentumEvent] = None

    def __post_init__(self) -> None:
        """Set the start and end thresholds from the chi-square quantiles."""
        self.multiscale = MultiScaleTest(self.dim, self.false_alarm_rate
                                         if self.significance > 0.0 else 0.0)
        self.start_threshold = float(chi2.isf(self.significance, self.dim))
        self.end_threshold = float(chi2.isf(0.01, self.dim))
        # Below the median w is indistinguishable from zero: mu there is "before".
        self.rest_threshold = float(chi2.isf(0.5, self.dim))

    @property
    def in_event(self) -> bool:
        """
        Return whether an event is under way: from a detection to the event's end.

        Predictions pause while one is (processing.py: they assume mu constant). The
        horizon after an end (:meth:`MomentumEvent.horizon`) is no part of it: it keeps
        the record open for a continuation, found up to 3 windows late and dated back
        to the end, when the rows in between have long been processed; only such a
        detection re-opens the event, from its own row on, and that stretch ends as the
        event it would have opened alone (docs/multiscale_events.md, "Which rows an
        event pauses").
        """
        return bool(self.events) and self.events[-1].end_ns is None

    def take_level_change(self) -> bool:
        """Return True once after an event ended (re-reduce at the new momentum)."""
        changed, self._changed = self._changed, False
        return changed

    def take_notices(self) -> list[EventNotice]:
        """Return the notices issued since the last call (the ``~/events`` messages)."""
        taken, self.notices = self.notices, []
        return taken

    def finish(self) -> None:
        """End of the data: the last event's notice becomes final as it stands."""
        last = self._settling
        if last is not None:
            if last.end_ns is not None:
                self._finalise(last.end_ns + int(SETTLE * 1e9), True)
            else:
                self.notices.append(notice(last, True))
            self._settling = None

    def _finalise(self, stamp_ns: int, starting: bool) -> None:
        """
        Settle the ended event's impulse after SETTLE s; its final notice after its horizon.

        Until :meth:`MomentumEvent.horizon` has passed, a detection dated at its end
        continues it (a push that went on), so its final notice waits; ``starting``: the
        next event starts, both now.
        """
        last = self._settling
        if last is None or last.end_ns is None:
            return
        since = (stamp_ns - last.end_ns) * 1e-9
        if not last.settled and (starting or since > SETTLE):
            # With measured twists, mu after is their mean over the settling time:
            # every sample's information, not the filter's last estimate.
            after = self.multiscale.measured_mean(
                last.end_ns, min(stamp_ns, last.end_ns + int(SETTLE * 1e9)))
            if after is not None:
                last.mu_after, last.cov_after = after
            last.settled = True
        if starting or since > last.horizon(self.multiscale.blocks.active):
            self.notices.append(notice(last, True))
            self._settling = None

    def _continues(self, pulse: ImpulseDetection, stamp_ns: int) -> bool:
        """
        Return whether a pulse detected at ``stamp_ns`` continues the last ended event.

        Its fit must date it within SETTLE of that end. Within SETTLE of the end, that
        is all. Later (up to the event's horizon), the block test must have found it
        within one window length L of that window reaching back to the end (3 L after
        it): a push that goes on moves the momentum across the end, so the window finds
        it as soon as it is covered (measured: within 0.8 L); a new push after the end
        is found later than that.
        """
        last = self._settling
        if last is None or last.end_ns is None or \
                pulse.start_ns - last.end_ns > SETTLE * 1e9:
            return False
        since = (stamp_ns - last.end_ns) * 1e-9
        return since <= SETTLE or (pulse.measured and since <= 4.0 * pulse.window)

    def _open(self, event: MomentumEvent, mu: np.ndarray,
              mu_cov: Optional[np.ndarray]) -> None:
        """Start an event: the previous one is final, this one is announced."""
        self._finalise(event.start_ns, True)
        self.events.append(event)
        self._settling = event
        self.notices.append(notice(event, False, mu, mu_cov))

    def _measured_before(self, start_ns: int, mu: np.ndarray, cov: Optional[np.ndarray]
                         ) -> tuple[np.ndarray, Optional[np.ndarray]]:
        """
        Return mu before an event starting at ``start_ns`` and its covariance.

        With measured twists, their mean over SETTLE s before it (not before the
        last event's end); else the filter's ``mu``, ``cov``.
        """
        floor = self.multiscale.floor_ns
        measured = self.multiscale.measured_mean(
            max(start_ns - int(SETTLE * 1e9), -1 if floor is None else floor), start_ns - 1)
        return (mu, cov) if measured is None else measured

    def update(self, stamp_ns: int, mu: np.ndarray, wrench_norm: float,
               significance: float, step: bool = False,
               mu_cov: Optional[np.ndarray] = None,
               measured: Optional[list[tuple]] = None) -> None:
        """
        Feed one filtered sample: mu, |w|, s = w^T P_ww^-1 w, and a GLR step (True: found).

        A step starts an event as s above its threshold does (the step test reacts
        to a thruster switching on before the random-walk w has grown). ``mu_cov``:
        P_mu, for the multi-scale test and the impulse's covariance (None: neither).
        ``measured``: (stamp, mu, covariance) of the twists measured since the last
        sample (measured_momentum.twist_momenta; None: none), for the block test and the
        impulse's ends.
        """
        # in_event once (the last event, looked up once): the multi-scale test does not
        # touch the events.
        last = self.events[-1] if self.events else None
        quiet = self.multiscale.quiet = last is None or last.end_ns is not None
        # A pulse is used only outside an event: inside one it is not located.
        pulse = None if mu_cov is None else \
            self.multiscale.update(stamp_ns, mu, mu_cov, measured, quiet)
        event = None if quiet else last
        if event is None and not step and self._settling is not None:
            # A step within SETTLE re-opens the last event: final only after that.
            self._finalise(stamp_ns, False)
        if event is None and last is not None and significance < self.end_threshold:
            if (stamp_ns - last.end_ns) * 1e-9 <= SETTLE:
                # The filter's mu still converges after the wrench has gone: the
                # impulse keeps following it for SETTLE seconds (or to the next event).
                last.mu_after = mu.copy()
                last.cov_after = None if mu_cov is None else mu_cov.copy()
        if event is None and step and self.events and \
                (stamp_ns - self.events[-1].end_ns) * 1e-9 <= SETTLE:
            # A step while the filter settles after an event (the compensation of its
            # own overshoot) belongs to that event: re-open it, its mu_before stays.
            event = self.events[-1]
            event.end_ns = None
            event.settled = False
            self._changed = False
        if event is None and pulse is not None and self._continues(pulse, stamp_ns):
            # The momentum moves on right after the last event's end (a long push
            # that the end criteria let go): that event goes on, its mu_before stays.
            event = self._settling
            event.end_ns = None
            event.settled = False
            self._changed = False
            # Its hold starts afresh (the quiet time before its end is not this one's),
            # and this stretch ends as an event the continuing detection opened would
            # (its window's end criteria below), not by the window that found the event:
            # the merge is of records, dated back to the end; which rows are paused (an
            # event under way: no prediction, processing.py) stays as without it
            # (docs/multiscale_events.md, "Which rows an event pauses").
            self._quiet_since = None
            event.stretch_window = pulse.window
            pulse = None
        if event is None:
            if significance > self.start_threshold or step:
                before = self._quiet_mu if self._quiet_mu is not None else mu
                cov = self._quiet_cov if self._quiet_mu is not None else mu_cov
                before, cov = self._measured_before(stamp_ns, before, cov)
                self._open(MomentumEvent(stamp_ns, mu_before=before.copy(),
                                         detected_ns=stamp_ns, peak_wrench=wrench_norm,
                                         peak_significance=significance,
                                         cov_before=None if cov is None else cov.copy()),
                           mu, mu_cov)
                self._quiet_since = None
            elif pulse is not None:
                # A pulse over the window: the event starts where the window does.
                before, cov = pulse.mu_before, pulse.cov_before
                if not pulse.measured:
                    before, cov = self._measured_before(pulse.start_ns, before, cov)
                self._open(MomentumEvent(
                    pulse.start_ns, mu_before=before, peak_wrench=wrench_norm,
                    peak_significance=significance, window=pulse.window,
                    cov_before=cov, detected_ns=stamp_ns), mu, mu_cov)
                self._quiet_since = None
            elif significance < self.rest_threshold:
                self._quiet_mu = mu
                self._quiet_cov = mu_cov
            return
        event.peak_wrench = max(event.peak_wrench, wrench_norm)
        event.peak_significance = max(event.peak_significance, significance)
        # A pulse found by its window goes on while the window of half its length
        # still moves mu beyond the median (a slow push barely moves w's chi-square).
        window = event.window if event.stretch_window is None else event.stretch_window
        pushing = window is not None and self.multiscale.window_statistic(
            window / 2) >= self.rest_threshold
        # With measured twists: while the measured momenta still move (a long push
        # goes on after the wrench estimate's chi-square dips; multiscale.py).
        pushing = pushing or self.multiscale.still_moving(
            MOVING_WINDOW if window is None else window / 2)
        if significance >= self.end_threshold or step or pushing:
            self._quiet_since = None
            return
        if self._quiet_since is None:
            self._quiet_since = stamp_ns
        if (stamp_ns - self._quiet_since) * 1e-9 >= self.hold:
            event.end_ns = stamp_ns
            event.mu_after = mu.copy()
            event.cov_after = None if mu_cov is None else mu_cov.copy()
            self._quiet_mu = mu
            self._quiet_cov = mu_cov
            self._changed = True
            # No window of the multi-scale test reaches back into this event.
            self.multiscale.reset(stamp_ns)
