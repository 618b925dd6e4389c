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

"""The bench rows of what the reduction costs (reduction_bench.py)."""

from dataclasses import asdict

from reduced_dynamics import bench, reduction_bench
from reduced_dynamics.robot.model import load_robot


def test_floor_is_the_pinocchio_ratio_times_the_evaluation_ratio():
    report = bench.Report({}, {})
    costs = {'crba': 1.0, 'coriolis': 2.0, 'aba': 2.0}
    full = [{'error': 1e-6, 'evaluations': 100}, {'error': 1e-10, 'evaluations': 300}]
    reduced = {'error': 1e-8, 'evaluations': 120}
    reduction_bench.floor_figures(report, 'x', costs, reduced, full, 3.0)
    floor, over = report.figures
    # 1.5 per call, 120 against 10^((2 + 2.477) / 2) = 173.2 interpolated evaluations.
    assert abs(floor.median - 1.5 * 120 / (100 * 3 ** 0.5)) < 1e-9
    assert abs(over.median - 3.0 / floor.median) < 1e-12 and over.met is False


def test_tree_row_and_paper_floor_are_measured():
    settings = bench.Settings(repeats=1, full_rtols=(1e-8, 1e-11), reduced_rtols=(1e-10,),
                              dg_steps=(0.05,), prediction_points=5, quick=True)
    report = bench.Report(bench.machine_info(), asdict(settings))
    bench.bench_prediction(report, load_robot(), settings)
    names = [f.name for f in report.figures]
    tree = 'reduced dop853 rtol 1e-08, random tree m=24'
    assert tree in names
    assert f'{tree}: Pinocchio floor of the ratio' in names
    assert 'reduced dop853 rtol 1e-10 (paper robot): ratio over its floor' in names
    rows = report.details['tree_prediction_sweep']
    assert all(r['evaluations'] > 0 and r['error'] < 1e-4 for r in rows)


def test_prediction_runs_take_turns_over_the_repeats():
    # round_robin (bench_prediction and the tree row): every run once per repeat, in turns,
    # so a change of machine load hits the reduced and the full runs alike.
    order = []
    runs = [lambda k=k: order.append(k) or 10 * k for k in range(3)]
    results, seconds = bench.round_robin(runs, 2)
    assert order == [0, 1, 2, 0, 1, 2] and results == [0, 10, 20]
    assert [len(s) for s in seconds] == [2, 2, 2] and min(min(s) for s in seconds) >= 0.0
