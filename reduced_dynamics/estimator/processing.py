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
The filter's orchestration: a chunk of rows through the kernel, the filter and events.

Part of :class:`~.pipeline.Estimator` (its state is set up there). A chunk of
synchronised rows is evaluated by the vectorised kernel at once (:mod:`.kernel`:
I, A = I^-1 B, pbar = S qbar_dot, 5.29, 5.35), then the filter (:mod:`.filter`)
steps through its rows one at a time with each row's base measurements, the
event detector (:mod:`.events`) reads the filter's statistics, and predictions
(:mod:`.prediction`) start where they are due (:mod:`.row_predictions`). The
result is an :class:`~.outputs.OutputChunk`.
"""

from __future__ import annotations

from itertools import chain
import math
from typing import Optional

import numpy as np
import pinocchio as pin

from reduced_dynamics.estimator.core.inputs import drift_energy, welford_row
from reduced_dynamics.estimator.covariance import NoisyRow
from reduced_dynamics.estimator.filter import Command, Linearisation, MAX_COAST_S, Measurement
from reduced_dynamics.estimator.multiscale import twist_momenta
from reduced_dynamics.estimator.outputs import OutputChunk
# NS: importable from here as before (pipeline); the predictions' own module defines it.
from reduced_dynamics.estimator.row_predictions import NS, RowPredictions

__all__ = ['COAST_NS', 'ChunkProcessing', 'NS', 'RowChunk']
#: The filter's coast cap in ns (a row further from its last step restarts it).
COAST_NS = int(MAX_COAST_S * NS)


class RowChunk:
    """
    Synchronised samples waiting for the vectorised update.

    Rows are tuples (stamp_ns, qbar, qbar_dot, tau, base row, measurements), like
    the pending shape samples (stamp_ns, qbar, qbar_dot, tau): tuples, because
    one object per sample is a measurable part of the per-sample cost. The base
    row is the base state at the row's stamp (interpolated: the measured history
    of the prediction residuals, and the filter's start); ``measurements`` are
    the base samples (stamp_ns, row) stamped since the previous row, which the
    filter updates with at their own stamps.
    """

    __slots__ = ('rows', 'diagnose', 'commands')

    def __init__(self) -> None:
        self.rows: list[tuple] = []
        self.diagnose = False
        #: commanded wrench on: per row, one :class:`~.filter.Command` per filter step
        self.commands: list[list[Command]] = []


class ChunkProcessing(RowPredictions):
    """
    The update of a chunk of rows (a part of :class:`~.pipeline.Estimator`).

    ``_process_chunk`` turns the open :class:`RowChunk` into an
    :class:`~.outputs.OutputChunk` in ``_done``; predictions start from the
    filter's pose and momentum where they are due (:class:`~.row_predictions.RowPredictions`).
    """

    def _process_chunk(self) -> None:
        chunk = self._chunk
        count = len(chunk.rows)
        if not count:
            return
        # A new chunk first: if the update raises, these samples are lost, not retried.
        self._chunk = RowChunk()
        if count == 1 and not self.commanded_wrench and self._cyclic_view is None:
            # The streaming path's chunk: the same operations on one row, unstacked.
            self._process_row(chunk)
        else:
            self._process_rows(chunk, count)

    def _process_rows(self, chunk: RowChunk, count: int) -> None:
        """Update a chunk of ``count`` rows (any chunk: the general path)."""
        rejected_at, self._rejected_at = self._rejected_at, 0
        m, n = self.robot.m, self.robot.n
        stamp_list, qbar, qbar_dot, taus, bases, measured = zip(*chunk.rows)
        stamps = np.array(stamp_list, dtype=np.int64)
        # The cheapest ways to stack these rows (arrays; lists of 13 floats).
        qbar = np.concatenate(qbar).reshape(count, m)
        qbar_dot = np.concatenate(qbar_dot).reshape(count, m)
        if bases[0].__class__ is np.ndarray:
            # Rows of the batched path's base columns (estimator/intake.py): one copy.
            bases = np.concatenate(bases).reshape(count, 13)
        else:
            bases = np.fromiter(chain.from_iterable(bases), float, count * 13).reshape(count,
                                                                                       13)
        result = self.kernel.filter_inputs(qbar, qbar_dot, bases,
                                           self.config.joint_velocity_noise ** 2)
        inverse = result.inverse
        # (map over the four row iterators: no zip tuple to unpack per row)
        lins = list(map(Linearisation, result.locked, inverse, result.connection_qd,
                        result.joint_cov))
        # The recursion, one sample at a time (the same code whatever the chunk).
        flt, detector, adjoint = self.filter, self.detector, self.filter._adjoint
        twists = result.xi if self.use_odometry else None
        mu = np.empty((count, n))
        rate = np.empty((count, n))
        pi = np.empty((count, n))
        mu_cov = np.empty((count, n, n))
        w_cov = np.empty((count, n, n))
        poses: list[pin.SE3] = []
        #: the filter's state (x, P) at each row (arrays are replaced, never modified)
        states: list[tuple] = []
        quiet: list[bool] = []
        rotation, translation = result.rotation, result.translation
        # The rows' base poses as 4 x 4 arrays, the bits of pin.SE3(R, t).homogeneous (the
        # filter's row step takes them; one array for the chunk, not one per row).
        homogeneous = np.zeros((count, 4, 4))
        homogeneous[:, :3, :3] = rotation
        homogeneous[:, :3, 3] = translation
        homogeneous[:, 3, 3] = 1.0
        commands = chunk.commands if self.commanded_wrench else None
        disturbance = None if commands is None else np.empty((count, n))
        lagged, fixed_lag, events = self.fixed_lag, {}, {}
        coast_ns = COAST_NS
        row_measurements = self._row_measurements
        # Ad_g on the subalgebra: the whole algebra's is the pose's action (filter._adjoint).
        whole = flt._whole
        # Poses, states and quiet flags serve the predictions only (_per_sample); nothing
        # in the loop starts or ends one, so this holds for the whole chunk.
        predicting = self.predictor.active or self._prediction_enabled()
        for k in range(count):
            stamp = stamp_list[k]
            prior = None
            samples = measured[k]
            if len(samples) == 1 and samples[0][0] == stamp and len(samples[0]) == 2 \
                    and samples[0][1].__class__ is not NoisyRow:
                # _row_measurements' common row, inline (one base sample at the row's stamp).
                measurements, at_row, sigma, noise = [None], True, None, None
            else:
                measurements, at_row, sigma, noise = row_measurements(samples, stamp)
            restart = flt._g is None or stamp - flt.stamp_ns > coast_ns
            if at_row or restart:
                # The base state at the row's stamp (a measurement there, the start, or
                # a restart after a coast beyond the filter's cap). (tuple.__new__: the
                # NamedTuple's fields as they are, without its Python __new__.)
                prior = tuple.__new__(Measurement, (
                    stamp, pin.SE3(rotation[k], translation[k]),
                    None if twists is None else twists[k], sigma, noise))
                if at_row:
                    measurements[-1] = prior
            before, start_ns = flt._lin, flt.stamp_ns
            if at_row and not restart and commands is None and len(measurements) == 1:
                # The common row: its one measurement at its stamp (filter.row_at).
                gated = flt.row_at(stamp, lins[k], prior, homogeneous[k])
                gated_at = self._count_gated(gated) if gated else []
            else:
                gated_at = self._filter_row(stamp, lins[k], prior, measurements,
                                            None if commands is None else commands[k])
            g = flt.g  # one pin.SE3 per row (the property builds a new one each time)
            # Each accepted twist's own momentum, for the event tests (multiscale.py).
            # (No measurement: twist_momenta finds none; [] without its pose products.)
            measured_mu = None if twists is None or commands is not None else \
                twist_momenta(flt, before, lins[k], start_ns, stamp, measurements, gated_at,
                              g) if measurements else []
            if lagged is not None and lagged._ready:
                # Rows whose lag passed during this row's steps go out with it.
                fixed_lag[k] = lagged.take()
            x, p = flt.x, flt.p
            mu[k] = x[:n]
            # ndarray.dot: the same BLAS call as @ (the same bits), a third of its dispatch.
            pi[k] = (g.action if whole else adjoint(g)).T.dot(x[:n])
            mu_cov[k] = p[n:2 * n, n:2 * n]
            if disturbance is None:
                rate[k] = peak = x[n:]
                w_cov[k] = p[2 * n:, 2 * n:]
            else:
                # The total wrench is what mu does; events concern the disturbance
                # beyond the command (a commanded firing is expected, not an event).
                rate[k], w_cov[k] = flt.total_wrench()
                disturbance[k] = peak = flt.wrench
            detector.update(stamp, mu[k], math.sqrt(float(peak.dot(peak))),
                            flt.wrench_significance(), flt.step_detected is not None,
                            # mu moves by the commanded impulses too: no window test.
                            mu_cov[k] if disturbance is None else None, measured_mu)
            if detector.notices:
                events[k] = detector.take_notices()
            if predicting:
                poses.append(g)
                # Commanded wrench: the total wrench (delivered command + disturbance) at
                # this row is what mu does over a prediction from it.
                states.append((x, p) if disturbance is None else (x, p, rate[k], w_cov[k]))
                # Predictions assume mu constant: none starts while an event is under way
                # (not while an ended event's record waits out its horizon: in_event).
                quiet.append(not detector.in_event)
        # Drift twist I^-1 pi and the reduced energy (5.36) from the filtered momentum,
        # 1/2 pi.I^-1 pi + 1/2 pbar.qbar_dot: one compiled call, the same per row whatever
        # the chunk (core/inputs.py).
        drift, energy = drift_energy(inverse, pi, qbar_dot, result.pbar)
        if self.robot.has_potential:
            energy += [self.robot.potential_energy(row) for row in qbar]
        extras: dict = {}
        cyclic = None
        if self._cyclic_view is not None:
            xi_hat = drift - result.connection_qd
            cyclic = self._cyclic_view.columns(result.mass, xi_hat, qbar, qbar_dot)
            self._last_theta = cyclic.theta[-1]
        if predicting:
            self._per_sample(stamp_list, qbar, qbar_dot, taus, result, extras, rejected_at,
                             cyclic, poses, mu, quiet, states)
        self.latest_state = (stamp_list[-1], result.rotation[-1], result.translation[-1],
                             qbar[-1], qbar_dot[-1])
        if self.first_stamp_ns is None:
            self.first_stamp_ns = stamp_list[0]
        self._accumulate_statistics(mu)
        self._last_mu, self._last_energy = mu[-1], float(energy[-1])
        if chunk.diagnose:
            stamp = stamp_list[-1]
            previous = extras.get(count - 1, (None, None, None))
            extras[count - 1] = previous[:2] + (self.diagnostics(stamp),) + previous[3:]
        out = OutputChunk(self, stamps, mu, pi, rate, drift, qbar, qbar_dot, result.pbar,
                          energy, extras, cyclic)
        out.mu_cov, out.w_cov = mu_cov, w_cov
        out.disturbance = disturbance
        out.fixed_lag = fixed_lag
        out.events = events
        self._done.append(out)

    def _process_row(self, chunk: RowChunk) -> None:
        """
        Update a chunk of one row (streaming): :meth:`_process_chunk`'s operations, unstacked.

        No commanded wrench and no second stage (those chunks take the general
        path). The columns are the general path's (1, ...) arrays, made from the
        row's own values without stacking, and every value goes through the same
        calls (the kernel, the filter's row, the event tests, the drift and
        energy, Welford's one-row update): the same bits (test_streaming_row.py).
        """
        rejected_at, self._rejected_at = self._rejected_at, 0
        stamp, qbar_row, qbar_dot_row, tau, base, samples = chunk.rows[0]
        n = self.robot.n
        # (1, m) copies of the row (np.concatenate of one row copies it too).
        qbar = qbar_row[None].copy()
        qbar_dot = qbar_dot_row[None].copy()
        if base.__class__ is np.ndarray:
            bases = base[None].copy()
        else:
            bases = np.fromiter(base, float, 13).reshape(1, 13)
        result = self.kernel.filter_inputs(qbar, qbar_dot, bases,
                                           self.config.joint_velocity_noise ** 2)
        inverse = result.inverse
        # tuple.__new__: the NamedTuple's fields as they are (its __new__ is Python).
        lin = tuple.__new__(Linearisation, (result.locked[0], inverse[0],
                                            result.connection_qd[0], result.joint_cov[0]))
        flt = self.filter
        twists = result.xi if self.use_odometry else None
        prior = None
        measurements, at_row, sigma, noise = self._row_measurements(samples, stamp)
        restart = flt._g is None or stamp - flt.stamp_ns > COAST_NS
        if at_row or restart:
            prior = tuple.__new__(Measurement, (
                stamp, pin.SE3(result.rotation[0], result.translation[0]),
                None if twists is None else twists[0], sigma, noise))
            if at_row:
                measurements[-1] = prior
        before, start_ns = flt._lin, flt.stamp_ns
        if at_row and not restart and len(measurements) == 1:
            gated = flt.row_at(stamp, lin, prior)  # the common row (see _process_rows)
            gated_at = self._count_gated(gated) if gated else []
        else:
            gated_at = self._filter_row(stamp, lin, prior, measurements, None)
        g = flt.g
        measured_mu = None if twists is None else \
            twist_momenta(flt, before, lin, start_ns, stamp, measurements, gated_at, g) \
            if measurements else []
        fixed_lag = {}
        lagged = self.fixed_lag
        if lagged is not None and lagged._ready:
            fixed_lag[0] = lagged.take()
        x, p = flt.x, flt.p
        # The (1, ...) columns as copies of the filter's state (the general path's stores).
        mu = x[None, :n].copy()
        rate = x[None, n:].copy()
        mu_cov = p[None, n:2 * n, n:2 * n].copy()
        w_cov = p[None, 2 * n:, 2 * n:].copy()
        peak = rate[0]
        detector = self.detector
        # ndarray.dot: the same BLAS call as @ (see _process_chunk).
        pi = (g.action if flt._whole else flt._adjoint(g)).T.dot(x[:n])[None]
        detector.update(stamp, mu[0], math.sqrt(float(peak.dot(peak))),
                        flt.wrench_significance(), flt.step_detected is not None,
                        mu_cov[0], measured_mu)
        events = {0: detector.take_notices()} if detector.notices else {}
        drift, energy = drift_energy(inverse, pi, qbar_dot, result.pbar)
        if self.robot.has_potential:
            energy += [self.robot.potential_energy(row) for row in qbar]
        extras: dict = {}
        if self.predictor.active or self._prediction_enabled():
            self._per_sample((stamp,), qbar, qbar_dot, (tau,), result, extras, rejected_at,
                             None, [g], mu, [not detector.in_event], [(x, p)])
        self.latest_state = (stamp, result.rotation[0], result.translation[0], qbar[0],
                             qbar_dot[0])
        if self.first_stamp_ns is None:
            self.first_stamp_ns = stamp
        # _accumulate_statistics of one row.
        self.processed = total = self.processed + 1
        welford_row(self._mu_mean, self._mu_m2, mu[0], total)
        self._last_mu, self._last_energy = mu[0], float(energy[0])
        if chunk.diagnose:
            previous = extras.get(0, (None, None, None))
            extras[0] = previous[:2] + (self.diagnostics(stamp),) + previous[3:]
        out = OutputChunk(self, np.array((stamp,), dtype=np.int64), mu, pi, rate, drift, qbar,
                          qbar_dot, result.pbar, energy, extras, None)
        out.mu_cov, out.w_cov = mu_cov, w_cov
        out.fixed_lag = fixed_lag
        out.events = events
        self._done.append(out)

    def _step_significance(self) -> float:
        """
        Return the false-alarm probability of the filter's wrench-step test (0: off).

        With a commanded wrench the thrusters' switches are in the command, and a
        step of the disturbance at a switch is a gain error the gain state must
        learn: the step test would take it into the disturbance instead (measured on
        the freeflyer2 PD bag: Fx gain 0.07 instead of 0.57), so it is off there.
        """
        return 0.0 if self.commanded_wrench else self.config.event_significance

    def _row_measurements(self, samples: list, stamp: int) -> tuple:
        """Return (measurements, one at the row's stamp, its sigma, noise) of a row's samples."""
        if len(samples) == 1 and samples[0][0] == stamp and len(samples[0]) == 2 \
                and samples[0][1].__class__ is not NoisyRow:
            # The common row: one base sample, at the row's own stamp, no stamp sigma and
            # no message noise (what _filter_measurements gives, without its loop).
            return [None], True, None, None
        if not samples:
            return [], False, None, None  # a row between base samples
        measurements = self._filter_measurements(samples, stamp)
        if measurements and measurements[-1] is None:
            return measurements, True, self._row_stamp_sigma, self._row_noise
        return measurements, False, None, None

    def _filter_row(self, stamp: int, lin: Linearisation, prior: Optional[Measurement],
                    measurements: list, commands: Optional[list[Optional[Command]]]) -> list:
        """Run the filter's row; count each measurement its gate refused; return their stamps."""
        return self._count_gated(self.filter.row(stamp, lin, prior, measurements, commands))

    def _count_gated(self, refused: list) -> list:
        """Count each (stamp, NIS) the innovation gate refused; return their stamps."""
        gated_at = []
        for gated, nis in refused:
            gated_at.append(gated)
            self.rejected['innovation_gate'] += 1
            self._period_rejected += 1
            self.last_rejection = (f'innovation_gate: base measurement at {gated} '
                                   f'improbable under the filter (chi-square {nis:.3g})')
        return gated_at

    def _filter_measurements(self, measured: tuple, stamp: int) -> list:
        """
        Return a row's base samples as filter measurements, in stamp order.

        The one at the row's own stamp is None: the row's base state is that
        sample, already evaluated by the kernel (the caller fills it in).
        """
        out: list = []
        odometry, kernel = self.use_odometry, self.kernel
        self._row_stamp_sigma = self._row_noise = None
        for sample in measured:
            sample_ns, row = sample[0], sample[1]
            sigma = sample[2] if len(sample) > 2 else None
            # A message covariance rides on its row (estimator/covariance.py).
            noise = row.noise if row.__class__ is NoisyRow else None
            if sample_ns == stamp:
                # The row's own sample: its stamp sigma goes with the row's prior.
                self._row_stamp_sigma, self._row_noise = sigma, noise
                out.append(None)
                continue
            twist = None
            if odometry:
                twist = np.array(row[7:13])
                if kernel.projects_twists:
                    twist = kernel.coordinates(twist[None])[0]
            out.append(Measurement(sample_ns, pin.XYZQUATToSE3(np.array(row[:7])), twist,
                                   sigma, noise))
        return out
