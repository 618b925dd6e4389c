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
from reduced_dynamics.estimator.core.impulse import calibrated_best, measured_momentum_se3


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
        best, value = calibrated_best(rows, statistics, above[0], inflation[0], median, rate,
                                      learn)
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
    # The blocks are active (True), as a runtime value: a literal True would compile
    # update a second time, specialised on it (numba types a constant argument as a literal).
    active = block_end >= 0
    best, value, block_best = update(
        stamps, mu_ring, cov_ring, start, end, lags, stamp_ns, floor_ns, has_floor, mu, cov,
        rows, statistics, above, inflation, scratch, median, rate, learn, active,
        blocks_ready, info, score, s0, s1, s2, y0, t1, counts, common, block_stamps,
        block_end, block_lags, first, mass, linear, block_statistics, grid)
    return added, best, value, block_best


@njit(cache=True)
def update_with_twist(ad_inverse: np.ndarray, locked: np.ndarray, twist: np.ndarray,
                      connection_qd: np.ndarray, twist_cov: np.ndarray, joint_cov: np.ndarray,
                      pose_cov: np.ndarray, structure: np.ndarray, rotation: np.ndarray,
                      translation: np.ndarray, com_pose_cov: np.ndarray,
                      com_locked: np.ndarray, raw: np.ndarray,
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
    (:func:`.impulse.measured_momentum_se3`: the row's locked inertia for the momentum,
    ``com_locked`` for the centre of mass),
    the sample into block row ``k`` and both banks' update, the same kernels in the
    same order as the calls it replaces (measured_momentum.TwistSample.momentum, then
    MomentumBlocks.prepare's arguments and :func:`update_with_sample`). The sample's
    momentum and white covariance are copied into ``keep_mu``, ``keep_cov`` (the
    next sample's successive difference reads them: MomentumBlocks._last) after
    ``last_mu``, ``last_cov`` were read (they may be the same arrays).
    """
    sample_mu, white, sample_common, centre, position_cov, _ = measured_momentum_se3(
        ad_inverse, locked, twist, connection_qd, twist_cov, joint_cov, pose_cov, structure,
        com_locked, rotation, translation, com_pose_cov)
    # A position is present (True), as a runtime value (see update_with_sample's call).
    with_positions = centre.shape[0] > 0
    result = update_with_sample(
        raw, sample_mu, white, last_mu, last_cov, divisor, excess, position_cov,
        sample_common, sample_stamp, k, t, centre, with_positions, stamps, mu_ring, cov_ring,
        start, end, lags, stamp_ns, floor_ns, has_floor, mu, cov, rows, statistics, above,
        inflation, scratch, median, rate, learn, blocks_ready, info, score, s0, s1, s2, y0,
        t1, counts, common, block_stamps, block_lags, first, mass, linear, block_statistics,
        grid)
    keep_mu[:] = sample_mu
    keep_cov[:] = white
    return result


#: MultiScaleTest's int64 state (``_state``): its ring's end and start, its update count,
#: the floor [ns] and whether there is one, the last twist_step's best windows.
END, START, UPDATES, FLOOR, HAS_FLOOR, BEST, BLOCK_BEST = range(7)
#: its float64 state (``_values``): the update period (NaN: not known yet), the threshold
#: and the period it was computed for, the calibration memory [s], the last best value.
PERIOD, THRESHOLD, THRESHOLD_PERIOD, MEMORY, VALUE = range(5)
#: MomentumBlocks' int64 state (``_state``): its ring's end, the successive differences
#: taken, the origin [ns] of its times.
BLOCK_END, DIFFERENCES, ORIGIN = range(3)
#: twist_step's answers. Nothing moved: not the common update (UNCOMMON), the null's
#: inflation due first (CALIBRATE), the filtered ring full (ROOM). Done: nothing to
#: tell (DONE), the threshold due at the new period (THRESHOLD_DUE), a statistic above
#: the threshold where a detection is wanted (DETECT); plus NEXT_CHECKED when the next
#: update is not known to be common (an excess decomposition or the inflation due, a
#: ring full: the caller checks it before the call).
DONE, UNCOMMON, CALIBRATE, ROOM, THRESHOLD_DUE, DETECT = range(6)
NEXT_CHECKED = 8
#: Updates between the null inflation's updates, the relative change of the update
#: period after which the threshold is recomputed, the memory of the excess noise's
#: running mean (samples): MultiScaleTest's and MomentumBlocks' settings
#: (multiscale_bank.py, momentum_blocks.py import them from here).
CALIBRATION_EVERY, PERIOD_TOLERANCE, EXCESS_SAMPLES = 256, 0.2, 2000


@njit(cache=True)
def twist_step(sample_stamp: int, ad_inverse: np.ndarray, locked: np.ndarray,
               twist: np.ndarray, connection_qd: np.ndarray, twist_cov: np.ndarray,
               joint_cov: np.ndarray, pose_cov: np.ndarray, structure: np.ndarray,
               rotation: np.ndarray, translation: np.ndarray, com_pose_cov: np.ndarray,
               com_locked: np.ndarray, stamp_ns: int, mu: np.ndarray, cov: np.ndarray,
               learn: bool, wanted: bool, calibrated: bool, last_mu: np.ndarray,
               last_cov: np.ndarray,
               state: np.ndarray, values: np.ndarray, block_state: np.ndarray,
               stamps: np.ndarray, mu_ring: np.ndarray, cov_ring: np.ndarray,
               block_stamps: np.ndarray, info: np.ndarray, score: np.ndarray,
               common: np.ndarray, s0: np.ndarray, s1: np.ndarray, s2: np.ndarray,
               y0: np.ndarray, t1: np.ndarray, counts: np.ndarray,
               window_values: np.ndarray, window_ints: np.ndarray, stack: np.ndarray,
               excess: np.ndarray, linear: np.ndarray, median: float, mass: float,
               minimum: int) -> int:
    """
    One common update of the multi-scale test (MultiScaleTest._update_twist) in one call.

    The arguments: a TwistSample's fields, the update's (stamp, mu, P_mu, whether the
    null learns, whether a detection is wanted, whether the inflation was just
    updated), the last measured sample, then what stays between updates: the two
    tests' scalar state (``state``, ``values``, ``block_state``: the indices above),
    their rings, the per-window rows (``window_values`` (6, windows): the filtered
    statistics, the two tests' fractions above the median and inflations, the block
    statistics; ``window_ints`` (6, windows): the filtered rows, the block grid, the
    two tests' lags), the work space (``stack`` (17, n, n): update's scratch (14), the
    raw excess, the kept sample's covariance, its momentum in row 0), and the
    differences before the block test runs (``minimum``: momentum_blocks.EXCESS_MINIMUM).

    Checks the common case first and returns UNCOMMON, CALIBRATE or ROOM with nothing
    moved; else takes the update as MultiScaleTest.update did in Python around
    :func:`update_with_twist` (the differences and update count advanced, the period's
    running mean, the block test's first stamp and the calibration's rate, the same
    bits), leaves the best windows and value in the state, and returns DONE,
    THRESHOLD_DUE (the caller recomputes the threshold and compares) or DETECT, plus
    NEXT_CHECKED unless the next update is common as far as this state tells.
    """
    end, start, k = state[END], state[START], block_state[BLOCK_END]
    differences = block_state[DIFFERENCES] + 1
    period = values[PERIOD]
    if math.isnan(period) or not k or k == block_stamps.shape[0] or linear.shape[0] != 3 \
            or sample_stamp <= block_stamps[k - 1] or differences % 16 == 1 or \
            differences == minimum or end <= start:
        return UNCOMMON
    if not calibrated and (state[UPDATES] + 1) % CALIBRATION_EVERY == 0:
        return CALIBRATE
    if end == stamps.shape[0]:
        return ROOM
    block_state[DIFFERENCES] = differences
    state[UPDATES] += 1
    # The period as MultiScaleTest._filtered: the int64 step, then in float64.
    dt = (stamp_ns - stamps[end - 1]) * 1e-9
    if dt > 0.0:
        period = period + 0.01 * (dt - period)
    floor_ns, has_floor = state[FLOOR], state[HAS_FLOOR] != 0
    first = block_stamps[0]
    if has_floor and floor_ns > first:
        first = floor_ns
    rate = min(1.0, period / values[MEMORY]) if learn else 0.0
    t = (sample_stamp - block_state[ORIGIN]) * 1e-9
    block_statistics = window_values[5]
    added, best, value, block_best = update_with_twist(
        ad_inverse, locked, twist, connection_qd, twist_cov, joint_cov, pose_cov, structure,
        rotation, translation, com_pose_cov, com_locked, stack[14], last_mu, last_cov,
        stack[16][0], stack[15], float(min(differences, EXCESS_SAMPLES)), excess,
        sample_stamp, k, t, stamps, mu_ring, cov_ring, start, end, window_ints[4], stamp_ns,
        floor_ns, has_floor, mu, cov, window_ints[0], window_values[0], window_values[1:3],
        window_values[3:5], stack[:14], median, rate, learn, differences >= minimum,
        info, score, s0, s1, s2, y0, t1, counts, common, block_stamps, window_ints[5],
        first, mass, linear, block_statistics, window_ints[1:4])
    values[PERIOD] = period
    if added:
        block_state[BLOCK_END] = k + 1
    state[END] = end + 1
    state[BEST], state[BLOCK_BEST], values[VALUE] = best, block_best, value
    k = block_state[BLOCK_END]
    following = differences + 1
    status = DONE
    if following % 16 == 1 or following == minimum or k == block_stamps.shape[0] or \
            end + 1 == stamps.shape[0] or (state[UPDATES] + 1) % CALIBRATION_EVERY == 0:
        status = NEXT_CHECKED
    threshold_period = values[THRESHOLD_PERIOD]
    if abs(period - threshold_period) > PERIOD_TOLERANCE * threshold_period or \
            not threshold_period:
        return status + THRESHOLD_DUE
    threshold = values[THRESHOLD]
    if wanted and ((best >= 0 and value > threshold) or (
            block_best >= 0 and block_statistics[block_best] > threshold)):
        return status + DETECT
    return status


@njit(cache=True)
def any_above(statistics: np.ndarray, count: int, threshold: float) -> bool:
    """Return whether any of the first ``count`` statistics is above ``threshold``."""
    for w in range(count):
        if statistics[w] > threshold:
            return True
    return False
