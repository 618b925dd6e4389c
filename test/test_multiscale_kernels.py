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

"""The multi-scale test's compiled per-update arithmetic equals the numpy it replaced."""

import os
from pathlib import Path
import subprocess
import sys
from typing import Optional

import numpy as np

from reduced_dynamics.estimator.core import blocks
from reduced_dynamics.estimator.multiscale import (EXCESS_MINIMUM, EXCESS_SAMPLES,
                                                   MomentumBlocks, MultiScaleTest)


def _numpy_statistics(test: MultiScaleTest, stamp_ns: int, mu: np.ndarray,
                      cov: np.ndarray, above: np.ndarray) -> Optional[np.ndarray]:
    """Return the calibrated statistics as the numpy code computed them (main 3a3a89e)."""
    stamps = test._stamps[test._start:test._end]
    index = np.searchsorted(stamps, stamp_ns - test._lags_ns, 'right') - 1
    floor = test.floor_ns
    covered = (index >= 0) & (stamps[np.maximum(index, 0)] >= (
        stamps[0] if floor is None else max(floor, int(stamps[0]))))
    statistics = np.zeros(len(test.windows))
    if not covered.any():
        return statistics
    rows = index[covered] + test._start
    d = mu - test._mu[rows]
    v = cov + test._cov[rows]
    solved = np.linalg.solve(v, d[..., None])[..., 0]
    statistics[covered] = np.einsum('ij,ij->i', d, solved)
    if test.quiet and test._period is not None:
        learn = statistics > 0.0
        rate = min(1.0, test._period / test.calibration_memory)
        above[learn] += rate * ((statistics[learn] > test._median) - above[learn])
    return statistics / test.inflation[0]


def test_the_compiled_window_statistics_equal_the_numpy_ones_to_rounding() -> None:
    """
    Random momenta and covariances, a floor, events (not quiet), rate changes, ring wraps.

    The compiled T_L is a Cholesky factor's forward substitution (core/bank_step.py), the
    numpy one an LU solve: equal to rounding, the learnt null the same.
    """
    rng = np.random.default_rng(7)
    for n in (6, 3):
        test = MultiScaleTest(n, 1.0)
        above = test._above[0].copy()
        stamp = 0
        compared = 0
        for k in range(1500):
            stamp += int(rng.choice([1_000_000, 5_000_000, 20_000_000]))
            root = rng.standard_normal((n, n)) * 1e-2
            cov = root @ root.T + 1e-6 * np.eye(n)
            mu = rng.standard_normal(n) * 1e-2 + 0.02 * (k > 900)
            if k == 600:
                test.reset(stamp - 200_000_000)
            test.quiet = not 700 <= k < 800
            test.update(stamp, mu, cov)
            if test._period is None:
                continue
            # The reference on the state the update computed with (this sample stored,
            # the period and the inflation as the update left them).
            expected = _numpy_statistics(test, stamp, mu, cov, above)
            np.testing.assert_allclose(test.statistics, expected, rtol=1e-10, atol=0.0)
            np.testing.assert_allclose(test._above[0], above, rtol=1e-12, atol=0.0)
            compared += int(np.count_nonzero(expected))
        assert compared > 1000


