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

"""The filter's fused step (kernels.propagate_update): the same bits as its two calls."""

import numpy as np
import pytest

from filter_helpers import linearisation_problem
from reduced_dynamics.estimator.core import kernels
from reduced_dynamics.estimator.filter import Linearisation, MomentumFilter, NoiseModel
from reduced_dynamics.geometry.lie_group import SUBGROUPS


@pytest.mark.parametrize('name,with_twist,gate', [
    ('SE(3)', True, np.inf), ('SE(3)', False, np.inf), ('SE(2)', True, np.inf),
    ('SE(3)', True, 0.0)])
def test_fused_step_equals_propagate_then_update_bit_for_bit(
        name: str, with_twist: bool, gate: float) -> None:
    """One compiled call per step gives what propagate then update gave, to the bit."""
    group = SUBGROUPS[name]
    n = group.dim
    rng, lin = linearisation_problem(n, 3)
    step = Linearisation(lin.locked, lin.locked_inverse * 1.01, lin.connection_qd * 0.9,
                         lin.joint_cov)
    flt = MomentumFilter(group, NoiseModel(), 1e-6)
    dim = flt.dim
    g = group.exp(rng.normal(size=n) * 0.3).homogeneous
    x = rng.normal(size=dim - n)
    root = rng.normal(size=(dim, dim))
    p = root @ root.T * 1e-2 + np.eye(dim) * 1e-3
    pose = np.ascontiguousarray(group.exp(rng.normal(size=n) * 1e-3).homogeneous @ g)
    measured = rng.normal(size=n) if with_twist else np.zeros(0)
    stamp_twist, sigma, weight, dt = rng.normal(size=n), 3e-3, 0.25, 0.01
    g0, x0, p0, phi = kernels.propagate(
        g, x, p, step.locked, step.locked_inverse, step.connection_qd, step.joint_cov, dt,
        np.zeros(0), False, flt._jerk_var, flt._densities(step), flt._basis, flt._pinv,
        flt._whole, flt._ad_rows, flt._form_rows)
    updated = kernels.update(g0, x0, p0, pose, measured, with_twist, lin.locked_inverse,
                             lin.connection_qd, lin.joint_cov, flt._pose_var, stamp_twist,
                             sigma, flt._twist_var, gate, flt._basis, flt._pinv, flt._whole,
                             flt._form_rows)
    fused = kernels.propagate_update(
        g, x, p, step.locked, step.locked_inverse, step.connection_qd, step.joint_cov, dt,
        flt._jerk_var, pose, measured, with_twist, lin.locked_inverse, lin.connection_qd,
        lin.joint_cov, flt._pose_var, stamp_twist, sigma, flt._twist_var, gate, weight,
        flt._basis, flt._pinv, flt._whole, flt._ad_rows, flt._form_rows)
    expected = (g0, x0, p0, phi) + tuple(updated)
    assert len(fused) == len(expected) + 3
    for got, want in zip(fused, expected):
        assert np.array_equal(np.asarray(got), np.asarray(want))
    accepted, g1, x1 = updated[0], updated[5], updated[6]
    assert accepted == (gate > 0.0)
    assert fused[15] == 0
    if accepted:
        twist = kernels.twist(g1, x1[:n], lin.locked_inverse, lin.connection_qd, flt._basis,
                              flt._pinv, flt._whole)
        assert np.array_equal(fused[16], stamp_twist + weight * (twist - stamp_twist))
    else:
        assert np.array_equal(fused[16], stamp_twist)
    # The wrench test of the resulting state, as the event detector asks it.
    assert fused[17] == kernels.significance(updated[6], updated[7], n)


def test_covariance_health_names_what_is_wrong() -> None:
    """0 usable, 1 not finite (anywhere), 2 a negative variance (NaN first)."""
    p = np.eye(4)
    assert kernels.covariance_health(p) == 0
    p[1, 2] = np.inf
    assert kernels.covariance_health(p) == 1
    p = np.eye(4)
    p[3, 3] = -1e-300
    assert kernels.covariance_health(p) == 2
    p[0, 1] = np.nan
    assert kernels.covariance_health(p) == 1
