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
The iterated update stops once a re-linearisation has converged (kernels.converged).

The update's Python source (numba's ``py_func``) runs with the compiled kernels it
calls, the re-linearisations counted; the compiled update is the same source.
"""

from unittest import mock

import numpy as np
import pytest

from filter_helpers import filter_problem
from reduced_dynamics.estimator.core import kernels, update


def _problem(offset: float) -> tuple:
    """Return the arguments of ``kernels._corrected`` with a twist ``offset`` off the estimate."""
    rng, lin, flt, g, x, p = filter_problem('SE(3)', False, 11)
    n = flt.n
    twist = kernels.twist(g, x[:n], lin.locked_inverse, lin.connection_qd, flt._basis,
                          flt._pinv, flt._whole)
    measured = twist + offset * rng.normal(size=n)
    r_pose = kernels.pose_noise(flt._pose_var, np.zeros(n), 0.0)
    h, nu, r, _, gain, _, _, y = kernels.innovation(
        g, x, p, g, measured, True, lin.locked_inverse, lin.connection_qd, lin.joint_cov,
        r_pose, flt._twist_var, flt._basis, flt._pinv, flt._whole, flt._form_rows)
    return (g, x, p, g, measured, True, h, nu, r, gain, y, lin.locked_inverse,
            lin.connection_qd, flt._basis, flt._pinv, flt._whole, flt._form_rows)


def _relinearisations(args: tuple) -> tuple[int, tuple]:
    """Run the update's source with the compiled kernels; return its re-linearisations."""
    calls = []
    blocks = update._twist_blocks

    def counted(*a):
        calls.append(1)
        return blocks(*a)

    # The module whose globals _corrected's source reads (kernels re-exports it).
    with mock.patch.object(update, '_twist_blocks', counted):
        out = kernels._corrected.py_func(*args)
    return len(calls), out


@pytest.mark.parametrize('offset,expected', [(1e-7, 1), (1.0, kernels.ITERATIONS)])
def test_the_iterated_update_stops_once_converged(offset: float, expected: int) -> None:
    """A small innovation: one re-linearisation; a large one: all of them."""
    args = _problem(offset)
    count, out = _relinearisations(args)
    assert count == expected
    compiled = kernels._corrected(*args)
    for mine, theirs in zip(compiled, out):
        np.testing.assert_allclose(mine, theirs, rtol=1e-12, atol=1e-15)


def test_converged_is_relative_to_each_coordinates_sigma() -> None:
    """Moves below CONVERGED sigma converge; NaN or one coordinate above does not."""
    p = np.diag([4.0, 1e-6])
    previous = np.zeros(2)
    tol = kernels.CONVERGED
    assert kernels.converged(previous, np.array([1.9 * tol, 0.9e-3 * tol]), p)
    assert not kernels.converged(previous, np.array([1.9 * tol, 1.1e-3 * tol]), p)
    assert not kernels.converged(previous, np.array([np.nan, 0.0]), p)