def test_the_filtered_bank_marks_the_windows_the_floor_leaves_uncovered() -> None:
    """Rows of the windows reaching back before the floor, or before the data, are -1."""
    from reduced_dynamics.estimator.core.bank_windows import filtered_bank
    stamps = np.arange(0, 1_000_000_000, 10_000_000, dtype=np.int64)
    mu_ring = np.arange(len(stamps), dtype=float)[:, None] * np.ones(3)
    cov_ring = np.tile(np.eye(3), (len(stamps), 1, 1))
    lags = np.array([50_000_000, 300_000_000, 2_000_000_000])
    now, last = int(stamps[-1]), len(stamps) - 1
    # C-contiguous arrays, as bank_step.update passes them (the variant it compiled).
    rows, raw = np.zeros(3, dtype=np.int64), np.zeros(3)
    work, y, d = np.zeros((3, 3)), np.zeros(3), np.zeros(3)
    # The bank stores the sample first (here the last row again, the same values).
    covered = filtered_bank(stamps, mu_ring, cov_ring, 0, last, lags, now, 0, False,
                            mu_ring[-1].copy(), np.eye(3), rows, raw, work, y, d)
    assert covered == 2 and rows.tolist() == [94, 69, -1]
    # d_L = 5 and 30 on each axis, V_L = 2 I: T_L = 3 d^2 / 2; an uncovered window 0.
    np.testing.assert_allclose(raw, [37.5, 1350.0, 0.0], rtol=1e-14, atol=0.0)
    covered = filtered_bank(stamps, mu_ring, cov_ring, 0, last, lags, now,
                            now - 100_000_000, True, mu_ring[-1].copy(), np.eye(3), rows, raw,
                            work, y, d)
    assert covered == 1 and rows.tolist() == [94, -1, -1]


class NumpyBlocks(MomentumBlocks):
    """The block test's per-sample code as it was in numpy (main 3a3a89e)."""

    def _learn_excess(self, mu: np.ndarray, cov: np.ndarray) -> None:
        last, self._last = self._last, (mu, cov)
        if last is None:
            return
        d = mu - last[0]
        sample = 0.5 * (np.outer(d, d) - cov - last[1])
        self._differences += 1
        self._excess_raw += (sample - self._excess_raw) / min(self._differences,
                                                              EXCESS_SAMPLES)
        if self._differences % 16 == 1 or self._differences == EXCESS_MINIMUM:
            values, vectors = np.linalg.eigh(self._excess_raw)
            self.excess = (vectors * np.maximum(values, 0.0)) @ vectors.T

    def add(self, stamp_ns: int, mu: np.ndarray, cov: np.ndarray,
            common: Optional[np.ndarray] = None,
            position: Optional[tuple] = None) -> None:
        if self._end and stamp_ns <= self._stamps[self._end - 1]:
            return
        self._learn_excess(mu, cov)
        try:
            info = np.linalg.inv(cov + self.excess)
            lam = None if position is None else np.linalg.inv(position[1])
        except np.linalg.LinAlgError:
            return
        if lam is not None and not len(self.linear):
            self.linear = np.asarray(position[3], dtype=np.int64)
            self.mass = float(position[2])
            self._positions = self._position_arrays(self._capacity, len(self.linear))
        if self._end == self._capacity:
            self._compact(stamp_ns)
        k = self._end
        if not k:
            self._origin_ns = stamp_ns
        self._stamps[k] = stamp_ns
        self._common[k] = 0.0 if common is None else common
        blocks.accumulate(self._info, self._score, k, info, mu)
        if len(self.linear):
            present = lam is not None and len(position[0]) == len(self.linear)
            d = len(self.linear)
            blocks.accumulate_position(
                *self._positions, k, lam if present else np.zeros((d, d)),
                (stamp_ns - self._origin_ns) * 1e-9,
                np.asarray(position[0], float) if present else np.zeros(d), present)
        self._end += 1
        self.active = True

    def update(self, stamp_ns: int, floor_ns: Optional[int]) -> int:
        self.statistics[:] = 0.0
        if self._end < 4 or not self.ready:
            return -1
        stamps = self._stamps[:self._end]
        first = int(stamps[0]) if floor_ns is None else max(floor_ns, int(stamps[0]))
        bounds = stamp_ns - np.outer(self._lags_ns, np.arange(3, -1, -1))
        index = np.searchsorted(stamps, bounds, 'right') - 1
        # Both blocks hold samples, and the before block starts within the data.
        covered = (bounds[:, 0] >= first) & (index[:, 1] > index[:, 0]) & \
            (index[:, 3] > index[:, 2])
        if not covered.any():
            return -1
        rows = np.ascontiguousarray(index[covered])
        try:
            values = blocks.window_statistics(*self._arrays(), self._common, rows,
                                              self.mass, self.linear)
        except np.linalg.LinAlgError:
            return -1
        self.statistics[covered] = values
        return int(np.argmax(self.statistics))


