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
The floor under the update and replay figures: what a sample costs without Python.

Issue 19's targets (streaming <= 20 x ``crba``, batched <= 10 x, replay >= 0.5 of
``rosbags`` decoding) are measured on the whole estimator. This section times the
parts no restructuring of the per-row Python can remove, in steady state (the
step test's bank full), each as a multiple of one ``crba``:

* ``mechanics``: the kernel's per-row inputs of the filter (``crba`` and the
  chunk algebra: I^-1, A qbar_dot, A Sigma A^T, pbar), one row at a time (the
  streaming path) and per row of a 1 000-row chunk (batched);
* ``filter step``: ``kernels.propagate_update`` (propagation + iterated update of
  the 18-state filter, structured: docs/structured_step.md) run in a compiled loop,
  i.e. without the interpreter, the same called from Python, and a row's whole
  compiled call (``step_row.filter_step``, with the step test's share) called from
  Python as the filter calls it;
* ``step test``: the wrench-step test's compiled kernels (``absorb`` +
  ``evaluate`` over a full bank of onsets, one call: ``absorb_evaluate``), in a
  compiled loop;
* ``smoother step``: one step of the smoother's backward pass
  (``core/smoother.backward_step``, structured), on two recorded steps, in a
  compiled loop (a smoothed replay pays it once per filter step, after the bag is
  read).

The dense steps these replaced (``core/reference.py``, ``core/smoother_reference.py``)
are no longer timed here: they are plain numpy test oracles now, not compiled (their
compilation cost every fresh CI run ~80 s of CPU); their side-by-side figures are in
docs/structured_step.md and docs/performance.md.

