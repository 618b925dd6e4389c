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
The ROS 2 node: a thin rclpy shell around :class:`reduced_dynamics.estimator.Estimator`.

It subscribes to joint states and to the base state (nav_msgs/Odometry or
geometry_msgs/PoseStamped), feeds the estimator and publishes every output on
the topics of :data:`reduced_dynamics.topics.OUTPUT_TOPICS` (``~/<name>`` and
``/diagnostics``). Output stamps are the input stamps; the node clock (which
follows ``/clock`` under ``use_sim_time``) times the node status, the log
throttle and the reset on a backwards jump of ROS time.

Inputs are taken as serialized CDR and decoded by the fixed-layout decoders
the replay uses; outputs are published as the CDR bytes the replay writes
(:mod:`reduced_dynamics.messages.cdr`). So the node and the replay share one
decoding, one estimator and one encoding: the same messages give the same
bytes, and no rclpy message object is built on the hot path. Predictions are
computed by a worker thread (``Estimator(defer_predictions=True)``), never on
the input path, and published when ready with the stamp of the sample they
start from.

Robot model: the ``robot_description`` parameter if non-empty, else
``urdf_path``, else the latched ``robot_description`` topic, with the built-in
paper robot standing in until that topic delivers. A model that fails to load
is logged and, if a working model exists, that one is kept.

Two shells share the logic: :class:`ReducedDynamicsNode` (plain, the default:
configured and active at construction) and
:class:`ReducedDynamicsLifecycleNode` (managed: configure loads and checks the
model, activate subscribes and publishes). ``main()`` picks one
(``--lifecycle`` or the ``reduced_dynamics_lifecycle_node`` executable);
``--help`` prints the parameters and topics instead. docs/node_seams.md says
what the node does with bad settings and with input from a loaded machine.

This is the only module importing rclpy, and it stays importable without it:
``main()`` then prints one line saying ROS 2 is not sourced and returns 1.
"""

from __future__ import annotations

import argparse
import array
from collections import Counter, deque
import difflib
import queue
import signal
import statistics
import sys
import textwrap
import threading
from typing import Any, Callable, Optional, Sequence

import numpy as np

from reduced_dynamics.blas_threads import limit_blas_threads
from reduced_dynamics.estimator import Estimator, EstimatorConfig, EstimatorOutput
from reduced_dynamics.estimator.base_motion import answer_messages
from reduced_dynamics.estimator.config import PARAMETERS as ESTIMATOR_PARAMETERS
from reduced_dynamics.estimator.config import ParameterSpec
from reduced_dynamics.estimator.core.warmup import compiling_notice, warm_up
from reduced_dynamics.estimator.fixed_lag import FixedLagRows
from reduced_dynamics.estimator.outputs import COLUMN_FIELDS, OutputChunk
from reduced_dynamics.messages import (
    cdr, command_from_ros, DIAG_ERROR, DIAG_OK, DIAG_WARN, Diagnostics, DiagnosticStatusSample,
    joint_state_from_ros, joint_trajectory_from_ros, odometry_from_ros,
    pose_stamped_from_ros, pose_with_covariance_stamped_from_ros, RclpyTypes, RosbagsTypes,
    string_from_ros)
from reduced_dynamics.messages.cdr_columns import COLUMN_ENCODERS, split
from reduced_dynamics.messages.samples import with_receive_time
from reduced_dynamics.params import ALL_PARAMETERS, check_any_parameter, RUNTIME_PARAMETERS
from reduced_dynamics.robot.model import load_robot, ModelError
from reduced_dynamics.topics import (active_topics, cdr_encoder, DIAGNOSTICS_TOPIC,
                                     EVENTS_TOPIC, FIXED_LAG_TOPICS,
                                     NODE_NAME, OUTPUT_TOPICS)

try:
    # rclpy first: if it is missing, ROS 2 is not sourced (rcl_interfaces comes with it).
    import rclpy
    from rclpy.duration import Duration
    from rclpy.exceptions import ParameterException
    from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
    from rclpy.lifecycle import LifecycleNode, TransitionCallbackReturn
    from rclpy.node import Node
    from rclpy.parameter import Parameter
    from rclpy.qos import DurabilityPolicy
    from rclpy.qos import HistoryPolicy
    from rclpy.qos import QoSPolicyKind
    from rclpy.qos import QoSProfile
    from rclpy.qos import ReliabilityPolicy
    from rclpy.qos_overriding_options import InvalidQosOverridesError, QoSOverridingOptions
    from rclpy.serialization import deserialize_message
    from rclpy.signals import SignalHandlerOptions
    from rclpy.clock import JumpThreshold
    from rclpy.event_handler import PublisherEventCallbacks
    from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
    from rcl_interfaces.msg import FloatingPointRange
    from rcl_interfaces.msg import ParameterDescriptor
    from rcl_interfaces.msg import SetParametersResult
except ImportError:  # main() explains; the ROS-free core must stay usable
    rclpy = None
    Node = LifecycleNode = object

    class InvalidQosOverridesError(Exception):  # type: ignore[no-redef]
        """Stands in for rclpy's (never raised without rclpy)."""

ROS_NOT_SOURCED = ('reduced_dynamics_node: ROS 2 Jazzy is not sourced (rclpy not importable); '
                   'source /opt/ros/jazzy/setup.bash, or install the rclpy wheels: '
                   'pip install ".[ros]"')
#: Latched URDF topic (robot_state_publisher), relative to the node's namespace.
ROBOT_DESCRIPTION_TOPIC = 'robot_description'
#: Longest steady-time period [s] of the status while the node has no robot model.
NO_MODEL_STATUS_PERIOD = 1.0
#: Node-clock time between two log lines about the same kind of rejected input.
LOG_THROTTLE_NS = 5_000_000_000
OUTPUT_QOS_DEPTH = 10
#: History depth of the sensor inputs. Sensor-data policies (best effort, volatile) as
#: other drivers use, but 100 deep instead of 5: at 1 kHz, 5 messages are 5 ms, less
#: than one scheduler time slice or one GIL switch interval of a busy 2-core machine,
#: so a depth of 5 loses input that did reach the node; 100 covers 100 ms of stall.
INPUT_QOS_DEPTH = 100
#: Sensor messages an input callback takes on its own at most (see ``_drain_inputs``).
DRAIN_LIMIT = 64
#: Prediction jobs waiting for the worker at most (a minute at the default 1 Hz): a worker
#: starved of CPU skips the oldest (the estimator has computed it for its residual at the
#: horizon; only its messages go unpublished, counted) instead of queueing without bound.
WORKER_QUEUE_KEEP = 64
#: The interpreter's GIL switch interval [s] once the prediction worker runs. A prediction
#: (DOP853 and its covariance, ~7 ms of Python for the paper robot) holds the GIL; at the
#: default 5 ms a sample arriving meanwhile waits up to 5 ms for the worker to yield it,
#: at 1 kHz several samples per prediction, i.e. the node's latency tail
#: (docs/output_path.md). At 0.2 ms the wait is bounded by that, for a few extra switches.
GIL_SWITCH_INTERVAL = 0.0002
#: ~/predict_base_motion as a request/response topic pair (standard types; README).
PREDICT_REQUEST_TOPIC = '~/predict_base_motion/request'
PREDICT_PATH_TOPIC = '~/predict_base_motion/path'
PREDICT_RESULT_TOPIC = '~/predict_base_motion/result'
NS_PER_S = 1_000_000_000
#: Name of the node's own status in /diagnostics (the estimator's is separate).
NODE_STATUS_NAME = f'{NODE_NAME}: node'
#: Payload identification (issue 22): the service and the estimate's topic.
IDENTIFY_PAYLOAD_SERVICE = '~/identify_payload'
PAYLOAD_TOPIC = '~/payload'
#: A stamp gap above this many nominal periods counts as missing samples (InputStats).
GAP_FACTOR = 1.5
#: Recent stamps of one input the nominal period is estimated from (InputStats).
PERIOD_STAMPS = 64

_DOUBLE_TYPES = (float, int)


def _plain(value: Any) -> Any:
    """Return a parameter value as the ROS-free core expects it (lists, not array.array)."""
    # rclpy hands DOUBLE_ARRAY values from overrides and services over as array.array.
    if isinstance(value, (array.array, tuple, np.ndarray)):
        return [v.item() if isinstance(v, np.generic) else v for v in value]
    return value


def received_ns(info: Any) -> Optional[int]:
    """Return the receive time [ns] of rclpy's message info (a dict), None if absent."""
    value = info.get('received_timestamp') if isinstance(info, dict) else None
    return value if isinstance(value, int) and value > 0 else None


def _is_double(spec: ParameterSpec) -> bool:
    return isinstance(spec.default, float)


def _is_double_array(spec: ParameterSpec) -> bool:
    return isinstance(spec.default, list) and all(isinstance(v, float) for v in spec.default)


