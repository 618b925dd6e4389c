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
Predictions from the filter's rows: the measured history, and where one starts.

Part of :class:`~.pipeline.Estimator` through :class:`~.processing.ChunkProcessing`
(its state is set up there). After the filter's pass over a chunk
(:mod:`.processing`), each row adds to the measured history of the prediction
residuals, and a prediction (:mod:`.prediction`) starts from the filter's pose
and momentum where one is due and no event is under way; also the base-motion
answer for a plan (``predict_base_motion``).
"""

from __future__ import annotations

from typing import Optional

import numpy as np
import pinocchio as pin

from reduced_dynamics.estimator.base_motion import BaseMotionAnswer, predict_base_motion
from reduced_dynamics.estimator.cyclic import CyclicColumns
from reduced_dynamics.estimator.prediction import PredictionMessages
from reduced_dynamics.estimator.prediction_covariance import StartUncertainty
from reduced_dynamics.messages.samples import JointTrajectorySample

NS = 1_000_000_000


class RowPredictions:
    """
    Predictions started from a chunk's rows (a part of :class:`~.pipeline.Estimator`).

    ``_per_sample`` records each row's measured history and starts predictions
    where they are due; the filter's chunk (:mod:`.processing`) calls it.
    """

    def _per_sample(self, stamp_list: tuple, qbar: np.ndarray, qbar_dot: np.ndarray,
                    taus: tuple, result, extras: dict, rejected_at: int,
                    cyclic: Optional[CyclicColumns], poses: list, mu: np.ndarray,
                    quiet: list, states: list) -> None:
        """Record the measured history for the residuals and start predictions when due."""
        predictor = self.predictor
        rotation, translation = result.rotation, result.translation
        held = self.held_torque
        for k, stamp in enumerate(stamp_list):
            # Measured history for the residuals (closes predictions whose horizon passed).
            predictor.observe(stamp, qbar[k], translation[k], rotation[k])
            if held is not None:
                held.update(stamp, taus[k])
            if quiet[k] and self._prediction_due(stamp):
                tau = taus[k] if held is None or held.estimate is None else held.estimate
                extra = self._predict(stamp, poses[k], qbar[k], qbar_dot[k], tau,
                                      k >= rejected_at, mu[k],
                                      None if cyclic is None else cyclic.theta[k],
                                      self._start_uncertainty(states[k]))
                if extra is not None:
                    extras[k] = extra

    def _start_uncertainty(self, state: tuple) -> Optional[StartUncertainty]:
        """Return a prediction's start uncertainty (None: prediction_covariance off)."""
        config = self.config
        if not config.prediction_covariance:
            return None
        x, p = state[:2]
        n, m = self.robot.n, self.robot.m
        if len(state) > 2:
            wrench, wrench_cov = state[2], state[3]
            cov = np.zeros((3 * n, 3 * n))
            cov[:2 * n, :2 * n] = p[:2 * n, :2 * n]
            cov[2 * n:, 2 * n:] = wrench_cov
        else:
            wrench, cov = x[n:2 * n], p[:3 * n, :3 * n]
        held = self.held_torque
        return StartUncertainty(cov, np.array(wrench),
                                np.full(m, config.joint_position_noise ** 2),
                                np.full(m, config.joint_velocity_noise ** 2),
                                None if held is None else held.covariance)

    def _prediction_enabled(self) -> bool:
        config = self.config
        return config.prediction_rate > 0.0 and config.prediction_horizon > 0.0 \
            and (self.robot.m > 0 or self.robot.n > 0)

    def _prediction_due(self, stamp: int) -> bool:
        if not self._prediction_enabled():
            return False
        last = self._last_prediction_ns
        return last is None or stamp - last >= int(NS / self.config.prediction_rate) - 1

    def _predict(self, stamp: int, g: pin.SE3, qbar: np.ndarray, qbar_dot: np.ndarray,
                 tau: np.ndarray, report: bool, mu: np.ndarray,
                 theta: Optional[np.ndarray] = None,
                 uncertainty: Optional[StartUncertainty] = None) -> Optional[tuple]:
        """
        Start a prediction from the filter's pose and momentum (re-reduced at that mu).

        Return the output extras (messages, or the deferred job).
        """
        self._last_prediction_ns = stamp
        self.detector.take_level_change()
        deferred = self.defer_predictions
        try:
            job = self.predictor.predict(stamp, g, qbar, qbar_dot, mu, tau, theta,
                                         deferred=deferred, uncertainty=uncertainty)
        except (RuntimeError, ValueError, ArithmeticError, np.linalg.LinAlgError) as error:
            # A prediction that cannot start must not stop the estimates. (Failures while
            # computing are the job's: counted when its horizon has passed.)
            self.prediction_failures[type(error).__name__] += 1
            if report:
                self.last_rejection = f'prediction failed: {error}'
            return None
        if deferred:
            return (None, None, None, (None, job))
        return self._prediction_messages(job.run())

    @staticmethod
    def _prediction_messages(messages: Optional[PredictionMessages]) -> Optional[tuple]:
        """Output extras of computed messages (None: the prediction failed)."""
        if messages is None:
            return None
        return (messages.shape, messages.path, None, (messages.phase_path, None),
                messages[3:])

    def predict_base_motion(self, trajectory: JointTrajectorySample) -> BaseMotionAnswer:
        """
        Answer "where will the base go if the arm executes this plan?" from the latest state.

        The filtered base pose and momentum and the shape of the last processed sample
        start the prediction (:func:`~.base_motion.predict_base_motion`); the
        plan's stamp 0 means "from that sample". ValueError when there is no
        state yet, the plan does not fit the robot, or it has ended.
        """
        if self.latest_state is None or self.filter.g is None:
            raise ValueError('no estimated state yet')
        stamp, _, _, qbar, qbar_dot = self.latest_state
        config = self.config
        # The filter's pose and momentum at that sample.
        return predict_base_motion(self.robot, trajectory, self.filter.g,
                                   self.filter.mu.copy(), qbar, qbar_dot, stamp,
                                   config.prediction_step, config.prediction_tolerance,
                                   config.prediction_max_evaluations,
                                   config.prediction_max_wall_time, config.world_frame,
                                   budget_horizon=config.prediction_horizon)
