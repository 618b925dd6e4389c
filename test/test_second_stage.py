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

"""Second-stage reduction (Theorem 57) against full dynamics and the first stage."""

import functools

import numpy as np
import pytest

from conftest_robots import paper_robot
from reduced_dynamics.cli import main
from reduced_dynamics.geometry.isotropy import MomentumClass
from reduced_dynamics.reduction.second_stage import (CyclicSplit, second_stage_terms,
                                                     SecondStagePropagator, SecondStageSystem)
from reduced_dynamics.resources import config_path
from reduced_dynamics.robot.model import load_robot, ModelError
from reduced_dynamics.robot.momentum import kinetic_energy
from reduced_dynamics.robot.state import zero_torque
from reduced_dynamics.validation import (compare_second_stage, cyclic_momenta,
                                         well_conditioned_scenario)

WHEELS = ('wheel_x', 'wheel_y', 'wheel_z')
ROTORS = [6, 7, 8]


@functools.lru_cache(maxsize=None)
def wheel_robot():
    """Return the paper robot with three reaction wheels."""
    return load_robot(str(config_path('robots/paper_robot_wheels.urdf')))


def scenario(cls=MomentumClass.GENERIC, seed=0, duration=10.0):
    """Return a regular scenario with spinning wheels and torques on every joint."""
    return well_conditioned_scenario(wheel_robot(), cls, seed, duration, rotors=ROTORS)


@pytest.mark.parametrize('cls', [MomentumClass.GENERIC, MomentumClass.ZERO])
def test_second_stage_matches_full_dynamics_over_10_s_with_wheel_torques(cls):
    run = scenario(cls)
    assert np.all(np.abs(run.torque(0.3, None, None)[ROTORS]) > 0.0)
    result = compare_second_stage(wheel_robot(), run, WHEELS, 10.0, samples=51)
    assert result.shape_error <= 1e-8
    assert result.cyclic_angle_error <= 1e-8
    assert result.pose_error <= 1e-7
    # theta exactly as the wheel torques dictate, and equal to the full system's.
    assert result.theta_torque_error <= 1e-12
    assert result.theta_full_error <= 1e-12
    # the same agreement as the first stage on the joints both keep.
    assert result.shape_error <= 3.0 * result.first_stage_shape_error + 1e-10


def test_hamiltonian_is_the_kinetic_energy_and_is_conserved_without_torques():
    robot = wheel_robot()
    state = scenario().state
    propagator, y0 = SecondStagePropagator.from_full_state(robot, state, WHEELS)
    system = propagator.system
    energy = kinetic_energy(robot.metric_blocks(state.qbar), state.xi, state.qbar_dot)
    assert system.hamiltonian(y0[:system.nz]) == pytest.approx(energy, rel=1e-13)
    run = propagator.propagate(y0, np.linspace(0.0, 2.0, 11))
    assert np.max(np.abs(run.energy - energy)) <= 1e-10 * energy
    assert np.max(np.abs(run.theta - run.theta[0])) == 0.0


def test_full_state_round_trip():
    robot = wheel_robot()
    state = scenario(MomentumClass.PURE_ANGULAR).state
    system, z = SecondStageSystem.from_full_state(robot, state, WHEELS)
    back = system.full_state(z, state.g, state.qbar[ROTORS])
    np.testing.assert_allclose(back.qbar, state.qbar, atol=1e-15)
    np.testing.assert_allclose(back.qbar_dot, state.qbar_dot, atol=1e-12)
    np.testing.assert_allclose(back.xi, state.xi, atol=1e-12)
    theta = cyclic_momenta(robot, state, np.array(ROTORS))
    np.testing.assert_allclose(system.split(z)[3], theta, rtol=1e-14)


def test_derivatives_against_finite_differences():
    robot = wheel_robot()
    state = scenario().state
    system, z = SecondStageSystem.from_full_state(robot, state, WHEELS)
    split = system.split_indices
    q1, qhat, phat, theta = system.split(z)
    pi_e = np.concatenate([system.body_momentum(q1), theta])
    terms = second_stage_terms(robot, split, pi_e, qhat, phat)
    h = 1e-6

    def energy(q):
        return second_stage_terms(robot, split, pi_e, q, phat).energy

    def one_form(q):
        # A_e^T pi_e: the pulled-back connection form on the kept shape.
        return second_stage_terms(robot, split, pi_e, q, phat).blocks.connection.T @ pi_e
    gradient = np.zeros(split.mk)
    jacobian = np.zeros((split.mk, split.mk))
    for i in range(split.mk):
        step = np.zeros(split.mk)
        step[i] = h
        gradient[i] = (energy(qhat + step) - energy(qhat - step)) / (2 * h)
        jacobian[i] = (one_form(qhat + step) - one_form(qhat - step)) / (2 * h)
    np.testing.assert_allclose(terms.dH_dqhat, gradient, atol=1e-7 * np.abs(gradient).max())
    curvature = jacobian - jacobian.T
    np.testing.assert_allclose(terms.curvature, curvature, atol=1e-7 * np.abs(curvature).max())


