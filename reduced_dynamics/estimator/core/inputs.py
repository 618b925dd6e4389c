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
The filter's inputs from a chunk's mass matrices, compiled (numba).

Per row: the locked inertia I, I^-1, A qbar_dot with A = I^-1 B (5.29) and the
encoder noise A Sigma A^T. In numpy these were six stacked calls; a streaming
chunk is one row, where the calls' overhead was most of the cost. numba's solve
and BLAS products in the same order give numpy's results bit for bit
(test_filter_inputs_kernel.py).
"""

import numpy as np
from numba import njit


@njit(cache=True)
def connection_terms(mass: np.ndarray, n: int, qbar_dot: np.ndarray, joint_variance: float
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Return stacks of I, I^-1, A qbar_dot and ``joint_variance`` A A^T of mass (K, nv, nv)."""
    count = mass.shape[0]
    locked = np.empty((count, n, n))
    inverse = np.empty((count, n, n))
    connection_qd = np.empty((count, n))
    joint_cov = np.empty((count, n, n))
    eye = np.eye(n)
    for k in range(count):
        locked[k] = mass[k, :n, :n]
        # solve(I, 1) in C order: numpy's inv (LAPACK gesv), bit for bit.
        inv = np.ascontiguousarray(np.linalg.solve(locked[k], eye))
        inverse[k] = inv
        connection = inv @ np.ascontiguousarray(mass[k, :n, n:])
        connection_qd[k] = connection @ qbar_dot[k]
        joint_cov[k] = joint_variance * (connection @ connection.T)
    return locked, inverse, connection_qd, joint_cov
