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
The ROS-free half of ``reduced-dynamics play`` (reduced_dynamics.bag.playback).

No rclpy here: the schedule runs on an injected clock, messages are rosbags
dataclasses, and ``publish`` is a list append. The DDS side is test_play_dds.py.
"""

import ast
from pathlib import Path
import subprocess
import sys
import threading

import numpy as np
import pytest
from rosbags.typesys import get_typestore, Stores

from reduced_dynamics.bag.playback import (
    clock_time_ns, play_messages, PlaybackClock, PlayOptions, restamp_offset_ns, shift_stamps)
from reduced_dynamics.bag.reader import open_bag

REPO_ROOT = Path(__file__).resolve().parent.parent
DATA = REPO_ROOT / 'test' / 'data'
BAG = DATA / 'paper_constant'
STORE = get_typestore(Stores.ROS2_JAZZY)
S = 1_000_000_000


class FakeTime:
    """A monotonic clock that moves only when told (waits advance it to their deadline)."""

    def __init__(self, start=5 * S):
        self.now = start

    def __call__(self):
        return self.now


def _clock(bag0=100 * S, rate=1.0, paused=False):
    fake = FakeTime()
    return fake, PlaybackClock(bag0, rate, paused=paused, now_ns=fake)


# ------------------------------------------------------------------ the schedule
def test_due_times_scale_with_the_rate():
    fake, clock = _clock(rate=2.0)
    assert clock.due_ns(100 * S) == fake.now
    assert clock.due_ns(104 * S) == fake.now + 2 * S  # 4 s of bag in 2 s
    fake.now += 3 * S
    assert clock.bag_time_ns() == 106 * S


def test_pause_freezes_bag_time_and_resume_does_not_catch_up():
    fake, clock = _clock()
    fake.now += 2 * S
    assert clock.pause() and not clock.pause()
    fake.now += 10 * S  # ten seconds paused
    assert clock.bag_time_ns() == 102 * S and clock.due_ns(103 * S) is None
    assert clock.resume() and not clock.resume()
    assert clock.due_ns(103 * S) == fake.now + S  # one second after resuming, not at once
    fake.now += S // 2
    assert clock.bag_time_ns() == 102 * S + S // 2


def test_jump_restarts_the_schedule_at_a_bag_time():
    fake, clock = _clock()
    fake.now += 7 * S
    clock.jump(100 * S)
    assert clock.bag_time_ns() == 100 * S and clock.due_ns(101 * S) == fake.now + S


def test_wait_returns_at_once_when_due_and_false_when_stopped():
    fake, clock = _clock()
    assert clock.wait_for(99 * S)  # in the past
    paused = PlaybackClock(0, paused=True)
    results = []
    waiter = threading.Thread(target=lambda: results.append(paused.wait_for(0)))
    waiter.start()
    paused.stop()  # wakes the paused waiter: no polling, no deadline
    waiter.join(timeout=60)
    assert results == [False]


def test_a_waiter_paused_before_its_message_plays_it_after_resume():
    clock = PlaybackClock(0, paused=True)
    results = []
    waiter = threading.Thread(target=lambda: results.append(clock.wait_for(0)))
    waiter.start()
    clock.resume()
    waiter.join(timeout=60)
    assert results == [True]


def test_options_problems_are_named():
    assert PlayOptions('b').problems() == []
    problems = PlayOptions('b', rate=0.0, clock_hz=-1, qos_depth=-2,
                           wait_timeout=float('nan'), ack_timeout=-1.0).problems()
    assert [p.split()[0] for p in problems] == ['--rate', '--clock', '--qos-depth',
                                                '--wait-timeout', '--ack-timeout']


def test_play_waits_for_acknowledgements_as_long_as_asked():
    import argparse
    from reduced_dynamics.player_node import ACK_TIMEOUT, options_from_args, register_command
    parser = argparse.ArgumentParser()
    register_command(parser.add_subparsers())
    assert options_from_args(parser.parse_args(['play', 'b'])).ack_timeout == ACK_TIMEOUT
    options = options_from_args(parser.parse_args(['play', 'b', '--ack-timeout', '0']))
    assert options.ack_timeout == 0.0 and options.problems() == []  # 0: for ever


# ------------------------------------------------------------------ playing
def _play(options, clock, accept=lambda message: True):
    published = []

    def publish(message, index):
        if not accept(message):
            return False
        published.append((index, message.topic, message.timestamp_ns, clock.now_ns()))
        return True
    return play_messages(options, clock, publish), published


def test_every_message_is_published_in_order_not_before_it_is_due():
    with open_bag(BAG) as reader:
        start, count = reader.start_ns, reader.message_count()
        order = [(m.topic, m.timestamp_ns) for m in reader.raw_messages(reader.topics())]
    clock = PlaybackClock(start, rate=1000.0)  # real time, 3 ms for the 3 s bag
    stats, published = _play(PlayOptions(str(BAG), rate=1000.0), clock)
    assert stats.total() == count and stats.passes == 1 and not stats.stopped
    assert [(t, s) for _, t, s, _ in published] == order
    # Lower bounds only: a loaded machine publishes late, never early.
    assert all(at >= clock.due_ns(stamp) for _, _, stamp, at in published)
    assert len(stats.late_ns) == count and min(stats.late_ns) >= 0
    median, worst = stats.lateness_ms()
    assert 0 <= median <= worst == max(stats.late_ns) / 1e6


def test_topics_filter_loop_and_skipped_counts():
    with open_bag(BAG) as reader:
        start = reader.start_ns
        joints = reader.message_count('/joint_states')
        odom = reader.message_count('/odom')
    clock = PlaybackClock(start, rate=1e6)
    options = PlayOptions(str(BAG), rate=1e6, topics=('/joint_states', '/odom'), loop=True)
    passes = []

    def accept(message):
        if len(passes) == 3 and message.topic == '/odom':
            clock.stop()  # Ctrl-C in the third pass
        return message.topic == '/joint_states'  # /odom: a type not installed
    published = []

    def publish(message, index):
        if index not in passes:
            passes.append(index)
        if not accept(message):
            return False
        published.append(index)
        return True
    stats = play_messages(options, clock, publish)
    assert stats.stopped and stats.passes == 3 and passes == [0, 1, 2]
    assert published.count(0) == published.count(1) == joints
    assert stats.published == {'/joint_states': len(published)}
    assert stats.skipped['/odom'] == 2 * odom + 1


def test_a_topic_not_in_the_bag_is_refused_with_the_available_ones():
    clock = PlaybackClock(0)
    with pytest.raises(ValueError, match=r"topics not in bag .*\['/nope'\]; available: "):
        play_messages(PlayOptions(str(BAG), topics=('/nope',)), clock, lambda m, i: True)


# ------------------------------------------------------------------ definitions
def write_redefined_bag(path):
    """Write a bag whose /odd is std_msgs/String defined as an int32; /same is Jazzy's Bool."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import get_types_from_msg
    odd_store = get_typestore(Stores.EMPTY)
    odd_store.register(get_types_from_msg('int32 data', 'std_msgs/msg/String'))
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        odd = writer.add_connection('/odd', 'std_msgs/msg/String', typestore=odd_store)
        same = writer.add_connection('/same', 'std_msgs/msg/Bool', typestore=STORE)
        writer.write(odd, 1, odd_store.serialize_cdr(
            odd_store.types['std_msgs/msg/String'](data=7), 'std_msgs/msg/String'))
        writer.write(same, 2, STORE.serialize_cdr(
            STORE.types['std_msgs/msg/Bool'](data=True), 'std_msgs/msg/Bool'))
    return path


