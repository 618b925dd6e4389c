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
The multi-scale test's two banks per update in one compiled call (core/bank_step.update).

The filtered bank: every window at every update (its T_L equal to the LU solve's to
rounding: test_multiscale_kernels.py). The block bank: window L evaluated on a grid
of stride L / GRID, its statistic what the block kernel (core/blocks.bank_statistics,
the per-update code before: LAPACK inverses) gives at an evaluation to rounding,
held between them, 0 while uncovered; its null learnt at evaluations with the same
memory in seconds. Through pushes, resets, events (not wanted), an unquiet null and
singular covariances.
"""

import math

import numpy as np
import pytest

from reduced_dynamics.estimator import momentum_blocks, multiscale, multiscale_twist
from reduced_dynamics.estimator.core import bank_step, blocks
from reduced_dynamics.estimator.multiscale import MultiScaleTest

from filter_helpers import assert_equal_arrays


def _excess_minimum(monkeypatch: pytest.MonkeyPatch, value: int) -> None:
    """Set EXCESS_MINIMUM in every module that reads it (the multi-scale test's parts)."""
    for module in (multiscale, momentum_blocks, multiscale_twist):
        monkeypatch.setattr(module, 'EXCESS_MINIMUM', value)


def _full_block_statistics(test: MultiScaleTest, stamp_ns: int) -> np.ndarray:
    """Return every block window's raw T_L at ``stamp_ns`` (0: not covered)."""
    measured = test.blocks
    first = int(measured._stamps[0])
    first = first if test.floor_ns is None else max(test.floor_ns, first)
    found, values = blocks.bank_statistics(
        *measured._arrays(), measured._common, measured._stamps, measured._end,
        measured._lags_ns, stamp_ns, first, measured.mass, measured.linear)
    return values if found else np.zeros(len(test.windows))


def _inputs(n: int, d: int, seconds: float, rate: float, seed: int) -> list:
    """Return per update (stamp, mu, cov, measured, wanted, quiet, reset, singular)."""
    rng = np.random.default_rng(seed)
    out = []
    mu_true = np.zeros(n)
    noise = np.diag(np.linspace(1.0, 2.0, n)) * 2.5e-3
    root = rng.standard_normal((n, n)) * 1e-3
    fixed = root @ root.T + 1e-6 * np.eye(n)
    for k in range(int(seconds * rate)):
        stamp = 10 ** 9 + int(round(k * 1e9 / rate))
        t = k / rate
        if 2.0 <= t < 2.6 or 5.0 <= t < 5.1:
            mu_true = mu_true + 0.15 / rate  # pushes: a long one and a short one
        cov = fixed
        mu = mu_true + rng.standard_normal(n) * 1e-3
        measured_mu = mu_true + rng.standard_normal(n) * 5e-2
        position = None
        if d:
            position = (rng.standard_normal(d) * 1e-3 + t * 0.01, 1e-6 * np.eye(d), 5.0,
                        tuple(range(d)))
        common = 1e-7 * np.eye(n)
        measured = [(stamp, measured_mu, noise, common, position)] if k % 3 else None
        singular = k in (700, 701)
        if singular:
            cov = -fixed  # V_L = 0 for every window reaching it: its solve raises
        out.append((stamp, mu, cov, measured, k % 50 < 35, (k // 200) % 3 != 1,
                    k in (450, 900), singular))
    return out


def _state(test: MultiScaleTest) -> list:
    blocks = test.blocks
    return [test.statistics.copy(), test._above.copy(), test.inflation.copy(),
            blocks.statistics.copy(), test._stamps[:test._end].copy(),
            test._mu[:test._end].copy(), np.array([test._start, test._end, test.threshold,
                                                   test._period or 0.0])]


@pytest.mark.parametrize('n,d', [(6, 3), (3, 2), (3, 0)])
def test_the_block_bank_is_evaluated_on_its_grid_and_held_between(n, d, monkeypatch) -> None:
    """At an evaluation the block kernel's T_L (to rounding), between them the last one."""
    _excess_minimum(monkeypatch, 50)
    test = MultiScaleTest(n, 50.0)
    found = {'filtered': 0, 'blocks': 0}
    evaluations = np.zeros(len(test.windows), dtype=int)
    covered_updates = np.zeros(len(test.windows), dtype=int)
    singular_seen = 0
    inputs = _inputs(n, d, 8.0, 100.0, n)
    for stamp, mu, cov, measured, wanted, quiet, reset, singular in inputs:
        test.quiet = quiet
        if reset:
            test.reset(stamp - 10 ** 8)
        slots = test._grid[1].copy()
        held = test.blocks.statistics.copy()
        out = test.update(stamp, mu, cov, measured, wanted)
        inflation = test.inflation[1]  # recomputed before the banks every 256 updates
        if out is not None:
            found['blocks' if out.measured else 'filtered'] += 1
        if singular:
            # V_L = 0 for every window: not positive, no filtered statistic.
            assert not test.statistics.any()
            singular_seen += 1
        if not (test.blocks.active and test.blocks.ready and test.blocks._end >= 4):
            continue
        full = _full_block_statistics(test, stamp)
        evaluated = (test._grid[1] != slots) & (test._grid[1] >= 0)
        live = test._grid[1] >= 0
        if out is not None and out.measured:
            # A detection reads every window at its sample (then located).
            np.testing.assert_array_equal(test.blocks.statistics, full / inflation)  # numpy's
            evaluations += evaluated
            covered_updates += live
            continue
        np.testing.assert_allclose(test.blocks.statistics[evaluated],
                                   full[evaluated] / inflation[evaluated], rtol=1e-9, atol=0.0)
        np.testing.assert_array_equal(test.blocks.statistics[live & ~evaluated],
                                      held[live & ~evaluated])
        assert not test.blocks.statistics[~live].any()
        evaluations += evaluated
        covered_updates += live
    assert found['filtered'] and found['blocks'], found
    assert singular_seen == 2
    # Each window about once per stride of L / GRID (at 100 Hz the short ones every update).
    stride_updates = np.maximum(1.0, test.windows / bank_step.GRID * 100.0)
    covered = covered_updates > 0
    assert covered.sum() >= 8
    expected = covered_updates[covered] / stride_updates[covered]
    assert np.all(evaluations[covered] <= expected + 12)
    assert np.all(evaluations[covered] >= 0.5 * expected)
    slow = covered & (stride_updates >= 4)
    assert slow.any() and np.all(evaluations[slow] <= 0.5 * covered_updates[slow])
    assert math.isfinite(test.threshold)


def test_the_grid_learns_the_block_null_at_the_per_update_rate(monkeypatch) -> None:
    """The learnt fraction above the median on the grid tracks learning at every update."""
    _excess_minimum(monkeypatch, 50)
    test = MultiScaleTest(6, 50.0, calibration_memory=1.0)
    reference = np.full(len(test.windows), 0.5)
    for stamp, mu, cov, measured, _, _, _, _ in _inputs(6, 3, 8.0, 100.0, 11):
        if stamp > 10 ** 9 + 1.9e9:
            break  # before the first push: no wrench, the null
        test.quiet = True
        test.update(stamp, mu, cov, measured, False)
        if not (test.blocks.active and test.blocks.ready and test.blocks._end >= 4) or \
                test._period is None:
            continue
        raw = _full_block_statistics(test, stamp)
        rate = min(1.0, test._period / test.calibration_memory)
        learn = raw > 0.0
        reference[learn] += rate * ((raw[learn] > test._median) - reference[learn])
    learnt = test._grid[1] >= 0
    assert learnt.sum() >= 5
    # Both moved off 0.5 by the same amount, to the sampling of the grid.
    np.testing.assert_allclose(test._above[1][learnt], reference[learnt], atol=0.08)
    assert np.abs(reference[learnt] - 0.5).max() > 0.2


def test_no_detection_is_formed_when_the_caller_has_no_use_for_it(monkeypatch) -> None:
    """An event open (not wanted): statistics updated, the pulse's dating not computed."""
    formed = []
    real = multiscale.ImpulseDetection

    def counted(*args, **kwargs):
        formed.append(1)
        return real(*args, **kwargs)
    monkeypatch.setattr(multiscale, 'ImpulseDetection', counted)
    test = MultiScaleTest(6, 50.0)
    above = 0
    for stamp, mu, cov, measured, _, _, _, _ in _inputs(6, 3, 8.0, 100.0, 6):
        assert test.update(stamp, mu, cov, measured, wanted=False) is None
        above += bool(test.statistics.max() > test.threshold)
    assert above > 10 and not formed


def _twist_samples(seconds: float, rate: float, seed: int) -> list:
    """Return per update (stamp, mu, cov, [TwistSample], wanted, quiet, reset): an SE(3) base."""
    import pinocchio as pin
    from reduced_dynamics.geometry.lie_group import SUBGROUPS
    rng = np.random.default_rng(seed)
    structure = SUBGROUPS['SE(3)'].structure_constants
    locked = pin.Inertia(16.0, np.array([0.05, -0.02, 0.1]),
                         np.diag([0.4, 0.5, 0.6])).matrix()
    twist_cov, pose_noise = np.diag(np.full(6, 1e-4)), np.diag(np.full(6, 1e-6))
    joint_cov = np.diag(np.full(6, 1e-5))
    root = rng.standard_normal((6, 6)) * 1e-3
    fixed = root @ root.T + 1e-6 * np.eye(6)
    xi_true = np.zeros(6)
    out = []
    for k in range(int(seconds * rate)):
        stamp = 10 ** 9 + int(round(k * 1e9 / rate))
        t = k / rate
        if 2.0 <= t < 2.6 or 5.0 <= t < 5.1:
            xi_true = xi_true + 0.2 / rate  # pushes: a long one and a short one
        g = pin.exp6(pin.Motion(xi_true * t + rng.standard_normal(6) * 1e-4))
        p = rng.standard_normal((18, 18)) * 1e-3
        p = p @ p.T + 1e-8 * np.eye(18)
        sample = multiscale.TwistSample(
            stamp, g.actionInverse, locked + rng.standard_normal((6, 6)) * 1e-6,
            xi_true + rng.standard_normal(6) * 1e-2, rng.standard_normal(6) * 1e-3,
            twist_cov, joint_cov, p[:6, :6], structure, g.rotation, g.translation,
            pose_noise, locked + rng.standard_normal((6, 6)) * 1e-6)
        mu = locked @ xi_true + rng.standard_normal(6) * 1e-3
        out.append((stamp, mu, fixed, [sample], k % 50 < 35, (k // 200) % 3 != 1,
                    k in (450, 900)))
    return out


def _blocks_state(test: MultiScaleTest) -> list:
    """Return the block test's arrays (rings to their end, excess, last sample)."""
    b = test.blocks
    return [b._stamps[:b._end].copy(), *(a[:b._end].copy() for a in b._arrays()),
            b._common[:b._end].copy(), b._excess_raw.copy(), b.excess.copy(),
            np.array([b._end, b._differences, b.mass, b._origin_ns]),
            *(np.array(a, copy=True) for a in (b._last or ()))]


def _fed_alike(fused: MultiScaleTest, separate: MultiScaleTest, seconds: float,
               each=None) -> int:
    """
    Feed ``fused`` twists and ``separate`` their momenta (the calls before); return detections.

    Every statistic, ring, calibration and detection must be equal bit for bit after each
    update; ``each`` (if given) is called after each update of ``fused``.
    """
    found = 0
    for stamp, mu, cov, measured, wanted, quiet, reset in _twist_samples(seconds, 100.0, 5):
        outs = []
        for test, items in ((fused, measured), (separate, [m.momentum() for m in measured])):
            test.quiet = quiet
            if reset:
                test.reset(stamp - 10 ** 8)
            outs.append(test.update(stamp, mu, cov, items, wanted))
            if each is not None and test is fused:
                each()
        assert (outs[0] is None) == (outs[1] is None)
        if outs[0] is not None:
            found += 1
            for mine, want in zip(outs[0], outs[1]):
                assert_equal_arrays(mine, want)
        for mine, want in zip(_state(fused) + _blocks_state(fused),
                              _state(separate) + _blocks_state(separate)):
            assert_equal_arrays(mine, want)
    return found


def test_the_fused_twist_call_gives_the_bits_of_the_calls_it_replaces(monkeypatch) -> None:
    """
    bank_step.twist_step = TwistSample.momentum, prepare and update_with_sample.

    Two tests fed the same updates, one the twists (the momentum computed in the banks'
    call), one their momenta computed from Python (the calls before): every statistic,
    ring, calibration and detection bit for bit, through pushes, resets, open events
    (not wanted), an unquiet null, ring growth and the excess decompositions.
    """
    _excess_minimum(monkeypatch, 50)
    calls = {'twist_step': 0}
    # (Only the outermost kernel is wrapped: a kernel compiled while one it calls is a
    # Python wrapper could not be.)

    def counted(*args, _function=bank_step.twist_step):
        calls['twist_step'] += 1
        return _function(*args)
    monkeypatch.setattr(bank_step, 'twist_step', counted)
    fused = MultiScaleTest(6, 50.0)
    assert _fed_alike(fused, MultiScaleTest(6, 50.0), 8.0)
    # The fused call took most samples (not the first two, the decompositions due).
    assert calls['twist_step'] > 700 and fused.blocks._capacity > 256


def test_a_compiled_call_that_disagrees_with_the_checks_takes_the_general_path(
        monkeypatch) -> None:
    """
    twist_step answering UNCOMMON after _checked_twist's checks passed: no loop.

    Nothing moves in such a call; the update then takes MultiScaleTest.update's
    general path once (the bits of a test fed the momenta), never the checks again.
    """
    _excess_minimum(monkeypatch, 50)
    calls = {'twist_step': 0}

    def disagreeing(*args):
        calls['twist_step'] += 1
        return bank_step.UNCOMMON
    monkeypatch.setattr(bank_step, 'twist_step', disagreeing)
    updates = []

    def one_call_at_most():
        updates.append(calls['twist_step'])
        assert len(updates) < 2 or updates[-1] - updates[-2] <= 1  # per update

    _fed_alike(MultiScaleTest(6, 50.0), MultiScaleTest(6, 50.0), 3.0, one_call_at_most)
    assert calls['twist_step'] > len(updates) // 2  # the checked call was made, and refused
