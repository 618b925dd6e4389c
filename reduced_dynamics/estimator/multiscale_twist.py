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
The multi-scale test's common update with a measured twist: one compiled call.

:class:`TwistUpdate` is :class:`~reduced_dynamics.estimator.multiscale.MultiScaleTest`'s
part for the common update (an SE(3) base's twist at the row): the period, both
banks, the measured momentum, the calibration and the comparison with the threshold
in core/bank_step.twist_step, on the tests' state arrays.
"""

from __future__ import annotations

import math
from typing import Any, Optional

import numpy as np
from reduced_dynamics.chi_square import chi2
from scipy.special import chdtri
from reduced_dynamics.estimator.core import bank_step
from reduced_dynamics.estimator.measured_momentum import TwistSample
from reduced_dynamics.estimator.momentum_blocks import EXCESS_MINIMUM
from reduced_dynamics.estimator.multiscale_bank import CALIBRATION_EVERY, state_slot

#: MultiScaleTest._update_twist's answer when the update is not its common one.
_UNCOMMON = object()


class TwistUpdate:
    """MultiScaleTest's common update with a measured twist (module doc)."""

    # The scalar state bank_step.twist_step reads and advances in place, as attributes:
    # the ring's end and start, the update count, the threshold and the period it was
    # computed for, the calibration memory [s] (core/bank_step.py: the indices).
    _end = state_slot('_state', bank_step.END)
    _start = state_slot('_state', bank_step.START)
    _updates = state_slot('_state', bank_step.UPDATES)
    threshold = state_slot('_values', bank_step.THRESHOLD, float)
    _threshold_period = state_slot('_values', bank_step.THRESHOLD_PERIOD, float)
    calibration_memory = state_slot('_values', bank_step.MEMORY, float)

    def _twist_arrays(self, n: int, count: int) -> None:
        """
        Allocate the state and the per-window and work arrays twist_step takes.

        ``_state``, ``_values``: the scalars above and the floor, the period, the last
        best windows; ``_window_values`` (6, windows): the filtered statistics, the two
        tests' fractions above the median and inflations, the block statistics;
        ``_window_ints``: the filtered rows, the block grid, the two tests' lags;
        ``_stack`` (17, n, n): update's scratch (14), the block test's raw excess, its
        last sample's covariance and momentum (row 0), kept for the next difference.
        """
        self._state = np.zeros(7, dtype=np.int64)
        self._values = np.array([math.nan, math.inf, 0.0, 0.0, 0.0])
        self._window_values = np.zeros((6, count))
        self._window_ints = np.zeros((6, count), dtype=np.int64)
        self._lags_ns = self._window_ints[4]
        self._stack = np.zeros((17, n, n))
        # The arguments that stay between calls (_kept_arrays), and whether the last
        # call told the next update common.
        self._kept: Optional[tuple] = None
        self._next_common = False

    def _share_with_blocks(self) -> None:
        """Make the block test's per-window and work arrays views of the arrays above."""
        blocks, stack = self.blocks, self._stack
        self._window_ints[5] = blocks._lags_ns
        blocks._lags_ns = self._window_ints[5]
        blocks.statistics = self._window_values[5]
        blocks._excess_raw = stack[14]
        blocks._keep = (stack[16][0], stack[15])

    @property
    def floor_ns(self) -> Optional[int]:
        """Return the stamp no window reaches back before (the last event's end, a reset)."""
        return int(self._state[bank_step.FLOOR]) if self._state[bank_step.HAS_FLOOR] else None

    @floor_ns.setter
    def floor_ns(self, value: Optional[int]) -> None:
        self._state[bank_step.HAS_FLOOR] = value is not None
        self._state[bank_step.FLOOR] = 0 if value is None else value

    @property
    def _period(self) -> Optional[float]:
        """Return the update period's running mean [s] (None: not known yet)."""
        period = float(self._values[bank_step.PERIOD])
        return None if math.isnan(period) else period

    @_period.setter
    def _period(self, value: Optional[float]) -> None:
        self._values[bank_step.PERIOD] = math.nan if value is None else value

    def _update_twist(self, stamp_ns: int, mu: np.ndarray, cov: np.ndarray,
                      sample: TwistSample, wanted: bool) -> Any:
        """
        Run MultiScaleTest.update on the common update in one compiled call; _UNCOMMON: not.

        Common: the update period known, the block test running on positions, and
        ``sample`` a common sample (:meth:`.MomentumBlocks.prepare`'s conditions, no
        excess decomposition due). The call (core/bank_step.twist_step) makes the steps
        of :meth:`.MultiScaleTest.update` with its ``_filtered``, in the same order, on
        the tests' state arrays, compares the best statistics with the threshold, and
        tells whether the next update is common as far as the state tells
        (``_next_common``); when it is not, :meth:`_checked_twist` checks it here first.
        Python is left with the rare outcomes (the threshold due, a detection).
        """
        blocks = self.blocks
        last = blocks._last
        if not self._next_common or last is None or not blocks.active:
            return self._checked_twist(stamp_ns, mu, cov, sample, wanted)
        kept = self._kept
        if kept[0] is not self._stamps or kept[1] is not blocks._stamps or \
                kept[2] is not blocks._positions or kept[3] is not blocks.excess:
            kept = self._kept_arrays()
        status = bank_step.twist_step(*sample, stamp_ns, mu, cov, self.quiet, wanted, False,
                                      last[0], last[1], *kept[4])
        if status == bank_step.DONE:
            # MomentumBlocks.prepare's last sample: the one the call left in _keep.
            blocks._last = blocks._keep
            return None
        return self._twist_status(status, stamp_ns, mu, cov, sample, wanted)

    def _checked_twist(self, stamp_ns: int, mu: np.ndarray, cov: np.ndarray,
                       sample: TwistSample, wanted: bool) -> Any:
        """
        :meth:`_update_twist` where the last call did not tell the update common.

        The checks before anything moves, from Python (as the call makes them), then the
        inflation when due and room in the filtered ring, then the call.
        """
        self._next_common = False
        blocks = self.blocks
        # The state arrays read once (their attributes are properties).
        end, start, updates = self._state.tolist()[:3]
        k, differences = blocks._state.tolist()[:2]
        last = blocks._last
        differences += 1
        if self._period is None or last is None or not k or k == blocks._capacity or \
                len(blocks.linear) != 3 or sample[0] <= blocks._stamps[k - 1] or \
                differences % 16 == 1 or differences == EXCESS_MINIMUM or \
                not blocks.active or end <= start:
            return _UNCOMMON
        if not (updates + 1) % CALIBRATION_EVERY:
            self._inflate()
        if end == self._capacity:
            self._make_room(stamp_ns)
        status = bank_step.twist_step(*sample, stamp_ns, mu, cov, self.quiet, wanted, True,
                                      last[0], last[1], *self._kept_arrays()[4])
        return self._twist_status(status, stamp_ns, mu, cov, sample, wanted, checked=True)

    def _inflate(self) -> None:
        """Set the null's inflation from the fractions above the median (update's calibration)."""
        # T ~ lambda chi2_n above the median a fraction p of the time: lambda =
        # median / isf(p). Never below 1 (never looser than the noise model).
        p = np.clip(self._above, 0.5, 1.0 - 1e-3)
        self.inflation[:] = np.maximum(1.0, self._median / chdtri(self.n, p))

    def _twist_status(self, status: int, stamp_ns: int, mu: np.ndarray, cov: np.ndarray,
                      sample: TwistSample, wanted: bool, checked: bool = False) -> Any:
        """
        Act on bank_step.twist_step's answers other than DONE (:meth:`_update_twist`).

        ``checked``: the call came from :meth:`_checked_twist`, whose checks passed; if
        the compiled call still finds the update uncommon (the two lists of checks
        disagree), the update takes the general path (_UNCOMMON), never the checks again.
        """
        if status < bank_step.NEXT_CHECKED:
            self._next_common = True
        else:
            self._next_common = False
            status -= bank_step.NEXT_CHECKED
        if status in (bank_step.UNCOMMON, bank_step.CALIBRATE, bank_step.ROOM):
            # Nothing moved: the state changed since the last call told the update
            # common (a stamp not after the last): the checked path, once.
            self._next_common = False
            if checked:
                return _UNCOMMON
            return self._checked_twist(stamp_ns, mu, cov, sample, wanted)
        self.blocks._last = self.blocks._keep
        if status == bank_step.THRESHOLD_DUE:
            # _filtered: the threshold when the period moved (chi2.isf is ~50 us).
            period = self._period
            self._threshold_period = period
            self.threshold = float(chi2.isf(self.significance(period), self.n))
        if not wanted or status == bank_step.DONE:
            return None
        best = int(self._state[bank_step.BEST])
        found = None
        if best >= 0 and self._values[bank_step.VALUE] > self.threshold:
            found = self._detection(best)
        return self._block_detection(stamp_ns, found, int(self._state[bank_step.BLOCK_BEST]))

    def _kept_arrays(self) -> tuple:
        """
        Return the arguments of bank_step.twist_step that stay between updates, and keys.

        Built again when one of them was replaced (a ring grown or compacted, the block
        test's positions started, a new excess): the identities kept with them (the
        first four) are those.
        """
        blocks = self.blocks
        kept = self._kept
        if kept is not None and kept[0] is self._stamps and kept[1] is blocks._stamps and \
                kept[2] is blocks._positions and kept[3] is blocks.excess:
            return kept
        arrays = (self._state, self._values, blocks._state, self._stamps, self._mu, self._cov,
                  blocks._stamps, blocks._info, blocks._score, blocks._common,
                  *blocks._positions, self._window_values, self._window_ints, self._stack,
                  blocks.excess, blocks.linear, self._median, blocks.mass, EXCESS_MINIMUM)
        self._kept = (self._stamps, blocks._stamps, blocks._positions, blocks.excess, arrays)
        return self._kept
