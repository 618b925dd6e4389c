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
The case for the mechanics (docs/mechanics_case.md): this filter against a base-only one.

Each scenario is simulated with ``reduced-dynamics simulate`` and realistic sensors:
the arm moves, nothing pushes the robot until one reference push. ``reduced-dynamics
replay --no-smooth`` (what the node publishes) gives this package's estimate;
:mod:`base_only_kf` the estimate of a per-axis constant-force Kalman filter on the
base pose with the same sensor figures and the same wrench random walk. Run as a
script to print the table and draw the plot::

    PYTHONPATH=. python test/mechanics_case.py --plot docs/images/mechanics_case.png
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass, replace
import json
from pathlib import Path
import sys
import tempfile
from typing import Optional

import numpy as np
import yaml

from reduced_dynamics.bag.reader import open_bag
from reduced_dynamics.cli import main as cli_main
from reduced_dynamics.params import defaults
from reduced_dynamics.robot.model import load_robot

from base_only_kf import base_only_filter, BaseTrack, read_base_track

#: Random walks of the base-only filter tried against the arm's reaction (x the default).
DETUNING = (1.0, 0.3, 0.1, 0.03)
RATE_TOPIC = '/reduced_dynamics/drift/momentum_rate'
#: Seconds at the start left out of every figure: both filters start from a diffuse prior.
SETTLE = 1.0


@dataclass(frozen=True)
class Scenario:
    """One simulated arm-plus-base case and the sensor figures both filters are given."""

    name: str
    title: str
    simulate: tuple[str, ...]
    robot: tuple[str, ...]
    #: replay inputs beside --params
    replay: tuple[str, ...]
    #: the sensor figures of the simulation, as replay parameters
    params: dict
    base_topic: str
    #: (start, duration) of the reference push [s]
    push: tuple[float, float]
    #: base-only filter: pose and twist noise (6 each; twist None: pose only), axes
    pose_sigma: tuple[float, ...]
    twist_sigma: Optional[tuple[float, ...]]
    axes: tuple[int, ...]
    #: --torque-scale of the PD arm motion: the table's rows, and the one the plot shows
    scales: tuple[float, ...]
    shown: float


#: Sensor options shared with test/data/paper_realistic (scripts/make_test_bags.sh).
PAPER_SENSORS = ('--noise-position', '1e-4', '--noise-velocity', '0.005', '--noise-effort',
                 '0.05', '--noise-pose', '0.001', '--noise-orientation', '0.0005',
                 '--noise-twist', '0.002', '--quantize', 'joint_position=1e-5',
                 '--stamp-jitter', '0.0003', '--latency', '0.004', '--latency-jitter',
                 '0.001', '--drop-rate', '0.01')
#: Motion-capture poses with the noise measured on the freeflyer2 recordings (25 um, 0.2 mrad;
#: test/data/freeflyer_testbed), 120 Hz, stamps and drops as freeflyer_realistic.
MOCAP_SENSORS = ('--noise-position', '1e-4', '--noise-velocity', '0.005', '--noise-pose',
                 '2.5e-5', '--noise-orientation', '2e-4',
                 '--stamp-jitter', '0.0005', '--latency', '0.003', '--latency-jitter', '0.001',
                 '--drop-rate', '0.01')
FREEFLYER_ARM_URDF = str(Path(__file__).parent / 'data' / 'freeflyer_arm.urdf')