def test_a_topic_defined_otherwise_than_in_jazzy_is_found_by_its_type_hash(tmp_path):
    from reduced_dynamics.bag.playback import definition_problems
    with open_bag(write_redefined_bag(tmp_path / 'bag')) as reader:
        problems = definition_problems(reader, reader.topics())
    assert list(problems) == ['/odd'] and 'type hash differs' in problems['/odd']
    for bag in (BAG, DATA / 'freeflyer2' / 'rosbag2_2024_03_14-14_17_23'):  # no definitions
        with open_bag(bag) as reader:
            assert definition_problems(reader, reader.topics()) == {}


# ------------------------------------------------------------------ stamps
def _header(sec, nanosec, frame='map'):
    time_ = STORE.types['builtin_interfaces/msg/Time'](sec=sec, nanosec=nanosec)
    return STORE.types['std_msgs/msg/Header'](stamp=time_, frame_id=frame)


def test_shift_stamps_moves_every_header_nested_too_and_keeps_zero_stamps():
    types = STORE.types
    vector = types['geometry_msgs/msg/Vector3'](x=1.0, y=2.0, z=3.0)
    rotation = types['geometry_msgs/msg/Quaternion'](x=0.0, y=0.0, z=0.0, w=1.0)
    transform = types['geometry_msgs/msg/Transform'](translation=vector, rotation=rotation)

    def stamped(sec, nanosec):
        return types['geometry_msgs/msg/TransformStamped'](
            header=_header(sec, nanosec), child_frame_id='b', transform=transform)
    tf = types['tf2_msgs/msg/TFMessage'](transforms=[stamped(10, 999_999_999),
                                                     stamped(0, 0), stamped(3, 5)])
    assert shift_stamps(tf, 2 * S + 1) == 2
    assert [(t.header.stamp.sec, t.header.stamp.nanosec) for t in tf.transforms] == \
        [(13, 0), (0, 0), (5, 6)]
    joints = types['sensor_msgs/msg/JointState'](
        header=_header(7, 0), name=['a'], position=np.zeros(1), velocity=np.zeros(1),
        effort=np.zeros(1))
    assert shift_stamps(joints, -S) == 1 and joints.header.stamp.sec == 6
    # A round trip through CDR: still a valid message of the same type.
    data = STORE.serialize_cdr(joints, 'sensor_msgs/msg/JointState')
    assert STORE.deserialize_cdr(data, 'sensor_msgs/msg/JointState').header.stamp.sec == 6


