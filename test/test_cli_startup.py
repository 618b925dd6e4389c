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


"""Cheap start-up: a subcommand imports what it uses, ``--help`` almost nothing."""

import contextlib
import json
import os
from pathlib import Path
import subprocess
import sys

import pytest

REPO = Path(__file__).resolve().parent.parent
#: Heavy modules none of the checked entry points may load.
HEAVY = ('scipy.stats', 'pinocchio', 'matplotlib', 'scipy.integrate', 'rosbags',
         'reduced_dynamics.estimator.pipeline')


def _loaded_after(code: str) -> list[str]:
    """Return the HEAVY modules loaded by running ``code`` in a fresh interpreter."""
    probe = (f'import sys\n{code}\n'
             f'import json; print(json.dumps([m for m in {HEAVY!r} if m in sys.modules]))')
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(
        [str(REPO)] + [p for p in os.environ.get('PYTHONPATH', '').split(os.pathsep) if p]))
    done = subprocess.run([sys.executable, '-c', probe], env=env, capture_output=True,
                          text=True, timeout=120, check=True)
    return json.loads(done.stdout.strip().splitlines()[-1])


def test_help_imports_no_heavy_module():
    code = ('from contextlib import redirect_stdout\nimport io\n'
            'from reduced_dynamics.cli import main\n'
            'try:\n    with redirect_stdout(io.StringIO()):\n        main(["--help"])\n'
            'except SystemExit:\n    pass')
    assert _loaded_after(code) == []


@pytest.mark.parametrize('command', ['validate', 'symmetries'])
def test_builtin_subcommand_help_loads_no_other_subcommand(command):
    code = ('from contextlib import redirect_stdout\nimport io\n'
            'from reduced_dynamics.cli import main\n'
            f'try:\n    with redirect_stdout(io.StringIO()):\n        main(["{command}", "-h"])\n'
            'except SystemExit:\n    pass')
    assert _loaded_after(code) == []


def test_predict_loads_neither_the_pipeline_nor_scipy_stats_nor_scipy_integrate():
    # Pinocchio it needs; the estimator pipeline, scipy.stats and scipy.integrate not.
    loaded = _loaded_after('import reduced_dynamics.predict')
    assert loaded == ['pinocchio']


def test_the_filter_gates_need_no_scipy_stats():
    loaded = _loaded_after('import reduced_dynamics.estimator.filter\n'
                           'import reduced_dynamics.estimator.events\n'
                           'import reduced_dynamics.estimator.detectability')
    assert 'scipy.stats' not in loaded


def test_chi_square_quantiles_equal_scipy_stats():
    from scipy.stats import chi2 as reference

    from reduced_dynamics.chi_square import chi2
    for probability in (1e-8, 1e-6, 1e-3, 0.01, 0.5):
        for dof in range(1, 31):
            assert chi2.isf(probability, dof) == float(reference.isf(probability, dof))


def test_every_lazy_subcommand_is_registered_under_its_name():
    from reduced_dynamics.cli import build_parser, LAZY_COMMANDS
    for name in LAZY_COMMANDS:
        args = build_parser(name).parse_args([name, '--help'][:1] + _required(name))
        assert args.command == name and args.func.__module__.startswith('reduced_dynamics.')


def _required(name: str) -> list[str]:
    """Return the least arguments ``name`` parses with."""
    return {'simulate': ['-o', 'x'], 'replay': ['bag', '-o', 'x'],
            'predict': ['--trajectory', 'x'], 'tune': ['bag', '-o', 'x'],
            'bench': [], 'replay-many': ['bag', '-o', 'x'],
            'identify': ['bag', '--link', 'l'], 'correlate': ['out'], 'compile': [],
            'play': ['bag']}[name]


def test_validate_loads_only_the_model_and_the_integrators():
    loaded = _loaded_after('import reduced_dynamics.validation\n'
                           'import reduced_dynamics.robot.symmetry')
    assert loaded == ['pinocchio']


def test_compiling_notice_says_why_only_when_it_takes_long():
    """A slow block (compiling) is announced once; a quick one (loading) is not."""
    import time
    from reduced_dynamics.estimator.core import warmup
    for seconds, expected in ((0.0, []), (0.6, [warmup.COMPILING_NOTICE])):
        said = []
        with warmup.compiling_notice(said.append, after_s=0.2):
            time.sleep(seconds)
        time.sleep(0.3)  # a timer left running would speak now
        assert said == expected


class _Timer:
    """A stand-in for compiling_notice's timer: records its cancellation."""

    def __init__(self) -> None:
        self.cancelled = False

    def cancel(self) -> None:
        self.cancelled = True


@pytest.mark.parametrize('quiet', [False, True])
def test_replay_announces_a_slow_first_chunk_unless_quiet(monkeypatch, capsys, tmp_path, quiet):
    """The notice's timer runs until replay's first chunk is done, only with progress shown."""
    from reduced_dynamics import replay
    from reduced_dynamics.cli import main
    from reduced_dynamics.estimator.core.warmup import COMPILING_NOTICE
    timers = []

    @contextlib.contextmanager
    def at_once(say):  # as if the first chunk took longer than NOTICE_AFTER_S
        say(COMPILING_NOTICE)
        timers.append(_Timer())
        yield timers[-1]
    monkeypatch.setattr(replay, 'compiling_notice', at_once)
    bag = REPO / 'test' / 'data' / 'paper_thruster'
    assert main(['replay', str(bag), '-o', str(tmp_path / 'out'), '--no-smooth']
                + ['--quiet'] * quiet) == 0
    said = f'replay: {COMPILING_NOTICE}' in capsys.readouterr().err.splitlines()
    assert said is not quiet and [t.cancelled for t in timers] == [True] * (not quiet)
