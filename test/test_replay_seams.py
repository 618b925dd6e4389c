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

"""The replay seams of issue 21 (CLI and bags): each test fails before its fix."""

import json
import os
from pathlib import Path
import shutil
import struct
import subprocess
import sys
from types import SimpleNamespace

import numpy as np
import pytest

from reduced_dynamics.bag import BagWriter, open_bag
from reduced_dynamics.cli import main
from reduced_dynamics.estimator.stamps import ACCEPTED, StampGate

from filter_helpers import bag_contents

REPO = Path(__file__).resolve().parent.parent
DATA = REPO / 'test' / 'data'
THRUSTER = DATA / 'paper_thruster'


def _convert(source: Path, path: Path, storage: str = 'sqlite3', edit=None) -> Path:
    """Write ``source`` as a ``storage`` bag at ``path``, ``edit(topic, data)`` per message."""
    with open_bag(source) as bag:
        topics = bag.topics()
        with BagWriter(path, topics, storage=storage) as writer:
            for message in bag.raw_messages(list(topics)):
                data = bytes(message.data) if edit is None else edit(message.topic,
                                                                     bytes(message.data))
                writer.write_raw(message.topic, message.timestamp_ns, data)
    return path


def _messages(path: Path) -> list[tuple[str, int, bytes]]:
    return bag_contents(path)[1]


