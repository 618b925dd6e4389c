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
The GLR test of a wrench step (Willsky & Jones 1976) on anchored signatures.

docs/step_test.md derives it; equation numbers (S1)-(S9) refer to it. A step
Delta in w at onset theta leaves ``D_k Delta`` in the error state, with
``D_k = Psi(k, theta) E`` (S2), ``E = [0; 0; I]`` and Psi the filter's closed-loop
transition (``Phi`` at a propagation, ``I - K H`` at an update). Every onset's
signature is the *same* Psi applied to a different matrix: with the newest onset
A as anchor, ``D_i(k) = Psi(k, A) C_i`` and ``C_i = D^-_i(A)`` (S4). So per sample
only Psi (dim x dim) and the anchor's information ``Omega = sum L^T S^-1 L`` and
score ``beta = sum L^T S^-1 nu``, ``L = H Psi``, are propagated (S5), whatever
the number of onsets; each onset's score is ``b_i = b0_i + C_i^T beta`` (S6).
Its information ``J_i = J0_i + C_i^T Omega C_i`` costs dim^2 n: it is formed only
where the bound ``T_i <= b_i^T J0_i^-1 b_i`` (S8; information only grows) cannot
rule the onset out, best bound first (branch and bound), so the detection and
the step chosen are those of the explicit bank (estimator/step_reference.py),
which the tests check. When a new onset opens, the anchor moves to it: every
C_i, J0_i, b0_i absorbs the segment (S7, the only hypotheses x state cost, once
per ``spacing``).

