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

"""The structured backward step (core/smoother.py) against the dense one it replaced."""

from pathlib import Path

import numpy as np
import pytest

from filter_helpers import close_relative, filter_problem, STRUCTURED_TOLERANCE
from reduced_dynamics.estimator import smoother
from reduced_dynamics.estimator.core import smoother as structured
from reduced_dynamics.estimator.core import smoother_reference as dense
from reduced_dynamics.geometry.lie_group import SUBGROUPS
from reduced_dynamics.replay import replay, ReplayOptions
from reduced_dynamics.resources import config_path
from reduced_dynamics.robot.model import load_robot

DATA = Path(__file__).parent / 'data'
#: Relative tolerance against the dense reference (filter_helpers).
TOLERANCE = STRUCTURED_TOLERANCE
_close = close_relative


def _close_rows(got, want, filtered, tolerance: float = TOLERANCE) -> bool:
    """Per row, to ``tolerance`` of the larger of the row's smoothed and filtered size."""
    axes = tuple(range(1, want.ndim))
    scale = np.maximum(np.abs(want).max(axis=axes), np.abs(filtered).max(axis=axes))
    error = np.abs(got - want).max(axis=axes)
    return got.shape == want.shape and bool(np.all(error <= tolerance * scale))


def _step_problem(name: str, command: bool, seed: int) -> tuple:
    """Return a filtered step k and step k + 1's prediction and smoothed state."""
    rng, lin, flt, g, x, p = filter_problem(name, command, seed)
    group, n = SUBGROUPS[name], flt.n
    args = (g, x, p, lin.locked, lin.locked_inverse, lin.connection_qd, lin.joint_cov, 0.01,
            rng.normal(size=n), command, flt._jerk_var, flt._densities(lin), flt._basis,
            flt._pinv, flt._whole, flt._ad_rows, flt._form_rows)
    from reduced_dynamics.estimator.core import kernels
    g1, x1, p1, phi = kernels.propagate(*args)
    # A smoothed state of step k + 1 near its prediction, its covariance smaller.
    g_s = np.ascontiguousarray(group.exp(rng.normal(size=n) * 1e-3).homogeneous @ g1)
    x_s = x1 + rng.normal(size=x1.shape) * 1e-2
    p_s = 0.5 * p1
    return (g, x, p, phi, g1, x1, p1, g_s, x_s, p_s, flt._basis, flt._pinv, flt._whole)


@pytest.mark.parametrize('name,command', [('SE(3)', False), ('SE(2)', False),
                                          ('SE(2)', True)])
def test_structured_backward_step_equals_the_dense_reference(name: str, command: bool) -> None:
    """Pose, x and P of a step (3n: the mu-w chain's zeros; 5n: the command's rows)."""
    args = _step_problem(name, command, 5)
    got, want = structured.backward_step(*args), dense.backward_step(*args)
    for a, b in zip(got, want):
        assert _close(a, b)
    assert not np.array_equal(got[2], want[2])  # not the dense arithmetic itself
    assert np.array_equal(got[2], got[2].T)  # one triangle, mirrored
    p, phi, p_pred = args[2], args[3], args[6]
    assert _close(structured.smoother_gain(p, phi, p_pred), dense.gain(p, phi, p_pred))


def test_a_prediction_that_is_not_positive_definite_takes_the_lu_path() -> None:
    """No Cholesky factor: the dense solve's gain, not an exception."""
    g, x, p, phi, g1, x1, p1, *rest = _step_problem('SE(3)', False, 9)
    p1 = p1.copy()
    p1[0, 0] = -p1[0, 0]
    args = (g, x, p, phi, g1, x1, p1, *rest)
    for a, b in zip(structured.backward_step(*args), dense.backward_step(*args)):
        assert _close(a, b)


def test_a_block_pass_equals_the_dense_pass_with_restarts_and_seams() -> None:
    """backward_block over blocks of 3 (the carry between calls) against dense, whole."""
    steps = []
    for k in range(10):
        g, x, p, phi, g1, x1, p1, *_ = _step_problem('SE(3)', False, 20 + k)
        steps.append((k in (0, 6), phi, g1, x1, p1, g, x, p))
    # The fields as the replay's store gives them (views into records: one compiled variant).
    records = np.zeros(10, structured.step_dtype(6, 18, False))
    names = ('transition', 'pose_pred', 'x_pred', 'p_pred', 'pose', 'x', 'p')
    records['has_transition'] = [not s[0] for s in steps]
    for i, name in enumerate(names, 1):
        records[name] = [s[i] for s in steps]
    fields = [~records['has_transition']] + [records[name] for name in names]
    group = SUBGROUPS['SE(3)']
    whole = structured.smooth_arrays(group, *fields)
    for reference in (True, False):
        module = dense if reference else structured
        carry = (np.zeros((4, 4)), np.zeros(12), np.zeros((18, 18)))
        out = tuple(np.zeros_like(f) for f in (fields[5], fields[6], fields[7]))
        # Blocks of 2-3 steps, never one: a lone step's field views are C-contiguous, a
        # layout replay never passes (smoother.strided), compiled for this test alone.
        for first, end in ((8, 10), (6, 8), (3, 6), (0, 3)):
            part = [f[first:end] for f in fields]
            after = end < 10
            following = [f[end:end + 1] if after else f[:1] for f in fields[:5]]
            module.backward_block(*part, after, *following, *carry, group.algebra_basis,
                                  group.algebra_pinv, group.is_whole,
                                  *(o[first:end] for o in out))
        for got, want in zip(whole, out):
            assert _close(got, want) if reference else np.array_equal(got, want)