@pytest.fixture(scope='module')
def thruster_sqlite(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Return paper_thruster converted to a sqlite3 bag."""
    return _convert(THRUSTER, tmp_path_factory.mktemp('sqlite') / 'bag')


def _summary(tmp_path: Path, *args: str) -> tuple[int, dict]:
    out = tmp_path / 'summary.json'
    code = main(['replay', *args, '--quiet', '--summary-json', str(out)])
    return code, json.loads(out.read_text()) if out.exists() else {}


# --------------------------------------------------------------------- 13: truncated sqlite3
@pytest.mark.parametrize('keep', [0.27, 0.4133, 0.62, 0.9])
def test_truncated_sqlite_delivers_no_invented_bytes(keep: float, thruster_sqlite: Path,
                                                     tmp_path: Path) -> None:
    """Item 13: a row whose payload runs past the cut is dropped and counted, not zero-filled."""
    bag = tmp_path / 'bag'
    shutil.copytree(thruster_sqlite, bag)
    db = next(bag.glob('*.db3'))
    data = db.read_bytes()
    db.write_bytes(data[:int(len(data) * keep)])
    clean = set(_messages(THRUSTER))
    with open_bag(bag) as reader:
        got = [(m.topic, m.timestamp_ns, bytes(m.data))
               for m in reader.raw_messages(list(reader.topics()))]
        damage = reader.damage
    assert got and set(got) <= clean
    if keep == 0.27:  # the cut: rows there straddle it
        past_end = [d for d in damage if 'past the readable end' in d.detail]
        assert past_end and all(d.messages_lost for d in past_end)


# ------------------------------------------------------------- 14: stamps decreasing throughout
def _reverse_stamps(start: int, end: int):
    def edit(topic: str, data: bytes) -> bytes:
        out = bytearray(data)
        sec, nsec = struct.unpack_from('<iI', out, 4)  # header.stamp after the CDR header
        stamp = start + end - (sec * 10**9 + nsec)
        struct.pack_into('<iI', out, 4, stamp // 10**9, stamp % 10**9)
        return bytes(out)
    return edit


def test_stamp_gate_accounts_for_every_sample() -> None:
    """Item 14: every offered sample is accepted or dropped with a reason, none vanishes."""
    for receive in (True, False):
        gate = StampGate('joint states', 10**9, 3)
        settled, offered = 0, 400
        for k in range(offered):
            stamp = 10**12 - k * 5_000_000  # 200 Hz, backwards throughout
            result = gate.offer(stamp, 10**12 + k * 5_000_000 if receive else None, k)
            settled += 1 if result is ACCEPTED else len(result.accepted) + len(result.dropped)
        settled += len(gate.finish())
        assert settled == offered, receive


@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
def test_replay_counts_every_joint_state_of_a_bag_with_decreasing_stamps(
        storage: str, tmp_path: Path) -> None:
    """Item 14: processed + rejected joint states = received, on a reversed-stamp bag."""
    with open_bag(THRUSTER) as bag:
        edit = _reverse_stamps(bag.start_ns, bag.end_ns)
    bag = _convert(THRUSTER, tmp_path / 'bag', storage, edit)
    code, summary = _summary(tmp_path, str(bag), '-o', str(tmp_path / 'out'))
    assert code == 0
    joint_rejected = sum(n for reason, n in summary['rejected'].items()
                         if not reason.startswith(('base_', 'command')))
    assert summary['received']['joint_states'] == 801
    assert summary['processed'] + joint_rejected == 801


# ------------------------------------------------------------ 15: metadata.yaml counts differ
def test_undamaged_sqlite_bag_with_other_metadata_counts_is_reported(
        thruster_sqlite: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """Item 15: the counts comparison runs on undamaged bags too."""
    bag = tmp_path / 'bag'
    shutil.copytree(thruster_sqlite, bag)
    meta = bag / 'metadata.yaml'
    text = meta.read_text()
    joint = text.index('name: /joint_states')
    odom = text.index('name: /odom')
    head = text[:joint].rsplit('message_count: 801', 1)
    middle = text[joint:odom].rsplit('message_count: 801', 1)
    meta.write_text('message_count: 850'.join(head) + 'message_count: 780'.join(middle)
                    + text[odom:])
    code, summary = _summary(tmp_path, str(bag), '-o', str(tmp_path / 'out'))
    damage = summary['damage']
    assert damage['regions'] == [] and damage['undecodable'] == 0
    assert damage['missing_vs_index'] == {'/joint_states': 49}
    assert damage['extra_vs_index'] == {'/odom': 21}
    assert code == 3
    out = capsys.readouterr().out
    assert "missing against the bag's own counts: /joint_states 49" in out
    assert "more messages than the bag's own counts" in out and '/odom 21' in out


# --------------------------------------------------------------- 16: CLI wording, closed pipes
def test_existing_output_error_names_the_cli_flag(tmp_path: Path,
                                                  capsys: pytest.CaptureFixture) -> None:
    """Item 16: the CLI's error names --overwrite, not the Python argument."""
    out = tmp_path / 'out'
    out.mkdir()
    assert main(['replay', str(THRUSTER), '-o', str(out), '--quiet']) == 2
    err = capsys.readouterr().err
    assert '--overwrite' in err and 'overwrite=True' not in err and len(err.splitlines()) == 1


def test_output_into_a_closed_pipe_ends_without_a_traceback() -> None:
    """Item 16: ``reduced-dynamics predict ... | head`` (reader gone) ends quietly."""
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get('PYTHONPATH', ''))
    proc = subprocess.Popen(
        [sys.executable, '-m', 'reduced_dynamics.cli', 'predict', '--trajectory',
         str(REPO / 'config' / 'plans' / 'example_plan.yaml')],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env)
    proc.stdout.close()  # the reader is gone before the first line is printed
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=300) == 1
    assert 'Traceback' not in err and 'BrokenPipeError' not in err, err


# --------------------------------------------------- 11: no joint states for a jointed robot
def _retopic(mapping: dict[str, tuple[str, str]], path: Path) -> Path:
    """Write paper_thruster with topics renamed/retyped: {old: (new name, new type)}."""
    with open_bag(THRUSTER) as bag:
        topics = bag.topics()
        messages = list(bag.raw_messages(list(topics)))
    renamed = {mapping.get(t, (t, m))[0]: mapping.get(t, (t, m))[1] for t, m in topics.items()
               if mapping.get(t, (t,))[0]}
    with BagWriter(path, renamed) as writer:
        for message in messages:
            name = mapping.get(message.topic, (message.topic,))[0]
            if name:
                writer.write_raw(name, message.timestamp_ns, bytes(message.data))
    return path


