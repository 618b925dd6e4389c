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

"""The filter's inputs from the mass matrices, compiled, equal the numpy ones bit for bit."""

import numpy as np

from reduced_dynamics.estimator.core import inputs
from reduced_dynamics.estimator.kernel import rotations, UpdateKernel
from reduced_dynamics.robot.model import load_robot


def _numpy_terms(mass: np.ndarray, n: int, qbar_dot: np.ndarray,
                 joint_variance: float) -> tuple:
    """UpdateKernel.filter_inputs' stacked numpy calls (main 3a3a89e)."""
    locked = mass[:, :n, :n].copy()
    inverse = np.linalg.inv(locked)
    connection = np.matmul(inverse, mass[:, :n, n:])
    connection_qd = np.matmul(connection, qbar_dot[:, :, None])[:, :, 0]
    joint_cov = joint_variance * np.matmul(connection, np.swapaxes(connection, 1, 2))
    return locked, inverse, connection_qd, joint_cov


def test_connection_terms_equal_the_stacked_numpy_calls() -> None:
    """Random positive definite mass matrices: one row (streaming) and chunks."""
    rng = np.random.default_rng(0)
    # (m = 0: a base-only robot, the products of empty blocks are zeros.)
    for n, m in ((6, 6), (6, 3), (3, 2), (6, 24), (6, 1), (6, 0), (3, 0)):
        for count in (1, 7, 40):
            root = rng.standard_normal((count, n + m, n + m))
            mass = root @ np.swapaxes(root, 1, 2) + (n + m) * np.eye(n + m)
            qbar_dot = rng.standard_normal((count, m))
            for mine, expected in zip(inputs.connection_terms(mass, n, qbar_dot, 1e-4),
                                      _numpy_terms(mass, n, qbar_dot, 1e-4)):
                np.testing.assert_array_equal(mine, expected)


def test_filter_inputs_of_the_paper_robot_equal_the_numpy_ones() -> None:
    """The kernel's own mass matrices (crba), one row and a chunk."""
    robot = load_robot()
    kernel = UpdateKernel(robot)
    rng = np.random.default_rng(1)
    for count in (1, 64):
        qbar = rng.uniform(-1.0, 1.0, (count, robot.m))
        qbar_dot = rng.standard_normal((count, robot.m))
        bases = np.zeros((count, 13))
        bases[:, 6] = 1.0
        result = kernel.filter_inputs(qbar, qbar_dot, bases, 1e-4)
        expected = _numpy_terms(kernel.mass_matrices(qbar).copy(), robot.n, qbar_dot, 1e-4)
        for mine, reference in zip((result.locked, result.inverse, result.connection_qd,
                                    result.joint_cov), expected):
            np.testing.assert_array_equal(mine, reference)


def _numpy_chunk(mass: np.ndarray, n: int, qbar_dot: np.ndarray, connection_qd: np.ndarray,
                 inverse: np.ndarray, pi: np.ndarray) -> tuple:
    """pbar, the drift and the energy as the stacked numpy calls gave them (main 32c72ab)."""
    shape_qd = np.matmul(mass[:, n:, n:], qbar_dot[:, :, None])[:, :, 0]
    pbar = shape_qd - np.matmul(connection_qd[:, None, :], mass[:, :n, n:])[:, 0]
    drift = np.matmul(inverse, pi[:, :, None])[:, :, 0]
    energy = 0.5 * (np.matmul(pi[:, None, :], drift[:, :, None])[:, 0, 0]
                    + np.matmul(qbar_dot[:, None, :], pbar[:, :, None])[:, 0, 0])
    return pbar, drift, energy


def test_chunk_terms_and_drift_energy_equal_the_stacked_numpy_calls() -> None:
    """The shape momentum pbar (4+ joints), rotations, drift, energy: rows and chunks."""
    rng = np.random.default_rng(2)
    for n in (6, 3):
        for m in (0, 1, 2, 3, 4, 6, 7, 24):
            for count in (1, 3, 40):
                root = rng.standard_normal((count, n + m, n + m))
                mass = root @ np.swapaxes(root, 1, 2) + (n + m) * np.eye(n + m)
                qbar_dot = rng.standard_normal((count, m))
                bases = rng.standard_normal((count, 13))
                bases[:, 3:7] /= np.linalg.norm(bases[:, 3:7], axis=1)[:, None]
                pi = rng.standard_normal((count, n))
                _, inverse, connection_qd, _, pbar, rotation = inputs.chunk_terms(
                    mass, n, qbar_dot, np.ascontiguousarray(bases[:, 3:7]), 1e-4, m >= 4)
                expected = _numpy_chunk(mass, n, qbar_dot, connection_qd, inverse, pi)
                if m < 4:
                    pbar = expected[0]  # the kernel leaves thin products to numpy
                drift, energy = inputs.drift_energy(inverse, pi, qbar_dot, pbar)
                for mine, reference in zip((pbar, drift, energy), expected):
                    np.testing.assert_array_equal(mine, reference)
                np.testing.assert_array_equal(rotation, rotations(bases[:, 3:7]))


def test_welford_row_equals_the_numpy_update() -> None:
    """The streaming path's running mu statistics, compiled, are numpy's bits."""
    rng = np.random.default_rng(3)
    mean, m2 = np.zeros(6), np.zeros(6)
    ref_mean, ref_m2 = np.zeros(6), np.zeros(6)
    for total in range(1, 200):
        mu = rng.standard_normal(6) * 1e3
        inputs.welford_row(mean, m2, mu, total)
        delta = mu - ref_mean
        ref_mean += delta / total
        ref_m2 += delta * (mu - ref_mean)
        np.testing.assert_array_equal(mean, ref_mean)
        np.testing.assert_array_equal(m2, ref_m2)
