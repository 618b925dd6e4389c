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
What judged predictions leave behind: running counts, maxima and medians per mode.

A prediction whose horizon has passed is compared with the measurements
(:mod:`.prediction`); afterwards only these aggregates remain of it, so a node
that predicts once a second for weeks holds the same few kilobytes (issue 27).
Medians come from :class:`~.running_quantile.RunningQuantile`: exact over the
first :data:`~.running_quantile.QUANTILE_CAPACITY` predictions of a mode (68
minutes at the default 1 Hz), a systematic sample of them after that.
"""

from __future__ import annotations

from collections import Counter
from typing import Any, Optional

from reduced_dynamics.estimator.running_quantile import RunningQuantile

RESIDUALS = ('shape_residual', 'position_residual', 'attitude_residual')


class ModeStatistics:
    """
    Aggregates of one effective prediction mode.

    Memory bound: four :class:`RunningQuantile` (evaluations and the three
    residuals), each at most its capacity of floats.
    """

    def __init__(self) -> None:
        """Start with no prediction."""
        self.predictions = self.compared = self.failed = 0
        self.evaluations = RunningQuantile()
        self.residuals = {key: RunningQuantile() for key in RESIDUALS}

    def entry(self, judged_by: str) -> dict:
        """Return this mode's summary: the keys of ``prediction_residuals`` entries."""
        out: dict = {'predictions': self.predictions, 'compared': self.compared,
                     'failed': self.failed, 'judged_by': judged_by,
                     'evaluations_median': self.evaluations.median()}
        for key, values in self.residuals.items():
            out[key + '_max'] = values.maximum
            out[key + '_median'] = values.median()
        return out


class PredictionStatistics:
    """
    Running aggregates over every finished prediction (per mode and over all).

    Memory bound: one :class:`ModeStatistics` per effective mode (four at most),
    two more running quantiles over all modes, a counter per failure kind and
    the last failure's text.
    """

    def __init__(self, prescribed: frozenset = frozenset()) -> None:
        """Start empty; ``prescribed``: the modes judged by the base path."""
        self.prescribed = prescribed
        self.by_mode: dict[str, ModeStatistics] = {}
        self.finished = 0
        self.failed = 0
        #: predictions published without their covariance (the sample points diverged)
        self.covariance_failures = 0
        self.failure_kinds: Counter = Counter()
        self.last_failure: Optional[str] = None
        #: whether the most recently finished prediction failed
        self.last_failed = False
        self.shape = RunningQuantile()
        self.position = RunningQuantile()

    def add(self, done: Any) -> None:
        """Take a finished prediction (a :class:`~.prediction.FinishedPrediction`)."""
        mode = self.by_mode.get(done.mode)
        if mode is None:
            mode = self.by_mode[done.mode] = ModeStatistics()
        self.finished += 1
        mode.predictions += 1
        mode.evaluations.add(done.result.evaluations)
        if getattr(done.result, 'covariance_failure', None) is not None:
            self.covariance_failures += 1
        failure = done.result.failure
        self.last_failed = failure is not None
        if failure is not None:
            self.failed += 1
            mode.failed += 1
            self.failure_kinds[done.result.failure_kind] += 1
            self.last_failure = failure
        if done.compared:
            mode.compared += 1
            for key, values in mode.residuals.items():
                values.add(getattr(done, key))
            self.shape.add(done.shape_residual)
            self.position.add(done.position_residual)

    def residuals_by_mode(self) -> dict:
        """
        Residual statistics per effective mode (max and median over predictions).

        Prescribed modes (planned, held_velocity) are judged by the base path
        (position, attitude); their shape residual says how far the arm left the
        prescribed path. Torque modes are judged by the shape.
        """
        return {name: self.by_mode[name].entry('base path' if name in self.prescribed
                                               else 'shape')
                for name in sorted(self.by_mode)}
