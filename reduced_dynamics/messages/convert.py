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
Pure conversions between sample dataclasses and ROS 2 messages.

``*_to_ros(sample, types)`` builds messages through a
:class:`~reduced_dynamics.messages.types.MessageTypes` (rosbags or rclpy
classes).  ``*_from_ros(msg)`` only reads attributes, so it accepts messages
from either source (numpy or ``array.array`` sequences, int or bytes bytes).
Arrays in the returned samples are always fresh copies, never views into
message buffers.
"""

from typing import Any, Optional

import numpy as np
from numpy.typing import ArrayLike

from reduced_dynamics.messages.samples import (
    BaseStateSample,
    CommandSample,
    Diagnostics,
    DiagnosticStatusSample,
    EVENT_FIELDS,
    EventSample,
    JointStateSample,
    JointTrajectorySample,
    message_covariance,
    PosePath,
    ShapePrediction,
    TwistSample,
    WrenchSample,
)
from reduced_dynamics.messages.stamps import (
    duration_from_ros,
    duration_to_ros,
    time_from_ros,
    time_to_ros,
)
from reduced_dynamics.messages.types import byte_to_int, MessageTypes

# ---------------------------------------------------------------- helpers


def _floats(values: Any) -> np.ndarray:
    """Copy a ROS float sequence (numpy, array.array or list) into a float64 array."""
    return np.array(values, dtype=np.float64, copy=True).reshape(-1)


def header_to_ros(stamp_ns: int, frame_id: str, types: MessageTypes) -> Any:
    """Build std_msgs/msg/Header."""
    return types.create(
        'std_msgs/msg/Header', stamp=time_to_ros(stamp_ns, types), frame_id=str(frame_id))


def header_from_ros(msg: Any) -> tuple[int, str]:
    """Return ``(stamp_ns, frame_id)`` of a std_msgs/msg/Header."""
    return time_from_ros(msg.stamp), str(msg.frame_id)


def vector3_to_ros(values: ArrayLike, types: MessageTypes) -> Any:
    """Build geometry_msgs/msg/Vector3."""
    x, y, z = (float(v) for v in np.asarray(values, dtype=np.float64).reshape(3))
    return types.create('geometry_msgs/msg/Vector3', x=x, y=y, z=z)


def point_to_ros(values: ArrayLike, types: MessageTypes) -> Any:
    """Build geometry_msgs/msg/Point."""
    x, y, z = (float(v) for v in np.asarray(values, dtype=np.float64).reshape(3))
    return types.create('geometry_msgs/msg/Point', x=x, y=y, z=z)


def quaternion_to_ros(xyzw: ArrayLike, types: MessageTypes) -> Any:
    """Build geometry_msgs/msg/Quaternion from (x, y, z, w)."""
    x, y, z, w = (float(v) for v in np.asarray(xyzw, dtype=np.float64).reshape(4))
    return types.create('geometry_msgs/msg/Quaternion', x=x, y=y, z=z, w=w)


def xyz_from_ros(msg: Any) -> np.ndarray:
    """Return (3,) from a Vector3 or Point."""
    return np.array([msg.x, msg.y, msg.z], dtype=np.float64)


def xyzw_from_ros(msg: Any) -> np.ndarray:
    """Return (4,) x, y, z, w from a Quaternion."""
    return np.array([msg.x, msg.y, msg.z, msg.w], dtype=np.float64)


def pose_to_ros(position: ArrayLike, orientation_xyzw: ArrayLike, types: MessageTypes) -> Any:
    """Build geometry_msgs/msg/Pose."""
    return types.create(
        'geometry_msgs/msg/Pose',
        position=point_to_ros(position, types),
        orientation=quaternion_to_ros(orientation_xyzw, types),
    )


def _twist_to_ros(linear: ArrayLike, angular: ArrayLike, types: MessageTypes) -> Any:
    """Build geometry_msgs/msg/Twist."""
    return types.create(
        'geometry_msgs/msg/Twist',
        linear=vector3_to_ros(linear, types),
        angular=vector3_to_ros(angular, types),
    )


# ---------------------------------------------------------------- joint state


def joint_state_to_ros(sample: JointStateSample, types: MessageTypes) -> Any:
    """Build sensor_msgs/msg/JointState."""
    return types.create(
        'sensor_msgs/msg/JointState',
        header=header_to_ros(sample.stamp_ns, sample.frame_id, types),
        name=list(sample.names),
        position=types.float_seq(sample.position),
        velocity=types.float_seq(sample.velocity),
        effort=types.float_seq(sample.effort),
    )


def joint_state_from_ros(msg: Any) -> JointStateSample:
    """Convert sensor_msgs/msg/JointState (velocity/effort may be empty)."""
    stamp_ns, frame_id = header_from_ros(msg.header)
    return JointStateSample(
        stamp_ns=stamp_ns,
        frame_id=frame_id,
        names=tuple(str(n) for n in msg.name),
        position=_floats(msg.position),
        velocity=_floats(msg.velocity),
        effort=_floats(msg.effort),
    )


# ---------------------------------------------------------------- base state


def odometry_from_ros(msg: Any) -> BaseStateSample:
    """Convert nav_msgs/msg/Odometry (twist in child frame per REP 105)."""
    stamp_ns, frame_id = header_from_ros(msg.header)
    twist = msg.twist.twist
    return BaseStateSample(
        stamp_ns=stamp_ns,
        frame_id=frame_id,
        child_frame_id=str(msg.child_frame_id),
        position=xyz_from_ros(msg.pose.pose.position),
        orientation_xyzw=xyzw_from_ros(msg.pose.pose.orientation),
        twist_linear=xyz_from_ros(twist.linear),
        twist_angular=xyz_from_ros(twist.angular),
        pose_covariance=message_covariance(_floats(msg.pose.covariance)),
        twist_covariance=message_covariance(_floats(msg.twist.covariance)),
    )


def pose_stamped_from_ros(msg: Any, child_frame_id: str = '') -> BaseStateSample:
    """Convert geometry_msgs/msg/PoseStamped (no twist; child frame given by caller)."""
    stamp_ns, frame_id = header_from_ros(msg.header)
    return BaseStateSample(
        stamp_ns=stamp_ns,
        frame_id=frame_id,
        child_frame_id=child_frame_id,
        position=xyz_from_ros(msg.pose.position),
        orientation_xyzw=xyzw_from_ros(msg.pose.orientation),
    )


def pose_with_covariance_stamped_from_ros(msg: Any, child_frame_id: str = '') -> BaseStateSample:
    """Convert geometry_msgs/msg/PoseWithCovarianceStamped (no twist; covariance kept)."""
    stamp_ns, frame_id = header_from_ros(msg.header)
    return BaseStateSample(
        stamp_ns=stamp_ns,
        frame_id=frame_id,
        child_frame_id=child_frame_id,
        position=xyz_from_ros(msg.pose.pose.position),
        orientation_xyzw=xyzw_from_ros(msg.pose.pose.orientation),
        pose_covariance=message_covariance(_floats(msg.pose.covariance)),
    )


def base_state_to_pose_with_covariance_stamped(sample: BaseStateSample, types: MessageTypes,
                                               covariance: Optional[ArrayLike] = None) -> Any:
    """Build geometry_msgs/msg/PoseWithCovarianceStamped (covariance defaults to zeros)."""
    return types.create(
        'geometry_msgs/msg/PoseWithCovarianceStamped',
        header=header_to_ros(sample.stamp_ns, sample.frame_id, types),
        pose=types.create(
            'geometry_msgs/msg/PoseWithCovariance',
            pose=pose_to_ros(sample.position, sample.orientation_xyzw, types),
            covariance=types.fixed_float_array(
                np.zeros(36) if covariance is None else covariance, 36),
        ),
    )


def base_state_to_odometry(
    sample: BaseStateSample,
    types: MessageTypes,
    pose_covariance: Optional[ArrayLike] = None,
    twist_covariance: Optional[ArrayLike] = None,
) -> Any:
    """
    Build nav_msgs/msg/Odometry; the sample must carry a twist (base frame).

    Covariances are row-major 6x6 (36 values) and default to zeros.
    """
    if not sample.has_twist:
        raise ValueError('BaseStateSample has no twist; use base_state_to_pose_stamped')
    zeros = np.zeros(36)
    pose_cov = zeros if pose_covariance is None else pose_covariance
    twist_cov = zeros if twist_covariance is None else twist_covariance
    return types.create(
        'nav_msgs/msg/Odometry',
        header=header_to_ros(sample.stamp_ns, sample.frame_id, types),
        child_frame_id=str(sample.child_frame_id),
        pose=types.create(
            'geometry_msgs/msg/PoseWithCovariance',
            pose=pose_to_ros(sample.position, sample.orientation_xyzw, types),
            covariance=types.fixed_float_array(pose_cov, 36),
        ),
        twist=types.create(
            'geometry_msgs/msg/TwistWithCovariance',
            twist=_twist_to_ros(sample.twist_linear, sample.twist_angular, types),
            covariance=types.fixed_float_array(twist_cov, 36),
        ),
    )


def base_state_to_pose_stamped(sample: BaseStateSample, types: MessageTypes) -> Any:
    """Build geometry_msgs/msg/PoseStamped (twist and child frame are dropped)."""
    return types.create(
        'geometry_msgs/msg/PoseStamped',
        header=header_to_ros(sample.stamp_ns, sample.frame_id, types),
        pose=pose_to_ros(sample.position, sample.orientation_xyzw, types),
    )


# ---------------------------------------------------------------- wrench / twist


def wrench_to_ros(sample: WrenchSample, types: MessageTypes) -> Any:
    """Build geometry_msgs/msg/WrenchStamped."""
    return types.create(
        'geometry_msgs/msg/WrenchStamped',
        header=header_to_ros(sample.stamp_ns, sample.frame_id, types),
        wrench=types.create(
            'geometry_msgs/msg/Wrench',
            force=vector3_to_ros(sample.force, types),
            torque=vector3_to_ros(sample.torque, types),
        ),
    )


def wrench_from_ros(msg: Any) -> WrenchSample:
    """Convert geometry_msgs/msg/WrenchStamped."""
    stamp_ns, frame_id = header_from_ros(msg.header)
    return WrenchSample(
        stamp_ns=stamp_ns,
        frame_id=frame_id,
        force=xyz_from_ros(msg.wrench.force),
        torque=xyz_from_ros(msg.wrench.torque),
    )


def command_from_ros(msg: Any) -> CommandSample:
    """Convert geometry_msgs/msg/WrenchStamped into a commanded-wrench input sample."""
    stamp_ns, frame_id = header_from_ros(msg.header)
    return CommandSample(stamp_ns=stamp_ns, frame_id=frame_id,
                         force=xyz_from_ros(msg.wrench.force),
                         torque=xyz_from_ros(msg.wrench.torque))


def twist_to_ros(sample: TwistSample, types: MessageTypes) -> Any:
    """Build geometry_msgs/msg/TwistStamped."""
    return types.create(
        'geometry_msgs/msg/TwistStamped',
        header=header_to_ros(sample.stamp_ns, sample.frame_id, types),
        twist=_twist_to_ros(sample.linear, sample.angular, types),
    )


def twist_from_ros(msg: Any) -> TwistSample:
    """Convert geometry_msgs/msg/TwistStamped."""
    stamp_ns, frame_id = header_from_ros(msg.header)
    return TwistSample(
        stamp_ns=stamp_ns,
        frame_id=frame_id,
        linear=xyz_from_ros(msg.twist.linear),
        angular=xyz_from_ros(msg.twist.angular),
    )


# ---------------------------------------------------------------- shape prediction


def _trajectory_to_ros(sample: Any, accelerations: Optional[np.ndarray],
                       types: MessageTypes) -> Any:
    """Build trajectory_msgs/msg/JointTrajectory from a sample's time, position, velocity rows."""
    empty = types.float_seq(np.zeros(0))
    points = []
    for i, t_ns in enumerate(sample.times_from_start_ns):
        points.append(types.create(
            'trajectory_msgs/msg/JointTrajectoryPoint',
            positions=types.float_seq(sample.positions[i]),
            velocities=empty if sample.velocities is None
            else types.float_seq(sample.velocities[i]),
            accelerations=empty if accelerations is None
            else types.float_seq(accelerations[i]),
            effort=types.float_seq(np.zeros(0)),
            time_from_start=duration_to_ros(int(t_ns), types),
        ))
    return types.create(
        'trajectory_msgs/msg/JointTrajectory',
        header=header_to_ros(sample.stamp_ns, sample.frame_id, types),
        joint_names=list(sample.joint_names),
        points=points,
    )


