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
Consistency of predicted covariances: NEES and coverage against reference poses.

Reads ``~/prediction/base_at_horizon`` (nav_msgs/Odometry, stamped with the time it
predicts) from a replay's output bag and the reference base poses from a bag:
the simulator's ``/ground_truth/base_pose``, or a measured pose topic (motion
capture) on real data. For each prediction, the pose error at the horizon,
``e = (p_ref - p, log(R_ref R^T))`` (world frame, the message's covariance order),
gives the normalised estimation error squared ``NEES = e^T P^-1 e`` (6 degrees
of freedom, 3 on a planar base: their mean for a consistent prediction) and
whether the reference lies in the 95 % ellipsoid (NEES below the chi-square 95 %
quantile: 12.59 for 6).
A measured reference carries its own noise: coverage then measures both.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Union

import numpy as np
import pinocchio as pin

from reduced_dynamics.bag import open_bag
from reduced_dynamics.chi_square import chi2

HORIZON_TOPIC = '/reduced_dynamics/prediction/base_at_horizon'
TRUTH_TOPIC = '/ground_truth/base_pose'
#: NEES bound of the 95 % ellipsoid of a 6-dof pose.
BOUND_95 = float(chi2.isf(0.05, 6))


@dataclass
class Consistency:
    """NEES of each compared prediction and their summary."""

    nees: np.ndarray
    #: stamp [ns] each prediction is for, and how far [s] its reference pose was from it
    stamps_ns: np.ndarray
    gaps: np.ndarray
    #: degrees of freedom of each (the base group's dimension: 6 for SE(3), 3 for SE(2))
    dofs: np.ndarray

    @property
    def count(self) -> int:
        """Return the number of compared predictions."""
        return len(self.nees)

    @property
    def mean_nees(self) -> float:
        """Return the mean NEES (the degrees of freedom expected)."""
        return float(np.mean(self.nees)) if self.count else float('nan')

    @property
    def coverage(self) -> float:
        """Return the fraction of references inside their 95 % ellipsoid."""
        if not self.count:
            return float('nan')
        bounds = np.array([chi2.isf(0.05, int(d)) for d in self.dofs])
        return float(np.mean(self.nees <= bounds))

    def text(self) -> str:
        """Return a one-line summary."""
        expected = f'{np.mean(self.dofs):g}' if self.count else '6'
        return (f'{self.count} predictions: mean NEES {self.mean_nees:.3g} ({expected} '
                f'expected), {100 * self.coverage:.1f} % inside their 95 % ellipsoid')


def _pose_of(msg: Any) -> pin.SE3:
    pose = msg.pose.pose if hasattr(msg.pose, 'pose') else msg.pose
    q = pose.orientation
    rotation = pin.Quaternion(q.w, q.x, q.y, q.z).normalized().toRotationMatrix()
    return pin.SE3(rotation, np.array([pose.position.x, pose.position.y, pose.position.z]))


def _stamp(msg: Any) -> int:
    return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec


def pose_error(predicted: pin.SE3, reference: pin.SE3) -> np.ndarray:
    """Return (p_ref - p, log(R_ref R^T)): world frame, ROS covariance order."""
    return np.concatenate([reference.translation - predicted.translation,
                           pin.log3(reference.rotation @ predicted.rotation.T)])


def measure(output_bag: Union[str, Path], reference_bag: Union[str, Path],
            reference_topic: str = TRUTH_TOPIC, horizon_topic: str = HORIZON_TOPIC,
            max_gap: float = 0.02) -> Consistency:
    """
    Return the NEES of every prediction against the reference pose nearest its stamp.

    Predictions without a reference within ``max_gap`` seconds are left out.
    """
    with open_bag(reference_bag) as bag:
        references = [(_stamp(m.msg), _pose_of(m.msg)) for m in bag.messages([reference_topic])]
    if not references:
        raise ValueError(f'{reference_bag} has no messages on {reference_topic}')
    stamps = np.array([s for s, _ in references], dtype=np.int64)
    order = np.argsort(stamps, kind='stable')
    stamps = stamps[order]
    poses = [references[i][1] for i in order]
    nees, at, gaps, dofs = [], [], [], []
    with open_bag(output_bag) as bag:
        for message in bag.messages([horizon_topic]):
            msg = message.msg
            stamp = _stamp(msg)
            i = int(np.searchsorted(stamps, stamp))
            near = [j for j in (i - 1, i) if 0 <= j < len(stamps)]
            j = min(near, key=lambda k: abs(int(stamps[k]) - stamp))
            gap = abs(int(stamps[j]) - stamp) * 1e-9
            if gap > max_gap:
                continue
            cov = np.asarray(msg.pose.covariance, dtype=float).reshape(6, 6)
            # A planar base: the covariance's zero rows (z, roll, pitch) are no freedom.
            free = np.flatnonzero(np.diag(cov) > 0.0)
            error = pose_error(_pose_of(msg), poses[j])[free]
            nees.append(float(error @ np.linalg.solve(cov[np.ix_(free, free)], error)))
            dofs.append(len(free))
            at.append(stamp)
            gaps.append(gap)
    return Consistency(np.array(nees), np.array(at, dtype=np.int64), np.array(gaps),
                       np.array(dofs, dtype=int))
