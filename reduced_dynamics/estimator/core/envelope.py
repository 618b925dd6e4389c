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
The re-timer's window arithmetic, compiled: the lower envelope and its scan.

:class:`~reduced_dynamics.estimator.retiming.FrameRetimer` refits its line every
few samples over a window of 256 (index, stamp) points; in Python that loop was a
tenth of a streaming update. These kernels do the same operations in the same
order: integer geometry on int64 (indices and ns stamps of a window: the products
stay far below 2^63) and the same float expressions, so the results are the
Python code's bit for bit (``test_retiming.py`` checks them against it).
"""

from itertools import chain
from typing import Optional

from numba import njit
import numpy as np


@njit(cache=True)
def lower_line(index: np.ndarray, stamp: np.ndarray) -> tuple:
    """
    Return (found, n1, s1, slope): the LP lower line of the points (index, stamp).

    The edge of the lower convex hull whose span holds the mean index (or the
    last edge); ``found`` False for fewer than two hull vertices.
    """
    count = index.shape[0]
    hull_n = np.empty(count, np.int64)
    hull_s = np.empty(count, np.int64)
    size = 0
    total = 0
    for k in range(count):
        n, s = index[k], stamp[k]
        total += n
        while size >= 2:
            n1, s1 = hull_n[size - 2], hull_s[size - 2]
            n2, s2 = hull_n[size - 1], hull_s[size - 1]
            # Keep the last vertex only if it lies strictly below the chord to (n, s).
            if (n2 - n1) * (s - s1) - (s2 - s1) * (n - n1) <= 0:
                size -= 1
            else:
                break
        hull_n[size] = n
        hull_s[size] = s
        size += 1
    if size < 2:
        return False, 0, 0, 0.0
    for k in range(size - 1):
        if count * hull_n[k + 1] >= total:
            return (True, hull_n[k], hull_s[k],
                    float(hull_s[k + 1] - hull_s[k]) / float(hull_n[k + 1] - hull_n[k]))
    k = size - 2
    return (True, hull_n[k], hull_s[k],
            float(hull_s[k + 1] - hull_s[k]) / float(hull_n[k + 1] - hull_n[k]))


@njit(cache=True)
def scan(index: np.ndarray, stamp: np.ndarray, n0: int, s0: int, period: float,
         limit: float, burst_step: float) -> tuple:
    """
    Return (consistent, bursts, longest run, 99th-percentile latency) of the window.

    Latencies d = s - s0 - T (n - n0) from the first point on; the scan stops at the
    first outside [-T/2, ``limit``] (not consistent; the percentile then covers the
    points up to that one). A burst is a step under ``burst_step`` T; a run is a
    stretch of latencies >= 3T/4 that a fresh sample ended.
    """
    count = index.shape[0]
    low = -0.5 * period
    late = 0.75 * period
    latencies = np.empty(count)
    used = 0
    bursts = 0
    run = 0
    longest = 0
    consistent = True
    for k in range(count):
        d = (stamp[k] - s0) - period * (index[k] - n0)
        latencies[used] = d
        used += 1
        if d < low or d > limit:
            consistent = False
            break
        if k > 0 and stamp[k] - stamp[k - 1] < burst_step * period:
            bursts += 1
        if d >= late:
            run += 1
        else:
            longest = max(longest, run)
            run = 0
    ordered = np.sort(latencies[:used])
    return consistent, bursts, longest, ordered[(99 * used) // 100]


def window_arrays(points) -> tuple[np.ndarray, np.ndarray]:
    """Return the (index, stamp) columns of a window of points as int64 arrays."""
    flat = np.fromiter(chain.from_iterable(points), np.int64, 2 * len(points))
    return flat[0::2], flat[1::2]


def optional_line(found: bool, n1: int, s1: int, slope: float) -> Optional[tuple]:
    """Return a :func:`lower_line` result as Python (n1, s1, slope), or None."""
    return (int(n1), int(s1), float(slope)) if found else None