def shape_prediction_to_ros(sample: ShapePrediction, types: MessageTypes) -> Any:
    """Build trajectory_msgs/msg/JointTrajectory (header stamp = start of prediction)."""
    return _trajectory_to_ros(sample, None, types)


def shape_prediction_from_ros(msg: Any) -> ShapePrediction:
    """Convert trajectory_msgs/msg/JointTrajectory (velocities None if absent)."""
    stamp_ns, frame_id = header_from_ros(msg.header)
    names = tuple(str(n) for n in msg.joint_names)
    points = list(msg.points)
    m = len(names)
    times = np.array([duration_from_ros(p.time_from_start) for p in points], dtype=np.int64)
    positions = np.array([_floats(p.positions) for p in points]).reshape(len(points), m)
    have_vel = [len(p.velocities) > 0 for p in points]
    velocities = None
    if points and all(have_vel):
        velocities = np.array([_floats(p.velocities) for p in points]).reshape(len(points), m)
    elif any(have_vel):
        raise ValueError('JointTrajectory has velocities on some points only')
    return ShapePrediction(
        stamp_ns=stamp_ns,
        frame_id=frame_id,
        joint_names=names,
        times_from_start_ns=times,
        positions=positions,
        velocities=velocities,
    )


def joint_trajectory_from_ros(msg: Any) -> JointTrajectorySample:
    """
    Convert trajectory_msgs/msg/JointTrajectory into a planned trajectory (an input).

    Velocities (accelerations) are kept when every point has them, dropped when
    none has; some points only is an error (the interpolation would be ambiguous).
    """
    stamp_ns, frame_id = header_from_ros(msg.header)
    names = tuple(str(n) for n in msg.joint_names)
    points = list(msg.points)
    m = len(names)
    times = np.array([duration_from_ros(p.time_from_start) for p in points], dtype=np.int64)
    positions = np.array([_floats(p.positions) for p in points]).reshape(len(points), m)
    columns = {}
    for key in ('velocities', 'accelerations'):
        have = [len(getattr(p, key)) > 0 for p in points]
        columns[key] = None
        if points and all(have):
            columns[key] = np.array([_floats(getattr(p, key)) for p in points]).reshape(
                len(points), m)
        elif any(have):
            raise ValueError(f'JointTrajectory has {key} on some points only')
    if columns['velocities'] is None:
        columns['accelerations'] = None
    return JointTrajectorySample(stamp_ns, frame_id, names, times, positions,
                                 columns['velocities'], columns['accelerations'])


