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
Prediction by the reduced model and its residual against what was then measured.

From a measured state, the reduced system at the current momentum level is
propagated over the horizon with the measured joint torques held, and the
base pose is reconstructed. Each later sample inside a prediction's horizon
is compared with it (cubic Hermite interpolation of the predicted shape), so
the residual measures model drift: unmodelled torques, external wrenches,
and (with noise) measurement error.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import numpy as np
import pinocchio as pin

from reduced_dynamics.reduction.reconstruction import ReducedPropagator
from reduced_dynamics.reduction.second_stage import (CyclicSplit, second_stage_blocks,
                                                     SecondStagePropagator, SecondStageSystem)
from reduced_dynamics.reduction.vector_field import ReducedSystem
from reduced_dynamics.robot.model import RobotModel


@dataclass
class Prediction:
    """A predicted trajectory and its running comparison with measurements."""

    start_ns: int
    times: np.ndarray
    qbar: np.ndarray
    qbar_dot: np.ndarray
    poses: np.ndarray
    at_points: list = field(default_factory=lambda: [0.0, 0.0, 0])
    between_points: list = field(default_factory=lambda: [0.0, 0.0, 0])

    @property
    def compared(self) -> int:
        """Return how many measurements were compared with this prediction."""
        return self.at_points[2] + self.between_points[2]

    @property
    def _residuals(self) -> list:
        # Measurements at predicted points are exact comparisons; interpolated
        # ones are used only when no measurement fell on a point.
        return self.at_points if self.at_points[2] else self.between_points

    @property
    def shape_residual(self) -> float:
        """Return the largest shape error [rad or m] seen over the horizon."""
        return self._residuals[0]

    @property
    def position_residual(self) -> float:
        """Return the largest base position error [m] seen over the horizon."""
        return self._residuals[1]

    @property
    def end_ns(self) -> int:
        """Return the stamp of the last predicted point."""
        return self.start_ns + int(round(self.times[-1] * 1e9))

    def shape_at(self, stamp_ns: int) -> np.ndarray:
        """
        Return the predicted shape at a stamp inside the horizon.

        At a predicted point (within 0.1 ms) the point itself; between points a
        cubic Hermite interpolation, whose error (h^4 / 384 times the fourth
        derivative) adds to the residual: choose a small step for fast motions.
        """
        t = (stamp_ns - self.start_ns) * 1e-9
        nearest = self.point_index(stamp_ns)
        if nearest is not None:
            return self.qbar[nearest]
        i = int(np.clip(np.searchsorted(self.times, t) - 1, 0, len(self.times) - 2))
        h = self.times[i + 1] - self.times[i]
        s = (t - self.times[i]) / h
        h00, h10 = 2 * s**3 - 3 * s**2 + 1, s**3 - 2 * s**2 + s
        h01, h11 = -2 * s**3 + 3 * s**2, s**3 - s**2
        return h00 * self.qbar[i] + h10 * h * self.qbar_dot[i] + h01 * self.qbar[i + 1] \
            + h11 * h * self.qbar_dot[i + 1]

    def point_index(self, stamp_ns: int) -> Optional[int]:
        """Return the index of the predicted point at this stamp (within 0.1 ms), if any."""
        t = (stamp_ns - self.start_ns) * 1e-9
        nearest = int(np.clip(np.rint(t / (self.times[1] - self.times[0])), 0,
                              len(self.times) - 1))
        return nearest if abs(self.times[nearest] - t) <= 1e-4 else None

    def record(self, stamp_ns: int, shape_error: float, position_error: float) -> None:
        """Fold one comparison into the residuals."""
        bucket = self.at_points if self.point_index(stamp_ns) is not None \
            else self.between_points
        bucket[0] = max(bucket[0], shape_error)
        bucket[1] = max(bucket[1], position_error)
        bucket[2] += 1

    def position_at(self, stamp_ns: int) -> np.ndarray:
        """Return the predicted base position at a stamp (linear between points)."""
        t = (stamp_ns - self.start_ns) * 1e-9
        return np.array([np.interp(t, self.times, self.poses[:, axis, 3]) for axis in range(3)])


