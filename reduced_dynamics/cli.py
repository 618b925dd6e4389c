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
Command line: ``reduced-dynamics validate | symmetries | simulate | replay | ...``.

Subcommands: validate, symmetries, simulate, replay, replay-many, predict, tune, bench,
identify, correlate, play.

One subcommand per task; ``--help`` on each lists its options.
"""

from __future__ import annotations

import argparse
import importlib
import os
import signal
import sys
from typing import Optional, Sequence

from reduced_dynamics import stop_signals


def add_robot_arguments(parser: argparse.ArgumentParser) -> None:
    """--urdf, --base-joint and --gravity, shared by every subcommand."""
    parser.add_argument('--urdf', default='',
                        help='robot URDF file, or a .xacro file expanded with xacro '
                             '(default: the paper robot, section 6)')
    parser.add_argument('--xacro-arg', action='append', default=[], metavar='NAME:=VALUE',
                        help='argument of a .xacro --urdf (repeat for several)')
    parser.add_argument('--base-joint', choices=('floating', 'planar'), default=None,
                        help='free base joint when the URDF has no world joint '
                             '(default: floating)')
    parser.add_argument('--gravity', type=float, nargs=3, default=None,
                        metavar=('GX', 'GY', 'GZ'),
                        help='gravity in the world frame, m/s^2 (planar base only, along z)')


def load_robot_from_args(args: argparse.Namespace):
    """Return the robot model the arguments describe."""
    import numpy as np

    from reduced_dynamics.robot.model import load_robot
    from reduced_dynamics.robot.xacro_file import parse_xacro_args
    gravity = None if args.gravity is None else np.array(args.gravity)
    return load_robot(args.urdf, args.base_joint, gravity,
                      parse_xacro_args(getattr(args, 'xacro_arg', None)))


def _validate(args: argparse.Namespace) -> int:
    from reduced_dynamics.robot.symmetry import detect_symmetries
    from reduced_dynamics.validation import (format_second_stage_table, format_table,
                                             second_stage_table, validation_table)
    robot = load_robot_from_args(args)
    print(f'robot {robot.model.name}: base {robot.group.name} ({robot.base_link}), '
          f'{robot.m} shape joints, {args.duration:g} s per run, DOP853 rtol {args.rtol:g}')
    rows = validation_table(robot, args.duration, args.seed, rtol=args.rtol)
    print(format_table(rows))
    worst = max(max(r.shape_error for r in rows), max(r.pose_error for r in rows) / 10.0,
                max(r.pi_error for r in rows))
    ok = worst <= args.tolerance
    print(f'{"PASS" if ok else "FAIL"}: reduced model agrees with full dynamics '
          f'(shape <= {args.tolerance:g} rad, pose <= {10 * args.tolerance:g}, '
          f'pi <= {args.tolerance:g} relative)')
    cyclic = detect_symmetries(robot).cyclic_joints
    if cyclic:
        print(f'\nsecond stage (Theorem 57) by the cyclic joints {", ".join(cyclic)}: '
              'shape error on the kept joints, the same for stage one, cyclic angles, '
              'base pose, theta against the torque impulse and against full dynamics')
        second = second_stage_table(robot, cyclic, args.duration, args.seed, rtol=args.rtol)
        print(format_second_stage_table(second))
        worst = max(max(max(r.shape_error, r.cyclic_angle_error, r.pose_error / 10.0,
                            r.theta_torque_error, r.theta_full_error) for r in second), 0.0)
        second_ok = worst <= args.tolerance
        print(f'{"PASS" if second_ok else "FAIL"}: second-stage model agrees with full '
              f'dynamics (shape and wheel angles <= {args.tolerance:g} rad, theta <= '
              f'{args.tolerance:g} relative)')
        ok = ok and second_ok
    return 0 if ok else 1


def _symmetries(args: argparse.Namespace) -> int:
    from reduced_dynamics.robot.symmetry import detect_symmetries
    robot = load_robot_from_args(args)
    report = detect_symmetries(robot, args.rtol, args.configurations, args.seed)
    print(report.format())
    return 0


#: Subcommands defined in their own modules: name -> (module, one-line help). Only
#: the module of the subcommand being run is imported (``--help`` imports none).
LAZY_COMMANDS = {
    'simulate': ('simulator', 'simulate full dynamics and write a rosbag2 (MCAP) bag'),
    'replay': ('replay', 'run the estimator over a recorded bag'),
    'replay-many': ('fleet', 'replay many bags (a test campaign) on a process pool, Ray '
                             'or Dask; one table of all bags'),
    'predict': ('predict', 'base motion for a planned joint trajectory (YAML/CSV file)'),
    'tune': ('tune', 'estimate the filter\'s noise parameters from a bag (maximum '
                     'innovation likelihood)'),
    'bench': ('bench', 'benchmark the estimator, prediction, replay and scaling'),
    'identify': ('identify', 'identify a grasped payload\'s inertial parameters from a bag'),
    'correlate': ('correlate', 'correlation and gain of the wrench estimate with a thruster '
                               'command, per axis'),
    'play': ('player_node', 'publish a bag over DDS with rclpy, as ros2 bag play does'),
    'compile': ('compile_kernels', 'compile the kernels ahead of the first run, on every '
                                   'core (once after an install; later runs load them)'),
}


def build_parser(command: Optional[str] = '') -> argparse.ArgumentParser:
    """
    Return the argument parser.

    ``command``: the subcommand whose full options are wanted (its module is
    imported); ``''``: every subcommand in full; None: none (the others appear
    with their one-line help only, enough for ``reduced-dynamics --help``).
    """
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
    validate.add_argument('--rtol', type=float, default=1e-12,
                          help='DOP853 relative (and absolute) tolerance of every run')
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
    for name, (module, summary) in LAZY_COMMANDS.items():
        if command == '' or command == name:
            imported = importlib.import_module(f'reduced_dynamics.{module}')
            imported.register_command(commands)
        else:
            commands.add_parser(name, help=summary)
    return parser


def _command_of(argv: Sequence[str]) -> Optional[str]:
    """Return the subcommand named in ``argv`` (None: none, e.g. ``--help`` alone)."""
    for arg in argv:
        if not arg.startswith('-'):
            return arg
        if arg in ('-h', '--help'):
            return None
    return None


#: While a subcommand runs, SIGINT and SIGTERM raise KeyboardInterrupt (its finally clauses
#: stop child processes); ``received`` tells the stop from an error (issue 24.2).
_INTERRUPTS = stop_signals.Interrupts()


def _stopped_line(signum: int) -> str:
    return f'reduced-dynamics: stopped by {signal.Signals(signum).name}'


def main(argv: Optional[Sequence[str]] = None, *, program: bool = False) -> int:
    """
    Entry point of ``reduced-dynamics``; in-process callers get their handlers back.

    ``program``: this is the executable (:func:`program`): once the command is done a
    late signal no longer changes its exit code (:func:`stop_signals.finish`).
    """
    # A signal in the subcommand's imports (pinocchio, numba: seconds): one line, exit
    # 128 + its number, the shell's convention (an interrupted run is no success).
    previous = stop_signals.current_handlers()  # main() is also called in-process
    stop_signals.exit_at_once(_stopped_line, lambda signum: 128 + signum)
    _INTERRUPTS.received = None
    code: Optional[int] = None
    try:
        code = _main_handled(argv)
        return code
    finally:
        if program and code is not None:
            stop_signals.finish(code)
        else:
            stop_signals.restore(previous)


def program() -> int:
    """Be the process's program: the ``reduced-dynamics`` console script."""
    return main(program=True)


