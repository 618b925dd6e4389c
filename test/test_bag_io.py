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
Tests for reduced_dynamics.bag: writing, reading, independent verification, errors.

All bags are generated inside ``tmp_path``; nothing is read from the network.
"""

import gc
from pathlib import Path
import tracemalloc
from typing import Any, Callable
import weakref

from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer as McapWriter
import numpy as np
import pytest
from rosbags.rosbag2 import Reader as RosbagsReader
from rosbags.typesys import get_types_from_msg, get_typestore, Stores
import yaml

from reduced_dynamics.bag import BagError, BagWriter, open_bag, QOS_LATCHED
from reduced_dynamics.bag.playback import definition_problems
from reduced_dynamics.messages import (
    base_state_to_odometry,
    base_state_to_pose_stamped,
    BaseStateSample,
    clock_from_ros,
    clock_to_ros,
    Diagnostics,
    diagnostics_from_ros,
    diagnostics_to_ros,
    DiagnosticStatusSample,
    joint_state_from_ros,
    joint_state_to_ros,
    JointStateSample,
    NS_PER_S,
    odometry_from_ros,
    pose_path_from_ros,
    pose_path_to_ros,
    pose_stamped_from_ros,
    PosePath,
    RosbagsTypes,
    shape_prediction_from_ros,
    shape_prediction_to_ros,
    ShapePrediction,
    string_from_ros,
    string_to_ros,
    twist_from_ros,
    twist_to_ros,
    TwistSample,
    wrench_from_ros,
    wrench_to_ros,
    WrenchSample,
)
from reduced_dynamics.messages.typestore import jazzy_typestore

T0 = 1_700_000_000 * NS_PER_S
DT = 10_000_000  # 100 Hz
N = 20
JOINTS = ('hip', 'knee', 'ankle')
CUSTOM_MSG = 'my_pkg/msg/Custom'
CUSTOM_DEF = 'string label\nfloat64[] values\nint32 count\n'

# topic -> (msgtype, sample factory(i), to_ros, from_ros, compare)
TOPICS: dict[str, str] = {
    '/joint_states': 'sensor_msgs/msg/JointState',
    '/odom': 'nav_msgs/msg/Odometry',
    '/base_pose': 'geometry_msgs/msg/PoseStamped',
    '/ground_truth/momentum': 'geometry_msgs/msg/WrenchStamped',
    '/reduced_dynamics/momentum': 'geometry_msgs/msg/WrenchStamped',
    '/reduced_dynamics/body_momentum': 'geometry_msgs/msg/WrenchStamped',
    '/reduced_dynamics/drift/momentum_rate': 'geometry_msgs/msg/WrenchStamped',
    '/reduced_dynamics/drift/base_twist': 'geometry_msgs/msg/TwistStamped',
    '/reduced_dynamics/shape_state': 'sensor_msgs/msg/JointState',
    '/reduced_dynamics/shape_prediction': 'trajectory_msgs/msg/JointTrajectory',
    '/reduced_dynamics/drift/path': 'nav_msgs/msg/Path',
    '/diagnostics': 'diagnostic_msgs/msg/DiagnosticArray',
    '/robot_description': 'std_msgs/msg/String',
    '/clock': 'rosgraph_msgs/msg/Clock',
}
URDF = '<robot name="toy"><link name="base_link"/></robot>'


def _vec(i: int, n: int, scale: float = 1.0) -> np.ndarray:
    return scale * (np.arange(n, dtype=float) + 0.25 * i)


def _quat(i: int) -> np.ndarray:
    q = np.array([0.1 * i, -0.2, 0.3, 1.0])
    return q / np.linalg.norm(q)


def make_sample(topic: str, i: int) -> Any:
    """Return the sample (or plain value) written on ``topic`` at index ``i``."""
    stamp = T0 + i * DT
    if topic in ('/joint_states', '/reduced_dynamics/shape_state'):
        return JointStateSample(stamp, '', JOINTS, _vec(i, 3), _vec(i, 3, 2.0),
                                _vec(i, 3, -1.0) if i % 2 else np.zeros(0))
    if topic == '/odom':
        return BaseStateSample(stamp, 'world', 'base_link', _vec(i, 3), _quat(i), _vec(i, 3),
                               _vec(i, 3, 0.5))
    if topic == '/base_pose':
        return BaseStateSample(stamp, 'world', 'base_link', _vec(i, 3), _quat(i))
    if 'momentum' in topic:
        return WrenchSample(stamp, 'world', _vec(i, 3), _vec(i, 3, 3.0))
    if topic.endswith('base_twist'):
        return TwistSample(stamp, 'base_link', _vec(i, 3), _vec(i, 3, -2.0))
    if topic.endswith('shape_prediction'):
        return ShapePrediction(stamp, 'base_link', JOINTS, np.arange(4) * DT,
                               np.outer(np.arange(4), _vec(i, 3)), np.ones((4, 3)) * i)
    if topic.endswith('path'):
        return PosePath(stamp, 'world', stamp + np.arange(3) * DT,
                        np.stack([_vec(i + k, 3) for k in range(3)]),
                        np.stack([_quat(i + k) for k in range(3)]))
    if topic == '/diagnostics':
        return Diagnostics(stamp, [
            DiagnosticStatusSample(i % 4, 'reduced_dynamics: estimator', f'msg {i}', 'hw',
                                   {'index': str(i)})])
    if topic == '/robot_description':
        return URDF
    if topic == '/clock':
        return stamp
    raise AssertionError(topic)


def to_ros(topic: str, value: Any, types_: RosbagsTypes) -> Any:
    """Convert a sample to its ROS message."""
    converters: dict[str, Callable[[Any, Any], Any]] = {
        'sensor_msgs/msg/JointState': joint_state_to_ros,
        'nav_msgs/msg/Odometry': base_state_to_odometry,
        'geometry_msgs/msg/PoseStamped': base_state_to_pose_stamped,
        'geometry_msgs/msg/WrenchStamped': wrench_to_ros,
        'geometry_msgs/msg/TwistStamped': twist_to_ros,
        'trajectory_msgs/msg/JointTrajectory': shape_prediction_to_ros,
        'nav_msgs/msg/Path': pose_path_to_ros,
        'diagnostic_msgs/msg/DiagnosticArray': diagnostics_to_ros,
        'std_msgs/msg/String': string_to_ros,
        'rosgraph_msgs/msg/Clock': clock_to_ros,
    }
    return converters[TOPICS[topic]](value, types_)


def from_ros(topic: str, msg: Any) -> Any:
    """Convert a ROS message back to its sample."""
    converters: dict[str, Callable[[Any], Any]] = {
        'sensor_msgs/msg/JointState': joint_state_from_ros,
        'nav_msgs/msg/Odometry': odometry_from_ros,
        'geometry_msgs/msg/PoseStamped': lambda m: pose_stamped_from_ros(m, 'base_link'),
        'geometry_msgs/msg/WrenchStamped': wrench_from_ros,
        'geometry_msgs/msg/TwistStamped': twist_from_ros,
        'trajectory_msgs/msg/JointTrajectory': shape_prediction_from_ros,
        'nav_msgs/msg/Path': pose_path_from_ros,
        'diagnostic_msgs/msg/DiagnosticArray': diagnostics_from_ros,
        'std_msgs/msg/String': string_from_ros,
        'rosgraph_msgs/msg/Clock': clock_from_ros,
    }
    return converters[TOPICS[topic]](msg)


def assert_same(a: Any, b: Any) -> None:
    """Compare samples field by field (numpy aware, recursing into tuples)."""
    if isinstance(a, (str, int)):
        assert a == b
        return
    assert type(a) is type(b)
    for key in a.__dataclass_fields__:
        x, y = getattr(a, key), getattr(b, key)
        if isinstance(x, np.ndarray) or isinstance(y, np.ndarray):
            np.testing.assert_array_equal(x, y, err_msg=key)
        elif isinstance(x, tuple) and x and hasattr(x[0], '__dataclass_fields__'):
            assert len(x) == len(y)
            for u, v in zip(x, y):
                assert_same(u, v)
        else:
            assert x == y, key


def write_full_bag(path: Path, *, storage: str = 'mcap', version: int = 9,
                   typestore: Any = None, extra: dict[str, str] | None = None,
                   extra_factory: Callable[[int], Any] | None = None) -> None:
    """Write N messages on every topic (robot_description once), interleaved in time."""
    types_ = RosbagsTypes(typestore)
    topics = dict(TOPICS, **(extra or {}))
    with BagWriter(path, topics, typestore=types_.typestore, storage=storage,
                   version=version) as bag:
        bag.write('/robot_description', T0 - 1, to_ros('/robot_description', URDF, types_))
        for i in range(N):
            for topic in TOPICS:
                if topic != '/robot_description':
                    bag.write(topic, T0 + i * DT, to_ros(topic, make_sample(topic, i), types_))
            for topic in extra or {}:
                bag.write(topic, T0 + i * DT + 1, extra_factory(i))


def custom_typestore() -> Any:
    """Jazzy typestore plus the custom type (only the writer knows it)."""
    store = get_typestore(Stores.ROS2_JAZZY)
    store.register(get_types_from_msg(CUSTOM_DEF, CUSTOM_MSG))
    return store


@pytest.fixture(scope='module')
def full_bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Bag with every supported topic, written once for the module."""
    path = tmp_path_factory.mktemp('full') / 'run'
    write_full_bag(path)
    return path