SCENARIOS = {
    'paper': Scenario(
        'paper', 'paper robot (SE(3) base, 6-joint arm), Odometry 100 Hz',
        ('--duration', '8', '--rate', '100', '--seed', '11', '--torque', 'pd',
         '--momentum-class', 'zero', '--thruster', '6,0.5,20,-10,5,2,-3,4', *PAPER_SENSORS),
        (), (),
        {'pose_position_noise': 1e-3, 'pose_angle_noise': 5e-4, 'pose_stamp_noise': 3e-4,
         'twist_linear_noise': 2e-3, 'twist_angular_noise': 2e-3,
         'joint_velocity_noise': 5e-3},
        '/odom', (6.0, 0.5), (1e-3,) * 3 + (5e-4,) * 3, (2e-3,) * 6, (0, 1, 2, 3, 4, 5),
        (1.0, 3.0, 6.0), 6.0),
    'freeflyer_arm': Scenario(
        'freeflyer_arm', 'planar free-flyer (16 kg, SE(2) base) with a 2-link arm, mocap 120 Hz',
        ('--duration', '8', '--rate', '120', '--seed', '12', '--torque', 'pd',
         '--momentum-class', 'zero', '--base-pose-only',
         '--thruster', '6,1,0.4,-0.3,0,0,0,0.02', *MOCAP_SENSORS),
        ('--urdf', FREEFLYER_ARM_URDF),
        ('--base-pose-topic', '/base_pose'),
        {'pose_position_noise': 2.5e-5, 'pose_angle_noise': 2e-4, 'pose_stamp_noise': 5e-4,
         'joint_velocity_noise': 5e-3},
        '/base_pose', (6.0, 1.0), (2.5e-5,) * 3 + (2e-4,) * 3, None, (0, 1, 5),
        (1.0, 3.0, 6.0, 12.0), 12.0),
}


@dataclass
class Filtered:
    """One filter's estimate on a scenario: stamps [s from the bag start], wrench, sigma."""

    seconds: np.ndarray
    wrench: np.ndarray
    #: (K, 6) standard deviations at each stamp (held from the last diagnostics for ours)
    sigma: np.ndarray


@dataclass
class CaseResult:
    """Both filters' estimates and the truth of one scenario."""

    scenario: Scenario
    scale: float
    #: largest measured joint speed while only the arm moves [rad/s]
    joint_speed: float
    ours: Filtered
    base_only: Filtered
    truth: Filtered
    world_impulse: np.ndarray
    #: events this filter flagged: start [s from the bag start]
    event_starts: list[float]
    #: what the base-only filter ran on: base track, 6x6 inertia, jerk densities, origin [ns]
    track: BaseTrack
    inertia: np.ndarray
    jerk: np.ndarray
    origin_ns: int
    #: replay arguments (bag, params and topics) for :func:`smoothed`
    replay_args: tuple[str, ...]


def run_base_only(scenario: Scenario, track: BaseTrack, inertia: np.ndarray,
                  jerk: np.ndarray, origin_ns: int, smooth: bool = False) -> Filtered:
    """Return the base-only filter's estimate with the scenario's sensor figures."""
    estimate = base_only_filter(track, inertia, np.array(scenario.pose_sigma),
                                None if scenario.twist_sigma is None
                                else np.array(scenario.twist_sigma), jerk,
                                list(scenario.axes), smooth)
    return Filtered((estimate.stamps_ns - origin_ns) * 1e-9, estimate.wrench, estimate.sigma)


def _wrenches(bag: str, topic: str, origin: int) -> tuple[np.ndarray, np.ndarray]:
    rows = []
    with open_bag(bag) as reader:
        for message in reader.messages([topic]):
            msg = message.msg
            stamp = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
            f, t = msg.wrench.force, msg.wrench.torque
            rows.append(((stamp - origin) * 1e-9, f.x, f.y, f.z, t.x, t.y, t.z))
    table = np.array(sorted(rows))
    return table[:, 0], table[:, 1:]


def _diagnostic_sigma(bag: str, origin: int, axes: tuple[int, ...]) -> tuple:
    """Return (seconds, (K, 6) sigma) of the external wrench from the replay's diagnostics."""
    stamps, rows = [], []
    with open_bag(bag) as reader:
        for message in reader.messages(['/diagnostics']):
            for status in message.msg.status:
                values = {kv.key: kv.value for kv in status.values}
                if 'external_wrench_sigma' in values:
                    sigma = np.zeros(6)
                    sigma[list(axes)] = [float(v) for v in values['external_wrench_sigma']
                                         .split()]
                    stamp = message.msg.header.stamp
                    stamps.append((stamp.sec * 10**9 + stamp.nanosec - origin) * 1e-9)
                    rows.append(sigma)
    return np.array(stamps), np.array(rows)


def _held(seconds: np.ndarray, source: np.ndarray, values: np.ndarray) -> np.ndarray:
    index = np.clip(np.searchsorted(source, seconds, side='right') - 1, 0, len(source) - 1)
    return values[index]


