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

"""State-transition matrices of the reduced flow against finite differences."""

import numpy as np
import pinocchio as pin
import pytest

from conftest_robots import ROBOTS
from reduced_dynamics.full_dynamics import FullDynamics
from reduced_dynamics.geometry.isotropy import MomentumClass
from reduced_dynamics.reduction.reconstruction import ReducedPropagator
from reduced_dynamics.reduction.sensitivity import flow_sensitivity, orbit_tangent
from reduced_dynamics.robot.state import FreeFloatingState
from reduced_dynamics.validation import random_scenario

TIMES = np.array([0.0, 0.5, 1.0])
#: central differences: truncation ~EPS^2, integration noise ~1e-13 / EPS
EPS = 1e-5
RTOL = 1e-6


def _setup(name, cls=MomentumClass.GENERIC):
    robot = ROBOTS[name]()
    scenario = random_scenario(robot, cls, 1)
    held = 0.05 * np.linspace(-1.0, 1.0, robot.m)
    return robot, scenario.state, held


def _column_errors(predicted, numeric):
    return [np.linalg.norm(predicted[:, j] - numeric[:, j]) / np.linalg.norm(numeric[:, j])
            for j in range(numeric.shape[1])]


def _full_difference(robot, state, held, x, tau):
    """Run full aba dynamics from a perturbed state (theta, qbar, xi, qbar_dot)."""
    n, m = robot.n, robot.m
    start = FreeFloatingState(state.g * robot.group.exp(x[:n]), state.xi + x[n + m:2 * n + m],
                              state.qbar + x[n:n + m], state.qbar_dot + x[2 * n + m:])
    run = FullDynamics(robot, lambda t, q, qd: tau).simulate(start, TIMES, 1e-13, 1e-13)
    return run


@pytest.mark.parametrize('name', sorted(ROBOTS))
def test_full_transition_and_torque_jacobian_match_finite_differences(name):
    # Independent of the reduction: perturb the full state, integrate aba.
    robot, state, held = _setup(name)
    n, m = robot.n, robot.m
    size = 2 * (n + m)
    sensitivity = flow_sensitivity(robot, state, TIMES, held, 1e-12, 1e-12)
    nominal = _full_difference(robot, state, held, np.zeros(size), held)

    def final(run):
        theta = robot.group.log(nominal.pose(-1).inverse() * run.pose(-1))
        return np.concatenate([theta, run.qbar[-1] - nominal.qbar[-1],
                               run.xi[-1] - nominal.xi[-1],
                               run.qbar_dot[-1] - nominal.qbar_dot[-1]])
    numeric = np.empty((size, size))
    for j in range(size):
        step = np.zeros(size)
        step[j] = EPS
        numeric[:, j] = (final(_full_difference(robot, state, held, step, held))
                         - final(_full_difference(robot, state, held, -step, held))) / (2 * EPS)
    assert max(_column_errors(sensitivity.full[-1], numeric)) <= RTOL
    numeric_tau = np.empty((size, m))
    for j in range(m):
        step = np.zeros(m)
        step[j] = EPS
        zero = np.zeros(size)
        numeric_tau[:, j] = (final(_full_difference(robot, state, held, zero, held + step))
                             - final(_full_difference(robot, state, held, zero, held - step))
                             ) / (2 * EPS)
    assert max(_column_errors(sensitivity.torque[-1], numeric_tau)) <= RTOL
    # The matrices start at the identity (and zero), and the trajectory is the prediction's.
    assert np.array_equal(sensitivity.full[0], np.eye(size))
    assert not sensitivity.torque[0].any()
    assert np.allclose(sensitivity.trajectory.qbar[-1], nominal.qbar[-1], atol=1e-9)


@pytest.mark.parametrize('name, cls', [(name, MomentumClass.GENERIC) for name in sorted(ROBOTS)]
                         + [('paper', MomentumClass.ZERO), ('paper', MomentumClass.PURE_ANGULAR)])
def test_reduced_transition_matches_finite_differences_of_the_propagator(name, cls):
    # Perturb y0 = (q~1, qbar, pbar, eta) of the reduced propagator itself; read q~1 at the
    # end through d pi / d q~1 (the chart there is centred at the nominal point).
    robot, state, held = _setup(name, cls)
    n, m = robot.n, robot.m
    sensitivity = flow_sensitivity(robot, state, TIMES, held, 1e-12, 1e-12)

    def run(dy):
        propagator, y0 = ReducedPropagator.from_full_state(robot, state,
                                                           lambda t, q, qd: held)
        return propagator.propagate(y0 + dy, TIMES, 'dop853', 1e-13, 1e-13)
    k = sensitivity.orbit_tangent.shape[2]
    size = k + 2 * m + n
    nominal = run(np.zeros(size))

    def final(trajectory):
        theta = robot.group.log(pin.SE3(nominal.poses[-1]).inverse()
                                * pin.SE3(trajectory.poses[-1]))
        return np.concatenate([trajectory.pi[-1] - nominal.pi[-1],
                               trajectory.qbar[-1] - nominal.qbar[-1],
                               trajectory.pbar[-1] - nominal.pbar[-1], theta])
    numeric = np.empty((n + 2 * m + n, size))
    for j in range(size):
        step = np.zeros(size)
        step[j] = EPS
        numeric[:, j] = (final(run(step)) - final(run(-step))) / (2 * EPS)
    reduced = sensitivity.reduced[-1]
    predicted = np.vstack([sensitivity.orbit_tangent[-1] @ reduced[:k], reduced[k:]])
    assert max(_column_errors(predicted, numeric)) <= RTOL
    assert np.allclose(sensitivity.reduced[0], np.eye(size), atol=1e-9)


def test_orbit_tangent_is_the_derivative_of_pi():
    robot, state, _ = _setup('paper')
    propagator, y0 = ReducedPropagator.from_full_state(robot, state)
    system = propagator.system
    y = y0.copy()
    y[:system.k] = [0.1, -0.2, 0.05, 0.3]
    system.chart = system.chart.recentred(y[:system.k])
    y[:system.k] = 0.0
    tangent = orbit_tangent(propagator, y)
    numeric = np.empty_like(tangent)
    for j in range(system.k):
        step = np.zeros(system.k)
        step[j] = 1e-6
        numeric[:, j] = (system.body_momentum(step) - system.body_momentum(-step)) / 2e-6
    assert np.allclose(tangent, numeric, rtol=1e-7, atol=1e-12)


def test_held_torque_of_the_wrong_shape_is_refused():
    robot, state, _ = _setup('paper')
    with pytest.raises(ValueError, match='held torque has shape'):
        flow_sensitivity(robot, state, TIMES, np.zeros(robot.m + 1))
