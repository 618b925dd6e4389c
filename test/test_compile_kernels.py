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

"""``reduced-dynamics compile``: warm_up's parts in processes of their own at once."""

import subprocess
import sys

import pytest

from reduced_dynamics import compile_kernels
from reduced_dynamics.estimator.core import warmup


def test_the_parts_are_warm_ups_and_the_predictions_each_with_a_measured_cost():
    names = compile_kernels.part_names()
    assert sorted(names) == sorted(list(warmup.PARTS) + ['prediction'])
    # The start order comes from measured costs, one per part, the costliest first.
    assert set(compile_kernels.PART_COST_S) == set(names)
    assert all(cost > 0 for cost in compile_kernels.PART_COST_S.values())
    costs = [compile_kernels.PART_COST_S[name] for name in names]
    assert costs == sorted(costs, reverse=True)


def test_warm_up_runs_every_part_in_order(monkeypatch):
    ran = []
    for name in warmup.PARTS:
        monkeypatch.setitem(warmup.PARTS, name, lambda name=name: ran.append(name))
    warmup.warm_up()
    assert ran == list(warmup.PARTS)
    ran.clear()
    warmup.warm_up(['inputs', 'filter'])
    assert ran == ['inputs', 'filter']


def test_a_part_run_twice_in_a_process_compiles_nothing_the_second_time():
    first = compile_kernels.run_part('inputs')
    assert first.name == 'inputs' and first.cpu_s >= 0 and first.compiled >= 0
    # The kernels are in the process now (compiled or loaded): none is compiled again.
    assert compile_kernels.run_part('inputs').compiled == 0


def test_an_unknown_part_is_refused_with_the_known_ones():
    with pytest.raises(ValueError, match=r'unknown part\(s\) fliter; the parts are '):
        compile_kernels.compile_kernels(2, ['fliter'])


def test_the_command_runs_parts_in_processes_and_reports_each():
    command = [sys.executable, '-m', 'reduced_dynamics.cli', 'compile', '--jobs', '2',
               '--parts', 'inputs', 'step test']
    done = subprocess.run(command, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    for name in ('inputs', 'step test'):
        line = next(line for line in lines if line.startswith(f'{name}: '))
        assert line.endswith(('kernels compiled', 'loaded from the cache')), line
    assert lines[-1].startswith('compile: 2 parts in ') and '(2 processes)' in lines[-1]
    refused = subprocess.run(command[:-2] + ['fliter'], capture_output=True, text=True,
                             timeout=600)
    assert refused.returncode == 2
    assert 'unknown part(s) fliter' in refused.stdout
