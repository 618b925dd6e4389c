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
What the estimator produces: one output per sample, and chunks of them column-wise.

:class:`EstimatorOutput` is the message-ready output of one processed sample (the
node's and replay's topics); :class:`OutputChunk` holds a processed chunk's
columns and makes the outputs on demand; :class:`EstimatorBatch` is what a call
of ``Estimator.add_samples`` returns. The smoothed rows' fields and columns
(``smoothed_fields``, ``SmoothedColumns``) are :mod:`.smoothed_outputs`' (importable
from here as before).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Optional

import numpy as np

from reduced_dynamics.estimator.cyclic import CyclicColumns
from reduced_dynamics.estimator.events import EventNotice
from reduced_dynamics.estimator.kernel import UpdateKernel
from reduced_dynamics.estimator.prediction import PredictionJob
from reduced_dynamics.estimator.smoothed_outputs import smoothed_fields, SmoothedColumns
from reduced_dynamics.messages.cdr_columns import (joint_state_records, stamp_columns,
                                                   vector6_records)
from reduced_dynamics.messages.samples import (Diagnostics, EventSample, JointStateSample,
                                               PosePath, ShapePrediction, trusted_sample,
                                               TwistSample, WrenchSample)

__all__ = ['COLUMN_FIELDS', 'EstimatorBatch', 'EstimatorOutput', 'event_samples', 'OutputChunk',
           'smoothed_fields', 'SmoothedColumns']


@dataclass
class EstimatorOutput:
    """What one processed sample produces (the node's and replay's output topics)."""

    stamp_ns: int
    momentum: WrenchSample
    body_momentum: WrenchSample
    shape_state: JointStateSample
    momentum_rate: WrenchSample
    drift_twist: TwistSample
    mu: np.ndarray
    energy: float
    prediction: Optional[ShapePrediction] = None
    prediction_path: Optional[PosePath] = None
    diagnostics: Optional[Diagnostics] = None
    #: second stage on: the cyclic joints' angles, rates and momenta theta (effort)
    cyclic_state: Optional[JointStateSample] = None
    #: prescribed prediction modes: the base path under the geometric phase alone
    prediction_phase_path: Optional[PosePath] = None
    #: ``Estimator(defer_predictions=True)``: the prediction started at this sample, to
    #: be computed off the input path (``job.run()`` returns its messages, see
    #: :class:`~reduced_dynamics.estimator.prediction.PredictionJob`)
    prediction_job: Optional[PredictionJob] = None
    #: ``prediction_covariance``: the base at the horizon with its covariance, the 95 %
    #: ellipsoids along the path and the shape covariance at the horizon
    #: (:mod:`reduced_dynamics.messages.uncertainty`)
    prediction_horizon: Optional[Any] = None
    prediction_ellipsoids: Optional[Any] = None
    prediction_shape_covariance: Optional[Any] = None
    #: covariance (n x n, algebra coordinates) of mu and of the wrench w
    momentum_covariance: Optional[np.ndarray] = None
    wrench_covariance: Optional[np.ndarray] = None
    #: commanded wrench on: the disturbance beyond the command (world frame); then
    #: ``momentum_rate`` is the total external wrench (disturbance + delivered command)
    disturbance: Optional[WrenchSample] = None
    #: ``smoothing_lag`` > 0: the rows whose lag passed at this sample, oldest first
    #: (:class:`~.fixed_lag.FixedLagRow`: each stamped with the time it describes)
    fixed_lag: Optional[list] = None
    #: the ``~/events`` records issued at this sample (:class:`EventSample`)
    events: Optional[list] = None