def _joint_speed(bag: str, origin: int, end: float) -> float:
    """Return the largest measured joint speed from SETTLE to ``end`` [s]."""
    speeds = [0.0]
    with open_bag(bag) as reader:
        for message in reader.messages(['/joint_states']):
            stamp = message.msg.header.stamp
            seconds = (stamp.sec * 10**9 + stamp.nanosec - origin) * 1e-9
            if SETTLE <= seconds < end:
                speeds.append(float(np.max(np.abs(message.msg.velocity))))
    return max(speeds)


def run_case(scenario: Scenario, directory: str, scale: float) -> CaseResult:
    """Simulate ``scenario`` (arm motion ``scale``), replay it, run the base-only filter."""
    work = Path(directory)
    name = f'{scenario.name}-{scale:g}'
    bag, out = work / name, work / f'{name}-replay'
    truth_file, summary_file = work / f'{name}.json', work / f'{name}-summary.json'
    params_file = work / f'{name}.params.yaml'
    if cli_main(['simulate', '-o', str(bag), '--overwrite', '--summary', str(truth_file),
                 '--torque-scale', str(scale), *scenario.robot,
                 *scenario.simulate]) != 0:
        raise RuntimeError(f'simulate failed for {scenario.name}')
    params_file.write_text(yaml.safe_dump(
        {'/**/reduced_dynamics': {'ros__parameters': scenario.params}}))
    if cli_main(['replay', str(bag), '-o', str(out), '--overwrite', '--quiet', '--no-smooth',
                 '--params', str(params_file), '--summary-json', str(summary_file),
                 *scenario.robot, *scenario.replay]) != 0:
        raise RuntimeError(f'replay failed for {scenario.name}')
    truth = json.loads(truth_file.read_text())
    origin = truth['start_time_ns']
    seconds, wrench = _wrenches(str(out), RATE_TOPIC, origin)
    sigma_stamps, sigma_rows = _diagnostic_sigma(str(out), origin, scenario.axes)
    ours = Filtered(seconds, wrench, _held(seconds, sigma_stamps, sigma_rows))
    truth_seconds, truth_wrench = _wrenches(str(bag), '/ground_truth/external_wrench', origin)
    summary = json.loads(summary_file.read_text())
    events = [(e['start_stamp_ns'] - origin) * 1e-9 for e in summary['events']]
    # The base-only filter: the whole robot's inertia at the first measured shape.
    robot = load_robot(FREEFLYER_ARM_URDF) if scenario.robot else load_robot()
    with open_bag(str(bag)) as reader:
        first = next(iter(reader.messages(['/joint_states'])))
        qbar = np.array(first.msg.position)
    inertia = robot.metric_blocks(qbar).locked_inertia
    if robot.n == 3:  # SE(2): (x, y, yaw) into the 6 axes
        full = np.eye(6)
        full[np.ix_([0, 1, 5], [0, 1, 5])] = inertia
        inertia = full
    track = read_base_track(str(bag), scenario.base_topic)
    # The same random walk as this package's filter (its defaults).
    values = defaults()
    jerk = np.array([values['wrench_jerk_linear']] * 3 + [values['wrench_jerk_angular']] * 3)
    impulse = np.array(truth['pulses'][0]['world_impulse'])
    return CaseResult(scenario, scale, _joint_speed(str(bag), origin, scenario.push[0]),
                      ours, run_base_only(scenario, track, inertia, jerk, origin),
                      Filtered(truth_seconds, truth_wrench, np.zeros_like(truth_wrench)),
                      impulse, events, track, inertia, jerk, origin,
                      (str(bag), '--params', str(params_file), *scenario.robot,
                       *scenario.replay))


def smoothed(result: CaseResult, directory: str) -> CaseResult:
    """Return ``result`` with both filters' fixed-interval smoothed estimates."""
    out = Path(directory) / f'{result.scenario.name}-{result.scale:g}-smoothed'
    if cli_main(['replay', '-o', str(out), '--overwrite', '--quiet',
                 *result.replay_args]) != 0:
        raise RuntimeError(f'replay failed for {result.scenario.name}')
    seconds, wrench = _wrenches(str(out), RATE_TOPIC, result.origin_ns)
    # /diagnostics hold the causal filter's covariance: no sigma for the smoothed estimate.
    ours = Filtered(seconds, wrench, np.full_like(wrench, np.nan))
    base_only = run_base_only(result.scenario, result.track, result.inertia, result.jerk,
                              result.origin_ns, smooth=True)
    return replace(result, ours=ours, base_only=base_only)


