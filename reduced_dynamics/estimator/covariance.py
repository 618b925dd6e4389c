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


def pose_in_body(matrix: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    """Return a world-frame pose covariance (x y z roll pitch yaw) in the base frame."""
    turn = np.zeros((6, 6))
    turn[:3, :3] = turn[3:, 3:] = rotation.T
    return turn @ matrix @ turn.T


def projected(matrix: np.ndarray, pinv: np.ndarray) -> tuple[Optional[np.ndarray],
                                                             Optional[str]]:
    """Return the covariance on the group's algebra coordinates, or (None, 'zero_variance')."""
    out = pinv @ matrix @ pinv.T
    out = 0.5 * (out + out.T)
    if not (np.diag(out) > 0.0).all():
        return None, 'zero_variance'
    return out, None


class CovarianceReader:
    """
    Turns a base sample's message covariances into :class:`MeasurementNoise`.

    ``pinv``: the base group's algebra pseudo-inverse (n x 6). The last checked
    matrix is kept per field: drivers send the same covariance message after
    message, and the checks need an eigendecomposition.
    """

    def __init__(self, pinv: np.ndarray) -> None:
        """Read covariances for a group with algebra pseudo-inverse ``pinv``."""
        self.pinv = np.ascontiguousarray(pinv)
        self._last: dict[str, tuple[bytes, Optional[np.ndarray], Optional[str]]] = {}

    def _checked(self, key: str, values: Optional[np.ndarray]
                 ) -> tuple[Optional[np.ndarray], Optional[str]]:
        if values is None:
            return None, None
        raw = values.tobytes()
        last = self._last.get(key)
        if last is not None and last[0] == raw:
            return last[1], last[2]
        matrix, reason = checked(values)
        self._last[key] = (raw, matrix, reason)
        return matrix, reason

    def read(self, pose_values: Optional[np.ndarray], twist_values: Optional[np.ndarray],
             rotation: np.ndarray) -> tuple[Optional[MeasurementNoise], list[str]]:
        """
        Return the sample's noise (None: the parameters throughout) and the fallbacks' reasons.

        ``rotation``: the base orientation (3 x 3), which turns the pose covariance
        from the header frame into the base frame.
        """
        reasons = []
        pose, reason = self._checked('pose', pose_values)
        if reason is not None:
            reasons.append(f'pose_{reason}')
        if pose is not None:
            pose, reason = projected(pose_in_body(pose, rotation), self.pinv)
            if reason is not None:
                reasons.append(f'pose_{reason}')
        twist, reason = self._checked('twist', twist_values)
        if reason is not None:
            reasons.append(f'twist_{reason}')
        if twist is not None:
            twist, reason = projected(twist, self.pinv)
            if reason is not None:
                reasons.append(f'twist_{reason}')
        if pose is None and twist is None:
            return None, reasons
        return MeasurementNoise(pose, twist), reasons
