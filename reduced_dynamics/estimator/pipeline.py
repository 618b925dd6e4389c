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

This module is the orchestration; each concern is a module of its own, a part
of :class:`Estimator` whose state :meth:`Estimator.__init__` sets up, and one
sample travels down through them:

* :mod:`.intake`: validation of every input, rejections counted by reason;
* :mod:`.timing`: stamp policy decisions, re-timing, joint/base pairing into
  rows, held commands, clock restarts;
* :mod:`.processing`: a chunk of rows through the kernel, the filter, the event
  detector and the predictor;
* :mod:`.outputs`: the outputs, per sample and per chunk;
* :mod:`.reporting`: statistics, summary and diagnostics;
* :mod:`~reduced_dynamics.estimator.smoother`: the fixed-interval smoother's disk-backed
  store (replay).
"""

from __future__ import annotations

from collections import Counter, deque
from typing import Iterable, Optional, Sequence, Union

import numpy as np

from reduced_dynamics.estimator.config import EstimatorConfig
from reduced_dynamics.estimator.cyclic import CYCLIC_OFF, CyclicView, resolve_cyclic_joints
from reduced_dynamics.estimator.events import EventDetector
from reduced_dynamics.estimator.filter import MomentumFilter, NoiseModel
from reduced_dynamics.estimator.fixed_lag import FixedLagSmoothing
from reduced_dynamics.estimator.intake import InputIntake, Sample
from reduced_dynamics.estimator.kernel import UpdateKernel
# EstimatorOutput and the chunks are imported from here by the node, replay and tools.
from reduced_dynamics.estimator.outputs import EstimatorBatch, EstimatorOutput, OutputChunk
from reduced_dynamics.estimator.plausibility import BaseBounds, JointBounds
from reduced_dynamics.estimator.held_torque import HeldTorqueEstimator
from reduced_dynamics.estimator.prediction import Predictor
from reduced_dynamics.estimator.processing import ChunkProcessing, NS, RowChunk
from reduced_dynamics.estimator.reporting import Reporting
from reduced_dynamics.estimator.retiming import FrameRetimer
from reduced_dynamics.estimator.smoother import SmootherFiles, Smoothing, StepStore
from reduced_dynamics.estimator.stamps import StampGate
from reduced_dynamics.estimator.sync import BaseBuffer
from reduced_dynamics.estimator.timing import RETIMED_KEEP, Timing
from reduced_dynamics.messages.samples import BaseStateSample, CommandSample, JointStateSample
from reduced_dynamics.robot.model import RobotModel

#: Synchronised samples per chunk of the batched path: enough to amortise the
#: numpy calls, few enough that the stack of mass matrices stays in cache.
CHUNK_BYTES = 512 * 1024
#: Consecutive samples at a new, self-consistent time that prove a clock jump
#: (estimator/stamps.py): fewer would follow two equal outliers, more delays outputs.
STAMP_JUMP_SAMPLES = 3


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


class Estimator(InputIntake, Timing, ChunkProcessing, Reporting, Smoothing,
                FixedLagSmoothing):
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
        #: base samples whose message covariance was bad, by reason (the noise
        #: parameters were used instead; estimator/covariance.py)
        self.covariance_fallbacks: Counter = Counter()
        self.last_covariance_fallback: Optional[str] = None
        self._covariance_reader = None
        self._period_covariance_fallbacks = 0
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
        self._chunk = RowChunk()
        self._chunk_limit = 1  # streaming; add_samples raises it
        self._batch_limit = max(16, CHUNK_BYTES // (8 * robot.model.nv ** 2))
        # Resolved samples in the open chunk when the last rejection was counted
        # (a failed prediction must not hide a later rejection, nor the reverse).
        self._rejected_at = 0
        self._done: list[OutputChunk] = []
        #: keep the filter's steps for :meth:`smoothed_rows` (see :meth:`enable_smoothing`)
        self.record_steps = False
        self.smoother_files: Optional[SmootherFiles] = None
        #: the full smoother's store of steps (:meth:`enable_smoothing`)
        self.step_store: Optional[StepStore] = None
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
                         'pose_offsets', '_stamp_twist', '_stamp_twist_ns', 'diverged',
                         'restart_causes', 'burst_skipped', 'stalls'):
                setattr(self.filter, name, getattr(old_filter, name))
            if self.commanded_wrench:
                self.filter._command = old_filter._command
        self._attach_fixed_lag()
        old_detector = getattr(self, 'detector', None)
        self.detector = EventDetector(self.robot.n, config.event_significance,
                                      config.event_hold, config.event_false_alarm_rate)
        if old_detector is not None:
            self.detector.events = old_detector.events
            self.detector.notices = old_detector.notices
            self.detector._settling = old_detector._settling
        old_predictor = getattr(self, 'predictor', None)
        self.predictor = Predictor(self.robot, config.prediction_horizon,
                                   config.prediction_step, config.prediction_integrator,
                                   config.prediction_tolerance, self.cyclic_joints,
                                   config.prediction_mode, config.prediction_max_evaluations,
                                   config.prediction_max_wall_time, config.world_frame,
                                   self.shape_names)
        if old_predictor is not None:
            self.predictor.adopt(old_predictor)
        # held_torque predicts with an estimate of the applied torques (.held_torque).
        held = getattr(self, 'held_torque', None)
        if config.prediction_mode != 'held_torque':
            held = None
        elif held is None or (held.r, held.follow_time) != (
                config.joint_effort_noise ** 2, config.held_torque_follow_time):
            held = HeldTorqueEstimator(self.robot.m, config.joint_effort_noise,
                                       config.held_torque_follow_time)
        self.held_torque: Optional[HeldTorqueEstimator] = held

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

    def joint_state_batch(self, sample: JointStateSample) -> EstimatorBatch:
        """Like :meth:`add_joint_state`, returning the outputs column-wise (the node)."""
        self._chunk_limit = self._batch_limit
        try:
            self._take_joint(sample)
        finally:
            self._chunk_limit = 1
        return self._streaming_batch()

    def base_state_batch(self, sample: BaseStateSample) -> EstimatorBatch:
        """Like :meth:`add_base_state`, returning the outputs column-wise (the node)."""
        self._chunk_limit = self._batch_limit
        try:
            self._take_base(sample)
        finally:
            self._chunk_limit = 1
        return self._streaming_batch()

    def command_batch(self, sample: CommandSample) -> EstimatorBatch:
        """Like :meth:`add_command`, returning the outputs column-wise (the node)."""
        self._take_command(sample)
        return self._streaming_batch()

    def _streaming_batch(self) -> EstimatorBatch:
        if self._chunk.rows:  # a joint state that waits for its base state: none
            self._process_chunk()
        return self._take_done()

    def add_samples(self, samples: Iterable[Sample]) -> EstimatorBatch:
        """
        Take joint-state, base (and command) samples in arrival order (the batched path).

        Equivalent to calling :meth:`add_joint_state` / :meth:`add_base_state` /
        :meth:`add_command` on each in turn, with the same outputs, rejections and
        events, but the update is vectorised over chunks of samples.
        """
        if not isinstance(samples, (list, tuple)):
            samples = list(samples)
        self._chunk_limit = self._batch_limit
        try:
            # Validation by columns, then per message in order (estimator/intake.py).
            self._take_batch(samples)
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
        if self._chunk.rows:  # a joint state that waits for its base state: none
            self._process_chunk()
        done = self._done
        if not done:
            return []
        self._done = []
        return done[0].outputs() if len(done) == 1 else [o for c in done for o in c.outputs()]

    def _take_done(self) -> EstimatorBatch:
        done, self._done = self._done, []
        return EstimatorBatch(done)
