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
The output topics shared by the node and the replay tool, and their conversion.

Names are relative to the node (``~/momentum`` for the node,
``/reduced_dynamics/momentum`` in a replayed bag); ``/diagnostics`` is absolute.
"""

from __future__ import annotations

from typing import Any, Callable, Iterator, NamedTuple

from reduced_dynamics.estimator.pipeline import EstimatorOutput
from reduced_dynamics.messages import cdr
from reduced_dynamics.messages.convert import (
    diagnostics_to_ros, event_to_ros, joint_state_to_ros, pose_path_to_ros,
    shape_prediction_to_ros, twist_to_ros, wrench_to_ros)
from reduced_dynamics.messages.types import MessageTypes, RosbagsTypes
from reduced_dynamics.messages.uncertainty import (
    ellipsoids_to_ros, predicted_odometry_to_ros, shape_covariance_to_ros)

NODE_NAME = 'reduced_dynamics'
DIAGNOSTICS_TOPIC = '/diagnostics'


class OutputTopic(NamedTuple):
    """An output: relative topic name, message type, field of EstimatorOutput, converter."""

    name: str
    msgtype: str
    field: str
    to_ros: Callable[[Any, MessageTypes], Any]
    meaning: str
    #: False: the sample is not what ``cdr.ENCODERS[msgtype]`` encodes (two samples share
    #: std_msgs/Float64MultiArray: events and the shape covariance); the generic serializer.
    fast_encoding: bool = True


OUTPUT_TOPICS: tuple[OutputTopic, ...] = (
    OutputTopic('momentum', 'geometry_msgs/msg/WrenchStamped', 'momentum', wrench_to_ros,
                'mu: force = linear momentum [kg m/s], torque = angular momentum about the '
                'world origin [kg m^2/s], world frame'),
    OutputTopic('body_momentum', 'geometry_msgs/msg/WrenchStamped', 'body_momentum',
                wrench_to_ros, 'pi = Ad_g^T mu, base frame'),
    OutputTopic('shape_state', 'sensor_msgs/msg/JointState', 'shape_state',
                joint_state_to_ros, 'qbar (position), qbar_dot (velocity), reduced momentum '
                'pbar = S qbar_dot (effort field) [N m s or N s]'),
    OutputTopic('cyclic_momenta', 'sensor_msgs/msg/JointState', 'cyclic_state',
                joint_state_to_ros, 'second stage only: cyclic joints (reaction wheels), '
                'angle (position), rate (velocity) and conserved momentum theta = rows of '
                'M v (effort) [N m s]; shape_state then holds the other joints, with p^ = '
                'K^ q^_dot'),
    OutputTopic('drift/momentum_rate', 'geometry_msgs/msg/WrenchStamped', 'momentum_rate',
                wrench_to_ros, 'estimated d mu/dt = external wrench [N, N m], world frame '
                '(with a commanded wrench: the total, delivered command plus disturbance)'),
    OutputTopic('drift/disturbance', 'geometry_msgs/msg/WrenchStamped', 'disturbance',
                wrench_to_ros, 'commanded wrench only (commanded_wrench_topic): the '
                'disturbance beyond the command, i.e. drift/momentum_rate minus the '
                'delivered command (estimated gain and bias) [N, N m], world frame'),
    OutputTopic('drift/base_twist', 'geometry_msgs/msg/TwistStamped', 'drift_twist',
                twist_to_ros, 'I^-1 pi: base twist due to momentum alone, base frame'),
    OutputTopic('prediction/shape', 'trajectory_msgs/msg/JointTrajectory', 'prediction',
                shape_prediction_to_ros, 'torque-driven prediction modes (coast, '
                'held_torque): predicted qbar, qbar_dot over the horizon'),
    OutputTopic('prediction/base_path', 'nav_msgs/msg/Path', 'prediction_path',
                pose_path_to_ros, 'predicted base poses, world frame (every mode)'),
    OutputTopic('prediction/geometric_phase_path', 'nav_msgs/msg/Path',
                'prediction_phase_path', pose_path_to_ros,
                'prescribed prediction modes (planned, held_velocity): the base path the '
                'arm motion alone causes (geometric phase -A qbar_dot, i.e. the same motion at '
                'zero momentum), world frame; base_path minus this is the drift\'s share'),
    OutputTopic('prediction/base_at_horizon', 'nav_msgs/msg/Odometry', 'prediction_horizon',
                predicted_odometry_to_ros,
                'prediction_covariance: the predicted base at the horizon, stamped with the '
                'time it predicts; pose covariance in the world frame (x, y, z, rotation '
                'about X, Y, Z), body twist with its covariance'),
    OutputTopic('prediction/covariance_ellipsoids', 'visualization_msgs/msg/MarkerArray',
                'prediction_ellipsoids', ellipsoids_to_ros,
                'prediction_covariance: the 95 % position ellipsoids along the predicted '
                'path (SPHERE markers, world frame, for RViz)'),
    OutputTopic('prediction/shape_covariance', 'std_msgs/msg/Float64MultiArray',
                'prediction_shape_covariance', shape_covariance_to_ros,
                'prediction_covariance: covariance of (qbar, qbar_dot) at the horizon, '
                '2m x 2m row-major; dims 2.. label the order (qbar:<joint>, '
                'qbar_dot:<joint>)', fast_encoding=False),
    OutputTopic(DIAGNOSTICS_TOPIC, 'diagnostic_msgs/msg/DiagnosticArray', 'diagnostics',
                diagnostics_to_ros, 'estimator status'),
)

#: Fixed-lag smoothing (``smoothing_lag`` > 0, estimator/fixed_lag.py): one message per
#: row once its lag has passed, stamped with the row's time; ``field`` is that of
#: :class:`~reduced_dynamics.estimator.fixed_lag.FixedLagRow`.
FIXED_LAG_TOPICS: tuple[OutputTopic, ...] = (
    OutputTopic('momentum_smoothed', 'geometry_msgs/msg/WrenchStamped', 'momentum',
                wrench_to_ros, 'momentum as ~/momentum, RTS-smoothed over at least '
                'smoothing_lag of later data, stamped with the time it describes'),
    OutputTopic('drift/momentum_rate_smoothed', 'geometry_msgs/msg/WrenchStamped',
                'momentum_rate', wrench_to_ros, 'drift/momentum_rate RTS-smoothed over at '
                'least smoothing_lag of later data, stamped with the time it describes'),
)

#: External-wrench events (estimator/events.py): one record at an event's detection and
#: one when its impulse has settled; ``field`` is that of EstimatorOutput (a list).
#: std_msgs/Float64MultiArray with the fields named in its layout (docs/multiscale_events.md).
EVENTS_TOPIC = OutputTopic(
    'events', 'std_msgs/msg/Float64MultiArray', 'events', event_to_ros,
    'external-wrench events: start, end, detected (sec, nanosec), window [s], peak |w|, '
    'impulse (fx fy fz tx ty tz [N s, N m s], world) and its 6x6 covariance, final; '
    'the layout names the fields (messages/samples.py EVENT_FIELDS)')

#: The output that exists only with the second-stage reduction on.
CYCLIC_TOPIC = 'cyclic_momenta'
#: The output that exists only with a commanded wrench.
DISTURBANCE_TOPIC = 'drift/disturbance'


def active_topics(second_stage: bool, commanded_wrench: bool = False
                  ) -> tuple[OutputTopic, ...]:
    """
    Return the outputs a run produces.

    ``cyclic_momenta`` only in the second stage, ``drift/disturbance`` only with a
    commanded wrench.
    """
    return tuple(t for t in OUTPUT_TOPICS
                 if (second_stage or t.name != CYCLIC_TOPIC)
                 and (commanded_wrench or t.name != DISTURBANCE_TOPIC))


def resolved_name(topic: OutputTopic, namespace: str = '/' + NODE_NAME) -> str:
    """Return the absolute topic name under the node's private namespace."""
    if topic.name.startswith('/'):
        return topic.name
    return f'{namespace.rstrip("/")}/{topic.name}'


def output_messages(output: EstimatorOutput,
                    types: MessageTypes) -> Iterator[tuple[OutputTopic, Any]]:
    """Yield (topic, ROS message) for every output the sample carries."""
    for topic in OUTPUT_TOPICS:
        sample = getattr(output, topic.field)
        if sample is not None:
            yield topic, topic.to_ros(sample, types)


def cdr_encoder(topic: OutputTopic, types: RosbagsTypes) -> Callable[[Any], bytes]:
    """
    Return a function turning the topic's sample into its CDR bytes.

    The fixed-layout encoder of :mod:`reduced_dynamics.messages.cdr` when it
    applies to ``types.typestore``, else the converter plus the typestore's
    generic serializer (same bytes, about ten times slower).
    """
    if topic.fast_encoding and topic.msgtype in cdr.ENCODERS \
            and cdr.fast_path_applies(types.typestore, topic.msgtype):
        return cdr.ENCODERS[topic.msgtype]
    store, to_ros, msgtype = types.typestore, topic.to_ros, topic.msgtype
    return lambda sample: bytes(store.serialize_cdr(to_ros(sample, types), msgtype))