@pytest.mark.parametrize('case', ['renamed', 'absent', 'other_type'])
def test_jointed_robot_without_joint_states_is_refused(case: str, tmp_path: Path,
                                                       capsys: pytest.CaptureFixture) -> None:
    """Item 11: exit 2 naming the bag's JointState topics; --base-driven runs it."""
    joint = 'sensor_msgs/msg/JointState'
    mapping = {'renamed': {'/joint_states': ('/arm/joint_states', joint)},
               'absent': {'/joint_states': ('', joint)},
               'other_type': {'/joint_states': ('/joint_states',
                                                'geometry_msgs/msg/WrenchStamped')}}[case]
    bag = _retopic(mapping, tmp_path / 'bag')
    out = tmp_path / 'out'
    assert main(['replay', str(bag), '-o', str(out), '--quiet']) == 2
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1 and '--base-driven' in err
    assert ('JointState topics: /arm/joint_states' if case == 'renamed'
            else 'JointState topics: none') in err
    if case == 'other_type':
        assert 'it is geometry_msgs/msg/WrenchStamped' in err
    assert not out.exists()
    code, summary = _summary(tmp_path, str(bag), '-o', str(out), '--base-driven')
    assert code == 0 and summary['base_driven'] and summary['processed'] > 0
    if case == 'absent':  # tune reads bags the same way
        params = tmp_path / 'tuned.yaml'
        assert main(['tune', str(bag), '-o', str(params), '--quiet']) == 2
        assert 'JointState topics: none' in capsys.readouterr().err and not params.exists()


