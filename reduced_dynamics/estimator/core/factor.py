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
The update's factor, compiled (numba): S by blocks, its Cholesky factor, the gain.

H enters by its blocks (pose rows select, w columns zero); one Cholesky factor of S
gives the gain K, the NIS and log det S, and P is updated as P - K S K^T
(docs/structured_step.md).
"""

import math

import numpy as np
from numba import njit

from reduced_dynamics.estimator.core.products import symmetric


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
def gain_of(p: np.ndarray, h: np.ndarray, r: np.ndarray) -> np.ndarray:
    """Return K = P H^T S^-1 with S = H P H^T + R symmetrised (Cholesky)."""
    ph = p @ h.T
    low = _cholesky(symmetric(h @ ph + r))
    return _gain_from(low, _whiten(low, ph))
