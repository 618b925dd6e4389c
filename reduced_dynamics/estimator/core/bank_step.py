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
One update of the multi-scale test's two banks, in two compiled calls (numba).

Per update :class:`~reduced_dynamics.estimator.multiscale.MultiScaleTest` stored
the filtered momentum and formed each window's change
(:func:`.impulse.store_window_changes`), then the block test's statistics
(:func:`.blocks.bank_statistics`), calibrated both (:func:`.impulse.calibrated_best`,
:func:`.impulse.calibrate`) and took the blocks' best window (``np.argmax``): five
dispatched calls with Python between them. :func:`changes` makes the first two,
:func:`calibrated` the rest; numpy's ``einsum`` of the changes stays between them
(its summation order is the build's). The same kernels in the same order, each
LinAlgError caught where the Python caught it: the same bits
(test/test_bank_step.py).
"""

import math

import numpy as np
from numba import njit

from reduced_dynamics.estimator.core.blocks import bank_statistics
from reduced_dynamics.estimator.core.impulse import calibrate, calibrated_best, \
    store_window_changes


@njit(cache=True)
def changes(stamps: np.ndarray, mu_ring: np.ndarray, cov_ring: np.ndarray, start: int,
            end: int, lags: np.ndarray, stamp_ns: int, floor_ns: int, has_floor: bool,
            mu: np.ndarray, cov: np.ndarray, blocks_on: bool, blocks_ready: bool,
            info: np.ndarray, score: np.ndarray, s0: np.ndarray, s1: np.ndarray,
            s2: np.ndarray, y0: np.ndarray, t1: np.ndarray, counts: np.ndarray,
            common: np.ndarray, block_stamps: np.ndarray, block_end: int,
            block_lags: np.ndarray, first: int, mass: float, linear: np.ndarray,
            block_statistics: np.ndarray) -> tuple:
    """
    Store the sample and form the windows' changes; then the block statistics.

    Returns (whether the changes were formed (False: a singular V_L; the sample is
    stored), the ring rows, d_L, V_L^-1 d_L, windows the blocks cover (-1: the
    block test did not run or raised)). ``blocks_on``: the block test runs
    (its statistics zeroed, then written when covered); ``blocks_ready``: it has
    enough samples and its excess noise (MomentumBlocks.update).
    """
    n = mu.shape[0]
    rows = np.full(lags.shape[0], -1, dtype=np.int64)
    d = np.empty((0, n))
    solved = np.empty((0, n))
    formed = True
    try:
        rows, d, solved = store_window_changes(stamps, mu_ring, cov_ring, start, end, lags,
                                               stamp_ns, floor_ns, has_floor, mu, cov)
    except Exception:  # noqa: B902 numba catches no narrower class (a LinAlgError here)
        formed = False
    found = -1
    if blocks_on:
        block_statistics[:] = 0.0
        if blocks_ready:
            values = np.empty(0)
            try:
                found, values = bank_statistics(info, score, s0, s1, s2, y0, t1, counts,
                                                common, block_stamps, block_end, block_lags,
                                                stamp_ns, first, mass, linear)
            except Exception:  # noqa: B902 as above
                found = -1
            if found > 0:
                block_statistics[:] = values
    return formed, rows, d, solved, found


@njit(cache=True)
def _argmax(values: np.ndarray) -> int:
    """Return ``np.argmax(values)``: the first largest, or the first NaN."""
    best = 0
    for w in range(values.shape[0]):
        v = values[w]
        if math.isnan(v):
            return w
        if v > values[best]:
            best = w
    return best


@njit(cache=True)
def calibrated(rows: np.ndarray, products: np.ndarray, statistics: np.ndarray,
               above: np.ndarray, inflation: np.ndarray, median: float, rate: float,
               learn: bool, block_statistics: np.ndarray, block_above: np.ndarray,
               block_inflation: np.ndarray, block_found: int) -> tuple[int, float, int]:
    """
    Calibrate both banks; return the filtered test's best (as calibrated_best), the blocks'.

    ``products``: d_L^T V_L^-1 d_L of the covered windows (empty: none covered or
    not formed, the filtered statistics are then zeros and its best -1);
    ``block_found``: windows the blocks cover (<= 0: their best is -1, nothing
    calibrated).
    """
    best, value = -1, 0.0
    if products.shape[0]:
        best, value = calibrated_best(rows, products, statistics, above, inflation, median,
                                      rate, learn)
    else:
        statistics[:] = 0.0
    block_best = -1
    if block_found > 0:
        block_statistics[:] = calibrate(block_statistics, block_above, block_inflation,
                                        median, rate, learn)
        block_best = _argmax(block_statistics)
    return best, value, block_best
