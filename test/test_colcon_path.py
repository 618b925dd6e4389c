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
After ``colcon build`` and ``source install/setup.bash`` (issue 14.2).

Both forms work: the plain ``reduced-dynamics`` command (colcon's PATH hook finds
``install/reduced_dynamics/bin/reduced-dynamics``) and the executables in
``lib/reduced_dynamics/`` that ``ros2 run reduced_dynamics <exe>`` runs (there is no
ros2cli here, so those are run directly). Built with colcon from pip
(colcon-common-extensions) into a temporary workspace, copy and symlink installs.
"""

import importlib.util
import os
from pathlib import Path
import subprocess
import sys

import pytest

REPO_ROOT = Path(__file__).resolve().parent.parent
PKG = 'reduced_dynamics'

pytestmark = pytest.mark.skipif(
    importlib.util.find_spec('colcon_core') is None,
    reason='colcon is not importable (scripts/test.sh installs colcon-common-extensions)')


def _clean_env() -> dict:
    # No sourced workspace, no venv on PATH: only what setup.bash provides may be found.
    env = {k: v for k, v in os.environ.items()
           if not k.startswith(('COLCON', 'AMENT_', 'CMAKE_PREFIX', 'VIRTUAL_ENV'))}
    env['PATH'] = '/usr/bin:/bin'
    return env


@pytest.mark.parametrize('symlink', [False, True], ids=['copy', 'symlink-install'])
def test_cli_on_path_after_sourcing(tmp_path, symlink):
    install = tmp_path / 'install'
    argv = [sys.executable, '-m', 'colcon', '--log-base', str(tmp_path / 'log'), 'build',
            '--base-paths', str(REPO_ROOT), '--build-base', str(tmp_path / 'build'),
            '--install-base', str(install), '--packages-select', PKG]
    env = {k: v for k, v in os.environ.items() if k != 'COLCON'}
    env['COLCON_HOME'] = str(tmp_path / 'colcon_home')
    build = subprocess.run(argv + (['--symlink-install'] if symlink else []), env=env,
                           capture_output=True, text=True, timeout=600)
    assert build.returncode == 0, build.stdout + build.stderr
    wrapper = install / PKG / 'bin' / 'reduced-dynamics'
    lib = install / PKG / 'lib' / PKG
    for exe in (wrapper, lib / 'reduced-dynamics', lib / 'reduced_dynamics_node'):
        assert os.access(exe, os.X_OK), exe
    script = (f'set +u; source {install}/setup.bash; set -u\n'
              'command -v reduced-dynamics\n'
              'reduced-dynamics --help\n')
    shell = subprocess.run(['bash', '-c', script], env=_clean_env(), capture_output=True,
                           text=True, timeout=120)
    assert shell.returncode == 0, shell.stdout + shell.stderr
    found, _, usage = shell.stdout.partition('\n')
    assert Path(found) == wrapper
    assert 'usage: reduced-dynamics' in usage and 'replay' in usage
    # What `ros2 run reduced_dynamics reduced-dynamics --help` executes.
    direct = subprocess.run([str(lib / 'reduced-dynamics'), '--help'], env=_clean_env(),
                            capture_output=True, text=True, timeout=120)
    assert direct.returncode == 0 and direct.stdout == usage, direct.stderr


@pytest.mark.parametrize('command', ['bdist_wheel', 'editable_wheel', 'dist_info', None])
def test_wrapper_only_outside_wheels(command):
    # pip (PEP 517) builds wheels, whose console script is bin/reduced-dynamics already: no
    # second one; colcon reads data_files with a bare `--dry-run` and installs with
    # `setup.py install`/`develop`: the wrapper is there.
    code = ('import sys; from distutils.core import run_setup; '
            "dist = run_setup('setup.py', script_args=sys.argv[1:], stop_after='init'); "
            'print(repr(dist.data_files))')
    args = [command] if command else ['--dry-run']
    proc = subprocess.run([sys.executable, '-c', code] + args, cwd=REPO_ROOT,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    has_wrapper = "('bin', ['bin/reduced-dynamics'])" in proc.stdout.splitlines()[-1]
    assert has_wrapper == (command is None), proc.stdout
