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
The numeric core of the estimator update, vectorised over a chunk of samples.

Per sample only ``crba`` runs in Python (into a preallocated stack); the rest is
a handful of numpy calls over the whole chunk. With M = [[I, B], [B^T, Mr]]:
``pi = I xi + B qbar_dot``, ``mu = Ad_{g^-1}^T pi`` (5.27) and, from the one
solve ``A qbar_dot = I^-1 B qbar_dot`` (connection 5.29), the drift
``I^-1 pi = xi + A qbar_dot`` and ``pbar = S qbar_dot = Mr qbar_dot - B^T A qbar_dot``
(5.35). S and A are never formed: the cost stays O(m^2) per sample. For an SE(3)
base I is a spatial inertia, solved in closed form.

Results do not depend on the chunk length, bit for bit: matmul and solve on
stacks call the same kernel per row, and the closed-form steps are written once
for Python floats (one or two rows: the streaming path) and numpy columns.
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import numpy as np
import pinocchio as pin

from reduced_dynamics.estimator.core import inputs
from reduced_dynamics.robot.model import RobotModel


class KernelResult(NamedTuple):
    """Per-sample results of one chunk (row k belongs to sample k)."""

    mu: np.ndarray
    pi: np.ndarray
    pbar: np.ndarray
    drift: np.ndarray
    energy: np.ndarray
    rotation: np.ndarray
    translation: np.ndarray
    mass: np.ndarray
    xi: np.ndarray


class FilterInputs(NamedTuple):
    """
    What the Kalman filter and the outputs need of a chunk (row k belongs to sample k).

    ``locked`` I, ``inverse`` I^-1, ``connection_qd`` A qbar_dot, ``joint_cov``
    A Sigma_qdot A^T (the filter's inputs), ``pbar`` = S qbar_dot (5.35), the
    base rotation and translation and body twist coordinates ``xi`` of the rows'
    base states, and the mass matrices.
    """

    locked: np.ndarray
    inverse: np.ndarray
    connection_qd: np.ndarray
    joint_cov: np.ndarray
    pbar: np.ndarray
    rotation: np.ndarray
    translation: np.ndarray
    xi: np.ndarray
    mass: np.ndarray


def _columnwise(formula: Callable[..., tuple], columns: np.ndarray) -> np.ndarray:
    """
    Apply an elementwise formula to every row of ``columns`` (K, p); return (K, q).

    ``formula`` takes the p columns and returns q results using + - * / and
    sqrt only. Python floats and numpy ufuncs round each such IEEE operation
    the same way, so the scalar branch (cheaper for a row or two, the streaming
    path) and the vectorised one agree bit for bit.
    """
    if len(columns) <= 2:
        return np.array([formula(*row) for row in columns.tolist()], dtype=float)
    return np.stack(formula(*np.ascontiguousarray(columns.T)), axis=1)


def _rotation_columns(x, y, z, w) -> tuple:
    # Eigen's Quaternion::toRotationMatrix, step by step (row-major entries).
    tx, ty, tz = 2.0 * x, 2.0 * y, 2.0 * z
    twx, twy, twz = tx * w, ty * w, tz * w
    txx, txy, txz = tx * x, ty * x, tz * x
    tyy, tyz, tzz = ty * y, tz * y, tz * z
    return (1.0 - (tyy + tzz), txy - twz, txz + twy,
            txy + twz, 1.0 - (txx + tzz), tyz - twx,
            txz - twy, tyz + twx, 1.0 - (txx + tyy))


def _act_columns(x, y, z, w, px, py, pz, fx, fy, fz, nx, ny, nz) -> tuple:
    # g = (R(x, y, z, w), p) acting on the wrench (f, n): (R f, R n + p x R f), the
    # coadjoint Ad_{g^-1}^T of 5.27. Returns R (row-major) then the wrench.
    r = _rotation_columns(x, y, z, w)
    gx = r[0] * fx + r[1] * fy + r[2] * fz
    gy = r[3] * fx + r[4] * fy + r[5] * fz
    gz = r[6] * fx + r[7] * fy + r[8] * fz
    return r + (gx, gy, gz,
                r[0] * nx + r[1] * ny + r[2] * nz + (py * gz - pz * gy),
                r[3] * nx + r[4] * ny + r[5] * nz + (pz * gx - px * gz),
                r[6] * nx + r[7] * ny + r[8] * nz + (px * gy - py * gx))


