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

"""Prediction modes: planned trajectories, prescribed-shape reconstruction, deferred jobs."""

import threading

from conftest_robots import paper_robot, tree_robot
import numpy as np
import pinocchio as pin
import pytest
from sim_samples import NOISE_FREE, samples

from reduced_dynamics.estimator import Estimator, EstimatorConfig
from reduced_dynamics.full_dynamics import PrescribedShapeDynamics
from reduced_dynamics.messages.samples import JointTrajectorySample
from reduced_dynamics.reduction.prescribed import attitude_angles, PrescribedReconstruction
from reduced_dynamics.reduction.shape_path import HeldVelocityPath, PlannedPath
from reduced_dynamics.robot.momentum import momentum_map

ROBOTS = {'paper': paper_robot, 'tree': tree_robot}


def _plan(m, seed=1, kind='cubic', seconds=10.0, points=11):
    rng = np.random.default_rng(seed)
    times = np.linspace(0.0, seconds, points)
    positions = 0.4 * rng.standard_normal((points, m))
    velocities = 0.2 * rng.standard_normal((points, m))
    velocities[0] = velocities[-1] = 0.0
    accelerations = 0.1 * rng.standard_normal((points, m))
    return times, positions, (velocities if kind != 'linear' else None), \
        (accelerations if kind == 'quintic' else None)


def _start(robot, path, g0, xi0):
    q0, qd0, _ = path(0.0)
    mass = robot.mass_matrix(q0)
    n = robot.n
    pi = mass[:n, :n] @ xi0 + mass[:n, n:] @ qd0
    return momentum_map(robot.group, g0, pi)


G0 = pin.SE3(pin.exp3(np.array([0.1, 0.2, -0.3])), np.array([1.0, 2.0, 3.0]))
XI0 = np.array([0.01, -0.02, 0.03, 0.02, -0.01, 0.015])


@pytest.mark.parametrize('kind', ['linear', 'cubic', 'quintic'])
def test_planned_path_interpolates_like_the_trajectory_controller(kind):
    times, positions, velocities, accelerations = _plan(3, kind=kind, points=5, seconds=2.0)
    path = PlannedPath(times, positions, velocities, accelerations)
    assert path.interpolation == kind
    for i, t in enumerate(times[:-1]):
        q, qd, qdd = path(t)
        np.testing.assert_allclose(q, positions[i], atol=1e-14)
        if velocities is not None:
            np.testing.assert_allclose(qd, velocities[i], atol=1e-13)
        if accelerations is not None:
            np.testing.assert_allclose(qdd, accelerations[i], atol=1e-12)
        # The end of each segment meets the next waypoint.
        left, _ = path.velocity_limits(times[i + 1])
        if velocities is not None:
            np.testing.assert_allclose(left, velocities[i + 1], atol=1e-12)
    # Derivatives are those of the position polynomial (central differences).
    t, h = 0.7, 1e-5
    q_plus, q_minus = path(t + h)[0], path(t - h)[0]
    np.testing.assert_allclose((q_plus - q_minus) / (2 * h), path(t)[1], atol=1e-8)
    # After the last waypoint the controller holds its positions.
    q, qd, _ = path(5.0)
    np.testing.assert_allclose(q, positions[-1])
    assert not qd.any()


@pytest.mark.parametrize('robot_name', sorted(ROBOTS))
@pytest.mark.parametrize('kind', ['linear', 'cubic', 'quintic'])
def test_predicted_base_pose_matches_prescribed_full_dynamics(robot_name, kind):
    # Acceptance (issue 13): a 10 s plan played with the exact shape path by the full
    # dynamics; the reconstruction alone predicts the base to 1e-6 m and 1e-6 rad.
    robot = ROBOTS[robot_name]()
    path = PlannedPath(*_plan(robot.m, kind=kind))
    mu = _start(robot, path, G0, XI0)
    times = np.linspace(0.0, 10.0, 201)
    full = PrescribedShapeDynamics(robot, path).simulate(G0, XI0, times)
    predicted = PrescribedReconstruction(robot, mu, G0, path).propagate(
        times, 1e-10, 1e-12, path.breakpoints)
    position = np.abs(full.poses[:, :3, 3] - predicted.poses[:, :3, 3]).max()
    attitude = max(np.linalg.norm(pin.log3(a[:3, :3].T @ b[:3, :3]))
                   for a, b in zip(full.poses, predicted.poses))
    assert position <= 1e-6 and attitude <= 1e-6
    # The full model keeps mu (a check that the ground truth is one).
    assert np.abs(full.mu - mu).max() <= 1e-7 * max(1.0, np.abs(mu).max())
    assert attitude_angles(full.poses[0, :3, :3], full.poses[:, :3, :3]).max() > 1e-2