# ============================================================================================
# round trips
# ============================================================================================


def check_round_trip(path: Path) -> None:
    """Read ``path`` back and compare to the generating samples."""
    with open_bag(path) as bag:
        assert bag.topics() == TOPICS
        assert bag.message_count('/robot_description') == 1
        assert bag.message_count('/joint_states') == N
        assert bag.message_count() == N * (len(TOPICS) - 1) + 1
        assert bag.start_ns == T0 - 1
        assert bag.end_ns == T0 + (N - 1) * DT
        assert bag.duration_ns == (N - 1) * DT + 1
        assert bag.duration == pytest.approx(bag.duration_ns * 1e-9)
        seen: dict[str, int] = {t: 0 for t in TOPICS}
        last = -1
        for topic, msgtype, stamp, msg in bag.messages(list(TOPICS)):
            assert msgtype == TOPICS[topic] and stamp >= last
            last = stamp
            i = seen[topic]
            expected = make_sample(topic, i)
            assert_same(from_ros(topic, msg), expected)
            seen[topic] += 1
        assert seen == {t: 1 if t == '/robot_description' else N for t in TOPICS}
        assert bag.skipped == {}


def test_round_trip_all_types_mcap(full_bag: Path) -> None:
    check_round_trip(full_bag)


def test_round_trip_bare_mcap_file(full_bag: Path) -> None:
    mcap_file = full_bag / 'run.mcap'
    check_round_trip(mcap_file)


