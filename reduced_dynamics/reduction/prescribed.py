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
Base motion for a prescribed shape path: the reconstruction equation alone.

With q(t) given (a planned arm motion) and no external wrench, mu is constant
(Noether) and the base pose obeys a first-order ODE on the base group
(REDUCED_MODEL.md 4)::

    g_dot = g xi,   xi = I(q)^-1 Ad_g^T mu  -  A(q) q_dot(t)
                         └ drift ┘            └ geometric phase ┘

No shape dynamics are integrated: one ``crba`` and one n x n solve per
evaluation. The geometric phase alone (g_dot = g (-A q_dot)) is the base
motion of the same arm motion at zero momentum; it is integrated beside the
full one (shared evaluations), so the prediction reports the split.
Both poses are carried in re-centred charts g = g_seg exp(eta).
"""

from __future__ import annotations

from typing import Callable, Optional, Sequence

import numpy as np
import pinocchio as pin
from scipy.linalg.lapack import dposv

from reduced_dynamics.integrators import Budget, integrate_pieces
from reduced_dynamics.robot.model import RobotModel

#: A shape path: t -> (q, q_dot, q_ddot), with ``breakpoints`` (knot times).
ShapePath = Callable[[float], tuple[np.ndarray, np.ndarray, np.ndarray]]


class PrescribedReconstruction:
    """
    The reconstruction ODE for a prescribed shape path, as a charted system.

    y = (eta, eta_phase): chart coordinates of the base pose g and of the
    geometric-phase-only pose, both starting at ``g0``.
    """

    def __init__(self, robot: RobotModel, mu: np.ndarray, g0: pin.SE3,
                 path: ShapePath) -> None:
        """Reconstruct from ``g0`` at momentum ``mu`` (world frame) along ``path``."""
        self.robot = robot
        self.group = robot.group
        self.mu = np.asarray(mu, dtype=float)
        self.path = path
        self.n = robot.n
        self.g_seg = pin.SE3(g0)
        self.phase_seg = pin.SE3(g0)

    def _pose(self, seg: pin.SE3, eta: np.ndarray) -> pin.SE3:
        return seg * self.group.exp(eta)

    def twists(self, t: float, g: pin.SE3) -> tuple[np.ndarray, np.ndarray]:
        """Return the drift I^-1 Ad_g^T mu and the geometric phase -A q_dot at (t, g)."""
        n = self.n
        q, qd, _ = self.path(t)
        # crba fills the upper triangle, which is all dposv reads (I and B lie in it).
        mass = self.robot.mass_matrix_upper(q)
        right = np.empty((n, 2), order='F')
        right[:, 0] = self.group.Ad(g).T @ self.mu
        right[:, 1] = -(mass[:n, n:] @ qd)
        _, solved, info = dposv(mass[:n, :n], right)
        if info:
            raise np.linalg.LinAlgError('locked inertia is not positive definite')
        return solved[:, 0], solved[:, 1]

    def rhs(self, t: float, y: np.ndarray) -> np.ndarray:
        """dy/dt: eta_dot = Jr(eta)^-1 xi for the full and the phase-only pose."""
        n = self.n
        drift, phase = self.twists(t, self._pose(self.g_seg, y[:n]))
        out = np.empty(2 * n)
        out[:n] = self.group.right_jacobian_inverse(y[:n]) @ (drift + phase)
        out[n:] = self.group.right_jacobian_inverse(y[n:]) @ phase
        return out

    def chart_size(self, y: np.ndarray) -> float:
        """Largest chart coordinate norm of the two poses."""
        n = self.n
        return max(float(np.linalg.norm(y[:n])), float(np.linalg.norm(y[n:])))

    def recentre(self, y: np.ndarray) -> np.ndarray:
        """Move both chart centres to the current poses."""
        n = self.n
        self.g_seg = self._pose(self.g_seg, y[:n])
        self.phase_seg = self._pose(self.phase_seg, y[n:])
        return np.zeros_like(y)

    def observe(self, t: float, y: np.ndarray) -> np.ndarray:
        """[g (16), g_phase (16), drift twist (n), phase twist (n)] at t."""
        n = self.n
        g = self._pose(self.g_seg, y[:n])
        drift, phase = self.twists(t, g)
        return np.concatenate([g.homogeneous.ravel(),
                               self._pose(self.phase_seg, y[n:]).homogeneous.ravel(),
                               drift, phase])

    def propagate(self, times: Sequence[float], rtol: float = 1e-10, atol: float = 1e-12,
                  breakpoints: Sequence[float] = (), budget: Optional[Budget] = None
                  ) -> 'PrescribedTrajectory':
        """Integrate (DOP853, restarted at the path's knots) and sample at ``times``."""
        times = np.asarray(times, dtype=float)
        records = integrate_pieces(self, np.zeros(2 * self.n), times, breakpoints, rtol, atol,
                                   budget)
        return PrescribedTrajectory(self.n, times, records)


class PrescribedTrajectory:
    """Samples of a prescribed-shape reconstruction: poses, phase-only poses, twist split."""

    def __init__(self, n: int, times: np.ndarray, records: np.ndarray) -> None:
        """Split observe() records into named arrays."""
        self.times = times
        self.poses = records[:, :16].reshape(-1, 4, 4)
        self.phase_poses = records[:, 16:32].reshape(-1, 4, 4)
        self.drift = records[:, 32:32 + n]
        self.phase = records[:, 32 + n:32 + 2 * n]


def attitude_angles(reference: np.ndarray, rotations: np.ndarray) -> np.ndarray:
    """
    Return the rotation angle [rad] between ``reference`` (3, 3) and each of ``rotations``.

    atan2 of the skew and symmetric parts of R_ref^T R: accurate at small
    angles, where arccos of the trace loses half the digits.
    """
    relative = np.einsum('ji,njk->nik', reference, rotations)
    return _angles(relative)


def relative_angles(first: np.ndarray, second: np.ndarray) -> np.ndarray:
    """Return the rotation angles between matching rotations of two (N, 3, 3) stacks."""
    return _angles(np.einsum('nji,njk->nik', first, second))


def _angles(relative: np.ndarray) -> np.ndarray:
    skew = np.stack([relative[:, 2, 1] - relative[:, 1, 2],
                     relative[:, 0, 2] - relative[:, 2, 0],
                     relative[:, 1, 0] - relative[:, 0, 1]], axis=1)
    sine = 0.5 * np.linalg.norm(skew, axis=1)
    cosine = 0.5 * (np.trace(relative, axis1=1, axis2=2) - 1.0)
    return np.arctan2(sine, cosine)
