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
Prescribed shape paths q(t): a planned joint trajectory, or held joint velocities.

:class:`PlannedPath` interpolates waypoints as ros2_controllers'
joint_trajectory_controller does (``Trajectory::interpolate_between_points``):
quintic between points that carry positions, velocities and accelerations,
cubic with positions and velocities, linear with positions only; before its
first point the path is joined from a given start state (the controller joins
it from the state it had when the trajectory arrived), after its last point
the last positions are held. Times are seconds from the path's origin.
"""

from __future__ import annotations

from typing import Optional

import numpy as np


class PlannedPath:
    """
    Piecewise-polynomial shape path through waypoints (joint_trajectory_controller rules).

    ``times`` (K,) strictly increasing seconds; ``positions`` (K, m);
    ``velocities`` / ``accelerations`` (K, m) or None. With ``start`` =
    (t0, q0, qd0) and t0 before the first waypoint, a first segment joins the
    start state to it (cubic, as the controller joins its current state, which has no
    accelerations; linear when the plan has no velocities). After the last waypoint
    its positions are held at zero velocity (the controller holds them).
    """

    def __init__(self, times: np.ndarray, positions: np.ndarray,
                 velocities: Optional[np.ndarray] = None,
                 accelerations: Optional[np.ndarray] = None,
                 start: Optional[tuple[float, np.ndarray, np.ndarray]] = None) -> None:
        """Precompute one polynomial per segment (coefficients in the local time)."""
        times = np.asarray(times, dtype=float)
        positions = np.atleast_2d(np.asarray(positions, dtype=float))
        if times.ndim != 1 or times.size == 0 or positions.shape[0] != times.size:
            raise ValueError('a planned path needs one time per waypoint')
        if np.any(np.diff(times) <= 0.0):
            raise ValueError('waypoint times must be strictly increasing')
        if not np.all(np.isfinite(positions)) or not np.all(np.isfinite(times)):
            raise ValueError('waypoints must be finite')
        m = positions.shape[1]
        has_velocity = velocities is not None
        has_acceleration = has_velocity and accelerations is not None
        vel = np.asarray(velocities, dtype=float).reshape(times.size, m) if has_velocity \
            else None
        acc = np.asarray(accelerations, dtype=float).reshape(times.size, m) \
            if has_acceleration else None
        joined = start is not None and start[0] < times[0]
        if joined:
            t0, q0, qd0 = start
            times = np.concatenate([[t0], times])
            positions = np.vstack([q0, positions])
            if has_velocity:
                vel = np.vstack([qd0, vel])
            if has_acceleration:
                acc = np.vstack([np.zeros(m), acc])
        self.times = times
        self.m = m
        self.interpolation = 'quintic' if has_acceleration else \
            'cubic' if has_velocity else 'linear'
        self._last = positions[-1].copy()
        # coefficients[i] (6, m): q(t) = sum_j c[j] s^j with s = t - times[i].
        count = max(times.size - 1, 0)
        coefficients = np.zeros((count, 6, m))
        for i in range(count):
            h = times[i + 1] - times[i]
            p0, p1 = positions[i], positions[i + 1]
            if has_acceleration and not (joined and i == 0):
                coefficients[i] = _quintic(p0, vel[i], acc[i], p1, vel[i + 1], acc[i + 1], h)
            elif has_velocity:
                # Also the join from a measured state, which has no accelerations: the
                # controller interpolates that segment as a cubic too.
                coefficients[i, :4] = _cubic(p0, vel[i], p1, vel[i + 1], h)
            else:
                coefficients[i, 0] = p0
                coefficients[i, 1] = (p1 - p0) / h
        self._coefficients = coefficients
        self._first = positions[0].copy()

    @property
    def breakpoints(self) -> np.ndarray:
        """Return the waypoint times, where the path's derivatives may jump."""
        return self.times

    @property
    def end(self) -> float:
        """Return the time of the last waypoint."""
        return float(self.times[-1])

    def __call__(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Return q(t), q_dot(t), q_ddot(t) (at a knot: the limit from the right)."""
        times = self.times
        if t > times[-1] or not len(self._coefficients):
            zero = np.zeros(self.m)
            return (self._last if t >= times[-1] else self._first).copy(), zero, zero.copy()
        if t <= times[0]:
            i = 0
        else:
            i = min(int(np.searchsorted(times, t, side='right')) - 1, len(times) - 2)
        return self._segment(i, max(t - times[i], 0.0))

    def velocity_limits(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Return q_dot just before and just after ``t`` (they differ at some knots)."""
        times = self.times
        right = self(t)[1]
        if t <= times[0] or not len(self._coefficients):
            return right, right
        i = int(np.searchsorted(times, t, side='left')) - 1
        i = min(i, len(times) - 2)
        return self._segment(i, t - times[i])[1], right

    def _segment(self, i: int, s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        c = self._coefficients[i]
        q = c[0] + s * (c[1] + s * (c[2] + s * (c[3] + s * (c[4] + s * c[5]))))
        qd = c[1] + s * (2.0 * c[2] + s * (3.0 * c[3] + s * (4.0 * c[4] + s * 5.0 * c[5])))
        qdd = 2.0 * c[2] + s * (6.0 * c[3] + s * (12.0 * c[4] + s * 20.0 * c[5]))
        return q, qd, qdd


def _cubic(p0: np.ndarray, v0: np.ndarray, p1: np.ndarray, v1: np.ndarray,
           h: float) -> np.ndarray:
    """Return the coefficients of the cubic with these end positions and velocities."""
    h2 = h * h
    return np.array([p0, v0,
                     (-3.0 * p0 + 3.0 * p1 - 2.0 * v0 * h - v1 * h) / h2,
                     (2.0 * p0 - 2.0 * p1 + v0 * h + v1 * h) / (h2 * h)])


def _quintic(p0: np.ndarray, v0: np.ndarray, a0: np.ndarray, p1: np.ndarray,
             v1: np.ndarray, a1: np.ndarray, h: float) -> np.ndarray:
    """Return the coefficients of the quintic with these end positions, rates, accelerations."""
    h2, h3 = h * h, h * h * h
    return np.array([
        p0, v0, 0.5 * a0,
        (-20.0 * p0 + 20.0 * p1 - 3.0 * a0 * h2 + a1 * h2 - 12.0 * v0 * h - 8.0 * v1 * h)
        / (2.0 * h3),
        (30.0 * p0 - 30.0 * p1 + 3.0 * a0 * h2 - 2.0 * a1 * h2 + 16.0 * v0 * h + 14.0 * v1 * h)
        / (2.0 * h3 * h),
        (-12.0 * p0 + 12.0 * p1 - a0 * h2 + a1 * h2 - 6.0 * v0 * h - 6.0 * v1 * h)
        / (2.0 * h3 * h2)])


class HeldVelocityPath:
    """q(t) = q0 + q_dot0 (t - t0): the shape keeps its current joint velocities."""

    def __init__(self, t0: float, q0: np.ndarray, qd0: np.ndarray) -> None:
        """Hold ``qd0`` from state ``q0`` at time ``t0``."""
        self.t0 = float(t0)
        self.q0 = np.asarray(q0, dtype=float).copy()
        self.qd0 = np.asarray(qd0, dtype=float).copy()
        self._zero = np.zeros_like(self.q0)
        self.breakpoints = np.zeros(0)

    def velocity_limits(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Return q_dot before and after ``t`` (equal: the path is smooth)."""
        return self.qd0, self.qd0

    def __call__(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Return q(t), q_dot(t), q_ddot(t)."""
        return self.q0 + (t - self.t0) * self.qd0, self.qd0, self._zero
