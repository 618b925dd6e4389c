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
The covariance of a prediction: the start's uncertainty carried through the flow.

What is uncertain when a prediction starts (docs/prediction_uncertainty.md):

* the filter's error state (:mod:`.filter`): base pose ``g = g_hat exp(d)``
  (body-frame algebra coordinates), momentum mu, and the held external wrench w
  (world frame about the origin), with their joint covariance P;
* the measured shape qbar and rate qbar_dot (``joint_position_noise``,
  ``joint_velocity_noise``), unless a plan prescribes the shape;
* in ``held_torque``, the held torque estimate (:mod:`.held_torque`).

These L variables are sampled at ``x_hat`` and at ``x_hat + S e_j`` for the L
columns of a square root S of their covariance (one-sided divided differences,
the first-order divided-difference transform of Norgaard, Poulsen & Ravn 2000):
L + 1 points, plus one at the mean with no wrench (the held wrench's share of the
mean). All points are propagated together as one batch through the flow the
prediction uses, with the held wrench added (mu_dot = w, REDUCED_MODEL.md 3):

* prescribed modes: reconstruction ``xi = I^-1 Ad_g^T mu(t) - A qbar_dot(t)``
  (REDUCED_MODEL.md 4) along each point's shape path; one ``crba`` per point
  and stage (one for all points when they share a plan);
* torque modes: the same mechanics as Pinocchio's ``aba`` on the body twist,
  shape and rates (the free-floating dynamics the reduced flow reduces, left
  invariant: the base at the identity), one call per point and stage.

The batch is integrated by classical RK4 on a coarse grid (``COVARIANCE_STEP``),
the pose by ``g exp(eta)`` with ``eta_dot = xi + [eta, xi] / 2`` per step; the
integration error is common to all points and cancels in their differences.
The covariance is ``sum_j (y_j - y_0)(y_j - y_0)^T``. The published mean is the
prediction's own (accurate) path shifted by ``y_0 - y_ref`` (the held wrench).
Pose covariances are in the world frame, ROS order (x, y, z, rotation about X,
Y, Z): position difference and ``log(R_j R_0^T)``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Optional

import numpy as np
import pinocchio as pin

# The batch's flow, and its SE(3) maps importable from here as before the split.
from reduced_dynamics.estimator.prediction_points import _Batch, _pi, exp_se3, log_so3
from reduced_dynamics.geometry.quaternion import matrix_to_unit_xyzw
from reduced_dynamics.robot.model import RobotModel

NS = 1_000_000_000
#: Largest RK4 step [s] of the sigma-point batch (a multiple of the prediction step).
COVARIANCE_STEP = 0.4
#: Largest turn [rad] of any point's base or joint in one RK4 step.
MAX_TURN = 0.25


@dataclass(frozen=True)
class StartUncertainty:
    """What is uncertain at a prediction's start (see the module docstring)."""

    #: filter covariance of (d_g, mu, w), 3n x 3n
    filter_cov: np.ndarray
    #: the held external wrench w (world frame, dual coordinates, n)
    wrench: np.ndarray
    #: variances of the measured shape and shape rate (m each)
    position_var: np.ndarray
    velocity_var: np.ndarray
    #: held torque covariance (m x m; ``held_torque`` only)
    torque_cov: Optional[np.ndarray] = None


@dataclass
class PredictionCovariance:
    """Covariances along a prediction at ``times`` [s from its start] (see module docstring)."""

    times: np.ndarray
    #: (N, 6, 6) world-frame pose covariance (x, y, z, rot X, Y, Z)
    pose_cov: np.ndarray
    #: (N, 4, 4) mean poses: the prediction's path with the held wrench's shift
    poses: np.ndarray
    #: body twist at the horizon (6, linear first) and its covariance (6 x 6)
    twist: np.ndarray
    twist_cov: np.ndarray
    #: covariance of (qbar, qbar_dot) at the horizon (2m x 2m)
    shape_cov: np.ndarray
    #: sample points propagated, and right-hand-side evaluations per point
    points: int
    evaluations: int


def _square_root(cov: np.ndarray) -> np.ndarray:
    """Return S with S S^T = cov (symmetric square root: a PSD cov may be singular)."""
    values, vectors = np.linalg.eigh(0.5 * (cov + cov.T))
    return vectors * np.sqrt(np.clip(values, 0.0, None))


