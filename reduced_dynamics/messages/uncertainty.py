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
Samples and converters of a prediction's uncertainty (docs/prediction_uncertainty.md).

* :class:`PredictedOdometry` -> nav_msgs/Odometry (``~/prediction/base_at_horizon``):
  stamped with the time it predicts, pose covariance in the world frame (x, y, z,
  rotation about X, Y, Z), body twist with its covariance.
* :class:`CovarianceEllipsoids` -> visualization_msgs/MarkerArray
  (``~/prediction/covariance_ellipsoids``): the 95 % position ellipsoid at points
  along the path, one SPHERE marker each (axes: the covariance's eigenvectors).
* :class:`ShapeCovariance` -> std_msgs/Float64MultiArray
  (``~/prediction/shape_covariance``): the covariance of (qbar, qbar_dot) at the
  horizon, 2m x 2m row-major; dimension labels give the joint order.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from reduced_dynamics.chi_square import chi2
from reduced_dynamics.geometry.quaternion import matrix_to_unit_xyzw
from reduced_dynamics.messages.convert import (base_state_to_odometry, header_to_ros,
                                               pose_to_ros)
from reduced_dynamics.messages.samples import BaseStateSample
from reduced_dynamics.messages.types import MessageTypes

#: Squared Mahalanobis radius of the 95 % ellipsoid in 3 dimensions.
RADIUS2_95 = float(chi2.isf(0.05, 3))
#: RGBA exact in float32 (ColorRGBA), so a decoded message equals the one built.
_COLOR = (0.25, 0.5, 1.0, 0.375)


@dataclass(frozen=True, eq=False)
class PredictedOdometry:
    """The predicted base state at the horizon with its covariances (row-major 6 x 6)."""

    base: BaseStateSample
    pose_covariance: np.ndarray
    twist_covariance: np.ndarray


@dataclass(frozen=True, eq=False)
class CovarianceEllipsoids:
    """Position means (N, 3) and covariances (N, 3, 3) along a path, at ``stamps_ns``."""

    stamp_ns: int
    frame_id: str
    stamps_ns: np.ndarray
    positions: np.ndarray
    covariances: np.ndarray


@dataclass(frozen=True, eq=False)
class ShapeCovariance:
    """Covariance (2m x 2m) of (qbar, qbar_dot) at the horizon, joints in ``joint_names``."""

    joint_names: tuple[str, ...]
    covariance: np.ndarray


def predicted_odometry_to_ros(sample: PredictedOdometry, types: MessageTypes) -> Any:
    """Build nav_msgs/msg/Odometry."""
    return base_state_to_odometry(sample.base, types, sample.pose_covariance.ravel(),
                                  sample.twist_covariance.ravel())


def ellipsoid_axes(cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return (quaternion x, y, z, w of the principal axes, 95 % diameters) of a 3 x 3 cov."""
    values, vectors = np.linalg.eigh(0.5 * (cov + cov.T))
    if np.linalg.det(vectors) < 0.0:
        vectors[:, 0] = -vectors[:, 0]
    quat = matrix_to_unit_xyzw(vectors)
    return quat, 2.0 * np.sqrt(RADIUS2_95 * np.clip(values, 0.0, None))


def ellipsoids_to_ros(sample: CovarianceEllipsoids, types: MessageTypes) -> Any:
    """Build visualization_msgs/msg/MarkerArray: one 95 % SPHERE per point."""
    markers = []
    for index, (stamp, position, cov) in enumerate(zip(sample.stamps_ns, sample.positions,
                                                       sample.covariances)):
        quat, diameters = ellipsoid_axes(cov)
        markers.append(types.create(
            'visualization_msgs/msg/Marker',
            header=header_to_ros(int(stamp), sample.frame_id, types),
            ns='prediction_covariance', id=index, type=2, action=0,
            pose=pose_to_ros(position, quat, types),
            scale=types.create('geometry_msgs/msg/Vector3', x=float(diameters[0]),
                               y=float(diameters[1]), z=float(diameters[2])),
            color=types.create('std_msgs/msg/ColorRGBA', r=_COLOR[0], g=_COLOR[1],
                               b=_COLOR[2], a=_COLOR[3]),
            lifetime=types.create('builtin_interfaces/msg/Duration', sec=0, nanosec=0),
            frame_locked=False, points=[], colors=[], texture_resource='',
            texture=types.create('sensor_msgs/msg/CompressedImage',
                                 header=header_to_ros(0, '', types), format='',
                                 data=np.zeros(0, np.uint8)),
            uv_coordinates=[], text='', mesh_resource='',
            mesh_file=types.create('visualization_msgs/msg/MeshFile', filename='',
                                   data=np.zeros(0, np.uint8)),
            mesh_use_embedded_materials=False))
    return types.create('visualization_msgs/msg/MarkerArray', markers=markers)


def shape_covariance_to_ros(sample: ShapeCovariance, types: MessageTypes) -> Any:
    """Build std_msgs/msg/Float64MultiArray (labels: qbar:<joint> then qbar_dot:<joint>)."""
    size = len(sample.covariance)
    dims = [types.create('std_msgs/msg/MultiArrayDimension', label='row', size=size,
                         stride=size * size),
            types.create('std_msgs/msg/MultiArrayDimension', label='col', size=size,
                         stride=size)]
    dims += [types.create('std_msgs/msg/MultiArrayDimension', label=f'{kind}:{name}', size=1,
                          stride=1)
             for kind in ('qbar', 'qbar_dot') for name in sample.joint_names]
    return types.create(
        'std_msgs/msg/Float64MultiArray',
        layout=types.create('std_msgs/msg/MultiArrayLayout', dim=dims, data_offset=0),
        data=types.float_seq(sample.covariance.ravel()))
