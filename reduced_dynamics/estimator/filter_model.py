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
The momentum filter's model: its state's pieces, the pose's maps, the propagation's terms.

A part of :class:`~reduced_dynamics.estimator.filter.MomentumFilter` (a mixin whose
state ``MomentumFilter.__init__`` sets up): what the filter reads off its state (mu,
w, the commanded wrench's gain and bias, the total wrench and its significance) and
the model's terms in Python (the twist, F, H of a twist, the densities), over the
compiled arithmetic of :mod:`~reduced_dynamics.estimator.core.kernels`.
"""

from __future__ import annotations

from typing import Optional

import numpy as np
import pinocchio as pin

from reduced_dynamics.estimator import command_gain
from reduced_dynamics.estimator.core import kernels
from reduced_dynamics.estimator.core.state import Linearisation

_EMPTY = np.zeros(0)


def _homogeneous(g: Optional[pin.SE3]) -> Optional[np.ndarray]:
    return None if g is None else np.ascontiguousarray(g.homogeneous)


class FilterModel:
    """The filter's model and what it reads off its state (a part of MomentumFilter)."""

    @property
    def mu(self) -> np.ndarray:
        """Return the momentum-map estimate (world frame, about the origin)."""
        return self.x[:self.n]

    @property
    def wrench(self) -> np.ndarray:
        """
        Return the wrench estimate w (world frame, about the origin).

        The external wrench; with the commanded wrench, the disturbance beyond it.
        """
        return self.x[self.n:2 * self.n]

    @property
    def wrench_cov(self) -> np.ndarray:
        """Return the covariance of w."""
        n = self.n
        return self.p[2 * n:3 * n, 2 * n:3 * n]

    @property
    def gain(self) -> np.ndarray:
        """Return the per-axis gain k of the delivered wrench (commanded wrench only)."""
        return self.x[2 * self.n:3 * self.n]

    @property
    def bias(self) -> np.ndarray:
        """Return the per-axis bias b of the delivered body wrench (commanded wrench only)."""
        return self.x[3 * self.n:]

    def body_momentum(self) -> np.ndarray:
        """Return pi = Ad_g^T mu (the momentum in the base frame) of the current estimate."""
        return kernels.adjoint(self._g, self._basis, self._pinv, self._whole).T @ self.mu

    def delivered(self, g: pin.SE3, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Return the delivered wrench Ad_{g^-1}^T (k o u + b) in the world frame."""
        return kernels.delivered(_homogeneous(g), x, u, self._basis, self._pinv, self._whole)

    def total_wrench(self) -> tuple[np.ndarray, np.ndarray]:
        """
        Return the total external wrench w + delivered and its covariance (n, n x n).

        The command is the one held at the last step's end. Without the
        commanded wrench: w and its covariance.
        """
        if not self.command:
            return self.wrench, self.wrench_cov
        return self._total(self.g, self.x, self.p, self._command)

    def _total(self, g: pin.SE3, x: np.ndarray, p: np.ndarray,
               u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        n = self.n
        to_world = self.group.Ad(g.inverse()).T
        c = x[2 * n:3 * n] * u + x[3 * n:]
        jac = np.zeros((n, 5 * n))
        jac[:, :n] = to_world @ self.group.coadjoint_form(c)
        jac[:, 2 * n:3 * n] = np.eye(n)
        jac[:, 3 * n:4 * n] = to_world * u
        jac[:, 4 * n:] = to_world
        cov = jac @ p @ jac.T
        return x[n:2 * n] + to_world @ c, 0.5 * (cov + cov.T)

    def wrench_significance(self) -> float:
        """
        Return w^T P_ww^-1 w (chi-square with n degrees of freedom when w = 0).

        Commanded wrench: an unidentified gain on an axis being commanded adds
        the wrench it may be off by to P_ww (command_gain.mismatch_covariance):
        its error is not an external wrench.
        """
        if self.command and self._g is not None and self._command.any():
            unidentified = ~command_gain.gains_identified(
                self.p, self.n, self.command_prior_sigma) & (self._command != 0.0)
            if unidentified.any():
                n = self.n
                w = self.x[n:2 * n]
                cov = self.p[2 * n:3 * n, 2 * n:3 * n] + command_gain.mismatch_covariance(
                    self.p, n, self._adjoint_inverse(self.g).T, self._command, unidentified)
                return float(w @ np.linalg.solve(cov, w))
        fused = self._fused_significance
        if fused is not None and self.p is fused[0] and self.x is fused[1]:
            return fused[2]  # computed by the last fused step, for this very state
        return kernels.significance(self.x, self.p, self.n)

    def _adjoint(self, g: pin.SE3) -> np.ndarray:
        """Return Ad_g on the subalgebra (n x n)."""
        if self._whole:
            return g.action
        return self._pinv @ g.action @ self._basis

    def _adjoint_inverse(self, g: pin.SE3) -> np.ndarray:
        """Return Ad_{g^-1} on the subalgebra (n x n)."""
        if self._whole:
            return g.actionInverse
        return self._pinv @ g.actionInverse @ self._basis

    def twist(self, g: pin.SE3, mu: np.ndarray, lin: Linearisation) -> np.ndarray:
        """Return xi = I^-1 Ad_g^T mu - A qbar_dot (reconstruction)."""
        return kernels.twist(_homogeneous(g), mu, lin.locked_inverse, lin.connection_qd,
                             self._basis, self._pinv, self._whole)

    def jacobian(self, g: pin.SE3, mu: np.ndarray, lin: Linearisation) -> np.ndarray:
        """Return F of the error dynamics at (g, mu) (3n x 3n)."""
        n, group = self.n, self.group
        ad_t = group.Ad(g).T
        pi = ad_t @ mu
        xi = lin.locked_inverse @ pi - lin.connection_qd
        f = np.zeros((self.dim, self.dim))
        f[:n, :n] = -group.ad(xi) - lin.locked_inverse @ group.coadjoint_form(pi)
        f[:n, n:2 * n] = lin.locked_inverse @ ad_t
        f[n:2 * n, 2 * n:3 * n] = np.eye(n)
        return f

    def twist_jacobian(self, g: pin.SE3, mu: np.ndarray, lin: Linearisation) -> np.ndarray:
        """Return H of the twist measurement (n x 3n): [H1, H2, 0], the update's blocks."""
        x = np.zeros(self.dim - self.n)
        x[:self.n] = mu
        pose = _homogeneous(g)
        h1, h2, _ = kernels._twist_blocks(pose, x, pose, np.zeros(self.n),
                                          lin.locked_inverse, lin.connection_qd, self._basis,
                                          self._pinv, self._whole, self._form_rows)
        return np.concatenate((h1, h2, np.zeros((self.n, self.dim - 2 * self.n))), axis=1)

    def wrench_density(self, g: pin.SE3, locked: np.ndarray) -> np.ndarray:
        """Return the spectral density of w_dot: Ad_{g^-1}^T I diag(s^2) I Ad_{g^-1}."""
        scaled = self._adjoint_inverse(g).T @ locked
        return (scaled * self._jerk_var) @ scaled.T

    def _command_input(self, u: Optional[np.ndarray]) -> np.ndarray:
        return _EMPTY if u is None else np.asarray(u, dtype=float)

    def _densities(self, lin: Linearisation) -> np.ndarray:
        """Return the random-walk density of (k, b) (commanded wrench; else unused)."""
        if not self.command:
            return self._command_density
        n = self.n
        drift = self.noise.command_gain_drift ** 2
        out = np.zeros((2 * n, 2 * n))
        out[:n, :n] = np.eye(n) * drift
        out[n:, n:] = (lin.locked * (self._bias_var * drift)) @ lin.locked.T
        return out

    def propagate_mean(self, g: pin.SE3, x: np.ndarray, lin: Linearisation,
                       dt: float, u: Optional[np.ndarray] = None
                       ) -> tuple[pin.SE3, np.ndarray]:
        """
        Return (g, x) after dt: midpoint rule on the group, mu exact for constant w.

        ``u`` (commanded wrench): the command's mean over the step; the
        delivered wrench is taken at the pose of the step's middle.
        """
        g1, x1 = kernels.propagate_mean(_homogeneous(g), x, lin.locked_inverse,
                                        lin.connection_qd, dt, self._command_input(u),
                                        u is not None, self._basis, self._pinv, self._whole)
        return pin.SE3(g1), x1

    def _transition(self, g: pin.SE3, x: np.ndarray, lin: Linearisation,
                    dt: float, u: Optional[np.ndarray] = None
                    ) -> tuple[np.ndarray, np.ndarray]:
        """Return Phi = exp(F dt) (third order) and Q (kernels.transition and _commanded)."""
        if u is not None:
            return kernels.transition_commanded(
                _homogeneous(g), x, lin.locked, lin.locked_inverse, lin.connection_qd,
                lin.joint_cov, dt, np.asarray(u, dtype=float), self._jerk_var,
                self._densities(lin), self._basis, self._pinv, self._whole, self._ad_rows,
                self._form_rows)
        return kernels.transition(_homogeneous(g), x, lin.locked, lin.locked_inverse,
                                  lin.connection_qd, lin.joint_cov, dt, self._jerk_var,
                                  self._basis, self._pinv, self._whole, self._ad_rows,
                                  self._form_rows)

    def _command_prior(self, locked: np.ndarray) -> np.ndarray:
        """Return the prior covariance of (k, b): k = 1 +- gain, b = 0 +- I bias."""
        n = self.n
        out = np.zeros((2 * n, 2 * n))
        out[:n, :n] = np.eye(n) * self.noise.command_gain ** 2
        out[n:, n:] = (locked * self._bias_var) @ locked.T
        return out
