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
encoder noise A Sigma A^T; with pbar (5.35) and the base rotations in
:func:`chunk_terms`; after the filter, the drift and energy (:func:`drift_energy`)
and, for a one-row chunk, the running mu statistics (:func:`welford_row`). In numpy
these were a dozen stacked calls; a streaming chunk is one row, where the calls'
overhead was most of the cost. numba's solve and BLAS products in the same order
give numpy's results bit for bit (test_filter_inputs_kernel.py, docs/streaming_path.md).
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
    # The products go into arrays allocated once (np.dot with out: the same BLAS calls
    # as @, gemm and gemv, so the same bits; test_filter_inputs_kernel.py).
    coupling = np.empty((n, mass.shape[1] - n))
    connection = np.empty((n, mass.shape[1] - n))
    outer = np.empty((n, n))
    for k in range(count):
        locked[k] = mass[k, :n, :n]
        # solve(I, 1) in C order: numpy's inv (LAPACK gesv), bit for bit.
        inverse[k] = np.linalg.solve(locked[k], eye)
        inv = inverse[k]
        coupling[:, :] = mass[k, :n, n:]
        np.dot(inv, coupling, connection)
        np.dot(connection, qbar_dot[k], connection_qd[k])
        np.dot(connection, connection.T, outer)
        joint_cov[k] = joint_variance * outer
    return locked, inverse, connection_qd, joint_cov


@njit(cache=True)
def chunk_terms(mass: np.ndarray, n: int, qbar_dot: np.ndarray, quaternions: np.ndarray,
                joint_variance: float, with_pbar: bool) -> tuple:
    """
    Return a chunk's filter inputs in one call: :func:`connection_terms`, pbar, rotations.

    pbar = Mr qbar_dot - (A qbar_dot)^T B (5.35) as numpy's stacked matmul gives it
    for 4 or more shape joints (``with_pbar``; fewer: numpy takes other BLAS paths
    for such thin products, the caller keeps them); the rotation matrices of the
    unit quaternions (K, 4) (x, y, z, w) step by step as Eigen's toRotationMatrix
    (kernel._rotation_columns: the same IEEE operations, so the same bits).
    """
    count = mass.shape[0]
    m = mass.shape[1] - n
    locked, inverse, connection_qd, joint_cov = connection_terms(mass, n, qbar_dot,
                                                                 joint_variance)
    pbar = np.empty((count, m))
    rotation = np.empty((count, 3, 3))
    # (Arrays allocated once, np.dot with out: the same gemv calls as @.)
    shape_block = np.empty((m, m))
    coupling = np.empty((n, m))
    shape_qd = np.empty(m)
    coupled = np.empty(m)
    for k in range(count):
        if with_pbar:
            shape_block[:, :] = mass[k, n:, n:]
            coupling[:, :] = mass[k, :n, n:]
            np.dot(shape_block, qbar_dot[k], shape_qd)
            np.dot(connection_qd[k], coupling, coupled)
            pbar[k] = shape_qd - coupled
        x, y, z, w = quaternions[k, 0], quaternions[k, 1], quaternions[k, 2], quaternions[k, 3]
        tx, ty, tz = 2.0 * x, 2.0 * y, 2.0 * z
        twx, twy, twz = tx * w, ty * w, tz * w
        txx, txy, txz = tx * x, ty * x, tz * x
        tyy, tyz, tzz = ty * y, tz * y, tz * z
        r = rotation[k]
        r[0, 0], r[0, 1], r[0, 2] = 1.0 - (tyy + tzz), txy - twz, txz + twy
        r[1, 0], r[1, 1], r[1, 2] = txy + twz, 1.0 - (txx + tzz), tyz - twx
        r[2, 0], r[2, 1], r[2, 2] = txz - twy, tyz + twx, 1.0 - (txx + tyy)
    return locked, inverse, connection_qd, joint_cov, pbar, rotation


@njit(cache=True)
def drift_energy(inverse: np.ndarray, pi: np.ndarray, qbar_dot: np.ndarray,
                 pbar: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """
    Return the drift twists I^-1 pi (K, n) and the reduced energies (5.36) (K,).

    1/2 pi.I^-1 pi + 1/2 pbar.qbar_dot per row, with the BLAS products numpy's
    stacked matmul makes of the same rows (gemv, dot), so the same bits.
    """
    count, n = pi.shape
    drift = np.empty((count, n))
    energy = np.empty(count)
    for k in range(count):
        # (Straight into the row: np.dot with out, the same gemv as @.)
        twist = drift[k]
        np.dot(inverse[k], pi[k], twist)
        energy[k] = 0.5 * (np.dot(pi[k], twist) + np.dot(qbar_dot[k], pbar[k]))
    return drift, energy


@njit(cache=True)
def welford_row(mean: np.ndarray, m2: np.ndarray, mu: np.ndarray, total: int) -> None:
    """Add one mu to a running mean and squared deviations (Welford), in place."""
    for i in range(mean.shape[0]):
        delta = mu[i] - mean[i]
        mean[i] += delta / total
        m2[i] += delta * (mu[i] - mean[i])