@pytest.mark.parametrize('robot_name', sorted(ROBOTS))
def test_geometric_phase_alone_equals_the_zero_momentum_motion(robot_name):
    robot = ROBOTS[robot_name]()
    path = PlannedPath(*_plan(robot.m, kind='quintic'))
    mu = _start(robot, path, G0, XI0)
    assert np.linalg.norm(mu) > 1.0
    times = np.linspace(0.0, 10.0, 101)
    predicted = PrescribedReconstruction(robot, mu, G0, path).propagate(
        times, 1e-10, 1e-12, path.breakpoints)
    # Zero momentum: xi0 = -A qbar_dot0, the same plan, the full dynamics.
    q0, qd0, _ = path(0.0)
    mass = robot.mass_matrix(q0)
    xi_zero = -np.linalg.solve(mass[:6, :6], mass[:6, 6:] @ qd0)
    zero = PrescribedShapeDynamics(robot, path).simulate(G0, xi_zero, times)
    assert np.abs(zero.mu).max() <= 1e-7  # the integrator keeps mu = 0
    np.testing.assert_allclose(predicted.phase_poses[:, :3, 3], zero.poses[:, :3, 3],
                               atol=1e-6)
    angles = [np.linalg.norm(pin.log3(a[:3, :3].T @ b[:3, :3]))
              for a, b in zip(predicted.phase_poses, zero.poses)]
    assert max(angles) <= 1e-6
    # And the full prediction differs from it: the drift is not negligible here.
    assert np.abs(predicted.poses[-1, :3, 3] - predicted.phase_poses[-1, :3, 3]).max() > 1e-2


@pytest.mark.parametrize('kind', ['linear', 'cubic', 'quintic'])
def test_planned_path_joins_the_current_state_to_its_first_point(kind):
    # Like the controller joining its state at arrival: a cubic from (q0, qd0), linear
    # without velocities; a quintic plan's join is a cubic too (the state has no accelerations).
    times, positions, velocities, accelerations = _plan(2, kind=kind, points=3, seconds=2.0)
    q0, qd0 = np.array([0.5, -0.5]), np.array([0.3, 0.1])
    path = PlannedPath(times + 1.0, positions, velocities, accelerations, start=(0.0, q0, qd0))
    np.testing.assert_allclose(path(0.0)[0], q0, atol=1e-15)
    if velocities is not None:
        np.testing.assert_allclose(path(0.0)[1], qd0, atol=1e-15)
        np.testing.assert_allclose(path.velocity_limits(1.0)[0], velocities[0], atol=1e-12)
        # Third derivative constant on the join (a cubic), by differences of q_ddot.
        jerk = [(path(t + 1e-4)[2] - path(t - 1e-4)[2]) / 2e-4 for t in (0.2, 0.5, 0.8)]
        np.testing.assert_allclose(jerk[0], jerk[2], rtol=1e-6, atol=1e-6)
    else:
        np.testing.assert_allclose(path(0.5)[0], 0.5 * (q0 + positions[0]), atol=1e-14)
    np.testing.assert_allclose(path(1.0)[0], positions[0], atol=1e-12)


def test_held_velocity_path_is_a_line():
    path = HeldVelocityPath(0.0, np.array([0.1, 0.2]), np.array([1.0, -2.0]))
    q, qd, qdd = path(0.5)
    np.testing.assert_allclose(q, [0.6, -0.8])
    np.testing.assert_allclose(qd, [1.0, -2.0])
    assert not qdd.any()


