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
Displacement subgroups of SE(3) (paper section 3.2.1, Table 1) as base groups.

A base group G is a subgroup of SE(3) given by its motion subspace ``S`` (6 x n):
its Lie algebra is span(S). Twists are ordered (v, omega), linear first, as in
Pinocchio; ``Ad`` and ``ad`` follow Pinocchio's ``SE3.action`` and
``Motion.action`` (REDUCED_MODEL.md section 1). Elements of G are ``pin.SE3``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pinocchio as pin


def _unit(*indices: int) -> np.ndarray:
    column = np.zeros(6)
    column[list(indices)] = 1.0
    return column


@dataclass(frozen=True)
class BaseGroup:
    """
    A Lie subgroup of SE(3) described by its motion subspace.

    ``algebra_basis`` is S (6 x n) with orthonormal-or-not columns spanning the
    subalgebra; coordinates eta in R^n stand for the twist S @ eta.
    """

    name: str
    algebra_basis: np.ndarray
    _pinv: np.ndarray = field(init=False, repr=False, compare=False)
    _structure: np.ndarray = field(init=False, repr=False, compare=False)
    _whole: bool = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        basis = np.asarray(self.algebra_basis, dtype=float)
        object.__setattr__(self, 'algebra_basis', basis)
        pinv = np.linalg.pinv(basis)
        object.__setattr__(self, '_pinv', pinv)
        n = basis.shape[1]
        # structure[a] = S+ ad_{S e_a} S: the bracket restricted to the subalgebra.
        structure = np.empty((n, n, n))
        for a in range(n):
            structure[a] = pinv @ pin.Motion(basis[:, a]).action @ basis
        for a in range(n):
            residual = basis @ structure[a] - pin.Motion(basis[:, a]).action @ basis
            if np.abs(residual).max() > 1e-9:
                raise ValueError(f'{self.name}: span(S) is not a Lie subalgebra of se(3)')
        object.__setattr__(self, '_structure', structure)
        # SE(3) itself (S = 1): the hot paths skip the products with S and S+.
        object.__setattr__(self, '_whole', bool(np.array_equal(basis, np.eye(6))))

    @property
    def dim(self) -> int:
        """Dimension n of the group."""
        return self.algebra_basis.shape[1]

    @property
    def structure_constants(self) -> np.ndarray:
        """Array c[a] = ad_{e_a} (n x n) so that [e_a, e_b] = c[a] @ e_b."""
        return self._structure

    def twist(self, eta: np.ndarray) -> np.ndarray:
        """Embed algebra coordinates into se(3): S eta."""
        return self.algebra_basis @ eta

    def coordinates(self, twist6: np.ndarray) -> np.ndarray:
        """Project an se(3) twist in span(S) to algebra coordinates."""
        return self._pinv @ twist6

    def dual_coordinates(self, wrench6: np.ndarray) -> np.ndarray:
        """Restrict an se*(3) covector to the subalgebra: S^T w."""
        return self.algebra_basis.T @ wrench6

    def dual_to_wrench(self, covector: np.ndarray) -> np.ndarray:
        """Lift a covector of the subalgebra to se*(3) (zero off the subalgebra)."""
        return self._pinv.T @ covector

    def Ad(self, g: pin.SE3) -> np.ndarray:
        """Adjoint Ad_g restricted to the subalgebra (n x n)."""
        if self._whole:
            return g.action
        return self._pinv @ g.action @ self.algebra_basis

    def ad(self, eta: np.ndarray) -> np.ndarray:
        """Adjoint ad_eta of the subalgebra (n x n): ad_eta @ zeta = [eta, zeta]."""
        return np.tensordot(eta, self._structure, axes=1)

    def coadjoint_form(self, covector: np.ndarray) -> np.ndarray:
        """Skew matrix W[a, b] = <covector, [e_a, e_b]> (the Kirillov form at covector)."""
        return np.einsum('acb,c->ab', self._structure, covector)

    @property
    def algebra_pinv(self) -> np.ndarray:
        """S+ (n x 6): algebra coordinates of a twist in span(S) (cached)."""
        return self._pinv

    @property
    def is_whole(self) -> bool:
        """Whether the group is SE(3) itself with the identity basis (S = 1)."""
        return self._whole

    def exp(self, eta: np.ndarray) -> pin.SE3:
        """Group exponential of algebra coordinates."""
        return pin.exp6(eta if self._whole else self.twist(eta))

    def log(self, g: pin.SE3) -> np.ndarray:
        """Group logarithm in algebra coordinates (g must lie in the subgroup)."""
        return self.coordinates(pin.log6(g).vector)

    def right_jacobian(self, eta: np.ndarray) -> np.ndarray:
        """J with exp(eta + d) = exp(eta) exp(J d) to first order (Pinocchio Jexp6)."""
        if self._whole:
            return pin.Jexp6(eta)
        return self._pinv @ pin.Jexp6(self.twist(eta)) @ self.algebra_basis

    def right_jacobian_inverse(self, eta: np.ndarray) -> np.ndarray:
        """Inverse of :meth:`right_jacobian` (Pinocchio Jlog6 at exp(eta))."""
        if self._whole:
            return pin.Jlog6(pin.exp6(eta))
        return self._pinv @ pin.Jlog6(pin.exp6(self.twist(eta))) @ self.algebra_basis

    def contains(self, g: pin.SE3, tol: float = 1e-9) -> bool:
        """Whether g lies in the subgroup (its logarithm is in span(S))."""
        twist6 = pin.log6(g).vector
        return bool(np.abs(self.twist(self.coordinates(twist6)) - twist6).max() <= tol)


def _helical(pitch: float) -> np.ndarray:
    return np.array([0.0, 0.0, pitch, 0.0, 0.0, 1.0])


#: The displacement subgroups of Table 1 (axes chosen along z / in the xy-plane).
SUBGROUPS: dict[str, BaseGroup] = {
    'SE(3)': BaseGroup('SE(3)', np.eye(6)),
    'SE(2)xR': BaseGroup('SE(2)xR', np.column_stack([_unit(0), _unit(1), _unit(2), _unit(5)])),
    'SE(2)': BaseGroup('SE(2)', np.column_stack([_unit(0), _unit(1), _unit(5)])),
    'SO(3)': BaseGroup('SO(3)', np.column_stack([_unit(3), _unit(4), _unit(5)])),
    'R3': BaseGroup('R3', np.column_stack([_unit(0), _unit(1), _unit(2)])),
    'H_p x R2': BaseGroup('H_p x R2', np.column_stack([_unit(0), _unit(1), _helical(0.1)])),
    'SO(2)xR': BaseGroup('SO(2)xR', np.column_stack([_unit(2), _unit(5)])),
    'R2': BaseGroup('R2', np.column_stack([_unit(0), _unit(1)])),
    'SO(2)': BaseGroup('SO(2)', _unit(5)[:, None]),
    'R': BaseGroup('R', _unit(2)[:, None]),
    'H_p': BaseGroup('H_p', _helical(0.1)[:, None]),
}
