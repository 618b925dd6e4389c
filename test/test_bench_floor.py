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

"""The bench's update floor (reduced_dynamics/bench_floor.py)."""

import math

import pytest

from reduced_dynamics import bench_floor
from reduced_dynamics.estimator.step_state import COUNT
from reduced_dynamics.robot.model import load_robot


#: In test_bench.py's worker, after or before its tiny bench: the floor's compiled loops are
#: compiled once and loaded from numba's cache by the other (two workers compiled them both).
@pytest.mark.xdist_group('bench_tiny_report')
def test_floor_times_the_steady_state_calls_and_adds_them_up() -> None:
    """Captured in steady state (a full step-test bank), each part timed, sums consistent."""
    robot = load_robot()
    captured = bench_floor._capture(robot)
    # absorb_evaluate(h, s, gain, nu, psi, omega, beta, outlier, c, b0, j0, bound_inv,
    # bounded, count, ...): onsets open, as in steady state.
    assert captured['absorb_evaluate'][13] >= 10
    step = captured['propagate_update']
    assert step[2].shape == (3 * robot.n, 3 * robot.n) and step[11]  # an Odometry update
    row = captured['filter_step']  # the row's one compiled call, as the filter made it
    # (g, x, P, ..., midway at 6, with_twist at 10, ..., the step test's state buffer and
    # int buffer at 28 and 29, step_row.filter_step's order): an Odometry row's own
    # measurement (the bench's stamps are equal) with onsets open.
    assert row[2].shape == step[2].shape and row[6] and row[10] and row[29][COUNT] >= 10
    floor = bench_floor.measure_floor(robot, calls=50)
    assert 'row_step_called' in floor
    assert all(math.isfinite(v) and v > 0.0 for v in floor.values())
    compiled = floor['filter_step_compiled'] + floor['step_test_compiled']
    assert math.isclose(floor['floor_streaming'], floor['mechanics_streaming'] + compiled)
    assert math.isclose(floor['floor_batched'], floor['mechanics_batched'] + compiled)
    # One row's mechanics include at least one crba: counted, not timed (a loaded run
    # measured the row below a lone crba once: timings are the bench's, not a test's).
    import pinocchio as pin
    calls = []
    real = pin.crba
    try:
        pin.crba = lambda *args: calls.append(1) or real(*args)
        captured['kernel'].filter_inputs(captured['qbar'][:1], captured['qbar_dot'][:1],
                                         captured['bases'][:1], captured['variance'])
    finally:
        pin.crba = real
    assert len(calls) >= 1


def test_the_capture_leaves_the_multi_scale_test_out(monkeypatch) -> None:
    """The floor has no event test: its capture does not locate the bench motion's wrench."""
    from reduced_dynamics.estimator.multiscale import MomentumBlocks, MultiScaleTest
    calls = []
    for cls, name in ((MultiScaleTest, '_filtered'), (MomentumBlocks, 'locate')):
        original = getattr(cls, name)

        def counted(self, *args, original=original, name=name, **kwargs):
            calls.append(name)
            return original(self, *args, **kwargs)
        monkeypatch.setattr(cls, name, counted)
    captured = bench_floor._capture(load_robot())
    assert calls == [] and captured['absorb_evaluate'][13] >= 10


def test_the_smoother_row_times_a_recorded_step_the_dense_step_agrees_on() -> None:
    """Two recorded steps (a transition between them); the dense reference agrees on them."""
    import numpy as np
    from reduced_dynamics.estimator.core import smoother, smoother_reference
    robot = load_robot()
    args = bench_floor._smoother_args(robot)
    dim = 3 * robot.n
    assert args[3] is not None and args[3].shape == (dim, dim)
    got, want = smoother.backward_step(*args), smoother_reference.backward_step(*args)
    for a, b in zip(got, want):
        assert np.allclose(a, b, rtol=0.0, atol=1e-9 * np.abs(b).max())
    rows = {key for key, *_ in bench_floor.FLOOR_ROWS}
    # The dense references are numpy test oracles, not compiled: no row times them.
    assert 'smoother_step' in rows and not any('reference' in key for key in rows)
