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
Noise parameters from data: ``reduced-dynamics tune BAG -o params.yaml``.

The filter's innovations nu_k with covariances S_k give the log-likelihood of
the measurements, ``sum_k log N(nu_k; 0, S_k)`` (prediction-error
decomposition). Maximising it over the noise parameters (log-scaled,
Nelder-Mead from the current values, after a scan of the wrench random walk
over ``PROCESS_SCAN`` that picks the basin) is maximum-likelihood
identification of the sensor and process noise. The bag's inputs are decoded once; each
evaluation runs the causal filter over them (predictions and diagnostics off).
The result is written as a params YAML the node (``--ros-args --params-file``)
and ``replay --params`` read.
"""

from __future__ import annotations

import argparse
import math
import sys
from typing import Any, Callable, Optional, Sequence

import numpy as np
from scipy.optimize import minimize
import yaml

from reduced_dynamics.bag.reader import open_bag
from reduced_dynamics.estimator.config import EstimatorConfig, PARAMETERS
from reduced_dynamics.estimator.pipeline import Estimator
from reduced_dynamics.messages.samples import JointTrajectorySample, with_receive_time
from reduced_dynamics.params import defaults, load_params_file
from reduced_dynamics.replay import (check_shape_input, choose_inputs, input_decoder,
                                     JOINT_STATE_TYPE, load_robot_from_params, ReplayOptions,
                                     robot_source)
from reduced_dynamics.robot.model import RobotModel

#: What is tuned: the pose noise and the wrench random walk always, the twist noise
#: with Odometry, the joint-velocity noise when the robot has shape joints.
POSE_PARAMETERS = ('pose_position_noise', 'pose_angle_noise')
PROCESS_PARAMETERS = ('wrench_jerk_linear', 'wrench_jerk_angular')
TWIST_PARAMETERS = ('twist_linear_noise', 'twist_angular_noise')
#: Factors tried on the wrench random walk before the local search. The likelihood has
#: two basins: a random walk fast enough to absorb thruster switches (the step test then
#: sees nothing) and a slow one with the switches taken as steps; Nelder-Mead from the
#: defaults stays in the first (paper_realistic: jerk 0.68 at log-likelihood 36 662,
#: against 37 563 at 0.0005 with the switches taken as steps).
PROCESS_SCAN = (0.01, 0.1, 1.0, 10.0)


class _BudgetSpent(Exception):
    """The optimiser asked for an evaluation beyond ``--max-evaluations``."""


def load_inputs(bag: str, robot: RobotModel, options: ReplayOptions
                ) -> tuple[list, bool, bool]:
    """Return the bag's decoded input samples, whether the base is Odometry, base-driven."""
    samples = []
    with open_bag(bag) as reader:
        joint_topic, base_topic, is_odom = choose_inputs(reader.topics(), options)
        check_shape_input(reader, joint_topic, robot, options)
        base_type = reader.topics()[base_topic]
        decoders = {}
        for topic, msgtype in reader.connection_types([t for t in (joint_topic, base_topic)
                                                       if t]):
            if msgtype in (JOINT_STATE_TYPE, base_type):
                decoders[topic] = input_decoder(reader, topic, msgtype,
                                                '' if topic == joint_topic
                                                else robot.base_link)
        start = None if options.start is None else reader.start_ns + int(options.start * 1e9)
        end = None if options.end is None else reader.start_ns + int(options.end * 1e9)
        for message in reader.raw_messages(list(decoders), start, end):
            try:
                sample = decoders[message.topic](message.data)
            except (ValueError, TypeError):
                continue  # replay counts these; they carry no likelihood
            if sample is not None and sample.__class__ is not JointTrajectorySample:
                samples.append(with_receive_time(sample, message.timestamp_ns))
    return samples, is_odom, joint_topic is None or robot.m == 0 or options.base_driven


def evaluate(robot: RobotModel, samples: Sequence, params: dict, is_odom: bool,
             base_driven: bool) -> dict:
    """Run the causal filter over ``samples``; return its innovation statistics."""
    # The noise parameters are what is tuned: a message's own covariance must not replace them.
    values = dict(params, prediction_rate=0.0, diagnostics_rate=0.0,
                  use_message_covariance=False)
    estimator = Estimator(robot, EstimatorConfig.from_mapping(values), use_odometry=is_odom,
                          base_driven=base_driven,
                          cyclic_joints=params.get('cyclic_joints', ''))
    estimator.add_samples(samples)
    estimator.flush_batch()
    return estimator.filter_statistics()


def tuned_names(robot: RobotModel, is_odom: bool) -> tuple[str, ...]:
    """Return the parameters tuned for this robot and base input."""
    names = POSE_PARAMETERS + PROCESS_PARAMETERS
    if is_odom:
        names += TWIST_PARAMETERS
    if is_odom and robot.m:
        names += ('joint_velocity_noise',)
    return names


