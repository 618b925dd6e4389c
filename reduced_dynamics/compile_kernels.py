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
Compile the kernels ahead of the first run, on every core: ``reduced-dynamics compile``.

numba compiles a kernel at its first call and keeps the machine code in its disk cache
beside the module. After an install or an upgrade the first node start or replay
compiles them all, for minutes, in one process on one core. This command runs the node's
warm-up in parts (:data:`~reduced_dynamics.estimator.core.warmup.PARTS`, each a set of
kernels of its own) and the prediction's kernels
(:func:`reduced_dynamics.reduction.lean_field.warm_up`) in ``jobs`` processes at once,
the costliest first; every later process loads them from the cache. Run again, it only
loads them (seconds) and says that nothing was compiled.
"""

import argparse
from concurrent.futures import as_completed, ProcessPoolExecutor
import multiprocessing
import os
import time
from typing import Any, Callable, Iterable, NamedTuple, Optional

#: CPU seconds each part took to compile alone from an empty cache (numba's LLVM level 1,
#: this project's 2-core VM under load; docs/performance.md, "Stop 42").
#: Only their order matters: the longest part starts first, so it ends no later than
#: needed.
PART_COST_S = {'filter': 127.3, 'event tests': 52.9, 'inputs': 21.6, 'prediction': 19.8,
               'step test': 11.2}


class PartResult(NamedTuple):
    """What compiling one part took: its name, CPU seconds, kernels compiled (0: loaded)."""

    name: str
    cpu_s: float
    compiled: int


def top_level_compiles(on_compile: Callable[[Any, Any, float], None]) -> Any:
    """
    Return a numba listener calling ``on_compile(dispatcher, args, cpu_s)`` per top-level compile.

    A kernel's callees compile inside its own ``numba:compile`` event: only the
    outermost event is reported, with the CPU seconds it took, callees included.
    (Install it with ``numba.core.event.install_listener('numba:compile', ...)``.)
    """
    from numba.core import event
    started: list[float] = []

    class _TopLevel(event.Listener):
        def on_start(self, ev: event.Event) -> None:
            started.append(time.process_time())

        def on_end(self, ev: event.Event) -> None:
            cpu_s = time.process_time() - started.pop()
            if not started:
                on_compile(ev.data.get('dispatcher'), ev.data.get('args'), cpu_s)

    return _TopLevel()


def run_part(name: str) -> PartResult:
    """Run one part's kernels in this process; count the kernels numba compiled for it."""
    from numba.core import event
    compiled = []
    listener = top_level_compiles(lambda dispatcher, args, cpu_s: compiled.append(dispatcher))
    started = time.process_time()
    with event.install_listener('numba:compile', listener):
        if name == 'prediction':
            from reduced_dynamics.reduction.lean_field import warm_up as warm_prediction
            warm_prediction()
        else:
            from reduced_dynamics.estimator.core.warmup import warm_up
            warm_up([name])
    return PartResult(name, time.process_time() - started, len(compiled))


def _start_worker() -> None:
    """Start a pool worker as the CLI starts: one BLAS thread (an entry point of its own)."""
    from reduced_dynamics.blas_threads import limit_blas_threads
    limit_blas_threads()


def part_names() -> list[str]:
    """Return every part, the costliest first."""
    from reduced_dynamics.estimator.core.warmup import PARTS
    names = list(PARTS) + ['prediction']
    return sorted(names, key=lambda name: -PART_COST_S.get(name, 0.0))


def default_jobs() -> int:
    """Return the CPUs this process may run on."""
    return len(os.sched_getaffinity(0)) if hasattr(os, 'sched_getaffinity') \
        else os.cpu_count() or 1


def compile_kernels(jobs: int, parts: Optional[Iterable[str]] = None) -> list[PartResult]:
    """
    Compile (or load) the kernels of ``parts`` (default: all) in ``jobs`` processes.

    ``jobs`` 1: in this process, one part after the other. Otherwise each part runs in a
    process of a pool (spawned: no state inherited from this one), the costliest first.
    Results come in the order the parts finished. A part that raises raises here.
    """
    names = part_names() if parts is None else list(parts)
    known = set(part_names())
    unknown = [name for name in names if name not in known]
    if unknown:
        raise ValueError(f'unknown part(s) {", ".join(unknown)}; the parts are '
                         f'{", ".join(sorted(known))}')
    if jobs <= 1 or len(names) <= 1:
        return [run_part(name) for name in names]
    results = []
    context = multiprocessing.get_context('spawn')
    with ProcessPoolExecutor(max_workers=min(jobs, len(names)), mp_context=context,
                             initializer=_start_worker) as pool:
        futures = [pool.submit(run_part, name) for name in names]
        for future in as_completed(futures):
            results.append(future.result())
    return results


def _run(args: argparse.Namespace) -> int:
    jobs = args.jobs if args.jobs > 0 else default_jobs()
    started = time.perf_counter()
    try:
        results = compile_kernels(jobs, args.parts or None)
    except ValueError as error:
        print(f'compile: {error}')
        return 2
    for result in results:
        what = f'{result.compiled} kernels compiled' if result.compiled else \
            'loaded from the cache'
        print(f'{result.name}: {result.cpu_s:.1f} s CPU, {what}')
    total = sum(result.compiled for result in results)
    processes = min(jobs, len(results)) if jobs > 1 else 1
    print(f'compile: {len(results)} parts in {time.perf_counter() - started:.1f} s '
          f'({processes} process{"es" if processes > 1 else ""}), {total} kernels compiled')
    return 0


def register_command(commands: Any) -> None:
    """Add the ``compile`` subcommand."""
    parser = commands.add_parser(
        'compile', help='compile the kernels ahead of the first run, on every core '
                        '(once after an install; later runs load them)')
    parser.add_argument('--jobs', '-j', type=int, default=0,
                        help='processes at once (default 0: one per CPU)')
    parser.add_argument('--parts', nargs='+', metavar='PART',
                        help='only these parts (filter, "step test", "event tests", '
                             'inputs, prediction)')
    parser.set_defaults(func=_run)