Their sum is the floor of a sample of the current algorithm; with the rosbags
decode of the same two messages it bounds the replay ratio.
"""

from __future__ import annotations

import time
from typing import Any, Callable

from numba import njit
import numpy as np

from reduced_dynamics.estimator import step_kernels
from reduced_dynamics.estimator.core import kernels, smoother

#: Steady state: the step test's bank is full after 2 s of 1 kHz samples.
WARMUP_SAMPLES = 2100


def _capture(robot) -> dict:
    """Run the estimator to steady state; return the arguments of its compiled calls."""
    from reduced_dynamics.bench import update_samples
    from reduced_dynamics.estimator import step_row
    from reduced_dynamics.estimator.config import EstimatorConfig
    from reduced_dynamics.estimator.pipeline import Estimator
    joints, bases = update_samples(robot, WARMUP_SAMPLES + 2)
    # Without the multi-scale event test (not part of the floor): the bench's motion is not
    # momentum-consistent, and locating the lasting wrench it sees took 97 % of this run's
    # CPU; the captured arguments are the same bit for bit (measured).
    estimator = Estimator(robot, EstimatorConfig(prediction_rate=0.0, smoothing_lag=0.0,
                                                 event_false_alarm_rate=0.0))
    messages = [m for pair in zip(joints, bases) for m in pair]
    estimator.add_samples(messages[:2 * WARMUP_SAMPLES])
    captured: dict = {}
    originals = {(kernels, 'propagate_update'): kernels.propagate_update,
                 (step_kernels, 'absorb_evaluate'): step_kernels.absorb_evaluate}

    def recorder(name: str, function: Callable) -> Callable:
        def record(*args: Any) -> Any:
            # Copies: absorb_evaluate works in place on the bank's arrays.
            captured[name] = tuple(a.copy() if isinstance(a, np.ndarray) else a
                                   for a in args)
            return function(*args)
        return record

    def separate(*args: Any) -> Any:
        # The filter's row step (step_row.filter_step) makes both calls inside one
        # compiled call; when it raises, the filter makes them from Python (the same
        # bits, test_step_row.py), where they are captured. Its own arguments are kept
        # for the row-call figure.
        captured['filter_step'] = tuple(a.copy() if isinstance(a, np.ndarray) else a
                                        for a in args)
        raise np.linalg.LinAlgError('captured as separate calls')

    for (module, name), function in originals.items():
        setattr(module, name, recorder(name, function))
    row_step = step_row.filter_step
    step_row.filter_step = separate
    try:
        estimator.add_samples(messages[2 * WARMUP_SAMPLES:])
    finally:
        for (module, name), function in originals.items():
            setattr(module, name, function)
        step_row.filter_step = row_step
    captured['qbar'] = np.array([j.position for j in joints[-1000:]])
    captured['qbar_dot'] = np.array([j.velocity for j in joints[-1000:]])
    captured['bases'] = np.array([np.r_[b.position, b.orientation_xyzw, b.twist_linear,
                                        b.twist_angular] for b in bases[-1000:]])
    captured['variance'] = estimator.config.joint_velocity_noise ** 2
    captured['kernel'] = estimator.kernel
    return captured


def _smoother_args(robot) -> tuple:
    """Return the arguments of a backward step: two recorded steps after 0.5 s at 1 kHz."""
    from reduced_dynamics.bench import update_samples
    from reduced_dynamics.estimator.config import EstimatorConfig
    from reduced_dynamics.estimator.pipeline import Estimator
    joints, bases = update_samples(robot, 500)
    estimator = Estimator(robot, EstimatorConfig(prediction_rate=0.0, smoothing_lag=0.0,
                                                 event_false_alarm_rate=0.0))
    estimator.enable_smoothing()
    estimator.add_samples([m for pair in zip(joints, bases) for m in pair])
    store, group = estimator.step_store, robot.group
    before, after = store[len(store) - 2], store[len(store) - 1]
    estimator.smoother_files.close()
    return (before.pose, before.x, before.p, after.transition, after.pose_pred, after.x_pred,
            after.p_pred, after.pose, after.x, after.p,
            np.ascontiguousarray(group.algebra_basis), np.ascontiguousarray(group.algebra_pinv),
            group.is_whole)


@njit(cache=True)
def _loop_propagate_update(count: int, args: tuple) -> int:
    for _ in range(count):
        kernels.propagate_update(*args)
    return count


@njit(cache=True)
def _loop_absorb_evaluate(count: int, args: tuple) -> int:
    for _ in range(count):
        step_kernels.absorb_evaluate(*args)
    return count


@njit(cache=True)
def _loop_backward_step(count: int, args: tuple) -> int:
    for _ in range(count):
        smoother.backward_step(*args)
    return count


#: A compiled ``loop(count, args)`` per timed kernel. One function each, in numba's disk
#: cache: a loop closed over the kernel (not cacheable) was compiled in every process that
#: ran the floor, ~34 s of CPU (measured, five loops then), twice in a CI run. Like every
#: cached kernel calling another module's, a loop keeps the kernel's code of when it was
#: compiled: after changing a kernel, clear the cache (docs/filter_row.md).
_LOOPS: dict = {kernels.propagate_update: _loop_propagate_update,
                step_kernels.absorb_evaluate: _loop_absorb_evaluate,
                smoother.backward_step: _loop_backward_step}


def _seconds_per_call(run: Callable[[], Any], calls: int) -> float:
    start = time.perf_counter()
    for _ in range(calls):
        run()
    return (time.perf_counter() - start) / calls


def _looped(function: Callable, args: tuple, calls: int) -> float:
    loop = _LOOPS[function]
    loop(1, args)  # compiles or loads from the cache
    start = time.perf_counter()
    loop(calls, args)
    return (time.perf_counter() - start) / calls


def measure_floor(robot, calls: int = 2000) -> dict:
    """
    Return seconds per sample of each floor part (see the module docstring), and crba's.

    Keys: ``crba``, ``mechanics_streaming``, ``mechanics_batched``,
    ``filter_step_compiled``, ``filter_step_called``,
    ``row_step_called`` (``step_row.filter_step``, a row's one compiled call),
    ``step_test_compiled``, ``smoother_step``,
    ``floor_streaming`` and ``floor_batched`` (the sums with the compiled parts).
    """
    from reduced_dynamics.bench import time_crba
    from reduced_dynamics.estimator import step_row
    captured = _capture(robot)
    kernel, variance = captured['kernel'], captured['variance']
    qbar, qbar_dot, bases = captured['qbar'], captured['qbar_dot'], captured['bases']
    out = {'crba': time_crba(robot, 4 * calls)}
    one = (qbar[:1], qbar_dot[:1], bases[:1], variance)
    out['mechanics_streaming'] = _seconds_per_call(lambda: kernel.filter_inputs(*one), calls)
    chunks = max(1, calls // len(qbar))
    out['mechanics_batched'] = _seconds_per_call(
        lambda: kernel.filter_inputs(qbar, qbar_dot, bases, variance), chunks) / len(qbar)
    step = captured['propagate_update']
    out['filter_step_compiled'] = _looped(kernels.propagate_update, step, calls)
    out['filter_step_called'] = _seconds_per_call(lambda: kernels.propagate_update(*step),
                                                  calls)
    # The whole compiled call of a row (the filter step and the step test's share) as
    # the filter makes it, dispatch included; repeated on one state (the bank's arrays
    # change in place, as in step_test_compiled).
    row = captured['filter_step']
    out['row_step_called'] = _seconds_per_call(lambda: step_row.filter_step(*row), calls)
    out['step_test_compiled'] = _looped(step_kernels.absorb_evaluate,
                                        captured['absorb_evaluate'], calls)
    backward = _smoother_args(robot)
    out['smoother_step'] = _looped(smoother.backward_step, backward, calls)
    compiled = out['filter_step_compiled'] + out['step_test_compiled']
    out['floor_streaming'] = out['mechanics_streaming'] + compiled
    out['floor_batched'] = out['mechanics_batched'] + compiled
    return out


#: Rows of :func:`bench_floor`: (key, figure name, note).
FLOOR_ROWS = (
    ('floor_streaming', 'update floor, streaming: mechanics + compiled filter step + step test',
     'no interpreter in the filter: filter_inputs of one row, kernels.propagate_update and '
     'the step-test kernels in compiled loops (bench_floor.py)'),
    ('floor_batched', 'update floor, batched: the same, mechanics per row of 1 000',
     'as above, filter_inputs over a 1 000-row chunk'),
    ('filter_step_compiled', 'update floor: compiled filter step alone',
     'kernels.propagate_update (propagation + iterated update, structured), compiled loop'),
    ('filter_step_called', 'update floor: compiled filter step called from Python',
     'the same call with numba dispatch (arguments in, 18 results out)'),
    ('row_step_called', 'update floor: a row\'s compiled call from Python (filter + step test)',
     'step_row.filter_step as the filter calls it: propagate_update, the step test\'s '
     'propagate and absorb_evaluate, numba dispatch (52 arguments in, 33 results out)'),
    ('step_test_compiled', 'update floor: step-test kernels (absorb + evaluate)',
     'a full bank of onsets, compiled loop'),
    ('mechanics_streaming', 'update floor: mechanics of one row (crba + chunk algebra)',
     'UpdateKernel.filter_inputs, one row'),
    ('mechanics_batched', 'update floor: mechanics per row of a 1 000-row chunk',
     'UpdateKernel.filter_inputs, 1 000 rows'),
    ('smoother_step', 'smoother backward step (structured), per filter step',
     'core/smoother.backward_step on two recorded steps, compiled loop (not in the floor)'))


def bench_floor(report: Any, robot, settings: Any) -> None:
    """Add the floor rows (section update), each against ``crba`` timed in the same repeat."""
    from reduced_dynamics.bench import make_figure
    runs = [measure_floor(robot) for _ in range(settings.repeats)]
    crbas = [run['crba'] for run in runs]
    targets = {'floor_streaming': 20.0, 'floor_batched': 10.0}
    for key, name, note in FLOOR_ROWS:
        values = [run[key] for run in runs]
        bound = targets.get(key)
        report.add(make_figure(
            'update', name, 'us/sample', [1e6 * v for v in values], 'crba',
            [1e6 * c for c in crbas], [v / c for v, c in zip(values, crbas)],
            '' if bound is None else f'ratio <= {bound:g} (reachable?)',
            None if bound is None else (lambda r, bound=bound: r <= bound), note))