def _spatial_solve_columns(m, hx, hy, hz, ixx, ixy, ixz, iyy, iyz, izz,
                           fx, fy, fz, nx, ny, nz) -> tuple:
    # Solve Y [v; w] = [f; n] for a spatial inertia in Pinocchio's layout,
    # Y = [[m E, -[h]], [[h], Io]], h = m c the first moment, Io the rotational
    # inertia about the origin: w = Ic^-1 (n - c x f) and v = f / m + c x w, with
    # Ic = Io + [h][c] the inertia about the centre of mass (3 x 3, by cofactors).
    cx, cy, cz = hx / m, hy / m, hz / m
    hc = hx * cx + hy * cy + hz * cz
    a, b, c = ixx + (hx * cx - hc), ixy + hx * cy, ixz + hx * cz
    d, e, f = iyy + (hy * cy - hc), iyz + hy * cz, izz + (hz * cz - hc)
    a00, a01, a02 = d * f - e * e, c * e - b * f, b * e - c * d
    a11, a12, a22 = a * f - c * c, b * c - a * e, a * d - b * b
    det = a * a00 + b * a01 + c * a02
    yx, yy, yz = nx - (cy * fz - cz * fy), ny - (cz * fx - cx * fz), nz - (cx * fy - cy * fx)
    wx = (a00 * yx + a01 * yy + a02 * yz) / det
    wy = (a01 * yx + a11 * yy + a12 * yz) / det
    wz = (a02 * yx + a12 * yy + a22 * yz) / det
    return (fx / m + (cy * wz - cz * wy), fy / m + (cz * wx - cx * wz),
            fz / m + (cx * wy - cy * wx), wx, wy, wz, det)


#: Entries of a 6 x 6 spatial inertia (row-major) that _spatial_solve_columns reads:
#: m, the first moment h from the lower-left [h], the upper triangle of Io.
_SPATIAL_ENTRIES = np.array([0, 31, 20, 24, 21, 22, 23, 28, 29, 35])


def rotations(quaternions: np.ndarray) -> np.ndarray:
    """Return rotation matrices (K, 3, 3) of unit quaternions (K, 4) stored x, y, z, w."""
    return _columnwise(_rotation_columns, quaternions).reshape(len(quaternions), 3, 3)


def _row_dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    # matmul per row, not einsum: einsum may pick a different summation order for
    # different chunk lengths, matmul calls the same BLAS kernel on every row.
    return np.matmul(a[:, None, :], b[:, :, None])[:, 0, 0]


def _row_times(rows: np.ndarray, matrix: np.ndarray) -> np.ndarray:
    # rows @ matrix as a stack of 1-row products: one 2-D GEMM could block rows
    # differently for different chunk lengths.
    return np.matmul(rows[:, None, :], matrix)[:, 0, :]