def test_the_compiled_block_test_equals_the_numpy_one_bit_for_bit() -> None:
    """Random measured momenta with and without positions: prefix sums, excess, statistics."""
    rng = np.random.default_rng(11)
    for n, d in ((6, 3), (3, 2), (6, 0)):
        windows = np.array([0.02, 0.05, 0.1, 0.3])
        mine, reference = MomentumBlocks(n, windows), NumpyBlocks(n, windows)
        stamp = 0
        compared = 0
        for k in range(EXCESS_MINIMUM + 400):
            stamp += int(rng.choice([1_000_000, 4_000_000, 10_000_000]))
            root = rng.standard_normal((n, n)) * 1e-2
            cov = root @ root.T + 1e-6 * np.eye(n)
            mu = rng.standard_normal(n) * 1e-2
            common = np.eye(n) * 1e-8 * k
            position = None
            if d and k % 3:
                proot = rng.standard_normal((d, d)) * 1e-3
                position = (rng.standard_normal(d), proot @ proot.T + 1e-9 * np.eye(d), 7.0,
                            tuple(range(d)))
            for bank in (mine, reference):
                bank.add(stamp, mu, cov, common, position)
            floor = None if k < 450 else stamp - 150_000_000
            assert mine.update(stamp, floor) == reference.update(stamp, floor)
            np.testing.assert_array_equal(mine.statistics, reference.statistics)
            compared += int(np.count_nonzero(mine.statistics))
        np.testing.assert_array_equal(mine.excess, reference.excess)
        for a, b in zip(mine._arrays(), reference._arrays()):
            np.testing.assert_array_equal(a, b)
        assert compared > 500


def _numpy_twist_momentum(ad_inverse, locked, connection_qd, twist, twist_cov, joint_cov,
                          pose_cov, kirillov):
    """multiscale.twist_momentum as it was in numpy (main 3a3a89e)."""
    pi = locked @ (twist + connection_qd)
    to_world = ad_inverse.T
    white = to_world @ locked @ (twist_cov + joint_cov) @ locked.T @ to_world.T
    w = to_world @ kirillov(pi)
    return to_world @ pi, white, w @ pose_cov @ w.T


def _numpy_centre_of_mass_se3(pose, locked, pose_cov):
    """multiscale.centre_of_mass's SE(3) branch as it was in numpy (main 3a3a89e)."""
    mass = float(locked[0, 0])
    c = np.array([locked[1, 5], locked[2, 3], locked[0, 4]]) / mass
    rotation = pose.rotation
    jacobian = np.zeros((3, 6))
    jacobian[:, :3] = rotation
    jacobian[:, 3:] = -rotation @ np.array([[0.0, -c[2], c[1]], [c[2], 0.0, -c[0]],
                                            [-c[1], c[0], 0.0]])
    world = pose.translation + rotation @ c
    return world, jacobian @ pose_cov @ jacobian.T, mass


def test_measured_momenta_and_centre_of_mass_equal_the_numpy_ones_bit_for_bit() -> None:
    """Poses from Pinocchio, the filter covariance's block as a strided view (as the filter)."""
    import pinocchio as pin
    from reduced_dynamics.estimator.multiscale import centre_of_mass, twist_momentum
    from reduced_dynamics.geometry.lie_group import SUBGROUPS
    rng = np.random.default_rng(5)
    group = SUBGROUPS['SE(3)']
    for _ in range(500):
        g = pin.SE3.Random()
        root = rng.standard_normal((6, 6))
        locked = root @ root.T + 6.0 * np.eye(6)
        p = rng.standard_normal((18, 18))
        p = p @ p.T
        args = (g.actionInverse, locked, rng.standard_normal(6), rng.standard_normal(6),
                np.diag(rng.uniform(0.1, 1.0, 6)), np.diag(rng.uniform(0.1, 1.0, 6)),
                p[:6, :6], group.coadjoint_form)
        for mine, expected in zip(twist_momentum(*args), _numpy_twist_momentum(*args)):
            np.testing.assert_array_equal(mine, expected)
        mine = centre_of_mass('SE(3)', g, locked, p[:6, :6])
        expected = _numpy_centre_of_mass_se3(g, locked, p[:6, :6])
        for a, b in zip(mine[:3], expected):
            np.testing.assert_array_equal(a, b)
        assert mine[3] == (0, 1, 2)


