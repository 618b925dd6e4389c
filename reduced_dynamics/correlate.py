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
``reduced-dynamics correlate OUT``: how well the wrench estimate follows the command.

Per axis (world Fx, Fy; Mz about the centre of mass) the correlation and the
gain (delivered / commanded) of a replay's (or a recorded node's)
``drift/momentum_rate`` with a thruster command, by
:func:`reduced_dynamics.thrust_correlation.command_fit`. The command message and
the thrusters are a command mapping (:mod:`reduced_dynamics.command_mapping`, the
file ``replay-many --command-mapping`` takes); the defaults fit the shipped
freeflyer2 recording.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from typing import Any, Optional

from reduced_dynamics.bag.reader import open_bag
from reduced_dynamics.command_mapping import CommandMapping, FREEFLYER2
from reduced_dynamics.resources import config_path
from reduced_dynamics.thrust_correlation import (command_fit, CommandFit, ORDER, POSE_TOPIC,
                                                 RATE_TOPIC, WINDOW)

#: Base pose types the command's body force is rotated by.
POSE_TYPES = ('geometry_msgs/msg/PoseStamped', 'nav_msgs/msg/Odometry')
AXES = ('fx', 'fy', 'mz')
UNITS = ('N', 'N', 'N m')


def load_mapping(path: Optional[str], command_topic: Optional[str]) -> CommandMapping:
    """Return the command mapping of ``path`` (default freeflyer2's), on ``command_topic``."""
    mapping = CommandMapping.load(path or config_path(FREEFLYER2))
    if command_topic:
        topic = command_topic if command_topic.startswith('/') else '/' + command_topic
        mapping = dataclasses.replace(mapping, topic=topic)
    return mapping


def choose_pose_topic(bag: str, given: Optional[str]) -> str:
    """Return ``given``, else freeflyer2's mocap topic, else the bag's only pose topic."""
    if given:
        return given
    with open_bag(bag) as reader:
        topics = reader.topics()
    if POSE_TOPIC in topics:
        return POSE_TOPIC
    poses = sorted(t for t, msgtype in topics.items() if msgtype in POSE_TYPES)
    if len(poses) != 1:
        raise ValueError(f'{bag}: give --pose-topic; pose topics in the bag: {poses or "none"}')
    return poses[0]


def format_fit(fit: CommandFit, mapping: CommandMapping, rate_topic: str) -> str:
    """Return the table ``correlate`` prints."""
    name = mapping.name or mapping.msgtype
    lines = [f'{rate_topic} against {mapping.topic} ({name}, {len(mapping.thrusters)} '
             f'thrusters), {fit.correlation.samples} samples',
             f'{"axis":<4}  {"correlation":>11}  {"gain":>8}  {"bias":>10}']
    for axis, unit, corr, gain, bias in zip(AXES, UNITS, fit.correlation[:3], fit.gain,
                                            fit.bias):
        lines.append(f'{axis:<4}  {corr:>11.4f}  {gain:>8.4f}  {bias:>+10.4g} {unit}')
    lines.append('(world frame; mz about the centre of mass; gain: estimate / command)')
    return '\n'.join(lines)


def _run(args: argparse.Namespace) -> int:
    mapping = load_mapping(args.thruster_map, args.command_topic)
    bag = args.bag or args.out
    if not args.bag:
        with open_bag(bag) as reader:
            if mapping.topic not in reader.topics():
                raise ValueError(f'{bag} has no command topic {mapping.topic}: give the '
                                 'recording that has it with --bag (the replay\'s input)')
    pose_topic = choose_pose_topic(bag, args.pose_topic)
    fit = command_fit(bag, args.out, pose_topic, args.window, args.order, mapping=mapping,
                      rate_topic=args.rate_topic)
    if args.json:
        print(json.dumps({'topic': mapping.topic, 'rate_topic': args.rate_topic,
                          'samples': fit.correlation.samples,
                          **{axis: {'correlation': corr, 'gain': gain, 'bias': bias}
                             for axis, corr, gain, bias in zip(
                                 AXES, fit.correlation[:3], fit.gain, fit.bias)}}))
    else:
        print(format_fit(fit, mapping, args.rate_topic))
    return 0


def register_command(commands: Any) -> None:
    """Add the ``correlate`` subcommand."""
    parser = commands.add_parser(
        'correlate', help='correlation and gain of the wrench estimate with a thruster '
                          'command, per axis')
    parser.add_argument('out', metavar='OUT',
                        help='bag with the estimate: a replay output, or a recording of '
                             'the node (then it may hold the command and the poses too)')
    parser.add_argument('--bag', help='the recording with the command and the base poses '
                                      '(the replay\'s input; default: OUT)')
    parser.add_argument('--thruster-map', metavar='FILE',
                        help='command mapping YAML (as replay-many --command-mapping; '
                             'default: the shipped config/thrusters/freeflyer2.yaml)')
    parser.add_argument('--command-topic', metavar='T',
                        help='the command topic (default: the thruster map\'s, '
                             'freeflyer2: /robot/commands/binary_thrust)')
    parser.add_argument('--pose-topic', help=f'base poses (default: {POSE_TOPIC} if present, '
                                             'else the bag\'s only pose topic)')
    parser.add_argument('--rate-topic', default=RATE_TOPIC,
                        help=f'the estimate (default {RATE_TOPIC}; e.g. the fixed-lag '
                             'drift/momentum_rate_smoothed)')
    parser.add_argument('--window', type=int, default=WINDOW,
                        help=f'Savitzky-Golay window, samples (default {WINDOW})')
    parser.add_argument('--order', type=int, default=ORDER,
                        help=f'Savitzky-Golay order (default {ORDER})')
    parser.add_argument('--json', action='store_true', help='print JSON instead of a table')
    parser.set_defaults(func=_run)