class UpdateKernel:
    """Momenta, drift and energy of a chunk of synchronised samples for one robot."""

    __slots__ = ('robot', 'n', 'm', 'nv', '_model', '_data', '_base_q', '_nq_base',
                 '_mirror', '_lift', '_restrict', '_embed', '_coords', '_stack', '_spatial',
                 '_q', '_thin', '_row_q', '_row_shape', '_row_stack')

    def __init__(self, robot: RobotModel) -> None:
        """Precompute what does not change between samples."""
        self.robot = robot
        self.n, self.m, self.nv = robot.n, robot.m, robot.model.nv
        self._model = robot.model
        # Own Data: the update never disturbs the model's shared work buffers.
        self._data = robot.model.createData()
        self._nq_base = robot.nq_base
        self._base_q = pin.neutral(robot.model)[:robot.nq_base].copy()
        group = robot.group
        basis = group.algebra_basis
        pinv = group.coordinates(np.eye(6))
        identity = basis.shape == (6, 6) and np.array_equal(basis, np.eye(6))
        # Row-vector forms of the group maps; None where they are the identity (SE(3)).
        self._coords = None if identity else np.ascontiguousarray(pinv.T)   # twist -> xi
        self._lift = None if identity else np.ascontiguousarray(pinv)       # pi -> wrench
        self._restrict = None if identity else np.ascontiguousarray(basis)  # wrench -> mu
        self._embed = None if identity else np.ascontiguousarray(basis.T)   # xi -> twist
        self._spatial = identity  # the locked inertia is a full spatial inertia
        # Some Pinocchio bindings return only the upper triangle of M: probe once.
        probe = pin.crba(self._model, self._data, robot.identity_configuration(
            np.linspace(-0.5, 0.7, self.m)).copy())
        self._mirror = None if np.array_equal(probe, probe.T) \
            else np.tril_indices(self.nv, -1)
        self._stack = np.empty((0, self.nv, self.nv))
        self._q = np.empty((0, self._model.nq))
        self._row_views(1)
        # pbar of 1 to 3 shape joints: numpy's matmul takes other BLAS paths for such
        # thin products than core/inputs.py's; numpy computes it then (same bits).
        self._thin = 0 < self.m < 4

    @property
    def projects_twists(self) -> bool:
        """Return whether twists need projecting onto the group (not SE(3))."""
        return self._coords is not None

    def coordinates(self, twists: np.ndarray) -> np.ndarray:
        """Return algebra coordinates, shape (K, n), of base twists in span(S), (K, 6)."""
        return twists if self._coords is None else _row_times(twists, self._coords)

    def twists(self, xi: np.ndarray) -> np.ndarray:
        """Return the twists, shape (K, 6), of algebra coordinates, shape (K, n)."""
        return xi if self._embed is None else _row_times(xi, self._embed)

    def wrenches(self, covectors: np.ndarray) -> np.ndarray:
        """Return wrenches, shape (K, 6), lifting covectors of the subalgebra, (K, n)."""
        return covectors if self._lift is None else _row_times(covectors, self._lift)

    def _row_views(self, count: int) -> None:
        """Allocate the stack and configurations for ``count`` rows (and the row's views)."""
        self._stack = np.empty((count, self.nv, self.nv))
        # Configurations: the base part (identity) is written once, here.
        self._q = np.empty((count, self._model.nq))
        self._q[:, :self._nq_base] = self._base_q
        # A one-row chunk's (streaming) views: no slicing per row.
        self._row_q, self._row_shape = self._q[0], self._q[0, self._nq_base:]
        self._row_stack = self._stack[:1]

    def mass_matrices(self, qbar: np.ndarray) -> np.ndarray:
        """Return the stack (K, nv, nv) of M(qbar_k) = crba(e, qbar_k) (Lemma 52)."""
        count = len(qbar)
        if count == 1:
            # The streaming path's row: the same crba into the same stack's first row.
            self._row_shape[:] = qbar[0]
            stack = self._row_stack
            stack[0] = pin.crba(self._model, self._data, self._row_q)
            if self._mirror is not None:
                rows, cols = self._mirror
                stack[:, rows, cols] = stack[:, cols, rows]
            return stack
        if len(self._stack) < count:
            self._row_views(count)
        stack, q = self._stack[:count], self._q
        q[:count, self._nq_base:] = qbar
        model, data, crba = self._model, self._data, pin.crba
        for k in range(count):
            stack[k] = crba(model, data, q[k])
        if self._mirror is not None:
            rows, cols = self._mirror
            stack[:, rows, cols] = stack[:, cols, rows]
        return stack

    def solve_locked(self, locked: np.ndarray, covectors: np.ndarray) -> np.ndarray:
        """Return I^-1 covector (K, n) for a stack of locked inertias I (K, n, n)."""
        if self._spatial:
            # SE(3): I is the spatial inertia of the whole robot; its closed-form
            # inverse costs a third of a stacked LU solve.
            columns = np.concatenate((locked.reshape(len(locked), 36)[:, _SPATIAL_ENTRIES],
                                      covectors), axis=1)
            try:
                with np.errstate(divide='ignore', invalid='ignore'):
                    solved = _columnwise(_spatial_solve_columns, columns)
            except ZeroDivisionError:  # Python floats: m or det is zero
                solved = None
            # Same failure on both paths, as Cholesky gave: I must be positive definite.
            if solved is None or not (np.all(columns[:, 0] > 0.0) and np.all(solved[:, 6] > 0.0)):
                raise np.linalg.LinAlgError('locked inertia is not positive definite')
            return solved[:, :6]
        return np.linalg.solve(locked, covectors[:, :, None])[:, :, 0]

    def filter_inputs(self, qbar: np.ndarray, qbar_dot: np.ndarray, bases: np.ndarray,
                      joint_variance: float) -> FilterInputs:
        """
        Evaluate a chunk for the filter: rows qbar, qbar_dot (m,), base state (13,).

        One stacked inverse of I gives the connection A = I^-1 B (5.29), the input
        A qbar_dot, the encoder noise A Sigma A^T (Sigma = ``joint_variance`` 1)
        and pbar = Mr qbar_dot - B^T A qbar_dot (5.35). Momenta are the filter's:
        none are computed here.
        """
        n = self.n
        mass = self.mass_matrices(qbar)
        # I (a copy: the stack of mass matrices is reused by the next chunk), I^-1,
        # A qbar_dot, A Sigma A^T, pbar and the rotations in one compiled call
        # (core/inputs.py): a streaming chunk is one row, where numpy's calls cost most.
        thin = self._thin
        # (The quaternions contiguous: a chunk of one row is, and numba compiles one
        # variant per array layout.)
        locked, inverse, connection_qd, joint_cov, pbar, rotation = inputs.chunk_terms(
            mass, n, qbar_dot, np.ascontiguousarray(bases[:, 3:7]), joint_variance, not thin)
        if thin:
            shape_qd = np.matmul(mass[:, n:, n:], qbar_dot[:, :, None])[:, :, 0]
            pbar = shape_qd - np.matmul(connection_qd[:, None, :], mass[:, :n, n:])[:, 0]
        # tuple.__new__: the NamedTuple's fields as they are (its __new__ is Python).
        return tuple.__new__(FilterInputs, (locked, inverse, connection_qd, joint_cov, pbar,
                                            rotation, bases[:, :3],
                                            self.coordinates(bases[:, 7:]), mass))

    def evaluate(self, qbar: np.ndarray, qbar_dot: np.ndarray,
                 bases: np.ndarray) -> KernelResult:
        """
        Evaluate a chunk: rows qbar (m,), qbar_dot (m,) and base state (13,).

        A base row is the translation, the unit quaternion (x, y, z, w) and the
        body twist (linear first).
        """
        n = self.n
        mass = self.mass_matrices(qbar)
        xi = self.coordinates(bases[:, 7:])
        locked = mass[:, :n, :n]
        # Columns of M against qbar_dot: [B qbar_dot; Mr qbar_dot].
        shape_part = np.matmul(mass[:, :, n:], qbar_dot[:, :, None])[:, :, 0]
        locked_xi = np.matmul(locked, xi[:, :, None])[:, :, 0]
        coupling_qd = shape_part[:, :n]
        pi = locked_xi + coupling_qd
        # A qbar_dot = I^-1 B qbar_dot (5.29) gives both the drift I^-1 pi = xi + A qbar_dot
        # and pbar = Mr qbar_dot - B^T A qbar_dot (5.35), without cancellation against xi.
        connection_qd = self.solve_locked(locked, coupling_qd)
        drift = xi + connection_qd
        pbar = shape_part[:, n:] - np.matmul(connection_qd[:, None, :], mass[:, :n, n:])[:, 0]
        # 2T = xi.I xi + 2 xi.B qbar_dot + qbar_dot.Mr qbar_dot.
        energy = 0.5 * (_row_dot(xi, locked_xi + 2.0 * coupling_qd)
                        + _row_dot(qbar_dot, shape_part[:, n:]))
        if self.robot.has_potential:
            energy += [self.robot.potential_energy(row) for row in qbar]
        # mu = Ad_{g^-1}^T pi (5.27): the wrench pi (base frame) acted on by g.
        acted = _columnwise(_act_columns, np.concatenate(
            (bases[:, 3:7], bases[:, :3], self.wrenches(pi)), axis=1))
        rotation = acted[:, :9].reshape(len(qbar), 3, 3)
        mu = acted[:, 9:]
        if self._restrict is not None:
            mu = _row_times(mu, self._restrict)
        return KernelResult(mu, pi, pbar, drift, energy, rotation, bases[:, :3], mass, xi)