def smoothed_table(results: list[CaseResult]) -> str:
    """Return the smoothed figures (replay's default, RTS on the base-only filter)."""
    lines = ['| scenario | PD scale | false force RMS (peak), base-only RTS [N] | '
             'false force RMS (peak), this filter smoothed [N] | ratio | '
             'push impulse error, base-only / this |', '|---|---|---|---|---|---|']
    for result in results:
        base, ours = figures(result, result.base_only), figures(result, result.ours)
        lines.append(f'| {result.scenario.name} | {result.scale:g} | '
                     f'{base.force_rms:.3g} ({base.force_peak:.3g}) | '
                     f'{ours.force_rms:.3g} ({ours.force_peak:.3g}) | '
                     f'{base.force_rms / ours.force_rms:.1f} | '
                     f'{100 * base.impulse_error:.0f} % / {100 * ours.impulse_error:.1f} % |')
    return '\n'.join(lines)


@dataclass
class Figures:
    """The measured comparison of one filter on one scenario."""

    force_rms: float
    torque_rms: float
    force_peak: float
    #: RMS of the force over its own standard deviation, per axis, pooled
    force_whitened_rms: float
    #: fraction of force components within 3 of their own standard deviations
    within_3_sigma: float
    #: |estimated - true| / |true| of the push's linear impulse
    impulse_error: float


def figures(result: CaseResult, filtered: Filtered) -> Figures:
    """Return the figures of ``filtered`` over the arm-only window and around the push."""
    start, duration = result.scenario.push
    arm_only = (filtered.seconds >= SETTLE) & (filtered.seconds < start)
    linear = [a for a in result.scenario.axes if a < 3]
    angular = [a for a in result.scenario.axes if a >= 3]
    force = filtered.wrench[arm_only][:, linear]
    torque = filtered.wrench[arm_only][:, angular]
    sigma = filtered.sigma[arm_only][:, linear]
    whitened = force / sigma
    window = (filtered.seconds >= start - 0.5) & (filtered.seconds <= start + duration + 1.0)
    impulse = np.trapezoid(filtered.wrench[window][:, :3], filtered.seconds[window], axis=0)
    truth = result.world_impulse[:3]
    return Figures(
        float(np.sqrt(np.mean(np.sum(force ** 2, axis=1)))),
        float(np.sqrt(np.mean(np.sum(torque ** 2, axis=1)))),
        float(np.max(np.linalg.norm(force, axis=1))),
        float(np.sqrt(np.mean(whitened ** 2))),
        float(np.mean(np.abs(whitened) <= 3.0)),
        float(np.linalg.norm(impulse[linear] - truth[linear]) / np.linalg.norm(truth[linear])))


def table(results: list[CaseResult]) -> str:
    """Return the Markdown table of docs/mechanics_case.md."""
    lines = ['| scenario | arm motion: PD scale, peak joint speed | false force RMS (peak), '
             'base-only KF [N] | false force RMS (peak), this filter [N] | ratio | '
             'false torque RMS, base-only / this [N m] | '
             'force / own sigma RMS, base-only / this | within 3 sigma, base-only / this | '
             'push impulse error, base-only / this | events while only the arm moves '
             '(this filter) |',
             '|---|---|---|---|---|---|---|---|---|---|']
    for result in results:
        base, ours = figures(result, result.base_only), figures(result, result.ours)
        arm_events = sum(1 for s in result.event_starts if s < result.scenario.push[0])
        lines.append(
            f'| {result.scenario.name} | {result.scale:g}, {result.joint_speed:.2f} rad/s | '
            f'{base.force_rms:.3g} ({base.force_peak:.3g}) | '
            f'{ours.force_rms:.3g} ({ours.force_peak:.3g}) | '
            f'{base.force_rms / ours.force_rms:.1f} | '
            f'{base.torque_rms:.3g} / {ours.torque_rms:.3g} | '
            f'{base.force_whitened_rms:.2f} / {ours.force_whitened_rms:.2f} | '
            f'{100 * base.within_3_sigma:.0f} % / {100 * ours.within_3_sigma:.0f} % | '
            f'{100 * base.impulse_error:.0f} % / {100 * ours.impulse_error:.1f} % | '
            f'{arm_events} |')
    return '\n'.join(lines)


