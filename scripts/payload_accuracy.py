#!/usr/bin/env python3
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
The accuracy tables of docs/payload.md.

    python scripts/payload_accuracy.py [--seeds 1 2 3] [--durations 5 10 20]
                                       [--noise 1 3]
    python scripts/payload_accuracy.py --success [--seeds 1 ... 16] [--robots paper tree]

Default: paper robot, 8 kg payload on the forearm, sinusoid torques; sensor noise
the realistic figures times a factor (the filter's noise parameters scaled alike).
Prints one Markdown row per (duration, noise): median |error| over the seeds
and how many of the seeds' estimates lie within 3 sigma of the truth.

``--success``: issue 22's acceptance cases (reduced_dynamics.payload_bench), 20 s
each, one row per robot: over how many seeds the bounds hold, the truth lies within
3 sigma, the report flags a weakly excited quantity, and the worst errors.
"""

import argparse
import os
import tempfile

import numpy as np

from reduced_dynamics.identify import identify_bag, IdentificationError
from reduced_dynamics.params import defaults
from reduced_dynamics.payload import Payload, with_payload
from reduced_dynamics.payload_bench import (
    ACCEPTANCE_CASES, acceptance_bag, acceptance_errors, acceptance_robot, BENCH_PAYLOAD,
    SENSOR_OPTIONS, SENSOR_PARAMETERS)
from reduced_dynamics.robot.model import load_robot
from reduced_dynamics.simulator import simulate_bag, SimulationOptions


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--seeds', type=int, nargs='+', default=[1, 2, 3])
    parser.add_argument('--durations', type=float, nargs='+', default=[5.0, 10.0, 20.0])
    parser.add_argument('--noise', type=float, nargs='+', default=[1.0, 3.0])
    parser.add_argument('--success', action='store_true',
                        help='success rate over the seeds per acceptance robot')
    parser.add_argument('--robots', nargs='+', default=list(ACCEPTANCE_CASES))
    args = parser.parse_args()
    if args.success:
        success_table(args.robots, args.seeds)
        return
    robot = load_robot('')
    truth = Payload.parse(BENCH_PAYLOAD)
    held = with_payload(robot, truth)
    print('| window | noise | mass error | CoM error (max axis) | principal inertia error '
          '(max) | within 3 sigma | refused |')
    print('|---|---|---|---|---|---|---|')
    workdir = tempfile.mkdtemp()
    for duration in args.durations:
        for factor in args.noise:
            options = {k: (v * factor if k.startswith('noise') else v)
                       for k, v in SENSOR_OPTIONS.items()}
            params = {**defaults(), **{k: v * factor for k, v in SENSOR_PARAMETERS.items()}}
            mass, com, inertia, inside, refused = [], [], [], 0, 0
            for seed in args.seeds:
                bag = f'{workdir}/{duration}_{factor}_{seed}'
                simulate_bag(held, bag, SimulationOptions(duration=duration, rate=100.0,
                                                          seed=seed, **options))
                try:
                    estimate = identify_bag(bag, robot, truth.link, params)
                except IdentificationError:
                    refused += 1
                    continue
                found = estimate.payload
                errors = np.r_[found.mass - truth.mass, found.com - truth.com,
                               found.principal_inertia - truth.principal_inertia]
                sigmas = np.r_[estimate.mass_sigma, estimate.com_sigma,
                               estimate.principal_sigma]
                mass.append(abs(errors[0]) / truth.mass)
                com.append(np.abs(errors[1:4]).max())
                inertia.append(np.max(np.abs(errors[4:]) / truth.principal_inertia))
                inside += bool(np.all(np.abs(errors) <= 3.0 * sigmas))
            used = len(mass)
            if used:
                print(f'| {duration:g} s | x{factor:g} | {100 * np.median(mass):.1f} % | '
                      f'{1000 * np.median(com):.1f} mm | {100 * np.median(inertia):.0f} % | '
                      f'{inside}/{used} | {refused} |')
            else:
                print(f'| {duration:g} s | x{factor:g} | - | - | - | - | {refused} |')


def success_table(robots: list, seeds: list) -> None:
    """Print issue 22's acceptance over the seeds, one Markdown row per robot."""
    params = {**defaults(), **SENSOR_PARAMETERS}
    workdir = tempfile.mkdtemp()
    print('| robot | arm torques | bounds met | truth within 3 sigma | flagged weakly excited '
          '| refused | worst mass / CoM / inertia error | failing seeds |')
    print('|---|---|---|---|---|---|---|---|')
    for name in robots:
        robot = acceptance_robot(name)
        spec, torque, scale = ACCEPTANCE_CASES[name]
        link = spec.split(',')[0]
        met, covered, weak, refused, failing = 0, 0, 0, 0, []
        worst = np.zeros(3)
        for seed in seeds:
            bag = os.path.join(workdir, f'{name}_{seed}')
            acceptance_bag(name, seed, bag)
            try:
                estimate = identify_bag(bag, robot, link, params)
            except IdentificationError:
                refused += 1
                failing.append(f'{seed} (refused)')
                continue
            errors = acceptance_errors(name, estimate)
            met += errors['accurate']
            covered += errors['covered']
            weak += bool(estimate.weakly_excited())
            worst = np.maximum(worst, [abs(errors['mass']), np.abs(errors['com']).max(),
                                       np.abs(errors['inertia']).max()])
            if not errors['accurate']:
                i = int(np.argmax(np.abs(errors['inertia'])))
                failing.append(f'{seed} (inertia {100 * errors["inertia"][i]:+.0f} % '
                               f'± {300 * errors["inertia_sigma"][i]:.0f} % at 3 sigma)')
        total = len(seeds)
        print(f'| {name} | {torque} x {scale:g} | {met}/{total} | {covered}/{total - refused} '
              f'| {weak}/{total - refused} | {refused} | {100 * worst[0]:.1f} % / '
              f'{1000 * worst[1]:.1f} mm / {100 * worst[2]:.0f} % | '
              f'{", ".join(failing) or "-"} |', flush=True)


if __name__ == '__main__':
    main()
