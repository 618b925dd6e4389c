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
Parameters of the node and the replay tool: one table, one YAML file format.

The YAML is the ROS 2 parameter file the node reads
(``reduced_dynamics: ros__parameters: {...}``); the replay tool reads the same.
"""

from __future__ import annotations

from typing import Any, Mapping

import yaml

from reduced_dynamics.estimator.config import check_parameter, ParameterSpec, PARAMETERS

#: Settings of the node shell (robot, inputs) beside the estimator's own.
NODE_PARAMETERS: dict[str, ParameterSpec] = {
    'robot_description': ParameterSpec('', None, None, (),
                                       'URDF XML; if empty, urdf_path; if both are empty, '
                                       'the robot_description topic (the paper robot stands '
                                       'in until it arrives)'),
    'urdf_path': ParameterSpec('', None, None, (), 'URDF file used when robot_description '
                                                   'is empty'),
    'base_joint': ParameterSpec('auto', None, None, ('auto', 'floating', 'planar'),
                                'free base: auto (the URDF\'s own world joint, else '
                                'floating), floating (SE(3)) or planar (SE(2), air bearing)'),
    'gravity': ParameterSpec([0.0, 0.0, 0.0], None, None, (),
                             'gravity [m/s^2], world frame; nonzero only for a planar base '
                             '(along z)'),
    'base_input': ParameterSpec('odom', None, None, ('odom', 'pose', 'pose_covariance'),
                                'base state source: nav_msgs/Odometry (odom), '
                                'geometry_msgs/PoseStamped (pose only: the filter '
                                'estimates the twist) or geometry_msgs/'
                                'PoseWithCovarianceStamped (pose_covariance: a pose with '
                                'its covariance, on base_pose_topic)'),
    'joint_states_topic': ParameterSpec('joint_states', None, None, (),
                                        'sensor_msgs/JointState input'),
    'odom_topic': ParameterSpec('odom', None, None, (), 'nav_msgs/Odometry input'),
    'base_pose_topic': ParameterSpec('base_pose', None, None, (),
                                     'geometry_msgs/PoseStamped (or, base_input '
                                     'pose_covariance, PoseWithCovarianceStamped) input'),
    'trajectory_topic': ParameterSpec('joint_trajectory', None, None, (),
                                      'trajectory_msgs/JointTrajectory input: the planned '
                                      'arm motion (e.g. a joint_trajectory_controller\'s '
                                      'command topic) that prediction_mode planned follows'),
    'commanded_wrench_topic': ParameterSpec(
        '', None, None, (),
        'geometry_msgs/WrenchStamped input of the commanded body wrench (thrusters, '
        'actuators; base frame, held until the next message); empty: off. With it the '
        'filter estimates the per-axis gain and bias of the delivered wrench and the '
        'disturbance beyond the command (~/drift/disturbance)'),
    'payload_link': ParameterSpec('', None, None, (),
                                  'URDF link holding a payload: payload_file\'s (if that '
                                  'names none) and ~/identify_payload\'s; empty: none'),
    'payload_file': ParameterSpec('', None, None, (),
                                  'payload YAML (reduced-dynamics identify -o): the robot '
                                  'model holds it from the start; empty: none'),
    'payload_window': ParameterSpec(20.0, 1.0, 3600.0, (),
                                    'seconds of input ~/identify_payload identifies over'),
    'cyclic_joints': ParameterSpec('', None, None, (),
                                   'second-stage reduction (Theorem 57): empty for off, '
                                   '"auto" for every cyclic joint found (reaction wheels, '
                                   'rotors), or comma-separated joint names; their momenta '
                                   'go to ~/cyclic_momenta and leave ~/shape_state'),
}

#: Parameters a running node may change (the others need a restart).
RUNTIME_PARAMETERS = frozenset(PARAMETERS)

ALL_PARAMETERS: dict[str, ParameterSpec] = {**NODE_PARAMETERS, **PARAMETERS}


def check_any_parameter(name: str, value: Any) -> None:
    """Raise ValueError unless ``value`` is acceptable for parameter ``name``."""
    if name in PARAMETERS:
        check_parameter(name, value)
        return
    spec = NODE_PARAMETERS.get(name)
    if spec is None:
        raise ValueError(f'unknown parameter {name!r}')
    if name == 'gravity':
        if isinstance(value, (str, bytes)) or not hasattr(value, '__len__') or \
                len(value) != 3 or not all(
                isinstance(v, (int, float)) and not isinstance(v, bool) for v in value):
            raise ValueError('gravity must be a list of three numbers')
        return
    if isinstance(spec.default, float):
        if isinstance(value, bool) or not isinstance(value, (int, float)) or \
                not spec.low <= float(value) <= spec.high:
            raise ValueError(f'{name} must be a number in [{spec.low}, {spec.high}], '
                             f'got {value!r}')
        return
    if not isinstance(value, str):
        raise ValueError(f'{name} must be a string, got {value!r}')
    if spec.choices and value not in spec.choices:
        raise ValueError(f'{name} must be one of {spec.choices}, got {value!r}')


def defaults() -> dict[str, Any]:
    """Return every parameter at its default."""
    return {name: spec.default for name, spec in ALL_PARAMETERS.items()}


def load_params_file(path: str, node_name: str = 'reduced_dynamics') -> dict[str, Any]:
    """Read a ROS 2 parameter YAML; return defaults updated by the node's section."""
    try:
        with open(path, encoding='utf-8') as stream:
            document = yaml.safe_load(stream) or {}
    except OSError as error:
        raise ValueError(f'cannot read parameters file {path}: {error}') from error
    except yaml.YAMLError as error:
        raise ValueError(f'parameters file {path} is not valid YAML: {error}') from error
    values = defaults()
    values.update(node_section(document, node_name, path))
    return values


def node_section(document: Any, node_name: str, path: str = '<yaml>') -> dict[str, Any]:
    """Return the ros__parameters of ``node_name`` (or of ``/**``) in a parameter file."""
    if not isinstance(document, Mapping):
        raise ValueError(f'{path}: expected a mapping at the top level')
    merged: dict[str, Any] = {}
    for key in ('/**', node_name, '/' + node_name, '/**/' + node_name):
        section = document.get(key)
        if isinstance(section, Mapping) and isinstance(section.get('ros__parameters'),
                                                       Mapping):
            merged.update(section['ros__parameters'])
    unknown = sorted(set(merged) - set(ALL_PARAMETERS) - {'use_sim_time'})
    if unknown:
        raise ValueError(f'{path}: unknown parameters {unknown}')
    for name, value in merged.items():
        if name != 'use_sim_time':
            check_any_parameter(name, value)
    return merged
