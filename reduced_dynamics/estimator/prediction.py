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
Predictions by the reduced model, as jobs, and their residuals against measurements.

Four modes (parameter ``prediction_mode``):

* ``planned``: the shape follows the latest planned joint trajectory
  (:class:`~reduced_dynamics.reduction.shape_path.PlannedPath`); the base
  follows from the reconstruction equation alone
  (:mod:`reduced_dynamics.reduction.prescribed`). Without a plan that covers
  the prediction's start, ``held_velocity`` stands in (reported as such).
* ``held_velocity``: the shape keeps its current joint velocities (prescribed).
* ``coast``: zero joint torques, the reduced dynamics at the current momentum.
* ``held_torque``: the estimated joint torques held (reduced dynamics;
  :mod:`.held_torque`).

A :class:`PredictionJob` holds everything a prediction needs (start state,
momentum level, plan snapshot, settings) and its own robot copy (own
Pinocchio Data), so :meth:`PredictionJob.run` may run in another thread; the
result does not depend on where or when it ran. Each job has a cost budget
(evaluations, wall time, :class:`~reduced_dynamics.integrators.Budget`); one
that runs out stops with the reason, and no messages.

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
import threading
from typing import Any, Callable, NamedTuple, Optional

import numpy as np
import pinocchio as pin

from reduced_dynamics.estimator.observations import ObservationBuffer
from reduced_dynamics.estimator.prediction_statistics import PredictionStatistics
from reduced_dynamics.geometry.quaternion import matrices_to_xyzw
from reduced_dynamics.integrators import Budget, BudgetExceeded
from reduced_dynamics.messages.samples import PosePath, ShapePrediction
from reduced_dynamics.reduction.prescribed import (attitude_angles, PrescribedReconstruction,
                                                   relative_angles)
from reduced_dynamics.reduction.lean_field import warm_up as warm_up_reduced_field
from reduced_dynamics.reduction.reconstruction import ReducedPropagator
from reduced_dynamics.reduction.second_stage import (CyclicSplit, second_stage_blocks,
                                                     SecondStagePropagator, SecondStageSystem)
from reduced_dynamics.reduction.shape_path import HeldVelocityPath, PlannedPath
from reduced_dynamics.reduction.vector_field import ReducedSystem
from reduced_dynamics.robot.model import RobotModel

NS = 1_000_000_000
_NEVER = 2 ** 63
PREDICTION_MODES = ('planned', 'coast', 'held_velocity', 'held_torque')
#: Modes that prescribe the shape path (the base from reconstruction alone).
PRESCRIBED_MODES = frozenset({'planned', 'held_velocity'})
#: Finished predictions kept (diagnostics, tests); the statistics keep the rest.
FINISHED_KEEP = 64


@dataclass(frozen=True)
class PredictionSettings:
    """What every prediction of a predictor shares (a snapshot of the configuration)."""

    horizon: float
    step: float
    integrator: str = 'dop853'
    tolerance: float = 1e-10
    max_evaluations: Optional[int] = None
    max_wall_time: Optional[float] = None
    cyclic_joints: tuple[str, ...] = ()
    world_frame: str = 'world'
    shape_names: tuple[str, ...] = ()

    def times(self) -> np.ndarray:
        """Return the predicted points' times [s] from the start."""
        count = max(1, int(round(self.horizon / self.step)))
        return np.linspace(0.0, count * self.step, count + 1)


class PredictionMessages(NamedTuple):
    """The messages of one prediction (None where the mode has none)."""

    shape: Optional[ShapePrediction]
    path: PosePath
    phase_path: Optional[PosePath]
    #: with the start's uncertainty (:mod:`.prediction_covariance`): the base at the
    #: horizon with its covariance, the 95 % ellipsoids along the path, the shape's
    #: covariance at the horizon
    horizon: Optional[Any] = None
    ellipsoids: Optional[Any] = None
    shape_covariance: Optional[Any] = None


