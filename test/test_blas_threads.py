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
One BLAS thread in every entry point (reduced_dynamics.blas_threads).

The thread counts are read with threadpoolctl in fresh processes started with
``OPENBLAS_NUM_THREADS=2`` (both numpy's and scipy's OpenBLAS load with two threads).
"""

import hashlib
import json
import os
from pathlib import Path
import subprocess
import sys

import pytest

from reduced_dynamics import blas_threads
from reduced_dynamics.blas_threads import ENV_BLAS_THREADS, requested_threads

ROOT = Path(__file__).resolve().parent.parent
DATA = Path(__file__).parent / 'data'


def _env(**values: str) -> dict:
    """Return this environment with ``values`` set, '' removing a variable; the checkout first."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(
        [str(ROOT)] + [p for p in os.environ.get('PYTHONPATH', '').split(os.pathsep) if p]))
    for name, value in values.items():
        if value:
            env[name] = value
        else:
            env.pop(name, None)
    return env


def _run_python(code: str, **env: str) -> list:
    """Run ``code`` in a fresh interpreter; return the JSON its last line prints."""
    done = subprocess.run([sys.executable, '-c', code], env=_env(**env), capture_output=True,
                          text=True, timeout=300, cwd=str(ROOT))
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


#: Prints the BLAS libraries' thread counts as JSON: (file name, threads), sorted.
COUNTS = ('from threadpoolctl import threadpool_info\n'
          'print(json.dumps(sorted((i["filepath"].rsplit("/", 1)[-1], i["num_threads"])\n'
          '                        for i in threadpool_info() if i["user_api"] == "blas")))\n')


def test_requested_threads_reads_the_override() -> None:
    assert requested_threads({}) == 1
    assert requested_threads({ENV_BLAS_THREADS: ''}) == 1
    assert requested_threads({ENV_BLAS_THREADS: ' 3 '}) == 3
    assert requested_threads({ENV_BLAS_THREADS: 'Inherit'}) is None
    # OPENBLAS_NUM_THREADS alone does not change it: the outputs must not depend on it.
    assert requested_threads({'OPENBLAS_NUM_THREADS': '2'}) == 1
    for bad in ('0', '-1', 'two', '1.5'):
        with pytest.raises(ValueError, match=ENV_BLAS_THREADS):
            requested_threads({ENV_BLAS_THREADS: bad})


def test_limit_reaches_numpys_and_scipys_openblas_whatever_was_imported() -> None:
    # Called before scipy is imported: threadpoolctl alone would miss scipy's library,
    # which loads later with its default (measured); the function loads both first.
    code = ('import json\nimport numpy\n'
            'from reduced_dynamics.blas_threads import limit_blas_threads\n'
            'assert limit_blas_threads() == 1\nimport scipy.linalg\n' + COUNTS)
    counts = _run_python(code, OPENBLAS_NUM_THREADS='2')
    assert len(counts) == 2, counts  # numpy's and scipy's OpenBLAS
    assert [threads for _, threads in counts] == [1, 1]
    # The opt-out leaves both as they loaded; a count is applied to both.
    counts = _run_python(code.replace('== 1', 'is None'), OPENBLAS_NUM_THREADS='2',
                         **{ENV_BLAS_THREADS: 'inherit'})
    assert [threads for _, threads in counts] == [2, 2]
    counts = _run_python(code.replace('== 1', '== 2'), OPENBLAS_NUM_THREADS='1',
                         **{ENV_BLAS_THREADS: '2'})
    assert [threads for _, threads in counts] == [2, 2]


