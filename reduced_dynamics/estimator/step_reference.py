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
The explicit GLR bank of a wrench step: one signature per onset hypothesis.

The reference for :class:`~reduced_dynamics.estimator.step_test.WrenchStepTest`
(docs/step_test.md): the same onsets, statistics and isolation, with each
onset's signature ``D_k`` (dim x n) propagated through every propagation and
update (Willsky & Jones 1976, (S1)-(S3) of docs/step_test.md), so a sample costs
O(onsets n dim^2). Kept for the tests, which check that both take the same
steps, and for ``reduced-dynamics bench``, which times both in one run.
"""

from __future__ import annotations

from collections import deque
import math
from typing import Optional

import numpy as np
from reduced_dynamics.chi_square import chi2

from reduced_dynamics.estimator.step_test import (
    fit_steps, GLR_SPACING, GLR_WINDOW, NIS_TIME, OUTLIER, pose_statistic,
    POSE_STEP_HYPOTHESES, StepDetection)

__all__ = ['ExplicitStepTest']


class ExplicitStepTest:
    """
    GLR test of a step in the external wrench from a Kalman filter's innovations.

    A bank of onset hypotheses (see the module docstring); per hypothesis the
    signature D (dim x n), the information J (n x n) and the score b (n) are
    kept stacked, so one step costs a few matrix products whatever their number.
    """

    #: the filter's compiled row step (estimator/step_row.py) needs WrenchStepTest's
    #: arrays: with this reference the filter makes the step test's calls from Python
    active = False

    def __init__(self, n: int, significance: float, dim: Optional[int] = None) -> None:
        """
        Set up for wrenches of dimension ``n``; ``significance`` 0 turns it off.

        ``dim``: the filter's error-state dimension (3n; more with further states
        after w, e.g. the commanded wrench's gain and bias); w is at [2n, 3n).
        """
        self.n = n
        self.dim = 3 * n if dim is None else dim
        self.threshold = math.inf if significance <= 0.0 \
            else float(chi2.isf(significance, n))
        self._onsets: list[int] = []
        self._d = np.zeros((self.dim, 0))
        #: per hypothesis: information J (M x n x n) and score b (M x n), stacked
        self._j = np.zeros((0, n, n))
        self._b = np.zeros((0, n))
        self.last_statistic = 0.0
        #: exponential average of the NIS per measured coordinate (1 when the noise fits)
        self.nis_scale = 1.0
        self._stamp: Optional[int] = None
        self._dt = 0.0
        self._elapsed = 0.0
        #: no onset is opened before this stamp (the filter's start-up transient)
        self._settle_until: Optional[int] = None
        #: NIS above which a single innovation is left out of the evidence (chi2_m 1e-3)
        self._outlier = {m: float(chi2.isf(OUTLIER, m)) for m in (n, 2 * n)}
        #: the last measurements (Phi since the previous one, H, S, K, innovation), for
        #: the pose-step hypotheses, and the transition accumulated since the last one
        self._recent: deque = deque(maxlen=POSE_STEP_HYPOTHESES)
        self._identity = np.eye(self.dim)  # shared: _since is replaced, never modified
        self._since = self._identity
        #: detections not taken because a step of the pose measurement explained more
        self.pose_steps = 0

    def reset(self, settle_from_ns: Optional[int] = None) -> None:
        """
        Forget every hypothesis (after a detection or a filter restart).

        ``settle_from_ns``: the filter (re)starts from a broad prior there. No onset
        is opened for ``GLR_WINDOW`` s after it: while the prior is being forgotten the
        innovations are neither small nor linear in the error, which the test assumes
        (a false step 0.38 s after the start of a simulated spacecraft bag, seed 10).
        """
        if settle_from_ns is not None:
            self._settle_until = settle_from_ns + int(GLR_WINDOW * 1e9)
        self._onsets = []
        self._d = np.zeros((self.dim, 0))
        self._j = np.zeros((0, self.n, self.n))
        self._b = np.zeros((0, self.n))
        self._recent.clear()
        self._since = self._identity
        # nis_scale stays: it describes the sensors, not the hypotheses.

    def propagate(self, stamp_ns: int, transition: np.ndarray) -> None:
        """Carry the signatures over a propagation step; open a new onset when due."""
        if not math.isfinite(self.threshold):
            return
        n = self.n
        self._dt = 0.0 if self._stamp is None else max(stamp_ns - self._stamp, 0) * 1e-9
        self._stamp = stamp_ns
        if self._onsets:
            self._d = transition @ self._d
        if self._recent:
            self._since = transition @ self._since
        # Expire hypotheses older than the window; open one every GLR_SPACING s.
        window = int(GLR_WINDOW * 1e9)
        expired = 0
        while expired < len(self._onsets) and stamp_ns - self._onsets[expired] > window:
            expired += 1
        if expired:
            del self._onsets[:expired]
            self._j, self._b = self._j[expired:], self._b[expired:]
            self._d = self._d[:, expired * n:]
        if self._settle_until is not None and stamp_ns < self._settle_until:
            return
        if not self._onsets or stamp_ns - self._onsets[-1] >= int(GLR_SPACING * 1e9):
            fresh = np.zeros((self.dim, n))
            fresh[2 * n:3 * n] = np.eye(n)
            self._onsets.append(stamp_ns)
            self._j = np.concatenate((self._j, np.zeros((1, n, n))))
            self._b = np.concatenate((self._b, np.zeros((1, n))))
            self._d = np.hstack((self._d, fresh))

    def update(self, h: np.ndarray, s: np.ndarray, gain: np.ndarray,
               nu: np.ndarray) -> Optional[StepDetection]:
        """Take one accepted measurement (H, S, K, innovation); return a detection or None."""
        if not math.isfinite(self.threshold):
            return None
        n = self.n
        g = h @ self._d                        # signatures in the innovation, m x (n M)
        self._d = self._d - gain @ g
        # Kept for the pose-step hypotheses (a single large innovation included: a
        # re-fit is one).
        self._recent.append((self._since, h, s, gain, nu))
        self._since = self._identity
        # One solve for the innovation and every signature: S^-1 [nu, G].
        solved = np.linalg.solve(s, np.column_stack((nu, g)))
        nis_total = float(nu @ solved[:, 0])
        nis = nis_total / len(nu)
        m = len(nu)
        if nis_total > self._outlier.get(len(nu), math.inf):
            # One improbable innovation is an outlier (a pose stamped tens of ms off),
            # not the growing drift a step makes: it carries no evidence here.
            return None
        # A running mean over the first NIS_TIME seconds, then an exponential average.
        self._elapsed += self._dt
        horizon = min(self._elapsed, NIS_TIME)
        weight = 1.0 if horizon <= 0.0 else min(1.0, self._dt / horizon)
        self.nis_scale += weight * (nis - self.nis_scale)
        if not self._onsets:
            # Settling (or no onset yet): the NIS average still describes the sensors.
            return None
        scale = max(1.0, self.nis_scale)
        count = len(self._onsets)
        # Per hypothesis i: G_i (m x n) and S^-1 G_i, stacked as (M, m, n).
        g_stack = g.reshape(m, count, n).transpose(1, 0, 2)
        s_inv_g = solved[:, 1:].reshape(m, count, n).transpose(1, 0, 2)
        self._j = self._j + np.matmul(g_stack.transpose(0, 2, 1), s_inv_g)
        self._b = self._b + np.matmul(nu, s_inv_g)
        steps = fit_steps(self._j, self._b)
        statistics = np.einsum('ij,ij->i', self._b, steps) / scale
        statistics[~np.isfinite(statistics)] = -math.inf
        best_index = int(np.argmax(statistics))
        self.last_statistic = max(0.0, float(statistics[best_index]))
        statistic = float(statistics[best_index])
        if not statistic > self.threshold:
            return None
        if self._pose_statistic() / scale >= statistic:
            # The innovations are a step of the measured pose, not of the wrench.
            self.pose_steps += 1
            return None
        block = slice(best_index * n, (best_index + 1) * n)
        d, j, step = self._d[:, block], self._j[best_index], steps[best_index]
        return StepDetection(statistic, step, d @ step, d @ np.linalg.solve(j, d.T))

    def _pose_statistic(self) -> float:
        """Return the largest statistic of a pose step at a recent measurement."""
        return pose_statistic(self._recent, self.dim, self.n)