@dataclass
class PredictionResult:
    """
    A computed prediction: sampled base poses, shape and the twist split.

    ``drift`` and ``phase`` (N, n): the base twist's parts I^-1 pi and -A qbar_dot
    at each point. ``phase_poses``: the base path under the geometric phase
    alone (prescribed modes). ``failure``: why there is no prediction.
    """

    mode: str
    times: np.ndarray
    poses: Optional[np.ndarray] = None
    qbar: Optional[np.ndarray] = None
    qbar_dot: Optional[np.ndarray] = None
    phase_poses: Optional[np.ndarray] = None
    drift: Optional[np.ndarray] = None
    phase: Optional[np.ndarray] = None
    evaluations: int = 0
    wall_time: float = 0.0
    failure: Optional[str] = None
    failure_kind: Optional[str] = None
    #: :class:`~.prediction_covariance.PredictionCovariance` (None: not asked, or failed)
    covariance: Optional[Any] = None
    covariance_failure: Optional[str] = None

    @property
    def ok(self) -> bool:
        """Whether the prediction was computed."""
        return self.failure is None

    def attitude_change(self) -> np.ndarray:
        """Return the base rotation angle [rad] from the start at each point."""
        return attitude_angles(self.poses[0, :3, :3], self.poses[:, :3, :3])

    def phase_attitude_change(self) -> Optional[np.ndarray]:
        """Return the rotation angle [rad] of the geometric phase alone at each point."""
        if self.phase_poses is None:
            return None
        return attitude_angles(self.phase_poses[0, :3, :3], self.phase_poses[:, :3, :3])