def _coerced(name: str, value: Any) -> Any:
    """Return a value in the parameter's own type: an integer given for a double is a double."""
    spec = ALL_PARAMETERS.get(name)
    value = _plain(value)
    if spec is not None and _is_double(spec):
        if isinstance(value, bool) or not isinstance(value, _DOUBLE_TYPES):
            raise ValueError(f'{name} must be a number, got {value!r}')
        return float(value)
    if spec is not None and _is_double_array(spec) and isinstance(value, list):
        return [float(v) if isinstance(v, int) and not isinstance(v, bool) else v
                for v in value]
    return value


def parameter_descriptor(name: str, spec: ParameterSpec) -> 'ParameterDescriptor':
    """
    Return the ParameterDescriptor of one row of ALL_PARAMETERS.

    Double parameters are dynamically typed so that ``-p prediction_rate:=2`` (an
    integer on the command line) is accepted; the node's own check then enforces
    the number type and the range (rclpy checks floating_point_range on doubles only).
    """
    double = _is_double(spec)
    descriptor = ParameterDescriptor(
        name=name, description=spec.description,
        type=Parameter.Type.from_parameter_value(_default(spec)).value,
        read_only=name not in RUNTIME_PARAMETERS, dynamic_typing=double)
    if spec.low is not None:
        descriptor.floating_point_range = [FloatingPointRange(
            from_value=float(spec.low), to_value=float(spec.high), step=0.0)]
    if spec.choices:
        descriptor.additional_constraints = 'one of: ' + ', '.join(spec.choices)
    elif double:
        descriptor.additional_constraints = 'a number (integers are taken as doubles)'
    return descriptor


def _default(spec: ParameterSpec) -> Any:
    """Return a fresh copy of a default (the table's lists are shared)."""
    return list(spec.default) if isinstance(spec.default, list) else spec.default


def quiet_publisher_events() -> 'PublisherEventCallbacks':
    """
    Return publisher event callbacks without rclpy's default handlers (outputs only).

    rclpy adds two QoS event handlers per publisher (incompatible QoS, incompatible
    type) to every wait of the executor, which rebuilds its wait set for each input
    message: on the 13 outputs they were two thirds of its entities. A subscriber
    with an incompatible QoS or type still says so in its own log (its handlers).
    """
    return PublisherEventCallbacks(use_default_callbacks=False)


def input_qos() -> 'QoSProfile':
    """Return the default QoS of the sensor inputs (see INPUT_QOS_DEPTH)."""
    return QoSProfile(depth=INPUT_QOS_DEPTH, history=HistoryPolicy.KEEP_LAST,
                      reliability=ReliabilityPolicy.BEST_EFFORT,
                      durability=DurabilityPolicy.VOLATILE)


def reliable_qos(depth: int = OUTPUT_QOS_DEPTH) -> 'QoSProfile':
    """Return the default QoS of the outputs, plans and requests."""
    return QoSProfile(depth=depth, history=HistoryPolicy.KEEP_LAST,
                      reliability=ReliabilityPolicy.RELIABLE)


#: Values each QoS override policy takes (rclpy's qos_overrides.<topic>.<entity>.<policy>).
QOS_POLICY_CHOICES = {
    'reliability': ('reliable', 'best_effort', 'best_available', 'system_default'),
    'history': ('keep_last', 'keep_all', 'system_default'),
    'durability': ('volatile', 'transient_local', 'best_available', 'system_default'),
    'liveliness': ('automatic', 'manual_by_topic', 'best_available', 'system_default'),
}
#: QoS override policies given as integers (depth: messages; the others: nanoseconds).
QOS_POLICY_INTEGERS = ('depth', 'deadline', 'lifespan', 'liveliness_lease_duration')
#: The largest history depth DDS takes (a signed 32-bit count).
QOS_MAX_DEPTH = 2**31 - 1


def qos_override_problem(name: str, value: Any) -> Optional[str]:
    """
    Return why a ``qos_overrides.*`` value would fail in rclpy, or None if it is valid.

    rclpy raises a RuntimeError (an unknown policy value) or an RCLError from
    rmw (a negative depth) deep in ``create_subscription``; checked first, the
    node can answer with one line instead.
    """
    policy = name.rpartition('.')[2]
    choices = QOS_POLICY_CHOICES.get(policy)
    if choices is not None:
        if not isinstance(value, str) or value.lower() not in choices:
            return f'{name} is {value!r}, must be one of: {", ".join(choices)}'
    elif policy in QOS_POLICY_INTEGERS:
        high = QOS_MAX_DEPTH if policy == 'depth' else 2**63 - 1
        if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= high:
            return f'{name} is {value!r}, must be an integer in [0, {high}]'
    elif policy == 'avoid_ros_namespace_conventions' and not isinstance(value, bool):
        return f'{name} is {value!r}, must be true or false'
    return None


def _as_double(parameter: 'Parameter') -> 'Parameter':
    """Return an integer given for a double parameter as a double (the same one otherwise)."""
    spec = ALL_PARAMETERS.get(parameter.name)
    if spec is not None and _is_double(spec) and parameter.type_ == Parameter.Type.INTEGER:
        return Parameter(parameter.name, Parameter.Type.DOUBLE, float(parameter.value))
    # The same for arrays: ``gravity: [0, 0, -10]`` in a params file is an INTEGER_ARRAY.
    if spec is not None and _is_double_array(spec) and \
            parameter.type_ == Parameter.Type.INTEGER_ARRAY:
        return Parameter(parameter.name, Parameter.Type.DOUBLE_ARRAY,
                         [float(v) for v in parameter.value])
    return parameter


class InputStats:
    """
    Received count, samples lost before the node (as far as stamps prove) and rates, per input.

    The nominal period is the stream's tick, a robust rate: the median of the last
    PERIOD_STAMPS gaps, leaving out the gaps shorter than a quarter of their mean
    (bunched stamps: two mocap packets stamped almost together, a loaded
    publisher's burst). It is re-estimated as the stream goes on, so it learns a
    longer period too.

    A gap is a loss only when the stamps prove it:

    * it exceeds GAP_FACTOR periods after subtracting the credit of the window:
      the samples it holds beyond what its time span and the period imply (a
      bunched pair and a long gap near it lose nothing: the packet of the long
      gap came with the pair);
    * the next stamp continues from the gap's far end at the stream's rate. A
      stamp the stream does not follow (an outlier, ahead or behind) fills a slot
      and counts nothing; a stamp that goes back and is followed (a bag loop)
      re-anchors the stream; a gap after which the stream runs slower is a rate
      change, not a loss.
    """

    def __init__(self) -> None:
        """Start empty."""
        self.received = 0
        self.missing = 0
        self._stamps: deque[int] = deque(maxlen=PERIOD_STAMPS)
        self._period_ns = 0.0  # 0: not known yet
        self._since_period = 0
        self._suspect: Optional[int] = None  # a stamp that broke the stream
        self._outliers = 0  # outliers since the last stamp: samples that fill a gap
        self._window_received = 0

    @property
    def period_ns(self) -> float:
        """Return the nominal period [ns] (0 until enough stamps are seen)."""
        return self._period_ns

    def take(self, stamp_ns: int) -> None:
        """Count one message; judge the gap before it once the next stamp shows what it was."""
        self.received += 1
        stamps = self._stamps
        suspect, self._suspect = self._suspect, None
        if suspect is not None:
            self._decide(suspect, stamp_ns)
        if not stamps:
            stamps.append(stamp_ns)
            return
        gap = stamp_ns - stamps[-1]
        limit = GAP_FACTOR * self._period_ns
        if gap < 0 or (limit and gap > limit and gap - self._credit_ns() > limit):
            self._suspect = stamp_ns  # the next stamp decides what it was
            return
        self._advance(stamp_ns)

    def _credit_ns(self) -> float:
        """Return the time [ns] of the window's samples beyond its span's count of periods."""
        stamps, period = self._stamps, self._period_ns
        extra = len(stamps) - 1 - (stamps[-1] - stamps[0]) / period
        return max(0.0, extra) * period

    def _decide(self, suspect: int, stamp_ns: int) -> None:
        """Judge a stamp that broke the stream by the stamp after it."""
        gap = suspect - self._stamps[-1]
        step = stamp_ns - suspect
        period = self._period_ns
        limit = GAP_FACTOR * period if period else abs(gap)
        if gap < 0:
            if 0 <= step <= limit:  # the stream goes on from the earlier time: re-anchor
                self._stamps.clear()
                self._stamps.append(suspect)
                self._outliers = 0
            else:
                self._outliers += 1  # an outlier behind the stream
            return
        if step < 0:
            self._outliers += 1  # an outlier ahead of the stream
            return
        if step <= limit:  # the stream goes on at its rate after the gap: samples lost
            slots = int(round((gap - self._credit_ns()) / period)) - 1
            self.missing += max(0, slots - self._outliers)
        self._advance(suspect)  # (else slower after the gap: a rate change)

    def _advance(self, stamp_ns: int) -> None:
        self._stamps.append(stamp_ns)
        self._outliers = 0
        self._since_period += 1
        # Re-estimated every half window (a median of 64 gaps costs ~40 us).
        if self._since_period >= PERIOD_STAMPS // 2 or not self._period_ns:
            self._since_period = 0
            stamps = self._stamps
            if len(stamps) > PERIOD_STAMPS // 4:
                gaps = [b - a for a, b in zip(stamps, list(stamps)[1:])]
                shortest = (stamps[-1] - stamps[0]) / len(gaps) / 4
                self._period_ns = float(statistics.median(g for g in gaps if g >= shortest))

    def window(self) -> int:
        """Return the messages received since the last call."""
        count = self.received - self._window_received
        self._window_received = self.received
        return count


