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

Starts the node of reduced_dynamics.launch.py with ``use_sim_time:=true`` and a bag
player publishing ``/clock``; everything shuts down when the bag ends::

    ros2 launch reduced_dynamics replay_bag.launch.py bag:=/path/to/bag

The player (argument ``player``) is ``ros2 bag play`` where ros2cli's bag verb is
installed, else ``reduced-dynamics play`` (rosbag2 has no PyPI wheels; docs/play.md).
``reduced-dynamics play`` starts when the node has subscribed to the ``wait_for``
topics, however long the node takes to start; ``ros2 bag play`` has no such option
and starts ``delay`` seconds after the launch.
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
from launch.conditions import IfCondition
from launch.event_handlers import OnProcessExit
from launch.events import Shutdown
from launch.launch_description_sources import PythonLaunchDescriptionSource
from launch.substitutions import LaunchConfiguration
from launch.substitutions import PythonExpression

# Installed side by side in share/reduced_dynamics/launch (setup.py data_files).
NODE_LAUNCH = os.path.join(os.path.dirname(os.path.abspath(__file__)),
                           'reduced_dynamics.launch.py')
# Arguments passed through to reduced_dynamics.launch.py unchanged (its defaults apply).
PASSED_THROUGH = ('params_file', 'urdf', 'namespace')
PLAYERS = ('ros2', 'reduced_dynamics')
# The node's input topics with its default parameters (base_input odom or pose); the
# player waits for those of them the bag has.
WAIT_FOR = '/joint_states /odom /base_pose'


def default_player() -> str:
    """Return 'ros2' where ``ros2 bag`` is installed, else 'reduced_dynamics'."""
    import importlib.util
    import shutil
    if shutil.which('ros2') and importlib.util.find_spec('ros2bag') is not None:
        return 'ros2'
    return 'reduced_dynamics'


def _player_is(name: str) -> IfCondition:
    return IfCondition(PythonExpression(["'", LaunchConfiguration('player'), f"' == '{name}'"]))


def generate_launch_description():
    """Return the launch description: arguments, the node, then the bag player."""
    ros2_play = ExecuteProcess(
        cmd=['ros2', 'bag', 'play', LaunchConfiguration('bag'),
             '--rate', LaunchConfiguration('rate'), '--clock'],
        output='screen', condition=_player_is('ros2'))
    # Started with the node: it waits for the node's subscriptions itself.
    own_play = ExecuteProcess(
        cmd=['reduced-dynamics', 'play', LaunchConfiguration('bag'),
             '--rate', LaunchConfiguration('rate'), '--clock',
             '--wait-for-subscribers', LaunchConfiguration('wait_for')],
        output='screen', condition=_player_is('reduced_dynamics'))
    node_arguments = {name: LaunchConfiguration(name) for name in PASSED_THROUGH}
    node_arguments['use_sim_time'] = 'true'
    default_params = os.path.join(get_package_share_directory('reduced_dynamics'), 'config',
                                  'params.yaml')
    return LaunchDescription([
        DeclareLaunchArgument('bag', description='bag directory or file to play'),
        DeclareLaunchArgument('rate', default_value='1.0', description='playback rate'),
        DeclareLaunchArgument('player', default_value=default_player(), choices=PLAYERS,
                              description="'ros2': ros2 bag play; 'reduced_dynamics': "
                                          'reduced-dynamics play (no ros2cli needed)'),
        DeclareLaunchArgument('wait_for', default_value=WAIT_FOR,
                              description='reduced-dynamics play starts when these topics '
                                          '(those in the bag) have a subscriber'),
        DeclareLaunchArgument('delay', default_value='2.0',
                              description='seconds between starting the node and ros2 bag '
                                          'play'),
        DeclareLaunchArgument('params_file', default_value=default_params,
                              description='ROS 2 parameter file of the node'),
        DeclareLaunchArgument('urdf', default_value='', description='robot URDF file'),
        DeclareLaunchArgument('namespace', default_value='', description='node namespace'),
        IncludeLaunchDescription(PythonLaunchDescriptionSource(NODE_LAUNCH),
                                 launch_arguments=node_arguments.items()),
        TimerAction(period=LaunchConfiguration('delay'), actions=[ros2_play]),
        own_play,
        *(RegisterEventHandler(OnProcessExit(
            target_action=play,
            on_exit=[EmitEvent(event=Shutdown(reason='bag playback finished'))]))
          for play in (ros2_play, own_play)),
    ])
