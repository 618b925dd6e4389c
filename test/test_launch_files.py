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
Tests of launch/*.launch.py.

ROS 2 ``launch``/``launch_ros`` are not installed here, so the files are loaded
against a minimal TEST DOUBLE of those modules (and of ament_index_python),
installed in sys.modules only inside the ``fake_launch`` fixture. The double
records constructor arguments and evaluates LaunchConfiguration, OpaqueFunction
and IncludeLaunchDescription the way launch does (included files see the
including file's configurations plus their launch_arguments). It checks what the
files ask launch to do, not that launch does it: that needs ROS 2
(``test_with_real_launch`` runs when launch_ros and the installed package are
available).
"""

import ast
import importlib.util
import os
from pathlib import Path
import sys
import types

import pytest
import yaml

from reduced_dynamics.params import node_section
from reduced_dynamics.topics import NODE_NAME

REPO_ROOT = Path(__file__).resolve().parent.parent
LAUNCH_DIR = REPO_ROOT / 'launch'
NODE_LAUNCH = LAUNCH_DIR / 'reduced_dynamics.launch.py'
REPLAY_LAUNCH = LAUNCH_DIR / 'replay_bag.launch.py'


# ------------------------------------------------------------- TEST DOUBLE of launch
class _Recorded:
    """TEST DOUBLE base: keeps positional and keyword constructor arguments."""

    def __init__(self, *args, **kwargs):
        self.args = args
        self.kwargs = kwargs


class LaunchDescription:
    """TEST DOUBLE of launch.LaunchDescription."""

    def __init__(self, initial_entities=None):
        self.entities = list(initial_entities or [])


class DeclareLaunchArgument(_Recorded):
    """TEST DOUBLE of launch.actions.DeclareLaunchArgument."""

    name = property(lambda self: self.args[0])
    default_value = property(lambda self: self.kwargs.get('default_value'))


class LaunchConfiguration(_Recorded):
    """TEST DOUBLE of launch.substitutions.LaunchConfiguration."""

    def perform(self, context):
        return context.launch_configurations[self.args[0]]


class OpaqueFunction(_Recorded):
    """TEST DOUBLE of launch.actions.OpaqueFunction."""


class ExecuteProcess(_Recorded):
    """TEST DOUBLE of launch.actions.ExecuteProcess."""


class IncludeLaunchDescription(_Recorded):
    """TEST DOUBLE of launch.actions.IncludeLaunchDescription."""


class PythonLaunchDescriptionSource(_Recorded):
    """TEST DOUBLE of launch.launch_description_sources.PythonLaunchDescriptionSource."""


class TimerAction(_Recorded):
    """TEST DOUBLE of launch.actions.TimerAction."""


class RegisterEventHandler(_Recorded):
    """TEST DOUBLE of launch.actions.RegisterEventHandler."""


class OnProcessExit(_Recorded):
    """TEST DOUBLE of launch.event_handlers.OnProcessExit."""


class EmitEvent(_Recorded):
    """TEST DOUBLE of launch.actions.EmitEvent."""


class Shutdown(_Recorded):
    """TEST DOUBLE of launch.events.Shutdown."""


class RosNode(_Recorded):
    """TEST DOUBLE of launch_ros.actions.Node."""


def _fake_modules():
    def module(name, **attrs):
        fake = types.ModuleType(name, 'TEST DOUBLE - not ROS 2 launch')
        fake.__dict__.update(attrs)
        return fake

    def get_package_share_directory(package):
        assert package == 'reduced_dynamics'
        return str(REPO_ROOT)  # the source tree has the share layout: config/, launch/
    return {
        'launch': module('launch', LaunchDescription=LaunchDescription),
        'launch.actions': module(
            'launch.actions', DeclareLaunchArgument=DeclareLaunchArgument,
            OpaqueFunction=OpaqueFunction, ExecuteProcess=ExecuteProcess,
            IncludeLaunchDescription=IncludeLaunchDescription, TimerAction=TimerAction,
            RegisterEventHandler=RegisterEventHandler, EmitEvent=EmitEvent),
        'launch.substitutions': module('launch.substitutions',
                                       LaunchConfiguration=LaunchConfiguration),
        'launch.launch_description_sources': module(
            'launch.launch_description_sources',
            PythonLaunchDescriptionSource=PythonLaunchDescriptionSource),
        'launch.event_handlers': module('launch.event_handlers', OnProcessExit=OnProcessExit),
        'launch.events': module('launch.events', Shutdown=Shutdown),
        'launch_ros': module('launch_ros'),
        'launch_ros.actions': module('launch_ros.actions', Node=RosNode),
        'ament_index_python': module('ament_index_python'),
        'ament_index_python.packages': module(
            'ament_index_python.packages',
            get_package_share_directory=get_package_share_directory),
    }


@pytest.fixture
def fake_launch(monkeypatch):
    # Also hides the repository's own launch/ folder, which would import as a namespace
    # package called `launch` from the repository root.
    for name, fake in _fake_modules().items():
        monkeypatch.setitem(sys.modules, name, fake)


def load_launch_file(path):
    spec = importlib.util.spec_from_file_location(
        'launch_file_' + path.name.replace('.', '_'), path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


class _Context:
    def __init__(self, launch_configurations):
        self.launch_configurations = launch_configurations


def _resolve(value, context):
    if isinstance(value, LaunchConfiguration):
        return value.perform(context)
    if isinstance(value, list):
        return [_resolve(v, context) for v in value]
    if isinstance(value, dict):
        return {k: _resolve(v, context) for k, v in value.items()}
    return value


def run_launch(path, arguments=None, inherited=None):
    """Evaluate a launch file like `ros2 launch`; return (context, [executed actions])."""
    description = load_launch_file(path).generate_launch_description()
    configurations = dict(inherited or {})
    configurations.update(arguments or {})
    actions = []
    for entity in description.entities:
        if isinstance(entity, DeclareLaunchArgument):
            if entity.name not in configurations:
                if entity.default_value is None:
                    raise KeyError(f'required launch argument {entity.name} not given')
                configurations[entity.name] = entity.default_value
            continue
        context = _Context(configurations)
        if isinstance(entity, OpaqueFunction):
            actions.extend(entity.kwargs['function'](context))
        elif isinstance(entity, IncludeLaunchDescription):
            source, = entity.args
            included_path = Path(_resolve(source.args[0], context))
            passed = {k: _resolve(v, context) for k, v in entity.kwargs['launch_arguments']}
            _, included = run_launch(included_path, passed, configurations)
            actions.append((entity, included_path, passed, included))
        else:
            actions.append(entity)
    return _Context(configurations), actions


def node_parameters(node, context):
    """Return (params file path, overrides dict) of a launch_ros Node double."""
    params_file, overrides = _resolve(node.kwargs['parameters'], context)
    return Path(params_file), overrides


# ------------------------------------------------------------- tests
@pytest.mark.parametrize('path', [NODE_LAUNCH, REPLAY_LAUNCH])
def test_launch_files_are_installed_python_with_generate_function(path):
    tree = ast.parse(path.read_text(), str(path))
    functions = {n.name for n in tree.body if isinstance(n, ast.FunctionDef)}
    assert 'generate_launch_description' in functions
    assert path.name.endswith('.launch.py')  # setup.py installs launch/*.launch.py
    assert "'share/' + package_name + '/launch'" in (REPO_ROOT / 'setup.py').read_text()


def test_node_launch_defaults(fake_launch):
    context, actions = run_launch(NODE_LAUNCH)
    node, = actions
    assert isinstance(node, RosNode)
    assert node.kwargs['package'] == 'reduced_dynamics'
    assert node.kwargs['name'] == NODE_NAME
    executable = node.kwargs['executable']
    assert f"'{executable} = reduced_dynamics.node:main'" in (REPO_ROOT / 'setup.py').read_text()
    assert _resolve(node.kwargs['namespace'], context) == ''
    params_file, overrides = node_parameters(node, context)
    assert params_file == REPO_ROOT / 'config' / 'params.yaml'
    assert '/**/' + NODE_NAME in yaml.safe_load(params_file.read_text())  # any namespace
    node_section(yaml.safe_load(params_file.read_text()), NODE_NAME)  # valid for the node
    assert overrides == {'use_sim_time': False}  # an empty urdf keeps the file's urdf_path


