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
A sinusoidal shape motion with the base motion momentum conservation gives.

The soak feeds the node for an hour; a base that moves on its own while the arm
swings is an external wrench to the estimator (an event that never closes, and
predictions pause inside events). Here the base follows the reconstruction
``xi = I^-1 pi - A qbar_dot`` with ``pi = Ad_g^T mu`` for a constant spatial
momentum mu (REDUCED_MODEL.md 4; (5.27), (5.29)), so the stream is free of
external wrenches up to the integrator's error: the pose advances by the
exponential midpoint rule, second order in the step.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
import pinocchio as pin

from reduced_dynamics.geometry.quaternion import matrix_to_xyzw
from reduced_dynamics.robot.momentum import base_twist, body_momentum, \
    body_momentum_from_spatial, momentum_map

#: The bench's base twist at t = 0 (body frame, [v; omega]): 1 cm/s forward, 0.05 rad/s yaw.
INITIAL_BASE_TWIST = (0.01, 0.0, 0.0, 0.0, 0.0, 0.05)


class ConsistentMotion:
    """
    Shape ``a sin(w t + phi)`` and the base pose and body twist of a free-floating robot.

    Step it forward with :meth:`advance` (a fixed step, one call per sample); read
    the current sample with :meth:`shape`, :attr:`pose` and :meth:`twist6`.
    """

    def __init__(self, robot, seed: int = 0,
                 initial_twist: Sequence[float] = INITIAL_BASE_TWIST) -> None:
        """Draw the sinusoids as the bench's motion does; mu from the twist at t = 0."""
        rng = np.random.default_rng(seed)
        m = robot.m
        self.amplitude = rng.uniform(0.1, 0.4, m)
        self.frequency = rng.uniform(0.5, 2.0, m)
        self.phase = rng.uniform(0.0, 2.0 * np.pi, m)
        self.robot = robot
        self.group = robot.group
        self.t = 0.0
        self.pose = pin.SE3.Identity()
        xi0 = self.group.coordinates(np.asarray(initial_twist, dtype=float))
        qbar, qbar_dot = self.shape(0.0)
        pi0 = body_momentum(robot.metric_blocks(qbar), xi0, qbar_dot)
        #: the constant spatial momentum about the world origin (5.27)
        self.mu = momentum_map(self.group, self.pose, pi0)
        self._xi = self._twist(0.0, self.pose)

    def shape(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Shape qbar(t) and its rate."""
        angle = self.frequency * t + self.phase
        return (self.amplitude * np.sin(angle),
                self.amplitude * self.frequency * np.cos(angle))

    def _twist(self, t: float, g: pin.SE3) -> np.ndarray:
        qbar, qbar_dot = self.shape(t)
        blocks = self.robot.metric_blocks(qbar)
        return base_twist(blocks, body_momentum_from_spatial(self.group, g, self.mu), qbar_dot)

    def twist6(self) -> np.ndarray:
        """Body twist [v; omega] (child frame, as nav_msgs/Odometry carries it) now."""
        return np.asarray(self.group.twist(self._xi), dtype=float)

    def orientation_xyzw(self) -> np.ndarray:
        """Return the base orientation as a unit quaternion (x, y, z, w), ROS order."""
        return matrix_to_xyzw(self.pose.rotation)

    def advance(self, dt: float) -> None:
        """One exponential midpoint step of g_dot = g xi: second-order accurate."""
        half = self.pose * self.group.exp(0.5 * dt * self._xi)
        xi_mid = self._twist(self.t + 0.5 * dt, half)
        self.pose = self.pose * self.group.exp(dt * xi_mid)
        self.t += dt
        self._xi = self._twist(self.t, self.pose)
