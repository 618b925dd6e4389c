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

"""The batched path's per-message shortcuts give what the general code gives."""

import math

import numpy as np
import pinocchio as pin

from reduced_dynamics.estimator.core import envelope, stalls
from reduced_dynamics.estimator.retiming import FrameRetimer
from reduced_dynamics.estimator.sync import BaseBuffer


def _brute_between(stamps: list, rows: list, after, until: int) -> tuple:
    return tuple((s, r) for s, r in zip(stamps, rows)
                 if (after is None or s > after) and s <= until)


def test_between_matches_a_plain_filter_including_the_newest_sample_shortcut() -> None:
    rng = np.random.default_rng(3)
    for _ in range(300):
        buffer = BaseBuffer(keep=int(rng.integers(1, 12)))
        stamps = np.cumsum(rng.integers(1, 5, size=int(rng.integers(1, 20)))).tolist()
        rows = [[float(s)] * 7 for s in stamps]
        for s, r in zip(stamps, rows):
            buffer.append(s, r)
        held_stamps, held_rows = stamps[-buffer._keep:], rows[-buffer._keep:]
        for after in [None] + list(range(-1, stamps[-1] + 2)):
            for until in range(0 if after is None else after + 1, stamps[-1] + 2):
                got = buffer.between(after, until)
                assert got == _brute_between(held_stamps, held_rows, after, until)
                # Rows are handed on by reference, as before the shortcut.
                assert all(a[1] is b[1] for a, b in
                           zip(got, _brute_between(held_stamps, held_rows, after, until)))


def test_ndarray_dot_gives_the_bits_of_matmul_for_the_row_products() -> None:
    # processing.py computes pi = Ad_g^T mu and |w|^2 with ndarray.dot (less dispatch than
    # @): the golden outputs rely on it being the same BLAS call, bit for bit.
    rng = np.random.default_rng(4)
    for _ in range(2000):
        g = pin.SE3.Random()
        g.translation = g.translation * 10.0 ** float(rng.integers(-3, 4))
        x = rng.standard_normal(12) * 10.0 ** float(rng.integers(-8, 9))
        action = g.action
        assert np.array_equal(action.T.dot(x[:6]), action.T @ x[:6])
        w = x[6:]
        assert float(w.dot(w)) == float(w @ w)


def test_retimer_window_arrays_equal_the_window_of_points() -> None:
    # The re-timer keeps its window as int64 pairs as they come (retiming.py _push); a fit
    # must read exactly the (index, stamp) columns envelope.window_arrays made of the
    # points, through drops, outages (restarts), lost-frame shifts and a clock jump.
    from test_retiming import _polled

    for seed, drop, outage in ((3, 0.0, 0.0), (5, 0.05, 0.0), (7, 0.02, 0.01)):
        _, stamps, _ = _polled(duration=20.0, drop_rate=drop, seed=seed, outage_rate=outage)
        stamps = stamps.tolist()
        half = len(stamps) // 2
        stamps = stamps[:half] + [s - 3 * 10 ** 9 for s in stamps[half:]]
        for mode in ('auto', 'on'):
            retimer = FrameRetimer(mode)
            previous = None
            for stamp in stamps:
                if previous is not None and stamp <= previous:
                    retimer.restart()
                previous = stamp
                retimer.retime(stamp)
                index, stamp_column = retimer._window_arrays()
                expected = envelope.window_arrays(retimer._points)
                assert np.array_equal(index, expected[0])
                assert np.array_equal(stamp_column, expected[1])
                assert index.dtype == expected[0].dtype and index.strides == expected[0].strides
            assert retimer.kept + retimer.retimed == len(stamps)


class _ReferenceStalls:
    """StallDetector.in_burst as it was written before its clamp was spelled out."""

    def __init__(self) -> None:
        self.interval = None
        self._first: list = []
        self._last_ns = None
        self.stall_from_ns = None

    def in_burst(self, stamp_ns: int) -> bool:
        last, self._last_ns = self._last_ns, stamp_ns
        if last is None or stamp_ns <= last:
            return False
        gap = (stamp_ns - last) * 1e-9
        nominal = self.interval
        if nominal is None:
            self._first.append(gap)
            if len(self._first) == stalls.FIRST_GAPS:
                self.interval = float(np.median(self._first))
            return False
        stall = gap > stalls.STALL_PERIODS * nominal
        if stall:
            self.stall_from_ns = last
        elif gap >= stalls.BUNCHED * nominal:
            self.stall_from_ns = None
        if self.stall_from_ns is None or stall:
            pull = min(max(math.log(gap / nominal), -stalls.LOG_4), stalls.LOG_4)
            self.interval = nominal * math.exp(stalls.INTERVAL_WEIGHT * pull)
        return self.stall_from_ns is not None