def propagate_covariance(robot: RobotModel, mode: str, g: pin.SE3, mu: np.ndarray,
                         qbar: np.ndarray, qbar_dot: np.ndarray, tau: np.ndarray,
                         uncertainty: StartUncertainty, times: np.ndarray,
                         nominal_poses: np.ndarray, nominal_twist: np.ndarray,
                         nominal_shape: tuple[np.ndarray, np.ndarray],
                         plan: Optional[Callable] = None) -> PredictionCovariance:
    """
    Return the prediction's covariance (module docstring) at a subset of ``times``.

    ``mode``: a prediction mode; ``plan``: the shape path (t -> qbar, qbar_dot, ...)
    of ``planned``. ``nominal_poses`` (N, 4, 4) the prediction's path at ``times``,
    ``nominal_twist`` its body twist (n) at the horizon, ``nominal_shape`` its
    (qbar, qbar_dot) at the horizon.
    """
    n, m = robot.n, robot.m
    group = robot.group
    basis, pinv = group.algebra_basis, group.algebra_pinv
    prescribed = mode in ('planned', 'held_velocity')
    with_shape = mode != 'planned'
    with_torque = mode == 'held_torque'
    blocks = [uncertainty.filter_cov]
    if with_shape:
        blocks += [np.diag(uncertainty.position_var), np.diag(uncertainty.velocity_var)]
    if with_torque:
        blocks.append(uncertainty.torque_cov)
    size = sum(len(b) for b in blocks)
    cov = np.zeros((size, size))
    at = 0
    for block in blocks:
        cov[at:at + len(block), at:at + len(block)] = block
        at += len(block)
    root = _square_root(cov)
    # Points: 0 the mean, 1..L the columns of S, L + 1 the mean with no wrench.
    deltas = np.vstack([np.zeros(size), root.T, np.zeros(size)])
    count = len(deltas)
    wrench = np.tile(uncertainty.wrench, (count, 1))
    wrench[-1] = 0.0
    wrench += deltas[:, 2 * n:3 * n]
    start = g.homogeneous
    r_d, p_d = exp_se3(deltas[:, :n] @ basis.T)
    rotation = start[:3, :3] @ r_d
    position = start[:3, 3] + np.einsum('ij,kj->ki', start[:3, :3], p_d)
    mu_points = mu + deltas[:, n:2 * n]
    mu6 = mu_points @ pinv
    w6 = wrench @ pinv
    q0 = np.tile(qbar, (count, 1))
    qd0 = np.tile(qbar_dot, (count, 1))
    at = 3 * n
    if with_shape:
        q0 += deltas[:, at:at + m]
        qd0 += deltas[:, at + m:at + 2 * m]
        at += 2 * m
    torques = np.tile(tau, (count, 1))
    if with_torque:
        torques += deltas[:, at:at + m]
    shape_path = None
    if mode == 'planned':
        def shape_path(t: float) -> tuple[np.ndarray, np.ndarray]:
            point = plan(t)
            return point[0], point[1]
    elif mode == 'held_velocity':
        def shape_path(t: float) -> tuple[np.ndarray, np.ndarray]:
            return q0 + t * qd0, qd0
    batch = _Batch(robot, shape_path, torques if not prescribed else np.zeros((count, m)),
                   mu6, w6)
    # The body twist at the start: xi = I^-1 (Ad_g^T mu - B qbar_dot) per point.
    state = np.zeros((count, n + 2 * m))
    if not prescribed:
        pi = _pi(rotation, position, mu6) @ basis
        for k in range(count):
            mass = robot.mass_matrix(q0[k])
            state[k, :n] = np.linalg.solve(mass[:n, :n], pi[k] - mass[:n, n:] @ qd0[k])
        state[:, n:n + m], state[:, n + m:] = q0, qd0
    stride = max(1, int(round(COVARIANCE_STEP / (times[1] - times[0])))) if len(times) > 1 \
        else 1
    nodes = list(range(0, len(times), stride))
    if nodes[-1] != len(times) - 1:
        nodes.append(len(times) - 1)
    pose_cov = np.empty((len(nodes), 6, 6))
    poses = np.empty((len(nodes), 4, 4))
    t = float(times[0])
    for j, index in enumerate(nodes):
        target = float(times[index])
        while target - t > 1e-12:
            # RK4 turns each point by at most MAX_TURN per step (stability and accuracy
            # of fast light links; the steps stay common to all points).
            h = min(target - t, MAX_TURN / max(batch.rate(t, state), 1e-9))
            if h < (target - float(times[0])) * 1e-4:
                raise ArithmeticError('the covariance propagation diverged (sample points '
                                      'turning too fast)')
            rotation, position, state = batch.step(t, h, rotation, position, state)
            t = t + h if target - (t + h) > 1e-12 else target
        pose_cov[j], poses[j] = _pose_statistics(rotation, position, nominal_poses[index])
    xi6, _ = batch.twists(t, rotation, position, state)
    batch.evaluations -= 1
    twist_dev = xi6[1:-1] - xi6[0]
    if prescribed:
        qbar_end, qbar_dot_end = shape_path(t)
        if qbar_end.ndim == 1:
            qbar_end, qbar_dot_end = np.tile(qbar_end, (count, 1)), \
                np.tile(qbar_dot_end, (count, 1))
    else:
        qbar_end, qbar_dot_end = state[:, n:n + m], state[:, n + m:]
    shape_dev = np.concatenate([qbar_end[1:-1] - qbar_end[0],
                                qbar_dot_end[1:-1] - qbar_dot_end[0]], axis=1)
    twist = basis @ nominal_twist + (xi6[0] - xi6[-1])
    return PredictionCovariance(times[nodes], pose_cov, poses, twist,
                                twist_dev.T @ twist_dev, shape_dev.T @ shape_dev, count,
                                batch.evaluations)


