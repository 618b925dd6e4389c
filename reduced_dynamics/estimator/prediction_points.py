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
The sample points of a prediction's covariance as one batch: their flow and an RK4 step.

:mod:`.prediction_covariance` samples the start's uncertainty at L + 2 points; here
they are carried together (poses, body twists, shapes, rates): SE(3) maps in
batch, the flow (the reconstruction along a prescribed shape path, else
Pinocchio's ``aba``), and one classical RK4 step with the pose by ``g exp(eta)``,
``eta_dot = xi + [eta, xi] / 2``.
"""

from __future__ import annotations

from typing import Callable, Optional

import numpy as np
import pinocchio as pin

from reduced_dynamics.robot.model import RobotModel


# --------------------------------------------------------------------------- SE(3) in batch
def _hat(w: np.ndarray) -> np.ndarray:
    out = np.zeros(w.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -w[..., 2], w[..., 1]
    out[..., 1, 0], out[..., 1, 2] = w[..., 2], -w[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -w[..., 1], w[..., 0]
    return out


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross products of (K, 3) arrays (np.cross costs more at this size)."""
    out = np.empty(a.shape)
    out[:, 0] = a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1]
    out[:, 1] = a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2]
    out[:, 2] = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    return out


def exp_se3(eta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return (R, p) of exp of twists eta (K, 6), linear first (Rodrigues, in batch)."""
    v, w = eta[:, :3], eta[:, 3:]
    theta = np.linalg.norm(w, axis=1)
    small = theta < 1e-6
    t = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta ** 2 / 6.0, np.sin(t) / t)
    b = np.where(small, 0.5 - theta ** 2 / 24.0, (1.0 - np.cos(t)) / t ** 2)
    c = np.where(small, 1.0 / 6.0 - theta ** 2 / 120.0, (t - np.sin(t)) / t ** 3)
    k = _hat(w)
    k2 = k @ k
    eye = np.eye(3)
    rotation = eye + a[:, None, None] * k + b[:, None, None] * k2
    left = eye + b[:, None, None] * k + c[:, None, None] * k2
    return rotation, np.einsum('kij,kj->ki', left, v)


def log_so3(rotation: np.ndarray) -> np.ndarray:
    """Return the rotation vectors of rotations (K, 3, 3)."""
    return np.array([pin.log3(r) for r in rotation])


def _pi(rotation: np.ndarray, position: np.ndarray, mu6: np.ndarray) -> np.ndarray:
    """Return Ad_g^T mu (body momentum) for poses (K) and world momenta mu6 (K, 6)."""
    force = np.einsum('kji,kj->ki', rotation, mu6[:, :3])
    moment = mu6[:, 3:] - _cross(position, mu6[:, :3])
    return np.concatenate([force, np.einsum('kji,kj->ki', rotation, moment)], axis=1)


# --------------------------------------------------------------------------- the batch
class _Batch:
    """K points: poses, body twists (6), shapes, rates; the flow and one RK4 step."""

    def __init__(self, robot: RobotModel, shape_path: Optional[Callable], torques: np.ndarray,
                 mu6: np.ndarray, w6: np.ndarray) -> None:
        self.robot = robot
        self.n, self.m = robot.n, robot.m
        self.basis = robot.group.algebra_basis
        self.shape_path = shape_path
        self.torques = torques
        self.mu6, self.w6 = mu6, w6
        self.model = robot.model
        self.data = robot.model.createData()
        self.q = robot.full_configuration(pin.SE3.Identity(), np.zeros(robot.m))
        self.nq_base = robot.nq_base
        #: the base rows of each point's mass matrix (prescribed modes)
        self.rows = np.empty((len(torques), robot.n, robot.n + robot.m))
        self.evaluations = 0

    def twists(self, t: float, rotation: np.ndarray, position: np.ndarray,
               state: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Return each point's body twist (6 values) and d state/dt at t (xi, qbar, qbar_dot)."""
        self.evaluations += 1
        n, m, basis = self.n, self.m, self.basis
        count = len(rotation)
        mu6 = self.mu6 + t * self.w6
        if self.shape_path is not None:
            qbar, qbar_dot = self.shape_path(t)
            pi = _pi(rotation, position, mu6) @ basis
            q, model, data = self.q, self.model, self.data
            if qbar.ndim == 1:
                # One plan for every point: one mass matrix, one factorisation.
                q[self.nq_base:] = qbar
                mass = pin.crba(model, data, q)
                rhs = (pi - mass[:n, n:] @ qbar_dot).T
                xi = np.linalg.solve(_upper_symmetric(mass[:n, :n]), rhs).T
            else:
                rows = self.rows
                nq_base, crba = self.nq_base, pin.crba
                for k in range(count):
                    q[nq_base:] = qbar[k]
                    rows[k] = crba(model, data, q)[:n]
                locked = np.triu(rows[:, :, :n])
                locked += np.swapaxes(np.triu(locked, 1), 1, 2)
                rhs = pi - np.einsum('kij,kj->ki', rows[:, :, n:], qbar_dot)
                xi = np.linalg.solve(locked, rhs[:, :, None])[:, :, 0]
            return xi @ basis.T, np.zeros_like(state)
        xi = state[:, :n]
        qbar = state[:, n:n + m]
        # A body wrench on the base is the base joint's generalised force (its motion
        # subspace is the algebra basis in the body frame): no external-force vector.
        forces = np.concatenate([_pi(rotation, position, np.broadcast_to(self.w6, (count, 6)))
                                 @ basis, self.torques], axis=1)
        velocities = np.concatenate([xi, state[:, n + m:]], axis=1)
        derivative = np.empty_like(state)
        q, model, data, aba = self.q, self.model, self.data, pin.aba
        nq_base = self.nq_base
        for k in range(count):
            q[nq_base:] = qbar[k]
            acceleration = aba(model, data, q, velocities[k], forces[k])
            derivative[k, :n] = acceleration[:n]
            derivative[k, n + m:] = acceleration[n:]
        derivative[:, n:n + m] = state[:, n + m:]
        return xi @ basis.T, derivative

    def rate(self, t: float, state: np.ndarray) -> float:
        """Return the fastest turning rate [rad/s] of any point's base or joint."""
        if self.shape_path is not None:
            joints = self.shape_path(t)[1]
            base = 0.0
        else:
            joints = state[:, self.n + self.m:]
            base = float(np.max(np.abs(state[:, :self.n] @ self.basis[3:].T)))
        return max(base, float(np.max(np.abs(joints))) if joints.size else 0.0)

    def step(self, t: float, h: float, rotation: np.ndarray, position: np.ndarray,
             state: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One RK4 step of (g, state); g by g exp(eta), eta_dot = xi + [eta, xi] / 2."""
        eta = np.zeros((len(rotation), 6))

        prescribed = self.shape_path is not None

        def rates(tt: float, eta_s: np.ndarray, state_s: np.ndarray):
            if prescribed:
                # pi = Ad_g^T mu needs the pose at the stage.
                r_e, p_e = exp_se3(eta_s)
                r_s = rotation @ r_e
                p_s = position + np.einsum('kij,kj->ki', rotation, p_e)
            else:
                # Only the held wrench's body frame: the step's start pose (its effect is
                # small against the twist's, and O(h) off).
                r_s, p_s = rotation, position
            xi6, d_state = self.twists(tt, r_s, p_s, state_s)
            bracket = np.concatenate([_cross(eta_s[:, 3:], xi6[:, :3])
                                      + _cross(eta_s[:, :3], xi6[:, 3:]),
                                      _cross(eta_s[:, 3:], xi6[:, 3:])], axis=1)
            return xi6 + 0.5 * bracket, d_state

        k1e, k1s = rates(t, eta, state)
        k2e, k2s = rates(t + 0.5 * h, eta + 0.5 * h * k1e, state + 0.5 * h * k1s)
        k3e, k3s = rates(t + 0.5 * h, eta + 0.5 * h * k2e, state + 0.5 * h * k2s)
        k4e, k4s = rates(t + h, eta + h * k3e, state + h * k3s)
        eta = (h / 6.0) * (k1e + 2.0 * k2e + 2.0 * k3e + k4e)
        state = state + (h / 6.0) * (k1s + 2.0 * k2s + 2.0 * k3s + k4s)
        r_e, p_e = exp_se3(eta)
        return rotation @ r_e, position + np.einsum('kij,kj->ki', rotation, p_e), state


def _upper_symmetric(matrix: np.ndarray) -> np.ndarray:
    """Return the symmetric matrix of an upper triangle (Pinocchio's crba fills that)."""
    return np.triu(matrix) + np.triu(matrix, 1).T
