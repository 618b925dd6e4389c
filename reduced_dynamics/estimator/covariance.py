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
Message covariances as the filter's measurement noise (docs/message_covariance.md).

A nav_msgs/Odometry or geometry_msgs/PoseWithCovarianceStamped carries row-major
6 x 6 covariances, order x y z roll pitch yaw (REP 103): the pose's in the header
frame (the world), the twist's in ``child_frame_id`` (the base, REP 105). The
filter's pose residual is ``log(g_hat^-1 g_meas)`` in body-frame algebra
coordinates (estimator/filter.py, right perturbation), so a pose covariance is
turned into the base frame: a world-frame error (dp, dtheta) is, to first order,
the body error (R^T dp, R^T dtheta), with R the base orientation. The twist is
already a body twist. Both are then projected onto the base group's algebra
coordinates (``P C P^T`` with P the algebra's pseudo-inverse: SE(2) keeps x, y, yaw).

A covariance is *unknown* when the message carries none, all zeros, or -1 in its
first element (the convention of sensor_msgs); the noise parameters are used then.
One that is not finite, has a negative variance, is not symmetric or not positive
semi-definite, or leaves a zero variance on a coordinate the filter uses, is *bad*:
the noise parameters are used, and the fallback is counted with its reason.
"""

from __future__ import annotations

from typing import NamedTuple, Optional

import numpy as np

#: The "unknown covariance" marker in the first element (sensor_msgs convention).
UNKNOWN = -1.0
#: Relative tolerance of the symmetry and positive semi-definiteness checks.
TOLERANCE = 1e-9

_EYE3 = np.eye(3)

#: Reasons a covariance is bad (fallback to the noise parameters), in check order.
REASONS = ('non_finite', 'negative_variance', 'not_symmetric', 'not_positive_semidefinite',
           'zero_variance')


class MeasurementNoise(NamedTuple):
    """A base sample's own noise in the filter's coordinates (n x n each; None: parameters)."""

    pose: Optional[np.ndarray]
    twist: Optional[np.ndarray]


class NoisyRow(list):
    """A base row (pose7 and twist, plain floats) that carries its sample's own noise."""

    __slots__ = ('noise',)

    def __init__(self, row: list, noise: MeasurementNoise) -> None:
        """Hold ``row``'s values and ``noise``."""
        super().__init__(row)
        self.noise = noise


def checked(values: Optional[np.ndarray]) -> tuple[Optional[np.ndarray], Optional[str]]:
    """
    Return (6 x 6 covariance, None), (None, None) when unknown, or (None, reason) when bad.

    ``values``: the message's 36 values (None: the message carried only zeros).
    """
    if values is None or values[0] == UNKNOWN:
        return None, None
    if not np.isfinite(values).all():
        return None, 'non_finite'
    matrix = values.reshape(6, 6)
    diagonal = np.diag(matrix)
    if (diagonal < 0.0).any():
        return None, 'negative_variance'
    scale = float(diagonal.max())
    if not (np.abs(matrix - matrix.T) <= TOLERANCE * scale).all():
        return None, 'not_symmetric'
    if float(np.linalg.eigvalsh(matrix)[0]) < -TOLERANCE * scale:
        return None, 'not_positive_semidefinite'
    return matrix, None


def _isotropic(matrix: np.ndarray) -> bool:
    """Return whether every 3 x 3 block is a multiple of the identity (no turn changes it)."""
    for block in (matrix[:3, :3], matrix[:3, 3:], matrix[3:, 3:]):
        if not np.array_equal(block, block[0, 0] * _EYE3):
            return False
    return True


def projected(matrix: np.ndarray, pinv: np.ndarray,
              rotation: Optional[np.ndarray] = None) -> tuple[Optional[np.ndarray],
                                                              Optional[str]]:
    """
    Return a 6 x 6 covariance on the group's algebra coordinates, or (None, 'zero_variance').

    ``rotation``: the base orientation R, which turns a world-frame pose covariance into
    the base frame first (``diag(R^T, R^T) C diag(R, R)``); None: already in the base frame.
    """
    if rotation is None:
        out = pinv @ matrix @ pinv.T
    else:
        # P diag(R^T, R^T) in one n x 6 matrix, then one sandwich.
        turn = np.empty(pinv.shape)
        turn[:, :3] = pinv[:, :3] @ rotation.T
        turn[:, 3:] = pinv[:, 3:] @ rotation.T
        out = turn @ matrix @ turn.T
    out = 0.5 * (out + out.T)
    if not (np.diag(out) > 0.0).all():
        return None, 'zero_variance'
    return out, None


class CovarianceReader:
    """
    Turns a base sample's message covariances into :class:`MeasurementNoise`.

    ``pinv``: the base group's algebra pseudo-inverse (n x 6). The last message
    covariance is kept per field with its verdict: drivers send the same one message
    after message, and the checks need an eigendecomposition. A twist covariance, and a
    pose covariance whose blocks are multiples of the identity (no turn changes it), are
    kept projected: the same matrix for every sample that repeats it.
    """

    def __init__(self, pinv: np.ndarray) -> None:
        """Read covariances for a group with algebra pseudo-inverse ``pinv``."""
        self.pinv = np.ascontiguousarray(pinv)
        self._last: dict[str, tuple] = {}

    def _read(self, key: str, values: Optional[np.ndarray], rotation: Optional[np.ndarray]
              ) -> tuple[Optional[np.ndarray], Optional[str]]:
        """Return (the covariance on the algebra coordinates or None, a fallback reason)."""
        if values is None:
            return None, None
        raw = values.tobytes()
        entry = self._last.get(key)
        if entry is None or entry[0] != raw:
            matrix, reason = checked(values)
            fixed = matrix is not None and (rotation is None or _isotropic(matrix))
            if fixed:
                matrix, reason = projected(matrix, self.pinv)
            entry = self._last[key] = (raw, matrix, reason, fixed)
        _, matrix, reason, fixed = entry
        if matrix is None or fixed:
            return matrix, reason
        return projected(matrix, self.pinv, rotation)

    def read(self, pose_values: Optional[np.ndarray], twist_values: Optional[np.ndarray],
             rotation: np.ndarray) -> tuple[Optional[MeasurementNoise], list[str]]:
        """
        Return the sample's noise (None: the parameters throughout) and the fallbacks' reasons.

        ``rotation``: the base orientation (3 x 3), which turns the pose covariance
        from the header frame into the base frame. The matrices returned may be shared
        between samples: read them, never modify them.
        """
        pose, pose_reason = self._read('pose', pose_values, rotation)
        twist, twist_reason = self._read('twist', twist_values, None)
        reasons = [] if pose_reason is None and twist_reason is None else \
            [f'{k}_{r}' for k, r in (('pose', pose_reason), ('twist', twist_reason)) if r]
        if pose is None and twist is None:
            return None, reasons
        return MeasurementNoise(pose, twist), reasons