def joint_trajectory_to_ros(sample: JointTrajectorySample, types: MessageTypes) -> Any:
    """Build trajectory_msgs/msg/JointTrajectory from a planned trajectory."""
    return _trajectory_to_ros(sample, sample.accelerations, types)


# ---------------------------------------------------------------- path


def pose_path_to_ros(sample: PosePath, types: MessageTypes) -> Any:
    """Build nav_msgs/msg/Path; every pose gets its own stamp and the path frame."""
    poses = [
        types.create(
            'geometry_msgs/msg/PoseStamped',
            header=header_to_ros(int(stamp), sample.frame_id, types),
            pose=pose_to_ros(sample.positions[i], sample.orientations_xyzw[i], types),
        )
        for i, stamp in enumerate(sample.stamps_ns)
    ]
    return types.create(
        'nav_msgs/msg/Path',
        header=header_to_ros(sample.stamp_ns, sample.frame_id, types),
        poses=poses,
    )


def pose_path_from_ros(msg: Any) -> PosePath:
    """Convert nav_msgs/msg/Path (per-pose frame ids are ignored)."""
    stamp_ns, frame_id = header_from_ros(msg.header)
    poses = list(msg.poses)
    n = len(poses)
    return PosePath(
        stamp_ns=stamp_ns,
        frame_id=frame_id,
        stamps_ns=np.array([time_from_ros(p.header.stamp) for p in poses], dtype=np.int64),
        positions=np.array([xyz_from_ros(p.pose.position) for p in poses]).reshape(n, 3),
        orientations_xyzw=np.array(
            [xyzw_from_ros(p.pose.orientation) for p in poses]).reshape(n, 4),
    )