def test_node_launch_arguments(fake_launch, monkeypatch, tmp_path):
    monkeypatch.chdir(tmp_path)
    context, (node,) = run_launch(NODE_LAUNCH, {
        'urdf': 'robots/arm.urdf', 'use_sim_time': 'True', 'namespace': 'robot',
        'params_file': '/etc/my_params.yaml'})
    params_file, overrides = node_parameters(node, context)
    assert params_file == Path('/etc/my_params.yaml')
    assert overrides == {'use_sim_time': True,
                         'urdf_path': str(tmp_path / 'robots' / 'arm.urdf')}
    assert _resolve(node.kwargs['namespace'], context) == 'robot'


def test_node_launch_rejects_a_misspelt_boolean(fake_launch):
    with pytest.raises(ValueError, match='use_sim_time must be true or false'):
        run_launch(NODE_LAUNCH, {'use_sim_time': 'ture'})


def test_replay_launch_plays_the_bag_on_sim_time(fake_launch):
    context, actions = run_launch(REPLAY_LAUNCH, {'bag': '/data/run1', 'rate': '0.5'})
    (include, included_path, passed, (node,)), timer, handler = actions
    assert included_path == NODE_LAUNCH and included_path.is_file()
    assert passed['use_sim_time'] == 'true'
    assert passed['params_file'] == str(REPO_ROOT / 'config' / 'params.yaml')
    included_context = _Context(dict(context.launch_configurations, **passed))
    _, overrides = node_parameters(node, included_context)
    assert overrides == {'use_sim_time': True}

    assert isinstance(timer, TimerAction)
    assert _resolve(timer.kwargs['period'], context) == '2.0'
    play, = timer.kwargs['actions']
    assert _resolve(play.kwargs['cmd'], context) == [
        'ros2', 'bag', 'play', '/data/run1', '--rate', '0.5', '--clock']

    assert isinstance(handler, RegisterEventHandler)
    on_exit, = handler.args
    assert on_exit.kwargs['target_action'] is play
    emit, = on_exit.kwargs['on_exit']
    assert isinstance(emit.kwargs['event'], Shutdown)


