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

"""The compiled reduced right-hand side (lean_field.py) against the reference routes."""

import numpy as np
import pinocchio as pin
import pytest

from conftest_robots import ROBOTS
from reduced_dynamics.estimator.core import lie
from reduced_dynamics.geometry.isotropy import MomentumClass
from reduced_dynamics.reduction import lean_field
from reduced_dynamics.reduction.reconstruction import ReducedPropagator
from reduced_dynamics.validation import random_scenario

CASES = [(name, cls) for name in sorted(ROBOTS) for cls in MomentumClass]


def _reference_rhs(propagator, t, y):
    """Return the propagator's field as it was: vector_field, then Jr(eta)^-1 xi by Pinocchio."""
    nz = propagator.nz
    out = np.empty(y.shape)
    law = propagator.torque
    _, xi = propagator.system.vector_field(y[:nz], lambda q, qd: law(t, q, qd), out)
    out[nz:] = propagator.group.right_jacobian_inverse(y[nz:]) @ xi
    return out


@pytest.mark.parametrize('name, cls', CASES)
def test_lean_rhs_equals_vector_field(name, cls):
    # Every base group and momentum class, off the chart centres, and again after a
    # re-centring (the chart constants are read afresh).
    robot = ROBOTS[name]()
    scenario = random_scenario(robot, cls, 2, drift_speed=0.3, shape_speed=0.5)
    propagator, y0 = ReducedPropagator.from_full_state(robot, scenario.state, scenario.torque)
    rng = np.random.default_rng(5)
    for _ in range(2):
        y = y0 + 0.2 * rng.standard_normal(y0.size)
        lean = propagator.rhs(0.7, y)
        reference = _reference_rhs(propagator, 0.7, y)
        assert np.abs(lean - reference).max() <= 1e-11 * (1.0 + np.abs(reference).max())
        observed = propagator.observe(0.7, y)
        pi, _, qbar_dot, energy = propagator.system.kinematics(y[:propagator.nz])
        n, m = robot.n, robot.m
        assert np.allclose(observed[16:16 + n], pi, rtol=1e-12, atol=1e-14)
        assert np.allclose(observed[16 + n + m:16 + n + 2 * m], qbar_dot, rtol=1e-11,
                           atol=1e-13)
        assert abs(observed[-1] - energy) <= 1e-12 * (1.0 + abs(energy))
        y0 = propagator.recentre(y)


@pytest.mark.parametrize('scale', [0.0, 1e-9, 1e-5, 0.05, 0.3, 0.8])
def test_se3_jacobians_equal_pinocchio(scale):
    # Jl(x) = Jexp6(-x) and Jr(x)^-1 = Jlog6(exp6(x)) (rotations below pi). Around 1e-3
    # rad Pinocchio's closed forms lose ~1e-10 to cancellation (checked against a
    # 40-digit reference when this was written), so that range is left out here.
    rng = np.random.default_rng(int(1e3 * scale) + 1)
    for _ in range(5):
        twist = scale * rng.standard_normal(6)
        assert np.abs(lean_field.left_jacobian6(twist) - pin.Jexp6(-twist)).max() <= 1e-13
        assert np.abs(lean_field.right_jacobian6_inverse(twist)
                      - pin.Jlog6(pin.exp6(twist))).max() <= 1e-13


@pytest.mark.parametrize('scale', [0.0, 1e-9, 1e-5, 1e-3, 0.3, 3.0])
def test_chart_exp_is_the_estimator_cores_exp6(scale):
    # chi = exp(S C q~1) g_ref takes exp6's closed form from the estimator core (one copy
    # of its series and closed-form branches): the core's exp6 then compose to round-off
    # (the sums run in another order), on both sides of the 1e-4 rad switch.
    rng = np.random.default_rng(int(1e3 * scale) + 7)
    reference = pin.exp6(rng.standard_normal(6)).homogeneous
    out, scratch = np.empty((4, 4)), np.empty((lean_field.SCRATCH3, 3, 3))
    for _ in range(5):
        twist = np.r_[rng.standard_normal(3), scale * rng.standard_normal(3)]
        lean_field._exp_times(twist, reference, out, scratch)
        assert np.abs(out - lie.compose(lie.exp6(twist), reference)).max() <= 1e-14
        t2 = float(twist[3:] @ twist[3:])
        if t2 > 1e-4:
            t = np.sqrt(t2)
            assert np.allclose(lie.exp6_coefficients(t2),
                               (np.sin(t) / t, (1 - np.cos(t)) / t2, (t - np.sin(t)) / t2 / t),
                               rtol=1e-13, atol=0.0)


