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
One update of the multi-scale test's two banks in one compiled call (numba).

Per update :class:`~reduced_dynamics.estimator.multiscale.MultiScaleTest` stores
the filtered momentum, forms each window's T_L, calibrates it and takes the best
window; the block test on measured momenta does the same on its windows. Where
that was two compiled calls with LAPACK solves per window and numpy between them
(~35 us a sample at 1 kHz, every window covered), :func:`update` is one call on
preallocated arrays:

- the filtered bank's V_L = P_mu(t) + P_mu(t - L) is factored by Cholesky, its
  T_L = ||L^-1 d_L||^2 (no LAPACK call, no allocation; equal to the LU solve's
  to rounding, test_multiscale_kernels.py);
- the block bank's window L is evaluated on a grid of stride L / :data:`GRID`
  (its blocks are L long: a stride of L / 16 moves them by 1/16 of their length
  between evaluations), its statistic held between them; its null calibration
  learns at evaluations, weighted by the updates since the last, so its memory in
  seconds is the same (docs/multiscale_events.md, "Cost").

The per-window kernels (:func:`.bank_windows.quadratic_form`, the filtered bank, a
block window) are in core/bank_windows.py.
"""

import math

import numpy as np
from numba import njit

from reduced_dynamics.estimator.core.bank_windows import (  # noqa: F401 (re-exported)
    block_window, filtered_bank, quadratic_form)
from reduced_dynamics.estimator.core.blocks import add_sample
from reduced_dynamics.estimator.core.impulse import measured_momentum_se3


#: Evaluations of a block window per its length: window L is evaluated on a grid of
#: stride L / GRID (docs/multiscale_events.md, "Cost").
GRID = 16


@njit(cache=True)
def update(stamps: np.ndarray, mu_ring: np.ndarray, cov_ring: np.ndarray, start: int,
           end: int, lags: np.ndarray, stamp_ns: int, floor_ns: int, has_floor: bool,
           mu: np.ndarray, cov: np.ndarray, rows: np.ndarray, statistics: np.ndarray,
           above: np.ndarray, inflation: np.ndarray, scratch: np.ndarray, median: float,
           rate: float, learn: bool, blocks_on: bool, blocks_ready: bool,
           info: np.ndarray, score: np.ndarray, s0: np.ndarray, s1: np.ndarray,
           s2: np.ndarray, y0: np.ndarray, t1: np.ndarray, counts: np.ndarray,
           common: np.ndarray, block_stamps: np.ndarray, block_end: int,
           block_lags: np.ndarray, first: int, mass: float, linear: np.ndarray,
           block_statistics: np.ndarray, grid: np.ndarray) -> tuple[int, float, int]:
    """
    One update of both banks in one call; return (filtered best, its value, blocks' best).

    The filtered bank (every window, every update): the sample stored at ring row
    ``end``, each window's row (``rows``, -1: not covered) and T_L by Cholesky
    (:func:`.bank_windows.quadratic_form`), calibrated into ``statistics``; its best as
    :func:`.impulse.calibrated_best` (-1: none covered or a V_L not positive).

    The block bank on a grid: window L is evaluated at the first update in each
    slot of length L / GRID of the stamps (``grid`` (3, windows) int64: each window's
    stride [ns], its last slot (-1: none since it was covered), the quiet updates
    since its last evaluation); between evaluations its statistic holds. Its null
    is learnt at evaluations only, at ``rate`` times the updates since the last one
    (the same memory in seconds as learning at every update). A window the floor or
    the data leave uncovered is 0 and evaluated as soon as it is covered again. The
    blocks' best: the largest calibrated statistic (-1: none covered). The block test
    runs when ``blocks_on`` (a twist measured), ``blocks_ready`` (its excess noise
    known) and it holds four samples (MomentumBlocks.update's conditions).
    ``above``, ``inflation`` (2, windows): the filtered bank's row, the blocks'.
    ``scratch`` (14, n, n): the block windows' work space (12), the filtered bank's
    Cholesky factor, its two work vectors.
    """
    count = lags.shape[0]
    covered = filtered_bank(stamps, mu_ring, cov_ring, start, end, lags, stamp_ns,
                            floor_ns, has_floor, mu, cov, rows, statistics, scratch[12],
                            scratch[13][0], scratch[13][1])
    best, value = -1, 0.0
    if covered > 0:
        for w in range(count):
            raw = statistics[w]
            if learn and raw > 0.0:
                above[0, w] += rate * ((1.0 if raw > median else 0.0) - above[0, w])
            statistics[w] = raw / inflation[0, w]
        k = 0
        for w in range(count):
            if rows[w] < 0:
                continue
            v = statistics[w]
            if best < 0 or (not math.isnan(value) and (v > value or math.isnan(v))):
                best, value = k, v
            k += 1
    block_best = -1
    if not blocks_on:
        return best, value, block_best
    if not (blocks_ready and block_end >= 4):
        block_statistics[:] = 0.0
        grid[1] = -1
        return best, value, block_best
    for w in range(count):
        lag = block_lags[w]
        if stamp_ns - 3 * lag < first:
            block_statistics[w] = 0.0
            grid[1, w] = -1
            grid[2, w] = 0
            continue
        if learn:
            grid[2, w] += 1
        slot = stamp_ns // grid[0, w]
        if slot != grid[1, w]:
            grid[1, w] = slot
            raw = block_window(info, score, s0, s1, s2, y0, t1, counts, common,
                               block_stamps, block_end, lag, stamp_ns, mass, linear,
                               scratch[:12])
            if learn and raw > 0.0 and grid[2, w] > 0:
                step = min(1.0, rate * grid[2, w])
                above[1, w] += step * ((1.0 if raw > median else 0.0) - above[1, w])
            grid[2, w] = 0
            block_statistics[w] = raw / inflation[1, w]
        if block_statistics[w] > 0.0 or math.isnan(block_statistics[w]):
            if block_best < 0 or (not math.isnan(block_statistics[block_best]) and (
                    block_statistics[w] > block_statistics[block_best]
                    or math.isnan(block_statistics[w]))):
                block_best = w
    return best, value, block_best


@njit(cache=True)
def update_with_sample(raw: np.ndarray, sample_mu: np.ndarray, sample_cov: np.ndarray,
                       last_mu: np.ndarray, last_cov: np.ndarray, divisor: float,
                       excess: np.ndarray, position_cov: np.ndarray, common_sample: np.ndarray,
                       sample_stamp: int, k: int, t: float, centre: np.ndarray,
                       with_positions: bool, stamps: np.ndarray, mu_ring: np.ndarray,
                       cov_ring: np.ndarray, start: int, end: int, lags: np.ndarray,
                       stamp_ns: int, floor_ns: int, has_floor: bool, mu: np.ndarray,
                       cov: np.ndarray, rows: np.ndarray, statistics: np.ndarray,
                       above: np.ndarray, inflation: np.ndarray, scratch: np.ndarray,
                       median: float, rate: float, learn: bool, blocks_ready: bool,
                       info: np.ndarray, score: np.ndarray, s0: np.ndarray, s1: np.ndarray,
                       s2: np.ndarray, y0: np.ndarray, t1: np.ndarray, counts: np.ndarray,
                       common: np.ndarray, block_stamps: np.ndarray, block_lags: np.ndarray,
                       first: int, mass: float, linear: np.ndarray,
                       block_statistics: np.ndarray, grid: np.ndarray) -> tuple:
    """
    Take one measured momentum into block row ``k`` (blocks.add_sample), then :func:`update`.

    The update's common case (one twist per update, MomentumBlocks._add_compiled's
    conditions) in one call. Returns (whether the sample was added (False: its
    covariance singular, as add_sample raised), then :func:`update`'s three values).
    """
    added = True
    try:
        add_sample(raw, sample_mu, sample_cov, last_mu, last_cov, divisor, excess,
                   position_cov, info, score, common, common_sample, block_stamps,
                   sample_stamp, k, s0, s1, s2, y0, t1, counts, t, centre, with_positions)
    except Exception:  # noqa: B902 numba catches no narrower class (a LinAlgError here)
        added = False
    block_end = k + 1 if added else k
    best, value, block_best = update(
        stamps, mu_ring, cov_ring, start, end, lags, stamp_ns, floor_ns, has_floor, mu, cov,
        rows, statistics, above, inflation, scratch, median, rate, learn, True,
        blocks_ready, info, score, s0, s1, s2, y0, t1, counts, common, block_stamps,
        block_end, block_lags, first, mass, linear, block_statistics, grid)
    return added, best, value, block_best


@njit(cache=True)
def update_with_twist(ad_inverse: np.ndarray, locked: np.ndarray, twist: np.ndarray,
                      connection_qd: np.ndarray, twist_cov: np.ndarray, joint_cov: np.ndarray,
                      pose_cov: np.ndarray, structure: np.ndarray, rotation: np.ndarray,
                      translation: np.ndarray, com_pose_cov: np.ndarray, raw: np.ndarray,
                      last_mu: np.ndarray, last_cov: np.ndarray, keep_mu: np.ndarray,
                      keep_cov: np.ndarray, divisor: float, excess: np.ndarray,
                      sample_stamp: int, k: int, t: float, stamps: np.ndarray,
                      mu_ring: np.ndarray, cov_ring: np.ndarray, start: int, end: int,
                      lags: np.ndarray, stamp_ns: int, floor_ns: int, has_floor: bool,
                      mu: np.ndarray, cov: np.ndarray, rows: np.ndarray,
                      statistics: np.ndarray, above: np.ndarray, inflation: np.ndarray,
                      scratch: np.ndarray, median: float, rate: float, learn: bool,
                      blocks_ready: bool, info: np.ndarray, score: np.ndarray,
                      s0: np.ndarray, s1: np.ndarray, s2: np.ndarray, y0: np.ndarray,
                      t1: np.ndarray, counts: np.ndarray, common: np.ndarray,
                      block_stamps: np.ndarray, block_lags: np.ndarray, first: int,
                      mass: float, linear: np.ndarray, block_statistics: np.ndarray,
                      grid: np.ndarray) -> tuple:
    """
    Turn one measured twist of an SE(3) base into its momentum, then :func:`update_with_sample`.

    The row's whole intake of the block test in the banks' call: the twist's
    momentum, its covariances and the measured centre of mass
    (:func:`.impulse.measured_momentum_se3`, the locked inertia of the row for both),
    the sample into block row ``k`` and both banks' update, the same kernels in the
    same order as the calls it replaces (measured_momentum.TwistSample.momentum, then
    MomentumBlocks.prepare's arguments and :func:`update_with_sample`). The sample's
    momentum and white covariance are copied into ``keep_mu``, ``keep_cov`` (the
    next sample's successive difference reads them: MomentumBlocks._last) after
    ``last_mu``, ``last_cov`` were read (they may be the same arrays).
    """
    sample_mu, white, sample_common, centre, position_cov, _ = measured_momentum_se3(
        ad_inverse, locked, twist, connection_qd, twist_cov, joint_cov, pose_cov, structure,
        locked, rotation, translation, com_pose_cov)
    result = update_with_sample(
        raw, sample_mu, white, last_mu, last_cov, divisor, excess, position_cov,
        sample_common, sample_stamp, k, t, centre, True, stamps, mu_ring, cov_ring, start,
        end, lags, stamp_ns, floor_ns, has_floor, mu, cov, rows, statistics, above,
        inflation, scratch, median, rate, learn, blocks_ready, info, score, s0, s1, s2, y0,
        t1, counts, common, block_stamps, block_lags, first, mass, linear, block_statistics,
        grid)
    keep_mu[:] = sample_mu
    keep_cov[:] = white
    return result


@njit(cache=True)
def twist_step(sample_stamp: int, ad_inverse: np.ndarray, locked: np.ndarray,
               twist: np.ndarray, connection_qd: np.ndarray, twist_cov: np.ndarray,
               joint_cov: np.ndarray, pose_cov: np.ndarray, structure: np.ndarray,
               rotation: np.ndarray, translation: np.ndarray, com_pose_cov: np.ndarray,
               stamp_ns: int, mu: np.ndarray, cov: np.ndarray, floor_ns: int,
               has_floor: bool, learn: bool, period: float, memory: float, ready: bool,
               divisor: float, last_mu: np.ndarray, last_cov: np.ndarray, start: int,
               end: int, k: int, origin_ns: int, raw: np.ndarray, keep_mu: np.ndarray,
               keep_cov: np.ndarray, excess: np.ndarray, stamps: np.ndarray,
               mu_ring: np.ndarray, cov_ring: np.ndarray, lags: np.ndarray, rows: np.ndarray,
               statistics: np.ndarray, above: np.ndarray, inflation: np.ndarray,
               scratch: np.ndarray, median: float, info: np.ndarray, score: np.ndarray,
               s0: np.ndarray, s1: np.ndarray, s2: np.ndarray, y0: np.ndarray,
               t1: np.ndarray, counts: np.ndarray, common: np.ndarray,
               block_stamps: np.ndarray, block_lags: np.ndarray, mass: float,
               linear: np.ndarray, block_statistics: np.ndarray,
               grid: np.ndarray) -> tuple:
    """
    One common update of the multi-scale test (MultiScaleTest._update_twist) in one call.

    The arguments: a TwistSample's fields, the update's (stamp, mu, P_mu, the floor,
    whether the null learns), the scalars of the two tests' state, then the arrays
    that stay between updates (the caller keeps them as one tuple). The update period
    (a running mean of the stamps' steps), the block test's first stamp and the
    calibration's rate as MultiScaleTest._filtered computes them, then
    :func:`update_with_twist`. Returns (whether the sample was added, the new period,
    the filtered best, its value, the blocks' best).
    """
    # The period as MultiScaleTest._filtered: the int64 step, then in float64.
    dt = (stamp_ns - stamps[end - 1]) * 1e-9
    if dt > 0.0:
        period = period + 0.01 * (dt - period)
    first = block_stamps[0]
    if has_floor and floor_ns > first:
        first = floor_ns
    rate = min(1.0, period / memory) if learn else 0.0
    t = (sample_stamp - origin_ns) * 1e-9
    added, best, value, block_best = update_with_twist(
        ad_inverse, locked, twist, connection_qd, twist_cov, joint_cov, pose_cov, structure,
        rotation, translation, com_pose_cov, raw, last_mu, last_cov, keep_mu, keep_cov,
        divisor, excess, sample_stamp, k, t, stamps, mu_ring, cov_ring, start, end, lags,
        stamp_ns, floor_ns, has_floor, mu, cov, rows, statistics, above, inflation, scratch,
        median, rate, learn, ready, info, score, s0, s1, s2, y0, t1, counts, common,
        block_stamps, block_lags, first, mass, linear, block_statistics, grid)
    return added, period, best, value, block_best
