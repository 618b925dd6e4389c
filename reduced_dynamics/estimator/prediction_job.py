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
A prediction by the reduced model as a job: its settings, computation and messages.

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
that runs out stops with the reason, and no messages. The predictor that starts
jobs and judges them is :mod:`.prediction`.
"""

from __future__ import annotations

from dataclasses import dataclass
import threading
from typing import Any, NamedTuple, Optional

import numpy as np
import pinocchio as pin

from reduced_dynamics.geometry.quaternion import matrices_to_xyzw
from reduced_dynamics.integrators import Budget, BudgetExceeded
from reduced_dynamics.messages.samples import PosePath, ShapePrediction
from reduced_dynamics.reduction.prescribed import attitude_angles, PrescribedReconstruction
from reduced_dynamics.reduction.reconstruction import ReducedPropagator
from reduced_dynamics.reduction.second_stage import (CyclicSplit, second_stage_blocks,
                                                     SecondStagePropagator, SecondStageSystem)
from reduced_dynamics.reduction.shape_path import HeldVelocityPath, PlannedPath
from reduced_dynamics.reduction.vector_field import ReducedSystem
from reduced_dynamics.robot.model import RobotModel

NS = 1_000_000_000
PREDICTION_MODES = ('planned', 'coast', 'held_velocity', 'held_torque')
#: Modes that prescribe the shape path (the base from reconstruction alone).
PRESCRIBED_MODES = frozenset({'planned', 'held_velocity'})


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