# ------------------------------------------------------- 12: joints of another robot, no --urdf
def test_joint_states_of_another_robot_are_refused_naming_the_robot(
        tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """Item 12: the built-in robot is named, and joint names that do not match refuse."""
    from rosbags.typesys import get_typestore, Stores
    store = get_typestore(Stores.ROS2_JAZZY)
    joint = 'sensor_msgs/msg/JointState'

    def rename(topic: str, data: bytes) -> bytes:
        if topic != '/joint_states':
            return data
        msg = store.deserialize_cdr(data, joint)
        msg.name = [f'arm_{k}' for k in range(len(msg.name))]
        return bytes(store.serialize_cdr(msg, joint))
    bag = _convert(THRUSTER, tmp_path / 'bag', 'mcap', rename)
    assert main(['replay', str(bag), '-o', str(tmp_path / 'out'), '--quiet']) == 2
    err = capsys.readouterr().err
    assert 'built-in paper robot' in err and 'arm_0' in err and '--urdf' in err
    assert len(err.splitlines()) == 1
    # A matching bag runs, and its summary says which robot was used.
    assert main(['replay', str(THRUSTER), '-o', str(tmp_path / 'good'), '--quiet']) == 0
    assert 'robot paper_robot from the built-in paper robot' in capsys.readouterr().out


# ------------------------------------------------------------------------------- 17: xacro
XACRO = DATA / 'xacro_arm' / 'arm.urdf.xacro'


def _inertias(robot) -> tuple[list[str], np.ndarray]:
    """Return the joint names and every joint's inertia and placement numbers."""
    model = robot.model
    return list(model.names), np.array([
        [model.inertias[k].mass, *model.inertias[k].lever, *model.inertias[k].inertia.flat,
         *model.jointPlacements[k].translation, *model.jointPlacements[k].rotation.flat]
        for k in range(model.njoints)])


def test_multi_file_xacro_expands_to_its_urdf_with_arguments() -> None:
    """Item 17: includes, properties, macros and <xacro:arg> through load_robot."""
    from reduced_dynamics.robot.model import load_robot
    expanded = load_robot(str(XACRO))
    written = load_robot(str(DATA / 'xacro_arm' / 'arm.urdf'))
    assert expanded.shape_joint_names == written.shape_joint_names == (
        'upper_joint', 'fore_joint')
    names, numbers = _inertias(expanded)
    written_names, written_numbers = _inertias(written)
    assert names == written_names
    np.testing.assert_allclose(numbers, written_numbers, rtol=1e-12, atol=1e-15)
    left = load_robot(str(XACRO), xacro_args={'prefix': 'left_', 'link_mass': '3.5'})
    assert left.shape_joint_names == ('left_upper_joint', 'left_fore_joint')
    masses = {name: left.model.inertias[k].mass for k, name in enumerate(left.model.names)}
    assert masses['left_upper_joint'] == masses['left_fore_joint'] == 3.5


def test_cli_takes_a_xacro_urdf_and_xacro_args(capsys: pytest.CaptureFixture) -> None:
    """Item 17: --urdf FILE.xacro --xacro-arg name:=value on the command line."""
    assert main(['symmetries', '--urdf', str(XACRO), '--xacro-arg', 'prefix:=r_',
                 '--configurations', '2']) == 0
    out = capsys.readouterr().out
    assert 'robot xacro_arm' in out and 'r_upper_joint' in out and 'r_fore_joint' in out
    assert main(['symmetries', '--urdf', str(XACRO), '--xacro-arg', 'prefix']) == 2
    assert 'name:=value' in capsys.readouterr().err
    broken = ['symmetries', '--urdf', str(DATA / 'xacro_arm' / 'macros' / 'arm_link.xacro')]
    assert main(broken) == 2  # macros only: no robot (a clear error, not a traceback)


# ---------------------------------------------------------- 18: replay independent of the load
def test_replay_outputs_do_not_depend_on_the_machine_load(tmp_path: Path,
                                                          monkeypatch: pytest.MonkeyPatch
                                                          ) -> None:
    """Item 18: on a machine where every evaluation takes 1 s, the outputs are the same."""
    from reduced_dynamics import integrators
    quiet_code, quiet = _summary(tmp_path, str(THRUSTER), '-o', str(tmp_path / 'quiet'))
    ticks = iter(range(10**9))
    # A clock that advances one second per reading: any wall-time budget is spent at once.
    monkeypatch.setattr(integrators, 'time', SimpleNamespace(perf_counter=lambda: next(ticks)))
    loaded_code, loaded = _summary(tmp_path, str(THRUSTER), '-o', str(tmp_path / 'loaded'))
    assert quiet_code == loaded_code == 0 and quiet['predictions'] > 0
    assert loaded['prediction_failures'] == quiet['prediction_failures'] == {}
    assert _messages(tmp_path / 'loaded') == _messages(tmp_path / 'quiet')


def test_innovation_gate_rejections_and_the_filter_count_are_one_count(
        tmp_path: Path) -> None:
    """Item 18: summary rejected innovation_gate == filter.innovation_gated."""
    from rosbags.typesys import get_typestore, Stores
    store = get_typestore(Stores.ROS2_JAZZY)
    odometry = 'nav_msgs/msg/Odometry'
    with open_bag(THRUSTER) as bag:
        start = bag.start_ns

    def shift(topic: str, data: bytes) -> bytes:
        # From 2 s on the base pose is 5 cm off: runs of gated poses, each ending in a
        # measurement the filter takes (a momentum jump), which is not a rejection.
        if topic != '/odom':
            return data
        msg = store.deserialize_cdr(data, odometry)
        if msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec - start > 2 * 10**9:
            msg.pose.pose.position.x += 0.05
        return bytes(store.serialize_cdr(msg, odometry))
    bag = _convert(THRUSTER, tmp_path / 'bag', 'mcap', shift)
    code, summary = _summary(tmp_path, str(bag), '-o', str(tmp_path / 'out'))
    assert code == 0
    assert summary['rejected']['innovation_gate'] > 0
    assert summary['rejected']['innovation_gate'] == summary['filter']['innovation_gated']


def test_node_urdf_path_takes_a_xacro_file() -> None:
    """Item 17: the node's urdf_path expands a .xacro (its defaults), on real rclpy."""
    try:
        from ros_harness import real_ros
    except ImportError:  # test/ imported as a package
        from test.ros_harness import real_ros
    with real_ros():
        from rclpy.parameter import Parameter
        from reduced_dynamics.node import ReducedDynamicsNode
        node = ReducedDynamicsNode(parameter_overrides=[Parameter('urdf_path',
                                                                  value=str(XACRO))])
        try:
            assert node.model_error is None
            assert node.estimator.robot.shape_joint_names == ('upper_joint', 'fore_joint')
        finally:
            node.destroy_node()
