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
Simulated sensor timing and resolution: what a real driver does to a perfect sample.

A measured topic samples the true state at the nominal instants t_k = k / rate. Its
message then carries:

- a **header stamp** t_k + e_k: e_k ~ N(0, ``stamp_jitter``) (a driver stamping on
  arrival, a clock that wanders); with probability ``bunch_fraction`` the message is
  stamped instead ``gap`` before the next message's stamp, gap uniform in
  [0.5, 1.5] ``bunch_gap`` (two mocap packets stamped tens of microseconds apart while
  their contents are a period apart, as on the freeflyer2 testbed). A bunched message
  is never followed by another bunched one, so they come in pairs.
- **stamped on receipt** (``poll_period`` > 0, instead of the jitter and bunching):
  a polling client (ROS 2 ``vrpn_mocap``) receives the frame ``transport`` after
  t_k and stamps it at its next poll; polls come every ``poll_period``, each one late
  by U(0.5, 1.5) ``poll_late_delay`` with probability ``poll_late_fraction`` (the
  schedule then continues from the late poll), and the frames one poll takes get
  stamps ``POLL_SPACING`` apart. Bursts of frames stamped together, up to tens of
  ms after their instant, as on the freeflyer2 testbed. The record time is then the
  stamp plus the latency below.
- a **record (receive) time** t_k + d_k, d_k = max(0, N(``latency``, ``latency_jitter``)):
  the transport delay the bag's log time shows.
- **dropouts**: each message is lost with probability ``drop_rate`` (independently),
  and every message whose t_k falls in an outage is lost; outages start as a Poisson
  process of ``outage_rate`` per second and last an exponential time of mean
  ``outage_duration``.
- **quantisation** of its values (:func:`quantize`), after the noise.

Every random quantity has its own seeded stream per topic, so turning one effect on
never changes the draws of another and runs are reproducible.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Optional

import numpy as np

NS_PER_S = 1_000_000_000

#: Quantised fields: joint positions, velocities, efforts; base position (m),
#: orientation (quaternion components, unnormalised afterwards as a fixed-point
#: transport would leave them), linear and angular velocity of the base twist.
QUANTIZE_FIELDS = ('joint_position', 'joint_velocity', 'joint_effort', 'base_position',
                   'base_orientation', 'base_linear_velocity', 'base_angular_velocity')

# Random stream ids (offsets per topic index); the simulator's own streams are below 20.
_STREAM_JITTER = 20
_STREAM_BUNCH = 30
_STREAM_LATENCY = 40
_STREAM_OUTAGE = 50
_STREAM_DROP = 10
_STREAM_POLL = 60
#: Stamp spacing [ns] of the frames one poll takes (the client's processing).
POLL_SPACING = 20_000  # the simulator's historical drop streams, kept so old bags reproduce


def quantize(values: np.ndarray, step: float) -> np.ndarray:
    """Round ``values`` to the nearest multiple of ``step`` (``step`` 0: unchanged)."""
    if step <= 0.0:
        return values
    return step * np.round(np.asarray(values) / step)


@dataclass(frozen=True)
class TimingOptions:
    """The timing effects of one measured topic (seconds, fractions, per second)."""

    stamp_jitter: float = 0.0
    bunch_fraction: float = 0.0
    bunch_gap: float = 3e-5
    latency: float = 0.0
    latency_jitter: float = 0.0
    drop_rate: float = 0.0
    outage_rate: float = 0.0
    outage_duration: float = 0.04
    poll_period: float = 0.0
    poll_late_fraction: float = 0.0
    poll_late_delay: float = 0.05
    transport: float = 2e-4


@dataclass
class TopicStatistics:
    """What the timing model did to one topic (the simulator's summary)."""

    written: int = 0
    dropped_random: int = 0
    dropped_outage: int = 0
    bunched: int = 0
    #: [start, end) of every outage that began inside the run, s from the first sample
    outages: list[tuple[float, float]] = field(default_factory=list)

    def to_dict(self) -> dict:
        """Return a JSON-ready dict."""
        return {'written': self.written, 'dropped_random': self.dropped_random,
                'dropped_outage': self.dropped_outage, 'bunched': self.bunched,
                'outages': [list(o) for o in self.outages]}