# --- the estimator: planned mode, deferred jobs, budgets ---------------------------------
def _planned_run(robot, seconds=4.0, rate=200.0, offset=0.0):
    """Return samples of a plan played by the prescribed full dynamics, and the plan."""
    times, positions, velocities, accelerations = _plan(robot.m, kind='cubic',
                                                        seconds=seconds, points=9)
    path = PlannedPath(times, positions, velocities, accelerations)
    sample_times = np.arange(int(seconds * rate) + 1) / rate
    run = PrescribedShapeDynamics(robot, path).simulate(G0, XI0, sample_times)
    # Stamps from ``offset`` seconds; the plan's stamp is its origin (0: on arrival).
    joints, bases = samples(robot, sample_times + offset, run.poses, run.xi, run.qbar,
                            run.qbar_dot)
    plan = JointTrajectorySample(int(round(offset * 1e9)), '', robot.shape_joint_names,
                                 np.round(times * 1e9).astype(np.int64), positions, velocities)
    return joints, bases, plan, run


def _feed(estimator, joints, bases, plan):
    outputs = []
    estimator.add_trajectory(plan)
    for joint, base in zip(joints, bases):
        outputs += estimator.add_joint_state(joint)
        outputs += estimator.add_base_state(base)
    return outputs + estimator.flush()


def test_planned_mode_predicts_the_measured_base_path():
    robot = paper_robot()
    joints, bases, plan, _ = _planned_run(robot)
    # Noise-free odometry, and the filter is told so: it then follows the sensors.
    config = EstimatorConfig(prediction_rate=1.0, prediction_horizon=1.0,
                             pose_position_noise=1e-10, pose_angle_noise=1e-10,
                             twist_linear_noise=1e-10, twist_angular_noise=1e-10,
                             joint_velocity_noise=0.0, innovation_gate=0.0,
                             pose_stamp_noise=0.0, prediction_max_wall_time=0.0)
    estimator = Estimator(robot, config)
    outputs = _feed(estimator, joints, bases, plan)
    started = [o for o in outputs if o.prediction_path is not None]
    assert len(started) >= 3
    assert all(o.prediction is None and o.prediction_phase_path is not None for o in started)
    summary = estimator.summary()
    planned = summary['prediction_residuals']['planned']
    assert planned['compared'] >= 3 and planned['judged_by'] == 'base path'
    # Odometry is exact here: the base residual is the integrators' error.
    assert planned['position_residual_max'] <= 1e-7
    assert planned['attitude_residual_max'] <= 1e-7
    assert planned['shape_residual_max'] <= 1e-9  # the arm followed the plan exactly
    # Held velocities are a worse guess for the same run (cubic segments curve).
    held = Estimator(robot, config.replaced(prediction_mode='held_velocity'))
    _feed(held, joints, bases, plan)
    other = held.summary()['prediction_residuals']['held_velocity']
    assert other['position_residual_max'] > 100 * planned['position_residual_max']


def test_deferred_predictions_give_identical_messages_and_residuals():
    robot = paper_robot()
    joints, bases, plan, _ = _planned_run(robot, seconds=3.0)
    for mode in ('planned', 'held_torque', 'coast'):
        config = EstimatorConfig(prediction_rate=2.0, prediction_horizon=0.5,
                                 prediction_mode=mode, diagnostics_rate=2.0,
                                 prediction_max_wall_time=0.0)  # equal under any load
        inline = _feed(Estimator(robot, config), joints, bases, plan)
        deferred_estimator = Estimator(robot, config, defer_predictions=True)
        deferred = _feed(deferred_estimator, joints, bases, plan)
        jobs = [o.prediction_job for o in deferred if o.prediction_job is not None]
        assert len(jobs) >= 4
        # Half of the jobs run in worker threads, after the fact.
        workers = [threading.Thread(target=job.run) for job in jobs[::2]]
        for worker in workers:
            worker.start()
        for worker in workers:
            worker.join()
        messages = [job.run() for job in jobs]
        expected = [(o.prediction, o.prediction_path, o.prediction_phase_path)
                    for o in inline if o.prediction_path is not None]
        assert len(expected) == len(messages)
        for (shape, path, phase), got in zip(expected, messages):
            assert np.array_equal(path.positions, got.path.positions)
            assert np.array_equal(path.orientations_xyzw, got.path.orientations_xyzw)
            assert (shape is None) == (got.shape is None) == (mode == 'planned')
            if shape is not None:
                assert np.array_equal(shape.positions, got.shape.positions)
            assert (phase is None) == (got.phase_path is None)
        # Diagnostics (residuals included) are the same whenever the jobs ran.
        diagnostics = [o.diagnostics.statuses for o in inline if o.diagnostics is not None]
        other = [o.diagnostics.statuses for o in deferred if o.diagnostics is not None]
        assert [[s.values for s in d] for d in diagnostics] == \
            [[s.values for s in d] for d in other]