def test_round_trip_sqlite3(tmp_path: Path) -> None:
    path = tmp_path / 'sql'
    write_full_bag(path, storage='sqlite3')
    assert (path / 'sql.db3').is_file()
    check_round_trip(path)
    check_round_trip(path / 'sql.db3')  # bare .db3 without metadata.yaml


def test_round_trip_metadata_version_8(tmp_path: Path) -> None:
    path = tmp_path / 'v8'
    write_full_bag(path, version=8)
    assert yaml.safe_load((path / 'metadata.yaml').read_text())[
        'rosbag2_bagfile_information']['version'] == 8
    check_round_trip(path)


@pytest.mark.parametrize('version', [5, 6, 7])
def test_reads_older_metadata_versions(full_bag: Path, tmp_path: Path, version: int) -> None:
    """Rewrite metadata.yaml as Humble/Iron-era rosbag2 would have written it."""
    path = tmp_path / f'v{version}'
    path.mkdir()
    (path / 'v.mcap').write_bytes((full_bag / 'run.mcap').read_bytes())
    meta = yaml.safe_load((full_bag / 'metadata.yaml').read_text())
    info = meta['rosbag2_bagfile_information']
    info['version'] = version
    info['relative_file_paths'] = ['v.mcap']
    info['files'][0]['path'] = 'v.mcap'
    del info['ros_distro']
    if version < 6:
        del info['custom_data']
    for entry in info['topics_with_message_count']:
        entry['topic_metadata']['offered_qos_profiles'] = ''  # pre-v9: YAML in a string
        if version < 7:
            del entry['topic_metadata']['type_description_hash']
    (path / 'metadata.yaml').write_text(yaml.safe_dump(meta))
    check_round_trip(path)


def test_rosbags_yaml_runs_on_libyaml_and_reads_what_either_yaml_writes(
        full_bag: Path, tmp_path: Path, monkeypatch) -> None:
    """
    Bag metadata.yaml and QoS profiles go through libyaml (C) in rosbags.

    ruamel.yaml >= 0.19 no longer requires its C extension (setup.py does): without it every
    bag's open and close ran pure-Python YAML, 60 % of a 60-sample replay's CPU. The two
    emitters wrap long scalars differently; both files must read back the same.
    """
    import ruamel.yaml.main as ruamel_main
    assert ruamel_main.CParser is not None and ruamel_main.CEmitter is not None
    with_c = yaml.safe_load((full_bag / 'metadata.yaml').read_text())
    monkeypatch.setattr(ruamel_main, 'CParser', None)
    monkeypatch.setattr(ruamel_main, 'CEmitter', None)
    path = tmp_path / 'run'
    write_full_bag(path)
    pure = yaml.safe_load((path / 'metadata.yaml').read_text())
    assert with_c == pure
    check_round_trip(path)  # the pure-Python reader on the pure-Python bag
    monkeypatch.undo()
    check_round_trip(path)  # libyaml's on it


def test_time_order_when_written_out_of_order(tmp_path: Path) -> None:
    types_ = RosbagsTypes()
    stamps = [T0 + k for k in (5, 1, 9, 3, 7, 0)]
    with BagWriter(tmp_path / 'ooo', {'/clock': 'rosgraph_msgs/msg/Clock'}) as bag:
        for stamp in stamps:
            bag.write('/clock', stamp, clock_to_ros(stamp, types_))
    with open_bag(tmp_path / 'ooo') as bag:
        got = [(m.timestamp_ns, clock_from_ros(m.msg)) for m in bag.messages(['/clock'])]
    assert got == [(s, s) for s in sorted(stamps)]


def test_fast_mcap_path_writes_the_same_bytes_as_rosbags(tmp_path: Path, monkeypatch) -> None:
    # BagWriter appends MCAP records itself (rosbags internals); the files must not differ
    # from rosbags' own path: out of order stamps, several chunks, every topic.
    import reduced_dynamics.bag.writer as writer_module
    rng = np.random.default_rng(5)
    topics = {f'/t{i}': 'std_msgs/msg/String' for i in range(4)}
    items = [(f'/t{int(rng.integers(0, 4))}', T0 + int(rng.integers(0, 10**9)),
              b'\x00\x01\x00\x00' + rng.bytes(int(rng.integers(0, 3000))))
             for _ in range(1500)]

    def write(path: Path) -> BagWriter:
        with BagWriter(path, topics) as bag:
            for topic, stamp, data in items:
                bag.write_raw(topic, stamp, data)
        return bag

    fast = write(tmp_path / 'fast' / 'bag')
    assert fast.message_counts == {t: sum(i[0] == t for i in items) for t in topics}
    monkeypatch.setattr(writer_module._McapAppender, 'attach', classmethod(lambda c, w: None))
    write(tmp_path / 'slow' / 'bag')
    for name in ('bag.mcap', 'metadata.yaml'):
        assert (tmp_path / 'fast' / 'bag' / name).read_bytes() == \
            (tmp_path / 'slow' / 'bag' / name).read_bytes(), name
    assert (tmp_path / 'fast' / 'bag' / 'bag.mcap').stat().st_size > 2 * 2**20  # chunks


