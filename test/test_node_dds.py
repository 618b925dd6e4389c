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
The node over real DDS: the installed executable as a process, a real rclpy client.

The executable is the colcon-installed ``lib/reduced_dynamics/reduced_dynamics_node``
(scripts/test.sh's ``.colcon/install`` when present, else a symlink install built
into a temporary workspace), run after ``source install/setup.bash``. Each test
module uses its own ROS domain (test/ros_harness.py), so parallel runs on one
machine do not mix.
"""

from collections import deque
import importlib.util
import os
from pathlib import Path
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

import rclpy  # noqa: E402  (after ros_harness set the domain)
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile  # noqa: E402
from rclpy.qos import ReliabilityPolicy  # noqa: E402

from reduced_dynamics.bag.reader import open_bag  # noqa: E402
from reduced_dynamics.messages import RclpyTypes  # noqa: E402
from reduced_dynamics.node import NODE_STATUS_NAME  # noqa: E402
from reduced_dynamics.resources import paper_robot_urdf  # noqa: E402
from reduced_dynamics.topics import active_topics, DIAGNOSTICS_TOPIC, resolved_name  # noqa: E402

REPO_ROOT = Path(__file__).resolve().parent.parent
PKG = 'reduced_dynamics'
DATA = REPO_ROOT / 'test' / 'data'
#: Transient local: the node's readers get what our writers sent before they matched them
#: (a volatile reader that matched late lost the start of a bag on a loaded machine).
RELIABLE_INPUTS = [
    f'qos_overrides./{topic}.subscription.{policy}:={value}'
    for topic in ('joint_states', 'odom', 'base_pose')
    for policy, value in (('reliability', 'reliable'), ('history', 'keep_all'),
                          ('durability', 'transient_local'))]
#: The shipped bags and the node parameters they need (replay gets the same): the
#: paper robot with Odometry (defaults; paper_spacecraft too: bit-equality does not need
#: the settings it was made for), the planar testbed with joints and poses only
#: (gravity in the plane's normal), the jointless free-flyer with mocap poses only.
BAGS = {
    'paper_constant': {},
    'paper_realistic': {},
    'paper_thruster': {},
    'paper_spacecraft': {},
    'planar_pose_only': {'urdf': 'robots/planar_testbed.urdf', 'base_joint': 'planar',
                         'gravity': [0.0, 0.0, -9.81], 'base_input': 'pose'},
    'freeflyer_realistic': {'urdf': 'robots/freeflyer.urdf', 'base_input': 'pose'},
    'freeflyer_testbed': {'urdf': 'robots/freeflyer.urdf', 'base_input': 'pose'},
}
#: Seconds a wait for a condition (the node up, an answer, a process's end) may take: it
#: bounds a hang only, the condition ends the wait. A loaded machine took 10-25 s to bring
#: the node up (issue 24.1), so no wait here is tight.
PATIENCE = 600
#: The stamp policy compares the receive times of one topic's messages (estimator/stamps.py):
#: a message whose transport took 1 s (stamp_outlier_tolerance) longer than the one before
#: is held as an outlier, and a loaded machine stalls a process that long (issue 24: a
#: node that published 280 of 281 outputs and waited for more input). Receive times are
#: the machine's, as a wall-time budget is: the equality tests tolerate an hour, in the
#: node and the replay alike. The replay's outputs of every bag in BAGS are byte for byte
#: those at the default tolerance (measured).
STAMP_PARAMETERS = {'stamp_outlier_tolerance': 3600.0}
#: Input topics and their types as the bags and the node's defaults name them.
INPUT_TYPES = {'/joint_states': 'sensor_msgs/msg/JointState',
               '/odom': 'nav_msgs/msg/Odometry',
               '/base_pose': 'geometry_msgs/msg/PoseStamped'}


#: Estimator diagnostics that count inputs taken so far when the status is made: DDS
#: gives two topics no common order (and an executor with both ready takes the first
#: subscription first), so these depend on how joint states and odometry interleaved
#: on arrival. Every other field and every other topic is compared bit for bit.
ORDER_DEPENDENT = {'received_joint_states', 'received_base', 'joint_state_rate_hz',
                   'base_rate_hz'}


@pytest.fixture(scope='module')
def install(tmp_path_factory):
    """Return the colcon install prefix holding this checkout's executables."""
    shared = REPO_ROOT / '.colcon' / 'install'
    if (shared / PKG / 'lib' / PKG / 'reduced_dynamics_lifecycle_node').exists():
        return shared
    if importlib.util.find_spec('colcon_core') is None:
        pytest.skip('colcon is not importable (scripts/test.sh installs it)')
    base = tmp_path_factory.mktemp('ws')
    env = dict(os.environ, COLCON_HOME=str(base / 'home'))
    build = subprocess.run(
        [sys.executable, '-m', 'colcon', '--log-base', str(base / 'log'), 'build',
         '--base-paths', str(REPO_ROOT), '--build-base', str(base / 'build'),
         '--install-base', str(base / 'install'), '--packages-select', PKG,
         '--symlink-install'], env=env, capture_output=True, text=True, timeout=300)
    assert build.returncode == 0, build.stdout + build.stderr
    return base / 'install'


