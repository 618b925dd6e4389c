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
follows ``/clock`` under ``use_sim_time``) only times the diagnostics watchdog
and the log throttle.

Robot model: the ``robot_description`` parameter if non-empty, else
``urdf_path``, else the latched ``robot_description`` topic, with the built-in
paper robot standing in until that topic delivers. A model that fails to load
is logged; the node keeps running, counts its inputs as rejected and reports
the error on ``/diagnostics``.

This is the only module importing rclpy, and it stays importable without it:
``main()`` then prints one line saying ROS 2 is not sourced and returns 1.
"""

from __future__ import annotations

import array
from collections import Counter
import sys
from typing import Any, Callable, Optional, Sequence

import numpy as np

from reduced_dynamics.estimator import Estimator, EstimatorConfig, EstimatorOutput
from reduced_dynamics.estimator.config import PARAMETERS as ESTIMATOR_PARAMETERS
from reduced_dynamics.estimator.base_motion import answer_messages
from reduced_dynamics.estimator.config import ParameterSpec
from reduced_dynamics.messages import (
    DIAG_ERROR, DIAG_WARN, Diagnostics, diagnostics_to_ros, DiagnosticStatusSample,
    joint_state_from_ros, joint_trajectory_from_ros, odometry_from_ros, pose_path_to_ros,
    pose_stamped_from_ros, RclpyTypes, string_from_ros)
from reduced_dynamics.params import ALL_PARAMETERS, check_any_parameter, RUNTIME_PARAMETERS
from reduced_dynamics.robot.model import load_robot, ModelError
from reduced_dynamics.topics import DIAGNOSTICS_TOPIC, NODE_NAME, OUTPUT_TOPICS, output_messages

try:
    # rclpy first: if it is missing, ROS 2 is not sourced (rcl_interfaces comes with it).
    import rclpy
    from rclpy.exceptions import ParameterException
    from rclpy.executors import ExternalShutdownException
    from rclpy.node import Node
    from rclpy.parameter import Parameter
    from rclpy.qos import DurabilityPolicy
    from rclpy.qos import HistoryPolicy
    from rclpy.qos import qos_profile_sensor_data
    from rclpy.qos import QoSProfile
    from rclpy.qos import ReliabilityPolicy
    from rcl_interfaces.msg import FloatingPointRange
    from rcl_interfaces.msg import ParameterDescriptor
    from rcl_interfaces.msg import SetParametersResult
except ImportError:  # main() explains; the ROS-free core must stay usable
    rclpy = None
    Node = object

ROS_NOT_SOURCED = ('reduced_dynamics_node: ROS 2 Jazzy is not sourced (rclpy not importable); '
                   'source /opt/ros/jazzy/setup.bash')
#: Latched URDF topic (robot_state_publisher), relative to the node's namespace.
ROBOT_DESCRIPTION_TOPIC = 'robot_description'
#: Node-clock time between two log lines about the same kind of rejected input.
LOG_THROTTLE_NS = 5_000_000_000
OUTPUT_QOS_DEPTH = 10
#: ~/predict_base_motion as a request/response topic pair (standard types; README).
PREDICT_REQUEST_TOPIC = '~/predict_base_motion/request'
PREDICT_PATH_TOPIC = '~/predict_base_motion/path'
PREDICT_RESULT_TOPIC = '~/predict_base_motion/result'
NS_PER_S = 1_000_000_000


def _plain(value: Any) -> Any:
    """Return a parameter value as the ROS-free core expects it (lists, not array.array)."""
    # rclpy hands DOUBLE_ARRAY values from overrides and services over as array.array.
    if isinstance(value, (array.array, tuple, np.ndarray)):
        return [v.item() if isinstance(v, np.generic) else v for v in value]
    return value


def parameter_descriptor(name: str, spec: ParameterSpec) -> 'ParameterDescriptor':
    """Return the ParameterDescriptor of one row of ALL_PARAMETERS."""
    descriptor = ParameterDescriptor(
        name=name, description=spec.description,
        type=Parameter.Type.from_parameter_value(_default(spec)).value,
        read_only=name not in RUNTIME_PARAMETERS)
    if spec.low is not None:
        descriptor.floating_point_range = [FloatingPointRange(
            from_value=float(spec.low), to_value=float(spec.high), step=0.0)]
    if spec.choices:
        descriptor.additional_constraints = 'one of: ' + ', '.join(spec.choices)
    return descriptor


def _default(spec: ParameterSpec) -> Any:
    """Return a fresh copy of a default (the table's lists are shared)."""
    return list(spec.default) if isinstance(spec.default, list) else spec.default


class ReducedDynamicsNode(Node):
    """Estimate momentum, shape state, drift and predictions from joint and base states."""

    def __init__(self, **node_options: Any) -> None:
        """Create the node; ``node_options`` go to rclpy's Node (parameter_overrides, ...)."""
        super().__init__(NODE_NAME, **node_options)
        self._types = RclpyTypes()
        self._started = False
        self._estimator: Optional[Estimator] = None
        self._robot_source = ''
        self._model_error: Optional[str] = None
        self._description_text: Optional[str] = None
        self._description_sub = None
        self._watchdog = None
        self._diagnostics_published = False
        self._last_log_ns: dict[str, int] = {}
        self._suppressed: Counter = Counter()
        #: Messages taken by the input callbacks, per input.
        self.received: Counter = Counter()
        #: Inputs rejected while there is no estimator (no usable robot model).
        self.rejected: Counter = Counter()

        # Validation is in place before declaring, so bad overrides fail at start-up.
        self.add_on_set_parameters_callback(self._validate_parameters)
        for name, spec in ALL_PARAMETERS.items():
            self.declare_parameter(name, _default(spec), parameter_descriptor(name, spec))
        self.add_post_set_parameters_callback(self._apply_parameters)
        self._config = EstimatorConfig.from_mapping(
            {name: self._value(name) for name in ESTIMATOR_PARAMETERS})

        reliable = QoSProfile(depth=OUTPUT_QOS_DEPTH, history=HistoryPolicy.KEEP_LAST,
                              reliability=ReliabilityPolicy.RELIABLE)
        self._publishers_by_topic = {
            topic.name: self.create_publisher(
                self._types.get(topic.msgtype),
                topic.name if topic.name.startswith('/') else '~/' + topic.name, reliable)
            for topic in OUTPUT_TOPICS}

        self._load_initial_model()
        self._subscribe_inputs()
        self._restart_watchdog()
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

    # --- parameters -------------------------------------------------------------------
    def _value(self, name: str) -> Any:
        return _plain(self.get_parameter(name).value)

    def _validate_parameters(self, parameters: list) -> 'SetParametersResult':
        """Accept or reject a change (on-set callback: no side effects here)."""
        changes = {}
        for parameter in parameters:
            if parameter.name not in ALL_PARAMETERS:
                continue  # use_sim_time and the like: rclpy's own callbacks decide
            if self._started and parameter.name not in RUNTIME_PARAMETERS:
                # The read_only descriptor already stops this; kept so the rule holds even
                # if a descriptor is ever relaxed.
                return SetParametersResult(
                    successful=False,
                    reason=f'{parameter.name} is read at start-up only; restart the node')
            value = _plain(parameter.value)
            try:
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
        changes = {p.name: _plain(p.value) for p in parameters if p.name in ESTIMATOR_PARAMETERS}
        if not changes:
            return
        self._config = self._config.replaced(**changes)
        if self._estimator is not None:
            self._estimator.apply_config(self._config)
        if 'diagnostics_rate' in changes:
            self._restart_watchdog()
        self.get_logger().info('parameters changed: ' + ', '.join(
            f'{name}={value!r}' for name, value in sorted(changes.items())))

    # --- robot model ------------------------------------------------------------------
    def _load_initial_model(self) -> None:
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

    def _set_robot(self, urdf: str, source: str) -> None:
        """Build the robot model and a fresh estimator; on failure stop estimating."""
        self._robot_source = source
        try:
            robot = load_robot(urdf, self._value('base_joint'),
                               np.array(self._value('gravity'), dtype=float))
            # cyclic_joints that the robot cannot be reduced by fail here, with the reason.
            self._estimator = Estimator(robot, self._config,
                                        use_odometry=self._value('base_input') == 'odom',
                                        cyclic_joints=self._value('cyclic_joints'))
        except (ModelError, OSError) as error:
            self._estimator = None
            self._model_error = f'cannot use the robot model from {source}: {error}'
            self.get_logger().error(self._model_error + '; not estimating until a usable '
                                                        'model is given')
            return
        self._model_error = None
        self.get_logger().info(
            f'robot {robot.model.name} from {source}: base {robot.group.name} '
            f'({robot.base_link}), {robot.m} shape joints {list(robot.shape_joint_names)}')
        if self._estimator.cyclic_joints:
            self.get_logger().info(
                'second-stage reduction (Theorem 57) by the cyclic joints '
                f'{list(self._estimator.cyclic_joints)}: their momenta on cyclic_momenta')

    def _on_robot_description(self, msg: Any) -> None:
        text = string_from_ros(msg)
        if text == self._description_text:
            return  # republished unchanged: keep the estimator's state
        self._description_text = text
        self._set_robot(text, f'the {self.resolve_topic_name(ROBOT_DESCRIPTION_TOPIC)} topic')

    # --- inputs and outputs -----------------------------------------------------------
    def _subscribe_inputs(self) -> None:
        self.create_subscription(
            self._types.get('sensor_msgs/msg/JointState'), self._value('joint_states_topic'),
            self._on_joint_state, qos_profile_sensor_data)
        if self._value('base_input') == 'odom':
            self.create_subscription(
                self._types.get('nav_msgs/msg/Odometry'), self._value('odom_topic'),
                self._on_odometry, qos_profile_sensor_data)
        else:
            self.create_subscription(
                self._types.get('geometry_msgs/msg/PoseStamped'),
                self._value('base_pose_topic'), self._on_pose, qos_profile_sensor_data)

        # Planned arm motions (prediction_mode planned) and the base-motion requests:
        # reliable, a plan must not be dropped.
        trajectory_type = self._types.get('trajectory_msgs/msg/JointTrajectory')
        reliable = QoSProfile(depth=OUTPUT_QOS_DEPTH, history=HistoryPolicy.KEEP_LAST,
                              reliability=ReliabilityPolicy.RELIABLE)
        self.create_subscription(trajectory_type, self._value('trajectory_topic'),
                                 self._on_trajectory, reliable)
        self.create_subscription(trajectory_type, PREDICT_REQUEST_TOPIC,
                                 self._on_predict_request, reliable)
        self._answer_path = self.create_publisher(self._types.get('nav_msgs/msg/Path'),
                                                  PREDICT_PATH_TOPIC, reliable)
        self._answer_result = self.create_publisher(
            self._types.get('diagnostic_msgs/msg/DiagnosticArray'), PREDICT_RESULT_TOPIC,
            reliable)

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
            self._answer_path.publish(pose_path_to_ros(path, self._types))
        self._answer_result.publish(diagnostics_to_ros(result, self._types))

    def _on_joint_state(self, msg: Any) -> None:
        self._take('joint_states', msg, joint_state_from_ros, 'add_joint_state')

    def _on_odometry(self, msg: Any) -> None:
        self._take('base', msg, odometry_from_ros, 'add_base_state')

    def _on_pose(self, msg: Any) -> None:
        base_link = self._estimator.robot.base_link if self._estimator else ''
        self._take('base', msg, lambda m: pose_stamped_from_ros(m, base_link), 'add_base_state')

    def _take(self, kind: str, msg: Any, convert: Callable[[Any], Any], method: str) -> None:
        """Convert one input message and feed it to the estimator; publish what is ready."""
        self.received[kind] += 1
        try:
            sample = convert(msg)
        except (ValueError, TypeError) as error:
            self._reject('malformed', f'{kind} message: {error}')
            return
        estimator = self._estimator
        if estimator is None:
            self._reject('no_robot_model', self._model_error or 'no robot model')
            return
        rejected_before = sum(estimator.rejected.values())
        try:
            outputs = getattr(estimator, method)(sample)
        except (ArithmeticError, RuntimeError, ValueError) as error:
            # The estimator rejects bad input itself; anything it raises is a numerical
            # failure (e.g. a prediction that did not converge). One sample is lost; a
            # crashed node would lose them all.
            self._reject('estimator_error', f'{type(error).__name__}: {error}', error=True)
            return
        if sum(estimator.rejected.values()) != rejected_before and estimator.last_rejection:
            reason = estimator.last_rejection.partition(':')[0]
            self._warn_throttled(reason, f'input rejected: {estimator.last_rejection}')
        for output in outputs:
            self._publish(output)

    def _reject(self, reason: str, detail: str, error: bool = False) -> None:
        """Count an input the estimator did not process, and say why (throttled)."""
        if self._estimator is None:
            self.rejected[reason] += 1
        else:
            # The estimator's own counter feeds its diagnostics (rejected_<reason>, WARN
            # level); it has no public method for rejections made outside it yet.
            self._estimator.reject(reason, detail)
        # An estimator failure is this package's fault, not the input's: log an error.
        self._warn_throttled(reason, f'input rejected ({reason}): {detail}', error)

    def _publish(self, output: EstimatorOutput) -> None:
        for topic, msg in output_messages(output, self._types):
            self._publishers_by_topic[topic.name].publish(msg)
            if topic.name == DIAGNOSTICS_TOPIC:
                self._diagnostics_published = True

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
        if rate > 0.0:
            self._watchdog = self.create_timer(1.0 / rate, self._on_watchdog)

    def _on_watchdog(self) -> None:
        """Publish the node's own status when the estimator published no diagnostics."""
        if self._diagnostics_published:
            self._diagnostics_published = False
            return
        stamp_ns = self.get_clock().now().nanoseconds
        estimator = self._estimator
        rejected = Counter(self.rejected)
        if estimator is not None:
            rejected.update(estimator.rejected)
        values = {'robot_model': self._robot_source,
                  'received_joint_states': str(self.received['joint_states']),
                  'received_base': str(self.received['base']),
                  'processed': str(estimator.processed if estimator else 0),
                  'rejected_total': str(sum(rejected.values()))}
        values.update({f'rejected_{k}': str(v) for k, v in sorted(rejected.items())})
        if self._model_error:
            level, message = DIAG_ERROR, self._model_error
        else:
            level = DIAG_WARN
            message = 'no input processed since the last status'
            if self._description_sub is not None and self._description_text is None:
                message += '; waiting for robot_description (paper robot stands in)'
        hardware = estimator.robot.model.name if estimator else ''
        status = DiagnosticStatusSample(level, f'{NODE_NAME}: node', message, hardware, values)
        self._publishers_by_topic[DIAGNOSTICS_TOPIC].publish(
            diagnostics_to_ros(Diagnostics(stamp_ns, (status,)), self._types))

    def destroy_node(self) -> None:
        """Log what was processed, then destroy the node."""
        estimator = self._estimator
        if estimator is not None:
            self.get_logger().info(
                f'processed {estimator.processed} samples; rejected '
                f'{dict(estimator.rejected + self.rejected) or "none"}')
        super().destroy_node()


def main(args: Optional[Sequence[str]] = None) -> int:
    """Run the node until Ctrl-C, SIGTERM or an external shutdown (Jazzy demo pattern)."""
    if rclpy is None:
        print(ROS_NOT_SOURCED, file=sys.stderr)
        return 1
    rclpy.init(args=args)
    try:
        node = ReducedDynamicsNode()
    except ParameterException as error:  # bad params file / -p value: one line, no traceback
        print(f'reduced_dynamics_node: invalid parameters: {error}', file=sys.stderr)
        rclpy.try_shutdown()
        return 2
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == '__main__':
    sys.exit(main())