def test_fast_mcap_path_only_for_the_layout_it_knows(tmp_path: Path) -> None:
    from types import SimpleNamespace
    import reduced_dynamics.bag.writer as writer_module
    with BagWriter(tmp_path / 'mcap', {'/a': 'std_msgs/msg/String'}) as bag:
        assert bag._appender is not None
        rosbags_writer = bag._writer
        assert writer_module._McapAppender.attach(rosbags_writer) is not None
        other = SimpleNamespace(**vars(rosbags_writer))  # e.g. another rosbags version
        other.storage = SimpleNamespace(chunk=rosbags_writer.storage.chunk)
        assert writer_module._McapAppender.attach(other) is None
    with BagWriter(tmp_path / 'db', {'/a': 'std_msgs/msg/String'}, storage='sqlite3') as bag:
        assert bag._appender is None
        bag.write('/a', T0, string_to_ros('x', RosbagsTypes()))
    with open_bag(tmp_path / 'db') as bag:
        assert [string_from_ros(m.msg) for m in bag.messages(['/a'])] == ['x']


# ============================================================================================
# independent verification of the written files
# ============================================================================================


def test_written_mcap_validates_with_mcap_package(full_bag: Path) -> None:
    with open(full_bag / 'run.mcap', 'rb') as stream:
        reader = make_reader(stream, validate_crcs=True)
        assert reader.get_header().profile == 'ros2'
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        assert summary.statistics.message_count == N * (len(TOPICS) - 1) + 1
        assert {c.topic for c in summary.channels.values()} == set(TOPICS)
        for schema in summary.schemas.values():
            assert schema.encoding == 'ros2msg' and schema.data
        decoded = 0
        stores: dict[int, Any] = {}
        for schema, channel, message in reader.iter_messages(log_time_order=True):
            assert channel.message_encoding == 'cdr'
            if schema.id not in stores:  # self-describing: decode with the embedded text only
                store = get_typestore(Stores.EMPTY)
                store.register(get_types_from_msg(schema.data.decode(), schema.name))
                stores[schema.id] = store
            msg = stores[schema.id].deserialize_cdr(message.data, schema.name)
            if channel.topic == '/joint_states':
                assert tuple(msg.name) == JOINTS
            decoded += 1
        assert decoded == summary.statistics.message_count


def test_written_bag_reads_with_rosbags(full_bag: Path) -> None:
    store = get_typestore(Stores.ROS2_JAZZY)
    with RosbagsReader(full_bag) as reader:
        assert reader.message_count == N * (len(TOPICS) - 1) + 1
        conns = {c.topic: c for c in reader.connections}
        assert conns['/odom'].msgtype == 'nav_msgs/msg/Odometry'
        assert conns['/odom'].digest == store.hash_rihs01('nav_msgs/msg/Odometry')
        assert conns['/robot_description'].ext.offered_qos_profiles == [QOS_LATCHED]
        msgs = [store.deserialize_cdr(raw, c.msgtype)
                for c, _, raw in reader.messages([conns['/odom']])]
    assert len(msgs) == N
    assert msgs[3].child_frame_id == 'base_link'
    meta = yaml.safe_load((full_bag / 'metadata.yaml').read_text())
    info = meta['rosbag2_bagfile_information']
    assert info['version'] == 9 and info['storage_identifier'] == 'mcap'


def test_reads_mcap_written_by_mcap_package(tmp_path: Path) -> None:
    """A bare MCAP from another producer (lz4 chunks, CRCs) with an embedded custom type."""
    store = custom_typestore()
    js_def, _ = store.generate_msgdef('sensor_msgs/msg/JointState', ros_version=2)
    path = tmp_path / 'other.mcap'
    custom = store.types[CUSTOM_MSG]
    with open(path, 'wb') as stream:
        writer = McapWriter(stream, compression=CompressionType.LZ4, chunk_size=4096)
        writer.start(profile='ros2', library='test')
        js_schema = writer.register_schema('sensor_msgs/msg/JointState', 'ros2msg',
                                           js_def.encode())
        custom_schema = writer.register_schema(CUSTOM_MSG, 'ros2msg', CUSTOM_DEF.encode())
        js_chan = writer.register_channel('/joint_states', 'cdr', js_schema)
        custom_chan = writer.register_channel('/custom', 'cdr', custom_schema)
        types_ = RosbagsTypes(store)
        for i in range(50):
            stamp = T0 + i * DT
            data = store.serialize_cdr(
                joint_state_to_ros(make_sample('/joint_states', i), types_),
                'sensor_msgs/msg/JointState')
            writer.add_message(js_chan, stamp, bytes(data), stamp)
            cdata = store.serialize_cdr(custom(label=f'c{i}', values=np.ones(i % 3), count=i),
                                        CUSTOM_MSG)
            writer.add_message(custom_chan, stamp + 1, bytes(cdata), stamp + 1)
        writer.finish()
    with open_bag(path) as bag:
        assert bag.topics() == {'/joint_states': 'sensor_msgs/msg/JointState',
                                '/custom': CUSTOM_MSG}
        states = [joint_state_from_ros(m.msg) for m in bag.messages(['/joint_states'])]
        assert len(states) == 50
        assert_same(states[7], make_sample('/joint_states', 7))
        customs = [m.msg for m in bag.messages(['/custom'])]  # registered from the schema
        assert [c.count for c in customs] == list(range(50)) and customs[4].label == 'c4'


