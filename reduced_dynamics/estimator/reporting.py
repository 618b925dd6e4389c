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
Statistics, summary and diagnostics of the estimator.

Part of :class:`~.pipeline.Estimator` (its state is set up there): the running
statistics of mu, the filter's innovation statistics, the commanded-wrench
estimate, the diagnostics message (inputs, momentum, commanded wrench,
prediction) and the summary a replay prints.
"""

from __future__ import annotations

from typing import Optional

import numpy as np

from reduced_dynamics.estimator.core.inputs import welford_row
from reduced_dynamics.estimator.events import MomentumEvent
from reduced_dynamics.estimator.outputs import event_samples
from reduced_dynamics.geometry.isotropy import isotropy_algebra
from reduced_dynamics.messages.samples import (DIAG_OK, DIAG_WARN, Diagnostics,
                                               DiagnosticStatusSample)

#: A gain off 1 by more than this (and by more than 3 sigma) makes the commanded-wrench
#: status WARN: thrusters delivering 10 % less or more than commanded.
COMMAND_GAIN_WARN = 0.1
#: A gain or bias the data cannot separate (estimator/command_gain.py), in place of a number.
UNIDENTIFIED = 'unidentified'


class Reporting:
    """
    Statistics, summary and diagnostics (a part of :class:`~.pipeline.Estimator`).

    Reads the counters of :mod:`.intake`, the filter, the detector and the
    predictor; writes nothing but the running mu statistics and the diagnostics
    period.
    """

    def _accumulate_statistics(self, mu: np.ndarray) -> None:
        """Update the running mean and squared deviations of mu (Welford; Chan et al.)."""
        count = len(mu)
        before = self.processed
        self.processed = total = before + count
        if count == 1:
            # No cancellation for a near-constant mu.
            # One compiled call (the streaming path's row): the same IEEE operations.
            welford_row(self._mu_mean, self._mu_m2, mu[0], total)
            return
        mean = mu.mean(axis=0)
        m2 = np.square(mu - mean).sum(axis=0)
        delta = mean - self._mu_mean
        self._mu_mean += delta * (count / total)
        self._mu_m2 += m2 + np.square(delta) * (before * count / total)

    def filter_statistics(self) -> dict:
        """
        Return the filter's innovation statistics.

        ``log_likelihood``: sum over the updates of log N(nu; 0, S);
        ``nis_per_dof``: mean normalised innovation squared per measured
        coordinate (1 when the noise parameters fit the data); ``innovation_gated``;
        ``pose_offsets``: runs of gated poses taken as a step of the pose sensor (a
        motion-capture body re-fitted), not as a momentum jump;
        ``filter_restarts``: re-initialisations after the covariance broke down (last
        resort, logged as a warning), ``filter_restart_causes`` by cause;
        ``burst_skipped``: base measurements left out as a burst after a stall of their
        stream (estimator/core/stalls.py);
        ``steps_taken``: wrench steps the GLR test detected and the filter took;
        ``pose_steps``: detections not taken, a step of the measured pose explaining the
        innovations better (events.py);
        ``poses_retimed``, ``retiming_restarts``: base samples given their frame time,
        restarts of the frame-clock estimate (estimator/retiming.py).
        """
        flt = self.filter
        return {'log_likelihood': flt.log_likelihood,
                'nis_per_dof': flt.nis_sum / flt.nis_dof if flt.nis_dof else None,
                'innovation_gated': flt.gated, 'pose_offsets': flt.pose_offsets,
                'filter_restarts': flt.diverged,
                'filter_restart_causes': dict(flt.restart_causes),
                'burst_skipped': flt.burst_skipped, 'steps_taken': flt.steps_taken,
                'pose_steps': flt.step_test.pose_steps,
                'poses_retimed': self._retimer.retimed,
                'retiming_restarts': self._retimer.restarts}

    def command_estimate(self) -> Optional[dict]:
        """
        Return the gain and bias of the delivered wrench with their sigmas (None: off).

        Per axis of the base group's dual (``axes``); the bias is a body wrench
        [N, N m]. The filter's latest estimate (at the end of a replay, also the
        smoothed one).
        """
        if not self.commanded_wrench:
            return None
        flt, n = self.filter, self.robot.n
        axes = _axis_names(self.robot.group)
        if flt.g is None:
            return {'axes': axes, 'samples': self._accepted_commands, 'gain': None,
                    'gain_sigma': None, 'bias': None, 'bias_sigma': None,
                    'gain_estimate': None, 'bias_estimate': None, 'gain_projections': 0}
        sigma = np.sqrt(np.diag(flt.p))
        gain_known, bias_known = flt.command_identified()
        return {'axes': axes, 'samples': self._accepted_commands,
                # What the data cannot separate is 'unidentified', not a number; the
                # filter's estimate stays in *_estimate (command_gain.py).
                'gain': [float(v) if ok else UNIDENTIFIED
                         for v, ok in zip(flt.gain, gain_known)],
                'gain_sigma': sigma[3 * n:4 * n].tolist(),
                'bias': [float(v) if ok else UNIDENTIFIED
                         for v, ok in zip(flt.bias, bias_known)],
                'bias_sigma': sigma[4 * n:].tolist(),
                'gain_estimate': flt.gain.tolist(), 'bias_estimate': flt.bias.tolist(),
                'gain_projections': flt.gain_projections}

    def diagnostics(self, stamp_ns: int) -> Diagnostics:
        """Return the estimator's status (and reset the per-period rates)."""
        period = max((stamp_ns - (self._last_diagnostics_ns or stamp_ns)) * 1e-9, 1e-9)
        self._last_diagnostics_ns = stamp_ns
        joints, bases, rejected = \
            self._period_joints, self._period_bases, self._period_rejected
        self._period_joints = self._period_bases = self._period_rejected = 0
        inputs = {'joint_state_rate_hz': f'{joints / period:.1f}',
                  'base_rate_hz': f'{bases / period:.1f}',
                  'received_joint_states': str(self.received['joint_states']),
                  'received_base': str(self.received['base']),
                  'processed': str(self.processed),
                  'rejected_total': str(sum(self.rejected.values()))}
        inputs.update({f'rejected_{k}': str(v) for k, v in sorted(self.rejected.items())})
        level = DIAG_WARN if rejected else DIAG_OK
        message = self.last_rejection if rejected else 'inputs nominal'
        if self.covariance_fallbacks:
            # A bad message covariance: the sample was used with the noise parameters.
            inputs.update({f'covariance_fallback_{k}': str(v)
                           for k, v in sorted(self.covariance_fallbacks.items())})
            if not rejected and self._period_covariance_fallbacks:
                level, message = DIAG_WARN, self.last_covariance_fallback
        self._period_covariance_fallbacks = 0
        statuses = [DiagnosticStatusSample(level, 'reduced_dynamics: inputs', message or '',
                                           self.robot.model.name, inputs)]
        if self._last_mu is not None:
            mu = self._last_mu
            iso = isotropy_algebra(self.robot.group, mu)
            flt = self.filter
            wrench = float(np.linalg.norm(flt.wrench))
            in_event = self.detector.in_event
            n = self.robot.n
            statuses.append(DiagnosticStatusSample(
                DIAG_WARN if in_event else DIAG_OK, 'reduced_dynamics: momentum',
                'external wrench event under way' if in_event else 'momentum conserved',
                self.robot.model.name,
                {'mu': ' '.join(f'{v:.6g}' for v in mu),
                 'momentum_class': iso.momentum_class.value,
                 'isotropy_dim': str(iso.dim),
                 'external_wrench_norm': f'{wrench:.6g}',
                 'external_wrench': ' '.join(f'{v:.6g}' for v in flt.wrench),
                 'external_wrench_sigma': ' '.join(
                     f'{v:.3g}' for v in np.sqrt(np.diag(flt.p)[2 * n:])),
                 'momentum_sigma': ' '.join(
                     f'{v:.3g}' for v in np.sqrt(np.diag(flt.p)[n:2 * n])),
                 'wrench_significance': f'{flt.wrench_significance():.4g}',
                 'event_threshold': f'{self.detector.start_threshold:.4g}',
                 'event_window_threshold': f'{self.detector.multiscale.threshold:.4g}',
                 'event_window_statistic':
                 f'{float(self.detector.multiscale.statistics.max()):.4g}',
                 'innovation_gated': str(flt.gated),
                 'pose_offsets': str(flt.pose_offsets),
                 'events': str(getattr(self.detector.events, 'detected',
                                       len(self.detector.events))),
                 **_last_event(self.detector.events),

                 'kinetic_plus_potential_energy': f'{self._last_energy:.9g}',
                 **self._cyclic_diagnostics()}))
        if self.commanded_wrench:
            statuses.append(self._command_status())
        statuses.append(self._prediction_status())
        return Diagnostics(stamp_ns, statuses)

    def _command_status(self) -> DiagnosticStatusSample:
        """
        Return the thruster-health status: gain and bias of the delivered wrench.

        WARN when a gain is off 1 by more than 3 sigma and more than
        COMMAND_GAIN_WARN (the delivered wrench is not what was commanded).
        """
        estimate = self.command_estimate()
        values = {'commands_received': str(self._received_commands),
                  'commands_used': str(self._accepted_commands),
                  'axes': ' '.join(estimate['axes'])}
        level, message = DIAG_OK, 'no estimate yet'
        if estimate['gain'] is not None:
            flt = self.filter
            known = np.array([v != UNIDENTIFIED for v in estimate['gain']])
            gain = np.array(estimate['gain_estimate'])
            gain_sigma = np.array(estimate['gain_sigma'])
            total, total_cov = flt.total_wrench()
            values.update({
                'gain': ' '.join(_number(v, '.4g') for v in estimate['gain']),
                'gain_sigma': ' '.join(f'{v:.3g}' for v in gain_sigma),
                'bias': ' '.join(_number(v, '.4g') for v in estimate['bias']),
                'bias_sigma': ' '.join(f'{v:.3g}' for v in estimate['bias_sigma']),
                'command': ' '.join(f'{v:.4g}' for v in flt._command),
                'disturbance': ' '.join(f'{v:.6g}' for v in flt.wrench),
                'disturbance_sigma': ' '.join(
                    f'{v:.3g}' for v in np.sqrt(np.diag(flt.wrench_cov))),
                'total_wrench': ' '.join(f'{v:.6g}' for v in total),
                'total_wrench_sigma': ' '.join(
                    f'{v:.3g}' for v in np.sqrt(np.diag(total_cov)))})
            # An unidentified gain says nothing of the thrusters' health.
            off = known & (np.abs(gain - 1.0) > 3.0 * gain_sigma) \
                & (np.abs(gain - 1.0) > COMMAND_GAIN_WARN)
            if off.any():
                level = DIAG_WARN
                message = 'delivered wrench differs from the command: ' + ', '.join(
                    f'gain {axis} {g:.3g} +- {s:.2g}' for axis, g, s, bad in
                    zip(estimate['axes'], gain, gain_sigma, off) if bad)
            else:
                message = 'delivered wrench as commanded'
        return DiagnosticStatusSample(level, 'reduced_dynamics: commanded wrench', message,
                                      self.robot.model.name, values)

    def _prediction_status(self) -> DiagnosticStatusSample:
        """Return the prediction status: mode, residuals, drift/phase split, failures."""
        predictor = self.predictor
        done = predictor.last_finished
        values = {'predictions': str(predictor.made),
                  'mode': self.config.prediction_mode,
                  'horizon_s': f'{self.config.prediction_horizon:g}',
                  'last_shape_residual_rad': 'n/a' if done is None
                  else f'{done.shape_residual:.3e}'}
        level, message = DIAG_OK, 'no finished prediction yet'
        if done is not None:
            message = 'prediction residual'
            result = done.result
            values.update({
                'last_mode': done.mode,
                'last_position_residual_m': f'{done.position_residual:.3e}',
                'last_attitude_residual_rad': f'{done.attitude_residual:.3e}',
                'last_attitude_change_rad': f'{result.attitude_change()[-1]:.6g}',
                'last_max_attitude_deviation_rad': f'{result.attitude_change().max():.6g}',
                'last_drift_twist_mean': ' '.join(f'{v:.4g}' for v in result.drift.mean(0)),
                'last_phase_twist_mean': ' '.join(f'{v:.4g}' for v in result.phase.mean(0)),
                # Evaluations, not wall time: outputs must not depend on the machine.
                'last_evaluations': str(result.evaluations)})
            phase = result.phase_attitude_change()
            if phase is not None:
                values['last_phase_attitude_change_rad'] = f'{phase[-1]:.6g}'
        statistics = predictor.statistics
        if statistics.failed:
            values['failed'] = str(statistics.failed)
            values['last_failure'] = statistics.last_failure
            if statistics.last_failed:
                level, message = DIAG_WARN, f'prediction stopped: {statistics.last_failure}'
        return DiagnosticStatusSample(level, 'reduced_dynamics: prediction', message,
                                      self.robot.model.name, values)

    def _cyclic_diagnostics(self) -> dict[str, str]:
        """Second-stage key-values: the cyclic joints and their momenta theta."""
        if self._cyclic_view is None:
            return {'second_stage': 'off'}
        theta = self._last_theta
        return {'second_stage': 'on (Theorem 57)',
                'cyclic_joints': ' '.join(self.cyclic_joints),
                'theta': 'n/a' if theta is None else ' '.join(f'{v:.6g}' for v in theta)}

    @property
    def events(self) -> list[MomentumEvent]:
        """Return the external-wrench events detected so far."""
        return self.detector.events

    def finish_events(self) -> list:
        """
        Return the ``~/events`` records still due at the end of the data.

        The last event's final record, its impulse as it stands (its settling time
        may not have passed), and any notice not yet attached to an output.
        """
        self.detector.finish()
        return event_samples(self.detector.take_notices(), self.kernel.wrenches,
                             self.robot.n)

    def summary(self) -> dict:
        """Return counts, momentum statistics, events and prediction residuals."""
        mean = self._mu_mean
        spread = np.sqrt(self._mu_m2 / max(self.processed, 1))
        statistics = self.predictor.statistics
        failures = self.prediction_failures + statistics.failure_kinds
        origin = self.first_stamp_ns or 0
        return {
            'first_stamp_ns': self.first_stamp_ns,
            'received': dict(self.received),
            'processed': self.processed,
            'rejected': dict(self.rejected),
            # base samples whose bad message covariance gave way to the noise parameters
            'covariance_fallbacks': dict(self.covariance_fallbacks),
            'clock_resets': self.clock_resets,
            'cyclic_joints': list(self.cyclic_joints),
            'mu_mean': mean.tolist(),
            'mu_spread': spread.tolist(),
            'events': [{'start_s': (e.start_ns - origin) * 1e-9,
                        'end_s': None if e.end_ns is None else (e.end_ns - origin) * 1e-9,
                        'start_stamp_ns': e.start_ns,
                        'detected_stamp_ns': e.detected_ns,
                        'impulse': None if e.impulse is None else e.impulse.tolist(),
                        'peak_wrench': e.peak_wrench,
                        'impulse_cov': None if e.impulse_cov is None
                        else e.impulse_cov.tolist(),
                        'window_s': e.window} for e in self.events],
            # every event detected (the list above: the last EVENTS_KEEP of them)
            'events_detected': getattr(self.events, 'detected', len(self.events)),
            'predictions': self.predictor.made,
            'prediction_failures': dict(failures),
            # predictions published without their covariance (prediction_covariance on: the
            # sample points diverged, e.g. right after the filter started)
            'prediction_covariance_failures': statistics.covariance_failures,
            'filter': self.filter_statistics(),
            **({'commanded_wrench': self.command_estimate()} if self.commanded_wrench else {}),
            'prediction_shape_residual_max': statistics.shape.maximum,
            'prediction_shape_residual_median': statistics.shape.median(),
            'prediction_position_residual_max': statistics.position.maximum,
            'prediction_mode': self.config.prediction_mode,
            'prediction_residuals': statistics.residuals_by_mode(),
            'trajectories_received': self.trajectories_received,
        }


