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
The magnetic term Xi_mu = d(sigma* alpha_mu) in chart coordinates (5.37, 5.40).

On the section sigma(q~1, qbar) = (chi(q~1), qbar) the connection one-form
alpha_mu = A* mu (5.34) pulls back to ``a = [L_chi^T pi; A^T pi]`` with
``pi = Ad_chi^T mu``. Its exterior derivative, ``U[i, j] = d_i a_j - d_j a_i``,
has the blocks (REDUCED_MODEL.md 7):

* ``U[q~1, q~1] = L^T W L``  (Maurer-Cartan: the Kirillov orbit form),
* ``U[qbar, q~1] = A^T W L`` (from d pi / d q~1_j = ad_{L_j}^T pi),
* ``U[qbar, qbar] = C``      (the curvature of the connection, pi fixed),

where ``W[a, b] = <pi, [e_a, e_b]>``.
"""

from __future__ import annotations

import numpy as np

from reduced_dynamics.geometry.lie_group import BaseGroup


def magnetic_form(group: BaseGroup, pi: np.ndarray, chart_jacobian: np.ndarray,
                  connection: np.ndarray, curvature: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
    """
    Return U, the matrix of Xi_mu in coordinates x = (q~1, qbar) (5.37 via Cartan).

    Also returns ``W L`` (the Kirillov form times the chart Jacobian), which the
    q~1-gradient of H~ shares: ``dH~/dq~1 = -(W L)^T I^-1 pi``.
    """
    kirillov_jac = group.coadjoint_form(pi) @ chart_jacobian
    k = chart_jacobian.shape[1]
    m = connection.shape[1]
    lower = connection.T @ kirillov_jac
    form = np.empty((k + m, k + m))
    form[:k, :k] = chart_jacobian.T @ kirillov_jac
    form[k:, :k] = lower
    form[:k, k:] = -lower.T
    form[k:, k:] = curvature
    return form, kirillov_jac


def magnetic_form_corollary55(group: BaseGroup, mu: np.ndarray, connection: np.ndarray,
                              connection_derivative: np.ndarray) -> np.ndarray:
    """
    Xi_mu by the explicit formula (5.40), valid when G_mu = G.

    ``Xi(u, w) = <mu, -[A u, A w] - (dA w) u + (dA u) w>`` with
    ``connection_derivative[i]`` = dA/dqbar_i (n x m); returns the m x m matrix.
    """
    kirillov = group.coadjoint_form(mu)
    bracket = connection.T @ kirillov @ connection
    # d[i, j] = <mu, d_i A_j>
    d = np.einsum('a,iaj->ij', mu, connection_derivative)
    return -bracket + d - d.T