# ============================================================================================
# custom types, missing topics, skipping
# ============================================================================================


def test_custom_topic_ignored_with_fresh_typestore(tmp_path: Path) -> None:
    store = custom_typestore()
    custom = store.types[CUSTOM_MSG]
    path = tmp_path / 'custom'
    write_full_bag(path, typestore=store, extra={'/custom': CUSTOM_MSG},
                   extra_factory=lambda i: custom(label='x', values=np.arange(i * 1.0), count=i))
    with open_bag(path) as bag:  # fresh Jazzy typestore: my_pkg/msg/Custom unknown
        assert CUSTOM_MSG not in bag.typestore.fielddefs
        assert bag.topics()['/custom'] == CUSTOM_MSG
        assert bag.message_count('/custom') == N
        assert sum(1 for _ in bag.messages(['/joint_states', '/odom'])) == 2 * N
        assert bag.skipped == {}
        # The bag is self-describing, so the custom topic is readable on request too.
        values = [m.msg.values for m in bag.messages(['/custom'])]
        assert len(values) == N and list(values[3]) == [0.0, 1.0, 2.0]


def test_readers_share_one_jazzy_store_and_a_custom_type_stays_in_its_reader(
        full_bag: Path, tmp_path: Path) -> None:
    """Readers, writers and RosbagsTypes share one store; a bag's own type never enters it."""
    shared = jazzy_typestore()
    assert RosbagsTypes().typestore is shared
    with open_bag(full_bag) as first, open_bag(full_bag) as second:
        assert first.typestore is second.typestore is shared
        assert sum(1 for _ in first.messages(['/joint_states'])) == N
        generated = shared.cache['sensor_msgs/msg/JointState']
        assert sum(1 for _ in second.messages(['/joint_states'])) == N
        # The second reader decoded with the first one's generated functions.
        assert shared.cache['sensor_msgs/msg/JointState'] is generated
    store = custom_typestore()
    custom = store.types[CUSTOM_MSG]
    path = tmp_path / 'custom'
    write_full_bag(path, typestore=store, extra={'/custom': CUSTOM_MSG},
                   extra_factory=lambda i: custom(label='x', values=np.arange(i * 1.0), count=i))
    with open_bag(path) as bag:
        odom = bag.typestore_for('/odom', 'nav_msgs/msg/Odometry')
        assert odom is shared  # resolved before the bag's own type is needed
        values = [m.msg.values for m in bag.messages(['/custom', '/odom'])
                  if m.topic == '/custom']
        assert len(values) == N and list(values[2]) == [0.0, 1.0]
        # Registering made the reader's store its own, and the topics resolved before
        # follow it: a Jazzy-defined topic is still "the reader's typestore".
        assert bag.typestore is not shared and CUSTOM_MSG in bag.typestore.fielddefs
        assert bag.typestore_for('/odom', 'nav_msgs/msg/Odometry') is bag.typestore
        assert definition_problems(bag, {'/odom': 'nav_msgs/msg/Odometry',
                                         '/custom': CUSTOM_MSG}) == {}
    assert CUSTOM_MSG not in shared.fielddefs and CUSTOM_MSG not in shared.types
    with BagWriter(tmp_path / 'plain', {'/odom': 'nav_msgs/msg/Odometry'}) as writer:
        assert writer.typestore is shared
    # The connection records what rosbags makes from a fresh store (cached per process).
    fresh = get_typestore(Stores.ROS2_JAZZY)
    with RosbagsReader(tmp_path / 'plain') as plain:
        (conn,) = plain.connections
    assert conn.msgdef.data == fresh.generate_msgdef('nav_msgs/msg/Odometry', ros_version=2)[0]
    assert conn.digest == fresh.hash_rihs01('nav_msgs/msg/Odometry')


def test_same_name_different_definition_uses_embedded_definition(tmp_path: Path) -> None:
    """A type whose bag definition differs from Jazzy's (hash mismatch) decodes via the bag."""
    store = get_typestore(Stores.EMPTY)
    store.register(get_types_from_msg('float32 x\nfloat32 y\n', 'geometry_msgs/msg/Vector3'))
    vec = store.types['geometry_msgs/msg/Vector3']
    path = tmp_path / 'other_distro'
    with BagWriter(path, {'/v': 'geometry_msgs/msg/Vector3'}, typestore=store) as bag:
        for i in range(3):
            bag.write('/v', T0 + i, vec(x=float(i), y=0.5))
    with open_bag(path) as reader:
        msgs = [m.msg for m in reader.messages(['/v'])]
        assert reader.skipped == {}
    assert [(m.x, m.y) for m in msgs] == [(0.0, 0.5), (1.0, 0.5), (2.0, 0.5)]
    assert not hasattr(msgs[0], 'z')