What is tested is unchanged: onsets from ``window`` s after a (re)start (the prior
being forgotten is not the linear-Gaussian error assumed); T divided by the
innovations' mean NIS per coordinate when it exceeds 1 (noisier sensors than
assumed do not read as steps); an innovation beyond the chi2_m 1e-3 quantile left
out of the evidence (a pose stamped tens of ms off); and a detection taken only if
no step of the measured pose (a mocap re-fit, (S9)) explains the innovations
better, else counted in ``pose_steps``.
"""

from __future__ import annotations

import math
from typing import NamedTuple, Optional, Sequence

import numpy as np
from reduced_dynamics.chi_square import chi2
from reduced_dynamics.estimator.step_state import (COUNT, NEXT, RECENT, SINCE_IDENTITY,
                                                   SPACING, StepTestState, WINDOW)
# The pose-step hypotheses' count, defined with the ring that keeps their measurements.
from reduced_dynamics.estimator.step_state import POSE_STEP_HYPOTHESES  # noqa: F401

#: Seconds between hypothesised step onsets of the GLR test, and how long each is followed.
#: An onset hypothesised delta after the true one misses the information of the first
#: delta seconds, which for a velocity ramp grows as tau^3 (tau^5 for positions): at
#: 0.125 s spacing a step flagged after ~0.1 s could have lost most of it. 25 ms keeps
#: the loss small at the 0.1 s scale (the window stays 1 s for small steps).
GLR_SPACING = 0.025
GLR_WINDOW = 1.0
#: Onset hypotheses alive at once (GLR_WINDOW / GLR_SPACING).
GLR_HYPOTHESES = 40
#: Probability below which one innovation is an outlier to the GLR test (not evidence).
OUTLIER = 1e-3
#: Time constant [s] of the average NIS per coordinate that scales the GLR statistic.
NIS_TIME = 10.0


class StepDetection(NamedTuple):
    """A detected wrench step: its size (n), the error-state correction and covariance."""

    statistic: float
    step: np.ndarray
    correction: np.ndarray
    covariance: np.ndarray


class WrenchStepTest(StepTestState):
    """
    GLR test of a step in the external wrench from a Kalman filter's innovations.

    Onsets every ``spacing`` s, each followed for ``window`` s, on signatures
    anchored at the newest onset (module docstring): the per-sample cost is
    O(dim^2 m + onsets n dim), the explicit bank's O(onsets n dim^2).
    """

    def __init__(self, n: int, significance: float, dim: Optional[int] = None,
                 spacing: float = GLR_SPACING, window: float = GLR_WINDOW) -> None:
        """
        Set up for wrenches of dimension ``n``; ``significance`` 0 turns it off.

        ``dim``: the filter's error-state dimension (3n; more with further states
        after w, e.g. the commanded wrench's gain and bias); w is at [2n, 3n).
        """
        self.n = n
        self.dim = dim = 3 * n if dim is None else dim
        self.threshold = math.inf if significance <= 0.0 \
            else float(chi2.isf(significance, n))
        if math.isfinite(self.threshold):
            # Compiled on first use (numba's import and its disk cache cost ~1 s).
            from reduced_dynamics.estimator import step_kernels
            self._kernels = step_kernels
        capacity = int(math.ceil(window / spacing)) + 2
        #: NIS above which a single innovation is left out of the evidence (chi2_m 1e-3)
        self._outlier = {m: float(chi2.isf(OUTLIER, m)) for m in (n, 2 * n)}
        super().__init__(n, dim, capacity, int(round(window * 1e9)),
                         int(round(spacing * 1e9)), self.threshold, self._outlier[n],
                         self._outlier[2 * n], NIS_TIME)
        self._spacing_ns = int(self._ints[SPACING])
        self._window_ns = int(self._ints[WINDOW])
        #: the largest bound on the statistic at the last update (exact when a step
        #: was detected); onsets whose statistic was formed exactly, in total
        self.last_statistic = 0.0
        self.evaluated = 0
        #: detections not taken because a step of the pose measurement explained more
        self.pose_steps = 0

    @property
    def onsets(self) -> int:
        """Return the number of onset hypotheses alive."""
        return self._count

    def reset(self, settle_from_ns: Optional[int] = None) -> None:
        """
        Forget every hypothesis (after a detection or a filter restart).

        ``settle_from_ns``: the filter (re)starts from a broad prior there. No onset
        is opened for ``window`` s after it: while the prior is being forgotten the
        innovations are neither small nor linear in the error, which the test assumes
        (a false step 0.38 s after the start of a simulated spacecraft bag, seed 10).
        """
        if settle_from_ns is not None:
            self._settle_until = settle_from_ns + self._window_ns
        ints = self._ints
        ints[COUNT] = ints[RECENT] = ints[NEXT] = 0
        ints[SINCE_IDENTITY] = 1
        # nis_scale stays: it describes the sensors, not the hypotheses.

    def propagate(self, stamp_ns: int, transition: np.ndarray) -> None:
        """Carry the anchor's Psi over a propagation step; open a new onset when due."""
        if not math.isfinite(self.threshold):
            return
        self._dt = 0.0 if self._stamp is None else max(stamp_ns - self._stamp, 0) * 1e-9
        self._stamp = stamp_ns
        if self._count:
            self._psi[:] = transition @ self._psi
        ints = self._ints
        if ints[RECENT]:
            # The first step since a measurement: Phi itself (no product with 1).
            if ints[SINCE_IDENTITY]:
                self._since_buffer[:] = transition
                ints[SINCE_IDENTITY] = 0
            else:
                self._since_buffer[:] = transition @ self._since_buffer
        # Expire hypotheses older than the window.
        count = self._count
        expired = 0
        oldest = stamp_ns - self._window_ns
        while expired < count and self._onsets[expired] < oldest:
            expired += 1
        if expired:
            keep = slice(expired, count)
            for array in (self._onsets, self._c, self._b0, self._j0, self._bound_inv,
                          self._bounded):
                array[:count - expired] = array[keep]
            self._count = count = count - expired
        if self._settle_until is not None and stamp_ns < self._settle_until:
            return
        if not count or stamp_ns - self._onsets[count - 1] >= self._spacing_ns:
            if count:
                self._kernels.fold(self._c, self._b0, self._j0, self._bound_inv,
                                   self._bounded, count, self._psi, self._omega, self._beta)
            self._onsets[count] = stamp_ns
            self._c[count] = self._e
            self._b0[count] = 0.0
            self._j0[count] = 0.0
            self._bounded[count] = False
            self._count = count + 1
            self._psi[:] = self._identity
            self._omega[:] = 0.0
            self._beta[:] = 0.0

    def update(self, h: np.ndarray, s: np.ndarray, gain: np.ndarray,
               nu: np.ndarray) -> Optional[StepDetection]:
        """Take one accepted measurement (H, S, K, innovation); return a detection or None."""
        if not math.isfinite(self.threshold):
            return None
        # Kept for the pose-step hypotheses (a single large innovation included: a
        # re-fit is one).
        self._keep(h, s, gain, nu)
        m = len(nu)
        outlier = self._outlier.get(m, math.inf)
        if self._count:
            # Absorb, the NIS average and the evaluation below in one compiled call.
            _, evidence, self.nis_scale, self._elapsed, best, statistic, top, evaluated = \
                self._kernels.absorb_evaluate(
                    np.ascontiguousarray(h), np.ascontiguousarray(s),
                    np.ascontiguousarray(gain), np.ascontiguousarray(nu), self._psi,
                    self._omega, self._beta, outlier, self._c, self._b0, self._j0,
                    self._bound_inv, self._bounded, self._count, self._score,
                    self.threshold, self.nis_scale, self._elapsed, self._dt, NIS_TIME)
            if not evidence:
                return None
            return self._evaluated(best, statistic, top, evaluated)
        # Settling (or no onset yet): the NIS average still describes the sensors.
        nis_total = float(nu @ np.linalg.solve(s, nu))
        if not nis_total <= outlier:
            # One improbable innovation is an outlier (a pose stamped tens of ms off),
            # not the growing drift a step makes: it carries no evidence here.
            return None
        # A running mean over the first NIS_TIME seconds, then an exponential average
        # (absorb_evaluate's arithmetic, in the same order).
        self._elapsed += self._dt
        horizon = min(self._elapsed, NIS_TIME)
        weight = 1.0 if horizon <= 0.0 else min(1.0, self._dt / horizon)
        self.nis_scale += weight * (nis_total / m - self.nis_scale)
        return None

    @property
    def active(self) -> bool:
        """Return whether the test runs (its significance is above 0)."""
        return math.isfinite(self.threshold)

    def _evaluated(self, best: int, statistic: float, top: float,
                   evaluated: int) -> Optional[StepDetection]:
        """Take the evaluation of the onsets (best, its statistic); return a detection."""
        scale = max(1.0, self.nis_scale)
        self.evaluated += evaluated
        self.last_statistic = top if best < 0 or not statistic > self.threshold \
            else statistic
        if best < 0 or not statistic > self.threshold:
            return None
        if self._pose_statistic() / scale >= statistic:
            # The innovations are a step of the measured pose, not of the wrench.
            self.pose_steps += 1
            return None
        d = self._psi @ self._c[best]
        j = self._j0[best] + self._c[best].T @ self._omega @ self._c[best]
        step = np.linalg.solve(j, self._score[best])
        return StepDetection(statistic, step, d @ step, d @ np.linalg.solve(j, d.T))

    def _pose_statistic(self) -> float:
        """Return the largest statistic of a pose step at a recent measurement (S9)."""
        return pose_statistic(self.kept(), self.dim, self.n)


