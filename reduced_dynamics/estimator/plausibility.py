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
Plausibility gates: input values the robot cannot have are rejected, not estimated.

Bounds per shape joint come from the URDF ``<limit>`` (:class:`JointLimit`):
position within ``[lower - margin, upper + margin]``, |velocity| and |effort|
below ``limit_factor`` times the URDF limit; joints without a limit (continuous
joints, joints expanded from planar/floating ones, limits not given) use the
configured bounds. Base samples need a quaternion norm within
``quaternion_norm_tolerance`` of 1 (inside it the quaternion is normalised, as
float32 and rounding errors need), a position and (Odometry) a twist inside
the configured bounds. The checks run on plain Python floats: they are on the
per-message path. Non-finite values are rejected before these gates.

The batched path (:meth:`~.intake.InputIntake._take_batch`) asks the same
questions of a whole batch at once (``passes``: numpy over the columns, the
same float operations in the same order); a message that fails goes through the
per-message check, which says why.
"""

from __future__ import annotations

import math
from operator import le
from typing import Optional, Sequence

import numpy as np

from reduced_dynamics.estimator.config import EstimatorConfig
from reduced_dynamics.robot.model import RobotModel

#: (reason, detail) of a rejection, or None.
Verdict = Optional[tuple[str, str]]


class JointBounds:
    """
    Per-joint bounds in one joint order (lists of floats, for the per-message checks).

    ``lower``/``upper`` positions, ``velocity``/``effort`` magnitudes.
    """

    __slots__ = ('names', 'lower', 'upper', 'velocity', 'effort', '_columns')

    def __init__(self, robot: RobotModel, config: EstimatorConfig,
                 names: Optional[Sequence[str]] = None) -> None:
        """Derive the bounds of ``names`` (default: the model's shape order)."""
        self.names = tuple(robot.shape_joint_names if names is None else names)
        limits = robot.shape_joint_limits
        margin, factor = config.joint_limit_margin, config.limit_factor
        self.lower, self.upper, self.velocity, self.effort = [], [], [], []
        for name in self.names:
            limit = limits.get(name)
            lower = None if limit is None else limit.lower
            if lower is None:
                self.lower.append(-config.joint_position_bound)
                self.upper.append(config.joint_position_bound)
            else:
                self.lower.append(lower - margin)
                self.upper.append(limit.upper + margin)
            velocity = None if limit is None else limit.velocity
            self.velocity.append(config.joint_velocity_bound if velocity is None
                                 else factor * velocity)
            effort = None if limit is None else limit.effort
            self.effort.append(config.joint_effort_bound if effort is None
                               else factor * effort)
        self._columns = tuple(np.array(b, dtype=float) for b in (
            self.lower, self.upper, self.velocity, self.effort))

    def passes(self, position: np.ndarray, velocity: np.ndarray, effort: np.ndarray,
               no_effort: Optional[np.ndarray] = None) -> np.ndarray:
        """
        Return per row of the (count, joints) columns whether :meth:`check` finds nothing.

        The values must be finite (checked before, as on the per-message path);
        ``no_effort`` marks rows whose message had no effort (not checked).
        """
        lower, upper, velocity_bound, effort_bound = self._columns
        ok = (lower <= position).all(axis=1)
        ok &= (position <= upper).all(axis=1)
        ok &= (np.abs(velocity) <= velocity_bound).all(axis=1)
        effort_ok = (np.abs(effort) <= effort_bound).all(axis=1)
        if no_effort is not None:
            effort_ok |= no_effort
        return ok & effort_ok

    def check(self, position: list, velocity: list, effort: list) -> Verdict:
        """Return why a joint state (lists in this order; effort may be empty) is implausible."""
        lower, upper = self.lower, self.upper
        if not (all(map(le, lower, position)) and all(map(le, position, upper))):
            k = next(i for i, p in enumerate(position) if not lower[i] <= p <= upper[i])
            return ('joint_position_limit',
                    f'{self.names[k]} at {position[k]:.6g} outside '
                    f'[{lower[k]:.6g}, {upper[k]:.6g}] (URDF limits plus margin)')
        bound = self.velocity
        if not all(map(le, map(abs, velocity), bound)):
            k = next(i for i, v in enumerate(velocity) if not abs(v) <= bound[i])
            return ('joint_velocity_limit',
                    f'{self.names[k]} velocity {velocity[k]:.6g} beyond {bound[k]:.6g}')
        bound = self.effort
        if effort and not all(map(le, map(abs, effort), bound)):
            k = next(i for i, e in enumerate(effort) if not abs(e) <= bound[i])
            return ('joint_effort_limit',
                    f'{self.names[k]} effort {effort[k]:.6g} beyond {bound[k]:.6g}')
        return None


class BaseBounds:
    """Bounds of a base sample: quaternion norm, position, Odometry twist."""

    __slots__ = ('norm_tolerance', 'position', 'speed', 'rate')

    def __init__(self, config: EstimatorConfig) -> None:
        """Take the bounds from the configuration."""
        self.norm_tolerance = config.quaternion_norm_tolerance
        self.position = config.base_position_bound
        self.speed = config.base_speed_bound
        self.rate = config.base_rate_bound

    def passes(self, position: np.ndarray, norm: np.ndarray,
               twist: Optional[np.ndarray]) -> np.ndarray:
        """
        Return per row whether :meth:`check` finds nothing (columns of 3, 1 and 6 values).

        ``twist`` None: the samples carry none. The sums and roots are those of
        :meth:`check`, in the same order (the same bits).
        """
        x, y, z = position.T
        ok = np.abs(norm - 1.0) <= self.norm_tolerance
        ok &= np.sqrt(x * x + y * y + z * z) <= self.position
        if twist is not None:
            vx, vy, vz, wx, wy, wz = twist.T
            ok &= np.sqrt(vx * vx + vy * vy + vz * vz) <= self.speed
            ok &= np.sqrt(wx * wx + wy * wy + wz * wz) <= self.rate
        return ok

    def check(self, position: list, norm: float, twist: list) -> Verdict:
        """Return why a base sample (position, quaternion norm, twist or []) is implausible."""
        if abs(norm - 1.0) > self.norm_tolerance:
            return ('quaternion_norm', f'orientation quaternion norm {norm:.6g}, not 1 '
                    f'within {self.norm_tolerance:g}')
        x, y, z = position
        if math.sqrt(x * x + y * y + z * z) > self.position:
            return ('base_position_bound',
                    f'base position {math.sqrt(x * x + y * y + z * z):.6g} m from the '
                    f'origin, beyond {self.position:g} m')
        if twist:
            vx, vy, vz, wx, wy, wz = twist
            speed = math.sqrt(vx * vx + vy * vy + vz * vz)
            if speed > self.speed:
                return ('base_twist_bound', f'base speed {speed:.6g} m/s beyond '
                        f'{self.speed:g} m/s')
            rate = math.sqrt(wx * wx + wy * wy + wz * wz)
            if rate > self.rate:
                return ('base_twist_bound', f'base angular rate {rate:.6g} rad/s beyond '
                        f'{self.rate:g} rad/s')
        return None
