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
Bench rows of section ``prediction`` on what the reduction costs (issue 26, item 5).

* The 24-joint random tree: reduced DOP853 at rtol 1e-8 against full ``aba``
  DOP853 at equal error (the paper robot's rows are :func:`.bench.bench_prediction`'s).
* The Pinocchio floor: one reduced evaluation needs ``crba`` and
  ``computeCoriolisMatrix`` (:mod:`.reduction.lean_field`), one full evaluation
  one ``aba``. Timed alone, in loops, at the prediction's start state; the floor
  of the time ratio at equal error is ``(crba + Coriolis) N_reduced / (aba
  N_full)`` with the evaluation counts N of the two runs (N_full interpolated
  at the reduced run's error). A row gives the measured ratio over that floor.
"""

from __future__ import annotations

import functools
import time
from typing import Any, Callable, Optional

import numpy as np
import pinocchio as pin

#: Shape joints and rtol of the random-tree row (issue 26: 24 joints at 1e-8).
TREE_JOINTS, TREE_RTOL = 24, 1e-8
TREE_FULL_RTOLS = (1e-6, 1e-7, 1e-8, 1e-9, 1e-10, 1e-11)
#: Calls per timing loop of the floor, repeats taken as the minimum.
FLOOR_CALLS = 500


def pinocchio_costs(robot, state, calls: int = FLOOR_CALLS, repeats: int = 9) -> dict:
    """
    Return seconds per ``crba``, ``computeCoriolisMatrix`` and ``aba`` call at ``state``.

    CPU time, as the prediction rows; the three loops take turns (a change of
    machine load hits all three) and each keeps its fastest repeat.
    """
    model = robot.model
    data = model.createData()
    q = robot.identity_configuration(state.qbar).copy()
    v = np.concatenate([state.xi, state.qbar_dot])
    tau = np.zeros(model.nv)
    runs = {'crba': lambda: pin.crba(model, data, q),
            'coriolis': lambda: pin.computeCoriolisMatrix(model, data, q, v),
            'aba': lambda: pin.aba(model, data, q, v, tau)}
    out = {name: np.inf for name in runs}
    for _ in range(repeats):
        for name, call in runs.items():
            start = time.process_time()
            for _ in range(calls):
                call()
            out[name] = min(out[name], (time.process_time() - start) / calls)
    return out


def interpolated_evaluations(rows: list, error: float) -> float:
    """Full evaluations at ``error``, log-log interpolated in a sweep's rows (ends clamp)."""
    errors = np.log10([max(r['error'], 1e-300) for r in rows])
    counts = np.log10([r['evaluations'] for r in rows])
    order = np.argsort(errors)
    return float(10.0 ** np.interp(np.log10(max(error, 1e-300)), errors[order],
                                   counts[order]))


def floor_figures(report: Any, name: str, costs: dict, reduced_row: dict, full_rows: list,
                  ratio: Optional[float]) -> None:
    """Add the floor of a reduced-vs-full row and the measured ratio over it."""
    from reduced_dynamics.bench import make_figure
    full_evaluations = interpolated_evaluations(full_rows, reduced_row['error'])
    per_call = (costs['crba'] + costs['coriolis']) / costs['aba']
    floor = per_call * reduced_row['evaluations'] / full_evaluations
    note = (f'crba {1e6 * costs["crba"]:.2f} + Coriolis {1e6 * costs["coriolis"]:.2f} us '
            f'vs aba {1e6 * costs["aba"]:.2f} us per call; {reduced_row["evaluations"]} vs '
            f'{full_evaluations:.0f} evaluations at equal error')
    report.add(make_figure('prediction', f'{name}: Pinocchio floor of the ratio', 'ratio',
                           [floor], note=note))
    if ratio is not None:
        report.add(make_figure('prediction', f'{name}: ratio over its floor', 'x floor',
                               [ratio / floor], target='<= 1.2',
                               check=lambda r: r <= 1.2,
                               note='measured ratio to full aba / Pinocchio floor'))


def bench_reduction_cost(report: Any, robot, settings: Any) -> None:
    """Add the random-tree row and the floors (after :func:`.bench.bench_prediction`)."""
    from reduced_dynamics.bench import HORIZON
    from reduced_dynamics.geometry.isotropy import MomentumClass
    from reduced_dynamics.validation import random_scenario
    paper = random_scenario(robot, MomentumClass.GENERIC, 0).state
    sweep = report.details.get('prediction_sweep')
    if sweep:
        row = next((r for r in sweep['reduced dop853'] if r['tolerance'] == 1e-10), None)
        figure = next((f for f in report.figures
                       if f.name == 'reduced dop853 rtol 1e-10' and f.section == 'prediction'),
                      None)
        if row is not None and 'evaluations' in row:
            floor_figures(report, 'reduced dop853 rtol 1e-10 (paper robot)',
                          pinocchio_costs(robot, paper), row, sweep['full dop853'],
                          figure.ratio if figure is not None else None)
    _bench_tree(report, settings, HORIZON)


def _bench_tree(report: Any, settings: Any, horizon: float) -> None:
    from reduced_dynamics.bench import full_prediction, make_figure, matched_time, \
        reduced_prediction, round_robin
    from reduced_dynamics.full_dynamics import FullDynamics
    from reduced_dynamics.geometry.isotropy import MomentumClass
    from reduced_dynamics.robot.model import load_robot
    from reduced_dynamics.robot.random_tree import random_tree_urdf
    from reduced_dynamics.validation import random_scenario
    robot = load_robot(random_tree_urdf(TREE_JOINTS, seed=1))
    scenario = random_scenario(robot, MomentumClass.GENERIC, 0)
    state, torque = scenario.state, scenario.torque
    times = np.linspace(0.0, horizon, settings.prediction_points)
    reference = FullDynamics(robot, torque).simulate(state, times, 1e-13, 1e-13).qbar

    full_run = functools.partial(full_prediction, robot, torque, state, times)

    def reduced_run(counter: Optional[list] = None) -> Callable[[], Any]:
        return reduced_prediction(robot, torque, state, times, 'dop853', TREE_RTOL, counter)

    rtols = TREE_FULL_RTOLS[::2] if settings.quick else TREE_FULL_RTOLS
    runs = [('full', rtol, full_run(rtol)) for rtol in rtols]
    runs.append(('reduced', TREE_RTOL, reduced_run()))
    results, seconds = round_robin([run for _, _, run in runs], settings.repeats)
    rows = []
    for (kind, rtol, _), result, timing in zip(runs, results, seconds):
        counter = [0]
        (full_run(rtol, counter) if kind == 'full' else reduced_run(counter))()
        rows.append({'kind': kind, 'tolerance': rtol, 'seconds': timing,
                     'error': float(np.max(np.abs(result.qbar - reference))),
                     'evaluations': counter[0]})
    full_rows = [r for r in rows if r['kind'] == 'full']
    reduced = rows[-1]
    report.details['tree_prediction_sweep'] = rows
    baseline, inside = [], True
    for repeat in range(settings.repeats):
        value, inside = matched_time([r['error'] for r in full_rows],
                                     [r['seconds'][repeat] for r in full_rows],
                                     reduced['error'])
        baseline.append(value)
    ratios = [s / b for s, b in zip(reduced['seconds'], baseline)]
    note = f'error {reduced["error"]:.1e} rad, {reduced["evaluations"]} evaluations'
    if not inside:
        note += ' (outside the full sweep: nearest end)'
    name = f'reduced dop853 rtol {TREE_RTOL:g}, random tree m={TREE_JOINTS}'
    figure = report.add(make_figure('prediction', name, 'ms',
                                    [1e3 * s for s in reduced['seconds']],
                                    'full aba dop853 at equal error',
                                    [1e3 * b for b in baseline], ratios, 'ratio <= 1',
                                    lambda r: r <= 1.0, note))
    floor_figures(report, name, pinocchio_costs(robot, state), reduced, full_rows,
                  figure.ratio)
