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
Tests of launch/*.launch.py without a stand-in for ROS 2 launch.

``launch``/``launch_ros`` have no PyPI wheels, so they are importable only on a ROS 2
install (README way A). Everywhere the files are checked from their source (syntax tree:
the arguments they declare and their defaults, the node they start) and their own helper
code is run as written; ``test_with_real_launch`` loads them with the real launch packages
and skips, saying why, where those are missing. The colcon install of the files is checked
in test_colcon_install.py.
"""

import ast
import importlib.util
import os
from pathlib import Path

import pytest
import yaml

from reduced_dynamics.params import node_section
from reduced_dynamics.topics import NODE_NAME

REPO_ROOT = Path(__file__).resolve().parent.parent
LAUNCH_DIR = REPO_ROOT / 'launch'
NODE_LAUNCH = LAUNCH_DIR / 'reduced_dynamics.launch.py'
REPLAY_LAUNCH = LAUNCH_DIR / 'replay_bag.launch.py'
_REQUIRED = object()  # a DeclareLaunchArgument without default_value


def _tree(path: Path) -> ast.Module:
    return ast.parse(path.read_text(), str(path))


def _calls(tree: ast.AST, name: str) -> list:
    return [n for n in ast.walk(tree) if isinstance(n, ast.Call)
            and isinstance(n.func, ast.Name) and n.func.id == name]


def _declared_arguments(path: Path) -> dict:
    """Return {argument name: default (a literal, an ast node, or _REQUIRED)}."""
    arguments = {}
    for call in _calls(_tree(path), 'DeclareLaunchArgument'):
        name = ast.literal_eval(call.args[0])
        default = next((k.value for k in call.keywords if k.arg == 'default_value'),
                       None)
        if default is None:
            arguments[name] = _REQUIRED
        elif isinstance(default, ast.Constant):
            arguments[name] = default.value
        else:
            arguments[name] = default
    return arguments


def _keywords(call: ast.Call) -> dict:
    return {k.arg: k.value for k in call.keywords}


def _definitions(path: Path, names: set) -> dict:
    """Execute only the named top-level functions/assignments of a launch file."""
    tree = _tree(path)
    keep = [n for n in tree.body
            if (isinstance(n, ast.FunctionDef) and n.name in names)
            or (isinstance(n, ast.Assign)
                and {t.id for t in n.targets if isinstance(t, ast.Name)} & names)]
    namespace: dict = {}
    exec(compile(ast.Module(body=keep, type_ignores=[]), str(path), 'exec'), namespace)
    return namespace


@pytest.mark.parametrize('path', [NODE_LAUNCH, REPLAY_LAUNCH])
def test_launch_files_are_installed_python_with_generate_function(path):
    functions = {n.name for n in _tree(path).body if isinstance(n, ast.FunctionDef)}
    assert 'generate_launch_description' in functions
    assert path.name.endswith('.launch.py')  # setup.py installs launch/*.launch.py
    assert "'share/' + package_name + '/launch'" in (REPO_ROOT / 'setup.py').read_text()


def test_node_launch_arguments_and_node():
    arguments = _declared_arguments(NODE_LAUNCH)
    assert set(arguments) == {'params_file', 'urdf', 'namespace', 'use_sim_time'}
    assert (arguments['urdf'], arguments['namespace'], arguments['use_sim_time']) == \
        ('', '', 'false')
    # params_file defaults to the installed share/reduced_dynamics/config/params.yaml
    assert ast.unparse(arguments['params_file']) == 'default_params'
    assert "get_package_share_directory(PACKAGE), 'config', 'params.yaml'" in \
        NODE_LAUNCH.read_text()
    node, = _calls(_tree(NODE_LAUNCH), 'Node')
    keywords = _keywords(node)
    assert ast.unparse(keywords['package']) == 'PACKAGE'
    assert _definitions(NODE_LAUNCH, {'PACKAGE'})['PACKAGE'] == 'reduced_dynamics'
    assert ast.literal_eval(keywords['name']) == NODE_NAME
    executable = ast.literal_eval(keywords['executable'])
    assert f"'{executable} = reduced_dynamics.node_main:main'" in \
        (REPO_ROOT / 'setup.py').read_text()
    # parameters: the file, then the overrides (use_sim_time, urdf_path from urdf)
    assert ast.unparse(keywords['parameters']) == \
        "[LaunchConfiguration('params_file'), overrides]"


def test_node_launch_boolean_parsing_as_written():
    as_bool = _definitions(NODE_LAUNCH, {'_as_bool', '_TRUE', '_FALSE'})['_as_bool']
    assert [as_bool('x', t) for t in ('true', 'True', ' 1', 'on', 'false', 'No', '0')] == \
        [True, True, True, True, False, False, False]
    with pytest.raises(ValueError, match='use_sim_time must be true or false'):
        as_bool('use_sim_time', 'ture')


def test_shipped_params_file_is_valid_for_the_node():
    params = yaml.safe_load((REPO_ROOT / 'config' / 'params.yaml').read_text())
    assert '/**/' + NODE_NAME in params  # any namespace
    node_section(params, NODE_NAME)


