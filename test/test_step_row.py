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
The filter's row step with the step test's share, one compiled call (estimator/step_row.py).

It equals the calls it replaces (``kernels.propagate_update``, the step test's
propagate in Python, ``absorb_evaluate``) bit for bit: filters with the step test
detecting steps, and the estimator on the bench's motion (events found), each run
once with it and once with it refused (the filter then makes the separate calls).
"""

from pathlib import Path
from unittest import mock

import numpy as np
import pytest

from reduced_dynamics.estimator import step_kernels, step_row
from reduced_dynamics.estimator.core import kernels

from filter_helpers import assert_equal_arrays


def _refused(*args):
    """Stand in for filter_step: raising makes the filter take the separate calls."""
    raise np.linalg.LinAlgError('refused')


def _snapshot(flt) -> dict:
    """Return the filter's and its step test's state (copies)."""
    test = flt.step_test
    count = test._count
    state = {'g': flt._g.copy(), 'x': flt.x.copy(), 'p': flt.p.copy(),
             'stamp': flt.stamp_ns, 'log_likelihood': flt.log_likelihood,
             'nis_sum': flt.nis_sum, 'nis_dof': flt.nis_dof, 'last_nis': flt.last_nis,
             'steps_taken': flt.steps_taken, 'gated': flt.gated, 'diverged': flt.diverged,
             'significance': flt.wrench_significance(), 'count': count,
             'onsets': test._onsets[:count].copy(), 'nis_scale': test.nis_scale,
             'elapsed': test._elapsed, 'dt': test._dt, 'evaluated': test.evaluated,
             'last_statistic': test.last_statistic, 'pose_steps': test.pose_steps,
             'since_identity': test._since is test._identity, 'recent': test.recent}
    for name in ('_psi', '_omega', '_beta', '_since'):
        state[name] = getattr(test, name).copy()
    for name in ('_c', '_b0', '_j0', '_bound_inv', '_bounded'):
        state[name] = getattr(test, name)[:count].copy()
    state['kept'] = [a for kept in test.kept() for a in kept]
    return state


def _run_filter(group_name: str, twist: bool, rate: float, force: float,
                seed: int) -> tuple[list, int]:
    """Return the filter's state after every step of a stepped-wrench run, and its steps."""
    from test_step_test import _record
    from reduced_dynamics.estimator.filter import MomentumFilter
    states = []
    original = MomentumFilter.step

    def step(self, *args, **kwargs):
        out = original(self, *args, **kwargs)
        states.append(_snapshot(self))
        return out

    with mock.patch.object(MomentumFilter, 'step', step), \
            mock.patch('test_step_test._Recorder.active', True):
        flt, _ = _record(group_name, twist, rate, force, 4.0, seed=seed)
    return states, flt.steps_taken


def _assert_same(mine: dict, expected: dict) -> None:
    assert mine.keys() == expected.keys()
    for name, value in expected.items():
        if isinstance(value, np.ndarray):
            assert_equal_arrays(mine[name], value, err_msg=name)
        elif isinstance(value, list):  # the kept measurements' arrays
            assert len(mine[name]) == len(value), name
            for a, b in zip(mine[name], value):
                assert a.shape == b.shape, name
                assert_equal_arrays(a, b, err_msg=name)
        else:
            assert mine[name] == value or (value != value and mine[name] != mine[name]), name


@pytest.mark.parametrize('group_name,twist,rate,force', [
    ('SE(2)', False, 120.0, 5.0), ('SE(3)', True, 100.0, 2.0)])
def test_the_row_step_equals_the_calls_it_replaces(group_name, twist, rate, force) -> None:
    """Steps on and off detected: the filter and its step test the same, bit for bit."""
    calls = []
    compiled = step_row.filter_step

    def counted(*args):
        calls.append(1)
        return compiled(*args)

    with mock.patch.object(step_row, 'filter_step', counted):
        mine, steps = _run_filter(group_name, twist, rate, force, seed=3)
    with mock.patch.object(step_row, 'filter_step', _refused):
        expected, expected_steps = _run_filter(group_name, twist, rate, force, seed=3)
    assert steps == expected_steps >= 2
    # Every step after the first (the start) went through the compiled row step.
    assert len(calls) == len(mine) - 1
    assert len(mine) == len(expected)
    for a, b in zip(mine, expected):
        _assert_same(a, b)


def _columns(robot, messages: list, refuse: bool) -> tuple:
    """Return the estimator's output columns and events over ``messages`` (batched)."""
    from reduced_dynamics.estimator.config import EstimatorConfig
    from reduced_dynamics.estimator.pipeline import Estimator
    estimator = Estimator(robot, EstimatorConfig(prediction_rate=0.0))
    patch = mock.patch.object(step_row, 'filter_step', _refused) if refuse \
        else mock.patch.object(step_row, 'filter_step', step_row.filter_step)
    with patch:
        batch = estimator.add_samples(messages)
    names = ('mu', 'pi', 'momentum_rate', 'drift', 'energy', 'mu_cov', 'w_cov')
    columns = {name: batch.column(name) for name in names}
    columns['x'], columns['p'] = estimator.filter.x, estimator.filter.p
    events = [(e.start_ns, e.end_ns, e.detected_ns, e.peak_significance,
               e.mu_before.tobytes(), None if e.mu_after is None else e.mu_after.tobytes())
              for e in estimator.detector.events]
    return columns, events, estimator.filter.steps_taken, estimator.filter.step_test.evaluated


