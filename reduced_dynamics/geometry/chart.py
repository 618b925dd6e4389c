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
Local chart chi of the coset space Q1/G_mu (REDUCED_MODEL.md section 5).

``chi(q1) = exp(C q1) g_ref`` with C a complement of Lie(G_mu): the classes
G_mu chi(q1) are distinct near q1 = 0 because exp(C q1) moves transversally to
the (right-trivialised) isotropy directions. Re-centre before |C q1| grows.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from reduced_dynamics.geometry.lie_group import BaseGroup


@dataclass
class CosetChart:
    """Chart chi of Q1/G_mu around a reference pose ``g_ref``."""

    group: BaseGroup
    complement: np.ndarray
    g_ref: pin.SE3

    @property
    def dim(self) -> int:
        """Return the number k of chart coordinates."""
        return self.complement.shape[1]

    def point(self, q1: np.ndarray) -> pin.SE3:
        """chi(q1) = exp(C q1) g_ref."""
        return self.group.exp(self.complement @ q1) * self.g_ref

    def body_jacobian(self, q1: np.ndarray) -> np.ndarray:
        """L_chi(q1): columns chi^-1 d chi / d q1_j as body twists (n x k)."""
        eta = self.complement @ q1
        return self.group.Ad(self.g_ref.inverse()) @ self.group.right_jacobian(eta) \
            @ self.complement

    def recentred(self, q1: np.ndarray) -> 'CosetChart':
        """Return the same chart re-centred at chi(q1) (whose coordinate is then 0)."""
        return CosetChart(self.group, self.complement, self.point(q1))
