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
Helpers shared by the filter tests.

A bag's messages and wrench series, group error-state arithmetic, a random linearisation.
"""

import numpy as np

from reduced_dynamics.bag.reader import open_bag
from reduced_dynamics.estimator.filter import Linearisation


#: Relative tolerance of a structured compiled kernel against its dense reference:
#: rounding (other summation orders, a Cholesky factor instead of LU), amplified by the
#: filter's conditioning.
STRUCTURED_TOLERANCE = 1e-9


def close_relative(got, want, tolerance: float = STRUCTURED_TOLERANCE) -> bool:
    """Return whether ``got`` equals ``want`` to ``tolerance`` of ``want``'s largest entry."""
    got, want = np.asarray(got, float), np.asarray(want, float)
    scale = np.abs(want).max() if want.size else 0.0
    return got.shape == want.shape and bool(np.all(np.abs(got - want) <= tolerance * scale))


def assert_equal_arrays(mine, want, err_msg: str = '') -> None:
    """
    ``np.testing.assert_array_equal``, with equal bytes first (the tests' usual outcome).

    The bit-equality tests compare ~10^5 small arrays: the numpy assertion costs
    ~0.1 ms each, a byte comparison a microsecond. Arrays whose bytes differ (or that
    are not arrays of one dtype and shape) go to the numpy assertion, whose verdict
    and message stand.
    """
    if mine.__class__ is np.ndarray and want.__class__ is np.ndarray and \
            mine.dtype == want.dtype and mine.shape == want.shape and \
            mine.tobytes() == want.tobytes():
        return
    np.testing.assert_array_equal(mine, want, err_msg=err_msg)


def fresh_process_words(code: str) -> list[str]:
    """Run ``code`` in a fresh interpreter with this checkout first; return its stdout words."""
    import os
    import subprocess
    import sys
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env = dict(os.environ, PYTHONPATH=root + os.pathsep + os.environ.get('PYTHONPATH', ''))
    return subprocess.run([sys.executable, '-c', code], env=env, capture_output=True,
                          text=True, check=True, timeout=600).stdout.split()


def bag_contents(path) -> tuple[dict, list[tuple[str, int, bytes]]]:
    """Return a bag's topics and every message (topic, record time, bytes) in read order."""
    with open_bag(path) as reader:
        topics = reader.topics()
        return topics, [(m.topic, m.timestamp_ns, bytes(m.data))
                        for m in reader.raw_messages(list(topics))]


def wrench_series(path, topic: str) -> np.ndarray:
    """Return rows (stamp_ns, fx, fy, fz, tx, ty, tz) of a WrenchStamped topic."""
    rows = []
    with open_bag(path) as reader:
        for message in reader.messages([topic]):
            msg = message.msg
            w = msg.wrench
            rows.append((msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec,
                         w.force.x, w.force.y, w.force.z, w.torque.x, w.torque.y, w.torque.z))
    return np.array(rows)


def plus(group, g, x, d):
    """Return the state (g, x) moved by the error d: g exp(d_g), x + d_x."""
    n = group.dim
    return g * group.exp(d[:n]), x + d[n:]


def minus(group, g, x, g0, x0):
    """Return the error of (g, x) from (g0, x0): log(g0^-1 g), x - x0."""
    return np.concatenate((group.log(g0.inverse() * g), x - x0))


def linearisation_problem(n: int, seed: int):
    """
    Return (rng, Linearisation) of a random n-dimensional problem, rng after drawing it.

    Locked inertia SPD and well conditioned, connection term ~0.3, joint covariance of
    rank 2 (the compiled-kernel tests' fixture).
    """
    rng = np.random.default_rng(seed)
    root = rng.normal(size=(n, n))
    locked = root @ root.T + n * np.eye(n)
    joint = rng.normal(size=(n, 2)) * 0.1
    lin = Linearisation(locked, np.linalg.inv(locked), rng.normal(size=n) * 0.3,
                        joint @ joint.T)
    return rng, lin


def filter_problem(name: str, command: bool, seed: int):
    """
    Return (rng, lin, flt, g, x, P): a random filter and state on subgroup ``name``.

    The linearisation of :func:`linearisation_problem`, then the pose g (~0.3 rad), x
    and an SPD covariance P, drawn in that order (the compiled-kernel tests' fixture).
    """
    from reduced_dynamics.estimator.filter import MomentumFilter, NoiseModel
    from reduced_dynamics.geometry.lie_group import SUBGROUPS
    group = SUBGROUPS[name]
    n = group.dim
    rng, lin = linearisation_problem(n, seed)
    flt = MomentumFilter(group, NoiseModel(), 1e-6, command=command)
    dim = flt.dim
    g = group.exp(rng.normal(size=n) * 0.3).homogeneous
    x = rng.normal(size=dim - n)
    root = rng.normal(size=(dim, dim))
    p = root @ root.T * 1e-2 + np.eye(dim) * 1e-3
    return rng, lin, flt, g, x, p
