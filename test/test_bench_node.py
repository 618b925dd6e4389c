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

"""The node section of ``bench``: window statistics, and one tiny run over real DDS."""

import importlib.util
import math

import pytest

from reduced_dynamics import bench


def test_phase_figures_count_drops_and_latency():
    ms = 1_000_000
    sent = [10 * ms * k for k in range(1, 101)]  # 100 joint states, 100 Hz
    # Every fourth one lost; the others come back 1 ms (and one 50 ms) later.
    received = [(s, s + ms) for k, s in enumerate(sent) if k % 4]
    received[0] = (received[0][0], received[0][0] + 50 * ms)
    received.append((123, 456))  # an output of another window: ignored
    row = bench.node_phase_figures(sent, received)
    assert row['sent'] == 100 and row['delivered'] == 75 and row['drops'] == 25
    assert math.isclose(row['input_rate'], 100.0)
    assert math.isclose(row['delivered_rate'], 75.0)
    assert math.isclose(row['p50_ms'], 1.0)
    assert 1.0 < row['p99_ms'] <= 50.0
    empty = bench.node_phase_figures(sent, [])
    assert empty['drops'] == 100 and math.isnan(empty['p50_ms'])
    assert 'wait_p99_ms' not in row


def test_phase_figures_split_the_wait_for_the_bracketing_base_sample():
    # Joint states at 1 kHz, base samples at 200 Hz sent just after every fifth joint
    # state (the bench publisher's order): a joint state waits 0-4 ms for the base sample
    # its row interpolates to. The node answers 0.5 ms after that sample.
    ms = 1_000_000
    sent = [ms * k for k in range(1, 1001)]
    bases = [ms * k + 1000 for k in range(0, 1006, 5)]
    ready = {s: next(b for b in bases if b >= s) for s in sent}
    received = [(s, ready[s] + ms // 2) for s in sent]
    row = bench.node_phase_figures(sent, received, bases)
    assert math.isclose(row['wait_p99_ms'], 4.001) and math.isclose(row['wait_p50_ms'], 2.001)
    assert math.isclose(row['ready_p99_ms'], 0.5) and math.isclose(row['ready_p50_ms'], 0.5)
    assert row['p99_ms'] > 4.0  # the raw latency carries the wait


def test_domain_id_is_its_own(monkeypatch):
    monkeypatch.delenv('RD_BENCH_DOMAIN_ID', raising=False)
    assert 60 <= bench.node_domain_id() < 100
    monkeypatch.setenv('RD_BENCH_DOMAIN_ID', '77')
    assert bench.node_domain_id() == 77


@pytest.mark.skipif(importlib.util.find_spec('rclpy') is None,
                    reason='rclpy not importable (CI installs it: pip install .[ros])')
def test_node_section_over_real_dds(tmp_path):
    # One configuration, one short window each for the relay and the node: the structure
    # and that messages flowed through both (no figure is asserted: machines are noisy).
    settings = bench.Settings(repeats=1, node_seconds=0.5, node_warmup=1.0,
                              node_sweep_seconds=0.5, node_callback_seconds=0.5, quick=True)
    report = bench.Report(bench.machine_info(), {})
    bench.bench_node(report, settings, str(tmp_path),
                     rates=(('joints 200 Hz + odom 100 Hz', 200.0, 100.0),), sweep=(50.0,))
    names = [f.name for f in report.figures]
    assert names == ['joints 200 Hz + odom 100 Hz: ' + n for n in
                     ('joint states delivered/s', 'drops', 'latency p50', 'latency p99',
                      'wait for the bracketing base sample, p99',
                      'latency p99 after the bracketing base sample')] + \
        ['in-process, joints 1 kHz + odom 200 Hz: odometry callback p50',
         'in-process, joints 1 kHz + odom 200 Hz: odometry callback p99',
         'sustained joint-state rate without drops (odom 200 Hz)']
    # The in-process callbacks: every odometry sample of the 0.5 s window (200 Hz) timed,
    # at the default smoothing_lag and without it.
    callbacks = report.details['node']['callbacks_ms']
    assert set(callbacks) == {'0.5', '0.0'}
    for runs in callbacks.values():
        (times,) = runs
        assert 95 <= len(times) <= 101 and all(t > 0.0 for t in times)
    sweep = report.details['node']['sweep_drops']
    assert set(sweep) == {'relay', 'node'} and all(list(d) == ['50.0'] for d in sweep.values())
    assert report.figures[-1].median in (0.0, 50.0)
    rows = report.details['node']['configurations']['joints 200 Hz + odom 100 Hz']
    for target in ('relay', 'node'):
        (row,) = rows[target]
        assert row['sent'] >= 90, row
        assert row['delivered'] > 0, (target, row)
        assert 0.0 < row['p50_ms'] <= row['p99_ms'], row
        # The publisher's base samples bracket its joint states (10 ms apart at 100 Hz,
        # more when the loaded machine delays the publisher's sleeps).
        assert row['wait_p99_ms'] >= 0.0 and row['ready_p99_ms'] <= row['p99_ms']
    assert all(f.section == 'node' for f in report.figures)


def test_node_rows_carry_the_issue_19_targets(monkeypatch):
    # Synthetic windows (no DDS): the node answers 3 ms late, the relay 0.5 ms; the node
    # drops nothing up to 2 kHz and one joint state at 5 kHz. The 1 kHz + 200 Hz p99 row
    # is held to 2 ms and the sweep, which now reaches 5 kHz, to 5 kHz.
    from reduced_dynamics.node_bench import NODE_OUTPUT, RELAY_OUTPUT

    def phases(workdir, joint_rates, base_rate, seconds, warmup, repeats, env):
        out, records = [], {NODE_OUTPUT: [], RELAY_OUTPUT: []}
        for rate in joint_rates:
            for target, output, delay in (('relay', RELAY_OUTPUT, 500_000),
                                          ('node', NODE_OUTPUT, 3_000_000)):
                stamps = [int(k * 1e9 / rate) + len(out) * 10 ** 10 for k in range(50)]
                lost = 1 if target == 'node' and rate >= 5000.0 else 0
                records[output] += [(s, s + delay) for s in stamps[lost:]]
                # A base sample 0.5 ms after every joint state: 0.5 ms of wait.
                out.append({'target': target, 'joint_stamps': stamps, 'joint_rate': rate,
                            'base_stamps': [s + 500_000 for s in stamps]})
        return out, records
    monkeypatch.setattr(bench, 'run_node_phases', phases)
    # The in-process callbacks: 4 ms once in 50 at the default lag, 2 ms otherwise.
    monkeypatch.setattr(bench, 'node_callback_times', lambda env, seconds, lag: (
        [0.002] * 49 + [0.004]) * 4 if lag else [0.002] * 200)
    report = bench.Report(bench.machine_info(), {})
    bench.bench_node(report, bench.Settings(repeats=1, quick=True), '/nonexistent')
    figures = {f.name: f for f in report.figures}
    p99 = figures['joints 1 kHz + odom 200 Hz: latency p99']
    assert p99.target == '<= 2 ms' and p99.met is False and abs(p99.median - 3.0) < 1e-9
    assert figures['joints 1 kHz + odom 1 kHz: latency p99'].target == ''
    after = figures['joints 1 kHz + odom 200 Hz: latency p99 after the bracketing base sample']
    assert after.target == '<= 2 ms' and after.met is False
    assert math.isclose(after.median, 2.5)  # 3 ms after the joint state, 2.5 after its base
    assert math.isclose(figures['joints 1 kHz + odom 200 Hz: wait for the bracketing base '
                                'sample, p99'].median, 0.5)
    callback = figures['in-process, joints 1 kHz + odom 200 Hz: odometry callback p99']
    assert math.isclose(callback.median, 4.0) and math.isclose(callback.ratio, 2.0)
    assert callback.target == '' and callback.baseline == 'the same, smoothing_lag 0'
    assert math.isclose(figures['in-process, joints 1 kHz + odom 200 Hz: odometry callback '
                                'p50'].median, 2.0)
    sustained = figures['sustained joint-state rate without drops (odom 200 Hz)']
    assert sustained.median == 2000.0 and sustained.baseline_median == 5000.0
    assert sustained.target == '>= 5000 Hz' and sustained.met is False
