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

"""The one-row chunk's own path (streaming) gives the general chunk path's bits."""

import numpy as np
import pytest

from conftest_robots import paper_robot, planar_robot
from reduced_dynamics import bench
from reduced_dynamics.estimator import Estimator, EstimatorConfig
from reduced_dynamics.estimator.outputs import OutputChunk
from reduced_dynamics.estimator.processing import ChunkProcessing
from reduced_dynamics.geometry.isotropy import MomentumClass
from reduced_dynamics.messages.samples import BaseStateSample, CommandSample, JointStateSample
from reduced_dynamics.validation import random_scenario
from sim_samples import feed_stream, samples, simulate
from test_estimator_batch import _same

MS = 1_000_000


def _general(monkeypatch: pytest.MonkeyPatch) -> None:
    """Send one-row chunks and their outputs down the general (stacked) path."""
    monkeypatch.setattr(ChunkProcessing, '_process_row',
                        lambda self, chunk: self._process_rows(chunk, 1))
    monkeypatch.setattr(OutputChunk, '_one_output', lambda self: self._row_outputs()[0])


def _row_calls(monkeypatch: pytest.MonkeyPatch) -> list:
    """Count the one-row path's chunks (a spy around the real method)."""
    calls = []
    real = ChunkProcessing._process_row

    def spy(self, chunk):
        calls.append(chunk.rows[0][0])
        return real(self, chunk)
    monkeypatch.setattr(ChunkProcessing, '_process_row', spy)
    return calls


def _both(make, stream, send=feed_stream):
    """Return (outputs, state) of the stream on the row path and on the general path."""
    results = []
    for general in (False, True):
        with pytest.MonkeyPatch.context() as patch:
            if general:
                _general(patch)
                calls = []
            else:
                calls = _row_calls(patch)
            estimator = make()
            outputs = send(estimator, stream)
            summary = estimator.summary()
            events = [(e.start_ns, e.end_ns, e.peak_wrench, e.mu_before, e.mu_after)
                      for e in estimator.events]
            results.append((outputs, (summary, events, estimator.last_rejection,
                                      dict(estimator.rejected), estimator.filter.x,
                                      estimator.filter.p), len(calls)))
    (row_out, row_state, row_calls), (general_out, general_state, _) = results
    assert len(row_out) == len(general_out)
    _same(row_out, general_out, 'outputs')
    # One row at a time on both: even the running mean and spread are the same bits.
    _same(row_state, general_state, 'state')
    return row_out, row_state, row_calls


def _pulse(robot, odometry: bool, late: bool = True):
    """Return simulated samples of a wrench pulse, base samples late and jittered (``late``)."""
    scenario = random_scenario(robot, MomentumClass.GENERIC, 5, drift_speed=0.1,
                               shape_speed=0.2)
    times = np.arange(401) / 200.0
    wrench = np.array([20.0, -10.0, 0.0, 0.0, 0.0, -3.0])
    run = simulate(robot, scenario.state, scenario.torque, times, (0.8, 0.1, wrench))
    joints, bases = samples(robot, times, *run[:4], torque=scenario.torque, odometry=odometry)
    rng = np.random.default_rng(0)
    stream = []
    for joint, base in zip(joints, bases):
        stamp = base.stamp_ns + (int(rng.integers(0, 2 * MS)) if late else 0)
        stream += [joint, BaseStateSample(stamp, base.frame_id, base.child_frame_id,
                                          base.position, base.orientation_xyzw,
                                          base.twist_linear, base.twist_angular)]
    return stream


PRECISE = dict(prediction_rate=2.0, prediction_horizon=0.3, diagnostics_rate=5.0,
               event_hold=0.05, pose_position_noise=1e-5, pose_angle_noise=1e-5,
               twist_linear_noise=1e-5, twist_angular_noise=1e-5, pose_stamp_noise=1e-3,
               prediction_max_wall_time=0.0)


@pytest.mark.parametrize('make_robot, odometry, late, lag', [
    (paper_robot, True, False, 0.0), (paper_robot, True, True, 0.05),
    (paper_robot, False, True, 0.0), (planar_robot, True, True, 0.0)])
