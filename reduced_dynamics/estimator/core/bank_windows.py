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
The multi-scale test's per-window statistics, compiled (numba): core/bank_step.py's kernels.

The filtered bank's T_L = d_L^T (P_mu(t) + P_mu(t - L))^-1 d_L by Cholesky
(:func:`quadratic_form`, no LAPACK call, no allocation) and the block bank's window
T_L from the prefix sums of core/blocks.py (:func:`block_window`), on preallocated
scratch; :mod:`.bank_step` calls them once per update.
"""

import math

import numpy as np
from numba import njit

from reduced_dynamics.estimator.core.cholesky import lower_factor, solve_factor


@njit(cache=True)
def quadratic_form(a: np.ndarray, b: np.ndarray, d: np.ndarray, work: np.ndarray,
                   y: np.ndarray) -> float:
    """
    Return d^T (a + b)^-1 d by Cholesky (``work`` n x n, ``y`` n: scratch); NaN: not positive.

    ||L^-1 d||^2 with a + b = L L^T: a factorisation and one forward substitution,
    no inverse, no allocation (a LAPACK solve per window allocated and pivoted).
    """
    n = d.shape[0]
    for i in range(n):
        for j in range(i + 1):
            s = a[i, j] + b[i, j]
            for k in range(j):
                s -= work[i, k] * work[j, k]
            if i == j:
                if not s > 0.0:
                    return math.nan
                work[i, i] = math.sqrt(s)
            else:
                work[i, j] = s / work[j, j]
    total = 0.0
    for i in range(n):
        s = d[i]
        for k in range(i):
            s -= work[i, k] * y[k]
        y[i] = s / work[i, i]
        total += y[i] * y[i]
    return total


@njit(cache=True)
def filtered_bank(stamps: np.ndarray, mu_ring: np.ndarray, cov_ring: np.ndarray,
                  start: int, end: int, lags: np.ndarray, stamp_ns: int, floor_ns: int,
                  has_floor: bool, mu: np.ndarray, cov: np.ndarray, rows: np.ndarray,
                  raw: np.ndarray, work: np.ndarray, y: np.ndarray,
                  d: np.ndarray) -> int:
    """
    Store the sample at ring row ``end``; write each window's row and raw T_L.

    Returns the windows covered, or -1 when a V_L is not positive definite (then
    every raw T_L is 0). Window L's row is the newest stored sample at or before
    t - L; it is covered (else -1) when that sample is at or after the floor (the
    last event's end; the ring's first sample without one).
    """
    stamps[end] = stamp_ns
    mu_ring[end] = mu
    cov_ring[end] = cov
    end += 1
    n = mu.shape[0]
    first = stamps[start]
    lowest = max(floor_ns, first) if has_floor else first
    covered = 0
    for w in range(lags.shape[0]):
        raw[w] = 0.0
        index = np.searchsorted(stamps[start:end], stamp_ns - lags[w], 'right') - 1
        rows[w] = -1
        if index >= 0 and stamps[start + index] >= lowest:
            rows[w] = start + index
            covered += 1
    for w in range(lags.shape[0]):
        row = rows[w]
        if row < 0:
            continue
        for i in range(n):
            d[i] = mu[i] - mu_ring[row, i]
        value = quadratic_form(cov, cov_ring[row], d, work, y)
        if math.isnan(value) and not math.isnan(d.sum()):
            raw[:] = 0.0
            return -1
        raw[w] = value
    return covered


@njit(cache=True)
def block_into(info: np.ndarray, score: np.ndarray, s0: np.ndarray, s1: np.ndarray,
               s2: np.ndarray, y0: np.ndarray, t1: np.ndarray, counts: np.ndarray, lo: int,
               hi: int, mass: float, linear: np.ndarray, cov: np.ndarray, mean: np.ndarray,
               work: np.ndarray) -> bool:
    """
    Write the block (lo, hi]'s mean momentum and covariance (:func:`.blocks.block_mean`).

    The same algebra by Cholesky factors on ``work`` ((6, n, n) scratch), no allocation:
    the slope's information a2 - a1 a0^-1 a1 and score b1 - a1 a0^-1 b0 (a1 and a0
    symmetric), then the inverse of the information. False: a factor not positive.
    """
    n = mean.shape[0]
    lam, factor, inverse = work[0], work[1], work[2]
    for i in range(n):
        mean[i] = score[hi, i] - (score[lo, i] if lo >= 0 else 0.0)
        for j in range(n):
            lam[i, j] = info[hi, i, j] - (info[lo, i, j] if lo >= 0 else 0.0)
    d = linear.shape[0]
    count = counts[hi] - (counts[lo] if lo >= 0 else 0) if d else 0
    if d and mass > 0.0 and count >= 2:
        a0, a1, x = work[3][:d, :d], work[4][:d, :d], work[5][:d, :d]
        chol0 = inverse[:d, :d]
        b0, b1 = factor[0, :d], factor[1, :d]
        for i in range(d):
            b0[i] = y0[hi, i] - (y0[lo, i] if lo >= 0 else 0.0)
            b1[i] = t1[hi, i] - (t1[lo, i] if lo >= 0 else 0.0)
            for j in range(d):
                a0[i, j] = s0[hi, i, j] - (s0[lo, i, j] if lo >= 0 else 0.0)
                a1[i, j] = s1[hi, i, j] - (s1[lo, i, j] if lo >= 0 else 0.0)
        if not lower_factor(a0, chol0):
            return False
        for j in range(d):
            # x = a0^-1 a1, column by column; a1 a0^-1 = x^T.
            for i in range(d):
                x[i, j] = a1[i, j]
            solve_factor(chol0, d, x[:, j])
        for i in range(d):
            residual = b1[i]
            for k in range(d):
                residual -= x[k, i] * b0[k]
            mean[linear[i]] += residual / mass
        for i in range(d):
            for j in range(d):
                schur_ij = s2[hi, i, j] - (s2[lo, i, j] if lo >= 0 else 0.0)
                schur_ji = s2[hi, j, i] - (s2[lo, j, i] if lo >= 0 else 0.0)
                for k in range(d):
                    schur_ij -= a1[i, k] * x[k, j]
                    schur_ji -= a1[j, k] * x[k, i]
                lam[linear[i], linear[j]] += 0.5 * (schur_ij + schur_ji) / (mass * mass)
    if not lower_factor(lam, factor):
        return False
    solve_factor(factor, n, mean)
    # cov = lam^-1 = L^-T L^-1: the inverse factor, then its product.
    for j in range(n):
        for i in range(n):
            if i < j:
                inverse[i, j] = 0.0
                continue
            s = 1.0 if i == j else 0.0
            for k in range(j, i):
                s -= factor[i, k] * inverse[k, j]
            inverse[i, j] = s / factor[i, i]
    for i in range(n):
        for j in range(i + 1):
            s = 0.0
            for k in range(i, n):
                s += inverse[k, i] * inverse[k, j]
            cov[i, j] = s
            cov[j, i] = s
    return True


@njit(cache=True)
def block_window(info: np.ndarray, score: np.ndarray, s0: np.ndarray, s1: np.ndarray,
                 s2: np.ndarray, y0: np.ndarray, t1: np.ndarray, counts: np.ndarray,
                 common: np.ndarray, stamps: np.ndarray, end: int, lag: int,
                 stamp_ns: int, mass: float, linear: np.ndarray,
                 work: np.ndarray) -> float:
    """
    Return window ``lag``'s block T_L (:func:`.blocks.window_statistics`); 0: not formed.

    Before (t-3L, t-2L] against after (t-L, t] (prefix rows up to ``end``); 0 when a
    block is empty or an information not positive. ``work``: (12, n, n) scratch.
    """
    rows = stamps[:end]
    r0 = np.searchsorted(rows, stamp_ns - 3 * lag, 'right') - 1
    r1 = np.searchsorted(rows, stamp_ns - 2 * lag, 'right') - 1
    r2 = np.searchsorted(rows, stamp_ns - lag, 'right') - 1
    r3 = np.searchsorted(rows, stamp_ns, 'right') - 1
    if not (r1 > r0 and r3 > r2):
        return 0.0
    n = info.shape[1]
    before_cov, after_cov, v = work[6], work[7], work[8]
    before, after = work[9][0], work[9][1]
    if not block_into(info, score, s0, s1, s2, y0, t1, counts, r0, r1, mass, linear,
                      before_cov, before, work[:6]):
        return 0.0
    if not block_into(info, score, s0, s1, s2, y0, t1, counts, r2, r3, mass, linear,
                      after_cov, after, work[:6]):
        return 0.0
    for i in range(n):
        after[i] -= before[i]
        for j in range(n):
            v[i, j] = before_cov[i, j] + common[r1, i, j] + after_cov[i, j]
    value = quadratic_form(v, common[r3], after, work[10], work[11][0])
    return 0.0 if math.isnan(value) else value
