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

Two evaluations of the same field: :meth:`ReducedSystem.evaluate` forms H~, its
gradient and U explicitly (the discrete-gradient integrator needs them; the
signs are validated against full dynamics), and
:meth:`ReducedSystem.vector_field` contracts the magnetic terms through
Pinocchio's Coriolis matrix, about four times cheaper. The tests hold the two
equal. :class:`.ReducedPropagator` integrates a compiled copy of the latter
(:mod:`.lean_field`), held equal to it in the tests.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Optional, Union

import numpy as np
import pinocchio as pin
from scipy.linalg.lapack import dgesv, dposv

from reduced_dynamics.geometry.chart import CosetChart
from reduced_dynamics.geometry.isotropy import isotropy_algebra, IsotropyAlgebra, RANK_RTOL
from reduced_dynamics.geometry.lie_group import SUBGROUPS
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
        self._fast = _FastConstants(robot, self.mu, self.isotropy.complement)
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

    def vector_field(self, z: np.ndarray, tau: Torque,
                     out: Optional[np.ndarray] = None) -> tuple[np.ndarray, np.ndarray]:
        """
        Return (z_dot, xi): the vector field of :meth:`evaluate`, by a cheaper route.

        Same equations (Theorem 54), with the magnetic terms contracted before
        they are formed: no derivative tensor, no U matrix. With
        ``u~ = [I^-1 pi; 0]``, ``w = M^-1 [0; pbar] = [-A qbar_dot; qbar_dot]`` and
        ``v = u~ + w = [xi; qbar_dot]`` (REDUCED_MODEL.md 3-4), Pinocchio's
        Coriolis matrix C = C(q, v) gives ``M_dot = C + C^T`` and
        ``dT/dqbar|_v = (C^T v)_qbar`` (checked in the tests). Then:

        * ``pbar_dot = [-A; 1]^T (C^T w - C u~) - dV/dqbar + tau``: the third
          equation of Thm 54 in the bundle form of REDUCED_MODEL.md 7. By the
          Legendre transform (pbar = p - A^T pi), ``-dH~/dqbar|_pi + C_A qbar_dot
          - A^T pi_dot = dT/dqbar|_v - (dA/dt)^T pi - A^T pi_dot``; the base rows
          of the full equations give ``pi_dot = (C^T v)_base``, and
          ``(dA/dt)^T pi = [-A; 1]^T M_dot u~`` from A = I^-1 B (5.29).
        * ``L^T W^T L q~1_dot = L^T W^T xi`` (W the Kirillov form at pi, L the
          chart Jacobian): the second equation, since ``U[q~1, q~1] = L^T W L``,
          ``U[qbar, q~1] = A^T W L`` and ``dH~/dq~1 = -(W L)^T I^-1 pi``
          (:mod:`.magnetic`) combine to ``(W L)^T xi`` on the right.

        ``tau`` is an array or a function tau(qbar, qbar_dot). z_dot is written to
        ``out[:len(z)]`` when ``out`` is given (an integrator's stage buffer). The
        tests check this against :meth:`evaluate` on every momentum class and base
        group.
        """
        k, m = self.k, self.m
        fast = self._fast
        n = fast.n
        q1, qbar, pbar = z[:k], z[k:k + m], z[k + m:]
        twist, chi = self._chart_point(q1)
        pi, u, connection, w = self._momenta(chi, qbar, pbar)
        qbar_dot = w[n:]
        drift = fast.drift
        drift[:n] = u
        v = w + drift
        xi = v[:n]
        work = fast.work
        coriolis = pin.computeCoriolisMatrix(work.kinetic_model, work.kinetic_data, work.q, v)
        # h = C^T w - C u~: pbar_dot = h_qbar - A^T h_base (+ tau - dV/dqbar).
        h = w @ coriolis
        h -= coriolis @ drift
        if callable(tau):
            tau = tau(qbar, qbar_dot)
        z_dot = np.empty(k + 2 * m) if out is None else out[:k + 2 * m]
        pbar_dot = z_dot[k + m:]
        np.subtract(h[n:], connection.T @ h[:n], out=pbar_dot)
        pbar_dot += tau
        if fast.potential:
            pbar_dot -= self.robot.potential_gradient(qbar)
        z_dot[k:k + m] = qbar_dot
        if k:
            # By coadjoint equivariance, with Ad_chi S L = Jexp6(-S C q~1) S C (the left
            # Jacobian of exp), L^T W(pi)^T L = P^T W(mu)^T P and L^T W(pi)^T xi =
            # P^T W(mu)^T Ad_chi xi, P = Ad_chi S L: W(mu) is constant, so no W(pi).
            spatial = pin.Jexp6(-twist) @ fast.chart_twist
            kirillov_t = spatial.T @ fast.kirillov_mu_t
            xi_world = chi.action @ (xi if fast.whole else fast.basis @ xi)
            _, _, q1_dot, info = dgesv(kirillov_t @ spatial, kirillov_t @ xi_world)
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
        pi, u, _, w = self._momenta(self._chart_point(q1)[1], qbar, pbar)
        n = self._fast.n
        qbar_dot = w[n:]
        energy = 0.5 * float(pi @ u) + 0.5 * float(pbar @ qbar_dot) \
            + self.robot.potential_energy(qbar)
        return pi, u + w[:n], qbar_dot, energy

    def _momenta(self, chi: pin.SE3, qbar: np.ndarray, pbar: np.ndarray) -> tuple:
        """
        Return (pi, I^-1 pi, A, w = M^-1 [0; pbar]) at chi = chi(q~1) and (qbar, pbar).

        ``pi = Ad_chi^T mu``; ``w = [-A qbar_dot; qbar_dot]`` with ``qbar_dot = S^-1
        pbar`` (S is the Schur complement of I in M, so one solve with M gives
        both). Leaves M(qbar) in the workspace's configuration for C(q, v).
        """
        fast = self._fast
        n = fast.n
        wrench = chi.action.T @ fast.mu6
        pi = wrench if fast.whole else fast.basis.T @ wrench
        work = fast.work
        work.q[work.nq_base:] = qbar
        mass = pin.crba(work.model, work.data, work.q)
        # LAPACK dposv reads the upper triangle only: no mirroring of crba's M.
        rhs = fast.locked_rhs
        rhs[:, 0] = pi
        rhs[:, 1:] = mass[:n, n:]
        _, solution, info = dposv(mass[:n, :n], rhs)
        if info:
            raise np.linalg.LinAlgError('locked inertia I is not positive definite')
        shape_rhs = fast.shape_rhs
        shape_rhs[n:] = pbar
        _, w, info = dposv(mass, shape_rhs)
        if info:
            raise np.linalg.LinAlgError('mass matrix M is not positive definite')
        return pi, solution[:, 0], solution[:, 1:], w

    def _chart_point(self, q1: np.ndarray) -> tuple[np.ndarray, pin.SE3]:
        """Return (S C q~1, chi(q~1)); refreshes the cached chart constants after a re-centring."""
        fast = self._fast
        if self._fast_chart is not self.chart:
            self._fast_chart = self.chart
            fast.g_ref = pin.SE3(self.chart.g_ref)
        if not self.k:
            return fast.zero_twist, fast.g_ref
        twist = fast.chart_twist @ q1
        return twist, pin.exp6(twist) * fast.g_ref

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

    def __init__(self, robot: RobotModel, mu: np.ndarray, complement: np.ndarray) -> None:
        group = robot.group
        basis = group.algebra_basis
        n, m = group.dim, robot.m
        self.n = n
        self.basis = basis
        self.whole = group.is_whole
        self.pinv = group.algebra_pinv
        self.work = robot.kinetic_workspace()
        self.potential = robot.has_potential
        # pi = Ad_chi^T mu = S^T Ad6_chi^T (S+)^T mu: the lift of mu is fixed.
        self.mu6 = self.pinv.T @ mu
        # W(mu)^T in se(3): W[a, b] = <mu, [e_a, e_b]>, mu lifted to se*(3).
        self.kirillov_mu_t = SUBGROUPS['SE(3)'].coadjoint_form(self.mu6).T.copy()
        # Chart twist S C q~1 (a subalgebra element: Jexp6 keeps it in span(S)).
        self.chart_twist = basis @ complement
        self.locked_rhs = np.empty((n, 1 + m), order='F')
        self.shape_rhs = np.zeros(n + m)
        # u~ = [I^-1 pi; 0]: the velocity of the locked system (drift).
        self.drift = np.zeros(n + m)
        self.zero_twist = np.zeros(6)
        self.g_ref = pin.SE3.Identity()


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