def test_warm_up_loads_the_impulse_kernels_with_the_estimators_argument_types() -> None:
    """A fresh process: after warm_up, an estimator's run compiles no new signature."""
    from filter_helpers import fresh_process_words
    code = ('from reduced_dynamics.estimator.core.warmup import warm_up; warm_up(); '
            'from reduced_dynamics.estimator.core import impulse as i; '
            'from reduced_dynamics.estimator.core import bank_step as s; '
            'from reduced_dynamics.robot.model import load_robot; '
            'from reduced_dynamics.bench import update_samples; '
            'from reduced_dynamics.estimator.pipeline import Estimator; '
            'kernels = (s.update, s.update_with_sample, s.twist_step, '
            'i.measured_momentum_se3); '
            'before = [len(k.signatures) for k in kernels]; '
            'robot = load_robot(); joints, bases = update_samples(robot, 300); '
            'e = Estimator(robot); '
            'e.add_samples([m for pair in zip(joints, bases) for m in pair]); '
            'print(min(before) > 0, before == [len(k.signatures) for k in kernels])')
    assert fresh_process_words(code) == ['True', 'True']


def _fit_grid(rng: np.random.Generator, samples: int) -> tuple[np.ndarray, ...]:
    """Return sample times and the (start, end) pairs MomentumBlocks.locate fits."""
    times = (np.cumsum(rng.integers(900_000, 1_100_000, samples)) - 1_000_000 * samples) * 1e-9
    times = times - times[-1]
    times[-1] = 0.0 * 1e-9  # the newest sample: its own stamp minus itself
    grid = np.unique(np.linspace(0, samples - 1, 40).round().astype(int))
    starts, ends = np.meshgrid(times[grid], times[grid], indexing='ij')
    keep = ends > starts
    return times, starts[keep], ends[keep]


def test_the_pulse_fits_ramps_are_numpys_bit_for_bit() -> None:
    """The ramps of locate and _position_rows, compiled, are the numpy expressions' bits."""
    rng = np.random.default_rng(7)
    for samples in (5, 77, 400):
        times, starts, ends = _fit_grid(rng, samples)
        ramp, square = np.empty((2, len(starts), len(times)))
        blocks.pulse_ramps(times, starts, ends, ramp, square)
        expected = np.clip((times[None, :] - starts[:, None]) / (ends - starts)[:, None],
                           0.0, 1.0)
        assert ramp.tobytes() == expected.tobytes()
        assert square.tobytes() == (expected ** 2).tobytes()
        # The positions' ramp integral, as _position_rows computed it.
        span = (ends - starts)[:, None]
        during = np.clip(times[None, :] - starts[:, None], 0.0, span)
        integral = during ** 2 / (2.0 * span) + np.maximum(times[None, :] - ends[:, None], 0.0)
        ramp, timed, squared = np.empty((3, len(starts), len(times)))
        blocks.position_ramps(times, starts, ends, ramp, timed, squared)
        assert ramp.tobytes() == integral.tobytes()
        assert timed.tobytes() == (integral * times[None, :]).tobytes()
        assert squared.tobytes() == (integral ** 2).tobytes()


def _detection_fields(detection: tuple) -> bytes:
    """Return a BlockDetection's fields as bytes (bit-for-bit comparison)."""
    return b''.join(np.asarray(field, dtype=float).tobytes() for field in detection)


