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
Base samples held for the joint-state rows.

A row gets the base samples stamped since the previous row (its measurements)
and the base state at its own stamp by SE(3) interpolation. The Kalman filter
(estimator/filter.py) updates with each base sample once, at its own stamp
(:meth:`BaseBuffer.between` hands them to the row after them). The interpolated
state at a row's stamp (the pose along the geodesic between the two bracketing
samples and, with Odometry, the body twist linearly) is the measured history the
prediction residuals compare against, and the filter's start. Poses are never
differentiated.
"""

from __future__ import annotations

from bisect import bisect_left, bisect_right
from collections import deque
from typing import Optional, Sequence

import numpy as np
import pinocchio as pin


class BasePoint:
    """
    A held base sample as the interpolation sees it: stamp, row and ``pin.SE3`` pose.

    ``row`` is pose7 (translation, unit quaternion x, y, z, w) then, with
    Odometry, the body twist (linear first).
    """

    __slots__ = ('stamp_ns', 'row', 'pose')

    def __init__(self, stamp_ns: int, row: Sequence[float], pose: pin.SE3) -> None:
        """Hold a sample and its pose."""
        self.stamp_ns = stamp_ns
        self.row = row
        self.pose = pose

    @property
    def pose7(self) -> np.ndarray:
        """Return translation and quaternion (x, y, z, w)."""
        return np.array(self.row[:7])

    @property
    def twist(self) -> Optional[np.ndarray]:
        """Return the body twist, or None without Odometry."""
        return np.array(self.row[7:]) if len(self.row) > 7 else None


def _row(pose: pin.SE3, twist: np.ndarray) -> np.ndarray:
    return np.concatenate((pin.SE3ToXYZQUAT(pose), twist))


class BaseBuffer:
    """
    A short history of base samples, strictly increasing in stamp.

    Samples are held as rows of plain floats, or rows of a float array (the batched
    path's base columns), what the update stacks for a whole chunk; a ``pin.SE3``
    is built, once, only when an interpolation needs it.
    """

    def __init__(self, keep: int = 64) -> None:
        """Keep at most ``keep`` samples."""
        self._keep = keep
        self._rows: deque[Sequence[float]] = deque(maxlen=keep)
        self._stamps: deque[int] = deque(maxlen=keep)
        self._poses: dict[int, pin.SE3] = {}
        self._around: dict[int, tuple] = {}

    def __len__(self) -> int:
        """Return the number of samples held."""
        return len(self._rows)

    @property
    def latest_ns(self) -> Optional[int]:
        """Return the newest stamp, or None when empty."""
        return self._stamps[-1] if self._stamps else None

    def append(self, stamp_ns: int, row: Sequence[float]) -> None:
        """Add a sample newer than every held one: 7 values (pose) or 13 (with twist)."""
        self._rows.append(row)
        self._stamps.append(stamp_ns)

    def between(self, after_ns: Optional[int], until_ns: int) -> tuple:
        """Return the held samples (stamp_ns, row) with after_ns < stamp <= until_ns, in order."""
        stamps = self._stamps
        if not stamps:
            return ()
        newest = stamps[-1]
        if after_ns is not None:
            if newest <= after_ns:
                return ()
            if newest == until_ns and (len(stamps) == 1 or stamps[-2] <= after_ns):
                # The common row: just the newest sample, at the row's stamp (no search).
                return ((newest, self._rows[-1]),)
        first = 0 if after_ns is None else bisect_right(stamps, after_ns)
        last = bisect_right(stamps, until_ns)
        if first >= last:
            return ()
        rows = self._rows
        return tuple((stamps[i], rows[i]) for i in range(first, last))

    def point(self, index: int) -> BasePoint:
        """Return held sample ``index`` with its pose (cached by stamp)."""
        stamp, row = self._stamps[index], self._rows[index]
        pose = self._poses.get(stamp)
        if pose is None:
            if len(self._poses) >= 2 * self._keep:
                self._poses.clear()  # older poses are no longer held anyway
            pose = self._poses[stamp] = pin.XYZQUATToSE3(row[:7])
        return BasePoint(stamp, row, pose)

    def status(self, stamp_ns: int,
               needs_successor: bool) -> tuple[Optional[int], bool, int]:
        """
        Return the nearest-stamp distance (None when empty), :meth:`ready` and an index.

        One search serves all three; pass the index on to :meth:`query`.
        """
        stamps = self._stamps
        if not stamps:
            return None, False, 0
        index = bisect_left(stamps, stamp_ns)
        count = len(stamps)
        if index == 0:
            gap = stamps[0] - stamp_ns
        elif index == count:
            gap = stamp_ns - stamps[-1]
        else:
            gap = min(stamp_ns - stamps[index - 1], stamps[index] - stamp_ns)
        latest = stamps[-1]
        if not needs_successor:
            return gap, latest >= stamp_ns, index
        # Differentiation uses three samples; at the start of a stream wait for them.
        return gap, latest > stamp_ns and count >= 3, index

    def nearest_gap_ns(self, stamp_ns: int) -> Optional[int]:
        """Return the distance to the nearest held stamp (None when empty)."""
        return self.status(stamp_ns, False)[0]

    def ready(self, stamp_ns: int, needs_successor: bool) -> bool:
        """Return whether a lookup at ``stamp_ns`` has all the samples it will use."""
        return self.status(stamp_ns, needs_successor)[1]

    def query(self, stamp_ns: int, index: Optional[int] = None) -> Sequence[float]:
        """
        Return pose7 and body twist at ``stamp_ns`` as one row of 13 values.

        The buffer must not be empty; ``index`` is the one :meth:`status` gave
        (the buffer unchanged since). At a held stamp with Odometry the held row
        itself is returned: do not modify it.
        """
        rows, stamps = self._rows, self._stamps
        if index is None:
            index = bisect_left(stamps, stamp_ns)
        if index < len(stamps) and stamps[index] == stamp_ns and len(rows[index]) > 7:
            return rows[index]
        if len(rows[0]) > 7:
            return self._interpolate(index, stamp_ns)
        return self._interpolate_pose(index, stamp_ns)

    def _interpolate_pose(self, index: int, stamp_ns: int) -> list:
        """Return the pose at ``stamp_ns`` (geodesic between neighbours), zero twist."""
        rows, stamps = self._rows, self._stamps
        count = len(rows)
        zeros = [0.0] * 6
        if index < count and stamps[index] == stamp_ns:
            return list(rows[index]) + zeros
        if index <= 0 or index >= count:
            # Before the first or after the last pose: the nearest pose is held.
            return list(rows[0 if index <= 0 else count - 1]) + zeros
        a, b = self.point(index - 1), self.point(index)
        s = (stamp_ns - a.stamp_ns) / (b.stamp_ns - a.stamp_ns)
        return pin.SE3ToXYZQUAT(pin.SE3.Interpolate(a.pose, b.pose, s)).tolist() + zeros

    def _interpolate(self, index: int, stamp_ns: int) -> np.ndarray:
        count = len(self._rows)
        if index <= 0 or index >= count:
            edge = self.point(0 if index <= 0 else count - 1)
            dt = (stamp_ns - edge.stamp_ns) * 1e-9
            return _row(edge.pose * pin.exp6(edge.twist * dt), edge.twist)
        a, b = self.point(index - 1), self.point(index)
        s = (stamp_ns - a.stamp_ns) / (b.stamp_ns - a.stamp_ns)
        # Along the geodesic a exp(s log(a^-1 b)): one Pinocchio call. The twist
        # linearly, in plain floats (13-value rows throughout).
        pose = pin.SE3.Interpolate(a.pose, b.pose, s)
        return pin.SE3ToXYZQUAT(pose).tolist() + [
            (1 - s) * u + s * v for u, v in zip(a.row[7:], b.row[7:])]
