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


"""The latest planned joint trajectory, and the shape path it prescribes from a stamp on."""

from __future__ import annotations

from typing import Optional

import numpy as np

from reduced_dynamics.reduction.shape_path import PlannedPath


class Plan:
    """
    The latest planned joint trajectory, in model joint order, with absolute times.

    ``start_ns``: the trajectory's header stamp (the time its
    ``time_from_start`` counts from). ``index``: for each planned joint, its
    shape index; joints the plan leaves out keep their velocities over it.
    """

    def __init__(self, start_ns: int, index: np.ndarray, times_ns: np.ndarray,
                 positions: np.ndarray, velocities: Optional[np.ndarray],
                 accelerations: Optional[np.ndarray], m: int) -> None:
        """Hold the waypoints (already validated)."""
        self.start_ns = int(start_ns)
        self.index = np.asarray(index, dtype=int)
        self.times_ns = np.asarray(times_ns, dtype=np.int64)
        self.positions = positions
        self.velocities = velocities
        self.accelerations = accelerations
        self.m = m

    @property
    def end_ns(self) -> int:
        """Return the absolute time of the last waypoint."""
        return self.start_ns + int(self.times_ns[-1])

    def path_from(self, stamp_ns: int, qbar: np.ndarray,
                  qbar_dot: np.ndarray) -> Optional[PlannedPath]:
        """
        Return the shape path from ``stamp_ns`` on (time 0 there), or None when done.

        A plan whose last waypoint is not after ``stamp_ns`` is over (the arm
        rests at its end): None, and the caller falls back to held velocities.
        Joints outside the plan move on at their current velocities.
        """
        if self.end_ns <= stamp_ns:
            return None
        times = (self.start_ns + self.times_ns - stamp_ns) * 1e-9
        count = len(times)
        full_q = qbar[None, :] + times[:, None] * qbar_dot[None, :]
        full_q[:, self.index] = self.positions
        full_v = full_a = None
        if self.velocities is not None:
            full_v = np.repeat(qbar_dot[None, :], count, axis=0)
            full_v[:, self.index] = self.velocities
            if self.accelerations is not None:
                full_a = np.zeros((count, self.m))
                full_a[:, self.index] = self.accelerations
        return PlannedPath(times, full_q, full_v, full_a, start=(0.0, qbar, qbar_dot))