def test_locate_keeps_its_ramps_work_space_without_changing_a_bit(monkeypatch) -> None:
    """A pulse fit in the kept work space (dirty from the last) equals one in fresh arrays."""
    from reduced_dynamics.estimator import block_pulse, multiscale
    rng = np.random.default_rng(3)
    test = MomentumBlocks(6, multiscale.window_bank())
    mu = np.zeros(6)
    for k in range(700):
        stamp = 1_000_000_000 + k * 1_000_000 + int(rng.integers(-50_000, 50_000))
        if 500 <= k < 560:  # a push: the momentum ramps
            mu = mu + np.array([0.02, -0.01, 0.0, 0.0, 0.005, 0.0])
        centre = np.array([0.001 * k, 0.0, 0.5]) + 1e-4 * rng.standard_normal(3)
        test.add(stamp, mu + 1e-3 * rng.standard_normal(6), 1e-6 * np.eye(6),
                 1e-8 * np.eye(6), (centre, 1e-8 * np.eye(3), 12.0, (0, 1, 2)))
    stamp = int(test._stamps[test._end - 1])
    kept = [_detection_fields(test.locate(stamp, window, None)) for window in (1, 2, 1)]
    assert test._fit_scratch is not None  # these fits used the kept work space
    monkeypatch.setattr(block_pulse, 'FIT_SCRATCH', 0)
    fresh = [_detection_fields(test.locate(stamp, window, None)) for window in (1, 2, 1)]
    assert kept == fresh
    assert kept[0] == kept[2] and kept[0] != kept[1]


