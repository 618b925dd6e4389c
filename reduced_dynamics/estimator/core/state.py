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
The filter's inputs, noise and recorded steps: plain data, no arithmetic.

Poses are 4 x 4 homogeneous arrays inside the core (what the compiled kernels
take); the ``pin.SE3`` views are for callers.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple, Optional

import numpy as np
import pinocchio as pin


@dataclass(frozen=True)
class NoiseModel:
    """
    Sensor and process noise in physical units (standard deviations).

    ``pose_position`` [m], ``pose_angle`` [rad]: pose measurement noise;
    ``twist_linear`` [m/s], ``twist_angular`` [rad/s]: Odometry twist noise;
    ``joint_velocity`` [rad/s or m/s]: encoder velocity noise;
    ``jerk_linear`` [m/s^3/sqrt(Hz)], ``jerk_angular`` [rad/s^3/sqrt(Hz)]: density
    of the body acceleration random walk that drives w (scaled by I);
    ``initial_speed`` [m/s], ``initial_rate`` [rad/s], ``initial_acceleration``
    [m/s^2 and rad/s^2]: prior spread of the motion before the first update.
    Commanded wrench only: ``command_gain`` prior spread of the gain (about 1),
    ``command_gain_drift`` [1/sqrt(s)] its random-walk density;
    ``command_bias_linear`` [m/s^2], ``command_bias_angular`` [rad/s^2] prior
    spread of the bias as a body acceleration (scaled by I), which drifts at
    ``command_gain_drift`` times that per sqrt(s); ``disturbance_linear``
    [m/s^3/sqrt(Hz)], ``disturbance_angular`` [rad/s^3/sqrt(Hz)]: the density
    of w's random walk in place of ``jerk_*`` (w is then the disturbance beyond
    the command, which no longer carries the thruster switching).
    """

    pose_position: float = 1e-3
    pose_angle: float = 2e-3
    twist_linear: float = 1e-2
    twist_angular: float = 1e-2
    joint_velocity: float = 1e-2
    jerk_linear: float = 0.05
    jerk_angular: float = 0.5
    initial_speed: float = 1.0
    initial_rate: float = 1.0
    initial_acceleration: float = 1.0
    command_gain: float = 0.5
    command_gain_drift: float = 2e-3
    command_bias_linear: float = 5e-3
    command_bias_angular: float = 2.5e-2
    disturbance_linear: float = 1e-3
    disturbance_angular: float = 5e-3
    pose_stamp: float = 0.0


class Linearisation(NamedTuple):
    """Per-sample inputs of the process model: I, I^-1, A qbar_dot, A Sigma A^T."""

    locked: np.ndarray
    locked_inverse: np.ndarray
    connection_qd: np.ndarray
    joint_cov: np.ndarray


def between(before: Linearisation, after: Linearisation, fraction: float) -> Linearisation:
    """
    Return the inputs ``fraction`` of the way from ``before`` to ``after``.

    I^-1 and A qbar_dot are interpolated linearly (the trapezoid of the step's
    inputs); I and A Sigma A^T are those of ``after``. ``fraction`` 0.5 is the
    middle of a joint-state interval, written as the plain mean.
    """
    if fraction == 0.5:
        return Linearisation(after.locked,
                             0.5 * (before.locked_inverse + after.locked_inverse),
                             0.5 * (before.connection_qd + after.connection_qd), after.joint_cov)
    return Linearisation(
        after.locked,
        before.locked_inverse + fraction * (after.locked_inverse - before.locked_inverse),
        before.connection_qd + fraction * (after.connection_qd - before.connection_qd),
        after.joint_cov)


class Measurement(NamedTuple):
    """A base measurement at its own stamp: the pose, and the body twist with Odometry."""

    stamp_ns: int
    pose: pin.SE3
    twist: Optional[np.ndarray]
    #: the stamp's standard deviation [s] when it differs from ``NoiseModel.pose_stamp``
    #: (a re-timed frame time, estimator/retiming.py); None: ``pose_stamp`` (used only
    #: when ``pose_stamp`` > 0)
    stamp_sigma: Optional[float] = None
    #: the sample's own noise (estimator/covariance.py ``MeasurementNoise``: pose and
    #: twist covariances in the filter's coordinates, each None for the parameters);
    #: None: the noise parameters
    noise: Optional[tuple] = None


@dataclass
class FilterStep:
    """
    What the RTS smoother needs from one step (predicted and filtered).

    ``transition`` Phi into this step (None: a restart, independent of the step
    before); poses as 4 x 4 homogeneous arrays (``pose_pred``, ``pose``; the
    ``g_pred``/``g`` properties give ``pin.SE3``). ``output``: the step is a
    joint-state row (an output of the estimator); False for a base measurement
    between two rows.
    """

    stamp_ns: int
    transition: Optional[np.ndarray]
    pose_pred: np.ndarray
    x_pred: np.ndarray
    p_pred: np.ndarray
    pose: np.ndarray
    x: np.ndarray
    p: np.ndarray
    locked_inverse: np.ndarray
    output: bool = True
    #: commanded wrench only: the command held at this step's end
    command: Optional[np.ndarray] = None

    @property
    def g_pred(self) -> pin.SE3:
        """Return the predicted pose."""
        return pin.SE3(self.pose_pred)

    @property
    def g(self) -> pin.SE3:
        """Return the filtered pose."""
        return pin.SE3(self.pose)


class Command(NamedTuple):
    """
    The commanded body wrench over a step (dual coordinates, body frame).

    ``mean``: its mean over the step (what the propagation integrates);
    ``now``: the value held at the step's end (what the total wrench reports).
    """

    mean: np.ndarray
    now: np.ndarray


class FilterState(NamedTuple):
    """A state estimate: pose, [mu; w] (and [k; b]), covariance (3n or 5n square)."""

    g: pin.SE3
    x: np.ndarray
    p: np.ndarray
