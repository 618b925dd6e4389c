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
Quaternions from rotation matrices: bit for bit Eigen's, and no C++ heap growth (issue 27).

``pin.Quaternion(R)`` leaked ~80 B per call outside tracemalloc's view; every
prediction converted 82 poses, so the node grew ~7 kB per prediction. The
growth is measured as the C heap in use (glibc ``mallinfo2``), which counts
bytes allocated and not freed, independent of the OS returning pages.
"""

import ctypes
import ctypes.util
import dataclasses

import numpy as np
import pinocchio as pin
import pytest

from reduced_dynamics.geometry.quaternion import (matrices_to_xyzw, matrix_to_unit_xyzw,
                                                  matrix_to_xyzw)


class _MallInfo2(ctypes.Structure):
    _fields_ = [(name, ctypes.c_size_t) for name in (
        'arena', 'ordblks', 'smblks', 'hblks', 'hblkhd', 'usmblks', 'fsmblks', 'uordblks',
        'fordblks', 'keepcost')]


def _heap_in_use():
    """Return the C heap bytes in use (glibc), or skip where mallinfo2 is missing."""
    libc = ctypes.CDLL(ctypes.util.find_library('c') or 'libc.so.6')
    if not hasattr(libc, 'mallinfo2'):
        pytest.skip('glibc mallinfo2 not available')
    libc.mallinfo2.restype = _MallInfo2
    info = libc.mallinfo2()
    return info.uordblks + info.hblkhd


def _rotations(count):
    quats = np.random.default_rng(7).normal(size=(count, 4))
    return np.array([pin.Quaternion(*(q / np.linalg.norm(q))).toRotationMatrix()
                     for q in quats])


def test_same_bits_as_eigen_quaternion():
    rotations = _rotations(500)
    poses = np.zeros((500, 4, 4))
    poses[:, :3, :3] = rotations
    expected = np.array([pin.Quaternion(r).coeffs() for r in rotations])
    assert np.array_equal(matrices_to_xyzw(poses[:, :3, :3]), expected)
    for rotation, quat in zip(rotations[:50], expected[:50]):
        assert np.array_equal(matrix_to_xyzw(rotation), quat)
        assert np.array_equal(matrix_to_unit_xyzw(rotation),
                              pin.Quaternion(rotation).normalized().coeffs())


def test_conversion_keeps_the_heap_flat():
    poses = np.zeros((41, 4, 4))
    poses[:, :3, :3] = _rotations(41)
    for _ in range(200):   # warm-up: numpy's and the allocator's caches
        matrices_to_xyzw(poses[:, :3, :3])
    before = _heap_in_use()
    for _ in range(2000):
        matrices_to_xyzw(poses[:, :3, :3])
    # 82 000 conversions: the old call grew the heap by ~6.5 MB here.
    assert _heap_in_use() - before < 100_000


def test_predictions_keep_the_heap_flat():
    """Prediction jobs run over and over from one start state: no heap growth per job."""
    from reduced_dynamics.estimator import Estimator, EstimatorConfig
    from reduced_dynamics.estimator.prediction import PredictionJob
    from reduced_dynamics.robot.model import load_robot
    from reduced_dynamics.soak import soak_messages
    robot = load_robot()
    estimator = Estimator(robot, dataclasses.replace(EstimatorConfig(), prediction_rate=25.0),
                          use_odometry=True, defer_predictions=True)
    jobs = []
    for _, kind, sample in soak_messages(robot, 600):
        for output in (estimator.add_base_state if kind else estimator.add_joint_state)(sample):
            if output.prediction_job is not None:
                jobs.append(output.prediction_job)
    start = jobs[-1]

    def run(count):
        for _ in range(count):
            job = PredictionJob(start.robot.worker_copy(), start.settings, start.start_ns,
                                start.g, start.qbar, start.qbar_dot, start.mu, start.tau,
                                start.theta, start.mode, start.requested_mode, start.plan,
                                start.uncertainty)
            assert job.run() is not None

    run(20)
    before = _heap_in_use()
    run(200)
    # ~7 kB per prediction before the fix (1.4 MB here); allow allocator slack.
    assert _heap_in_use() - before < 200_000
