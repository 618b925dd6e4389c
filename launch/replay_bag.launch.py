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
Replay a bag into the reduced_dynamics node on simulated time.

Runs ``ros2 bag play BAG --rate RATE --clock`` after ``delay`` seconds (so the
node is subscribed first) and the node of reduced_dynamics.launch.py with
``use_sim_time:=true``; everything shuts down when the bag ends::

    ros2 launch reduced_dynamics replay_bag.launch.py bag:=/path/to/bag
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.actions import EmitEvent
from launch.actions import ExecuteProcess
from launch.actions import IncludeLaunchDescription
from launch.actions import RegisterEventHandler
from launch.actions import TimerAction
from launch.event_handlers import OnProcessExit
from launch.events import Shutdown
from launch.launch_description_sources import PythonLaunchDescriptionSource
from launch.substitutions import LaunchConfiguration

# Installed side by side in share/reduced_dynamics/launch (setup.py data_files).
NODE_LAUNCH = os.path.join(os.path.dirname(os.path.abspath(__file__)),
                           'reduced_dynamics.launch.py')
# Arguments passed through to reduced_dynamics.launch.py unchanged (its defaults apply).
PASSED_THROUGH = ('params_file', 'urdf', 'namespace')


def generate_launch_description():
    """Return the launch description: arguments, the node, then the bag player."""
    play = ExecuteProcess(
        cmd=['ros2', 'bag', 'play', LaunchConfiguration('bag'),
             '--rate', LaunchConfiguration('rate'), '--clock'],
        output='screen')
    node_arguments = {name: LaunchConfiguration(name) for name in PASSED_THROUGH}
    node_arguments['use_sim_time'] = 'true'
    default_params = os.path.join(get_package_share_directory('reduced_dynamics'), 'config',
                                  'params.yaml')
    return LaunchDescription([
        DeclareLaunchArgument('bag', description='bag directory or file to play'),
        DeclareLaunchArgument('rate', default_value='1.0', description='playback rate'),
        DeclareLaunchArgument('delay', default_value='2.0',
                              description='seconds between starting the node and the bag'),
        DeclareLaunchArgument('params_file', default_value=default_params,
                              description='ROS 2 parameter file of the node'),
        DeclareLaunchArgument('urdf', default_value='', description='robot URDF file'),
        DeclareLaunchArgument('namespace', default_value='', description='node namespace'),
        IncludeLaunchDescription(PythonLaunchDescriptionSource(NODE_LAUNCH),
                                 launch_arguments=node_arguments.items()),
        TimerAction(period=LaunchConfiguration('delay'), actions=[play]),
        RegisterEventHandler(OnProcessExit(
            target_action=play,
            on_exit=[EmitEvent(event=Shutdown(reason='bag playback finished'))])),
    ])
