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

"""Smoke test of the benchmark machinery at tiny sizes (structure and ratios, no timings)."""

import json
import math

import numpy as np
import pytest

from reduced_dynamics import bench
from reduced_dynamics.cli import build_parser


def _tiny() -> bench.Settings:
    return bench.Settings(repeats=1, update_samples=60, update_warmup=0.05, crba_calls=50,
                          full_rtols=(1e-6, 1e-9), reduced_rtols=(1e-8,),
                          dg_steps=(0.05,), prediction_points=11, replay_seconds=0.3,
                          memory_short_seconds=0.2, memory_long_seconds=0.4,
                          scaling_samples=40, scaling_evaluations=3,
                          shape_joints=(6, 12), planned_bag_seconds=2.0,
                          planned_bags=('paper_thruster',), payload_seconds=4.0,
                          step_test_samples=2200, quick=True)


def test_statistics_helpers():
    median, q1, q3 = bench.spread([1.0, 2.0, 3.0, 4.0, 100.0])
    assert (median, q1, q3) == (3.0, 2.0, 4.0)
    assert math.isclose(bench.fit_exponent([6, 12, 24], [36.0, 144.0, 576.0]), 2.0)
    time_at, inside = bench.matched_time([1e-4, 1e-8], [1.0, 100.0], 1e-6)
    assert inside and math.isclose(time_at, 10.0)
    _, inside = bench.matched_time([1e-4, 1e-8], [1.0, 100.0], 1e-12)
    assert not inside
    figure = bench.make_figure('s', 'x', 'us', [2.0, 4.0], 'base', [1.0, 1.0], [2.0, 4.0],
                               'ratio <= 10', lambda r: r <= 10.0)
    assert figure.ratio == 3.0 and figure.met is True and figure.baseline_median == 1.0


#: The node section (real DDS, processes) has its own test: test_bench_node.py; the fleet
#: section (process pools, Ray) its own in test_fleet.py.
TINY_SECTIONS = [s for s in bench.SECTIONS if s not in ('node', 'fleet')]


@pytest.fixture(scope='session')
def tiny_report() -> bench.Report:
    """
    Run every section but node and fleet once at tiny sizes; the tests below read it.

    Session scope: pytest-xdist interleaves other modules' tests with this group's, and
    a module-scoped fixture is torn down at each switch (CI ran it twice, ~400 s each).
    """
    return bench.run_bench(_tiny(), TINY_SECTIONS)


#: The tests reading tiny_report run in one pytest-xdist worker, so it is made once.
ONE_WORKER = pytest.mark.xdist_group('bench_tiny_report')


@ONE_WORKER
def test_bench_sections_tiny(tiny_report, tmp_path):
    sections, report = TINY_SECTIONS, tiny_report
    assert {f.section for f in report.figures} == set(sections)
    for figure in report.figures:
        assert figure.low <= figure.median <= figure.high or figure.low == figure.high
        if figure.baseline_median is not None:
            assert figure.ratio is not None and figure.ratio > 0.0
            assert math.isfinite(figure.ratio)
    names = [f.name for f in report.figures]
    assert 'estimator update (paper robot)' in names
    first_call = [f for f in report.figures if f.name == 'filter kernels: first call, cached']
    assert first_call and 0.0 < first_call[0].median < 600.0
    assert 'wrench step test, anchored vs explicit (paper robot)' in names
    assert 'multi-scale event test (paper robot)' in names
    assert any(n.startswith('reduced dop853') for n in names)
    assert any(n.startswith('reduced discrete_gradient') for n in names)
    assert 'replay throughput (prediction off)' in names
    typestore = [f for f in report.figures
                 if f.name == "a bag's message types, shared typestore"]
    assert typestore and typestore[0].baseline_median > 0.0 and typestore[0].ratio > 0.0
    assert 'update cost exponent' in names
    assert any(n.startswith('base motion for a 10 s plan') for n in names)
    assert any(n.startswith('replay with defaults, paper_thruster') for n in names)
    sweep = report.details['prediction_sweep']
    assert all(row['error'] < 1e-2 for row in sweep['full dop853'])
    assert report.details['replay_memory']['long']['processed'] > \
        report.details['replay_memory']['short']['processed'] > 0
    assert np.all(np.isfinite(report.details['scaling']['update_s']))
    table = bench.format_report(report)
    assert 'estimator update' in table and 'machine:' in table
    path = tmp_path / 'bench.csv'
    bench.write_csv(report, str(path))
    assert len(path.read_text().splitlines()) == len(report.figures) + 1
    json.dumps(report.to_dict())


