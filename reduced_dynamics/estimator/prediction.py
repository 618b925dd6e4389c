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
The predictor: starts prediction jobs and judges them against measurements.

The jobs and their four modes are :mod:`.prediction_job`; the planned
trajectory the ``planned`` mode follows is :mod:`.prediction_plan`. Both stay
importable from here (``PredictionJob``, ``PredictionSettings``, ``Plan``, ...).

Residuals are computed when a prediction's horizon has passed in stamp time,
against a history of the measured states kept for the horizon, so they do
not depend on when a deferred job finished. A judged prediction leaves its
residuals to running statistics (:mod:`.prediction_statistics`); only the last
:data:`FINISHED_KEEP` finished ones are kept, and only the last compared one
keeps its sampled paths (memory bounds: issue 27, docs/soak.md). Prescribed modes compare the
base path (position [m], attitude [rad]) and report how far the shape left
the prescribed path; torque modes compare the shape.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, replace
from typing import Any, Callable, Optional

import numpy as np
import pinocchio as pin

from reduced_dynamics.estimator.observations import ObservationBuffer
# The jobs and the plan, importable from here as before the split (issue 19 item 5).
from reduced_dynamics.estimator.prediction_job import (  # noqa: F401
    _twist_split, NS, pose_path, PREDICTION_MODES, PredictionJob, PredictionMessages,
    PredictionResult, PredictionSettings, PRESCRIBED_MODES)
from reduced_dynamics.estimator.prediction_plan import Plan  # noqa: F401
from reduced_dynamics.estimator.prediction_statistics import PredictionStatistics
from reduced_dynamics.reduction.lean_field import warm_up as warm_up_reduced_field
from reduced_dynamics.reduction.prescribed import relative_angles
from reduced_dynamics.reduction.second_stage import CyclicSplit
from reduced_dynamics.robot.model import RobotModel

_NEVER = 2 ** 63
#: Finished predictions kept (diagnostics, tests); the statistics keep the rest.
FINISHED_KEEP = 64


@dataclass
class FinishedPrediction:
    """A prediction whose horizon has passed, with its residuals against measurements."""

    start_ns: int
    mode: str
    requested_mode: str
    result: PredictionResult
    compared: int = 0
    shape_residual: float = 0.0
    position_residual: float = 0.0
    attitude_residual: float = 0.0
    at_points: bool = True

    @property
    def failure(self) -> Optional[str]:
        """Return why the prediction was not computed (None if it was)."""
        return self.result.failure