class _Ready:
    """A worker job whose messages are ready (the fixed-lag rows' encoded columns)."""

    __slots__ = ('messages',)

    def __init__(self, messages: Any) -> None:
        self.messages = messages

    def run(self) -> Any:
        return self.messages


class _PredictionWorker:
    """
    Run deferred jobs off the input path and publish their messages (one thread, in order).

    Prediction jobs (``keep``: the oldest skipped beyond it), and the fixed-lag rows a
    backward pass emits (a second worker that keeps every job: nothing valid is lost).
    """

    def __init__(self, publish: Callable[[Any], None], on_error: Callable[[str], None],
                 keep: int = WORKER_QUEUE_KEEP, name: str = 'predictions') -> None:
        self._jobs: queue.Queue = queue.Queue()
        self._publish = publish
        self._on_error = on_error
        self._keep = keep
        self.done = 0
        #: jobs skipped because the queue was full (their messages not published)
        self.skipped = 0
        # Two threads now share the GIL: the input path must not wait a whole default
        # interval for a running prediction to yield it.
        if sys.getswitchinterval() > GIL_SWITCH_INTERVAL:
            sys.setswitchinterval(GIL_SWITCH_INTERVAL)
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def submit(self, job: Any) -> None:
        """Queue ``job``; when ``keep`` wait already, skip the oldest (memory bound)."""
        while self._jobs.qsize() >= self._keep:
            try:
                old = self._jobs.get_nowait()
            except queue.Empty:
                break
            self._jobs.task_done()
            if old is None:  # a stop request stays last
                self._jobs.put(None)
                return
            self.skipped += 1
        self._jobs.put(job)

    @property
    def pending(self) -> int:
        return self._jobs.qsize()

    def _run(self) -> None:
        while True:
            job = self._jobs.get()
            if job is None:
                return
            try:
                messages = job.run()
                if messages is not None:
                    self._publish(messages)
            except Exception as error:  # noqa: B902 - a failed job must not end the worker
                self._on_error(f'{self._thread.name} failed: {type(error).__name__}: {error}')
            finally:
                self.done += 1
                self._jobs.task_done()

    def wait_idle(self) -> None:
        """Block until every submitted job is published (tests, orderly shutdown)."""
        self._jobs.join()

    def stop(self, timeout: float = 5.0) -> None:
        """Finish the queued jobs (bounded by ``timeout``), then end the thread."""
        self._jobs.put(None)
        self._thread.join(timeout)


