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
from typing import Callable, Union

import numpy as np
import pinocchio as pin

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