def test_the_estimator_with_the_row_step_is_bit_identical() -> None:
    """The bench's motion, 2.5 s (the step test's bank full, events found): same outputs."""
    from reduced_dynamics.bench import update_samples
    from reduced_dynamics.robot.model import load_robot
    robot = load_robot()
    joints, bases = update_samples(robot, 2500)
    messages = [m for pair in zip(joints, bases) for m in pair]
    mine = _columns(robot, messages, refuse=False)
    expected = _columns(robot, messages, refuse=True)
    assert expected[1], 'the bench motion finds events'
    assert expected[3] > 0, 'onsets were evaluated'
    for name, value in expected[0].items():
        np.testing.assert_array_equal(mine[0][name], value, err_msg=name)
    assert mine[1:] == expected[1:]


@pytest.mark.parametrize('joint_every,base_every,offset_ns', [
    (1, 5, 300_000),  # 1 kHz joints, 200 Hz odometry 0.3 ms later: between two rows
    (2, 1, 0),        # odometry twice as fast: one between the rows, one at the row after it
])
def test_measurements_off_the_rows_take_the_row_step_bit_identically(
        joint_every, base_every, offset_ns) -> None:
    """
    Base samples on their own clock: each takes the compiled row step, with the same bits.

    A measurement between two rows (or at a row after another one) steps with the
    inputs interpolated at its own fraction (state.between), not the rows' mean.
    """
    from reduced_dynamics.bench import update_samples
    from reduced_dynamics.messages.samples import BaseStateSample
    from reduced_dynamics.robot.model import load_robot
    robot = load_robot()
    joints, bases = update_samples(robot, 2500)
    bases = [BaseStateSample(b.stamp_ns + offset_ns, b.frame_id, b.child_frame_id,
                             b.position, b.orientation_xyzw, b.twist_linear, b.twist_angular)
             for b in bases[::base_every]]
    messages = [m for _, _, m in sorted(
        [(j.stamp_ns, 0, j) for j in joints[::joint_every]]
        + [(b.stamp_ns, 1, b) for b in bases], key=lambda e: e[:2])]
    calls = []
    compiled = step_row.filter_step

    def counted(*args):
        calls.append(args[6])  # midway
        return compiled(*args)

    with mock.patch.object(step_row, 'filter_step', counted):
        mine = _columns(robot, messages, refuse=False)
    expected = _columns(robot, messages, refuse=True)
    assert expected[1], 'the bench motion finds events'
    assert expected[3] > 0, 'onsets were evaluated'
    # Every measurement after the filter's start went through the row step (measured:
    # all but one or two), none of them midway.
    assert len(calls) >= len(bases) - 2 and not any(calls)
    for name, value in expected[0].items():
        np.testing.assert_array_equal(mine[0][name], value, err_msg=name)
    assert mine[1:] == expected[1:]


def test_a_row_is_one_compiled_filter_call() -> None:
    """In steady state: filter_step per row; propagate_update, absorb_evaluate not called."""
    from reduced_dynamics.bench import update_samples
    from reduced_dynamics.estimator.config import EstimatorConfig
    from reduced_dynamics.estimator.pipeline import Estimator
    from reduced_dynamics.robot.model import load_robot
    robot = load_robot()
    joints, bases = update_samples(robot, 1300)
    estimator = Estimator(robot, EstimatorConfig(prediction_rate=0.0))
    for joint, base in zip(joints[:1200], bases[:1200]):
        estimator.add_joint_state(joint)
        estimator.add_base_state(base)
    assert estimator.filter.step_test.onsets
    calls = {'filter_step': 0, 'propagate_update': 0, 'absorb_evaluate': 0}

    def counted(module, name):
        function = getattr(module, name)

        def wrapper(*args):
            calls[name] += 1
            return function(*args)
        return mock.patch.object(module, name, wrapper)

    with counted(step_row, 'filter_step'), counted(kernels, 'propagate_update'), \
            counted(step_kernels, 'absorb_evaluate'):
        for joint, base in zip(joints[1200:], bases[1200:]):
            estimator.add_joint_state(joint)
            estimator.add_base_state(base)
    assert calls == {'filter_step': 100, 'propagate_update': 0, 'absorb_evaluate': 0}