def test_vector_field_does_not_depend_on_the_cyclic_angles():
    robot = wheel_robot()
    run = scenario()
    system, z = SecondStageSystem.from_full_state(robot, run.state, WHEELS)
    tau = np.linspace(-1.0, 1.0, robot.m)
    base = system.evaluate(z, tau, np.zeros(3)).z_dot
    turned = system.evaluate(z, tau, np.array([1.0, -2.0, 3.0])).z_dot
    np.testing.assert_array_equal(base, turned)
    # theta_dot is the wheel torque; the kept momentum feels its reaction.
    np.testing.assert_array_equal(base[-3:], tau[ROTORS])
    free = system.evaluate(z, np.zeros(robot.m)).z_dot
    assert np.all(free[-3:] == 0.0) and np.linalg.norm(free - base) > 0.0


def test_bad_cyclic_joints_are_refused_with_the_reason():
    robot = wheel_robot()
    with pytest.raises(ModelError, match='unknown cyclic joint'):
        CyclicSplit(robot, ['wheel_w'])
    with pytest.raises(ModelError, match='j4 cannot be reduced: not cyclic: its centre of mass'):
        CyclicSplit(robot, ['wheel_x', 'j4'])
    with pytest.raises(ModelError, match='listed twice'):
        CyclicSplit(robot, ['wheel_x', 'wheel_x'])
    state = scenario().state
    with pytest.raises(ModelError, match='at least one cyclic joint'):
        SecondStageSystem(robot, [], np.zeros(6), state.g)
    with pytest.raises(ModelError):
        SecondStagePropagator.from_full_state(paper_robot(), state, WHEELS, zero_torque(9))


def test_validate_command_covers_the_second_stage(capsys):
    urdf = str(config_path('robots/paper_robot_wheels.urdf'))
    assert main(['validate', '--urdf', urdf, '--duration', '1']) == 0
    out = capsys.readouterr().out
    assert 'second stage (Theorem 57) by the cyclic joints wheel_x, wheel_y, wheel_z' in out
    assert 'PASS: second-stage model agrees with full dynamics' in out
    assert main(['validate', '--duration', '1']) == 0
    assert 'second stage' not in capsys.readouterr().out


def test_replay_with_the_second_stage(tmp_path, capsys):
    from reduced_dynamics.bag import open_bag
    from reduced_dynamics.simulator import simulate_bag, SimulationOptions
    robot = wheel_robot()
    simulate_bag(robot, tmp_path / 'in', SimulationOptions(duration=1.0, rate=100.0))
    urdf = str(config_path('robots/paper_robot_wheels.urdf'))
    args = ['replay', str(tmp_path / 'in'), '-o', str(tmp_path / 'out'), '--urdf', urdf,
            '--quiet', '--cyclic-joints', 'auto']
    assert main(args) == 0
    out = capsys.readouterr().out
    assert 'second stage (Theorem 57) by the cyclic joints wheel_x, wheel_y, wheel_z' in out
    with open_bag(str(tmp_path / 'out')) as reader:
        assert reader.topics()['/reduced_dynamics/cyclic_momenta'] == \
            'sensor_msgs/msg/JointState'
    args[3] = str(tmp_path / 'out2')
    args[-1] = 'wheel_x,j3'
    assert main(args) == 2
    assert 'joint j3 cannot be reduced: not cyclic' in capsys.readouterr().err


@pytest.mark.parametrize('cls', list(MomentumClass))
def test_coriolis_vector_field_equals_the_magnetic_form_one(cls):
    robot = wheel_robot()
    run = scenario(cls, duration=1.0)
    system, z = SecondStageSystem.from_full_state(robot, run.state, WHEELS)
    z = z + 0.01 * np.sin(np.arange(len(z)))  # off the chart centre too
    tau = np.linspace(-1.0, 1.0, robot.m)
    reference = system.evaluate(z, tau)
    z_dot, xi, rates = system.vector_field(z, tau)
    scale = np.abs(reference.z_dot).max()
    np.testing.assert_allclose(z_dot, reference.z_dot, atol=1e-11 * scale)
    np.testing.assert_allclose(xi, reference.xi, atol=1e-12)
    np.testing.assert_allclose(rates, reference.cyclic_rate, atol=1e-12)
