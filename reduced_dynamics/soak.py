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
``reduced-dynamics bench --sections soak``: whether a long run stays flat (issue 27).

Three measurements, each reported as figures of the bench report:

* **the node** on real rclpy (``python -m reduced_dynamics.node``, default
  parameters, predictions on) fed 1 kHz joint states and 200 Hz odometry for
  ``--soak-duration`` seconds by :mod:`reduced_dynamics.node_bench`'s
  ``soak-publish``, its ``~/momentum`` recorded by ``soak-probe`` in a process of
  its own. The node's RSS and CPU time are read from ``/proc`` every second. It
  reports the RSS slope after the warm-up (Theil-Sen with its interval, least
  squares with its standard error, the ceiling's slope: :func:`rss_trend`), CPU per
  sample and latency p99 in the first and the last tenth of the measured
  window, outputs per input and log lines per hour;
* **retained bytes per sample**: tracemalloc around an in-process
  :class:`~reduced_dynamics.estimator.pipeline.Estimator` with the node's
  defaults fed the bench's 1 kHz samples (200 Hz odometry), after a warm-up:
  the growth rate of traced memory (:func:`growth_figures`), not a one-off step;
* **replay**: ``replay --no-smooth`` (default parameters, predictions on) of a
  short and a long simulated 1 kHz bag in fresh interpreters: peak RSS ratio.

The figure computations are ROS-free functions (tested in test/test_soak.py).
"""

from __future__ import annotations

import functools
import json
import os
import subprocess
import sys
import time
from typing import Any, Callable, Optional, Sequence

import numpy as np

NS = 1_000_000_000
MIB = 1024.0 * 1024.0
#: Targets of issue 27.
SLOPE_TARGET_MIB_H, RETAINED_TARGET_B, REPLAY_RATIO_TARGET, TENTH_TARGET = 1.0, 2.0, 1.1, 1.1


def rss_slope(times_s: Sequence[float], rss_bytes: Sequence[float], warmup_s: float) -> float:
    """Return the least-squares slope [MiB/h] of RSS over time from ``warmup_s`` on."""
    t, rss = np.asarray(times_s, float), np.asarray(rss_bytes, float)
    chosen = t >= warmup_s
    if chosen.sum() < 2:
        raise ValueError('fewer than two RSS samples after the warm-up')
    slope = np.polyfit(t[chosen], rss[chosen], 1)[0]
    return float(slope * 3600.0 / MIB)


def rss_trend(times_s: Sequence[float], rss_bytes: Sequence[float], warmup_s: float,
              block_s: Optional[float] = None, max_points: int = 4000,
              draws: int = 200) -> dict[str, float]:
    """
    Robust RSS slopes [MiB/h] after ``warmup_s``, each with its uncertainty.

    An allocator that maps and returns blocks of a few MiB makes RSS swing down
    from a ceiling every few tens of seconds; a least-squares line over 45 minutes
    then moves by its standard error (~0.7 MiB/h in stop 22's hour) with where the
    swings fall. So three figures, each robust in its own way:

    * ``theil_sen``: the median of the pairwise slopes of the samples (evenly
      thinned to ``max_points``), which a swing moves little. Its standard error
      and 95 % interval (``theil_sen_se``, ``_low``, ``_high``) come from a
      residual block bootstrap (``draws`` series, blocks of ``block_s``, seeded):
      the swings last tens of seconds, so 1 s samples are not independent;
    * ``least_squares`` over ``block_s`` block means (default 60 s, a tenth of a
      shorter window) and its standard error;
    * ``ceiling``: the Theil-Sen slope of each block's maximum, the high-water
      mark a leak raises and a returned block does not lower.
    """
    from scipy.stats import linregress, theilslopes
    t, rss = np.asarray(times_s, float), np.asarray(rss_bytes, float) / MIB
    chosen = t >= warmup_s
    t, rss = t[chosen], rss[chosen]
    if block_s is None:
        block_s = min(60.0, (t.max() - warmup_s) / 10.0) if t.size else 60.0
    edges = np.arange(warmup_s, t.max() + block_s, block_s) if t.size else np.array([])
    index = np.searchsorted(edges, t, side='right') - 1
    blocks = [index == k for k in range(max(len(edges) - 1, 0)) if (index == k).any()]
    if len(blocks) < 3:
        raise ValueError(f'fewer than three {block_s:g} s blocks of RSS after the warm-up')
    thin = np.linspace(0, t.size - 1, min(t.size, max_points)).round().astype(int)
    slope, intercept = theilslopes(rss[thin], t[thin])[:2]
    boot = _block_bootstrap(t, rss, slope, intercept, block_s, draws)
    centre = np.array([t[k].mean() for k in blocks])
    line = linregress(centre, [rss[k].mean() for k in blocks])
    hour = 3600.0
    return {'theil_sen': float(slope * hour),
            'theil_sen_se': float(boot.std() * hour),
            'theil_sen_low': float(np.quantile(boot, 0.025) * hour),
            'theil_sen_high': float(np.quantile(boot, 0.975) * hour),
            'least_squares': float(line.slope * hour),
            'least_squares_se': float(line.stderr * hour),
            'ceiling': float(theilslopes([rss[k].max() for k in blocks], centre)[0] * hour),
            'blocks': len(blocks), 'block_s': float(block_s)}


def _block_bootstrap(t: np.ndarray, rss: np.ndarray, slope: float, intercept: float,
                     block_s: float, draws: int, points: int = 900) -> np.ndarray:
    """Theil-Sen slopes of ``draws`` series: the fitted line plus resampled residual blocks."""
    from scipy.stats import theilslopes
    keep = np.linspace(0, t.size - 1, min(t.size, points)).round().astype(int)
    t, residual = t[keep], (rss - (intercept + slope * t))[keep]
    spacing = (t[-1] - t[0]) / max(t.size - 1, 1)
    size = int(np.clip(round(block_s / spacing) if spacing > 0 else 1, 1, t.size))
    rng = np.random.default_rng(0)  # the same series give the same figures
    count = -(-t.size // size)
    slopes = np.empty(draws)
    for draw in range(draws):
        starts = rng.integers(0, t.size - size + 1, count)
        noise = np.concatenate([residual[a:a + size] for a in starts])[:t.size]
        slopes[draw] = theilslopes(intercept + slope * t + noise, t)[0]
    return slopes


def tenth_figures(records: np.ndarray, cpu: np.ndarray, start_ns: int,
                  end_ns: int, reference: Optional[np.ndarray] = None) -> dict[str, dict]:
    """
    CPU per sample [us] and latency p50/p99 [ms] in the first and last tenth of a window.

    ``records`` (K, 2): the probe's (stamp, receive time) per output, stamps
    being send times; ``cpu`` (J, 2): (wall time ns, process CPU seconds)
    samples. The window [start_ns, end_ns] is split in ten by stamp. With
    ``reference`` (L, 3: wall ns, CPU s of one crba, load average), each tenth
    also has the median crba [us] and load in it and the CPU per sample in crba.
    """
    edges = np.linspace(start_ns, end_ns, 11)
    return {name: window_figures(records, cpu, low, high, reference)
            for name, (low, high) in (('first', edges[:2]), ('last', edges[-2:]))}


def window_figures(records: np.ndarray, cpu: np.ndarray, low: float, high: float,
                   reference: Optional[np.ndarray] = None) -> dict[str, float]:
    """Return :func:`tenth_figures`'s figures of the outputs stamped in [low, high)."""
    chosen = (records[:, 0] >= low) & (records[:, 0] < high)
    latency = (records[chosen, 1] - records[chosen, 0]) * 1e-6
    at = np.interp([low, high], cpu[:, 0], cpu[:, 1])
    count = int(chosen.sum())
    out = {'outputs': count,
           'cpu_us_per_sample': float(at[1] - at[0]) / count * 1e6 if count else float('nan'),
           'p50_ms': float(np.percentile(latency, 50)) if count else float('nan'),
           'p99_ms': float(np.percentile(latency, 99)) if count else float('nan')}
    inside = np.zeros(0, bool) if reference is None else \
        (reference[:, 0] >= low) & (reference[:, 0] < high)
    if inside.any():
        crba_us = float(np.median(reference[inside, 1])) * 1e6
        out.update(crba_us=crba_us, load=float(np.median(reference[inside, 2])),
                   cpu_crba_per_sample=out['cpu_us_per_sample'] / crba_us)
    return out


def minute_series(records: np.ndarray, cpu: np.ndarray, start_ns: int, end_ns: int,
                  reference: Optional[np.ndarray] = None,
                  block_s: float = 60.0) -> list[list[float]]:
    """
    Per ``block_s`` from ``start_ns``: [start s, CPU us/sample, p99 ms, crba us, load].

    Blocks without an output are left out (NaN has no place in the bench's JSON).

    A drift over the run shows as a trend in these rows, a change of the machine's
    load as a step in the load and crba columns at the same time.
    """
    rows = []
    for low in np.arange(start_ns, end_ns, block_s * NS):
        figures = window_figures(records, cpu, low, min(low + block_s * NS, end_ns), reference)
        if not figures['outputs']:
            continue  # the end's sliver (the window's end is a stamp, not a minute)
        rows.append([round((low - start_ns) * 1e-9, 1)]
                    + [round(figures.get(key, float('nan')), 3)
                       for key in ('cpu_us_per_sample', 'p99_ms', 'crba_us', 'load')])
    return rows


def proc_sample(pid: int) -> tuple[int, float]:
    """Return a process's resident set [bytes] and CPU time [s] (user + system), from /proc."""
    with open(f'/proc/{pid}/statm', encoding='ascii') as stream:
        resident = int(stream.read().split()[1]) * os.sysconf('SC_PAGE_SIZE')
    with open(f'/proc/{pid}/stat', encoding='ascii') as stream:
        fields = stream.read().rpartition(')')[2].split()
    # Fields 14 and 15 of stat (utime, stime), counted after the command's closing ')'.
    ticks = int(fields[11]) + int(fields[12])
    return resident, ticks / os.sysconf('SC_CLK_TCK')


#: glibc's thread arenas are heaps of HEAP_MAX_SIZE (64 MiB on 64-bit), aligned to it.
ARENA_ALIGN = 64 << 20
#: Kinds of resident memory :func:`rss_by_kind` tells apart.
RSS_KINDS = ('heap', 'thread_arenas', 'anon', 'shm', 'files')
#: Every how many /proc samples the node's smaps is read (~ms each).
SMAPS_EVERY = 10


def classify_smaps(text: str) -> dict[str, int]:
    """
    Return resident bytes per kind from a ``/proc/PID/smaps`` text.

    ``heap``: the main thread's malloc heap (brk); ``thread_arenas``: anonymous
    mappings starting on a 64 MiB boundary (other threads' malloc arenas);
    ``anon``: other anonymous memory (Python's object arenas, large numpy arrays,
    stacks); ``shm``: /dev/shm (Fast DDS shared-memory transport); ``files``:
    every other file-backed mapping (libraries). Which kind grows tells a
    Python-level leak from a thread's malloc arena or the middleware.
    """
    out = dict.fromkeys(RSS_KINDS, 0)
    kind = 'anon'
    for line in text.splitlines():
        head, _, rest = line.partition(' ')
        if head == 'Rss:':
            out[kind] += int(rest.split()[0]) * 1024
        elif '-' in head and not head.endswith(':'):
            fields = rest.split()
            path = fields[4] if len(fields) > 4 else ''
            if path == '[heap]':
                kind = 'heap'
            elif path.startswith('/dev/shm'):
                kind = 'shm'
            elif path.startswith('/'):
                kind = 'files'
            elif not path and int(head.partition('-')[0], 16) % ARENA_ALIGN == 0:
                kind = 'thread_arenas'
            else:
                kind = 'anon'
    return out


def rss_by_kind(pid: int) -> dict[str, int]:
    """Return a process's resident bytes per kind (:func:`classify_smaps`)."""
    with open(f'/proc/{pid}/smaps', encoding='ascii', errors='replace') as stream:
        return classify_smaps(stream.read())


def _stop(process: subprocess.Popen, timeout: float = 20.0) -> Optional[int]:
    """SIGINT, then SIGKILL after ``timeout``; return the exit code (None: killed)."""
    from reduced_dynamics.bench import _stop as stop
    return stop(process, timeout)


def run_node_soak(workdir: str, seconds: float, env: dict, period: float = 1.0,
                  reference: Optional[Callable[[], float]] = None) -> dict:
    """
    Run the node, the probe and the publisher for ``seconds``; return the raw measurements.

    Returns the publisher's JSON, the probe's records (K, 2), the /proc samples
    (J, 3: wall ns, RSS bytes, CPU s) of the node, every SMAPS_EVERY-th with its
    RSS by kind ((wall ns, {kind: bytes}), :func:`rss_by_kind`), its log lines
    and its exit code. With ``reference`` (CPU seconds of a fixed piece of work,
    :func:`crba_reference`), also (L, 3) ``reference`` samples every
    SMAPS_EVERY-th sample: (wall ns, CPU seconds of the work, 1-minute load average).
    """
    python = sys.executable
    node_log = os.path.join(workdir, 'node.log')
    log = open(os.path.join(workdir, 'processes.log'), 'a', encoding='utf-8')
    probe_out = os.path.join(workdir, 'probe.npy')
    ready = os.path.join(workdir, 'probe.ready')
    publish_out = os.path.join(workdir, 'publish.json')
    with open(node_log, 'w', encoding='utf-8') as stream:
        node = subprocess.Popen([python, '-m', 'reduced_dynamics.node'], env=env,
                                stdout=stream, stderr=subprocess.STDOUT)
    probe = subprocess.Popen([python, '-m', 'reduced_dynamics.node_bench', 'soak-probe',
                              '--out', probe_out, '--ready', ready],
                             env=env, stdout=log, stderr=log)
    samples: list[tuple[int, int, float]] = []
    kinds: list[tuple[int, dict]] = []
    references: list[tuple[int, float, float]] = []
    code: Optional[int] = None
    try:
        deadline = time.monotonic() + 120.0
        while not os.path.exists(ready):
            if time.monotonic() > deadline or node.poll() is not None \
                    or probe.poll() is not None:
                raise RuntimeError(f'soak: processes did not come up (see {log.name}, '
                                   f'{node_log})')
            time.sleep(0.1)
        publisher = subprocess.Popen([python, '-m', 'reduced_dynamics.node_bench',
                                      'soak-publish', '--out', publish_out,
                                      '--seconds', str(seconds)],
                                     env=env, stdout=log, stderr=log)
        next_at = time.monotonic()
        while publisher.poll() is None:
            if node.poll() is not None:
                raise RuntimeError(f'soak: the node exited early (see {node_log})')
            resident, cpu = proc_sample(node.pid)
            samples.append((time.time_ns(), resident, cpu))
            if len(samples) % SMAPS_EVERY == 1:
                kinds.append((samples[-1][0], rss_by_kind(node.pid)))
                if reference is not None:
                    references.append((time.time_ns(), reference(), os.getloadavg()[0]))
            next_at += period
            time.sleep(max(0.0, next_at - time.monotonic()))
        if publisher.returncode:
            raise RuntimeError(f'soak: the publisher failed (see {log.name})')
        time.sleep(1.0)  # outputs still in flight
        resident, cpu = proc_sample(node.pid)
        samples.append((time.time_ns(), resident, cpu))
    finally:
        _stop(probe)
        code = _stop(node)
        log.close()
    with open(publish_out, encoding='utf-8') as stream:
        sent = json.load(stream)
    with open(node_log, encoding='utf-8', errors='replace') as stream:
        lines = stream.read().splitlines()
    return {'sent': sent, 'records': np.load(probe_out), 'proc': np.array(samples, float),
            'log_lines': lines, 'exit_code': code, 'rss_kinds': kinds,
            'reference': np.array(references, float).reshape(-1, 3)}


def crba_reference(robot: Any, calls: int = 500) -> Callable[[], float]:
    """
    Return a function giving the CPU seconds of one ``crba`` call, timed over ``calls``.

    The bench's unit of cost, timed beside the node in the same scheduling group:
    on a shared 2-core machine the CPU time a sample costs rises with the load on
    the other core (caches, a shared physical core), so a tenth's CPU per sample
    is compared in this unit as well as in microseconds.
    """
    from reduced_dynamics.bench import time_crba
    return functools.partial(time_crba, robot, calls, time.process_time)


def soak_warmup(seconds: float) -> float:
    """
    Return the warm-up [s] before the RSS slope of a ``seconds`` soak is fitted.

    The estimator's stores fill up to their bounds within its longest memory, the
    multi-scale test's calibration (``CALIBRATION_MEMORY``, 600 s): the one-hour soak
    of 65325c5 saw its last RSS step at 710 s and nothing after it (832.20 to 832.21
    MiB from 900 s to 3600 s), while a fit from 60 s read those steps as 4.2 MiB/h.
    So the warm-up is that memory plus 300 s, never more than a quarter of the run
    (a short run still fits three quarters; it then includes the filling) and never
    less than the 60 s the issue's first measurement used.
    """
    from reduced_dynamics.estimator.multiscale import CALIBRATION_MEMORY
    return max(min(CALIBRATION_MEMORY + 300.0, seconds / 4.0), min(60.0, seconds / 4.0))


def node_soak_figures(raw: dict, warmup_s: float) -> dict:
    """Return the soak's figures from :func:`run_node_soak`'s measurements."""
    sent, records, proc = raw['sent'], raw['records'], raw['proc']
    start_ns, end_ns = int(sent['start_ns']), int(sent['end_ns'])
    t = (proc[:, 0] - start_ns) * 1e-9
    window_start = start_ns + int(warmup_s * NS)
    tenths = tenth_figures(records, proc[:, [0, 2]], window_start, end_ns,
                           raw.get('reference'))
    hours = (end_ns - start_ns) * 1e-9 / 3600.0
    during = (proc[:, 0] >= start_ns) & (proc[:, 0] <= end_ns + NS)
    rss = proc[during, 1] / MIB
    return {'seconds': (end_ns - start_ns) * 1e-9, 'warmup_s': warmup_s,
            'rss_slope_mib_per_h': rss_slope(t[during], proc[during, 1], warmup_s),
            'rss_trend_mib_per_h': rss_trend(t[during], proc[during, 1], warmup_s),
            'rss_start_mib': float(rss[0]), 'rss_end_mib': float(rss[-1]),
            'rss_at_warmup_mib': float(np.interp(warmup_s, t[during], rss)),
            'joint_states_sent': sent['joint_states'], 'odometry_sent': sent['odometry'],
            'outputs': int(len(records)),
            'outputs_per_input': len(records) / sent['joint_states']
            if sent['joint_states'] else float('nan'),
            'log_lines': len(raw['log_lines']),
            'log_lines_per_hour': len(raw['log_lines']) / hours if hours else float('nan'),
            'publisher_late_max_s': sent['late_max_s'], 'exit_code': raw['exit_code'],
            'first_tenth': tenths['first'], 'last_tenth': tenths['last'],
            'by_minute': minute_series(records, proc[:, [0, 2]], start_ns, end_ns,
                                       raw.get('reference')),
            'rss_slope_by_kind_mib_per_h': kind_slopes(raw.get('rss_kinds', []), start_ns,
                                                       warmup_s),
            # the RSS curve itself, every 1 s sample, to tell a step from a slope
            'rss_series_s_mib': [[round(float(a), 1), round(float(b), 2)]
                                 for a, b in zip(t[during], rss)]}


def kind_slopes(kinds: Sequence[tuple[int, dict]], start_ns: int,
                warmup_s: float) -> dict[str, float]:
    """Return the RSS slope [MiB/h] of each kind after the warm-up (empty: too few samples)."""
    t = np.array([(wall - start_ns) * 1e-9 for wall, _ in kinds])
    if (t >= warmup_s).sum() < 2:
        return {}
    return {kind: rss_slope(t, [sample[kind] for _, sample in kinds], warmup_s)
            for kind in RSS_KINDS}


_RETAINED_SCRIPT = """
import json, sys
from reduced_dynamics.soak import retained_per_sample
print(json.dumps(retained_per_sample(int(sys.argv[1]), int(sys.argv[2]))))
"""


def soak_messages(robot: Any, count: int) -> list:
    """
    Return ``count`` joint states at 1 kHz and odometry at 200 Hz 0.3 ms after (arrival order).

    The motion is :class:`~reduced_dynamics.consistent_motion.ConsistentMotion`: no
    external wrench, so no event opens and predictions run at their rate, as the
    node's defaults have them.
    """
    from reduced_dynamics.bench import ODOMETRY_EVERY, ODOMETRY_OFFSET_NS
    from reduced_dynamics.consistent_motion import ConsistentMotion
    from reduced_dynamics.messages.samples import BaseStateSample, JointStateSample
    motion = ConsistentMotion(robot)
    efforts = np.zeros(robot.m)
    messages = []
    for index in range(count):
        stamp = NS + index * 1_000_000
        qbar, qbar_dot = motion.shape(motion.t)
        messages.append((stamp, 0, JointStateSample(stamp, '', robot.shape_joint_names, qbar,
                                                    qbar_dot, efforts)))
        if index % ODOMETRY_EVERY == 0:
            twist = motion.twist6()
            messages.append((stamp + ODOMETRY_OFFSET_NS, 1, BaseStateSample(
                stamp + ODOMETRY_OFFSET_NS, 'world', robot.base_link,
                motion.pose.translation.copy(), motion.orientation_xyzw(), twist[:3].copy(),
                twist[3:].copy())))
        motion.advance(1e-3)
    return messages


#: Joint states between two checkpoints of the retained-memory series: one period of the
#: default 1 Hz predictions at 1 kHz, so every checkpoint sees the same phase of the
#: prediction cycle (the same number of open predictions and live results).
RETAINED_EVERY = 1000


def growth_figures(samples: Sequence[int], traced: Sequence[int]) -> dict:
    """
    Retained bytes per sample from checkpoints (samples processed, traced bytes) of a window.

    ``bytes_per_sample`` is the Theil-Sen slope (median of the pairwise slopes) over
    the window's second half: a store growing per sample moves every pairwise slope,
    a one-off step (a ring reallocated once, a bounded store's last fill) moves less
    than half of them, so the figure measures growth, not a step. The naive
    end-minus-start figures of the whole window and of its second half are reported
    beside it (they include any step: divided by the window, they fall as 1/length).
    """
    from scipy.stats import theilslopes
    n = np.asarray(samples, float)
    memory = np.asarray(traced, float)
    if len(n) < 5 or np.any(np.diff(n) <= 0):
        raise ValueError('need >= 5 checkpoints at increasing sample counts')
    half = len(n) // 2
    late_n, late_memory = n[half:], memory[half:]
    return {'bytes_per_sample': float(theilslopes(late_memory, late_n)[0]),
            'window_bytes_per_sample': float((memory[-1] - memory[0]) / (n[-1] - n[0])),
            'second_half_bytes_per_sample': float((late_memory[-1] - late_memory[0])
                                                  / (late_n[-1] - late_n[0])),
            'checkpoints': len(n), 'fitted_checkpoints': len(late_n)}


def retained_per_sample(warmup: int, samples: int, every: int = RETAINED_EVERY) -> dict:
    """
    Bytes tracemalloc finds retained per processed sample after ``warmup`` samples.

    The estimator has the node's defaults (odometry input, deferred predictions,
    each job run as the node's worker would); the messages are built before
    tracing starts. Traced memory is read (after a full collection) every
    ``every`` joint states of the window; :func:`growth_figures` turns the
    series into the figure.
    """
    import gc
    import tracemalloc
    from reduced_dynamics.estimator import Estimator, EstimatorConfig
    from reduced_dynamics.robot.model import load_robot
    robot = load_robot()
    messages = soak_messages(robot, warmup + samples)
    estimator = Estimator(robot, EstimatorConfig(), use_odometry=True, defer_predictions=True)

    def feed(part: list) -> None:
        for _, kind, sample in part:
            for output in (estimator.add_base_state if kind
                           else estimator.add_joint_state)(sample):
                if output.prediction_job is not None:
                    output.prediction_job.run()
    origin = messages[0][0]
    ends = list(range(warmup, warmup + samples + 1, every))
    cuts = [next((i for i, m in enumerate(messages) if m[0] >= origin + n * 1_000_000),
                 len(messages)) for n in ends]
    # Traced from the start: a ring reallocated after the warm-up frees memory allocated
    # before it, which a trace started later would not see (and count the new as retained).
    tracemalloc.start()
    counts, traced = [], []
    done = 0
    for cut in cuts:
        feed(messages[done:cut])
        done = cut
        gc.collect()
        traced.append(tracemalloc.get_traced_memory()[0])
        counts.append(estimator.processed)
    tracemalloc.stop()
    return {'warmup': warmup, 'samples': counts[-1] - counts[0], 'every': every,
            'retained_bytes': traced[-1] - traced[0],
            **growth_figures(counts, traced),
            'series': [[int(c), int(t)] for c, t in zip(counts, traced)]}


_REPLAY_SCRIPT = """
import sys, time
from reduced_dynamics.peak_memory import peak_resident_kib
from reduced_dynamics.robot.model import load_robot
from reduced_dynamics.params import defaults
from reduced_dynamics.replay import replay, ReplayOptions
robot = load_robot()
before = peak_resident_kib()
start = time.perf_counter()
summary = replay(sys.argv[1], sys.argv[2], robot,
                 ReplayOptions(params=defaults(), overwrite=True, smooth=False))
elapsed = time.perf_counter() - start
after = peak_resident_kib()
print(before, after, summary['processed'], summary['predictions'], elapsed)
"""


def replay_peak(bag: str, out: str) -> dict:
    """``replay --no-smooth`` with the default parameters in a fresh interpreter: peak RSS."""
    env = _package_env()
    result = subprocess.run([sys.executable, '-c', _REPLAY_SCRIPT, bag, out], env=env,
                            capture_output=True, text=True, check=True)
    before, after, processed, predictions, elapsed = result.stdout.split()[-5:]
    return {'rss_before_mib': int(before) / 1024.0, 'peak_rss_mib': int(after) / 1024.0,
            'processed': int(processed), 'predictions': int(predictions),
            'seconds': float(elapsed)}


def retained_in_subprocess(warmup: int, samples: int) -> dict:
    """:func:`retained_per_sample` in a fresh interpreter (no other section's garbage)."""
    result = subprocess.run([sys.executable, '-c', _RETAINED_SCRIPT, str(warmup), str(samples)],
                            env=_package_env(), capture_output=True, text=True, check=True)
    return json.loads(result.stdout.splitlines()[-1])


def _package_env() -> dict:
    env = dict(os.environ)
    package_root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env['PYTHONPATH'] = package_root + os.pathsep + env.get('PYTHONPATH', '')
    return env


def bench_soak(report: Any, robot: Any, settings: Any, workdir: str) -> None:
    """
    Section soak: the node over real DDS for ``soak_seconds``, retained bytes, replay RSS.

    ``settings``: :class:`reduced_dynamics.bench.Settings` (``soak_seconds``,
    ``soak_retained_samples``, ``soak_bag_seconds``, ``soak_short_bag_seconds``).
    The node part is skipped when rclpy is not importable.
    """
    import importlib.util
    import shutil
    from reduced_dynamics.bench import make_figure, node_domain_id, simulate_input_bag, \
        tile_bag
    from reduced_dynamics.simulator import TOPIC_JOINT_STATES, TOPIC_ODOM
    details: dict = {}
    report.details['soak'] = details
    if importlib.util.find_spec('rclpy') is None:
        details['node'] = 'skipped: rclpy is not importable (pip install .[ros])'
    else:
        env = dict(os.environ, ROS_DOMAIN_ID=str(node_domain_id()),
                   ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST', PYTHONUNBUFFERED='1')
        seconds = settings.soak_seconds
        warmup = soak_warmup(seconds)
        node = node_soak_figures(run_node_soak(workdir, seconds, env,
                                               reference=crba_reference(robot)), warmup)
        details['node'] = node
        window = f'{node["seconds"]:.0f} s at 1 kHz + 200 Hz, defaults; after {warmup:g} s'
        trend = node['rss_trend_mib_per_h']
        report.add(make_figure(
            'soak', 'node RSS slope after warm-up', 'MiB/h', [trend['theil_sen']],
            target=f'<= {SLOPE_TARGET_MIB_H:g} MiB/h',
            check=lambda v: v <= SLOPE_TARGET_MIB_H,
            note=f'{window}; RSS {node["rss_at_warmup_mib"]:.1f} -> {node["rss_end_mib"]:.1f}'
                 ' MiB; Theil-Sen over 1 s samples of /proc, standard error '
                 f'{trend["theil_sen_se"]:.2f}, 95 % interval [{trend["theil_sen_low"]:.2f}, '
                 f'{trend["theil_sen_high"]:.2f}] (block bootstrap, {trend["block_s"]:.3g} s '
                 f'blocks); least squares '
                 f'{trend["least_squares"]:.2f} +- {trend["least_squares_se"]:.2f} (block '
                 f'means; over 1 s samples {node["rss_slope_mib_per_h"]:.2f}); ceiling (block '
                 f'maxima) {trend["ceiling"]:.2f}; by kind (least squares): '
                 + ', '.join(f'{kind} {slope:.1f}' for kind, slope in
                             node['rss_slope_by_kind_mib_per_h'].items())))
        first, last = node['first_tenth'], node['last_tenth']
        loads = (f'; load average {first.get("load", float("nan")):.1f} and '
                 f'{last.get("load", float("nan")):.1f}, crba '
                 f'{first.get("crba_us", float("nan")):.2f} and '
                 f'{last.get("crba_us", float("nan")):.2f} us in the first and last')
        for key, name, unit in (('cpu_us_per_sample', 'node CPU per sample', 'us'),
                                ('cpu_crba_per_sample', 'node CPU per sample', 'crba'),
                                ('p99_ms', 'node latency p99', 'ms')):
            if key not in last or key not in first:
                continue
            report.add(make_figure(
                'soak', f'{name}, last tenth', unit, [last[key]], 'same, first tenth',
                [first[key]], [last[key] / first[key]], f'ratio <= {TENTH_TARGET:g}',
                lambda r: r <= TENTH_TARGET, f'tenths of the window after {warmup:g} s'
                + loads))
        report.add(make_figure(
            'soak', 'node outputs per input', '1', [node['outputs_per_input']],
            target='1', check=lambda v: v >= 0.999,
            note=f'{node["outputs"]} ~/momentum for {node["joint_states_sent"]} joint states'))
        report.add(make_figure(
            'soak', 'node log lines per hour', 'lines/h', [node['log_lines_per_hour']],
            note=f'{node["log_lines"]} lines in {node["seconds"]:.0f} s; exit code '
                 f'{node["exit_code"]}'))
    retained = retained_in_subprocess(settings.soak_retained_warmup,
                                      settings.soak_retained_samples)
    details['retained'] = retained
    report.add(make_figure(
        'soak', 'retained bytes per sample (tracemalloc)', 'B', [retained['bytes_per_sample']],
        target=f'<= {RETAINED_TARGET_B:g} B', check=lambda v: v <= RETAINED_TARGET_B,
        note=f'Estimator with the node defaults, {retained["samples"]} samples after '
             f'{retained["warmup"]}: Theil-Sen slope of traced memory over the second half '
             f'(checkpoints every {retained["every"]}); end minus start over the window '
             f'{retained["window_bytes_per_sample"]:.2f}, over the second half '
             f'{retained["second_half_bytes_per_sample"]:.2f} B/sample'))
    topics = (TOPIC_JOINT_STATES, TOPIC_ODOM)
    source, out = os.path.join(workdir, 'source'), os.path.join(workdir, 'out')
    # 5 s tiled: the simulated arm reaches its joint limits later (rejected samples).
    simulate_input_bag(robot, source, min(5.0, settings.soak_short_bag_seconds))
    peaks = {}
    for name, length in (('short', settings.soak_short_bag_seconds),
                         ('long', settings.soak_bag_seconds)):
        bag = os.path.join(workdir, name)
        tile_bag(source, bag, length, topics)
        peaks[name] = replay_peak(bag, out)
        shutil.rmtree(bag, ignore_errors=True)
        shutil.rmtree(out, ignore_errors=True)
    shutil.rmtree(source, ignore_errors=True)
    details['replay'] = peaks
    short, long = peaks['short']['peak_rss_mib'], peaks['long']['peak_rss_mib']
    report.add(make_figure(
        'soak', 'replay --no-smooth peak RSS, long bag', 'MiB', [long], 'same, short bag',
        [short], [long / short], f'ratio <= {REPLAY_RATIO_TARGET:g}',
        lambda r: r <= REPLAY_RATIO_TARGET,
        f'{settings.soak_bag_seconds:g} s vs {settings.soak_short_bag_seconds:g} s at 1 kHz '
        f'(tiled simulated bag), default parameters (predictions on); '
        f'{peaks["long"]["processed"]} samples, {peaks["long"]["predictions"]} predictions'))