def test_the_row_path_equals_the_general_path(make_robot, odometry, late, lag):
    """Predictions, diagnostics, events, fixed-lag rows, pose mode, SE(2): the same bits."""
    robot = make_robot()
    stream = _pulse(robot, odometry, late)
    config = EstimatorConfig(smoothing_lag=lag, **PRECISE)
    outputs, state, calls = _both(lambda: Estimator(robot, config, use_odometry=odometry),
                                  stream)
    assert calls >= 290 and len(outputs) >= 290
    assert any(o.diagnostics is not None for o in outputs)
    assert any(o.prediction_path is not None for o in outputs)
    assert state[1], 'the pulse is an event'
    if lag:
        assert any(o.fixed_lag for o in outputs)


def test_rows_between_measurements_and_measurements_before_the_row():
    """
    1 kHz joint states + 200 Hz odometry on their own clocks, each odometry sample early.

    Every joint state then finds a base sample after it and is a chunk of one: rows
    with no measurement (they only propagate) and rows with one before their stamp.
    """
    robot = paper_robot()
    joints, bases = bench.update_samples(robot, 400)
    shifted = [BaseStateSample(b.stamp_ns + bench.ODOMETRY_OFFSET_NS, b.frame_id,
                               b.child_frame_id, b.position, b.orientation_xyzw,
                               b.twist_linear, b.twist_angular)
               for b in bases[::bench.ODOMETRY_EVERY]]
    early = 5 * MS  # arrives one odometry period before its stamp
    stream = [s for _, _, s in sorted([(j.stamp_ns, 1, j) for j in joints]
                                      + [(b.stamp_ns - early, 0, b) for b in shifted],
                                      key=lambda e: e[:2])]
    outputs, _, calls = _both(lambda: Estimator(robot, EstimatorConfig(prediction_rate=0.0)),
                              stream)
    assert calls >= 390 and len(outputs) >= 390


def test_message_noise_gated_poses_and_a_coast_restart():
    """Rare rows: the message's own covariance, a pose jump the gate refuses, a coast."""
    robot = paper_robot()
    joints, bases = bench.update_samples(robot, 300)
    covariance = np.diag([1e-4, 1e-4, 1e-4, 1e-3, 1e-3, 1e-3]).ravel()
    coast = int(11e9)  # beyond the filter's 10 s coast cap: it restarts
    stream = []
    for k, (joint, base) in enumerate(zip(joints, bases)):
        shift = coast if k >= 200 else 0
        position = base.position + (np.array([0.5, 0.0, 0.0]) if k in (120, 121) else 0.0)
        noisy = k % 3 == 0
        stream += [
            type(joint)(joint.stamp_ns + shift, joint.frame_id, joint.names, joint.position,
                        joint.velocity, joint.effort),
            BaseStateSample(base.stamp_ns + shift, base.frame_id, base.child_frame_id,
                            position, base.orientation_xyzw, base.twist_linear,
                            base.twist_angular,
                            pose_covariance=covariance if noisy else None,
                            twist_covariance=covariance if noisy else None)]
    config = EstimatorConfig(prediction_rate=0.0, use_message_covariance=True)
    outputs, state, calls = _both(lambda: Estimator(robot, config), stream)
    assert calls >= 290 and len(outputs) >= 290
    assert state[3].get('innovation_gate', 0) >= 1
    assert state[0]['filter']['filter_restart_causes'].get('coast', 0) == 1


def test_a_commanded_wrench_takes_the_general_path():
    """The row path hands a commanded-wrench chunk back to the general path."""
    robot = paper_robot()
    joints, bases = bench.update_samples(robot, 50)
    stream = []
    for joint, base in zip(joints, bases):
        stream += [CommandSample(joint.stamp_ns, robot.base_link, np.full(3, 0.1),
                                 np.zeros(3)), joint, base]

    def send(estimator, stream):
        outputs = []
        for sample in stream:
            add = estimator.add_command if isinstance(sample, CommandSample) \
                else estimator.add_joint_state if isinstance(sample, JointStateSample) \
                else estimator.add_base_state
            outputs += add(sample)
        return outputs + estimator.flush()
    outputs, _, calls = _both(lambda: Estimator(robot, EstimatorConfig(prediction_rate=0.0),
                                                commanded_wrench=True), stream, send)
    assert calls == 0 and len(outputs) >= 45
    assert outputs[-1].disturbance is not None
