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
The filter's propagation, compiled (numba): the mean, the transition Phi and Q.

The model is estimator/filter.py's; the step is structured (docs/structured_step.md):
of the transition only the pose block row and the mu-w chain are formed, and
Phi P Phi^T + Q by blocks. Arguments as in :mod:`~reduced_dynamics.estimator.core.kernels`.
"""

import numpy as np
from numba import njit

from reduced_dynamics.estimator.core.lie import adjoint, compose, group_exp, inverse
from reduced_dynamics.estimator.core.products import (_ad, _form, _mat_vec, _mul, _mul_into,
                                                      _mul_t, _mul_t_into, form, symmetric)

#: 3-point Gauss-Legendre nodes and weights on [-1, 1] (exact to degree 5).
_GAUSS_NODES = np.array([-np.sqrt(0.6), 0.0, np.sqrt(0.6)])
_GAUSS_WEIGHTS = np.array([5.0 / 9.0, 8.0 / 9.0, 5.0 / 9.0])


@njit(cache=True)
def twist(g: np.ndarray, mu: np.ndarray, inverse_locked: np.ndarray,
          connection_qd: np.ndarray, basis: np.ndarray, pinv: np.ndarray,
          whole: bool) -> np.ndarray:
    """Return xi = I^-1 Ad_g^T mu - A qbar_dot (reconstruction)."""
    return _mat_vec(inverse_locked, _mat_vec(adjoint(g, basis, pinv, whole).T, mu)) \
        - connection_qd


@njit(cache=True)
def delivered(g: np.ndarray, x: np.ndarray, u: np.ndarray, basis: np.ndarray,
              pinv: np.ndarray, whole: bool) -> np.ndarray:
    """Return the delivered wrench Ad_{g^-1}^T (k o u + b) in the world frame."""
    n = u.shape[0]
    return adjoint(inverse(g), basis, pinv, whole).T @ (x[2 * n:3 * n] * u + x[3 * n:])


@njit(cache=True)
def propagate_mean(g: np.ndarray, x: np.ndarray, inverse_locked: np.ndarray,
                   connection_qd: np.ndarray, dt: float, u: np.ndarray, commanded: bool,
                   basis: np.ndarray, pinv: np.ndarray, whole: bool) -> tuple:
    """
    Return (g, x) after dt: midpoint rule on the group, mu exact for constant w.

    ``commanded``: u is the command's mean over the step, delivered at the pose of
    the step's middle.
    """
    n = inverse_locked.shape[0]
    mu = x[:n]
    middle = compose(g, group_exp(twist(g, mu, inverse_locked, connection_qd, basis, pinv,
                                        whole) * (0.5 * dt), basis, whole))
    rate = x[n:2 * n].copy()
    if commanded:
        rate += delivered(middle, x, u, basis, pinv, whole)
    xi = twist(middle, mu + rate * (0.5 * dt), inverse_locked, connection_qd, basis, pinv,
               whole)
    out = x.copy()
    out[:n] = mu + rate * dt
    return compose(g, group_exp(xi * dt, basis, whole)), out


@njit(cache=True)
def transition(g: np.ndarray, x: np.ndarray, locked: np.ndarray, inverse_locked: np.ndarray,
               connection_qd: np.ndarray, joint_cov: np.ndarray, dt: float,
               jerk_var: np.ndarray, basis: np.ndarray, pinv: np.ndarray, whole: bool,
               ad_rows: np.ndarray, form_rows: np.ndarray) -> tuple:
    """
    Return Phi = exp(F dt) (third order) and the discrete process noise Q (3n).

    F has two non-trivial blocks only, F_gg = -(ad_xi + I^-1 W(pi)) and
    F_gmu = I^-1 Ad_g^T, at mu in the middle of the step; the mu-w chain is
    nilpotent. With a = F_gg dt, b = F_gmu dt the series gives, blockwise,
    Phi_gg = 1 + a + a^2/2 + a^3/6, Phi_gmu = b + ab/2 + a^2 b/6,
    Phi_gw = (b/2 + ab/6) dt, Phi_muw = dt. Q is Van Loan's integral of the wrench
    density through Phi(s)'s w column (3-point Gauss-Legendre; with q = Q_w dt it
    gives Q_ww = q, Q_muw = q dt/2, Q_mumu = q dt^2/3, Q_gw = (b/6 + ab/24) q dt,
    Q_gmu = b q dt^2/8 + O(dt^5), Q_gg = b q b^T dt^2/20 + O(dt^6)), plus
    Q_gg += A Sigma_qdot A^T dt^2 (encoder velocity noise held over the step).
    Only these blocks are computed (n x n products by loops, no BLAS call); the
    same operations as the dense reference up to rounding (core/reference.py).
    """
    n = locked.shape[0]
    ad_t = adjoint(g, basis, pinv, whole).T
    pi = _mat_vec(ad_t, x[:n] + x[n:2 * n] * (0.5 * dt))
    xi = _mat_vec(inverse_locked, pi) - connection_qd
    a = (_ad(ad_rows, xi) + _mul(inverse_locked, _form(form_rows, pi))) * -dt
    b = _mul(inverse_locked, ad_t) * dt
    ab = _mul(a, b)
    aa = _mul(a, a)
    a_aa = _mul(a, aa)
    a_ab = _mul(a, ab)
    dim = 3 * n
    phi = np.zeros((dim, dim))
    for i in range(dim):
        phi[i, i] = 1.0
    for i in range(n):
        for j in range(n):
            phi[i, j] += a[i, j] + 0.5 * aa[i, j] + a_aa[i, j] / 6.0
            phi[i, n + j] = b[i, j] + 0.5 * ab[i, j] + a_ab[i, j] / 6.0
            phi[i, 2 * n + j] = (0.5 * b[i, j] + ab[i, j] / 6.0) * dt
        phi[n + i, 2 * n + i] = dt
    # Q_w = Ad_{g^-1}^T I diag(s^2) I Ad_{g^-1} (a density: per second).
    scaled = _mul(adjoint(inverse(g), basis, pinv, whole).T, locked)
    density = _mul_t(scaled * jerk_var, scaled)
    # Van Loan's integral int_0^dt Phi(s) L Qc L^T Phi(s)^T ds by 3-point Gauss-Legendre:
    # a sum of terms v Qc v^T, so Q is positive semi-definite by construction (the
    # truncated series was not: after a 1 s stall its Q_gg = 0 beside Q_gw != 0 made P
    # indefinite). Exact for the mu-w chain (polynomials of degree <= 5 in s).
    # With r = s/dt the w column is [g_r; s 1; 1], g_r = (b r/2 + ab r^2/6) s, so the
    # blocks are sums over the nodes of g D g^T, s g D, g D, s^2 D, s D and D.
    q = np.zeros((dim, dim))
    # One set of the per-node blocks, written again at each node.
    g_s = np.empty((n, n))
    gd = np.empty((n, n))
    gdg = np.empty((n, n))
    for node in range(3):
        r = 0.5 * (1.0 + _GAUSS_NODES[node])
        s = r * dt
        weight = 0.5 * dt * _GAUSS_WEIGHTS[node]
        for i in range(n):
            for j in range(n):
                g_s[i, j] = ((0.5 * r) * b[i, j] + (r * r / 6.0) * ab[i, j]) * s
        _mul_into(g_s, density, gd)
        _mul_t_into(gd, g_s, gdg)
        for i in range(n):
            for j in range(n):
                q[i, j] += weight * gdg[i, j]
                q[i, n + j] += (weight * s) * gd[i, j]
                q[i, 2 * n + j] += weight * gd[i, j]
                q[n + i, n + j] += (weight * s * s) * density[i, j]
                q[n + i, 2 * n + j] += (weight * s) * density[i, j]
                q[2 * n + i, 2 * n + j] += weight * density[i, j]
    for i in range(n):
        for j in range(n):
            q[i, j] += joint_cov[i, j] * (dt * dt)
    # The lower blocks mirror the upper ones; the diagonal blocks are symmetrised.
    for i in range(dim):
        for j in range(i + 1, dim):
            if j // n == i // n:
                v = 0.5 * (q[i, j] + q[j, i])
                q[i, j] = v
            q[j, i] = q[i, j]
    return phi, q


@njit(cache=True)
def transition_commanded(g: np.ndarray, x: np.ndarray, locked: np.ndarray,
                         inverse_locked: np.ndarray, connection_qd: np.ndarray,
                         joint_cov: np.ndarray, dt: float, u: np.ndarray,
                         jerk_var: np.ndarray, command_density: np.ndarray,
                         basis: np.ndarray, pinv: np.ndarray, whole: bool,
                         ad_rows: np.ndarray, form_rows: np.ndarray) -> tuple:
    """
    Return Phi and Q of the commanded-wrench filter (5n): the dense series.

    F at mu in the middle of the step with the command's blocks (filter.py's
    module docstring); Phi = 1 + F dt + (F dt)^2/2 + (F dt)^3/6 and Van Loan's
    integral as its Taylor series (exact for the mu-w chain, fourth order else).
    ``command_density``: the random-walk density of (k, b) (2n x 2n).
    """
    n = locked.shape[0]
    dim = 5 * n
    to_world = adjoint(inverse(g), basis, pinv, whole).T
    c = x[2 * n:3 * n] * u + x[3 * n:]
    mu_mid = x[:n] + (x[n:2 * n] + to_world @ c) * (0.5 * dt)
    ad_t = adjoint(g, basis, pinv, whole).T
    pi = ad_t @ mu_mid
    xi = inverse_locked @ pi - connection_qd
    f = np.zeros((dim, dim))
    f[:n, :n] = -(xi @ ad_rows).reshape(n, n) - inverse_locked @ form(form_rows, pi)
    f[:n, n:2 * n] = inverse_locked @ ad_t
    for i in range(n):
        f[n + i, 2 * n + i] = 1.0
    f[n:2 * n, :n] = to_world @ form(form_rows, c)
    f[n:2 * n, 3 * n:4 * n] = to_world * u
    f[n:2 * n, 4 * n:] = to_world
    fdt = f * dt
    f2 = fdt @ fdt
    phi = np.eye(dim) + fdt + 0.5 * f2 + (f2 @ fdt) / 6.0
    scaled = to_world @ locked
    qc = np.zeros((dim, dim))
    qc[2 * n:3 * n, 2 * n:3 * n] = (scaled * jerk_var) @ scaled.T
    qc[3 * n:, 3 * n:] = command_density
    # Van Loan's integral by 3-point Gauss-Legendre with Phi(s) the same series at s:
    # positive semi-definite by construction (see transition).
    q = np.zeros((dim, dim))
    for node in range(3):
        s = 0.5 * dt * (1.0 + _GAUSS_NODES[node])
        fs = f * s
        fs2 = fs @ fs
        phi_s = np.eye(dim) + fs + 0.5 * fs2 + (fs2 @ fs) / 6.0
        q += (0.5 * dt * _GAUSS_WEIGHTS[node]) * (phi_s @ qc @ phi_s.T)
    q[:n, :n] += joint_cov * (dt * dt)
    return phi, symmetric(q)


@njit(cache=True)
def propagate(g: np.ndarray, x: np.ndarray, p: np.ndarray, locked: np.ndarray,
              inverse_locked: np.ndarray, connection_qd: np.ndarray, joint_cov: np.ndarray,
              dt: float, u: np.ndarray, commanded: bool, jerk_var: np.ndarray,
              command_density: np.ndarray, basis: np.ndarray, pinv: np.ndarray, whole: bool,
              ad_rows: np.ndarray, form_rows: np.ndarray) -> tuple:
    """Return (g, x, P, Phi) after dt: the mean, and P = Phi P Phi^T + Q symmetrised."""
    if commanded:
        phi, q = transition_commanded(g, x, locked, inverse_locked, connection_qd, joint_cov,
                                      dt, u, jerk_var, command_density, basis, pinv, whole,
                                      ad_rows, form_rows)
    else:
        phi, q = transition(g, x, locked, inverse_locked, connection_qd, joint_cov, dt,
                            jerk_var, basis, pinv, whole, ad_rows, form_rows)
    g1, x1 = propagate_mean(g, x, inverse_locked, connection_qd, dt, u, commanded, basis, pinv,
                            whole)
    if commanded:
        return g1, x1, symmetric(phi @ p @ phi.T + q), phi
    return g1, x1, _predicted_covariance(phi, p, q, dt), phi


@njit(cache=True)
def _predicted_covariance(phi: np.ndarray, p: np.ndarray, q: np.ndarray,
                          dt: float) -> np.ndarray:
    """
    Return Phi P Phi^T + Q, symmetric, for the 3n transition (lower block rows [0 1 dt; 0 0 1]).

    Phi P's rows: the pose block row is a product, the mu row is P_mu + dt P_w, the w
    row P_w; the same again on the columns, one triangle of the result, mirrored.
    """
    dim = p.shape[0]
    n = dim // 3
    m = np.empty((dim, dim))
    for i in range(n):
        for j in range(dim):
            acc = 0.0
            for k in range(dim):
                acc += phi[i, k] * p[k, j]
            m[i, j] = acc
    for i in range(n, 2 * n):
        for j in range(dim):
            m[i, j] = p[i, j] + dt * p[i + n, j]
    for i in range(2 * n, dim):
        for j in range(dim):
            m[i, j] = p[i, j]
    out = np.empty((dim, dim))
    for i in range(dim):
        for j in range(n):
            acc = 0.0
            for k in range(dim):
                acc += m[i, k] * phi[j, k]
            out[i, j] = acc
        for j in range(n, 2 * n):
            out[i, j] = m[i, j] + dt * m[i, j + n]
        for j in range(2 * n, dim):
            out[i, j] = m[i, j]
    for i in range(dim):
        out[i, i] += q[i, i]
        for j in range(i + 1, dim):
            v = 0.5 * ((out[i, j] + q[i, j]) + (out[j, i] + q[j, i]))
            out[i, j] = v
            out[j, i] = v
    return out
