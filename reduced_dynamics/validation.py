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
The reduced model checked against full dynamics (REDUCED_MODEL.md section 9).

A scenario is an initial full state chosen so that mu falls in a given class of
Table 2, plus smooth joint torques. Both models start from the same state
and torques; the reduced trajectory's shape, reconstructed base pose and
pi(q~1) are compared with the full one, and mu is checked for constancy.
"""

from __future__ import annotations

from dataclasses import dataclass
import time
from typing import Optional, Sequence

import numpy as np
import pinocchio as pin

from reduced_dynamics.full_dynamics import FullDynamics
from reduced_dynamics.geometry.isotropy import MomentumClass
from reduced_dynamics.reduction.reconstruction import ReducedPropagator
from reduced_dynamics.reduction.second_stage import SecondStagePropagator
from reduced_dynamics.robot.model import RobotModel
from reduced_dynamics.robot.momentum import body_momentum_from_spatial
from reduced_dynamics.robot.state import FreeFloatingState, sinusoid_torque, TorqueLaw


@dataclass
class Scenario:
    """An initial full state and a joint-torque law."""

    name: str
    state: FreeFloatingState
    torque: TorqueLaw
    momentum_class: MomentumClass


def _momentum_of_class(robot: RobotModel, cls: MomentumClass,
                       rng: np.random.Generator) -> np.ndarray:
    wrench = rng.standard_normal(6)
    if cls is MomentumClass.PURE_ANGULAR:
        wrench[:3] = 0.0
    elif cls is MomentumClass.PURE_LINEAR:
        wrench[3:] = 0.0
    elif cls is MomentumClass.ZERO:
        wrench[:] = 0.0
    mu = robot.group.dual_coordinates(wrench)
    if cls is not MomentumClass.ZERO and np.linalg.norm(mu) == 0.0:
        raise ValueError(f'base group {robot.group.name} has no {cls.value} momentum')
    return mu


def random_scenario(robot: RobotModel, cls: MomentumClass, seed: int,
                    drift_speed: float = 0.05, shape_speed: float = 0.1,
                    shape_accel: float = 0.1, rotors: Sequence[int] = (),
                    rotor_speed: float = 5.0) -> Scenario:
    """
    Return a gentle random scenario whose momentum mu lies in class ``cls``.

    The shape starts within +-0.5 of zero (away from the gimbal lock of a
    spherical joint written as three revolutes), moving at about
    ``shape_speed``; mu is scaled so the drift twist I^-1 pi has norm
    ``drift_speed``; torques are sinusoids giving shape accelerations of about
    ``shape_accel`` (scaled by the reduced metric's diagonal). Joints listed in
    ``rotors`` (shape indices: reaction wheels) spin at about ``rotor_speed``.
    """
    rng = np.random.default_rng(seed)
    qbar = rng.uniform(-0.5, 0.5, robot.m)
    qbar_dot = shape_speed * rng.standard_normal(robot.m)
    rotors = list(rotors)
    qbar_dot[rotors] = rotor_speed * rng.uniform(-1.0, 1.0, len(rotors))
    quat = rng.standard_normal(4)
    rotation = pin.Quaternion(*(quat / np.linalg.norm(quat))).toRotationMatrix()
    g = robot.project_pose(pin.SE3(rotation, rng.uniform(-1.0, 1.0, 3)))
    blocks = robot.metric_blocks(qbar)
    mu = _momentum_of_class(robot, cls, rng)
    if cls is not MomentumClass.ZERO:
        drift = blocks.solve_locked(body_momentum_from_spatial(robot.group, g, mu))
        mu *= drift_speed / np.linalg.norm(drift)
    pi = body_momentum_from_spatial(robot.group, g, mu)
    xi = blocks.solve_locked(pi - blocks.coupling @ qbar_dot)
    amplitude = shape_accel * np.diag(blocks.reduced_metric) * rng.uniform(0.5, 1.0, robot.m)
    torque = sinusoid_torque(amplitude, rng.uniform(0.5, 2.0, robot.m),
                             rng.uniform(0.0, 2.0 * np.pi, robot.m))
    return Scenario(f'{cls.value} mu', FreeFloatingState(g, xi, qbar, qbar_dot), torque, cls)


def integration_sensitivity(robot: RobotModel, scenario: Scenario, duration: float,
                            samples: int = 51) -> float:
    """
    Largest shape difference between full runs at rtol 1e-9 and 1e-10 (rad).

    It estimates how much the integrator, not the model, limits any comparison:
    near a coordinate singularity (the gimbal lock of a spherical joint written
    as three revolutes) it grows by orders of magnitude. Measured on the wheel
    robot, runs at rtol 1e-12 are accurate to about 1e-3 of this figure.
    """
    times = np.linspace(0.0, duration, samples)
    dynamics = FullDynamics(robot, scenario.torque)
    coarse = dynamics.simulate(scenario.state, times, 1e-9, 1e-11).qbar
    fine = dynamics.simulate(scenario.state, times, 1e-10, 1e-12).qbar
    return float(np.max(np.abs(coarse - fine)))


def well_conditioned_scenario(robot: RobotModel, cls: MomentumClass, seed: int,
                              duration: float, attempts: int = 20,
                              max_sensitivity: float = 5e-7, **options) -> Scenario:
    """
    Return the first of seeds ``seed, seed + 1000, ...`` the integrator resolves well.

    A scenario is kept when :func:`integration_sensitivity` is at most
    ``max_sensitivity``: runs that graze a coordinate singularity are limited by
    the integrator in both models and say nothing about the reduction.
    """
    for attempt in range(attempts):
        scenario = random_scenario(robot, cls, seed + 1000 * attempt, **options)
        try:
            if integration_sensitivity(robot, scenario, duration) <= max_sensitivity:
                return scenario
        except RuntimeError:
            continue
    raise ValueError(f'no regular {cls.value} scenario in {attempts} attempts from seed {seed}')


@dataclass
class Comparison:
    """Agreement of the reduced model with full dynamics over one run."""

    scenario: str
    orbit_dim: int
    isotropy_dim: int
    duration: float
    mu_variation: float
    shape_error: float
    pose_error: float
    pi_error: float
    full_seconds: float
    reduced_seconds: float


def pose_distance(a: pin.SE3, b: pin.SE3) -> float:
    """|log6(a^-1 b)|: metres and radians together."""
    return float(np.linalg.norm(pin.log6(a.inverse() * b).vector))


def compare(robot: RobotModel, scenario: Scenario, duration: float = 10.0,
            samples: int = 101, rtol: float = 1e-12, atol: float = 1e-12,
            integrator: str = 'dop853', step: float = 1e-3) -> Comparison:
    """Run both models from the scenario and measure their disagreement."""
    times = np.linspace(0.0, duration, samples)
    start = time.perf_counter()
    full = FullDynamics(robot, scenario.torque).simulate(scenario.state, times, rtol, atol)
    middle = time.perf_counter()
    propagator, y0 = ReducedPropagator.from_full_state(robot, scenario.state, scenario.torque)
    reduced = propagator.propagate(y0, times, integrator, rtol, atol, step)
    end = time.perf_counter()
    mu0 = full.mu[0]
    # Errors in mu and pi are relative to the system's momentum scale max(|mu|, |M v|):
    # at mu = 0 a relative error is meaningless, and a small mu rides on large
    # internal momenta that set the integrator's absolute error.
    state = scenario.state
    momentum_scale = float(np.linalg.norm(robot.mass_matrix(state.qbar) @ np.concatenate(
        [state.xi, state.qbar_dot])))
    momentum_scale = max(momentum_scale, float(np.linalg.norm(mu0)))
    mu_variation = float(np.max(np.linalg.norm(full.mu - mu0, axis=1))) / momentum_scale
    pi_full = np.array([robot.group.Ad(full.pose(i)).T @ mu0 for i in range(samples)])
    pi_scale = max(float(np.max(np.linalg.norm(pi_full, axis=1))), momentum_scale) \
        if scenario.momentum_class is not MomentumClass.ZERO else momentum_scale
    pi_error = float(np.max(np.linalg.norm(pi_full - reduced.pi, axis=1))) / pi_scale
    return Comparison(
        scenario=scenario.name, orbit_dim=propagator.system.k,
        isotropy_dim=propagator.system.isotropy.dim, duration=duration,
        mu_variation=mu_variation,
        shape_error=float(np.max(np.abs(full.qbar - reduced.qbar))),
        pose_error=max(pose_distance(full.pose(i), reduced.pose(i)) for i in range(samples)),
        pi_error=pi_error, full_seconds=middle - start, reduced_seconds=end - middle)


def validation_table(robot: RobotModel, duration: float = 10.0, seed: int = 0,
                     classes: Optional[list[MomentumClass]] = None,
                     rtol: float = 1e-12) -> list[Comparison]:
    """Compare reduced and full dynamics for each momentum class the base group has."""
    from reduced_dynamics.reduction.lean_field import warm_up
    warm_up()  # the table times the runs: not the compiled kernels' first load
    rows = []
    for index, cls in enumerate(classes or list(MomentumClass)):
        try:
            scenario = well_conditioned_scenario(robot, cls, seed + index, duration)
        except ValueError:
            continue
        rows.append(compare(robot, scenario, duration, rtol=rtol, atol=rtol))
    return rows


def format_table(rows: list[Comparison]) -> str:
    """Return a plain-text table of comparisons."""
    header = (f'{"momentum":<14}{"dim G_mu":>9}{"k":>3}{"mu drift":>11}{"shape err":>11}'
              f'{"pose err":>11}{"pi err":>11}{"full s":>8}{"red s":>8}')
    lines = [header, '-' * len(header)]
    for r in rows:
        lines.append(f'{r.scenario:<14}{r.isotropy_dim:>9}{r.orbit_dim:>3}'
                     f'{r.mu_variation:>11.1e}{r.shape_error:>11.1e}{r.pose_error:>11.1e}'
                     f'{r.pi_error:>11.1e}{r.full_seconds:>8.2f}{r.reduced_seconds:>8.2f}')
    return '\n'.join(lines)


@dataclass
class SecondStageComparison:
    """Agreement of the second-stage model (Theorem 57) with full dynamics and stage one."""

    scenario: str
    cyclic_joints: tuple[str, ...]
    duration: float
    shape_error: float
    first_stage_shape_error: float
    cyclic_angle_error: float
    pose_error: float
    theta_torque_error: float
    theta_full_error: float
    full_seconds: float
    first_seconds: float
    second_seconds: float


def cyclic_momenta(robot: RobotModel, state: FreeFloatingState,
                   cyclic: np.ndarray) -> np.ndarray:
    """theta: the rows of M v of the cyclic joints (their conjugate momenta)."""
    velocity = np.concatenate([state.xi, state.qbar_dot])
    return (robot.mass_matrix(state.qbar) @ velocity)[robot.n + cyclic]


def _torque_impulse(torque: TorqueLaw, full_states: list[FreeFloatingState],
                    times: np.ndarray, cyclic: np.ndarray, substeps: int = 64) -> np.ndarray:
    """Integral of the cyclic torques from times[0] to each sample (composite Simpson)."""
    impulse = [np.zeros(len(cyclic))]
    for index in range(1, len(times)):
        grid = np.linspace(times[index - 1], times[index], 2 * substeps + 1)
        state = full_states[index - 1]
        values = np.array([torque(t, state.qbar, state.qbar_dot)[cyclic] for t in grid])
        weights = np.ones(len(grid))
        weights[1:-1:2], weights[2:-1:2] = 4.0, 2.0
        step = (grid[-1] - grid[0]) / (len(grid) - 1)
        impulse.append(impulse[-1] + step / 3.0 * (weights @ values))
    return np.array(impulse)


def compare_second_stage(robot: RobotModel, scenario: Scenario, cyclic_joints: Sequence[str],
                         duration: float = 10.0, samples: int = 101, rtol: float = 1e-12,
                         atol: float = 1e-12) -> SecondStageComparison:
    """
    Run full dynamics, stage one (Thm 54) and stage two (Thm 57) from one state.

    ``theta_torque_error`` compares theta(t) with theta(0) + the integral of the
    wheel torques (exact for state-independent torque laws such as the scenarios').
    """
    times = np.linspace(0.0, duration, samples)
    start = time.perf_counter()
    full = FullDynamics(robot, scenario.torque).simulate(scenario.state, times, rtol, atol)
    after_full = time.perf_counter()
    first, y1 = ReducedPropagator.from_full_state(robot, scenario.state, scenario.torque)
    stage_one = first.propagate(y1, times, 'dop853', rtol, atol)
    after_first = time.perf_counter()
    second, y2 = SecondStagePropagator.from_full_state(robot, scenario.state, cyclic_joints,
                                                       scenario.torque)
    stage_two = second.propagate(y2, times, rtol, atol)
    end = time.perf_counter()
    split = second.system.split_indices
    states = [full.state(i) for i in range(samples)]
    theta_full = np.array([cyclic_momenta(robot, s, split.cyclic) for s in states])
    impulse = _torque_impulse(scenario.torque, states, times, split.cyclic)
    scale = max(float(np.max(np.abs(theta_full))), 1e-300)
    return SecondStageComparison(
        scenario=scenario.name, cyclic_joints=split.names, duration=duration,
        shape_error=float(np.max(np.abs(full.qbar[:, split.kept]
                                        - stage_two.qbar[:, split.kept]))),
        first_stage_shape_error=float(np.max(np.abs(full.qbar[:, split.kept]
                                                    - stage_one.qbar[:, split.kept]))),
        cyclic_angle_error=float(np.max(np.abs(full.qbar[:, split.cyclic]
                                               - stage_two.qbar[:, split.cyclic]))),
        pose_error=max(pose_distance(full.pose(i), stage_two.pose(i)) for i in range(samples)),
        theta_torque_error=float(np.max(np.abs(stage_two.theta - stage_two.theta[0] - impulse)))
        / scale,
        theta_full_error=float(np.max(np.abs(stage_two.theta - theta_full))) / scale,
        full_seconds=after_full - start, first_seconds=after_first - after_full,
        second_seconds=end - after_first)


def second_stage_table(robot: RobotModel, cyclic_joints: Sequence[str],
                       duration: float = 10.0, seed: int = 0,
                       classes: Optional[list[MomentumClass]] = None,
                       rtol: float = 1e-12) -> list[SecondStageComparison]:
    """Compare stage two with full dynamics (and stage one) for each momentum class."""
    names = list(robot.shape_joint_names)
    rotors = [names.index(name) for name in cyclic_joints]
    rows = []
    for index, cls in enumerate(classes or list(MomentumClass)):
        try:
            scenario = well_conditioned_scenario(robot, cls, seed + index, duration,
                                                 rotors=rotors)
        except ValueError:
            continue
        rows.append(compare_second_stage(robot, scenario, cyclic_joints, duration,
                                         rtol=rtol, atol=rtol))
    return rows


def format_second_stage_table(rows: list[SecondStageComparison]) -> str:
    """Return a plain-text table of second-stage comparisons."""
    header = (f'{"momentum":<14}{"shape err":>11}{"stage 1":>11}{"wheel err":>11}'
              f'{"pose err":>11}{"theta-tau":>11}{"theta-full":>11}{"full s":>8}'
              f'{"st1 s":>8}{"st2 s":>8}')
    lines = [header, '-' * len(header)]
    for r in rows:
        lines.append(f'{r.scenario:<14}{r.shape_error:>11.1e}{r.first_stage_shape_error:>11.1e}'
                     f'{r.cyclic_angle_error:>11.1e}{r.pose_error:>11.1e}'
                     f'{r.theta_torque_error:>11.1e}{r.theta_full_error:>11.1e}'
                     f'{r.full_seconds:>8.2f}{r.first_seconds:>8.2f}{r.second_seconds:>8.2f}')
    return '\n'.join(lines)