class Predictor:
    """
    Runs predictions and tracks their residuals.

    With ``cyclic_joints`` the second-stage model (Theorem 57) predicts: the
    predicted and compared shape is then that of the kept joints only.
    """

    def __init__(self, robot: RobotModel, horizon: float, step: float, integrator: str,
                 tolerance: float, cyclic_joints: tuple[str, ...] = ()) -> None:
        """Predict over ``horizon`` seconds with points every ``step`` seconds."""
        self.robot = robot
        self.cyclic_joints = tuple(cyclic_joints)
        self.kept: Optional[np.ndarray] = None
        if self.cyclic_joints:
            self.kept = CyclicSplit(robot, self.cyclic_joints).kept
        self.horizon = horizon
        self.step = step
        self.integrator = integrator
        self.tolerance = tolerance
        self.active: list[Prediction] = []
        self.finished: list[Prediction] = []
        self.made = 0

    def predict(self, stamp_ns: int, g: pin.SE3, qbar: np.ndarray, qbar_dot: np.ndarray,
                mu: np.ndarray, tau: np.ndarray,
                theta: Optional[np.ndarray] = None) -> Prediction:
        """
        Predict from a measured shape state and base pose at momentum level ``mu``.

        ``theta``: the cyclic momenta, needed when predicting by the second stage.
        """
        count = max(1, int(round(self.horizon / self.step)))
        times = np.linspace(0.0, count * self.step, count + 1)
        if self.cyclic_joints:
            return self._predict_second_stage(stamp_ns, times, g, qbar, qbar_dot, mu, tau,
                                              theta)
        system = ReducedSystem(self.robot, mu, g)
        blocks = self.robot.metric_blocks(qbar)
        z = np.concatenate([np.zeros(system.k), qbar, blocks.reduced_metric @ qbar_dot])
        held = np.array(tau, dtype=float)
        propagator = ReducedPropagator(system, g, lambda t, q, qd: held)
        y0 = np.concatenate([z, np.zeros(self.robot.n)])
        trajectory = propagator.propagate(y0, times, self.integrator, self.tolerance,
                                          self.tolerance, self.step)
        prediction = Prediction(stamp_ns, times, trajectory.qbar, trajectory.qbar_dot,
                                trajectory.poses)
        self.active.append(prediction)
        self.made += 1
        return prediction

    def _predict_second_stage(self, stamp_ns: int, times: np.ndarray, g: pin.SE3,
                              qbar: np.ndarray, qbar_dot: np.ndarray, mu: np.ndarray,
                              tau: np.ndarray, theta: Optional[np.ndarray]) -> Prediction:
        if theta is None:
            raise ValueError('second-stage prediction needs the cyclic momenta theta')
        if self.integrator != 'dop853':
            raise ValueError('the second-stage model predicts with dop853 only')
        system = SecondStageSystem(self.robot, self.cyclic_joints, mu, g)
        split = system.split_indices
        blocks = second_stage_blocks(self.robot, split, qbar)
        z = np.concatenate([np.zeros(system.k), qbar[split.kept],
                            blocks.reduced_metric @ qbar_dot[split.kept], theta])
        held = np.array(tau, dtype=float)
        propagator = SecondStagePropagator(system, g, qbar[split.cyclic],
                                           lambda t, q, qd: held)
        y0 = np.concatenate([z, qbar[split.cyclic], np.zeros(self.robot.n)])
        trajectory = propagator.propagate(y0, times, self.tolerance, self.tolerance)
        prediction = Prediction(stamp_ns, times, trajectory.qbar[:, split.kept],
                                trajectory.qbar_dot[:, split.kept], trajectory.poses)
        self.active.append(prediction)
        self.made += 1
        return prediction

    def compare(self, stamp_ns: int, qbar: np.ndarray, g: pin.SE3) -> list[Prediction]:
        """Compare a measurement with active predictions; return the ones that expired."""
        if self.kept is not None:
            qbar = qbar[self.kept]
        expired = []
        still = []
        for prediction in self.active:
            if stamp_ns > prediction.end_ns:
                expired.append(prediction)
                continue
            still.append(prediction)
            if stamp_ns <= prediction.start_ns:
                continue
            error = float(np.max(np.abs(prediction.shape_at(stamp_ns) - qbar))) \
                if qbar.size else 0.0
            position = float(np.linalg.norm(prediction.position_at(stamp_ns) - g.translation))
            prediction.record(stamp_ns, error, position)
        self.active = still
        self.finished.extend(expired)
        return expired

    def finish(self) -> None:
        """Close every active prediction (end of input)."""
        self.finished.extend(self.active)
        self.active = []

    @property
    def last_residual(self) -> Optional[float]:
        """Return the shape residual of the most recently finished prediction."""
        done = [p for p in self.finished if p.compared]
        return done[-1].shape_residual if done else None
