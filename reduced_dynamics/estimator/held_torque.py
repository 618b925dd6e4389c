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
The held joint torques of ``prediction_mode: held_torque``: an estimate, not a sample.

A measured effort is the applied torque plus noise of standard deviation
``r = joint_effort_noise``; held for a horizon and integrated twice through
light links, one sample's noise is the whole prediction error (issue 26: 5.5 rad
median over 2 s at 0.05 N m). Per joint, a local-level Kalman filter estimates
the torque instead::

    tau_k = tau_{k-1} + eta,   eta ~ N(0, q dt),   q = r^2 dt / T^2
    y_k   = tau_k + eps,       eps ~ N(0, r^2)

With the process density tied to the sample period dt and the follow time T
(``held_torque_follow_time``), the steady-state gain is about dt / T: an
exponential mean over the last T seconds. Its variance is about ``r^2 dt / T``
(the error under the random-walk model; a torque that stays constant is known
twice as well, ``r^2 dt / (2 T)``).
A torque step much larger than that variance (a controller switching) is
caught by a two-sided CUSUM test on the normalised innovations (Page 1954;
drift 0.5, threshold ``CUSUM_THRESHOLD``): the estimate restarts from the
latest effort with one sample's variance, and the filter's gains then average
the efforts since the change (a recursive mean). The covariance (diagonal) goes with the estimate
into the prediction's uncertainty (:mod:`.prediction_covariance`).
"""

from __future__ import annotations

from typing import Optional

import numpy as np

#: CUSUM threshold on normalised innovations (drift 0.5): a mean run length of
#: ~10^5 samples without a change, a one-sigma step found in ~10 samples.
CUSUM_THRESHOLD = 10.0
CUSUM_DRIFT = 0.5


class HeldTorqueEstimator:
    """Local-level Kalman filter with a CUSUM change test, per joint (module docstring)."""

    def __init__(self, m: int, effort_noise: float, follow_time: float) -> None:
        """Estimate m torques; ``effort_noise`` [N m], ``follow_time`` T [s]."""
        self.m = m
        self.r = max(float(effort_noise), 1e-12) ** 2
        self.follow_time = float(follow_time)
        self.estimate: Optional[np.ndarray] = None
        self.variance = np.zeros(m)
        self.stamp_ns: Optional[int] = None
        self.changes = 0
        self._up = np.zeros(m)
        self._down = np.zeros(m)

    @property
    def covariance(self) -> np.ndarray:
        """Return the covariance of the estimate (m x m, diagonal)."""
        return np.diag(self.variance)

    def update(self, stamp_ns: int, effort: np.ndarray) -> None:
        """Take one measured effort vector at ``stamp_ns``."""
        effort = np.asarray(effort, dtype=float)
        if not np.isfinite(effort).all():
            return
        if self.estimate is None:
            self.estimate = effort.copy()
            self.variance = np.full(self.m, self.r)
            self.stamp_ns = stamp_ns
            return
        dt = max(stamp_ns - self.stamp_ns, 0) * 1e-9
        self.stamp_ns = stamp_ns
        prior = self.variance + self.r * (dt / self.follow_time) ** 2
        innovation = effort - self.estimate
        scale = np.sqrt(prior + self.r)
        z = innovation / scale
        # Two-sided CUSUM of the normalised innovations.
        self._up = np.maximum(self._up + z - CUSUM_DRIFT, 0.0)
        self._down = np.maximum(self._down - z - CUSUM_DRIFT, 0.0)
        gain = prior / (prior + self.r)
        self.estimate = self.estimate + gain * innovation
        self.variance = (1.0 - gain) * prior
        alarm = (self._up > CUSUM_THRESHOLD) | (self._down > CUSUM_THRESHOLD)
        if alarm.any():
            # Restart at the change: the latest effort, one sample's variance; the filter's
            # gains then make a recursive mean of the efforts since.
            self.changes += int(alarm.sum())
            self.estimate[alarm] = effort[alarm]
            self.variance[alarm] = self.r
            self._reset(alarm)

    def _reset(self, joints: np.ndarray) -> None:
        self._up[joints] = 0.0
        self._down[joints] = 0.0
