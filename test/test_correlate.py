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

"""``reduced-dynamics correlate`` on the shipped freeflyer2 recording (issue 24 item 6)."""

import json
from pathlib import Path
import subprocess
import sys

import numpy as np
import pytest

from reduced_dynamics.cli import main
from reduced_dynamics.resources import config_path
from reduced_dynamics.thrust_correlation import savitzky_golay_inner, thrust_correlation

DATA = Path(__file__).parent / 'data'
PD_BAG = str(DATA / 'freeflyer2' / 'rosbag2_2024_03_14-14_17_23')


#: The tests reading :func:`replayed` run in one pytest-xdist worker: one replay, not two.
ONE_WORKER = pytest.mark.xdist_group('correlate_replay')


@pytest.fixture(scope='session')
def replayed(tmp_path_factory):
    """Return the replay output of the shipped freeflyer2 bag (replay's defaults)."""
    out = str(tmp_path_factory.mktemp('correlate') / 'out')
    assert main(['replay', PD_BAG, '-o', out, '--urdf',
                 str(config_path('robots/freeflyer.urdf')), '--base-pose-topic',
                 '/vrpn_mocap/robot/pose']) == 0
    return out


def _json(capsys, *args) -> dict:
    capsys.readouterr()
    assert main(['correlate', *args, '--json']) == 0
    return json.loads(capsys.readouterr().out)


@ONE_WORKER
def test_correlate_prints_the_python_functions_figures(replayed, capsys):
    expected = thrust_correlation(PD_BAG, replayed)
    # Defaults: the shipped freeflyer2 thruster map and its command topic.
    printed = _json(capsys, replayed, '--bag', PD_BAG)
    assert printed['samples'] == expected.samples
    assert [printed[axis]['correlation'] for axis in ('fx', 'fy', 'mz')] == list(expected[:3])
    # The data README: the thrusters deliver about half their nominal 0.2 N (the
    # commanded-wrench input measured torque gains 0.58 and 0.66); here 0.49/0.62/0.64.
    for axis in ('fx', 'fy', 'mz'):
        assert 0.3 < printed[axis]['gain'] < 1.0, printed
    given = _json(capsys, replayed, '--bag', PD_BAG, '--thruster-map',
                  str(config_path('thrusters/freeflyer2.yaml')),
                  '--command-topic', '/robot/commands/binary_thrust')
    assert given == printed
    assert main(['correlate', replayed, '--bag', PD_BAG]) == 0
    table = capsys.readouterr().out.splitlines()
    assert table[0].startswith('/reduced_dynamics/drift/momentum_rate against '
                               '/robot/commands/binary_thrust (freeflyer2, 8 thrusters)')
    rows = {line.split()[0]: line.split()[1:] for line in table[2:5]}
    assert [float(rows[axis][0]) for axis in ('fx', 'fy', 'mz')] == \
        [round(value, 4) for value in expected[:3]]


@ONE_WORKER
def test_correlate_says_what_is_missing(replayed, capsys):
    assert main(['correlate', replayed]) == 2
    assert 'no command topic /robot/commands/binary_thrust: give the recording that has ' \
        'it with --bag' in capsys.readouterr().err
    assert main(['correlate', replayed, '--bag', PD_BAG, '--command-topic', '/thrust']) == 2
    assert 'no command topic /thrust' in capsys.readouterr().err


@pytest.mark.parametrize('window, order', [(61, 3), (3, 1), (11, 0), (31, 5), (5, 4)])
def test_smoothing_is_scipys_savitzky_golay_inside_the_series(window, order):
    from scipy.signal import savgol_filter
    values = np.random.default_rng(window).normal(size=(700, 3)).cumsum(axis=0)
    ours = savitzky_golay_inner(values, window, order)
    theirs = savgol_filter(values, window, order, axis=0)[window:-window]
    assert ours.shape == theirs.shape
    # scipy's coefficients (lstsq on unscaled offsets) are off by up to 3e-13 at (31, 5).
    assert np.abs(ours - theirs).max() <= 1e-11 * np.abs(theirs).max()


@pytest.mark.parametrize('window, order', [(60, 3), (5, 5), (3, -1)])
def test_a_window_the_smoothing_cannot_take_is_refused(window, order):
    with pytest.raises(ValueError, match='window must be odd and longer than the order'):
        savitzky_golay_inner(np.zeros((500, 3)), window, order)
    with pytest.raises(ValueError, match='keeps none with 61 cut at each end'):
        savitzky_golay_inner(np.zeros((122, 3)), 61, 3)


def test_correlate_does_not_import_scipy_signal():
    """scipy.signal's import alone took 3.8 s of CPU here: correlate does without it."""
    code = ('import sys, reduced_dynamics.correlate, reduced_dynamics.thrust_correlation; '
            'print("scipy.signal" in sys.modules)')
    out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                         check=True).stdout
    assert out.strip() == 'False'
