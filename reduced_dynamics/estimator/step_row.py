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
from reduced_dynamics.estimator.step_state import (COUNT, DT, ELAPSED, LAST_STAMP, NEXT,
                                                   NIS_HORIZON, NIS_SCALE, OFFSETS, ONSETS,
                                                   OUTLIER_2N, OUTLIER_N,
                                                   POSE_STEP_HYPOTHESES, RECENT,
                                                   SETTLE_UNTIL, SETTLING, SINCE_IDENTITY,
                                                   SIZE_CAPACITY, SIZE_DIM, SIZE_N,
                                                   SPACING, THRESHOLD, WINDOW)


@njit(cache=True)
def _shift(array: np.ndarray, expired: int, count: int) -> None:
    """Move rows [expired, count) to [0, count - expired) (front to back: no overlap issue)."""
    for i in range(count - expired):
        array[i] = array[i + expired]


@njit(cache=True)
def test_views(state: np.ndarray, ints: np.ndarray) -> tuple:
    """
    Return the step test's arrays as views of its buffers (step_test.state_shapes).

    (floats, onsets, C, b0, J0, J0^-1, scores, Psi, Omega, beta, E, the transition since
    the last kept measurement, then the ring: Phi, H, S, K, nu and the innovation sizes.)
    """
    n, dim, cap = ints[SIZE_N], ints[SIZE_DIM], ints[SIZE_CAPACITY]
    slots, top = POSE_STEP_HYPOTHESES, 2 * n
    # The float buffer's arrays (FLOAT_ARRAYS' order) start at at[i]. (Sliced here: a
    # helper taking i would compile once per literal i.)
    at = ints[OFFSETS:ONSETS]
    return (state[at[0]:at[0] + 7], ints[ONSETS:ONSETS + cap],
            state[at[1]:at[1] + cap * dim * n].reshape((cap, dim, n)),
            state[at[2]:at[2] + cap * n].reshape((cap, n)),
            state[at[3]:at[3] + cap * n * n].reshape((cap, n, n)),
            state[at[4]:at[4] + cap * n * n].reshape((cap, n, n)),
            state[at[5]:at[5] + cap * n].reshape((cap, n)),
            state[at[6]:at[6] + dim * dim].reshape((dim, dim)),
            state[at[7]:at[7] + dim * dim].reshape((dim, dim)),
            state[at[8]:at[8] + dim],
            state[at[9]:at[9] + dim * n].reshape((dim, n)),
            state[at[10]:at[10] + dim * dim].reshape((dim, dim)),
            state[at[11]:at[11] + slots * dim * dim].reshape((slots, dim, dim)),
            state[at[12]:at[12] + slots * top * dim].reshape((slots, top, dim)),
            state[at[13]:at[13] + slots * top * top].reshape((slots, top, top)),
            state[at[14]:at[14] + slots * dim * top].reshape((slots, dim, top)),
            state[at[15]:at[15] + slots * top].reshape((slots, top)),
            ints[ONSETS + cap:ONSETS + cap + slots])


@njit(cache=True)
def work_views(work: np.ndarray, n: int, dim: int) -> tuple:
    """
    Return the filter's row-step work arrays as views of ``work`` (:func:`work_size`).

    The prediction g (4 x 4), x, P, Phi, then nu, R, H, S, K of an innovation of up to
    2n coordinates (an innovation of m uses their top-left corners).
    """
    m = 2 * n
    x_at = 16
    p_at = x_at + dim - n
    phi_at = p_at + dim * dim
    nu_at = phi_at + dim * dim
    r_at = nu_at + m
    h_at = r_at + m * m
    s_at = h_at + m * dim
    gain_at = s_at + m * m
    return (work[:16].reshape((4, 4)), work[x_at:p_at],
            work[p_at:phi_at].reshape((dim, dim)), work[phi_at:nu_at].reshape((dim, dim)),
            work[nu_at:r_at], work[r_at:h_at].reshape((m, m)),
            work[h_at:s_at].reshape((m, dim)), work[s_at:gain_at].reshape((m, m)),
            work[gain_at:gain_at + dim * m].reshape((dim, m)))


def work_size(n: int, dim: int) -> int:
    """Return the length of the filter's row-step work buffer (:func:`work_views`)."""
    m = 2 * n
    return 16 + (dim - n) + 2 * dim * dim + m + 2 * m * m + 2 * m * dim