class Predictor:
    """
    Starts prediction jobs and tracks their residuals against measured history.

    With ``cyclic_joints`` the torque modes predict by the second stage
    (Theorem 57): their predicted and compared shape is that of the kept
    joints only. The prescribed modes always reconstruct with the full shape.
    """

    def __init__(self, robot: RobotModel, horizon: float, step: float, integrator: str,
                 tolerance: float, cyclic_joints: tuple[str, ...] = (),
                 mode: str = 'held_torque', max_evaluations: Optional[int] = None,
                 max_wall_time: Optional[float] = None, world_frame: str = 'world',
                 shape_names: Optional[tuple[str, ...]] = None) -> None:
        """Predict over ``horizon`` seconds with points every ``step`` seconds."""
        if mode not in PREDICTION_MODES:
            raise ValueError(f'unknown prediction mode {mode!r}; choose from {PREDICTION_MODES}')
        self.robot = robot
        self.cyclic_joints = tuple(cyclic_joints)
        self.kept: Optional[np.ndarray] = None
        if self.cyclic_joints:
            self.kept = CyclicSplit(robot, self.cyclic_joints).kept
        names = shape_names if shape_names is not None else tuple(
            robot.shape_joint_names[i] for i in (self.kept if self.kept is not None
                                                 else range(robot.m)))
        # A wall-time budget of 0 is none (offline runs: the evaluations alone decide).
        self.settings = PredictionSettings(horizon, step, integrator, tolerance,
                                           max_evaluations, max_wall_time or None,
                                           self.cyclic_joints, world_frame, tuple(names))
        self.mode = mode
        self.horizon = horizon
        self.step = step
        # Modes that integrate the reduced dynamics: load its compiled right-hand side
        # now, not inside the first prediction's wall-time budget.
        if mode not in PRESCRIBED_MODES and not self.cyclic_joints:
            warm_up_reduced_field()
        #: open predictions: at most horizon x prediction_rate (+1)
        self.active: list[PredictionJob] = []
        #: the last FINISHED_KEEP finished predictions (the statistics keep the rest)
        self.finished: deque[FinishedPrediction] = deque(maxlen=FINISHED_KEEP)
        self.statistics = PredictionStatistics(PRESCRIBED_MODES)
        #: called with each finished prediction (e.g. replay's residual plot)
        self.on_finished: Optional[Callable[[FinishedPrediction], None]] = None
        self.made = 0
        self.plan: Optional['Plan'] = None
        self._history = ObservationBuffer()
        self._inline_robot: Optional[RobotModel] = None
        # The first stamp at which an active prediction's horizon has passed, and the
        # next stamp at which the history is trimmed (per-sample work stays O(1)).
        self._next_end = _NEVER
        self._trim_at = -1
        # Finished predictions keep their sampled paths only while they are the last
        # compared one (diagnostics read it): a node or replay of hours holds one.
        self._kept: Optional[FinishedPrediction] = None

    def adopt(self, old: 'Predictor') -> None:
        """Take over another predictor's open jobs, results, history and plan."""
        self.active, self.finished, self.made = old.active, old.finished, old.made
        self.statistics, self.on_finished = old.statistics, old.on_finished
        self._kept = old._kept
        self.plan, self._history = old.plan, old._history
        self._next_end, self._trim_at = old._next_end, old._trim_at

    # --- starting predictions -----------------------------------------------------------
    def predict(self, stamp_ns: int, g: pin.SE3, qbar: np.ndarray, qbar_dot: np.ndarray,
                mu: np.ndarray, tau: np.ndarray, theta: Optional[np.ndarray] = None,
                deferred: bool = False, uncertainty: Optional[Any] = None) -> PredictionJob:
        """
        Start a prediction from a measured state at momentum level ``mu``.

        Returns the job, already run unless ``deferred``; it is tracked for the
        residual either way. ``theta``: the cyclic momenta (second stage).
        ``uncertainty``: the start's (:mod:`.prediction_covariance`), for a covariance.
        """
        mode, plan = self.mode, None
        if mode == 'planned':
            plan = None if self.plan is None else self.plan.path_from(stamp_ns, qbar, qbar_dot)
            if plan is None:
                mode = 'held_velocity'
        if deferred:
            robot = self.robot.worker_copy()
        else:
            if self._inline_robot is None:
                self._inline_robot = self.robot.worker_copy()
            robot = self._inline_robot
        job = PredictionJob(robot, self.settings, stamp_ns, g, qbar, qbar_dot, mu, tau, theta,
                            mode, self.mode, plan, uncertainty)
        if not deferred:
            job.run()
        self.active.append(job)
        self._next_end = min(self._next_end, job.end_ns)
        self.made += 1
        return job

    def set_plan(self, plan: 'Plan') -> None:
        """Adopt a new planned trajectory (it replaces the previous one)."""
        self.plan = plan

    # --- residuals -----------------------------------------------------------------------
    def observe(self, stamp_ns: int, qbar: np.ndarray, translation: np.ndarray,
                rotation: np.ndarray) -> None:
        """Record a measured state; close the predictions whose horizon has passed."""
        # Hot path (every sample): two comparisons unless a horizon has passed.
        if stamp_ns > self._next_end:
            still = []
            for job in self.active:
                if stamp_ns > job.end_ns:
                    self._close(job)
                else:
                    still.append(job)
            self.active = still
            self._next_end = min((job.end_ns for job in still), default=_NEVER)
        history = self._history
        history.append(stamp_ns, qbar, translation, rotation)
        if stamp_ns > self._trim_at:
            oldest = min((job.start_ns for job in self.active), default=None)
            keep_from = stamp_ns - int(self.horizon * NS) if oldest is None else oldest
            history.trim(keep_from - 1)
            self._trim_at = stamp_ns + NS

    def finish(self) -> None:
        """Close every active prediction against the history so far (end of input)."""
        for job in self.active:
            self._close(job)
        self.active = []
        self._next_end = _NEVER

    def forget_history(self) -> None:
        """Drop the measured history (the clock restarted)."""
        self._history = ObservationBuffer()
        self._trim_at = -1

    def _close(self, job: PredictionJob) -> None:
        try:
            self._compare(job)
        finally:
            self._thin()
        done = self.finished[-1]
        self.statistics.add(done)
        if self.on_finished is not None:
            self.on_finished(done)

    def _thin(self) -> None:
        """Drop the sampled paths of finished predictions but the last compared one."""
        done = self.finished[-1]
        if not done.compared:
            done.result = _summary_only(done.result)
            return
        if self._kept is not None and self._kept is not done:
            self._kept.result = _summary_only(self._kept.result)
        self._kept = done

    def _compare(self, job: PredictionJob) -> None:
        """Record ``job`` as finished, with its residuals against the measured history."""
        result = job.result
        done = FinishedPrediction(job.start_ns, job.mode, job.requested_mode, result)
        self.finished.append(done)
        if not result.ok:
            return
        stamps, qbar, translation, rotation = self._history.window(job.start_ns, job.end_ns)
        if qbar is None:
            return
        t = (stamps - job.start_ns) * 1e-9
        times = result.times
        index = np.clip(np.rint(t / (times[1] - times[0])).astype(int), 0, len(times) - 1)
        at = np.abs(times[index] - t) <= 1e-4
        if at.any():
            index, qbar, translation, rotation = index[at], qbar[at], translation[at], \
                rotation[at]
            predicted_q = result.qbar[index]
            poses = result.poses[index]
        else:
            done.at_points = False
            predicted_q, poses = _interpolate(result, t)
        if self.kept is not None and job.mode not in PRESCRIBED_MODES:
            # The second stage predicts the kept joints; the wheels follow from theta.
            qbar, predicted_q = qbar[:, self.kept], predicted_q[:, self.kept]
        done.compared = len(qbar)
        done.shape_residual = float(np.max(np.abs(predicted_q - qbar))) if qbar.size else 0.0
        done.position_residual = float(np.max(np.linalg.norm(poses[:, :3, 3] - translation,
                                                             axis=1)))
        done.attitude_residual = float(np.max(relative_angles(poses[:, :3, :3], rotation)))

    @property
    def last_finished(self) -> Optional[FinishedPrediction]:
        """Return the most recently closed prediction that was compared."""
        return self._kept

    @property
    def last_residual(self) -> Optional[float]:
        """Return the shape residual of the most recently finished prediction."""
        done = self.last_finished
        return None if done is None else done.shape_residual


