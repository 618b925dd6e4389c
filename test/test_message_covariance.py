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

"""Message covariances as measurement noise (docs/message_covariance.md)."""

import dataclasses
import functools
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest
from rosbags.typesys import get_typestore, Stores

from conftest_robots import paper_robot, planar_robot
from reduced_dynamics.bag import open_bag
from reduced_dynamics.estimator import Estimator
from reduced_dynamics.estimator.config import EstimatorConfig
from reduced_dynamics.estimator.covariance import checked, CovarianceReader
from reduced_dynamics.messages import cdr
from reduced_dynamics.messages.convert import (base_state_to_pose_with_covariance_stamped,
                                               pose_with_covariance_stamped_from_ros,
                                               wrench_from_ros)
from reduced_dynamics.messages.samples import BaseStateSample, DIAG_WARN
from reduced_dynamics.messages.types import RosbagsTypes
from reduced_dynamics.params import defaults
from reduced_dynamics.replay import replay, ReplayOptions
from reduced_dynamics.simulator import SimulationOptions, simulate_bag, ThrusterPulse
from reduced_dynamics.tune import load_inputs

STORE = get_typestore(Stores.ROS2_JAZZY)


def _random_covariance(rng: np.random.Generator, scale: np.ndarray) -> np.ndarray:
    """Return a random full-rank 6 x 6 covariance with standard deviations about ``scale``."""
    root = np.diag(scale) @ (np.eye(6) + 0.4 * rng.normal(size=(6, 6)))
    return root @ root.T


# ------------------------------------------------------------------ the mapping


def test_unknown_and_bad_covariances_are_told_apart():
    good = np.diag([1e-6] * 3 + [4e-6] * 3)
    matrix, reason = checked(good.ravel())
    assert reason is None and np.array_equal(matrix, good)
    assert checked(None) == (None, None)
    unknown = good.ravel().copy()
    unknown[0] = -1.0  # the sensor_msgs convention: the rest is meaningless
    assert checked(unknown) == (None, None)
    cases = {'non_finite': (7, np.nan), 'negative_variance': (14, -1e-6),
             'not_symmetric': (1, 5e-7)}
    for expected, (index, value) in cases.items():
        bad = good.ravel().copy()
        bad[index] = value
        assert checked(bad) == (None, expected)
    indefinite = good.copy()
    indefinite[0, 1] = indefinite[1, 0] = 3e-6  # |corr| > 1
    assert checked(indefinite.ravel()) == (None, 'not_positive_semidefinite')


def test_order_is_x_y_z_roll_pitch_yaw_linear_first():
    reader = CovarianceReader(paper_robot().group.algebra_pinv)
    values = np.diag(np.arange(1.0, 7.0))
    noise, reasons = reader.read(values.ravel(), values.ravel(), np.eye(3))
    assert not reasons
    # The filter's coordinates: log6 of the pose residual, (v, omega); the body twist (v, w).
    assert np.array_equal(noise.pose, values) and np.array_equal(noise.twist, values)


def test_pose_covariance_is_the_covariance_of_the_filters_pose_residual():
    # Sample world-frame errors (the header frame, REP 105: position, then small rotations
    # about the fixed x, y, z axes) and compare the covariance of the residual the filter
    # forms, log6(g^-1 g_meas), with the mapped covariance.
    rng = np.random.default_rng(5)
    g = pin.SE3(pin.exp3(np.array([0.7, -1.1, 2.0])), np.array([3.0, -2.0, 1.0]))
    world = _random_covariance(rng, np.array([2e-3, 1e-3, 3e-3, 1e-3, 4e-3, 2e-3]))
    errors = rng.multivariate_normal(np.zeros(6), world, size=40000)
    residuals = np.array([pin.log6(g.actInv(pin.SE3(pin.exp3(e[3:]) @ g.rotation,
                                                    g.translation + e[:3]))).vector
                          for e in errors])
    reader = CovarianceReader(paper_robot().group.algebra_pinv)
    noise, reasons = reader.read(world.ravel(), None, g.rotation)
    assert not reasons and noise.twist is None
    # Whitened by the mapped covariance, the residuals' covariance is the identity (to the
    # sampling error, ~ sqrt(2 / 40000) = 0.007 per entry).
    whiten = np.linalg.inv(np.linalg.cholesky(noise.pose))
    sample = whiten @ np.cov(residuals.T) @ whiten.T
    assert np.abs(sample - np.eye(6)).max() < 0.05
    # Without the turn into the base frame the same check fails: the frames matter here.
    whiten = np.linalg.inv(np.linalg.cholesky(world))
    assert np.abs(whiten @ np.cov(residuals.T) @ whiten.T - np.eye(6)).max() > 0.5