def tune(robot: RobotModel, samples: Sequence, params: dict, is_odom: bool,
         base_driven: bool, names: Sequence[str], max_evaluations: int = 60,
         progress: Optional[Callable[[str], None]] = None) -> dict[str, Any]:
    """
    Maximise the innovation log-likelihood over ``names`` (log10-scaled).

    Return the tuned values with the statistics before and after.
    """
    lows = np.array([math.log10(max(PARAMETERS[n].low, 1e-12)) for n in names])
    highs = np.array([math.log10(PARAMETERS[n].high) for n in names])
    start = np.array([math.log10(max(float(params[n]), 1e-12)) for n in names])
    count = 0
    best: list = [math.inf, start]  # lowest cost seen, where

    def cost(x: np.ndarray) -> float:
        nonlocal count
        if count >= max_evaluations:
            # One budget for the scan and the local search, whatever scipy's maxfev
            # does (it asked for one more evaluation when the scan had spent it).
            raise _BudgetSpent
        count += 1
        given, x = x, np.clip(x, lows, highs)
        trial = dict(params, **{n: float(10.0 ** v) for n, v in zip(names, x)})
        try:
            value = evaluate(robot, samples, trial, is_odom, base_driven)['log_likelihood']
        except np.linalg.LinAlgError:
            value = -math.inf  # the filter diverged at these values: no likelihood
        if progress is not None:
            progress(f'tune: evaluation {count}: log-likelihood {value:.6g} at '
                     + ', '.join(f'{n}={10.0 ** v:.3g}' for n, v in zip(names, x)))
        result = -value if math.isfinite(value) else math.inf
        if result < best[0] or count == 1:
            best[:] = [result, given]
        return result

    before = evaluate(robot, samples, params, is_odom, base_driven)
    process = np.array([n in PROCESS_PARAMETERS for n in names])
    try:
        if process.any():
            # Pick the basin first: the process noise scaled together, the rest as given.
            for factor in PROCESS_SCAN:
                cost(start + process * math.log10(factor))
            start = best[1]
        minimize(cost, start, method='Nelder-Mead',
                 options={'maxfev': max_evaluations, 'xatol': 0.02, 'fatol': 0.5,
                          'initial_simplex': np.vstack([start] + [
                              start + 0.5 * np.eye(len(names))[i]
                              for i in range(len(names))])})
    except _BudgetSpent:
        pass
    best = np.clip(best[1], lows, highs)
    values = {n: float(f'{10.0 ** v:.4g}') for n, v in zip(names, best)}
    after = evaluate(robot, samples, dict(params, **values), is_odom, base_driven)
    return {'values': values, 'before': before, 'after': after, 'evaluations': count}


def params_yaml(values: dict[str, float], comment: str) -> str:
    """Return a params file (the node's format) setting ``values``."""
    lines = [f'# {line}' for line in comment.splitlines()]
    document = {'/**/reduced_dynamics': {'ros__parameters': values}}
    return '\n'.join(lines) + '\n' + yaml.safe_dump(document, sort_keys=False)


def _run(args: argparse.Namespace) -> int:
    params = load_params_file(args.params) if args.params else defaults()
    robot = load_robot_from_params(params, args.urdf, args.base_joint, args.gravity,
                                   args.xacro_arg)
    options = ReplayOptions(params=params, joint_states_topic=args.joint_states_topic,
                            odom_topic=args.odom_topic, base_pose_topic=args.base_pose_topic,
                            start=args.start, end=args.end, base_driven=args.base_driven,
                            robot_source=robot_source(params, args.urdf))
    samples, is_odom, base_driven = load_inputs(args.bag, robot, options)
    if not samples:
        print('reduced-dynamics tune: error: no input samples in the bag', file=sys.stderr)
        return 2
    names = tuple(args.parameters.split(',')) if args.parameters \
        else tuned_names(robot, is_odom)
    unknown = [n for n in names if n not in PARAMETERS]
    if unknown:
        print(f'reduced-dynamics tune: error: unknown parameters {unknown}', file=sys.stderr)
        return 2
    report = None if args.quiet else (lambda line: print(line, file=sys.stderr))
    result = tune(robot, samples, params, is_odom, base_driven, names,
                  args.max_evaluations, report)
    before, after = result['before'], result['after']
    comment = (f'reduced-dynamics tune {args.bag}: maximum innovation likelihood over '
               f'{len(samples)} input messages, {result["evaluations"]} evaluations\n'
               f'log-likelihood {before["log_likelihood"]:.6g} -> '
               f'{after["log_likelihood"]:.6g}; NIS per dof {before["nis_per_dof"]:.3g} -> '
               f'{after["nis_per_dof"]:.3g} (1 when the noise fits)')
    text = params_yaml(result['values'], comment)
    with open(args.output, 'w', encoding='utf-8') as stream:
        stream.write(text)
    print(text, end='')
    return 0


def register_command(commands: Any) -> None:
    """Add the ``tune`` subcommand."""
    from reduced_dynamics.cli import add_robot_arguments
    parser = commands.add_parser('tune', help='estimate the filter\'s noise parameters from '
                                              'a bag (maximum innovation likelihood)')
    parser.add_argument('bag', help='rosbag2 directory (MCAP or sqlite3) or .mcap file')
    parser.add_argument('-o', '--output', required=True, help='params YAML to write')
    add_robot_arguments(parser)
    parser.add_argument('--params', help='starting parameters YAML (the node\'s format)')
    parser.add_argument('--joint-states-topic')
    group = parser.add_mutually_exclusive_group()
    group.add_argument('--odom-topic')
    group.add_argument('--base-pose-topic')
    parser.add_argument('--start', type=float, help='seconds from the bag start')
    parser.add_argument('--end', type=float, help='seconds from the bag start')
    parser.add_argument('--parameters', metavar='NAMES',
                        help='comma-separated parameters to tune (default: pose noise, '
                             'wrench random walk, and twist/joint noise with Odometry)')
    parser.add_argument('--max-evaluations', type=int, default=60,
                        help='filter runs the optimiser may make (default 60)')
    parser.add_argument('--base-driven', action='store_true',
                        help='as replay --base-driven: the shape held from the latest joint '
                             'state (at zero when the bag has none)')
    parser.add_argument('--quiet', action='store_true', help='no progress lines')
    parser.set_defaults(func=_run)