def detuning_table(results: list[CaseResult], factors: tuple[float, ...]) -> str:
    """Return the base-only filter's figures with its random walk scaled by ``factors``."""
    lines = ['| scenario | PD scale | random walk / default | false force RMS [N] | '
             'within 3 sigma | push impulse error |', '|---|---|---|---|---|---|']
    for result in results:
        if result.scale != result.scenario.shown:
            continue
        for factor in factors:
            filtered = run_base_only(result.scenario, result.track, result.inertia,
                                     factor * result.jerk, result.origin_ns)
            f = figures(result, filtered)
            lines.append(f'| {result.scenario.name} | {result.scale:g} | {factor:g} | '
                         f'{f.force_rms:.3g} | {100 * f.within_3_sigma:.0f} % | '
                         f'{100 * f.impulse_error:.0f} % |')
    return '\n'.join(lines)


def plot(results: list[CaseResult], path: str) -> None:
    """Draw the force norms over time of each scenario's shown case, and RMS vs arm speed."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    shown = [r for r in results if r.scale == r.scenario.shown]
    fig, panels = plt.subplots(len(shown) + 1, 1, figsize=(8, 2.6 * (len(shown) + 1)))
    for axis, result in zip(panels, shown):
        start, duration = result.scenario.push
        axis.axvspan(start, start + duration, color='0.88', label='push')
        for filtered, label, style in ((result.base_only, 'base-only per-axis KF', 'C3'),
                                       (result.ours, 'reduced mechanics (this package)', 'C0'),
                                       (result.truth, 'true external force', 'k--')):
            norm = np.linalg.norm(filtered.wrench[:, :3], axis=1)
            axis.plot(filtered.seconds, norm, style, lw=1.0, label=label)
        axis.plot(result.ours.seconds, 3.0 * np.linalg.norm(result.ours.sigma[:, :3], axis=1),
                  'C0:', lw=0.8, label='this package: 3 sigma')
        axis.set_xlim(SETTLE, result.ours.seconds[-1])
        # Scaled to what follows the settling time (the base-only prior is diffuse).
        after = result.base_only.seconds >= SETTLE
        axis.set_ylim(0.0, 1.15 * np.linalg.norm(result.base_only.wrench[after, :3],
                                                 axis=1).max())
        axis.set_ylabel('|force| [N]')
        axis.set_title(f'{result.scenario.title}, PD scale {result.scale:g}', fontsize=9)
        axis.legend(fontsize=6, loc='upper left')
    panels[-2].set_xlabel('time [s]')
    axis = panels[-1]
    for index, name in enumerate(dict.fromkeys(r.scenario.name for r in results)):
        rows = [r for r in results if r.scenario.name == name]
        speed = [r.joint_speed for r in rows]
        axis.plot(speed, [figures(r, r.base_only).force_rms for r in rows], 'o-',
                  color=f'C{3 + index}', label=f'{name}: base-only KF')
        axis.plot(speed, [figures(r, r.ours).force_rms for r in rows], 's--',
                  color=f'C{index}', label=f'{name}: this package')
    axis.set_yscale('log')
    axis.set_xlabel('peak joint speed while only the arm moves [rad/s]')
    axis.set_ylabel('false force RMS [N]')
    axis.set_title('force reported while only the arm moves', fontsize=9)
    axis.legend(fontsize=6)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def main(argv: Optional[list[str]] = None) -> int:
    """Print the table (and draw the plot) of the chosen scenarios."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--scenario', action='append', choices=sorted(SCENARIOS))
    parser.add_argument('--plot', help='write the PNG here')
    parser.add_argument('--work', help='directory for the bags (default: a temporary one)')
    args = parser.parse_args(argv)
    names = args.scenario or list(SCENARIOS)
    with tempfile.TemporaryDirectory() as scratch:
        results = [run_case(SCENARIOS[name], args.work or scratch, scale)
                   for name in names for scale in SCENARIOS[name].scales]
        print(table(results))
        print()
        print(detuning_table(results, DETUNING))
        print()
        print(smoothed_table([smoothed(r, args.work or scratch) for r in results
                              if r.scale == r.scenario.shown]))
        if args.plot:
            plot(results, args.plot)
    return 0


if __name__ == '__main__':
    sys.exit(main())