class _Shell:
    """The node logic shared by the plain and the lifecycle node (a mixin over rclpy's Node)."""

    def _init_shell(self) -> None:
        self._types = RclpyTypes()
        self._started = False
        self._shell_active = False
        self._estimator: Optional[Estimator] = None
        self._robot_source = ''
        self._model_error: Optional[str] = None
        self._description_text: Optional[str] = None
        self._description_sub = None
        self._watchdog = None
        self._last_log_ns: dict[str, int] = {}
        self._suppressed: Counter = Counter()
        self._publishers_by_topic: dict[str, Any] = {}
        self._encoders: dict[str, Callable[[Any], bytes]] = {}
        #: The outputs advertised (topics.active_topics of the features that are on).
        self._output_topics = OUTPUT_TOPICS
        #: (topic, field) published from a chunk's columns, and the others (_activate)
        self._column_topics: list[tuple[str, str]] = []
        #: fixed-lag rows published from their columns (their encoder is cdr's)
        self._fixed_lag_columns = False
        self._occasional_topics: list = []
        self._input_subscriptions: list = []
        #: (subscription, callback) of the sensor inputs, which _drain_inputs takes from
        self._sensor_inputs: list = []
        self._draining = False
        self._answer_path = self._answer_result = None
        self._worker: Optional[_PredictionWorker] = None
        #: publishes the fixed-lag rows of a backward pass (hundreds of messages at once)
        self._lagged_worker: Optional[_PredictionWorker] = None
        self._publish_lock = threading.Lock()  # publishers vs. the worker during deactivate
        self._last_status_ns: Optional[int] = None
        self._processed_at_status = 0
        self._jump_handler = None
        #: Messages taken by the input callbacks, per input.
        self.received: Counter = Counter()
        #: Inputs rejected while there is no estimator (and rejected robot models).
        self.rejected: Counter = Counter()
        #: Per sensor input: counts, stamp gaps and rates.
        self.input_stats = {'joint_states': InputStats(), 'base': InputStats()}
        #: Times the estimator was reset because ROS time jumped back.
        self.time_resets = 0
        # Payload (issue 22): the robot without it, the input window identify_payload
        # uses, the payload held, and its service and topic while active.
        self._nominal_robot = None
        self._payload_window = None
        self.payload = None
        self._payload_service = self._payload_publisher = None
        #: Times the header stamps jumped back while ROS time did not (estimator/stamps.py).
        self.stamp_resets = 0
        self._resets_seen = 0  # the estimator's clock_resets already accounted for
        self._warned_unknown: set[str] = set()

        overrides = self._parameter_overrides  # rclpy's: command line and parameter files
        problems = [problem for name, parameter in overrides.items()
                    if name.startswith('qos_overrides.')
                    for problem in [qos_override_problem(name, parameter.value)] if problem]
        if problems:
            raise InvalidQosOverridesError('; '.join(problems))
        # An integer given for a double is stored as a double (it then reports DOUBLE):
        # the overrides here (declare_parameter does not call pre-set callbacks), later
        # changes in the pre-set callback.
        for name, parameter in list(overrides.items()):
            overrides[name] = _as_double(parameter)
        self.add_pre_set_parameters_callback(
            lambda parameters: [_as_double(p) for p in parameters])
        # Validation is in place before declaring, so bad overrides fail at start-up.
        self.add_on_set_parameters_callback(self._validate_parameters)
        for name, spec in ALL_PARAMETERS.items():
            self.declare_parameter(name, _default(spec), parameter_descriptor(name, spec))
        self.add_post_set_parameters_callback(self._apply_parameters)
        self._warn_unknown_overrides(qos=False)
        self._config = EstimatorConfig.from_mapping(
            {name: self._value(name) for name in ESTIMATOR_PARAMETERS})
        # robot_localization's answer to a bag loop or a simulator restart: a backwards
        # jump of ROS time resets the filter (it cannot be continued across the jump).
        self._jump_handler = self.get_clock().create_jump_callback(
            JumpThreshold(min_forward=None, min_backward=Duration(nanoseconds=-1),
                          on_clock_change=False),
            post_callback=self._on_time_jump)
        self._started = True

    # --- public state -----------------------------------------------------------------
    @property
    def estimator(self) -> Optional[Estimator]:
        """Return the running Estimator, or None while no robot model is usable."""
        return self._estimator

    @property
    def model_error(self) -> Optional[str]:
        """Return why the robot model could not be used (None when it could)."""
        return self._model_error

    @property
    def predictions_pending(self) -> int:
        """Return the prediction jobs waiting for the worker."""
        return self._worker.pending if self._worker else 0

    def wait_for_predictions(self) -> None:
        """Block until every prediction started so far, and every fixed-lag row, is published."""
        for worker in (self._worker, self._lagged_worker):
            if worker is not None:
                worker.wait_idle()

    # --- parameters -------------------------------------------------------------------
    def _value(self, name: str) -> Any:
        return _coerced(name, self.get_parameter(name).value)

    def _warn_unknown_overrides(self, qos: bool) -> None:
        """
        Warn once per name about a given parameter the node does not have (a typo).

        rclpy ignores them silently. ``qos``: the ``qos_overrides.*`` names, known
        once the topics exist (after activation); else the others.
        """
        declared = [name for name in self._parameters if name.startswith('qos_overrides.') == qos]
        for name in self._parameter_overrides:
            if name.startswith('qos_overrides.') != qos or name in self._parameters \
                    or name in self._warned_unknown:
                continue
            self._warned_unknown.add(name)
            close = difflib.get_close_matches(name, declared, n=1)
            self.get_logger().warning(f'unknown parameter {name} ignored'
                                      + (f'; did you mean {close[0]}?' if close else ''))

    def _validate_parameters(self, parameters: list) -> 'SetParametersResult':
        """Accept or reject a change (on-set callback: no side effects here)."""
        changes = {}
        for parameter in parameters:
            if parameter.name not in ALL_PARAMETERS:
                continue  # use_sim_time, qos_overrides.*: rclpy's own checks decide
            if self._started and parameter.name not in RUNTIME_PARAMETERS:
                # The read_only descriptor already stops this; kept so the rule holds even
                # if a descriptor is ever relaxed.
                return SetParametersResult(
                    successful=False,
                    reason=f'{parameter.name} is read at start-up only; restart the node')
            try:
                value = _coerced(parameter.name, parameter.value)
                check_any_parameter(parameter.name, value)
            except ValueError as error:
                return SetParametersResult(successful=False, reason=str(error))
            if parameter.name in ESTIMATOR_PARAMETERS:
                changes[parameter.name] = value
        if changes and self._started:
            try:
                self._config.replaced(**changes)
            except ValueError as error:
                return SetParametersResult(successful=False, reason=str(error))
        return SetParametersResult(successful=True)

    def _apply_parameters(self, parameters: list) -> None:
        """Adopt accepted estimator settings (post-set callback)."""
        changes = {p.name: _coerced(p.name, p.value) for p in parameters
                   if p.name in ESTIMATOR_PARAMETERS}
        if not changes or not self._started:
            return
        self._config = self._config.replaced(**changes)
        if self._estimator is not None:
            self._estimator.apply_config(self._config)
        if 'diagnostics_rate' in changes and self._shell_active:
            self._restart_watchdog()
        self.get_logger().info('parameters changed: ' + ', '.join(
            f'{name}={value!r}' for name, value in sorted(changes.items())))

    # --- robot model ------------------------------------------------------------------
    def _configure(self) -> Optional[str]:
        """Load the robot model (and wait for the topic if none is given); return an error."""
        # The compiled kernels load (or, after an install, compile) here, not in the
        # callback of the first message, which would wait for them.
        warm_up()
        description = self._value('robot_description')
        path = self._value('urdf_path')
        if description:
            self._set_robot(description, 'the robot_description parameter')
        elif path:
            self._set_robot(path, f'urdf_path {path}')
        else:
            latched = QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST,
                                 durability=DurabilityPolicy.TRANSIENT_LOCAL,
                                 reliability=ReliabilityPolicy.RELIABLE)
            self._description_sub = self.create_subscription(
                self._types.get('std_msgs/msg/String'), ROBOT_DESCRIPTION_TOPIC,
                self._on_robot_description, latched)
            topic = self.resolve_topic_name(ROBOT_DESCRIPTION_TOPIC)
            self.get_logger().warning(
                f'robot_description and urdf_path are empty: waiting for a URDF on {topic}; '
                'the built-in paper robot is used until it arrives')
            self._set_robot('', 'the built-in paper robot (stand-in)')
        return self._model_error

    def _cleanup(self) -> None:
        """Forget the robot model and the estimator (lifecycle cleanup)."""
        if self._description_sub is not None:
            self.destroy_subscription(self._description_sub)
            self._description_sub = None
        self._description_text = None
        self._estimator = None
        self._model_error = None

    def _set_robot(self, urdf: str, source: str) -> bool:
        """
        Build the robot model and a fresh estimator; return whether it replaced the old.

        A model that cannot be used is rejected with the reason; a working model, if
        there is one, stays (its estimator state too).
        """
        try:
            nominal = load_robot(urdf, self._value('base_joint'),
                                 np.array(self._value('gravity'), dtype=float))
            robot, payload, window = self._payload_model(nominal)
            # cyclic_joints that the robot cannot be reduced by fail here, with the reason.
            estimator = self._make_estimator(robot)
        except (ModelError, OSError, ValueError) as error:
            problem = f'cannot use the robot model from {source}: {error}'
            if self._estimator is not None:
                self.rejected['robot_model'] += 1
                self.get_logger().error(
                    f'{problem}; keeping robot {self._estimator.robot.model.name} from '
                    f'{self._robot_source}')
            else:
                self._model_error = problem
                self.get_logger().error(problem + '; not estimating until a usable model '
                                                  'is given')
            return False
        replaced = self._estimator is not None
        self._estimator = estimator
        self._nominal_robot, self.payload, self._payload_window = nominal, payload, window
        self._resets_seen = estimator.clock_resets
        self._robot_source = source
        if self._model_error is not None and self._shell_active:
            self._model_error = None
            self._restart_watchdog()  # back to diagnostics_rate of node time
        self._model_error = None
        self.get_logger().info(
            f'robot {robot.model.name} from {source}'
            + (' replaces the previous model (estimator state reset)' if replaced else '')
            + f': base {robot.group.name} ({robot.base_link}), {robot.m} shape joints '
            f'{list(robot.shape_joint_names)}')
        if estimator.cyclic_joints:
            self.get_logger().info(
                'second-stage reduction (Theorem 57) by the cyclic joints '
                f'{list(estimator.cyclic_joints)}: their momenta on cyclic_momenta')
        return True

    def _make_estimator(self, robot: Any) -> Estimator:
        return Estimator(robot, self._config, use_odometry=self._value('base_input') == 'odom',
                         cyclic_joints=self._value('cyclic_joints'), defer_predictions=True,
                         commanded_wrench=bool(self._value('commanded_wrench_topic')))

    # --- payload (issue 22, docs/payload.md) --------------------------------------------
    def _payload_model(self, nominal: Any) -> tuple:
        """Return (robot with payload_file's payload, the payload, the identification window)."""
        from reduced_dynamics.payload import load_payload, with_payload
        from reduced_dynamics.payload_online import PayloadWindow
        link, path = self._value('payload_link'), self._value('payload_file')
        payload = load_payload(path, link or None) if path else None
        window = PayloadWindow(nominal, link, self._value('payload_window')) if link else None
        return (with_payload(nominal, payload) if payload else nominal), payload, window

    def _on_identify_payload(self, request: Any, response: Any) -> Any:
        """Identify the payload over the last payload_window seconds and apply it."""
        response.success, response.message = self.identify_payload()
        return response

    def identify_payload(self) -> tuple[bool, str]:
        """
        Identify the payload, re-reduce with it and restart the filter; return (ok, report).

        The new estimator starts from the next samples: the filter initialises at
        the new mu with its covariance. A refusal (poor excitation, an external
        wrench in the window) keeps the model and says why.
        """
        from reduced_dynamics.identify import IdentificationError, SensorNoise
        from reduced_dynamics.payload import with_payload
        window = self._payload_window
        if window is None:
            return False, 'payload_link is empty: no link to identify a payload on'
        try:
            estimate = window.identify(SensorNoise.from_config(self._config))
            estimator = self._make_estimator(with_payload(self._nominal_robot,
                                                          estimate.payload))
        except (IdentificationError, ModelError, ValueError, ArithmeticError) as error:
            self.get_logger().warning(f'payload identification refused: {error}')
            return False, f'refused: {error}'
        self._flush_pending()
        self._estimator = estimator
        self.payload = estimate.payload
        window.clear()
        self._publish_payload()
        report = estimate.text()
        self.get_logger().info('payload applied, robot re-reduced, filter restarted:\n'
                               + report)
        return True, report

    def _publish_payload(self) -> None:
        if self._payload_publisher is None or self.payload is None:
            return
        from reduced_dynamics.payload_online import inertia_fields
        fields = inertia_fields(self.payload)
        msg = self._types.get('geometry_msgs/msg/InertiaStamped')()
        msg.header.stamp = self.get_clock().now().to_msg()
        msg.header.frame_id = self.payload.link
        msg.inertia.m = fields['m']
        msg.inertia.com.x, msg.inertia.com.y, msg.inertia.com.z = fields['com']
        for name in ('ixx', 'ixy', 'ixz', 'iyy', 'iyz', 'izz'):
            setattr(msg.inertia, name, fields[name])
        self._payload_publisher.publish(msg)

    def _on_robot_description(self, msg: Any) -> None:
        text = string_from_ros(msg)
        if text == self._description_text:
            return  # republished unchanged: keep the estimator's state
        if not text.lstrip().startswith('<'):
            # A message must never make the node open a path on its disk.
            self._reject('malformed', f'robot_description message is not URDF XML '
                                      f'({text[:40]!r}): ignored')
            return
        self._description_text = text
        self._set_robot(text, f'the {self.resolve_topic_name(ROBOT_DESCRIPTION_TOPIC)} topic')

    # --- activation -------------------------------------------------------------------
    def _activate(self) -> None:
        """Advertise the outputs, subscribe to the inputs, start the worker and the status."""
        # rclpy's default policies, and durability: a transient-local reader gets what a
        # writer sent before the two matched (issue 24.1: a late match lost a bag's start).
        overridable = QoSOverridingOptions(
            policy_kinds=(QoSPolicyKind.HISTORY, QoSPolicyKind.DEPTH,
                          QoSPolicyKind.RELIABILITY, QoSPolicyKind.DURABILITY))
        # cyclic_joints and commanded_wrench_topic are read-only: a topic that can never
        # carry a message is not advertised (a stack would wait on it).
        self._output_topics = active_topics(bool(self._value('cyclic_joints')),
                                            bool(self._value('commanded_wrench_topic')))
        for topic in self._output_topics + FIXED_LAG_TOPICS + (EVENTS_TOPIC,):
            self._publishers_by_topic[topic.name] = self.create_publisher(
                self._types.get(topic.msgtype),
                topic.name if topic.name.startswith('/') else '~/' + topic.name,
                reliable_qos(), qos_overriding_options=overridable,
                event_callbacks=quiet_publisher_events())
            # Types without a fixed-layout encoder (prediction covariance): the typestore's
            # serializer, as replay writes them (same bytes).
            encoder = cdr.ENCODERS.get(topic.msgtype) if topic.fast_encoding else None
            self._encoders[topic.name] = encoder or cdr_encoder(topic, RosbagsTypes())
        # A chunk's every-row outputs published from its columns (_publish_chunk).
        column = [t for t in self._output_topics if t.field in COLUMN_FIELDS]
        self._column_topics = [(t.name, t.field) for t in column]
        self._occasional_topics = [t for t in self._output_topics
                                   if t.field not in COLUMN_FIELDS]
        if not all(self._encoders[t.name] in COLUMN_ENCODERS for t in column):
            self._column_topics = []
        self._fixed_lag_columns = all(self._encoders[t.name] is cdr.encode_wrench_stamped
                                      for t in FIXED_LAG_TOPICS)
        self._subscribe_inputs(overridable)
        latched = QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL,
                             reliability=ReliabilityPolicy.RELIABLE)
        self._payload_publisher = self.create_publisher(
            self._types.get('geometry_msgs/msg/InertiaStamped'), PAYLOAD_TOPIC, latched)
        self._payload_service = self.create_service(
            self._types.get('std_srvs/srv/Trigger'), IDENTIFY_PAYLOAD_SERVICE,
            self._on_identify_payload)
        self._publish_payload()
        self._warn_unknown_overrides(qos=True)
        self._worker = _PredictionWorker(self._publish_prediction, self._on_worker_error)
        self._lagged_worker = _PredictionWorker(self._publish_lagged, self._on_worker_error,
                                                keep=sys.maxsize, name='fixed-lag rows')
        self._shell_active = True
        self._restart_watchdog()

    def _deactivate(self) -> None:
        """Stop taking input and publishing (outputs of running predictions are dropped)."""
        self._flush_pending()
        self._shell_active = False
        if self._watchdog is not None:
            self.destroy_timer(self._watchdog)
            self._watchdog = None
        self._sensor_inputs = []
        for subscription in self._input_subscriptions:
            self.destroy_subscription(subscription)
        self._input_subscriptions = []
        if self._worker is not None:
            self._worker.stop()
            self._worker = None
        if self._lagged_worker is not None:
            self._lagged_worker.stop()  # what the last passes emitted goes out first
            self._lagged_worker = None
        if self._payload_service is not None:
            self.destroy_service(self._payload_service)
            self.destroy_publisher(self._payload_publisher)
            self._payload_service = self._payload_publisher = None
        with self._publish_lock:
            for publisher in (*self._publishers_by_topic.values(), self._answer_path,
                              self._answer_result):
                if publisher is not None:
                    self.destroy_publisher(publisher)
            self._publishers_by_topic = {}
            self._answer_path = self._answer_result = None

    def _subscribe_inputs(self, overridable: 'QoSOverridingOptions') -> None:
        def subscribe(msgtype: str, topic: str, callback: Callable, qos: 'QoSProfile',
                      raw: bool = False) -> None:
            subscription = self.create_subscription(
                self._types.get(msgtype), topic, callback, qos, raw=raw,
                qos_overriding_options=overridable)
            self._input_subscriptions.append(subscription)
            if raw:  # the sensor inputs
                self._sensor_inputs.append((subscription, callback))

        subscribe('sensor_msgs/msg/JointState', self._value('joint_states_topic'),
                  self._on_joint_state, input_qos(), raw=True)
        if self._value('base_input') == 'odom':
            subscribe('nav_msgs/msg/Odometry', self._value('odom_topic'), self._on_odometry,
                      input_qos(), raw=True)
        elif self._value('base_input') == 'pose_covariance':
            subscribe('geometry_msgs/msg/PoseWithCovarianceStamped',
                      self._value('base_pose_topic'), self._on_pose_covariance, input_qos(),
                      raw=True)
        else:
            subscribe('geometry_msgs/msg/PoseStamped', self._value('base_pose_topic'),
                      self._on_pose, input_qos(), raw=True)
        if self._value('commanded_wrench_topic'):
            # A sensor-like stream (the thrusters' command), the same policies.
            subscribe('geometry_msgs/msg/WrenchStamped', self._value('commanded_wrench_topic'),
                      self._on_command, input_qos(), raw=True)
        # Planned arm motions (prediction_mode planned) and the base-motion requests:
        # reliable, a plan must not be dropped.
        subscribe('trajectory_msgs/msg/JointTrajectory', self._value('trajectory_topic'),
                  self._on_trajectory, reliable_qos())
        subscribe('trajectory_msgs/msg/JointTrajectory', PREDICT_REQUEST_TOPIC,
                  self._on_predict_request, reliable_qos())
        self._answer_path = self.create_publisher(self._types.get('nav_msgs/msg/Path'),
                                                  PREDICT_PATH_TOPIC, reliable_qos(),
                                                  event_callbacks=quiet_publisher_events())
        self._answer_result = self.create_publisher(
            self._types.get('diagnostic_msgs/msg/DiagnosticArray'), PREDICT_RESULT_TOPIC,
            reliable_qos(), event_callbacks=quiet_publisher_events())

    # --- inputs -----------------------------------------------------------------------
    def _on_trajectory(self, msg: Any) -> None:
        """Take a planned trajectory (what prediction_mode planned follows)."""
        self.received['trajectory'] += 1
        try:
            sample = joint_trajectory_from_ros(msg)
        except (ValueError, TypeError) as error:
            self._reject('malformed', f'trajectory message: {error}')
            return
        if self._estimator is not None:
            self._estimator.add_trajectory(sample)

    def _on_predict_request(self, msg: Any) -> None:
        """
        Answer ~/predict_base_motion: where the base goes if the arm executes this plan.

        Standard types stand in for a service (README "Topics"): the request is a
        JointTrajectory on ~/predict_base_motion/request; the answer a Path on
        ~/predict_base_motion/path and a DiagnosticArray on .../result, whose status
        hardware_id echoes the request header's frame_id.
        """
        self.received['predict_request'] += 1
        request_id = str(getattr(msg.header, 'frame_id', ''))
        answer, error, stamp = None, None, 0
        try:
            sample = joint_trajectory_from_ros(msg)
            if self._estimator is None:
                raise ValueError(self._model_error or 'no robot model')
            stamp = self._estimator.latest_state[0] if self._estimator.latest_state else 0
            answer = self._estimator.predict_base_motion(sample)
        except (ValueError, TypeError, ArithmeticError, RuntimeError) as failure:
            error = str(failure)
        path, result = answer_messages(answer, stamp, request_id, error)
        if path is not None:
            self._answer_path.publish(cdr.encode_path(path))
        self._answer_result.publish(cdr.encode_diagnostic_array(result))

    # Two parameters: rclpy then passes the message info, whose receive time the
    # estimator's stamp policy compares header stamps with (estimator/stamps.py).
    def _on_joint_state(self, data: bytes, info: Any) -> None:
        self._take('joint_states', data, cdr.decode_joint_state, 'sensor_msgs/msg/JointState',
                   joint_state_from_ros, 'joint_state_batch', received_ns(info))
        self._drain_inputs()

    def _on_odometry(self, data: bytes, info: Any) -> None:
        self._take('base', data, cdr.decode_odometry, 'nav_msgs/msg/Odometry',
                   odometry_from_ros, 'base_state_batch', received_ns(info))
        self._drain_inputs()

    def _on_command(self, data: bytes, info: Any) -> None:
        self._take('command', data, cdr.decode_wrench_stamped,
                   'geometry_msgs/msg/WrenchStamped', command_from_ros, 'command_batch',
                   received_ns(info))

    def _on_pose(self, data: bytes, info: Any) -> None:
        base_link = self._estimator.robot.base_link if self._estimator else ''
        self._take('base', data, lambda d: cdr.decode_pose_stamped(d, base_link),
                   'geometry_msgs/msg/PoseStamped',
                   lambda m: pose_stamped_from_ros(m, base_link), 'base_state_batch',
                   received_ns(info))
        self._drain_inputs()

    def _on_pose_covariance(self, data: bytes, info: Any) -> None:
        base_link = self._estimator.robot.base_link if self._estimator else ''
        self._take('base', data,
                   lambda d: cdr.decode_pose_with_covariance_stamped(d, base_link),
                   'geometry_msgs/msg/PoseWithCovarianceStamped',
                   lambda m: pose_with_covariance_stamped_from_ros(m, base_link),
                   'base_state_batch', received_ns(info))
        self._drain_inputs()

    def _drain_inputs(self) -> None:
        """
        Take the sensor messages already waiting, without a round through the executor.

        rclpy's executor takes one message per subscription per wait, and building its
        wait set costs more than the estimator's update of a row; at 1 kHz a node that
        fell behind for a moment would stay behind. Here the sensor subscriptions are
        taken from in turn (one message each, as the executor's order would be) until
        both are empty, at most DRAIN_LIMIT messages, so that a signal or a parameter
        change waits little. Outputs do not depend on how the two inputs interleave.
        """
        if self._draining:
            return
        self._draining = True
        try:
            for _ in range(DRAIN_LIMIT):
                took = False
                for subscription, callback in self._sensor_inputs:
                    try:
                        with subscription.handle:
                            taken = subscription.handle.take_message(subscription.msg_type,
                                                                     subscription.raw)
                    except Exception:  # noqa: B902 - destroyed meanwhile (InvalidHandle)
                        return
                    if taken is not None:
                        callback(*taken)
                        took = True
                if not took:
                    return
        finally:
            self._draining = False

    def _flush_pending(self) -> None:
        """
        Process what is still waiting when the input ends (deactivation, shutdown).

        Joint states newer than the last base sample wait for the next one, and the
        stamp policy holds its candidate outliers: as replay does at a bag's end, they
        are processed or counted as rejected now instead of being lost silently.
        """
        estimator = self._estimator
        if estimator is None:
            return
        self._drain_inputs()
        for output in self._estimate(estimator.flush) or []:
            self._publish(output)

    def _estimate(self, call: Callable[[], list]) -> Optional[list]:
        """
        Return ``call()``'s outputs; on a numerical failure count it and return None.

        The estimator rejects bad input itself; anything it raises is a numerical
        failure. One sample is lost; a crashed node would lose them all.
        """
        try:
            return call()
        except (ArithmeticError, RuntimeError, ValueError) as error:
            self._reject('estimator_error', f'{type(error).__name__}: {error}', error=True)
            return None

    def _decode(self, data: bytes, fast: Callable[[bytes], Any], msgtype: str,
                convert: Callable[[Any], Any]) -> Any:
        """Decode like the replay: the fixed layout first, rclpy's deserializer if it refuses."""
        try:
            return fast(data)
        except cdr.CdrError:
            return convert(deserialize_message(data, self._types.get(msgtype)))

    def _take(self, kind: str, data: bytes, fast: Callable[[bytes], Any], msgtype: str,
              convert: Callable[[Any], Any], method: str,
              receive_ns: Optional[int] = None) -> None:
        """Decode one input message and feed it to the estimator; publish what is ready."""
        self.received[kind] += 1
        try:
            sample = with_receive_time(self._decode(data, fast, msgtype, convert), receive_ns)
        except Exception as error:  # noqa: B902 - rclpy raises several types on bad bytes
            self._reject('malformed', f'{kind} message: {error}')
            return
        stats = self.input_stats.get(kind)
        if stats is not None:
            # Not for commands: sent at switches, their gaps are not losses.
            stats.take(sample.stamp_ns)
            if self._payload_window is not None:
                self._payload_window.take(sample)
        estimator = self._estimator
        if estimator is None:
            self._reject('no_robot_model', self._model_error or 'no robot model')
            return
        rejected_before = sum(estimator.rejected.values())
        batch = self._estimate(lambda: getattr(estimator, method)(sample))
        if batch is None:
            return
        if sum(estimator.rejected.values()) != rejected_before and estimator.last_rejection:
            reason = estimator.last_rejection.partition(':')[0]
            self._warn_throttled(reason, f'input rejected: {estimator.last_rejection}')
        if estimator.clock_resets != self._resets_seen:
            self._on_stamp_reset(estimator)
        for chunk in batch.chunks:
            self._publish_chunk(chunk)

    def _reject(self, reason: str, detail: str, error: bool = False) -> None:
        """Count an input the estimator did not process, and say why (throttled)."""
        if self._estimator is None:
            self.rejected[reason] += 1
        else:
            self._estimator.reject(reason, detail)
        # An estimator failure is this package's fault, not the input's: log an error.
        self._warn_throttled(reason, f'input rejected ({reason}): {detail}', error)

    def _on_stamp_reset(self, estimator: Estimator) -> None:
        """Log and count a restart of the estimator's clock that the stamps caused."""
        self.stamp_resets += estimator.clock_resets - self._resets_seen
        self._resets_seen = estimator.clock_resets
        self.get_logger().warning(
            f'input stamps jumped back while ROS time did not ({estimator.last_reset}): '
            f'estimator clock restarted (stamp reset {self.stamp_resets})')

    def _on_time_jump(self, jump: Any) -> None:
        """Reset the estimator when ROS time went backwards (bag loop, simulator restart)."""
        delta_ns = jump.delta.nanoseconds
        if delta_ns >= 0 or self._estimator is None:
            return
        self.time_resets += 1
        self._last_log_ns.clear()  # throttle times of the old clock are meaningless
        self.get_logger().warning(
            f'ROS time jumped back {-delta_ns * 1e-9:.6g} s: estimator reset '
            f'(reset {self.time_resets})')
        outputs = self._estimator.reset(f'ROS time jumped back {-delta_ns * 1e-9:.6g} s')
        self._resets_seen = self._estimator.clock_resets
        for output in outputs:
            self._publish(output)

    # --- outputs ----------------------------------------------------------------------
    def _publish(self, output: EstimatorOutput) -> None:
        publishers, encoders = self._publishers_by_topic, self._encoders
        if not publishers:
            return  # deactivated
        for topic in self._output_topics:
            sample = getattr(output, topic.field)
            if sample is not None:
                publishers[topic.name].publish(encoders[topic.name](sample))
        if output.fixed_lag:
            # smoothing_lag > 0: rows whose lag passed here, stamped with their own time.
            self._publish_fixed_lag(output.fixed_lag)
        for event in output.events or ():
            publishers[EVENTS_TOPIC.name].publish(encoders[EVENTS_TOPIC.name](event))
        job = output.prediction_job
        if job is not None and self._worker is not None:
            self._worker.submit(job)

    def _publish_chunk(self, chunk: OutputChunk) -> None:
        """
        Publish a processed chunk's outputs, as :meth:`_publish` would output by output.

        The every-row messages are encoded from the chunk's columns at once
        (:meth:`OutputChunk.records`, the bytes of the per-message encoders) and go
        out topic by topic: ``~/momentum`` of every row the sample released first,
        then the other topics; a row's predictions, diagnostics, fixed-lag rows and
        events after them.
        """
        records = chunk.records() if self._column_topics else None
        if records is None:
            for output in chunk.outputs():
                self._publish(output)
            return
        publishers, encoders = self._publishers_by_topic, self._encoders
        if not publishers:
            return  # deactivated
        for name, field in self._column_topics:
            part = records.get(field)
            if part is not None:
                publish = publishers[name].publish
                for data in split(part):
                    publish(data)
        rows = set(chunk.extras or ()) | set(chunk.fixed_lag or ()) | set(chunk.events or ())
        for k in sorted(rows):
            fields = chunk.extra_fields(k)
            for topic in self._occasional_topics:
                sample = fields.get(topic.field)
                if sample is not None:
                    publishers[topic.name].publish(encoders[topic.name](sample))
            lagged = chunk.fixed_lag.get(k) if chunk.fixed_lag else None
            if lagged:
                self._publish_fixed_lag(lagged)
            for event in chunk.row_events(k) or ():
                publishers[EVENTS_TOPIC.name].publish(encoders[EVENTS_TOPIC.name](event))
            job = fields.get('prediction_job')
            if job is not None and self._worker is not None:
                self._worker.submit(job)

    def _publish_fixed_lag(self, rows: Any) -> None:
        """
        Publish fixed-lag rows (a pass's FixedLagRows, or a list of FixedLagRow).

        A pass's rows are encoded topic by topic from their columns (the bytes of the
        per-message encoder; other rows message by message) and published by the
        fixed-lag worker thread: a pass emits a quarter second of rows at once, whose
        publication in the input callback was its largest latency spike
        (docs/fixed_lag.md, "Latency in the node"). The rows are already a lag late;
        every row goes through the one worker, so each topic keeps its order.
        """
        records = rows.records() \
            if self._fixed_lag_columns and isinstance(rows, FixedLagRows) else None
        if records is None:
            encoders = self._encoders
            records = {topic.field: [encoders[topic.name](getattr(row, topic.field))
                                     for row in rows] for topic in FIXED_LAG_TOPICS}
        if self._lagged_worker is not None:
            self._lagged_worker.submit(_Ready(records))
        else:
            self._publish_lagged(records)

    def _publish_lagged(self, records: dict[str, Any]) -> None:
        """Publish fixed-lag messages, per topic field (K, size) uint8 rows or bytes (worker)."""
        with self._publish_lock:
            publishers = self._publishers_by_topic
            if not publishers:
                return  # deactivated meanwhile
            for topic in FIXED_LAG_TOPICS:
                publish = publishers[topic.name].publish
                messages = records[topic.field]
                for data in split(messages) if isinstance(messages, np.ndarray) else messages:
                    publish(data)

    def _publish_prediction(self, messages: Any) -> None:
        """Publish a finished prediction (worker thread), stamped with its start sample."""
        with self._publish_lock:
            publishers = self._publishers_by_topic
            if not publishers:
                return
            for name, sample in (('prediction/shape', messages.shape),
                                 ('prediction/base_path', messages.path),
                                 ('prediction/geometric_phase_path', messages.phase_path),
                                 ('prediction/base_at_horizon', messages.horizon),
                                 ('prediction/covariance_ellipsoids', messages.ellipsoids),
                                 ('prediction/shape_covariance', messages.shape_covariance)):
                if sample is not None:
                    publishers[name].publish(self._encoders[name](sample))

    def _on_worker_error(self, message: str) -> None:
        self.get_logger().error(message)

    # --- node-clock duties ------------------------------------------------------------
    def _warn_throttled(self, key: str, message: str, error: bool = False) -> None:
        """Log a warning (or error) at most once per LOG_THROTTLE_NS of node time per key."""
        now = self.get_clock().now().nanoseconds
        last = self._last_log_ns.get(key)
        # A clock that went backwards (bag loop, sim restart) re-arms the throttle.
        if last is not None and last <= now < last + LOG_THROTTLE_NS:
            self._suppressed[key] += 1
            return
        suppressed = self._suppressed.pop(key, 0)
        if suppressed:
            message += f' ({suppressed} similar suppressed)'
        self._last_log_ns[key] = now
        logger = self.get_logger()
        (logger.error if error else logger.warning)(message)

    def _restart_watchdog(self) -> None:
        if self._watchdog is not None:
            self.destroy_timer(self._watchdog)
            self._watchdog = None
        rate = self._config.diagnostics_rate
        if self._model_error is not None:
            # No model: the ERROR status goes out on steady time, at least every
            # NO_MODEL_STATUS_PERIOD (a diagnostic updater's period), even with
            # diagnostics_rate 0 or use_sim_time without /clock (ROS time stands still).
            from rclpy.clock import Clock, ClockType
            period = min(1.0 / rate, NO_MODEL_STATUS_PERIOD) if rate > 0.0 \
                else NO_MODEL_STATUS_PERIOD
            self._watchdog = self.create_timer(period, self._on_watchdog,
                                               clock=Clock(clock_type=ClockType.STEADY_TIME))
        elif rate > 0.0:
            self._watchdog = self.create_timer(1.0 / rate, self._on_watchdog)

    def node_status(self) -> DiagnosticStatusSample:
        """
        Return the node's own status: model, input and processed rates, losses seen.

        Rates are per second of node time since the previous status. ``missing_*``
        counts samples absent from the input stamps (gaps beyond GAP_FACTOR nominal
        periods): lost before the node (transport, queue overflow) or never sent.
        """
        now = self.get_clock().now().nanoseconds
        estimator = self._estimator
        processed = estimator.processed if estimator else 0
        elapsed = (now - self._last_status_ns) * 1e-9 if self._last_status_ns else 0.0
        self._last_status_ns = now
        rejected = Counter(self.rejected)
        if estimator is not None:
            rejected.update(estimator.rejected)
        values = {'robot_model': self._robot_source,
                  'processed': str(processed),
                  'rejected_total': str(sum(rejected.values())),
                  'predictions_pending': str(self.predictions_pending),
                  'predictions_skipped': str(self._worker.skipped if self._worker else 0),
                  'time_resets': str(self.time_resets),
                  'stamp_resets': str(self.stamp_resets)}
        lost = 0
        for kind, stats in self.input_stats.items():
            window = stats.window()
            values[f'received_{kind}'] = str(stats.received)
            values[f'missing_{kind}'] = str(stats.missing)
            lost += stats.missing
            if elapsed > 0.0:
                values[f'input_rate_{kind}'] = f'{window / elapsed:.1f}'
        if elapsed > 0.0:
            values['processed_rate'] = f'{(processed - self._processed_at_status) / elapsed:.1f}'
        self._processed_at_status = processed
        if self._value('commanded_wrench_topic'):
            values['received_command'] = str(self.received['command'])
        if self.payload is not None:
            sigma = self.payload.sigma
            values['payload'] = (
                f'{self.payload.mass:.4g} kg on {self.payload.link}, CoM '
                + ' '.join(f'{c:+.4f}' for c in self.payload.com) + ' m, principal inertia '
                + ' '.join(f'{c:.4g}' for c in self.payload.principal_inertia) + ' kg m^2'
                + (f' (mass sigma {sigma["mass"]:.2g} kg)' if 'mass' in sigma else ''))
        if self._payload_window is not None and self._payload_window.last_error:
            values['payload_identification'] = self._payload_window.last_error
        values.update({f'rejected_{k}': str(v) for k, v in sorted(rejected.items())})
        if self._model_error:
            level, message = DIAG_ERROR, self._model_error
        elif lost:
            level = DIAG_WARN
            message = f'{lost} input samples missing (stamp gaps): input lost before the node'
        elif not sum(s.received for s in self.input_stats.values()):
            level, message = DIAG_WARN, 'no input received yet'
        else:
            level, message = DIAG_OK, 'running'
        if self._description_sub is not None and self._description_text is None:
            message += '; waiting for robot_description (paper robot stands in)'
        hardware = estimator.robot.model.name if estimator else ''
        return DiagnosticStatusSample(level, NODE_STATUS_NAME, message, hardware, values)

    def _on_watchdog(self) -> None:
        """Publish the node's status at diagnostics_rate (node clock)."""
        if not self._publishers_by_topic:
            return
        status = self.node_status()
        stamp_ns = self.get_clock().now().nanoseconds
        self._publishers_by_topic[DIAGNOSTICS_TOPIC].publish(
            cdr.encode_diagnostic_array(Diagnostics(stamp_ns, (status,))))

    def _summary(self) -> None:
        estimator = self._estimator
        if estimator is not None:
            self.get_logger().info(
                f'processed {estimator.processed} samples; rejected '
                f'{dict(estimator.rejected + self.rejected) or "none"}')


