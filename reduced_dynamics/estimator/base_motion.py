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
"Where will the base go if the arm executes this plan?": one answer for a planner.

The shape path is prescribed (the plan, interpolated as joint_trajectory_controller
does), so the base follows from the reconstruction equation alone
(:mod:`reduced_dynamics.reduction.prescribed`) at the current momentum mu:
the node's ``~/predict_base_motion``, ``reduced-dynamics predict`` and the
bench use this one function.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np
import pinocchio as pin

from reduced_dynamics.estimator.prediction import pose_path, Plan
from reduced_dynamics.geometry.quaternion import matrix_to_xyzw
from reduced_dynamics.integrators import Budget, BudgetExceeded
from reduced_dynamics.messages.samples import (DIAG_ERROR, DIAG_OK, Diagnostics,
                                               DiagnosticStatusSample, JointTrajectorySample,
                                               PosePath)
from reduced_dynamics.reduction.prescribed import attitude_angles, PrescribedReconstruction
from reduced_dynamics.robot.model import RobotModel

NS = 1_000_000_000


@dataclass
class BaseMotionAnswer:
    """
    The predicted base motion for a plan.

    ``path``: base poses (world frame) every ``step`` seconds to the plan's
    end; ``final_pose``; ``max_attitude_deviation`` [rad]: the largest rotation
    angle of the base from its attitude at the start; ``phase_path``: the
    base path of the geometric phase alone (the same plan at zero momentum).
    ``failure``: why there is no answer (the other fields are then None).
    """

    path: Optional[PosePath]
    phase_path: Optional[PosePath]
    final_pose: Optional[pin.SE3]
    max_attitude_deviation: Optional[float]
    attitude_change: Optional[float]
    phase_attitude_change: Optional[float]
    evaluations: int
    failure: Optional[str] = None


#: A request is answered once, not every prediction period, so its wall time need not fit
#: half a period: it gets this many times the periodic budget (scaled to the plan's length),
#: a margin for a loaded machine. Issue 21: the shipped 10 s example plan took 866
#: evaluations, more than 0.5 s on a loaded machine (over 0.58 ms each; 0.04 ms idle).
REQUEST_WALL_MARGIN = 4.0


def plan_of(robot: RobotModel, trajectory: JointTrajectorySample, start_ns: int) -> Plan:
    """Return the plan of a trajectory in model joint order (ValueError for bad joints)."""
    index = {name: i for i, name in enumerate(robot.shape_joint_names)}
    unknown = [n for n in trajectory.joint_names if n not in index]
    if unknown:
        raise ValueError(f'joints {", ".join(unknown[:5])} are not shape joints of the robot')
    if not trajectory.times_from_start_ns.size:
        raise ValueError('the trajectory has no points')
    if len(set(trajectory.joint_names)) != len(trajectory.joint_names):
        raise ValueError('joint names repeat')
    stamp = trajectory.stamp_ns or start_ns
    return Plan(stamp, np.array([index[n] for n in trajectory.joint_names], dtype=int),
                trajectory.times_from_start_ns, trajectory.positions,
                trajectory.velocities, trajectory.accelerations, robot.m)


def request_budget(horizon: float, budget_horizon: Optional[float],
                   max_evaluations: Optional[float], max_wall_time: Optional[float]
                   ) -> Budget:
    """
    Return the budget of one request for a plan ``horizon`` seconds long.

    ``max_evaluations`` and ``max_wall_time`` are the budget of a prediction
    ``budget_horizon`` seconds long (the periodic predictions'; None or 0: taken
    as they are). A longer plan gets proportionally more of both, and the wall
    time REQUEST_WALL_MARGIN on top: evaluations bound the work the same on any
    machine, the wall time only caps a machine too loaded to answer.
    """
    if not budget_horizon or budget_horizon <= 0.0:
        return Budget(max_evaluations, max_wall_time)
    scale = max(1.0, horizon / budget_horizon)
    return Budget(None if max_evaluations is None else max_evaluations * scale,
                  None if max_wall_time is None else
                  max_wall_time * scale * REQUEST_WALL_MARGIN)


