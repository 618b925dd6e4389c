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
Compiled inner loops of the wrench-step test (estimator/step_test.py).

Small dense algebra on preallocated arrays, compiled once with numba and cached
on disk (``cache=True``). Imported on first use, so that commands that never
run the filter do not pay for importing numba. Equations (S5)-(S8) are those
of docs/step_test.md.
"""

import math

from numba import njit
import numpy as np

from reduced_dynamics.estimator.core.cholesky import lower_factor


@njit(cache=True)
def _solve_in_place(low: np.ndarray, rhs: np.ndarray) -> None:
    """Overwrite the columns of ``rhs`` with (L L^T)^-1 rhs (forward, then back)."""
    n, cols = rhs.shape
    for r in range(n):
        for k in range(r):
            f = low[r, k]
            for c in range(cols):
                rhs[r, c] -= f * rhs[k, c]
        d = 1.0 / low[r, r]
        for c in range(cols):
            rhs[r, c] *= d
    for r in range(n - 1, -1, -1):
        for k in range(r + 1, n):
            f = low[k, r]
            for c in range(cols):
                rhs[r, c] -= f * rhs[k, c]
        d = 1.0 / low[r, r]
        for c in range(cols):
            rhs[r, c] *= d


@njit(cache=True)
def _quadratic(j: np.ndarray, b: np.ndarray) -> float:
    """Return b^T j^-1 b; NaN when j is not positive definite."""
    n = len(b)
    low = np.zeros((n, n))
    if not lower_factor(j, low):
        return math.nan
    quad = 0.0
    y = np.empty(n)
    for r in range(n):
        acc = b[r]
        for k in range(r):
            acc -= low[r, k] * y[k]
        y[r] = acc / low[r, r]
        quad += y[r] * y[r]
    return quad


@njit(cache=True)
def _information(c: np.ndarray, omega: np.ndarray, j0: np.ndarray, out: np.ndarray) -> None:
    """Write J0 + C^T Omega C into ``out`` (S6); C is dim x n."""
    dim, n = c.shape
    oc = np.zeros((dim, n))
    for r in range(dim):
        for k in range(dim):
            o = omega[r, k]
            if o != 0.0:
                for col in range(n):
                    oc[r, col] += o * c[k, col]
    for a in range(n):
        for b in range(n):
            acc = j0[a, b]
            for r in range(dim):
                acc += c[r, a] * oc[r, b]
            out[a, b] = acc


@njit(cache=True)
def absorb(h: np.ndarray, s: np.ndarray, gain: np.ndarray, nu: np.ndarray,
           psi: np.ndarray, omega: np.ndarray, beta: np.ndarray, outlier: float) -> float:
    """
    Take one update into Psi, Omega and beta (S5); return the innovation's NIS.

    Psi follows the update whatever the NIS (the filter took it); an outlier
    (NIS above ``outlier``) adds no evidence. NaN: S is not positive definite.
    """
    m, dim = h.shape
    lower = np.zeros((m, dim))           # L = H Psi^-: every onset's G is L C_i
    for r in range(m):
        for k in range(dim):
            f = h[r, k]
            if f != 0.0:                 # a pose's H is mostly zeros
                for c in range(dim):
                    lower[r, c] += f * psi[k, c]
    for r in range(dim):
        for k in range(m):
            f = gain[r, k]
            for c in range(dim):
                psi[r, c] -= f * lower[k, c]
    low = np.zeros((m, m))
    if not lower_factor(s, low):
        return math.nan
    solved = np.empty((m, dim + 1))      # S^-1 [L, nu]
    for r in range(m):
        for c in range(dim):
            solved[r, c] = lower[r, c]
        solved[r, dim] = nu[r]
    _solve_in_place(low, solved)
    nis = 0.0
    for r in range(m):
        nis += nu[r] * solved[r, dim]
    if nis > outlier:
        return nis
    for k in range(m):
        for a in range(dim):
            f = lower[k, a]
            if f != 0.0:
                beta[a] += f * solved[k, dim]
                for b in range(dim):
                    omega[a, b] += f * solved[k, b]
    return nis


@njit(cache=True)
def evaluate(c: np.ndarray, b0: np.ndarray, j0: np.ndarray, bound_inv: np.ndarray,
             bounded: np.ndarray, count: int, omega: np.ndarray, beta: np.ndarray,
             scale: float, threshold: float, score: np.ndarray) -> tuple:
    """
    Return (best onset or -1, its statistic, the largest bound, onsets evaluated exactly).

    Scores b_i (S6) of all onsets go to ``score``; bounds (S8) order the exact
    evaluations (S6, S3), which stop where no bound exceeds both the threshold
    and the best statistic found: the maximiser above the threshold, if any,
    is then the explicit bank's.
    """
    dim, n = c.shape[1], c.shape[2]
    bounds = np.empty(count)
    candidates = 0
    top = 0.0
    for i in range(count):
        for a in range(n):
            score[i, a] = b0[i, a]
        for r in range(dim):
            f = beta[r]
            for a in range(n):
                score[i, a] += c[i, r, a] * f
        bound = math.inf
        if bounded[i]:
            bound = 0.0
            for a in range(n):
                acc = 0.0
                for b in range(n):
                    acc += bound_inv[i, a, b] * score[i, b]
                bound += score[i, a] * acc
            bound /= scale
        bounds[i] = bound
        top = max(top, bound)
        candidates += bound > threshold
    # Only onsets whose bound passes the threshold can be detected: best bound first.
    order = np.argsort(-bounds)[:candidates]
    best, best_index, evaluated = -math.inf, -1, 0
    information = np.empty((n, n))
    for index in order:
        if not bounds[index] > max(best, threshold):
            break
        _information(c[index], omega, j0[index], information)
        statistic = _quadratic(information, score[index]) / scale
        evaluated += 1
        if statistic > best:
            best, best_index = statistic, index
    return best_index, best, top, evaluated


@njit(cache=True)
def fold(c: np.ndarray, b0: np.ndarray, j0: np.ndarray, bound_inv: np.ndarray,
         bounded: np.ndarray, count: int, psi: np.ndarray, omega: np.ndarray,
         beta: np.ndarray) -> None:
    """Move the anchor to now (S7): each onset absorbs the segment's Omega, beta and Psi."""
    dim, n = c.shape[1], c.shape[2]
    # Every C_i side by side (dim x count n): Omega C and Psi C as two matrix products.
    stacked = np.empty((dim, count * n))
    for i in range(count):
        for r in range(dim):
            for a in range(n):
                stacked[r, i * n + a] = c[i, r, a]
    weighted = omega @ stacked
    moved = psi @ stacked
    low = np.zeros((n, n))
    for i in range(count):
        for a in range(n):
            col = i * n + a
            acc = 0.0
            for r in range(dim):
                acc += stacked[r, col] * beta[r]
            b0[i, a] += acc
            for b in range(n):
                acc = 0.0
                for r in range(dim):
                    acc += stacked[r, col] * weighted[r, i * n + b]
                j0[i, a, b] += acc
        for r in range(dim):
            for a in range(n):
                c[i, r, a] = moved[r, i * n + a]
        # J0^-1 for the bound (S8); none while J0 is singular (no evidence yet).
        bounded[i] = lower_factor(j0[i], low)
        if bounded[i]:
            inverse = np.eye(n)
            _solve_in_place(low, inverse)
            bound_inv[i] = inverse


