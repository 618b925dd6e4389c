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
from typing import Optional

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
    """External-wrench observer, event detector and momentum level."""

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

    @property
    def in_event(self) -> bool:
        """Return whether an event is under way."""
        return bool(self.events) and self.events[-1].end_ns is None

    @property
    def level(self) -> Optional[np.ndarray]:
        """Return the momentum level the reduced model uses (mean since the last event)."""
        if self._level_count == 0:
            return None
        return self._level_sum / self._level_count

    def take_level_change(self) -> bool:
        """Return True once after the level was reset (an event ended: re-reduce)."""
        changed, self._changed = self._changed, False
        return changed

    def update(self, stamp_ns: int, mu: np.ndarray) -> np.ndarray:
        """Feed mu at a stamp; return the external-wrench estimate r."""
        if self._last_mu is None or stamp_ns <= self._last_ns:
            self.rate = np.zeros_like(mu) if self.rate is None else self.rate
        else:
            dt = (stamp_ns - self._last_ns) * 1e-9
            decay = math.exp(-self.bandwidth * dt)
            self.rate = decay * self.rate + (1.0 - decay) * (mu - self._last_mu) / dt
        self._detect(stamp_ns, mu)
        self._last_mu, self._last_ns = mu.copy(), stamp_ns
        return self.rate

    def _detect(self, stamp_ns: int, mu: np.ndarray) -> None:
        size = float(np.linalg.norm(self.rate))
        if not self.in_event:
            if size > self.threshold:
                before = self.level if self.level is not None else self._last_mu
                self.events.append(MomentumEvent(stamp_ns, mu_before=None if before is None
                                                 else before.copy(), peak_wrench=size))
                self._quiet_since = None
                return
            self._accumulate(mu)
            return
        event = self.events[-1]
        event.peak_wrench = max(event.peak_wrench, size)
        if size > 0.5 * self.threshold:
            self._quiet_since = None
            return
        if self._quiet_since is None:
            self._quiet_since = stamp_ns
        if (stamp_ns - self._quiet_since) * 1e-9 >= self.hold:
            event.end_ns = stamp_ns
            event.mu_after = mu.copy()
            self._level_sum, self._level_count = None, 0
            self._accumulate(mu)
            self._changed = True

    def _accumulate(self, mu: np.ndarray) -> None:
        self._level_sum = mu.copy() if self._level_sum is None else self._level_sum + mu
        self._level_count += 1