def test_a_prediction_over_budget_stops_with_the_reason():
    robot = paper_robot()
    joints, bases, plan, _ = _planned_run(robot, seconds=3.0)
    config = EstimatorConfig(prediction_rate=1.0, prediction_horizon=1.0,
                             prediction_max_evaluations=10.0, diagnostics_rate=1.0,
                             prediction_mode='coast', prediction_max_wall_time=0.0)
    estimator = Estimator(robot, config)
    outputs = _feed(estimator, joints, bases, plan)
    assert not any(o.prediction_path is not None for o in outputs)
    assert estimator.summary()['prediction_failures'] == {'budget': estimator.predictor.made}
    statuses = [s for o in outputs if o.diagnostics is not None
                for s in o.diagnostics.statuses if s.name.endswith('prediction')]
    assert any('evaluation budget exceeded' in s.message for s in statuses)
    # The estimates themselves go on.
    assert len(outputs) == len(joints)


def test_bad_trajectories_are_rejected_and_counted():
    robot = paper_robot()
    estimator = Estimator(robot)
    names = robot.shape_joint_names
    estimator.add_trajectory(JointTrajectorySample(0, '', ('nope',), [0], [[0.0]]))
    estimator.add_trajectory(JointTrajectorySample(0, '', names[:2], [0, 10],
                                                   [[0.0, np.nan], [0.0, 0.0]]))
    assert estimator.rejected == {'trajectory_unknown_joint': 1, 'trajectory_non_finite': 1}
    assert estimator.predictor.plan is None
    # A subset of the joints is a valid plan (the others keep their velocities).
    estimator.add_trajectory(JointTrajectorySample(5, '', names[:2], [0, 10**9],
                                                   [[0.0, 0.1], [0.2, 0.3]]))
    plan = estimator.predictor.plan
    assert plan is not None and plan.start_ns == 5 and list(plan.index) == [0, 1]
    path = plan.path_from(5, np.zeros(robot.m), np.ones(robot.m))
    np.testing.assert_allclose(path(0.5)[0][2:], 0.5)
    np.testing.assert_allclose(path(0.5)[0][:2], [0.1, 0.2])
    assert plan.path_from(2 * 10**9, np.zeros(robot.m), np.zeros(robot.m)) is None


# --- files, the simulator's --trajectory, replay, the predict command -------------------
PLAN_YAML = """
joint_names: [j2_x, j2_y, j2_z, j3]
points:
  - {time: 0.0, positions: [0.0, 0.0, 0.0, 0.0], velocities: [0, 0, 0, 0]}
  - {time: 2.5, positions: [0.6, -0.3, 0.4, 0.8], velocities: [0.1, 0, 0, 0]}
  - {time: 5.0, positions: [0.2, 0.1, -0.2, 0.3], velocities: [0, 0, 0, 0]}
"""