# --- every shipped bag: the smoothed rows with each backward step --------------------
#: bag -> (URDF ('' = the paper robot), load_robot's extra arguments, replay options)
BAGS = {
    'paper_constant': ('', {}, {}),
    'paper_realistic': ('', {}, {}),
    'paper_thruster': ('', {}, {}),
    'paper_spacecraft': ('', {}, {}),
    'planar_pose_only': ('robots/planar_testbed.urdf',
                         {'base_joint': 'planar', 'gravity': np.array([0.0, 0.0, -9.81])}, {}),
    # SE(2), poses, the commanded-wrench (5n) filter.
    'freeflyer_realistic': ('robots/freeflyer.urdf', {},
                            {'base_pose_topic': '/base_pose',
                             'commanded_wrench_topic': '/commanded_wrench'}),
    'freeflyer_testbed': ('robots/freeflyer.urdf', {},
                          {'base_pose_topic': '/base_pose',
                           'commanded_wrench_topic': '/commanded_wrench'}),
    'freeflyer2/rosbag2_2024_03_14-14_17_23': ('robots/freeflyer.urdf', {},
                                               {'base_pose_topic': '/vrpn_mocap/robot/pose'}),
}


@pytest.mark.parametrize('bag', sorted(BAGS))
def test_every_shipped_bag_smooths_to_the_dense_steps_rows(tmp_path, monkeypatch, bag):
    """Each smoothed row's fields (what the smoothed messages carry), to 1e-9 relative."""
    urdf, robot_args, options = BAGS[bag]
    robot = load_robot(str(config_path(urdf)) if urdf else '', **robot_args)
    compared = []
    smooth_rows = smoother.smooth_rows

    def both(group, steps, files, form_rows):
        rows = smooth_rows(group, steps, files, form_rows)
        got = np.concatenate(list(rows.blocks()))
        reference_files = smoother.SmootherFiles()
        with monkeypatch.context() as patch:
            patch.setattr(structured, 'backward_block', dense.backward_block)
            reference = smooth_rows(group, steps, reference_files, form_rows)
            want = np.concatenate(list(reference.blocks()))
        reference.close()
        reference_files.close()
        # The filtered rows' covariances: what the smoothed ones are computed from.
        records = np.concatenate([r.copy() for r in steps.blocks_backward()][::-1])
        filtered = np.zeros(len(got), got.dtype)
        # The filtered state in C-contiguous arrays, as smooth_rows passes its smoothed
        # state (its work arrays): the variant replay compiled, not one for this test.
        structured.row_fields(
            np.ascontiguousarray(records['pose']), np.ascontiguousarray(records['x']),
            np.ascontiguousarray(records['p']), records['locked_inverse'],
            records['command'] if steps.command else smoother.absent_command(group.dim),
            records['output'], steps.command, np.ascontiguousarray(group.algebra_basis),
            np.ascontiguousarray(group.algebra_pinv), group.is_whole, form_rows,
            filtered['mu'], filtered['pi'], filtered['rate'], filtered['drift'],
            filtered['disturbance'], filtered['mu_cov'], filtered['w_cov'])
        compared.append((got, want, filtered, steps.command))
        return rows

    monkeypatch.setattr(smoother, 'smooth_rows', both)
    replay(str(DATA / bag), str(tmp_path / 'out'), robot, ReplayOptions(smooth=True, **options))
    [(got, want, filtered, command)] = compared
    assert len(got) == len(want) > 100
    assert np.array_equal(got['stamp_ns'], want['stamp_ns'])
    for field in ('mu', 'pi', 'rate', 'drift') + (('disturbance',) if command else ()):
        assert _close(got[field], want[field]), field
    # P^s = P + C (P^s_{k+1} - P^-) C^T is a difference of terms of the filtered P's size:
    # at a bag's start (the prior's variances, 256 against a smoothed 3.5e-5 on
    # freeflyer_realistic) either step's rounding is ~1e-16 of those, 3e-9 of the result.
    for field in ('mu_cov', 'w_cov'):
        assert _close_rows(got[field], want[field], filtered[field]), field