def start_node(install, *ros_args, executable='reduced_dynamics_node'):
    """Start the installed executable (after sourcing setup.bash) in this module's domain."""
    args = ' '.join(ros_args)
    script = (f'set +u; source {install}/setup.bash; set -u\n'
              f'exec {install}/{PKG}/lib/{PKG}/{executable} --ros-args {args}')
    env = dict(os.environ, ROS_DOMAIN_ID=DOMAIN_ID, PYTHONUNBUFFERED='1')
    return subprocess.Popen(['bash', '-c', script], env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True)


def wait_until_up(client, topic='/joint_states', timeout=PATIENCE):
    """Wait until the node subscribes ``topic`` (it is then spinning)."""
    node, executor = client
    assert spin_until(executor, lambda: node.count_subscribers(topic) > 0, timeout), \
        'the node did not come up'


def stop(proc, sig=signal.SIGINT, timeout=PATIENCE):
    """Send ``sig``; return (exit code, stdout + stderr)."""
    proc.send_signal(sig)
    out, err = proc.communicate(timeout=timeout)
    return proc.returncode, out + err


def error_lines(output):
    """Return the lines that are errors or tracebacks."""
    return [line for line in output.splitlines()
            if 'Traceback' in line or '[ERROR]' in line or 'Error' in line
            or 'Failed' in line]


