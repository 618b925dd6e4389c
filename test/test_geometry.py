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

"""Base groups, isotropy (Table 2) and coset charts."""

import numpy as np
import pinocchio as pin
import pytest

from reduced_dynamics.geometry.chart import CosetChart
from reduced_dynamics.geometry.isotropy import isotropy_algebra, MomentumClass, RANK_RTOL
from reduced_dynamics.geometry.lie_group import BaseGroup, SUBGROUPS

# Table 2 as dimensions of G_mu: (generic, pure angular, pure linear, zero).
TABLE_2 = {
    'SE(3)': (2, 4, 2, 6),
    'SE(2)xR': (2, 4, 2, 4),
    'SE(2)': (1, 3, 1, 3),
    'H_p x R2': (1, 3, 1, 3),
    'R3': (3, 3, 3, 3),
    'SO(2)xR': (2, 2, 2, 2),
    'R2': (2, 2, 2, 2),
    'SO(2)': (1, 1, 1, 1),
    'R': (1, 1, 1, 1),
    'H_p': (1, 1, 1, 1),
}


def _wrench(kind, rng):
    w = rng.standard_normal(6)
    if kind == 'angular':
        w[:3] = 0.0
    elif kind == 'linear':
        w[3:] = 0.0
    elif kind == 'zero':
        w[:] = 0.0
    return w


@pytest.mark.parametrize('name', sorted(TABLE_2))
def test_table_2_dimensions(name):
    group = SUBGROUPS[name]
    rng = np.random.default_rng(1)
    for kind, expected in zip(('generic', 'angular', 'linear', 'zero'), TABLE_2[name]):
        for _ in range(5):
            mu = group.dual_coordinates(_wrench(kind, rng))
            iso = isotropy_algebra(group, mu)
            assert iso.dim == expected, (name, kind)
            assert iso.dim + iso.orbit_dim == group.dim
            # The basis really is the isotropy: ad_eta^T mu = 0.
            for eta in iso.basis.T:
                assert np.linalg.norm(group.ad(eta).T @ mu) <= 1e-12 * max(1, np.linalg.norm(mu))


def test_so3_isotropy_is_so2():
    group = SUBGROUPS['SO(3)']
    iso = isotropy_algebra(group, np.array([0.3, -0.2, 0.5]))
    assert iso.dim == 1
    assert np.allclose(np.abs(iso.basis[:, 0]), np.abs([0.3, -0.2, 0.5]) / np.linalg.norm(
        [0.3, -0.2, 0.5]))


def test_se2xr_linear_momentum_along_rotation_axis_has_full_isotropy():
    group = SUBGROUPS['SE(2)xR']
    mu = group.dual_coordinates(np.array([0.0, 0.0, 2.0, 0.0, 0.0, 1.0]))
    assert isotropy_algebra(group, mu).dim == 4


@pytest.mark.parametrize('epsilon, expected', [(1e-13, 4), (1e-6, 2)])
def test_class_boundary_uses_documented_rank_tolerance(epsilon, expected):
    group = SUBGROUPS['SE(3)']
    mu = np.array([epsilon, 0.0, 0.0, 0.0, 0.0, 1.0])
    iso = isotropy_algebra(group, mu)
    assert iso.dim == expected
    assert (iso.momentum_class is MomentumClass.PURE_ANGULAR) == (epsilon <= RANK_RTOL)


def test_zero_momentum_is_whole_group():
    iso = isotropy_algebra(SUBGROUPS['SE(3)'], np.full(6, 1e-14))
    assert iso.momentum_class is MomentumClass.ZERO and iso.dim == 6 and iso.orbit_dim == 0


def test_bracket_is_matrix_commutator():
    group = SUBGROUPS['SE(3)']
    rng = np.random.default_rng(2)
    x, y = rng.standard_normal(6), rng.standard_normal(6)
    hx, hy = pin.exp6(pin.Motion(1e-7 * x)), pin.exp6(pin.Motion(1e-7 * y))
    commutator = pin.log6(hx * hy * hx.inverse() * hy.inverse()).vector / 1e-14
    assert np.allclose(group.ad(x) @ y, commutator, atol=1e-5)


def test_adjoint_of_exponential():
    group = SUBGROUPS['SE(3)']
    eta = np.random.default_rng(3).standard_normal(6) * 0.3
    from scipy.linalg import expm
    assert np.allclose(group.Ad(group.exp(eta)), expm(group.ad(eta)), atol=1e-12)


def test_non_subalgebra_rejected():
    bad = np.zeros((6, 2))
    bad[3, 0] = bad[4, 1] = 1.0  # rotations about x and y do not close
    with pytest.raises(ValueError, match='not a Lie subalgebra'):
        BaseGroup('bad', bad)


@pytest.mark.parametrize('name', ['SE(3)', 'SE(2)'])
def test_chart_jacobian_matches_finite_differences(name):
    group = SUBGROUPS[name]
    rng = np.random.default_rng(4)
    mu = group.dual_coordinates(rng.standard_normal(6))
    iso = isotropy_algebra(group, mu)
    g_ref = group.exp(rng.standard_normal(group.dim))
    chart = CosetChart(group, iso.complement, g_ref)
    q = 0.2 * rng.standard_normal(chart.dim)
    jac = chart.body_jacobian(q)
    for j in range(chart.dim):
        dq = np.zeros(chart.dim)
        dq[j] = 1e-6
        fd = group.log(chart.point(q).inverse() * chart.point(q + dq)) / 1e-6
        assert np.allclose(jac[:, j], fd, atol=1e-6)
    # Re-centring keeps the point and the class.
    moved = chart.recentred(q)
    assert np.allclose(moved.point(np.zeros(chart.dim)).homogeneous,
                       chart.point(q).homogeneous)
