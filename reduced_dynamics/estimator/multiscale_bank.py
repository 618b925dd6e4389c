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
The multi-scale test's bank of windows, its settings, and what it detects.

A geometric bank of window lengths (0.05-3 s, ratio 1.5, and 3 s itself: 12
windows); a detection names the window, the pulse's start and the momentum before
it (docs/multiscale_events.md).
"""

from __future__ import annotations

import math
from typing import Any, Callable, NamedTuple

import numpy as np
from reduced_dynamics.estimator.core.bank_step import (  # noqa: F401 (re-exported)
    CALIBRATION_EVERY, PERIOD_TOLERANCE)

#: Shortest and longest window [s] and the ratio between successive windows.
SHORTEST = 0.05
LONGEST = 3.0
RATIO = 1.5
#: Memory [s] of the null calibration (the running fraction of quiet updates whose
#: statistic is above the chi2_n median). Updates between its inflation's updates
#: (CALIBRATION_EVERY) and the relative change of the update period after which the
#: threshold is recomputed (PERIOD_TOLERANCE): core/bank_step.py's, which uses them.
CALIBRATION_MEMORY = 600.0


def state_slot(array: str, index: int, kind: Callable[[Any], Any] = int) -> property:
    """
    Return a property kept in element ``index`` of the instance's array ``array``.

    The state bank_step.twist_step reads and advances in place (one array argument,
    not one per scalar); Python reads and sets it as an attribute of type ``kind``.
    """
    def get(self: Any) -> Any:
        return kind(getattr(self, array)[index])

    def set_(self: Any, value: Any) -> None:
        getattr(self, array)[index] = value
    return property(get, set_)


def window_bank(shortest: float = SHORTEST, longest: float = LONGEST,
                ratio: float = RATIO) -> np.ndarray:
    """Return the geometric bank of window lengths [s], ``longest`` included."""
    count = int(math.floor(math.log(longest / shortest) / math.log(ratio) + 1e-9)) + 1
    windows = shortest * ratio ** np.arange(count)
    if windows[-1] < longest * (1 - 1e-9):
        windows = np.append(windows, longest)
    return windows


class ImpulseDetection(NamedTuple):
    """A window whose momentum change is significant."""

    #: the pulse's estimated start [ns] and the length [s] of the window whose
    #: statistic is largest
    start_ns: int
    window: float
    statistic: float
    #: the momentum before the pulse (at the longest significant window's start)
    #: and its covariance
    mu_before: np.ndarray
    cov_before: np.ndarray
    #: whether the block test on measured momenta found it (mu before is then theirs)
    measured: bool = False