class ReducedDynamicsNode(_Shell, Node):
    """Estimate momentum, shape state, drift and predictions (plain node: active at once)."""

    def __init__(self, **node_options: Any) -> None:
        """Create the node; ``node_options`` go to rclpy's Node (parameter_overrides, ...)."""
        Node.__init__(self, NODE_NAME, **node_options)
        self._init_shell()
        self._configure()
        self._activate()

    def destroy_node(self) -> None:
        """Stop the worker, log what was processed, then destroy the node."""
        if self._shell_active:
            self._deactivate()
        self._summary()
        if self._jump_handler is not None:
            self._jump_handler.unregister()
            self._jump_handler = None
        Node.destroy_node(self)


class ReducedDynamicsLifecycleNode(_Shell, LifecycleNode):
    """
    The same node as a managed (lifecycle) node.

    configure: read the parameters, load and check the robot model (FAILURE with
    the reason if unusable); activate: subscribe and publish; deactivate: stop
    both; cleanup: forget the model; shutdown: from any state.
    """

    def __init__(self, **node_options: Any) -> None:
        """Create the node unconfigured; ``node_options`` go to rclpy's LifecycleNode."""
        LifecycleNode.__init__(self, NODE_NAME, **node_options)
        self._init_shell()
        # rclpy's change_state service raises on a transition the current state does not
        # have ("Transition is not registered"), which ends the executor: answer failure.
        service = self._service_change_state
        change_state = service.callback

        def refuse_invalid(request: Any, response: Any) -> Any:
            try:
                return change_state(request, response)
            except _rclpy.RCLError as error:
                transition = request.transition
                self.get_logger().warning(
                    f'lifecycle transition {transition.label or transition.id} refused in '
                    f'state {self._state_machine.current_state[1]}: '
                    f'{str(error).splitlines()[0]}')
                response.success = False
                return response
        service.callback = refuse_invalid

    def on_configure(self, state: Any) -> 'TransitionCallbackReturn':
        """Load and check the robot model."""
        error = self._configure()
        if error:
            self._cleanup()
            return TransitionCallbackReturn.FAILURE
        return TransitionCallbackReturn.SUCCESS

    def on_activate(self, state: Any) -> 'TransitionCallbackReturn':
        """Subscribe and publish."""
        self._activate()
        return TransitionCallbackReturn.SUCCESS

    def on_deactivate(self, state: Any) -> 'TransitionCallbackReturn':
        """Stop taking input and publishing; keep the model and the estimator state."""
        self._deactivate()
        return TransitionCallbackReturn.SUCCESS

    def on_cleanup(self, state: Any) -> 'TransitionCallbackReturn':
        """Forget the robot model and the estimator."""
        self._cleanup()
        return TransitionCallbackReturn.SUCCESS

    def on_shutdown(self, state: Any) -> 'TransitionCallbackReturn':
        """Stop everything, from any primary state."""
        if self._shell_active:
            self._deactivate()
        self._summary()
        self._cleanup()
        return TransitionCallbackReturn.SUCCESS

    def destroy_node(self) -> None:
        """Stop the worker, then destroy the node."""
        if self._shell_active:
            self._deactivate()
        if self._jump_handler is not None:
            self._jump_handler.unregister()
            self._jump_handler = None
        LifecycleNode.destroy_node(self)


