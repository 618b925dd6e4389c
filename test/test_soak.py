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


"""The soak section's figures: RSS slope, first and last tenth; one short run over real DDS."""

import importlib.util
import json
import os

import numpy as np
import pytest

from reduced_dynamics.bench import register_command, Settings
from reduced_dynamics.soak import (classify_smaps, crba_reference, growth_figures,
                                   kind_slopes, MIB, minute_series, node_soak_figures,
                                   proc_sample, retained_per_sample, rss_by_kind, RSS_KINDS,
                                   rss_slope, rss_trend, run_node_soak, soak_warmup,
                                   tenth_figures)

NS = 1_000_000_000


def test_rss_slope_fits_after_the_warm_up_only():
    t = np.arange(0.0, 600.0, 1.0)
    # 20 MiB of start-up growth in the first minute, then 0.5 MiB per hour and noise.
    rss = 150 * MIB + np.minimum(t, 60.0) / 60.0 * 20 * MIB + t / 3600.0 * 0.5 * MIB
    rss += np.random.default_rng(0).normal(0.0, 0.01 * MIB, t.size)
    assert rss_slope(t, rss, 60.0) == pytest.approx(0.5, abs=0.1)
    assert rss_slope(t, rss, 0.0) > 10.0
    with pytest.raises(ValueError, match='fewer than two'):
        rss_slope(t, rss, 1e6)


