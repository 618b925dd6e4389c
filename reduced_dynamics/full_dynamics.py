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
Ground truth: full free-floating dynamics with Pinocchio ``aba`` (REDUCED_MODEL.md 9).

State ``y = (eta, qbar, xi, qbar_dot)`` with base pose ``g = g_seg exp(eta)``
(a chart re-centred by the integrator), body twist ``xi`` and shape rates.
Joint torques act on the shape; an optional external wrench acts on the base
body, given in the base frame (a thruster) and reported in the world frame.
"""

from __future__ import annotations

from typing import Callable, Optional, Sequence

import numpy as np
import pinocchio as pin

from reduced_dynamics.integrators import integrate_adaptive, integrate_pieces
from reduced_dynamics.robot.model import RobotModel
from reduced_dynamics.robot.momentum import momentum_map
from reduced_dynamics.robot.state import FreeFloatingState, TorqueLaw, zero_torque

#: A base-frame wrench w(t) = (force, torque) on the base body, 6-vector.
WrenchLaw = Callable[[float], np.ndarray]


class FullDynamics:
    """Free-floating rigid-body dynamics (Pinocchio ABA), the reference model."""

    def __init__(self, robot: RobotModel, torque: Optional[TorqueLaw] = None,
                 base_wrench: Optional[WrenchLaw] = None) -> None:
        """Dynamics of ``robot`` under shape torques and an optional base wrench."""
        self.robot = robot
        self.torque = torque or zero_torque(robot.m)
        self.base_wrench = base_wrench
        self.g_seg = pin.SE3.Identity()
        self._data = robot.model.createData()
        self._fext = [pin.Force.Zero() for _ in range(robot.model.njoints)]
        n, m = robot.n, robot.m
        self._slices = (slice(0, n), slice(n, n + m), slice(n + m, 2 * n + m),
                        slice(2 * n + m, 2 * n + 2 * m))
        # Joint torques with the unactuated base rows kept at zero (aba's tau).
        self._tau = np.zeros(n + m)
        self._q = np.empty(robot.model.nq)

    def pose(self, y: np.ndarray) -> pin.SE3:
        """Return base pose g of state y."""
        return self.g_seg * self.robot.group.exp(y[self._slices[0]])

    def pack(self, state: FreeFloatingState) -> np.ndarray:
        """State vector y for a full state (chart centred at its pose)."""
        self.g_seg = pin.SE3(state.g)
        return np.concatenate([np.zeros(self.robot.n), state.qbar, state.xi, state.qbar_dot])

    def unpack(self, y: np.ndarray) -> FreeFloatingState:
        """Full state of y."""
        s = self._slices
        return FreeFloatingState(self.pose(y), y[s[2]].copy(), y[s[1]].copy(), y[s[3]].copy())

    def acceleration(self, t: float, g: pin.SE3, qbar: np.ndarray, xi: np.ndarray,
                     qbar_dot: np.ndarray) -> np.ndarray:
        """Generalised acceleration [xi_dot; qbar_ddot] from ABA."""
        return self._aba(t, g, qbar, np.concatenate([xi, qbar_dot]))

    def _aba(self, t: float, g: pin.SE3, qbar: np.ndarray, v: np.ndarray) -> np.ndarray:
        robot = self.robot
        q = self._q
        q[:robot.nq_base] = robot.base_configuration(g)
        q[robot.nq_base:] = qbar
        tau = self._tau
        tau[robot.n:] = self.torque(t, qbar, v[robot.n:])
        if self.base_wrench is None:
            return pin.aba(robot.model, self._data, q, v, tau)
        self._fext[1] = pin.Force(np.asarray(self.base_wrench(t), dtype=float))
        return pin.aba(robot.model, self._data, q, v, tau, self._fext)

    def rhs(self, t: float, y: np.ndarray) -> np.ndarray:
        """dy/dt."""
        s = self._slices
        eta, qbar, xi = y[s[0]], y[s[1]], y[s[2]]
        out = np.empty(y.shape)
        # y = (eta, qbar, xi, qbar_dot): v = (xi, qbar_dot) is one contiguous slice.
        v = y[s[2].start:]
        out[s[2].start:] = self._aba(t, self.pose(y), qbar, v)
        np.matmul(self.robot.group.right_jacobian_inverse(eta), xi, out=out[s[0]])
        out[s[1]] = v[self.robot.n:]
        return out

    def chart_size(self, y: np.ndarray) -> float:
        """Norm of the base chart coordinates."""
        return float(np.linalg.norm(y[self._slices[0]]))

    def recentre(self, y: np.ndarray) -> np.ndarray:
        """Move the base chart to the current pose."""
        self.g_seg = self.pose(y)
        out = y.copy()
        out[self._slices[0]] = 0.0
        return out

    def observe(self, t: float, y: np.ndarray) -> np.ndarray:
        """[g (4x4 flattened, 16), xi, qbar, qbar_dot, mu]."""
        s = self._slices
        g = self.pose(y)
        # pi = (M v)_base = I xi + B qbar_dot (5.27) from the base rows of M alone.
        pi = self.robot.mass_matrix(y[s[1]])[:self.robot.n] @ y[s[2].start:]
        return np.concatenate([g.homogeneous.ravel(), y[s[2]], y[s[1]], y[s[3]],
                               momentum_map(self.robot.group, g, pi)])

    def world_wrench(self, t: float, g: pin.SE3) -> np.ndarray:
        """Return the external wrench in the world frame about the origin (= d mu / dt)."""
        if self.base_wrench is None:
            return np.zeros(self.robot.n)
        wrench6 = np.asarray(self.base_wrench(t), dtype=float)
        return self.robot.group.Ad(g.inverse()).T @ self.robot.group.dual_coordinates(wrench6)

    def simulate(self, state: FreeFloatingState, times: Sequence[float], rtol: float = 1e-12,
                 atol: float = 1e-12, method: str = 'DOP853',
                 max_step: float = np.inf) -> 'FullTrajectory':
        """Integrate from ``state`` at times[0]; sample at ``times``."""
        records = integrate_adaptive(self, self.pack(state), times, method, rtol, atol,
                                     max_step=max_step)
        return FullTrajectory(self.robot, np.asarray(times, dtype=float), records)


class PrescribedShapeDynamics:
    """
    Full dynamics with the shape path prescribed: the arm tracks q(t) exactly.

    The shape is a rheonomic constraint; the base obeys the base rows of the
    full equations of motion, ``I xi_dot + (B q_ddot + c(q, v))_base = 0``
    (RNEA with zero base acceleration gives the bracket), integrated as a
    second-order ODE on the base group: state y = (eta, xi), g = g_seg exp(eta).
    The joint torques that realise the motion are the shape rows of RNEA.
    This is the simulator's ground truth for predictions of planned motions
    (independent of the reduction: it never uses mu or the connection).
    """

    def __init__(self, robot: RobotModel, path: Callable) -> None:
        """Track ``path`` (t -> q, q_dot, q_ddot; with ``breakpoints``)."""
        self.robot = robot
        self.path = path
        self.g_seg = pin.SE3.Identity()
        self._data = robot.model.createData()
        self._q = np.empty(robot.model.nq)
        self._a = np.zeros(robot.model.nv)

    def pose(self, y: np.ndarray) -> pin.SE3:
        """Return base pose g of state y."""
        return self.g_seg * self.robot.group.exp(y[:self.robot.n])

    def _terms(self, t: float, y: np.ndarray) -> tuple:
        robot, n = self.robot, self.robot.n
        qbar, qbar_dot, qbar_ddot = self.path(t)
        q = self._q
        q[:robot.nq_base] = robot.base_configuration(self.pose(y))
        q[robot.nq_base:] = qbar
        v = np.concatenate([y[n:], qbar_dot])
        a = self._a
        a[:n] = 0.0
        a[n:] = qbar_ddot
        bias = pin.rnea(robot.model, self._data, q, v, a)[:n].copy()
        locked = pin.crba(robot.model, self._data, q)[:n, :n]
        xi_dot = -np.linalg.solve(locked, bias)
        return q, v, a, xi_dot

    def rhs(self, t: float, y: np.ndarray) -> np.ndarray:
        """dy/dt: eta_dot = Jr(eta)^-1 xi, xi_dot from the base rows."""
        n = self.robot.n
        out = np.empty(y.shape)
        out[n:] = self._terms(t, y)[3]
        out[:n] = self.robot.group.right_jacobian_inverse(y[:n]) @ y[n:]
        return out

    def chart_size(self, y: np.ndarray) -> float:
        """Norm of the base chart coordinates."""
        return float(np.linalg.norm(y[:self.robot.n]))

    def recentre(self, y: np.ndarray) -> np.ndarray:
        """Move the base chart to the current pose."""
        self.g_seg = self.pose(y)
        out = y.copy()
        out[:self.robot.n] = 0.0
        return out

    def observe(self, t: float, y: np.ndarray) -> np.ndarray:
        """[g (16), xi, qbar, qbar_dot, mu, joint torques]."""
        robot, n = self.robot, self.robot.n
        q, v, a, xi_dot = self._terms(t, y)
        a = a.copy()
        a[:n] = xi_dot
        torques = pin.rnea(robot.model, self._data, q, v, a)[n:].copy()
        qbar = q[robot.nq_base:].copy()
        g = self.pose(y)
        pi = robot.mass_matrix(qbar)[:n] @ v
        return np.concatenate([g.homogeneous.ravel(), y[n:], qbar, v[n:],
                               momentum_map(robot.group, g, pi), torques])

    def velocity_jump(self, t: float, y: np.ndarray) -> np.ndarray:
        """
        Carry the base twist across a jump of q_dot (a knot of a linear path).

        The impulsive joint forces are internal: pi = I xi + B q_dot is the
        same just before and after, so xi+ = I^-1 (pi - B q_dot+).
        """
        before, after = self.path.velocity_limits(t)
        if np.array_equal(before, after):
            return y
        n = self.robot.n
        mass = self.robot.mass_matrix(self.path(t)[0])
        out = y.copy()
        out[n:] = y[n:] + np.linalg.solve(mass[:n, :n], mass[:n, n:] @ (before - after))
        return out

    def simulate(self, g0: pin.SE3, xi0: np.ndarray, times: Sequence[float],
                 rtol: float = 1e-12, atol: float = 1e-12) -> 'FullTrajectory':
        """Integrate from base pose g0 and twist xi0 at times[0] (shape on the path)."""
        self.g_seg = pin.SE3(g0)
        y0 = np.concatenate([np.zeros(self.robot.n), np.asarray(xi0, dtype=float)])
        times = np.asarray(times, dtype=float)
        records = integrate_pieces(self, y0, times, getattr(self.path, 'breakpoints', ()),
                                   rtol, atol, jump=self.velocity_jump)
        trajectory = FullTrajectory(self.robot, times, records[:, :-self.robot.m]
                                    if self.robot.m else records)
        trajectory.torques = records[:, records.shape[1] - self.robot.m:]
        return trajectory


class FullTrajectory:
    """Samples of a full-dynamics run: poses, twists, shape, rates and mu."""

    def __init__(self, robot: RobotModel, times: np.ndarray, records: np.ndarray) -> None:
        """Split observe() records into named arrays."""
        n, m = robot.n, robot.m
        self.robot = robot
        self.times = times
        self.poses = records[:, :16].reshape(-1, 4, 4)
        self.xi = records[:, 16:16 + n]
        self.qbar = records[:, 16 + n:16 + n + m]
        self.qbar_dot = records[:, 16 + n + m:16 + n + 2 * m]
        self.mu = records[:, 16 + n + 2 * m:]

    def pose(self, index: int) -> pin.SE3:
        """Return base pose at sample ``index``."""
        return pin.SE3(self.poses[index])

    def state(self, index: int) -> FreeFloatingState:
        """Full state at sample ``index``."""
        return FreeFloatingState(self.pose(index), self.xi[index].copy(),
                                 self.qbar[index].copy(), self.qbar_dot[index].copy())