def test_topic_with_no_definition(tmp_path: Path) -> None:
    """A custom type without embedded definition: ignorable, but BagError if requested."""
    path = tmp_path / 'nodef.mcap'
    store = custom_typestore()
    with open(path, 'wb') as stream:
        writer = McapWriter(stream, compression=CompressionType.NONE)
        writer.start(profile='ros2', library='test')
        clock_def, _ = store.generate_msgdef('rosgraph_msgs/msg/Clock', ros_version=2)
        clock_schema = writer.register_schema('rosgraph_msgs/msg/Clock', 'ros2msg',
                                              clock_def.encode())
        custom_schema = writer.register_schema(CUSTOM_MSG, '', b'')
        clock_chan = writer.register_channel('/clock', 'cdr', clock_schema)
        custom_chan = writer.register_channel('/custom', 'cdr', custom_schema)
        types_ = RosbagsTypes(store)
        for i in range(5):
            writer.add_message(clock_chan, T0 + i, bytes(store.serialize_cdr(
                clock_to_ros(T0 + i, types_), 'rosgraph_msgs/msg/Clock')), T0 + i)
            writer.add_message(custom_chan, T0 + i, b'\x00\x01\x00\x00garbage', T0 + i)
        writer.finish()
    with open_bag(path) as bag:
        assert [clock_from_ros(m.msg) for m in bag.messages(['/clock'])] == [
            T0 + i for i in range(5)]
        with pytest.raises(BagError, match='no definition'):
            bag.messages(['/custom'])
        assert len(list(bag.raw_messages(['/custom']))) == 5


def test_missing_topics(full_bag: Path) -> None:
    with open_bag(full_bag) as bag:
        with pytest.raises(BagError, match='/nope'):
            bag.messages(['/joint_states', '/nope'])
        got = list(bag.messages(['/joint_states', '/nope'], ignore_missing=True))
        assert len(got) == N
        assert list(bag.messages([])) == []
        assert len(list(bag.messages('/clock'))) == N  # a bare string is one topic
        with pytest.raises(BagError, match='not in bag'):
            bag.message_count('/nope')


def test_undeserializable_messages_are_skipped_and_counted(tmp_path: Path) -> None:
    types_ = RosbagsTypes()
    path = tmp_path / 'bad_msgs'
    with BagWriter(path, {'/joint_states': 'sensor_msgs/msg/JointState'}) as bag:
        for i in range(6):
            if i in (2, 4):
                bag.write_raw('/joint_states', T0 + i, b'\x00\x01\x00\x00\xff\xff\xff')
            else:
                bag.write('/joint_states', T0 + i,
                          joint_state_to_ros(make_sample('/joint_states', i), types_))
    with open_bag(path) as bag:
        stamps = [m.timestamp_ns for m in bag.messages(['/joint_states'])]
        assert stamps == [T0 + i for i in (0, 1, 3, 5)]
        assert list(bag.skipped.values()) == [2]
        (reason,) = bag.skipped
        assert '/joint_states' in reason and reason in bag.skip_details


# ============================================================================================
# time ranges and raw access
# ============================================================================================


def test_time_range_filtering(full_bag: Path) -> None:
    with open_bag(full_bag) as bag:
        start, end = T0 + 5 * DT, T0 + 9 * DT
        stamps = [m.timestamp_ns for m in bag.messages(['/joint_states'], start, end)]
        assert stamps == [T0 + i * DT for i in range(5, 9)]  # [start, end)
        assert [m.timestamp_ns for m in bag.messages(['/joint_states'], start_ns=T0 + 18 * DT)
                ] == [T0 + 18 * DT, T0 + 19 * DT]
        assert len(list(bag.messages(['/joint_states'], end_ns=T0 + DT))) == 1
        assert list(bag.messages(['/joint_states'], T0 + 100 * DT)) == []
        raw = list(bag.raw_messages(['/clock'], start, end))
        assert [r.timestamp_ns for r in raw] == stamps
        assert all(isinstance(r.data, (bytes, memoryview)) and r.msgtype ==
                   'rosgraph_msgs/msg/Clock' for r in raw)
        with pytest.raises(BagError, match='before'):
            list(bag.messages(['/clock'], end, start))


# ============================================================================================
# writer behaviour
# ============================================================================================


def test_writer_refuses_existing_path_and_overwrites_bags_only(tmp_path: Path) -> None:
    types_ = RosbagsTypes()
    topics = {'/clock': 'rosgraph_msgs/msg/Clock'}
    path = tmp_path / 'out'
    with BagWriter(path, topics) as bag:
        bag.write('/clock', 1, clock_to_ros(1, types_))
    with pytest.raises(BagError, match='exists'):
        BagWriter(path, topics)
    with BagWriter(path, topics, overwrite=True) as bag:
        bag.write('/clock', 2, clock_to_ros(2, types_))
        bag.write('/clock', 3, clock_to_ros(3, types_))
    with open_bag(path) as reader:
        assert reader.message_count() == 2
    precious = tmp_path / 'precious'
    precious.mkdir()
    (precious / 'notes.txt').write_text('keep me')
    with pytest.raises(BagError, match='refusing'):
        with BagWriter(precious, topics, overwrite=True):
            pass
    assert (precious / 'notes.txt').read_text() == 'keep me'


