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

"""Acceptance: the reduced model against full free-floating dynamics (aba), 10 s runs."""

import numpy as np
import pinocchio as pin
import pytest

from conftest_robots import ROBOTS
from reduced_dynamics.cli import main
from reduced_dynamics.full_dynamics import FullDynamics
from reduced_dynamics.geometry.isotropy import MomentumClass
from reduced_dynamics.reduction.reconstruction import ReducedPropagator
from reduced_dynamics.robot.state import FreeFloatingState, random_sinusoid_torque
from reduced_dynamics.validation import compare, random_scenario


@pytest.mark.parametrize('name', ['paper', 'tree'])
def test_momentum_is_constant_along_full_dynamics(name):
    robot = ROBOTS[name]()
    rng = np.random.default_rng(11)
    state = FreeFloatingState(pin.SE3.Random(), 0.2 * rng.standard_normal(robot.n),
                              rng.uniform(-0.5, 0.5, robot.m), 0.2 * rng.standard_normal(robot.m))
    blocks = robot.metric_blocks(state.qbar)
    torque = random_sinusoid_torque(robot.m, rng, scale=0.2 * np.diag(blocks.reduced_metric).min())
    full = FullDynamics(robot, torque).simulate(state, np.linspace(0, 10, 201))
    variation = np.max(np.linalg.norm(full.mu - full.mu[0], axis=1)) / np.linalg.norm(full.mu[0])
    assert variation <= 1e-10
    assert np.ptp(full.qbar, axis=0).max() > 0.05  # the torques really moved the arm


@pytest.mark.parametrize('name, cls', [(n, c) for n in sorted(ROBOTS) for c in MomentumClass])
def test_reduced_matches_full_dynamics(name, cls):
    robot = ROBOTS[name]()
    result = compare(robot, random_scenario(robot, cls, seed=11), duration=10.0)
    assert result.shape_error <= 1e-8
    assert result.pose_error <= 1e-7
    assert result.pi_error <= 1e-8
    # The reference's own integration error (the 1e-10 bound is the dedicated test above,
    # on a state whose momentum is not small against the internal momenta).
    assert result.mu_variation <= 1e-9


def test_discrete_gradient_conserves_reduced_energy():
    robot = ROBOTS['paper']()
    scenario = random_scenario(robot, MomentumClass.GENERIC, seed=5, drift_speed=0.2,
                               shape_speed=0.3)
    propagator, y0 = ReducedPropagator.from_full_state(robot, scenario.state)
    step = 1e-3
    trajectory = propagator.propagate(y0, np.arange(10001) * step, 'discrete_gradient',
                                      step=step)
    energy = trajectory.energy
    relative = (energy - energy[0]) / energy[0]
    assert np.abs(relative).max() <= 1e-9
    # Bounded, no secular trend: the fitted drift over the run is below the noise bound.
    slope = np.polyfit(trajectory.times, relative, 1)[0]
    assert abs(slope * trajectory.times[-1]) <= 1e-11
    assert np.ptp(trajectory.qbar, axis=0).max() > 0.1  # the system really moved
    # And it tracks the adaptive solution to second order.
    reference = ReducedPropagator.from_full_state(robot, scenario.state)
    adaptive = reference[0].propagate(reference[1], trajectory.times[::1000])
    assert np.abs(adaptive.qbar - trajectory.qbar[::1000]).max() <= 1e-4


def test_validate_command_prints_the_table(capsys):
    assert main(['validate', '--duration', '1']) == 0
    out = capsys.readouterr().out
    for word in ('generic mu', 'pure angular mu', 'pure linear mu', 'zero mu', 'PASS'):
        assert word in out


def test_validate_command_rejects_bad_robot(capsys):
    assert main(['validate', '--urdf', '/nonexistent.urdf']) == 2
    assert 'not found' in capsys.readouterr().err


def test_discrete_gradient_with_torques_converges_at_second_order():
    robot = ROBOTS['paper']()
    scenario = random_scenario(robot, MomentumClass.GENERIC, seed=8)
    times = np.linspace(0.0, 0.5, 3)
    reference = ReducedPropagator.from_full_state(robot, scenario.state, scenario.torque)
    exact = reference[0].propagate(reference[1], times).qbar
    errors = []
    for step in (0.02, 0.01):
        propagator, y0 = ReducedPropagator.from_full_state(robot, scenario.state,
                                                           scenario.torque)
        fixed = propagator.propagate(y0, times, 'discrete_gradient', step=step).qbar
        errors.append(np.abs(fixed - exact).max())
    assert 3.0 <= errors[0] / errors[1] <= 5.0
