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

One class serves the replay tool and the node. A joint-state sample becomes a
row once a base sample at or after its stamp has come (:mod:`.sync`; base stamps
only increase, so every base sample up to the row is then known, whatever the
order in which the two inputs arrived). The row carries the base samples
stamped since the previous row, which the error-state Kalman filter of base
pose, momentum mu and external wrench w (:mod:`.filter`) updates with at their
own stamps, and the metric evaluated once (:mod:`.kernel`: I, A = I^-1 B,
pbar = S qbar_dot, 5.29, 5.35) as the inputs of its process model, the reduced
mechanics. From the filter's state at the row it reports mu (5.27),
pi = Ad_g^T mu, the drift twist I^-1 pi and w with covariances, detects events
from the filter's statistics (:mod:`.events`), predicts with the reduced model
at a set rate (:mod:`.prediction`) and reports diagnostics. Bad input is
rejected with a reason and counted; it never raises.

Work happens in two passes. Validation and synchronisation run per sample, in
arrival order; synchronised samples collect in a chunk, which the vectorised
kernel evaluates together before the filter steps through them. ``add_joint_state`` and
``add_base_state`` close the chunk at the end of every call (streaming: the rows
one message released); ``add_samples`` closes it every few hundred samples
(batched). A chunk is also closed where a diagnostics message is due, so that its
counters are those a sample-by-sample run would report; the two paths give
bit-identical outputs.
"""

from __future__ import annotations

from bisect import bisect_right
from collections import Counter, deque
from dataclasses import dataclass
from itertools import chain
import math
from typing import Any, Iterable, Iterator, Optional, Sequence, Union

import numpy as np
import pinocchio as pin

from reduced_dynamics.estimator.base_motion import BaseMotionAnswer, predict_base_motion
from reduced_dynamics.estimator.config import EstimatorConfig
from reduced_dynamics.estimator.cyclic import (CYCLIC_OFF, CyclicColumns, CyclicView,
                                               resolve_cyclic_joints)
from reduced_dynamics.estimator.kernel import UpdateKernel
from reduced_dynamics.estimator.events import EventDetector, MomentumEvent
from reduced_dynamics.estimator.filter import (Command, FilterState, Linearisation,
                                               Measurement, MomentumFilter, NoiseModel)
from reduced_dynamics.estimator.plausibility import BaseBounds, JointBounds
from reduced_dynamics.estimator.retiming import FrameRetimer
from reduced_dynamics.estimator.smoother import smooth_rows, SmootherFiles, StepStore
from reduced_dynamics.estimator.prediction import (
    FinishedPrediction, Plan, PredictionJob, PredictionMessages, Predictor, PRESCRIBED_MODES)
from reduced_dynamics.estimator.stamps import ACCEPTED, ClockJump, StampGate, StampResult
from reduced_dynamics.estimator.sync import BaseBuffer
from reduced_dynamics.geometry.isotropy import isotropy_algebra
from reduced_dynamics.messages.samples import (
    BaseStateSample, CommandSample, DIAG_OK, DIAG_WARN, Diagnostics, DiagnosticStatusSample,
    JointStateSample, JointTrajectorySample, PosePath, ShapePrediction, trusted_sample,
    TwistSample, WrenchSample)
from reduced_dynamics.robot.model import RobotModel

NS = 1_000_000_000
#: Synchronised samples per chunk of the batched path: enough to amortise the
#: numpy calls, few enough that the stack of mass matrices stays in cache.
CHUNK_BYTES = 512 * 1024
#: Consecutive samples at a new, self-consistent time that prove a clock jump
#: (estimator/stamps.py): fewer would follow two equal outliers, more delays outputs.
STAMP_JUMP_SAMPLES = 3
#: A gain off 1 by more than this (and by more than 3 sigma) makes the commanded-wrench
#: status WARN: thrusters delivering 10 % less or more than commanded.
COMMAND_GAIN_WARN = 0.1
#: Re-timed stamps held until their measurement is resolved: far more than the base
#: buffer holds (older ones are no longer measured anyway).
RETIMED_KEEP = 4096


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
    #: covariance (n x n, algebra coordinates) of mu and of the wrench w
    momentum_covariance: Optional[np.ndarray] = None
    wrench_covariance: Optional[np.ndarray] = None
    #: commanded wrench on: the disturbance beyond the command (world frame); then
    #: ``momentum_rate`` is the total external wrench (disturbance + delivered command)
    disturbance: Optional[WrenchSample] = None


class OutputChunk:
    """
    The outputs of one processed chunk, column-wise: row k is the k-th sample.

    ``mu``, ``pi``, ``momentum_rate``, ``drift`` (K, n) in algebra coordinates;
    ``qbar``, ``qbar_dot``, ``pbar`` (K, m); ``energy`` (K,); ``extras`` maps a
    row to its prediction, prediction path and diagnostics, where there are any.
    """

    __slots__ = ('stamps_ns', 'mu', 'pi', 'momentum_rate', 'drift', 'qbar', 'qbar_dot',
                 'pbar', 'energy', 'extras', 'cyclic', '_kernel', '_world', '_base',
                 '_names', 'mu_cov', 'w_cov', 'disturbance')

    def __init__(self, estimator: 'Estimator', stamps_ns: np.ndarray, mu: np.ndarray,
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

    def __len__(self) -> int:
        """Return the number of samples."""
        return len(self.stamps_ns)

    def outputs(self) -> list[EstimatorOutput]:
        """Return one :class:`EstimatorOutput` per row (message-ready samples)."""
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
        cyclic = self.cyclic
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
                output.prediction, output.prediction_path, output.diagnostics = extra[:3]
                if len(extra) > 3:
                    output.prediction_phase_path, output.prediction_job = extra[3]
            if cyclic is not None:
                output.cyclic_state = cyclic.sample(k, stamp)
            if self.mu_cov is not None:
                output.momentum_covariance = self.mu_cov[k]
                output.wrench_covariance = self.w_cov[k]
            if disturbance is not None:
                output.disturbance = trusted_sample(wrench, stamp, world, disturbance[k, :3],
                                                    disturbance[k, 3:])
            out.append(output)
        return out


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


class _Chunk:
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


class _Identity:
    """Name-mapping marker: the joint state lists the joints in model order."""


_IDENTITY = _Identity()


def _all_finite(*arrays: np.ndarray) -> bool:
    """Return whether every entry is finite (the exact test behind a non-finite sum)."""
    return all(bool(np.isfinite(array).all()) for array in arrays)


Sample = Union[JointStateSample, BaseStateSample, CommandSample]


def noise_model(config: EstimatorConfig) -> NoiseModel:
    """Return the filter's noise model from the estimator settings."""
    return NoiseModel(pose_position=config.pose_position_noise,
                      pose_angle=config.pose_angle_noise,
                      twist_linear=config.twist_linear_noise,
                      twist_angular=config.twist_angular_noise,
                      joint_velocity=config.joint_velocity_noise,
                      jerk_linear=config.wrench_jerk_linear,
                      jerk_angular=config.wrench_jerk_angular,
                      pose_stamp=config.pose_stamp_noise,
                      command_gain=config.command_gain_sigma,
                      command_gain_drift=config.command_gain_drift,
                      command_bias_linear=config.command_bias_linear,
                      command_bias_angular=config.command_bias_angular,
                      disturbance_linear=config.disturbance_jerk_linear,
                      disturbance_angular=config.disturbance_jerk_angular)


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

    ``commanded_wrench``: commanded-wrench samples (:meth:`add_command`, body
    frame) enter the filter's process model (:mod:`.filter`: gain and bias of the
    delivered wrench, w the disturbance beyond it); ``momentum_rate`` is then
    the total external wrench and ``disturbance`` the part beyond the command.

    ``defer_predictions`` (the node): an output where a prediction starts
    carries ``prediction_job`` (:class:`~.prediction.PredictionJob`) instead of
    the prediction messages; ``job.run()`` computes them (thread-safe, its own
    Pinocchio Data; the first call computes, later ones return the same
    messages) and returns ``PredictionMessages(shape, path, phase_path)`` or
    None if the prediction failed or ran out of budget. The messages equal
    those computed inline (replay); residuals and diagnostics do not depend on
    when a job ran (the estimator runs it itself when its horizon has passed).
    """

    def __init__(self, robot: RobotModel, config: Optional[EstimatorConfig] = None,
                 use_odometry: bool = True, base_driven: Optional[bool] = None,
                 cyclic_joints: Union[str, Sequence[str]] = CYCLIC_OFF,
                 defer_predictions: bool = False, commanded_wrench: bool = False) -> None:
        """Set up the pipeline for ``robot`` (ModelError for unusable cyclic joints)."""
        self.robot = robot
        self.commanded_wrench = commanded_wrench
        self.defer_predictions = defer_predictions
        #: the latest processed state (stamp, rotation, translation, qbar, qbar_dot)
        self.latest_state: Optional[tuple] = None
        self.trajectories_received = 0
        self.cyclic_joints = resolve_cyclic_joints(robot, cyclic_joints)
        self._cyclic_view = CyclicView(robot, self.cyclic_joints) if self.cyclic_joints \
            else None
        self.shape_names = self._cyclic_view.kept_names if self._cyclic_view \
            else robot.shape_joint_names
        self._last_theta: Optional[np.ndarray] = None
        self.kernel = UpdateKernel(robot)
        self.config = config or EstimatorConfig()
        self.use_odometry = use_odometry
        self.base_driven = robot.m == 0 if base_driven is None else base_driven
        # Inputs taken, by kind (see :attr:`received`): plain ints on the hot path.
        self._received_joints = self._received_bases = 0
        self.rejected: Counter = Counter()
        self.last_rejection: Optional[str] = None
        self.processed = 0
        self.prediction_failures: Counter = Counter()
        self.first_stamp_ns: Optional[int] = None
        self._buffer = BaseBuffer()
        #: stamp up to which base samples went to the filter (with the row at that stamp)
        self._measured_ns: Optional[int] = None
        self._pending: deque[tuple] = deque()
        self._last_joint_ns: Optional[int] = None
        self._last_base_ns: Optional[int] = None
        self._empty = np.zeros(0)
        self._m = robot.m
        self._zeros_m = np.zeros(robot.m)
        self._held = (0, self._zeros_m, self._zeros_m, self._zeros_m)
        self._have_shape = robot.m == 0
        self._name_maps: dict[tuple[str, ...], object] = {}
        self._index = {name: i for i, name in enumerate(robot.shape_joint_names)}
        self._floating = robot.base_joint_type == 'floating'
        self._project_twists = self.kernel.projects_twists
        self._last_prediction_ns: Optional[int] = None
        self._last_diagnostics_ns: Optional[int] = None
        # Inputs since the last diagnostics: joint states, base states, rejections
        # (plain ints, not a Counter: they change on every sample).
        self._period_joints = self._period_bases = self._period_rejected = 0
        self._mu_mean = np.zeros(robot.n)
        self._mu_m2 = np.zeros(robot.n)
        self._last_mu: Optional[np.ndarray] = None
        self._last_energy = 0.0
        self._chunk = _Chunk()
        self._chunk_limit = 1  # streaming; add_samples raises it
        self._batch_limit = max(16, CHUNK_BYTES // (8 * robot.model.nv ** 2))
        # Resolved samples in the open chunk when the last rejection was counted
        # (a failed prediction must not hide a later rejection, nor the reverse).
        self._rejected_at = 0
        self._done: list[OutputChunk] = []
        #: keep the filter's steps for :meth:`smoothed_rows` (see :meth:`enable_smoothing`)
        self.record_steps = False
        self.smoother_files: Optional[SmootherFiles] = None
        # Input gates (estimator/stamps.py, estimator/plausibility.py).
        self._joint_gate = StampGate('joint state', NS, 3)
        self._base_gate = StampGate('base', NS, 3)
        # One clock: a stream's first stamp is judged by the other stream's last.
        self._joint_gate.peer, self._base_gate.peer = self._base_gate, self._joint_gate
        # Commanded wrench: its own stream on the same clock, the held commands (stamps
        # ascending, values in dual coordinates) and where the next step starts.
        self._command_gate = StampGate('command', NS, 3)
        # Re-timing of a periodic pose source stamped on receipt (estimator/retiming.py);
        # the stamps it re-timed, until their measurement is resolved.
        self._retimer = FrameRetimer('off')
        self._retimed_ns: deque[tuple[int, float]] = deque(maxlen=RETIMED_KEEP)
        self._row_stamp_sigma: Optional[float] = None
        self._command_gate.peer = self._base_gate
        self._received_commands = self._accepted_commands = 0
        self._command_stamps: list[int] = []
        self._command_values: list[np.ndarray] = []
        self._command_from_ns: Optional[int] = None
        self._command_zero = np.zeros(robot.n)
        self._command_scale: Optional[np.ndarray] = None
        self._joint_bounds: dict[tuple[str, ...], JointBounds] = {}
        #: Clock restarts so far (a backwards jump, :meth:`reset`), and the last reason.
        self.clock_resets = 0
        self.last_reset: Optional[str] = None
        self.apply_config(self.config)

    # --- configuration -------------------------------------------------------------
    def apply_config(self, config: EstimatorConfig) -> None:
        """Adopt new settings (validated by EstimatorConfig); the state is kept."""
        self.config = config
        self._tolerance_ns = int(config.sync_tolerance * NS)
        # Input gates: bounds per joint-name order are rebuilt lazily.
        outlier_ns = int(config.stamp_outlier_tolerance * NS)
        self._joint_gate.configure(outlier_ns, STAMP_JUMP_SAMPLES)
        self._base_gate.configure(outlier_ns, STAMP_JUMP_SAMPLES)
        self._command_gate.configure(outlier_ns, STAMP_JUMP_SAMPLES)
        self._retimer.configure(config.pose_retiming, min(config.pose_retimed_stamp_noise,
                                                          config.pose_stamp_noise))
        self._joint_bounds = {}
        self._base_bounds = BaseBounds(config)
        rate = config.diagnostics_rate
        self._diagnostics_period_ns = int(NS / rate) if rate > 0.0 else None
        self.noise = noise_model(config)
        old_filter = getattr(self, 'filter', None)
        self.filter = MomentumFilter(self.robot.group, self.noise, config.innovation_gate,
                                     record=self.record_steps, command=self.commanded_wrench,
                                     step_significance=self._step_significance())
        if old_filter is not None:
            # New noise and gate; the estimate and the recorded steps stay.
            for name in ('g', 'x', 'p', 'stamp_ns', 'steps', 'gated', 'log_likelihood',
                         'nis_sum', 'nis_dof', '_lin', '_gated_run', '_gated_residuals',
                         'pose_offsets', '_stamp_twist', '_stamp_twist_ns', 'diverged'):
                setattr(self.filter, name, getattr(old_filter, name))
            if self.commanded_wrench:
                self.filter._command = old_filter._command
        old_detector = getattr(self, 'detector', None)
        self.detector = EventDetector(self.robot.n, config.event_significance,
                                      config.event_hold)
        if old_detector is not None:
            self.detector.events = old_detector.events
        old_predictor = getattr(self, 'predictor', None)
        self.predictor = Predictor(self.robot, config.prediction_horizon,
                                   config.prediction_step, config.prediction_integrator,
                                   config.prediction_tolerance, self.cyclic_joints,
                                   config.prediction_mode, config.prediction_max_evaluations,
                                   config.prediction_max_wall_time, config.world_frame,
                                   self.shape_names)
        if old_predictor is not None:
            self.predictor.adopt(old_predictor)

    @property
    def received(self) -> Counter:
        """Return how many joint-state and base samples came in (a fresh Counter)."""
        counts = Counter()
        if self._received_joints:
            counts['joint_states'] = self._received_joints
        if self._received_bases:
            counts['base'] = self._received_bases
        if self._received_commands:
            counts['command'] = self._received_commands
        return counts

    # --- input -----------------------------------------------------------------------
    def reject(self, reason: str, detail: str) -> list[EstimatorOutput]:
        """Count an input rejected before it reached the pipeline (e.g. malformed)."""
        return self._reject(reason, detail)

    def _reject(self, reason: str, detail: str) -> list[EstimatorOutput]:
        self.rejected[reason] += 1
        self._period_rejected += 1
        self.last_rejection = f'{reason}: {detail}'
        self._rejected_at = len(self._chunk.rows)
        return []

    def add_joint_state(self, sample: JointStateSample) -> list[EstimatorOutput]:
        """Take a joint-state sample; return the outputs that became ready."""
        # The rows one message releases (e.g. the joint states that waited for the
        # next odometry) are updated as one chunk: the same outputs, fewer calls.
        self._chunk_limit = self._batch_limit
        try:
            self._take_joint(sample)
        finally:
            self._chunk_limit = 1
        return self._close_streaming()

    def add_base_state(self, sample: BaseStateSample) -> list[EstimatorOutput]:
        """Take a base pose (with twist for Odometry); return outputs that became ready."""
        self._chunk_limit = self._batch_limit
        try:
            self._take_base(sample)
        finally:
            self._chunk_limit = 1
        return self._close_streaming()

    def add_command(self, sample: CommandSample) -> list[EstimatorOutput]:
        """
        Take a commanded wrench (body frame), held until the next (zero-order hold).

        Only an estimator built with ``commanded_wrench=True`` uses it; others
        count it as rejected (``command_unused``). It applies from its stamp on;
        one arriving after samples it should have applied to applies from the
        next processed sample on (what the node and replay both see).
        """
        self._take_command(sample)
        return self._close_streaming()

    def add_samples(self, samples: Iterable[Sample]) -> EstimatorBatch:
        """
        Take joint-state, base (and command) samples in arrival order (the batched path).

        Equivalent to calling :meth:`add_joint_state` / :meth:`add_base_state` /
        :meth:`add_command` on each in turn, with the same outputs, rejections and
        events, but the update is vectorised over chunks of samples.
        """
        take_joint, take_base = self._take_joint, self._take_base
        self._chunk_limit = self._batch_limit
        try:
            for sample in samples:
                if sample.__class__ is JointStateSample or isinstance(sample, JointStateSample):
                    take_joint(sample)
                elif sample.__class__ is CommandSample:
                    self._take_command(sample)
                else:
                    take_base(sample)
            self._process_chunk()
        finally:
            self._chunk_limit = 1
        return self._take_done()

    def flush(self) -> list[EstimatorOutput]:
        """Process what is still waiting (end of input) and close open predictions."""
        return self.flush_batch().outputs()

    def flush_batch(self) -> EstimatorBatch:
        """Like :meth:`flush`, returning the outputs column-wise."""
        # Candidates the stamp policy still holds were never confirmed: outliers.
        for gate, prefix in ((self._joint_gate, 'stamp_'), (self._base_gate, 'base_stamp_'),
                             (self._command_gate, 'command_stamp_')):
            for _, reason, detail in gate.finish():
                self._reject(prefix + reason, detail)
        self._drain(final=True)
        self._process_chunk()
        self.predictor.finish()
        return self._take_done()

    def _close_streaming(self) -> list[EstimatorOutput]:
        self._process_chunk()
        done = self._done
        if not done:
            return []
        self._done = []
        return done[0].outputs() if len(done) == 1 else [o for c in done for o in c.outputs()]

    def _take_done(self) -> EstimatorBatch:
        done, self._done = self._done, []
        return EstimatorBatch(done)

    def _take_joint(self, sample: JointStateSample) -> None:
        # Hot path (every message): locals over repeated attribute lookups.
        self._received_joints += 1
        self._period_joints += 1
        names = sample.names
        mapping = self._name_maps.get(names)
        if mapping is None:
            mapping = self._name_maps[names] = self._map_names(names)
        if mapping.__class__ is str:
            reason, _, detail = mapping.partition(':')
            self._reject(reason, detail.strip())
            return
        m = self._m
        stamp = sample.stamp_ns
        position, velocity, effort = sample.position, sample.velocity, sample.effort
        if m and not velocity.size:
            self._reject('missing_velocity', 'joint state has no velocities')
            return
        if m:
            # Names match the model one to one, so checking whole arrays is checking qbar.
            # A finite sum proves every entry finite; otherwise the exact test decides
            # (finite values can overflow the sum).
            values = position.tolist(), velocity.tolist(), effort.tolist()
            if not math.isfinite(sum(values[0]) + sum(values[1]) + sum(values[2])) \
                    and not _all_finite(position, velocity, effort):
                self._reject('non_finite', f'NaN or inf in joint state at {stamp}')
                return
            # Plausibility gate (estimator/plausibility.py): URDF limits and bounds.
            bounds = self._joint_bounds.get(names)
            if bounds is None:
                bounds = self._joint_bounds[names] = JointBounds(self.robot, self.config,
                                                                 names)
            verdict = bounds.check(*values)
            if verdict is not None:
                self._reject(*verdict)
                return
        if not m:
            empty = self._empty
            pending = (stamp, empty, empty, empty)
        elif mapping is _IDENTITY:
            # Kept by reference: the chunk copies them when it stacks its rows.
            pending = (stamp, position, velocity, effort if effort.size else self._zeros_m)
        else:
            pending = (stamp, position[mapping], velocity[mapping],
                       effort[mapping] if effort.size else self._zeros_m)
        # Stamp policy (estimator/stamps.py): outliers dropped, clock jumps followed.
        result = self._joint_gate.offer(stamp, sample.receive_ns, pending)
        if result is not ACCEPTED:
            self._stamp_result(result, True)
            return
        self._accept_joint(pending)

    def _accept_joint(self, pending: tuple) -> None:
        """Queue a joint sample whose stamp the stamp policy accepted."""
        stamp = self._last_joint_ns = pending[0]
        if self.base_driven:
            self._held, self._have_shape = pending, True
            return
        waiting = self._pending
        waiting.append(pending)
        if len(waiting) == 1:
            latest = self._buffer.latest_ns
            if latest is None or latest < stamp:
                # Alone and newer than every base state: it waits (as _drain would find).
                return
        self._drain(final=False)

    def _map_names(self, names: tuple[str, ...]):
        if len(set(names)) != len(names):
            return 'duplicate_joint: joint names repeat'
        unknown = [n for n in names if n not in self._index]
        if unknown:
            return f'unknown_joint: {", ".join(unknown[:5])} not in the robot model'
        missing = [n for n in self.robot.shape_joint_names if n not in names]
        if missing:
            return f'missing_joint: {", ".join(missing[:5])} absent from the joint state'
        if names == self.robot.shape_joint_names:
            return _IDENTITY
        order = {n: i for i, n in enumerate(names)}
        return np.array([order[n] for n in self.robot.shape_joint_names], dtype=int)

    def _take_base(self, sample: BaseStateSample) -> None:
        # Hot path (every message): plain floats and locals, few numpy calls.
        self._received_bases += 1
        self._period_bases += 1
        stamp = sample.stamp_ns
        row = sample.position.tolist()
        x, y, z, w = quaternion = sample.orientation_xyzw.tolist()
        linear = sample.twist_linear
        twist = [] if linear is None else linear.tolist() + sample.twist_angular.tolist()
        if not math.isfinite(sum(row) + sum(quaternion) + sum(twist)) \
                and not all(map(math.isfinite, row + quaternion + twist)):
            self._reject('non_finite_base', f'NaN or inf in base state at {stamp}')
            return
        norm = math.sqrt(x * x + y * y + z * z + w * w)
        if norm < 1e-6:
            self._reject('invalid_quaternion', f'zero quaternion at {stamp}')
            return
        odometry = self.use_odometry
        if odometry and linear is None:
            self._reject('missing_twist', 'base sample without twist (use pose mode)')
            return
        # Plausibility gate (estimator/plausibility.py): quaternion norm, position, twist.
        verdict = self._base_bounds.check(row, norm, twist)
        if verdict is not None:
            self._reject(*verdict)
            return
        row += (x / norm, y / norm, z / norm, w / norm)
        if not self._floating:
            pose = self.robot.project_pose(pin.XYZQUATToSE3(np.array(row)))
            row = pin.SE3ToXYZQUAT(pose).tolist()
        if odometry:
            if self._project_twists:
                # Only the part of the twist inside the base group's algebra is kept.
                kernel = self.kernel
                twist = kernel.twists(kernel.coordinates(np.array([twist])))[0].tolist()
            row += twist
        # Stamp policy (estimator/stamps.py): outliers dropped, clock jumps followed.
        result = self._base_gate.offer(stamp, sample.receive_ns, (stamp, row))
        if result is not ACCEPTED:
            self._stamp_result(result, False)
            return
        self._accept_base((stamp, row))

    def _accept_base(self, item: tuple) -> None:
        """Buffer a base sample whose stamp the stamp policy accepted."""
        stamp, row = item
        odometry = self.use_odometry
        if self._retimer.mode != 'off':
            # The filter takes the frame time of a re-timed pose (estimator/retiming.py).
            stamp, sigma = self._retimer.retime(stamp)
            if sigma is not None:
                self._retimed_ns.append((stamp, sigma))
        self._last_base_ns = stamp
        self._buffer.append(stamp, row)
        pending = self._pending
        if self.base_driven:
            pending.append((stamp,) + self._held[1:])
        if odometry and len(pending) == 1 and pending[0][0] == stamp:
            # The one waiting shape sample has this very stamp (simulators, drivers on
            # one clock tick): _drain would find gap 0, ready, and this row. Skip it.
            self._resolve(pending.popleft() + (row, self._measurements(stamp)))
            return
        self._drain(final=False)

    # --- commanded wrench ----------------------------------------------------------------
    def _take_command(self, sample: CommandSample) -> None:
        """Validate a commanded wrench (finite, plausible, stamp policy) and hold it."""
        self._received_commands += 1
        stamp = sample.stamp_ns
        if not self.commanded_wrench:
            self._reject('command_unused', 'commanded wrench given to an estimator '
                                           'without commanded_wrench')
            return
        wrench = np.concatenate((sample.force, sample.torque))
        if not _all_finite(wrench):
            self._reject('non_finite_command', f'NaN or inf in commanded wrench at {stamp}')
            return
        u = self.robot.group.dual_coordinates(wrench)
        if self._command_scale is None:
            # I^-1 at zero shape: the bound is an acceleration, the same at any mass.
            zero = np.zeros((1, self.robot.m))
            locked = self.kernel.mass_matrices(zero)[0][:self.robot.n, :self.robot.n]
            self._command_scale = np.linalg.inv(locked)
        acceleration = np.abs(self._command_scale @ u)
        if float(acceleration.max(initial=0.0)) > self.config.command_acceleration_bound:
            self._reject('command_bound', f'commanded wrench at {stamp} asks for a body '
                                          f'acceleration of {acceleration.max():.3g} '
                                          f'(bound {self.config.command_acceleration_bound:g})')
            return
        result = self._command_gate.offer(stamp, sample.receive_ns, (stamp, u))
        if result is not ACCEPTED:
            self._stamp_result(result, None)
            return
        self._accept_command((stamp, u))

    def _accept_command(self, item: tuple) -> None:
        """Hold a command whose stamp the stamp policy accepted (stamps ascend)."""
        stamp, u = item
        self._accepted_commands += 1
        if self._command_stamps and stamp <= self._command_stamps[-1]:
            # The command stream's own clock jumped back (its gate followed it): the
            # held commands are of the old time.
            self._command_stamps, self._command_values = [], []
        self._command_stamps.append(stamp)
        self._command_values.append(u)

    def _command_at(self, index: int) -> np.ndarray:
        """Return the command held at entry ``index - 1`` (zero before the first)."""
        return self._command_values[index - 1] if index > 0 else self._command_zero

    def _command_input(self, stamp: int) -> Command:
        """
        Return the command over the step that ends at ``stamp`` (zero-order hold).

        ``mean``: its exact mean over [previous sample, stamp]; ``now``: the value
        held at ``stamp``. Commands before the step's start are forgotten.
        """
        stamps, values = self._command_stamps, self._command_values
        start, self._command_from_ns = self._command_from_ns, stamp
        end_index = bisect_right(stamps, stamp)
        now = self._command_at(end_index)
        if start is None or stamp <= start:
            mean = now
        else:
            index = bisect_right(stamps, start)
            mean = now
            if index < end_index:
                # Piecewise constant over [start, stamp]: the switches in between.
                total = self._command_at(index) * float(stamps[index] - start)
                for k in range(index, end_index):
                    until = stamps[k + 1] if k + 1 < end_index else stamp
                    total = total + values[k] * float(until - stamps[k])
                mean = total / float(stamp - start)
        if end_index > 1:
            del stamps[:end_index - 1], values[:end_index - 1]
        return Command(mean, now)

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
                    'gain_sigma': None, 'bias': None, 'bias_sigma': None}
        sigma = np.sqrt(np.diag(flt.p))
        return {'axes': axes, 'samples': self._accepted_commands,
                'gain': flt.gain.tolist(), 'gain_sigma': sigma[3 * n:4 * n].tolist(),
                'bias': flt.bias.tolist(), 'bias_sigma': sigma[4 * n:].tolist()}

    # --- stamp policy and clock restarts (estimator/stamps.py) -----------------------
    def _stamp_result(self, result: StampResult, joint: Optional[bool]) -> None:
        """
        Apply a stamp decision of the joint (or base) stream: drops, a jump, accepts.

        ``joint`` None: the command stream, whose jumps restart nothing (its
        commands are held by stamp; the sensor streams own the clock).
        """
        if joint is None:
            prefix, accept = 'command_stamp_', self._accept_command
        else:
            prefix, accept = ('stamp_', self._accept_joint) if joint \
                else ('base_stamp_', self._accept_base)
        for _, reason, detail in result.dropped:
            self._reject(prefix + reason, detail)
        if result.jump is not None and joint is not None:
            self._clock_jump(result.jump, joint)
        for item in result.accepted:
            accept(item)

    def _clock_jump(self, jump: ClockJump, joint: bool) -> None:
        """
        Follow a confirmed clock jump of one stream.

        Forward, nothing restarts (a gap; the other stream confirms its own
        jump). Backwards, the estimator restarts its clock and the other
        stream re-anchors on the new time, releasing what it held.
        """
        if not jump.backwards:
            return
        self._restart_clock(f'{jump.stream} clock jumped back '
                            f'{(jump.from_ns - jump.to_ns) * 1e-9:.6g} s')
        other = self._base_gate if joint else self._joint_gate
        self._stamp_result(other.follow(jump.to_ns, jump.to_receive_ns), not joint)

    def reset(self, reason: str) -> list[EstimatorOutput]:
        """
        Restart the estimator's clock (e.g. ROS time jumped back); return ready outputs.

        What waits at the old time is processed first; then every time-dependent
        state is forgotten (base buffer, last stamps, the filter's state, open
        predictions, prediction and diagnostics times). The momentum level,
        events and counters stay. Samples the stamp policy held are re-judged
        against the new clock.
        """
        held = [(self._joint_gate.restart(), True), (self._base_gate.restart(), False)]
        if self.commanded_wrench:
            held.append((self._command_gate.restart(), None))
        self._restart_clock(reason)
        accepts = {True: self._accept_joint, False: self._accept_base,
                   None: self._accept_command}
        gates = {True: self._joint_gate, False: self._base_gate, None: self._command_gate}
        for items, joint in held:
            gate = gates[joint]
            for stamp, receive, item in items:
                result = gate.offer(stamp, receive, item)
                if result is ACCEPTED:
                    accepts[joint](item)
                else:
                    self._stamp_result(result, joint)
        return self._close_streaming()

    def _restart_clock(self, reason: str) -> None:
        self._drain(final=True)
        self._process_chunk()
        self.predictor.finish()
        self.predictor.forget_history()
        self._buffer = BaseBuffer()
        self._measured_ns = None
        self._retimer.restart()
        self._retimed_ns.clear()
        self._last_joint_ns = self._last_base_ns = None
        self._last_prediction_ns = self._last_diagnostics_ns = None
        # The filter restarts from the next sample (its recorded steps stay, the
        # smoother sees the restart); detected events stay reported.
        old = self.filter
        config = self.config
        self.filter = MomentumFilter(self.robot.group, self.noise, config.innovation_gate,
                                     record=self.record_steps, command=self.commanded_wrench,
                                     step_significance=self._step_significance())
        if self.commanded_wrench:
            # The held commands belong to the old clock; the command stream re-anchors.
            self._command_stamps, self._command_values = [], []
            self._command_from_ns = None
            self._command_gate.restart()
        for name in ('steps', 'gated', 'log_likelihood', 'nis_sum', 'nis_dof', 'diverged'):
            setattr(self.filter, name, getattr(old, name))
        events = self.detector.events
        self.detector = EventDetector(self.robot.n, config.event_significance,
                                      config.event_hold)
        self.detector.events = events
        self.clock_resets += 1
        self.last_reset = reason

    # --- processing ------------------------------------------------------------------
    def _drain(self, final: bool) -> None:
        pending = self._pending
        if not pending:
            return
        buffer, tolerance_ns = self._buffer, self._tolerance_ns
        needs_successor = False
        while pending:
            head = pending[0]
            stamp = head[0]
            gap, ready, index = buffer.status(stamp, needs_successor)
            if not ready and not final:
                newest_joint = self._last_joint_ns or stamp
                waited = max(newest_joint, buffer.latest_ns or 0) - stamp
                if waited <= 4 * tolerance_ns:
                    break
            pending.popleft()
            if gap is None:
                self._reject('no_base_state', f'no base pose near {stamp}')
            elif gap > tolerance_ns:
                detail = f'nearest base pose {gap * 1e-9:.3f} s from joint state {stamp}'
                self._reject('stale_base_state', detail)
            else:
                self._resolve(head + (buffer.query(stamp, index), self._measurements(stamp)))

    def _measurements(self, stamp_ns: int) -> tuple:
        """
        Return the base samples (stamp_ns, row) stamped after the previous row, up to ``stamp_ns``.

        Called when the row is resolved, i.e. when the buffer holds a base sample
        at or after ``stamp_ns`` (base stamps only increase): every sample up to the
        row has arrived, whatever the order in which the two streams came in.
        """
        after, self._measured_ns = self._measured_ns, stamp_ns
        samples = self._buffer.between(after, stamp_ns)
        queue = self._retimed_ns
        if not queue or queue[0][0] > stamp_ns:
            return samples
        # Re-timed samples carry their stamp sigma as a third entry (resolved per sample
        # in arrival order: the same in the streaming and batched paths).
        sigmas = {}
        while queue and queue[0][0] <= stamp_ns:
            retimed, sigma = queue.popleft()
            sigmas[retimed] = sigma
        return tuple((s, row, sigmas[s]) if s in sigmas else (s, row) for s, row in samples)

    def _resolve(self, row: tuple) -> None:
        """Queue a synchronised sample for the update (processing it where it must be)."""
        chunk = self._chunk
        chunk.rows.append(row)
        if self.commanded_wrench:
            # The commands known now (arrival order), whatever the chunk's length: one per
            # filter step of the row (to each base measurement before it, then to it).
            stamp = row[0]
            command_input = self._command_input
            chunk.commands.append([command_input(sample[0]) for sample in row[5]
                                   if sample[0] < stamp] + [command_input(stamp)])
        period = self._diagnostics_period_ns
        if period is not None:
            # Diagnostics report the counters at their sample: close the chunk there.
            last = self._last_diagnostics_ns
            if last is None:
                self._last_diagnostics_ns = row[0]
            elif row[0] - last >= period:
                chunk.diagnose = True
                self._process_chunk()
                return
        if len(chunk.rows) >= self._chunk_limit:
            self._process_chunk()

    def _process_chunk(self) -> None:
        chunk = self._chunk
        count = len(chunk.rows)
        if not count:
            return
        # A new chunk first: if the update raises, these samples are lost, not retried.
        self._chunk = _Chunk()
        rejected_at, self._rejected_at = self._rejected_at, 0
        m, n = self.robot.m, self.robot.n
        stamp_list, qbar, qbar_dot, taus, bases, measured = zip(*chunk.rows)
        stamps = np.array(stamp_list, dtype=np.int64)
        # The cheapest ways to stack these rows (arrays; lists of 13 floats).
        qbar = np.concatenate(qbar).reshape(count, m)
        qbar_dot = np.concatenate(qbar_dot).reshape(count, m)
        bases = np.fromiter(chain.from_iterable(bases), float, count * 13).reshape(count, 13)
        result = self.kernel.filter_inputs(qbar, qbar_dot, bases,
                                           self.config.joint_velocity_noise ** 2)
        inverse = result.inverse
        lins = [Linearisation(*row) for row in zip(result.locked, inverse, result.connection_qd,
                                                   result.joint_cov)]
        # The recursion, one sample at a time (the same code whatever the chunk).
        flt, detector, adjoint = self.filter, self.detector, self.filter._adjoint
        twists = result.xi if self.use_odometry else None
        mu = np.empty((count, n))
        rate = np.empty((count, n))
        pi = np.empty((count, n))
        mu_cov = np.empty((count, n, n))
        w_cov = np.empty((count, n, n))
        poses: list[pin.SE3] = []
        quiet: list[bool] = []
        rotation, translation = result.rotation, result.translation
        commands = chunk.commands if self.commanded_wrench else None
        disturbance = None if commands is None else np.empty((count, n))
        for k in range(count):
            stamp = stamp_list[k]
            prior = None
            measurements = self._filter_measurements(measured[k], stamp)
            at_row = bool(measurements) and measurements[-1] is None
            if at_row or flt.g is None:
                # The base state at the row's stamp (a measurement there, or the start).
                prior = Measurement(stamp, pin.SE3(rotation[k], translation[k]),
                                    None if twists is None else twists[k],
                                    self._row_stamp_sigma if at_row else None)
                if at_row:
                    measurements[-1] = prior
            for gated, nis in flt.row(stamp, lins[k], prior, measurements,
                                      None if commands is None else commands[k]):
                self.rejected['innovation_gate'] += 1
                self._period_rejected += 1
                self.last_rejection = (f'innovation_gate: base measurement at {gated} '
                                       f'improbable under the filter (chi-square {nis:.3g})')
            g = flt.g
            x, p = flt.x, flt.p
            mu[k] = x[:n]
            pi[k] = adjoint(g).T @ x[:n]
            mu_cov[k] = p[n:2 * n, n:2 * n]
            if disturbance is None:
                rate[k] = peak = x[n:]
                w_cov[k] = p[2 * n:, 2 * n:]
            else:
                # The total wrench is what mu does; events concern the disturbance
                # beyond the command (a commanded firing is expected, not an event).
                rate[k], w_cov[k] = flt.total_wrench()
                disturbance[k] = peak = flt.wrench
            detector.update(stamp, mu[k], math.sqrt(float(peak @ peak)),
                            flt.wrench_significance(), flt.step_detected is not None)
            poses.append(g)
            quiet.append(not detector.in_event)
        # Drift twist I^-1 pi, stacked (the same kernel per row, whatever the chunk).
        drift = np.matmul(inverse, pi[:, :, None])[:, :, 0]
        # Reduced energy (5.36) from the filtered momentum: 1/2 pi.I^-1 pi + 1/2 pbar.qbar_dot.
        energy = 0.5 * (np.matmul(pi[:, None, :], drift[:, :, None])[:, 0, 0]
                        + np.matmul(qbar_dot[:, None, :], result.pbar[:, :, None])[:, 0, 0])
        if self.robot.has_potential:
            energy += [self.robot.potential_energy(row) for row in qbar]
        extras: dict = {}
        cyclic = None
        if self._cyclic_view is not None:
            xi_hat = drift - result.connection_qd
            cyclic = self._cyclic_view.columns(result.mass, xi_hat, qbar, qbar_dot)
            self._last_theta = cyclic.theta[-1]
        if self.predictor.active or self._prediction_enabled():
            self._per_sample(stamp_list, qbar, qbar_dot, taus, result, extras, rejected_at,
                             cyclic, poses, mu, quiet)
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

    def _filter_measurements(self, measured: tuple, stamp: int) -> list:
        """
        Return a row's base samples as filter measurements, in stamp order.

        The one at the row's own stamp is None: the row's base state is that
        sample, already evaluated by the kernel (the caller fills it in).
        """
        out: list = []
        odometry, kernel = self.use_odometry, self.kernel
        self._row_stamp_sigma = None
        for sample in measured:
            sample_ns, row = sample[0], sample[1]
            sigma = sample[2] if len(sample) > 2 else None
            if sample_ns == stamp:
                # The row's own sample: its stamp sigma goes with the row's prior.
                self._row_stamp_sigma = sigma
                out.append(None)
                continue
            twist = None
            if odometry:
                twist = np.array(row[7:13])
                if kernel.projects_twists:
                    twist = kernel.coordinates(twist[None])[0]
            out.append(Measurement(sample_ns, pin.XYZQUATToSE3(np.array(row[:7])), twist,
                                   sigma))
        return out

    def _accumulate_statistics(self, mu: np.ndarray) -> None:
        """Update the running mean and squared deviations of mu (Welford; Chan et al.)."""
        count = len(mu)
        before = self.processed
        self.processed = total = before + count
        if count == 1:
            # No cancellation for a near-constant mu.
            delta = mu[0] - self._mu_mean
            self._mu_mean += delta / total
            self._mu_m2 += delta * (mu[0] - self._mu_mean)
            return
        mean = mu.mean(axis=0)
        m2 = np.square(mu - mean).sum(axis=0)
        delta = mean - self._mu_mean
        self._mu_mean += delta * (count / total)
        self._mu_m2 += m2 + np.square(delta) * (before * count / total)

    def _per_sample(self, stamp_list: tuple, qbar: np.ndarray, qbar_dot: np.ndarray,
                    taus: tuple, result, extras: dict, rejected_at: int,
                    cyclic: Optional[CyclicColumns], poses: list, mu: np.ndarray,
                    quiet: list) -> None:
        """Record the measured history for the residuals and start predictions when due."""
        predictor = self.predictor
        rotation, translation = result.rotation, result.translation
        for k, stamp in enumerate(stamp_list):
            # Measured history for the residuals (closes predictions whose horizon passed).
            predictor.observe(stamp, qbar[k], translation[k], rotation[k])
            if quiet[k] and self._prediction_due(stamp):
                extra = self._predict(stamp, poses[k], qbar[k], qbar_dot[k], taus[k],
                                      k >= rejected_at, mu[k],
                                      None if cyclic is None else cyclic.theta[k])
                if extra is not None:
                    extras[k] = extra

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
                 theta: Optional[np.ndarray] = None) -> Optional[tuple]:
        """
        Start a prediction from the filter's pose and momentum (re-reduced at that mu).

        Return the output extras (messages, or the deferred job).
        """
        self._last_prediction_ns = stamp
        self.detector.take_level_change()
        deferred = self.defer_predictions
        try:
            job = self.predictor.predict(stamp, g, qbar, qbar_dot, mu, tau, theta,
                                         deferred=deferred)
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
        return (messages.shape, messages.path, None, (messages.phase_path, None))

    # --- planned trajectories ------------------------------------------------------------
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
                                   config.prediction_max_wall_time, config.world_frame)

    def add_trajectory(self, sample: JointTrajectorySample) -> None:
        """
        Take a planned joint trajectory (prediction_mode planned follows the latest).

        Its times count from its header stamp; stamp 0 means "from now" (the
        newest joint-state stamp), as joint_trajectory_controller starts such
        a trajectory on arrival. Joints must be shape joints of the model (a
        subset: the others keep their velocities); bad trajectories are
        counted as rejections (``trajectory_*``) and the previous plan stays.
        """
        self.trajectories_received += 1
        names = sample.joint_names
        unknown = [n for n in names if n not in self._index]
        if not names or not sample.times_from_start_ns.size:
            self._reject('trajectory_empty', 'planned trajectory without joints or points')
            return
        if unknown:
            self._reject('trajectory_unknown_joint',
                         f'{", ".join(unknown[:5])} not in the robot model')
            return
        if len(set(names)) != len(names):
            self._reject('trajectory_duplicate_joint', 'joint names repeat')
            return
        arrays = [a for a in (sample.positions, sample.velocities, sample.accelerations)
                  if a is not None]
        if not _all_finite(*arrays):
            self._reject('trajectory_non_finite', 'NaN or inf in a planned trajectory')
            return
        start = sample.stamp_ns
        if start == 0:
            start = self._last_joint_ns if self._last_joint_ns is not None else 0
        index = np.array([self._index[n] for n in names], dtype=int)
        self.predictor.set_plan(Plan(start, index, sample.times_from_start_ns,
                                     sample.positions, sample.velocities,
                                     sample.accelerations, self.robot.m))

    def filter_statistics(self) -> dict:
        """
        Return the filter's innovation statistics.

        ``log_likelihood``: sum over the updates of log N(nu; 0, S);
        ``nis_per_dof``: mean normalised innovation squared per measured
        coordinate (1 when the noise parameters fit the data); ``innovation_gated``;
        ``pose_offsets``: runs of gated poses taken as a step of the pose sensor (a
        motion-capture body re-fitted), not as a momentum jump;
        ``filter_restarts``: re-initialisations after the covariance broke down;
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
                'filter_restarts': flt.diverged, 'steps_taken': flt.steps_taken,
                'pose_steps': flt.step_test.pose_steps,
                'poses_retimed': self._retimer.retimed,
                'retiming_restarts': self._retimer.restarts}

    # --- smoothing (replay) -----------------------------------------------------------
    def enable_smoothing(self, files: Optional[SmootherFiles] = None) -> None:
        """
        Record the filter's steps from now on, for :meth:`smoothed_rows` (replay).

        The steps go to disk (:mod:`.smoother`) in ``files`` (default: a
        temporary directory of the estimator's own, removed when it is collected).
        """
        self.record_steps = True
        self.smoother_files = files if files is not None else SmootherFiles()
        self.filter.record = True
        self.filter.steps = StepStore(self.smoother_files, self.robot.n, self.filter.dim,
                                      self.commanded_wrench)

    def smoothed_rows(self) -> Iterator[dict[str, Any]]:
        """
        Yield, per output since :meth:`enable_smoothing`, its RTS-smoothed fields.

        Each a dict of :class:`EstimatorOutput` fields: ``mu``, ``momentum``,
        ``body_momentum``, ``momentum_rate``, ``drift_twist``, ``momentum_covariance``,
        ``wrench_covariance`` (and ``disturbance`` with a commanded wrench); the
        shape state, predictions, diagnostics and events stay those of the causal
        run. Memory stays a block of rows whatever the length (:mod:`.smoother`).
        """
        flt, n, group, kernel = self.filter, self.robot.n, self.robot.group, self.kernel
        command = self.commanded_wrench

        def wrench(state: FilterState, held: Optional[np.ndarray]) -> tuple:
            if command:
                total, cov = flt._total(state.g, state.x, state.p, held)
                return total, cov, state.x[n:2 * n]
            return state.x[n:], state.p[2 * n:, 2 * n:], None

        rows = smooth_rows(group, flt.steps, self.smoother_files, wrench)
        world, base = self.config.world_frame, self.robot.base_link
        wrench_sample, twist_sample = WrenchSample, TwistSample
        try:
            for block in rows.blocks():
                mu = np.ascontiguousarray(block['mu'])
                momentum = kernel.wrenches(mu)
                body = kernel.wrenches(np.ascontiguousarray(block['pi']))
                rate = kernel.wrenches(np.ascontiguousarray(block['rate']))
                drift = kernel.twists(np.ascontiguousarray(block['drift']))
                disturbance = kernel.wrenches(np.ascontiguousarray(block['disturbance'])) \
                    if command else None
                mu_cov, w_cov = block['mu_cov'], block['w_cov']
                for k, stamp in enumerate(block['stamp_ns'].tolist()):
                    fields = {
                        'mu': mu[k],
                        'momentum': trusted_sample(wrench_sample, stamp, world,
                                                   momentum[k, :3], momentum[k, 3:]),
                        'body_momentum': trusted_sample(wrench_sample, stamp, base,
                                                        body[k, :3], body[k, 3:]),
                        'momentum_rate': trusted_sample(wrench_sample, stamp, world,
                                                        rate[k, :3], rate[k, 3:]),
                        'drift_twist': trusted_sample(twist_sample, stamp, base,
                                                      drift[k, :3], drift[k, 3:]),
                        'momentum_covariance': mu_cov[k], 'wrench_covariance': w_cov[k]}
                    if disturbance is not None:
                        fields['disturbance'] = trusted_sample(
                            wrench_sample, stamp, world, disturbance[k, :3], disturbance[k, 3:])
                    yield fields
        finally:
            rows.close()

    def smooth_outputs(self, outputs: Sequence[EstimatorOutput]) -> None:
        """
        Replace the filtered estimates of ``outputs`` by the RTS-smoothed ones, in place.

        ``outputs`` are all outputs since :meth:`enable_smoothing`, in order (one
        recorded filter row each); :meth:`smoothed_rows` says what changes.
        """
        recorded = self.filter.steps.outputs
        if recorded != len(outputs):
            raise ValueError(f'{len(outputs)} outputs for {recorded} recorded filter rows')
        for output, fields in zip(outputs, self.smoothed_rows()):
            for name, value in fields.items():
                setattr(output, name, value)

    # --- reporting -------------------------------------------------------------------
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
                 'innovation_gated': str(flt.gated),
                 'pose_offsets': str(flt.pose_offsets),
                 'events': str(len(self.detector.events)),

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
            gain, gain_sigma = np.array(estimate['gain']), np.array(estimate['gain_sigma'])
            total, total_cov = flt.total_wrench()
            values.update({
                'gain': ' '.join(f'{v:.4g}' for v in gain),
                'gain_sigma': ' '.join(f'{v:.3g}' for v in gain_sigma),
                'bias': ' '.join(f'{v:.4g}' for v in estimate['bias']),
                'bias_sigma': ' '.join(f'{v:.3g}' for v in estimate['bias_sigma']),
                'command': ' '.join(f'{v:.4g}' for v in flt._command),
                'disturbance': ' '.join(f'{v:.6g}' for v in flt.wrench),
                'disturbance_sigma': ' '.join(
                    f'{v:.3g}' for v in np.sqrt(np.diag(flt.wrench_cov))),
                'total_wrench': ' '.join(f'{v:.6g}' for v in total),
                'total_wrench_sigma': ' '.join(
                    f'{v:.3g}' for v in np.sqrt(np.diag(total_cov)))})
            off = (np.abs(gain - 1.0) > 3.0 * gain_sigma) \
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
        failures = [f for f in predictor.finished if f.failure is not None]
        if failures:
            values['failed'] = str(len(failures))
            values['last_failure'] = failures[-1].failure
            if failures[-1] is predictor.finished[-1]:
                level, message = DIAG_WARN, f'prediction stopped: {failures[-1].failure}'
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

    def summary(self) -> dict:
        """Return counts, momentum statistics, events and prediction residuals."""
        mean = self._mu_mean
        spread = np.sqrt(self._mu_m2 / max(self.processed, 1))
        finished = self.predictor.finished
        residuals = [p.shape_residual for p in finished if p.compared]
        positions = [p.position_residual for p in finished if p.compared]
        failures = self.prediction_failures + Counter(p.result.failure_kind for p in finished
                                                      if p.failure is not None)
        origin = self.first_stamp_ns or 0
        return {
            'first_stamp_ns': self.first_stamp_ns,
            'received': dict(self.received),
            'processed': self.processed,
            'rejected': dict(self.rejected),
            'clock_resets': self.clock_resets,
            'cyclic_joints': list(self.cyclic_joints),
            'mu_mean': mean.tolist(),
            'mu_spread': spread.tolist(),
            'events': [{'start_s': (e.start_ns - origin) * 1e-9,
                        'end_s': None if e.end_ns is None else (e.end_ns - origin) * 1e-9,
                        'start_stamp_ns': e.start_ns,
                        'impulse': None if e.impulse is None else e.impulse.tolist(),
                        'peak_wrench': e.peak_wrench} for e in self.events],
            'predictions': self.predictor.made,
            'prediction_failures': dict(failures),
            'filter': self.filter_statistics(),
            **({'commanded_wrench': self.command_estimate()} if self.commanded_wrench else {}),
            'prediction_shape_residual_max': max(residuals) if residuals else None,
            'prediction_shape_residual_median': float(np.median(residuals))
            if residuals else None,
            'prediction_position_residual_max': max(positions) if positions else None,
            'prediction_mode': self.config.prediction_mode,
            'prediction_residuals': _residuals_by_mode(finished),
            'trajectories_received': self.trajectories_received,
        }


