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
``pi = I xi + B qbar_dot``, ``mu = Ad_{g^-1}^T pi`` (5.27), the drift
``I^-1 pi`` and ``pbar = S qbar_dot = Mr qbar_dot - B^T I^-1 B qbar_dot`` (5.35,
with A = I^-1 B from 5.29) come from one stacked solve with two right-hand
sides. S and A are never formed: that keeps the cost O(m^2) per sample.

Every operation acts row by row, whatever the chunk length: elementwise ufuncs,
and matmul and solve on stacks, which call the same BLAS/LAPACK kernel per row.
So a chunk of one sample (the streaming path) and a chunk of many (the batched
path) give bit-identical rows.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import pinocchio as pin

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


def rotations(quaternions: np.ndarray) -> np.ndarray:
    """
    Rotation matrices (K, 3, 3) of unit quaternions (K, 4), stored x, y, z, w.

    The steps are Eigen's ``Quaternion::toRotationMatrix``. Python floats and
    numpy ufuncs both round each IEEE operation, so the scalar branch (cheaper
    for a few rows) and the vectorised one agree bit for bit.
    """
    count = len(quaternions)
    if count <= 2:
        out = []
        for x, y, z, w in quaternions.tolist():
            tx, ty, tz = 2.0 * x, 2.0 * y, 2.0 * z
            twx, twy, twz = tx * w, ty * w, tz * w
            txx, txy, txz = tx * x, ty * x, tz * x
            tyy, tyz, tzz = ty * y, tz * y, tz * z
            out.append((1.0 - (tyy + tzz), txy - twz, txz + twy,
                        txy + twz, 1.0 - (txx + tzz), tyz - twx,
                        txz - twy, tyz + twx, 1.0 - (txx + tyy)))
        return np.array(out).reshape(count, 3, 3)
    x, y, z, w = quaternions.T
    tx, ty, tz = 2.0 * x, 2.0 * y, 2.0 * z
    twx, twy, twz = tx * w, ty * w, tz * w
    txx, txy, txz = tx * x, ty * x, tz * x
    tyy, tyz, tzz = ty * y, tz * y, tz * z
    out = np.empty((count, 3, 3))
    out[:, 0, 0] = 1.0 - (tyy + tzz)
    out[:, 0, 1] = txy - twz
    out[:, 0, 2] = txz + twy
    out[:, 1, 0] = txy + twz
    out[:, 1, 1] = 1.0 - (txx + tzz)
    out[:, 1, 2] = tyz - twx
    out[:, 2, 0] = txz - twy
    out[:, 2, 1] = tyz + twx
    out[:, 2, 2] = 1.0 - (txx + tyy)
    return out


def _row_dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    # matmul per row, not einsum: einsum may pick a different summation order for
    # different chunk lengths, matmul calls the same BLAS kernel on every row.
    return np.matmul(a[:, None, :], b[:, :, None])[:, 0, 0]