# ---------------------------------------------------------------- diagnostics


def diagnostics_to_ros(sample: Diagnostics, types: MessageTypes) -> Any:
    """Build diagnostic_msgs/msg/DiagnosticArray."""
    statuses = [
        types.create(
            'diagnostic_msgs/msg/DiagnosticStatus',
            level=types.byte(status.level),
            name=status.name,
            message=status.message,
            hardware_id=status.hardware_id,
            values=[
                types.create('diagnostic_msgs/msg/KeyValue', key=key, value=value)
                for key, value in status.values
            ],
        )
        for status in sample.statuses
    ]
    return types.create(
        'diagnostic_msgs/msg/DiagnosticArray',
        header=header_to_ros(sample.stamp_ns, sample.frame_id, types),
        status=statuses,
    )


def diagnostics_from_ros(msg: Any) -> Diagnostics:
    """Convert diagnostic_msgs/msg/DiagnosticArray (level may be int or bytes)."""
    stamp_ns, frame_id = header_from_ros(msg.header)
    statuses = tuple(
        DiagnosticStatusSample(
            level=byte_to_int(status.level),
            name=str(status.name),
            message=str(status.message),
            hardware_id=str(status.hardware_id),
            values=tuple((str(kv.key), str(kv.value)) for kv in status.values),
        )
        for status in msg.status
    )
    return Diagnostics(stamp_ns=stamp_ns, statuses=statuses, frame_id=frame_id)