def _axis_names(group) -> list[str]:
    """Return a name per coordinate of the group's dual (fx ... tz, or a combination)."""
    names = ('fx', 'fy', 'fz', 'tx', 'ty', 'tz')
    out = []
    for column in group.algebra_basis.T:
        nonzero = np.flatnonzero(np.abs(column) > 1e-12)
        out.append(names[nonzero[0]] if len(nonzero) == 1
                   else '+'.join(names[i] for i in nonzero))
    return out


def _residuals_by_mode(finished: list[FinishedPrediction]) -> dict:
    """
    Residual statistics per effective mode (max and median over predictions).

    Prescribed modes (planned, held_velocity) are judged by the base path
    (position, attitude); their shape residual says how far the arm left the
    prescribed path. Torque modes are judged by the shape.
    """
    out: dict = {}
    for mode in sorted({p.mode for p in finished}):
        runs = [p for p in finished if p.mode == mode]
        compared = [p for p in runs if p.compared]
        entry: dict = {'predictions': len(runs),
                       'compared': len(compared),
                       'failed': sum(p.failure is not None for p in runs),
                       'judged_by': 'base path' if mode in PRESCRIBED_MODES else 'shape',
                       'evaluations_median': float(np.median([p.result.evaluations
                                                              for p in runs]))}
        for key in ('shape_residual', 'position_residual', 'attitude_residual'):
            values = [getattr(p, key) for p in compared]
            entry[key + '_max'] = max(values) if values else None
            entry[key + '_median'] = float(np.median(values)) if values else None
        out[mode] = entry
    return out
