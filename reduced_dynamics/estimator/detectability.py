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
How soon any test can flag a wrench step, from the sensors alone.

A step of body acceleration a (per coordinate of the base group's algebra,
``I^-1`` times the body wrench) at t = 0 moves the measured pose by a t^2 / 2
and the measured twist by a t. With the state before the step known exactly
(the most favourable case) the samples at t_k = k / f up to tau carry the
non-centrality

    lambda(tau) = sum_k (a t_k^2 / 2)^T R_pose^-1 (a t_k^2 / 2) + (a t_k)^T R_twist^-1 (a t_k)

(continuous limits a^2 f tau^5 / (20 sigma^2) and a^2 f tau^3 / (3 sigma_v^2)).
A chi-square test at the event threshold cannot, in the median, flag the step
before lambda reaches that threshold: :func:`detection_bound`. A filter that
also lets the wrench wander (its random walk) explains part of a step by it and
needs longer.
"""

from __future__ import annotations

import math
from typing import Optional, Sequence

import numpy as np
from reduced_dynamics.chi_square import chi2


def step_information(acceleration: Sequence[float], tau: float, rate: float,
                     pose_sigma: Sequence[float],
                     twist_sigma: Optional[Sequence[float]] = None) -> float:
    """
    Return lambda(tau): the information on a body-acceleration step after ``tau`` s.

    ``acceleration``, ``pose_sigma`` and ``twist_sigma`` (None: pose only) per
    coordinate of the algebra (x, y, yaw for SE(2); linear then angular for
    SE(3)); ``rate`` the base-measurement rate [Hz].
    """
    a = np.asarray(acceleration, dtype=float)
    t = np.arange(1, int(math.floor(tau * rate + 1e-9)) + 1) / rate
    pose = np.sum((a / np.asarray(pose_sigma, dtype=float)) ** 2) * np.sum(0.25 * t ** 4)
    twist = 0.0 if twist_sigma is None else \
        np.sum((a / np.asarray(twist_sigma, dtype=float)) ** 2) * np.sum(t ** 2)
    return float(pose + twist)


def detection_bound(acceleration: Sequence[float], rate: float, pose_sigma: Sequence[float],
                    twist_sigma: Optional[Sequence[float]] = None,
                    significance: float = 1e-6, limit: float = 10.0) -> float:
    """
    Return the first sample time tau [s] at which lambda(tau) reaches the chi2_n quantile.

    ``significance``: the event test's false-alarm probability (``event_significance``);
    n = len(acceleration). ``math.inf`` when not reached within ``limit`` s.
    """
    threshold = float(chi2.isf(significance, len(acceleration)))
    for k in range(1, int(limit * rate) + 1):
        if step_information(acceleration, k / rate, rate, pose_sigma, twist_sigma) \
                >= threshold:
            return k / rate
    return math.inf


def impulse_bound(acceleration: Sequence[float], duration: float, rate: float,
                  pose_sigma: Sequence[float],
                  twist_sigma: Optional[Sequence[float]] = None,
                  significance: float = 1e-6) -> float:
    """
    Return the smallest scale c of ``acceleration`` a push of ``duration`` s needs to be flagged.

    The bound above turned around: a constant body acceleration c a over the push
    carries lambda(duration) = c^2 lambda_1(duration) by its end, which reaches the
    chi2_n quantile at c = sqrt(quantile / lambda_1). The push's velocity change is
    then c a duration (times the inertia: the impulse). A test that also reads the
    samples after the push (the multi-scale test's longer windows) can flag less.
    """
    unit = step_information(acceleration, duration, rate, pose_sigma, twist_sigma)
    if unit <= 0.0:
        return math.inf
    return math.sqrt(float(chi2.isf(significance, len(acceleration))) / unit)


def measured_momentum_bound(momentum_cov: np.ndarray, direction: Sequence[float], window: float,
                            rate: float, significance: float = 1e-6) -> float:
    """
    Return the impulse along ``direction`` the block test needs to reach its threshold.

    The test of :class:`~reduced_dynamics.estimator.momentum_blocks.MomentumBlocks` at
    window L compares the means of two blocks of L s of measured momenta, each sample
    with covariance ``momentum_cov`` (n x n) at ``rate`` Hz: V = 2 C / (L f). A pulse
    J u inside the gap gives the non-centrality J^2 u^T V^-1 u, which reaches the
    chi2_n quantile at J = sqrt(quantile / u^T V^-1 u). What the measured twists tell
    about a push of up to L s; the position samples, which :func:`impulse_bound`
    counts, are not used by this test.
    """
    cov = np.asarray(momentum_cov, dtype=float)
    unit = np.asarray(direction, dtype=float)
    unit = unit / np.linalg.norm(unit)
    information = float(unit @ np.linalg.solve(2.0 * cov / (window * rate), unit))
    return math.sqrt(float(chi2.isf(significance, len(unit))) / information)
