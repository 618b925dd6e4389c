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
``reduced-dynamics predict --trajectory FILE``: base motion for a planned arm motion, offline.

The arm starts at the plan's first point (joints the plan leaves out at zero,
at rest); the base starts at ``--base-pose`` with momentum ``--mu`` (world
frame, about the origin). Prints the final base pose, the largest attitude
deviation and the attitude change split into drift and geometric phase;
with ``--pose-sigma``/``--mu-sigma`` (the initial covariance, diagonal) also the
final pose's standard deviations (docs/prediction_uncertainty.md); ``-o``
writes the path (CSV, or JSON by extension).
"""

from __future__ import annotations

import argparse
import json
from typing import Any, Optional

import numpy as np
import pinocchio as pin

from reduced_dynamics.estimator.base_motion import BaseMotionAnswer, predict_base_motion
from reduced_dynamics.geometry.quaternion import matrix_to_xyzw
from reduced_dynamics.trajectory_file import load_trajectory

NS = 1_000_000_000


def _run(args: argparse.Namespace) -> int:
    from reduced_dynamics.cli import load_robot_from_args
    robot = load_robot_from_args(args)
    trajectory = load_trajectory(args.trajectory, robot.shape_joint_names)
    pose = np.array(args.base_pose, dtype=float)
    if np.linalg.norm(pose[3:]) < 1e-9:
        raise ValueError('--base-pose needs a nonzero quaternion')
    pose[3:] /= np.linalg.norm(pose[3:])
    g0 = robot.project_pose(pin.XYZQUATToSE3(pose))
    mu = robot.group.dual_coordinates(np.array(args.mu, dtype=float))
    qbar0 = np.zeros(robot.m)
    index = [robot.shape_joint_names.index(n) for n in trajectory.joint_names
             if n in robot.shape_joint_names]
    if len(index) == len(trajectory.joint_names):
        qbar0[index] = trajectory.positions[0]
    # Before its first point (if that is after 0) the arm rests there.
    answer = predict_base_motion(robot, trajectory, g0, mu, qbar0, np.zeros(robot.m), 0,
                                 args.step, args.tolerance)
    print(format_answer(answer))
    if answer.failure is None and (args.pose_sigma or args.mu_sigma):
        print(format_sigma(final_covariance(robot, trajectory, answer, g0, mu, qbar0,
                                            args.pose_sigma, args.mu_sigma)))
    if args.output:
        write_answer(args.output, answer)
    return 0 if answer.failure is None else 1


def format_answer(answer: BaseMotionAnswer) -> str:
    """Return the answer in a few lines of text."""
    if answer.failure is not None:
        return f'no prediction: {answer.failure}'
    final = answer.final_pose
    quat = matrix_to_xyzw(final.rotation)
    duration = (answer.path.stamps_ns[-1] - answer.path.stamps_ns[0]) / NS
    return '\n'.join([
        f'predicted base motion over {duration:g} s ({len(answer.path.stamps_ns)} poses, '
        f'{answer.evaluations} evaluations)',
        'final base position [m]: ' + ' '.join(f'{v:+.6f}' for v in final.translation),
        'final base orientation (x y z w): ' + ' '.join(f'{v:+.6f}' for v in quat),
        f'max attitude deviation: {answer.max_attitude_deviation:.6g} rad '
        f'({np.degrees(answer.max_attitude_deviation):.4g} deg)',
        f'attitude change at the end: {answer.attitude_change:.6g} rad; geometric phase '
        f'alone (same plan at zero momentum): {answer.phase_attitude_change:.6g} rad'])


def final_covariance(robot: Any, trajectory: Any, answer: BaseMotionAnswer, g0: pin.SE3,
                     mu: np.ndarray, qbar0: np.ndarray, pose_sigma: Optional[list],
                     mu_sigma: Optional[list]) -> np.ndarray:
    """
    Return the world-frame covariance (x, y, z, rot X, Y, Z) of the final pose.

    The start's uncertainty: base pose (body frame, ``pose_sigma``) and momentum
    (world frame, ``mu_sigma``), independent, through the plan's reconstruction
    (:mod:`reduced_dynamics.estimator.prediction_covariance`).
    """
    from reduced_dynamics.estimator.base_motion import plan_of
    from reduced_dynamics.estimator.prediction_covariance import (propagate_covariance,
                                                                  StartUncertainty)
    n, m, group = robot.n, robot.m, robot.group
    variances = np.zeros(3 * n)
    if pose_sigma:
        variances[:n] = group.algebra_pinv @ np.square(np.array(pose_sigma, dtype=float))
    if mu_sigma:
        variances[n:2 * n] = group.algebra_pinv @ np.square(np.array(mu_sigma, dtype=float))
    path = plan_of(robot, trajectory, 0).path_from(0, qbar0, np.zeros(m))
    times = (answer.path.stamps_ns - answer.path.stamps_ns[0]) / NS
    poses = np.array([pin.XYZQUATToSE3(np.r_[p, q]).homogeneous for p, q in
                      zip(answer.path.positions, answer.path.orientations_xyzw)])
    zeros = np.zeros(m)
    uncertainty = StartUncertainty(np.diag(np.abs(variances)), np.zeros(n), zeros, zeros)
    covariance = propagate_covariance(robot, 'planned', g0, mu, qbar0, zeros, zeros,
                                      uncertainty, times, poses, np.zeros(n),
                                      (qbar0, zeros), path)
    return covariance.pose_cov[-1]


def format_sigma(cov: np.ndarray) -> str:
    """Return the final pose's standard deviations in two lines."""
    sigma = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    return '\n'.join([
        'final base position sigma [m] (world x y z): '
        + ' '.join(f'+-{v:.6f}' for v in sigma[:3]),
        'final base rotation sigma [rad] (about world X Y Z): '
        + ' '.join(f'+-{v:.6f}' for v in sigma[3:])])


