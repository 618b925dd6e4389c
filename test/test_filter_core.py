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

"""The compiled filter core (estimator/core): reference, robustness, stalls."""

import logging

import numpy as np
import pinocchio as pin
import pytest

from filter_helpers import filter_problem, linearisation_problem
from reduced_dynamics.estimator import Estimator, EstimatorConfig
from reduced_dynamics.estimator.core import kernels, lie
from reduced_dynamics.estimator.filter import Linearisation, MomentumFilter, NoiseModel
from reduced_dynamics.geometry.lie_group import SUBGROUPS
from reduced_dynamics.messages.samples import BaseStateSample
from reduced_dynamics.resources import config_path
from reduced_dynamics.robot.model import load_robot

NS = 1_000_000_000


def test_group_maps_match_pinocchio() -> None:
    """exp6, log6 and Ad against Pinocchio, small angles included (series branches)."""
    rng = np.random.default_rng(0)
    for scale in (1e-9, 1e-5, 1e-3, 0.1, 1.0, 3.0):
        for _ in range(20):
            axis = rng.normal(size=3)
            twist = np.r_[rng.normal(size=3), axis / np.linalg.norm(axis) * scale]
            g = pin.exp6(twist)
            assert np.abs(lie.exp6(twist) - g.homogeneous).max() < 1e-12
            assert np.abs(lie.log6(g.homogeneous) - pin.log6(g).vector).max() < 1e-12
            assert np.abs(lie.action(g.homogeneous) - g.action).max() < 1e-12


@pytest.mark.parametrize('name,command', [('SE(3)', False), ('SE(2)', False), ('SE(2)', True)])
def test_compiled_kernels_equal_their_interpreted_source(name: str, command: bool) -> None:
    """The reference path is the kernels' own source run by the interpreter (py_func)."""
    rng, lin, flt, g, x, p = filter_problem(name, command, 1)
    group, n = SUBGROUPS[name], flt.n
    u = rng.normal(size=n) if command else np.zeros(0)
    args = (g, x, p, lin.locked, lin.locked_inverse, lin.connection_qd, lin.joint_cov, 0.01,
            u, command, flt._jerk_var, flt._densities(lin), flt._basis, flt._pinv, flt._whole,
            flt._ad_rows, flt._form_rows)
    pose = group.exp(rng.normal(size=n) * 1e-3).homogeneous @ g
    update = (g, x, p, np.ascontiguousarray(pose), rng.normal(size=n), True,
              lin.locked_inverse, lin.connection_qd, lin.joint_cov, flt._pose_var,
              rng.normal(size=n), 3e-3, flt._twist_var, np.inf, flt._basis, flt._pinv,
              flt._whole, flt._form_rows)
    for kernel, inputs in ((kernels.propagate, args), (kernels.update, update)):
        compiled, interpreted = kernel(*inputs), kernel.py_func(*inputs)
        for a, b in zip(compiled, interpreted):
            assert np.abs(np.asarray(a, float) - np.asarray(b, float)).max() <= 1e-12


@pytest.mark.parametrize('command', [False, True])
def test_process_noise_is_positive_semidefinite_after_a_long_gap(command: bool) -> None:
    """
    Q by quadrature is a sum of v Qc v^T: no negative eigenvalue for any step.

    The truncated series it replaced had Q_gg = 0 beside Q_gw != 0 for a jointless
    body: after a 1 s gap P went indefinite and the filter restarted.
    """
    group = SUBGROUPS['SE(2)']
    n = group.dim
    _, lin = linearisation_problem(n, 2)
    lin = lin._replace(joint_cov=np.zeros((n, n)))
    flt = MomentumFilter(group, NoiseModel(), 0.0, command=command)
    g = group.exp(np.array([0.1, -0.2, 0.3]))
    x = np.r_[np.array([0.5, -0.3, 0.2]), np.zeros(flt.dim - 2 * n)]
    for dt in (1e-3, 0.1, 1.0, 3.0):
        _, q = flt._transition(g, x, lin, dt, np.ones(n) if command else None)
        eig = np.linalg.eigvalsh(q)
        assert eig.min() >= -1e-12 * eig.max(), (dt, eig.min(), eig.max())


