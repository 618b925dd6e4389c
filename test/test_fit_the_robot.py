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

"""Options and outputs that fit the robot (issue 24 item 6): tune's budget, integer doubles."""

from pathlib import Path

import pytest

from reduced_dynamics.cli import main
from reduced_dynamics.resources import config_path

DATA = Path(__file__).parent / 'data'
PD_BAG = DATA / 'freeflyer2' / 'rosbag2_2024_03_14-14_17_23'


@pytest.mark.parametrize('budget', [1, 4, 7])
def test_tune_makes_exactly_max_evaluations_filter_runs(tmp_path, capsys, budget):
    """1: part of the process-noise scan; 4: the scan alone; 7: the scan and Nelder-Mead."""
    out = tmp_path / 'tuned.yaml'
    assert main(['tune', str(PD_BAG), '-o', str(out), '--urdf',
                 str(config_path('robots/freeflyer.urdf')), '--end', '4', '--base-pose-topic', '/vrpn_mocap/robot/pose',
                 '--max-evaluations', str(budget)]) == 0
    progress = [line for line in capsys.readouterr().err.splitlines()
                if line.startswith('tune: evaluation ')]
    assert len(progress) == budget
    assert f', {budget} evaluations' in out.read_text().splitlines()[0]
