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
Physical gains of the commanded wrench: the constraint k > 0 and identifiability.

The commanded-wrench filter (filter.py, docs/commanded_wrench.md) has the error
state (dg, dmu, dw, dk, db), 5n, and the mean x = (mu, w, k, b).

**Constraint.** A thruster delivers a non-negative fraction of its command, so
``k_i >= GAIN_FLOOR``. After an update whose mean leaves that range, the mean
is projected onto it in the metric of P^-1 (Simon & Chia 2002, "Kalman
filtering with state equality constraints", eq. 11; for inequalities the
active set: the axes below the floor are held at it, Simon 2010 §2.4)::

    x~ = x - P D^T (D P D^T)^-1 (D x - d)

with D selecting the active gains and d the floor: the most probable state on
the constraint under the Gaussian posterior. The correction moves the
correlated states (the bias, the disturbance) with the gain, so k u + b + w,
what the data pinned, is kept. P is left as it is (Simon & Chia: the projected
estimate's error covariance is no larger; the projected P is singular and would
stop the filter from leaving the floor).

**Identifiability.** A gain the data cannot separate is reported as
``unidentified`` (not a number): its posterior sigma is above
``IDENTIFIED_SIGMA_RATIO`` of its prior's (the data brought less than three
times the prior's information), or its multiple correlation with the bias and
the disturbance is above ``IDENTIFIED_CORRELATION`` (only k u + b + w is pinned,
as when the command barely changes: a still robot held against a tilt). The
same test applies to a bias (its correlation taken with the gains and the
disturbance).
"""

from __future__ import annotations

from typing import Optional

import numpy as np

#: Lowest gain a thruster is given: 1 % of its command (a dead thruster, for the filter).
GAIN_FLOOR = 0.01
#: A gain (bias) whose posterior sigma exceeds this fraction of its prior's is unidentified:
#: 0.5 means the data's information is below 3x the prior's (1/s^2 = 1/s0^2 + data).
IDENTIFIED_SIGMA_RATIO = 0.5
#: A gain (bias) whose multiple correlation with the bias (gain) and the disturbance exceeds
#: this is unidentified: over 80 % of its variance is the trade-off with those states.
#: Measured: 0.99 for a still robot held against a force, below 0.1 when the command varies.
IDENTIFIED_CORRELATION = 0.9


def project_gains(x: np.ndarray, p: np.ndarray, n: int,
                  floor: float = GAIN_FLOOR) -> Optional[np.ndarray]:
    """
    Return the error-state correction projecting the gains onto k >= ``floor`` (None: inside).

    Active set: the axes below the floor are put on it; the projection can push
    another gain below, which then joins (at most n passes).
    """
    gains = x[2 * n:3 * n]
    active = gains < floor
    if not active.any():
        return None
    correction = np.zeros(p.shape[0])
    for _ in range(n):
        index = 3 * n + np.flatnonzero(active)
        # D x - d, D selecting the active gains (the correction so far included).
        excess = gains[active] + correction[index] - floor
        block = p[np.ix_(index, index)]
        correction = correction - p[:, index] @ np.linalg.solve(block, excess)
        below = gains + correction[3 * n:4 * n] < floor - 1e-12
        if not (below & ~active).any():
            break
        active |= below
    return correction


def _multiple_correlation(p: np.ndarray, target: int, others) -> float:
    """Return the multiple correlation of error coordinate ``target`` with ``others``."""
    index = np.concatenate(([target], others))
    block = p[np.ix_(index, index)]
    try:
        conditional = 1.0 / np.linalg.inv(block)[0, 0]
    except np.linalg.LinAlgError:
        return 1.0
    r2 = 1.0 - conditional / block[0, 0]
    return float(np.sqrt(min(max(r2, 0.0), 1.0)))


def _known(p: np.ndarray, n: int, prior_sigma: np.ndarray, states: np.ndarray,
           others: np.ndarray) -> np.ndarray:
    """Return per state of ``states`` (error coordinates) whether it is identified."""
    sigma = np.sqrt(np.maximum(np.diag(p)[states], 0.0))
    wide = sigma > IDENTIFIED_SIGMA_RATIO * prior_sigma
    tied = np.array([_multiple_correlation(p, i, others) for i in states])
    return ~(wide | (tied > IDENTIFIED_CORRELATION))


def gains_identified(p: np.ndarray, n: int, prior_sigma: np.ndarray) -> np.ndarray:
    """Return per axis whether the gain is identified; ``prior_sigma``: of (k, b), 2n."""
    return _known(p, n, prior_sigma[:n], np.arange(3 * n, 4 * n),
                  np.arange(4 * n, 5 * n).tolist() + list(range(2 * n, 3 * n)))


def identified(p: np.ndarray, n: int, prior_sigma: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """
    Return per axis whether gain and bias are identified: two boolean arrays.

    ``prior_sigma``: the prior sigmas of (k, b), 2n. A bias's correlation is
    taken with the gains and the disturbance.
    """
    biases = _known(p, n, prior_sigma[n:], np.arange(4 * n, 5 * n),
                    np.arange(2 * n, 4 * n))
    return gains_identified(p, n, prior_sigma), biases


def mismatch_covariance(p: np.ndarray, n: int, to_world: np.ndarray, command: np.ndarray,
                        unidentified: np.ndarray) -> np.ndarray:
    """
    Return the covariance of the gain error on the command, in the world (n x n).

    ``Ad_{g^-1}^T diag(u) P_kk diag(u) Ad_{g^-1}^T^T`` over the ``unidentified``
    axes (``to_world``: Ad_{g^-1}^T): the wrench an unidentified gain may be
    off by, which the event test must not read as an external wrench.
    """
    jacobian = to_world * np.where(unidentified, command, 0.0)
    block = p[3 * n:4 * n, 3 * n:4 * n]
    return jacobian @ block @ jacobian.T
