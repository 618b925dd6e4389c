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

"""Torque changes and thruster pulses marked on the replay plots (issue 14.7)."""

import numpy as np
import pytest

from reduced_dynamics.params import defaults
from reduced_dynamics.plot_marks import pulse_intervals, torque_steps
from reduced_dynamics.replay import replay, ReplayOptions
from reduced_dynamics.robot.model import load_robot
from reduced_dynamics.simulator import simulate_bag, SimulationOptions, ThrusterPulse

MS = 1_000_000


def test_torque_steps_only_for_steps():
    stamps = np.arange(100) * 10 * MS
    held = np.where(stamps < 300 * MS, 1.0, -1.0)[:, None] * [2.0, 0.5]
    assert torque_steps(stamps, held) == [300 * MS]
    t = stamps * 1e-9
    smooth = np.column_stack([np.sin(2 * t), np.cos(3 * t)])
    noisy = smooth + np.random.default_rng(0).normal(0.0, 0.01, smooth.shape)
    assert torque_steps(stamps, smooth) == [] and torque_steps(stamps, noisy) == []
    assert torque_steps(stamps, np.zeros((100, 2))) == []


def test_pulse_intervals():
    stamps = np.arange(10) * MS
    wrench = np.zeros((10, 6))
    wrench[2:4, 0] = 1.0
    wrench[8:, 5] = -0.1
    assert pulse_intervals(stamps, wrench) == [(2 * MS, 4 * MS), (8 * MS, 9 * MS)]


def test_demo_marks_match_the_simulation(tmp_path):
    # The demo's pattern, shorter: --torque constant --torque-hold 2 switches at 1 s and 3 s
    # (a half hold, then full holds), a 0.5 s thruster pulse at 2 s.
    robot = load_robot()
    bag = tmp_path / 'recorded'
    simulate_bag(robot, str(bag), SimulationOptions(
        duration=4.0, rate=100.0, seed=1, torque='constant', torque_hold=2.0,
        torque_scale=0.5, thrusters=(ThrusterPulse(2.0, 0.5, (20, -10, 5, 2, -3, 4)),),
        overwrite=True))
    summary = replay(str(bag), str(tmp_path / 'out'), robot, ReplayOptions(
        plots_dir=str(tmp_path / 'plots'), overwrite=True,
        params=dict(defaults(), prediction_rate=0.0)))
    marks = summary['plot_marks']
    assert marks['torque_steps_s'] == pytest.approx([1.0, 3.0], abs=0.011)
    (pulse,) = marks['thruster_pulses_s']
    assert pulse == pytest.approx([2.0, 2.5], abs=0.011)
    assert marks['pulse_topic'] == '/ground_truth/external_wrench'
    assert len(summary['plots']) == 4