class TopicTiming:
    """Header stamps, record times and dropouts of one measured topic, sample by sample."""

    def __init__(self, options: TimingOptions, seed: int, index: int,
                 nominal_ns: Callable[[int], int], duration: float) -> None:
        """``index`` numbers the topic (its random streams); ``nominal_ns(k)`` is t_k."""
        self.options = options
        self.nominal_ns = nominal_ns
        self.duration = duration
        self.jitter_rng = np.random.default_rng([seed, _STREAM_JITTER + index])
        self.bunch_rng = np.random.default_rng([seed, _STREAM_BUNCH + index])
        self.latency_rng = np.random.default_rng([seed, _STREAM_LATENCY + index])
        self.outage_rng = np.random.default_rng([seed, _STREAM_OUTAGE + index])
        self.drop_rng = np.random.default_rng([seed, _STREAM_DROP + index])
        self.stats = TopicStatistics()
        self._jitter: dict[int, int] = {}
        self._previous_bunched = False
        self._outage: Optional[tuple[float, float]] = None
        self._outage_clock = 0.0
        self.poll_rng = np.random.default_rng([seed, _STREAM_POLL + index])
        self._poll_ns: Optional[int] = None
        self._poll_taken = 0
        if options.outage_rate > 0.0:
            self._next_outage()

    def _error_ns(self, k: int) -> int:
        """Return the jitter of sample k's stamp, drawn once in order of k."""
        if k not in self._jitter:
            sigma = self.options.stamp_jitter
            self._jitter[k] = int(round(sigma * NS_PER_S * self.jitter_rng.standard_normal())) \
                if sigma > 0.0 else 0
        return self._jitter[k]

    def _next_outage(self) -> None:
        rate, mean = self.options.outage_rate, self.options.outage_duration
        start = self._outage_clock + self.outage_rng.exponential(1.0 / rate)
        end = start + self.outage_rng.exponential(mean)
        self._outage, self._outage_clock = (start, end), end
        if start <= self.duration:
            self.stats.outages.append((float(start), float(end)))

    def _in_outage(self, t: float) -> bool:
        while self._outage is not None and t >= self._outage[1]:
            self._next_outage()
        return self._outage is not None and self._outage[0] <= t

    def _polled_ns(self, true_ns: int) -> int:
        """Return the stamp of a frame taken at ``true_ns`` by a polling client."""
        options = self.options
        period = int(round(options.poll_period * NS_PER_S))
        arrival = true_ns + int(round(options.transport * NS_PER_S))
        if self._poll_ns is None:
            # The client's schedule starts at a random phase of its period.
            self._poll_ns = true_ns + int(self.poll_rng.integers(0, period))
        while self._poll_ns < arrival:
            self._poll_ns += period
            self._poll_taken = 0
            if self.poll_rng.random() < options.poll_late_fraction:
                self._poll_ns += int(round(self.poll_rng.uniform(0.5, 1.5)
                                           * options.poll_late_delay * NS_PER_S))
        self._poll_taken += 1
        return self._poll_ns + (self._poll_taken - 1) * POLL_SPACING

    def message(self, k: int, t: float) -> Optional[tuple[int, int]]:
        """Return (header stamp, record time) of sample k at t s, or None when it is lost."""
        options = self.options
        true_ns = self.nominal_ns(k)
        stamp = true_ns + self._error_ns(k)
        self._jitter.pop(k, None)
        if options.bunch_fraction > 0.0:
            draw = self.bunch_rng.random()
            gap = self.bunch_rng.uniform(0.5, 1.5) * options.bunch_gap
            bunched = not self._previous_bunched and draw < options.bunch_fraction
            if bunched:
                stamp = self.nominal_ns(k + 1) + self._error_ns(k + 1) \
                    - int(round(gap * NS_PER_S))
            self._previous_bunched = bunched
        else:
            bunched = False
        polled = options.poll_period > 0.0
        if polled:
            stamp = self._polled_ns(true_ns)
        record = stamp if polled else true_ns
        if options.latency > 0.0 or options.latency_jitter > 0.0:
            delay = options.latency + options.latency_jitter * self.latency_rng.standard_normal()
            record += int(round(max(0.0, delay) * NS_PER_S))
        # Always draw, so a drop rate does not shift the other effects' sequences.
        kept = self.drop_rng.random() >= options.drop_rate
        if options.outage_rate > 0.0 and self._in_outage(t):
            self.stats.dropped_outage += 1
            return None
        if not kept:
            self.stats.dropped_random += 1
            return None
        self.stats.written += 1
        self.stats.bunched += int(bunched)
        return stamp, record
