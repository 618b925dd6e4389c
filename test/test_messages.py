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
Tests for reduced_dynamics.messages (samples, time helpers, conversions).

Every conversion is exercised with rosbags typestore classes (including a CDR
serialize/deserialize round trip) and with ``FakeRclpyMessages``, a TEST DOUBLE
that mimics the behaviour of rclpy-generated message classes.
"""

from collections.abc import Sequence
import array
from pathlib import Path
import re
import types
from typing import Any, Callable

import numpy as np
import pytest
from rosbags.typesys import get_typestore, Stores

from reduced_dynamics.messages import (
    base_state_to_odometry,
    base_state_to_pose_stamped,
    BaseStateSample,
    byte_to_int,
    clock_from_ros,
    clock_to_ros,
    DIAG_ERROR,
    DIAG_OK,
    DIAG_STALE,
    DIAG_WARN,
    Diagnostics,
    diagnostics_from_ros,
    diagnostics_to_ros,
    DiagnosticStatusSample,
    duration_from_ros,
    duration_to_ros,
    joint_state_from_ros,
    joint_state_to_ros,
    JointStateSample,
    MessageTypes,
    NS_PER_S,
    odometry_from_ros,
    pose_path_from_ros,
    pose_path_to_ros,
    pose_stamped_from_ros,
    PosePath,
    RclpyTypes,
    RosbagsTypes,
    shape_prediction_from_ros,
    shape_prediction_to_ros,
    ShapePrediction,
    string_from_ros,
    string_to_ros,
    time_from_ros,
    time_to_ros,
    twist_from_ros,
    twist_to_ros,
    TwistSample,
    wrench_from_ros,
    wrench_to_ros,
    WrenchSample,
)

JAZZY = get_typestore(Stores.ROS2_JAZZY)
T0 = 1_700_000_000 * NS_PER_S + 123_456_789


# ============================================================================================
# TEST DOUBLE: fake rclpy message classes (NOT rclpy).
#
# Classes are generated from the rosbags Jazzy field definitions and enforce the checks the
# rosidl-generated Python setters perform, so conversions that would fail with real rclpy
# fail here too:
#   * keyword-only constructor, unknown keywords rejected, missing fields get defaults;
#   * float32/float64 fields require ``float``; integer fields require ``int`` (not bool);
#   * ``byte`` fields require a length-1 ``bytes``;
#   * ``float64[]`` sequences accept ``array.array('d')`` or a non-numpy Sequence of floats
#     and are stored as ``array.array('d')`` (rclpy rejects numpy arrays there);
#   * fixed-size ``float64[N]`` arrays are stored as numpy float64 arrays of size N;
#   * nested messages / message sequences must be instances of the fake classes.
# ============================================================================================

_INT_TYPES = {'int8', 'uint8', 'int16', 'uint16', 'int32', 'uint32', 'int64', 'uint64', 'char'}
_FLOAT_TYPES = {'float32', 'float64'}


class FakeRclpyMessages:
    """TEST DOUBLE namespace providing ``import_module('<pkg>.msg')``-like lookups."""

    def __init__(self) -> None:
        """Start with no generated classes."""
        self.classes: dict[str, type] = {}
        self.imports: list[str] = []

    def import_module(self, name: str) -> types.ModuleType:
        """Return a fake ``<pkg>.msg`` module whose attributes are fake message classes."""
        self.imports.append(name)
        pkg, sub = name.split('.')
        if not any(k.startswith(f'{pkg}/{sub}/') for k in JAZZY.fielddefs):
            raise ImportError(f'No module named {name!r} (fake rclpy namespace)')
        module = types.ModuleType(name, 'TEST DOUBLE of an rclpy message module')
        for key in JAZZY.fielddefs:
            if key.startswith(f'{pkg}/{sub}/'):
                setattr(module, key.rsplit('/', 1)[1], self.get(key))
        return module

    def get(self, msgtype: str) -> type:
        """Return (creating lazily) the fake class for ``msgtype``."""
        if msgtype not in self.classes:
            self.classes[msgtype] = self._make(msgtype)
        return self.classes[msgtype]

    def _make(self, msgtype: str) -> type:
        consts, fields = JAZZY.fielddefs[msgtype]
        owner = self
        specs = [(name, node) for name, node in fields
                 if name != 'structure_needs_at_least_one_member']

        def init(msg: Any, **kwargs: Any) -> None:
            unknown = set(kwargs) - {n for n, _ in specs}
            assert not unknown, f'Invalid arguments passed to constructor: {unknown}'
            for name, node in specs:
                if name in kwargs:
                    setattr(msg, name, kwargs[name])
                else:
                    object.__setattr__(msg, '_' + name, owner._default(node))

        namespace: dict[str, Any] = {'__init__': init, '__slots__': (), '_TYPE': msgtype}
        namespace['__slots__'] = tuple('_' + n for n, _ in specs)
        for cname, ctype, cvalue in consts:
            namespace[cname] = bytes([cvalue]) if ctype == 'byte' else cvalue
        for name, node in specs:
            namespace[name] = self._property(msgtype, name, node)
        return type(msgtype.rsplit('/', 1)[1], (), namespace)

    def _default(self, node: Any) -> Any:
        kind, detail = node
        if kind == 1:  # base
            base = detail[0]
            if base == 'byte':
                return b'\x00'
            if base in ('string', 'bounded_string'):
                return ''
            return 0.0 if base in _FLOAT_TYPES else (False if base == 'bool' else 0)
        if kind == 2:  # nested message
            return self.get(detail)()
        inner, size = detail
        if kind == 3:  # fixed array
            if inner[0] == 1 and inner[1][0] in _FLOAT_TYPES:
                return np.zeros(size)
            return [self._default(inner) for _ in range(size)]
        if inner[0] == 1 and inner[1][0] == 'float64':
            return array.array('d')
        return []

    def _check_scalar(self, where: str, base: str, value: Any) -> Any:
        if base == 'byte':
            assert isinstance(value, bytes) and len(value) == 1, \
                f"The '{where}' field must be of type 'bytes' (length 1), got {value!r}"
        elif base in _FLOAT_TYPES:
            assert isinstance(value, float), f"The '{where}' field must be float, got {value!r}"
        elif base in _INT_TYPES:
            assert isinstance(value, int) and not isinstance(value, bool), \
                f"The '{where}' field must be int, got {type(value).__name__}"
        elif base == 'bool':
            assert isinstance(value, bool), f"The '{where}' field must be bool"
        else:
            assert isinstance(value, str), f"The '{where}' field must be str, got {value!r}"
        return value

    def _property(self, msgtype: str, name: str, node: Any) -> property:
        owner = self
        where = f'{msgtype}.{name}'

        def getter(msg: Any) -> Any:
            return object.__getattribute__(msg, '_' + name)

        def setter(msg: Any, value: Any) -> None:
            kind, detail = node
            if kind == 1:
                value = owner._check_scalar(where, detail[0], value)
            elif kind == 2:
                assert isinstance(value, owner.get(detail)), \
                    f"The '{where}' field must be a sub message of type '{detail}'"
            else:
                inner, size = detail
                if kind == 3 and inner[0] == 1 and inner[1][0] in _FLOAT_TYPES:
                    if isinstance(value, np.ndarray):
                        assert value.dtype == np.float64 and value.size == size, where
                    else:
                        value = np.array(value, dtype=np.float64)
                        assert value.size == size, where
                elif kind == 4 and inner[0] == 1 and inner[1][0] == 'float64':
                    if isinstance(value, array.array):
                        assert value.typecode == 'd', where
                    else:
                        assert isinstance(value, Sequence) and not isinstance(value, str), \
                            f"The '{where}' field must be a sequence (numpy arrays rejected)"
                        assert all(isinstance(v, float) for v in value), where
                        value = array.array('d', value)
                else:
                    assert isinstance(value, Sequence) and not isinstance(value, str), where
                    if kind == 3:
                        assert len(value) == size, where
                    for item in value:
                        if inner[0] == 2:
                            assert isinstance(item, owner.get(inner[1])), where
                        else:
                            owner._check_scalar(where, inner[1][0], item)
                    value = list(value)
            object.__setattr__(msg, '_' + name, value)

        return property(getter, setter)


# ============================================================================================
# fixtures and helpers
# ============================================================================================


@pytest.fixture
def fake_rclpy() -> FakeRclpyMessages:
    """Provide a fresh TEST DOUBLE namespace."""
    return FakeRclpyMessages()


def cdr_round_trip(msg: Any) -> Any:
    """Serialize a rosbags message to CDR and back."""
    raw = JAZZY.serialize_cdr(msg, msg.__msgtype__)
    return JAZZY.deserialize_cdr(raw, msg.__msgtype__)


@pytest.fixture(params=['rosbags', 'rclpy_double'])
def source(request: pytest.FixtureRequest) -> tuple[MessageTypes, Callable[[Any], Any]]:
    """Yield (types, transport) for both message sources; transport mimics pub/sub."""
    if request.param == 'rosbags':
        return RosbagsTypes(), cdr_round_trip
    fake = FakeRclpyMessages()
    return RclpyTypes(importer=fake.import_module), lambda msg: msg


def rng_vec(n: int, seed: int = 0) -> np.ndarray:
    """Return deterministic random values."""
    return np.random.default_rng(seed).normal(size=n)


def unit_quat(seed: int = 0) -> np.ndarray:
    """Return a deterministic unit quaternion (x, y, z, w)."""
    q = rng_vec(4, seed)
    return q / np.linalg.norm(q)


# ============================================================================================
# round trips through both sources
# ============================================================================================


def test_joint_state_round_trip(source: Any) -> None:
    types_, transport = source
    sample = JointStateSample(T0, 'base_link', ('j1', 'j2', 'j3'), rng_vec(3), rng_vec(3, 1),
                              np.zeros(0))
    msg = transport(joint_state_to_ros(sample, types_))
    back = joint_state_from_ros(msg)
    assert back.stamp_ns == T0 and back.frame_id == 'base_link'
    assert back.names == ('j1', 'j2', 'j3')
    np.testing.assert_array_equal(back.position, sample.position)
    np.testing.assert_array_equal(back.velocity, sample.velocity)
    assert back.effort.shape == (0,)


def test_float_seq_kinds_per_source(fake_rclpy: FakeRclpyMessages) -> None:
    sample = JointStateSample(5, '', ('a',), [1.0])
    bag_msg = joint_state_to_ros(sample, RosbagsTypes())
    assert isinstance(bag_msg.position, np.ndarray) and bag_msg.position.dtype == np.float64
    ros_msg = joint_state_to_ros(sample, RclpyTypes(importer=fake_rclpy.import_module))
    assert isinstance(ros_msg.position, array.array) and ros_msg.position.typecode == 'd'
    assert type(ros_msg).__name__ == 'JointState'


def test_from_ros_copies_arrays() -> None:
    types_ = RosbagsTypes()
    msg = cdr_round_trip(joint_state_to_ros(JointStateSample(1, '', ('a',), [2.0]), types_))
    back = joint_state_from_ros(msg)
    assert back.position.flags.writeable and not np.shares_memory(back.position, msg.position)


def test_odometry_round_trip(source: Any) -> None:
    types_, transport = source
    sample = BaseStateSample(T0, 'world', 'base_link', rng_vec(3), unit_quat(), rng_vec(3, 2),
                             rng_vec(3, 3))
    cov = np.arange(36.0)
    msg = transport(base_state_to_odometry(sample, types_, pose_covariance=cov))
    np.testing.assert_array_equal(np.asarray(msg.pose.covariance), cov)
    back = odometry_from_ros(msg)
    assert (back.stamp_ns, back.frame_id, back.child_frame_id) == (T0, 'world', 'base_link')
    for key in ('position', 'orientation_xyzw', 'twist_linear', 'twist_angular'):
        np.testing.assert_array_equal(getattr(back, key), getattr(sample, key))


def test_pose_stamped_round_trip(source: Any) -> None:
    types_, transport = source
    sample = BaseStateSample(T0, 'world', 'base_link', rng_vec(3), unit_quat(4), rng_vec(3),
                             rng_vec(3))
    back = pose_stamped_from_ros(transport(base_state_to_pose_stamped(sample, types_)),
                                 child_frame_id='base_link')
    assert back.twist_linear is None and back.twist_angular is None and not back.has_twist
    assert back.child_frame_id == 'base_link'
    np.testing.assert_array_equal(back.orientation_xyzw, sample.orientation_xyzw)


def test_odometry_requires_twist() -> None:
    sample = BaseStateSample(0, 'world', 'base', np.zeros(3), [0, 0, 0, 1])
    with pytest.raises(ValueError, match='no twist'):
        base_state_to_odometry(sample, RosbagsTypes())


def test_wrench_and_twist_round_trip(source: Any) -> None:
    types_, transport = source
    wrench = WrenchSample(T0, 'world', rng_vec(3, 5), rng_vec(3, 6))
    back = wrench_from_ros(transport(wrench_to_ros(wrench, types_)))
    assert (back.stamp_ns, back.frame_id) == (T0, 'world')
    np.testing.assert_array_equal(back.force, wrench.force)
    np.testing.assert_array_equal(back.torque, wrench.torque)
    twist = TwistSample(T0, 'base_link', rng_vec(3, 7), rng_vec(3, 8))
    tback = twist_from_ros(transport(twist_to_ros(twist, types_)))
    np.testing.assert_array_equal(tback.linear, twist.linear)
    np.testing.assert_array_equal(tback.angular, twist.angular)
    assert tback.frame_id == 'base_link'


@pytest.mark.parametrize('with_velocities', [True, False])
def test_shape_prediction_round_trip(source: Any, with_velocities: bool) -> None:
    types_, transport = source
    n, m = 4, 3
    sample = ShapePrediction(
        T0, 'base_link', ('a', 'b', 'c'),
        np.array([0, 10_000_000, 2 * NS_PER_S, 3 * NS_PER_S + 5]),
        rng_vec(n * m).reshape(n, m),
        rng_vec(n * m, 1).reshape(n, m) if with_velocities else None)
    msg = transport(shape_prediction_to_ros(sample, types_))
    assert time_from_ros(msg.header.stamp) == T0
    assert [duration_from_ros(p.time_from_start) for p in msg.points] == [
        0, 10_000_000, 2 * NS_PER_S, 3 * NS_PER_S + 5]
    back = shape_prediction_from_ros(msg)
    assert back.joint_names == sample.joint_names
    np.testing.assert_array_equal(back.times_from_start_ns, sample.times_from_start_ns)
    np.testing.assert_array_equal(back.positions, sample.positions)
    if with_velocities:
        np.testing.assert_array_equal(back.velocities, sample.velocities)
    else:
        assert back.velocities is None


def test_pose_path_round_trip(source: Any) -> None:
    types_, transport = source
    n = 5
    quats = np.array([unit_quat(i) for i in range(n)])
    sample = PosePath(T0, 'odom', T0 + np.arange(n) * 1000, rng_vec(3 * n).reshape(n, 3), quats)
    msg = transport(pose_path_to_ros(sample, types_))
    assert len(msg.poses) == n and msg.poses[0].header.frame_id == 'odom'
    back = pose_path_from_ros(msg)
    np.testing.assert_array_equal(back.stamps_ns, sample.stamps_ns)
    np.testing.assert_array_equal(back.positions, sample.positions)
    np.testing.assert_array_equal(back.orientations_xyzw, sample.orientations_xyzw)
    empty = PosePath(T0, 'odom', np.zeros(0, dtype=np.int64), np.zeros((0, 3)), np.zeros((0, 4)))
    assert pose_path_from_ros(transport(pose_path_to_ros(empty, types_))).positions.shape == (0, 3)


def test_diagnostics_round_trip(source: Any) -> None:
    types_, transport = source
    sample = Diagnostics(T0, [
        DiagnosticStatusSample(DIAG_OK, 'estimator', 'fine', 'hw0', {'rate': '100'}),
        DiagnosticStatusSample(DIAG_WARN, 'drift', 'large', '', [('a', '1'), ('b', '2')]),
        DiagnosticStatusSample(DIAG_ERROR, 'x'),
        DiagnosticStatusSample(DIAG_STALE, 'y'),
    ])
    msg = transport(diagnostics_to_ros(sample, types_))
    back = diagnostics_from_ros(msg)
    assert back.stamp_ns == T0
    assert [s.level for s in back.statuses] == [0, 1, 2, 3]
    assert back.statuses[0].values_dict() == {'rate': '100'}
    assert back.statuses[1].values == (('a', '1'), ('b', '2'))
    assert (back.statuses[0].name, back.statuses[0].message, back.statuses[0].hardware_id) == (
        'estimator', 'fine', 'hw0')


def test_diagnostic_level_encoding_per_source(fake_rclpy: FakeRclpyMessages) -> None:
    sample = Diagnostics(0, [DiagnosticStatusSample(DIAG_ERROR, 'n')])
    assert diagnostics_to_ros(sample, RosbagsTypes()).status[0].level == 2
    rclpy_types = RclpyTypes(importer=fake_rclpy.import_module)
    msg = diagnostics_to_ros(sample, rclpy_types)
    assert msg.status[0].level == b'\x02'
    assert type(msg.status[0]).ERROR == b'\x02'  # constants are bytes like in rclpy


def test_byte_to_int_accepts_both() -> None:
    assert byte_to_int(3) == 3
    assert byte_to_int(b'\x01') == 1
    assert byte_to_int(bytearray(b'\x02')) == 2
    with pytest.raises(ValueError):
        byte_to_int(b'\x01\x02')


def test_string_and_clock_round_trip(source: Any) -> None:
    types_, transport = source
    urdf = '<robot name="r"><link name="base"/></robot>'
    assert string_from_ros(transport(string_to_ros(urdf, types_))) == urdf
    assert clock_from_ros(transport(clock_to_ros(T0, types_))) == T0


# ============================================================================================
# time conversions
# ============================================================================================


def test_time_conversions(source: Any) -> None:
    types_, transport = source
    for ns in (0, 1, NS_PER_S - 1, NS_PER_S, T0, (2**31 - 1) * NS_PER_S + NS_PER_S - 1):
        msg = transport(time_to_ros(ns, types_))
        assert 0 <= msg.nanosec < NS_PER_S
        assert time_from_ros(msg) == ns
    assert time_to_ros(np.int64(5), types_).nanosec == 5
    for ns in (-1, 2**31 * NS_PER_S):
        with pytest.raises(ValueError):
            time_to_ros(ns, types_)
    for bad in (1.5, True, '3'):
        with pytest.raises(TypeError):
            time_to_ros(bad, types_)


def test_time_from_ros_rejects_negative_and_accepts_unnormalized() -> None:
    time_cls = JAZZY.types['builtin_interfaces/msg/Time']
    with pytest.raises(ValueError, match='negative'):
        time_from_ros(time_cls(sec=-1, nanosec=0))
    assert time_from_ros(time_cls(sec=1, nanosec=NS_PER_S)) == 2 * NS_PER_S


def test_duration_conversions(source: Any) -> None:
    types_, transport = source
    for ns in (0, 5, -1, -NS_PER_S, -NS_PER_S - 1, 3 * NS_PER_S + 7):
        msg = transport(duration_to_ros(ns, types_))
        assert 0 <= msg.nanosec < NS_PER_S
        assert duration_from_ros(msg) == ns
    neg = duration_to_ros(-1, types_)
    assert (neg.sec, neg.nanosec) == (-1, NS_PER_S - 1)
    with pytest.raises(ValueError):
        duration_to_ros(2**31 * NS_PER_S, types_)


# ============================================================================================
# sample validation
# ============================================================================================


def test_sample_validation() -> None:
    with pytest.raises(ValueError, match='position'):
        JointStateSample(0, '', ('a', 'b'), [1.0])
    with pytest.raises(ValueError, match='velocity'):
        JointStateSample(0, '', ('a',), [1.0], [1.0, 2.0])
    with pytest.raises(ValueError, match='>= 0'):
        JointStateSample(-1, '', (), [])
    with pytest.raises(TypeError):
        WrenchSample(1.0, '', np.zeros(3), np.zeros(3))
    with pytest.raises(ValueError, match='both'):
        BaseStateSample(0, 'w', 'b', np.zeros(3), [0, 0, 0, 1], twist_linear=np.zeros(3))
    with pytest.raises(ValueError, match='orientation'):
        BaseStateSample(0, 'w', 'b', np.zeros(3), [0, 0, 1])
    with pytest.raises(ValueError, match='strictly increasing'):
        ShapePrediction(0, '', ('a',), [0, 0], np.zeros((2, 1)))
    with pytest.raises(ValueError, match='integer'):
        ShapePrediction(0, '', ('a',), [0.0, 0.5], np.zeros((2, 1)))
    with pytest.raises(ValueError, match='positions'):
        ShapePrediction(0, '', ('a',), [0, 1], np.zeros((2, 2)))
    with pytest.raises(ValueError, match='level'):
        DiagnosticStatusSample(4, 'x')
    with pytest.raises(TypeError):
        Diagnostics(0, ['not a status'])
    sample = JointStateSample(np.int64(3), 'f', ['a'], [1])
    assert isinstance(sample.stamp_ns, int) and sample.position.dtype == np.float64
    with pytest.raises(AttributeError):
        sample.stamp_ns = 4  # frozen


# ============================================================================================
# message type sources
# ============================================================================================


def test_rclpy_types_import_lazily_and_cache(fake_rclpy: FakeRclpyMessages) -> None:
    rclpy_types = RclpyTypes(importer=fake_rclpy.import_module)
    assert fake_rclpy.imports == []
    cls = rclpy_types.get('sensor_msgs/msg/JointState')
    assert rclpy_types.get('sensor_msgs/msg/JointState') is cls
    assert fake_rclpy.imports == ['sensor_msgs.msg']
    with pytest.raises(LookupError):
        rclpy_types.get('no_such_pkg/msg/Thing')
    with pytest.raises(LookupError):
        rclpy_types.get('sensor_msgs/msg/NoSuchType')
    with pytest.raises(ValueError):
        rclpy_types.get('sensor_msgs/JointState')


def test_rosbags_types_lookup_and_byte() -> None:
    rosbags_types = RosbagsTypes()
    cls = rosbags_types.get('std_msgs/msg/String')
    assert cls.__msgtype__ == 'std_msgs/msg/String'
    assert rosbags_types.get('std_msgs/msg/String') is cls  # cached
    for _ in range(2):  # a failed lookup is not cached
        with pytest.raises(LookupError):
            rosbags_types.get('my_pkg/msg/Custom')
        with pytest.raises(ValueError):
            rosbags_types.get('std_msgs/String')
    with pytest.raises(ValueError):
        rosbags_types.byte(256)
    assert RclpyTypes().byte(7) == b'\x07'


def test_fake_double_is_strict(fake_rclpy: FakeRclpyMessages) -> None:
    """The TEST DOUBLE must reject what rclpy rejects, or the tests above prove nothing."""
    js = fake_rclpy.get('sensor_msgs/msg/JointState')
    with pytest.raises(AssertionError):
        js(position=np.zeros(2))
    with pytest.raises(AssertionError):
        fake_rclpy.get('builtin_interfaces/msg/Time')(sec=np.int64(1))
    with pytest.raises(AssertionError):
        fake_rclpy.get('geometry_msgs/msg/Vector3')(x=1)
    with pytest.raises(AssertionError):
        fake_rclpy.get('diagnostic_msgs/msg/DiagnosticStatus')(level=1)
    with pytest.raises(AssertionError):
        js(bogus=1)


def test_cdr_encoders_give_what_real_rclpy_reads_as_the_converted_message() -> None:
    """The node publishes cdr.ENCODERS bytes: rclpy must read them as the converters' messages."""
    from rclpy.serialization import deserialize_message
    from reduced_dynamics.messages import cdr
    rclpy_types = RclpyTypes()
    samples = [
        (JointStateSample(T0, 'b', ('a', 'bc'), [1.0, 2.0], [2.0, 3.0], [3.0, 4.0]),
         joint_state_to_ros, 'sensor_msgs/msg/JointState'),
        (Diagnostics(T0, [DiagnosticStatusSample(1, 'n', values={'k': 'v'})]),
         diagnostics_to_ros, 'diagnostic_msgs/msg/DiagnosticArray'),
        (ShapePrediction(T0, 'b', ('a',), [0, 1], np.ones((2, 1)), np.ones((2, 1))),
         shape_prediction_to_ros, 'trajectory_msgs/msg/JointTrajectory'),
        (PosePath(T0, 'o', [T0], np.ones((1, 3)), [unit_quat()]), pose_path_to_ros,
         'nav_msgs/msg/Path'),
    ]
    for sample, to_ros, msgtype in samples:
        expected = to_ros(sample, rclpy_types)
        assert deserialize_message(cdr.ENCODERS[msgtype](sample), type(expected)) == expected


def test_no_rclpy_import_in_sources() -> None:
    root = Path(__file__).resolve().parent.parent / 'reduced_dynamics'
    pattern = re.compile(r'^\s*(import|from)\s+rclpy\b', re.MULTILINE)
    for sub in ('messages', 'bag'):
        for path in (root / sub).glob('*.py'):
            assert not pattern.search(path.read_text()), f'{path} imports rclpy'
