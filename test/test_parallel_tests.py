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

"""The suite runs in pytest-xdist workers: each has a ROS domain of its own."""

import importlib.util
import os
from pathlib import Path
import subprocess
import sys

import pytest

REPO = Path(__file__).resolve().parent.parent


def _root_conftest():
    spec = importlib.util.spec_from_file_location('root_conftest', REPO / 'conftest.py')
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.parametrize('run', ['0' * 32, 'ff' * 16, '5a1e' * 8])
def test_xdist_workers_get_distinct_ros_domains(monkeypatch, run):
    conftest = _root_conftest()
    monkeypatch.setenv('PYTEST_XDIST_TESTRUNUID', run)
    domains = []
    for worker in range(8):
        monkeypatch.setenv('PYTEST_XDIST_WORKER', f'gw{worker}')
        domains.append(int(conftest.xdist_domain_id()))
    assert len(set(domains)) == 8 and all(1 <= d <= 100 for d in domains), domains
    monkeypatch.delenv('PYTEST_XDIST_WORKER')
    assert conftest.xdist_domain_id() == ''  # not a worker: ros_harness picks by pid


def test_the_harness_and_the_bench_take_the_workers_domain():
    probe = ('import ros_harness, os\n'
             'from reduced_dynamics.bench import node_domain_id\n'
             'print(ros_harness.DOMAIN_ID, os.environ["ROS_DOMAIN_ID"], node_domain_id())\n')
    env = dict(os.environ, RD_TEST_DOMAIN_ID='42', RD_BENCH_DOMAIN_ID='42', ROS_DOMAIN_ID='7',
               PYTHONPATH=os.pathsep.join([str(REPO / 'test'), str(REPO)]))
    done = subprocess.run([sys.executable, '-c', probe], env=env, capture_output=True,
                          text=True, timeout=600, check=True)
    assert done.stdout.split() == ['42', '42', '42']


def test_this_worker_uses_its_domain():
    domain = _root_conftest().xdist_domain_id()
    if not domain:
        pytest.skip('not run by a pytest-xdist worker')
    assert os.environ['ROS_DOMAIN_ID'] == os.environ['RD_TEST_DOMAIN_ID'] == domain
    assert os.environ['RD_BENCH_DOMAIN_ID'] == domain


def test_test_sh_runs_the_suite_in_xdist_workers():
    script = (REPO / 'scripts' / 'test.sh').read_text()
    assert 'pytest_args+=(-n "$RD_TEST_WORKERS" --dist loadgroup)' in script
    assert "'pytest-xdist'" in (REPO / 'setup.py').read_text()
