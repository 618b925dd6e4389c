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

"""Options and outputs that fit the robot (issue 24 item 6): tune's budget, integer doubles."""

from pathlib import Path

import pytest

from reduced_dynamics.cli import main
from reduced_dynamics.resources import config_path

DATA = Path(__file__).parent / 'data'
PD_BAG = DATA / 'freeflyer2' / 'rosbag2_2024_03_14-14_17_23'


@pytest.mark.parametrize('budget', [1, 4, 7])
def test_tune_makes_exactly_max_evaluations_filter_runs(tmp_path, capsys, budget):
    """1: part of the process-noise scan; 4: the scan alone; 7: the scan and Nelder-Mead."""
    out = tmp_path / 'tuned.yaml'
    assert main(['tune', str(PD_BAG), '-o', str(out), '--urdf',
                 str(config_path('robots/freeflyer.urdf')), '--end', '4',
                 '--base-pose-topic', '/vrpn_mocap/robot/pose',
                 '--max-evaluations', str(budget)]) == 0
    progress = [line for line in capsys.readouterr().err.splitlines()
                if line.startswith('tune: evaluation ')]
    assert len(progress) == budget
    assert f', {budget} evaluations' in out.read_text().splitlines()[0]


@pytest.fixture
def ros():
    try:
        from ros_harness import real_ros
    except ImportError:  # test/ imported as a package
        from test.ros_harness import real_ros
    with real_ros() as backend:
        yield backend


def _gravity_file(tmp_path: Path) -> Path:
    path = tmp_path / 'gravity.yaml'
    path.write_text('/**:\n  ros__parameters:\n    base_joint: planar\n'
                    '    gravity: [0, 0, -10]\n')
    return path


def test_integer_gravity_is_taken_as_doubles_by_the_node(ros, tmp_path):
    """README: integers are accepted for doubles; the same for a list of doubles."""
    from rclpy.parameter import Parameter
    from reduced_dynamics.node import ReducedDynamicsNode
    given = ReducedDynamicsNode(parameter_overrides=[
        Parameter('gravity', value=[0, 0, -10]), Parameter('base_joint', value='planar')])
    from_file = ReducedDynamicsNode(
        cli_args=['--ros-args', '--params-file', str(_gravity_file(tmp_path))])
    try:
        for node in (given, from_file):
            parameter = node.get_parameter('gravity')
            assert parameter.type_ == Parameter.Type.DOUBLE_ARRAY
            assert list(parameter.value) == [0.0, 0.0, -10.0]
            assert node.model_error is None
            assert node.estimator.robot.group.name == 'SE(2)'
    finally:
        given.destroy_node()
        from_file.destroy_node()


def test_integer_gravity_in_a_replay_params_file(tmp_path):
    from reduced_dynamics.params import load_params_file
    from reduced_dynamics.replay import load_robot_from_params
    params = load_params_file(str(_gravity_file(tmp_path)))
    robot = load_robot_from_params(params)
    assert robot.group.name == 'SE(2)'
    assert list(robot.gravity) == [0.0, 0.0, -10.0]


@pytest.mark.parametrize('cyclic, command', [(False, False), (True, False), (False, True),
                                             (True, True)])
def test_optional_outputs_are_advertised_only_when_their_feature_is_on(ros, cyclic, command):
    from rclpy.parameter import Parameter
    from reduced_dynamics.node import ReducedDynamicsNode
    overrides = {'urdf_path': str(config_path('robots/paper_robot_wheels.urdf'))}
    if cyclic:
        overrides['cyclic_joints'] = 'auto'
    if command:
        overrides['commanded_wrench_topic'] = 'wrench_command'
    node = ReducedDynamicsNode(
        parameter_overrides=[Parameter(k, value=v) for k, v in overrides.items()])
    try:
        advertised = {pub.topic_name for pub in node.publishers}
        assert ('/reduced_dynamics/cyclic_momenta' in advertised) == cyclic
        assert ('/reduced_dynamics/drift/disturbance' in advertised) == command
        assert '/reduced_dynamics/momentum' in advertised
    finally:
        node.destroy_node()