@pytest.fixture
def client():
    """Yield (node, executor) of a test client in its own context; spin with spin_until."""
    context = rclpy.Context()
    rclpy.init(context=context)
    node = rclpy.create_node('test_client', context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    yield node, executor
    executor.shutdown()
    node.destroy_node()
    rclpy.try_shutdown(context=context)


def spin_until(executor, condition, timeout):
    """Spin until ``condition()`` holds; return whether it did."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if condition():
            return True
        executor.spin_once(timeout_sec=0.05)
    return condition()


def spin_while_progress(executor, condition, progress, stall=PATIENCE / 10):
    """
    Spin until ``condition()`` holds, or ``progress()`` has not changed for ``stall`` s.

    A node that is slow (a loaded machine) keeps publishing and is waited for; one that
    lost a message stops publishing, and the wait ends a minute later, not ten.
    """
    end = time.monotonic() + PATIENCE
    last, changed = progress(), time.monotonic()
    while not condition() and time.monotonic() < end:
        executor.spin_once(timeout_sec=0.05)
        now = progress()
        if now != last:
            last, changed = now, time.monotonic()
        elif time.monotonic() - changed > stall:
            break


# ------------------------------------------------------------------ bags over DDS
@pytest.mark.parametrize('bag', list(BAGS))
def test_bag_played_over_dds_gives_replays_bytes(install, client, tmp_path, bag):
    """
    Every output the replay writes for the bag, bit for bit, from the running executable.

    Excluded: the node's own status on /diagnostics (name NODE_STATUS_NAME): it is
    published on the node clock with input and processed rates, which depend on the
    machine, and the replay has no node. Everything else is compared byte for byte.
    """
    _compare_bag_over_dds(install, client, tmp_path, bag)


#: The odometry message test_a_topic_delivered_late_gives_replays_bytes delays, and by how
#: much: Fast DDS's default heartbeat period, after which a reliable writer repairs a lost
#: sample; far beyond the 4 x sync_tolerance = 80 ms a joint state waits for its base pose.
LATE_INDEX, LATE_SECONDS = 40, 3.0


def test_a_topic_delivered_late_gives_replays_bytes(install, client, tmp_path):
    """
    One odometry message reaches the node 3 s late, the rest of its topic behind it.

    What DDS does on a loaded machine (a sample repaired at the writer's next heartbeat,
    a reader that matched its writer late; issue 24: 436 joint states rejected as
    stale_base_state): the joint states must not run ahead meanwhile. The stamp policy
    compares receive times of one topic's messages (a 3 s late one is an outlier at the
    default 1 s tolerance): STAMP_PARAMETERS.
    """
    _compare_bag_over_dds(install, client, tmp_path, 'paper_constant',
                          late=('/odom', LATE_INDEX, LATE_SECONDS))


def _compare_bag_over_dds(install, client, tmp_path, bag, late=None):
    """
    Feed ``bag`` to the installed node over DDS; assert its outputs are replay's.

    ``late``: (topic, index, seconds), that topic's message ``index`` delivered late
    (LateCourier).
    """
    import numpy as np
    from reduced_dynamics.params import defaults
    from reduced_dynamics.replay import replay, ReplayOptions
    from reduced_dynamics.resources import config_path
    from reduced_dynamics.robot.model import load_robot
    node, executor = client
    spec = BAGS[bag]
    urdf = str(config_path(spec['urdf'])) if 'urdf' in spec else paper_robot_urdf()
    params = defaults()
    # Bit equality with replay: no wall-time prediction budget (replay has none; a loaded
    # machine would drop predictions, issue 24.1).
    node_params = [f'urdf_path:={urdf}', 'prediction_max_wall_time:=0.0']
    spec = dict(spec, **STAMP_PARAMETERS)
    for name in ('base_joint', 'gravity', 'base_input', *STAMP_PARAMETERS):
        if name in spec:
            params[name] = spec[name]
            value = spec[name]
            if isinstance(value, list):  # a YAML list, no spaces: one shell word
                value = '[' + ','.join(str(v) for v in value) + ']'
            node_params.append(shlex.quote(f'{name}:={value}'))
    robot = load_robot(urdf, params['base_joint'], np.array(params['gravity'], dtype=float))
    pose_input = params['base_input'] == 'pose'
    replay(str(DATA / bag), str(tmp_path / 'out'), robot,
           ReplayOptions(params=params, base_pose_topic='/base_pose' if pose_input else None,
                         smooth=False))  # causal: what the node publishes
    expected = {}
    with open_bag(tmp_path / 'out') as reader:
        for topic in active_topics(False):
            name = resolved_name(topic)
            expected[name] = [bytes(m.data) for m in reader.raw_messages([name])]
    got = {name: [] for name in expected}
    status_name = NODE_STATUS_NAME.encode()

    def keep(name, data):
        if status_name not in data:  # the node's own status: see the docstring
            got[name].append(data)

    types = RclpyTypes()
    keep_all = QoSProfile(history=HistoryPolicy.KEEP_ALL, depth=1,
                          reliability=ReliabilityPolicy.RELIABLE,
                          durability=DurabilityPolicy.VOLATILE)
    # Inputs kept for a reader that matches late: no wait for the match (issue 24.1).
    kept_inputs = QoSProfile(history=HistoryPolicy.KEEP_ALL, depth=1,
                             reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
    for topic in active_topics(False):
        name = resolved_name(topic)
        node.create_subscription(types.get(topic.msgtype), name,
                                 lambda data, name=name: keep(name, data), keep_all, raw=True)
    with open_bag(DATA / bag) as reader:
        inputs = [t for t in INPUT_TYPES if t in reader.topics()]
    publishers = {t: node.create_publisher(types.get(INPUT_TYPES[t]), t, kept_inputs)
                  for t in inputs}
    marks = momentum_marks(DATA / bag, robot, params, inputs)
    momentum = resolved_name(next(t for t in active_topics(False) if t.name == 'momentum'))
    # Outputs kept whole too: a reliable KEEP_LAST writer may overwrite what a busy
    # reader has not acknowledged yet.
    keep_outputs = [f'-p qos_overrides.{name}.publisher.history:=keep_all' for name in expected]
    proc = start_node(install, *(f'-p {arg}' for arg in node_params + RELIABLE_INPUTS),
                      *keep_outputs)
    courier = None
    try:
        matched = spin_until(executor, lambda: all(
            p.get_subscription_count() for p in publishers.values()) and all(
            node.count_publishers(name) for name in expected), PATIENCE)
        assert matched, 'the node did not come up'
        send = {t: p.publish for t, p in publishers.items()}
        if late is not None:
            courier = LateCourier(publishers[late[0]].publish, *late[1:])
            send[late[0]] = courier.publish
        with open_bag(DATA / bag) as reader:
            stalled = feed_in_bag_order(executor, send, reader.raw_messages(inputs), marks,
                                        lambda: len(got[momentum]), proc)
        if stalled:
            code, output = stop(proc)
            raise AssertionError(f'{stalled} (exit {code}):\n{output[-3000:]}')
        spin_while_progress(
            executor, lambda: all(len(got[n]) >= len(expected[n]) for n in expected),
            lambda: sum(len(v) for v in got.values()))
        code, output = stop(proc)
    finally:
        if courier is not None:
            courier.close()
        if proc.poll() is None:
            proc.kill()
    assert code == 0, output
    diagnostics = resolved_name(next(t for t in active_topics(False)
                                     if t.name == DIAGNOSTICS_TOPIC))
    for name, wanted in expected.items():
        least = 0 if name.endswith('prediction/shape') else 1
        assert len(got[name]) == len(wanted) >= least, (name, output[-2000:])
        for i, (mine, theirs) in enumerate(zip(got[name], wanted)):
            if mine != theirs and name == diagnostics:
                assert _differences(name, mine, theirs) == [], f'{name}[{i}]'
            else:
                assert _same_payload(mine, theirs), f'{name}[{i}]'


def momentum_marks(bag, robot, params, inputs):
    """
    Return, per input message of ``bag``, the momentum outputs due once the node has taken it.

    The node's estimator fed one message at a time, in the bag's order, as the node
    feeds it (the replay's estimator, streaming): each output carries one momentum.
    """
    from reduced_dynamics.estimator import Estimator, EstimatorConfig
    from reduced_dynamics.messages.samples import JointStateSample, with_receive_time
    from reduced_dynamics.replay import input_decoder
    config = EstimatorConfig.from_mapping(params).replaced(prediction_max_wall_time=0.0)
    estimator = Estimator(robot, config, use_odometry='/odom' in inputs,
                          base_driven='/joint_states' not in inputs or robot.m == 0)
    marks, due = [], 0
    with open_bag(bag) as reader:
        decoders = {topic: input_decoder(reader, topic, msgtype, robot.base_link)
                    for topic, msgtype in reader.connection_types(inputs)}
        for message in reader.raw_messages(inputs):
            sample = with_receive_time(decoders[message.topic](message.data),
                                       message.timestamp_ns)
            take = estimator.add_joint_state if isinstance(sample, JointStateSample) \
                else estimator.add_base_state
            due += len(take(sample))
            marks.append(due)
    return marks


def feed_in_bag_order(executor, send, messages, marks, published, proc):
    """
    Publish a bag's input messages so that the node takes them in the bag's order.

    DDS orders the messages of one writer, never those of two: a node that got one
    topic's messages late (a sample repaired at the next heartbeat, a reader that matched
    late: a loaded machine) took the other topic's far ahead, and rejected joint states
    as stale_base_state that the replay used (issue 24). So before the first message of
    a run of one topic, the node must have published the momentum outputs (``marks``,
    ``published()``) that every message before it produces: no topic gets ahead of the
    other by more than the bag's own interleaving. One topic alone needs no wait. No
    sleep: every wait ends on its condition; PATIENCE bounds a hang only. Return None,
    or why the feed stopped.
    """
    previous, due = None, 0
    for message, mark in zip(messages, marks):
        if previous is not None and message.topic != previous:
            done = spin_until(executor, lambda: published() >= due or proc.poll() is not None,
                              PATIENCE)
            if not done or proc.poll() is not None:
                return f'the node published {published()} of the {due} momentum outputs due'
        send[message.topic](bytes(message.data))
        # Paced: the outputs are read as they come (the test's reader keeps all).
        executor.spin_once(timeout_sec=0.002)
        previous, due = message.topic, mark
    return None


class LateCourier:
    """
    Deliver one message ``delay`` seconds late, and the messages after it behind it.

    As DDS delivers a reliable topic whose sample was lost: the reader gives the
    repaired sample, then the ones held after it, in order.
    """

    def __init__(self, publish, index, delay):
        """Publish through ``publish``; hold message number ``index`` for ``delay`` s."""
        self._publish, self._index, self._delay = publish, index, delay
        self._queue = deque()
        self._count = 0
        self._ready = threading.Condition()
        self._closed = False
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def publish(self, data):
        """Queue ``data``; it goes when it is due and everything before it went."""
        with self._ready:
            due = time.monotonic() + (self._delay if self._count == self._index else 0.0)
            self._count += 1
            self._queue.append((due, data))
            self._ready.notify()

    def _run(self):
        with self._ready:
            while not self._closed:
                if not self._queue:
                    self._ready.wait()
                    continue
                due, data = self._queue[0]
                wait = due - time.monotonic()
                if wait > 0:
                    self._ready.wait(wait)
                    continue
                self._queue.popleft()
                self._publish(data)

    def close(self):
        """Stop delivering."""
        with self._ready:
            self._closed = True
            self._ready.notify()
        self._thread.join()


def _same_payload(received, written):
    """
    Tell whether DDS delivered the written CDR bytes, up to the transport's padding.

    RTPS carries a serialized payload padded to a multiple of 4 bytes: a message whose
    CDR ends unaligned (a MarkerArray ends with a bool) arrives with up to 3 zero bytes
    more. Every byte written is compared.
    """
    extra = len(received) - len(written)
    return received == written or (0 < extra < 4 and len(received) % 4 == 0
                                   and received.startswith(written)
                                   and not any(received[len(written):]))


def _differences(name, mine, theirs):
    """Describe how two CDR messages differ (diagnostics: by key)."""
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.serialization import deserialize_message
    if not name.endswith('diagnostics'):
        return 'bytes differ'
    a, b = (deserialize_message(d, DiagnosticArray) for d in (mine, theirs))
    diffs = []
    if [st.name for st in a.status] != [st.name for st in b.status]:
        diffs.append(('statuses', [st.name for st in a.status], [st.name for st in b.status]))
    for sa, sb in zip(a.status, b.status):
        va = {kv.key: kv.value for kv in sa.values}
        vb = {kv.key: kv.value for kv in sb.values}
        diffs += [(sa.name, k, va.get(k), vb.get(k)) for k in sorted(set(va) | set(vb))
                  if va.get(k) != vb.get(k) and k not in ORDER_DEPENDENT]
        for field in ('message', 'level', 'hardware_id'):
            if getattr(sa, field) != getattr(sb, field):
                diffs.append((sa.name, field, getattr(sa, field), getattr(sb, field)))
    if a.header != b.header:
        diffs.append(('header', a.header, b.header))
    return diffs


# ------------------------------------------------------------------ shutdown
def _stream_joint_states(node, executor, seconds, rate=1000.0):
    """Publish joint states at ``rate`` for ``seconds`` (best effort, as sensors do)."""
    from rclpy.qos import qos_profile_sensor_data
    from sensor_msgs.msg import JointState
    publisher = node.create_publisher(JointState, '/joint_states', qos_profile_sensor_data)
    names = ['j2_x', 'j2_y', 'j2_z', 'j3', 'j4', 'j5']
    msg = JointState(name=names, position=[0.1] * 6, velocity=[0.0] * 6, effort=[0.0] * 6)
    period = 1.0 / rate
    start = next_time = time.monotonic()
    sent = 0
    while time.monotonic() - start < seconds:
        now_ns = time.time_ns()
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(now_ns, 1_000_000_000)
        publisher.publish(msg)
        sent += 1
        next_time += period
        delay = next_time - time.monotonic()
        if delay > 0:
            time.sleep(delay)
    node.destroy_publisher(publisher)
    return sent


@pytest.mark.slow
def test_ten_sigints_under_a_1khz_stream_all_exit_0(install, client):
    """Issue 14.5: 10 SIGINTs while 1 kHz joint states flow: 10 exits 0, no error line."""
    # Each run is a node start-up (most of its time); issue 14 ran 20. The exit 1 one
    # time in four it fixed is missed by 10 runs with probability 0.75 ** 10 = 6 %.
    node, executor = client
    results = []
    for run in range(10):
        proc = start_node(install, '-p', f'urdf_path:={paper_robot_urdf()}')
        try:
            wait_until_up(client)
            # The signal lands while the stream flows, at a phase varied over the runs
            # (0.2 s to 0.56 s into it, as the 20 runs had).
            timer = threading.Timer(0.2 + 0.04 * run, proc.send_signal, (signal.SIGINT,))
            timer.start()
            _stream_joint_states(node, executor, 0.8)
            timer.join()
            out, err = proc.communicate(timeout=PATIENCE)
            code, output = proc.returncode, out + err
        finally:
            if proc.poll() is None:
                proc.kill()
        results.append((code, error_lines(output)))
    assert results == [(0, [])] * 10


def test_sigterm_while_messages_flow_exits_0(install, client):
    node, executor = client
    proc = start_node(install, '-p', f'urdf_path:={paper_robot_urdf()}')
    try:
        wait_until_up(client)
        _stream_joint_states(node, executor, 0.5)
        code, output = stop(proc, signal.SIGTERM)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert code == 0 and error_lines(output) == [], output
    assert 'processed' in output  # the summary line made it out while the context lived


#: Seconds a service call may stay unanswered before it is sent again. A client's
#: ``service_is_ready`` says its requests reach the server, not that the server's
#: answers reach the client yet (DDS matches the two topics apart): a call made in
#: between is answered into the void, and waiting PATIENCE for it hung CI 10 minutes
#: (twice in one run, stop 24). A late first answer is still taken.
RESEND_AFTER = 15.0


def answer(executor, client_, request, proc, settled=None):
    """
    Return the service's answer to ``request``, sent again while unanswered.

    ``settled()`` (a transition's goal state reached, asked by the caller) tells a
    request the server carried out whose answer was lost: then the return is None, and
    the request is not sent again (a transition is not idempotent).
    """
    futures = []
    end = time.monotonic() + PATIENCE
    while time.monotonic() < end:
        futures.append(client_.call_async(request))
        spin_until(executor, lambda: any(f.done() for f in futures)
                   or proc.poll() is not None, RESEND_AFTER)
        done = [f for f in futures if f.done()]
        if done:
            return done[0].result()
        assert proc.poll() is None, 'no answer: the node died'
        if settled is not None and settled():
            return None
    raise AssertionError(f'no answer to {type(request).__name__} in {PATIENCE} s')


class LifecycleClient:
    """The node's get_state and change_state services, answered despite lost answers."""

    def __init__(self, client, proc):
        """Create both clients on the test client's node; wait until both are ready."""
        from lifecycle_msgs.srv import ChangeState, GetState
        self._node, self._executor = client
        self._proc = proc
        self._get = self._node.create_client(GetState, '/reduced_dynamics/get_state')
        self._change = self._node.create_client(ChangeState,
                                                '/reduced_dynamics/change_state')
        assert spin_until(self._executor, lambda: self._get.service_is_ready()
                          and self._change.service_is_ready(), PATIENCE)

    def state(self):
        """Return the node's lifecycle state id."""
        from lifecycle_msgs.srv import GetState
        return answer(self._executor, self._get, GetState.Request(),
                      self._proc).current_state.id

    def transition(self, transition_id, goal=None):
        """Return whether the node took it (``goal``: the state it ends in)."""
        from lifecycle_msgs.msg import Transition
        from lifecycle_msgs.srv import ChangeState
        settled = None if goal is None else (lambda: self.state() == goal)
        result = answer(self._executor, self._change,
                        ChangeState.Request(transition=Transition(id=transition_id)),
                        self._proc, settled)
        return True if result is None else result.success


# ------------------------------------------------------------------ lifecycle
def test_lifecycle_transitions_through_the_real_services(install, client):
    from lifecycle_msgs.msg import State, Transition
    node, executor = client
    proc = start_node(install, '-p', f'urdf_path:={paper_robot_urdf()}',
                      executable='reduced_dynamics_lifecycle_node')
    try:
        lifecycle = LifecycleClient(client, proc)
        state = lifecycle.state

        def transition(transition_id, goal):
            return lifecycle.transition(transition_id, goal)

        assert state() == State.PRIMARY_STATE_UNCONFIGURED
        assert node.count_subscribers('/joint_states') == 0
        assert transition(Transition.TRANSITION_CONFIGURE, State.PRIMARY_STATE_INACTIVE)
        assert state() == State.PRIMARY_STATE_INACTIVE
        assert transition(Transition.TRANSITION_ACTIVATE, State.PRIMARY_STATE_ACTIVE)
        assert state() == State.PRIMARY_STATE_ACTIVE
        assert spin_until(executor, lambda: node.count_subscribers('/joint_states') == 1,
                          PATIENCE)
        assert spin_until(executor,
                          lambda: node.count_publishers('/reduced_dynamics/momentum') == 1,
                          PATIENCE)
        assert transition(Transition.TRANSITION_DEACTIVATE, State.PRIMARY_STATE_INACTIVE)
        assert state() == State.PRIMARY_STATE_INACTIVE
        assert spin_until(executor, lambda: node.count_subscribers('/joint_states') == 0,
                          PATIENCE)
        assert transition(Transition.TRANSITION_CLEANUP, State.PRIMARY_STATE_UNCONFIGURED)
        assert state() == State.PRIMARY_STATE_UNCONFIGURED
        assert transition(Transition.TRANSITION_UNCONFIGURED_SHUTDOWN,
                          State.PRIMARY_STATE_FINALIZED)
        assert state() == State.PRIMARY_STATE_FINALIZED
        code, output = stop(proc)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert code == 0 and error_lines(output) == [], output


def test_lifecycle_configure_fails_on_an_unusable_model(install, client):
    from lifecycle_msgs.msg import State, Transition
    proc = start_node(install, '-p', 'urdf_path:=/nonexistent/robot.urdf',
                      executable='reduced_dynamics_lifecycle_node')
    try:
        lifecycle = LifecycleClient(client, proc)
        # A failed configure leaves the node unconfigured: sent again, it fails again.
        assert not lifecycle.transition(Transition.TRANSITION_CONFIGURE)
        assert lifecycle.state() == State.PRIMARY_STATE_UNCONFIGURED
        code, output = stop(proc)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert code == 0
    assert 'URDF file not found' in output


# ------------------------------------------------------------------ issue 21: start-up seams
def run_executable(install, *args, executable='reduced_dynamics_node', timeout=PATIENCE):
    """Run the installed executable with ``args`` to its end; return the CompletedProcess."""
    script = (f'set +u; source {install}/setup.bash; set -u\n'
              f'exec {install}/{PKG}/lib/{PKG}/{executable} '
              + ' '.join(shlex.quote(arg) for arg in args))
    env = dict(os.environ, ROS_DOMAIN_ID=DOMAIN_ID, PYTHONUNBUFFERED='1')
    return subprocess.run(['bash', '-c', script], env=env, capture_output=True, text=True,
                          timeout=timeout)


@pytest.mark.parametrize('executable', ['reduced_dynamics_node',
                                        'reduced_dynamics_lifecycle_node'])
def test_help_prints_usage_and_exits_0(install, executable):
    """Issue 21.6: --help does not start the node."""
    proc = run_executable(install, '--help', executable=executable)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.startswith(f'usage: {executable}')
    assert 'prediction_rate (default: 1.0' in proc.stdout and '~/momentum' in proc.stdout


def test_bad_qos_override_exits_2_with_one_line(install):
    """Issue 21.5: as a bad parameter does."""
    proc = run_executable(install, '--ros-args', '-p',
                          'qos_overrides./joint_states.subscription.reliability:=bogus')
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.strip().splitlines() == [
        'reduced_dynamics_node: invalid QoS override: qos_overrides./joint_states.subscription.'
        "reliability is 'bogus', must be one of: reliable, best_effort, best_available, "
        'system_default']


def test_invalid_lifecycle_transition_is_refused_and_the_node_stays(install, client):
    """Issue 21.4: `ros2 lifecycle set /reduced_dynamics activate` while unconfigured."""
    from lifecycle_msgs.msg import State, Transition
    proc = start_node(install, '-p', f'urdf_path:={paper_robot_urdf()}',
                      executable='reduced_dynamics_lifecycle_node')
    try:
        lifecycle = LifecycleClient(client, proc)
        # Refused, the node stays unconfigured: a refusal sent again is refused again.
        assert not lifecycle.transition(Transition.TRANSITION_ACTIVATE)
        assert not lifecycle.transition(Transition.TRANSITION_DEACTIVATE)
        assert lifecycle.state() == State.PRIMARY_STATE_UNCONFIGURED
        assert lifecycle.transition(Transition.TRANSITION_CONFIGURE,
                                    State.PRIMARY_STATE_INACTIVE)
        assert lifecycle.transition(Transition.TRANSITION_ACTIVATE, State.PRIMARY_STATE_ACTIVE)
        assert proc.poll() is None
        code, output = stop(proc)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert code == 0 and 'Traceback' not in output, output
    assert 'refused in state unconfigured' in output
