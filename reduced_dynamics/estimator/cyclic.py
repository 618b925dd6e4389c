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

from typing import Sequence, Union

import numpy as np

from reduced_dynamics.messages.samples import JointStateSample, trusted_sample
from reduced_dynamics.reduction.second_stage import CyclicSplit, SecondStageBlocks
from reduced_dynamics.robot.model import ModelError, RobotModel

#: Values of the ``cyclic_joints`` setting besides a comma-separated list of names.
CYCLIC_OFF = ''
CYCLIC_AUTO = 'auto'


def resolve_cyclic_joints(robot: RobotModel,
                          setting: Union[str, Sequence[str]]) -> tuple[str, ...]:
    """
    Return the cyclic joints a ``cyclic_joints`` setting selects for this robot.

    ``''``: none (first stage only); ``'auto'``: every joint section 5.1 finds
    cyclic; otherwise comma-separated names (or a list of names), each of which
    must be cyclic (ModelError with the reason otherwise). Returned in shape order.
    """
    if isinstance(setting, str):
        setting = setting.strip()
        if setting == CYCLIC_OFF:
            return ()
        if setting == CYCLIC_AUTO:
            return robot.symmetry_report().cyclic_joints
        setting = [name.strip() for name in setting.split(',') if name.strip()]
    return CyclicSplit(robot, tuple(setting)).names


class CyclicColumns:
    """
    Second-stage columns of one chunk: row k belongs to sample k.

    Kept joints: ``qhat``, ``qhat_dot``, ``phat = K^ q^_dot``; cyclic joints:
    ``angles``, ``rates`` and their momenta ``theta``.
    """

    __slots__ = ('kept_names', 'cyclic_names', 'qhat', 'qhat_dot', 'phat', 'angles',
                 'rates', 'theta')

    def __init__(self, view: 'CyclicView', qhat: np.ndarray, qhat_dot: np.ndarray,
                 phat: np.ndarray, angles: np.ndarray, rates: np.ndarray,
                 theta: np.ndarray) -> None:
        """Hold contiguous (K, .) columns."""
        self.kept_names, self.cyclic_names = view.kept_names, view.cyclic_names
        self.qhat, self.qhat_dot, self.phat = qhat, qhat_dot, phat
        self.angles, self.rates, self.theta = angles, rates, theta

    def sample(self, k: int, stamp_ns: int) -> JointStateSample:
        """Return the cyclic-momenta sample of row k (angles, rates, theta as effort)."""
        return trusted_sample(JointStateSample, stamp_ns, '', self.cyclic_names,
                              self.angles[k], self.rates[k], self.theta[k])


class CyclicView:
    """Splits the estimates of a chunk into the kept shape state and the cyclic momenta."""

    def __init__(self, robot: RobotModel, cyclic_joints: tuple[str, ...]) -> None:
        """Prepare the index split for ``cyclic_joints`` (all must be cyclic)."""
        if not cyclic_joints:
            raise ModelError('no cyclic joints to reduce by')
        self.split = CyclicSplit(robot, cyclic_joints)
        self.n = robot.n
        self.kept_names = self.split.kept_names
        self.cyclic_names = self.split.names

    def columns(self, mass: np.ndarray, xi: np.ndarray, qbar: np.ndarray,
                qbar_dot: np.ndarray) -> CyclicColumns:
        """
        Return the second-stage columns from a chunk's mass matrices (K, nv, nv).

        ``theta = (M v)`` on the cyclic rows, ``p^ = (M_kk - B_e^T I_e^-1 B_e) q^_dot``
        with the locked group G x N of Theorem 57.
        """
        split = self.split
        ne = split.n + split.c
        count = len(mass)
        velocity = np.concatenate([xi, qbar_dot], axis=1)[:, split.order]
        kept_rate = np.ascontiguousarray(velocity[:, ne:])
        theta = np.empty((count, split.c))
        phat = np.empty((count, split.mk))
        # Row by row with the same operations whatever the chunk size (stacked BLAS
        # kernels round differently with the stack size).
        for k in range(count):
            blocks = SecondStageBlocks.from_mass(split, mass[k])
            theta[k] = blocks.locked_momentum(velocity[k, :ne], kept_rate[k])[split.n:]
            phat[k] = blocks.reduced_metric @ kept_rate[k]
        return CyclicColumns(self, np.ascontiguousarray(qbar[:, split.kept]), kept_rate, phat,
                             np.ascontiguousarray(qbar[:, split.cyclic]),
                             np.ascontiguousarray(qbar_dot[:, split.cyclic]), theta)
