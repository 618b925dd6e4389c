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
banks, the measured momentum and the calibration in core/bank_step.twist_step.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from reduced_dynamics.chi_square import chi2
from scipy.special import chdtri
from reduced_dynamics.estimator.core import bank_step
from reduced_dynamics.estimator.measured_momentum import TwistSample
from reduced_dynamics.estimator.momentum_blocks import EXCESS_MINIMUM, EXCESS_SAMPLES
from reduced_dynamics.estimator.multiscale_bank import CALIBRATION_EVERY, PERIOD_TOLERANCE

#: MultiScaleTest._update_twist's answer when the update is not its common one.
_UNCOMMON = object()


class TwistUpdate:
    """MultiScaleTest's common update with a measured twist (module doc)."""

    def _update_twist(self, stamp_ns: int, mu: np.ndarray, cov: np.ndarray,
                      sample: TwistSample, wanted: bool) -> Any:
        """
        Run MultiScaleTest.update on the common update in one compiled call; _UNCOMMON: not.

        Common: the update period known, the block test running on positions, and
        ``sample`` a common sample (:meth:`.MomentumBlocks.prepare`'s conditions, no
        excess decomposition due; checked before anything moves). The same steps as
        :meth:`.MultiScaleTest.update` with its ``_filtered``, in the same order: the
        period, the block test's first stamp and the calibration's rate in the call
        (core/bank_step.twist_step), the arrays that stay passed as one kept tuple.
        """
        blocks, period, end = self.blocks, self._period, self._end
        last, k = blocks._last, blocks._end
        differences = blocks._differences + 1
        if period is None or last is None or not k or k == blocks._capacity or \
                len(blocks.linear) != 3 or sample[0] <= blocks._stamps[k - 1] or \
                differences % 16 == 1 or differences == EXCESS_MINIMUM or \
                not blocks.active or end <= self._start:
            return _UNCOMMON
        # MomentumBlocks.prepare's state, advanced (called per sample).
        blocks._last = blocks._keep
        blocks._differences = differences
        self._updates += 1
        if not self._updates % CALIBRATION_EVERY:
            # As in update.
            p = np.clip(self._above, 0.5, 1.0 - 1e-3)
            self.inflation[:] = np.maximum(1.0, self._median / chdtri(self.n, p))
        if end == self._capacity:
            # (_filtered takes the period from the last stamp first: it stays the last.)
            self._make_room(stamp_ns)
            end = self._end
        floor = self.floor_ns
        added, period, best, value, block_best = bank_step.twist_step(
            *sample, stamp_ns, mu, cov, 0 if floor is None else floor, floor is not None,
            self.quiet, period, self.calibration_memory, differences >= EXCESS_MINIMUM,
            float(min(differences, EXCESS_SAMPLES)), last[0], last[1], self._start, end, k,
            blocks._origin_ns, *self._kept_arrays())
        # _filtered: the threshold when the period moved (the call does not read it).
        self._period = period
        threshold_period = self._threshold_period
        if abs(period - threshold_period) > PERIOD_TOLERANCE * threshold_period or \
                not threshold_period:
            self._threshold_period = period
            self.threshold = float(chi2.isf(self.significance(period), self.n))
        if added:
            blocks._end = k + 1
        self._end = end + 1
        found = None
        if wanted and best >= 0 and value > self.threshold:
            found = self._detection(best)
        if not wanted:
            return None
        return self._block_detection(stamp_ns, found, block_best)

    def _kept_arrays(self) -> tuple:
        """
        Return the arrays bank_step.twist_step takes that stay between updates, as one tuple.

        Built again when one of them was replaced (a ring grown or compacted, the block
        test's positions started, a new excess): the identities checked are those.
        """
        blocks = self.blocks
        kept = self._kept
        if kept is not None and kept[0] is self._stamps and kept[1] is blocks._stamps and \
                kept[2] is blocks._positions and kept[3] is blocks.excess:
            return kept[4]
        arrays = (blocks._excess_raw, *blocks._keep, blocks.excess, self._stamps, self._mu,
                  self._cov, self._lags_ns, self._rows, self.statistics, self._above,
                  self.inflation, self._scratch, self._median, blocks._info, blocks._score,
                  *blocks._positions, blocks._common, blocks._stamps, blocks._lags_ns,
                  blocks.mass, blocks.linear, blocks.statistics, self._grid)
        self._kept = (self._stamps, blocks._stamps, blocks._positions, blocks.excess, arrays)
        return arrays