@njit(cache=True)
def test_propagate(stamp_ns: int, transition: np.ndarray, ints: np.ndarray,
                   floats: np.ndarray, onsets: np.ndarray, c: np.ndarray, b0: np.ndarray,
                   j0: np.ndarray, bound_inv: np.ndarray, bounded: np.ndarray,
                   psi: np.ndarray, omega: np.ndarray, beta: np.ndarray, e: np.ndarray,
                   since: np.ndarray) -> None:
    """
    Run WrenchStepTest.propagate on its arrays, in place (``ints``/``floats``: its scalars).

    The same operations in the same order: Psi and the transition since the last
    kept measurement carried over the step, old onsets expired, a new one opened and
    the bank folded to it when due.
    """
    last_stamp = ints[LAST_STAMP]
    floats[DT] = 0.0 if last_stamp < 0 else max(stamp_ns - last_stamp, 0) * 1e-9
    ints[LAST_STAMP] = stamp_ns
    count = ints[COUNT]
    if count:
        psi[:] = transition @ psi
    if ints[RECENT]:
        # The first step since a measurement: Phi itself (no product with 1).
        if ints[SINCE_IDENTITY]:
            since[:] = transition
            ints[SINCE_IDENTITY] = 0
        else:
            since[:] = transition @ since
    expired = 0
    oldest = stamp_ns - ints[WINDOW]
    while expired < count and onsets[expired] < oldest:
        expired += 1
    if expired:
        for array in (c, j0, bound_inv):
            _shift(array, expired, count)
        _shift(onsets, expired, count)
        _shift(b0, expired, count)
        _shift(bounded, expired, count)
        count -= expired
        ints[COUNT] = count
    if ints[SETTLING] and stamp_ns < ints[SETTLE_UNTIL]:
        return
    if not count or stamp_ns - onsets[count - 1] >= ints[SPACING]:
        if count:
            fold(c, b0, j0, bound_inv, bounded, count, psi, omega, beta)
        onsets[count] = stamp_ns
        c[count] = e
        b0[count] = 0.0
        j0[count] = 0.0
        bounded[count] = False
        ints[COUNT] = count + 1
        psi[:] = 0.0
        for i in range(psi.shape[0]):
            psi[i, i] = 1.0
        omega[:] = 0.0
        beta[:] = 0.0


@njit(cache=True)
def keep(ints: np.ndarray, since: np.ndarray, ring_since: np.ndarray, ring_h: np.ndarray,
         ring_s: np.ndarray, ring_gain: np.ndarray, ring_nu: np.ndarray, ring_m: np.ndarray,
         h: np.ndarray, s: np.ndarray, gain: np.ndarray, nu: np.ndarray) -> None:
    """Keep a measurement in the step test's ring (WrenchStepTest._keep, compiled)."""
    slot = ints[NEXT]
    m = nu.shape[0]
    dim = ring_since.shape[1]
    if ints[SINCE_IDENTITY]:
        ring_since[slot] = 0.0
        for i in range(dim):
            ring_since[slot, i, i] = 1.0
    else:
        ring_since[slot] = since
    ring_h[slot, :m] = h
    ring_s[slot, :m, :m] = s
    ring_gain[slot, :, :m] = gain
    ring_nu[slot, :m] = nu
    ring_m[slot] = m
    ints[NEXT] = (slot + 1) % POSE_STEP_HYPOTHESES
    ints[RECENT] = min(ints[RECENT] + 1, POSE_STEP_HYPOTHESES)
    ints[SINCE_IDENTITY] = 1


@njit(cache=True)
def _put(work: np.ndarray, value: np.ndarray) -> None:
    """Write ``value`` into the top-left corner of ``work`` (2-d)."""
    for i in range(value.shape[0]):
        for j in range(value.shape[1]):
            work[i, j] = value[i, j]


