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
The multi-scale event test's detection table (docs/multiscale_events.md).

Simulates robots whose arm moves under PD tracking, with realistic sensors, and
pushes of 0.05-3 s whose impulse is a multiple of the detectability bound
(estimator/detectability.py ``impulse_bound``: the smallest push of that duration
any test could flag by the push's end, with the state before it known). Replays
each bag causally with the sensor figures the simulation used and prints, per
duration and multiple: detection probability, median latency (detection - push
start), median start error, median impulse error (linear part), and events outside
every push. Then simulates coasting with the arm moving and prints events per hour.
Usage::

    python scripts/multiscale_detection_table.py WORKDIR [--robots freeflyer_arm paper]
        [--seeds 3] [--pushes 4] [--coast-minutes 30] [--durations 0.05 0.3 1 3]
        [--multiples 1 3 10 30] [--skip-pushes] [--coast-bags BAG...] [--no-predictions]
"""

import argparse
import json
from pathlib import Path
import shutil
import sys
import tempfile
from typing import Optional

import numpy as np

from reduced_dynamics.cli import main as cli_main
from reduced_dynamics.estimator.detectability import impulse_bound
from reduced_dynamics.estimator.multiscale import window_bank
from reduced_dynamics.params import defaults
from reduced_dynamics.replay import replay, ReplayOptions
from reduced_dynamics.robot.humanoid_bus import humanoid_on_bus_urdf
from reduced_dynamics.robot.model import load_robot

DATA = Path(__file__).resolve().parent.parent / 'test' / 'data'
ROBOTS = {
    # The small free-flyer case: pose 1 mm / 1 mrad, twist 3 mm/s, 62.5 Hz.
    'freeflyer_arm': {
        'urdf': str(DATA / 'freeflyer_arm.urdf'), 'rate': 62.5,
        'simulate': ['--torque', 'pd', '--noise-position', '1e-3', '--noise-velocity',
                     '0.005', '--noise-pose', '0.001', '--noise-orientation', '0.001',
                     '--noise-twist', '0.003'],
        'params': {'pose_position_noise': 1e-3, 'pose_angle_noise': 1e-3,
                   'twist_linear_noise': 3e-3, 'twist_angular_noise': 3e-3,
                   'joint_velocity_noise': 5e-3},
        'pose_sigma': (1e-3, 1e-3, 1e-3), 'twist_sigma': (3e-3, 3e-3, 3e-3)},
    # test/data/paper_realistic's sensors (scripts/make_test_bags.sh), Odometry 100 Hz.
    'paper': {
        'urdf': None, 'rate': 100.0,
        'simulate': ['--torque', 'pd', '--noise-position', '1e-4', '--noise-velocity',
                     '0.005', '--noise-effort', '0.05', '--noise-pose', '0.001',
                     '--noise-orientation', '0.0005', '--noise-twist', '0.002',
                     '--quantize', 'joint_position=1e-5', '--stamp-jitter', '0.0003',
                     '--latency', '0.004', '--latency-jitter', '0.001', '--drop-rate',
                     '0.01'],
        'params': {'pose_position_noise': 1e-3, 'pose_angle_noise': 5e-4,
                   'pose_stamp_noise': 3e-4, 'twist_linear_noise': 2e-3,
                   'twist_angular_noise': 2e-3, 'joint_velocity_noise': 5e-3},
        'pose_sigma': (1e-3,) * 3 + (5e-4,) * 3, 'twist_sigma': (2e-3,) * 6},
    # A 29-joint humanoid (70 kg, robot/humanoid_bus.py) on a 500 kg bus: the issue's
    # sensors (pose 1 mm / 1 mrad, velocities 0.01), Odometry at 100 Hz (500 Hz in
    # test_multiscale_events; 100 Hz keeps an hour of coasting affordable here).
    'bus_humanoid': {
        'urdf': 'humanoid_on_bus', 'rate': 100.0,
        'simulate': ['--torque', 'pd', '--noise-position', '1e-4', '--noise-velocity',
                     '0.01', '--noise-pose', '0.001', '--noise-orientation', '0.001',
                     '--noise-twist', '0.01'],
        'params': {'pose_position_noise': 1e-3, 'pose_angle_noise': 1e-3,
                   'twist_linear_noise': 0.01, 'twist_angular_noise': 0.01,
                   'joint_velocity_noise': 0.01},
        'pose_sigma': (1e-3,) * 6, 'twist_sigma': (0.01,) * 6},
}
DURATIONS = (0.05, 0.3, 1.0, 3.0)
MULTIPLES = (1.0, 3.0, 10.0, 30.0)
#: Seconds from one push's end to the next push (the longest window and settling).
GAP = 9.0
FIRST = 5.0
#: Print every bag's events and pushes (--verbose).
VERBOSE = False
#: Replay without predictions (--no-predictions).
NO_PREDICTIONS = False
#: Take the next seed when a bag's simulation fails (--skip-failed-seeds): most seeds
#: drive the bus's humanoid past a joint's limits (docs/multiscale_events.md).
SKIP_FAILED = False


def _bound(name: str, robot, duration: float) -> float:
    """Return the force [N] along body x whose push of ``duration`` is at the bound."""
    spec = ROBOTS[name]
    inertia = robot.metric_blocks(np.zeros(robot.m)).locked_inertia
    unit = np.zeros(robot.n)
    unit[0] = 1.0
    acceleration = np.linalg.solve(inertia, unit)
    # Two tests share the rate when a twist is measured (multiscale.py), each over the bank.
    significance = defaults()['event_false_alarm_rate'] / spec['rate'] / 3600.0 \
        / len(window_bank()) / 2
    return impulse_bound(acceleration, duration, spec['rate'], spec['pose_sigma'],
                         spec['twist_sigma'], significance)


def _simulate(name: str, path: Path, seconds: float, seed: int, pushes: list) -> dict:
    spec = ROBOTS[name]
    truth = path.parent / f'{path.name}.json'
    args = ['simulate', '-o', str(path), '--overwrite', '--summary', str(truth),
            '--duration', f'{seconds:g}', '--rate', f"{spec['rate']:g}", '--seed', str(seed),
            '--momentum-class', 'zero', *spec['simulate']]
    if spec['urdf']:
        args += ['--urdf', spec['urdf']]
    for start, duration, force in pushes:
        args += ['--thruster', f'{start:g},{duration:g},{force:.9g},0,0,0,0,0']
    if cli_main(args) != 0:
        raise RuntimeError(f'simulate failed: {args}')
    return json.loads(truth.read_text())


def _replay(name: str, robot, bag: Path) -> dict:
    params = defaults()
    params.update(ROBOTS[name]['params'])
    if NO_PREDICTIONS:
        # Predictions read the filter and never feed the event tests (the events of the
        # issue's two cases are byte for byte the same without them): a third of the
        # bus's replay time saved on an hour of coasting.
        params['prediction_rate'] = 0.0
    out = Path(tempfile.mkdtemp(dir=bag.parent))
    try:
        return replay(str(bag), str(out / 'out'), robot,
                      ReplayOptions(params=params, smooth=False))
    finally:
        shutil.rmtree(out, ignore_errors=True)


def _linear(robot, vector) -> np.ndarray:
    vector = np.asarray(vector, float)
    return vector[:2] if robot.n == 3 else vector[:3]


def detection_rows(name: str, work: Path, seeds: int, pushes: int,
                   durations: tuple = DURATIONS, multiples: tuple = MULTIPLES) -> list[str]:
    """Return the table's rows for robot ``name``."""
    robot = _robot(name)
    rows = []
    for duration in durations:
        bound = _bound(name, robot, duration)
        for multiple in multiples:
            force = multiple * bound
            found, latencies, starts, errors, others, split = 0, [], [], [], 0, 0
            plan = [(FIRST + k * (duration + GAP), duration, force) for k in range(pushes)]
            seconds = FIRST + pushes * (duration + GAP)
            seed, used = -1, []
            while len(used) < seeds:
                seed += 1
                bag = work / f'{name}-{duration:g}-{multiple:g}-{seed}'
                try:
                    truth = _simulate(name, bag, seconds, 100 + seed, plan)
                except RuntimeError:
                    if not SKIP_FAILED or seed >= 4 * seeds + 20:
                        raise
                    shutil.rmtree(bag, ignore_errors=True)
                    continue
                used.append(100 + seed)
                events = list(_replay(name, robot, bag)["events"])
                if VERBOSE:
                    origin = truth['start_time_ns']
                    print('events (start, detected, end, window):',
                          [(round((e['start_stamp_ns'] - origin) * 1e-9, 2),
                            round((e['detected_stamp_ns'] - origin) * 1e-9, 2),
                            None if e['end_s'] is None else round(e['end_s'], 2),
                            e['window_s']) for e in events],
                          'pushes at', [p[0] for p in plan], flush=True)
                origin = truth['start_time_ns']
                for (start, _, _), pulse in zip(plan, truth['pulses']):
                    mine = [e for e in events
                            if start - 0.5 <= (e['start_stamp_ns'] - origin) * 1e-9
                            <= start + duration + 0.5]
                    for event in mine:
                        events.remove(event)
                    if not mine:
                        continue
                    found += 1
                    split += len(mine) > 1
                    first = mine[0]
                    latencies.append((first['detected_stamp_ns'] - origin) * 1e-9 - start)
                    starts.append((first['start_stamp_ns'] - origin) * 1e-9 - start)
                    if first['impulse'] is not None:
                        true = _linear(robot, pulse['world_impulse'])
                        estimate = _linear(robot, first['impulse'])
                        errors.append(float(np.linalg.norm(estimate - true)
                                            / np.linalg.norm(true)))
                others += len(events)
                shutil.rmtree(bag, ignore_errors=True)
            total = seeds * pushes

            def median(values: list) -> str:
                return f'{np.median(values):.3g}' if values else '—'
            rows.append(f'| {name} | {duration:g} | {multiple:g} | {force * duration:.3g} | '
                        f'{found}/{total} ({found / total:.0%}) | {median(latencies)} | '
                        f'{median(starts)} | {median(errors)} | {others} |')
            print(rows[-1], flush=True)
            if VERBOSE:
                print(f'seeds {used}: {split} of {total} pushes gave more than one event',
                      flush=True)
    return rows


def coasting_row(name: str, work: Path, minutes: float, seed: int,
                 bag: Optional[Path] = None) -> str:
    """
    Return the false-alarm row: events on a coasting bag with the arm moving.

    ``bag``: a coasting bag simulated before (its ``<bag>.json`` summary beside it),
    replayed instead of a new one. The row lists each event's start [min] and the
    test that found it: the multi-scale window [s], or chi2/step (the per-sample
    chi-square or the wrench-step test, which ``event_significance`` governs).
    """
    robot = _robot(name)
    if bag is None:
        bag = work / f'{name}-coast-{seed}'
        truth = _simulate(name, bag, minutes * 60.0, seed, [])
        keep = False
    else:
        truth = json.loads(Path(f'{bag}.json').read_text())
        minutes, seed, keep = truth['duration'] / 60.0, truth['seed'], True
    summary = _replay(name, robot, bag)
    if not keep:
        shutil.rmtree(bag, ignore_errors=True)
    events = summary['events']
    origin = truth['start_time_ns']
    found = ', '.join(
        f"{(e['start_stamp_ns'] - origin) * 1e-9 / 60:.1f} min "
        f"({'chi2/step' if e['window_s'] is None else format(e['window_s'], '.2g') + ' s'})"
        for e in events) or '—'
    hours = minutes / 60.0
    row = (f'| {name} | {minutes:g} min (seed {seed}) | {len(events)} | '
           f'{len(events) / hours:.2f} | {found} |')
    print(row, flush=True)
    return row


def _robot(name: str):
    spec = ROBOTS[name]
    return load_robot(spec['urdf']) if spec['urdf'] else load_robot()


def main() -> int:
    """Print the detection table and the false-alarm rows."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[1])
    parser.add_argument('workdir')
    parser.add_argument('--robots', nargs='+', default=list(ROBOTS), choices=list(ROBOTS))
    parser.add_argument('--seeds', type=int, default=3)
    parser.add_argument('--pushes', type=int, default=4)
    parser.add_argument('--coast-minutes', type=float, default=30.0)
    parser.add_argument('--coast-seeds', type=int, nargs='+', default=[31])
    parser.add_argument('--coast-bags', nargs='+', default=[],
                        help='coasting bags simulated before (a <bag>.json beside each): '
                        'replayed instead of simulating (--robots: one robot)')
    parser.add_argument('--no-predictions', action='store_true',
                        help='replay with prediction_rate 0 (the events do not change)')
    parser.add_argument('--skip-pushes', action='store_true')
    parser.add_argument('--verbose', action='store_true')
    parser.add_argument('--skip-failed-seeds', action='store_true',
                        help='a bag whose simulation fails (a joint past its limits): '
                        'take the next seed')
    parser.add_argument('--durations', type=float, nargs='+', default=list(DURATIONS))
    parser.add_argument('--multiples', type=float, nargs='+', default=list(MULTIPLES))
    args = parser.parse_args()
    global VERBOSE, NO_PREDICTIONS, SKIP_FAILED
    VERBOSE = args.verbose
    SKIP_FAILED = args.skip_failed_seeds
    NO_PREDICTIONS = args.no_predictions
    work = Path(args.workdir)
    work.mkdir(parents=True, exist_ok=True)
    humanoid = work / 'humanoid_on_bus.urdf'
    humanoid.write_text(humanoid_on_bus_urdf())
    ROBOTS['bus_humanoid']['urdf'] = str(humanoid)
    if not args.skip_pushes:
        print('| robot | push [s] | x bound | impulse [N s] | detected | latency [s] | '
              'start error [s] | impulse error | other events |')
        print('|---|---|---|---|---|---|---|---|---|')
        for name in args.robots:
            detection_rows(name, work, args.seeds, args.pushes, tuple(args.durations),
                           tuple(args.multiples))
    if args.coast_minutes > 0 or args.coast_bags:
        print('| robot | coasting, arm moving | events | per hour | events at (test) |')
        print('|---|---|---|---|---|')
        for name in args.robots:
            for bag in args.coast_bags:
                coasting_row(name, work, 0.0, 0, Path(bag))
            for seed in args.coast_seeds if args.coast_minutes > 0 else []:
                coasting_row(name, work, args.coast_minutes, seed)
    return 0


if __name__ == '__main__':
    sys.exit(main())
