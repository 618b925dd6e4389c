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
Benchmark: ``reduced-dynamics bench [--quick] [--json FILE] [--csv FILE] [--repeats N]``.

One process measures, side by side, each figure as a median over repeats with
its spread (interquartile range) and as a ratio to a baseline measured in the
same run (machines are noisy: ratios, not absolutes):

1. ``update``: the per-sample estimator update (mu, pi, pbar, drift observer;
   prediction off) against one Pinocchio ``crba`` call on the same robot, for
   both paths: streaming (``add_joint_state``/``add_base_state`` per message,
   per-sample outputs, as the node runs) and batched (``add_samples`` on
   slices of the message stream, column outputs; also with the per-sample
   outputs built). Each row is timed in steady state, after
   :data:`STEADY_SECONDS` of samples (the wrench-step test's bank full). Also the
   first call of the compiled filter kernels in a fresh process: loaded from
   numba's disk cache, and (not with ``--quick``) compiled from an empty cache.
2. ``prediction``: a 2 s prediction of the paper robot by the reduced model
   (DOP853 and the discrete gradient) against full dynamics (Pinocchio ``aba``,
   DOP853) at equal accuracy: each method is swept over tolerances (steps), the
   achieved shape error is measured against a DOP853 rtol 1e-13 reference, and
   the full model's time is interpolated (log-log) at the reduced model's
   achieved error (times: the process's CPU time, :data:`PREDICTION_CLOCK`). Also
   a 24-joint random tree and the Pinocchio floors of the ratios
   (:mod:`reduced_dynamics.reduction_bench`).
3. ``replay``: replay throughput of a simulated 1 kHz bag (prediction off)
   against bare read-and-decode of the same topics; peak resident memory of
   replay subprocesses on a short and a long (10-minute) bag.
4. ``scaling``: random trees with 6, 12, 24 and 48 shape joints: update (both
   paths) and reduced-vector-field cost, with exponents fitted by log-log least
   squares.
5. ``planned``: base motion for a planned arm motion against the shape-prescribed
   full dynamics; replay with the default predictions against predictions off.
6. ``node``: the node over real DDS (separate processes, a ROS_DOMAIN_ID of its
   own): joint states delivered per second, drops and input-to-output latency
   p50/p99 at 1 kHz joint states with 200 Hz and 1 kHz odometry, predictions on, and
   the highest joint-state rate (of a sweep) sustained without a drop,
   against a bare rclpy relay node measured in windows of the same run
   (:mod:`reduced_dynamics.node_bench`). Skipped when rclpy is not importable.
7. ``payload``: one payload identification (``identify``: read, fit, step test)
   against a causal replay of the same simulated window
   (:mod:`reduced_dynamics.payload_bench`, docs/payload.md).
8. ``soak`` (only when asked for, ``--sections soak``; ``--soak-duration``): the node
   over real DDS for a long window, retained bytes per sample and replay peak RSS
   against bag length (:mod:`reduced_dynamics.soak`, docs/soak.md).
"""

from __future__ import annotations

import argparse
import csv
from dataclasses import asdict, dataclass, field
import functools
import json
import os
import platform
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from typing import Any, Callable, Optional, Sequence
from unittest import mock

import numpy as np
import pinocchio as pin

NS = 1_000_000_000
SHAPE_JOINTS = (6, 12, 24, 48)
#: Input messages per ``add_samples`` call in the batched update (as a replay would read).
UPDATE_FEED = 1000
HORIZON = 2.0
#: Seconds of 1 kHz samples fed before an update row is timed: the wrench-step test opens
#: no onset for its 1 s window after the start and then one every 25 ms for another 1 s
#: (estimator/events.py), so from 2 s on its bank of hypotheses is full (steady state).
STEADY_SECONDS = 2.1


@dataclass
class Settings:
    """Sizes of the benchmark runs (``quick`` shrinks all of them)."""

    repeats: int = 7
    #: timed samples per update row, after ``update_warmup`` seconds of samples
    update_samples: int = 3000
    update_warmup: float = STEADY_SECONDS
    crba_calls: int = 5000
    full_rtols: tuple = (1e-5, 1e-6, 1e-7, 1e-8, 1e-9, 1e-10, 1e-11, 1e-12)
    reduced_rtols: tuple = (1e-6, 1e-8, 1e-10, 1e-12)
    dg_steps: tuple = (0.05, 0.025, 0.01)
    prediction_points: int = 41
    replay_seconds: float = 20.0
    memory_short_seconds: float = 60.0
    memory_long_seconds: float = 600.0
    scaling_samples: int = 600
    #: 1 kHz samples of the step-test rows: 1 s settling, 1 s to open every onset, then timed
    step_test_samples: int = 3000
    scaling_evaluations: int = 300
    shape_joints: tuple = SHAPE_JOINTS
    #: the torque-varying 200 Hz bag of section planned (issue 13: 60 s)
    planned_bag_seconds: float = 60.0
    #: the shipped bags section planned replays (names of :data:`SHIPPED_BAGS`; None: all)
    planned_bags: Optional[tuple] = None
    #: measured window and warm-up of each node/relay phase of section node [s]
    node_seconds: float = 5.0
    node_warmup: float = 1.0
    #: window of each rate of the sustained-rate sweep of section node [s]
    node_sweep_seconds: float = 2.0
    #: section node, in-process callbacks: the timed window after 2.1 s of input [s]
    node_callback_seconds: float = 6.0
    #: the simulated window of section payload [s]
    payload_seconds: float = 20.0
    #: bags of section fleet and the length of each (1 kHz, simulated)
    fleet_bags: int = 8
    fleet_bag_seconds: float = 2.0
    #: section soak: the node's window [s], tracemalloc samples, replay bag lengths [s]
    soak_seconds: float = 60.0
    # The finished-prediction store (64 at 1 Hz) fills in ~66 s: warm up beyond it.
    soak_retained_warmup: int = 80_000
    # Checkpoints every 1000 samples; the growth is fitted over the second half (21 of them).
    soak_retained_samples: int = 40_000
    soak_short_bag_seconds: float = 60.0
    soak_bag_seconds: float = 300.0
    quick: bool = False

    @classmethod
    def quick_settings(cls, repeats: Optional[int] = None) -> 'Settings':
        """Return small settings for a fast run (shorter bags, fewer tolerances)."""
        return cls(repeats=repeats or 3, update_samples=600, crba_calls=2000,
                   full_rtols=(1e-6, 1e-8, 1e-10, 1e-12), reduced_rtols=(1e-8, 1e-10),
                   dg_steps=(0.05, 0.025), replay_seconds=3.0, memory_short_seconds=5.0,
                   memory_long_seconds=20.0, scaling_samples=200, scaling_evaluations=60,
                   planned_bag_seconds=20.0, node_seconds=2.0, step_test_samples=2200,
                   node_warmup=1.0, node_sweep_seconds=1.0, node_callback_seconds=2.0,
                   payload_seconds=6.0,
                   fleet_bag_seconds=1.0, soak_seconds=30.0, soak_retained_warmup=5000,
                   soak_retained_samples=10_000, soak_short_bag_seconds=20.0,
                   soak_bag_seconds=60.0, quick=True)


@dataclass
class Figure:
    """One benchmark figure: median over repeats, spread, baseline and ratio."""

    section: str
    name: str
    unit: str
    median: float
    low: float
    high: float
    baseline: str = ''
    baseline_median: Optional[float] = None
    ratio: Optional[float] = None
    ratio_low: Optional[float] = None
    ratio_high: Optional[float] = None
    target: str = ''
    met: Optional[bool] = None
    note: str = ''


@dataclass
class Report:
    """Everything a bench run produced."""

    machine: dict
    settings: dict
    figures: list = field(default_factory=list)
    details: dict = field(default_factory=dict)

    def add(self, figure: Figure) -> Figure:
        """Append a figure and return it."""
        self.figures.append(figure)
        return figure

    def to_dict(self) -> dict:
        """Return a JSON-serialisable dict."""
        return {'machine': self.machine, 'settings': self.settings,
                'figures': [asdict(f) for f in self.figures], 'details': self.details}


# --------------------------------------------------------------------------- statistics
def spread(values: Sequence[float]) -> tuple[float, float, float]:
    """Return (median, first quartile, third quartile)."""
    data = np.asarray(values, dtype=float)
    q1, median, q3 = np.percentile(data, [25.0, 50.0, 75.0])
    return float(median), float(q1), float(q3)


def make_figure(section: str, name: str, unit: str, values: Sequence[float],
                baseline: str = '', baseline_values: Optional[Sequence[float]] = None,
                ratios: Optional[Sequence[float]] = None, target: str = '',
                check: Optional[Callable[[float], bool]] = None, note: str = '') -> Figure:
    """
    Summarise repeated measurements (and their per-repeat ratios to a baseline).

    ``check`` is applied to the median ratio (or to the median when there are
    no ratios) to decide whether the target is met.
    """
    median, low, high = spread(values)
    figure = Figure(section, name, unit, median, low, high, baseline, target=target, note=note)
    if baseline_values is not None:
        figure.baseline_median = spread(baseline_values)[0]
    if ratios is not None:
        figure.ratio, figure.ratio_low, figure.ratio_high = spread(ratios)
    if check is not None:
        figure.met = bool(check(figure.ratio if figure.ratio is not None else figure.median))
    return figure


def fit_exponent(sizes: Sequence[float], costs: Sequence[float]) -> float:
    """Slope of log(cost) against log(size) by least squares."""
    slope, _ = np.polyfit(np.log(np.asarray(sizes, float)), np.log(np.asarray(costs, float)), 1)
    return float(slope)


def machine_info() -> dict:
    """Return CPU model, CPU count and library versions."""
    cpu = platform.processor() or platform.machine()
    try:
        with open('/proc/cpuinfo', encoding='utf-8') as stream:
            for line in stream:
                if line.startswith('model name'):
                    cpu = line.split(':', 1)[1].strip()
                    break
    except OSError:
        pass
    import scipy
    return {'cpu': cpu, 'nproc': os.cpu_count(), 'python': platform.python_version(),
            'numpy': np.__version__, 'scipy': scipy.__version__, 'pinocchio': pin.__version__,
            'platform': platform.platform()}


# --------------------------------------------------------------------------- 1. update
def update_samples(robot, count: int, seed: int = 0) -> tuple[list, list]:
    """Return pre-built joint and Odometry base samples of a smooth motion at 1 kHz."""
    from reduced_dynamics.messages.samples import BaseStateSample, JointStateSample
    rng = np.random.default_rng(seed)
    m = robot.m
    amplitude = rng.uniform(0.1, 0.4, m)
    frequency = rng.uniform(0.5, 2.0, m)
    phase = rng.uniform(0.0, 2.0 * np.pi, m)
    joints, bases = [], []
    for index in range(count):
        t = index * 1e-3
        stamp = NS + index * 1_000_000
        qbar = amplitude * np.sin(frequency * t + phase)
        qbar_dot = amplitude * frequency * np.cos(frequency * t + phase)
        joints.append(JointStateSample(stamp, '', robot.shape_joint_names, qbar, qbar_dot,
                                       np.zeros(m)))
        angle = 0.05 * t
        quat = np.array([0.0, 0.0, np.sin(0.5 * angle), np.cos(0.5 * angle)])
        bases.append(BaseStateSample(stamp, 'world', robot.base_link,
                                     np.array([0.01 * t, 0.0, 0.0]), quat,
                                     np.array([0.01, 0.0, 0.0]), np.array([0.0, 0.0, 0.05])))
    return joints, bases


def time_crba(robot, calls: int, clock: Callable[[], float] = time.perf_counter) -> float:
    """Return seconds (of ``clock``) per ``crba`` call at a generic shape (base at identity)."""
    model, data = robot.model, robot.model.createData()
    q = robot.identity_configuration(np.linspace(-0.3, 0.3, robot.m)).copy()
    crba = pin.crba
    start = clock()
    for _ in range(calls):
        crba(model, data, q)
    return (clock() - start) / calls


UPDATE_PATHS = ('streaming', 'batched', 'batched+outputs', 'streaming, odometry 200 Hz',
                'streaming, odometry off the rows', 'streaming, fixed-lag')
#: smoothing_lag [s] of the fixed-lag path (the node's default); the others run without.
BENCH_FIXED_LAG = 0.5
#: The node bench's mix: every 5th base sample, stamped 0.3 ms after its joint state.
ODOMETRY_EVERY, ODOMETRY_OFFSET_NS = 5, 300_000
#: The streaming paths whose base samples run on their own clock: (every n-th, offset [ns]).
ODOMETRY_MIXES = {'streaming, odometry 200 Hz': (ODOMETRY_EVERY, ODOMETRY_OFFSET_NS),
                  'streaming, odometry off the rows': (1, ODOMETRY_OFFSET_NS)}


def time_update(robot, joints: list, bases: list, warmup: int = 20,
                path: str = 'streaming') -> float:
    """
    Return seconds per processed sample (joint state + base state, prediction off).

    ``streaming``: one ``add_joint_state`` and one ``add_base_state`` call per
    sample, per-sample outputs (the node). ``batched``: the same messages in
    arrival order, :data:`UPDATE_FEED` per ``add_samples`` call, column outputs;
    ``batched+outputs`` also builds the per-sample outputs from the columns.
    ``streaming, odometry 200 Hz``: streaming with every fifth base sample only,
    stamped 0.3 ms after its joint state (1 kHz joint states + 200 Hz odometry on
    their own clocks, as in the node bench): a base measurement updates the filter
    at its own stamp, the rows between only propagate. ``streaming, odometry off the
    rows``: every base sample, 0.3 ms after its joint state (both at 1 kHz, unsynchronised
    sensors): each row a measurement between two rows, then the propagation on to the
    row. ``streaming, fixed-lag``:
    streaming with fixed-lag smoothing at :data:`BENCH_FIXED_LAG` (the others: off).
    """
    from reduced_dynamics.estimator.config import EstimatorConfig
    from reduced_dynamics.estimator.pipeline import Estimator
    from reduced_dynamics.messages.samples import BaseStateSample
    lag = BENCH_FIXED_LAG if path == 'streaming, fixed-lag' else 0.0
    estimator = Estimator(robot, EstimatorConfig(prediction_rate=0.0, smoothing_lag=lag))
    if path in ODOMETRY_MIXES:
        every, offset_ns = ODOMETRY_MIXES[path]
        shifted = [BaseStateSample(b.stamp_ns + offset_ns, b.frame_id,
                                   b.child_frame_id, b.position, b.orientation_xyzw,
                                   b.twist_linear, b.twist_angular)
                   for b in bases[::every]]
        messages = sorted([(j.stamp_ns, 0, j) for j in joints]
                          + [(b.stamp_ns, 1, b) for b in shifted], key=lambda e: e[:2])
        calls = [estimator.add_base_state if kind else estimator.add_joint_state
                 for _, kind, _ in messages]
        samples = [sample for _, _, sample in messages]
        # The warm-up: every message before the first timed joint state.
        first_ns = joints[min(warmup, len(joints) - 1)].stamp_ns
        split = next((i for i, (stamp, _, _) in enumerate(messages) if stamp >= first_ns),
                     len(messages))
        for call, sample in zip(calls[:split], samples[:split]):
            call(sample)
        before = estimator.processed
        start = time.perf_counter()
        for call, sample in zip(calls[split:], samples[split:]):
            call(sample)
        elapsed = time.perf_counter() - start
    elif path in ('streaming', 'streaming, fixed-lag'):
        add_joint, add_base = estimator.add_joint_state, estimator.add_base_state
        for joint, base in zip(joints[:warmup], bases[:warmup]):
            add_joint(joint)
            add_base(base)
        before = estimator.processed
        start = time.perf_counter()
        for joint, base in zip(joints[warmup:], bases[warmup:]):
            add_joint(joint)
            add_base(base)
        elapsed = time.perf_counter() - start
    else:
        messages = [m for pair in zip(joints, bases) for m in pair]
        estimator.add_samples(messages[:2 * warmup])
        outputs = path == 'batched+outputs'
        before = estimator.processed
        start = time.perf_counter()
        for first in range(2 * warmup, len(messages), UPDATE_FEED):
            batch = estimator.add_samples(messages[first:first + UPDATE_FEED])
            if outputs:
                batch.outputs()
        elapsed = time.perf_counter() - start
    processed = estimator.processed - before
    if processed <= 0:
        raise RuntimeError('the estimator processed no sample')
    return elapsed / processed


def measure_update(robot, settings: Settings, samples: int,
                   paths: Sequence[str] = UPDATE_PATHS,
                   warmup: int = 20) -> tuple[dict, list]:
    """
    Interleave update and crba timings over the repeats; return ({path: s}, crba s).

    ``samples`` are timed after ``warmup`` samples (1 kHz) fed untimed.
    """
    joints, bases = update_samples(robot, warmup + samples)
    updates: dict = {path: [] for path in paths}
    crbas = []
    for _ in range(settings.repeats):
        crbas.append(time_crba(robot, settings.crba_calls))
        for path in paths:
            updates[path].append(time_update(robot, joints, bases, warmup, path=path))
    return updates, crbas


#: What a fresh process runs to time the filter kernels' first call (imports included).
_FIRST_CALL = ('import time; start = time.perf_counter(); '
               'from reduced_dynamics.estimator.core.warmup import warm_up; warm_up(); '
               'print(time.perf_counter() - start)')


def time_first_call(cache_dir: Optional[str] = None) -> float:
    """
    Return seconds of a fresh process's first run of every filter kernel (with imports).

    ``cache_dir``: numba's cache directory (an empty one measures compilation);
    None: the default cache beside the modules (what a user's process loads).
    """
    env = dict(os.environ)
    if cache_dir is not None:
        env['NUMBA_CACHE_DIR'] = cache_dir
    done = subprocess.run([sys.executable, '-c', _FIRST_CALL], env=env, check=True,
                          capture_output=True, text=True, timeout=1800)
    return float(done.stdout.strip().splitlines()[-1])


def bench_update(report: Report, robot, settings: Settings) -> None:
    """Section 1: per-sample estimator update (both paths) against one crba call."""
    warmup = int(settings.update_warmup * 1000)
    updates, crbas = measure_update(robot, settings, settings.update_samples, warmup=warmup)
    names = {'streaming': 'estimator update (paper robot)',
             'batched': 'estimator update, batched (paper robot)',
             'batched+outputs': 'estimator update, batched + outputs (paper robot)',
             'streaming, odometry 200 Hz':
                 'estimator update, 1 kHz joints + 200 Hz odometry (paper robot)',
             'streaming, odometry off the rows':
                 'estimator update, 1 kHz joints + 1 kHz odometry off their stamps '
                 '(paper robot)',
             'streaming, fixed-lag':
                 f'estimator update, fixed-lag smoothing {BENCH_FIXED_LAG:g} s (paper robot)'}
    notes = {'streaming': 'add_joint_state/add_base_state per sample, outputs built; '
                          'joint and base stamps equal: an update every sample',
             'batched': f'add_samples, {UPDATE_FEED} messages per call, column outputs',
             'batched+outputs': 'as batched, then EstimatorOutput per sample',
             'streaming, odometry 200 Hz': 'streaming; odometry every 5th sample, 0.3 ms '
                                           'later: an update per odometry sample',
             'streaming, odometry off the rows': 'streaming; every odometry sample 0.3 ms '
                                                 'after its joint state (sensors on their '
                                                 'own clocks): per row an update between '
                                                 'two rows, then a propagation',
             'streaming, fixed-lag': 'streaming, smoothing_lag = '
                                     f'{BENCH_FIXED_LAG:g} s (the node\'s default; the other '
                                     'rows 0): the backward passes and the lagged rows'}
    # Targets of issue 19: streaming <= 20 x crba, batched <= 10 x crba.
    targets = {'streaming': 20.0, 'streaming, odometry 200 Hz': 20.0,
               'streaming, odometry off the rows': 20.0, 'streaming, fixed-lag': 20.0}
    steady = f'; timed after {settings.update_warmup:g} s of samples' + (
        ' (step test full)' if settings.update_warmup >= STEADY_SECONDS else '')
    for path, values in updates.items():
        ratios = [u / c for u, c in zip(values, crbas)]
        bound = targets.get(path, 10.0)
        report.add(make_figure('update', names[path], 'us/sample',
                               [1e6 * u for u in values], 'crba',
                               [1e6 * c for c in crbas], ratios, f'ratio <= {bound:g}',
                               lambda r, bound=bound: r <= bound, note=notes[path] + steady))
    lagged, plain = updates.get('streaming, fixed-lag'), updates.get('streaming')
    if lagged and plain:
        report.add(make_figure(
            'update', 'fixed-lag smoothing: update with it / without (paper robot)', 'us/sample',
            [1e6 * u for u in lagged], 'estimator update (streaming, without)',
            [1e6 * u for u in plain], [a / b for a, b in zip(lagged, plain)],
            'ratio <= 2', lambda r: r <= 2.0,
            note='the same samples and repeats; estimator/fixed_lag.py'))
    report.add(make_figure('update', 'crba (paper robot)', 'us/call',
                           [1e6 * c for c in crbas], note='baseline'))
    from reduced_dynamics.bench_floor import bench_floor
    bench_floor(report, robot, settings)  # what the targets leave for the interpreter
    bench_first_call(report, settings)


def bench_first_call(report: Report, settings: Settings) -> None:
    """Time the compiled filter kernels' first call in a fresh process (numba's disk cache)."""
    time_first_call()  # fills the cache if this checkout never ran the kernels
    warm = [time_first_call() for _ in range(min(settings.repeats, 3))]
    report.add(make_figure('update', 'filter kernels: first call, cached', 's', warm,
                           note='fresh process: imports + every kernel once, loaded from '
                                "numba's disk cache (what each process start pays)"))
    if settings.quick:
        return
    with tempfile.TemporaryDirectory(prefix='reduced_dynamics_numba_') as empty:
        cold = [time_first_call(empty)]
    report.add(make_figure('update', 'filter kernels: first call, compiling', 's', cold,
                           note='fresh process with an empty NUMBA_CACHE_DIR: the one-off '
                                'compilation after an install'))


def record_step_calls(robot, joints: list, bases: list) -> list:
    """Run the streaming estimator; return its step test's calls (name, arguments)."""
    from reduced_dynamics.estimator import filter as filter_module
    from reduced_dynamics.estimator.step_test import WrenchStepTest
    calls: list = []

    class Recording(WrenchStepTest):
        # The filter's compiled row step (estimator/step_row.py) would run the test
        # without these calls: recorded, the filter makes them (the same bits).
        active = False

        def reset(self, settle_from_ns: Optional[int] = None) -> None:
            calls.append(('reset', settle_from_ns))
            super().reset(settle_from_ns)

        def propagate(self, stamp_ns: int, transition: np.ndarray) -> None:
            calls.append(('propagate', stamp_ns, transition.copy()))
            super().propagate(stamp_ns, transition)

        def update(self, *args: np.ndarray):
            calls.append(('update',) + tuple(a.copy() for a in args))
            return super().update(*args)

    with mock.patch.object(filter_module, 'WrenchStepTest', Recording):
        time_update(robot, joints, bases, warmup=1)
    return calls


def time_step_calls(test: Any, calls: list, from_ns: int) -> tuple[float, int]:
    """Feed ``calls`` to ``test``; return the seconds spent from stamp ``from_ns`` and the rows."""
    start, rows, timed = 0.0, 0, False
    for call in calls:
        if call[0] == 'propagate' and not timed and call[1] >= from_ns:
            timed, start = True, time.perf_counter()
        if call[0] == 'reset':
            test.reset(call[1])
        elif call[0] == 'propagate':
            rows += timed
            test.propagate(call[1], call[2])
        else:
            test.update(*call[1:])
    return time.perf_counter() - start, rows


def bench_step_test(report: Report, robot, settings: Settings) -> None:
    """
    Time the wrench-step test alone: explicit bank against anchored signatures.

    Both (docs/step_test.md) are fed the calls one streaming run made (1 kHz pose and
    twist), timed once every onset is open (from 2 s: 1 s settling, 1 s window); the
    estimator update with each, streaming, in the same repeats gives the test's share.
    """
    from reduced_dynamics.estimator import filter as filter_module
    from reduced_dynamics.estimator.config import EstimatorConfig
    from reduced_dynamics.estimator.step_reference import ExplicitStepTest
    from reduced_dynamics.estimator.step_test import GLR_WINDOW, WrenchStepTest
    significance = EstimatorConfig().event_significance
    joints, bases = update_samples(robot, settings.step_test_samples)
    full = int(2 * GLR_WINDOW * 1000) + 10     # samples at 1 kHz until every onset is open
    calls = record_step_calls(robot, joints, bases)
    from_ns = joints[full].stamp_ns
    kinds = {'explicit': ExplicitStepTest, 'anchored': WrenchStepTest}
    tests: dict = {kind: [] for kind in kinds}
    updates: dict = {kind: [] for kind in kinds}
    for _ in range(settings.repeats):
        for kind, cls in kinds.items():
            test = cls(robot.n, significance, 3 * robot.n)
            seconds, rows = time_step_calls(test, calls, from_ns)
            tests[kind].append(seconds / rows)
            with mock.patch.object(filter_module, 'WrenchStepTest', cls):
                updates[kind].append(time_update(robot, joints, bases, warmup=full))
    for kind, label in (('explicit', 'explicit bank, 40 onsets x dim'),
                        ('anchored', 'anchored signatures')):
        report.add(make_figure(
            'update', f'wrench step test, {label} (paper robot)', 'us/sample',
            [1e6 * t for t in tests[kind]], 'estimator update with it',
            [1e6 * u for u in updates[kind]],
            [t / u for t, u in zip(tests[kind], updates[kind])],
            note='the test alone on one run\'s recorded calls, every onset open; ratio: '
                 'its share of a streaming update (1 kHz pose + twist)'))
    report.add(make_figure(
        'update', 'wrench step test, anchored vs explicit (paper robot)', 'us/sample',
        [1e6 * t for t in tests['anchored']], 'explicit bank',
        [1e6 * t for t in tests['explicit']],
        [a / e for a, e in zip(tests['anchored'], tests['explicit'])],
        note='same detections (test_step_test.py)'))


def multiscale_steady_ns() -> int:
    """Return the data span [ns] after which every window of both banks is covered (3 L)."""
    from reduced_dynamics.estimator.multiscale import LONGEST
    return int(round(3.0 * LONGEST * 1e9))


def time_multiscale_calls(n: int, calls: list,
                          clock: Callable[[], float] = time.perf_counter) -> tuple[float, int]:
    """
    Replay recorded multi-scale test calls; return seconds per timed update, their count.

    ``calls``: ("update", stamp, mu, P_mu, measured, wanted, quiet) or ("reset", stamp)
    in the order the event detector made them (its resets and quiet flag move the
    windows' floor and the calibration: without them the replay is another run).
    Timed: the updates from :func:`multiscale_steady_ns` after the first one on
    (every window covered; a test updating at half the sample rate reaches it at
    the same stamp). ValueError when no call is that late.
    """
    from reduced_dynamics.estimator.multiscale import MultiScaleTest
    stamps = [call[1] for call in calls if call[0] == 'update']
    if not stamps:
        raise ValueError('no multi-scale test update was recorded')
    steady = stamps[0] + multiscale_steady_ns()
    first = next((k for k, call in enumerate(calls)
                  if call[0] == 'update' and call[1] >= steady), None)
    if first is None:
        raise ValueError(f'the recorded updates span {(stamps[-1] - stamps[0]) * 1e-9:.2f} s, '
                         f'fewer than the {multiscale_steady_ns() * 1e-9:.1f} s that cover '
                         'every window')
    test = MultiScaleTest(n, 1.0)
    start, timed = 0.0, 0
    for k, call in enumerate(calls):
        if k == first:
            start = clock()
        if call[0] == 'reset':
            test.reset(call[1])
            continue
        _, stamp, mu, cov, measured, wanted, quiet = call
        test.quiet = quiet
        test.update(stamp, mu, cov, measured, wanted)
        timed += k >= first
    return (clock() - start) / timed, timed


def bench_multiscale(report: Report, robot, settings: Settings) -> None:
    """
    Time the multi-scale event test alone (docs/multiscale_events.md) and its share.

    The test is fed the calls one streaming run made (1 kHz, every window of both
    banks covered after 3 x 3 s, :func:`time_multiscale_calls`); the share is against
    the streaming update of the same samples after the same warm-up, in the same
    repeats (the clock of :func:`time_update`).
    """
    from reduced_dynamics.estimator import events as events_module
    from reduced_dynamics.estimator.multiscale import MultiScaleTest
    calls: list = []

    class Recording(MultiScaleTest):
        def update(self, stamp_ns, mu, cov, measured=None, wanted=True):
            calls.append(('update', stamp_ns, mu.copy(), cov.copy(), measured, wanted,
                          self.quiet))
            return super().update(stamp_ns, mu, cov, measured, wanted)

        def reset(self, from_ns):
            calls.append(('reset', from_ns))
            return super().reset(from_ns)

    # One second timed after every window is covered (1 kHz samples).
    full = multiscale_steady_ns() // 1_000_000
    samples = max(settings.step_test_samples, full + 1000)
    joints, bases = update_samples(robot, samples)
    with mock.patch.object(events_module, 'MultiScaleTest', Recording):
        time_update(robot, joints, bases, warmup=1)
    alone, updates = [], []
    for _ in range(settings.repeats):
        alone.append(time_multiscale_calls(robot.n, calls)[0])
        updates.append(time_update(robot, joints, bases, warmup=full))
    report.add(make_figure(
        'update', 'multi-scale event test (paper robot)', 'us/sample',
        [1e6 * t for t in alone], 'estimator update with it', [1e6 * u for u in updates],
        [t / u for t, u in zip(alone, updates)],
        note='the test alone on one run\'s recorded calls (the filtered '
             'momentum\'s windows and the compiled block test on measured twists and centre '
             'of mass, the twists\' momenta computed in its call), from 9 s on (every window '
             'of both banks covered); ratio: its share of a streaming update (1 kHz pose + '
             'twist)'))


# --------------------------------------------------------------------------- 2. prediction
def _timed(run: Callable[[], Any], repeats: int,
           clock: Callable[[], float] = time.perf_counter) -> tuple[Any, list]:
    result, times = None, []
    for _ in range(repeats):
        start = clock()
        result = run()
        times.append(clock() - start)
    return result, times


#: Clock of the single-threaded prediction rows: the process's CPU time. On a loaded
#: machine wall time also counts the other jobs' time slices (a 3 ms run preempted once
#: doubles), which no median over repeats removes; on a quiet one the two agree.
PREDICTION_CLOCK = time.process_time


def matched_time(errors: Sequence[float], seconds: Sequence[float],
                 error: float) -> tuple[float, bool]:
    """
    Interpolate log(time) against log(error) of a tolerance sweep at ``error``.

    Returns (time, inside) where ``inside`` tells whether ``error`` lies in the
    swept range (outside it the nearest end is used: no extrapolation).
    """
    log_e = np.log10(np.maximum(np.asarray(errors, float), 1e-300))
    log_t = np.log10(np.asarray(seconds, float))
    order = np.argsort(log_e)
    log_e, log_t = log_e[order], log_t[order]
    target = np.log10(max(error, 1e-300))
    inside = bool(log_e[0] <= target <= log_e[-1])
    return float(10.0 ** np.interp(target, log_e, log_t)), inside


def bench_prediction(report: Report, robot, settings: Settings) -> None:
    """Section 2: 2 s prediction, reduced against full dynamics at equal accuracy."""
    from reduced_dynamics.full_dynamics import FullDynamics
    from reduced_dynamics.geometry.isotropy import MomentumClass
    from reduced_dynamics.validation import random_scenario

    from reduced_dynamics.reduction.lean_field import warm_up
    warm_up()  # the compiled kernels' first call is not what these rows measure
    scenario = random_scenario(robot, MomentumClass.GENERIC, 0)
    state, torque = scenario.state, scenario.torque
    times = np.linspace(0.0, HORIZON, settings.prediction_points)
    reference = FullDynamics(robot, torque).simulate(state, times, 1e-13, 1e-13).qbar

    def error_of(qbar: np.ndarray) -> float:
        return float(np.max(np.abs(qbar - reference)))

    full_run = functools.partial(full_prediction, robot, torque, state, times)
    reduced_run = functools.partial(reduced_prediction, robot, torque, state, times)
    sweep: dict[str, list] = {'full dop853': [], 'reduced dop853': [],
                              'reduced discrete_gradient': []}
    runs = [('full dop853', rtol, full_run(rtol)) for rtol in settings.full_rtols]
    runs += [('reduced dop853', rtol, reduced_run('dop853', rtol))
             for rtol in settings.reduced_rtols]
    runs += [('reduced discrete_gradient', step, reduced_run('discrete_gradient', step))
             for step in settings.dg_steps]
    trajectories, seconds = round_robin([run for _, _, run in runs], settings.repeats)
    for (method, tol, _), trajectory, timing in zip(runs, trajectories, seconds):
        sweep[method].append({'tolerance': tol, 'error': error_of(trajectory.qbar),
                              'seconds': timing})
    # Right-hand-side evaluations per prediction, counted in one extra untimed run.
    for method, tol in [(m, row['tolerance']) for m in sweep for row in sweep[m]]:
        if method.endswith('gradient'):
            continue
        counter = [0]
        (full_run(tol, counter) if method.startswith('full')
         else reduced_run('dop853', tol, counter))()
        next(r for r in sweep[method] if r['tolerance'] == tol)['evaluations'] = counter[0]
    report.details['prediction_sweep'] = sweep
    full = sweep['full dop853']
    full_errors = [row['error'] for row in full]
    for method in ('reduced dop853', 'reduced discrete_gradient'):
        knob = 'rtol' if method.endswith('dop853') else 'step'
        for row in sweep[method]:
            # Full-dynamics time at the reduced run's error, per repeat.
            baseline = []
            inside = True
            for repeat in range(settings.repeats):
                value, inside = matched_time(full_errors,
                                             [r['seconds'][repeat] for r in full],
                                             row['error'])
                baseline.append(value)
            ratios = [s / b for s, b in zip(row['seconds'], baseline)]
            is_default = method.endswith('dop853') and row['tolerance'] == 1e-10
            note = f'error {row["error"]:.1e} rad'
            if 'evaluations' in row:
                note += f', {row["evaluations"]} evaluations'
            if not inside:
                note += ' (outside the full sweep: nearest end)'
            report.add(make_figure(
                'prediction', f'{method} {knob} {row["tolerance"]:g}', 'ms',
                [1e3 * s for s in row['seconds']], 'full aba dop853 at equal error',
                [1e3 * b for b in baseline], ratios, 'ratio <= 1' if is_default else '',
                (lambda r: r <= 1.0) if is_default else None, note))
            if is_default or (method.endswith('gradient')
                              and row['tolerance'] == settings.dg_steps[0]):
                realtime = [HORIZON / s for s in row['seconds']]
                report.add(make_figure(
                    'prediction', f'{method} {knob} {row["tolerance"]:g} vs real time',
                    'x real time', realtime, target='>= 100',
                    check=lambda r: r >= 100.0, note='2 s horizon / CPU time of the run'))
    for row in full:
        report.add(make_figure('prediction', f'full aba dop853 rtol {row["tolerance"]:g}', 'ms',
                               [1e3 * s for s in row['seconds']],
                               note=f'error {row["error"]:.1e} rad, {row["evaluations"]} '
                                    'evaluations (baseline sweep)'))
    # What the reduction costs: the random-tree row and the Pinocchio floors (issue 26).
    from reduced_dynamics.reduction_bench import bench_reduction_cost
    bench_reduction_cost(report, robot, settings)


def full_prediction(robot, torque: Callable, state, times: np.ndarray, rtol: float,
                    counter: Optional[list] = None) -> Callable[[], Any]:
    """Return a run of the full dynamics' DOP853 prediction (rtol = atol) from ``state``."""
    from reduced_dynamics.full_dynamics import FullDynamics

    def run():
        model = FullDynamics(robot, torque)
        _count_evaluations(model, counter)
        return model.simulate(state, times, rtol, rtol)
    return run


def reduced_prediction(robot, torque: Callable, state, times: np.ndarray, integrator: str,
                       tol: float, counter: Optional[list] = None) -> Callable[[], Any]:
    """Return a run of the reduced prediction (tol: rtol, atol and DG step) from ``state``."""
    from reduced_dynamics.reduction.reconstruction import ReducedPropagator

    def run():
        propagator, y0 = ReducedPropagator.from_full_state(robot, state, torque)
        _count_evaluations(propagator, counter)
        return propagator.propagate(y0, times, integrator, tol, tol, tol)
    return run


def round_robin(runs: Sequence[Callable[[], Any]], repeats: int) -> tuple[list, list]:
    """
    Time each run ``repeats`` times on :data:`PREDICTION_CLOCK`; return (results, seconds).

    The repeats go round-robin over all runs, so a change of machine load during
    a section hits the reduced and the full runs alike (ratios stay comparable).
    """
    seconds: list = [[] for _ in runs]
    results: list = [None] * len(runs)
    for _ in range(repeats):
        for index, run in enumerate(runs):
            results[index], timing = _timed(run, 1, PREDICTION_CLOCK)
            seconds[index] += timing
    return results, seconds


def _count_evaluations(system: Any, counter: Optional[list]) -> None:
    """Count ``system.rhs`` calls in ``counter[0]`` (not in timed runs: it costs a call)."""
    if counter is None:
        return
    rhs = system.rhs

    def counted(t: float, y: np.ndarray) -> np.ndarray:
        counter[0] += 1
        return rhs(t, y)
    system.rhs = counted


# --------------------------------------------------------------------------- planned motions
#: Shipped bags replayed with predictions on (defaults) and off, with their robots.
SHIPPED_BAGS = (('paper_thruster', '', None, None), ('paper_constant', '', None, None),
                ('paper_realistic', '', None, None),
                ('planar_pose_only', 'robots/planar_testbed.urdf', 'planar', (0.0, 0.0, -9.81)),
                ('freeflyer_realistic', 'robots/freeflyer.urdf', None, None))


def bench_plan(seconds: float = 10.0, points: int = 11, seed: int = 1) -> tuple:
    """Return (path, g0, xi0, mu) of a seeded cubic plan for the paper robot's shape."""
    from reduced_dynamics.reduction.shape_path import PlannedPath
    from reduced_dynamics.robot.model import load_robot
    from reduced_dynamics.robot.momentum import momentum_map
    robot = load_robot()
    rng = np.random.default_rng(seed)
    times = np.linspace(0.0, seconds, points)
    positions = 0.4 * rng.standard_normal((points, robot.m))
    velocities = 0.2 * rng.standard_normal((points, robot.m))
    velocities[0] = velocities[-1] = 0.0
    path = PlannedPath(times, positions, velocities)
    g0 = pin.SE3(pin.exp3(np.array([0.1, 0.2, -0.3])), np.array([1.0, 2.0, 3.0]))
    xi0 = np.array([0.01, -0.02, 0.03, 0.02, -0.01, 0.015])
    n = robot.n
    mass = robot.mass_matrix(path(0.0)[0])
    mu = momentum_map(robot.group, g0, mass[:n] @ np.concatenate([xi0, path(0.0)[1]]))
    return robot, path, g0, xi0, mu


def bench_planned(report: Report, settings: Settings, workdir: str) -> None:
    """
    Section planned (issue 13): base motion for a 10 s plan, and replay cost of predictions.

    (a) The reconstruction alone (what ``~/predict_base_motion`` runs) against
    one full-dynamics simulation of the same plan (shape prescribed, base by
    the full equations), each swept over tolerances; time at equal base-pose
    error. (b) Replay with default settings against predictions off, side by
    side (interleaved repeats) on the shipped bags and a 60 s, 200 Hz bag with
    varying (PD) torques.
    """
    from reduced_dynamics.full_dynamics import PrescribedShapeDynamics
    from reduced_dynamics.reduction.prescribed import PrescribedReconstruction, relative_angles
    shipped = [name for name, *_ in SHIPPED_BAGS]
    unknown = set(settings.planned_bags or ()) - set(shipped)
    if unknown:
        raise ValueError(f'planned_bags: no shipped bag named {sorted(unknown)} '
                         f'(known: {", ".join(shipped)})')
    robot, path, g0, xi0, mu = bench_plan()
    times = np.linspace(0.0, 10.0, 201)
    reference = PrescribedShapeDynamics(robot, path).simulate(g0, xi0, times, 1e-13, 1e-13)

    def error_of(poses: np.ndarray) -> float:
        position = np.abs(poses[:, :3, 3] - reference.poses[:, :3, 3]).max()
        attitude = relative_angles(poses[:, :3, :3], reference.poses[:, :3, :3]).max()
        return float(max(position, attitude))

    def reduced(tol: float) -> Callable[[], Any]:
        return lambda: PrescribedReconstruction(robot, mu, g0, path).propagate(
            times, tol, tol, path.breakpoints).poses

    def full(tol: float) -> Callable[[], Any]:
        return lambda: PrescribedShapeDynamics(robot, path).simulate(g0, xi0, times, tol,
                                                                     tol).poses

    full_tols = (1e-6, 1e-8, 1e-10, 1e-12)
    reduced_tols = (1e-8, 1e-10) if settings.quick else (1e-6, 1e-8, 1e-10, 1e-12)
    runs = [('full', t, full(t)) for t in full_tols] + \
        [('reduced', t, reduced(t)) for t in reduced_tols]
    seconds = [[] for _ in runs]
    errors = [0.0] * len(runs)
    for _ in range(settings.repeats):
        for index, (_, _, run) in enumerate(runs):
            poses, timing = _timed(run, 1)
            seconds[index] += timing
            errors[index] = error_of(poses)
    full_rows = [(e, s) for (kind, _, _), e, s in zip(runs, errors, seconds) if kind == 'full']
    sweep = {f'{kind} {tol:g}': {'error': e, 'seconds': s}
             for (kind, tol, _), e, s in zip(runs, errors, seconds)}
    report.details['planned_sweep'] = sweep
    for (kind, tol, _), error, timing in zip(runs, errors, seconds):
        if kind != 'reduced':
            continue
        baseline, inside = [], True
        for repeat in range(settings.repeats):
            value, inside = matched_time([e for e, _ in full_rows],
                                         [s[repeat] for _, s in full_rows], error)
            baseline.append(value)
        is_default = tol == 1e-10
        note = f'paper robot, 10 s cubic plan, base pose error {error:.1e} (m and rad)'
        if not inside:
            note += ' (outside the full sweep: nearest end)'
        report.add(make_figure(
            'planned', f'base motion for a 10 s plan, reconstruction rtol {tol:g}', 'ms',
            [1e3 * t for t in timing], 'full dynamics, shape prescribed, at equal error',
            [1e3 * b for b in baseline], [t / b for t, b in zip(timing, baseline)],
            'ratio < 1' if is_default else '', (lambda r: r < 1.0) if is_default else None,
            note))
    _bench_replay_predictions(report, settings, workdir)


def _bench_replay_predictions(report: Report, settings: Settings, workdir: str) -> None:
    """Replay with default settings against predictions off, interleaved, per bag."""
    from reduced_dynamics.params import defaults
    from reduced_dynamics.replay import replay, ReplayOptions
    from reduced_dynamics.resources import config_path
    from reduced_dynamics.robot.model import load_robot
    from reduced_dynamics.simulator import SimulationOptions, simulate_bag
    data = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))),
                        'test', 'data')
    bags = []
    for name, urdf, joint, gravity in SHIPPED_BAGS:
        if settings.planned_bags is not None and name not in settings.planned_bags:
            continue
        if os.path.isdir(os.path.join(data, name)):
            robot = load_robot(str(config_path(urdf)) if urdf else '', joint,
                               None if gravity is None else np.array(gravity))
            bags.append((name, os.path.join(data, name), robot))
    varying = os.path.join(workdir, 'pd60')
    seconds = settings.planned_bag_seconds
    paper = load_robot()
    simulate_bag(paper, varying, SimulationOptions(duration=seconds, rate=200.0, torque='pd',
                                                   overwrite=True))
    varying_label = f'{seconds:g} s, 200 Hz, PD torques (simulated)'
    bags.append((varying_label, varying, paper))
    out = os.path.join(workdir, 'replayed')
    off = {**defaults(), 'prediction_rate': 0.0}
    for label, bag, robot in bags:
        variants = [('default', defaults())]
        if bag == varying:
            # The torque-driven mode for comparison (the default before issue 13).
            variants.append(('held_torque', {**defaults(), 'prediction_mode': 'held_torque'}))
        rates = {key: [] for key in ['off'] + [v[0] for v in variants]}
        summaries = {}
        for _ in range(settings.repeats):
            for key, params in [('off', off)] + variants:
                start = time.perf_counter()
                result = replay(bag, out, robot, ReplayOptions(params=params, overwrite=True))
                rates[key].append(result['processed'] / (time.perf_counter() - start))
                summaries[key] = result
        for key, _ in variants:
            summary = summaries[key]
            modes = ', '.join(f'{m} {v["predictions"]}'
                              for m, v in summary['prediction_residuals'].items())
            name = 'defaults' if key == 'default' else f'prediction_mode {key}'
            report.add(make_figure(
                'planned', f'replay with {name}, {label}', 'samples/s', rates[key],
                'same bag, predictions off', rates['off'],
                [d / o for d, o in zip(rates[key], rates['off'])],
                'ratio >= 0.5' if key == 'default' else '',
                (lambda r: r >= 0.5) if key == 'default' else None,
                f'{summary["processed"]} samples; predictions: {modes or "none"}'))
    shutil.rmtree(out, ignore_errors=True)