def write_answer(path: str, answer: BaseMotionAnswer) -> None:
    """Write the path as CSV (time, x, y, z, qx, qy, qz, qw) or JSON (by extension)."""
    times = (answer.path.stamps_ns - answer.path.stamps_ns[0]) / NS
    rows = np.column_stack([times, answer.path.positions, answer.path.orientations_xyzw])
    if path.lower().endswith('.json'):
        document: dict[str, Any] = {
            'times': times.tolist(), 'positions': answer.path.positions.tolist(),
            'orientations_xyzw': answer.path.orientations_xyzw.tolist(),
            'phase_positions': answer.phase_path.positions.tolist(),
            'phase_orientations_xyzw': answer.phase_path.orientations_xyzw.tolist(),
            'max_attitude_deviation_rad': answer.max_attitude_deviation,
            'attitude_change_rad': answer.attitude_change,
            'phase_attitude_change_rad': answer.phase_attitude_change,
            'evaluations': answer.evaluations}
        with open(path, 'w', encoding='utf-8') as stream:
            json.dump(document, stream, indent=1)
        return
    np.savetxt(path, rows, delimiter=',', header='time,x,y,z,qx,qy,qz,qw', comments='')


def register_command(commands: Any) -> None:
    """Add the ``predict`` subcommand."""
    from reduced_dynamics.cli import add_robot_arguments
    parser = commands.add_parser(
        'predict', help='base motion for a planned joint trajectory (YAML/CSV file)')
    add_robot_arguments(parser)
    parser.add_argument('--trajectory', required=True, metavar='FILE',
                        help='planned joint trajectory: YAML (joint_names, points with time, '
                             'positions, optional velocities/accelerations) or CSV (time, '
                             '<joint>..., optional <joint>:velocity, <joint>:acceleration)')
    parser.add_argument('--mu', type=float, nargs=6, default=[0.0] * 6,
                        metavar=('PX', 'PY', 'PZ', 'LX', 'LY', 'LZ'),
                        help='momentum (world frame, about the origin): linear [kg m/s], '
                             'angular [kg m^2/s] (default 0)')
    parser.add_argument('--base-pose', type=float, nargs=7,
                        default=[0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0],
                        metavar=('X', 'Y', 'Z', 'QX', 'QY', 'QZ', 'QW'),
                        help='initial base pose in the world frame (default identity)')
    parser.add_argument('--step', type=float, default=0.05,
                        help='spacing of the output poses [s] (default 0.05)')
    parser.add_argument('--tolerance', type=float, default=1e-10,
                        help='DOP853 relative and absolute tolerance (default 1e-10)')
    parser.add_argument('--pose-sigma', type=float, nargs=6, default=None,
                        metavar=('X', 'Y', 'Z', 'RX', 'RY', 'RZ'),
                        help='standard deviations of the initial base pose (base frame: m, '
                             'rad); prints the final pose +- sigma (world frame)')
    parser.add_argument('--mu-sigma', type=float, nargs=6, default=None,
                        metavar=('PX', 'PY', 'PZ', 'LX', 'LY', 'LZ'),
                        help='standard deviations of the momentum (world frame); prints the '
                             'final pose +- sigma')
    parser.add_argument('-o', '--output', metavar='FILE',
                        help='write the path: .json (with the geometric-phase path) or CSV')
    parser.set_defaults(func=_run)