def test_replay_launch_arguments_and_actions():
    arguments = _declared_arguments(REPLAY_LAUNCH)
    assert arguments['bag'] is _REQUIRED
    assert (arguments['rate'], arguments['delay'], arguments['urdf'],
            arguments['namespace']) == ('1.0', '2.0', '', '')
    passed = _definitions(REPLAY_LAUNCH, {'PASSED_THROUGH'})['PASSED_THROUGH']
    assert set(passed) <= set(_declared_arguments(NODE_LAUNCH))
    ros2_play, own_play = _calls(_tree(REPLAY_LAUNCH), 'ExecuteProcess')
    assert ast.unparse(_keywords(ros2_play)['cmd']) == (
        "['ros2', 'bag', 'play', LaunchConfiguration('bag'), '--rate', "
        "LaunchConfiguration('rate'), '--clock']")
    assert ast.unparse(_keywords(ros2_play)['condition']) == "_player_is('ros2')"
    assert ast.unparse(_keywords(own_play)['condition']) == "_player_is('reduced_dynamics')"
    text = REPLAY_LAUNCH.read_text()
    assert "node_arguments['use_sim_time'] = 'true'" in text  # the bag's /clock drives it
    assert "'reduced_dynamics.launch.py'" in text and NODE_LAUNCH.is_file()
    # Only ros2 bag play waits the fixed delay; reduced-dynamics play waits for the node.
    timer, = _calls(_tree(REPLAY_LAUNCH), 'TimerAction')
    assert ast.unparse(_keywords(timer)['actions']) == '[ros2_play]'
    on_exit, = _calls(_tree(REPLAY_LAUNCH), 'OnProcessExit')
    assert ast.unparse(_keywords(on_exit)['target_action']) == 'play'
    assert 'for play in (ros2_play, own_play)' in text
    assert _calls(_tree(REPLAY_LAUNCH), 'Shutdown')  # the bag's end ends the launch


def _command_with_defaults(call: ast.Call) -> list:
    """Return an ExecuteProcess cmd with each LaunchConfiguration at its default."""
    arguments = _declared_arguments(REPLAY_LAUNCH)
    arguments['bag'] = str(REPO_ROOT / 'test' / 'data' / 'paper_constant')
    out = []
    for element in _keywords(call)['cmd'].elts:
        if isinstance(element, ast.Constant):
            out.append(element.value)
        else:
            name = ast.literal_eval(element.args[0])
            default = arguments[name]
            if isinstance(default, ast.Name):  # a module constant (WAIT_FOR)
                default = _definitions(REPLAY_LAUNCH, {default.id})[default.id]
            out.append(default)
    return out


def test_replay_launch_runs_reduced_dynamics_play_with_options_it_takes():
    from reduced_dynamics.cli import build_parser
    from reduced_dynamics.player_node import options_from_args
    _, own_play = _calls(_tree(REPLAY_LAUNCH), 'ExecuteProcess')
    command = _command_with_defaults(own_play)
    assert command[:2] == ['reduced-dynamics', 'play']
    options = options_from_args(build_parser('play').parse_args(command[1:]))
    assert options.clock_hz > 0 and options.rate == 1.0  # /clock for use_sim_time
    # The node's default inputs (odom or pose input); the player skips those not in the bag.
    assert options.wait_for_subscribers == ('/joint_states', '/odom', '/base_pose')


@pytest.mark.parametrize('ros2, ros2bag, expected', [
    ('/opt/ros/jazzy/bin/ros2', True, 'ros2'), (None, False, 'reduced_dynamics'),
    ('/usr/bin/ros2', False, 'reduced_dynamics')])
def test_replay_launch_plays_with_ros2_bag_only_where_installed(
        monkeypatch, ros2, ros2bag, expected):
    import importlib.util as util
    import shutil
    default_player = _definitions(REPLAY_LAUNCH, {'default_player'})['default_player']
    monkeypatch.setattr(shutil, 'which', lambda name: ros2 if name == 'ros2' else None)
    real_find_spec = util.find_spec
    monkeypatch.setattr(util, 'find_spec', lambda name, *a: (
        (object() if ros2bag else None) if name == 'ros2bag' else real_find_spec(name, *a)))
    assert default_player() == expected
    assert expected in _definitions(REPLAY_LAUNCH, {'PLAYERS'})['PLAYERS']


def _import_real_launch():
    # The repository's own launch/ folder would import as a namespace package `launch`
    # from the repository root; the real package has launch.actions.
    from ament_index_python.packages import get_package_share_directory
    from launch import LaunchDescription
    import launch.actions  # noqa: F401
    import launch_ros.actions  # noqa: F401
    return get_package_share_directory, LaunchDescription


def load_launch_file(path: Path):
    spec = importlib.util.spec_from_file_location(
        'launch_file_' + path.name.replace('.', '_'), path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_with_real_launch():
    try:
        get_package_share_directory, real_launch_description = _import_real_launch()
    except ImportError:
        pytest.skip('ROS 2 launch/launch_ros are not importable: they have no PyPI wheels '
                    '(a ROS 2 Jazzy install provides them, README way A)')
    try:
        get_package_share_directory('reduced_dynamics')
    except Exception:  # PackageNotFoundError: the package is not built/installed
        pytest.skip('reduced_dynamics is not installed in the ament index (colcon build, '
                    'source install/setup.bash)')
    for path, required in ((NODE_LAUNCH, set()), (REPLAY_LAUNCH, {'bag'})):
        description = load_launch_file(path).generate_launch_description()
        assert isinstance(description, real_launch_description)
        arguments = {a.name: a for a in description.get_launch_arguments()}
        assert {'params_file', 'urdf', 'namespace'} <= set(arguments)
        assert {n for n, a in arguments.items() if a.default_value is None} == required
    assert os.path.isfile(os.path.join(get_package_share_directory('reduced_dynamics'),
                                       'launch', NODE_LAUNCH.name))