def event_samples(notices: list[EventNotice], wrenches: Any, n: int) -> list[EventSample]:
    """
    Return the ``~/events`` records of the detector's notices.

    ``wrenches``: the kernel's lift of algebra covectors (K, n) to wrenches (K, 6),
    linear, so the covariance goes through its matrix E as E^T C E.
    """
    lift = wrenches(np.eye(n))
    out = []
    for item in notices:
        impulse = np.full(6, np.nan) if item.impulse is None \
            else wrenches(item.impulse[None, :])[0]
        cov = np.full((6, 6), np.nan) if item.impulse_cov is None \
            else lift.T @ item.impulse_cov @ lift
        out.append(EventSample(item.start_ns, item.end_ns, item.detected_ns, item.window,
                               item.peak_wrench, impulse, cov, item.final))
    return out


class OutputChunk:
    """
    The outputs of one processed chunk, column-wise: row k is the k-th sample.

    ``mu``, ``pi``, ``momentum_rate``, ``drift`` (K, n) in algebra coordinates;
    ``qbar``, ``qbar_dot``, ``pbar`` (K, m); ``energy`` (K,); ``extras`` maps a
    row to its prediction, prediction path and diagnostics, where there are any.
    """

    __slots__ = ('stamps_ns', 'mu', 'pi', 'momentum_rate', 'drift', 'qbar', 'qbar_dot',
                 'pbar', 'energy', 'extras', 'cyclic', '_kernel', '_world', '_base',
                 '_names', 'mu_cov', 'w_cov', 'disturbance', 'fixed_lag', 'events')

    def __init__(self, estimator: Any, stamps_ns: np.ndarray, mu: np.ndarray,
                 pi: np.ndarray, rate: np.ndarray, drift: np.ndarray, qbar: np.ndarray,
                 qbar_dot: np.ndarray, pbar: np.ndarray, energy: np.ndarray,
                 extras: dict, cyclic: Optional[CyclicColumns] = None) -> None:
        """
        Hold the columns of a chunk (the arrays are owned by the chunk).

        ``cyclic`` (second stage): the kept-shape and cyclic columns that replace
        the shape state in :meth:`outputs`.
        """
        self.stamps_ns, self.mu, self.pi, self.momentum_rate = stamps_ns, mu, pi, rate
        self.drift, self.qbar, self.qbar_dot, self.pbar = drift, qbar, qbar_dot, pbar
        self.energy, self.extras = energy, extras
        self._kernel = estimator.kernel
        self._world = estimator.config.world_frame
        self._base = estimator.robot.base_link
        self._names = estimator.robot.shape_joint_names
        self.cyclic = cyclic
        #: covariances (K, n, n) of mu and w (set by the estimator)
        self.mu_cov: Optional[np.ndarray] = None
        self.w_cov: Optional[np.ndarray] = None
        #: commanded wrench on: the disturbance w beyond the command (K, n)
        self.disturbance: Optional[np.ndarray] = None
        #: fixed-lag smoothing on: row -> the fixed-lag rows emitted there
        self.fixed_lag: Optional[dict] = None
        #: row -> the event detector's notices issued there
        self.events: Optional[dict] = None

    def __len__(self) -> int:
        """Return the number of samples."""
        return len(self.stamps_ns)

    @property
    def kernel(self) -> UpdateKernel:
        """Return the kernel of the estimator (lifts of algebra columns to wrenches)."""
        return self._kernel

    def outputs(self) -> list[EstimatorOutput]:
        """Return one :class:`EstimatorOutput` per row (message-ready samples)."""
        if self.cyclic is None and self.disturbance is None and len(self.stamps_ns) == 1:
            return [self._one_output()]
        return self._row_outputs()

    def _row_outputs(self) -> list[EstimatorOutput]:
        """Return the outputs of any chunk, row by row (the general path)."""
        kernel = self._kernel
        # Rows of the chunk's own contiguous float64 arrays: the samples skip their
        # validation (hot path).
        momentum = kernel.wrenches(self.mu)
        body = kernel.wrenches(self.pi)
        rate = kernel.wrenches(self.momentum_rate)
        drift = kernel.twists(self.drift)
        world, base, names = self._world, self._base, self._names
        wrench, twist, joint = WrenchSample, TwistSample, JointStateSample
        extras = self.extras
        out = []
        disturbance = None if self.disturbance is None else kernel.wrenches(self.disturbance)
        cyclic, fixed_lag = self.cyclic, self.fixed_lag
        shape_columns = (self.qbar, self.qbar_dot, self.pbar) if cyclic is None \
            else (cyclic.qhat, cyclic.qhat_dot, cyclic.phat)
        if cyclic is not None:
            names = cyclic.kept_names
        # Row views by iteration: cheaper than indexing each column per sample.
        rows = zip(self.stamps_ns.tolist(), self.energy.tolist(), self.mu,
                   momentum[:, :3], momentum[:, 3:], body[:, :3], body[:, 3:],
                   *shape_columns, rate[:, :3], rate[:, 3:],
                   drift[:, :3], drift[:, 3:])
        for k, (stamp, energy, mu, force, torque, body_force, body_torque, qbar, qbar_dot,
                pbar, rate_force, rate_torque, linear, angular) in enumerate(rows):
            output = EstimatorOutput(
                stamp,
                trusted_sample(wrench, stamp, world, force, torque),
                trusted_sample(wrench, stamp, base, body_force, body_torque),
                trusted_sample(joint, stamp, '', names, qbar, qbar_dot, pbar),
                trusted_sample(wrench, stamp, world, rate_force, rate_torque),
                trusted_sample(twist, stamp, base, linear, angular),
                mu, energy)
            extra = extras.get(k) if extras else None
            if extra:
                _set_extra(output, extra)
            if cyclic is not None:
                output.cyclic_state = cyclic.sample(k, stamp)
            if self.mu_cov is not None:
                output.momentum_covariance = self.mu_cov[k]
                output.wrench_covariance = self.w_cov[k]
            if disturbance is not None:
                output.disturbance = trusted_sample(wrench, stamp, world, disturbance[k, :3],
                                                    disturbance[k, 3:])
            if fixed_lag and k in fixed_lag:
                # (A pass's columns as the rows they hold: a list, as documented.)
                output.fixed_lag = list(fixed_lag[k])
            if self.events and k in self.events:
                output.events = event_samples(self.events[k], kernel.wrenches,
                                              self.mu.shape[1])
            out.append(output)
        return out

    def _one_output(self) -> EstimatorOutput:
        """
        Return the output of a one-row chunk (streaming): :meth:`outputs` without the zip.

        The same views of the same columns (row 0 of each), so the same samples.
        """
        kernel = self._kernel
        momentum = kernel.wrenches(self.mu)[0]
        body = kernel.wrenches(self.pi)[0]
        rate = kernel.wrenches(self.momentum_rate)[0]
        drift = kernel.twists(self.drift)[0]
        world, base = self._world, self._base
        wrench = WrenchSample
        stamp = self.stamps_ns.item()
        output = EstimatorOutput(
            stamp,
            trusted_sample(wrench, stamp, world, momentum[:3], momentum[3:]),
            trusted_sample(wrench, stamp, base, body[:3], body[3:]),
            trusted_sample(JointStateSample, stamp, '', self._names, self.qbar[0],
                           self.qbar_dot[0], self.pbar[0]),
            trusted_sample(wrench, stamp, world, rate[:3], rate[3:]),
            trusted_sample(TwistSample, stamp, base, drift[:3], drift[3:]),
            self.mu[0], self.energy.item())
        extras = self.extras
        extra = extras.get(0) if extras else None
        if extra:
            _set_extra(output, extra)
        if self.mu_cov is not None:
            output.momentum_covariance = self.mu_cov[0]
            output.wrench_covariance = self.w_cov[0]
        if self.fixed_lag and 0 in self.fixed_lag:
            output.fixed_lag = list(self.fixed_lag[0])
        if self.events and 0 in self.events:
            output.events = event_samples(self.events[0], kernel.wrenches, self.mu.shape[1])
        return output

    def records(self) -> Optional[dict[str, np.ndarray]]:
        """
        Return the every-row messages as CDR columns: field -> (K, size) uint8 arrays.

        The fields (:data:`COLUMN_FIELDS`) of :meth:`outputs`' samples that every
        row carries, row k the bytes ``cdr.ENCODERS`` gives for row k's sample
        (messages/cdr_columns.py), without building the samples. None when a
        stamp is not a ROS Time (the per-message encoders then say why).
        """
        stamps = stamp_columns(self.stamps_ns)
        if stamps is None:
            return None
        kernel, world, base = self._kernel, self._world, self._base
        out = {
            'momentum': vector6_records(stamps, world, kernel.wrenches(self.mu)),
            'body_momentum': vector6_records(stamps, base, kernel.wrenches(self.pi)),
            'momentum_rate': vector6_records(stamps, world,
                                             kernel.wrenches(self.momentum_rate)),
            'drift_twist': vector6_records(stamps, base, kernel.twists(self.drift))}
        cyclic = self.cyclic
        if cyclic is None:
            out['shape_state'] = joint_state_records(stamps, '', self._names, self.qbar,
                                                     self.qbar_dot, self.pbar)
        else:
            out['shape_state'] = joint_state_records(stamps, '', cyclic.kept_names,
                                                     cyclic.qhat, cyclic.qhat_dot,
                                                     cyclic.phat)
            out['cyclic_state'] = joint_state_records(stamps, '', cyclic.cyclic_names,
                                                      cyclic.angles, cyclic.rates,
                                                      cyclic.theta)
        if self.disturbance is not None:
            out['disturbance'] = vector6_records(stamps, world,
                                                 kernel.wrenches(self.disturbance))
        return out

    def extra_fields(self, k: int) -> dict[str, Any]:
        """Return row k's occasional fields (predictions, diagnostics) that are set."""
        extra = self.extras.get(k) if self.extras else None
        if not extra:
            return {}
        holder = _Fields()
        _set_extra(holder, extra)
        return {name: value for name, value in holder.__dict__.items() if value is not None}

    def row_events(self, k: int) -> Optional[list[EventSample]]:
        """Return the ``~/events`` records of row k (None: none)."""
        if self.events and k in self.events:
            return event_samples(self.events[k], self._kernel.wrenches, self.mu.shape[1])
        return None


