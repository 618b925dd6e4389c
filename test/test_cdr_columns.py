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

"""The column encoders give the per-message encoders' bytes for every output topic."""

import numpy as np
import pytest

from conftest_robots import paper_robot, planar_robot
from reduced_dynamics.estimator import Estimator, EstimatorConfig
from reduced_dynamics.estimator.outputs import COLUMN_FIELDS
from reduced_dynamics.geometry.isotropy import MomentumClass
from reduced_dynamics.messages import cdr
from reduced_dynamics.messages.cdr_columns import (joint_state_records, split, stamp_columns,
                                                   vector6_records)
from reduced_dynamics.messages.samples import (JointStateSample, trusted_sample, TwistSample,
                                               WrenchSample)
from reduced_dynamics.resources import config_path
from reduced_dynamics.robot.model import load_robot
from reduced_dynamics.validation import random_scenario
from sim_samples import samples, simulate

NS = 1_000_000_000
#: stamps at the edges of builtin_interfaces/Time: 0, a second's last ns, int32 max sec
STAMPS = np.array([0, 1, NS - 1, NS, 1_700_000_000 * NS + 123, (2**31 - 1) * NS + NS - 1])


def _awkward(rng, shape):
    """Return float64 values with NaN (two payloads), infinities, -0.0 and subnormals."""
    values = rng.normal(size=shape)
    flat = values.reshape(-1)
    specials = [np.nan, -np.nan, np.inf, -np.inf, -0.0, 5e-324,
                np.frombuffer(b'\x01\x00\x00\x00\x00\x00\xf8\x7f', '<f8')[0]]
    flat[:len(specials)] = specials[:flat.size]
    return values


@pytest.mark.parametrize('frame_id', ['', 'w', 'world', 'base_link', 'abcdefg', 'bäse'])
def test_vector6_records_are_the_wrench_and_twist_bytes(frame_id):
    rng = np.random.default_rng(4)
    values = _awkward(rng, (len(STAMPS), 6))
    rows = split(vector6_records(stamp_columns(STAMPS), frame_id, values))
    for k, stamp in enumerate(STAMPS.tolist()):
        wrench = trusted_sample(WrenchSample, stamp, frame_id, values[k, :3], values[k, 3:])
        twist = trusted_sample(TwistSample, stamp, frame_id, values[k, :3], values[k, 3:])
        assert rows[k] == cdr.encode_wrench_stamped(wrench) == cdr.encode_twist_stamped(twist)


@pytest.mark.parametrize('names', [(), ('a',), ('j1', 'j22', 'j333'), ('abcd', 'e', 'fgh')])
@pytest.mark.parametrize('frame_id', ['', 'x', 'base_link'])
def test_joint_state_records_are_the_joint_state_bytes(names, frame_id):
    rng = np.random.default_rng(len(names))
    m = len(names)
    columns = [_awkward(rng, (len(STAMPS), m)) for _ in range(3)]
    rows = split(joint_state_records(stamp_columns(STAMPS), frame_id, names, *columns))
    for k, stamp in enumerate(STAMPS.tolist()):
        sample = trusted_sample(JointStateSample, stamp, frame_id, names,
                                *(c[k] for c in columns))
        assert rows[k] == cdr.encode_joint_state(sample)


def test_stamps_outside_ros_time_leave_the_columns():
    assert stamp_columns(np.array([0, -1])) is None
    assert stamp_columns(np.array([2**31 * NS])) is None
    assert stamp_columns(np.zeros(0, np.int64)) is not None
    with pytest.raises(ValueError):
        vector6_records(stamp_columns(STAMPS[:2]), '', np.zeros((2, 3)))
    with pytest.raises(ValueError):
        joint_state_records(stamp_columns(STAMPS[:2]), '', ('a',), *[np.zeros((2, 2))] * 3)