def test_stall_detector_matches_its_reference_bit_for_bit() -> None:
    rng = np.random.default_rng(6)
    for _ in range(20):
        detector, reference = stalls.StallDetector(), _ReferenceStalls()
        stamp = 10 ** 18
        for _ in range(3000):
            kind = rng.random()
            # Regular frames, jitter, stalls of 0.1-1 s, bursts within 1 ms, repeats.
            step = (int(rng.uniform(0.1e9, 1e9)) if kind < 0.01 else
                    int(rng.uniform(0, 1e6)) if kind < 0.1 else
                    0 if kind < 0.12 else int(8.3e6 * rng.uniform(0.2, 3.0)))
            stamp += step
            assert detector.in_burst(stamp) == reference.in_burst(stamp)
            assert detector.interval == reference.interval
            assert detector.stall_from_ns == reference.stall_from_ns


def test_chunk_homogeneous_poses_are_the_bits_of_se3_homogeneous() -> None:
    # processing.py passes the filter's row step the chunk's poses stacked from R and t
    # instead of pin.SE3(R, t).homogeneous: the golden outputs rely on the same bits.
    rng = np.random.default_rng(5)
    for _ in range(500):
        g = pin.SE3.Random()
        g.translation = g.translation * 10.0 ** float(rng.integers(-3, 4))
        rotation, translation = g.rotation.copy(), g.translation.copy()
        stacked = np.zeros((1, 4, 4))
        stacked[:, :3, :3] = rotation
        stacked[:, :3, 3] = translation
        stacked[:, 3, 3] = 1.0
        expected = np.ascontiguousarray(pin.SE3(rotation, translation).homogeneous)
        assert stacked[0].tobytes() == expected.tobytes()
        assert stacked[0].flags.c_contiguous


def _batched_outputs(row_at) -> tuple:
    """Return the bench motion's outputs (2.5 s, events found), batched, with ``row_at`` given."""
    from unittest import mock

    from reduced_dynamics.bench import update_samples
    from reduced_dynamics.estimator.config import EstimatorConfig
    from reduced_dynamics.estimator.filter import MomentumFilter
    from reduced_dynamics.estimator.pipeline import Estimator
    from reduced_dynamics.robot.model import load_robot
    robot = load_robot()
    joints, bases = update_samples(robot, 2500)
    messages = [m for pair in zip(joints, bases) for m in pair]
    calls = []

    def counted(self, *args):
        calls.append(1)
        return row_at(self, *args)

    estimator = Estimator(robot, EstimatorConfig(prediction_rate=0.0))
    with mock.patch.object(MomentumFilter, 'row_at', counted):
        batch = estimator.add_samples(messages)
    names = ('mu', 'pi', 'momentum_rate', 'drift', 'energy', 'mu_cov', 'w_cov')
    columns = [batch.column(name).tobytes() for name in names]
    flt = estimator.filter
    state = (flt.x.tobytes(), flt.p.tobytes(), flt._g.tobytes(), flt.log_likelihood,
             flt.nis_sum, flt.steps_taken, flt.step_test.evaluated, flt.stalls.interval)
    events = [(e.start_ns, e.end_ns, e.detected_ns) for e in estimator.detector.events]
    return columns, state, events, len(calls)


def test_the_common_row_equals_the_general_row_bit_for_bit() -> None:
    # MomentumFilter.row_at (the common row: one measurement at the row's stamp, with the
    # chunk's 4 x 4 pose) against the general row() with the same measurement.
    from reduced_dynamics.estimator.filter import MomentumFilter

    def general(self, stamp_ns, lin, measurement, pose=None):
        return self.row(stamp_ns, lin, measurement, [measurement])

    mine = _batched_outputs(MomentumFilter.row_at)
    expected = _batched_outputs(general)
    assert mine[3] == expected[3] > 2000  # (the first row starts the filter: row())
    assert expected[2], 'the bench motion finds events'
    assert mine[:3] == expected[:3]
