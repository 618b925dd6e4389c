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
Payload identification on a running node: the last seconds of input, on request.

The node's ``~/identify_payload`` service (std_srvs/Trigger) asks
:class:`PayloadWindow` to identify the payload on ``payload_link`` over the last
``payload_window`` seconds of joint states and Odometry
(:mod:`reduced_dynamics.identify`); the node then rebuilds its robot model
with the payload (:func:`reduced_dynamics.payload.with_payload`) and restarts
the filter, which initialises at the new mu with its covariance.
"""

from __future__ import annotations

from collections import deque
from typing import Optional

from reduced_dynamics.identify import (identify_window, IdentificationError, PayloadEstimate,
                                       SensorNoise, synchronise)
from reduced_dynamics.messages.samples import BaseStateSample, JointStateSample
from reduced_dynamics.payload import link_frame
from reduced_dynamics.robot.model import RobotModel


class PayloadWindow:
    """The recent input samples of a nominal robot, and the identification over them."""

    def __init__(self, robot: RobotModel, link: str, seconds: float) -> None:
        """Hold up to ``seconds`` of samples (by stamp) for a payload on ``link``."""
        link_frame(robot, link)  # PayloadError now rather than at the first request
        self.robot = robot
        self.link = link
        self.window_ns = int(seconds * 1e9)
        self._joints: deque = deque()
        self._bases: deque = deque()
        #: the last identified payload (None until one succeeded)
        self.estimate: Optional[PayloadEstimate] = None
        self.last_error: Optional[str] = None

    def take(self, sample: object) -> None:
        """Keep a joint-state or base sample; forget those older than the window."""
        if isinstance(sample, JointStateSample):
            queue = self._joints
        elif isinstance(sample, BaseStateSample) and sample.twist_linear is not None:
            queue = self._bases
        else:
            return
        queue.append(sample)
        oldest = sample.stamp_ns - self.window_ns
        for held in (self._joints, self._bases):
            while held and held[0].stamp_ns < oldest:
                held.popleft()

    def identify(self, noise: SensorNoise) -> PayloadEstimate:
        """Identify over the held samples (IdentificationError with the reason if refused)."""
        try:
            window = synchronise(self.robot, list(self._joints), list(self._bases))
            estimate = identify_window(self.robot, self.link, window, noise)
        except IdentificationError as error:
            self.last_error = str(error)
            raise
        self.estimate = estimate
        self.last_error = None
        return estimate

    def clear(self) -> None:
        """Forget the held samples (a new window starts, e.g. after a clock jump)."""
        self._joints.clear()
        self._bases.clear()


def inertia_fields(estimate_payload) -> dict:
    """Return geometry_msgs/Inertia fields of a payload (CoM in the link frame)."""
    inertia = estimate_payload.inertia
    return {'m': float(estimate_payload.mass),
            'com': tuple(float(c) for c in estimate_payload.com),
            'ixx': float(inertia[0, 0]), 'ixy': float(inertia[0, 1]),
            'ixz': float(inertia[0, 2]), 'iyy': float(inertia[1, 1]),
            'iyz': float(inertia[1, 2]), 'izz': float(inertia[2, 2])}
