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

"""The structured filter step (core/kernels.py) against the dense one it replaced."""

import numbers
from pathlib import Path

import numpy as np
import pytest

from filter_helpers import close_relative, filter_problem, STRUCTURED_TOLERANCE
from reduced_dynamics.bag.reader import open_bag
from reduced_dynamics.estimator.core import kernels, reference
from reduced_dynamics.estimator.filter import Linearisation
from reduced_dynamics.geometry.lie_group import SUBGROUPS
from reduced_dynamics.replay import replay, ReplayOptions
from reduced_dynamics.robot.model import load_robot

DATA = Path(__file__).parent / 'data'
#: Relative tolerance against the dense reference (filter_helpers).
TOLERANCE = STRUCTURED_TOLERANCE
_close = close_relative


def _problem(name: str, command: bool, seed: int) -> tuple:
    rng, lin, flt, g, x, p = filter_problem(name, command, seed)
    group, n = SUBGROUPS[name], flt.n
    pose = np.ascontiguousarray(group.exp(rng.normal(size=n) * 1e-3).homogeneous @ g)
    return rng, lin, flt, g, x, p, pose


@pytest.mark.parametrize('name,with_twist,gate', [
    ('SE(3)', True, np.inf), ('SE(3)', False, np.inf), ('SE(2)', True, np.inf),
    ('SE(2)', False, np.inf), ('SE(3)', True, 0.0)])
def test_structured_step_equals_the_dense_reference(name: str, with_twist: bool,
                                                    gate: float) -> None:
    """Every result of the fused step: the dense algebra's to 1e-9 of its size."""
    rng, lin, flt, g, x, p, pose = _problem(name, False, 5)
    n = flt.n
    step = Linearisation(lin.locked, lin.locked_inverse * 1.01, lin.connection_qd * 0.9,
                         lin.joint_cov)
    measured = rng.normal(size=n) if with_twist else np.zeros(0)
    args = (g, x, p, step.locked, step.locked_inverse, step.connection_qd, step.joint_cov,
            0.01, flt._jerk_var, pose, measured, with_twist, lin.locked_inverse,
            lin.connection_qd, lin.joint_cov, flt._pose_var, rng.normal(size=n), 3e-3,
            flt._twist_var, gate, 0.25, flt._basis, flt._pinv, flt._whole, flt._ad_rows,
            flt._form_rows)
    structured, dense = kernels.propagate_update(*args), reference.propagate_update(*args)
    assert len(structured) == len(dense) == 18
    for got, want in zip(structured, dense):
        assert _close(got, want)
    # The updated covariance is symmetric to the bit (one triangle, mirrored).
    assert np.array_equal(structured[11], structured[11].T)


@pytest.mark.parametrize('with_twist', [True, False])
def test_commanded_filter_update_and_propagation_equal_the_dense_reference(
        with_twist: bool) -> None:
    """The 5n filter's update (H's zero columns now skipped) and propagation."""
    rng, lin, flt, g, x, p, pose = _problem('SE(2)', True, 7)
    n = flt.n
    update = (g, x, p, pose, rng.normal(size=n) if with_twist else np.zeros(0), with_twist,
              lin.locked_inverse, lin.connection_qd, lin.joint_cov, flt._pose_var,
              rng.normal(size=n), 3e-3, flt._twist_var, np.inf, flt._basis, flt._pinv,
              flt._whole, flt._form_rows)
    for got, want in zip(kernels.update(*update), reference.update(*update)):
        assert _close(got, want)
    propagate = (g, x, p, lin.locked, lin.locked_inverse, lin.connection_qd, lin.joint_cov,
                 0.01, rng.normal(size=n), True, flt._jerk_var, flt._densities(lin),
                 flt._basis, flt._pinv, flt._whole, flt._ad_rows, flt._form_rows)
    for got, want in zip(kernels.propagate(*propagate), reference.propagate(*propagate)):
        assert _close(got, want)


def test_gain_of_and_correct_equal_the_dense_reference() -> None:
    """The gate-reset path: a gain for any H, and the correction with it."""
    rng, lin, flt, g, x, p, pose = _problem('SE(3)', False, 11)
    n = flt.n
    h = np.zeros((n, flt.dim))
    h[:, :n] = np.eye(n)
    r = np.diag(flt._pose_var)
    gain = kernels.gain_of(p, h, r)
    assert _close(gain, reference.gain_of(p, h, r))
    nu = rng.normal(size=n) * 1e-3
    args = (g, x, p, pose, np.zeros(0), False, h, nu, r, gain, lin.locked_inverse,
            lin.connection_qd, flt._basis, flt._pinv, flt._whole, flt._form_rows)
    for got, want in zip(kernels.correct(*args), reference.correct(*args)):
        assert _close(got, want)


def test_an_indefinite_innovation_covariance_is_a_linear_algebra_error() -> None:
    """The Cholesky factor of S says so; the filter then takes its restart path."""
    rng, lin, flt, g, x, p, pose = _problem('SE(3)', False, 13)
    p = p.copy()
    p[0, 0] = -1.0
    with pytest.raises(np.linalg.LinAlgError):
        kernels.update(g, x, p, pose, np.zeros(0), False, lin.locked_inverse,
                       lin.connection_qd, lin.joint_cov, flt._pose_var, np.zeros(flt.n), 0.0,
                       flt._twist_var, np.inf, flt._basis, flt._pinv, flt._whole,
                       flt._form_rows)


# --- a shipped bag, replayed with each ---------------------------------------------------
#: The filter's own outputs (predictions' covariance ellipsoids come from an eigen-
#: decomposition whose near-equal axes turn by more than the state's rounding).
FILTER_TOPICS = ('/reduced_dynamics/momentum', '/reduced_dynamics/body_momentum',
                 '/reduced_dynamics/drift/momentum_rate', '/reduced_dynamics/drift/base_twist')


def _numbers(message, out: list) -> None:
    if isinstance(message, (bool, str, bytes)):
        return
    if isinstance(message, numbers.Number):
        out.append(float(message))
    elif isinstance(message, np.ndarray):
        out.extend(message.astype(float).ravel().tolist())
    elif isinstance(message, (list, tuple)):
        for item in message:
            _numbers(item, out)
    elif hasattr(message, '__dataclass_fields__'):
        for field in message.__dataclass_fields__:
            if field != 'header':
                _numbers(getattr(message, field), out)


def _filter_outputs(out: Path) -> dict:
    series: dict = {}
    with open_bag(str(out)) as reader:
        for message in reader.messages(FILTER_TOPICS):
            values: list = []
            _numbers(message.msg, values)
            series.setdefault(message.topic, []).append(values)
    return {topic: np.array(rows) for topic, rows in series.items()}


def test_a_shipped_bag_replays_to_the_dense_references_outputs(tmp_path, monkeypatch) -> None:
    """paper_realistic (SE(3), Odometry: iterated updates), causal, with each kernel set."""
    robot = load_robot()
    structured = tmp_path / 'structured'
    replay(str(DATA / 'paper_realistic'), str(structured), robot, ReplayOptions(smooth=False))
    for name in ('transition', 'propagate', 'gain_of', 'correct', 'update', 'update_noise',
                 'propagate_update'):
        monkeypatch.setattr(kernels, name, getattr(reference, name))
    dense = tmp_path / 'dense'
    replay(str(DATA / 'paper_realistic'), str(dense), robot, ReplayOptions(smooth=False))
    got, want = _filter_outputs(structured), _filter_outputs(dense)
    assert set(got) == set(want) == set(FILTER_TOPICS)
    for topic in FILTER_TOPICS:
        assert _close(got[topic], want[topic]), topic
