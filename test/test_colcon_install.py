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
The colcon install as a ROS 2 user gets it (issue 14.2).

`colcon build` (plain and --symlink-install) into a temporary workspace, then, in bash
after `source install/setup.bash`: `reduced-dynamics` is the install's bin/ wrapper, on PATH,
and runs; the executables `ros2 run` looks for are in lib/reduced_dynamics/ and run with the
interpreter colcon built with (ros2cli is not installed here: they are run directly); the
launch and config files are in share/. A pip wheel build leaves the bin/ wrapper out (its
console scripts are in bin/ already).
"""

import importlib.util
import os
from pathlib import Path
import runpy
import subprocess
import sys

import pytest

REPO_ROOT = Path(__file__).resolve().parent.parent
PKG = 'reduced_dynamics'


def _bash(install: Path, script: str) -> subprocess.CompletedProcess:
    # set +u: colcon's setup.bash reads unset variables.
    return subprocess.run(
        ['bash', '-c', f'set -e; set +u; source {install}/setup.bash; set -u; {script}'],
        capture_output=True, text=True, timeout=300, check=False)


@pytest.fixture(scope='module', params=['symlink-install', 'install'])
def colcon_install(request, tmp_path_factory) -> Path:
    if importlib.util.find_spec('colcon_core') is None:
        pytest.skip('colcon is not installed (scripts/test.sh installs colcon-common-extensions)')
    ws = tmp_path_factory.mktemp(request.param)
    env = dict(os.environ, COLCON_HOME=str(ws / 'colcon_home'),
               COLCON_EXTENSION_BLOCKLIST='colcon_core.event_handler.desktop_notification')
    cmd = [sys.executable, '-m', 'colcon', '--log-base', str(ws / 'log'), 'build',
           '--paths', str(REPO_ROOT), '--build-base', str(ws / 'build'),
           '--install-base', str(ws / 'install')]
    if request.param == 'symlink-install':
        cmd.append('--symlink-install')
    proc = subprocess.run(cmd, cwd=ws, env=env, capture_output=True, text=True,
                          timeout=600, check=False)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return ws / 'install'


def test_cli_on_path_after_sourcing(colcon_install):
    proc = _bash(colcon_install, 'command -v reduced-dynamics; reduced-dynamics --help')
    assert proc.returncode == 0, proc.stdout + proc.stderr
    found, *usage = proc.stdout.splitlines()
    assert found == str(colcon_install / PKG / 'bin' / 'reduced-dynamics')
    assert usage[0].startswith('usage: reduced-dynamics')
    assert 'validate' in proc.stdout and 'replay' in proc.stdout


def test_ros2_run_executables(colcon_install):
    lib = colcon_install / PKG / 'lib' / PKG
    for exe in ('reduced-dynamics', 'reduced_dynamics_node'):
        assert os.access(lib / exe, os.X_OK), f'{lib / exe} is not executable'
    proc = _bash(colcon_install, f'{lib}/reduced-dynamics simulate --help')
    assert proc.returncode == 0 and 'usage: reduced-dynamics simulate' in proc.stdout, \
        proc.stdout + proc.stderr
    # The node executable's interpreter finds rclpy and this install's package.
    interpreter = (lib / 'reduced_dynamics_node').read_text().splitlines()[0][2:].strip()
    proc = _bash(colcon_install, f'{interpreter} -c "import rclpy, {PKG}.node, {PKG}; '
                 f'print({PKG}.__file__)"')
    assert proc.returncode == 0, proc.stdout + proc.stderr
    where = Path(proc.stdout.strip()).resolve()
    assert where.is_relative_to(colcon_install.parent.resolve()) or \
        where.is_relative_to(REPO_ROOT.resolve()), where


def test_share_files_installed(colcon_install):
    share = colcon_install / PKG / 'share' / PKG
    for name in ('package.xml', 'launch/reduced_dynamics.launch.py',
                 'launch/replay_bag.launch.py', 'config/params.yaml',
                 'config/robots/paper_robot.urdf'):
        assert (share / name).is_file(), name
    assert (colcon_install / PKG / 'share' / 'ament_index' / 'resource_index' / 'packages'
            / PKG).is_file()


@pytest.mark.parametrize('argv, has_wrapper', [
    (['--dry-run'], True),  # how colcon reads setup.py
    (['install'], True), (['develop'], True),
    (['bdist_wheel'], False), (['editable_wheel'], False)])
def test_bin_wrapper_only_outside_wheels(monkeypatch, argv, has_wrapper):
    captured = {}
    import setuptools
    monkeypatch.setattr(setuptools, 'setup', lambda **kw: captured.update(kw))
    monkeypatch.setattr(sys, 'argv', ['setup.py'] + argv)
    runpy.run_path(str(REPO_ROOT / 'setup.py'))
    destinations = dict(captured['data_files'])
    assert (destinations.get('bin') == ['bin/reduced-dynamics']) == has_wrapper
    assert os.access(REPO_ROOT / 'bin' / 'reduced-dynamics', os.X_OK)