def _summary_only(result: PredictionResult) -> PredictionResult:
    """Return ``result`` without its sampled paths (mode, cost and failure stay)."""
    return replace(result, times=result.times[:0].copy(), poses=None, qbar=None,
                   qbar_dot=None, phase_poses=None, drift=None, phase=None, covariance=None)


def _interpolate(result: PredictionResult, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Predicted shape (cubic Hermite) and poses (SE(3) geodesic) between points."""
    times = result.times
    i = np.clip(np.searchsorted(times, t) - 1, 0, len(times) - 2)
    h = times[i + 1] - times[i]
    s = ((t - times[i]) / h)[:, None]
    h00, h10 = 2 * s**3 - 3 * s**2 + 1, s**3 - 2 * s**2 + s
    h01, h11 = -2 * s**3 + 3 * s**2, s**3 - s**2
    q, qd = result.qbar, result.qbar_dot
    shape = h00 * q[i] + h10 * h[:, None] * qd[i] + h01 * q[i + 1] + h11 * h[:, None] * qd[i + 1]
    poses = np.array([pin.SE3.Interpolate(pin.SE3(result.poses[a]), pin.SE3(result.poses[a + 1]),
                                          float(u)).homogeneous for a, u in zip(i, s[:, 0])])
    return shape, poses
