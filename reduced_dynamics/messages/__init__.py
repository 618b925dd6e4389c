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

"""ROS-free samples and pure ``*_to_ros`` / ``*_from_ros`` message conversions."""

from reduced_dynamics.messages.convert import (
    base_state_to_odometry,
    base_state_to_pose_stamped,
    base_state_to_pose_with_covariance_stamped,
    clock_from_ros,
    command_from_ros,
    clock_to_ros,
    diagnostics_from_ros,
    diagnostics_to_ros,
    header_from_ros,
    header_to_ros,
    joint_state_from_ros,
    joint_state_to_ros,
    joint_trajectory_from_ros,
    joint_trajectory_to_ros,
    odometry_from_ros,
    pose_path_from_ros,
    pose_path_to_ros,
    pose_stamped_from_ros,
    pose_with_covariance_stamped_from_ros,
    shape_prediction_from_ros,
    shape_prediction_to_ros,
    string_from_ros,
    string_to_ros,
    twist_from_ros,
    twist_to_ros,
    wrench_from_ros,
    wrench_to_ros,
)
from reduced_dynamics.messages.samples import (
    BaseStateSample,
    CommandSample,
    DIAG_ERROR,
    DIAG_OK,
    DIAG_STALE,
    DIAG_WARN,
    Diagnostics,
    DiagnosticStatusSample,
    JointStateSample,
    JointTrajectorySample,
    PosePath,
    ShapePrediction,
    TwistSample,
    WrenchSample,
)
from reduced_dynamics.messages.stamps import (
    duration_from_ros,
    duration_to_ros,
    NS_PER_S,
    time_from_ros,
    time_to_ros,
)
from reduced_dynamics.messages.types import (
    byte_to_int,
    MessageTypes,
    RclpyTypes,
    RosbagsTypes,
)

__all__ = [
    'BaseStateSample',
    'CommandSample',
    'DIAG_ERROR',
    'DIAG_OK',
    'DIAG_STALE',
    'DIAG_WARN',
    'DiagnosticStatusSample',
    'Diagnostics',
    'JointStateSample',
    'JointTrajectorySample',
    'MessageTypes',
    'NS_PER_S',
    'PosePath',
    'RclpyTypes',
    'RosbagsTypes',
    'ShapePrediction',
    'TwistSample',
    'WrenchSample',
    'base_state_to_odometry',
    'base_state_to_pose_stamped',
    'base_state_to_pose_with_covariance_stamped',
    'byte_to_int',
    'clock_from_ros',
    'clock_to_ros',
    'command_from_ros',
    'diagnostics_from_ros',
    'diagnostics_to_ros',
    'duration_from_ros',
    'duration_to_ros',
    'header_from_ros',
    'header_to_ros',
    'joint_state_from_ros',
    'joint_state_to_ros',
    'joint_trajectory_from_ros',
    'joint_trajectory_to_ros',
    'odometry_from_ros',
    'pose_path_from_ros',
    'pose_path_to_ros',
    'pose_stamped_from_ros',
    'pose_with_covariance_stamped_from_ros',
    'shape_prediction_from_ros',
    'shape_prediction_to_ros',
    'string_from_ros',
    'string_to_ros',
    'time_from_ros',
    'time_to_ros',
    'twist_from_ros',
    'twist_to_ros',
    'wrench_from_ros',
    'wrench_to_ros',
]
