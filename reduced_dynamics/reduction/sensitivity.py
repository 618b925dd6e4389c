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
Sensitivities of the reduced flow: its state-transition matrix and the torque Jacobian.

The reduced flow of :class:`.ReducedPropagator` is the full free-floating flow
seen through the reduction map (REDUCED_MODEL.md 3-4): ``y = (q~1, qbar, pbar,
eta)`` gives ``v = M^-1 [pi(q~1); pbar + A^T pi]`` and the pose
``g = g_seg exp(eta)``. So the variational equations need only first
derivatives, of the full dynamics in body coordinates
``x = (theta, qbar, xi, qbar_dot)`` (the pose perturbed as ``g exp(theta)``)::

    theta_dot = -ad_xi theta + d xi
    d qbar_dot = d qbar_dot
    d v_dot = (d aba / d qbar) d qbar + (d aba / d v) d v + M^-1 [0; d tau]

(Pinocchio's ``computeABADerivatives`` at the base identity: by Theorem 51 the
body-frame dynamics do not depend on the pose), integrated alongside the
reduced flow by the same DOP853 (the base pose and the body dynamics never
see the charts, so re-centring leaves the matrices alone). The reduced
state-transition matrix follows by the chain rule through the reduction map
and its left inverse, whose derivatives are ``d(M w)/dqbar`` (RNEA derivatives,
REDUCED_MODEL.md 8): exact, no finite differences anywhere.

Reduced perturbations are ``r = (d q~1, d qbar, d pbar, theta)``: ``d q~1`` in
the chart of Q1/G_mu centred at the nominal point at that time
(``pi = Ad_{exp(C dq~1) chi}^T mu``), ``theta`` the body-frame pose
perturbation (``eta`` when the chart is centred). Held torques (constant over
the horizon, or a law of time only) get ``d x(t) / d tau``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Sequence, Union

import numpy as np
import pinocchio as pin

from reduced_dynamics.integrators import Budget, integrate_adaptive
from reduced_dynamics.reduction.reconstruction import ReducedPropagator, ReducedTrajectory
from reduced_dynamics.robot.model import RobotModel
from reduced_dynamics.robot.state import FreeFloatingState, TorqueLaw


@dataclass
class FlowSensitivity:
    """
    A reduced prediction with its sensitivities at every sample time.

    ``full[i]``: ``d x(t_i) / d x(t_0)`` with ``x = (theta, qbar, xi, qbar_dot)``
    (2n + 2m; the full-dynamics state-transition matrix, any perturbation,
    momentum included). ``torque[i]``: ``d x(t_i) / d tau`` (2n + 2m by m).
    ``reduced[i]``: ``d r(t_i) / d r(t_0)`` with ``r = (q~1, qbar, pbar, theta)``
    at fixed momentum mu (k + 2m + n), ``reduced_torque[i]``: ``d r(t_i) / d tau``.
    ``orbit_tangent[i]``: ``d pi / d q~1`` at t_i (n by k), to read ``d q~1`` as
    a body-momentum perturbation.
    """

    times: np.ndarray
    trajectory: ReducedTrajectory
    full: np.ndarray
    torque: np.ndarray
    reduced: np.ndarray
    reduced_torque: np.ndarray
    orbit_tangent: np.ndarray

    def pose_covariance(self, initial: np.ndarray, index: int = -1) -> np.ndarray:
        """
        Return the linearised covariance of ``theta`` at sample ``index``.

        ``initial`` is the covariance of ``x(t_0)`` (2n + 2m square), propagated
        as ``Phi P Phi^T``.
        """
        n = self.trajectory.pi.shape[1]
        phi = self.full[index][:n]
        return phi @ np.asarray(initial, dtype=float) @ phi.T


