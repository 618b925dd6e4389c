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
The per-row Python around the compiled kernels, trimmed: the same numbers, fewer calls.

Each compiled routine that fuses kernels equals the calls it replaces bit for bit, and
the counts of per-row calls show what left the row (issue 19, docs/performance.md).
"""

from unittest import mock

import numpy as np
import pinocchio as pin
import pytest

from reduced_dynamics.estimator import multiscale
from reduced_dynamics.estimator.core import impulse


@pytest.fixture(scope='module')
def bench_run():
    """Return (robot, the bench's messages of 400 samples) (1 kHz, joints and Odometry)."""
    from reduced_dynamics.bench import update_samples
    from reduced_dynamics.robot.model import load_robot
    from reduced_dynamics.estimator.core.warmup import warm_up
    # Compiled (or loaded) before a test patches the kernels a fused one calls.
    warm_up()
    robot = load_robot()
    joints, bases = update_samples(robot, 400)
    return robot, [m for pair in zip(joints, bases) for m in pair]


def _estimator(robot):
    from reduced_dynamics.estimator.config import EstimatorConfig
    from reduced_dynamics.estimator.pipeline import Estimator
    return Estimator(robot, EstimatorConfig(prediction_rate=0.0))


def test_measured_momentum_se3_equals_the_two_kernels_it_fuses() -> None:
    """Poses from Pinocchio, the filter covariance's block as a strided view (as the filter)."""
    from reduced_dynamics.geometry.lie_group import SUBGROUPS
    rng = np.random.default_rng(11)
    group = SUBGROUPS['SE(3)']
    for _ in range(300):
        g, pose = pin.SE3.Random(), pin.SE3.Random()
        root = rng.standard_normal((6, 6))
        locked = root @ root.T + 6.0 * np.eye(6)
        interpolated = locked + 0.01 * rng.standard_normal((6, 6))
        p = rng.standard_normal((18, 18))
        p = p @ p.T
        twist, connection = rng.standard_normal(6), rng.standard_normal(6)
        twist_cov = np.diag(rng.uniform(0.1, 1.0, 6))
        joint_cov, pose_noise = np.diag(rng.uniform(0.1, 1.0, 6)), np.diag(rng.uniform(0.1, 1, 6))
        expected = multiscale.twist_momentum(g.actionInverse, locked, connection, twist,
                                             twist_cov, joint_cov, p[:6, :6],
                                             group.coadjoint_form) \
            + multiscale.centre_of_mass('SE(3)', pose, interpolated, pose_noise)[:3]
        fused = impulse.measured_momentum_se3(
            g.actionInverse, locked, twist, connection, twist_cov, joint_cov, p[:6, :6],
            group.structure_constants, interpolated, pose.rotation, pose.translation,
            pose_noise)
        assert len(fused) == len(expected)
        for mine, want in zip(fused, expected):
            np.testing.assert_array_equal(mine, want)


def test_the_compiled_kirillov_form_equals_the_einsum_bit_for_bit() -> None:
    """Every base group, covectors of every scale and sign, zeros: the same bits."""
    from reduced_dynamics.geometry.lie_group import SUBGROUPS
    rng = np.random.default_rng(2)
    for group in SUBGROUPS.values():
        n = group.dim
        for k in range(400):
            covector = rng.standard_normal(n) * 10.0 ** rng.integers(-6, 6)
            if k % 3 == 0:
                covector = -np.abs(covector)
            if k % 5 == 0:
                covector[rng.integers(n)] = 0.0 if k % 2 else -0.0
            expected = group.coadjoint_form(covector)
            mine = impulse.kirillov_form(group.structure_constants, covector)
            np.testing.assert_array_equal(mine.view(np.uint64), expected.view(np.uint64))


def test_a_measured_twist_is_one_compiled_call_per_row(bench_run) -> None:
    """
    An SE(3) row with a twist: its momentum and centre of mass come from one call.

    The banks' (bank_step.twist_step) where the sample is common, else
    impulse.measured_momentum_se3 from Python (TwistSample.momentum).
    """
    from reduced_dynamics.estimator.core import bank_step
    robot, messages = bench_run
    calls = {'fused': 0, 'twist_momentum': 0, 'centre_of_mass_se3': 0, 'banks': 0}

    def counted(name, function):
        def wrapper(*args):
            calls[name] += 1
            return function(*args)
        return wrapper

    estimator = _estimator(robot)
    with mock.patch.object(impulse, 'measured_momentum_se3',
                           counted('fused', impulse.measured_momentum_se3)), \
            mock.patch.object(impulse, 'twist_momentum',
                              counted('twist_momentum', impulse.twist_momentum)), \
            mock.patch.object(impulse, 'centre_of_mass_se3',
                              counted('centre_of_mass_se3', impulse.centre_of_mass_se3)), \
            mock.patch.object(bank_step, 'twist_step',
                              counted('banks', bank_step.twist_step)):
        estimator.add_samples(messages)
    assert estimator.processed == 400
    # Every row measures a twist (the first one's starts the filter and is one too).
    # From Python: the first two (no update period yet), the one that finds the ring
    # full, and the 25 others whose excess decomposition is due (MomentumBlocks.prepare:
    # differences 1, 17, ..., 385 and 200; difference 1 is the second sample).
    assert calls == {'fused': 28, 'twist_momentum': 0, 'centre_of_mass_se3': 0,
                     'banks': 400 - 28}


def test_the_event_windows_lookups_are_done_once_per_window_length() -> None:
    """still_moving and window_statistic: the direct formulas' answers, bank scans once."""
    from reduced_dynamics.chi_square import chi2
    rng = np.random.default_rng(3)
    test = multiscale.MultiScaleTest(6, 1.0)
    test.blocks.active = True
    lengths = [0.3, 0.05, 1.7, 0.3, 3.0, 1.7]
    with mock.patch.object(multiscale.np, 'argmin', wraps=np.argmin) as argmin:
        for _ in range(50):
            test.statistics[:] = rng.chisquare(6, len(test.windows))
            test.blocks.statistics[:] = rng.chisquare(6, len(test.windows)) * 2.0
            for window in lengths:
                short = test.windows <= max(window, test.windows[0]) * (1 + 1e-9)
                threshold = float(chi2.isf(0.01 / int(short.sum()), 6))
                assert test.still_moving(window) == bool(
                    np.any(test.blocks.statistics[short] > threshold))
                nearest = int(np.argmin(np.abs(test.windows - window)))
                assert test.window_statistic(window) == float(test.statistics[nearest])
        # 50 x 6 direct lookups above, and one per distinct length in the test itself.
        assert argmin.call_count == 50 * len(lengths) + len(set(lengths))


def test_a_measured_momentum_enters_the_block_test_in_one_compiled_call(bench_run) -> None:
    """
    Per sample the measured momentum and both banks in one call (twist_step).

    update_with_sample where the excess decomposition is due (MomentumBlocks.prepare);
    the separate kernels only where add_sample cannot run.
    """
    from reduced_dynamics.estimator.core import bank_step, blocks
    robot, messages = bench_run
    calls = {'add_sample': 0, 'accumulate': 0, 'learn_excess': 0, 'update_with_sample': 0,
             'twist_step': 0}

    def counted(module, name):
        function = getattr(module, name)

        def wrapper(*args):
            calls[name] += 1
            return function(*args)
        return mock.patch.object(module, name, wrapper)

    estimator = _estimator(robot)
    with counted(blocks, 'add_sample'), counted(blocks, 'accumulate'), \
            counted(blocks, 'learn_excess'), counted(bank_step, 'update_with_sample'), \
            counted(bank_step, 'twist_step'):
        estimator.add_samples(messages)
    # 400 measured momenta: the first (no difference yet) and the one that finds the
    # ring full (row 256: compacted) take the separate calls; the second comes before
    # the update period is known (add_sample alone); the others enter with the banks'
    # update, one per row: those where the excess noise's eigen-decomposition is due
    # (differences 1, 17, ..., 385 and 200: 26; the first of them is the second sample)
    # by update_with_sample, learn_excess run first on a copy; the rest with the
    # twist's momentum too (twist_step).
    assert calls == {'add_sample': 1, 'accumulate': 2, 'learn_excess': 26 + 1,
                     'update_with_sample': 26 - 1, 'twist_step': 400 - 3 - 25}


def test_calibrated_best_equals_the_numpy_steps_it_replaces() -> None:
    """
    Covered windows, ties, NaN, learning on and off: statistics, above and the argmax.

    The rule ``bank_step.update`` inlines, compiled here on its own from the same source.
    """
    rng = np.random.default_rng(8)
    for trial in range(2000):
        count = int(rng.integers(1, 14))
        rows = np.where(rng.random(count) < 0.7, rng.integers(0, 50, count), -1)
        covered = rows >= 0
        products = rng.chisquare(6, int(covered.sum()))
        if trial % 5 == 0 and len(products):
            products[rng.integers(len(products))] = products.max()  # a tie
        if trial % 7 == 0 and len(products):
            products[rng.integers(len(products))] = np.nan
        inflation = rng.uniform(1.0, 3.0, count)
        above, learn = rng.uniform(0.3, 0.9, count), bool(trial % 2)
        rate, median = 0.01, 5.35
        # The numpy steps of MultiScaleTest._filtered before (main 7bf0c5e).
        statistics = np.full(count, -1.0)
        statistics[:] = 0.0
        statistics[covered] = products
        mine = statistics.copy()  # as bank_windows.filtered_bank leaves them
        expected_above = above.copy()
        statistics[:] = impulse.calibrate(statistics, expected_above, inflation, median, rate,
                                          learn)
        mine_above = above.copy()
        best, value = impulse.calibrated_best(rows, mine, mine_above, inflation, median,
                                              rate, learn)
        np.testing.assert_array_equal(mine, statistics)
        np.testing.assert_array_equal(mine_above, expected_above)
        if not covered.any():
            assert best == -1
            continue
        values = statistics[covered]
        assert best == int(np.argmax(values))
        np.testing.assert_array_equal(value, values[best])


def test_the_filtered_momentum_test_is_one_call_per_update() -> None:
    """
    Per update: bank_step.update, not the kernels it replaced.

    (They were store_window_changes and calibrated_best from Python, then
    bank_step.changes and calibrated with numpy's einsum between them.)
    """
    from reduced_dynamics.estimator.core import bank_step
    rng = np.random.default_rng(4)
    test = multiscale.MultiScaleTest(6, 1.0)
    calls = {'calibrated_best': 0, 'calibrate': 0, 'update': 0, 'update_with_sample': 0}

    def counted(name):
        module = bank_step if name in ('update', 'update_with_sample') else impulse
        function = getattr(module, name)

        def wrapper(*args):
            calls[name] += 1
            return function(*args)
        return mock.patch.object(module, name, wrapper)

    patches = [counted(name) for name in calls]
    for patch in patches:
        patch.start()
    try:
        for k in range(300):
            root = rng.standard_normal((6, 6)) * 1e-2
            test.update(1_000_000 * k, rng.standard_normal(6) * 1e-2,
                        root @ root.T + 1e-6 * np.eye(6))
    finally:
        for patch in patches:
            patch.stop()
    # The first update has no period yet (stored only); then each stores, computes and
    # calibrates in one call (zeros until a window is covered: k >= 50).
    assert calls == {'calibrated_best': 0, 'calibrate': 0, 'update': 299,
                     'update_with_sample': 0}
    assert test.statistics.any()


class _SeparateCalls:
    """WrenchStepTest.update as it was (main 7bf0c5e): absorb, then evaluate, from Python."""

    @staticmethod
    def update(test, h, s, gain, nu):
        import math
        from reduced_dynamics.estimator.step_test import NIS_TIME
        kernels = test._kernels
        test._keep(h, s, gain, nu)
        m = len(nu)
        outlier = test._outlier.get(m, math.inf)
        if test._count:
            nis_total = kernels.absorb(
                np.ascontiguousarray(h), np.ascontiguousarray(s), np.ascontiguousarray(gain),
                np.ascontiguousarray(nu), test._psi, test._omega, test._beta, outlier)
        else:
            nis_total = float(nu @ np.linalg.solve(s, nu))
        if not nis_total <= outlier:
            return None
        test._elapsed += test._dt
        horizon = min(test._elapsed, NIS_TIME)
        weight = 1.0 if horizon <= 0.0 else min(1.0, test._dt / horizon)
        test.nis_scale += weight * (nis_total / m - test.nis_scale)
        if not test._count:
            return None
        scale = max(1.0, test.nis_scale)
        best, statistic, top, evaluated = kernels.evaluate(
            test._c, test._b0, test._j0, test._bound_inv, test._bounded, test._count,
            test._omega, test._beta, scale, test.threshold, test._score)
        test.evaluated += evaluated
        test.last_statistic = top if best < 0 or not statistic > test.threshold \
            else statistic
        if best < 0 or not statistic > test.threshold:
            return None
        if test._pose_statistic() / scale >= statistic:
            test.pose_steps += 1
            return None
        d = test._psi @ test._c[best]
        j = test._j0[best] + test._c[best].T @ test._omega @ test._c[best]
        step = np.linalg.solve(j, test._score[best])
        from reduced_dynamics.estimator.step_test import StepDetection
        return StepDetection(statistic, step, d @ step, d @ np.linalg.solve(j, d.T))


@pytest.mark.parametrize('group_name,twist,rate,force', [
    ('SE(2)', False, 120.0, 5.0), ('SE(3)', True, 100.0, 2.0)])
def test_the_step_tests_one_call_update_equals_its_two_calls(bench_run, group_name, twist,
                                                             rate, force) -> None:
    """Recorded filter runs with steps on and off: detections and state bit for bit."""
    from test_step_test import _record
    from reduced_dynamics.estimator.step_test import WrenchStepTest
    flt, calls = _record(group_name, twist, rate, force, 4.0, seed=3)
    assert flt.steps_taken >= 2
    fused, separate = (WrenchStepTest(flt.n, 1e-6, flt.dim) for _ in range(2))
    detections = 0
    for call in calls:
        if call[0] == 'reset':
            fused.reset(call[1])
            separate.reset(call[1])
        elif call[0] == 'propagate':
            fused.propagate(call[1], call[2])
            separate.propagate(call[1], call[2])
        else:
            mine = fused.update(*call[1:])
            expected = _SeparateCalls.update(separate, *call[1:])
            assert (mine is None) == (expected is None)
            if mine is not None:
                detections += 1
                for a, b in zip(mine, expected):
                    np.testing.assert_array_equal(a, b)
        for name in ('nis_scale', '_elapsed', 'evaluated', 'last_statistic', 'pose_steps'):
            assert getattr(fused, name) == getattr(separate, name), name
        for name in ('_psi', '_omega', '_beta', '_c', '_b0', '_j0', '_score'):
            np.testing.assert_array_equal(getattr(fused, name), getattr(separate, name))
    assert detections >= 2


def test_a_step_test_update_is_one_compiled_call(bench_run) -> None:
    """
    With onsets open: no step-test kernel is called from Python per update.

    absorb_evaluate (one call where absorb and evaluate were two) now runs inside
    the filter's compiled row step (step_row.filter_step, test_step_row.py).
    """
    from reduced_dynamics.bench import update_samples
    from reduced_dynamics.estimator import step_kernels, step_row
    robot = bench_run[0]
    joints, bases = update_samples(robot, 1200)
    messages = [m for pair in zip(joints, bases) for m in pair]
    calls = {'absorb_evaluate': 0, 'absorb': 0, 'evaluate': 0, 'filter_step': 0}

    def counted(name):
        function = getattr(step_row if name == 'filter_step' else step_kernels, name)

        def wrapper(*args):
            calls[name] += 1
            return function(*args)
        return wrapper

    estimator = _estimator(robot)
    estimator.add_samples(messages[:2 * 1100])  # settled (1 s from the start), onsets open
    assert estimator.filter.step_test.onsets
    with mock.patch.object(step_kernels, 'absorb_evaluate', counted('absorb_evaluate')), \
            mock.patch.object(step_kernels, 'absorb', counted('absorb')), \
            mock.patch.object(step_kernels, 'evaluate', counted('evaluate')), \
            mock.patch.object(step_row, 'filter_step', counted('filter_step')):
        estimator.add_samples(messages[2 * 1100:])
    # One update per row (the joint and base stamps are equal), each one call.
    assert calls == {'absorb_evaluate': 0, 'absorb': 0, 'evaluate': 0, 'filter_step': 100}


def _off_row_run(robot, messages: list, separate: bool) -> tuple:
    """
    Return the estimator's columns, events and multi-scale state over ``messages``.

    ``separate``: every measured twist off its row's stamp goes to the banks as its
    momentum computed from Python, with A qbar_dot and the centre of mass's inertia
    interpolated here to its stamp (the route such samples took before they entered
    the banks' call).
    """
    from reduced_dynamics.estimator import processing
    from reduced_dynamics.estimator.config import EstimatorConfig
    from reduced_dynamics.estimator.pipeline import Estimator
    computed = processing.twist_momenta

    def momenta(flt, before, lin, start_ns, stamp, *rest):
        out = computed(flt, before, lin, start_ns, stamp, *rest)
        if not separate:
            return out
        separated = []
        for item in out:
            if item.__class__ is not multiscale.TwistSample or item.stamp_ns == stamp:
                separated.append(item)
                continue
            fraction = (item.stamp_ns - start_ns) / (stamp - start_ns)
            connection = before.connection_qd + fraction * (lin.connection_qd
                                                            - before.connection_qd)
            np.testing.assert_array_equal(item.connection_qd, connection)
            locked = before.locked + fraction * (lin.locked - before.locked)
            mu, white, common, world, cov, mass = impulse.measured_momentum_se3(
                item.ad_inverse, lin.locked, item.twist, connection, item.twist_cov,
                item.joint_cov, item.pose_cov, item.structure, locked, item.rotation,
                item.translation, item.com_pose_cov)
            separated.append((item.stamp_ns, mu, white, common,
                              (world, cov, mass, multiscale.LINEAR['SE(3)'])))
        return separated

    estimator = Estimator(robot, EstimatorConfig(prediction_rate=0.0))
    with mock.patch.object(processing, 'twist_momenta', momenta):
        batch = estimator.add_samples(messages)
    names = ('mu', 'pi', 'momentum_rate', 'drift', 'energy', 'mu_cov', 'w_cov')
    columns = {name: batch.column(name) for name in names}
    test = estimator.detector.multiscale
    columns['statistics'], columns['block_statistics'] = test.statistics, \
        test.blocks.statistics
    columns['inflation'] = test.inflation
    events = [(e.start_ns, e.end_ns, e.detected_ns, e.peak_significance,
               e.mu_before.tobytes(), None if e.mu_after is None else e.mu_after.tobytes(),
               None if e.impulse is None else e.impulse.tobytes())
              for e in estimator.detector.events]
    return columns, events


@pytest.mark.parametrize('base_every', [5, 1], ids=['odometry 200 Hz', 'odometry 1 kHz'])
def test_a_twist_between_two_rows_enters_the_banks_call_with_the_same_bits(
        bench_run, base_every) -> None:
    """
    Odometry on its own clock (0.3 ms after the joint states): one banks' call per twist.

    Its momentum takes the row's inertia, and for the centre of mass the inertia
    interpolated to its stamp (TwistSample.com_locked); the outputs, events and the
    multi-scale test's statistics equal those of its momentum computed from Python.
    """
    from reduced_dynamics.bench import update_samples
    from reduced_dynamics.estimator.core import bank_step
    from reduced_dynamics.messages.samples import BaseStateSample
    robot, _ = bench_run
    joints, bases = update_samples(robot, 2500)
    shifted = [BaseStateSample(b.stamp_ns + 300_000, b.frame_id, b.child_frame_id,
                               b.position, b.orientation_xyzw, b.twist_linear,
                               b.twist_angular) for b in bases[::base_every]]
    messages = [m for _, _, m in sorted([(j.stamp_ns, 0, j) for j in joints]
                                        + [(b.stamp_ns, 1, b) for b in shifted],
                                        key=lambda e: e[:2])]
    calls = {'twist_step': 0}

    def counted(*args, _function=bank_step.twist_step):
        calls['twist_step'] += 1
        return _function(*args)

    with mock.patch.object(bank_step, 'twist_step', counted):
        mine = _off_row_run(robot, messages, separate=False)
    entered = calls['twist_step']
    calls['twist_step'] = 0
    with mock.patch.object(bank_step, 'twist_step', counted):
        expected = _off_row_run(robot, messages, separate=True)
    assert expected[1], 'the bench motion finds events'
    # Most twists entered the banks' call (not: the first ones, a ring compacted, the
    # excess decompositions due); with their momenta from Python none did.
    assert entered > 0.85 * len(shifted) and calls['twist_step'] == 0
    for name, value in expected[0].items():
        np.testing.assert_array_equal(mine[0][name], value, err_msg=name)
    assert mine[1] == expected[1]
