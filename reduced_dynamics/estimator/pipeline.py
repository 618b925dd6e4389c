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
The estimator pipeline: samples in, momentum, shape state, drift and predictions out.

One class serves the replay tool and the node. Per joint-state sample it pairs
the shape with the base state at the same stamp (:mod:`.sync`), evaluates the
metric once and computes mu (5.27), pi, qbar, qbar_dot, pbar (5.35), the drift
twist I^-1 pi and the geometric phase -A qbar_dot; it updates the momentum
observer (:mod:`.observer`), predicts with the reduced model at a set rate
(:mod:`.prediction`) and reports diagnostics. Bad input is rejected with a
reason and counted; it never raises.
"""

from __future__ import annotations

from collections import Counter, deque
from dataclasses import dataclass
import math
from typing import Optional, Sequence, Union

import numpy as np
import pinocchio as pin

from reduced_dynamics.estimator.config import EstimatorConfig
from reduced_dynamics.estimator.cyclic import CYCLIC_OFF, CyclicView, resolve_cyclic_joints
from reduced_dynamics.estimator.observer import MomentumEvent, MomentumObserver
from reduced_dynamics.estimator.prediction import Prediction, Predictor
from reduced_dynamics.estimator.sync import BaseBuffer, BasePoint
from reduced_dynamics.geometry.isotropy import isotropy_algebra
from reduced_dynamics.messages.samples import (
    BaseStateSample, DIAG_OK, DIAG_WARN, Diagnostics, DiagnosticStatusSample, JointStateSample,
    PosePath, ShapePrediction, trusted_sample, TwistSample, WrenchSample)
from reduced_dynamics.reduction.second_stage import CyclicSplit
from reduced_dynamics.robot.model import RobotModel

NS = 1_000_000_000


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


class _Pending:
    """A validated shape sample waiting for its base state."""

    __slots__ = ('stamp_ns', 'qbar', 'qbar_dot', 'tau')

    def __init__(self, stamp_ns: int, qbar: np.ndarray, qbar_dot: np.ndarray,
                 tau: np.ndarray) -> None:
        self.stamp_ns = stamp_ns
        self.qbar = qbar
        self.qbar_dot = qbar_dot
        self.tau = tau


class Estimator:
    """
    Streaming estimator of momentum, shape state and drift for one robot.

    ``use_odometry``: base samples carry a twist (Odometry); otherwise the twist
    is differentiated from poses. ``base_driven``: base samples drive the
    pipeline (default: when the robot has no shape joints); the shape is then
    held at its last joint state, or at rest at zero if none came.
    ``cyclic_joints``: ``''`` (first stage), ``'auto'`` (every cyclic joint of
    section 5.1), or joint names: the second stage (Theorem 57) then shapes the
    outputs, see :mod:`.cyclic`.
    """

    def __init__(self, robot: RobotModel, config: Optional[EstimatorConfig] = None,
                 use_odometry: bool = True, base_driven: Optional[bool] = None,
                 cyclic_joints: Union[str, Sequence[str]] = CYCLIC_OFF) -> None:
        """Set up the pipeline for ``robot`` (ModelError for unusable cyclic joints)."""
        self.robot = robot
        self.cyclic_joints = resolve_cyclic_joints(robot, cyclic_joints) \
            if isinstance(cyclic_joints, str) else CyclicSplit(robot, tuple(cyclic_joints)).names
        self._cyclic_view = CyclicView(robot, self.cyclic_joints) if self.cyclic_joints \
            else None
        self.shape_names = self._cyclic_view.kept_names if self._cyclic_view \
            else robot.shape_joint_names
        self.config = config or EstimatorConfig()
        self.use_odometry = use_odometry
        self.base_driven = robot.m == 0 if base_driven is None else base_driven
        self.received: Counter = Counter()
        self.rejected: Counter = Counter()
        self.last_rejection: Optional[str] = None
        self.processed = 0
        self.prediction_failures: Counter = Counter()
        self.first_stamp_ns: Optional[int] = None
        self._buffer = BaseBuffer()
        self._pending: deque[_Pending] = deque()
        self._last_joint_ns: Optional[int] = None
        self._last_base_ns: Optional[int] = None
        self._held = _Pending(0, np.zeros(robot.m), np.zeros(robot.m), np.zeros(robot.m))
        self._have_shape = robot.m == 0
        self._name_maps: dict[tuple[str, ...], object] = {}
        self._index = {name: i for i, name in enumerate(robot.shape_joint_names)}
        self._last_prediction_ns: Optional[int] = None
        self._last_diagnostics_ns: Optional[int] = None
        self._period_counts: Counter = Counter()
        self._mu_mean = np.zeros(robot.n)
        self._mu_m2 = np.zeros(robot.n)
        self._last_output: Optional[EstimatorOutput] = None
        self.apply_config(self.config)

    # --- configuration -------------------------------------------------------------
    def apply_config(self, config: EstimatorConfig) -> None:
        """Adopt new settings (validated by EstimatorConfig); the state is kept."""
        old_observer = getattr(self, 'observer', None)
        self.config = config
        self.observer = MomentumObserver(config.observer_bandwidth, config.event_threshold,
                                         config.event_hold)
        if old_observer is not None:
            self.observer.__dict__.update({k: v for k, v in old_observer.__dict__.items()
                                           if k not in ('bandwidth', 'threshold', 'hold')})
        old_predictor = getattr(self, 'predictor', None)
        self.predictor = Predictor(self.robot, config.prediction_horizon,
                                   config.prediction_step, config.prediction_integrator,
                                   config.prediction_tolerance, self.cyclic_joints)
        if old_predictor is not None:
            self.predictor.active = old_predictor.active
            self.predictor.finished = old_predictor.finished
            self.predictor.made = old_predictor.made

    # --- input -----------------------------------------------------------------------
    def reject(self, reason: str, detail: str) -> list[EstimatorOutput]:
        """Count an input rejected before it reached the pipeline (e.g. malformed)."""
        return self._reject(reason, detail)

    def _reject(self, reason: str, detail: str) -> list[EstimatorOutput]:
        self.rejected[reason] += 1
        self._period_counts['rejected'] += 1
        self.last_rejection = f'{reason}: {detail}'
        return []

    def add_joint_state(self, sample: JointStateSample) -> list[EstimatorOutput]:
        """Take a joint-state sample; return the outputs that became ready."""
        self.received['joint_states'] += 1
        self._period_counts['joint_states'] += 1
        mapping = self._name_maps.get(sample.names)
        if mapping is None:
            mapping = self._map_names(sample.names)
            self._name_maps[sample.names] = mapping
        if isinstance(mapping, str):
            reason, _, detail = mapping.partition(':')
            return self._reject(reason, detail.strip())
        if sample.velocity.size == 0 and self.robot.m:
            return self._reject('missing_velocity', 'joint state has no velocities')
        qbar = sample.position[mapping]
        qbar_dot = sample.velocity[mapping] if self.robot.m else np.zeros(0)
        tau = sample.effort[mapping] if sample.effort.size else np.zeros(self.robot.m)
        if not (np.isfinite(qbar).all() and np.isfinite(qbar_dot).all()
                and np.isfinite(tau).all()):
            return self._reject('non_finite', f'NaN or inf in joint state at {sample.stamp_ns}')
        if self._last_joint_ns is not None and sample.stamp_ns <= self._last_joint_ns:
            return self._reject('stamp_backwards', f'joint state stamp {sample.stamp_ns} <= '
                                                   f'previous {self._last_joint_ns}')
        self._last_joint_ns = sample.stamp_ns
        pending = _Pending(sample.stamp_ns, qbar, qbar_dot, tau)
        if self.base_driven:
            self._held, self._have_shape = pending, True
            return []
        self._pending.append(pending)
        return self._drain(final=False)

    def _map_names(self, names: tuple[str, ...]):
        if len(set(names)) != len(names):
            return 'duplicate_joint: joint names repeat'
        unknown = [n for n in names if n not in self._index]
        if unknown:
            return f'unknown_joint: {", ".join(unknown[:5])} not in the robot model'
        missing = [n for n in self.robot.shape_joint_names if n not in names]
        if missing:
            return f'missing_joint: {", ".join(missing[:5])} absent from the joint state'
        order = {n: i for i, n in enumerate(names)}
        return np.array([order[n] for n in self.robot.shape_joint_names], dtype=int)

    def add_base_state(self, sample: BaseStateSample) -> list[EstimatorOutput]:
        """Take a base pose (with twist for Odometry); return outputs that became ready."""
        self.received['base'] += 1
        self._period_counts['base'] += 1
        values = (sample.position, sample.orientation_xyzw, sample.twist_linear,
                  sample.twist_angular) if sample.has_twist \
            else (sample.position, sample.orientation_xyzw)
        if not np.isfinite(np.concatenate(values)).all():
            return self._reject('non_finite_base', f'NaN or inf in base state at '
                                                   f'{sample.stamp_ns}')
        x, y, z, w = sample.orientation_xyzw.tolist()
        norm = math.sqrt(x * x + y * y + z * z + w * w)
        if norm < 1e-6:
            return self._reject('invalid_quaternion', f'zero quaternion at {sample.stamp_ns}')
        if self.use_odometry and not sample.has_twist:
            return self._reject('missing_twist', 'base sample without twist (use pose mode)')
        if self._last_base_ns is not None and sample.stamp_ns <= self._last_base_ns:
            return self._reject('base_stamp_backwards', f'base stamp {sample.stamp_ns} <= '
                                                        f'previous {self._last_base_ns}')
        self._last_base_ns = sample.stamp_ns
        quat = pin.Quaternion(w / norm, x / norm, y / norm, z / norm)
        pose = self.robot.project_pose(pin.SE3(quat.toRotationMatrix(), sample.position))
        twist = None
        if self.use_odometry:
            twist6 = np.concatenate([sample.twist_linear, sample.twist_angular])
            twist = self.robot.group.twist(self.robot.group.coordinates(twist6))
        self._buffer.append(BasePoint(sample.stamp_ns, pose, twist))
        if self.base_driven:
            self._pending.append(_Pending(sample.stamp_ns, self._held.qbar,
                                          self._held.qbar_dot, self._held.tau))
        return self._drain(final=False)

    def flush(self) -> list[EstimatorOutput]:
        """Process what is still waiting (end of input) and close open predictions."""
        outputs = self._drain(final=True)
        self.predictor.finish()
        return outputs

    # --- processing ------------------------------------------------------------------
    def _drain(self, final: bool) -> list[EstimatorOutput]:
        outputs = []
        tolerance_ns = int(self.config.sync_tolerance * NS)
        needs_successor = not self.use_odometry
        while self._pending:
            head = self._pending[0]
            gap = self._buffer.nearest_gap_ns(head.stamp_ns)
            ready = self._buffer.ready(head.stamp_ns, needs_successor)
            latest = self._buffer.latest_ns
            if not ready and not final:
                newest_joint = self._last_joint_ns or head.stamp_ns
                waited = max(newest_joint, latest or 0) - head.stamp_ns
                if waited <= 4 * tolerance_ns:
                    break
            self._pending.popleft()
            if gap is None:
                self._reject('no_base_state', f'no base pose near {head.stamp_ns}')
            elif gap > tolerance_ns:
                detail = f'nearest base pose {gap * 1e-9:.3f} s from joint state {head.stamp_ns}'
                self._reject('stale_base_state', detail)
            else:
                outputs.append(self._process(head))
        return outputs

    def _process(self, sample: _Pending) -> EstimatorOutput:
        robot, group, config = self.robot, self.robot.group, self.config
        base = self._buffer.query(sample.stamp_ns)
        g = base.pose
        xi = group.coordinates(base.twist)
        qbar, qbar_dot = sample.qbar, sample.qbar_dot
        blocks = robot.metric_blocks(qbar)
        n = robot.n
        velocity = np.concatenate((xi, qbar_dot))
        momentum = blocks.mass_matrix @ velocity  # [pi; p] = M [xi; qbar_dot]
        pi = momentum[:n]
        mu = group.Ad(g.inverse()).T @ pi
        pbar = blocks.reduced_metric @ qbar_dot
        drift = blocks.solve_locked(pi)
        energy = 0.5 * float(velocity @ momentum)
        if robot.has_potential:
            energy += robot.potential_energy(qbar)
        rate = self.observer.update(sample.stamp_ns, mu)
        self.processed += 1
        if self.first_stamp_ns is None:
            self.first_stamp_ns = sample.stamp_ns
        delta = mu - self._mu_mean  # Welford: no cancellation for a near-constant mu
        self._mu_mean += delta / self.processed
        self._mu_m2 += delta * (mu - self._mu_mean)
        stamp, world, base_frame = sample.stamp_ns, config.world_frame, robot.base_link
        # One product lifts mu, pi and the rate to 6-D; rows are contiguous (3,) halves.
        wrenches = group.dual_to_wrench(np.stack((mu, pi, rate), axis=1)).T.copy()
        drift6 = group.twist(drift)
        # Every array below is a fresh contiguous float64 of the right shape, so
        # the samples skip their constructors' validation (the hot path).
        output = EstimatorOutput(
            stamp_ns=stamp,
            momentum=trusted_sample(WrenchSample, stamp, world, wrenches[0, :3],
                                    wrenches[0, 3:]),
            body_momentum=trusted_sample(WrenchSample, stamp, base_frame, wrenches[1, :3],
                                         wrenches[1, 3:]),
            shape_state=trusted_sample(JointStateSample, stamp, '', robot.shape_joint_names,
                                       qbar, qbar_dot, pbar),
            momentum_rate=trusted_sample(WrenchSample, stamp, world, wrenches[2, :3],
                                         wrenches[2, 3:]),
            drift_twist=trusted_sample(TwistSample, stamp, base_frame, drift6[:3], drift6[3:]),
            mu=mu, energy=energy)
        if self._cyclic_view is not None:
            output.shape_state, output.cyclic_state = self._cyclic_view.samples(
                stamp, blocks.mass_matrix, momentum, qbar, qbar_dot)
        self.predictor.compare(stamp, qbar, g)
        if self._prediction_due(stamp):
            self._predict(output, g, sample)
        if self._diagnostics_due(stamp):
            output.diagnostics = self.diagnostics(stamp)
        self._last_output = output
        return output

    def _prediction_due(self, stamp: int) -> bool:
        rate = self.config.prediction_rate
        if rate <= 0.0 or self.config.prediction_horizon <= 0.0:
            return False
        if self.observer.in_event or self.observer.level is None:
            return False
        if self.robot.m == 0 and self.robot.n == 0:
            return False
        last = self._last_prediction_ns
        return last is None or stamp - last >= int(NS / rate) - 1

    def _predict(self, output: EstimatorOutput, g: pin.SE3, sample: _Pending) -> None:
        self._last_prediction_ns = sample.stamp_ns
        self.observer.take_level_change()
        try:
            theta = None if output.cyclic_state is None else output.cyclic_state.effort
            prediction = self.predictor.predict(sample.stamp_ns, g, sample.qbar,
                                                sample.qbar_dot, self.observer.level,
                                                sample.tau, theta)
        except (RuntimeError, ValueError, ArithmeticError, np.linalg.LinAlgError) as error:
            # A failed prediction (e.g. a singular chart) must not stop the estimates.
            self.prediction_failures[type(error).__name__] += 1
            self.last_rejection = f'prediction failed: {error}'
            return
        output.prediction, output.prediction_path = self._prediction_messages(prediction)

    def _prediction_messages(self, prediction: Prediction) -> tuple[ShapePrediction, PosePath]:
        offsets = np.round(prediction.times * NS).astype(np.int64)
        shape = ShapePrediction(prediction.start_ns, '', self.shape_names,
                                offsets, prediction.qbar, prediction.qbar_dot)
        quats = np.array([pin.Quaternion(pose[:3, :3]).coeffs() for pose in prediction.poses])
        path = PosePath(prediction.start_ns, self.config.world_frame,
                        prediction.start_ns + offsets, prediction.poses[:, :3, 3], quats)
        return shape, path

    def _diagnostics_due(self, stamp: int) -> bool:
        rate = self.config.diagnostics_rate
        if rate <= 0.0:
            return False
        last = self._last_diagnostics_ns
        if last is None:
            self._last_diagnostics_ns = stamp
            return False
        return stamp - last >= int(NS / rate)

    # --- reporting -------------------------------------------------------------------
    def diagnostics(self, stamp_ns: int) -> Diagnostics:
        """Return the estimator's status (and reset the per-period rates)."""
        period = max((stamp_ns - (self._last_diagnostics_ns or stamp_ns)) * 1e-9, 1e-9)
        self._last_diagnostics_ns = stamp_ns
        counts, self._period_counts = self._period_counts, Counter()
        inputs = {'joint_state_rate_hz': f'{counts["joint_states"] / period:.1f}',
                  'base_rate_hz': f'{counts["base"] / period:.1f}',
                  'received_joint_states': str(self.received['joint_states']),
                  'received_base': str(self.received['base']),
                  'processed': str(self.processed),
                  'rejected_total': str(sum(self.rejected.values()))}
        inputs.update({f'rejected_{k}': str(v) for k, v in sorted(self.rejected.items())})
        level = DIAG_WARN if counts['rejected'] else DIAG_OK
        message = self.last_rejection if counts['rejected'] else 'inputs nominal'
        statuses = [DiagnosticStatusSample(level, 'reduced_dynamics: inputs', message or '',
                                           self.robot.model.name, inputs)]
        out = self._last_output
        if out is not None:
            mu = out.mu
            iso = isotropy_algebra(self.robot.group, mu)
            wrench = float(np.linalg.norm(self.observer.rate))
            in_event = self.observer.in_event
            statuses.append(DiagnosticStatusSample(
                DIAG_WARN if in_event else DIAG_OK, 'reduced_dynamics: momentum',
                'external wrench event under way' if in_event else 'momentum conserved',
                self.robot.model.name,
                {'mu': ' '.join(f'{v:.6g}' for v in mu),
                 'momentum_class': iso.momentum_class.value,
                 'isotropy_dim': str(iso.dim),
                 'external_wrench_norm': f'{wrench:.6g}',
                 'events': str(len(self.observer.events)),
                 'kinetic_plus_potential_energy': f'{out.energy:.9g}',
                 **self._cyclic_diagnostics(out)}))
        residual = self.predictor.last_residual
        statuses.append(DiagnosticStatusSample(
            DIAG_OK, 'reduced_dynamics: prediction',
            'no finished prediction yet' if residual is None else 'prediction residual',
            self.robot.model.name,
            {'predictions': str(self.predictor.made),
             'last_shape_residual_rad': 'n/a' if residual is None else f'{residual:.3e}',
             'horizon_s': f'{self.config.prediction_horizon:g}'}))
        return Diagnostics(stamp_ns, statuses)

    def _cyclic_diagnostics(self, out: EstimatorOutput) -> dict[str, str]:
        """Second-stage key-values: the cyclic joints and their momenta theta."""
        if out.cyclic_state is None:
            return {'second_stage': 'off'}
        return {'second_stage': 'on (Theorem 57)',
                'cyclic_joints': ' '.join(out.cyclic_state.names),
                'theta': ' '.join(f'{v:.6g}' for v in out.cyclic_state.effort)}

    @property
    def events(self) -> list[MomentumEvent]:
        """Return the external-wrench events detected so far."""
        return self.observer.events

    def summary(self) -> dict:
        """Return counts, momentum statistics, events and prediction residuals."""
        mean = self._mu_mean
        spread = np.sqrt(self._mu_m2 / max(self.processed, 1))
        residuals = [p.shape_residual for p in self.predictor.finished if p.compared]
        positions = [p.position_residual for p in self.predictor.finished if p.compared]
        origin = self.first_stamp_ns or 0
        return {
            'first_stamp_ns': self.first_stamp_ns,
            'received': dict(self.received),
            'processed': self.processed,
            'rejected': dict(self.rejected),
            'cyclic_joints': list(self.cyclic_joints),
            'mu_mean': mean.tolist(),
            'mu_spread': spread.tolist(),
            'events': [{'start_s': (e.start_ns - origin) * 1e-9,
                        'end_s': None if e.end_ns is None else (e.end_ns - origin) * 1e-9,
                        'start_stamp_ns': e.start_ns,
                        'impulse': None if e.impulse is None else e.impulse.tolist(),
                        'peak_wrench': e.peak_wrench} for e in self.events],
            'predictions': self.predictor.made,
            'prediction_failures': dict(self.prediction_failures),
            'prediction_shape_residual_max': max(residuals) if residuals else None,
            'prediction_shape_residual_median': float(np.median(residuals))
            if residuals else None,
            'prediction_position_residual_max': max(positions) if positions else None,
        }
