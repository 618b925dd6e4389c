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
Small dense products of the filter's compiled step, as loops (numba).

``_mul``, ``_mul_t`` and ``_mat_vec`` are loops where BLAS would cost its call at these
sizes (docs/filter_row.md); ``form`` and ``_ad`` turn the group's structure constants
(``form_rows``, ``ad_rows``: :mod:`~reduced_dynamics.estimator.core.kernels`) into
W(pi) and ad(eta). The operations' order is part of the filter's bits (golden outputs).
"""

import warnings

import numpy as np
from numba import njit
from numba.core.errors import NumbaPerformanceWarning

# Printed once, when a kernel compiles after an install, about products of small strided
# views (a few dozen elements): not worth a copy, and not for the user to act on.
warnings.filterwarnings('ignore', message=".*'@' is faster on contiguous arrays",
                        category=NumbaPerformanceWarning)


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