class _Variational:
    """The propagator's ODE with the full variational equations appended (ChartedSystem)."""

    def __init__(self, propagator: ReducedPropagator, torque_law: TorqueLaw) -> None:
        robot = propagator.system.robot
        self.propagator = propagator
        self.robot = robot
        self.group = robot.group
        self.torque_law = torque_law
        self.n, self.m = robot.n, robot.m
        self.size = 2 * (self.n + self.m)
        self.ny = propagator.nz + self.n
        self._data = robot.model.createData()
        self._q = pin.neutral(robot.model)
        self._tau = np.zeros(robot.model.nv)
        self._a = np.zeros((self.size, self.size))

    def linearisation(self, t: float, v: np.ndarray, qbar: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray]:
        """Return (A, B): ``d x_dot = A d x + B d tau`` at (qbar, v) under tau(t)."""
        n, m = self.n, self.m
        robot = self.robot
        self._q[robot.nq_base:] = qbar
        self._tau[n:] = self.torque_law(t, qbar, v[n:])
        ddq_dq, ddq_dv, minv = pin.computeABADerivatives(robot.model, self._data, self._q, v,
                                                         self._tau)
        a = self._a
        a[:] = 0.0
        # theta_dot = -ad_xi theta + d xi (g exp(theta), g_dot = g xi)
        a[:n, :n] = -self.group.ad(v[:n])
        a[:n, n + m:2 * n + m] = np.eye(n)
        a[n:n + m, 2 * n + m:] = np.eye(m)
        a[n + m:, n:n + m] = ddq_dq[:, n:]
        a[n + m:, n + m:] = ddq_dv
        b = np.zeros((self.size, m))
        b[n + m:] = minv[:, n:]
        return a, b

    def rhs(self, t: float, y: np.ndarray) -> np.ndarray:
        """dY/dt: the propagator's field, then Phi_dot = A Phi and Gamma_dot = A Gamma + B."""
        ny, size = self.ny, self.size
        out = np.empty(y.shape)
        propagator = self.propagator
        lean = propagator._lean_field()
        out[:ny] = lean(t, y[:ny], propagator.torque)
        k, m = propagator.system.k, self.m
        a, b = self.linearisation(t, lean.v.copy(), y[k:k + m])
        matrices = y[ny:].reshape(size, size + m)
        rates = out[ny:].reshape(size, size + m)
        np.matmul(a, matrices, out=rates)
        rates[:, size:] += b
        return out

    def chart_size(self, y: np.ndarray) -> float:
        """Return the propagator's chart size (the matrices are chart-free)."""
        return self.propagator.chart_size(y[:self.ny])

    def recentre(self, y: np.ndarray) -> np.ndarray:
        """Re-centre the propagator's charts; the body-frame matrices stay."""
        out = y.copy()
        out[:self.ny] = self.propagator.recentre(y[:self.ny])
        return out

    def observe(self, t: float, y: np.ndarray) -> np.ndarray:
        """[propagator record, matrices, d r / d x (reduced from full), d pi / d q~1]."""
        ny = self.ny
        record = self.propagator.observe(t, y[:ny])
        to_reduced, tangent = reduction_jacobians(self.propagator, y[:ny])[1:]
        return np.concatenate([record, y[ny:], to_reduced.ravel(), tangent.ravel()])


def orbit_tangent(propagator: ReducedPropagator, y: np.ndarray) -> np.ndarray:
    """
    Return ``d pi / d q~1`` (n by k) in the chart centred at chi(q~1) of y.

    ``pi(e) = Ad_{exp(C e) chi}^T mu`` gives columns ``Ad_chi^T ad_{c_j}^T mu``.
    """
    system = propagator.system
    group = system.group
    chi = system.chart.point(y[:system.k])
    ad_t = group.Ad(chi).T
    complement = system.isotropy.complement
    columns = [ad_t @ group.ad(complement[:, j]).T @ system.mu for j in range(system.k)]
    return np.array(columns).T.reshape(group.dim, system.k)


