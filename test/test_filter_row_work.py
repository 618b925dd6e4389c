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
The filter row's preallocated state and work arrays (docs/filter_row.md).

The step test keeps its scalars, its kept measurements (a ring) and the transition
since the last one in arrays the compiled row step changes in place; the row step
writes the prediction and its rare-path results into the filter's work arrays. A row
with that state gives the same bits as the separate calls, the ring reads back what a
deque of the measurements held, and the steps recorded for the smoother own their
arrays (the work arrays are written again by the next row).
"""

import copy
from collections import deque

import numpy as np
import pytest

from reduced_dynamics.estimator import step_row
from reduced_dynamics.estimator.core import kernels
from reduced_dynamics.estimator.step_state import POSE_STEP_HYPOTHESES
from reduced_dynamics.estimator.step_test import WrenchStepTest


def _estimator_filter(record: bool, rows: int = 1300, odometry_200hz: bool = False):
    """Return the paper robot's estimator and filter after ``rows`` rows, and the rest."""
    from reduced_dynamics.bench import update_samples
    from reduced_dynamics.estimator.config import EstimatorConfig
    from reduced_dynamics.estimator.pipeline import Estimator
    from reduced_dynamics.robot.model import load_robot
    from test_step_row import _odometry_200hz
    robot = load_robot()
    if odometry_200hz:  # four rows in five without a measurement (step_row.propagate_step)
        messages = _odometry_200hz(robot, rows + 40)
        split = rows + rows // 5
    else:
        joints, bases = update_samples(robot, rows + 40)
        messages = [m for pair in zip(joints, bases) for m in pair]
        split = 2 * rows
    estimator = Estimator(robot, EstimatorConfig(prediction_rate=0.0, smoothing_lag=0.0))
    estimator.add_samples(messages[:split])
    flt = estimator.filter
    flt.record = record
    return estimator, flt, messages[split:]


def test_a_row_with_the_packed_state_equals_the_separate_calls() -> None:
    """filter_step on the step test's arrays: the bits of propagate_update + propagate + update."""
    estimator, flt, rest = _estimator_filter(record=False)
    captured = []
    compiled = step_row.filter_step

    def capture(*args):
        captured.append(copy.deepcopy(args))
        return compiled(*args)

    step_row.filter_step = capture
    try:
        estimator.add_samples(rest[:2])
    finally:
        step_row.filter_step = compiled
    args = captured[0]
    test = flt.step_test
    n, dim = test.n, test.dim
    head, fixed = args[:19], args[19:]
    assert len(fixed) == 13 and test.onsets
    (jerk_var, pose_var, twist_var, basis, pinv, whole, ad_rows, form_rows, h_pose) = fixed[:9]
    arrays, work = fixed[9:12], fixed[12]

    # The packed call, on copies of the state before the row.
    mine = copy.deepcopy(arrays)
    mine_work = work.copy()
    stamp_twist = head[14].copy()
    out = compiled(*head[:14], stamp_twist, *head[15:], *fixed[:9], *mine, mine_work)

    # The separate calls: propagate_update, then a step test holding the same state
    # stepped from Python (WrenchStepTest.propagate and update).
    (g, x, p, locked, before_inverse, before_qd, midway, dt, pose, measured, with_twist,
     inverse_locked, connection_qd, joint_cov, twist_avg, sigma, gate, weight,
     stamp_ns) = head
    assert midway  # the bench's stamps are equal: each measurement is its row's own
    fused = kernels.propagate_update(
        g, x, p, locked, 0.5 * (before_inverse + inverse_locked),
        0.5 * (before_qd + connection_qd), joint_cov, dt, jerk_var, pose, measured,
        with_twist, inverse_locked, connection_qd, joint_cov, pose_var, twist_avg, sigma,
        twist_var, gate, weight, basis, pinv, whole, ad_rows, form_rows)
    reference = WrenchStepTest(n, 1e-6, dim)
    for mine_array, theirs in zip(reference.compiled_arrays, copy.deepcopy(arrays)):
        mine_array[...] = theirs
    reference.threshold, reference._outlier = test.threshold, test._outlier
    reference.propagate(stamp_ns, fused[3])
    m = len(fused[7])
    reference.update(fused[12] if with_twist else h_pose, fused[13], fused[14], fused[7])

    g1, x1, p1, accepted, nis, logdet, health, wrench_test, tested = out[:9]
    assert tested and accepted and health == 0
    for value, expected in zip((g1, x1, p1, nis, logdet, wrench_test),
                               (fused[9], fused[10], fused[11], fused[5], fused[6],
                                fused[17])):
        np.testing.assert_array_equal(value, expected)
    # The prediction in the work arrays; the stamp twist's average moved in place.
    for value, expected in zip(step_row.work_views(mine_work, n, dim)[:4], fused[:4]):
        np.testing.assert_array_equal(value, expected)
    np.testing.assert_array_equal(stamp_twist, fused[16])
    # The step test's whole state (scalars, bank, Psi, Omega, beta, ring) the same bits.
    for name, value, expected in zip(range(3), mine, reference.compiled_arrays):
        np.testing.assert_array_equal(value, expected, err_msg=str(name))
    assert m in (n, 2 * n)


