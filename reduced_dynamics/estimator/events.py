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
Thruster/contact events from the filter's own statistics.

Without external wrench mu is constant (Noether) and the filter's wrench
estimate w is consistent with zero: its significance ``s = w^T P_ww^-1 w`` is
then chi-square with n degrees of freedom. An event starts when s exceeds the
chi2_n quantile at the false-alarm probability ``event_significance``; it ends
after ``hold`` seconds with s below the 99 % quantile, and the reduced model
is then re-reduced at the new momentum. The test is dimensionless: the same
default works for a 16 kg testbed and a 500 kg spacecraft.

The random-walk w needs time to grow after a thruster switches, so the test on
w alone lags. :class:`WrenchStepTest` is a generalised-likelihood-ratio test
(Willsky & Jones 1976) of a *step* Delta in w at an unknown time theta, run on
the filter's own innovations: after the step the error state carries
``D_k Delta`` with ``D_theta = [0; 0; 1]``, ``D^-_k = Phi_k D_{k-1}``,
``G_k = H_k D^-_k`` (the step's signature in the innovation) and
``D_k = D^-_k - K_k G_k``. With ``J = sum G^T S^-1 G`` and ``b = sum G^T S^-1 nu``
the log-likelihood ratio of the step's maximum-likelihood size ``J^-1 b`` is
``T/2``, ``T = b^T J^-1 b``, chi-square with n degrees of freedom without a
step. Onsets are hypothesised every ``GLR_SPACING`` s and each is followed for
``GLR_WINDOW`` s. A step is detected when T exceeds the same chi2_n quantile
as the wrench test; the filter then takes it (Willsky-Jones compensation:
``x += D Delta``, ``P += D J^-1 D^T``), so w follows a thruster switching on or
off at once instead of through its random walk. Without a step, the
per-sample false-alarm probability is at most ``GLR_HYPOTHESES`` times
``event_significance`` (a union bound over the hypotheses alive). That holds
when the noise parameters fit; when the sensors are noisier than assumed, the
innovations' mean NIS per coordinate (``nis_scale``, an exponential average
over ``NIS_TIME`` s, a running mean before, floored at 1) exceeds 1 and T is divided by it, so an
underestimated noise does not read as steps. A single innovation beyond the
chi2_m 1e-3 quantile (a pose stamped tens of milliseconds off) is left out of
the evidence: a step shows as a drift of the innovations, growing with time.

Before a detected step is taken it is told apart from a step of the *pose
measurement* (fault isolation, as in Willsky & Jones): motion capture re-fits
its rigid body when a marker drops out or returns, and the measured pose then
steps by a constant body-frame offset beta (``g_meas = g delta``: the residual
carries log delta). Its signature has a direct term, ``F_k = H_k E^-_k + B`` with
``B = [I; 0]`` (the pose rows), ``E_k = E^-_k - K_k F_k``, ``E^-_{k+1} = Phi_k E_k``,
``E^-_theta = 0``, and its statistic ``T_pose = b_F^T J_F^-1 b_F`` is computed, when
a step is detected, for an onset at each of the last ``POSE_STEP_HYPOTHESES``
measurements (kept with the transitions between them: no cost until then). A wrench step
is taken only if it explains the innovations better than the best pose step
(``T > T_pose``); otherwise it is counted as vetoed (``pose_steps``). Without it a
re-fit too small for the innovation gate (4 mrad at 9.5 s of the freeflyer2 PD
recording, replayed with 1 mrad pose noise) was taken as an 11 N wrench step.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
import math
from typing import NamedTuple, Optional

import numpy as np
from reduced_dynamics.chi_square import chi2

#: Seconds after an event's end during which its mu_after follows the filter.
SETTLE = 1.0
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
#: Measurements back at which a step of the pose measurement is hypothesised (one onset
#: each): a re-fit is seen at once, and a detection comes within a few samples of it.
POSE_STEP_HYPOTHESES = 32


class StepDetection(NamedTuple):
    """A detected wrench step: its size (n), the error-state correction and covariance."""

    statistic: float
    step: np.ndarray
    correction: np.ndarray
    covariance: np.ndarray