class _StopOnSignal:
    """
    SIGINT and SIGTERM set a flag (and wake the executor) instead of raising.

    rclpy's own signal handler shuts the context down at once, under the
    callbacks' feet: a message being taken then fails inside rclpy.spin
    ("Unable to convert call argument"), and the shutdown log lines cannot
    reach /rosout. A Python KeyboardInterrupt can land anywhere, including
    inside rclpy's conversions. Here the signal only asks the spin loop to end;
    the node is destroyed while the context is still valid, then rclpy shuts down.
    """

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self) -> None:
        self.stop = threading.Event()
        self.executor: Optional[Any] = None
        self._previous = {sig: signal.signal(sig, self._on_signal) for sig in self.SIGNALS}

    def _on_signal(self, signum: int, frame: Any) -> None:
        self.stop.set()
        if self.executor is not None:
            self.executor.wake()

    def restore(self) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)


def spin_until_signal(node: Any, stopper: '_StopOnSignal') -> None:
    """Spin ``node`` until SIGINT or SIGTERM (or an external shutdown)."""
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    stopper.executor = executor
    try:
        while not stopper.stop.is_set():
            executor.spin_once(timeout_sec=0.1)
    except ExternalShutdownException:
        pass
    finally:
        stopper.executor = None
        executor.remove_node(node)
        executor.shutdown(timeout_sec=1.0)


