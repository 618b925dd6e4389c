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
Reduced Hamilton equations at fixed momentum mu (Theorem 54, Corollary 55).

State ``z = (q~1, qbar, pbar)``: chart coordinates of Q1/G_mu, shape, reduced
shape momentum. With ``U`` the magnetic form (:mod:`.magnetic`) and torques
``tau`` on the shape, ``i_X(-dpbar ^ dqbar - Xi_mu) = dH~`` reads
(REDUCED_MODEL.md 7)::

    qbar_dot = S^-1 pbar
    U[q~1, q~1]^T q~1_dot = -dH~/dq~1 - U[qbar, q~1]^T qbar_dot
    pbar_dot = -dH~/dqbar - U[:, qbar]^T x_dot + tau

For mu = 0 (k = 0, U = 0) the shape follows geodesics of S plus tau
(Corollary 55). The base pose is reconstructed from ``g_dot = g xi`` with
``xi = I^-1 pi - A qbar_dot``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Optional, Union

import numpy as np
import pinocchio as pin
from scipy.linalg.lapack import dgesv, dposv

from reduced_dynamics.geometry.chart import CosetChart
from reduced_dynamics.geometry.isotropy import isotropy_algebra, IsotropyAlgebra, RANK_RTOL
from reduced_dynamics.reduction.hamiltonian import shape_terms, ShapeTerms
from reduced_dynamics.reduction.magnetic import magnetic_form
from reduced_dynamics.robot.model import RobotModel
from reduced_dynamics.robot.momentum import body_momentum, momentum_map, reduced_momentum
from reduced_dynamics.robot.state import FreeFloatingState

#: Shape torques: an array, or tau(qbar, qbar_dot) for a feedback law.
Torque = Union[np.ndarray, Callable[[np.ndarray, np.ndarray], np.ndarray]]


@dataclass
class ReducedEvaluation:
    """Everything one evaluation of the reduced vector field produces."""

    z_dot: np.ndarray
    xi: np.ndarray
    pi: np.ndarray
    energy: float
    gradient: np.ndarray
    structure: np.ndarray
    terms: ShapeTerms


