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

"""Command line: ``reduced-dynamics validate | symmetries | simulate | replay | bench``."""

from __future__ import annotations

import argparse
import sys
from typing import Optional, Sequence

import numpy as np


def add_robot_arguments(parser: argparse.ArgumentParser) -> None:
    """--urdf, --base-joint and --gravity, shared by every subcommand."""
    parser.add_argument('--urdf', default='',
                        help='robot URDF file (default: the paper robot, section 6)')
    parser.add_argument('--base-joint', choices=('floating', 'planar'), default=None,
                        help='free base joint when the URDF has no world joint '
                             '(default: floating)')
    parser.add_argument('--gravity', type=float, nargs=3, default=None,
                        metavar=('GX', 'GY', 'GZ'),
                        help='gravity in the world frame, m/s^2 (planar base only, along z)')


def load_robot_from_args(args: argparse.Namespace):
    """Return the robot model the arguments describe."""
    from reduced_dynamics.robot.model import load_robot
    gravity = None if args.gravity is None else np.array(args.gravity)
    return load_robot(args.urdf, args.base_joint, gravity)


def _validate(args: argparse.Namespace) -> int:
    from reduced_dynamics.validation import format_table, validation_table
    robot = load_robot_from_args(args)
    print(f'robot {robot.model.name}: base {robot.group.name} ({robot.base_link}), '
          f'{robot.m} shape joints, {args.duration:g} s per run, DOP853 rtol 1e-12')
    rows = validation_table(robot, args.duration, args.seed)
    print(format_table(rows))
    worst = max(max(r.shape_error for r in rows), max(r.pose_error for r in rows) / 10.0,
                max(r.pi_error for r in rows))
    ok = worst <= args.tolerance
    print(f'{"PASS" if ok else "FAIL"}: reduced model agrees with full dynamics '
          f'(shape <= {args.tolerance:g} rad, pose <= {10 * args.tolerance:g}, '
          f'pi <= {args.tolerance:g} relative)')
    return 0 if ok else 1


def _symmetries(args: argparse.Namespace) -> int:
    from reduced_dynamics.robot.symmetry import detect_symmetries
    robot = load_robot_from_args(args)
    report = detect_symmetries(robot, args.rtol, args.configurations, args.seed)
    print(report.format())
    return 0


def build_parser() -> argparse.ArgumentParser:
    """Return the argument parser of every subcommand."""
    parser = argparse.ArgumentParser(
        prog='reduced-dynamics',
        description='Symplectically reduced dynamics of free-floating robots '
                    '(Chhabra & Emami 2014).')
    commands = parser.add_subparsers(dest='command', required=True)
    validate = commands.add_parser(
        'validate', help='compare the reduced model with full dynamics (Pinocchio aba)')
    add_robot_arguments(validate)
    validate.add_argument('--duration', type=float, default=10.0, help='seconds per run')
    validate.add_argument('--seed', type=int, default=0)
    validate.add_argument('--tolerance', type=float, default=1e-8,
                          help='largest shape error accepted, rad')
    validate.set_defaults(func=_validate)
    symmetries = commands.add_parser(
        'symmetries', help='report the cyclic joints (section 5.1: 5.43, Prop. 56, 5.46)')
    add_robot_arguments(symmetries)
    symmetries.add_argument('--rtol', type=float, default=1e-9,
                            help='invariance tolerance relative to the inertias')
    symmetries.add_argument('--configurations', type=int, default=12,
                            help='random configurations tested besides the home pose')
    symmetries.add_argument('--seed', type=int, default=0)
    symmetries.set_defaults(func=_symmetries)
    for register in _extra_commands():
        register(commands)
    return parser


def _extra_commands() -> list:
    registrars = []
    for module in ('simulator', 'replay', 'bench'):
        try:
            imported = __import__(f'reduced_dynamics.{module}', fromlist=['register_command'])
        except ImportError:
            continue
        if hasattr(imported, 'register_command'):
            registrars.append(imported.register_command)
    return registrars


def main(argv: Optional[Sequence[str]] = None) -> int:
    """Entry point of ``reduced-dynamics``."""
    from reduced_dynamics.robot.model import ModelError
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except (ModelError, FileNotFoundError, ValueError) as error:
        print(f'reduced-dynamics {args.command}: error: {error}', file=sys.stderr)
        return 2


if __name__ == '__main__':
    sys.exit(main())