def _main_handled(argv: Optional[Sequence[str]]) -> int:
    """Run :func:`_main`; a stop signal and a closed stdout become exit codes."""
    try:
        code = _main(argv)
        sys.stdout.flush()  # inside the try: a closed pipe must surface here
        return code
    except BrokenPipeError:
        # The reader went away (``... | head -2``): the Python documentation's recipe
        # (signal module, "Note on SIGPIPE"): point stdout at devnull so the flush at
        # exit does not raise again, and exit 1 without a traceback.
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 1
    except BaseException:
        # Whatever the KeyboardInterrupt became (numba's dispatcher turns it into a
        # SystemError): a stop, not an error.
        if _INTERRUPTS.received is None:
            raise
        print(_stopped_line(_INTERRUPTS.received), file=sys.stderr)
        return 128 + _INTERRUPTS.received


def _main(argv: Optional[Sequence[str]]) -> int:
    if argv is None:
        argv = sys.argv[1:]
    parser = build_parser(_command_of(argv))
    args = parser.parse_args(argv)
    from reduced_dynamics.blas_threads import limit_blas_threads
    from reduced_dynamics.robot.model import ModelError
    _INTERRUPTS.install()  # imports done: the subcommand's cleanup runs on a signal
    try:
        # One BLAS thread for the process (every subcommand): outputs and CPU per call
        # independent of the machine's core count (reduced_dynamics.blas_threads).
        limit_blas_threads()
        return int(args.func(args) or 0)
    except (ModelError, FileNotFoundError, ValueError) as error:
        print(f'reduced-dynamics {args.command}: error: {error}', file=sys.stderr)
        return 2


if __name__ == '__main__':
    sys.exit(program())
