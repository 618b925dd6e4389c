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
The measured states prediction residuals are judged against, copied into a bounded ring.

The predictor compares each prediction, once its horizon has passed in stamp
time, with the measured shape and base pose over the horizon. Keeping those as
views of the chunk arrays they came from would keep every chunk alive as long
as one row of it is held (issue 27: 82 B a sample retained at 1 kHz); here
each row is copied into preallocated arrays, and rows are dropped as soon as no
open prediction needs them.
"""

from __future__ import annotations

from typing import Optional

import numpy as np

#: Initial rows of the ring (it doubles while the window needs more).
INITIAL_ROWS = 256


class ObservationBuffer:
    """
    Stamped measured states (shape, base translation and rotation), stamps ascending.

    Memory bound: the rows after the last :meth:`trim`, in arrays of at most
    twice that many rows (the predictor trims every second of stamp time to its
    oldest open prediction's start, or to one horizon back: at most
    ``(horizon + 1 s) * sample rate`` rows, ~3000 at 1 kHz with the 2 s default).
    """

    def __init__(self) -> None:
        """Start empty (the arrays are allocated at the first row, to its sizes)."""
        self._stamps = np.zeros(0, np.int64)
        self._qbar: Optional[np.ndarray] = None
        self._translation = np.zeros((0, 3))
        self._rotation = np.zeros((0, 3, 3))
        self._start = self._end = 0

    def __len__(self) -> int:
        """Return the rows held."""
        return self._end - self._start

    @property
    def capacity(self) -> int:
        """Return the rows the arrays have room for."""
        return len(self._stamps)

    def _allocate(self, rows: int, m: int) -> None:
        start, end = self._start, self._end
        stamps = np.zeros(rows, np.int64)
        qbar, translation = np.zeros((rows, m)), np.zeros((rows, 3))
        rotation = np.zeros((rows, 3, 3))
        count = end - start
        if count:
            stamps[:count] = self._stamps[start:end]
            qbar[:count] = self._qbar[start:end]
            translation[:count] = self._translation[start:end]
            rotation[:count] = self._rotation[start:end]
        self._stamps, self._qbar = stamps, qbar
        self._translation, self._rotation = translation, rotation
        self._start, self._end = 0, count

    def _compact(self) -> None:
        # In place, no new arrays: a reallocation at every wrap (every ~2 s at 1 kHz) churns
        # the C heap. The live rows are at most half and end at the last slot, so they
        # start at or after slot ``count``: source and destination do not overlap.
        start, end = self._start, self._end
        count = end - start
        for array in (self._stamps, self._qbar, self._translation, self._rotation):
            array[:count] = array[start:end]
        self._start, self._end = 0, count

    def append(self, stamp_ns: int, qbar: np.ndarray, translation: np.ndarray,
               rotation: np.ndarray) -> None:
        """Copy one measured state in (the arguments may be views: none is kept)."""
        end = self._end
        if self._qbar is None or end == len(self._stamps) or len(qbar) != self._qbar.shape[1]:
            count = end - self._start
            capacity = len(self._stamps)
            m = len(qbar)
            if self._qbar is not None and self._qbar.shape[1] != m:
                self._start = self._end = count = 0  # another robot: a new history
            if self._qbar is not None and self._qbar.shape[1] == m and 2 * count <= capacity:
                self._compact()
            else:
                # Grow when more than half is live (amortised O(1) a row).
                self._allocate(max(INITIAL_ROWS, capacity if 2 * count <= capacity
                                   else 2 * capacity), m)
            end = self._end
        self._stamps[end] = stamp_ns
        self._qbar[end] = qbar
        self._translation[end] = translation
        self._rotation[end] = rotation
        self._end = end + 1

    def trim(self, before_ns: int) -> None:
        """Drop the rows stamped at or before ``before_ns``."""
        start, end = self._start, self._end
        self._start = start + int(np.searchsorted(self._stamps[start:end], before_ns,
                                                  side='right'))

    def window(self, start_ns: int, end_ns: int) -> tuple:
        """
        Return (stamps, qbar, translation, rotation) stamped in (start_ns, end_ns].

        Copies (never views of the ring); the three states are None when no row
        is in the window.
        """
        stamps = self._stamps[self._start:self._end]
        chosen = self._start + np.flatnonzero((stamps > start_ns) & (stamps <= end_ns))
        if not chosen.size:
            return self._stamps[chosen], None, None, None
        return (self._stamps[chosen], self._qbar[chosen], self._translation[chosen],
                self._rotation[chosen])