class WrenchStepTest:
    """
    GLR test of a step in the external wrench from a Kalman filter's innovations.

    A bank of onset hypotheses (see the module docstring); per hypothesis the
    signature D (dim x n), the information J (n x n) and the score b (n) are
    kept stacked, so one step costs a few matrix products whatever their number.
    """

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
        steps = _fit(self._j, self._b)
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
        """
        Return the largest statistic b_F^T J_F^-1 b_F of a pose step at a recent measurement.

        The recursion of the module docstring, run over the kept measurements with an
        onset opened at each (E = 0 there, so its step enters through B alone).
        """
        n = self.n
        e = np.zeros((self.dim, 0))
        j, b = np.zeros((0, n, n)), np.zeros((0, n))
        for transition, h, s, gain, nu in self._recent:
            e = np.hstack((transition @ e, np.zeros((self.dim, n))))
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
        statistics = np.einsum('ij,ij->i', b, _fit(j, b))
        finite = statistics[np.isfinite(statistics)]
        return float(finite.max()) if len(finite) else -math.inf


def _fit(j: np.ndarray, b: np.ndarray) -> np.ndarray:
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


@dataclass
class MomentumEvent:
    """A detected external-wrench event and the momentum change across it."""

    start_ns: int
    end_ns: Optional[int] = None
    mu_before: Optional[np.ndarray] = None
    mu_after: Optional[np.ndarray] = None
    peak_wrench: float = 0.0
    peak_significance: float = 0.0

    @property
    def impulse(self) -> Optional[np.ndarray]:
        """Return mu_after - mu_before (world frame), once the event has ended."""
        if self.mu_before is None or self.mu_after is None:
            return None
        return self.mu_after - self.mu_before


@dataclass
class EventDetector:
    """Chi-square test of the wrench estimate with hysteresis and a hold time."""

    dim: int
    significance: float
    hold: float
    events: list[MomentumEvent] = field(default_factory=list)
    _quiet_mu: Optional[np.ndarray] = None
    _quiet_since: Optional[int] = None
    _changed: bool = False

    def __post_init__(self) -> None:
        """Set the start and end thresholds from the chi-square quantiles."""
        self.start_threshold = float(chi2.isf(self.significance, self.dim))
        self.end_threshold = float(chi2.isf(0.01, self.dim))
        # Below the median w is indistinguishable from zero: mu there is "before".
        self.rest_threshold = float(chi2.isf(0.5, self.dim))

    @property
    def in_event(self) -> bool:
        """Return whether an event is under way."""
        return bool(self.events) and self.events[-1].end_ns is None

    def take_level_change(self) -> bool:
        """Return True once after an event ended (re-reduce at the new momentum)."""
        changed, self._changed = self._changed, False
        return changed

    def update(self, stamp_ns: int, mu: np.ndarray, wrench_norm: float,
               significance: float, step: bool = False) -> None:
        """
        Feed one filtered sample: mu, |w|, s = w^T P_ww^-1 w, and a GLR step (True: found).

        A step starts an event as s above its threshold does (the step test reacts
        to a thruster switching on before the random-walk w has grown).
        """
        event = self.events[-1] if self.in_event else None
        if event is None and self.events and significance < self.end_threshold:
            last = self.events[-1]
            if (stamp_ns - last.end_ns) * 1e-9 <= SETTLE:
                # The filter's mu still converges after the wrench has gone: the
                # impulse keeps following it for SETTLE seconds (or to the next event).
                last.mu_after = mu.copy()
        if event is None and step and self.events and \
                (stamp_ns - self.events[-1].end_ns) * 1e-9 <= SETTLE:
            # A step while the filter settles after an event (the compensation of its
            # own overshoot) belongs to that event: re-open it, its mu_before stays.
            event = self.events[-1]
            event.end_ns = None
            self._changed = False
        if event is None:
            if significance > self.start_threshold or step:
                before = self._quiet_mu if self._quiet_mu is not None else mu
                self.events.append(MomentumEvent(stamp_ns, mu_before=before.copy(),
                                                 peak_wrench=wrench_norm,
                                                 peak_significance=significance))
                self._quiet_since = None
            elif significance < self.rest_threshold:
                self._quiet_mu = mu
            return
        event.peak_wrench = max(event.peak_wrench, wrench_norm)
        event.peak_significance = max(event.peak_significance, significance)
        if significance >= self.end_threshold or step:
            self._quiet_since = None
            return
        if self._quiet_since is None:
            self._quiet_since = stamp_ns
        if (stamp_ns - self._quiet_since) * 1e-9 >= self.hold:
            event.end_ns = stamp_ns
            event.mu_after = mu.copy()
            self._quiet_mu = mu
            self._changed = True
