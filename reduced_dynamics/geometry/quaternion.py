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
Rotation matrix to quaternion (x, y, z, w; ROS order) without a per-call memory leak.

``pin.Quaternion(rotation_matrix)`` (Pinocchio 4.1 / eigenpy bindings) leaks ~80 B
of C++ heap per call, invisible to tracemalloc: a node that converts 82 poses per
prediction grew ~7 kB per prediction (issue 27). ``pin.SE3ToXYZQUAT`` runs the
same Eigen conversion (``Eigen::Quaternion(R)``), so the coefficients are bit for
bit those of the old call, and frees what it allocates
(test/test_quaternion_leak.py checks both).
"""

from __future__ import annotations

import numpy as np
import pinocchio as pin

_ZERO = np.zeros(3)


def matrix_to_xyzw(rotation: np.ndarray) -> np.ndarray:
    """Return the quaternion (x, y, z, w) of a 3x3 rotation matrix (Eigen's conversion)."""
    return pin.SE3ToXYZQUAT(pin.SE3(rotation, _ZERO))[3:].copy()


def matrices_to_xyzw(rotations: np.ndarray) -> np.ndarray:
    """Return the quaternions (N, 4) of rotation matrices (N, 3, 3)."""
    out = np.empty((len(rotations), 4))
    for i, rotation in enumerate(rotations):
        out[i] = pin.SE3ToXYZQUAT(pin.SE3(rotation, _ZERO))[3:]
    return out


def matrix_to_unit_xyzw(rotation: np.ndarray) -> np.ndarray:
    """Return :func:`matrix_to_xyzw` normalised (Eigen's ``normalized()``)."""
    x, y, z, w = matrix_to_xyzw(rotation)
    return pin.Quaternion(w, x, y, z).normalized().coeffs().copy()
