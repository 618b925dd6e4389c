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
Run every compiled filter kernel once (load or compile them): ``warm_up()``.

numba compiles a kernel at its first call and caches the machine code on disk
(``cache=True``); a process that calls :func:`warm_up` at start-up (the node before
rclpy starts) pays that load before the first message instead of in it. The
bench times it in a fresh process (``reduced-dynamics bench``, section update).
:func:`compiling_notice` around it (or, in replay, around the first chunk) says so when
that takes long: the first run after an install compiles for minutes, in silence otherwise.
"""

import contextlib
import threading
from typing import Callable, Iterable, Iterator, TYPE_CHECKING

import numpy as np
import pinocchio as pin

from reduced_dynamics.estimator.core import kernels
from reduced_dynamics.estimator.core.state import Command, Linearisation, NoiseModel
from reduced_dynamics.geometry.lie_group import BaseGroup, SUBGROUPS

if TYPE_CHECKING:  # (imported at run time by warm_up: the filter imports these kernels)
    from reduced_dynamics.estimator.filter import MomentumFilter


#: Seconds after which :func:`compiling_notice` says what is going on: loading the
#: cached kernels takes 1.4-2.4 s of CPU here (more under load); compiling them
#: after an install ~3 min (README).
NOTICE_AFTER_S = 10.0
#: What it says then.
COMPILING_NOTICE = ('the compiled filter kernels are still loading: the first run after '
                    'an install or an upgrade compiles them (minutes of CPU, once; later '
                    'runs load them from the cache in seconds; `reduced-dynamics compile` '
                    'does it ahead, on every core)')


@contextlib.contextmanager
def compiling_notice(say: Callable[[str], None],
                     after_s: float = NOTICE_AFTER_S) -> Iterator[threading.Timer]:
    """
    Say ``COMPILING_NOTICE`` (once) if the block still runs after ``after_s`` seconds.

    Yields the timer: cancelling it early (replay's first chunk) keeps it quiet too.
    """
    timer = threading.Timer(after_s, say, (COMPILING_NOTICE,))
    timer.daemon = True  # never keeps a process alive
    timer.start()
    try:
        yield timer
    finally:
        timer.cancel()


def _warm_backward_pass(group: BaseGroup, flt: 'MomentumFilter', command: bool) -> None:
    """Run the smoother's backward pass over ``flt``'s steps as replay runs it (its store)."""
    from reduced_dynamics.estimator.smoother import SmootherFiles, smooth_rows, StepStore
    try:
        files = SmootherFiles()
    except OSError:
        return  # no writable temporary directory (a node's read-only disk): replay compiles
    try:
        store = StepStore(files, group.dim, flt.dim, command)
        for step in flt.steps:
            store.append(step)
        smooth_rows(group, store, files, flt._form_rows).close()
        store.close()
    finally:
        files.close()


def _warm_fixed_lag(group: BaseGroup, flt: 'MomentumFilter', command: bool) -> None:
    """Feed ``flt``'s steps to a fixed-lag smoother with a lag shorter than them (passes)."""
    from reduced_dynamics.estimator.fixed_lag import FixedLagSmoother

    def wrenches(covectors: np.ndarray) -> np.ndarray:
        return group.dual_to_wrench(covectors.T).T  # each row lifted (K x n -> K x 6)

    lagged = FixedLagSmoother(group, 0.005, flt.dim, command, wrenches, 'world')
    for step in flt.steps:
        lagged.append(step)
    lagged.flush()


def _warm_filters() -> None:
    """Run the filter's step, update and smoothers: SE(3) and a subgroup, a command."""
    from reduced_dynamics.estimator.filter import MomentumFilter
    for name, command in (('SE(3)', False), ('SE(2)', False), ('SE(2)', True)):
        group = SUBGROUPS[name]
        n = group.dim
        locked = np.diag(np.linspace(2.0, 3.0, n))
        lin = Linearisation(locked, np.linalg.inv(locked), np.full(n, 0.01),
                            np.eye(n) * 1e-6)
        flt = MomentumFilter(group, NoiseModel(), 1e-6, record=True, command=command,
                             step_significance=0.0 if command else 1e-6)
        held = Command(np.zeros(n), np.zeros(n)) if command else None
        for k in range(4):
            pose = group.exp(np.full(n, 1e-3 * k))
            twist = None if k % 2 else np.full(n, 1e-3)
            flt.step(k * 10_000_000, lin, pose, twist, held)
        # A row without a measurement (joint states between odometry samples).
        flt.step(45_000_000, lin, None, None, held)
        flt.wrench_significance()
        _warm_backward_pass(group, flt, command)
        # The node's fixed-lag smoothing (its default smoothing_lag), and the twist a
        # pose measurement's stamp noise averages (the filter's Python path).
        _warm_fixed_lag(group, flt, command)
        flt.twist(pin.SE3.Identity(), flt.x[:n], lin)
        flt._transition(pin.SE3.Identity(), flt.x, lin, 0.01,
                        np.zeros(n) if command else None)
        # The paths a gate reset and a detected step take.
        h = np.zeros((n, flt.dim))
        h[:, :n] = np.eye(n)
        kernels.correct(flt._g, flt.x, flt.p, flt._g, np.zeros(0), False, h, np.zeros(n),
                        np.eye(n), kernels.gain_of(flt.p, h, np.eye(n)), lin.locked_inverse,
                        lin.connection_qd, flt._basis, flt._pinv, flt._whole, flt._form_rows)
        kernels.compensate(flt._g, flt.x, flt.p, np.zeros(flt.dim), np.zeros_like(flt.p),
                           flt._basis, flt._whole)


def _warm_step_test() -> None:
    """Run the wrench step test's kernels."""
    # The wrench step test's kernels (estimator/step_kernels.py): a few onsets opened,
    # folded, absorbed and evaluated (twist and pose-only measurement sizes).
    from reduced_dynamics.estimator.step_test import WrenchStepTest
    for name in ('SE(3)', 'SE(2)'):
        n = SUBGROUPS[name].dim
        dim = 3 * n
        test = WrenchStepTest(n, 1e-6, dim)
        transition = np.eye(dim)
        transition[:n, n:2 * n] = 0.01 * np.eye(n)
        for k in range(8):
            test.propagate(k * 30_000_000, transition)
            m = n if k % 2 else 2 * n
            h = np.zeros((m, dim))
            h[:, :m] = np.eye(m)
            test.update(h, np.eye(m), 0.1 * h.T, np.full(m, 1e-3))


def _warm_event_tests() -> None:
    """Run the block test, the multi-scale banks and the measured momenta they take."""
    # The block test's kernels (core/blocks.py): measured momenta with and without the
    # centre of mass, every window covered.
    from reduced_dynamics.estimator.block_pulse import locate
    from reduced_dynamics.estimator.multiscale import MomentumBlocks
    for n, d in ((6, 3), (3, 2), (3, 0)):
        blocks = MomentumBlocks(n, np.array([0.02, 0.04]))
        blocks._differences = 10 ** 6  # ready at once
        position = None if not d else (np.zeros(d), np.eye(d), 2.0, tuple(range(d)))
        for k in range(16):
            blocks.add(k * 10_000_000, np.full(n, 1e-3 * k), np.eye(n), None, position)
        blocks.update(15 * 10_000_000, None)
        blocks.update(15 * 10_000_000, 0)
        blocks.mean(0, 15 * 10_000_000)
        # A detection's pulse fit (block_pulse.locate: its ramps and normal equations).
        locate(blocks, 15 * 10_000_000, 0, None)
    # The multi-scale test's banks (core/bank_step.py): through its update, without a
    # measured twist (bank_step.update) and with one per update, centre of mass
    # included (bank_step.update_with_sample from the third on).
    from reduced_dynamics.estimator.multiscale import MultiScaleTest
    for n, d in ((6, 3), (3, 2)):
        for twist in (False, True):
            multiscale = MultiScaleTest(n, 1.0)
            for k in range(4):
                stamp = k * 100_000_000
                measured = None if not twist else [(
                    stamp, np.full(n, 1e-3 * k), np.eye(n), np.eye(n) * 1e-6,
                    (np.zeros(d), np.eye(d), 2.0, tuple(range(d))))]
                multiscale.update(stamp, np.full(n, 1e-3 * k), np.eye(n), measured)
    # The same with an SE(3) base's twist turned into its momentum in the banks' call
    # (multiscale.TwistSample: bank_step.twist_step from the third on), in the
    # layouts of a run (Pinocchio's poses, a strided block of the filter's covariance).
    from reduced_dynamics.estimator.multiscale import TwistSample
    multiscale = MultiScaleTest(6, 1.0)
    eye, p, pose = np.eye(6), np.eye(18), pin.SE3.Identity()
    rows = np.tile(eye, (2, 1, 1))
    for k in range(4):
        stamp = k * 100_000_000
        measured = [TwistSample(stamp, pose.actionInverse, rows[0], np.full(6, 1e-3 * k),
                                np.zeros((2, 6))[0], eye, rows[1], p[:6, :6],
                                SUBGROUPS['SE(3)'].structure_constants, pose.rotation,
                                pose.translation, eye, rows[0])]
        multiscale.update(stamp, np.full(6, 1e-3 * k), eye, measured)
    # The block windows' scan while an event is open (MultiScaleTest.still_moving:
    # bank_step.any_above).
    multiscale.still_moving(0.3)
    # Measured momenta and centre of mass (core/impulse.py); the pose covariance is a
    # block of the filter's, a strided view.
    from reduced_dynamics.estimator.core import impulse
    for n in (6, 3):
        eye, p = np.eye(n), np.eye(3 * n)
        impulse.twist_momentum(eye, eye, np.ones(n), eye, eye, p[:n, :n], eye)
    pose = pin.SE3.Identity()  # its rotation comes in Fortran order
    for pose_cov in (np.eye(6), np.eye(18)[:6, :6]):
        impulse.centre_of_mass_se3(np.eye(6), pose.rotation, pose.translation, pose_cov)
    # The block test's statistics are calibrated from Python (multiscale._calibrate).
    impulse.calibrate(np.zeros(2), np.full(2, 0.5), np.ones(2), 1.0, 0.0, False)
    eye, p = np.eye(6), np.eye(18)
    impulse.measured_momentum_se3(pose.actionInverse, eye, np.ones(6), np.ones(6), eye, eye,
                                  p[:6, :6], SUBGROUPS['SE(3)'].structure_constants, eye,
                                  pose.rotation, pose.translation, eye)


def _warm_inputs() -> None:
    """Run the filter's inputs from mass matrices and the re-timer's window fit."""
    # The filter's inputs from a chunk's mass matrices (core/inputs.py).
    from reduced_dynamics.estimator.core import inputs
    inputs.connection_terms(np.tile(np.eye(8), (2, 1, 1)), 6, np.zeros((2, 2)), 1e-4)
    bases = np.zeros((2, 13))
    _, inverse, _, _, pbar, _ = inputs.chunk_terms(np.tile(np.eye(12), (2, 1, 1)), 6,
                                                   np.zeros((2, 6)), bases[:, 3:7].copy(),
                                                   1e-4, True)
    inputs.drift_energy(inverse, np.zeros((2, 6)), np.zeros((2, 6)), pbar)
    inputs.welford_row(np.zeros(6), np.zeros(6), np.zeros(6), 1)
    # The re-timer's window fit (core/envelope.py): the strided columns it is given (a
    # window of one point is contiguous: another signature).
    from reduced_dynamics.estimator.core import envelope
    envelope.lower_line(*envelope.window_arrays([(0, 0)]))
    index, stamp = envelope.window_arrays([(0, 0), (1, 10), (2, 21)])
    found, n1, s1, slope = envelope.lower_line(index, stamp)
    envelope.scan(index, stamp, n1, s1, slope, 1e9, 0.05)


#: warm_up's parts by name, each a set of kernels of its own (numba compiles a kernel's
#: callees into it, so two parts share only small helpers): ``reduced-dynamics compile``
#: runs them in processes of their own at once (reduced_dynamics/compile_kernels.py).
PARTS: dict[str, Callable[[], None]] = {
    'filter': _warm_filters,
    'step test': _warm_step_test,
    'event tests': _warm_event_tests,
    'inputs': _warm_inputs,
}


def warm_up(parts: Iterable[str] = tuple(PARTS)) -> None:
    """Run each kernel on a tiny problem: SE(3) and a subgroup, poses and twists, a command."""
    for name in parts:
        PARTS[name]()