class UpdateKernel:
    """Momenta, drift and energy of a chunk of synchronised samples for one robot."""

    __slots__ = ('robot', 'n', 'm', 'nv', '_model', '_data', '_base_q', '_nq_base',
                 '_mirror', '_lift', '_restrict', '_embed', '_coords', '_stack')

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
        # Some Pinocchio bindings return only the upper triangle of M: probe once.
        probe = pin.crba(self._model, self._data, robot.identity_configuration(
            np.linspace(-0.5, 0.7, self.m)).copy())
        self._mirror = None if np.array_equal(probe, probe.T) \
            else np.tril_indices(self.nv, -1)
        self._stack = np.empty((0, self.nv, self.nv))

    @property
    def projects_twists(self) -> bool:
        """Return whether twists need projecting onto the group (not SE(3))."""
        return self._coords is not None

    def coordinates(self, twists: np.ndarray) -> np.ndarray:
        """Return algebra coordinates, shape (K, n), of base twists in span(S), (K, 6)."""
        return twists if self._coords is None else twists @ self._coords

    def twists(self, xi: np.ndarray) -> np.ndarray:
        """Return the twists, shape (K, 6), of algebra coordinates, shape (K, n)."""
        return xi if self._embed is None else xi @ self._embed

    def wrenches(self, covectors: np.ndarray) -> np.ndarray:
        """Return wrenches, shape (K, 6), lifting covectors of the subalgebra, (K, n)."""
        return covectors if self._lift is None else covectors @ self._lift

    def mass_matrices(self, qbar: np.ndarray) -> np.ndarray:
        """Return the stack (K, nv, nv) of M(qbar_k) = crba(e, qbar_k) (Lemma 52)."""
        count = len(qbar)
        if len(self._stack) < count:
            self._stack = np.empty((count, self.nv, self.nv))
        stack = self._stack[:count]
        q = np.empty((count, self._model.nq))
        q[:, :self._nq_base] = self._base_q
        q[:, self._nq_base:] = qbar
        model, data, crba = self._model, self._data, pin.crba
        for k in range(count):
            stack[k] = crba(model, data, q[k])
        if self._mirror is not None:
            rows, cols = self._mirror
            stack[:, rows, cols] = stack[:, cols, rows]
        return stack

    def evaluate(self, qbar: np.ndarray, qbar_dot: np.ndarray,
                 bases: np.ndarray) -> KernelResult:
        """
        Evaluate a chunk: rows qbar (m,), qbar_dot (m,) and base state (13,).

        A base row is the translation, the unit quaternion (x, y, z, w) and the
        body twist (linear first).
        """
        n = self.n
        mass = self.mass_matrices(qbar)
        poses = bases[:, :7]
        xi = self.coordinates(bases[:, 7:])
        locked = mass[:, :n, :n]
        # Columns of M against qbar_dot: [B qbar_dot; Mr qbar_dot].
        shape_part = np.matmul(mass[:, :, n:], qbar_dot[:, :, None])[:, :, 0]
        locked_xi = np.matmul(locked, xi[:, :, None])[:, :, 0]
        coupling_qd = shape_part[:, :n]
        pi = locked_xi + coupling_qd
        # One factorisation of I per sample for both I^-1 pi and I^-1 B qbar_dot.
        rhs = np.empty((len(qbar), n, 2))
        rhs[:, :, 0] = pi
        rhs[:, :, 1] = coupling_qd
        solved = np.linalg.solve(locked, rhs)
        drift = solved[:, :, 0]
        # pbar = Mr qbar_dot - B^T (I^-1 B qbar_dot): no cancellation against xi.
        pbar = shape_part[:, n:] - np.matmul(solved[:, None, :, 1], mass[:, :n, n:])[:, 0]
        # 2T = xi.I xi + 2 xi.B qbar_dot + qbar_dot.Mr qbar_dot.
        energy = 0.5 * (_row_dot(xi, locked_xi + 2.0 * coupling_qd)
                        + _row_dot(qbar_dot, shape_part[:, n:]))
        if self.robot.has_potential:
            energy += [self.robot.potential_energy(row) for row in qbar]
        rotation = rotations(poses[:, 3:])
        translation = poses[:, :3]
        # mu = Ad_{g^-1}^T pi (5.27): the wrench pi (base frame) acted on by g.
        wrench = self.wrenches(pi)
        force = np.matmul(rotation, wrench[:, :3, None])[:, :, 0]
        torque = np.matmul(rotation, wrench[:, 3:, None])[:, :, 0]
        tx, ty, tz = translation[:, 0], translation[:, 1], translation[:, 2]
        fx, fy, fz = force[:, 0], force[:, 1], force[:, 2]
        torque[:, 0] += ty * fz - tz * fy
        torque[:, 1] += tz * fx - tx * fz
        torque[:, 2] += tx * fy - ty * fx
        mu = np.concatenate((force, torque), axis=1)
        if self._restrict is not None:
            mu = mu @ self._restrict
        return KernelResult(mu, pi, pbar, drift, energy, rotation, translation)
