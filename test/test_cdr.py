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
Fixed-layout CDR codecs against rosbags' generic serializer, byte for byte.

Encoders must give exactly ``typestore.serialize_cdr(<x>_to_ros(sample))``;
decoders must give the sample ``<x>_from_ros(typestore.deserialize_cdr(data))``
gives, and must refuse whatever they do not handle exactly.
"""

import string

import numpy as np
import pytest
from rosbags.typesys import get_types_from_msg, get_typestore, Stores

from reduced_dynamics.messages import cdr
from reduced_dynamics.messages.convert import (
    base_state_to_odometry, base_state_to_pose_stamped, diagnostics_to_ros, event_to_ros,
    joint_state_from_ros, joint_state_to_ros, odometry_from_ros, pose_path_to_ros,
    pose_stamped_from_ros, shape_prediction_to_ros, twist_to_ros, wrench_to_ros)
from reduced_dynamics.messages.samples import (
    BaseStateSample, Diagnostics, DiagnosticStatusSample, EventSample, JointStateSample, PosePath,
    ShapePrediction, TwistSample, WrenchSample)
from reduced_dynamics.messages.types import RosbagsTypes

STORE = get_typestore(Stores.ROS2_JAZZY)
TYPES = RosbagsTypes(STORE)
ALPHABET = string.ascii_letters + string.digits + '_/'
NS = 1_000_000_000


def _text(rng: np.random.Generator, longest: int = 11) -> str:
    """Return a random name of 0..longest characters (non-ASCII now and then)."""
    text = ''.join(rng.choice(list(ALPHABET), int(rng.integers(0, longest + 1))))
    return text + 'é' if rng.random() < 0.1 else text


def _stamp(rng: np.random.Generator) -> int:
    return int(rng.integers(0, 2**31 - 1)) * NS + int(rng.integers(0, NS))


def _vector(rng: np.random.Generator, size: int) -> np.ndarray:
    values = rng.normal(size=size) * 10.0 ** rng.integers(-300, 300, size)
    special = rng.random(size) < 0.05
    values[special] = rng.choice([0.0, -0.0, np.inf, -np.inf, np.nan], int(special.sum()))
    return values


def _generic(msg, msgtype: str) -> bytes:
    return bytes(STORE.serialize_cdr(msg, msgtype))


def _samples(rng: np.random.Generator):
    """Yield (sample, to_ros, msgtype) of every encoded type with random content."""
    m = int(rng.integers(0, 8))
    names = tuple(_text(rng) or 'j' for _ in range(m))
    yield (WrenchSample(_stamp(rng), _text(rng), _vector(rng, 3), _vector(rng, 3)),
           wrench_to_ros, 'geometry_msgs/msg/WrenchStamped')
    yield (TwistSample(_stamp(rng), _text(rng), _vector(rng, 3), _vector(rng, 3)),
           twist_to_ros, 'geometry_msgs/msg/TwistStamped')
    yield (JointStateSample(_stamp(rng), _text(rng), names, _vector(rng, m),
                            _vector(rng, m) if rng.random() < 0.7 else np.zeros(0),
                            _vector(rng, m) if rng.random() < 0.5 else np.zeros(0)),
           joint_state_to_ros, 'sensor_msgs/msg/JointState')
    n = int(rng.integers(0, 5))
    yield (ShapePrediction(_stamp(rng), _text(rng), names,
                           np.cumsum(rng.integers(1, 3 * NS, n)),
                           _vector(rng, n * m).reshape(n, m),
                           _vector(rng, n * m).reshape(n, m) if rng.random() < 0.7 else None),
           shape_prediction_to_ros, 'trajectory_msgs/msg/JointTrajectory')
    yield (PosePath(_stamp(rng), _text(rng), np.sort(rng.integers(0, 2**40, n)),
                    _vector(rng, 3 * n).reshape(n, 3), _vector(rng, 4 * n).reshape(n, 4)),
           pose_path_to_ros, 'nav_msgs/msg/Path')
    statuses = tuple(
        DiagnosticStatusSample(int(rng.integers(0, 4)), _text(rng), _text(rng, 30),
                               _text(rng), [(_text(rng), _text(rng, 20))
                                            for _ in range(int(rng.integers(0, 4)))])
        for _ in range(int(rng.integers(0, 4))))
    yield (Diagnostics(_stamp(rng), statuses, _text(rng)), diagnostics_to_ros,
           'diagnostic_msgs/msg/DiagnosticArray')
    cov = _vector(rng, 36).reshape(6, 6)
    yield (EventSample(_stamp(rng), _stamp(rng) if rng.random() < 0.5 else None, _stamp(rng),
                       float(rng.random()) if rng.random() < 0.5 else None, float(rng.random()),
                       _vector(rng, 6), cov, bool(rng.random() < 0.5)),
           event_to_ros, 'std_msgs/msg/Float64MultiArray')


def test_encoders_match_rosbags_byte_for_byte():
    rng = np.random.default_rng(7)
    seen = set()
    for _ in range(300):
        for sample, to_ros, msgtype in _samples(rng):
            mine = cdr.ENCODERS[msgtype](sample)
            assert isinstance(mine, bytes)
            assert mine == _generic(to_ros(sample, TYPES), msgtype), (msgtype, sample)
            seen.add(msgtype)
    assert seen == set(cdr.ENCODERS)


@pytest.mark.parametrize('length', range(0, 10))
def test_every_frame_id_length_aligns_like_rosbags(length):
    frame = 'f' * length
    wrench = WrenchSample(3 * NS + 7, frame, [1.0, 2.0, 3.0], [4.0, 5.0, 6.0])
    assert cdr.encode_wrench_stamped(wrench) == _generic(
        wrench_to_ros(wrench, TYPES), 'geometry_msgs/msg/WrenchStamped')
    joints = JointStateSample(1, frame, ('a' * length,), [1.0], [], [2.0])
    assert cdr.encode_joint_state(joints) == _generic(
        joint_state_to_ros(joints, TYPES), 'sensor_msgs/msg/JointState')


def test_encoders_reject_what_the_converters_reject():
    late = WrenchSample(2**31 * NS, 'w', np.zeros(3), np.zeros(3))
    with pytest.raises(ValueError, match='overflows int32'):
        cdr.encode_wrench_stamped(late)
    with pytest.raises(ValueError):
        wrench_to_ros(late, TYPES)
    with pytest.raises(UnicodeEncodeError):
        cdr.encode_twist_stamped(TwistSample(0, '\udc80', np.zeros(3), np.zeros(3)))


def _odometry(rng: np.random.Generator) -> BaseStateSample:
    return BaseStateSample(_stamp(rng), _text(rng), _text(rng), _vector(rng, 3),
                           _vector(rng, 4), _vector(rng, 3), _vector(rng, 3))


def _assert_same_sample(mine, theirs):
    assert type(mine) is type(theirs)
    for name in type(theirs).__dataclass_fields__:
        a, b = getattr(mine, name), getattr(theirs, name)
        if isinstance(b, np.ndarray):
            assert isinstance(a, np.ndarray) and a.dtype == b.dtype and a.shape == b.shape
            assert a.flags.c_contiguous and a.flags.writeable
            assert a.tobytes() == b.tobytes(), name
        else:
            assert type(a) is type(b) and a == b, name


def test_decoders_match_rosbags_and_the_converters():
    rng = np.random.default_rng(11)
    for _ in range(300):
        m = int(rng.integers(0, 8))
        joints = JointStateSample(_stamp(rng), _text(rng), tuple(_text(rng) for _ in range(m)),
                                  _vector(rng, m), _vector(rng, m) if rng.random() < 0.7 else [],
                                  _vector(rng, m) if rng.random() < 0.5 else [])
        data = _generic(joint_state_to_ros(joints, TYPES), 'sensor_msgs/msg/JointState')
        _assert_same_sample(cdr.decode_joint_state(data), joint_state_from_ros(
            STORE.deserialize_cdr(data, 'sensor_msgs/msg/JointState')))
        base = _odometry(rng)
        covariance = rng.normal(size=36)
        data = _generic(base_state_to_odometry(base, TYPES, covariance, covariance),
                        'nav_msgs/msg/Odometry')
        _assert_same_sample(cdr.decode_odometry(data), odometry_from_ros(
            STORE.deserialize_cdr(data, 'nav_msgs/msg/Odometry')))
        data = _generic(base_state_to_pose_stamped(base, TYPES), 'geometry_msgs/msg/PoseStamped')
        _assert_same_sample(cdr.decode_pose_stamped(data, 'base'), pose_stamped_from_ros(
            STORE.deserialize_cdr(data, 'geometry_msgs/msg/PoseStamped'), 'base'))


def _bad_inputs():
    """Yield (name, decoder, bytes) that the fixed-layout decoders must refuse."""
    joints = JointStateSample(5 * NS, 'base', ('a', 'bb'), [1.0, 2.0], [3.0, 4.0], [])
    good = _generic(joint_state_to_ros(joints, TYPES), 'sensor_msgs/msg/JointState')
    decode = cdr.decode_joint_state
    yield 'empty', decode, b''
    yield 'header only', decode, good[:4]
    yield 'big endian', decode, b'\x00\x00' + good[2:]
    yield 'truncated', decode, good[:-3]
    yield 'trailing bytes', decode, good + b'\x00' * 4
    yield 'no frame terminator', decode, good[:15] + b'X' + good[16:]
    yield 'zero string length', decode, good[:12] + b'\x00\x00\x00\x00' + good[16:]
    yield 'huge name count', decode, good[:24] + b'\xff\xff\xff\x7f' + good[28:]
    yield 'invalid utf-8', decode, good[:16] + b'\xff' + good[17:]
    negative = bytearray(good)
    negative[4:8] = (-1).to_bytes(4, 'little', signed=True)
    yield 'negative stamp', decode, bytes(negative)
    short = JointStateSample(5 * NS, 'base', ('a', 'bb'), [1.0, 2.0], [3.0, 4.0], [])
    msg = joint_state_to_ros(short, TYPES)
    msg.velocity = np.zeros(1)
    yield 'velocity size', decode, _generic(msg, 'sensor_msgs/msg/JointState')
    odom = _generic(base_state_to_odometry(_odometry(np.random.default_rng(1)), TYPES),
                    'nav_msgs/msg/Odometry')
    yield 'odometry truncated', cdr.decode_odometry, odom[:-8]
    yield 'odometry trailing', cdr.decode_odometry, odom + b'\x00' * 8
    yield 'odometry as pose', cdr.decode_pose_stamped, odom


@pytest.mark.parametrize('name, decode, data', list(_bad_inputs()),
                         ids=[case[0] for case in _bad_inputs()])
def test_decoders_refuse_what_they_do_not_handle_exactly(name, decode, data):
    with pytest.raises(ValueError):
        decode(data)


def test_random_corruption_never_decodes_differently():
    # Whatever the damage, the fast decoder either refuses or agrees with rosbags.
    rng = np.random.default_rng(3)
    joints = JointStateSample(5 * NS, 'base', ('a', 'bb', 'ccc'), [1.0, 2.0, 3.0],
                              [4.0, 5.0, 6.0], [])
    good = _generic(joint_state_to_ros(joints, TYPES), 'sensor_msgs/msg/JointState')
    for _ in range(2000):
        data = bytearray(good)
        for index in rng.integers(0, len(data), int(rng.integers(1, 4))):
            data[index] = int(rng.integers(0, 256))
        data = bytes(data[:len(data) - int(rng.integers(0, 3))])
        try:
            mine = cdr.decode_joint_state(data)
        except ValueError:
            continue
        _assert_same_sample(mine, joint_state_from_ros(
            STORE.deserialize_cdr(data, 'sensor_msgs/msg/JointState')))


def test_fast_path_only_for_the_standard_definitions():
    assert cdr.fast_path_applies(None, 'sensor_msgs/msg/JointState')
    assert cdr.fast_path_applies(STORE, 'nav_msgs/msg/Odometry')
    assert not cdr.fast_path_applies(STORE, 'std_msgs/msg/String')
    other = get_typestore(Stores.EMPTY)
    other.register(get_types_from_msg('std_msgs/Header header\nstring[] name\n'
                                      'float32[] position', 'sensor_msgs/msg/JointState'))
    assert not cdr.fast_path_applies(other, 'sensor_msgs/msg/JointState')
    limited = get_typestore(Stores.ROS2_JAZZY)
    limited.max_sequence_length = 100
    assert not cdr.fast_path_applies(limited, 'sensor_msgs/msg/JointState')


def test_every_output_topic_encodes_its_own_sample_as_rosbags_does():
    """Two outputs share Float64MultiArray (events, shape covariance): each its own bytes."""
    from reduced_dynamics.messages.uncertainty import ShapeCovariance
    from reduced_dynamics.topics import cdr_encoder, OUTPUT_TOPICS
    topic = next(t for t in OUTPUT_TOPICS if t.name == 'prediction/shape_covariance')
    sample = ShapeCovariance(('a', 'b'), np.arange(16.0).reshape(4, 4))
    expected = bytes(STORE.serialize_cdr(topic.to_ros(sample, TYPES), topic.msgtype))
    assert cdr_encoder(topic, TYPES)(sample) == expected