def _numpy_locate(test: MomentumBlocks, stamp_ns: int, window: int,
                  floor_ns: Optional[int]) -> tuple:
    """Return locate's detection, normal equations and right-hand sides as numpy built them."""
    stamps = test._stamps[:test._end]
    lo_ns = stamp_ns - 3 * int(test._lags_ns[window])
    lo_ns = lo_ns if floor_ns is None else max(lo_ns, floor_ns)
    lo = max(int(np.searchsorted(stamps, lo_ns, 'right')) - 1, -1)
    hi = test._end - 1
    index = np.arange(lo + 1, hi + 1)
    previous = np.concatenate(([lo], index[:-1]))
    first, low = previous < 0, np.maximum(previous, 0)
    info_k = test._info[index] - np.where(first[:, None, None], 0.0, test._info[low])
    score_k = test._score[index] - np.where(first[:, None], 0.0, test._score[low])
    n = test.n
    times = (stamps[index] - stamps[hi]) * 1e-9
    grid = np.unique(np.linspace(0, len(index) - 1, 40).round().astype(int))
    starts, ends = np.meshgrid(times[grid], times[grid], indexing='ij')
    keep = ends > starts
    starts, ends = starts[keep], ends[keep]
    ramp = np.clip((times[None, :] - starts[:, None]) / (ends - starts)[:, None], 0.0, 1.0)
    flat_info = info_k.reshape(len(index), n * n)
    cross = (ramp @ flat_info).reshape(-1, n, n)
    d = len(test.linear)
    size = 2 * n + d
    normal = np.zeros((len(starts), size, size))
    rhs = np.zeros((len(starts), size))
    mu0, c0, jj = slice(0, n), slice(n, n + d), slice(size - n, size)
    normal[:, mu0, mu0] = flat_info.sum(axis=0).reshape(n, n)
    normal[:, jj, mu0] = cross
    normal[:, mu0, jj] = cross.transpose(0, 2, 1)
    normal[:, jj, jj] = ((ramp ** 2) @ flat_info).reshape(-1, n, n)
    rhs[:, mu0] = score_k.sum(axis=0)
    rhs[:, jj] = ramp @ score_k
    s0, _, _, y0, _, counts = test._positions
    present = (counts[index] - np.where(first, 0, counts[low])) > 0 if d else index < 0
    if present.sum() >= 2:
        lam = (s0[index] - np.where(first[:, None, None], 0.0, s0[low]))[present]
        weighted = (y0[index] - np.where(first[:, None], 0.0, y0[low]))[present]
        t = times[present]
        c = np.linalg.solve(lam, weighted[..., None])[..., 0]
        c = c - c.mean(axis=0)
        span = (ends - starts)[:, None]
        integral = np.clip(t[None, :] - starts[:, None], 0.0, span) ** 2 / (2.0 * span) \
            + np.maximum(t[None, :] - ends[:, None], 0.0)
        flat = lam.reshape(len(t), d * d)
        sums = {name: (weights @ flat).reshape(-1, d, d) for name, weights in (
            ('R', integral), ('tR', integral * t[None, :]), ('RR', integral ** 2))}
        p0, p1, p2 = (((t ** j)[None, :] @ flat).reshape(d, d) for j in range(3))
        pc = np.einsum('kij,kj->ki', lam, c)
        select = np.zeros((d, n))
        select[np.arange(d), test.linear] = 1.0
        st, mass = select.T, test.mass
        normal[:, mu0, mu0] += st @ p2 @ select / mass ** 2
        normal[:, mu0, c0] += st @ p1 / mass
        normal[:, c0, mu0] += p1 @ select / mass
        normal[:, c0, c0] += p0
        coupling = st @ sums['tR'] @ select / mass ** 2
        normal[:, mu0, jj] += coupling
        normal[:, jj, mu0] += coupling
        normal[:, c0, jj] += sums['R'] @ select / mass
        normal[:, jj, c0] += st @ sums['R'] / mass
        normal[:, jj, jj] += st @ sums['RR'] @ select / mass ** 2
        rhs[:, mu0] += (st @ (t @ pc)) / mass
        rhs[:, c0] += pc.sum(axis=0)
        rhs[:, jj] += (integral @ pc) @ select / mass
    nuisance = slice(0, size - n)
    try:
        inverse = np.linalg.inv(normal[:, nuisance, nuisance])
        couple = normal[:, jj, nuisance]
        schur = normal[:, jj, jj] - couple @ inverse @ couple.transpose(0, 2, 1)
        residual = rhs[:, jj] - (couple @ (inverse @ rhs[:, nuisance, None]))[..., 0]
        impulse = np.linalg.solve(schur, residual[..., None])[..., 0]
    except np.linalg.LinAlgError:
        impulse = residual = np.zeros((len(starts), n))
    values = np.einsum('ij,ij->i', residual, impulse)
    best = int(np.argmax(values))
    try:
        joint = np.linalg.inv(normal[best])
    except np.linalg.LinAlgError:
        joint = np.linalg.pinv(normal[best])
    detection = (int(stamps[hi] + round(starts[best] * 1e9)),
                 int(stamps[hi] + round(ends[best] * 1e9)), float(test.windows[window]),
                 float(values[best]), (joint @ rhs[best])[:n],
                 joint[:n, :n] + test._common[max(lo, 0)])
    return detection, normal, rhs


def _pushed_blocks(rng: np.random.Generator, positions: bool,
                   positions_until: int = 700) -> MomentumBlocks:
    """Return blocks fed 700 samples at 1 kHz with a push at 0.5-0.56 s."""
    from reduced_dynamics.estimator import multiscale
    test = MomentumBlocks(6, multiscale.window_bank())
    mu = np.zeros(6)
    for k in range(700):
        stamp = 1_000_000_000 + k * 1_000_000 + int(rng.integers(-50_000, 50_000))
        if 500 <= k < 560:  # a push: the momentum ramps
            mu = mu + np.array([0.02, -0.01, 0.0, 0.0, 0.005, 0.0])
        centre = np.array([0.001 * k, 0.0, 0.5]) + 1e-4 * rng.standard_normal(3)
        position = (centre, 1e-8 * np.eye(3), 12.0, (0, 1, 2))
        test.add(stamp, mu + 1e-3 * rng.standard_normal(6), 1e-6 * np.eye(6),
                 1e-8 * np.eye(6), position if positions and k < positions_until else None)
    return test


