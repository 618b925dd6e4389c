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

"""The full state of a free-floating robot and joint-torque laws."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
import pinocchio as pin

#: A joint-torque law tau(t, qbar, qbar_dot) on the shape joints (N m or N).
TorqueLaw = Callable[[float, np.ndarray, np.ndarray], np.ndarray]


@dataclass
class FreeFloatingState:
    """Base pose g, base body twist xi = g^-1 g_dot, shape qbar and its rate."""

    g: pin.SE3
    xi: np.ndarray
    qbar: np.ndarray
    qbar_dot: np.ndarray

    def copy(self) -> 'FreeFloatingState':
        """Return a deep copy."""
        return FreeFloatingState(pin.SE3(self.g), self.xi.copy(), self.qbar.copy(),
                                 self.qbar_dot.copy())


def zero_torque(m: int) -> TorqueLaw:
    """No joint torques."""
    zeros = np.zeros(m)

    def law(t: float, qbar: np.ndarray, qbar_dot: np.ndarray) -> np.ndarray:
        return zeros
    law.is_zero = True
    return law


def sinusoid_torque(amplitudes: np.ndarray, frequencies: np.ndarray,
                    phases: np.ndarray) -> TorqueLaw:
    """tau_i(t) = a_i sin(w_i t + phi_i): a smooth, state-independent excitation."""
    amplitudes = np.asarray(amplitudes, dtype=float)
    frequencies = np.asarray(frequencies, dtype=float)
    phases = np.asarray(phases, dtype=float)
    return lambda t, qbar, qbar_dot: amplitudes * np.sin(frequencies * t + phases)


def random_sinusoid_torque(m: int, rng: np.random.Generator, scale: float = 1.0) -> TorqueLaw:
    """Random sinusoids of amplitude up to ``scale`` and periods of 1 to 6 s."""
    return sinusoid_torque(scale * rng.uniform(0.2, 1.0, m), rng.uniform(1.0, 6.0, m),
                           rng.uniform(0.0, 2.0 * np.pi, m))
