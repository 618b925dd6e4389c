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
The estimator's second-stage view (Theorem 57): kept shape state and cyclic momenta.

With the ``cyclic_joints`` setting on, the published shape state holds only the
joints of the theta-shape space, with the second-stage momentum
``p^ = K^ q^_dot`` in its effort field, and the cyclic joints (reaction wheels)
are published apart with their conserved momenta ``theta`` (rows of ``M v``).
"""

from __future__ import annotations

import numpy as np

from reduced_dynamics.messages.samples import JointStateSample, trusted_sample
from reduced_dynamics.reduction.second_stage import CyclicSplit
from reduced_dynamics.robot.model import ModelError, RobotModel

#: Values of the ``cyclic_joints`` setting besides a comma-separated list of names.
CYCLIC_OFF = ''
CYCLIC_AUTO = 'auto'


def resolve_cyclic_joints(robot: RobotModel, setting: str) -> tuple[str, ...]:
    """
    Return the cyclic joints a ``cyclic_joints`` setting selects for this robot.

    ``''``: none (first stage only); ``'auto'``: every joint section 5.1 finds
    cyclic; otherwise comma-separated names, each of which must be cyclic
    (ModelError with the reason otherwise).
    """
    setting = setting.strip()
    if setting == CYCLIC_OFF:
        return ()
    if setting == CYCLIC_AUTO:
        return robot.symmetry_report().cyclic_joints
    names = tuple(name.strip() for name in setting.split(',') if name.strip())
    return CyclicSplit(robot, names).names


class CyclicView:
    """Splits each estimate into the kept shape state and the cyclic momenta."""

    def __init__(self, robot: RobotModel, cyclic_joints: tuple[str, ...]) -> None:
        """Prepare the index split for ``cyclic_joints`` (all must be cyclic)."""
        if not cyclic_joints:
            raise ModelError('no cyclic joints to reduce by')
        self.split = CyclicSplit(robot, cyclic_joints)
        self.n = robot.n
        self.kept_names = self.split.kept_names
        self.cyclic_names = self.split.names

    def samples(self, stamp_ns: int, mass_matrix: np.ndarray, momentum: np.ndarray,
                qbar: np.ndarray, qbar_dot: np.ndarray
                ) -> tuple[JointStateSample, JointStateSample]:
        """
        Return (kept shape state, cyclic state) from one sample's ``M`` and ``M v``.

        Kept: ``q^, q^_dot, p^ = K^ q^_dot``; cyclic: angles, rates and ``theta``.
        """
        split = self.split
        locked = mass_matrix[np.ix_(split.locked_rows, split.locked_rows)]
        coupling = mass_matrix[np.ix_(split.locked_rows, split.kept_rows)]
        shape = mass_matrix[np.ix_(split.kept_rows, split.kept_rows)]
        kept_rate = qbar_dot[split.kept]
        # p^ = (M_kk - B_e^T I_e^-1 B_e) q^_dot, the metric K^ of Theorem 57.
        phat = shape @ kept_rate - coupling.T @ np.linalg.solve(locked, coupling @ kept_rate)
        kept = trusted_sample(JointStateSample, stamp_ns, '', self.kept_names,
                              qbar[split.kept], kept_rate, phat)
        cyclic = trusted_sample(JointStateSample, stamp_ns, '', self.cyclic_names,
                                qbar[split.cyclic], qbar_dot[split.cyclic],
                                momentum[self.n + split.cyclic])
        return kept, cyclic
