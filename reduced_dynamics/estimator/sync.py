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
Base state at a joint-state stamp: SE(3) interpolation and differentiation.

With Odometry the pose is interpolated along the geodesic between the two
bracketing samples and the body twist linearly. With poses only, the twist
comes from the derivative of the quadratic through the three nearest poses in
exponential coordinates about the middle one (second order, like a central
difference).
"""

from __future__ import annotations

from bisect import bisect_left
from collections import deque
from typing import Optional, Sequence

import numpy as np
import pinocchio as pin


class BasePoint:
    """
    A validated base sample: stamp and ``row`` = pose7 then, with Odometry, twist.

    pose7 is the translation then the unit quaternion (x, y, z, w); the twist is
    the body twist (linear first). A row of plain floats is what the update
    stacks into arrays for a whole chunk; ``pin.SE3`` and arrays are built only
    when an interpolation needs them.
    """

    __slots__ = ('stamp_ns', 'row', '_pose')

    def __init__(self, stamp_ns: int, row: list[float]) -> None:
        """Hold a sample: 7 values (pose only) or 13 (pose and twist)."""
        self.stamp_ns = stamp_ns
        self.row = row
        self._pose: Optional[pin.SE3] = None

    @property
    def pose7(self) -> np.ndarray:
        """Return translation and quaternion (x, y, z, w)."""
        return np.array(self.row[:7])

    @property
    def twist(self) -> Optional[np.ndarray]:
        """Return the body twist, or None without Odometry."""
        return np.array(self.row[7:]) if len(self.row) > 7 else None

    @property
    def pose(self) -> pin.SE3:
        """Return the pose as a ``pin.SE3`` (built on first use)."""
        if self._pose is None:
            self._pose = pin.XYZQUATToSE3(self.pose7)
        return self._pose


def _row(pose: pin.SE3, twist: np.ndarray) -> np.ndarray:
    return np.concatenate((pin.SE3ToXYZQUAT(pose), twist))


class BaseBuffer:
    """A short history of base samples, strictly increasing in stamp."""

    def __init__(self, keep: int = 64) -> None:
        """Keep at most ``keep`` samples."""
        self._points: deque[BasePoint] = deque(maxlen=keep)
        self._stamps: deque[int] = deque(maxlen=keep)

    def __len__(self) -> int:
        """Return the number of samples held."""
        return len(self._points)

    @property
    def latest_ns(self) -> Optional[int]:
        """Return the newest stamp, or None when empty."""
        return self._stamps[-1] if self._stamps else None

    def append(self, point: BasePoint) -> None:
        """Add a sample newer than every held one."""
        self._points.append(point)
        self._stamps.append(point.stamp_ns)

    def status(self, stamp_ns: int, needs_successor: bool) -> tuple[Optional[int], bool]:
        """Return (distance to the nearest held stamp or None, :meth:`ready`) in one search."""
        stamps = self._stamps
        if not stamps:
            return None, False
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
            return gap, latest >= stamp_ns
        # Differentiation uses three samples; at the start of a stream wait for them.
        return gap, latest > stamp_ns and count >= 3

    def nearest_gap_ns(self, stamp_ns: int) -> Optional[int]:
        """Return the distance to the nearest held stamp (None when empty)."""
        return self.status(stamp_ns, False)[0]

    def ready(self, stamp_ns: int, needs_successor: bool) -> bool:
        """Return whether a lookup at ``stamp_ns`` has all the samples it will use."""
        return self.status(stamp_ns, needs_successor)[1]

    def query(self, stamp_ns: int) -> Sequence[float]:
        """
        Return pose7 and body twist at ``stamp_ns`` as one row of 13 values.

        The buffer must not be empty. At a held stamp with Odometry the held row
        itself is returned: do not modify it.
        """
        points, stamps = self._points, self._stamps
        index = bisect_left(stamps, stamp_ns)
        if index < len(stamps) and stamps[index] == stamp_ns and len(points[index].row) > 7:
            return points[index].row
        if len(points[0].row) > 7:
            return self._interpolate(index, stamp_ns)
        return self._differentiate(index, stamp_ns)

    def _interpolate(self, index: int, stamp_ns: int) -> np.ndarray:
        points = self._points
        if index <= 0 or index >= len(points):
            edge = points[0] if index <= 0 else points[-1]
            dt = (stamp_ns - edge.stamp_ns) * 1e-9
            return _row(edge.pose * pin.exp6(edge.twist * dt), edge.twist)
        a, b = points[index - 1], points[index]
        s = (stamp_ns - a.stamp_ns) / (b.stamp_ns - a.stamp_ns)
        delta = pin.log6(a.pose.inverse() * b.pose).vector
        return _row(a.pose * pin.exp6(s * delta), (1 - s) * a.twist + s * b.twist)

    def _differentiate(self, index: int, stamp_ns: int) -> np.ndarray:
        points = self._points
        count = len(points)
        if count == 1:
            return np.concatenate((points[0].pose7, np.zeros(6)))
        # The three samples around the nearest one.
        stamps = self._stamps
        nearest = min((i for i in (index - 1, index) if 0 <= i < count),
                      key=lambda i: abs(stamps[i] - stamp_ns))
        centre = min(max(nearest, 1), count - 2)
        if count == 2:
            a, b = points[0], points[1]
            delta = pin.log6(a.pose.inverse() * b.pose).vector
            rate = delta / ((b.stamp_ns - a.stamp_ns) * 1e-9)
            s = (stamp_ns - a.stamp_ns) * 1e-9
            return _row(a.pose * pin.exp6(rate * s), pin.Jexp6(rate * s) @ rate)
        mid = points[centre]
        times = np.array([(points[centre + j].stamp_ns - mid.stamp_ns) * 1e-9
                          for j in (-1, 0, 1)])
        etas = np.array([pin.log6(mid.pose.inverse() * points[centre + j].pose).vector
                         for j in (-1, 0, 1)])
        tau = (stamp_ns - mid.stamp_ns) * 1e-9
        t0, t1, t2 = times
        # Lagrange basis values and derivatives at tau.
        weights = np.array([(tau - t1) * (tau - t2) / ((t0 - t1) * (t0 - t2)),
                            (tau - t0) * (tau - t2) / ((t1 - t0) * (t1 - t2)),
                            (tau - t0) * (tau - t1) / ((t2 - t0) * (t2 - t1))])
        slopes = np.array([(2 * tau - t1 - t2) / ((t0 - t1) * (t0 - t2)),
                           (2 * tau - t0 - t2) / ((t1 - t0) * (t1 - t2)),
                           (2 * tau - t0 - t1) / ((t2 - t0) * (t2 - t1))])
        eta = weights @ etas
        eta_dot = slopes @ etas
        return _row(mid.pose * pin.exp6(eta), pin.Jexp6(eta) @ eta_dot)