def test_the_pulse_fits_normal_equations_are_numpys_bit_for_bit() -> None:
    """
    Locate's compiled normal equations and once-inverted nuisance give numpy's bits.

    With one BLAS thread, in a process of its own: the fit's large OpenBLAS products
    differ in their last bits between thread counts (docs/performance.md), and a
    product of two columns and two products of one each agree only on one thread.
    """
    env = dict(os.environ, OPENBLAS_NUM_THREADS='1',
               PYTHONPATH=os.pathsep.join(filter(None, (str(Path(__file__).parent),
                                                        os.environ.get('PYTHONPATH')))))
    check = subprocess.run(
        [sys.executable, '-c', 'import test_multiscale_kernels as t; t.check_pulse_fits()'],
        env=env, capture_output=True, text=True, timeout=600)
    assert check.returncode == 0, check.stdout + check.stderr


def check_pulse_fits() -> None:
    """Assert the compiled normal equations are numpy's, bit for bit (one BLAS thread)."""
    written = []
    pulse_normals = blocks.pulse_normals

    def kept(*args):
        pulse_normals(*args)
        written.append((args[-2].copy(), args[-1].copy()))
    blocks.pulse_normals = kept
    try:
        _compare_pulse_fits(written)
    finally:
        blocks.pulse_normals = pulse_normals


def _compare_pulse_fits(written: list) -> None:
    rng = np.random.default_rng(11)
    # With positions; without (d = 0); positions ending before the short windows'
    # span (fewer than two in the fit: the nuisance singular, the pseudo-inverse).
    cases = [(_pushed_blocks(rng, True), (0, 1, 2, 3, 5)), (_pushed_blocks(rng, False), (1, 2)),
             (_pushed_blocks(rng, True, 300), (0, 1))]
    for test, windows in cases:
        stamp = int(test._stamps[test._end - 1])
        for window in windows:
            for floor in (None, stamp - 100_000_000):
                written.clear()
                detection = test.locate(stamp, window, floor)
                expected, normal, rhs = _numpy_locate(test, stamp, window, floor)
                assert written[0][0].tobytes() == normal.tobytes()
                assert written[0][1].tobytes() == rhs.tobytes()
                assert _detection_fields(detection) == _detection_fields(expected)


def test_a_sample_due_for_the_excess_decomposition_takes_the_compiled_path() -> None:
    """Every 16th sample (the excess re-decomposed) is common too, with add's bits."""
    from reduced_dynamics.estimator import multiscale
    rng = np.random.default_rng(5)
    compiled = MomentumBlocks(6, multiscale.window_bank())
    reference = MomentumBlocks(6, multiscale.window_bank())
    reference.prepare = lambda *args, **kwargs: None  # add's own steps, one by one
    taken = []
    for k in range(EXCESS_MINIMUM + 40):
        stamp = 1_000_000_000 + k * 1_000_000
        centre = np.array([0.001 * k, 0.0, 0.5]) + 1e-4 * rng.standard_normal(3)
        cov = 1e-6 * (np.eye(6) + 0.1 * np.diag(rng.random(6)))
        sample = (stamp, 1e-3 * rng.standard_normal(6), cov, 1e-8 * np.eye(6),
                  (centre, 1e-8 * np.eye(3), 12.0, (0, 1, 2)))
        due = compiled._differences + 1
        if compiled._end and (due % 16 == 1 or due == EXCESS_MINIMUM):
            taken.append(compiled._add_compiled(*sample))
        else:
            compiled.add(*sample)
        reference.add(*sample)
    assert taken and all(taken)  # prepare gave those samples to the compiled call
    for name in ('_info', '_score', '_common', '_stamps', 'excess', '_excess_raw'):
        assert getattr(compiled, name).tobytes() == getattr(reference, name).tobytes(), name
    for ours, theirs in zip(compiled._positions, reference._positions):
        assert ours.tobytes() == theirs.tobytes()
    assert compiled._end == reference._end