def _swinging_hour(growth_mib_h: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """One hour of 1 s RSS samples: a ceiling, 5 MiB blocks returned for 10-40 s at a time."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, 3600.0, 1.0)
    rss = 410.0 + growth_mib_h * t / 3600.0 + rng.normal(0.0, 0.05, t.size)
    at = 900.0
    while at < 3600.0:
        length = rng.uniform(10.0, 40.0)
        rss[(t >= at) & (t < at + length)] -= 5.0 * rng.integers(1, 3)
        at += length + rng.uniform(20.0, 90.0)
    return t, rss * MIB


def test_rss_trend_reads_a_swinging_flat_hour_as_flat_and_growth_at_its_rate():
    # Stop 22's hour: flat but swinging; its least-squares slope read 1.03 MiB/h.
    # Over many such hours the robust slopes stay near 0 where least squares
    # wanders by its standard error; a true 3 MiB/h shows as 3 in all of them.
    flat = [rss_trend(*_swinging_hour(0.0, seed), 900.0, draws=40) for seed in range(8)]
    least = np.array([trend['least_squares'] for trend in flat])
    robust = np.array([trend['theil_sen'] for trend in flat])
    ceiling = np.array([trend['ceiling'] for trend in flat])
    assert np.abs(least).max() > 2 * np.abs(robust).max()
    assert np.abs(robust).max() < 0.3 and np.abs(ceiling).max() < 0.3
    assert all(trend['blocks'] == 45 and trend['block_s'] == 60.0 for trend in flat)
    # each standard error is the spread its slope shows over the hours
    for key, slopes in (('least_squares', least), ('theil_sen', robust)):
        assert np.median([trend[f'{key}_se'] for trend in flat]) == pytest.approx(
            slopes.std(), rel=0.6)
    assert sum(trend['theil_sen_low'] <= 0.0 <= trend['theil_sen_high'] for trend in flat) >= 7
    for seed in range(3):
        growing = rss_trend(*_swinging_hour(3.0, seed), 900.0, draws=40)
        assert growing['theil_sen'] == pytest.approx(3.0, abs=0.3)
        assert growing['ceiling'] == pytest.approx(3.0, abs=0.3)
        assert growing['theil_sen_low'] < 3.0 < growing['theil_sen_high']
        assert growing['theil_sen_high'] - growing['theil_sen_low'] < 1.0
    again = rss_trend(*_swinging_hour(3.0, 0), 900.0, draws=40)
    assert again == rss_trend(*_swinging_hour(3.0, 0), 900.0, draws=40)  # seeded
    with pytest.raises(ValueError, match='fewer than three'):
        rss_trend(np.arange(0.0, 100.0), np.ones(100), 50.0, block_s=30.0)


def test_the_warm_up_covers_the_stores_filling_in_a_long_soak():
    # The one-hour soak's RSS (65325c5): steps while the stores fill (the last at
    # 710 s, within the 600 s calibration memory plus its updates), flat after.
    t = np.arange(0.0, 3600.0, 10.0)
    steps = [(10.0, 37.0), (20.0, 2.0), (90.0, 2.25), (140.0, 2.25), (320.0, 0.16),
             (340.0, 0.16), (710.0, 3.95)]
    rss = (784.45 + sum(size * (t >= at) for at, size in steps)) * MIB
    assert rss_slope(t, rss, 60.0) > 1.0  # the old 60 s warm-up: the filling as a slope
    assert soak_warmup(3600.0) == 900.0
    assert rss_slope(t, rss, soak_warmup(3600.0)) == pytest.approx(0.0, abs=1e-9)
    # Short runs keep three quarters of their window; never under 60 s when it allows.
    assert soak_warmup(600.0) == 150.0 and soak_warmup(240.0) == 60.0
    assert soak_warmup(30.0) == 7.5


def test_tenths_compare_cpu_and_latency_at_both_ends():
    start, end = 10 * NS, 110 * NS
    stamps = np.arange(start, end, 1_000_000, dtype=np.int64)
    # Latency 1 ms, 3 ms in the last tenth; CPU 100 us a sample, 150 us in the last tenth.
    latency = np.where(stamps >= start + 90 * NS, 3_000_000, 1_000_000)
    records = np.column_stack([stamps, stamps + latency])
    wall = np.arange(0, 121 * NS, NS, dtype=float)
    rate = np.where(wall >= start + 90 * NS, 0.15, 0.1)  # CPU seconds per second
    cpu = np.column_stack([wall, np.concatenate([[0.0], np.cumsum(rate[:-1])])])
    figures = tenth_figures(records, cpu, start, end)
    assert figures['first']['outputs'] == figures['last']['outputs'] == 10_000
    assert figures['first']['cpu_us_per_sample'] == pytest.approx(100.0)
    assert figures['last']['cpu_us_per_sample'] == pytest.approx(150.0)
    assert figures['first']['p99_ms'] == pytest.approx(1.0)
    assert figures['last']['p99_ms'] == pytest.approx(3.0)


def test_cpu_per_sample_is_also_compared_in_crba_timed_beside_it():
    # The machine's load doubles in the last tenth: CPU per sample 100 -> 150 us and
    # crba 2 -> 3 us at the same time; in crba the node costs the same (50 crba).
    start, end = 10 * NS, 110 * NS
    stamps = np.arange(start, end, 1_000_000, dtype=np.int64)
    records = np.column_stack([stamps, stamps + 1_000_000])
    wall = np.arange(0, 121 * NS, NS, dtype=float)
    late = wall >= start + 90 * NS
    rate = np.where(late, 0.15, 0.1)
    cpu = np.column_stack([wall, np.concatenate([[0.0], np.cumsum(rate[:-1])])])
    reference = np.column_stack([wall, np.where(late, 3e-6, 2e-6), np.where(late, 4.0, 2.0)])
    figures = tenth_figures(records, cpu, start, end, reference)
    first, last = figures['first'], figures['last']
    assert (first['crba_us'], last['crba_us']) == pytest.approx((2.0, 3.0))
    assert (first['load'], last['load']) == (2.0, 4.0)
    assert first['cpu_crba_per_sample'] == pytest.approx(50.0)
    assert last['cpu_crba_per_sample'] == pytest.approx(50.0)
    assert 'crba_us' not in tenth_figures(records, cpu, start, end)['first']
    rows = minute_series(records, cpu, start, end + 1, reference, block_s=10.0)
    # ten rows, not an eleventh for the 1 ns sliver at the end
    assert len(rows) == 10 and [row[0] for row in rows] == pytest.approx(np.arange(0, 100, 10))
    assert rows[0][1:] == pytest.approx([100.0, 1.0, 2.0, 2.0])
    assert rows[-1][1:] == pytest.approx([150.0, 1.0, 3.0, 4.0])


def test_crba_reference_times_one_call_in_cpu_seconds():
    from reduced_dynamics.robot.model import load_robot
    cost = crba_reference(load_robot(), calls=50)
    # no wall-clock figure asserted: a positive CPU time under a millisecond a call
    assert all(0.0 < cost() < 1e-3 for _ in range(3))


def test_node_soak_figures_from_raw_measurements():
    start, end = 0, 100 * NS
    stamps = np.arange(start, end, 1_000_000, dtype=np.int64)
    records = np.column_stack([stamps[:-10], stamps[:-10] + 500_000])
    wall = np.arange(0, 102 * NS, NS, dtype=float)
    proc = np.column_stack([wall, 100 * MIB + wall * 1e-9 * 1e3, wall * 1e-9 * 0.2])
    raw = {'sent': {'start_ns': start, 'end_ns': end, 'joint_states': len(stamps),
                    'odometry': len(stamps) // 5, 'late_max_s': 0.001},
           'records': records, 'proc': proc, 'log_lines': ['a'] * 5, 'exit_code': 0}
    figures = node_soak_figures(raw, 20.0)
    assert figures['outputs_per_input'] == pytest.approx(1.0 - 10 / len(stamps))
    assert figures['log_lines_per_hour'] == pytest.approx(5 * 36.0)
    assert figures['rss_slope_mib_per_h'] == pytest.approx(1e3 * 3600 / MIB)
    trend = figures['rss_trend_mib_per_h']
    assert trend['theil_sen'] == trend['ceiling'] == pytest.approx(1e3 * 3600 / MIB)
    assert trend['least_squares_se'] == pytest.approx(0.0, abs=1e-9)
    assert trend['block_s'] == pytest.approx(8.1)  # samples to 101 s
    assert len(figures['by_minute']) == 2 and figures['by_minute'][0][1] == pytest.approx(200.0)
    assert figures['first_tenth']['cpu_us_per_sample'] == pytest.approx(200.0)
    assert json.dumps(figures)


def test_proc_sample_reads_this_process():
    resident, cpu = proc_sample(os.getpid())
    assert 10 * MIB < resident < 1 << 40 and cpu > 0.0


def test_soak_section_only_on_request_and_its_options():
    import argparse
    parser = argparse.ArgumentParser()
    register_command(parser.add_subparsers())
    args = parser.parse_args(['bench', '--sections', 'soak', '--soak-duration', '600'])
    assert args.sections == ['soak'] and args.soak_duration == 600.0
    assert Settings().soak_seconds == 60.0 and Settings.quick_settings().soak_seconds < 60.0


@pytest.mark.skipif(importlib.util.find_spec('rclpy') is None,
                    reason='rclpy not importable (CI installs it: pip install .[ros])')
def test_node_soak_over_real_dds(tmp_path):
    # node_bench's soak-probe and soak-publish around the real node for 2 s: the probe
    # comes up (its ready file), the publisher sends on schedule, outputs come back
    # stamped with sent joint states (no figure asserted: machines are noisy).
    from reduced_dynamics.bench import node_domain_id
    from reduced_dynamics.soak import _package_env
    env = dict(_package_env(), ROS_DOMAIN_ID=str(node_domain_id()),
               ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST', PYTHONUNBUFFERED='1')
    calls = []
    raw = run_node_soak(str(tmp_path), 2.0, env, reference=lambda: calls.append(1) or 2e-6)
    sent, records = raw['sent'], raw['records']
    # the reference is timed with the first /proc sample and then every SMAPS_EVERY-th
    assert raw['reference'].shape == (len(calls), 3) and len(calls) >= 1
    assert np.all(raw['reference'][:, 1] == 2e-6) and np.all(raw['reference'][:, 2] >= 0)
    assert sent['joint_states'] == 2000 and sent['odometry'] == 401, sent
    assert sent['start_ns'] < sent['end_ns']
    assert records.dtype == np.int64 and records.shape[1] == 2 and len(records) > 0
    # Stamps are send times inside the window; each output is received after its input.
    assert np.all((records[:, 0] >= sent['start_ns']) & (records[:, 0] <= sent['end_ns']))
    assert np.all(records[:, 1] >= records[:, 0])
    assert len(raw['proc']) >= 2 and raw['exit_code'] == 0


SMAPS = """\
55d0c0a00000-55d0c5a00000 rw-p 00000000 00:00 0                          [heap]
Size:              81920 kB
Rss:               40000 kB
7f026c000000-7f026c480000 rw-p 00000000 00:00 0
Size:               4608 kB
Rss:                4608 kB
7f026c480000-7f0270000000 ---p 00000000 00:00 0
Size:              60928 kB
Rss:                   0 kB
7f02a5f00000-7f02a6000000 rw-p 00000000 00:00 0
Rss:                1024 kB
7f02b0000000-7f02b0001000 rw-s 00000000 00:1a 12   /dev/shm/fastrtps_abc
Rss:                   4 kB
7f02c0000000-7f02c0100000 r-xp 00000000 08:01 99   /usr/lib/libfoo.so
Rss:                 512 kB
"""


def test_resident_memory_is_told_apart_by_kind():
    # A thread's malloc arena starts on a 64 MiB boundary; Python's arenas do not.
    kinds = classify_smaps(SMAPS)
    assert kinds == {'heap': 40000 * 1024, 'thread_arenas': 4608 * 1024, 'anon': 1024 * 1024,
                     'shm': 4 * 1024, 'files': 512 * 1024}
    assert sum(rss_by_kind(os.getpid()).values()) > 10 * MIB


def test_the_growing_kind_has_the_slope():
    # 1 MiB per 100 s in the thread arenas only, from the warm-up on.
    kinds = [(k * 10 * NS, {'heap': 5 * MIB, 'thread_arenas': k * MIB // 10, 'anon': MIB,
                            'shm': 0, 'files': 0}) for k in range(20)]
    slopes = kind_slopes(kinds, 0, 50.0)
    assert slopes['thread_arenas'] == pytest.approx(36.0)
    assert slopes['heap'] == pytest.approx(0.0) and set(slopes) == set(RSS_KINDS)
    assert kind_slopes(kinds[:3], 0, 50.0) == {}


def test_retained_growth_is_a_slope_not_a_step():
    # Checkpoints every 1000 samples over a 40 000-sample window.
    samples = np.arange(80_000, 120_001, 1000)
    # A bounded store: flat, but a ring reallocated once (+600 kB) late in the window.
    step = np.where(samples >= 108_000, 600_000, 0) + 50_000_000
    figures = growth_figures(samples, step)
    assert figures['bytes_per_sample'] == 0.0
    assert figures['window_bytes_per_sample'] == pytest.approx(15.0)  # what it used to say
    assert figures['second_half_bytes_per_sample'] == pytest.approx(30.0)
    assert figures['checkpoints'] == 41 and figures['fitted_checkpoints'] == 21
    # A store growing 3 B per sample is measured as such, with or without the step.
    growing = 50_000_000 + 3 * (samples - samples[0])
    assert growth_figures(samples, growing)['bytes_per_sample'] == pytest.approx(3.0)
    assert growth_figures(samples, growing + step - step[0])['bytes_per_sample'] \
        == pytest.approx(3.0)
    # A store growing in steps of 16 kB every 4000 samples (4 B per sample) is growth too
    # (steps at most a fifth of the fitted half apart; one step per half is a step).
    stairs = 50_000_000 + 16_000 * ((samples - samples[0]) // 4000)
    assert growth_figures(samples, stairs)['bytes_per_sample'] == pytest.approx(4.0, rel=0.3)
    with pytest.raises(ValueError, match='checkpoints'):
        growth_figures(samples[:4], step[:4])


def test_retained_per_sample_reads_checkpoints_every_prediction_period():
    # A short window: the structure of the measurement, not its figure.
    retained = retained_per_sample(1000, 4000, every=1000)
    counts = [count for count, _ in retained['series']]
    assert len(counts) == 5 and retained['checkpoints'] == 5
    assert np.all(np.diff(counts) > 900) and retained['samples'] == counts[-1] - counts[0]
    assert np.isfinite(retained['bytes_per_sample'])
    assert json.dumps(retained)