def usage_text() -> str:
    """Return the parameters (with defaults) and the topics, as ``--help`` prints them."""
    def entry(head: str, text: str) -> list[str]:
        indent = ' ' * 6
        return ['  ' + head] + textwrap.wrap(text, 92, initial_indent=indent,
                                             subsequent_indent=indent)

    lines = ['parameters (--ros-args -p NAME:=VALUE, or --ros-args --params-file FILE):']
    for name, spec in ALL_PARAMETERS.items():
        default = spec.default if spec.default != '' else "''"
        changes = 'at run time' if name in RUNTIME_PARAMETERS else 'at start-up'
        lines += entry(f'{name} (default: {default}; set {changes})', spec.description)
    lines += ['', 'inputs (topic names are the parameters named; relative to the namespace):']
    for head, text in (
            ('joint_states_topic: sensor_msgs/msg/JointState', 'shape joint states'),
            ('odom_topic: nav_msgs/msg/Odometry', 'base state (base_input odom)'),
            ('base_pose_topic: geometry_msgs/msg/PoseStamped', 'base pose (base_input pose)'),
            ('base_pose_topic: geometry_msgs/msg/PoseWithCovarianceStamped',
             'base pose with its covariance (base_input pose_covariance)'),
            ('trajectory_topic: trajectory_msgs/msg/JointTrajectory',
             'planned arm motion (prediction_mode planned)'),
            ('commanded_wrench_topic: geometry_msgs/msg/WrenchStamped',
             'commanded body wrench (empty: off)'),
            (f'{ROBOT_DESCRIPTION_TOPIC}: std_msgs/msg/String (latched)',
             'URDF XML, when the robot_description and urdf_path parameters are empty'),
            (f'{PREDICT_REQUEST_TOPIC}: trajectory_msgs/msg/JointTrajectory',
             'where does the base go if the arm executes this plan (answered on '
             f'{PREDICT_PATH_TOPIC}, nav_msgs/msg/Path, and {PREDICT_RESULT_TOPIC}, '
             'diagnostic_msgs/msg/DiagnosticArray)')):
        lines += entry(head, text)
    lines += ['', 'outputs:']
    for topic in OUTPUT_TOPICS + FIXED_LAG_TOPICS + (EVENTS_TOPIC,):
        name = topic.name if topic.name.startswith('/') else '~/' + topic.name
        lines += entry(f'{name}: {topic.msgtype}', topic.meaning)
    return '\n'.join(lines)


