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
The reduced right-hand side with its algebra compiled: two Pinocchio calls per evaluation.

Same equations and the same route as :meth:`.ReducedSystem.vector_field`
(Theorem 54 with the magnetic terms contracted through Pinocchio's Coriolis
matrix, REDUCED_MODEL.md 7), plus the base-pose chart of
:class:`.ReducedPropagator` (``eta_dot = Jr(eta)^-1 xi``). One evaluation is

1. ``crba`` (M at the base identity),
2. :func:`momenta_kernel`: chi(q~1) = exp(S C q~1) g_ref, ``pi = Ad_chi^T mu``,
   one Cholesky factorisation of M (its leading block is I's), ``u = I^-1 pi``,
   ``A = I^-1 B``, ``w = M^-1 [0; pbar]`` and ``v = [u; 0] + w``,
3. ``computeCoriolisMatrix(q, v)``,
4. :func:`rates_kernel`: ``pbar_dot``, the orbit equation for ``q~1_dot``
   (left Jacobian of exp, closed form) and ``eta_dot``,

with the torque law called once in between. Everything numba compiles is
cached on disk (``cache=True``) and works in caller-owned buffers. The tests
hold it equal to :meth:`.ReducedSystem.vector_field` (round-off) on every
momentum class and base group, and the Lie maps equal to Pinocchio's.
"""

from __future__ import annotations

import math
from typing import Callable, Optional

import numpy as np
from numba import njit
import pinocchio as pin

from reduced_dynamics.estimator.core.cholesky import solve_factor
from reduced_dynamics.estimator.core.lie import exp6_coefficients

_crba = pin.crba
_coriolis = pin.computeCoriolisMatrix

#: Cholesky pivot below which M is reported as not positive definite.
_PIVOT_FLOOR = 0.0


@njit(cache=True)
def _mm3(a: np.ndarray, b: np.ndarray, out: np.ndarray) -> None:
    """Write a b into out, 3 x 3 (loops into scratch: BLAS and allocation cost more here)."""
    for i in range(3):
        for j in range(3):
            out[i, j] = a[i, 0] * b[0, j] + a[i, 1] * b[1, j] + a[i, 2] * b[2, j]


@njit(cache=True)
def _hat(x0: float, x1: float, x2: float, out: np.ndarray) -> None:
    out[0, 0], out[1, 1], out[2, 2] = 0.0, 0.0, 0.0
    out[0, 1], out[0, 2], out[1, 2] = -x2, x1, -x0
    out[1, 0], out[2, 0], out[2, 1] = x2, -x1, x0


#: 3 x 3 scratch matrices the Lie maps below need.
SCRATCH3 = 12


@njit(cache=True)
def left_jacobian6_into(twist: np.ndarray, out: np.ndarray, s3: np.ndarray) -> None:
    """
    Left Jacobian of exp on SE(3) at a twist (v, omega) into out: ``pin.Jexp6(-twist)``.

    ``exp(twist + d) = exp(Jl d) exp(twist)`` to first order. Blocks
    ``[[Jl(w), Q], [0, Jl(w)]]``, ``Jl(w) = 1 + (1 - cos t)/t^2 [w] + (t - sin t)/t^3
    [w]^2`` and Barfoot's Q (State Estimation for Robotics, 7.86). Series below
    1e-2 rad, where the closed forms cancel (Pinocchio's Jexp6 is off by ~1e-10
    around 1e-3 rad; this is within round-off of a 40-digit reference there).
    ``s3``: scratch of :data:`SCRATCH3` 3 x 3 matrices.
    """
    t2 = twist[3] * twist[3] + twist[4] * twist[4] + twist[5] * twist[5]
    t = math.sqrt(t2)
    if t < 1e-2:
        b = 0.5 - t2 / 24.0 + t2 * t2 / 720.0
        c1 = 1.0 / 6.0 - t2 / 120.0 + t2 * t2 / 5040.0
        c2 = 1.0 / 24.0 - t2 / 720.0 + t2 * t2 / 40320.0
        c3 = 1.0 / 120.0 - t2 / 2520.0 + t2 * t2 / 120960.0
    else:
        s, c = math.sin(t), math.cos(t)
        half = math.sin(0.5 * t)
        t4 = t2 * t2
        b = 2.0 * half * half / t2
        c1 = (t - s) / (t2 * t)
        c2 = (t2 + 2.0 * c - 2.0) / (2.0 * t4)
        c3 = (2.0 * t - 3.0 * s + t * c) / (2.0 * t4 * t)
    wx, rx, ww, wr, rw, wrw, wwr, rww, wrww, wwrw = \
        s3[0], s3[1], s3[2], s3[3], s3[4], s3[5], s3[6], s3[7], s3[8], s3[9]
    _hat(twist[3], twist[4], twist[5], wx)
    _hat(twist[0], twist[1], twist[2], rx)
    _mm3(wx, wx, ww)
    _mm3(wx, rx, wr)
    _mm3(rx, wx, rw)
    _mm3(wr, wx, wrw)
    _mm3(wx, wr, wwr)
    _mm3(rw, wx, rww)
    _mm3(wrw, wx, wrww)
    _mm3(wx, wrw, wwrw)
    for i in range(3):
        for j in range(3):
            jl = b * wx[i, j] + c1 * ww[i, j]
            if i == j:
                jl += 1.0
            out[i, j] = jl
            out[3 + i, 3 + j] = jl
            out[3 + i, j] = 0.0
            out[i, 3 + j] = 0.5 * rx[i, j] + c1 * (wr[i, j] + rw[i, j] + wrw[i, j]) \
                + c2 * (wwr[i, j] + rww[i, j] - 3.0 * wrw[i, j]) \
                + c3 * (wrww[i, j] + wwrw[i, j])


@njit(cache=True)
def left_jacobian6(twist: np.ndarray) -> np.ndarray:
    """Return :func:`left_jacobian6_into` as a new 6 x 6 array (``pin.Jexp6(-twist)``)."""
    out = np.empty((6, 6))
    left_jacobian6_into(twist, out, np.empty((SCRATCH3, 3, 3)))
    return out


@njit(cache=True)
def _inverse3(a: np.ndarray, out: np.ndarray) -> None:
    """Inverse of a 3 x 3 matrix by cofactors (the SO(3) Jacobian: well conditioned)."""
    out[0, 0] = a[1, 1] * a[2, 2] - a[1, 2] * a[2, 1]
    out[0, 1] = a[0, 2] * a[2, 1] - a[0, 1] * a[2, 2]
    out[0, 2] = a[0, 1] * a[1, 2] - a[0, 2] * a[1, 1]
    out[1, 0] = a[1, 2] * a[2, 0] - a[1, 0] * a[2, 2]
    out[1, 1] = a[0, 0] * a[2, 2] - a[0, 2] * a[2, 0]
    out[1, 2] = a[0, 2] * a[1, 0] - a[0, 0] * a[1, 2]
    out[2, 0] = a[1, 0] * a[2, 1] - a[1, 1] * a[2, 0]
    out[2, 1] = a[0, 1] * a[2, 0] - a[0, 0] * a[2, 1]
    out[2, 2] = a[0, 0] * a[1, 1] - a[0, 1] * a[1, 0]
    det = a[0, 0] * out[0, 0] + a[0, 1] * out[1, 0] + a[0, 2] * out[2, 0]
    for i in range(3):
        for j in range(3):
            out[i, j] /= det


@njit(cache=True)
def right_jacobian6_inverse_into(twist: np.ndarray, out: np.ndarray, s3: np.ndarray) -> None:
    """
    Inverse right Jacobian of exp on SE(3) into out: ``pin.Jlog6(pin.exp6(twist))``.

    ``Jr(x) = Jl(-x)`` is block upper triangular ``[[J, Q], [0, J]]``, so its
    inverse is ``[[J^-1, -J^-1 Q J^-1], [0, J^-1]]`` (|omega| < pi). Uses ``out``
    itself for Jr first.
    """
    negated = np.empty(6)
    for i in range(6):
        negated[i] = -twist[i]
    left_jacobian6_into(negated, out, s3)
    inv, tmp = s3[10], s3[11]
    _inverse3(out[:3, :3], inv)
    _mm3(inv, out[:3, 3:], tmp)
    _mm3(tmp, inv, s3[0])
    for i in range(3):
        for j in range(3):
            out[i, j] = inv[i, j]
            out[3 + i, 3 + j] = inv[i, j]
            out[3 + i, j] = 0.0
            out[i, 3 + j] = -s3[0, i, j]


@njit(cache=True)
def right_jacobian6_inverse(twist: np.ndarray) -> np.ndarray:
    """Return :func:`right_jacobian6_inverse_into` as a new array (``Jlog6(exp6(x))``)."""
    out = np.empty((6, 6))
    right_jacobian6_inverse_into(twist, out, np.empty((SCRATCH3, 3, 3)))
    return out


@njit(cache=True)
def _solve_small(a: np.ndarray, b: np.ndarray, out: np.ndarray) -> bool:
    """Gaussian elimination with partial pivoting (k <= 6); False if singular."""
    size = b.shape[0]
    work = a.copy()
    rhs = b.copy()
    for col in range(size):
        pivot = col
        for row in range(col + 1, size):
            if abs(work[row, col]) > abs(work[pivot, col]):
                pivot = row
        if work[pivot, col] == 0.0:
            return False
        if pivot != col:
            for j in range(size):
                work[col, j], work[pivot, j] = work[pivot, j], work[col, j]
            rhs[col], rhs[pivot] = rhs[pivot], rhs[col]
        for row in range(col + 1, size):
            factor = work[row, col] / work[col, col]
            for j in range(col, size):
                work[row, j] -= factor * work[col, j]
            rhs[row] -= factor * rhs[col]
    for row in range(size - 1, -1, -1):
        total = rhs[row]
        for j in range(row + 1, size):
            total -= work[row, j] * out[j]
        out[row] = total / work[row, row]
    return True


@njit(cache=True)
def _cholesky_upper(mass: np.ndarray, factor: np.ndarray) -> bool:
    """Lower Cholesky factor of M from its upper triangle (crba fills only that)."""
    size = mass.shape[0]
    for j in range(size):
        total = mass[j, j]
        for p in range(j):
            total -= factor[j, p] * factor[j, p]
        if not total > _PIVOT_FLOOR:
            return False
        diagonal = math.sqrt(total)
        factor[j, j] = diagonal
        for i in range(j + 1, size):
            total = mass[j, i]
            for p in range(j):
                total -= factor[i, p] * factor[j, p]
            factor[i, j] = total / diagonal
    return True


@njit(cache=True)
def _exp_times(twist: np.ndarray, g: np.ndarray, out: np.ndarray, s3: np.ndarray) -> None:
    """
    Write exp6(twist) g into out (``pin.exp6``'s closed form, in loops: no BLAS).

    The closed form's coefficients are :func:`.core.lie.exp6_coefficients`, the
    estimator core's ``exp6``.
    """
    w0, w1, w2 = twist[3], twist[4], twist[5]
    a, b, c = exp6_coefficients(w0 * w0 + w1 * w1 + w2 * w2)
    k, k2 = s3[0], s3[1]
    _hat(w0, w1, w2, k)
    _mm3(k, k, k2)
    e = np.empty((3, 4))
    for i in range(3):
        for j in range(3):
            e[i, j] = a * k[i, j] + b * k2[i, j]
        e[i, i] += 1.0
        e[i, 3] = twist[i]
        for j in range(3):
            e[i, 3] += (b * k[i, j] + c * k2[i, j]) * twist[j]
    for i in range(3):
        for j in range(4):
            total = e[i, 0] * g[0, j] + e[i, 1] * g[1, j] + e[i, 2] * g[2, j]
            out[i, j] = total + e[i, 3] if j == 3 else total
    out[3, 0], out[3, 1], out[3, 2], out[3, 3] = 0.0, 0.0, 0.0, 1.0


@njit(cache=True)
def momenta_kernel(q1: np.ndarray, pbar: np.ndarray, mass: np.ndarray,
                   with_connection: bool, chart_twist: np.ndarray, g_ref: np.ndarray,
                   mu6: np.ndarray, basis: np.ndarray, whole: bool, factor: np.ndarray,
                   twist: np.ndarray, chi: np.ndarray, pi: np.ndarray, drift: np.ndarray,
                   connection: np.ndarray, v: np.ndarray, s3: np.ndarray) -> bool:
    """
    Fill chi, pi, u~ = [I^-1 pi; 0], v = u~ + M^-1 [0; pbar] (and A = I^-1 B).

    ``factor`` receives the lower Cholesky factor L of M; A only
    ``with_connection`` (the right-hand side contracts it through L instead).

    ``pi = S^T Ad_chi^T (S+)^T mu`` with ``chi = exp(S C q~1) g_ref``
    (REDUCED_MODEL.md 5); ``w = M^-1 [0; pbar] = [-A qbar_dot; qbar_dot]`` since
    S is the Schur complement of I in M (3-4). Returns False when M is not
    positive definite.
    """
    n = pi.shape[0]
    size = mass.shape[0]
    k = q1.shape[0]
    for i in range(6):
        total = 0.0
        for j in range(k):
            total += chart_twist[i, j] * q1[j]
        twist[i] = total
    if k:
        _exp_times(twist, g_ref, chi, s3)
    else:
        chi[:, :] = g_ref
    # Ad_chi^T [f; t] = [R^T f; R^T (t - p x f)] (loops: no products of strided views)
    torque = np.empty(3)
    for i in range(3):
        a, b = (i + 1) % 3, (i + 2) % 3
        torque[i] = mu6[3 + i] - (chi[a, 3] * mu6[b] - chi[b, 3] * mu6[a])
    wrench = np.empty(6)
    for i in range(3):
        wrench[i] = chi[0, i] * mu6[0] + chi[1, i] * mu6[1] + chi[2, i] * mu6[2]
        wrench[3 + i] = chi[0, i] * torque[0] + chi[1, i] * torque[1] + chi[2, i] * torque[2]
    if whole:
        pi[:] = wrench
    else:
        for a in range(n):
            total = 0.0
            for i in range(6):
                total += basis[i, a] * wrench[i]
            pi[a] = total
    if not _cholesky_upper(mass, factor):
        return False
    drift[:] = 0.0
    drift[:n] = pi
    solve_factor(factor, n, drift)
    if with_connection:
        column = np.empty(n)
        for j in range(size - n):
            for i in range(n):
                column[i] = mass[i, n + j]
            solve_factor(factor, n, column)
            connection[:, j] = column
    v[:n] = 0.0
    v[n:] = pbar
    solve_factor(factor, size, v)
    for i in range(n):
        v[i] += drift[i]
    return True


@njit(cache=True)
def rates_kernel(coriolis: np.ndarray, tau: np.ndarray, eta: np.ndarray, out: np.ndarray,
                 v: np.ndarray, drift: np.ndarray, factor: np.ndarray,
                 twist: np.ndarray, chi: np.ndarray, chart_twist: np.ndarray,
                 kirillov_mu_t: np.ndarray, basis: np.ndarray, pinv: np.ndarray,
                 whole: bool, s3: np.ndarray) -> bool:
    """
    Fill out = (q~1_dot, qbar_dot, pbar_dot, eta_dot) from C(q, v) and the momenta.

    ``pbar_dot = [-A; 1]^T (C^T w - C u~) + tau`` and ``L^T W^T L q~1_dot =
    L^T W^T xi`` written with W(mu) through coadjoint equivariance
    (:meth:`.ReducedSystem.vector_field`); ``eta_dot = Jr(eta)^-1 xi``. With L
    the Cholesky factor of M (:func:`momenta_kernel`), ``A^T h_base = L21 L11^-1
    h_base``: no A needed. Returns False when the orbit form is singular.
    """
    n = basis.shape[1]
    size = v.shape[0]
    m = size - n
    k = chart_twist.shape[1]
    # h = C^T w - C u~ with w = v - u~ (u~ vanishes below row n).
    h = np.zeros(size)
    for j in range(size):
        total = 0.0
        for i in range(size):
            wi = v[i] - drift[i] if i < n else v[i]
            total += coriolis[i, j] * wi
        for i in range(n):
            total -= coriolis[j, i] * drift[i]
        h[j] = total
    # y = L11^-1 h_base; A^T h_base = L21 y (B = L11 L21^T, I = L11 L11^T).
    y = np.empty(n)
    for i in range(n):
        total = h[i]
        for p in range(i):
            total -= factor[i, p] * y[p]
        y[i] = total / factor[i, i]
    for j in range(m):
        total = h[n + j] + tau[j]
        for i in range(n):
            total -= factor[n + j, i] * y[i]
        out[k + m + j] = total
        out[k + j] = v[n + j]
    xi6 = np.empty(6)
    for i in range(6):
        total = 0.0
        if whole:
            total = v[i]
        else:
            for a in range(n):
                total += basis[i, a] * v[a]
        xi6[i] = total
    jac = np.empty((6, 6))
    if k:
        # P = Jl(S C q~1) S C (6 x k), solve (P^T W^T P) q~1_dot = P^T W^T Ad_chi xi.
        left_jacobian6_into(twist, jac, s3)
        spatial = np.zeros((6, k))
        for i in range(6):
            for j in range(k):
                total = 0.0
                for a in range(6):
                    total += jac[i, a] * chart_twist[a, j]
                spatial[i, j] = total
        kirillov_t = np.zeros((k, 6))
        for i in range(k):
            for j in range(6):
                total = 0.0
                for a in range(6):
                    total += spatial[a, i] * kirillov_mu_t[a, j]
                kirillov_t[i, j] = total
        lhs = np.zeros((k, k))
        for i in range(k):
            for j in range(k):
                total = 0.0
                for a in range(6):
                    total += kirillov_t[i, a] * spatial[a, j]
                lhs[i, j] = total
        # Ad_chi xi = [R v + p x (R w); R w]
        rw = np.empty(3)
        xi_world = np.empty(6)
        for i in range(3):
            rw[i] = chi[i, 0] * xi6[3] + chi[i, 1] * xi6[4] + chi[i, 2] * xi6[5]
        for i in range(3):
            a, b = (i + 1) % 3, (i + 2) % 3
            xi_world[i] = chi[i, 0] * xi6[0] + chi[i, 1] * xi6[1] + chi[i, 2] * xi6[2] \
                + chi[a, 3] * rw[b] - chi[b, 3] * rw[a]
            xi_world[3 + i] = rw[i]
        rhs = np.zeros(k)
        for i in range(k):
            total = 0.0
            for a in range(6):
                total += kirillov_t[i, a] * xi_world[a]
            rhs[i] = total
        if not _solve_small(lhs, rhs, out[:k]):
            return False
    eta6 = np.empty(6)
    for i in range(6):
        total = 0.0
        if whole:
            total = eta[i]
        else:
            for a in range(n):
                total += basis[i, a] * eta[a]
        eta6[i] = total
    right_jacobian6_inverse_into(eta6, jac, s3)
    rate = np.empty(6)
    for i in range(6):
        total = 0.0
        for a in range(6):
            total += jac[i, a] * xi6[a]
        rate[i] = total
    base = k + 2 * m
    for i in range(n):
        if whole:
            out[base + i] = rate[i]
        else:
            total = 0.0
            for a in range(6):
                total += pinv[i, a] * rate[a]
            out[base + i] = total
    return True


@njit(cache=True)
def gradient_kernel(d_mu: np.ndarray, d_mw: np.ndarray, v: np.ndarray, drift: np.ndarray,
                    connection: np.ndarray, pi: np.ndarray, twist: np.ndarray,
                    g_ref: np.ndarray, chart_twist: np.ndarray, basis: np.ndarray,
                    pinv: np.ndarray, whole: bool, gradient: np.ndarray,
                    structure: np.ndarray, s3: np.ndarray) -> None:
    """
    Fill grad H~ and the structure matrix of Theorem 54 (:meth:`.ReducedSystem.evaluate`).

    ``d_mu``, ``d_mw``: RNEA derivatives ``d(M u~)/dq`` and ``d(M w)/dq`` (all nv
    columns; the shape ones are used). ``dH~/dqbar = -1/2 u~^T d_iM u~ - 1/2 w^T
    d_iM w``, curvature ``C = P^T - P`` with ``P = [-A; 1]^T dM u~``
    (hamiltonian.py), ``U[q~1, q~1] = L^T W L``, ``U[qbar, q~1] = A^T W L``,
    ``dH~/dq~1 = -(W L)^T I^-1 pi`` (magnetic.py) with L the chart's body
    Jacobian and ``W = S^T W6(S+^T pi) S``, ``W6(f, t) = [[0, -[f]], [-[f], -[t]]]``
    the Kirillov form on se(3). The potential's gradient is the caller's.
    """
    n = pi.shape[0]
    size = v.shape[0]
    m = size - n
    k = chart_twist.shape[1]
    for j in range(m):
        total = 0.0
        for a in range(n):
            total -= 0.5 * drift[a] * d_mu[a, n + j]
        for a in range(size):
            wa = v[a] - drift[a] if a < n else v[a]
            total -= 0.5 * wa * d_mw[a, n + j]
        gradient[k + j] = total
        gradient[k + m + j] = v[n + j]
    structure[:, :] = 0.0
    # P[i, j] = (d_mu[n + i] - A^T d_mu[:n])[j]; C = P^T - P.
    p_mat = np.empty((m, m))
    for i in range(m):
        for j in range(m):
            total = d_mu[n + i, n + j]
            for a in range(n):
                total -= connection[a, i] * d_mu[a, n + j]
            p_mat[i, j] = total
    for i in range(m):
        for j in range(m):
            structure[k + i, k + j] = p_mat[j, i] - p_mat[i, j]
        structure[k + i, k + m + i] = -1.0
        structure[k + m + i, k + i] = 1.0
    if not k:
        return
    # L = S+ Ad(g_ref^-1) Jr(S C q~1) S C  (n x k): CosetChart.body_jacobian.
    jac = np.empty((6, 6))
    negated = np.empty(6)
    for i in range(6):
        negated[i] = -twist[i]
    left_jacobian6_into(negated, jac, s3)
    body = np.zeros((6, k))
    for i in range(6):
        for j in range(k):
            total = 0.0
            for a in range(6):
                total += jac[i, a] * chart_twist[a, j]
            body[i, j] = total
    # Ad(g^-1) x = [R^T (v - p x w); R^T w] for x = (v, w)
    lift = np.zeros((6, k))
    for j in range(k):
        for i in range(3):
            a, b = (i + 1) % 3, (i + 2) % 3
            s3[0, 0, i] = body[i, j] - (g_ref[a, 3] * body[3 + b, j]
                                        - g_ref[b, 3] * body[3 + a, j])
        for i in range(3):
            lift[i, j] = g_ref[0, i] * s3[0, 0, 0] + g_ref[1, i] * s3[0, 0, 1] \
                + g_ref[2, i] * s3[0, 0, 2]
            lift[3 + i, j] = g_ref[0, i] * body[3, j] + g_ref[1, i] * body[4, j] \
                + g_ref[2, i] * body[5, j]
    # W6 L6 with W6(f, t) = [[0, -[f]], [-[f], -[t]]], pi6 = S+^T pi.
    pi6 = np.empty(6)
    for i in range(6):
        if whole:
            pi6[i] = pi[i]
        else:
            total = 0.0
            for a in range(n):
                total += pinv[a, i] * pi[a]
            pi6[i] = total
    wl6 = np.zeros((6, k))
    for j in range(k):
        for i in range(3):
            a, b = (i + 1) % 3, (i + 2) % 3
            # -[f] x = x x f ; rows v: -[f] w_part ; rows w: -[f] v_part - [t] w_part
            wl6[i, j] = lift[3 + a, j] * pi6[b] - lift[3 + b, j] * pi6[a]
            wl6[3 + i, j] = lift[a, j] * pi6[b] - lift[b, j] * pi6[a] \
                + lift[3 + a, j] * pi6[3 + b] - lift[3 + b, j] * pi6[3 + a]
    # Project: L = S+ lift (lift lies in span S), W L = S^T wl6.
    chart_jac = np.zeros((n, k))
    wl = np.zeros((n, k))
    for i in range(n):
        for j in range(k):
            if whole:
                chart_jac[i, j] = lift[i, j]
                wl[i, j] = wl6[i, j]
            else:
                t1 = 0.0
                t2 = 0.0
                for a in range(6):
                    t1 += pinv[i, a] * lift[a, j]
                    t2 += basis[a, i] * wl6[a, j]
                chart_jac[i, j] = t1
                wl[i, j] = t2
    for j in range(k):
        total = 0.0
        for a in range(n):
            total -= wl[a, j] * drift[a]
        gradient[j] = total
        for i in range(k):
            total = 0.0
            for a in range(n):
                total += chart_jac[a, i] * wl[a, j]
            structure[i, j] = total
        for i in range(m):
            total = 0.0
            for a in range(n):
                total += connection[a, i] * wl[a, j]
            structure[k + i, j] = total
            structure[j, k + i] = -total


class LeanField:
    """
    The reduced right-hand side of a :class:`.ReducedPropagator`, compiled.

    Owns its buffers; reads the system's chart centre afresh after a re-centring.
    """

    def __init__(self, system) -> None:
        """Set up buffers and constants for ``system`` (a :class:`.ReducedSystem`)."""
        fast = system._fast
        self.system = system
        self.k, self.m, self.n = system.k, system.m, fast.n
        self.nz = self.k + 2 * self.m
        self.work = fast.work
        self.potential = bool(fast.potential)
        size = self.n + self.m
        self.whole = bool(fast.whole)
        self.basis = np.ascontiguousarray(fast.basis, dtype=float)
        self.pinv = np.ascontiguousarray(fast.pinv, dtype=float)
        self.mu6 = np.ascontiguousarray(fast.mu6, dtype=float)
        self.kirillov_mu_t = np.ascontiguousarray(fast.kirillov_mu_t, dtype=float)
        self.chart_twist = np.ascontiguousarray(fast.chart_twist, dtype=float).reshape(6, self.k)
        self.g_ref = np.eye(4)
        self.factor = np.zeros((size, size))
        self.twist = np.zeros(6)
        self.chi = np.eye(4)
        self.pi = np.zeros(self.n)
        self.drift = np.zeros(size)
        self.connection = np.zeros((self.n, self.m))
        self.v = np.zeros(size)
        self.s3 = np.zeros((SCRATCH3, 3, 3))
        self._w = np.zeros(size)
        self._zero = np.zeros(size)
        work = self.work
        self._q, self._model, self._data = work.q, work.model, work.data
        self._kinetic_model, self._kinetic_data = work.kinetic_model, work.kinetic_data
        k, m, nz = self.k, self.m, self.nz
        self._q_shape = slice(work.nq_base, None)
        self._q1, self._shape = slice(0, k), slice(k, k + m)
        self._pbar, self._eta = slice(k + m, nz), slice(nz, None)
        # Buffers and constants, in the kernels' argument order (updated in place).
        self._momenta_args = (self.chart_twist, self.g_ref, self.mu6, self.basis, self.whole,
                              self.factor, self.twist, self.chi, self.pi, self.drift,
                              self.connection, self.v, self.s3)
        self._rates_args = (self.v, self.drift, self.factor, self.twist, self.chi,
                            self.chart_twist, self.kirillov_mu_t, self.basis, self.pinv,
                            self.whole, self.s3)
        self._chart = None

    def _refresh_chart(self) -> None:
        chart = self.system.chart
        if self._chart is not chart:
            self._chart = chart
            self.g_ref[:, :] = chart.g_ref.homogeneous

    def _momenta(self, y: np.ndarray, with_connection: bool = False) -> None:
        """Run crba and :func:`momenta_kernel` at y: fills pi, u~, v (and A)."""
        if self._chart is not self.system.chart:
            self._refresh_chart()
        q = self._q
        q[self._q_shape] = y[self._shape]
        mass = _crba(self._model, self._data, q)
        if not momenta_kernel(y[self._q1], y[self._pbar], mass, with_connection,
                              *self._momenta_args):
            raise np.linalg.LinAlgError('mass matrix M is not positive definite')

    def kinematics(self, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        """
        Return (pi, xi, qbar_dot, H~) at y, as :meth:`.ReducedSystem.kinematics`.

        ``H~ = 1/2 pi^T I^-1 pi + 1/2 pbar^T qbar_dot + V`` (5.36).
        """
        self._momenta(y)
        n, k, m = self.n, self.k, self.m
        v = self.v
        pi = self.pi.copy()
        qbar_dot = v[n:].copy()
        energy = 0.5 * float(pi @ self.drift[:n]) + 0.5 * float(y[k + m:self.nz] @ qbar_dot)
        if self.potential:
            energy += self.system.robot.potential_energy(y[k:k + m])
        return pi, v[:n].copy(), qbar_dot, energy

    def energy(self, z: np.ndarray) -> float:
        """Return H~ at z = (q~1, qbar, pbar) (5.36), as :meth:`.ReducedSystem.hamiltonian`."""
        self._momenta(z)
        k, m, n = self.k, self.m, self.n
        pbar = z[k + m:self.nz]
        energy = 0.5 * float(self.pi @ self.drift[:n]) + 0.5 * float(pbar @ self.v[n:])
        if self.potential:
            energy += self.system.robot.potential_energy(z[k:k + m])
        return energy

    def evaluate(self, z: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
        """
        Return (H~, grad H~, structure) at z: :meth:`.ReducedSystem.evaluate` without tau.

        What the discrete gradient needs, from crba, two RNEA-derivative calls and
        :func:`gradient_kernel`. Leaves v = [xi; qbar_dot] in :attr:`v`.
        """
        self._momenta(z, True)
        k, m, n = self.k, self.m, self.n
        work = self.work
        drift, v = self.drift, self.v
        w = self._w
        np.subtract(v, drift, out=w)
        derivatives = pin.computeRNEADerivatives
        # Pinocchio hands back its Data's dtau_dq: copy before the second call overwrites it.
        d_mu = derivatives(work.kinetic_model, work.kinetic_data, work.q, self._zero,
                           drift)[0].copy()
        d_mw = derivatives(work.kinetic_model, work.kinetic_data, work.q, self._zero, w)[0]
        gradient = np.empty(self.nz)
        structure = np.empty((self.nz, self.nz))
        gradient_kernel(d_mu, d_mw, v, drift, self.connection, self.pi, self.twist,
                        self.g_ref, self.chart_twist, self.basis, self.pinv, self.whole,
                        gradient, structure, self.s3)
        energy = 0.5 * float(self.pi @ drift[:n]) + 0.5 * float(z[k + m:self.nz] @ v[n:])
        if self.potential:
            qbar = z[k:k + m]
            gradient[k:k + m] += self.system.robot.potential_gradient(qbar)
            energy += self.system.robot.potential_energy(qbar)
        return energy, gradient, structure

    def __call__(self, t: float, y: np.ndarray, torque: Callable,
                 out: Optional[np.ndarray] = None) -> np.ndarray:
        """Return dy/dt for y = (q~1, qbar, pbar, eta) under ``torque(t, qbar, qbar_dot)``."""
        # _momenta inlined, attributes bound once: this is the integrator's inner loop.
        if self._chart is not self.system.chart:
            self._refresh_chart()
        q = self._q
        qbar = y[self._shape]
        q[self._q_shape] = qbar
        mass = _crba(self._model, self._data, q)
        if not momenta_kernel(y[self._q1], y[self._pbar], mass, False, *self._momenta_args):
            raise np.linalg.LinAlgError('mass matrix M is not positive definite')
        v = self.v
        coriolis = _coriolis(self._kinetic_model, self._kinetic_data, q, v)
        tau = torque(t, qbar, v[self.n:])
        if self.potential:
            tau = tau - self.system.robot.potential_gradient(qbar)
        if out is None:
            out = np.empty(y.shape)
        if not rates_kernel(coriolis, tau, y[self._eta], out, *self._rates_args):
            raise np.linalg.LinAlgError('orbit form L^T W L is singular')
        return out


_warm = False


def warm_up() -> None:
    """
    Run every kernel of this module once in this process (load or compile them).

    Called where predictions are configured, so the first prediction's wall-time
    budget does not pay numba's load (or compilation) of these kernels.
    """
    global _warm
    if _warm:
        return
    from reduced_dynamics.reduction.reconstruction import ReducedPropagator
    from reduced_dynamics.robot.model import load_robot
    from reduced_dynamics.robot.random_tree import random_tree_urdf
    from reduced_dynamics.robot.state import FreeFloatingState
    robot = load_robot(random_tree_urdf(2, seed=0))
    state = FreeFloatingState(pin.SE3.Identity(), np.full(robot.n, 0.01), np.full(robot.m, 0.1),
                              np.full(robot.m, 0.02))
    propagator, y = ReducedPropagator.from_full_state(robot, state)
    propagator.rhs(0.0, y)
    propagator.observe(0.0, y)
    field = propagator._lean_field()
    field.evaluate(y[:field.nz])
    field.energy(y[:field.nz])
    left_jacobian6(np.zeros(6))
    right_jacobian6_inverse(np.zeros(6))
    _warm = True