def _chunks(robot, cyclic_joints='', rotors=(), seconds=1.0, config=None, poisoned=False):
    scenario = random_scenario(robot, MomentumClass.GENERIC, 3, drift_speed=0.1,
                               shape_speed=0.2, rotors=rotors)
    times = np.arange(int(round(seconds * 200)) + 1) / 200.0
    run = simulate(robot, scenario.state, scenario.torque, times, None)
    joints, bases = samples(robot, times, *run[:4], torque=scenario.torque)
    config = (config or EstimatorConfig(prediction_rate=2.0, prediction_horizon=0.2,
                                        diagnostics_rate=5.0, prediction_max_wall_time=0.0)
              ).replaced(joint_limit_margin=1e6)
    estimator = Estimator(robot, config, cyclic_joints=cyclic_joints)
    stream = [item for pair in zip(bases, joints) for item in pair]
    chunks = []
    for start in range(0, len(stream), 64):
        chunks += estimator.add_samples(stream[start:start + 64]).chunks
    chunks += estimator.flush_batch().chunks
    if poisoned:
        # Columns as a diverged filter could leave them: NaN, infinities, -0.0.
        rng = np.random.default_rng(9)
        for chunk in chunks:
            for name in ('mu', 'pi', 'momentum_rate', 'drift', 'pbar'):
                column = getattr(chunk, name)
                column[:] = _awkward(rng, column.shape)
    return chunks


CASES = {
    # SE(3), predictions and diagnostics on some rows
    'paper': lambda: _chunks(paper_robot()),
    'paper_nan': lambda: _chunks(paper_robot(), poisoned=True),
    # SE(2): the algebra's 3 coordinates lifted to 6-vectors
    'planar': lambda: _chunks(planar_robot()),
    # second stage: shape state of the kept joints, cyclic momenta
    'cyclic': lambda: _chunks(load_robot(str(config_path('robots/paper_robot_wheels.urdf'))),
                              'auto', [6, 7, 8],
                              config=EstimatorConfig(prediction_rate=0.0)),
}


@pytest.mark.parametrize('case', sorted(CASES))
def test_chunk_records_are_the_outputs_encoded_one_by_one(case):
    chunks = CASES[case]()
    fields_seen = set()
    rows = 0
    for chunk in chunks:
        records = chunk.records()
        outputs = chunk.outputs()
        assert set(records) <= set(COLUMN_FIELDS)
        for name, part in records.items():
            fields_seen.add(name)
            got = split(part)
            assert len(got) == len(outputs)
            for k, output in enumerate(outputs):
                sample = getattr(output, name)
                assert got[k] == cdr.ENCODERS[_MSGTYPE[name]](sample), (name, k)
        for name in set(COLUMN_FIELDS) - set(records):
            assert all(getattr(o, name) is None for o in outputs), name
        rows += len(outputs)
    assert rows >= 200
    expected = {'momentum', 'body_momentum', 'shape_state', 'momentum_rate', 'drift_twist'}
    assert expected <= fields_seen
    assert ('cyclic_state' in fields_seen) == (case == 'cyclic')


def test_chunk_records_with_a_commanded_wrench_carry_the_disturbance():
    robot = planar_robot()
    chunks = _chunks(robot)
    for chunk in chunks:
        chunk.disturbance = np.random.default_rng(1).normal(size=chunk.mu.shape)
        records = chunk.records()
        for k, output in enumerate(chunk.outputs()):
            assert split(records['disturbance'])[k] == \
                cdr.encode_wrench_stamped(output.disturbance)


_MSGTYPE = {'momentum': 'geometry_msgs/msg/WrenchStamped',
            'body_momentum': 'geometry_msgs/msg/WrenchStamped',
            'momentum_rate': 'geometry_msgs/msg/WrenchStamped',
            'disturbance': 'geometry_msgs/msg/WrenchStamped',
            'drift_twist': 'geometry_msgs/msg/TwistStamped',
            'shape_state': 'sensor_msgs/msg/JointState',
            'cyclic_state': 'sensor_msgs/msg/JointState'}
