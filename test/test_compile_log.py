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

"""The opt-in compile log of the test runs (conftest.py, ``RD_COMPILE_LOG``)."""

import json
import os
from pathlib import Path
import subprocess
import sys

ROOT = Path(__file__).resolve().parents[1]

SAMPLE = '''
from numba import njit


@njit
def twice(x):
    return 2 * x


def test_loads_nothing():
    assert 1 + 1 == 2


def test_compiles():
    assert twice(2.0) == 4.0
    assert twice(3.0) == 6.0  # the same signature: loaded, not compiled again
'''


def test_the_log_names_each_compile_and_the_test_it_ran_in(tmp_path) -> None:
    """One line per top-level compile, with the test that triggered it; none without."""
    (tmp_path / 'test_sample.py').write_text(SAMPLE)
    log = tmp_path / 'compiles.jsonl'
    env = dict(os.environ, RD_COMPILE_LOG=str(log), PYTHONPATH=str(ROOT))
    # Not this run's options: colcon test passes its pytest arguments (-n 2 ...) this way.
    env.pop('PYTEST_ADDOPTS', None)
    # The root conftest as a plugin: the sample lies outside the checkout.
    proc = subprocess.run([sys.executable, '-m', 'pytest', '-q', '-p', 'conftest',
                           '-p', 'no:cacheprovider', '-p', 'no:xdist', str(tmp_path)],
                          cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    records = [json.loads(line) for line in log.read_text().splitlines()]
    assert [(r['test'], r['kernel']) for r in records] == [
        ('test_sample.py::test_compiles', 'test_sample.twice')]
    assert 'float64' in records[0]['signature'] and records[0]['cpu_s'] > 0.0


def test_without_the_variable_nothing_is_registered() -> None:
    """The log is opt-in: a plain run has no listener and writes nothing."""
    import conftest

    class Manager:
        registered: list = []

        def register(self, plugin, name):
            self.registered.append(name)

    class Config:
        pluginmanager = Manager()

    saved = os.environ.pop('RD_COMPILE_LOG', None)
    try:
        conftest.pytest_configure(Config())
    finally:
        if saved is not None:
            os.environ['RD_COMPILE_LOG'] = saved
    assert Config.pluginmanager.registered == []