def test_trajectory_files_yaml_and_csv_agree(tmp_path):
    from reduced_dynamics.trajectory_file import load_trajectory, TrajectoryFileError
    (tmp_path / 'plan.yaml').write_text(PLAN_YAML)
    yaml_plan = load_trajectory(str(tmp_path / 'plan.yaml'))
    header = 'time,j2_x,j2_y,j2_z,j3,' + ','.join(
        f'{n}:velocity' for n in ('j2_x', 'j2_y', 'j2_z', 'j3'))
    rows = ['0,0,0,0,0,0,0,0,0', '2.5,0.6,-0.3,0.4,0.8,0.1,0,0,0', '5,0.2,0.1,-0.2,0.3,0,0,0,0']
    (tmp_path / 'plan.csv').write_text('\n'.join([header] + rows) + '\n')
    csv_plan = load_trajectory(str(tmp_path / 'plan.csv'))
    assert yaml_plan.joint_names == csv_plan.joint_names == ('j2_x', 'j2_y', 'j2_z', 'j3')
    assert np.array_equal(yaml_plan.times_from_start_ns, [0, 2_500_000_000, 5_000_000_000])
    np.testing.assert_array_equal(yaml_plan.positions, csv_plan.positions)
    np.testing.assert_array_equal(yaml_plan.velocities, csv_plan.velocities)
    assert csv_plan.accelerations is None
    (tmp_path / 'bad.yaml').write_text('points: [{time: 0, positions: [1, nan]}]\n'
                                       'joint_names: [a, b]\n')
    with pytest.raises(TrajectoryFileError, match='NaN'):
        load_trajectory(str(tmp_path / 'bad.yaml'))
    (tmp_path / 'back.csv').write_text('time,a\n1,0\n0.5,1\n')
    with pytest.raises(TrajectoryFileError, match='increasing'):
        load_trajectory(str(tmp_path / 'back.csv'))


def test_simulated_plan_replayed_in_planned_mode(tmp_path):
    from reduced_dynamics.cli import main
    from reduced_dynamics.params import defaults
    from reduced_dynamics.replay import replay, ReplayOptions
    from reduced_dynamics.robot.model import load_robot
    (tmp_path / 'plan.yaml').write_text(PLAN_YAML)
    bag = tmp_path / 'bag'
    assert main(['simulate', '-o', str(bag), '--trajectory', str(tmp_path / 'plan.yaml'),
                 '--duration', '6', '--rate', '100']) == 0
    summary = replay(str(bag), str(tmp_path / 'out'), load_robot(),
                     ReplayOptions(params={**defaults(), **NOISE_FREE}))
    assert summary['trajectory_topic'] == '/joint_trajectory'
    assert summary['trajectories_received'] == 1
    planned = summary['prediction_residuals']['planned']
    assert planned['predictions'] == 5 and planned['compared'] == 5
    # The bag's base is the full dynamics with the exact shape path; the prediction is the
    # reconstruction alone: they agree to the integrators' accuracy.
    assert planned['position_residual_max'] <= 1e-7
    assert planned['attitude_residual_max'] <= 1e-7
    # After the plan the arm rests: held velocities (zero) are exact as well.
    assert summary['prediction_residuals']['held_velocity']['position_residual_max'] <= 1e-7


def test_predict_command_prints_and_writes_the_path(tmp_path, capsys):
    import json
    from reduced_dynamics.cli import main
    (tmp_path / 'plan.yaml').write_text(PLAN_YAML)
    out = tmp_path / 'path.json'
    assert main(['predict', '--trajectory', str(tmp_path / 'plan.yaml'), '--mu', '1', '0', '0',
                 '0', '0', '2', '-o', str(out)]) == 0
    text = capsys.readouterr().out
    assert 'final base position' in text and 'max attitude deviation' in text
    document = json.loads(out.read_text())
    assert len(document['times']) == 101 and document['times'][-1] == 5.0
    # The same computation through the library (what the node's service runs).
    from reduced_dynamics.estimator.base_motion import predict_base_motion
    from reduced_dynamics.trajectory_file import load_trajectory
    robot = paper_robot()
    plan = load_trajectory(str(tmp_path / 'plan.yaml'))
    mu = np.array([1.0, 0, 0, 0, 0, 2.0])
    answer = predict_base_motion(robot, plan, pin.SE3.Identity(), mu, np.zeros(robot.m),
                                 np.zeros(robot.m))
    np.testing.assert_allclose(answer.path.positions, document['positions'], atol=1e-12)
    assert answer.max_attitude_deviation == pytest.approx(document['max_attitude_deviation_rad'])
    # Against the prescribed full dynamics of the same plan (arm from rest at q = 0).
    path = PlannedPath(plan.times_from_start_ns * 1e-9,
                       np.column_stack([plan.positions, np.zeros((3, 2))]),
                       np.column_stack([plan.velocities, np.zeros((3, 2))]))
    mass = robot.mass_matrix(np.zeros(robot.m))
    xi0 = np.linalg.solve(mass[:6, :6], mu)  # g0 = identity: pi = mu
    full = PrescribedShapeDynamics(robot, path).simulate(pin.SE3.Identity(), xi0,
                                                         np.linspace(0, 5, 101))
    np.testing.assert_allclose(answer.path.positions, full.poses[:, :3, 3], atol=1e-8)
    final = pin.SE3(full.poses[-1])
    assert np.linalg.norm(pin.log3(final.rotation.T @ answer.final_pose.rotation)) <= 1e-8


