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

"""Run ament_xmllint on the whole package (the repository root)."""

from pathlib import Path
import subprocess

import pytest

try:
    from linters import find_linter, HOW, linter_env
except ImportError:  # test/ imported as a package
    from test.linters import find_linter, HOW, linter_env

REPO_ROOT = Path(__file__).resolve().parent.parent
# Workspace/build outputs created when colcon or pip run in the repository root;
# they hold copies of (or generated) sources and must not be linted.
ARTIFACT_DIRS = [d for d in ('build', 'install', 'log') if (REPO_ROOT / d).is_dir()]


@pytest.mark.xmllint
@pytest.mark.linter
def test_xmllint():
    # The ament CLI is used rather than an in-process import so the linter runs with
    # the interpreter and flake8/pydocstyle versions it was installed with (the venv's
    # [lint] extra, Debian apt or a sourced ROS 2): test/linters.py says where.
    exe = find_linter('ament_xmllint')
    assert exe, f'ament_xmllint missing: {HOW["ament_xmllint"]}'
    argv = [exe] + (['--exclude'] + ARTIFACT_DIRS if ARTIFACT_DIRS else [])
    proc = subprocess.run(argv, cwd=REPO_ROOT, capture_output=True, text=True, check=False,
                          env=linter_env(exe))
    assert proc.returncode == 0, \
        'Found errors:\n' + proc.stdout + proc.stderr