@pytest.mark.parametrize('n,dim', [(6, 18), (3, 9), (6, 30)])
def test_the_compiled_views_are_the_step_tests_arrays(n: int, dim: int) -> None:
    """step_row.test_views and work_views: the arrays the Python side holds, same memory."""
    test = WrenchStepTest(n, 1e-6, dim)
    names = ('_floats', '_onsets', '_c', '_b0', '_j0', '_bound_inv', '_score', '_psi',
             '_omega', '_beta', '_e', '_since_buffer', '_ring_since', '_ring_h', '_ring_s',
             '_ring_gain', '_ring_nu', '_ring_m')
    views = step_row.test_views(test._state, test._ints)
    assert len(views) == len(names)
    for name, view in zip(names, views):
        mine = getattr(test, name)
        assert view.shape == mine.shape and view.dtype == mine.dtype, name
        assert view.__array_interface__['data'][0] == mine.__array_interface__['data'][0], \
            name
    # Disjoint, and the buffers used to the end.
    ends = sorted((v.__array_interface__['data'][0], v.nbytes) for v in views)
    for (start, size), (after, _) in zip(ends, ends[1:]):
        assert start + size <= after
    work = np.zeros(step_row.work_size(n, dim))
    arrays = step_row.work_views(work, n, dim)
    assert [a.shape for a in arrays] == [(4, 4), (dim - n,), (dim, dim), (dim, dim),
                                         (2 * n,), (2 * n, 2 * n), (2 * n, dim),
                                         (2 * n, 2 * n), (dim, 2 * n)]
    assert sum(a.size for a in arrays) == work.size
    for k, a in enumerate(arrays):
        a[...] = k + 1
    assert (work > 0).all()


def test_the_kept_measurements_read_back_as_a_deque_of_them() -> None:
    """The ring (POSE_STEP_HYPOTHESES slots, both innovation sizes, wrapped) = a deque."""
    n, dim = 3, 9
    test = WrenchStepTest(n, 1e-6, dim)
    rng = np.random.default_rng(4)
    expected: deque = deque(maxlen=POSE_STEP_HYPOTHESES)
    since = np.eye(dim)
    for k in range(2 * POSE_STEP_HYPOTHESES + 5):
        transition = np.eye(dim) + 0.01 * rng.standard_normal((dim, dim))
        test.propagate(k * 10_000_000, transition)
        if expected:
            since = transition if since is None else transition @ since
        m = n if k % 3 else 2 * n
        h, s = rng.standard_normal((m, dim)), np.eye(m) * (1.0 + k)
        gain, nu = rng.standard_normal((dim, m)), rng.standard_normal(m)
        test._keep(h, s, gain, nu)
        expected.append((np.eye(dim) if since is None else since, h, s, gain, nu))
        since = None
        kept = test.kept()
        assert len(kept) == len(expected) == test.recent
        for mine, theirs in zip(kept, expected):
            for a, b in zip(mine, theirs):
                assert a.flags.c_contiguous and a.shape == b.shape
                np.testing.assert_array_equal(a, b)
    test.reset()
    assert test.kept() == [] and test._since is test._identity


@pytest.mark.parametrize('odometry_200hz', [False, True])
def test_recorded_steps_own_their_arrays(odometry_200hz: bool) -> None:
    """Steps recorded for the smoother keep their values after later rows (no aliasing)."""
    estimator, flt, rest = _estimator_filter(True, 1200, odometry_200hz)
    flt.steps = []
    estimator.add_samples(rest[:40])
    steps = list(flt.steps)
    assert len(steps) >= 19
    frozen = [tuple(np.array(a, copy=True) for a in (
        s.transition, s.pose_pred, s.x_pred, s.p_pred, s.pose, s.x, s.p)) for s in steps]
    estimator.add_samples(rest[40:])
    work = {id(a) for a in flt._work}
    for step, values in zip(steps, frozen):
        arrays = (step.transition, step.pose_pred, step.x_pred, step.p_pred, step.pose,
                  step.x, step.p)
        assert not work & {id(a) for a in arrays}
        for a, b in zip(arrays, values):
            np.testing.assert_array_equal(a, b)
    # Updates (prediction and update differ) among them; consecutive steps differ.
    assert any(not np.array_equal(s.p_pred, s.p) for s in steps)
    assert not np.array_equal(steps[-1].transition, steps[-2].transition)
    assert not np.array_equal(steps[-1].p_pred, steps[-2].p_pred)


def test_a_copied_or_unpickled_step_test_keeps_its_arrays_views_of_its_own_buffers() -> None:
    """A deep copy and a pickle: the copy's arrays are views of its own buffers, same state."""
    import pickle
    n, dim = 3, 9
    rng = np.random.default_rng(7)
    calls = []
    for k in range(80):
        transition = np.eye(dim) + 0.01 * rng.standard_normal((dim, dim))
        m = n if k % 3 else 2 * n
        h = rng.standard_normal((m, dim))
        calls.append((k * 10_000_000, transition, h, np.eye(m) * 2.0 + 0.1 * h @ h.T,
                      0.1 * rng.standard_normal((dim, m)), rng.standard_normal(m)))
    test = WrenchStepTest(n, 1e-6, dim)
    for stamp, transition, h, s, gain, nu in calls[:40]:
        test.propagate(stamp, transition)
        test.update(h, s, gain, nu)
    copies = [copy.deepcopy(test), pickle.loads(pickle.dumps(test))]
    for other in [test] + copies:
        for stamp, transition, h, s, gain, nu in calls[40:]:
            other.propagate(stamp, transition)
            other.update(h, s, gain, nu)
    for other in copies:
        for name in ('_psi', '_c', '_onsets', '_ring_h', '_since_buffer', '_floats'):
            assert np.shares_memory(getattr(other, name), other._state if name not in (
                '_onsets',) else other._ints), name
            assert not np.shares_memory(getattr(other, name), getattr(test, name)), name
        for mine, theirs in zip(other.compiled_arrays, test.compiled_arrays):
            np.testing.assert_array_equal(mine, theirs)
        assert other.nis_scale == test.nis_scale and other.recent == test.recent