def test_replay_launch_needs_a_bag(fake_launch):
    with pytest.raises(KeyError, match='bag'):
        run_launch(REPLAY_LAUNCH)


def test_with_real_launch():
    try:
        from ament_index_python.packages import get_package_share_directory
        from launch import LaunchDescription as RealLaunchDescription
        import launch.actions  # noqa: F401  the repository's launch/ folder lacks it
        import launch_ros.actions  # noqa: F401
    except ImportError:
        pytest.skip('ROS 2 launch/launch_ros are not importable (ROS 2 not sourced)')
    try:
        get_package_share_directory('reduced_dynamics')
    except Exception:  # PackageNotFoundError: the package is not built/installed
        pytest.skip('reduced_dynamics is not installed in the ament index')
    for path, required in ((NODE_LAUNCH, set()), (REPLAY_LAUNCH, {'bag'})):
        description = load_launch_file(path).generate_launch_description()
        assert isinstance(description, RealLaunchDescription)
        arguments = {a.name: a for a in description.get_launch_arguments()}
        assert {'params_file', 'urdf', 'namespace'} <= set(arguments)
        assert {n for n, a in arguments.items() if a.default_value is None} == required
    assert os.path.isfile(os.path.join(get_package_share_directory('reduced_dynamics'),
                                       'launch', NODE_LAUNCH.name))