def test_writer_argument_errors(tmp_path: Path) -> None:
    types_ = RosbagsTypes()
    with pytest.raises(BagError, match='not in the typestore'):
        BagWriter(tmp_path / 'a', {'/x': CUSTOM_MSG})
    with pytest.raises(BagError, match='storage'):
        BagWriter(tmp_path / 'a', {'/clock': 'rosgraph_msgs/msg/Clock'}, storage='rosbag1')
    with pytest.raises(BagError, match='version'):
        BagWriter(tmp_path / 'a', {'/clock': 'rosgraph_msgs/msg/Clock'}, version=5)
    with BagWriter(tmp_path / 'b', {'/clock': 'rosgraph_msgs/msg/Clock'}) as bag:
        with pytest.raises(BagError, match='not declared'):
            bag.write('/other', 1, clock_to_ros(1, types_))
        with pytest.raises(BagError, match='expects'):
            bag.write('/clock', 1, string_to_ros('x', types_))
        with pytest.raises(BagError, match='integer'):
            bag.write('/clock', 1.5, clock_to_ros(1, types_))
        with pytest.raises(BagError, match='range'):
            bag.write('/clock', -1, clock_to_ros(1, types_))
        bag.write('/clock', np.int64(7), clock_to_ros(7, types_))
        assert bag.message_counts == {'/clock': 1}
    with pytest.raises(BagError, match='not open'):
        bag.write('/clock', 8, clock_to_ros(8, types_))


def test_writer_finalizes_bag_when_block_raises(tmp_path: Path) -> None:
    types_ = RosbagsTypes()
    path = tmp_path / 'crash'
    with pytest.raises(RuntimeError):
        with BagWriter(path, {'/clock': 'rosgraph_msgs/msg/Clock'}) as bag:
            bag.write('/clock', 1, clock_to_ros(1, types_))
            raise RuntimeError('simulator died')
    with open_bag(path) as reader:
        assert reader.message_count() == 1


# ============================================================================================
# corrupted / invalid inputs
# ============================================================================================


def _assert_bag_error(path: Path, match: str) -> BagError:
    with pytest.raises(BagError, match=match) as info:
        open_bag(path)
    text = str(info.value)
    assert '\n' not in text and len(text) < 600, text
    return info.value


def test_error_missing_path(tmp_path: Path) -> None:
    _assert_bag_error(tmp_path / 'nope', 'does not exist')


def test_error_empty_directory(tmp_path: Path) -> None:
    _assert_bag_error(tmp_path, 'empty')


def test_error_directory_without_metadata(full_bag: Path, tmp_path: Path) -> None:
    (tmp_path / 'x.mcap').write_bytes((full_bag / 'run.mcap').read_bytes())
    err = _assert_bag_error(tmp_path, 'metadata.yaml')
    assert 'x.mcap' in str(err)  # hints at opening the storage file directly