#: The fields of :meth:`OutputChunk.records`: every row's messages, in topic order.
COLUMN_FIELDS = ('momentum', 'body_momentum', 'shape_state', 'cyclic_state', 'momentum_rate',
                 'disturbance', 'drift_twist')


class _Fields:
    """Attribute holder for :func:`_set_extra` outside an :class:`EstimatorOutput`."""


def _set_extra(output: Any, extra: tuple) -> None:
    """Set a row's predictions and diagnostics (a chunk's ``extras`` entry) on ``output``."""
    output.prediction, output.prediction_path, output.diagnostics = extra[:3]
    if len(extra) > 3:
        output.prediction_phase_path, output.prediction_job = extra[3]
    if len(extra) > 4:
        (output.prediction_horizon, output.prediction_ellipsoids,
         output.prediction_shape_covariance) = extra[4]


class EstimatorBatch:
    """The outputs of a call of :meth:`Estimator.add_samples`: a list of chunks."""

    __slots__ = ('chunks',)

    def __init__(self, chunks: list[OutputChunk]) -> None:
        """Hold the processed chunks in order."""
        self.chunks = chunks

    def __len__(self) -> int:
        """Return the number of processed samples."""
        return sum(len(c) for c in self.chunks)

    def outputs(self) -> list[EstimatorOutput]:
        """Return the per-sample outputs, as the streaming calls would have."""
        return [o for chunk in self.chunks for o in chunk.outputs()]

    def column(self, name: str) -> np.ndarray:
        """Return one column over all chunks, by name: ``'mu'``, ``'stamps_ns'``..."""
        parts = [getattr(c, name) for c in self.chunks]
        return np.concatenate(parts) if parts else np.zeros(0)
