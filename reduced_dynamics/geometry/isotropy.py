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
Isotropy algebra Lie(G_mu) of a momentum and its complement (Table 2, 5.31).

``Lie(G_mu) = {eta : ad_eta^T mu = 0}``: the null space of the linear map
eta -> ad_eta^T mu, computed by SVD. A singular value at or below
``rank_rtol * |mu|`` counts as zero, so a momentum within that relative distance
of a class boundary (mu = 0, pure linear, pure angular) is reduced with the
larger isotropy group of the boundary; the error this makes in the reduced
model is of the order of ``rank_rtol``. ``|mu|`` is the Euclidean norm of the
SI components (kg m/s and kg m^2/s together), so robots of metre scale are
assumed. Below ``zero_atol`` the momentum is zero and G_mu = G (Corollary 55).
"""

from __future__ import annotations

from dataclasses import dataclass
import enum

import numpy as np

from reduced_dynamics.geometry.lie_group import BaseGroup

#: Default relative rank tolerance for the isotropy null space.
RANK_RTOL = 1e-9
#: Default absolute norm below which a momentum is zero (SI units).
ZERO_ATOL = 1e-12


class MomentumClass(enum.Enum):
    """The columns of Table 2: which parts of mu = (mu_v, mu_omega) vanish."""

    GENERIC = 'generic'
    PURE_ANGULAR = 'pure angular'
    PURE_LINEAR = 'pure linear'
    ZERO = 'zero'


@dataclass(frozen=True)
class IsotropyAlgebra:
    """Basis of Lie(G_mu) and of a complement, in the base group's coordinates."""

    basis: np.ndarray
    complement: np.ndarray
    momentum_class: MomentumClass
    singular_values: np.ndarray

    @property
    def dim(self) -> int:
        """Dimension of G_mu."""
        return self.basis.shape[1]

    @property
    def orbit_dim(self) -> int:
        """Compute k = dim G - dim G_mu: the dimension of Q1/G_mu (and the coadjoint orbit)."""
        return self.complement.shape[1]


def momentum_class(group: BaseGroup, mu: np.ndarray, rtol: float = RANK_RTOL,
                   atol: float = ZERO_ATOL) -> MomentumClass:
    """Classify mu (coordinates of the group's dual) into a column of Table 2."""
    wrench = group.dual_to_wrench(np.asarray(mu, dtype=float))
    norm = float(np.linalg.norm(wrench))
    if norm <= atol:
        return MomentumClass.ZERO
    linear = np.linalg.norm(wrench[:3]) > rtol * norm
    angular = np.linalg.norm(wrench[3:]) > rtol * norm
    if linear and angular:
        return MomentumClass.GENERIC
    return MomentumClass.PURE_LINEAR if linear else MomentumClass.PURE_ANGULAR


def isotropy_algebra(group: BaseGroup, mu: np.ndarray, rank_rtol: float = RANK_RTOL,
                     zero_atol: float = ZERO_ATOL) -> IsotropyAlgebra:
    """
    Lie(G_mu) for the coadjoint action of the base group (5.31, Table 2).

    Returns orthonormal bases of the isotropy algebra and of its orthogonal
    complement, which spans the chart directions of Q1/G_mu.
    """
    mu = np.asarray(mu, dtype=float)
    n = group.dim
    norm = float(np.linalg.norm(mu))
    cls = momentum_class(group, mu, rank_rtol, zero_atol)
    if cls is MomentumClass.ZERO:
        return IsotropyAlgebra(np.eye(n), np.zeros((n, 0)), cls, np.zeros(n))
    # Column j of L is ad_{e_j}^T mu, so L @ eta = ad_eta^T mu.
    lin = np.einsum('jab,a->bj', group.structure_constants, mu)
    _, sigma, vt = np.linalg.svd(lin)
    rank = int(np.sum(sigma > rank_rtol * norm))
    complement = vt[:rank].T
    basis = vt[rank:].T
    return IsotropyAlgebra(basis, complement, cls, sigma)