@njit(cache=True)
def filter_step(g: np.ndarray, x: np.ndarray, p: np.ndarray, locked: np.ndarray,
                before_inverse: np.ndarray, before_connection_qd: np.ndarray,
                midway: bool, dt: float, pose: np.ndarray, measured: np.ndarray,
                with_twist: bool,
                inverse_locked: np.ndarray, connection_qd: np.ndarray, joint_cov: np.ndarray,
                stamp_twist: np.ndarray, stamp_sigma: float, gate: float,
                twist_weight: float, stamp_ns: int, jerk_var: np.ndarray,
                pose_var: np.ndarray, twist_var: np.ndarray, basis: np.ndarray,
                pinv: np.ndarray, whole: bool, ad_rows: np.ndarray, form_rows: np.ndarray,
                h_pose: np.ndarray, state: np.ndarray, ints: np.ndarray,
                bounded: np.ndarray, work: np.ndarray) -> tuple:
    """
    Run a step that ends in a measurement (at a row or between two) and its step test.

    The row's values first, then what is fixed for the filter's life (its noise and
    group constants, the step test's buffers, the work buffer: the filter passes these
    as one tuple built once, ``MomentumFilter._row_fixed``).

    ``midway``: the step's inputs are the mean of the previous row's (``before_*``)
    and this row's (state.between at 0.5), a measurement at the row's stamp; else
    ``before_*`` are the step's inputs themselves (state.between at the caller's
    fraction: a measurement between two rows, whose I and A Sigma A^T, ``locked`` and
    ``joint_cov``, are the step's too); then ``kernels.propagate_update``,
    :func:`test_propagate` on its transition, and, when the measurement was accepted
    into a healthy covariance with an onset open, ``absorb_evaluate`` and :func:`keep`
    (the step test's whole update but its outcome). The step test's state
    (WrenchStepTest.compiled_arrays: :func:`test_views`) changes in place; the
    prediction (g, x, P, Phi) goes into ``work`` (:func:`work_views`), and, when the
    step test did not take the update (the filter's general path then runs from these),
    nu, R, H, S, K into the top-left corners of its further arrays; the
    stamp-noise twist average moves in ``stamp_twist`` itself. Nothing is written
    before ``propagate_update`` returned (when it raises, nothing changed).

    Returns (g, x, P) after the update (the prediction's arrays when gated), whether
    accepted, NIS, log det S, the covariance's health, w^T P_ww^-1 w, whether the
    step test took the update, whether it was evidence, the best onset, its
    statistic, the largest bound and the onsets evaluated.
    """
    if midway:
        step_inverse = 0.5 * (before_inverse + inverse_locked)
        step_connection_qd = 0.5 * (before_connection_qd + connection_qd)
    else:
        step_inverse, step_connection_qd = before_inverse, before_connection_qd
    (g0, x0, p0, phi, accepted, nis, logdet, nu, r, g1, x1, p1, h, s, gain, health,
     averaged, wrench_test) = propagate_update(
        g, x, p, locked, step_inverse, step_connection_qd, joint_cov, dt, jerk_var, pose,
        measured, with_twist, inverse_locked, connection_qd, joint_cov, pose_var,
        stamp_twist, stamp_sigma, twist_var, gate, twist_weight, basis, pinv, whole,
        ad_rows, form_rows)
    (floats, onsets, c, b0, j0, bound_inv, score, psi, omega, beta, e, since, ring_since,
     ring_h, ring_s, ring_gain, ring_nu, ring_m) = test_views(state, ints)
    work_g, work_x, work_p, work_phi, work_nu, work_r, work_h, work_s, work_gain = \
        work_views(work, inverse_locked.shape[0], p.shape[0])
    _put(work_g, g0)
    work_x[:] = x0
    _put(work_p, p0)
    _put(work_phi, phi)
    test_propagate(stamp_ns, phi, ints, floats, onsets, c, b0, j0, bound_inv, bounded, psi,
                   omega, beta, e, since)
    count = ints[COUNT]
    tested, evidence, best, statistic, top, evaluated = False, False, -1, 0.0, 0.0, 0
    m = nu.shape[0]
    if accepted and health == 0 and count:
        tested = True
        used = np.ascontiguousarray(h) if with_twist else h_pose
        outlier = floats[OUTLIER_2N] if with_twist else floats[OUTLIER_N]
        _, evidence, nis_scale, elapsed, best, statistic, top, evaluated = absorb_evaluate(
            used, np.ascontiguousarray(s), np.ascontiguousarray(gain),
            np.ascontiguousarray(nu), psi, omega, beta, outlier, c, b0, j0, bound_inv,
            bounded, count, score, floats[THRESHOLD], floats[NIS_SCALE], floats[ELAPSED],
            floats[DT], floats[NIS_HORIZON])
        floats[NIS_SCALE] = nis_scale
        floats[ELAPSED] = elapsed
        keep(ints, since, ring_since, ring_h, ring_s, ring_gain, ring_nu, ring_m, used, s,
             gain, nu)
    else:
        work_nu[:m] = nu
        _put(work_r, r)
        _put(work_h, h)
        _put(work_s, s)
        _put(work_gain, gain)
    if accepted and twist_weight >= 0.0:
        # Last (nothing after it raises): a new array exactly then (propagate_update).
        stamp_twist[:] = averaged
    return (g1, x1, p1, accepted, nis, logdet, health, wrench_test, tested, evidence, best,
            statistic, top, evaluated)


@njit(cache=True)
def propagate_step(g: np.ndarray, x: np.ndarray, p: np.ndarray, locked: np.ndarray,
                   inverse_locked: np.ndarray, connection_qd: np.ndarray,
                   joint_cov: np.ndarray, dt: float, u: np.ndarray, jerk_var: np.ndarray,
                   density: np.ndarray, basis: np.ndarray, pinv: np.ndarray, whole: bool,
                   ad_rows: np.ndarray, form_rows: np.ndarray, stamp_ns: int,
                   state: np.ndarray, ints: np.ndarray, bounded: np.ndarray,
                   work: np.ndarray) -> tuple:
    """
    Propagate without a measurement (``kernels.propagate``), then :func:`test_propagate`.

    A row between two base measurements (joint states faster than odometry). The
    step test's arrays are :func:`filter_step`'s (its update's part unused).
    Returns (g, x, P); Phi goes into ``work`` (:func:`work_views`: read only to record).
    """
    # commanded: u's size (empty here), a runtime bool: a constant False would compile
    # propagate once more, for that literal (numba specialises on constants).
    g1, x1, p1, phi = propagate(g, x, p, locked, inverse_locked, connection_qd, joint_cov,
                                dt, u, u.shape[0] > 0, jerk_var, density, basis, pinv, whole,
                                ad_rows, form_rows)
    (floats, onsets, c, b0, j0, bound_inv, _, psi, omega, beta, e, since, _, _, _, _, _,
     _) = test_views(state, ints)
    test_propagate(stamp_ns, phi, ints, floats, onsets, c, b0, j0, bound_inv, bounded, psi,
                   omega, beta, e, since)
    _put(work_views(work, inverse_locked.shape[0], p.shape[0])[3], phi)
    return g1, x1, p1