def test_an_accepted_row_is_taken_without_the_general_measure_path() -> None:
    """Steady state: _measure, _update, _stamp_noise not called; Psi, Omega, beta in place."""
    from reduced_dynamics.bench import update_samples
    from reduced_dynamics.estimator.config import EstimatorConfig
    from reduced_dynamics.estimator.filter import MomentumFilter
    from reduced_dynamics.estimator.pipeline import Estimator
    from reduced_dynamics.robot.model import load_robot
    robot = load_robot()
    joints, bases = update_samples(robot, 1300)
    estimator = Estimator(robot, EstimatorConfig(prediction_rate=0.0))
    messages = [m for pair in zip(joints, bases) for m in pair]
    estimator.add_samples(messages[:2400])
    test = estimator.filter.step_test
    assert test.onsets
    arrays = (test._psi, test._omega, test._beta)
    calls = {'_measure': 0, '_update': 0, '_stamp_noise': 0}

    def counted(name):
        function = getattr(MomentumFilter, name)

        def wrapper(self, *args, **kwargs):
            calls[name] += 1
            return function(self, *args, **kwargs)
        return mock.patch.object(MomentumFilter, name, wrapper)

    before = estimator.filter.steps_taken
    with counted('_measure'), counted('_update'), counted('_stamp_noise'):
        estimator.add_samples(messages[2400:])
    assert estimator.filter.steps_taken == before and not estimator.filter.gated
    assert calls == {'_measure': 0, '_update': 0, '_stamp_noise': 0}
    assert all(a is b for a, b in zip(arrays, (test._psi, test._omega, test._beta)))


def test_warm_up_loads_the_row_step_with_the_estimators_argument_types() -> None:
    """A fresh process: after warm_up, an estimator's run compiles no new signature."""
    from filter_helpers import fresh_process_words
    code = ('from reduced_dynamics.estimator.core.warmup import warm_up; warm_up(); '
            'from reduced_dynamics.estimator import step_row; '
            'from reduced_dynamics.robot.model import load_robot; '
            'from reduced_dynamics.bench import update_samples; '
            'from reduced_dynamics.estimator.pipeline import Estimator; '
            f'import sys; sys.path.insert(0, {str(Path(__file__).parent)!r}); '
            'from test_step_row import _odometry_200hz; '
            'kernels = (step_row.filter_step, step_row.propagate_step); '
            'before = [len(k.signatures) for k in kernels]; '
            'robot = load_robot(); joints, bases = update_samples(robot, 1300); '
            'e = Estimator(robot); '
            'e.add_samples([m for pair in zip(joints, bases) for m in pair]); '
            'Estimator(robot).add_samples(_odometry_200hz(robot, 1300)); '
            'print(min(before) > 0, before == [len(k.signatures) for k in kernels])')
    assert fresh_process_words(code) == ['True', 'True']


def _odometry_200hz(robot, count: int) -> list:
    """Return the bench's 1 kHz joint states with every 5th base sample, 0.3 ms later."""
    from reduced_dynamics.bench import ODOMETRY_EVERY, ODOMETRY_OFFSET_NS, update_samples
    from reduced_dynamics.messages.samples import BaseStateSample
    joints, bases = update_samples(robot, count)
    shifted = [BaseStateSample(b.stamp_ns + ODOMETRY_OFFSET_NS, b.frame_id, b.child_frame_id,
                               b.position, b.orientation_xyzw, b.twist_linear,
                               b.twist_angular) for b in bases[::ODOMETRY_EVERY]]
    return [m for _, _, m in sorted([(j.stamp_ns, 0, j) for j in joints]
                                    + [(b.stamp_ns, 1, b) for b in shifted],
                                    key=lambda e: e[:2])]


def test_rows_between_odometry_samples_propagate_in_one_call_bit_identically() -> None:
    """1 kHz joints, 200 Hz odometry: propagate_step on the rows between, same outputs."""
    from reduced_dynamics.estimator.step_test import WrenchStepTest
    from reduced_dynamics.robot.model import load_robot
    robot = load_robot()
    messages = _odometry_200hz(robot, 2500)
    calls = []
    compiled = step_row.propagate_step

    def counted(*args):
        calls.append(1)
        return compiled(*args)

    with mock.patch.object(step_row, 'propagate_step', counted):
        mine = _columns(robot, messages, refuse=False)
    # The reference: the step test's propagate from Python after kernels.propagate.
    with mock.patch.object(WrenchStepTest, 'active', mock.PropertyMock(return_value=False)):
        expected = _columns(robot, messages, refuse=True)
    assert len(calls) > 1500  # four rows in five
    assert expected[3] > 0, 'onsets were evaluated'
    for name, value in expected[0].items():
        np.testing.assert_array_equal(mine[0][name], value, err_msg=name)
    assert mine[1:] == expected[1:]


def test_the_bench_still_records_the_step_tests_calls_and_runs_the_explicit_bank() -> None:
    """The bench's step-test rows: every propagate and update recorded; the reference runs."""
    from reduced_dynamics import bench
    from reduced_dynamics.estimator import filter as filter_module
    from reduced_dynamics.estimator.step_reference import ExplicitStepTest
    from reduced_dynamics.robot.model import load_robot
    robot = load_robot()
    joints, bases = bench.update_samples(robot, 300)
    calls = bench.record_step_calls(robot, joints, bases)
    names = [call[0] for call in calls]
    assert names.count('propagate') >= 299 and names.count('update') >= 299
    with mock.patch.object(filter_module, 'WrenchStepTest', ExplicitStepTest):
        assert bench.time_update(robot, joints, bases, warmup=10) > 0.0
