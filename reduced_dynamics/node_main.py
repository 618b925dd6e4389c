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
Entry points of the node executables: SIGINT/SIGTERM handling first, the heavy imports after.

Importing :mod:`reduced_dynamics.node` (rclpy, pinocchio, numba, numpy, the
estimator) takes about 2 s of CPU, 10-25 s of wall time on a loaded machine
(issue 24.2). A signal in that time used to end the process with a
``KeyboardInterrupt`` traceback (SIGINT) or kill it (SIGTERM, exit -15). This
module imports only the standard library and :mod:`reduced_dynamics.stop_signals`: its
handlers are in place before anything heavy loads, and a signal then ends the
process at once with exit 0 and one line on stderr. ``node.main()`` installs the
node's own handling (:class:`reduced_dynamics.node._StopOnSignal`: the signal
asks the spin loop to end, the node is destroyed, rclpy shut down) before
``rclpy.init``; from then on that takes over. A signal while the process
tears down after ``node.main()`` returned ends it at once with main's code, or
is ignored once the interpreter finalises (:func:`stop_signals.finish`).

Not covered: the interpreter's own start before this module's first line runs
(0.1-0.2 s of CPU here, most of it the environment's ``.pth`` files).
"""

import signal
import sys
from typing import Optional, Sequence

from reduced_dynamics.stop_signals import exit_at_once, finish


def start_up_message(program: str, signum: int) -> str:
    """Return the one line a signal during start-up prints."""
    return f'{program}: {signal.Signals(signum).name} during start-up: stopped (exit 0)'


def stop_on_signal_during_start_up(program: str) -> None:
    """Make SIGINT and SIGTERM end the process with exit 0 and one line on stderr."""
    exit_at_once(lambda signum: start_up_message(program, signum), lambda signum: 0)


def run(program: str, lifecycle: bool, args: Optional[Sequence[str]] = None) -> int:
    """Install the start-up handlers, import the node module and run its ``main``."""
    stop_on_signal_during_start_up(program)
    from reduced_dynamics import node  # the heavy imports, signals handled
    code = node.main(args, lifecycle=lifecycle)
    # Tearing down (rclpy, numba and the executor's threads): a signal ends it quietly.
    return finish(code)


def main(args: Optional[Sequence[str]] = None) -> int:
    """Run the plain node: the ``reduced_dynamics_node`` executable."""
    return run('reduced_dynamics_node', False, args)


def lifecycle_main(args: Optional[Sequence[str]] = None) -> int:
    """Run the managed (lifecycle) node: the ``reduced_dynamics_lifecycle_node`` executable."""
    return run('reduced_dynamics_lifecycle_node', True, args)


if __name__ == '__main__':
    sys.exit(main())