def test_estimator_answers_a_plan_from_its_latest_state():
    robot = paper_robot()
    joints, bases, plan, run = _planned_run(robot, seconds=2.0, offset=1.0)
    estimator = Estimator(robot, EstimatorConfig(prediction_rate=0.0, **NOISE_FREE))
    with pytest.raises(ValueError, match='no estimated state'):
        estimator.predict_base_motion(plan)
    for joint, base in list(zip(joints, bases))[:101]:  # up to 0.5 s into the plan
        estimator.add_joint_state(joint)
        estimator.add_base_state(base)
    # The rest of the same plan, asked 0.5 s in: the stamped plan's absolute times hold.
    answer = estimator.predict_base_motion(plan)
    assert answer.path.stamp_ns == joints[100].stamp_ns
    index = [int(round((s * 1e-9 - 1.0) * 200)) for s in answer.path.stamps_ns]
    np.testing.assert_allclose(answer.path.positions, run.poses[index, :3, 3], atol=1e-8)


def test_budget_counts_evaluations_and_wall_time(monkeypatch):
    from reduced_dynamics import integrators
    from reduced_dynamics.integrators import Budget, BudgetExceeded
    budget = Budget(max_evaluations=3)
    budget.charge(3)
    with pytest.raises(BudgetExceeded, match='evaluation budget exceeded'):
        budget.charge()
    clock = iter([100.0, 100.2, 100.9])  # start, then two charges: a fake clock
    monkeypatch.setattr(integrators.time, 'perf_counter', lambda: next(clock))
    budget = Budget(max_wall_time=0.5)
    budget.charge()
    with pytest.raises(BudgetExceeded, match='wall-time budget exceeded') as caught:
        budget.charge()
    assert caught.value.reason.startswith('wall-time budget exceeded (0.5 s, 2 evaluations)')


def test_planar_base_with_gravity_predicts_a_plan():
    # SE(2) base, gravity normal to the plane: the potential does not enter the
    # reconstruction (it is invariant under the base group), only the shape's torques.
    from conftest_robots import planar_robot
    from reduced_dynamics.reduction.prescribed import relative_angles
    robot = planar_robot()
    n = robot.n
    path = PlannedPath(*_plan(robot.m, seed=2, points=6))
    g0 = robot.project_pose(pin.SE3(pin.utils.rotate('z', 0.3), np.array([1.0, 2.0, 0.0])))
    xi0 = np.array([0.05, -0.02, 0.1])
    q0, qd0, _ = path(0.0)
    mass = robot.mass_matrix(q0)
    mu = momentum_map(robot.group, g0, mass[:n, :n] @ xi0 + mass[:n, n:] @ qd0)
    times = np.linspace(0.0, 10.0, 101)
    full = PrescribedShapeDynamics(robot, path).simulate(g0, xi0, times)
    predicted = PrescribedReconstruction(robot, mu, g0, path).propagate(
        times, 1e-10, 1e-12, path.breakpoints)
    assert np.abs(full.poses[:, :3, 3] - predicted.poses[:, :3, 3]).max() <= 1e-6
    assert relative_angles(full.poses[:, :3, :3], predicted.poses[:, :3, :3]).max() <= 1e-6