def test_error_truncated_mcap(full_bag: Path, tmp_path: Path) -> None:
    # Cut in the data: readable up to the damage (test_damaged_bags.py), refused when strict.
    data = (full_bag / 'run.mcap').read_bytes()
    for cut in (len(data) // 2, len(data) - 10):
        path = tmp_path / f'cut{cut}.mcap'
        path.write_bytes(data[:cut])
        with open_bag(path) as bag:
            assert bag.damage
        with pytest.raises(BagError, match='damaged bag'):
            open_bag(path, strict=True)
    for cut in (20, 9):  # cut in the header: nothing to read
        path = tmp_path / f'cut{cut}.mcap'
        path.write_bytes(data[:cut])
        _assert_bag_error(path, 'cannot open bag')


def test_error_truncated_mcap_inside_bag_directory(full_bag: Path, tmp_path: Path) -> None:
    path = tmp_path / 'bag'
    path.mkdir()
    (path / 'metadata.yaml').write_text((full_bag / 'metadata.yaml').read_text())
    (path / 'run.mcap').write_bytes((full_bag / 'run.mcap').read_bytes()[:5000])
    with open_bag(path) as bag:
        assert bag.damage and bag.damage[0].kind == 'truncated'
    with pytest.raises(BagError, match='damaged bag'):
        open_bag(path, strict=True)


def test_error_garbage_files(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    garbage = rng.integers(0, 256, 4096, dtype=np.uint8).tobytes()
    for name, match in (('g.mcap', 'magic'), ('g.db3', 'SQLite'), ('g.bag', 'not a bag'),
                        ('g.txt', 'not a bag')):
        (tmp_path / name).write_bytes(garbage)
        _assert_bag_error(tmp_path / name, match)
    (tmp_path / 'empty.mcap').write_bytes(b'')
    _assert_bag_error(tmp_path / 'empty.mcap', 'empty')
    (tmp_path / 'fake.mcap').write_bytes(b'\x89MCAP0\r\n' + garbage)
    _assert_bag_error(tmp_path / 'fake.mcap', 'cannot open bag')
    (tmp_path / 'fake.db3').write_bytes(b'SQLite format 3\x00' + garbage)
    _assert_bag_error(tmp_path / 'fake.db3', 'cannot open bag')


@pytest.mark.parametrize('text, match', [
    ('rosbag2_bagfile_information: {version: 9\n  : : [', 'YAML'),
    ('', 'metadata'),
    ('just a string', 'metadata'),
    ('rosbag2_bagfile_information: {version: 9}', 'missing'),
    ('other_key: 1', 'missing'),
])
def test_error_malformed_metadata(full_bag: Path, tmp_path: Path, text: str,
                                  match: str) -> None:
    path = tmp_path / 'bag'
    path.mkdir()
    (path / 'run.mcap').write_bytes((full_bag / 'run.mcap').read_bytes())
    (path / 'metadata.yaml').write_text(text)
    _assert_bag_error(path, match)


def test_error_unknown_storage_and_future_version(full_bag: Path, tmp_path: Path) -> None:
    meta = yaml.safe_load((full_bag / 'metadata.yaml').read_text())
    for key, value, match in (('storage_identifier', 'rosbag_v3', 'rosbag_v3'),
                              ('version', 42, '42')):
        path = tmp_path / f'bag_{key}'
        path.mkdir()
        (path / 'run.mcap').write_bytes((full_bag / 'run.mcap').read_bytes())
        info = dict(meta['rosbag2_bagfile_information'], **{key: value})
        (path / 'metadata.yaml').write_text(yaml.safe_dump({'rosbag2_bagfile_information': info}))
        _assert_bag_error(path, match)


def test_error_missing_storage_file(full_bag: Path, tmp_path: Path) -> None:
    path = tmp_path / 'bag'
    path.mkdir()
    (path / 'metadata.yaml').write_text((full_bag / 'metadata.yaml').read_text())
    _assert_bag_error(path, 'missing')


def test_closed_reader(full_bag: Path) -> None:
    bag = open_bag(full_bag)
    bag.close()
    bag.close()  # idempotent
    assert bag.closed
    with pytest.raises(BagError, match='closed'):
        list(bag.messages(['/clock']))


# ============================================================================================
# streaming memory
# ============================================================================================


def _write_repeated(path: Path, topic: str, msg: Any, count: int) -> int:
    """Write ``count`` copies of ``msg`` (serialized once) and return the .mcap size."""
    store = get_typestore(Stores.ROS2_JAZZY)
    data = bytes(store.serialize_cdr(msg, msg.__msgtype__))
    with BagWriter(path, {topic: msg.__msgtype__}, typestore=store) as bag:
        for i in range(count):
            bag.write_raw(topic, T0 + i * 1_000_000, data)
    return (path / f'{path.name}.mcap').stat().st_size


def _traced_peak(func: Callable[[], int]) -> tuple[int, int]:
    gc.collect()
    tracemalloc.start()
    try:
        result = func()
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    return result, peak


def test_streaming_memory_is_flat_raw_50k(tmp_path: Path) -> None:
    """50k small messages (~60 MB): raw streaming peak must be a small fraction of the bag."""
    types_ = RosbagsTypes()
    names = tuple(f'joint_{k:02d}' for k in range(30))
    msg = joint_state_to_ros(
        JointStateSample(T0, 'base', names, np.ones(30), np.ones(30), np.ones(30)), types_)
    size = _write_repeated(tmp_path / 'small', '/joint_states', msg, 50_000)
    with open_bag(tmp_path / 'small') as bag:
        count, peak = _traced_peak(lambda: sum(1 for _ in bag.raw_messages(['/joint_states'])))
    assert count == 50_000
    # Chunked streaming keeps ~one 1 MiB chunk (plus copies) alive; loading the bag would not.
    assert peak < 0.15 * size, (peak, size)


def test_streaming_memory_is_flat_deserialized(tmp_path: Path) -> None:
    """Deserializing stream (~48 MB): peak stays small and yielded messages are not retained."""
    types_ = RosbagsTypes()
    joint_state = types_.get('sensor_msgs/msg/JointState')
    empty = np.zeros(0)
    msg = joint_state(header=types_.create('std_msgs/msg/Header', stamp=types_.create(
        'builtin_interfaces/msg/Time', sec=0, nanosec=0), frame_id=''), name=[],
        position=np.arange(2000.0), velocity=empty, effort=empty)
    size = _write_repeated(tmp_path / 'large', '/joint_states', msg, 3000)
    refs: list[weakref.ref] = []

    def consume() -> int:
        count = 0
        for item in bag.messages(['/joint_states']):
            if count % 500 == 0:
                refs.append(weakref.ref(item.msg))
            count += 1
        return count

    with open_bag(tmp_path / 'large') as bag:
        count, peak = _traced_peak(consume)
    assert count == 3000
    assert peak < 0.15 * size, (peak, size)
    gc.collect()
    assert all(ref() is None for ref in refs)  # the reader keeps no reference
