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
The filter's common step and the wrench-step test's share of it, in one compiled call.

A step that ends in a measurement (no commanded wrench, the noise parameters,
not a burst frame) ran as ``kernels.propagate_update``, then the step test's
:meth:`~.step_test.WrenchStepTest.propagate` (Psi and the transition since the
last measurement carried over the step, old onsets expired, a new one opened and
the bank folded to it) in Python, then its ``absorb_evaluate`` (S5-S8 of
docs/step_test.md). :func:`filter_step` runs the three in one call, with the
same operations in the same order, so the results are the same bits
(test/test_step_row.py compares it with the calls it replaces). The step test's
update runs only where the filter's own would reach it (measurement accepted,
covariance healthy, an onset open); elsewhere the caller takes the Python path
from the prediction on, as before. A row without a measurement (joint states
between odometry samples) propagates in one call the same way
(:func:`propagate_step`).
"""

import numpy as np
from numba import njit

from reduced_dynamics.estimator.core.kernels import propagate, propagate_update
from reduced_dynamics.estimator.step_kernels import absorb_evaluate, fold


@njit(cache=True)
def _shift(array: np.ndarray, expired: int, count: int) -> None:
    """Move rows [expired, count) to [0, count - expired) (front to back: no overlap issue)."""
    for i in range(count - expired):
        array[i] = array[i + expired]


@njit(cache=True)
def test_propagate(stamp_ns: int, last_stamp: int, transition: np.ndarray, count: int,
                   onsets: np.ndarray, c: np.ndarray, b0: np.ndarray, j0: np.ndarray,
                   bound_inv: np.ndarray, bounded: np.ndarray, psi: np.ndarray,
                   omega: np.ndarray, beta: np.ndarray, e: np.ndarray, since: np.ndarray,
                   since_identity: bool, recent: bool, window_ns: int, spacing_ns: int,
                   settle_until: int, settling: bool) -> tuple:
    """
    Return WrenchStepTest.propagate's state after one step (``last_stamp`` < 0: none yet).

    Returns (dt, count, psi, omega, beta, since, since still the identity); the
    onset arrays, Psi, Omega and beta are changed in place (and returned).
    """
    dt = 0.0 if last_stamp < 0 else max(stamp_ns - last_stamp, 0) * 1e-9
    if count:
        # In place (the step test's own arrays; absorb works on them in place too): a
        # returned input array goes back to Python as itself, without a new object.
        psi[:] = transition @ psi
    if recent:
        # The first step since a measurement: Phi itself (no product with 1).
        since = transition if since_identity else transition @ since
        since_identity = False
    expired = 0
    oldest = stamp_ns - window_ns
    while expired < count and onsets[expired] < oldest:
        expired += 1
    if expired:
        for array in (c, j0, bound_inv):
            _shift(array, expired, count)
        _shift(onsets, expired, count)
        _shift(b0, expired, count)
        _shift(bounded, expired, count)
        count -= expired
    if settling and stamp_ns < settle_until:
        return dt, count, psi, omega, beta, since, since_identity
    if not count or stamp_ns - onsets[count - 1] >= spacing_ns:
        if count:
            fold(c, b0, j0, bound_inv, bounded, count, psi, omega, beta)
        onsets[count] = stamp_ns
        c[count] = e
        b0[count] = 0.0
        j0[count] = 0.0
        bounded[count] = False
        count += 1
        psi[:] = 0.0
        for i in range(psi.shape[0]):
            psi[i, i] = 1.0
        omega[:] = 0.0
        beta[:] = 0.0
    return dt, count, psi, omega, beta, since, since_identity


@njit(cache=True)
def filter_step(g: np.ndarray, x: np.ndarray, p: np.ndarray, locked: np.ndarray,
                before_inverse: np.ndarray, before_connection_qd: np.ndarray,
                dt: float, jerk_var: np.ndarray, pose: np.ndarray, measured: np.ndarray,
                with_twist: bool, inverse_locked: np.ndarray, connection_qd: np.ndarray,
                joint_cov: np.ndarray, pose_var: np.ndarray, stamp_twist: np.ndarray,
                stamp_sigma: float, twist_var: np.ndarray, gate: float, twist_weight: float,
                basis: np.ndarray, pinv: np.ndarray, whole: bool, ad_rows: np.ndarray,
                form_rows: np.ndarray, h_pose: np.ndarray, stamp_ns: int, last_stamp: int,
                count: int, onsets: np.ndarray, c: np.ndarray, b0: np.ndarray,
                j0: np.ndarray, bound_inv: np.ndarray, bounded: np.ndarray,
                score: np.ndarray, psi: np.ndarray, omega: np.ndarray, beta: np.ndarray,
                e: np.ndarray, since: np.ndarray, since_identity: bool, recent: bool,
                window_ns: int, spacing_ns: int, settle_until: int, settling: bool,
                outlier: float, threshold: float, nis_scale: float, elapsed: float,
                nis_time: float) -> tuple:
    """
    Run a row's step (a measurement at the row, the step's inputs midway) and its step test.

    The step's inputs are the mean of the previous row's (``before_*``) and this
    row's (state.between at 0.5); then ``kernels.propagate_update`` (its 18
    results first), :func:`test_propagate` on its transition, and, when the
    measurement was accepted into a healthy covariance with an onset open,
    ``absorb_evaluate`` (whether it ran, then its results but the NIS).
    """
    step_inverse = 0.5 * (before_inverse + inverse_locked)
    step_connection_qd = 0.5 * (before_connection_qd + connection_qd)
    (g0, x0, p0, phi, accepted, nis, logdet, nu, r, g1, x1, p1, h, s, gain, health,
     averaged, wrench_test) = propagate_update(
        g, x, p, locked, step_inverse, step_connection_qd, joint_cov, dt, jerk_var, pose,
        measured, with_twist, inverse_locked, connection_qd, joint_cov, pose_var,
        stamp_twist, stamp_sigma, twist_var, gate, twist_weight, basis, pinv, whole,
        ad_rows, form_rows)
    test_dt, count, psi, omega, beta, since, since_identity = test_propagate(
        stamp_ns, last_stamp, phi, count, onsets, c, b0, j0, bound_inv, bounded, psi,
        omega, beta, e, since, since_identity, recent, window_ns, spacing_ns, settle_until,
        settling)
    tested, evidence, best, statistic, top, evaluated = False, False, -1, 0.0, 0.0, 0
    if accepted and health == 0 and count:
        tested = True
        used = h if with_twist else h_pose
        _, evidence, nis_scale, elapsed, best, statistic, top, evaluated = absorb_evaluate(
            np.ascontiguousarray(used), np.ascontiguousarray(s),
            np.ascontiguousarray(gain), np.ascontiguousarray(nu), psi, omega, beta,
            outlier, c, b0, j0, bound_inv, bounded, count, score, threshold, nis_scale,
            elapsed, test_dt, nis_time)
    return (g0, x0, p0, phi, accepted, nis, logdet, nu, r, g1, x1, p1, h, s, gain, health,
            averaged, wrench_test, test_dt, count, psi, omega, beta, since, since_identity,
            tested, evidence, nis_scale, elapsed, best, statistic, top, evaluated)


@njit(cache=True)
def propagate_step(g: np.ndarray, x: np.ndarray, p: np.ndarray, locked: np.ndarray,
                   inverse_locked: np.ndarray, connection_qd: np.ndarray,
                   joint_cov: np.ndarray, dt: float, u: np.ndarray, jerk_var: np.ndarray,
                   density: np.ndarray, basis: np.ndarray, pinv: np.ndarray, whole: bool,
                   ad_rows: np.ndarray, form_rows: np.ndarray, stamp_ns: int,
                   last_stamp: int, count: int, onsets: np.ndarray, c: np.ndarray,
                   b0: np.ndarray, j0: np.ndarray, bound_inv: np.ndarray,
                   bounded: np.ndarray, score: np.ndarray, psi: np.ndarray,
                   omega: np.ndarray, beta: np.ndarray, e: np.ndarray, since: np.ndarray,
                   since_identity: bool, recent: bool, window_ns: int, spacing_ns: int,
                   settle_until: int, settling: bool, outlier: float, threshold: float,
                   nis_scale: float, elapsed: float, nis_time: float) -> tuple:
    """
    Propagate without a measurement (``kernels.propagate``), then :func:`test_propagate`.

    A row between two base measurements (joint states faster than odometry). The
    step test's state is :func:`filter_step`'s (its update's part unused). Returns
    (g, x, P, Phi), then :func:`test_propagate`'s results.
    """
    g1, x1, p1, phi = propagate(g, x, p, locked, inverse_locked, connection_qd, joint_cov,
                                dt, u, False, jerk_var, density, basis, pinv, whole,
                                ad_rows, form_rows)
    test_dt, count, psi, omega, beta, since, since_identity = test_propagate(
        stamp_ns, last_stamp, phi, count, onsets, c, b0, j0, bound_inv, bounded, psi,
        omega, beta, e, since, since_identity, recent, window_ns, spacing_ns, settle_until,
        settling)
    return (g1, x1, p1, phi, test_dt, count, psi, omega, beta, since, since_identity)
