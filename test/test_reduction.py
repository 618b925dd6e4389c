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

"""The reduced system: derivatives, magnetic term, paper form vs bundle form."""

import numpy as np
import pytest

from conftest_robots import ROBOTS
from reduced_dynamics.geometry.isotropy import MomentumClass
from reduced_dynamics.reduction.magnetic import magnetic_form_corollary55
from reduced_dynamics.reduction.vector_field import bundle_vector_field, ReducedSystem
from reduced_dynamics.robot.momentum import kinetic_energy
from reduced_dynamics.validation import random_scenario

CASES = [(name, cls) for name in sorted(ROBOTS) for cls in MomentumClass]


def _system(name, cls, seed=0, offset=0.3):
    robot = ROBOTS[name]()
    scenario = random_scenario(robot, cls, seed, drift_speed=0.3, shape_speed=0.5)
    system, z = ReducedSystem.from_full_state(robot, scenario.state)
    rng = np.random.default_rng(seed)
    z[:system.k] = offset * rng.standard_normal(system.k)
    return robot, system, z


@pytest.mark.parametrize('name, cls', CASES)
def test_paper_form_equals_bundle_form(name, cls):
    robot, system, z = _system(name, cls)
    tau = np.random.default_rng(9).standard_normal(robot.m)
    evaluation = system.evaluate(z, tau)
    q1, qbar, pbar = system.split(z)
    pi_dot, qbar_dot, pbar_dot, xi = bundle_vector_field(robot, evaluation.pi, qbar, pbar, tau)
    scale = 1.0 + np.abs(pbar_dot).max()
    assert np.abs(evaluation.z_dot[system.k + robot.m:] - pbar_dot).max() <= 1e-10 * scale
    assert np.allclose(evaluation.z_dot[system.k:system.k + robot.m], qbar_dot, atol=1e-12)
    # The orbit chart moves pi exactly as pi_dot = ad_xi^T pi does.
    jac = system.chart.body_jacobian(q1)
    chart_pi_dot = robot.group.ad(jac @ evaluation.z_dot[:system.k]).T @ evaluation.pi
    assert np.abs(chart_pi_dot - pi_dot).max() <= 1e-10 * (1.0 + np.abs(pi_dot).max())


@pytest.mark.parametrize('name, cls', CASES)
def test_fast_vector_field_equals_theorem_54_evaluation(name, cls):
    # vector_field (Coriolis matrix, contracted magnetic terms) is what the propagator
    # integrates; evaluate (explicit U, the signs validated against full dynamics) is
    # the reference. Also after a re-centring (the cached chart constants change).
    robot, system, z = _system(name, cls, seed=3)
    rng = np.random.default_rng(5)
    for _ in range(2):
        tau = rng.standard_normal(robot.m)
        evaluation = system.evaluate(z, tau)
        z_dot, xi = system.vector_field(z, tau)
        assert np.abs(z_dot - evaluation.z_dot).max() <= 1e-12 * (1 + np.abs(z_dot).max())
        assert np.abs(xi - evaluation.xi).max() <= 1e-13 * (1 + np.abs(xi).max())
        pi, xi_k, qbar_dot, energy = system.kinematics(z)
        assert np.allclose(pi, evaluation.pi, rtol=0, atol=1e-13)
        assert np.allclose(xi_k, evaluation.xi, rtol=0, atol=1e-13)
        assert np.allclose(qbar_dot, evaluation.terms.qbar_dot, rtol=0, atol=1e-13)
        assert np.isclose(energy, evaluation.energy, rtol=1e-13)
        z = system.recentre(z)
        z[:system.k] = 0.2 * rng.standard_normal(system.k)


@pytest.mark.parametrize('name, cls', CASES)
def test_gradient_and_magnetic_form_match_finite_differences(name, cls):
    robot, system, z = _system(name, cls, seed=1)
    evaluation = system.evaluate(z, np.zeros(robot.m))
    eps = 1e-6
    eye = np.eye(z.size)
    fd_grad = np.array([(system.hamiltonian(z + eps * e) - system.hamiltonian(z - eps * e))
                        / (2 * eps) for e in eye])
    assert np.abs(fd_grad - evaluation.gradient).max() <= 1e-6 * (1 + np.abs(fd_grad).max())

    def one_form(x):
        q1, qbar = x[:system.k], x[system.k:]
        pi = system.body_momentum(q1)
        jac = system.chart.body_jacobian(q1)
        return np.r_[jac.T @ pi, robot.metric_blocks(qbar).connection.T @ pi]
    x = z[:system.k + robot.m]
    d = np.array([(one_form(x + eps * e) - one_form(x - eps * e)) / (2 * eps)
                  for e in np.eye(x.size)])
    fd_form = d - d.T
    form = evaluation.structure[:x.size, :x.size]
    assert np.abs(fd_form - form).max() <= 1e-6 * (1 + np.abs(fd_form).max())


@pytest.mark.parametrize('name', sorted(ROBOTS))
def test_reduced_hamiltonian_is_the_energy(name):
    robot, system, z = _system(name, MomentumClass.GENERIC, seed=2, offset=0.0)
    evaluation = system.evaluate(z, np.zeros(robot.m))
    blocks = evaluation.terms.blocks
    energy = kinetic_energy(blocks, evaluation.xi, evaluation.terms.qbar_dot) \
        + robot.potential_energy(z[system.k:system.k + robot.m])
    assert np.isclose(evaluation.energy, energy, rtol=1e-12)
    assert np.isclose(system.hamiltonian(z), energy, rtol=1e-12)


def test_corollary_55_formula_when_isotropy_is_whole_group():
    # A planar base with purely angular momentum: G_mu = SE(2) = G, k = 0, mu != 0.
    robot, system, z = _system('planar', MomentumClass.PURE_ANGULAR, offset=0.0)
    assert system.k == 0 and np.linalg.norm(system.mu) > 0
    qbar = z[:robot.m]
    eps = 1e-6
    derivative = np.array([
        (robot.metric_blocks(qbar + eps * e).connection
         - robot.metric_blocks(qbar - eps * e).connection) / (2 * eps)
        for e in np.eye(robot.m)])
    blocks = robot.metric_blocks(qbar)
    xi_540 = magnetic_form_corollary55(robot.group, system.mu, blocks.connection, derivative)
    form = system.evaluate(z, np.zeros(robot.m)).structure[:robot.m, :robot.m]
    assert np.abs(xi_540 - form).max() <= 1e-7 * (1 + np.abs(form).max())
    assert np.abs(form).max() > 1e-6  # the magnetic term is really there


def test_zero_momentum_has_no_magnetic_term():
    robot, system, z = _system('paper', MomentumClass.ZERO)
    assert system.k == 0
    assert np.abs(system.evaluate(z, np.zeros(robot.m)).structure[:robot.m, :robot.m]).max() \
        < 1e-12