def _stalled_stream(robot, stall: float, seed: int = 0):
    """
    Return the start and the poses of a free-flyer drifting without wrench (120 Hz).

    The mocap is stamped on receipt.
    Frames of [4 s, 4 s + stall) are held and delivered at its end in one burst,
    stamped 20 us apart (a stalled mocap client), as in the recording of issue 19.
    """
    rng = np.random.default_rng(seed)
    start, rate = 1_700_000_000 * NS, 120.0
    velocity, omega, stall_at = np.array([0.05, -0.03]), 0.2, 4.0
    frames = np.arange(int(8.0 * rate)) / rate
    held = 0
    out = []
    for t in frames:
        stamp = t + 0.003 + rng.normal(0.0, 5e-4)
        if stall_at <= t < stall_at + stall:
            stamp = stall_at + stall + 0.003 + held * 2e-5
            held += 1
        position = velocity * t + rng.normal(0.0, 5e-4, 2)
        yaw = omega * t + rng.normal(0.0, 2e-3)
        out.append(BaseStateSample(start + int(round(stamp * NS)), 'world', robot.base_link,
                                   np.r_[position, 0.55],
                                   np.array([0.0, 0.0, np.sin(yaw / 2), np.cos(yaw / 2)])))
    out.sort(key=lambda sample: sample.stamp_ns)
    return start, out


@pytest.mark.parametrize('stall', [0.1, 0.3, 1.0])
def test_a_stall_and_its_burst_leave_the_wrench_within_its_covariance(stall: float) -> None:
    """
    No restart, and w^T P_ww^-1 w stays below chi2_3's 1e-3 quantile (16.3) throughout.

    Before (main 1e76fa4): a 1 s stall restarted the filter (P indefinite) and the
    causal force reached 143 N (w^T P^-1 w = 83); 0.3 s reached 10 (this body has no
    wrench).
    """
    robot = load_robot(str(config_path('robots/freeflyer.urdf')))
    start, samples = _stalled_stream(robot, stall)
    estimator = Estimator(robot, EstimatorConfig(prediction_rate=0.0), use_odometry=False,
                          base_driven=True)
    outputs = estimator.add_samples(samples).outputs() + estimator.flush()
    statistics = estimator.filter_statistics()
    assert statistics['filter_restarts'] == 0
    assert statistics['burst_skipped'] >= int(stall * 120)
    worst = 0.0
    for output in outputs:
        if (output.stamp_ns - start) * 1e-9 < 1.5:
            continue  # the prior's transient
        rate = output.momentum_rate
        w = np.array([rate.force[0], rate.force[1], rate.torque[2]])
        worst = max(worst, float(w @ np.linalg.solve(output.wrench_covariance, w)))
    assert worst < 16.3, worst


def test_a_restart_is_logged_and_counted_with_its_cause(caplog) -> None:
    """The last resort: a non-finite covariance restarts the filter, with a WARN."""
    group = SUBGROUPS['SE(2)']
    locked = np.diag([16.0, 16.0, 0.18])
    lin = Linearisation(locked, np.linalg.inv(locked), np.zeros(3), np.zeros((3, 3)))
    flt = MomentumFilter(group, NoiseModel(), 1e-6, record=True)
    flt.step(0, lin, pin.SE3.Identity(), None)
    broken = flt.p.copy()
    broken[4, 4] = np.nan
    flt.p = broken
    with caplog.at_level(logging.WARNING):
        flt.step(10_000_000, lin, pin.SE3.Identity(), None)
    assert flt.diverged == 1 and flt.restart_causes == {'covariance not finite': 1}
    assert any('restarted' in record.message and record.levelno == logging.WARNING
               for record in caplog.records)
    assert np.isfinite(flt.p).all()


def test_stall_detector_flags_a_burst_and_nothing_else() -> None:
    """120 Hz with bunched pairs and 40 ms gaps: no burst; a 0.3 s stall: its burst only."""
    from reduced_dynamics.estimator.core.stalls import StallDetector
    rng = np.random.default_rng(4)
    period = NS // 120
    stamps, t = [], 0
    # The first gap a bunched pair (30 us): the median start must not take it as nominal.
    stamps += [0, 30_000]
    t = period
    for k in range(2000):
        t += period + int(rng.normal(0.0, 5e5))
        stamps.append(t)
        if k % 100 == 50:
            stamps.append(t + 30_000)   # a bunched pair (1 %)
        if k % 300 == 150:
            t += 4 * period             # a 40 ms gap (frames lost)
    detector = StallDetector()
    assert not any(detector.in_burst(stamp) for stamp in stamps)
    assert abs(detector.interval - period * 1e-9) < 0.1 * period * 1e-9
    stall_end = stamps[-1] + int(0.3 * NS)
    burst = [stall_end + k * 20_000 for k in range(36)]
    after = [burst[-1] + period * (k + 1) for k in range(5)]
    flags = [detector.in_burst(stamp) for stamp in burst + after]
    assert all(flags[:36]) and not any(flags[36:])