def test_limited_blas_threads_restores_the_callers_counts() -> None:
    code = ('import json\nfrom threadpoolctl import threadpool_info\n'
            'from reduced_dynamics.blas_threads import limited_blas_threads\n'
            'def counts():\n'
            '    return sorted(i["num_threads"] for i in threadpool_info()\n'
            '                  if i["user_api"] == "blas")\n'
            'import numpy, scipy.linalg\nbefore = counts()\n'
            'with limited_blas_threads() as count:\n    inside = counts()\n'
            'print(json.dumps([count, before, inside, counts()]))\n')
    count, before, inside, after = _run_python(code, OPENBLAS_NUM_THREADS='2')
    assert count == 1
    assert before == [2, 2] and after == [2, 2]
    assert inside == [1, 1]


def test_node_main_sets_one_thread_before_rclpy_init() -> None:
    code = ('import json\nfrom reduced_dynamics import node\n'
            'if node.rclpy is None:\n    print(json.dumps(None)); raise SystemExit(0)\n'
            'from threadpoolctl import threadpool_info\nseen = []\n'
            'class Stop(Exception):\n    pass\n'
            'def init(*args, **kwargs):\n'
            '    seen.extend(i["num_threads"] for i in threadpool_info()\n'
            '                if i["user_api"] == "blas")\n'
            '    raise Stop\n'
            'node.rclpy.init = init\n'
            'try:\n    node.main(["reduced_dynamics_node"])\nexcept Stop:\n    pass\n'
            'print(json.dumps(seen))\n')
    seen = _run_python(code, OPENBLAS_NUM_THREADS='2')
    if seen is None:
        pytest.skip('rclpy is not available')
    assert seen == [1, 1]


def test_node_main_refuses_a_malformed_override(monkeypatch, capsys) -> None:
    from reduced_dynamics import node
    monkeypatch.setenv(ENV_BLAS_THREADS, 'many')
    if node.rclpy is None:
        pytest.skip('rclpy is not available')
    assert node.main(['reduced_dynamics_node']) == 2
    assert ENV_BLAS_THREADS in capsys.readouterr().err


def test_fleet_worker_limits_its_process(monkeypatch, tmp_path) -> None:
    # run_bag is what every backend (process pool, Ray, Dask) runs in its workers.
    from reduced_dynamics import fleet
    calls = []
    monkeypatch.setattr(blas_threads, 'limit_blas_threads', lambda: calls.append(1) or 1)
    row = fleet.run_bag(fleet.BagJob(str(tmp_path / 'missing'), 'missing',
                                     str(tmp_path / 'out'), {}))
    assert calls == [1]
    assert row['status'] == 'failed'  # the bag is missing: the limit came first


def _output_digest(out: Path) -> str:
    from reduced_dynamics.bag.reader import open_bag
    digest = hashlib.sha256()
    with open_bag(str(out)) as reader:
        for message in reader.raw_messages(sorted(reader.topics())):
            digest.update(message.topic.encode())
            digest.update(message.timestamp_ns.to_bytes(8, 'little'))
            digest.update(bytes(message.data))
    return digest.hexdigest()


@pytest.mark.slow
def test_replay_outputs_do_not_depend_on_openblas_num_threads(tmp_path) -> None:
    """The CLI's replay of a bag with a detection (a pulse fit): the same bytes."""
    digests = {}
    for threads in ('', '1', '2'):
        out = tmp_path / f'out{threads or "_unset"}'
        done = subprocess.run(
            [sys.executable, '-m', 'reduced_dynamics.cli', 'replay',
             str(DATA / 'paper_realistic'), '-o', str(out), '--quiet', '--no-smooth'],
            env=_env(OPENBLAS_NUM_THREADS=threads, **{ENV_BLAS_THREADS: ''}),
            capture_output=True, text=True, timeout=900, cwd=str(ROOT))
        assert done.returncode == 0, done.stderr[-3000:]
        digests[threads] = _output_digest(out)
        from reduced_dynamics.bag.reader import open_bag
        with open_bag(str(out)) as reader:
            events = sum(1 for _ in reader.raw_messages(['/reduced_dynamics/events']))
        assert events >= 1  # the bag's pulse is detected and located
    assert len(set(digests.values())) == 1, digests