def test_left_jacobian_small_angle_matches_its_definition():
    # exp(x + d) exp(x)^-1 = exp(Jl d): central differences at 1 mrad, where the series
    # branch is used (Pinocchio's Jexp6 is itself off by ~1e-10 there).
    twist = 1e-3 * np.array([0.3, -0.5, 0.2, 0.6, -0.4, 0.5])
    base = pin.exp6(twist)
    numeric = np.empty((6, 6))
    h = 1e-6
    for j in range(6):
        step = np.zeros(6)
        step[j] = h
        plus = pin.log6(pin.exp6(twist + step) * base.inverse()).vector
        minus = pin.log6(pin.exp6(twist - step) * base.inverse()).vector
        numeric[:, j] = (plus - minus) / (2.0 * h)
    assert np.abs(lean_field.left_jacobian6(twist) - numeric).max() <= 1e-9


def test_not_positive_definite_mass_is_reported():
    robot = ROBOTS['paper']()
    scenario = random_scenario(robot, MomentumClass.GENERIC, 0)
    propagator, y0 = ReducedPropagator.from_full_state(robot, scenario.state)
    field = propagator._lean_field()
    bad = -np.eye(robot.n + robot.m)
    ok = lean_field.momenta_kernel(
        y0[:field.k], y0[field.k + field.m:field.nz], bad, True, field.chart_twist, field.g_ref,
        field.mu6, field.basis, field.whole, field.factor, field.twist, field.chi, field.pi,
        field.drift, field.connection, field.v, field.s3)
    assert not ok


@pytest.mark.parametrize('name, cls', CASES)
def test_lean_evaluation_equals_theorem_54_evaluation(name, cls):
    # What the discrete gradient integrates: H~, its gradient and the structure matrix.
    robot = ROBOTS[name]()
    scenario = random_scenario(robot, cls, 4, drift_speed=0.3, shape_speed=0.5)
    propagator, y0 = ReducedPropagator.from_full_state(robot, scenario.state)
    z = y0[:propagator.nz] + 0.2 * np.random.default_rng(8).standard_normal(propagator.nz)
    energy, gradient, structure = propagator._lean_field().evaluate(z)
    reference = propagator.system.evaluate(z, np.zeros(robot.m))
    assert abs(energy - reference.energy) <= 1e-13 * (1.0 + abs(reference.energy))
    assert np.abs(gradient - reference.gradient).max() <= 1e-12 * (
        1.0 + np.abs(reference.gradient).max())
    assert np.abs(structure - reference.structure).max() <= 1e-12 * (
        1.0 + np.abs(reference.structure).max())
    assert abs(propagator._lean_field().energy(z) - propagator.system.hamiltonian(z)) <= \
        1e-13 * (1.0 + abs(reference.energy))


def test_discrete_gradient_steps_as_with_the_reference_evaluation():
    # The compiled route and the explicit one converge to the same fixed point.
    from reduced_dynamics.integrators import DiscreteGradient
    robot = ROBOTS['paper']()
    scenario = random_scenario(robot, MomentumClass.GENERIC, 0)
    times = np.linspace(0.0, 1.0, 11)
    propagator, y0 = ReducedPropagator.from_full_state(robot, scenario.state, scenario.torque)
    lean = propagator.propagate(y0, times, 'discrete_gradient', step=0.05)
    system = propagator.system
    reference, y = ReducedPropagator.from_full_state(robot, scenario.state, scenario.torque)
    system = reference.system

    def evaluate(z):
        evaluation = system.evaluate(z, np.zeros(system.m))
        return evaluation.energy, evaluation.gradient, evaluation.structure

    def forcing(t, z):
        out = np.zeros_like(z)
        qbar_dot = system.kinematics(z)[2]
        out[system.k:system.k + system.m] = scenario.torque(t, system.split(z)[1], qbar_dot)
        return out
    reference.fixed_step_integrator = lambda: DiscreteGradient(evaluate, system.hamiltonian,
                                                               forcing)
    explicit = reference.propagate(y, times, 'discrete_gradient', step=0.05)
    assert np.abs(lean.qbar - explicit.qbar).max() <= 1e-11
    assert np.abs(lean.poses - explicit.poses).max() <= 1e-11
