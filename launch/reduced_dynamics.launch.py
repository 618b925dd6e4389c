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
Launch the reduced_dynamics node with a parameter file.

Arguments: ``params_file`` (default: the installed config/params.yaml),
``urdf`` (a URDF file overriding the file's ``urdf_path``; empty keeps it),
``namespace`` and ``use_sim_time`` (true when replaying a bag with --clock)::

    ros2 launch reduced_dynamics reduced_dynamics.launch.py urdf:=/path/robot.urdf
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.actions import OpaqueFunction
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

PACKAGE = 'reduced_dynamics'
_TRUE = ('true', '1', 'yes', 'on')
_FALSE = ('false', '0', 'no', 'off')


def _as_bool(name: str, text: str) -> bool:
    """Return the boolean a launch argument spells (a typo must not mean false)."""
    if text.strip().lower() in _TRUE:
        return True
    if text.strip().lower() in _FALSE:
        return False
    raise ValueError(f'launch argument {name} must be true or false, got {text!r}')


def _node(context, *args, **kwargs):
    """Return the node action, with arguments resolved (an empty urdf overrides nothing)."""
    urdf = LaunchConfiguration('urdf').perform(context)
    use_sim_time = _as_bool('use_sim_time', LaunchConfiguration('use_sim_time').perform(context))
    overrides = {'use_sim_time': use_sim_time}
    if urdf:
        # The node resolves relative paths against its own working directory; make the
        # argument mean what the user typed, relative to where `ros2 launch` ran.
        overrides['urdf_path'] = os.path.abspath(os.path.expanduser(urdf))
    return [Node(
        package=PACKAGE,
        executable='reduced_dynamics_node',
        name='reduced_dynamics',
        namespace=LaunchConfiguration('namespace'),
        parameters=[LaunchConfiguration('params_file'), overrides],
        output='screen',
        emulate_tty=True,
    )]


def generate_launch_description():
    """Return the launch description: arguments, then the node."""
    default_params = os.path.join(get_package_share_directory(PACKAGE), 'config', 'params.yaml')
    return LaunchDescription([
        DeclareLaunchArgument('params_file', default_value=default_params,
                              description='ROS 2 parameter file of the node'),
        DeclareLaunchArgument('urdf', default_value='',
                              description="robot URDF file ('' = the parameter file's "
                                          'urdf_path / robot_description)'),
        DeclareLaunchArgument('namespace', default_value='',
                              description='namespace of the node and its input topics'),
        DeclareLaunchArgument('use_sim_time', default_value='false',
                              description='follow /clock (true when replaying a bag)'),
        OpaqueFunction(function=_node),
    ])
