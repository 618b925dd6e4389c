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
The filter's propagation and update, compiled (numba), on arrays.

The model is the one of estimator/filter.py's module docstring; the functions
here are its arithmetic, written once for the interpreter and the compiler. A
call returns fresh state arrays (the filter's recorded steps share them) and
allocates nothing else the caller sees. Constants of the base group and the
noise are packed once per filter into :class:`Model`-like tuples by the caller:

``basis`` S (6 x n), ``pinv`` S+ (n x 6), ``whole`` (S = 1), ``ad_rows``
(n x n^2) and ``form_rows`` (n^2 x n) the structure constants as matrices
(``ad(eta) = (eta ad_rows).reshape(n, n)``, ``W(pi) = (form_rows pi).reshape(n, n)``).

Covariances are symmetrised after every operation that could make them drift
apart (propagation, update, a step's compensation).

The step is structured (docs/structured_step.md): of the transition only the
pose block row and the mu-w chain are formed, Phi P Phi^T + Q by blocks; H enters
by its blocks (pose rows select, w columns zero), one Cholesky factor of S gives
the gain, the NIS and log det S, and P is updated as P - K S K^T. The dense step
it replaced is ``core/reference.py``, equal to 1e-9 (test/test_structured_step.py).
"""

import math
import warnings

import numpy as np
from numba import njit
from numba.core.errors import NumbaPerformanceWarning

from reduced_dynamics.estimator.core.lie import adjoint, compose, group_exp, group_log, inverse

# Printed once, when a kernel compiles after an install, about products of small strided
# views (a few dozen elements): not worth a copy, and not for the user to act on.
warnings.filterwarnings('ignore', message=".*'@' is faster on contiguous arrays",
                        category=NumbaPerformanceWarning)

#: Re-linearisations of an update with a twist (iterated EKF). The twist is bilinear in
#: (delta_g, delta_mu), so each re-linearisation moves the estimate by a second-order term:
#: replaying the shipped Odometry bags with 1 instead of 2 moved the published wrench by
#: up to 2.7e-5 of its range (1 mN of 40 N, paper_spacecraft; 4e-7 on paper_realistic),
#: far above the 1e-9 the structured step holds against the dense one, so both stay
#: (one costs ~4 x crba). A pose alone is not iterated.
ITERATIONS = 2
#: A re-linearisation that moved the estimate by less than this fraction of every error
#: coordinate's prior standard deviation ends the iteration: the iterated update converges
#: quadratically, so the next one would move it by ~this squared (measured in the bench's
#: steady state: 6e-9 sigma after the first re-linearisation, 1e-14 after the second,
#: i.e. rounding), and stopping skips a re-linearisation (~4 x crba) that changes nothing
#: a figure can see. Larger moves (fast rotation, a transient) iterate as before.
CONVERGED = 1e-6
#: 3-point Gauss-Legendre nodes and weights on [-1, 1] (exact to degree 5).
_GAUSS_NODES = np.array([-np.sqrt(0.6), 0.0, np.sqrt(0.6)])
_GAUSS_WEIGHTS = np.array([5.0 / 9.0, 8.0 / 9.0, 5.0 / 9.0])


@njit(cache=True)
def _mul_into(a: np.ndarray, b: np.ndarray, out: np.ndarray) -> None:
    """Write a b into ``out`` by loops (zeroed, then accumulated: :func:`_mul`'s order)."""
    rows, inner = a.shape
    cols = b.shape[1]
    for i in range(rows):
        for j in range(cols):
            out[i, j] = 0.0
    for i in range(rows):
        for k in range(inner):
            v = a[i, k]
            for j in range(cols):
                out[i, j] += v * b[k, j]


@njit(cache=True)
def _mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Return a b by loops: no BLAS call or copy for the filter's n x n blocks."""
    out = np.empty((a.shape[0], b.shape[1]))
    _mul_into(a, b, out)
    return out


@njit(cache=True)
def _mul_t_into(a: np.ndarray, b: np.ndarray, out: np.ndarray) -> None:
    """Write a b^T into ``out`` by loops."""
    rows, inner = a.shape
    cols = b.shape[0]
    for i in range(rows):
        for j in range(cols):
            acc = 0.0
            for k in range(inner):
                acc += a[i, k] * b[j, k]
            out[i, j] = acc


@njit(cache=True)
def _mul_t(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Return a b^T by loops."""
    out = np.empty((a.shape[0], b.shape[0]))
    _mul_t_into(a, b, out)
    return out


@njit(cache=True)
def _mat_vec(a: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Return a v by loops."""
    rows, inner = a.shape
    out = np.empty(rows)
    for i in range(rows):
        acc = 0.0
        for k in range(inner):
            acc += a[i, k] * v[k]
        out[i] = acc
    return out


@njit(cache=True)
def symmetric(p: np.ndarray) -> np.ndarray:
    """Return (P + P^T) / 2."""
    return 0.5 * (p + p.T)


@njit(cache=True)
def form(form_rows: np.ndarray, covector: np.ndarray) -> np.ndarray:
    """Return W(covector)[a, b] = <covector, [e_a, e_b]> (``coadjoint_form``)."""
    n = covector.shape[0]
    return (form_rows @ covector).reshape(n, n)


@njit(cache=True)
def _form(form_rows: np.ndarray, covector: np.ndarray) -> np.ndarray:
    """Return :func:`form` by loops."""
    n = covector.shape[0]
    return _mat_vec(form_rows, covector).reshape(n, n)


@njit(cache=True)
def _ad(ad_rows: np.ndarray, eta: np.ndarray) -> np.ndarray:
    """Return ad(eta) = (eta ad_rows).reshape(n, n)."""
    n = eta.shape[0]
    out = np.zeros(n * n)
    for k in range(n):
        v = eta[k]
        for j in range(n * n):
            out[j] += v * ad_rows[k, j]
    return out.reshape(n, n)


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


@njit(cache=True)
def twist_measurement(g: np.ndarray, x: np.ndarray, pose: np.ndarray, measured: np.ndarray,
                      inverse_locked: np.ndarray, connection_qd: np.ndarray, dim: int,
                      basis: np.ndarray, pinv: np.ndarray, whole: bool,
                      form_rows: np.ndarray) -> tuple:
    """Return H (2n x dim) and the innovation of a pose and a body twist at (g, x)."""
    n = inverse_locked.shape[0]
    residual = group_log(compose(inverse(g), pose), pinv, whole)
    ad_t = adjoint(g, basis, pinv, whole).T
    pi = ad_t @ x[:n]
    h = np.zeros((2 * n, dim))
    for i in range(n):
        h[i, i] = 1.0
    h[n:, :n] = -inverse_locked @ form(form_rows, pi)
    h[n:, n:2 * n] = inverse_locked @ ad_t
    nu = np.empty(2 * n)
    nu[:n] = residual
    nu[n:] = measured - (inverse_locked @ pi - connection_qd)
    return h, nu


@njit(cache=True)
def pose_noise(pose_var: np.ndarray, stamp_twist: np.ndarray, stamp_sigma: float) -> np.ndarray:
    """Return R of a pose: diag(pose_var) + xi xi^T sigma_t^2 (a stamp off by sigma_t)."""
    n = pose_var.shape[0]
    r = np.zeros((n, n))
    for i in range(n):
        r[i, i] = pose_var[i]
    if stamp_sigma > 0.0:
        xi = stamp_twist * stamp_sigma
        r += np.outer(xi, xi)
    return r


@njit(cache=True)
def _twist_blocks(g: np.ndarray, x: np.ndarray, pose: np.ndarray, measured: np.ndarray,
                  inverse_locked: np.ndarray, connection_qd: np.ndarray, basis: np.ndarray,
                  pinv: np.ndarray, whole: bool, form_rows: np.ndarray) -> tuple:
    """
    Return (H1, H2, nu) of a pose and a body twist at (g, x): H = [[1, 0, 0], [H1, H2, 0]].

    H1 = -I^-1 W(pi), H2 = I^-1 Ad_g^T (:func:`twist_measurement`'s blocks).
    """
    n = inverse_locked.shape[0]
    residual = group_log(compose(inverse(g), pose), pinv, whole)
    ad_t = adjoint(g, basis, pinv, whole).T
    pi = _mat_vec(ad_t, x[:n])
    h1 = _mul(inverse_locked, _form(form_rows, pi))
    for i in range(n):
        for j in range(n):
            h1[i, j] = -h1[i, j]
    h2 = _mul(inverse_locked, ad_t)
    predicted = _mat_vec(inverse_locked, pi)
    nu = np.empty(2 * n)
    for i in range(n):
        nu[i] = residual[i]
        nu[n + i] = measured[i] - (predicted[i] - connection_qd[i])
    return h1, h2, nu


@njit(cache=True)
def _dense_h(h1: np.ndarray, h2: np.ndarray, n: int, dim: int, with_twist: bool) -> np.ndarray:
    """Return H (m x dim) from its blocks: [1 0 0], or [[1, 0, 0], [H1, H2, 0]]."""
    m = 2 * n if with_twist else n
    h = np.zeros((m, dim))
    for i in range(n):
        h[i, i] = 1.0
    if with_twist:
        for i in range(n):
            for j in range(n):
                h[n + i, j] = h1[i, j]
                h[n + i, n + j] = h2[i, j]
    return h


@njit(cache=True)
def _cross(p: np.ndarray, h1: np.ndarray, h2: np.ndarray, n: int,
           with_twist: bool) -> np.ndarray:
    """Return P H^T (dim x m): P's pose columns, and P_g H1^T + P_mu H2^T for a twist."""
    dim = p.shape[0]
    m = 2 * n if with_twist else n
    out = np.empty((dim, m))
    for i in range(dim):
        for j in range(n):
            out[i, j] = p[i, j]
        if with_twist:
            for j in range(n):
                acc = 0.0
                for k in range(n):
                    acc += p[i, k] * h1[j, k] + p[i, n + k] * h2[j, k]
                out[i, n + j] = acc
    return out


@njit(cache=True)
def _innovation_covariance(cross: np.ndarray, h1: np.ndarray, h2: np.ndarray,
                           r: np.ndarray, n: int, with_twist: bool) -> np.ndarray:
    """Return S = H (P H^T) + R, symmetrised, from P H^T and H's blocks."""
    m = cross.shape[1]
    s = np.empty((m, m))
    for i in range(n):
        for j in range(m):
            s[i, j] = cross[i, j] + r[i, j]
    if with_twist:
        for i in range(n):
            for j in range(m):
                acc = 0.0
                for k in range(n):
                    acc += h1[i, k] * cross[k, j] + h2[i, k] * cross[n + k, j]
                s[n + i, j] = acc + r[n + i, j]
    for i in range(m):
        for j in range(i + 1, m):
            v = 0.5 * (s[i, j] + s[j, i])
            s[i, j] = v
            s[j, i] = v
    return s


@njit(cache=True)
def _cholesky(s: np.ndarray) -> np.ndarray:
    """Return the lower Cholesky factor of S; LinAlgError when S is not positive definite."""
    m = s.shape[0]
    low = np.zeros((m, m))
    for j in range(m):
        d = s[j, j]
        for k in range(j):
            d -= low[j, k] * low[j, k]
        if not d > 0.0:
            raise np.linalg.LinAlgError('innovation covariance not positive definite')
        root = math.sqrt(d)
        low[j, j] = root
        for i in range(j + 1, m):
            acc = s[i, j]
            for k in range(j):
                acc -= low[i, k] * low[j, k]
            low[i, j] = acc / root
    return low


@njit(cache=True)
def _whiten(low: np.ndarray, cross: np.ndarray) -> np.ndarray:
    """Return Y = L^-1 (P H^T)^T (m x dim): the forward substitution, all columns at once."""
    dim, m = cross.shape
    y = np.empty((m, dim))
    for i in range(m):
        for c in range(dim):
            y[i, c] = cross[c, i]
        for k in range(i):
            lik = low[i, k]
            for c in range(dim):
                y[i, c] -= lik * y[k, c]
        for c in range(dim):
            y[i, c] /= low[i, i]
    return y


@njit(cache=True)
def _gain_from(low: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Return K = P H^T S^-1 (dim x m) as (L^-T Y)^T: the backward substitution."""
    m, dim = y.shape
    # Z = L^-T Y solved in K's own (transposed) layout: the same operations per element.
    gain = np.empty((dim, m))
    for i in range(m - 1, -1, -1):
        for c in range(dim):
            gain[c, i] = y[i, c]
        for k in range(i + 1, m):
            lki = low[k, i]
            for c in range(dim):
                gain[c, i] -= lki * gain[c, k]
        for c in range(dim):
            gain[c, i] /= low[i, i]
    return gain


@njit(cache=True)
def _downdate(p: np.ndarray, y: np.ndarray) -> np.ndarray:
    """
    Return P - Y^T Y = P - P H^T S^-1 H P (one triangle, mirrored: symmetric).

    The Joseph form (1 - K H) P (1 - K H)^T + K R K^T equals this for the gain
    K = P H^T S^-1 of the same H, which every caller uses (core/reference.py kept the
    Joseph form); see docs/estimator_core.md for why rounding does not break it here.
    """
    m, dim = y.shape
    yt = np.ascontiguousarray(y.T)
    out = np.empty((dim, dim))
    for i in range(dim):
        for j in range(i, dim):
            acc = 0.0
            for k in range(m):
                acc += yt[i, k] * yt[j, k]
            v = 0.5 * (p[i, j] + p[j, i]) - acc
            out[i, j] = v
            out[j, i] = v
    return out


@njit(cache=True)
def _factor(p: np.ndarray, h1: np.ndarray, h2: np.ndarray, r: np.ndarray, n: int,
            with_twist: bool) -> tuple:
    """Return (S, L, Y, K) of a measurement: S, its Cholesky factor, L^-1 H P and the gain."""
    cross = _cross(p, h1, h2, n, with_twist)
    s = _innovation_covariance(cross, h1, h2, r, n, with_twist)
    low = _cholesky(s)
    y = _whiten(low, cross)
    return s, low, y, _gain_from(low, y)


@njit(cache=True)
def innovation(g: np.ndarray, x: np.ndarray, p: np.ndarray, pose: np.ndarray,
               measured: np.ndarray, with_twist: bool, inverse_locked: np.ndarray,
               connection_qd: np.ndarray, joint_cov: np.ndarray, r_pose: np.ndarray,
               twist_var: np.ndarray, basis: np.ndarray, pinv: np.ndarray, whole: bool,
               form_rows: np.ndarray) -> tuple:
    """
    Return (H, nu, R, S, K, NIS, log det S, L^-1 H P) of a measurement.

    A pose alone has H = [1 0 0]; with a twist the H and innovation of
    :func:`twist_measurement`, and R holds the joint-velocity noise through A. One
    Cholesky factorisation of S gives the gain, the NIS and log det S; H enters by
    its blocks (its w columns are zero, its pose rows select).
    """
    n = inverse_locked.shape[0]
    dim = p.shape[0]
    if with_twist:
        h1, h2, nu = _twist_blocks(g, x, pose, measured, inverse_locked, connection_qd, basis,
                                   pinv, whole, form_rows)
        r = np.zeros((2 * n, 2 * n))
        for i in range(n):
            for j in range(n):
                r[i, j] = r_pose[i, j]
                r[n + i, n + j] = joint_cov[i, j]
            r[n + i, n + i] += twist_var[i]
    else:
        h1 = h2 = np.empty((0, 0))
        nu = group_log(compose(inverse(g), pose), pinv, whole)
        r = r_pose.copy()
    s, low, y, gain = _factor(p, h1, h2, r, n, with_twist)
    m = nu.shape[0]
    white = np.empty(m)
    logdet = 0.0
    for i in range(m):
        acc = nu[i]
        for k in range(i):
            acc -= low[i, k] * white[k]
        white[i] = acc / low[i, i]
        logdet += 2.0 * math.log(low[i, i])
    nis = 0.0
    for i in range(m):
        nis += white[i] * white[i]
    return _dense_h(h1, h2, n, dim, with_twist), nu, r, s, gain, nis, logdet, y


@njit(cache=True)
def correct(g: np.ndarray, x: np.ndarray, p: np.ndarray, pose: np.ndarray,
            measured: np.ndarray, with_twist: bool, h: np.ndarray, nu: np.ndarray,
            r: np.ndarray, gain: np.ndarray, inverse_locked: np.ndarray,
            connection_qd: np.ndarray, basis: np.ndarray, pinv: np.ndarray, whole: bool,
            form_rows: np.ndarray) -> tuple:
    """Return (g, x, P, H, S, K) after the update with the prior's gain K (dim x m)."""
    n = inverse_locked.shape[0]
    y = np.empty((0, 0))
    if not with_twist:
        _, _, y, _ = _factor(p, np.empty((0, 0)), np.empty((0, 0)), r, n, False)
    return _corrected(g, x, p, pose, measured, with_twist, h, nu, r, gain, y, inverse_locked,
                      connection_qd, basis, pinv, whole, form_rows)


@njit(cache=True)
def converged(previous: np.ndarray, dx: np.ndarray, p: np.ndarray) -> bool:
    """Whether dx moved from ``previous`` by less than CONVERGED sigma of P's every coordinate."""
    for i in range(dx.shape[0]):
        # NaN (a corrupted P) compares False: iterate on, as before.
        if not abs(dx[i] - previous[i]) <= CONVERGED * math.sqrt(max(p[i, i], 0.0)):
            return False
    return True


@njit(cache=True)
def _corrected(g: np.ndarray, x: np.ndarray, p: np.ndarray, pose: np.ndarray,
               measured: np.ndarray, with_twist: bool, h: np.ndarray, nu: np.ndarray,
               r: np.ndarray, gain: np.ndarray, y: np.ndarray, inverse_locked: np.ndarray,
               connection_qd: np.ndarray, basis: np.ndarray, pinv: np.ndarray, whole: bool,
               form_rows: np.ndarray) -> tuple:
    """
    Return (g, x, P, H, S, K) after the update with gain K (dim x m) from the prior.

    ``y``: L^-1 H P of the prior (:func:`innovation`), used by a pose alone.

    ``gain`` must be the prior's K = P H^T S^-1 (every caller passes it so). With a
    twist the update is iterated (Gauss-Newton on the posterior: the twist is
    bilinear in (g, mu)), up to ITERATIONS re-linearisations, fewer once one has
    :func:`converged`. P is P - K S K^T from the
    Cholesky factor of the last S (:func:`_downdate`): symmetric by construction, and
    equal to the Joseph form for this gain.
    """
    n = inverse_locked.shape[0]
    dim = p.shape[0]
    dx = _mat_vec(gain, nu)
    h1 = h2 = np.empty((0, 0))
    if with_twist:
        x_len = x.shape[0]
        s = np.empty((0, 0))
        y = np.empty((0, 0))
        for iteration in range(ITERATIONS):
            previous = dx
            g_i = compose(g, group_exp(dx[:n], basis, whole))
            x_i = x + dx[n:n + x_len]
            h1, h2, nu_i = _twist_blocks(g_i, x_i, pose, measured, inverse_locked,
                                         connection_qd, basis, pinv, whole, form_rows)
            s, _, y, gain = _factor(p, h1, h2, r, n, True)
            # nu_i + H_i dx, with H_i's blocks.
            for i in range(n):
                acc = 0.0
                for k in range(n):
                    acc += h1[i, k] * dx[k] + h2[i, k] * dx[n + k]
                nu_i[i] += dx[i]
                nu_i[n + i] += acc
            dx = _mat_vec(gain, nu_i)
            if iteration + 1 < ITERATIONS and converged(previous, dx, p):
                break
        h = _dense_h(h1, h2, n, dim, True)
    else:
        s = np.empty((n, n))
        for i in range(n):
            for j in range(n):
                s[i, j] = 0.5 * ((p[i, j] + r[i, j]) + (p[j, i] + r[j, i]))
    g1 = compose(g, group_exp(dx[:n], basis, whole))
    x1 = x + dx[n:]
    return g1, x1, _downdate(p, y), h, s, gain


@njit(cache=True)
def update(g: np.ndarray, x: np.ndarray, p: np.ndarray, pose: np.ndarray,
           measured: np.ndarray, with_twist: bool, inverse_locked: np.ndarray,
           connection_qd: np.ndarray, joint_cov: np.ndarray, pose_var: np.ndarray,
           stamp_twist: np.ndarray, stamp_sigma: float, twist_var: np.ndarray,
           gate: float, basis: np.ndarray, pinv: np.ndarray, whole: bool,
           form_rows: np.ndarray) -> tuple:
    """
    Update with a pose (and twist) unless its NIS exceeds ``gate``: one call per sample.

    Return (accepted, nis, logdet, nu, R, g, x, P, H, S, K); when gated (NIS above
    ``gate``) the state is the prior's and H, S, K those of the innovation.
    """
    return update_noise(g, x, p, pose, measured, with_twist, inverse_locked, connection_qd,
                        joint_cov, pose_noise(pose_var, stamp_twist, stamp_sigma), twist_var,
                        gate, basis, pinv, whole, form_rows)


@njit(cache=True)
def update_noise(g: np.ndarray, x: np.ndarray, p: np.ndarray, pose: np.ndarray,
                 measured: np.ndarray, with_twist: bool, inverse_locked: np.ndarray,
                 connection_qd: np.ndarray, joint_cov: np.ndarray, r_pose: np.ndarray,
                 twist_var: np.ndarray, gate: float, basis: np.ndarray, pinv: np.ndarray,
                 whole: bool, form_rows: np.ndarray) -> tuple:
    """
    Return what :func:`update` does, with the pose noise R given as a full matrix.

    For a sample that carries its own covariance (estimator/covariance.py): the
    twist's goes in with ``joint_cov``, ``twist_var`` then zeros.
    """
    h, nu, r, s, gain, nis, logdet, y = innovation(
        g, x, p, pose, measured, with_twist, inverse_locked, connection_qd, joint_cov, r_pose,
        twist_var, basis, pinv, whole, form_rows)
    if nis > gate:
        return False, nis, logdet, nu, r, g, x, p, h, s, gain
    g1, x1, p1, h1, s1, gain1 = _corrected(g, x, p, pose, measured, with_twist, h, nu, r,
                                           gain, y, inverse_locked, connection_qd, basis, pinv,
                                           whole, form_rows)
    return True, nis, logdet, nu, r, g1, x1, p1, h1, s1, gain1


@njit(cache=True)
def gain_of(p: np.ndarray, h: np.ndarray, r: np.ndarray) -> np.ndarray:
    """Return K = P H^T S^-1 with S = H P H^T + R symmetrised (Cholesky)."""
    ph = p @ h.T
    low = _cholesky(symmetric(h @ ph + r))
    return _gain_from(low, _whiten(low, ph))


@njit(cache=True)
def compensate(g: np.ndarray, x: np.ndarray, p: np.ndarray, correction: np.ndarray,
               covariance: np.ndarray, basis: np.ndarray, whole: bool) -> tuple:
    """Return the state after a detected wrench step: g exp(d_g), x + d_x, P + D J^-1 D^T."""
    n = p.shape[0] - x.shape[0]
    return (compose(g, group_exp(correction[:n], basis, whole)), x + correction[n:],
            symmetric(p + covariance))


@njit(cache=True)
def significance(x: np.ndarray, p: np.ndarray, n: int) -> float:
    """Return w^T P_ww^-1 w (chi-square with n degrees of freedom when w = 0)."""
    w = x[n:2 * n].copy()
    block = np.ascontiguousarray(p[2 * n:3 * n, 2 * n:3 * n])
    return w @ np.linalg.solve(block, w)


@njit(cache=True)
def covariance_health(p: np.ndarray) -> int:
    """Return 0 for a usable covariance, 1 when not finite, 2 with a negative variance."""
    dim = p.shape[0]
    for i in range(dim):
        for j in range(dim):
            if not np.isfinite(p[i, j]):
                return 1
    for i in range(dim):
        if not p[i, i] >= 0.0:
            return 2
    return 0


@njit(cache=True)
def propagate_update(g: np.ndarray, x: np.ndarray, p: np.ndarray, locked: np.ndarray,
                     step_inverse: np.ndarray, step_connection_qd: np.ndarray,
                     step_joint_cov: np.ndarray, dt: float, jerk_var: np.ndarray,
                     pose: np.ndarray, measured: np.ndarray, with_twist: bool,
                     inverse_locked: np.ndarray, connection_qd: np.ndarray,
                     joint_cov: np.ndarray, pose_var: np.ndarray, stamp_twist: np.ndarray,
                     stamp_sigma: float, twist_var: np.ndarray, gate: float,
                     twist_weight: float, basis: np.ndarray, pinv: np.ndarray, whole: bool,
                     ad_rows: np.ndarray, form_rows: np.ndarray) -> tuple:
    """
    Propagate (3n filter, ``step_*`` the step's inputs) and update: one call per step.

    The same operations as :func:`propagate` then :func:`update`, in one compiled
    call (the filter's common step: a measurement at the step's end). Return
    (g, x, P, Phi) predicted, then :func:`update`'s eleven results, then the
    health of the resulting covariance (:func:`covariance_health`: of the update's
    P when accepted, else of the prediction's), the stamp-noise twist average
    moved ``twist_weight`` towards the updated twist (accepted and
    ``twist_weight`` >= 0; else ``stamp_twist``) and :func:`significance` of the
    resulting state (NaN when its covariance is not healthy).
    """
    phi, q = transition(g, x, locked, step_inverse, step_connection_qd, step_joint_cov, dt,
                        jerk_var, basis, pinv, whole, ad_rows, form_rows)
    g0, x0 = propagate_mean(g, x, step_inverse, step_connection_qd, dt, np.empty(0), False,
                            basis, pinv, whole)
    p0 = _predicted_covariance(phi, p, q, dt)
    accepted, nis, logdet, nu, r, g1, x1, p1, h, s, gain = update(
        g0, x0, p0, pose, measured, with_twist, inverse_locked, connection_qd, joint_cov,
        pose_var, stamp_twist, stamp_sigma, twist_var, gate, basis, pinv, whole, form_rows)
    health = covariance_health(p1 if accepted else p0)
    # w^T P_ww^-1 w of the result (the event detector reads it after each row).
    wrench_test = significance(x1, p1, inverse_locked.shape[0]) if health == 0 else np.nan
    averaged = stamp_twist
    if accepted and twist_weight >= 0.0:
        n = inverse_locked.shape[0]
        averaged = stamp_twist + twist_weight * (
            twist(g1, x1[:n], inverse_locked, connection_qd, basis, pinv, whole) - stamp_twist)
    return (g0, x0, p0, phi, accepted, nis, logdet, nu, r, g1, x1, p1, h, s, gain, health,
            averaged, wrench_test)
