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
Reduced Hamiltonian H~ (5.36) and the shape-space terms its equations need.

``H~ = 1/2 pi^T I^-1 pi + 1/2 pbar^T S^-1 pbar + V`` (REDUCED_MODEL.md 6): the
amended potential of the locked body plus the shape kinetic energy. Its shape
gradient and the curvature term ``C[i, j] = d_i (A^T pi)_j - d_j (A^T pi)_i``
come from two RNEA-derivative calls (REDUCED_MODEL.md 8): with
``u~ = [I^-1 pi; 0]`` and ``w = [-A qbar_dot; qbar_dot]``,
``d_i(1/2 pi^T I^-1 pi) = -1/2 u~^T d_iM u~``, ``d_i(1/2 pbar^T S^-1 pbar) =
-1/2 w^T d_iM w`` and ``pi^T d_i A_j = [-A; 1]_j^T d_iM u~``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Union

import numpy as np

from reduced_dynamics.robot.model import MetricBlocks, RobotModel

#: Rows or columns of M: a slice or an index array.
IndexLike = Union[slice, np.ndarray]


@dataclass
class ShapeTerms:
    """H~ and its shape derivatives at (pi, qbar, pbar), pi held fixed."""

    blocks: MetricBlocks
    pi: np.ndarray
    locked_velocity: np.ndarray
    qbar_dot: np.ndarray
    xi: np.ndarray
    energy: float
    dH_dqbar: np.ndarray
    curvature: np.ndarray


def reduced_hamiltonian(robot: RobotModel, pi: np.ndarray, qbar: np.ndarray,
                        pbar: np.ndarray) -> float:
    """H~ (5.36) from the body momentum pi = pi(q~1), the shape and pbar."""
    blocks = robot.metric_blocks(qbar)
    qbar_dot = np.linalg.solve(blocks.reduced_metric, pbar)
    return 0.5 * float(pi @ blocks.solve_locked(pi)) + 0.5 * float(pbar @ qbar_dot) \
        + robot.potential_energy(qbar)


def kinetic_shape_derivatives(robot: RobotModel, qbar: np.ndarray, locked_rows: IndexLike,
                              shape_rows: IndexLike, shape_columns: IndexLike,
                              connection: np.ndarray, locked_velocity: np.ndarray,
                              shape_rate: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """
    Return (d(kinetic H)/dq_shape, curvature C) from two RNEA-derivative calls.

    The rows of M split into a locked group (G, or G x N for the second stage)
    and shape coordinates; ``shape_columns`` picks the shape coordinates among
    qbar. With ``u~`` the locked velocity on the locked rows and
    ``w = [-A qdot; qdot]`` (REDUCED_MODEL.md 8): ``dH = -1/2 u~^T dM u~ -
    1/2 w^T dM w`` and ``C[i, j] = pi^T d_i A_j - pi^T d_j A_i`` with
    ``pi^T d_i A_j = ([-A; 1]^T dM_i u~)_j``.
    """
    nv = robot.model.nv
    u_full = np.zeros(nv)
    u_full[locked_rows] = locked_velocity
    w_full = np.empty(nv)
    w_full[locked_rows] = -(connection @ shape_rate)
    w_full[shape_rows] = shape_rate
    d_mu, d_mw = robot.mass_matrix_derivative_action(qbar, (u_full, w_full))[:, :, shape_columns]
    p_mat = d_mu[shape_rows] - connection.T @ d_mu[locked_rows]
    gradient = -0.5 * (locked_velocity @ d_mu[locked_rows]) - 0.5 * (w_full @ d_mw)
    return gradient, p_mat.T - p_mat


def shape_terms(robot: RobotModel, pi: np.ndarray, qbar: np.ndarray,
                pbar: np.ndarray) -> ShapeTerms:
    """Evaluate H~, dH~/dqbar (pi, pbar fixed), qbar_dot = S^-1 pbar, xi and C."""
    blocks = robot.metric_blocks(qbar)
    n = robot.n
    u = blocks.solve_locked(pi)
    # numpy rather than scipy's cho_factor/cho_solve: their wrappers dominate at this size.
    qbar_dot = np.linalg.solve(blocks.reduced_metric, pbar)
    dH, curvature = kinetic_shape_derivatives(robot, qbar, slice(0, n), slice(n, None),
                                              slice(None), blocks.connection, u, qbar_dot)
    energy = 0.5 * float(pi @ u) + 0.5 * float(pbar @ qbar_dot)
    if robot.has_potential:
        dH += robot.potential_gradient(qbar)
        energy += robot.potential_energy(qbar)
    return ShapeTerms(blocks, pi, u, qbar_dot, u - blocks.connection @ qbar_dot, energy, dH,
                      curvature)
