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
``reduced-dynamics play`` over real DDS: the player, the node and a recorder as processes.

Every party is a process of its own (test/dds_recorder.py records): one process
both publishing and recording lost most outputs on a loaded machine. Nothing waits
a fixed time: the player starts when its publishers are matched
(``--wait-for-subscribers``), the recorder ends when it has the expected counts, and
the timeouts only turn a hang into a failure.
"""

import json
import os
from pathlib import Path
import queue
import shlex
import signal
import subprocess
import sys
import threading
import time

import pytest

try:
    from ros_harness import DOMAIN_ID
except ImportError:  # test/ imported as a package
    from test.ros_harness import DOMAIN_ID

import test_node_dds as dds  # noqa: E402  (the installed node and its comparison)
from test_node_dds import install  # noqa: E402,F401  (fixture: the colcon install)

from reduced_dynamics.bag.reader import open_bag  # noqa: E402
from reduced_dynamics.node import NODE_STATUS_NAME  # noqa: E402
from reduced_dynamics.resources import paper_robot_urdf  # noqa: E402
from reduced_dynamics.topics import active_topics, resolved_name  # noqa: E402

REPO_ROOT = Path(__file__).resolve().parent.parent
DATA = REPO_ROOT / 'test' / 'data'
SQLITE_BAG = DATA / 'freeflyer2' / 'rosbag2_2024_03_14-14_17_23'
MOCAP = '/vrpn_mocap/robot/pose'
GUARD = 300  # seconds: only a hang reaches it


def _env():
    path = os.pathsep.join([str(REPO_ROOT)] + [
        p for p in os.environ.get('PYTHONPATH', '').split(os.pathsep) if p])
    return dict(os.environ, ROS_DOMAIN_ID=DOMAIN_ID, PYTHONUNBUFFERED='1', PYTHONPATH=path)


def _start(args):
    """Start a process whose stdout lines are collected (``proc.lines``) as they come."""
    proc = subprocess.Popen(args, env=_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, start_new_session=True)
    proc.lines, proc.new_lines = [], queue.Queue()

    def read():
        for line in proc.stdout:
            proc.lines.append(line)
            proc.new_lines.put(line)
        proc.new_lines.put(None)
    proc.reader = threading.Thread(target=read, daemon=True)
    proc.reader.start()
    return proc


def start_player(bag, *options):
    """
    Start ``reduced-dynamics play BAG OPTIONS`` (this checkout's package).

    The player waits for every acknowledgement however long it takes (``--ack-timeout 0``;
    GUARD bounds a hang): at a load of 15-18 the recorder of 6 569 messages had not
    acknowledged them 30 s after the last was played, and waited in vain for the rest.
    """
    return _start([sys.executable, '-m', 'reduced_dynamics.cli', 'play', str(bag),
                   '--ack-timeout', '0', *options])


def start_recorder(output, specs, exclude=''):
    """Start test/dds_recorder.py; ``specs``: TOPIC:TYPE[:COUNT] strings."""
    script = str(Path(__file__).resolve().parent / 'dds_recorder.py')
    return _start([sys.executable, script, str(output), *specs]
                  + (['--exclude', exclude] if exclude else []))


def wait_for_line(proc, text, timeout=GUARD):
    """Wait until a stdout line of ``proc`` holds ``text`` (a readiness sign)."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        try:
            line = proc.new_lines.get(timeout=max(end - time.monotonic(), 0.01))
        except queue.Empty:
            break
        if line is None:
            break
        if text in line:
            return
    error = proc.stderr.read() if proc.poll() is not None else ''
    raise AssertionError(f'no line with {text!r}: {proc.lines} {error}')


def finish(proc, timeout=GUARD):
    """
    Wait for ``proc`` to end by itself; return (code, stdout, stderr).

    For as long as it prints a line within ``timeout`` (the recorder's progress): at a
    load of 24 the recorder of 6569 messages had not ended 300 s after the player
    (issue 24). A hang prints nothing: the wait ends, the process is killed and the test
    fails with what it printed.
    """
    hung = False
    try:
        seen, since = len(proc.lines), time.monotonic()
        while True:
            try:
                proc.wait(timeout=1.0)
                break
            except subprocess.TimeoutExpired:
                if len(proc.lines) != seen:
                    seen, since = len(proc.lines), time.monotonic()
                elif time.monotonic() - since > timeout:
                    hung = True
                    break
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    proc.reader.join(timeout=timeout)
    out, err = ''.join(proc.lines), proc.stderr.read()
    # What it printed says where it stopped (a CI run's player once hung here, unexplained).
    assert not hung, f'{proc.args} printed nothing for {timeout:g} s, then was killed; ' \
        f'its stdout: {out!r}; its stderr: {err!r}'
    return proc.returncode, out, err


def _bag_raw(bag, topic):
    with open_bag(bag) as reader:
        return [bytes(m.data) for m in reader.raw_messages([topic])]


# ------------------------------------------------------------------ sqlite, no definitions
@pytest.mark.parametrize('restamp', [False, True])
def test_sqlite_bag_without_definitions_is_played_bit_for_bit(tmp_path, restamp):
    """The real freeflyer2 sqlite bag: PoseStamped played, ff_msgs skipped and counted."""
    from geometry_msgs.msg import PoseStamped
    from rclpy.serialization import deserialize_message
    with open_bag(SQLITE_BAG) as reader:
        counts = {t: reader.message_count(t) for t in reader.topics()}
        start_ns = reader.start_ns
    sent = _bag_raw(SQLITE_BAG, MOCAP)
    recorder = start_recorder(tmp_path / 'got.json',
                              [f'{MOCAP}:geometry_msgs/msg/PoseStamped:{len(sent)}'])
    before = time.time_ns()
    player = start_player(SQLITE_BAG, '--rate', '200', '--qos-depth', '0',
                          '--wait-for-subscribers', MOCAP, *(['--restamp'] if restamp else []))
    code, out, err = finish(player)
    after = time.time_ns()
    assert code == 0, out + err
    recorded, rec_out, rec_err = finish(recorder)
    assert recorded == 0, rec_out + rec_err
    got = [bytes.fromhex(h) for h in json.loads((tmp_path / 'got.json').read_text())[MOCAP]]
    # Every ff_msgs topic: one line; their messages counted in the summary.
    assert sorted(line.split()[3].rstrip(':') for line in err.splitlines()
                  if 'skipping' in line) == \
        sorted(t for t in counts if t != MOCAP)
    skipped = sum(n for t, n in counts.items() if t != MOCAP)
    assert f'published {len(sent)} messages on 1 topic(s)' in out
    assert f'{skipped} skipped' in out
    assert len(got) == len(sent)
    if not restamp:
        assert got == sent
        return
    offsets = set()
    for mine, theirs in zip(got, sent):
        a, b = (deserialize_message(d, PoseStamped) for d in (mine, theirs))
        offsets.add((a.header.stamp.sec - b.header.stamp.sec) * 10**9
                    + a.header.stamp.nanosec - b.header.stamp.nanosec)
        a.header.stamp = b.header.stamp
        assert a == b  # only the stamp moved
    offset, = offsets  # one shift for all: the spacing is kept
    assert before - start_ns <= offset <= after - start_ns


def test_a_topic_defined_otherwise_is_skipped_and_counted(tmp_path):
    """Bytes of another definition would not decode as the installed type: not published."""
    from test_playback import write_redefined_bag
    bag = write_redefined_bag(tmp_path / 'bag')
    code, out, err = finish(start_player(bag, '--rate', '1000'))
    assert code == 0, out + err
    assert [line for line in err.splitlines() if 'skipping' in line] == [
        'reduced-dynamics play: skipping /odd: the bag defines std_msgs/msg/String '
        'differently from ROS 2 Jazzy (its type hash differs): its bytes would not decode '
        'as the installed type']
    assert 'published 1 messages on 1 topic(s)' in out and '1 skipped' in out


@pytest.mark.parametrize('sig, sign', [
    (signal.SIGINT, 'playing'), (signal.SIGTERM, 'playing'),
    (signal.SIGINT, 'waiting for subscribers')])
def test_a_signal_stops_playback_with_exit_0_and_one_summary_line(sig, sign):
    """Ctrl-C or SIGTERM while playing, or while waiting for a subscriber that never comes."""
    waiting = ['--wait-for-subscribers', MOCAP] if sign.startswith('waiting') else []
    player = start_player(SQLITE_BAG, '--topics', MOCAP, *waiting)  # 55 s at rate 1
    try:
        wait_for_line(player, sign)
        player.send_signal(sig)
        code, out, err = finish(player)
    finally:
        if player.poll() is None:
            player.kill()
    assert code == 0, err
    assert 'Traceback' not in err and err.strip() == '', err
    if sign == 'playing':
        summary, = [line for line in out.splitlines() if 'published' in line]
        assert summary.endswith(', stopped)'), summary


def test_a_stamp_that_cannot_move_is_skipped_and_counted(tmp_path):
    """--restamp of a stamp near the end of int32 seconds: one line, counted, no crash."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import get_typestore, Stores
    store = get_typestore(Stores.ROS2_JAZZY)
    types = store.types
    msgtype = 'geometry_msgs/msg/PointStamped'

    def stamped(sec):
        header = types['std_msgs/msg/Header'](
            stamp=types['builtin_interfaces/msg/Time'](sec=sec, nanosec=0), frame_id='map')
        point = types['geometry_msgs/msg/Point'](x=1.0, y=2.0, z=3.0)
        return store.serialize_cdr(types[msgtype](header=header, point=point), msgtype)
    with Writer(tmp_path / 'bag', version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        far = writer.add_connection('/far', msgtype, typestore=store)
        near = writer.add_connection('/near', msgtype, typestore=store)
        writer.write(far, 1, stamped(2**31 - 10))  # a year-2038 stamp: now + it overflows
        writer.write(near, 2, stamped(1))
    code, out, err = finish(start_player(tmp_path / 'bag', '--restamp', '--rate', '1000'))
    assert code == 0, out + err
    line, = err.splitlines()
    assert line.startswith('reduced-dynamics play: skipping messages of /far: cannot '
                           'restamp: a shifted stamp') and 'builtin_interfaces/Time' in line
    assert 'published 1 messages on 1 topic(s)' in out and '1 skipped' in out


# ------------------------------------------------------------------ into the node
def test_bag_played_into_the_node_gives_replays_outputs(install, tmp_path):  # noqa: F811
    """
    paper_constant played with ``--clock`` into the node on sim time, as replay_bag.launch.py.

    Compared as test_node_dds compares the node fed by a test client: every causal
    output bit for bit, the estimator's diagnostics but for the counts that depend on
    how two topics interleaved on arrival; the node's own status is left out.
    """
    from reduced_dynamics.params import defaults
    from reduced_dynamics.replay import replay, ReplayOptions
    from reduced_dynamics.robot.model import load_robot
    bag = DATA / 'paper_constant'
    urdf = str(paper_robot_urdf())
    # Receive times are the machine's: tolerated alike in the node and the replay
    # (test_node_dds.STAMP_PARAMETERS).
    params = dict(defaults(), **dds.STAMP_PARAMETERS)
    replay(str(bag), str(tmp_path / 'out'), load_robot(urdf),
           ReplayOptions(params=params, smooth=False))
    expected = {}
    with open_bag(tmp_path / 'out') as reader:
        for topic in active_topics(False):
            name = resolved_name(topic)
            expected[name] = (topic.msgtype, [bytes(m.data) for m in reader.raw_messages([name])])
    # Counts to wait for: every topic but the node's own status mixed into /diagnostics.
    specs = [f'{name}:{msgtype}:{len(messages)}' for name, (msgtype, messages)
             in expected.items()]
    keep_outputs = [f'-p qos_overrides.{name}.publisher.history:=keep_all' for name in expected]
    # The recorder first: its readers are known to the node before the node's writers
    # exist, so they match them before anything is published (volatile writers send only
    # what they write after matching); "ready" says the recorder sees them too.
    recorder = start_recorder(tmp_path / 'got.json', specs, exclude=NODE_STATUS_NAME)
    node = player = None
    try:
        # No wall-time prediction budget: replay has none, a loaded machine would make the
        # node drop predictions (issue 24.1). Volatile inputs, as the player's writers (a
        # transient-local reader never matches a volatile writer).
        node = dds.start_node(install, f'-p urdf_path:={shlex.quote(urdf)}',
                              '-p use_sim_time:=true', '-p prediction_max_wall_time:=0.0',
                              *(f'-p {name}:={value}'
                                for name, value in dds.STAMP_PARAMETERS.items()),
                              *(f'-p {arg}' for arg in dds.RELIABLE_INPUTS
                                if '.durability:=' not in arg), *keep_outputs)
        wait_for_line(recorder, 'ready')  # the node's outputs are matched
        # As launch/replay_bag.launch.py runs it (its wait_for default: one word).
        player = start_player(bag, '--clock', '--qos-depth', '0',
                              '--wait-for-subscribers', '/joint_states /odom /base_pose')
        code, out, err = finish(player)
        assert code == 0, out + err
        recorded, rec_out, rec_err = finish(recorder)
        assert recorded == 0, rec_out + rec_err
        node_code, node_output = dds.stop(node)
    finally:
        for proc in (node, recorder, player):
            if proc is not None and proc.poll() is None:
                proc.kill()
    assert node_code == 0, node_output
    got = {name: [bytes.fromhex(h) for h in messages] for name, messages
           in json.loads((tmp_path / 'got.json').read_text()).items()}
    diagnostics = '/diagnostics'
    for name, (_, wanted) in expected.items():
        assert len(got[name]) == len(wanted), name
        for i, (mine, theirs) in enumerate(zip(got[name], wanted)):
            if mine != theirs and name == diagnostics:
                assert dds._differences(name, mine, theirs) == [], f'{name}[{i}]'
            else:  # every written byte; DDS may add up to 3 zero bytes of padding
                assert dds._same_payload(mine, theirs), f'{name}[{i}]'


# ------------------------------------------------------------------ paused start
def test_start_paused_plays_when_the_resume_service_is_called(tmp_path):
    """
    ``--start-paused``: nothing until ~/resume (std_srvs/Trigger); then the whole bag.

    Played under another name (``--remap``), as into a namespaced node.
    """
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from std_srvs.srv import Trigger
    sent = _bag_raw(DATA / 'paper_constant', '/joint_states')
    recorder = start_recorder(tmp_path / 'got.json',
                              [f'/sc1/joint_states:sensor_msgs/msg/JointState:{len(sent)}'])
    player = start_player(DATA / 'paper_constant', '--start-paused', '--rate', '20',
                          '--topics', '/joint_states', '--qos-depth', '0',
                          '--remap', '/joint_states:=/sc1/joint_states',
                          '--wait-for-subscribers', '/joint_states')
    context = rclpy.Context()
    rclpy.init(context=context)
    node = rclpy.create_node('test_resume', context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    try:
        wait_for_line(player, 'paused')  # after its writer matched the recorder's reader

        def call(name, attempts=30):
            """Return (attempt, success, message) of the first answered request."""
            client = node.create_client(Trigger, f'/reduced_dynamics_player/{name}')
            assert client.wait_for_service(timeout_sec=GUARD)
            for attempt in range(attempts):
                future = client.call_async(Trigger.Request())
                executor.spin_until_future_complete(future, timeout_sec=GUARD / attempts)
                if future.done():
                    return attempt, future.result().success, future.result().message
                client.remove_pending_request(future)
            raise AssertionError(f'no answer from ~/{name}')
        # A service's answer can be lost while its reply writer has not yet matched the
        # client (ROS 2 services over DDS), so a request unanswered is asked again: an
        # earlier one may have been served, with its answer lost.
        assert call('pause')[1:] == (False, 'already paused')
        attempt, *answer = call('resume')
        assert answer == [True, 'playing'] or attempt and answer == [False, 'already playing']
        code, out, err = finish(player)
        assert code == 0, out + err
        recorded, rec_out, rec_err = finish(recorder)
        assert recorded == 0, rec_out + rec_err
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=context)
        for proc in (player, recorder):
            if proc.poll() is None:
                proc.kill()
    got = [bytes.fromhex(h) for h in json.loads((tmp_path / 'got.json').read_text())
           ['/sc1/joint_states']]
    assert got == sent