def _argument_parser(lifecycle: bool) -> argparse.ArgumentParser:
    """Return the parser of the executable's own arguments (ROS arguments are rclpy's)."""
    prog = 'reduced_dynamics_lifecycle_node' if lifecycle else 'reduced_dynamics_node'
    parser = argparse.ArgumentParser(
        prog=prog, allow_abbrev=False, formatter_class=argparse.RawDescriptionHelpFormatter,
        usage='%(prog)s [-h] [--lifecycle] [--ros-args -p NAME:=VALUE ... '
              '--params-file FILE ...]',
        description='ROS 2 node: momentum, shape state, drift and predictions of a '
                    'free-floating robot from its joint states and base state.',
        epilog=usage_text())
    parser.add_argument('--lifecycle', action='store_true',
                        help='run as a managed (lifecycle) node')
    return parser


def _own_args(argv: Sequence[str]) -> list[str]:
    """Return the arguments outside ``--ros-args ... [--]`` (the program name dropped)."""
    own, in_ros = [], False
    for arg in argv[1:]:
        if arg == '--ros-args':
            in_ros = True
        elif in_ros and arg == '--':
            in_ros = False
        elif not in_ros:
            own.append(arg)
    return own


def main(args: Optional[Sequence[str]] = None, lifecycle: bool = False) -> int:
    """Run the node until Ctrl-C, SIGTERM or an external shutdown; ``--lifecycle``: managed."""
    argv = list(sys.argv if args is None else args)
    try:
        # Unknown arguments are left to rclpy, as before (launch adds its own).
        options, _ = _argument_parser(lifecycle).parse_known_args(_own_args(argv))
    except SystemExit as done:  # --help (exit 0) or a malformed option (exit 2)
        return int(done.code or 0)
    if rclpy is None:
        print(ROS_NOT_SOURCED, file=sys.stderr)
        return 1
    try:
        # One BLAS thread for the process, the prediction worker's included: the node's
        # outputs are replay's, whatever the machine's core count (blas_threads).
        limit_blas_threads()
    except ValueError as error:
        print(f'reduced_dynamics_node: {error}', file=sys.stderr)
        return 2
    # The kernels load (after an install: compile, minutes) before rclpy starts: a signal
    # meanwhile still ends the process at once with node_main's start-up line (the
    # node's own handling below would wait for the compilation to finish), and the
    # node's configuration then finds them loaded.
    if options.lifecycle:
        argv.remove('--lifecycle')
        lifecycle = True
    program = 'reduced_dynamics_lifecycle_node' if lifecycle else 'reduced_dynamics_node'
    with compiling_notice(lambda text: print(f'{program}: {text}', file=sys.stderr,
                                             flush=True)):
        warm_up()
    stopper = _StopOnSignal()  # first: a signal during start-up also ends cleanly
    try:
        rclpy.init(args=argv, signal_handler_options=SignalHandlerOptions.NO)
        node_class = ReducedDynamicsLifecycleNode if lifecycle else ReducedDynamicsNode
        try:
            node = node_class()
        except ParameterException as error:  # bad params file / -p value: one line
            print(f'reduced_dynamics_node: invalid parameters: {error}', file=sys.stderr)
            rclpy.try_shutdown()
            return 2
        except InvalidQosOverridesError as error:
            print(f'reduced_dynamics_node: invalid QoS override: {error}', file=sys.stderr)
            rclpy.try_shutdown()
            return 2
        try:
            spin_until_signal(node, stopper)
        finally:
            node.destroy_node()
            rclpy.try_shutdown()
    finally:
        stopper.restore()
    return 0


def lifecycle_main(args: Optional[Sequence[str]] = None) -> int:
    """Run the managed (lifecycle) node: the ``reduced_dynamics_lifecycle_node`` executable."""
    return main(args, lifecycle=True)


if __name__ == '__main__':
    sys.exit(main())
