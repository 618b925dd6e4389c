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
Bench rows of section prediction: a prediction with covariance against one without.

The paper robot's 2 s prediction (the node's defaults: DOP853 at 1e-10, points
every 0.05 s) from the simulator's generic start, with a start uncertainty of
the size a filter reaches on realistic sensors; each mode run with and without
the covariance (:mod:`reduced_dynamics.estimator.prediction_covariance`),
interleaved, so a change of load hits both alike. Target: ratio <= 3 (issue 26).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from reduced_dynamics.estimator.prediction import PredictionJob, PredictionSettings
from reduced_dynamics.estimator.prediction_covariance import StartUncertainty
from reduced_dynamics.robot.momentum import body_momentum, momentum_map
from reduced_dynamics.simulator import initial_state

MODES = ('held_torque', 'coast', 'held_velocity')


def bench_covariance(report: Any, robot: Any, settings: Any) -> None:
    """Add one row per mode: ms with covariance, ratio to without (target <= 3)."""
    import time

    from reduced_dynamics.bench import make_figure
    n, m = robot.n, robot.m
    state, _ = initial_state(robot, 'generic', 4)
    blocks = robot.metric_blocks(state.qbar)
    mu = momentum_map(robot.group, state.g, body_momentum(blocks, state.xi, state.qbar_dot))
    filter_cov = np.diag(np.r_[[1e-3 ** 2] * 3, [5e-4 ** 2] * 3, [0.01 ** 2] * n,
                               [1e-4 ** 2] * n])
    uncertainty = StartUncertainty(filter_cov, np.zeros(n), np.full(m, 1e-4 ** 2),
                                   np.full(m, 0.005 ** 2), np.diag(np.full(m, 0.003 ** 2)))
    prediction = PredictionSettings(2.0, 0.05, shape_names=tuple(robot.shape_joint_names))

    def run(mode: str, with_covariance: bool) -> PredictionJob:
        job = PredictionJob(robot.worker_copy(), prediction, 0, state.g, state.qbar,
                            state.qbar_dot, mu, np.zeros(m), None, mode, mode, None,
                            uncertainty if with_covariance else None)
        job.run()
        return job

    for mode in MODES:
        run(mode, True)  # first call: imports, compilation
        plain, covariance = [], []
        for _ in range(settings.repeats):
            for timings, flag in ((plain, False), (covariance, True)):
                start = time.perf_counter()
                job = run(mode, flag)
                timings.append(time.perf_counter() - start)
        result = job.result.covariance
        ratios = [c / p for c, p in zip(covariance, plain)]
        report.add(make_figure(
            'prediction', f'{mode} prediction with covariance', 'ms',
            [1e3 * s for s in covariance], 'the same prediction without',
            [1e3 * s for s in plain], ratios, 'ratio <= 3', lambda r: r <= 3.0,
            f'{result.points} sample points in one batch, {result.evaluations} batch '
            f'evaluations; {job.result.evaluations} DOP853 evaluations'))