def pose_statistic(recent: Sequence, dim: int, n: int) -> float:
    """
    Return the largest statistic b_F^T J_F^-1 b_F of a pose step at a recent measurement.

    The signature of a step of the measured pose (S9), run over the kept
    measurements (Phi since the previous one, H, S, K, innovation) with an onset
    opened at each (E = 0 there, so its step enters through B alone).
    """
    e = np.zeros((dim, 0))
    j, b = np.zeros((0, n, n)), np.zeros((0, n))
    for transition, h, s, gain, nu in recent:
        e = np.hstack((transition @ e, np.zeros((dim, n))))
        j = np.concatenate((j, np.zeros((1, n, n))))
        b = np.concatenate((b, np.zeros((1, n))))
        f = h @ e
        f.reshape(len(nu), -1, n)[:n] += np.eye(n)[:, None, :]
        e = e - gain @ f
        solved = np.linalg.solve(s, np.column_stack((nu, f)))
        count = e.shape[1] // n
        f_stack = f.reshape(len(nu), count, n).transpose(1, 0, 2)
        s_inv_f = solved[:, 1:].reshape(len(nu), count, n).transpose(1, 0, 2)
        j = j + np.matmul(f_stack.transpose(0, 2, 1), s_inv_f)
        b = b + np.matmul(nu, s_inv_f)
    statistics = np.einsum('ij,ij->i', b, fit_steps(j, b))
    finite = statistics[np.isfinite(statistics)]
    return float(finite.max()) if len(finite) else -math.inf


def fit_steps(j: np.ndarray, b: np.ndarray) -> np.ndarray:
    """
    Return each hypothesis' maximum-likelihood step J^-1 b (M x n), NaN where J is singular.

    A hypothesis opened at this update has J = 0 (its step is not yet in the
    innovation): it is left out of the stacked solve, which is tried whole first
    and hypothesis by hypothesis if some J is singular.
    """
    steps = np.full(b.shape, math.nan)
    seen = np.flatnonzero(np.abs(j).sum(axis=(1, 2)) > 0.0)
    if not len(seen):
        return steps
    try:
        steps[seen] = np.linalg.solve(j[seen], b[seen][..., None])[..., 0]
    except np.linalg.LinAlgError:
        for i in seen:
            try:
                steps[i] = np.linalg.solve(j[i], b[i])
            except np.linalg.LinAlgError:
                continue
    return steps