def test_a_stamp_moved_out_of_range_is_refused():
    message = _header(1, 0)
    with pytest.raises(ValueError, match='outside builtin_interfaces/Time'):
        shift_stamps(message, -2 * S)


def test_restamp_offset_is_the_system_time_the_bag_start_was_due_at():
    fake, clock = _clock(bag0=100 * S, rate=2.0)
    fake.now += 3 * S  # the first message of the pass goes out 3 s after the start
    assert restamp_offset_ns(clock, 100 * S, 2_000 * S) == 2_000 * S - 3 * S - 100 * S
    clock.pause()  # paused meanwhile (the ~/pause service): the same start
    fake.now += 10 * S
    assert restamp_offset_ns(clock, 100 * S, 2_010 * S) == 2_000 * S - 3 * S - 100 * S + 10 * S


def test_remap_names_the_published_topic():
    from reduced_dynamics.bag.playback import parse_remap
    options = PlayOptions('b', remap=(parse_remap('/joint_states:=/sc1/joint_states'),))
    assert options.published_name('/joint_states') == '/sc1/joint_states'
    assert options.published_name('/odom') == '/odom'
    with pytest.raises(ValueError, match='FROM:=TO'):
        parse_remap('/joint_states')


def test_the_clock_topic_follows_bag_time_and_the_stamps():
    fake, clock = _clock(bag0=100 * S)
    fake.now += S
    assert clock_time_ns(clock) == 101 * S
    assert clock_time_ns(clock, 50 * S) == 151 * S


# ------------------------------------------------------------------ the ROS shells
#: The modules that import rclpy: the ROS shells. Everything else is ROS-free.
ROS_SHELLS = {
    'reduced_dynamics/node.py',  # the node
    'reduced_dynamics/player_node.py',  # reduced-dynamics play
    'reduced_dynamics/node_bench.py',  # the processes of bench --sections node
}


def _imports_rclpy(path):
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                 else [node.module or ''] if isinstance(node, ast.ImportFrom) else [])
        if any(n == 'rclpy' or n.startswith('rclpy.') for n in names):
            return True
    return False


def test_only_the_ros_shells_import_rclpy():
    found = {str(p.relative_to(REPO_ROOT)) for p in (REPO_ROOT / 'reduced_dynamics').rglob('*.py')
             if _imports_rclpy(p)}
    assert found == ROS_SHELLS


def _play_without_rclpy(*args: str) -> subprocess.CompletedProcess:
    """Run ``reduced-dynamics play BAG args`` in an interpreter where rclpy cannot import."""
    code = ('import sys\nsys.modules["rclpy"] = None\n'
            'from reduced_dynamics.cli import main\n'
            f'sys.exit(main(["play", {str(BAG)!r}, *{list(args)!r}]))')
    return subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                          timeout=120, cwd=REPO_ROOT)


def test_play_help_and_bad_options_need_no_rclpy():
    done = _play_without_rclpy('--rate', '0', '--topics', '/nope')
    assert done.returncode == 2, done.stderr
    assert done.stderr.splitlines() == [
        'reduced-dynamics play: error: --rate must be a positive number, got 0.0',
        f"reduced-dynamics play: error: topics not in bag {BAG}: ['/nope']; available: "
        "['/ground_truth/external_wrench', '/ground_truth/momentum', '/joint_states', "
        "'/odom']"]


def test_play_without_rclpy_says_so_in_one_line():
    done = _play_without_rclpy()
    assert done.returncode == 1
    assert done.stderr.splitlines() == [
        'reduced-dynamics play: rclpy is not importable; source /opt/ros/jazzy/setup.bash, '
        'or install the rclpy wheels: pip install ".[ros]"']