def reduction_jacobians(propagator: ReducedPropagator, y: np.ndarray
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """
    Return (d x / d r, d r / d x, d pi / d q~1) at the propagator state y.

    ``x = (theta, qbar, xi, qbar_dot)``, ``r = (q~1, qbar, pbar, theta)``. With
    ``D(w) = d(M w)/d qbar`` (RNEA derivatives), ``u~ = [I^-1 pi; 0]`` and
    ``J = d pi / d q~1``: ``d v = M^-1 ([J dq~1; dpbar + A^T J dq~1 +
    [-A; 1]^T D(u~) dqbar] - D(v) dqbar)`` (from ``M v = [pi; pbar + A^T pi]``);
    the left inverse reads ``d (M v) = M d v + D(v) d qbar``, ``d pbar =
    [-A; 1]^T (d (M v) - D(u~) d qbar)`` and ``d q~1 = J^+ d pi``.
    """
    system = propagator.system
    robot = system.robot
    n, m, k = robot.n, robot.m, system.k
    nz = k + 2 * m
    qbar = y[k:k + m]
    lean = propagator._lean_field()
    lean.kinematics(y)
    v = lean.v.copy()
    drift = lean.drift.copy()
    mass = robot.mass_matrix(qbar)
    d_drift, d_v = robot.mass_matrix_derivative_action(qbar, (drift, v))
    connection = np.linalg.solve(mass[:n, :n], mass[:n, n:])
    projection = np.vstack([-connection, np.eye(m)])      # [-A; 1] (nv x m)
    tangent = orbit_tangent(propagator, y)
    size, nr = 2 * (n + m), nz + n
    # Reduced -> full: columns for (q~1, qbar, pbar, theta).
    momentum = np.zeros((n + m, nr))                       # d [pi; p]
    momentum[:n, :k] = tangent
    momentum[n:, :k] = connection.T @ tangent
    momentum[n:, k:k + m] = projection.T @ d_drift
    momentum[n:, k + m:nz] = np.eye(m)
    momentum[:, k:k + m] -= d_v
    to_full = np.zeros((size, nr))
    to_full[:n, nz:] = np.eye(n)
    to_full[n:n + m, k:k + m] = np.eye(m)
    to_full[n + m:] = np.linalg.solve(mass, momentum)
    # Full -> reduced.
    to_reduced = np.zeros((nr, size))
    d_mv = np.zeros((n + m, size))
    d_mv[:, n + m:] = mass
    d_mv[:, n:n + m] = d_v
    d_pbar = projection.T @ d_mv
    d_pbar[:, n:n + m] -= projection.T @ d_drift
    if k:
        to_reduced[:k] = np.linalg.pinv(tangent) @ d_mv[:n]
    to_reduced[k:k + m, n:n + m] = np.eye(m)
    to_reduced[k + m:nz] = d_pbar
    to_reduced[nz:, :n] = np.eye(n)
    return to_full, to_reduced, tangent


def flow_sensitivity(robot: RobotModel, state: FreeFloatingState, times: Sequence[float],
                     torque: Union[None, np.ndarray, TorqueLaw] = None, rtol: float = 1e-10,
                     atol: float = 1e-10, budget: Optional[Budget] = None) -> FlowSensitivity:
    """
    Predict from a full state and return the state-transition matrices along the way.

    ``torque``: joint torques held over the horizon (an m-vector), or a law
    ``tau(t, qbar, qbar_dot)`` that depends on time only (its state dependence
    would be missed: the Jacobians treat it as an input); None is zero. The
    torque sensitivities are with respect to a constant added to it. DOP853
    with ``rtol``/``atol`` controls the error of the state and of the matrices.
    """
    law = _torque_law(robot, torque)
    propagator, y0 = ReducedPropagator.from_full_state(robot, state, law)
    variational = _Variational(propagator, law)
    size, m = variational.size, robot.m
    start = np.zeros((size, size + m))
    start[:, :size] = np.eye(size)
    # The reduction map at t0 (q~1 = 0: the chart is centred at the initial pose).
    to_full0 = reduction_jacobians(propagator, y0)[0]
    times = np.asarray(times, dtype=float)
    records = integrate_adaptive(variational, np.concatenate([y0, start.ravel()]), times,
                                 'DOP853', rtol, atol, budget=budget)
    nr = variational.ny
    width = 16 + robot.n + 3 * m + 1      # ReducedPropagator.observe's record
    trajectory = ReducedTrajectory(propagator.system, times, records[:, :width])
    offset = width
    matrices = records[:, offset:offset + size * (size + m)].reshape(-1, size, size + m)
    offset += size * (size + m)
    to_reduced = records[:, offset:offset + nr * size].reshape(-1, nr, size)
    offset += nr * size
    tangent = records[:, offset:].reshape(times.size, robot.n, propagator.system.k)
    full, torque_jac = matrices[:, :, :size], matrices[:, :, size:]
    reduced = to_reduced @ full @ to_full0
    return FlowSensitivity(times, trajectory, full.copy(), torque_jac.copy(), reduced,
                           to_reduced @ torque_jac, tangent)


def _torque_law(robot: RobotModel, torque: Union[None, np.ndarray, TorqueLaw]) -> TorqueLaw:
    if torque is None:
        torque = np.zeros(robot.m)
    if callable(torque):
        return torque
    held = np.asarray(torque, dtype=float)
    if held.shape != (robot.m,):
        raise ValueError(f'held torque has shape {held.shape}; expected ({robot.m},)')

    def law(t: float, qbar: np.ndarray, qbar_dot: np.ndarray) -> np.ndarray:
        return held
    return law
