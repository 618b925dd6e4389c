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
Small Cholesky kernels shared by the compiled tests and the reduced field (numba).

Written out (no LAPACK call, no allocation) for the small symmetric systems solved per
sample; every caller's bits are pinned by its tests, so the operations' order here is
part of the contract: change it only with their golden figures.
"""

import math

from numba import njit
import numpy as np


@njit(cache=True)
def lower_factor(a: np.ndarray, low: np.ndarray) -> bool:
    """Write the Cholesky factor of the symmetric ``a`` into ``low``; False if not definite."""
    n = a.shape[0]
    for r in range(n):
        for c in range(r + 1):
            acc = a[r, c]
            for k in range(c):
                acc -= low[r, k] * low[c, k]
            if r == c:
                if not acc > 0.0:
                    return False
                low[r, r] = math.sqrt(acc)
            else:
                low[r, c] = acc / low[c, c]
    return True


@njit(cache=True)
def solve_factor(factor: np.ndarray, size: int, rhs: np.ndarray) -> None:
    """Solve (L L^T) x = rhs in place with the leading size x size block of L."""
    for i in range(size):
        total = rhs[i]
        for p in range(i):
            total -= factor[i, p] * rhs[p]
        rhs[i] = total / factor[i, i]
    for i in range(size - 1, -1, -1):
        total = rhs[i]
        for p in range(i + 1, size):
            total -= factor[p, i] * rhs[p]
        rhs[i] = total / factor[i, i]