def test_planned_bags_must_name_shipped_bags(tmp_path):
    settings = bench.Settings(planned_bags=('paper_thruster', 'paper_thrusters'))
    with pytest.raises(ValueError, match=r"no shipped bag named \['paper_thrusters'\]"):
        bench.bench_planned(bench.Report({}, {}), settings, str(tmp_path))


def test_cli_registers_bench():
    args = build_parser().parse_args(['bench', '--quick', '--repeats', '2', '--json', 'x.json',
                                      '--csv', 'x.csv', '--sections', 'update'])
    assert args.quick and args.repeats == 2 and args.sections == ['update']
    assert args.func is bench._run


@ONE_WORKER
def test_update_section_times_fixed_lag_smoothing_against_crba_and_without(tiny_report):
    figures = {f.name: f for f in tiny_report.figures if f.section == 'update'}
    lagged = figures['estimator update, fixed-lag smoothing 0.5 s (paper robot)']
    assert lagged.baseline == 'crba' and lagged.ratio > 0.0
    share = figures['fixed-lag smoothing: update with it / without (paper robot)']
    assert share.baseline_median == figures['estimator update (paper robot)'].median
    assert math.isfinite(share.ratio) and share.ratio > 0.0


@ONE_WORKER
def test_update_section_times_odometry_off_the_rows(tiny_report):
    # Sensors on their own clocks: every base sample between two joint-state rows.
    figures = {f.name: f for f in tiny_report.figures if f.section == 'update'}
    off = figures['estimator update, 1 kHz joints + 1 kHz odometry off their stamps '
                  '(paper robot)']
    assert off.baseline == 'crba' and off.ratio > 0.0 and 'ratio <= 20' in off.target


@ONE_WORKER
def test_replay_rows_against_rosbags(tiny_report):
    # Issue 19's two replay targets: --no-smooth (>= 0.5) and smoothed (>= 0.4) replay,
    # each against rosbags read+deserialize of the same bag, in the same repeats.
    figures = {f.name: f for f in tiny_report.figures if f.section == 'replay'}
    causal = figures['replay --no-smooth, against rosbags decoding']
    smoothed = figures['replay throughput, against rosbags decoding']
    generic = figures['read+decode only (rosbags)']
    for figure, target in ((causal, '>= 0.5'), (smoothed, '>= 0.4')):
        assert figure.baseline_median == generic.median
        assert figure.ratio is not None and 0.0 < figure.ratio < 10.0
        assert target in figure.target and figure.met is (figure.ratio >= float(target[3:]))


def test_multiscale_row_times_the_updates_after_every_window_is_covered():
    """A test updating at half the sample rate: the row times its late calls, not the epoch."""
    n = 6
    step_ns = 2_000_000  # 500 Hz: fewer calls than 1 kHz samples in the same span
    steady = bench.multiscale_steady_ns()
    count = steady // step_ns + 50
    rng = np.random.default_rng(0)
    calls = [('update', 10**9 + k * step_ns, 0.01 * rng.standard_normal(n), np.eye(n) * 1e-4,
              None, True, True) for k in range(count)]
    calls.insert(100, ('reset', calls[99][1]))
    ticks = iter(range(10**6))
    seconds, timed = bench.time_multiscale_calls(n, calls, clock=lambda: float(next(ticks)))
    # The 50 calls from every window covered on, one clock tick between start and end.
    assert timed == 50
    assert seconds == 1.0 / 50
    with pytest.raises(ValueError, match='cover'):
        bench.time_multiscale_calls(n, calls[:1000])