def test_planar_base_keeps_x_y_yaw_and_turns_the_pose_by_the_heading():
    reader = CovarianceReader(planar_robot().group.algebra_pinv)
    yaw = 0.5 * np.pi
    rotation = pin.exp3(np.array([0.0, 0.0, yaw]))
    pose = np.diag([4e-6, 1e-6, 0.0, 0.0, 0.0, 9e-6])  # what a 2-D driver sends
    twist = np.diag([1e-4, 2e-4, 0.0, 0.0, 0.0, 3e-4])
    twist[0, 5] = twist[5, 0] = 1e-4
    noise, reasons = reader.read(pose.ravel(), twist.ravel(), rotation)
    assert not reasons
    # Heading 90 degrees: world x is the base's -y, world y its x.
    assert np.allclose(noise.pose, np.diag([1e-6, 4e-6, 9e-6]), rtol=0, atol=1e-18)
    # The twist is in the child (base) frame already: only projected.
    assert np.array_equal(noise.twist, twist[np.ix_([0, 1, 5], [0, 1, 5])])


def test_repeated_covariances_are_turned_by_each_samples_heading():
    # The reader keeps the last covariance checked; the turn is still each sample's own,
    # except where no turn changes the matrix (blocks multiple of the identity).
    reader = CovarianceReader(paper_robot().group.algebra_pinv)
    rng = np.random.default_rng(8)
    full = _random_covariance(rng, np.full(6, 1e-3))
    isotropic = np.diag([4e-6] * 3 + [1e-6] * 3)
    isotropic[:3, 3:] = isotropic[3:, :3] = 5e-7 * np.eye(3)
    for _ in range(3):
        rotation = pin.exp3(rng.normal(size=3))
        turn = np.kron(np.eye(2), rotation.T)
        for values in (full, isotropic):
            noise, reasons = reader.read(values.ravel(), values.ravel(), rotation)
            assert not reasons
            assert np.allclose(noise.pose, turn @ values @ turn.T, rtol=1e-12, atol=1e-20)
            assert np.array_equal(noise.twist, values)


def test_zero_variance_on_a_used_coordinate_falls_back():
    reader = CovarianceReader(paper_robot().group.algebra_pinv)
    pose = np.diag([4e-6, 1e-6, 0.0, 1e-6, 1e-6, 1e-6])  # a 2-D driver on a 3-D robot
    noise, reasons = reader.read(pose.ravel(), None, np.eye(3))
    assert noise is None and reasons == ['pose_zero_variance']


def test_pose_with_covariance_stamped_round_trip():
    types = RosbagsTypes(STORE)
    rng = np.random.default_rng(2)
    covariance = _random_covariance(rng, np.full(6, 1e-3)).ravel()
    base = BaseStateSample(123, 'world', 'base', [1.0, 2.0, 3.0], [0.0, 0.0, 0.6, 0.8])
    msg = base_state_to_pose_with_covariance_stamped(base, types, covariance)
    data = bytes(STORE.serialize_cdr(msg, 'geometry_msgs/msg/PoseWithCovarianceStamped'))
    fast = cdr.decode_pose_with_covariance_stamped(data, 'base')
    slow = pose_with_covariance_stamped_from_ros(
        STORE.deserialize_cdr(data, 'geometry_msgs/msg/PoseWithCovarianceStamped'), 'base')
    for sample in (fast, slow):
        assert sample.pose_covariance.tobytes() == covariance.tobytes()
        assert sample.twist_covariance is None and not sample.has_twist
        assert sample.position.tolist() == [1.0, 2.0, 3.0] and sample.child_frame_id == 'base'
    zeros = base_state_to_pose_with_covariance_stamped(base, types)
    data = bytes(STORE.serialize_cdr(zeros, 'geometry_msgs/msg/PoseWithCovarianceStamped'))
    assert cdr.decode_pose_with_covariance_stamped(data).pose_covariance is None


