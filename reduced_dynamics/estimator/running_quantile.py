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
A running quantile of a stream in bounded memory: exact up to a capacity, then a systematic sample.

Running statistics of a node that runs for weeks cannot keep every value
(issue 27). :class:`RunningQuantile` keeps the values themselves while there
are at most ``capacity`` of them, so its quantiles are then exactly
``numpy.quantile`` of the stream. When the store is full it keeps every second
value (in arrival order) and from then on takes every second value of the
stream, doubling the stride each time it fills again: a deterministic,
evenly spread sample of at most ``capacity`` values (no random numbers, so
replays are reproducible). Count, maximum and mean stay exact.
"""

from __future__ import annotations

from typing import Optional

import numpy as np

#: Values a running quantile keeps (exact medians up to this many values).
QUANTILE_CAPACITY = 4096


class RunningQuantile:
    """
    Count, max, mean and quantiles of a stream of floats.

    Memory bound: at most ``capacity`` stored floats (a list), whatever the
    stream's length.
    """

    __slots__ = ('capacity', 'count', 'maximum', 'total', '_kept', '_stride')

    def __init__(self, capacity: int = QUANTILE_CAPACITY) -> None:
        """Start empty; keep at most ``capacity`` (>= 2) values."""
        if capacity < 2:
            raise ValueError(f'a running quantile needs a capacity >= 2, got {capacity}')
        self.capacity = int(capacity)
        self.count = 0
        self.maximum: Optional[float] = None
        self.total = 0.0
        self._kept: list[float] = []
        self._stride = 1

    def add(self, value: float) -> None:
        """Take one value."""
        value = float(value)
        self.count += 1
        self.total += value
        if self.maximum is None or value > self.maximum:
            self.maximum = value
        if (self.count - 1) % self._stride:
            return  # kept: the stream's every stride-th value, from the first on
        kept = self._kept
        kept.append(value)
        if len(kept) >= self.capacity:
            # Full: keep every second value, take every second one from now on.
            del kept[1::2]
            self._stride *= 2

    @property
    def exact(self) -> bool:
        """Whether every value is still kept (quantiles exact)."""
        return self._stride == 1

    @property
    def mean(self) -> Optional[float]:
        """Return the mean of every value taken (None before the first)."""
        return self.total / self.count if self.count else None

    def quantile(self, q: float) -> Optional[float]:
        """Return the q-quantile, exact while :attr:`exact`; None before the first value."""
        if not self._kept:
            return None
        return float(np.quantile(self._kept, q))

    def median(self) -> Optional[float]:
        """Return the middle value (numpy's median of the values while :attr:`exact`)."""
        if not self._kept:
            return None
        return float(np.median(self._kept))

    def __len__(self) -> int:
        """Return how many values are stored (at most ``capacity``)."""
        return len(self._kept)
