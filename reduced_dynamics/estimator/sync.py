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
from typing import NamedTuple, Optional

import numpy as np
import pinocchio as pin


class BasePoint(NamedTuple):
    """A validated base sample: stamp, pose, body twist (None without Odometry)."""

    stamp_ns: int
    pose: pin.SE3
    twist: Optional[np.ndarray]


class BaseQuery(NamedTuple):
    """Result of a lookup: pose and body twist (6-D, linear first) at a stamp."""

    pose: pin.SE3
    twist: np.ndarray


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

    def nearest_gap_ns(self, stamp_ns: int) -> Optional[int]:
        """Return the distance to the nearest held stamp (None when empty)."""
        if not self._stamps:
            return None
        index = bisect_left(self._stamps, stamp_ns)
        gaps = [abs(self._stamps[i] - stamp_ns) for i in (index - 1, index)
                if 0 <= i < len(self._stamps)]
        return min(gaps)

    def ready(self, stamp_ns: int, needs_successor: bool) -> bool:
        """Return whether a lookup at ``stamp_ns`` has all the samples it will use."""
        latest = self.latest_ns
        if latest is None:
            return False
        if not needs_successor:
            return latest >= stamp_ns
        # Differentiation uses three samples; at the start of a stream wait for them.
        return latest > stamp_ns and len(self._stamps) >= 3

    def query(self, stamp_ns: int) -> BaseQuery:
        """Return pose and twist at ``stamp_ns`` (the buffer must not be empty)."""
        points, stamps = self._points, self._stamps
        index = bisect_left(stamps, stamp_ns)
        if index < len(stamps) and stamps[index] == stamp_ns and points[index].twist is not None:
            return BaseQuery(points[index].pose, points[index].twist)
        if points[0].twist is not None:
            return self._interpolate(index, stamp_ns)
        return self._differentiate(index, stamp_ns)

    def _interpolate(self, index: int, stamp_ns: int) -> BaseQuery:
        points = self._points
        if index <= 0 or index >= len(points):
            edge = points[0] if index <= 0 else points[-1]
            dt = (stamp_ns - edge.stamp_ns) * 1e-9
            return BaseQuery(edge.pose * pin.exp6(edge.twist * dt), edge.twist)
        a, b = points[index - 1], points[index]
        s = (stamp_ns - a.stamp_ns) / (b.stamp_ns - a.stamp_ns)
        delta = pin.log6(a.pose.inverse() * b.pose).vector
        return BaseQuery(a.pose * pin.exp6(s * delta), (1 - s) * a.twist + s * b.twist)

    def _differentiate(self, index: int, stamp_ns: int) -> BaseQuery:
        points = self._points
        count = len(points)
        if count == 1:
            return BaseQuery(points[0].pose, np.zeros(6))
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
            return BaseQuery(a.pose * pin.exp6(rate * s), pin.Jexp6(rate * s) @ rate)
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
        return BaseQuery(mid.pose * pin.exp6(eta), pin.Jexp6(eta) @ eta_dot)