def _pose_statistics(rotation: np.ndarray, position: np.ndarray,
                     nominal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return the world-frame covariance of points 1..L about 0 and the shifted mean."""
    d_position = position[1:-1] - position[0]
    d_rotation = log_so3(rotation[1:-1] @ rotation[0].T)
    dev = np.concatenate([d_position, d_rotation], axis=1)
    # The held wrench's share of the mean: point 0 (w held) against the last (no w).
    shift_r = rotation[0] @ rotation[-1].T
    shift_p = position[0] - position[-1]
    mean = np.eye(4)
    mean[:3, :3] = shift_r @ nominal[:3, :3]
    mean[:3, 3] = nominal[:3, 3] + shift_p
    return dev.T @ dev, mean


def pose_nees(mean: np.ndarray, cov: np.ndarray, truth: np.ndarray) -> float:
    """Return the NEES of a true pose (4 x 4) about a mean (4 x 4), world-frame covariance."""
    error = np.concatenate([truth[:3, 3] - mean[:3, 3],
                            pin.log3(truth[:3, :3] @ mean[:3, :3].T)])
    return float(error @ np.linalg.solve(cov, error))


def with_uncertainty(job: Any, result: Any, messages: Any) -> Any:
    """
    Return ``messages`` with the covariance messages of a computed prediction.

    Sets ``result.covariance`` (or ``result.covariance_failure``: the prediction's
    own messages still go out).
    """
    from reduced_dynamics.messages.samples import BaseStateSample
    from reduced_dynamics.messages.uncertainty import (
        CovarianceEllipsoids, PredictedOdometry, ShapeCovariance)
    robot, settings = job.robot, job.settings
    try:
        plan = job.plan if job.mode == 'planned' else None
        nominal_twist = result.drift[-1] + result.phase[-1]
        with np.errstate(all='ignore'):
            covariance = propagate_covariance(
                robot, job.mode, job.g, job.mu, job.qbar, job.qbar_dot, job.tau,
                job.uncertainty, result.times, result.poses, nominal_twist,
                (result.qbar[-1], result.qbar_dot[-1]), plan)
        arrays = (covariance.pose_cov, covariance.poses, covariance.twist,
                  covariance.twist_cov, covariance.shape_cov)
        if not all(np.isfinite(a).all() for a in arrays):
            # A start so uncertain that the sample points leave the model's good region.
            raise ArithmeticError('the covariance propagation diverged (start too uncertain)')
    except (RuntimeError, ValueError, ArithmeticError, np.linalg.LinAlgError) as error:
        result.covariance_failure = f'{type(error).__name__}: {error}'
        return messages
    result.covariance = covariance
    offsets = np.round(covariance.times * NS).astype(np.int64)
    end = covariance.poses[-1]
    quat = matrix_to_unit_xyzw(end[:3, :3])
    base = BaseStateSample(job.end_ns, settings.world_frame, robot.base_link, end[:3, 3],
                           quat, covariance.twist[:3], covariance.twist[3:])
    horizon = PredictedOdometry(base, covariance.pose_cov[-1], covariance.twist_cov)
    ellipsoids = CovarianceEllipsoids(job.start_ns, settings.world_frame,
                                      job.start_ns + offsets, covariance.poses[:, :3, 3],
                                      covariance.pose_cov[:, :3, :3])
    shape = ShapeCovariance(tuple(robot.shape_joint_names), covariance.shape_cov)
    return messages._replace(horizon=horizon, ellipsoids=ellipsoids, shape_covariance=shape)