class PredictionJob:
    """
    One prediction from a captured start state; :meth:`run` computes it (thread-safe).

    ``run()`` returns the :class:`PredictionMessages` (None if the prediction
    failed or ran out of budget: see ``result.failure``). The first call
    computes, later calls (from any thread) return the same objects; the
    estimator calls it when the horizon has passed in stamp time if no one
    did. The job owns a robot copy (own Pinocchio Data): running it
    concurrently with the estimator is safe.
    """

    def __init__(self, robot: RobotModel, settings: PredictionSettings, start_ns: int,
                 g: pin.SE3, qbar: np.ndarray, qbar_dot: np.ndarray, mu: np.ndarray,
                 tau: np.ndarray, theta: Optional[np.ndarray], mode: str,
                 requested_mode: str, plan: Optional[PlannedPath] = None,
                 uncertainty: Optional[Any] = None) -> None:
        """Capture the start state (copies), the plan snapshot and its uncertainty."""
        self.robot = robot
        self.settings = settings
        self.start_ns = int(start_ns)
        self.g = pin.SE3(g)
        self.qbar = np.array(qbar, dtype=float)
        self.qbar_dot = np.array(qbar_dot, dtype=float)
        self.mu = np.array(mu, dtype=float)
        self.tau = np.array(tau, dtype=float)
        self.theta = None if theta is None else np.array(theta, dtype=float)
        self.mode = mode
        self.requested_mode = requested_mode
        self.plan = plan
        #: :class:`~.prediction_covariance.StartUncertainty` (None: no covariance)
        self.uncertainty = uncertainty
        self.times = settings.times()
        self.end_ns = self.start_ns + int(round(self.times[-1] * NS))
        self._lock = threading.Lock()
        self._done = False
        self._result: Optional[PredictionResult] = None
        self._messages: Optional[PredictionMessages] = None

    @property
    def done(self) -> bool:
        """Whether the prediction has been computed."""
        return self._done

    def run(self) -> Optional[PredictionMessages]:
        """Compute the prediction once; return its messages (None when it failed)."""
        with self._lock:
            if not self._done:
                self._result = self._compute()
                if self._result.ok:
                    self._messages = self._to_messages(self._result)
                    if self.uncertainty is not None:
                        from reduced_dynamics.estimator.prediction_covariance import \
                            with_uncertainty
                        self._messages = with_uncertainty(self, self._result, self._messages)
                self._done = True
            return self._messages

    @property
    def result(self) -> PredictionResult:
        """Return what was computed (computing it now if nobody has)."""
        self.run()
        return self._result

    # --- computation -------------------------------------------------------------------
    def _compute(self) -> PredictionResult:
        settings = self.settings
        budget = Budget(settings.max_evaluations, settings.max_wall_time)
        try:
            if self.mode in PRESCRIBED_MODES:
                result = self._prescribed(budget)
            else:
                result = self._dynamic(budget)
        except BudgetExceeded as error:
            result = PredictionResult(self.mode, self.times, failure=error.reason,
                                      failure_kind='budget')
        except (RuntimeError, ValueError, ArithmeticError, np.linalg.LinAlgError) as error:
            # A failed prediction (e.g. a singular chart) must not stop the estimates.
            result = PredictionResult(self.mode, self.times, failure=str(error),
                                      failure_kind=type(error).__name__)
        result.evaluations = budget.evaluations
        result.wall_time = budget.elapsed
        return result

    def _prescribed(self, budget: Budget) -> PredictionResult:
        path = self.plan if self.mode == 'planned' else \
            HeldVelocityPath(0.0, self.qbar, self.qbar_dot)
        times = self.times
        system = PrescribedReconstruction(self.robot, self.mu, self.g, path)
        trajectory = system.propagate(times, self.settings.tolerance, self.settings.tolerance,
                                      path.breakpoints, budget)
        shape = [path(t) for t in times]
        return PredictionResult(self.mode, times, trajectory.poses,
                                np.array([s[0] for s in shape]),
                                np.array([s[1] for s in shape]), trajectory.phase_poses,
                                trajectory.drift, trajectory.phase)

    def _dynamic(self, budget: Budget) -> PredictionResult:
        settings, robot = self.settings, self.robot
        held = np.zeros(robot.m) if self.mode == 'coast' else self.tau.copy()
        times = self.times
        if settings.cyclic_joints:
            if self.theta is None:
                raise ValueError('second-stage prediction needs the cyclic momenta theta')
            if settings.integrator != 'dop853':
                raise ValueError('the second-stage model predicts with dop853 only')
            system = SecondStageSystem(robot, settings.cyclic_joints, self.mu, self.g)
            split = system.split_indices
            blocks = second_stage_blocks(robot, split, self.qbar)
            z = np.concatenate([np.zeros(system.k), self.qbar[split.kept],
                                blocks.reduced_metric @ self.qbar_dot[split.kept],
                                self.theta])
            propagator = SecondStagePropagator(system, self.g, self.qbar[split.cyclic],
                                               lambda t, q, qd: held)
            y0 = np.concatenate([z, self.qbar[split.cyclic], np.zeros(robot.n)])
            trajectory = propagator.propagate(y0, times, settings.tolerance,
                                              settings.tolerance, budget)
            qbar, qbar_dot = trajectory.qbar, trajectory.qbar_dot
        else:
            system = ReducedSystem(robot, self.mu, self.g)
            blocks = robot.metric_blocks(self.qbar)
            z = np.concatenate([np.zeros(system.k), self.qbar,
                                blocks.reduced_metric @ self.qbar_dot])
            propagator = ReducedPropagator(system, self.g, lambda t, q, qd: held)
            y0 = np.concatenate([z, np.zeros(robot.n)])
            trajectory = propagator.propagate(y0, times, settings.integrator,
                                              settings.tolerance, settings.tolerance,
                                              settings.step, budget)
            qbar, qbar_dot = trajectory.qbar, trajectory.qbar_dot
        drift, phase = _twist_split(robot, trajectory.poses, trajectory.pi, qbar, qbar_dot)
        return PredictionResult(self.mode, times, trajectory.poses, qbar, qbar_dot, None,
                                drift, phase)

    def _to_messages(self, result: PredictionResult) -> PredictionMessages:
        settings = self.settings
        offsets = np.round(result.times * NS).astype(np.int64)
        shape = None
        if self.mode not in PRESCRIBED_MODES:
            qbar, qbar_dot = result.qbar, result.qbar_dot
            if settings.cyclic_joints:
                kept = CyclicSplit(self.robot, settings.cyclic_joints).kept
                qbar, qbar_dot = qbar[:, kept], qbar_dot[:, kept]
            shape = ShapePrediction(self.start_ns, '', settings.shape_names, offsets,
                                    qbar, qbar_dot)
        path = pose_path(self.start_ns, settings.world_frame, offsets, result.poses)
        phase = None if result.phase_poses is None else \
            pose_path(self.start_ns, settings.world_frame, offsets, result.phase_poses)
        return PredictionMessages(shape, path, phase)


def pose_path(start_ns: int, frame: str, offsets: np.ndarray, poses: np.ndarray) -> PosePath:
    quats = matrices_to_xyzw(poses[:, :3, :3])
    return PosePath(start_ns, frame, start_ns + offsets, poses[:, :3, 3], quats)


def _twist_split(robot: RobotModel, poses: np.ndarray, pi: Optional[np.ndarray],
                 qbar: np.ndarray, qbar_dot: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return the drift I^-1 pi and the geometric phase -A qbar_dot at each point."""
    n = robot.n
    drift = np.empty((len(qbar), n))
    phase = np.empty((len(qbar), n))
    for i, (q, qd) in enumerate(zip(qbar, qbar_dot)):
        mass = robot.mass_matrix(q)
        solved = np.linalg.solve(mass[:n, :n], np.column_stack([pi[i], -(mass[:n, n:] @ qd)]))
        drift[i], phase[i] = solved[:, 0], solved[:, 1]
    return drift, phase


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
