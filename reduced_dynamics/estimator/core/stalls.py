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
Stalls of a base stream and the bursts of frames that end them.

A stream that stalls (a gap of more than ``STALL_PERIODS`` nominal intervals) and
then delivers its buffered frames in a burst, stamped on receipt less than
``BUNCHED`` of an interval apart, gives those frames stamps that say nothing of
when they were taken (anywhere since the stall began), and their errors are not
independent: all are late, the oldest most. Updating with them drove the momentum
(a 309 ms stall of a real mocap stream spiked the causal force to 9 N, issue 19).
:class:`StallDetector` flags the first frame after a stall and the bunched ones
after it; the next regular interval ends the burst.

The nominal interval is the median of the first ``FIRST_GAPS`` gaps (one may be a
bunched pair), then a running average in the log domain whose pull per gap is
clipped to 4x: a lone stall or bunched pair barely moves it, and the gaps inside
a burst are not used.
"""

import math
from typing import Optional

import numpy as np

#: A gap of more than STALL_PERIODS nominal intervals is a stall; gaps below BUNCHED of
#: an interval after it are its burst.
STALL_PERIODS = 8.0
BUNCHED = 0.25
#: Weight of a gap in the nominal interval's running average; first gaps whose median
#: starts it.
INTERVAL_WEIGHT = 0.05
FIRST_GAPS = 9
LOG_4 = math.log(4.0)


class StallDetector:
    """Flag the measurements of a burst after a stall (see the module docstring)."""

    def __init__(self) -> None:
        """Start without a nominal interval."""
        #: nominal interval [s] between measurements (None until FIRST_GAPS are seen)
        self.interval: Optional[float] = None
        self._first: list[float] = []
        self._last_ns: Optional[int] = None
        #: stamp of the last measurement before the current stall (None: no stall)
        self.stall_from_ns: Optional[int] = None

    def in_burst(self, stamp_ns: int) -> bool:
        """Take the next measurement's stamp; return whether it belongs to a burst."""
        last, self._last_ns = self._last_ns, stamp_ns
        if last is None or stamp_ns <= last:
            return False
        gap = (stamp_ns - last) * 1e-9
        nominal = self.interval
        if nominal is None:
            self._first.append(gap)
            if len(self._first) == FIRST_GAPS:
                self.interval = float(np.median(self._first))
            return False
        stall = gap > STALL_PERIODS * nominal
        if stall:
            self.stall_from_ns = last
        elif gap >= BUNCHED * nominal:
            self.stall_from_ns = None
        stalled = self.stall_from_ns
        if stalled is None or stall:
            # min(max(log, -LOG_4), LOG_4) spelled out (the same operand returned, fewer
            # calls: this runs at every measurement).
            pull = math.log(gap / nominal)
            if -LOG_4 > pull:
                pull = -LOG_4
            if LOG_4 < pull:
                pull = LOG_4
            self.interval = nominal * math.exp(INTERVAL_WEIGHT * pull)
        return stalled is not None
