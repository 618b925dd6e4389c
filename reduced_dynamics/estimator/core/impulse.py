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
The multi-scale impulse test's smaller kernels, compiled (numba).

:class:`~reduced_dynamics.estimator.multiscale.MultiScaleTest` compares the
filtered momentum with its value one window ago, for every window of its bank
(``d_L = mu(t) - mu(t - L)``, ``V_L = P_mu(t) + P_mu(t - L)``: core/bank_windows.py,
in core/bank_step.py's one call per update). Here: the null calibration of the
statistics (:func:`calibrate`, and :func:`calibrated_best`, the rule the bank's
call applies), and the measured momentum of a twist with its covariance and
the centre of mass (:func:`twist_momentum`, :func:`measured_momentum_se3`) that the
block test takes; the same elementwise expressions in the same order as the numpy
code they replaced (test_multiscale_kernels.py, test_row_kernels.py).
"""

import math

import numpy as np
from numba import njit


@njit(cache=True, inline='always')
def calibrated_best(rows: np.ndarray, statistics: np.ndarray, above: np.ndarray,
                    inflation: np.ndarray, median: float, rate: float,
                    learn: bool) -> tuple[int, float]:
    """
    Calibrate the filtered bank's statistics in place; return the best covered one.

    ``statistics``: T_L per window, 0 where not covered (``rows`` < 0); each becomes
    T_L / ``inflation``, and ``learn`` first moves ``above`` towards T_L > ``median``
    where T_L > 0 (:func:`calibrate_into`). Returns (its index among the covered windows,
    its value) as ``np.argmax`` picks it: the first largest, or the first NaN; (-1, 0.0)
    when none is covered. ``bank_step.update`` applies it to the filtered bank, inlined
    (``inline='always'``: as cheap to compile as the copy of it that update held before).
    """
    calibrate_into(statistics, statistics, above, inflation, median, rate, learn)
    best, value, k = -1, 0.0, 0
    for w in range(rows.shape[0]):
        if rows[w] < 0:
            continue
        v = statistics[w]
        if best < 0 or (not math.isnan(value) and (v > value or math.isnan(v))):
            best, value = k, v
        k += 1
    return best, value


@njit(cache=True)
def calibrate(raw: np.ndarray, above: np.ndarray, inflation: np.ndarray, median: float,
              rate: float, learn: bool) -> np.ndarray:
    """
    Return ``raw`` / ``inflation``; if ``learn``, first move ``above`` towards raw > median.

    ``above``: the running fraction of quiet updates above the chi2_n median, per
    window, learnt where the window is covered (raw > 0) at ``rate`` per update.
    """
    out = np.empty_like(raw)
    calibrate_into(raw, out, above, inflation, median, rate, learn)
    return out


@njit(cache=True, inline='always')
def calibrate_into(raw: np.ndarray, out: np.ndarray, above: np.ndarray,
                   inflation: np.ndarray, median: float, rate: float, learn: bool) -> None:
    """Write :func:`calibrate`'s result into ``out`` (which may be ``raw`` itself)."""
    for w in range(raw.shape[0]):
        value = raw[w]
        if learn and value > 0.0:
            above[w] += rate * ((1.0 if value > median else 0.0) - above[w])
        out[w] = value / inflation[w]


@njit(cache=True)
def twist_momentum(ad_inverse: np.ndarray, locked: np.ndarray, pi: np.ndarray,
                   twist_cov: np.ndarray, joint_cov: np.ndarray, pose_cov: np.ndarray,
                   kirillov: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return mu = Ad_{g^-1}^T pi, its white covariance and its pose-error one (multiscale)."""
    to_world = ad_inverse.T
    white = to_world @ locked @ (twist_cov + joint_cov) @ locked.T @ to_world.T
    w = to_world @ kirillov
    return to_world @ pi, white, w @ np.ascontiguousarray(pose_cov) @ w.T


@njit(cache=True)
def centre_of_mass_se3(locked: np.ndarray, rotation: np.ndarray, translation: np.ndarray,
                       pose_cov: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Return the measured centre of mass in the world, its covariance, the mass (SE(3))."""
    mass = locked[0, 0]
    c = np.array([locked[1, 5], locked[2, 3], locked[0, 4]]) / mass
    skew = np.array([[0.0, -c[2], c[1]], [c[2], 0.0, -c[0]], [-c[1], c[0], 0.0]])
    jacobian = np.zeros((3, 6))
    jacobian[:, :3] = rotation
    jacobian[:, 3:] = -rotation @ skew
    world = translation + rotation @ c
    return world, jacobian @ np.ascontiguousarray(pose_cov) @ jacobian.T, mass


@njit(cache=True)
def kirillov_form(structure: np.ndarray, covector: np.ndarray) -> np.ndarray:
    """
    Return W[a, b] = sum_c structure[a, c, b] covector[c] (BaseGroup.coadjoint_form).

    Summed from +0.0 in the order of c, as numpy's einsum does: with the structure
    constants of the base groups (0 and +-1, at most one non-zero term per entry)
    every entry is exact, zero signs included (test_row_kernels.py).
    """
    n = covector.shape[0]
    out = np.empty((n, n))
    for a in range(n):
        for b in range(n):
            acc = 0.0
            for c in range(n):
                acc += structure[a, c, b] * covector[c]
            out[a, b] = acc
    return out


@njit(cache=True)
def measured_momentum_se3(ad_inverse: np.ndarray, locked: np.ndarray, twist: np.ndarray,
                          connection_qd: np.ndarray, twist_cov: np.ndarray,
                          joint_cov: np.ndarray, pose_cov: np.ndarray, structure: np.ndarray,
                          com_locked: np.ndarray, rotation: np.ndarray,
                          translation: np.ndarray, com_pose_cov: np.ndarray) -> tuple:
    """
    Return measured_momentum.twist_momentum's and :func:`centre_of_mass_se3`'s results in one call.

    A measured twist of an SE(3) base gives both per row (measured_momentum.twist_momenta):
    pi = I (xi + A qbar_dot), its Kirillov form and the two kernels in one dispatch,
    the same operations.
    """
    pi = locked @ (twist + connection_qd)
    mu, white, common = twist_momentum(ad_inverse, locked, pi, twist_cov, joint_cov,
                                       pose_cov, kirillov_form(structure, pi))
    world, cov, mass = centre_of_mass_se3(com_locked, rotation, translation, com_pose_cov)
    return mu, white, common, world, cov, mass