# ------------------------------------------------------------------ the estimator

#: Sensors far from the default noise parameters (pose 1 mm / 2 mrad, twist 1e-2).
SENSORS = dict(noise_position=1e-3, noise_velocity=1e-2, noise_pose=4e-3,
               noise_orientation=5e-4, noise_twist=3e-2, noise_twist_angular=2e-3)
#: The parameters file a careful user would write for SENSORS.
MATCHING = dict(pose_position_noise=4e-3, pose_angle_noise=5e-4, twist_linear_noise=3e-2,
                twist_angular_noise=2e-3, joint_velocity_noise=1e-2)


@functools.lru_cache(maxsize=None)
def _bag(directory: str, name: str, **extra) -> Path:
    path = Path(directory) / name
    options = SimulationOptions(duration=6.0, rate=100.0, seed=4, torque='sinusoid',
                                thrusters=(ThrusterPulse(2.0, 1.0, (3, 0, 0, 0, 0, 1)),),
                                **SENSORS, **extra)
    simulate_bag(paper_robot(), path, options)
    return path


@pytest.fixture(scope='module')
def odom_bag(tmp_path_factory) -> Path:
    return _bag(str(tmp_path_factory.mktemp('cov')), 'odom')


def _run(samples, **params):
    config = EstimatorConfig.from_mapping({**defaults(), 'prediction_rate': 0.0, **params})
    estimator = Estimator(paper_robot(), config, use_odometry=True)
    outputs = estimator.add_samples(samples).outputs() + estimator.flush_batch().outputs()
    return estimator, outputs


def _columns(outputs):
    return (np.array([o.mu for o in outputs]), np.array([o.momentum_covariance for o in outputs]),
            np.array([o.wrench_covariance for o in outputs]))


def _stripped(samples, indices=None):
    """Return the samples with the covariances of base samples (at ``indices``) removed."""
    out, k = [], 0
    for sample in samples:
        if isinstance(sample, BaseStateSample):
            if indices is None or k in indices:
                sample = dataclasses.replace(sample, pose_covariance=None, twist_covariance=None)
            k += 1
        out.append(sample)
    return out


def test_switch_off_is_the_noise_parameters_alone(odom_bag):
    samples, _, _ = load_inputs(str(odom_bag), paper_robot(), ReplayOptions())
    assert all(s.pose_covariance is not None for s in samples if isinstance(s, BaseStateSample))
    _, off = _run(samples, use_message_covariance=False)
    _, plain = _run(_stripped(samples))
    _, on = _run(samples)
    for a, b in zip(_columns(off), _columns(plain)):
        assert a.tobytes() == b.tobytes()
    assert not np.array_equal(_columns(on)[0], _columns(off)[0])


def test_bad_covariance_falls_back_to_the_parameters_and_is_counted(odom_bag):
    samples, _, _ = load_inputs(str(odom_bag), paper_robot(), ReplayOptions())
    bad = {40, 41, 42, 300}
    broken, k = [], 0
    for sample in samples:
        if isinstance(sample, BaseStateSample):
            if k in bad:
                values = sample.pose_covariance.copy()
                values[7] = np.nan
                sample = dataclasses.replace(sample, pose_covariance=values)
            k += 1
        broken.append(sample)
    estimator, outputs = _run(broken, diagnostics_rate=1.0)
    assert dict(estimator.covariance_fallbacks) == {'pose_non_finite': len(bad)}
    # Not rejected (the innovation gate may take one: 1 mm parameters for a 4 mm sensor).
    assert set(estimator.rejected) <= {'innovation_gate'}
    assert estimator.summary()['covariance_fallbacks'] == {'pose_non_finite': len(bad)}
    # Those samples are used with the noise parameters (their twist covariance is good
    # and used); the others with their own covariance.
    partly = [dataclasses.replace(s, pose_covariance=None) if s is not t else s
              for s, t in zip(broken, samples)]
    _, expected = _run(partly)
    for a, b in zip(_columns(outputs), _columns(expected)):
        assert a.tobytes() == b.tobytes()
    statuses = [s for o in outputs if o.diagnostics is not None
                for s in o.diagnostics.statuses if s.name == 'reduced_dynamics: inputs']
    assert statuses[-1].values_dict()['covariance_fallback_pose_non_finite'] == str(len(bad))
    assert any(s.level == DIAG_WARN and s.message.startswith('pose_non_finite: base sample')
               for s in statuses)