# --------------------------------------------------------------------------- 3. replay
def simulate_input_bag(robot, path: str, seconds: float) -> None:
    """Simulate the robot and write a 1 kHz bag (Odometry base) at ``path``."""
    from reduced_dynamics.simulator import SimulationOptions, simulate_bag
    # PD tracking about the initial shape: the joints stay inside their URDF limits, which
    # the simulator enforces (the default sinusoid leaves j5's at 3.9 s).
    simulate_bag(robot, path, SimulationOptions(duration=seconds, rate=1000.0, torque='pd',
                                                overwrite=True))


def tile_bag(source: str, target: str, seconds: float, topics: Sequence[str]) -> int:
    """
    Write a ``seconds`` long bag by repeating ``source``'s ``topics`` shifted in time.

    Header stamps are patched in the CDR bytes (a std_msgs/Header leads both
    JointState and Odometry: sec at bytes 4-8, nanosec at 8-12, little endian),
    so the copy costs no (de)serialisation. The motion jumps at each seam (the
    estimator sees momentum steps there); the bag is for memory measurements.
    Returns the number of messages written.
    """
    from reduced_dynamics.bag.reader import open_bag
    from reduced_dynamics.bag.writer import BagWriter
    with open_bag(source) as reader:
        types = {t: m for t, m in reader.topics().items() if t in topics}
        items = [(m.topic, m.timestamp_ns, bytes(m.data)) for m in reader.raw_messages(topics)]
        start, period = reader.start_ns, reader.duration_ns + 1_000_000
    written = 0
    with BagWriter(target, types, overwrite=True) as writer:
        for tile in range(max(1, int(np.ceil(seconds * NS / period)))):
            shift = tile * period
            for topic, stamp, data in items:
                new = stamp + shift
                if new - start > seconds * NS:
                    break
                buffer = bytearray(data)
                header = int.from_bytes(buffer[4:8], 'little', signed=True) * NS \
                    + int.from_bytes(buffer[8:12], 'little') + shift
                buffer[4:8] = int(header // NS).to_bytes(4, 'little', signed=True)
                buffer[8:12] = int(header % NS).to_bytes(4, 'little')
                writer.write_raw(topic, new, bytes(buffer))
                written += 1
    return written


def replay_once(robot, bag: str, out: str, smooth: bool = True) -> tuple[float, int]:
    """Replay ``bag`` with prediction off; return (seconds, processed samples)."""
    from reduced_dynamics.params import defaults
    from reduced_dynamics.replay import replay, ReplayOptions
    params = defaults()
    params['prediction_rate'] = 0.0
    start = time.perf_counter()
    summary = replay(bag, out, robot, ReplayOptions(params=params, overwrite=True,
                                                    smooth=smooth))
    return time.perf_counter() - start, int(summary['processed'])


def decode_once(bag: str, topics: Sequence[str], joint_topic: str,
                fixed_layout: bool = False) -> tuple[float, int]:
    """
    Read and decode ``topics`` of ``bag``; return (seconds, joint-state messages).

    ``fixed_layout`` False: rosbags message objects (``BagReader.messages``);
    True: samples through replay's own input decoders (fixed-layout CDR, the
    typestore only for what they refuse), i.e. what replay itself pays.
    """
    from reduced_dynamics.bag.reader import open_bag
    from reduced_dynamics.replay import input_decoder
    start = time.perf_counter()
    count = 0
    with open_bag(bag) as reader:
        if fixed_layout:
            decoders = {pair: input_decoder(reader, *pair, '')
                        for pair in reader.connection_types(topics)}
            for message in reader.raw_messages(topics):
                decoders[message.topic, message.msgtype](message.data)
                count += message.topic == joint_topic
        else:
            for message in reader.messages(topics):
                count += message.topic == joint_topic
    return time.perf_counter() - start, count


_MEMORY_SCRIPT = """
import sys, time
from reduced_dynamics.peak_memory import peak_resident_kib
from reduced_dynamics.robot.model import load_robot
from reduced_dynamics.params import defaults
from reduced_dynamics.replay import replay, ReplayOptions
robot = load_robot()
params = defaults()
params['prediction_rate'] = 0.0
before = peak_resident_kib()
start = time.perf_counter()
summary = replay(sys.argv[1], sys.argv[2], robot,
                 ReplayOptions(params=params, overwrite=True, smooth=True))
elapsed = time.perf_counter() - start
after = peak_resident_kib()
print(before, after, summary['processed'], elapsed)
"""


def replay_memory(bag: str, out: str) -> dict:
    """Replay ``bag`` in a fresh interpreter; return its peak RSS (MiB) before and after."""
    env = dict(os.environ)
    package_root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env['PYTHONPATH'] = package_root + os.pathsep + env.get('PYTHONPATH', '')
    result = subprocess.run([sys.executable, '-c', _MEMORY_SCRIPT, bag, out], env=env,
                            capture_output=True, text=True, check=True)
    before, after, processed, elapsed = result.stdout.split()[-4:]
    return {'rss_before_mib': int(before) / 1024.0, 'peak_rss_mib': int(after) / 1024.0,
            'processed': int(processed), 'seconds': float(elapsed)}


def bench_replay(report: Report, robot, settings: Settings, workdir: str) -> None:
    """Section 3: replay throughput against decode-only; peak memory against bag length."""
    from reduced_dynamics.simulator import TOPIC_JOINT_STATES, TOPIC_ODOM
    topics = (TOPIC_JOINT_STATES, TOPIC_ODOM)
    bag = os.path.join(workdir, 'input')
    simulate_input_bag(robot, bag, settings.replay_seconds)
    out = os.path.join(workdir, 'output')
    replays, causal, decodes, generic, processed = [], [], [], [], 0
    for _ in range(settings.repeats):
        seconds, count = decode_once(bag, topics, TOPIC_JOINT_STATES, fixed_layout=True)
        decodes.append(count / seconds)
        seconds, count = decode_once(bag, topics, TOPIC_JOINT_STATES)
        generic.append(count / seconds)
        seconds, processed = replay_once(robot, bag, out)
        replays.append(processed / seconds)
        seconds, processed = replay_once(robot, bag, out, smooth=False)
        causal.append(processed / seconds)
    shutil.rmtree(out, ignore_errors=True)
    label = f'{settings.replay_seconds:g} s at 1 kHz, {processed} samples'
    # The ratio is against the faster decoding, the one replay itself uses.
    report.add(make_figure('replay', 'replay throughput (prediction off)', 'samples/s',
                           replays, 'read+decode only (fixed layout)', decodes,
                           [r / d for r, d in zip(replays, decodes)],
                           '>= 10000/s, ratio >= 0.5',
                           lambda r: r >= 0.5 and spread(replays)[0] >= 10000.0, label))
    report.add(make_figure('replay', 'read+decode only (fixed layout)', 'samples/s', decodes,
                           note='baseline: raw messages through replay.input_decoder, '
                                'same topics'))
    report.add(make_figure('replay', 'replay throughput, against rosbags decoding', 'samples/s',
                           replays, 'read+decode only (rosbags)', generic,
                           [r / g for r, g in zip(replays, generic)],
                           '>= 0.4 (issue 19, smoothed)', lambda r: r >= 0.4,
                           note='the same replays; the earlier baseline'))
    report.add(make_figure('replay', 'replay --no-smooth, against rosbags decoding',
                           'samples/s', causal, 'read+decode only (rosbags)', generic,
                           [c / g for c, g in zip(causal, generic)], '>= 0.5 (issue 19)',
                           lambda r: r >= 0.5, note='prediction off, the causal outputs only'))
    report.add(make_figure('replay', 'read+decode only (rosbags)', 'samples/s', generic,
                           note='baseline: BagReader.messages (rosbags objects), same topics'))
    short_bag, long_bag = os.path.join(workdir, 'short'), os.path.join(workdir, 'long')
    tile_bag(bag, short_bag, settings.memory_short_seconds, topics)
    tile_bag(bag, long_bag, settings.memory_long_seconds, topics)
    short = replay_memory(short_bag, out)
    long = replay_memory(long_bag, out)
    shutil.rmtree(out, ignore_errors=True)
    shutil.rmtree(short_bag, ignore_errors=True)
    shutil.rmtree(long_bag, ignore_errors=True)
    report.details['replay_memory'] = {'short': short, 'long': long}
    growth = short['peak_rss_mib'], long['peak_rss_mib']
    note = (f'{settings.memory_long_seconds:g} s vs {settings.memory_short_seconds:g} s bag at '
            f'1 kHz (tiled from the simulated one); {long["processed"]} samples; '
            f'{long["processed"] / long["seconds"]:.0f} samples/s in the subprocess')
    if settings.quick:
        note += '; --quick: shorter than the 10-minute bag'
    report.add(make_figure('replay', 'smoothed replay peak RSS, long bag', 'MiB', [growth[1]],
                           'same, short bag', [growth[0]], [growth[1] / growth[0]],
                           'ratio <= 1.2 (flat)', lambda r: r <= 1.2, note))


def bench_typestore(report: Report, settings: Settings) -> None:
    """
    Section 3: a bag's message types in a fresh rosbags typestore, against the shared one.

    The work a replay's reader and writer did per bag before stop 41 (each made its own
    Jazzy store): rosbags' 14 generated functions per type, and the definition text and
    hash each output connection records.
    """
    from reduced_dynamics.messages.typestore import (definition, jazzy_typestore,
                                                     private_jazzy_typestore)
    from reduced_dynamics.topics import EVENTS_TOPIC, FIXED_LAG_TOPICS, OUTPUT_TOPICS
    outputs = {t.msgtype for t in (*OUTPUT_TOPICS, *FIXED_LAG_TOPICS, EVENTS_TOPIC)}
    types = sorted(outputs | {'sensor_msgs/msg/JointState', 'nav_msgs/msg/Odometry'})

    def cpu_ms(store: Any) -> float:
        start = time.process_time()
        for msgtype in types:
            store.get_msgdef(msgtype)
            definition(store, msgtype)
        return 1e3 * (time.process_time() - start)
    cpu_ms(jazzy_typestore())  # steady state: the shared store's first bag is behind it
    fresh, shared = [], []
    for _ in range(max(settings.repeats, 3)):
        fresh.append(cpu_ms(private_jazzy_typestore()))
        shared.append(cpu_ms(jazzy_typestore()))
    report.add(make_figure('replay', "a bag's message types, shared typestore", 'ms CPU',
                           shared, 'a fresh typestore per bag', fresh,
                           [a / b for a, b in zip(shared, fresh)],
                           note=f'{len(types)} types: the inputs and every output topic; '
                                'the fixed cost per bag stop 41 removed'))


# --------------------------------------------------------------------------- fleet
def _fleet_seconds(jobs: list, out: str, workers: int, backend: str) -> float:
    """Run a fleet into a fresh ``out``; return its wall time (every bag must replay)."""
    from reduced_dynamics.fleet import run_fleet
    shutil.rmtree(out, ignore_errors=True)
    start = time.perf_counter()
    result = run_fleet(jobs, out, workers, backend, progress=False)
    elapsed = time.perf_counter() - start
    failed = [row for row in result.rows if row['status'] != 'ok']
    if failed:
        raise RuntimeError(f'fleet bench: a bag failed: {failed[0]}')
    return elapsed


def bench_fleet(report: Report, robot, settings: Settings, workdir: str) -> None:
    """
    Section fleet: replay-many throughput, 2 workers vs 1, Ray on this machine vs the pool.

    ``fleet_bags`` copies of one simulated bag (1 kHz); every repeat runs each
    configuration into a fresh OUTDIR (nothing resumed). The Ray cluster is started
    once before the repeats, as a campaign's would be (its start-up is not timed), or
    the cluster this process runs already is used.
    """
    from reduced_dynamics.fleet import plan_jobs
    source = os.path.join(workdir, 'bags', 'bag0')
    simulate_input_bag(robot, source, settings.fleet_bag_seconds)
    for k in range(1, settings.fleet_bags):
        shutil.copytree(source, os.path.join(workdir, 'bags', f'bag{k}'))
    out = os.path.join(workdir, 'out')
    jobs = plan_jobs([os.path.join(workdir, 'bags')], out, {})
    # A cluster this process runs already is used as it is (as replay-many uses it), and
    # left running; otherwise one of 2 CPUs is started here, and shut down at the end.
    started_here = False
    try:
        import ray
        if not ray.is_initialized():
            ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
            started_here = True
        ray_note = ''
    except Exception as error:  # noqa: B902 (not installed, or it cannot start here)
        ray, ray_note = None, f'Ray unavailable: {error}'
    runs: dict[str, list] = {'1': [], '2': [], 'ray': []}
    # Other processes on the machine take cores the 2 workers would use: say how busy it was.
    load = os.getloadavg()[0]
    try:
        cluster = '' if ray is None else \
            f'; {ray.cluster_resources().get("CPU", 0):g} Ray CPUs, ' + (
                'ray.init before the repeats' if started_here else 'a running cluster')
        for _ in range(settings.repeats):
            # Alternating the configurations spreads the machine's drift over all three.
            runs['1'].append(_fleet_seconds(jobs, out, 1, 'local'))
            runs['2'].append(_fleet_seconds(jobs, out, 2, 'local'))
            if ray is not None:
                runs['ray'].append(_fleet_seconds(jobs, out, 2, 'ray'))
    finally:
        if started_here:
            ray.shutdown()
        shutil.rmtree(out, ignore_errors=True)
    count = len(jobs)
    rate = {k: [count / s for s in v] for k, v in runs.items()}
    label = (f'{count} bags of {settings.fleet_bag_seconds:g} s at 1 kHz, '
             f'{os.cpu_count()} CPUs, load average {load:.1f} -> {os.getloadavg()[0]:.1f}')
    try:
        with open('/proc/sys/kernel/sched_autogroup_enabled', encoding='ascii') as stream:
            if stream.read().strip() == '1':
                # Linux shares the CPUs between sessions, not processes: on a busy
                # machine the workers of one fleet split one session's share.
                label += '; kernel autogroup on (CPU shared per session)'
    except OSError:
        pass
    report.add(make_figure('fleet', 'replay-many, local pool, 2 workers', 'bags/s', rate['2'],
                           'same, 1 worker', rate['1'],
                           [a / b for a, b in zip(rate['2'], rate['1'])], 'ratio >= 1.7',
                           lambda r: r >= 1.7, label))
    if ray is not None:
        report.add(make_figure('fleet', 'replay-many, Ray on this machine, 2 CPUs', 'bags/s',
                               rate['ray'], 'local pool, 2 workers', rate['2'],
                               [a / b for a, b in zip(rate['ray'], rate['2'])],
                               'ratio >= 0.85 (within 15 %)', lambda r: r >= 0.85,
                               label + cluster))
    else:
        report.add(make_figure('fleet', 'replay-many, local pool, 1 worker', 'bags/s',
                               rate['1'], note=ray_note))


# --------------------------------------------------------------------------- 4. scaling
def time_evaluation(robot, calls: int, repeats: int) -> list:
    """Return seconds per reduced vector-field evaluation at a generic state."""
    from reduced_dynamics.geometry.isotropy import MomentumClass
    from reduced_dynamics.reduction.vector_field import ReducedSystem
    from reduced_dynamics.validation import random_scenario
    scenario = random_scenario(robot, MomentumClass.GENERIC, 0)
    system, z = ReducedSystem.from_full_state(robot, scenario.state)
    tau = np.zeros(robot.m)
    evaluate = system.evaluate
    out = []
    for _ in range(repeats):
        start = time.perf_counter()
        for _ in range(calls):
            evaluate(z, tau)
        out.append((time.perf_counter() - start) / calls)
    return out


def bench_scaling(report: Report, settings: Settings) -> None:
    """Section 4: costs on random trees and their fitted exponents in m."""
    from reduced_dynamics.robot.model import load_robot
    from reduced_dynamics.robot.random_tree import random_tree_urdf
    sizes, update_costs, evaluation_costs, crba_costs = [], [], [], []
    streaming_costs = []
    for m in settings.shape_joints:
        robot = load_robot(random_tree_urdf(m, seed=1))
        timings, crbas = measure_update(robot, settings, settings.scaling_samples,
                                        ('batched', 'streaming'))
        updates = timings['batched']
        evaluations = time_evaluation(robot, settings.scaling_evaluations, settings.repeats)
        sizes.append(m)
        update_costs.append(spread(updates)[0])
        streaming_costs.append(spread(timings['streaming'])[0])
        crba_costs.append(spread(crbas)[0])
        evaluation_costs.append(spread(evaluations)[0])
        report.add(make_figure('scaling', f'update, random tree m={m}', 'us/sample',
                               [1e6 * u for u in updates], 'crba', [1e6 * c for c in crbas],
                               [u / c for u, c in zip(updates, crbas)], note='batched'))
        report.add(make_figure('scaling', f'update streaming, random tree m={m}', 'us/sample',
                               [1e6 * u for u in timings['streaming']], 'crba',
                               [1e6 * c for c in crbas],
                               [u / c for u, c in zip(timings['streaming'], crbas)]))
        report.add(make_figure('scaling', f'reduced evaluation, random tree m={m}', 'us/call',
                               [1e6 * e for e in evaluations], 'crba',
                               [1e6 * c for c in crbas],
                               [e / c for e, c in zip(evaluations, crbas)]))
    exponents = {'update': fit_exponent(sizes, update_costs),
                 'update_streaming': fit_exponent(sizes, streaming_costs),
                 'reduced_evaluation': fit_exponent(sizes, evaluation_costs),
                 'crba': fit_exponent(sizes, crba_costs)}
    report.details['scaling'] = {'shape_joints': sizes, 'update_s': update_costs,
                                 'update_streaming_s': streaming_costs,
                                 'evaluation_s': evaluation_costs, 'crba_s': crba_costs,
                                 'exponents': exponents}
    sizes_text = ','.join(str(m) for m in sizes)
    report.add(make_figure('scaling', 'update cost exponent', 'p in m^p', [exponents['update']],
                           target='<= 2', check=lambda p: p <= 2.0,
                           note=f'batched; log-log fit over m={sizes_text}'))
    report.add(make_figure('scaling', 'update cost exponent, streaming', 'p in m^p',
                           [exponents['update_streaming']], target='<= 2',
                           check=lambda p: p <= 2.0, note=f'm={sizes_text}'))
    report.add(make_figure('scaling', 'reduced evaluation exponent', 'p in m^p',
                           [exponents['reduced_evaluation']], note=f'm={sizes_text}'))
    report.add(make_figure('scaling', 'crba exponent', 'p in m^p', [exponents['crba']],
                           note=f'm={sizes_text}'))


# --------------------------------------------------------------------------- 6. node
#: Input configurations of the node section: (label, joint-state rate, odometry rate).
NODE_RATES = (('joints 1 kHz + odom 200 Hz', 1000.0, 200.0),
              ('joints 1 kHz + odom 1 kHz', 1000.0, 1000.0))
#: Joint-state rates [Hz] of the sustained-rate sweep (odometry 200 Hz, at most the joints').
NODE_SWEEP = (250.0, 500.0, 1000.0, 2000.0, 5000.0)
#: Issue 19's targets: the sustained rate [Hz] and the p99 latency [ms] at 1 kHz + 200 Hz.
SUSTAINED_TARGET, P99_TARGET_MS = 5000.0, 2.0


def node_domain_id() -> int:
    """Return a ROS_DOMAIN_ID of its own for this run (RD_BENCH_DOMAIN_ID overrides)."""
    if os.environ.get('RD_BENCH_DOMAIN_ID'):
        return int(os.environ['RD_BENCH_DOMAIN_ID'])
    # 0..101 are safe with Fast DDS's port mapping on Linux; stay off the common 0.
    return 60 + os.getpid() % 40


def node_phase_figures(sent: Sequence[int], received: Sequence[tuple],
                       base_stamps: Optional[Sequence[int]] = None) -> dict:
    """
    Summarise one measured window: inputs sent, outputs that came back, latency.

    ``sent`` are the stamps (send times, ns) of the joint states of the window,
    ``received`` (stamp, receive time) pairs of every output the probe took.
    Latency is receive time minus stamp; an input without an output is a drop.
    ``base_stamps``: the send times of the window's base samples. A joint state's
    row needs the base sample at or after its stamp (its pose is interpolated
    between the two bracketing samples, estimator/sync.py), so its output cannot
    leave before that sample was sent: ``wait_*`` is that bound per joint state,
    ``ready_*`` the latency counted from it (what the node itself adds).
    """
    arrival = dict(received)
    latency = np.array([arrival[s] - s for s in sent if s in arrival], dtype=float) * 1e-6
    count = len(sent)
    rate = (count - 1) / ((sent[-1] - sent[0]) * 1e-9) if count > 1 else 0.0
    delivered = latency.size
    row = {'sent': count, 'delivered': delivered, 'drops': count - delivered,
           'input_rate': rate, 'delivered_rate': rate * delivered / count if count else 0.0,
           'p50_ms': float(np.percentile(latency, 50)) if delivered else float('nan'),
           'p99_ms': float(np.percentile(latency, 99)) if delivered else float('nan')}
    if base_stamps:
        bases = np.sort(np.asarray(base_stamps, dtype=np.int64))
        joints = np.asarray(sent, dtype=np.int64)
        after = np.searchsorted(bases, joints, side='left')
        bracketed = after < bases.size
        ready = np.where(bracketed, bases[np.minimum(after, bases.size - 1)], joints)
        wait = (ready - joints)[bracketed] * 1e-6
        ready_at = dict(zip(joints.tolist(), ready.tolist()))
        beyond = np.array([arrival[s] - ready_at[s] for s in sent if s in arrival],
                          dtype=float) * 1e-6
        row.update({
            'wait_p50_ms': float(np.percentile(wait, 50)) if wait.size else float('nan'),
            'wait_p99_ms': float(np.percentile(wait, 99)) if wait.size else float('nan'),
            'ready_p50_ms': float(np.percentile(beyond, 50)) if delivered else float('nan'),
            'ready_p99_ms': float(np.percentile(beyond, 99)) if delivered else float('nan')})
    return row


def _stop(process: subprocess.Popen, timeout: float = 10.0) -> Optional[int]:
    """SIGINT, then SIGKILL after ``timeout``; return the exit code (None: killed)."""
    if process.poll() is None:
        process.send_signal(signal.SIGINT)
        try:
            return process.wait(timeout)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
            return None
    return process.returncode


def run_node_phases(workdir: str, joint_rates: Sequence[float], base_rate: float,
                    seconds: float, warmup: float, repeats: int,
                    env: dict) -> tuple[list, dict]:
    """
    One configuration over real DDS: the node, the relay, the probe and the publisher.

    Four processes: ``python -m reduced_dynamics.node`` (defaults: predictions on),
    the relay and the probe of :mod:`reduced_dynamics.node_bench`, then the publisher,
    which feeds ``repeats`` windows per joint-state rate to the relay, then as many to the
    node (each stream pauses 0.5 s between windows). Returns the
    publisher's phases and the probe's records.
    """
    python = sys.executable
    log = open(os.path.join(workdir, 'processes.log'), 'a', encoding='utf-8')
    probe_out = os.path.join(workdir, 'probe.json')
    ready = os.path.join(workdir, 'probe.ready')
    publish_out = os.path.join(workdir, 'publish.json')
    for path in (probe_out, ready, publish_out):
        if os.path.exists(path):
            os.remove(path)
    spawn = [[python, '-m', 'reduced_dynamics.node'],
             [python, '-m', 'reduced_dynamics.node_bench', 'relay']]
    targets = [subprocess.Popen(argv, env=env, stdout=log, stderr=log) for argv in spawn]
    probe = subprocess.Popen([python, '-m', 'reduced_dynamics.node_bench', 'probe',
                              '--out', probe_out, '--ready', ready],
                             env=env, stdout=log, stderr=log)
    try:
        deadline = time.monotonic() + 120.0
        while not os.path.exists(ready):
            if time.monotonic() > deadline or any(p.poll() is not None
                                                  for p in targets + [probe]):
                raise RuntimeError('node bench: processes did not come up (see '
                                   f'{log.name})')
            time.sleep(0.1)
        subprocess.run([python, '-m', 'reduced_dynamics.node_bench', 'publish',
                        '--out', publish_out,
                        '--joint-rates', ','.join(str(r) for r in joint_rates),
                        '--base-rate', str(base_rate), '--seconds', str(seconds),
                        '--warmup', str(warmup), '--repeats', str(repeats)],
                       env=env, stdout=log, stderr=log, check=True, timeout=600)
        time.sleep(0.5)  # outputs still in flight
    finally:
        _stop(probe)
        for process in targets:
            _stop(process)
        log.close()
    with open(publish_out, encoding='utf-8') as stream:
        phases = json.load(stream)['phases']
    with open(probe_out, encoding='utf-8') as stream:
        records = json.load(stream)
    return phases, records


def bench_node(report: Report, settings: Settings, workdir: str,
               rates: Sequence[tuple] = NODE_RATES,
               sweep: Sequence[float] = NODE_SWEEP) -> None:
    """
    Section 6: the node over real DDS against a bare rclpy relay, same run.

    Per configuration of :data:`NODE_RATES`: the input rate sustained (joint states
    delivered per second), drops (joint states without an output) and input-to-output
    latency p50/p99 of the node's ``~/momentum``, each with the relay's figure of the
    window of the same rank as baseline. Separate processes, a ROS_DOMAIN_ID of its own,
    discovery on localhost only.
    """
    import importlib.util
    if importlib.util.find_spec('rclpy') is None:
        report.details['node'] = 'skipped: rclpy is not importable (pip install .[ros])'
        return
    env = dict(os.environ, ROS_DOMAIN_ID=str(node_domain_id()),
               ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST', PYTHONUNBUFFERED='1')
    from reduced_dynamics.node_bench import NODE_OUTPUT, RELAY_OUTPUT
    details = {'domain_id': env['ROS_DOMAIN_ID'], 'configurations': {}}
    for label, joint_rate, base_rate in rates:
        phases, records = run_node_phases(workdir, [joint_rate], base_rate,
                                          settings.node_seconds, settings.node_warmup,
                                          settings.repeats, env)
        rows: dict[str, list] = {'relay': [], 'node': []}
        for phase in phases:
            output = NODE_OUTPUT if phase['target'] == 'node' else RELAY_OUTPUT
            rows[phase['target']].append(node_phase_figures(
                phase['joint_stamps'], [tuple(r) for r in records[output]],
                phase.get('base_stamps')))
        details['configurations'][label] = rows
        node, relay = rows['node'], rows['relay']

        def column(rows: list, key: str) -> list:
            return [row[key] for row in rows]
        window = (f'{settings.node_seconds:g} s windows after {settings.node_warmup:g} s '
                  f'warm-up; {int(np.median(column(node, "sent")))} joint states each')
        report.add(make_figure(
            'node', f'{label}: joint states delivered/s', 'msg/s',
            column(node, 'delivered_rate'), 'bare rclpy relay', column(relay, 'delivered_rate'),
            [n / r for n, r in zip(column(node, 'delivered_rate'),
                                   column(relay, 'delivered_rate'))],
            'no drops', lambda _r: max(column(node, 'drops')) == 0,
            f'{window}; input {np.median(column(node, "input_rate")):.0f}/s'))
        report.add(make_figure(
            'node', f'{label}: drops', 'msgs', column(node, 'drops'), 'bare rclpy relay',
            column(relay, 'drops'), note='joint states of the window without ~/momentum'))
        for key, name in (('p50_ms', 'latency p50'), ('p99_ms', 'latency p99')):
            values = column(node, key)
            targeted = key == 'p99_ms' and (joint_rate, base_rate) == (1000.0, 200.0)
            met = bool(float(np.median(values)) <= P99_TARGET_MS)
            report.add(make_figure(
                'node', f'{label}: {name}', 'ms', values, 'bare rclpy relay',
                column(relay, key), [n / r for n, r in zip(values, column(relay, key))],
                f'<= {P99_TARGET_MS:g} ms' if targeted else '',
                (lambda _r, met=met: met) if targeted else None,
                note='joint state sent -> ~/momentum received (relay: -> relayed copy)'))
        if all('ready_p99_ms' in row for row in node):
            # The bound no interpolating estimator can beat, and the latency beyond it.
            targeted = (joint_rate, base_rate) == (1000.0, 200.0)
            wait, beyond = column(node, 'wait_p99_ms'), column(node, 'ready_p99_ms')
            met = bool(float(np.median(beyond)) <= P99_TARGET_MS)
            report.add(make_figure(
                'node', f'{label}: wait for the bracketing base sample, p99', 'ms', wait,
                note='joint state sent -> the first base sample at or after its stamp sent: '
                     'its row interpolates the pose between the two (estimator/sync.py), '
                     'so no output can leave earlier (a lower bound of the latency)'))
            report.add(make_figure(
                'node', f'{label}: latency p99 after the bracketing base sample', 'ms',
                beyond, 'bare rclpy relay', column(relay, 'p99_ms'),
                [n / r for n, r in zip(beyond, column(relay, 'p99_ms'))],
                f'<= {P99_TARGET_MS:g} ms' if targeted else '',
                (lambda _r, met=met: met) if targeted else None,
                note='that base sample sent -> ~/momentum received: what the node adds'))
    bench_node_callbacks(report, settings, env, details)
    if sweep:
        bench_node_sweep(report, settings, workdir, env, sweep, details)
    report.details['node'] = details


#: The in-process callback rows: the node at its default smoothing_lag, and without it.
CALLBACK_LAGS = (0.5, 0.0)


def node_callback_times(env: dict, seconds: float, smoothing_lag: float) -> list:
    """Return the node's odometry callback durations [s] (node_bench ``callbacks``)."""
    done = subprocess.run(
        [sys.executable, '-m', 'reduced_dynamics.node_bench', 'callbacks', '--seconds',
         str(seconds), '--warmup', '2.1', '--smoothing-lag', str(smoothing_lag)],
        env=env, check=True, capture_output=True, text=True)
    return json.loads(done.stdout.strip().splitlines()[-1])['odometry_callback_s']


def bench_node_callbacks(report: Report, settings: Settings, env: dict,
                         details: dict) -> None:
    """
    Time the node's odometry callbacks in-process (1 kHz joints + 200 Hz odometry, real pace).

    Each odometry sample releases the rows that waited for it: its callback is what the
    node adds after the bracketing base sample, without DDS. At the default
    smoothing_lag and without it (the baseline), alternating processes, ``repeats`` each.
    """
    times: dict[float, list] = {lag: [] for lag in CALLBACK_LAGS}
    for _ in range(settings.repeats):
        for lag in CALLBACK_LAGS:
            times[lag].append(1e3 * np.asarray(node_callback_times(
                env, settings.node_callback_seconds, lag)))
    details['callbacks_ms'] = {str(lag): [t.tolist() for t in runs] for lag, runs in times.items()}
    lagged, plain = times[CALLBACK_LAGS[0]], times[CALLBACK_LAGS[1]]
    for name, q in (('p50', 50), ('p99', 99)):
        values = [float(np.percentile(t, q)) for t in lagged]
        base = [float(np.percentile(t, q)) for t in plain]
        report.add(make_figure(
            'node', f'in-process, joints 1 kHz + odom 200 Hz: odometry callback {name}', 'ms',
            values, 'the same, smoothing_lag 0', base, [v / b for v, b in zip(values, base)],
            note=f'the node in one process (node_bench callbacks), smoothing_lag '
                 f'{CALLBACK_LAGS[0]:g} (default); {settings.node_callback_seconds:g} s after '
                 '2.1 s of input: the rows an odometry sample releases, processed and '
                 'published (what the node adds after the bracketing base sample, no DDS)'))


def bench_node_sweep(report: Report, settings: Settings, workdir: str, env: dict,
                     sweep: Sequence[float], details: dict) -> None:
    """Measure the highest joint-state rate (odometry 200 Hz) that no window dropped from."""
    from reduced_dynamics.node_bench import NODE_OUTPUT, RELAY_OUTPUT
    repeats = min(settings.repeats, 3)
    phases, records = run_node_phases(workdir, sweep, 200.0, settings.node_sweep_seconds,
                                      settings.node_warmup, repeats, env)
    drops: dict[str, dict] = {'relay': {}, 'node': {}}
    for phase in phases:
        output = NODE_OUTPUT if phase['target'] == 'node' else RELAY_OUTPUT
        row = node_phase_figures(phase['joint_stamps'], [tuple(r) for r in records[output]])
        drops[phase['target']].setdefault(phase['joint_rate'], []).append(row['drops'])
    details['sweep_drops'] = {t: {str(r): d for r, d in rows.items()} for t, rows in drops.items()}

    def sustained(target: str) -> float:
        clean = [rate for rate, d in drops[target].items() if max(d) == 0]
        return max(clean, default=0.0)
    node, relay = sustained('node'), sustained('relay')
    report.add(make_figure(
        'node', 'sustained joint-state rate without drops (odom 200 Hz)', 'Hz', [node],
        'bare rclpy relay', [relay], [node / relay] if relay else None,
        f'>= {SUSTAINED_TARGET:g} Hz', lambda _r: node >= SUSTAINED_TARGET,
        f'highest of {", ".join(f"{r:g}" for r in sweep)} Hz with 0 drops in {repeats} '
        f'windows of {settings.node_sweep_seconds:g} s'))


# --------------------------------------------------------------------------- output
def _number(value: Optional[float]) -> str:
    if value is None:
        return ''
    magnitude = abs(value)
    if magnitude != 0.0 and (magnitude >= 1e5 or magnitude < 1e-2):
        return f'{value:.3g}'
    return f'{value:.4g}' if magnitude < 100 else f'{value:.0f}'


def format_report(report: Report) -> str:
    """Return the printed table."""
    machine = report.machine
    lines = [f'machine: {machine["cpu"]}, {machine["nproc"]} CPUs; Python {machine["python"]}, '
             f'numpy {machine["numpy"]}, scipy {machine["scipy"]}, '
             f'pinocchio {machine["pinocchio"]}',
             f'each figure: median [IQR] over {report.settings["repeats"]} repeats'
             + ('; --quick sizes' if report.settings.get('quick') else '')]
    header = (f'{"section":<11}{"figure":<48}{"median [IQR]":>26} {"unit":<12}'
              f'{"ratio [IQR]":>24}  {"vs":<32}{"target":<26}{"met":<5}note')
    lines += [header, '-' * len(header)]
    for f in report.figures:
        value = f'{_number(f.median)} [{_number(f.low)}, {_number(f.high)}]'
        ratio = '' if f.ratio is None else \
            f'{_number(f.ratio)} [{_number(f.ratio_low)}, {_number(f.ratio_high)}]'
        met = '' if f.met is None else ('yes' if f.met else 'NO')
        lines.append(f'{f.section:<11}{f.name:<48}{value:>26} {f.unit:<12}{ratio:>24}  '
                     f'{f.baseline:<32}{f.target:<26}{met:<5}{f.note}')
    return '\n'.join(lines)


def write_csv(report: Report, path: str) -> None:
    """Write one row per figure."""
    names = list(Figure.__dataclass_fields__)
    with open(path, 'w', newline='', encoding='utf-8') as stream:
        writer = csv.DictWriter(stream, fieldnames=names)
        writer.writeheader()
        for figure in report.figures:
            writer.writerow(asdict(figure))


SECTIONS = ('update', 'prediction', 'replay', 'scaling', 'planned', 'node', 'payload',
            'fleet')
#: Sections run only when named (long by design).
ON_REQUEST = ('soak',)


def _workdir() -> tempfile.TemporaryDirectory:
    """Return a scratch folder (context manager) removed after the section, errors ignored."""
    return tempfile.TemporaryDirectory(prefix='reduced_dynamics_bench_',
                                       ignore_cleanup_errors=True)


def run_bench(settings: Settings, sections: Sequence[str] = SECTIONS,
              progress: Optional[Callable[[str], None]] = None) -> Report:
    """Run the chosen sections and return the report."""
    from reduced_dynamics.robot.model import load_robot
    say = progress or (lambda text: None)
    report = Report(machine_info(), asdict(settings))
    robot = load_robot()
    if 'update' in sections:
        say('update...')
        bench_update(report, robot, settings)
        bench_step_test(report, robot, settings)
        bench_multiscale(report, robot, settings)
    if 'prediction' in sections:
        say('prediction...')
        bench_prediction(report, robot, settings)
        from reduced_dynamics.covariance_bench import bench_covariance
        bench_covariance(report, robot, settings)
    if 'replay' in sections:
        say('replay...')
        with _workdir() as workdir:
            bench_replay(report, robot, settings, workdir)
        bench_typestore(report, settings)
    if 'scaling' in sections:
        say('scaling...')
        bench_scaling(report, settings)
    if 'planned' in sections:
        say('planned...')
        with _workdir() as workdir:
            bench_planned(report, settings, workdir)
    if 'payload' in sections:
        say('payload...')
        from reduced_dynamics.payload_bench import bench_payload
        with _workdir() as workdir:
            bench_payload(report, robot, settings, workdir)
    if 'node' in sections:
        say('node (real DDS)...')
        with _workdir() as workdir:
            bench_node(report, settings, workdir)
    if 'fleet' in sections:
        say('fleet (replay-many)...')
        with _workdir() as workdir:
            bench_fleet(report, robot, settings, workdir)
    if 'soak' in sections:
        say(f'soak (node {settings.soak_seconds:g} s over real DDS, then replays)...')
        from reduced_dynamics.soak import bench_soak
        with _workdir() as workdir:
            bench_soak(report, robot, settings, workdir)
    return report


def _run(args: argparse.Namespace) -> int:
    settings = Settings.quick_settings(args.repeats) if args.quick else Settings()
    if args.repeats and not args.quick:
        settings.repeats = args.repeats
    if settings.repeats < 1:
        raise ValueError('--repeats must be at least 1')
    if args.soak_duration is not None:
        if not args.soak_duration > 0.0:
            raise ValueError('--soak-duration must be > 0 s')
        settings.soak_seconds = args.soak_duration
    if args.soak_bag_seconds is not None:
        if not args.soak_bag_seconds > 0.0:
            raise ValueError('--soak-bag-seconds must be > 0 s')
        settings.soak_bag_seconds = args.soak_bag_seconds
    sections = args.sections or SECTIONS
    report = run_bench(settings, sections,
                       lambda text: print(f'bench: {text}', file=sys.stderr, flush=True))
    print(format_report(report))
    if args.json:
        with open(args.json, 'w', encoding='utf-8') as stream:
            json.dump(report.to_dict(), stream, indent=2)
    if args.csv:
        write_csv(report, args.csv)
    return 0


def register_command(commands: Any) -> None:
    """Add the ``bench`` subcommand."""
    parser = commands.add_parser(
        'bench', help='benchmark the estimator, prediction, replay and scaling',
        description='Measure each figure as a median over repeats (with its interquartile '
                    'range) and as a ratio to a baseline measured in the same run.')
    parser.add_argument('--quick', action='store_true',
                        help='small sizes (short bags, fewer tolerances); the node section '
                             'over DDS alone takes ~2 min')
    parser.add_argument('--repeats', type=int, default=None,
                        help='repeats per figure (default 7, or 3 with --quick)')
    parser.add_argument('--json', metavar='FILE', help='write the report as JSON')
    parser.add_argument('--csv', metavar='FILE', help='write the figures as CSV')
    parser.add_argument('--sections', nargs='+',
                        choices=SECTIONS + ON_REQUEST,
                        help='run only these sections (default: all but soak)')
    parser.add_argument('--soak-duration', type=float, default=None, metavar='SECONDS',
                        help='section soak: how long the node is fed (default 60 s, '
                             '30 s with --quick)')
    parser.add_argument('--soak-bag-seconds', type=float, default=None, metavar='SECONDS',
                        help='section soak: the long replay bag (default 300 s)')
    parser.set_defaults(func=_run)
