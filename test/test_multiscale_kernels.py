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

from typing import Optional

import numpy as np

from reduced_dynamics.estimator.multiscale import MultiScaleTest


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


def test_the_compiled_window_statistics_equal_the_numpy_ones_bit_for_bit() -> None:
    """Random momenta and covariances, a floor, events (not quiet), rate changes, ring wraps."""
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
            np.testing.assert_array_equal(test.statistics, expected)
            np.testing.assert_array_equal(test._above[0], above)
            compared += int(np.count_nonzero(expected))
        assert compared > 1000


def test_window_changes_marks_the_windows_the_floor_leaves_uncovered() -> None:
    """Rows of the windows reaching back before the floor, or before the data, are -1."""
    from reduced_dynamics.estimator.core import impulse
    stamps = np.arange(0, 1_000_000_000, 10_000_000, dtype=np.int64)
    mu_ring = np.arange(len(stamps), dtype=float)[:, None] * np.ones(3)
    cov_ring = np.tile(np.eye(3), (len(stamps), 1, 1))
    lags = np.array([50_000_000, 300_000_000, 2_000_000_000])
    now = int(stamps[-1])
    rows, d, solved = impulse.window_changes(stamps, mu_ring, cov_ring, 0, len(stamps), lags,
                                             now, 0, False, mu_ring[-1], np.eye(3))
    assert rows.tolist() == [94, 69, -1]
    np.testing.assert_array_equal(d, [[5.0] * 3, [30.0] * 3])
    np.testing.assert_array_equal(solved, d / 2.0)
    rows, d, _ = impulse.window_changes(stamps, mu_ring, cov_ring, 0, len(stamps), lags,
                                        now, now - 100_000_000, True, mu_ring[-1], np.eye(3))
    assert rows.tolist() == [94, -1, -1] and d.shape == (1, 3)