class ReducedSystem:
    """
    The reduced Hamiltonian system of a robot at a fixed momentum mu (Thm 54).

    The chart of Q1/G_mu is centred at ``g_ref`` and re-centred by
    :meth:`recentre`; ``mu`` is in world-frame coordinates of the base group's dual.
    """

    def __init__(self, robot: RobotModel, mu: np.ndarray, g_ref: pin.SE3,
                 rank_rtol: float = RANK_RTOL) -> None:
        """Set up the isotropy algebra of mu and a chart of Q1/G_mu at ``g_ref``."""
        self.robot = robot
        self.group = robot.group
        self.mu = np.asarray(mu, dtype=float)
        self.isotropy: IsotropyAlgebra = isotropy_algebra(self.group, self.mu, rank_rtol)
        self.chart = CosetChart(self.group, self.isotropy.complement, pin.SE3(g_ref))
        self.k = self.isotropy.orbit_dim
        self.m = robot.m
        self._fast = _FastConstants(self.group, self.mu, self.isotropy.complement, self.m)
        self._fast_chart: Optional[CosetChart] = None

    @classmethod
    def from_full_state(cls, robot: RobotModel, state: FreeFloatingState,
                        rank_rtol: float = RANK_RTOL) -> tuple['ReducedSystem', np.ndarray]:
        """Return the reduced system through a full state, and its z (q~1 = 0 at g)."""
        blocks = robot.metric_blocks(state.qbar)
        pi = body_momentum(blocks, state.xi, state.qbar_dot)
        system = cls(robot, momentum_map(robot.group, state.g, pi), state.g, rank_rtol)
        z = np.concatenate([np.zeros(system.k), state.qbar,
                            reduced_momentum(blocks, state.qbar_dot)])
        return system, z

    def split(self, z: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(q~1, qbar, pbar) views of z."""
        k, m = self.k, self.m
        return z[:k], z[k:k + m], z[k + m:]

    def body_momentum(self, q1: np.ndarray) -> np.ndarray:
        """pi(q~1) = Ad_chi(q~1)^T mu: the point of the coadjoint orbit."""
        return self.group.Ad(self.chart.point(q1)).T @ self.mu

    def hamiltonian(self, z: np.ndarray) -> float:
        """H~(q~1, qbar, pbar) (5.36)."""
        q1, qbar, pbar = self.split(z)
        pi = self.body_momentum(q1)
        blocks = self.robot.metric_blocks(qbar)
        qbar_dot = np.linalg.solve(blocks.reduced_metric, pbar)
        return 0.5 * float(pi @ blocks.solve_locked(pi)) + 0.5 * float(pbar @ qbar_dot) \
            + self.robot.potential_energy(qbar)

    def evaluate(self, z: np.ndarray, tau: Torque) -> ReducedEvaluation:
        """
        Return the vector field of Theorem 54 at z with shape torques tau.

        ``tau`` is an array or a function tau(qbar, qbar_dot) (for feedback laws).
        """
        k, m = self.k, self.m
        q1, qbar, pbar = self.split(z)
        pi = self.body_momentum(q1)
        terms = shape_terms(self.robot, pi, qbar, pbar)
        jac = self.chart.body_jacobian(q1)
        form, kirillov_jac = magnetic_form(self.group, pi, jac, terms.blocks.connection,
                                           terms.curvature)
        lower = form[k:, :k]
        dH_dq1 = -(kirillov_jac.T @ terms.locked_velocity)
        qbar_dot = terms.qbar_dot
        if k:
            rhs = -dH_dq1 - lower.T @ qbar_dot
            q1_dot = np.linalg.solve(form[:k, :k].T, rhs)
        else:
            q1_dot = np.zeros(0)
        x_dot = np.concatenate([q1_dot, qbar_dot])
        if callable(tau):
            tau = tau(qbar, qbar_dot)
        pbar_dot = -terms.dH_dqbar - form[:, k:].T @ x_dot + tau
        gradient = np.concatenate([dH_dq1, terms.dH_dqbar, qbar_dot])
        structure = np.zeros((k + 2 * m, k + 2 * m))
        structure[:k + m, :k + m] = form
        diagonal = np.arange(m)
        structure[k + diagonal, k + m + diagonal] = -1.0
        structure[k + m + diagonal, k + diagonal] = 1.0
        return ReducedEvaluation(np.concatenate([q1_dot, qbar_dot, pbar_dot]), terms.xi, pi,
                                 terms.energy, gradient, structure, terms)

    def vector_field(self, z: np.ndarray, tau: Torque) -> tuple[np.ndarray, np.ndarray]:
        """
        Return (z_dot, xi): the vector field of :meth:`evaluate`, by a cheaper route.

        Same equations (Theorem 54), with the magnetic terms contracted before
        they are formed, so no derivative tensor and no U matrix is built. With
        ``v = [xi; qbar_dot]``, Pinocchio's Coriolis matrix C(q, v) gives
        ``M_dot = C + C^T`` and ``dT/dqbar|_v = (C^T v)_qbar``. Then, using
        ``pi_dot = ad_xi^T pi = W^T xi`` (5.27 conserved mu; W the Kirillov form):

        * ``L^T W^T L q~1_dot = L^T pi_dot``: the second equation of Thm 54, since
          ``U[q~1, q~1] = L^T W L``, ``U[qbar, q~1] = A^T W L`` and
          ``dH~/dq~1 = -(W L)^T I^-1 pi`` combine to ``(W L)^T xi`` on the right;
        * ``pbar_dot = dT/dqbar|_v - [-A; 1]^T M_dot [I^-1 pi; 0] - A^T pi_dot
          - dV/dqbar + tau``: the third equation, written as the bundle form of
          REDUCED_MODEL.md 7 (``-dH~/dqbar|_pi + C_A qbar_dot = dT/dqbar|_v -
          (d/dt A)^T pi``, Legendre transform with pbar = p - A^T pi).

        ``tau`` is an array or a function tau(qbar, qbar_dot). The tests check
        this against :meth:`evaluate` on every momentum class and base group.
        """
        k, m = self.k, self.m
        fast = self._fast
        n = fast.n
        q1, qbar, pbar = z[:k], z[k:k + m], z[k + m:]
        chart_lift, pi, mass, u, connection, qbar_dot = self._momenta(q1, qbar, pbar)
        v = fast.velocity
        v[:n] = u - connection @ qbar_dot
        v[n:] = qbar_dot
        xi = v[:n].copy()
        coriolis = self.robot.coriolis_matrix(qbar, v)
        # M_dot [u; 0] = (C + C^T) [u; 0].
        mdot_u = coriolis[:, :n] @ u + coriolis[:n].T @ u
        kirillov_t = (pi @ fast.kirillov_map).reshape(n, n).T
        pi_dot = kirillov_t @ xi
        if callable(tau):
            tau = tau(qbar, qbar_dot)
        z_dot = np.empty(k + 2 * m)
        pbar_dot = z_dot[k + m:]
        np.matmul(v, coriolis[:, n:], out=pbar_dot)
        pbar_dot -= mdot_u[n:]
        pbar_dot += connection.T @ (mdot_u[:n] - pi_dot)
        pbar_dot += tau
        if self.robot.has_potential:
            pbar_dot -= self.robot.potential_gradient(qbar)
        z_dot[k:k + m] = qbar_dot
        if k:
            jac = chart_lift @ pin.Jexp6(fast.chart_twist @ q1) @ fast.chart_twist
            jac_t = jac.T
            _, _, q1_dot, info = dgesv(jac_t @ (kirillov_t @ jac), jac_t @ pi_dot)
            if info:
                raise np.linalg.LinAlgError('orbit form L^T W L is singular')
            z_dot[:k] = q1_dot
        return z_dot, xi

    def kinematics(self, z: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        """
        Return (pi, xi, qbar_dot, H~) at z: what an observer records, without derivatives.

        ``pi = Ad_chi^T mu``, ``qbar_dot = S^-1 pbar``, ``xi = I^-1 pi - A qbar_dot``
        (REDUCED_MODEL.md 4) and H~ (5.36).
        """
        k, m = self.k, self.m
        q1, qbar, pbar = z[:k], z[k:k + m], z[k + m:]
        _, pi, _, u, connection, qbar_dot = self._momenta(q1, qbar, pbar)
        energy = 0.5 * float(pi @ u) + 0.5 * float(pbar @ qbar_dot) \
            + self.robot.potential_energy(qbar)
        return pi, u - connection @ qbar_dot, qbar_dot, energy

    def _momenta(self, q1: np.ndarray, qbar: np.ndarray, pbar: np.ndarray) -> tuple:
        """Return (chart lift, pi, M upper, I^-1 pi, A, qbar_dot) at one z."""
        fast = self._fast
        n = fast.n
        chart_lift, chi = self._chart_point(q1)
        pi = fast.body_momentum(chi)
        mass = self.robot.mass_matrix_upper(qbar)
        # One Cholesky of I for I^-1 pi and A = I^-1 B (5.29); dposv reads the upper triangle.
        rhs = fast.locked_rhs
        rhs[:, 0] = pi
        rhs[:, 1:] = mass[:n, n:]
        _, solution, info = dposv(mass[:n, :n], rhs)
        if info:
            raise np.linalg.LinAlgError('locked inertia I is not positive definite')
        connection = solution[:, 1:]
        if not self.m:
            return chart_lift, pi, mass, solution[:, 0], connection, np.zeros(0)
        _, qbar_dot, info = dposv(mass[n:, n:] - mass[:n, n:].T @ connection, pbar)
        if info:
            raise np.linalg.LinAlgError('reduced metric S is not positive definite')
        return chart_lift, pi, mass, solution[:, 0], connection, qbar_dot

    def _chart_point(self, q1: np.ndarray) -> tuple[np.ndarray, pin.SE3]:
        """Return (Ad(g_ref^-1) restricted, chi(q~1)), caching what depends on the chart only."""
        fast = self._fast
        if self._fast_chart is not self.chart:
            self._fast_chart = self.chart
            fast.g_ref = pin.SE3(self.chart.g_ref)
            fast.chart_lift = fast.pinv @ fast.g_ref.inverse().action
        if not self.k:
            return fast.chart_lift, fast.g_ref
        return fast.chart_lift, pin.exp6(fast.chart_twist @ q1) * fast.g_ref

    def recentre(self, z: np.ndarray) -> np.ndarray:
        """Move the chart centre to chi(q~1); returns z with q~1 = 0."""
        q1, _, _ = self.split(z)
        self.chart = self.chart.recentred(q1)
        out = z.copy()
        out[:self.k] = 0.0
        return out

    def full_state(self, z: np.ndarray, g: pin.SE3) -> FreeFloatingState:
        """Return the full state with base pose g (reconstructed separately) at z."""
        q1, qbar, pbar = self.split(z)
        terms = shape_terms(self.robot, self.body_momentum(q1), qbar, pbar)
        return FreeFloatingState(pin.SE3(g), terms.xi, qbar.copy(), terms.qbar_dot)


class _FastConstants:
    """Work buffers and group constants of :meth:`ReducedSystem.vector_field`."""

    def __init__(self, group, mu: np.ndarray, complement: np.ndarray, m: int) -> None:
        basis = group.algebra_basis
        n = group.dim
        self.n = n
        self.basis = basis
        self.full = n == 6 and bool(np.array_equal(basis, np.eye(6)))
        self.pinv = np.linalg.pinv(basis)
        # pi = Ad_chi^T mu = S^T Ad6_chi^T (S+)^T mu: the lift of mu is fixed.
        self.mu6 = self.pinv.T @ mu
        # W = (pi @ kirillov_map).reshape(n, n) with W[a, b] = <pi, [e_a, e_b]>.
        self.kirillov_map = np.ascontiguousarray(
            group.structure_constants.transpose(1, 0, 2).reshape(n, n * n))
        # Chart twist S C q~1 (a subalgebra element: Jexp6 keeps it in span(S)).
        self.chart_twist = basis @ complement
        self.locked_rhs = np.empty((n, 1 + m), order='F')
        self.velocity = np.empty(n + m)
        self.g_ref = pin.SE3.Identity()
        self.chart_lift = np.eye(n)

    def body_momentum(self, chi: pin.SE3) -> np.ndarray:
        """Return pi = Ad_chi^T mu in the group's coordinates."""
        wrench = chi.action.T @ self.mu6
        return wrench if self.full else self.basis.T @ wrench


def bundle_vector_field(robot: RobotModel, pi: np.ndarray, qbar: np.ndarray,
                        pbar: np.ndarray, tau: np.ndarray) -> tuple[np.ndarray, ...]:
    """
    Return the chart-free "bundle" form (REDUCED_MODEL.md 7): (pi_dot, qbar_dot, pbar_dot, xi).

    ``pi_dot = ad_xi^T pi``, ``pbar_dot = -dH~/dqbar|pi + C qbar_dot - A^T pi_dot + tau``.
    """
    terms = shape_terms(robot, pi, qbar, pbar)
    pi_dot = robot.group.ad(terms.xi).T @ pi
    pbar_dot = -terms.dH_dqbar + terms.curvature @ terms.qbar_dot \
        - terms.blocks.connection.T @ pi_dot + tau
    return pi_dot, terms.qbar_dot, pbar_dot, terms.xi