@njit(cache=True)
def absorb_evaluate(h: np.ndarray, s: np.ndarray, gain: np.ndarray, nu: np.ndarray,
                    psi: np.ndarray, omega: np.ndarray, beta: np.ndarray, outlier: float,
                    c: np.ndarray, b0: np.ndarray, j0: np.ndarray, bound_inv: np.ndarray,
                    bounded: np.ndarray, count: int, score: np.ndarray, threshold: float,
                    nis_scale: float, elapsed: float, dt: float, nis_time: float) -> tuple:
    """
    Run :func:`absorb`, the NIS average and :func:`evaluate` of one update (count > 0).

    Returns (NIS, whether it was evidence, the new NIS average and elapsed time, best
    onset, its statistic, the largest bound, onsets evaluated). An outlier (or NaN)
    NIS stops after absorb, as WrenchStepTest.update does.
    """
    nis_total = absorb(h, s, gain, nu, psi, omega, beta, outlier)
    if not nis_total <= outlier:
        return nis_total, False, nis_scale, elapsed, -1, 0.0, 0.0, 0
    # A running mean over the first nis_time seconds, then an exponential average.
    elapsed += dt
    horizon = min(elapsed, nis_time)
    weight = 1.0 if horizon <= 0.0 else min(1.0, dt / horizon)
    nis_scale += weight * (nis_total / nu.shape[0] - nis_scale)
    scale = max(1.0, nis_scale)
    best, statistic, top, evaluated = evaluate(c, b0, j0, bound_inv, bounded, count, omega,
                                               beta, scale, threshold, score)
    return nis_total, True, nis_scale, elapsed, best, statistic, top, evaluated
