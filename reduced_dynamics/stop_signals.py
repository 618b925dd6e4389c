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
SIGINT and SIGTERM in the executables: one line on stderr, never a traceback (issue 24.2).

Two regimes. :func:`exit_at_once` is for start-up: the heavy imports (numpy,
numba, pinocchio, rclpy) take seconds, and a ``KeyboardInterrupt`` raised inside
them ends in a long traceback, or in a ``SystemError`` when it lands in numba's
dispatcher; SIGTERM's default kills the process. There nothing needs cleaning
up, so the handler writes its line and calls ``os._exit``. :class:`Interrupts`
is for a command at work: either signal raises ``KeyboardInterrupt`` where the
program is, so ``finally`` clauses stop child processes and close files, and
remembers which signal came, so the caller can tell it from an error whatever
exception it was turned into.

A third moment is the end: once a program's ``main`` has returned, :func:`finish`
keeps a late signal from changing its result. Two ways it used to (measured: 7
and 1-3 of 40 SIGINTs sent 0.3-3 s into a short replay, the second under load):
the interpreter's finalisation puts every handler back to the kernel's default
(CPython ``_PySignal_Fini``) and then tears the modules down, slowly with
pinocchio and numba loaded, so a signal landing there killed the process (exit
-2, nothing printed); and a ``KeyboardInterrupt`` that once passed through C code
running Python (``PyRun_*``) sets CPython's sticky "unhandled KeyboardInterrupt"
flag even when our own code then catches it, and the interpreter kills itself
with SIGINT after finalising (exit -2 after "stopped by SIGINT"). So after the
exit handlers a finished program ends with ``os._exit(code)``.

A signal can also land in Python code that C code called through a ctypes callback:
llvmlite's object-cache hooks run while numba compiles a kernel. ctypes prints an
exception raised there as "Exception ignored" and drops it, so the stop was lost and
the program went on to exit 0 with a traceback on stderr (seen once in CI, SIGTERM 1 s
into a replay). :class:`Interrupts` therefore does not raise inside such code: it sends
the signal again a moment later, until it lands outside.

This module imports only the standard library's ``atexit``, ``os``, ``signal``,
``sys``, ``threading`` and ``typing``: entry points import it before anything heavy.
"""

import atexit
import os
import signal
import sys
import threading
from typing import Any, Callable, Optional

#: The signals that stop a program (what Ctrl-C, ``timeout``, ``ros2 launch`` send).
SIGNALS = (signal.SIGINT, signal.SIGTERM)


def exit_at_once(message: Optional[Callable[[int], str]], code: Callable[[int], int]) -> None:
    """Make SIGINT and SIGTERM write ``message(signum)`` and exit ``code(signum)`` at once."""
    owner = os.getpid()

    def handler(signum: int, frame: Any) -> None:
        if os.getpid() != owner:  # a forked child (multiprocessing 'fork'): as before
            _default(signum)
            return
        # os._exit: no exception to unwind through a half-done import (no traceback, no
        # library's except clause to swallow it); stderr is the one stream to flush.
        try:
            if message is not None:
                sys.stderr.write(message(signum) + '\n')
            sys.stderr.flush()
        finally:
            os._exit(code(signum))
    _install(handler)


def finish(code: int) -> int:
    """
    Make the process end with ``code`` whatever signal comes from now on; return it.

    A signal before the interpreter's exit handlers are done (joining threads,
    flushing logs) exits at once with ``code``; after them the process exits with
    ``code`` without the rest of finalisation (module teardown: the program's files
    are closed by then). Call it in the program's entry point only, after its work.
    """
    global _FINISHED_WITH
    _FINISHED_WITH = code
    exit_at_once(None, lambda signum: code)
    return code


#: The code :func:`finish` was given (None: the program is not finishing through it).
_FINISHED_WITH: Optional[int] = None


def _exit_if_finished() -> None:
    if _FINISHED_WITH is None:  # an in-process caller, a test: normal finalisation
        return
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # closed, or a reader gone: nothing left to save
            pass
    os._exit(_FINISHED_WITH)


# Registered at import, before any library's handler: atexit runs handlers last-in
# first-out, so this one runs after all of them.
atexit.register(_exit_if_finished)


def _default(signum: int) -> None:
    """Do what the signal does by default in Python: KeyboardInterrupt, or die of it."""
    if signum == signal.SIGINT:
        raise KeyboardInterrupt
    signal.signal(signum, signal.SIG_DFL)
    os.kill(os.getpid(), signum)


def _install(handler: Callable[[int, Any], None]) -> None:
    # Python lets the main thread alone set handlers; elsewhere (a command run in a
    # thread) the process's own handling stays.
    if threading.current_thread() is threading.main_thread():
        for sig in SIGNALS:
            signal.signal(sig, handler)


def current_handlers() -> dict:
    """Return the handlers of :data:`SIGNALS` now (for :func:`restore`)."""
    return {sig: signal.getsignal(sig) for sig in SIGNALS}


def restore(handlers: dict) -> None:
    """Put back handlers :func:`current_handlers` returned."""
    if threading.current_thread() is threading.main_thread():
        for sig, handler in handlers.items():
            if handler is not None:  # None: set outside Python, cannot be put back
                signal.signal(sig, handler)


#: Path parts of the modules whose Python code C calls through ctypes callbacks, where an
#: exception is printed and dropped (llvmlite's object-cache hooks, its lock callbacks).
CALLBACK_MODULES = (os.sep + 'llvmlite' + os.sep,)

#: Seconds before a signal that landed in such code is sent again.
REDELIVERY_S = 0.01


def in_callback_code(frame: Any) -> bool:
    """Return True if ``frame`` or a caller of it runs in :data:`CALLBACK_MODULES`."""
    while frame is not None:
        name = frame.f_code.co_filename
        if any(part in name for part in CALLBACK_MODULES):
            return True
        frame = frame.f_back
    return False


class Interrupts:
    """SIGINT and SIGTERM raise KeyboardInterrupt; :attr:`received` says which came."""

    def __init__(self) -> None:
        """Handle nothing yet: :meth:`install` does."""
        self.received: Optional[signal.Signals] = None
        self._owner = os.getpid()

    def install(self) -> None:
        """Handle both signals from now on."""
        self._owner = os.getpid()
        _install(self._raise)

    def _raise(self, signum: int, frame: Any) -> None:
        if os.getpid() != self._owner:  # a forked child: as before
            _default(signum)
            return
        self.received = signal.Signals(signum)
        if in_callback_code(frame):
            # Raised here, ctypes would print and drop it: try again once out of it. To the
            # main thread: sent to the process, it may reach the timer's thread and leave
            # a blocking call of the main thread (a sleep, a wait) uninterrupted.
            timer = threading.Timer(REDELIVERY_S, signal.pthread_kill,
                                    (threading.main_thread().ident, signum))
            timer.daemon = True
            timer.start()
            return
        raise KeyboardInterrupt(self.received.name)