# ---------------------------------------------------------------- events


def event_to_ros(sample: EventSample, types: MessageTypes) -> Any:
    """Build the ``~/events`` record: std_msgs/msg/Float64MultiArray, fields named."""
    dims = [types.create('std_msgs/msg/MultiArrayDimension', label=name, size=size,
                         stride=size) for name, size in EVENT_FIELDS]
    return types.create(
        'std_msgs/msg/Float64MultiArray',
        layout=types.create('std_msgs/msg/MultiArrayLayout', dim=dims, data_offset=0),
        data=types.float_seq(sample.values()))


def event_from_ros(msg: Any) -> EventSample:
    """Read an ``~/events`` record (the fields by their labels, in any order)."""
    offsets, start = {}, int(msg.layout.data_offset)
    for dim in msg.layout.dim:
        offsets[str(dim.label)] = (start, int(dim.size))
        start += int(dim.size)
    data = np.asarray(msg.data, dtype=float)
    missing = [name for name, size in EVENT_FIELDS if offsets.get(name, (0, -1))[1] != size]
    if missing or start > len(data):
        raise ValueError(f'not an event record: fields {missing} missing or mis-sized')
    return EventSample.from_values(np.concatenate(
        [data[offsets[name][0]:offsets[name][0] + size] for name, size in EVENT_FIELDS]))


# ---------------------------------------------------------------- misc


def string_to_ros(text: str, types: MessageTypes) -> Any:
    """Build std_msgs/msg/String (e.g. robot_description)."""
    return types.create('std_msgs/msg/String', data=str(text))


def string_from_ros(msg: Any) -> str:
    """Return the text of a std_msgs/msg/String."""
    return str(msg.data)


def clock_to_ros(stamp_ns: int, types: MessageTypes) -> Any:
    """Build rosgraph_msgs/msg/Clock."""
    return types.create('rosgraph_msgs/msg/Clock', clock=time_to_ros(stamp_ns, types))


def clock_from_ros(msg: Any) -> int:
    """Return the nanoseconds of a rosgraph_msgs/msg/Clock."""
    return time_from_ros(msg.clock)