def predict_base_motion(robot: RobotModel, trajectory: JointTrajectorySample, g0: pin.SE3,
                        mu: np.ndarray, qbar0: np.ndarray, qbar_dot0: np.ndarray,
                        start_ns: int = 0, step: float = 0.05, tolerance: float = 1e-10,
                        max_evaluations: Optional[float] = None,
                        max_wall_time: Optional[float] = None,
                        world_frame: str = 'world',
                        budget_horizon: Optional[float] = None) -> BaseMotionAnswer:
    """
    Predict the base path from pose ``g0`` at momentum ``mu`` while the arm follows a plan.

    The arm starts at (``qbar0``, ``qbar_dot0``) at ``start_ns``; the plan's
    times count from its stamp (0: from ``start_ns``). Joints outside the
    plan keep their velocities. Raises ValueError for a plan that does not
    fit the robot or has ended before ``start_ns``. The budgets are those of a
    plan ``budget_horizon`` seconds long (:func:`request_budget`).
    """
    plan = plan_of(robot, trajectory, start_ns)
    path = plan.path_from(start_ns, np.asarray(qbar0, dtype=float),
                          np.asarray(qbar_dot0, dtype=float))
    if path is None:
        raise ValueError('the plan ends before the start time')
    horizon = (plan.end_ns - start_ns) / NS
    times = np.append(np.arange(0.0, horizon, step), horizon)
    if times.size > 1 and times[-1] - times[-2] < 1e-9:
        times = np.delete(times, -2)
    # 0 or None: no wall-time budget (replay: outputs must not depend on the machine's load)
    budget = request_budget(horizon, budget_horizon, max_evaluations, max_wall_time or None)
    system = PrescribedReconstruction(robot, mu, g0, path)
    try:
        trajectory_out = system.propagate(times, tolerance, tolerance, path.breakpoints, budget)
    except BudgetExceeded as error:
        return BaseMotionAnswer(None, None, None, None, None, None, budget.evaluations,
                                error.reason)
    offsets = np.round(times * NS).astype(np.int64)
    poses, phase = trajectory_out.poses, trajectory_out.phase_poses
    angles = attitude_angles(poses[0, :3, :3], poses[:, :3, :3])
    phase_angles = attitude_angles(phase[0, :3, :3], phase[:, :3, :3])
    return BaseMotionAnswer(
        pose_path(start_ns, world_frame, offsets, poses),
        pose_path(start_ns, world_frame, offsets, phase),
        pin.SE3(poses[-1]), float(angles.max()), float(angles[-1]), float(phase_angles[-1]),
        budget.evaluations)


#: The name of the answer's status (the result topic of ``~/predict_base_motion``).
ANSWER_STATUS = 'reduced_dynamics: predict_base_motion'


def answer_messages(answer: Optional[BaseMotionAnswer], stamp_ns: int, request_id: str,
                    error: Optional[str] = None) -> tuple[Optional[PosePath], Diagnostics]:
    """
    Return the response of ``~/predict_base_motion`` as (path, result) samples.

    Standard types (no generated interface): the path is a nav_msgs/Path
    whose last pose is the final base pose; the result a DiagnosticArray
    stamped like the path, one status whose ``hardware_id`` echoes the
    request id (the request header's frame_id) with the final pose, the
    largest attitude deviation and the drift/phase split as key-values.
    ``error``: why the request could not be answered.
    """
    reason = error or (answer.failure if answer is not None else 'no answer')
    if answer is None or answer.failure is not None:
        status = DiagnosticStatusSample(DIAG_ERROR, ANSWER_STATUS, reason, request_id,
                                        {'request_id': request_id})
        return None, Diagnostics(stamp_ns, (status,))
    final = answer.final_pose
    quat = matrix_to_xyzw(final.rotation)
    values = {'request_id': request_id,
              'final_position': ' '.join(f'{v:.9g}' for v in final.translation),
              'final_orientation_xyzw': ' '.join(f'{v:.9g}' for v in quat),
              'max_attitude_deviation_rad': f'{answer.max_attitude_deviation:.9g}',
              'attitude_change_rad': f'{answer.attitude_change:.9g}',
              'phase_attitude_change_rad': f'{answer.phase_attitude_change:.9g}',
              'duration_s': f'{(answer.path.stamps_ns[-1] - answer.path.stamps_ns[0]) / NS:g}',
              'evaluations': str(answer.evaluations)}
    status = DiagnosticStatusSample(DIAG_OK, ANSWER_STATUS, 'predicted', request_id, values)
    return answer.path, Diagnostics(answer.path.stamp_ns, (status,))
