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
The momentum filter's measurement update: gating, gate resets, restarts, a step taken.

A part of :class:`~reduced_dynamics.estimator.filter.MomentumFilter` (a mixin whose
state ``MomentumFilter.__init__`` sets up): a base measurement's update (compiled or
already done by the row's call), the run of gated measurements and what it is taken
for (a pose offset, a momentum jump), the covariance's health and the restart that is
the last resort, a wrench step's compensation and the commanded wrench's gain floor.
"""

from __future__ import annotations

import logging
import math
from typing import Optional

import numpy as np
import pinocchio as pin

from reduced_dynamics.estimator import command_gain
from reduced_dynamics.estimator.core import kernels
from reduced_dynamics.estimator.core.state import FilterStep, Linearisation, Measurement
from reduced_dynamics.estimator.events import StepDetection
from reduced_dynamics.estimator.filter_model import _EMPTY

#: The filter's logger (its records keep the name they had in estimator/filter.py).
LOG = logging.getLogger('reduced_dynamics.estimator.filter')

#: Consecutive gated measurements after which a momentum jump is accepted.
GATE_RESET = 3
#: False-alarm probability of the test that a run of gated poses is a constant offset
#: (a mocap body re-fitted to other markers) rather than a momentum jump.
OFFSET_PROBABILITY = 1e-3
#: Time constant [s] of the twist average that scales the pose stamp noise.
STAMP_TWIST_TIME = 0.5
LOG_2PI = math.log(2.0 * math.pi)
#: Restart causes by ``kernels.covariance_health`` code (0: healthy).
_HEALTH_CAUSES = (None, 'covariance not finite', 'negative variance')


class FilterUpdate:
    """The filter's measurement update and its gating (a part of MomentumFilter)."""

    def _measure(self, stamp_ns: int, transition: np.ndarray,
                 measurement: Optional[Measurement], lin: Linearisation, output: bool,
                 gated: list, burst: Optional[bool] = None,
                 fused: Optional[tuple] = None) -> None:
        """
        Update with ``measurement`` (if any) at the current time and record the step.

        ``burst``: whether the measurement is a burst's (None: ask the stall detector).
        ``fused``: ``kernels.propagate_update``'s results (the update already done).
        """
        g_pred, x_pred, p_pred = self._g, self.x, self.p
        if burst is None:
            burst = measurement is not None and self.stalls.in_burst(measurement.stamp_ns) \
                and measurement.stamp_sigma is None
        if burst:
            # A frame of a burst after a stall (core/stalls.py): its stamp says nothing of
            # when it was taken. A re-timed stamp (its own sigma) is a frame time: kept.
            self.burst_skipped += 1
            measurement = None
        if measurement is not None:
            cause = None
            try:
                accepted = self._update(measurement.pose, measurement.twist, lin,
                                        measurement.stamp_sigma, measurement.noise, fused)
                if fused is not None and self.p is fused[11]:
                    # The compiled call checked this covariance already.
                    cause = _HEALTH_CAUSES[fused[15]]
                else:
                    cause = self._health_cause()
            except (np.linalg.LinAlgError, ZeroDivisionError) as error:
                accepted = False
                cause = 'covariance not finite' if not np.isfinite(self.p).all() \
                    else f'singular matrix ({error})'
            if cause is not None:
                self._restart(stamp_ns, cause, measurement, lin, output)
                return
            if not accepted:
                gated.append((measurement.stamp_ns, self.last_nis))
        if self.record:
            self.steps.append(FilterStep(stamp_ns, transition, g_pred, x_pred, p_pred,
                                         self._g, self.x, self.p, lin.locked_inverse, output,
                                         self._held_command()))

    def _update(self, pose: pin.SE3, twist: Optional[np.ndarray],
                lin: Linearisation, stamp_sigma: Optional[float] = None,
                noise: Optional[tuple] = None, fused: Optional[tuple] = None) -> bool:
        """Update with a measurement (``fused``: the compiled call's results, already done)."""
        n = self.n
        g0, x0, p0 = self._g, self.x, self.p
        measured = np.ascontiguousarray(pose.homogeneous)
        with_twist = twist is not None
        values = _EMPTY if twist is None else np.asarray(twist, dtype=float)
        sigma = 0.0
        if self.noise.pose_stamp > 0.0:
            # Stamp error dt: the measured pose is g exp(xi dt), so R += xi xi^T sigma_t^2,
            # with xi the body twist averaged over STAMP_TWIST_TIME: the estimate's own
            # transients (after a gate reset) must not weaken the poses that correct them.
            # A re-timed stamp (a frame time, estimator/retiming.py) carries its own.
            sigma = self.noise.pose_stamp if stamp_sigma is None else stamp_sigma
        size = 2 * n if with_twist else n
        if fused is not None:
            accepted, nis, logdet, nu, r, g1, x1, p1, h, s, gain = fused[4:15]
        elif noise is None:
            accepted, nis, logdet, nu, r, g1, x1, p1, h, s, gain = kernels.update(
                g0, x0, p0, measured, values, with_twist, lin.locked_inverse,
                lin.connection_qd, lin.joint_cov, self._pose_var, self._stamp_twist, sigma,
                self._twist_var, self._gates[size], self._basis, self._pinv, self._whole,
                self._form_rows)
        else:
            # The message's own covariances (estimator/covariance.py), full matrices; a
            # part the message left unknown keeps the noise parameters.
            r_pose = self._r_pose if noise[0] is None else noise[0]
            if sigma > 0.0:
                xi = self._stamp_twist * sigma
                r_pose = r_pose + np.outer(xi, xi)
            joint_cov, twist_var = lin.joint_cov, self._twist_var
            if with_twist and noise[1] is not None:
                joint_cov, twist_var = joint_cov + noise[1], self._twist_zero
            accepted, nis, logdet, nu, r, g1, x1, p1, h, s, gain = kernels.update_noise(
                g0, x0, p0, measured, values, with_twist, lin.locked_inverse,
                lin.connection_qd, joint_cov, r_pose, twist_var, self._gates[size],
                self._basis, self._pinv, self._whole, self._form_rows)
        self.last_nis = nis
        # Innovation log-likelihood (what `reduced-dynamics tune` maximises) and NIS sums.
        self.log_likelihood -= 0.5 * (nis + logdet + size * LOG_2PI)
        self.nis_sum += nis
        self.nis_dof += size
        if not accepted:
            self._gated_run += 1
            if not with_twist:
                self._gated_residuals.append((nu, r))
            if self._gated_run < GATE_RESET:
                # Counted only when rejected: ``gated`` is the measurements not used (the
                # pipeline's innovation_gate rejections), not those over the gate.
                self.gated += 1
                return False
            p0 = p0.copy()
            offset = self._pose_offset()
            if offset is not None:
                # The sensor's pose stepped (see the module docstring): re-anchor the
                # pose by the offset's size; the momentum and the wrench are untouched.
                p0[:n, :n] += np.diag(offset ** 2)
                self.pose_offsets += 1
            else:
                # A momentum jump no wrench of the random walk explains, seen 3 times
                # in a row: believe it, with the prior spread of mu and w added.
                to_world = self._adjoint_inverse(pin.SE3(g0)).T @ lin.locked
                p0[n:2 * n, n:2 * n] += (to_world * self._speed_var) @ to_world.T
                p0[2 * n:3 * n, 2 * n:3 * n] += (to_world * self._accel_var) @ to_world.T
            self.p = p0
            # The step hypotheses described the filter before the jump: start afresh.
            self.step_test.reset()
            g1, x1, p1, h, s, gain = kernels.correct(
                g0, x0, p0, measured, values, with_twist, h, nu, r,
                kernels.gain_of(p0, h, r), lin.locked_inverse, lin.connection_qd,
                self._basis, self._pinv, self._whole, self._form_rows)
        self._gated_run = 0
        self._gated_residuals = []
        self._g, self.x, self.p = g1, x1, p1
        if self.noise.pose_stamp > 0.0 and fused is not None and p1 is fused[11]:
            # Accepted at once: the compiled call moved the average (same operations).
            self._stamp_twist_ns = self.stamp_ns
            self._stamp_twist = fused[16]
        elif self.noise.pose_stamp > 0.0:
            last, self._stamp_twist_ns = self._stamp_twist_ns, self.stamp_ns
            dt = 0.0 if last is None else max(self.stamp_ns - last, 0) * 1e-9
            weight = min(1.0, dt / STAMP_TWIST_TIME)
            self._stamp_twist = self._stamp_twist + weight * (kernels.twist(
                g1, x1[:n], lin.locked_inverse, lin.connection_qd, self._basis, self._pinv,
                self._whole) - self._stamp_twist)
        detection = self.step_test.update(self._h_pose if not with_twist else h, s, gain, nu)
        if detection is not None:
            self._take_step(detection)
        if self.command:
            self._constrain_gains()
        return True

    def _take_step(self, detection: StepDetection) -> None:
        """Take a detected wrench step (Willsky-Jones compensation); forget the hypotheses."""
        # A wrench step (thruster on/off: a jump, not a random walk): take its
        # maximum-likelihood size and its uncertainty.
        self._g, self.x, self.p = kernels.compensate(
            self._g, self.x, self.p, detection.correction, detection.covariance,
            self._basis, self._whole)
        self.step_test.reset()
        self.step_detected = detection
        self.steps_taken += 1

    def _health_cause(self) -> Optional[str]:
        """Return why the covariance is unusable (a restart's cause), or None."""
        if not np.isfinite(self.p).all():
            return 'covariance not finite'
        if not (np.diag(self.p) >= 0.0).all():
            return 'negative variance'
        return None

    def _restart(self, stamp_ns: int, cause: str, measurement: Measurement,
                 lin: Linearisation, output: bool) -> None:
        """Start again from ``measurement``: the last resort, logged and counted by cause."""
        # The update keeps P positive semi-definite (measured over long runs,
        # docs/structured_step.md), so this takes a covariance corrupted before the
        # update (a non-finite input, an overflow), or an S that is not positive definite.
        self.diverged += 1
        self.restart_causes[cause] += 1
        LOG.warning('momentum filter restarted at %d ns: %s (restart %d)',
                    stamp_ns, cause, self.diverged)
        self.initialise(stamp_ns, measurement.pose, lin, measurement.twist, output,
                        measurement.noise)

    def _constrain_gains(self) -> None:
        """Project the gains onto k >= GAIN_FLOOR (command_gain.py: Simon & Chia)."""
        correction = command_gain.project_gains(self.x, self.p, self.n)
        if correction is None:
            return
        self._g, self.x, self.p = kernels.compensate(
            self._g, self.x, self.p, correction, np.zeros_like(self.p), self._basis,
            self._whole)
        self.gain_projections += 1

    def command_identified(self) -> tuple[np.ndarray, np.ndarray]:
        """Return per axis whether the gain and the bias are identified (command_gain.py)."""
        return command_gain.identified(self.p, self.n, self.command_prior_sigma)

    def _pose_offset(self) -> Optional[np.ndarray]:
        """
        Return the mean residual of the gated run when it is one constant pose offset.

        Offset hypothesis: every gated pose residual is the same offset plus its
        measurement noise R_k, so ``sum (r_k - r_mean)^T R_k^-1 (r_k - r_mean)`` is
        chi-square with n (K - 1) degrees of freedom (the prediction's own error is
        common to the run and cancels). A momentum jump large enough to be gated at
        its first pose moves the later residuals by several sigma per sample.
        None: not pose-only residuals, or not constant (a momentum jump).
        """
        runs = self._gated_residuals
        if len(runs) < 2 or len(runs) != self._gated_run:
            return None
        residuals = np.array([r for r, _ in runs])
        mean = residuals.mean(axis=0)
        spread = sum(float(d @ np.linalg.solve(noise, d))
                     for d, (_, noise) in zip(residuals - mean, runs))
        return mean if spread <= self._offset_threshold[len(runs)] else None
