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
The momentum filter's rows: a joint-state row with the base measurements since the last.

A part of :class:`~reduced_dynamics.estimator.filter.MomentumFilter` (a mixin whose
state ``MomentumFilter.__init__`` sets up): each measurement updates at its own stamp,
the propagation between them, the coast cap, and the common step as one compiled call
(``step_row.filter_step`` with the step test's share, or ``kernels.propagate_update``)
with the bookkeeping of its common outcome (docs/filter_row.md).
"""

from __future__ import annotations

import logging
from typing import Optional, Sequence

import numpy as np
import pinocchio as pin

from reduced_dynamics.estimator import step_row
from reduced_dynamics.estimator.core import kernels
from reduced_dynamics.estimator.core.state import (Command, FilterStep, Linearisation,
                                                   Measurement, between)
from reduced_dynamics.estimator.filter_model import _EMPTY
from reduced_dynamics.estimator.filter_update import LOG_2PI, STAMP_TWIST_TIME

#: The filter's logger (its records keep the name they had in estimator/filter.py).
LOG = logging.getLogger('reduced_dynamics.estimator.filter')

#: The covariance cap of a coast [s]: a row whose filter went longer than this without a
#: base measurement restarts from the row's base state (restart cause ``coast``) instead
#: of propagating over the gap. Over a gap T the momentum's variance grows by the wrench
#: random walk integrated twice (~T^3): after a minute of lost odometry it reached ~1e8
#: times its steady value and, over ten minutes, lost positive definiteness
#: (test/test_mission_soak.py); a fresh start from the measurement says more.
MAX_COAST_S = 10.0


class FilterRows:
    """A row's propagation and updates (a part of MomentumFilter)."""

    def step(self, stamp_ns: int, lin: Linearisation, pose: Optional[pin.SE3],
             twist: Optional[np.ndarray], command: Optional[Command] = None) -> bool:
        """
        Propagate to ``stamp_ns`` and update with the pose (and twist) when given.

        ``command``: the commanded wrench over the step (filters built with
        ``command=True``; None there means no command: zero).
        Return False when the measurement was gated out (counted in ``gated``).
        """
        measurement = None if pose is None else Measurement(stamp_ns, pose, twist)
        commands = None if command is None else (command,)
        if self._g is None:
            self.row(stamp_ns, lin, measurement, (), commands)
            return True
        return not self.row(stamp_ns, lin, None, () if measurement is None else (measurement,),
                            commands)

    def row(self, stamp_ns: int, lin: Linearisation, prior: Optional[Measurement],
            measurements: Sequence[Measurement] = (),
            commands: Optional[Sequence[Optional[Command]]] = None
            ) -> list[tuple[int, float]]:
        """
        Process one joint-state row at ``stamp_ns`` with its inputs ``lin``.

        Each base measurement stamped since the previous row updates the filter
        once, at its own stamp: the filter propagates to it with the joint inputs
        interpolated between the bracketing rows, updates, and propagates on to
        the row (robot_localization's order); a row without a measurement only
        propagates. A measurement at the row's stamp updates at the row.
        Measurements not after the filter's time (late) are skipped. Before the
        first row the filter starts from ``prior`` (the base state at the row's
        stamp) and skips the measurements it came from. ``commands``
        (commanded-wrench filters): the command over each step, one per
        measurement before the row's stamp, then the one of the step that ends at
        the row. Return the gated measurements as (stamp, NIS).
        """
        self.step_detected = None
        if self._g is None:
            if prior is not None:
                if self.command and commands:
                    self._command = commands[-1].now
                self.initialise(stamp_ns, prior.pose, lin, prior.twist, True, prior.noise)
            return []
        if prior is not None and self._coasted(stamp_ns, measurements):
            self.restart_causes['coast'] += 1
            LOG.warning('momentum filter restarted at %d ns: %.3g s without a base '
                        'measurement (more than %g s)', stamp_ns,
                        (stamp_ns - self.stamp_ns) * 1e-9, MAX_COAST_S)
            self.initialise(stamp_ns, prior.pose, lin, prior.twist, True, prior.noise)
            return []
        before = self._lin if self._lin is not None else lin
        self._lin = lin
        start = self.stamp_ns
        span = stamp_ns - start
        gated: list[tuple[int, float]] = []
        last: Optional[Measurement] = None
        done = 0.0  # fraction of the row's interval already propagated
        for index, measurement in enumerate(measurements):
            stamp = measurement.stamp_ns
            if stamp >= stamp_ns:
                if stamp == stamp_ns:
                    last = measurement
                break
            if stamp <= self.stamp_ns:
                continue
            fraction = (stamp - start) / span
            self._step_to(stamp, between(before, lin, 0.5 * (done + fraction)),
                          None if commands is None else commands[index], measurement,
                          between(before, lin, fraction), False, gated)
            done = fraction
        # A measurement at the row with none before it in the interval: the step's
        # inputs are the rows' mean, which the compiled row step forms itself.
        midway = done == 0.0 and last is not None
        self._step_to(stamp_ns, None if midway else between(before, lin, 0.5 * (done + 1.0)),
                      None if commands is None else commands[-1], last, lin, True, gated,
                      before if midway else None)
        return gated

    def row_at(self, stamp_ns: int, lin: Linearisation, measurement: Measurement,
               pose: Optional[np.ndarray] = None) -> list[tuple[int, float]]:
        """
        Run :meth:`row` of the common row: its one base measurement, at its own stamp.

        ``row(stamp_ns, lin, measurement, [measurement])`` with what the caller checked
        (the filter started, within the coast cap, no commanded wrench) left out: the
        same operations in the same order. ``pose``: the measurement's pose as a
        C-contiguous 4 x 4 array when the caller has one (the chunk's rows: no pin.SE3
        round trip per row).
        """
        self.step_detected = None
        before = self._lin if self._lin is not None else lin
        self._lin = lin
        gated: list[tuple[int, float]] = []
        self._step_to(stamp_ns, None, None, measurement, lin, True, gated, before, pose)
        return gated

    def _coasted(self, stamp_ns: int, measurements: Sequence[Measurement]) -> bool:
        """Whether the filter would go more than MAX_COAST_S without a base measurement."""
        cap = MAX_COAST_S * 1e9
        if stamp_ns - self.stamp_ns <= cap:
            return False  # the hot path: one comparison
        times = [self.stamp_ns] + [m.stamp_ns for m in measurements
                                   if m is not None and m.stamp_ns > self.stamp_ns] + [stamp_ns]
        return max(b - a for a, b in zip(times, times[1:])) > cap

    def _step_to(self, stamp_ns: int, step: Optional[Linearisation],
                 command: Optional[Command], measurement: Optional[Measurement],
                 lin: Linearisation, output: bool, gated: list,
                 before: Optional[Linearisation] = None,
                 pose: Optional[np.ndarray] = None) -> None:
        """
        Propagate to ``stamp_ns`` with inputs ``step``, then measure (:meth:`_measure`).

        The common step (no commanded wrench, the noise parameters, not a burst) runs
        as one compiled call (``kernels.propagate_update``) doing the same operations
        as :meth:`_propagate` and :meth:`_update` one after the other; with the step
        test on, the step test's share of the step joins that call
        (:mod:`~reduced_dynamics.estimator.step_row`), with the inputs ``step`` (a
        measurement between rows, or at a row after others) or, ``step`` None, the
        mean of ``before`` and ``lin`` (a row's one measurement, at its stamp).
        ``pose``: the measurement's pose as a 4 x 4 array when the caller has one
        (:meth:`row_at`).
        """
        if measurement is not None and not self.command and measurement.noise is None \
                and stamp_ns > self.stamp_ns:
            burst = self.stalls.in_burst(measurement.stamp_ns) \
                and measurement.stamp_sigma is None
            if not burst and self.step_test.active and \
                    self._row_measured(stamp_ns, before, measurement, lin, output, gated, pose,
                                       step):
                return
            self._measured_step(stamp_ns, step, command, measurement, lin, output, gated,
                                before, burst)
            return
        if step is None:
            step = between(before, lin, 0.5)
        transition = self._propagate(stamp_ns, step, command)
        self._measure(stamp_ns, transition, measurement, lin, output, gated, burst=None)

    def _measured_step(self, stamp_ns: int, step: Optional[Linearisation],
                       command: Optional[Command], measurement: Measurement,
                       lin: Linearisation, output: bool, gated: list,
                       before: Optional[Linearisation], burst: bool) -> None:
        """:meth:`_step_to` of a measurement the row step did not take (a burst, no test)."""
        if step is None:
            step = between(before, lin, 0.5)
        if not burst:
            fused = self._fused_step(stamp_ns, step, measurement, lin)
            if fused is not None:
                self._measure(stamp_ns, fused[3], measurement, lin, output, gated,
                              burst=False, fused=fused)
                return
        transition = self._propagate(stamp_ns, step, command)
        self._measure(stamp_ns, transition, measurement, lin, output, gated, burst=burst)

    def _propagate(self, stamp_ns: int, lin: Linearisation,
                   command: Optional[Command]) -> np.ndarray:
        """
        Propagate mean and covariance to ``stamp_ns`` with inputs ``lin``; return Phi.

        ``command``: the commanded wrench over the step (commanded-wrench filters;
        None there: zero).
        """
        u = _EMPTY
        if self.command:
            u = self._command_zero if command is None else command.mean
            self._command = self._command_zero if command is None else command.now
        dt = (stamp_ns - self.stamp_ns) * 1e-9
        if dt <= 0.0:
            self.step_test.propagate(stamp_ns, self._eye)
            return self._eye
        test = self.step_test
        if not self.command and test.active:
            # The step test's propagate in the same compiled call (step_row.py).
            out = step_row.propagate_step(
                self._g, self.x, self.p, lin.locked, lin.locked_inverse, lin.connection_qd,
                lin.joint_cov, dt, u, self._jerk_var, self._densities(lin), self._basis,
                self._pinv, self._whole, self._ad_rows, self._form_rows, stamp_ns,
                *test.compiled_arrays, self._work_buffer)
            self._g, self.x, self.p = out
            self.stamp_ns = stamp_ns
            # Phi in the work arrays: read only to record the step (a copy: written again).
            return self._work[3].copy() if self.record else self._work[3]
        self._g, self.x, self.p, transition = kernels.propagate(
            self._g, self.x, self.p, lin.locked, lin.locked_inverse, lin.connection_qd,
            lin.joint_cov, dt, u, self.command, self._jerk_var, self._densities(lin),
            self._basis, self._pinv, self._whole, self._ad_rows, self._form_rows)
        self.stamp_ns = stamp_ns
        self.step_test.propagate(stamp_ns, transition)
        return transition

    def _stamp_noise(self, stamp_ns: int, measurement: Measurement) -> tuple[float, float]:
        """Return the stamp sigma and the stamp twist's average weight of a fused step."""
        if not self.noise.pose_stamp > 0.0:
            return 0.0, -1.0
        sigma = self.noise.pose_stamp if measurement.stamp_sigma is None \
            else measurement.stamp_sigma
        # The stamp twist's average weight of _update (the time since its last move).
        last = self._stamp_twist_ns
        dt = 0.0 if last is None else max(stamp_ns - last, 0) * 1e-9
        return sigma, min(1.0, dt / STAMP_TWIST_TIME)

    def _row_measured(self, stamp_ns: int, before: Optional[Linearisation],
                      measurement: Measurement, lin: Linearisation, output: bool,
                      gated: list, pose: Optional[np.ndarray] = None,
                      step: Optional[Linearisation] = None) -> bool:
        """
        Run ``step_row.filter_step`` (:meth:`_fused_step` and the step test's share) and measure.

        The step's inputs: ``step`` when given (a measurement between two rows, or at a
        row after others: ``state.between`` at the caller's fraction), else the mean of
        ``before`` and ``lin`` (formed in the call). The common outcome (accepted into a
        healthy covariance, the step test's bank open) is taken here with
        :meth:`_update`'s bookkeeping in the same order; any other goes on to
        :meth:`_measure` with the call's results, as before. Return False when the call
        raised, or when ``step``'s I or A Sigma A^T are not ``lin``'s (the call propagates
        with ``lin``'s): nothing changed, the caller takes the separate calls.
        ``pose``: the measurement's pose as a C-contiguous 4 x 4 array (None: from it).
        """
        if step is None:
            if before is None:
                return False
            step_inverse, step_connection_qd, midway = \
                before.locked_inverse, before.connection_qd, True
        elif step.locked is lin.locked and step.joint_cov is lin.joint_cov:
            # (state.between keeps the later row's I and A Sigma A^T: the same objects.)
            step_inverse, step_connection_qd, midway = \
                step.locked_inverse, step.connection_qd, False
        else:
            return False
        twist = measurement.twist
        with_twist = twist is not None
        size = 2 * self.n if with_twist else self.n
        noise = self.noise
        if noise.pose_stamp > 0.0:
            # _stamp_noise's arithmetic, inline (a row's hot path).
            sigma = noise.pose_stamp if measurement.stamp_sigma is None \
                else measurement.stamp_sigma
            last = self._stamp_twist_ns
            dt = 0.0 if last is None else max(stamp_ns - last, 0) * 1e-9
            weight = min(1.0, dt / STAMP_TWIST_TIME)
        else:
            sigma, weight = 0.0, -1.0
        test = self.step_test
        fixed = self._row_fixed
        if fixed[0] is not test:
            fixed = self._row_fixed = self._fixed_arguments()
        try:
            (g1, x1, p1, accepted, nis, logdet, health, wrench_test, tested, evidence, best,
             statistic, top, evaluated) = step_row.filter_step(
                self._g, self.x, self.p, lin.locked, step_inverse, step_connection_qd,
                midway, (stamp_ns - self.stamp_ns) * 1e-9,
                np.ascontiguousarray(measurement.pose.homogeneous) if pose is None else pose,
                _EMPTY if twist is None else np.asarray(twist, dtype=float), with_twist,
                lin.locked_inverse, lin.connection_qd, lin.joint_cov, self._stamp_twist, sigma,
                self._gates[size], weight, stamp_ns, *fixed[1])
        except (np.linalg.LinAlgError, ZeroDivisionError):
            return False
        self.stamp_ns = stamp_ns
        self._fused_significance = (p1, x1, wrench_test)
        if not tested:
            # Gated, a broken covariance or no onset open: the general path, with
            # propagate_update's results as _fused_step gives them (copies of the work
            # arrays; when gated, the update's state is the prediction itself).
            if accepted:
                work = self._work
                self._g, self.x, self.p = work[0].copy(), work[1].copy(), work[2].copy()
            else:
                self._g, self.x, self.p = g1, x1, p1
            fused = self._work_results(size, accepted, nis, logdet, g1, x1, p1, health,
                                       wrench_test)
            self._measure(stamp_ns, fused[3], measurement, lin, output, gated, burst=False,
                          fused=fused)
            return True
        # _update's bookkeeping of an accepted fused update, in its order.
        self.last_nis = nis
        self.log_likelihood -= 0.5 * (nis + logdet + size * LOG_2PI)
        self.nis_sum += nis
        self.nis_dof += size
        self._gated_run = 0
        self._gated_residuals = []
        self._g, self.x, self.p = g1, x1, p1
        if noise.pose_stamp > 0.0:
            self._stamp_twist_ns = stamp_ns  # the average moved in place (filter_step)
        cause = None
        if evidence:
            # The step test took the update (filter_step); its outcome, from Python.
            try:
                detection = test._evaluated(best, statistic, top, evaluated)
                if detection is not None:
                    self._take_step(detection)
                    cause = self._health_cause()
            except (np.linalg.LinAlgError, ZeroDivisionError) as error:
                cause = 'covariance not finite' if not np.isfinite(self.p).all() \
                    else f'singular matrix ({error})'
        if cause is not None:
            self._restart(stamp_ns, cause, measurement, lin, output)
        elif self.record:
            # Copies: the work arrays are written again by the next row.
            work_g, work_x, work_p, work_phi = self._work[:4]
            self.steps.append(FilterStep(stamp_ns, work_phi.copy(), work_g.copy(),
                                         work_x.copy(), work_p.copy(), self._g, self.x,
                                         self.p, lin.locked_inverse, output,
                                         self._held_command()))
        return True

    def _fixed_arguments(self) -> tuple:
        """Return (the step test, step_row.filter_step's arguments fixed for the filter)."""
        test = self.step_test
        return test, (self._jerk_var, self._pose_var, self._twist_var, self._basis,
                      self._pinv, self._whole, self._ad_rows, self._form_rows, self._h_pose,
                      *test.compiled_arrays, self._work_buffer)

    def _work_results(self, size: int, accepted: bool, nis: float, logdet: float,
                      g1: np.ndarray, x1: np.ndarray, p1: np.ndarray, health: int,
                      wrench_test: float) -> tuple:
        """Return ``kernels.propagate_update``'s results from a row step's work arrays."""
        g0, x0, p0 = self._g, self.x, self.p
        _, _, _, phi, nu, r, h, s, gain = self._work
        if not accepted:
            g1, x1, p1 = g0, x0, p0
        return (g0, x0, p0, phi.copy(), accepted, nis, logdet, nu[:size].copy(),
                r[:size, :size].copy(), g1, x1, p1, h[:size].copy(), s[:size, :size].copy(),
                gain[:, :size].copy(), health, self._stamp_twist, wrench_test)

    def _fused_step(self, stamp_ns: int, step: Linearisation, measurement: Measurement,
                    lin: Linearisation) -> Optional[tuple]:
        """
        Run ``kernels.propagate_update``; take its prediction as :meth:`_propagate` does.

        Return its results, or None when it raised (the caller then takes the two
        steps one by one, which raise or restart as they always did).
        """
        twist = measurement.twist
        with_twist = twist is not None
        values = _EMPTY if twist is None else np.asarray(twist, dtype=float)
        sigma, weight = self._stamp_noise(stamp_ns, measurement)
        try:
            fused = kernels.propagate_update(
                self._g, self.x, self.p, step.locked, step.locked_inverse,
                step.connection_qd, step.joint_cov, (stamp_ns - self.stamp_ns) * 1e-9,
                self._jerk_var, np.ascontiguousarray(measurement.pose.homogeneous), values,
                with_twist, lin.locked_inverse, lin.connection_qd, lin.joint_cov,
                self._pose_var, self._stamp_twist, sigma, self._twist_var,
                self._gates[2 * self.n if with_twist else self.n], weight, self._basis,
                self._pinv, self._whole, self._ad_rows, self._form_rows)
        except (np.linalg.LinAlgError, ZeroDivisionError):
            return None
        self._g, self.x, self.p = fused[0], fused[1], fused[2]
        self.stamp_ns = stamp_ns
        self._fused_significance = (fused[11], fused[10], fused[17])
        self.step_test.propagate(stamp_ns, fused[3])
        return fused