def _last_event(events: list[MomentumEvent]) -> dict[str, str]:
    """Return the last event's start, end, impulse, its sigma and window (diagnostics)."""
    if not events:
        return {}
    event = events[-1]
    impulse, cov = event.impulse, event.impulse_cov
    return {'last_event_start_ns': str(event.start_ns),
            'last_event_end_ns': 'under way' if event.end_ns is None else str(event.end_ns),
            'last_event_impulse': 'n/a' if impulse is None
            else ' '.join(f'{v:.6g}' for v in impulse),
            'last_event_impulse_sigma': 'n/a' if cov is None
            else ' '.join(f'{v:.3g}' for v in np.sqrt(np.diag(cov))),
            'last_event_peak_wrench': f'{event.peak_wrench:.6g}',
            'last_event_window': 'per-sample' if event.window is None
            else f'{event.window:.3g}'}


def _axis_names(group) -> list[str]:
    """Return a name per coordinate of the group's dual (fx ... tz, or a combination)."""
    names = ('fx', 'fy', 'fz', 'tx', 'ty', 'tz')
    out = []
    for column in group.algebra_basis.T:
        nonzero = np.flatnonzero(np.abs(column) > 1e-12)
        out.append(names[nonzero[0]] if len(nonzero) == 1
                   else '+'.join(names[i] for i in nonzero))
    return out


def _number(value, spec: str) -> str:
    """Return ``value`` formatted by ``spec``, or as it is when it is not a number."""
    return value if isinstance(value, str) else format(value, spec)