def _truth(bag: Path) -> tuple[dict, dict]:
    """Return the simulator's momentum and external wrench by stamp."""
    out = {}
    with open_bag(str(bag)) as reader:
        for topic in ('/ground_truth/momentum', '/ground_truth/external_wrench'):
            values = {}
            for message in reader.messages([topic]):
                w = wrench_from_ros(message.msg)
                values[w.stamp_ns] = np.concatenate((w.force, w.torque))
            out[topic] = values
    return out['/ground_truth/momentum'], out['/ground_truth/external_wrench']


def _scores(bag: Path, params: dict) -> dict:
    """Return momentum NEES per dof, wrench RMS error and mean wrench sigma of a replay."""
    samples, _, _ = load_inputs(str(bag), paper_robot(), ReplayOptions())
    _, outputs = _run(samples, **params)
    momentum, wrench = _truth(bag)
    start = outputs[0].stamp_ns + 1_000_000_000  # past the start transient
    nees, errors, sigmas = [], [], []
    for o in outputs:
        if o.stamp_ns < start or o.stamp_ns not in momentum:
            continue
        e = o.mu - momentum[o.stamp_ns]
        nees.append(e @ np.linalg.solve(o.momentum_covariance, e) / e.size)
        rate = np.concatenate((o.momentum_rate.force, o.momentum_rate.torque))
        errors.append(rate - wrench[o.stamp_ns])
        sigmas.append(np.sqrt(np.diag(o.wrench_covariance)))
    return {'nees': float(np.mean(nees)),
            'wrench_rms': np.sqrt(np.mean(np.square(errors), axis=0)),
            'wrench_sigma': np.mean(sigmas, axis=0)}


def test_a_bag_with_covariances_needs_no_params_file(odom_bag):
    own = _scores(odom_bag, {})
    careful = _scores(odom_bag, {**MATCHING, 'use_message_covariance': False})
    naive = _scores(odom_bag, {'use_message_covariance': False})
    # The simulator's covariances are the parameters a careful user gives: the same filter
    # to rounding (measured: NEES 0.69555 both, agreeing to 2e-15).
    assert own['nees'] == pytest.approx(careful['nees'], rel=1e-9)
    assert np.allclose(own['wrench_rms'], careful['wrench_rms'], rtol=1e-9, atol=0)
    assert np.allclose(own['wrench_sigma'], careful['wrench_sigma'], rtol=1e-9, atol=0)
    # The defaults (1 mm, 1e-2 m/s for a 4 mm, 3e-2 m/s sensor) are what the covariances
    # spare the user: measured NEES 4.7, wrench errors hundreds of times larger.
    assert naive['nees'] > 2.0 * careful['nees']
    assert (naive['wrench_rms'] > 10.0 * careful['wrench_rms']).all()


def test_pose_with_covariance_bag_replays_like_its_params_file(tmp_path):
    bag = _bag(str(tmp_path), 'pose', base_pose_only=True, base_pose_covariance=True)
    with open_bag(str(bag)) as reader:
        assert reader.topics()['/base_pose'] == 'geometry_msgs/msg/PoseWithCovarianceStamped'
    summaries = {}
    for name, params in (('own', {}),
                         ('careful', {**MATCHING, 'use_message_covariance': False}),
                         ('naive', {'use_message_covariance': False})):
        options = ReplayOptions(params={**defaults(), 'base_input': 'pose', **params})
        summaries[name] = replay(str(bag), str(tmp_path / name), paper_robot(), options)
    own, careful, naive = (summaries[k]['filter'] for k in ('own', 'careful', 'naive'))
    assert not summaries['own']['covariance_fallbacks']
    # Measured: NIS per dof 0.9166 both (to 2e-15), 21.8 with the default parameters.
    assert own['nis_per_dof'] == pytest.approx(careful['nis_per_dof'], rel=1e-9)
    assert own['log_likelihood'] == pytest.approx(careful['log_likelihood'], rel=1e-9)
    assert naive['nis_per_dof'] > 2.0 * careful['nis_per_dof']
