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
The ROS 2 processes of ``reduced-dynamics bench --sections node`` (real DDS).

``python -m reduced_dynamics.node_bench ROLE ...`` with ROLE one of

* ``relay``: the baseline, a bare rclpy node that republishes every joint state
  and odometry message it takes (sensor-data QoS in, reliable out, as the node);
* ``publish``: the input source, joint states and odometry at fixed rates, in
  phases, first the relay's input topics, then the node's; the
  header stamp of each message is its send time (system clock), so an output
  stamped with its input's stamp carries the send time with it;
* ``probe``: subscribes to the relay's and the node's outputs and records, per
  message, the stamp and the receive time;
* ``soak-publish`` and ``soak-probe``: the same for ``--sections soak``, one
  long window to the node alone; the probe keeps its records in a growing
  int64 array (16 B an output) and writes them as ``.npy``;
* ``callbacks``: the node in this process, without DDS in between: the publisher's
  messages (serialised) handed to its input callbacks at their real-time pace, each
  callback timed; prints the odometry callbacks' durations as JSON. An odometry sample
  releases the rows waiting for it, so its callback is the latency the node adds after
  the bracketing base sample, without the transport's share.

The orchestration (processes, statistics) is ROS-free, in
:func:`reduced_dynamics.bench.bench_node`. Besides the node shell this is the
only module importing rclpy, and only inside these roles.
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import time
from typing import Any, Optional, Sequence

import numpy as np

#: Input topics of the relay and the node (the node's defaults, relative names).
RELAY_INPUTS = ('relay_in/joint_states', 'relay_in/odom')
NODE_INPUTS = ('joint_states', 'odom')
#: Output topics the probe records: a relayed joint state, the node's momentum (one per
#: processed joint state, stamped with it).
RELAY_OUTPUT = '/relay/joint_states'
NODE_OUTPUT = '/reduced_dynamics/momentum'
PROBE_DEPTH = 100_000


def _rclpy() -> Any:
    import rclpy
    return rclpy


def relay(_args: argparse.Namespace) -> int:
    """Republish joint states and odometry unchanged (subscribe, republish)."""
    rclpy = _rclpy()
    from nav_msgs.msg import Odometry
    from rclpy.executors import ExternalShutdownException
    from rclpy.qos import qos_profile_sensor_data, QoSProfile
    from sensor_msgs.msg import JointState
    rclpy.init()
    node = rclpy.create_node('relay')
    out_qos = QoSProfile(depth=10)
    joints_out = node.create_publisher(JointState, '~/joint_states', out_qos)
    odom_out = node.create_publisher(Odometry, '~/odom', out_qos)
    node.create_subscription(JointState, RELAY_INPUTS[0], joints_out.publish,
                             qos_profile_sensor_data)
    node.create_subscription(Odometry, RELAY_INPUTS[1], odom_out.publish,
                             qos_profile_sensor_data)
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        rclpy.try_shutdown()
    return 0


def _probe_node(name: str) -> tuple[Any, Any, Any]:
    """
    Return (rclpy, node, QoS) of a probe: rclpy up without its signal handlers.

    The probe stops on SIGINT/SIGTERM itself (:func:`_spin_until_stopped`) and
    then writes its records; the QoS keeps every output (reliable, deep).
    """
    rclpy = _rclpy()
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
    rclpy.init(signal_handler_options=rclpy.signals.SignalHandlerOptions.NO)
    node = rclpy.create_node(name)
    qos = QoSProfile(depth=PROBE_DEPTH, history=HistoryPolicy.KEEP_LAST,
                     reliability=ReliabilityPolicy.RELIABLE)
    return rclpy, node, qos


def _spin_until_stopped(rclpy: Any, node: Any, topics: Sequence[str], ready: str) -> None:
    """Spin until SIGINT/SIGTERM; write the file ``ready`` once each topic has a publisher."""
    stop = []
    signal.signal(signal.SIGINT, lambda *_: stop.append(1))
    signal.signal(signal.SIGTERM, lambda *_: stop.append(1))
    announced = False
    while not stop:
        rclpy.spin_once(node, timeout_sec=0.05)
        if not announced and all(node.count_publishers(t) for t in topics):
            announced = True
            with open(ready, 'w', encoding='utf-8') as stream:
                stream.write('ready\n')


def probe(args: argparse.Namespace) -> int:
    """Record (stamp, receive time) of every output until SIGINT/SIGTERM; write JSON."""
    from geometry_msgs.msg import WrenchStamped
    from sensor_msgs.msg import JointState
    rclpy, node, qos = _probe_node('bench_probe')
    records: dict[str, list] = {RELAY_OUTPUT: [], NODE_OUTPUT: []}
    clock = time.time_ns

    def recorder(topic: str) -> Any:
        rows = records[topic]

        def record(msg: Any) -> None:
            stamp = msg.header.stamp
            rows.append((stamp.sec * 1_000_000_000 + stamp.nanosec, clock()))
        return record
    node.create_subscription(JointState, RELAY_OUTPUT, recorder(RELAY_OUTPUT), qos)
    node.create_subscription(WrenchStamped, NODE_OUTPUT, recorder(NODE_OUTPUT), qos)
    _spin_until_stopped(rclpy, node, list(records), args.ready)
    with open(args.out, 'w', encoding='utf-8') as stream:
        json.dump(records, stream)
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


class _Motion:
    """Joint positions and velocities of a smooth motion at time t (lists)."""

    def __init__(self, m: int, seed: int = 0) -> None:
        rng = np.random.default_rng(seed)
        self.amplitude = rng.uniform(0.1, 0.4, m)
        self.frequency = rng.uniform(0.5, 2.0, m)
        self.phase = rng.uniform(0.0, 2.0 * np.pi, m)

    def __call__(self, t: float) -> tuple[list, list]:
        angle = self.frequency * t + self.phase
        return ((self.amplitude * np.sin(angle)).tolist(),
                (self.amplitude * self.frequency * np.cos(angle)).tolist())


class _Inputs:
    """The joint state and odometry messages of the publishers, refilled per send."""

    def __init__(self, robot: Any) -> None:
        from nav_msgs.msg import Odometry
        from sensor_msgs.msg import JointState
        names = list(robot.shape_joint_names)
        self.motion = _Motion(len(names))
        self.joint = JointState()
        self.joint.name = names
        self.joint.effort = [0.0] * len(names)
        self.odom = Odometry()
        self.odom.header.frame_id = 'world'
        self.odom.child_frame_id = robot.base_link
        self.odom.twist.twist.linear.x = 0.01
        self.odom.twist.twist.angular.z = 0.05

    def joint_state(self, stamp: int, t: float) -> Any:
        """Return the joint state stamped ``stamp`` [ns] at motion time t."""
        msg = self.joint
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp, 1_000_000_000)
        msg.position, msg.velocity = self.motion(t)
        return msg

    def odometry(self, stamp: int, t: float) -> Any:
        """Return the odometry stamped ``stamp`` [ns] at motion time t."""
        msg = self.odom
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp, 1_000_000_000)
        msg.pose.pose.position.x = 0.01 * t
        msg.pose.pose.orientation.z = float(np.sin(0.025 * t))
        msg.pose.pose.orientation.w = float(np.cos(0.025 * t))
        return msg


def _await_subscribers(rclpy: Any, node: Any, publishers: Sequence[Any], timeout: float,
                       who: str) -> bool:
    """Spin until every publisher has a subscriber; False (and a message) after timeout s."""
    deadline = time.monotonic() + timeout
    while not all(p.get_subscription_count() for p in publishers):
        if time.monotonic() > deadline:
            print(f'{who}: no subscriber on the inputs', file=sys.stderr)
            return False
        rclpy.spin_once(node, timeout_sec=0.05)
    return True


def publish(args: argparse.Namespace) -> int:
    """Publish the phases; write the stamps sent in each phase's measured window."""
    rclpy = _rclpy()
    from nav_msgs.msg import Odometry
    from rclpy.qos import qos_profile_sensor_data
    from sensor_msgs.msg import JointState
    from reduced_dynamics.robot.model import load_robot
    robot = load_robot()
    rclpy.init()
    node = rclpy.create_node('bench_publisher')
    targets = {'relay': RELAY_INPUTS, 'node': NODE_INPUTS}
    publishers = {name: (node.create_publisher(JointState, topics[0], qos_profile_sensor_data),
                         node.create_publisher(Odometry, topics[1], qos_profile_sensor_data))
                  for name, topics in targets.items()}
    if not _await_subscribers(rclpy, node, [p for pair in publishers.values() for p in pair],
                              args.discovery_timeout, 'bench publisher'):
        return 1
    phase_seconds = args.warmup + args.seconds
    inputs = _Inputs(robot)
    phases = []
    clock = time.time_ns
    joint_rates = [float(r) for r in args.joint_rates.split(',')]
    # All relay windows, then all node windows: a target's input stream pauses only
    # args.pause between its windows (a longer pause would be a clock jump to the node's
    # stamp policy, stamp_outlier_tolerance 1 s). Motion time runs on per target.
    for name in ('relay', 'node'):
        joints_pub, odom_pub = publishers[name]
        motion_time = 0.0
        for joint_rate in joint_rates:
            base_rate = min(args.base_rate, joint_rate)
            for repeat in range(args.repeats):
                # One base sample more, at the window's end: the estimator processes a
                # joint state once a base sample at or after its stamp has come (every
                # base measurement up to it is then known); without it the joint states
                # after the last base sample of a window would wait for the next window.
                events = sorted([(k / joint_rate, 0) for k in
                                 range(int(phase_seconds * joint_rate))]
                                + [(k / base_rate, 1) for k in
                                   range(int(phase_seconds * base_rate) + 1)])
                sent: list[int] = []
                base_stamps: list[int] = []
                base_sent = 0
                start = time.monotonic()
                for offset, kind in events:
                    delay = start + offset - time.monotonic()
                    if delay > 0.0:
                        time.sleep(delay)
                    measured = offset >= args.warmup
                    stamp = clock()
                    t = motion_time + offset
                    if kind == 0:
                        joints_pub.publish(inputs.joint_state(stamp, t))
                        if measured:
                            sent.append(stamp)
                    else:
                        odom_pub.publish(inputs.odometry(stamp, t))
                        base_sent += measured
                        base_stamps.append(stamp)
                lateness = time.monotonic() - start - events[-1][0]
                motion_time += phase_seconds + args.pause
                phases.append({'repeat': repeat, 'target': name, 'joint_rate': joint_rate,
                               'base_rate': base_rate, 'joint_stamps': sent,
                               'base_sent': base_sent, 'base_stamps': base_stamps,
                               'seconds': args.seconds,
                               'late_at_end_s': lateness})
                time.sleep(args.pause)
    with open(args.out, 'w', encoding='utf-8') as stream:
        json.dump({'phases': phases}, stream)
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


def soak_probe(args: argparse.Namespace) -> int:
    """Record (stamp, receive time) of every ``~/momentum`` until SIGINT/SIGTERM; write .npy."""
    from geometry_msgs.msg import WrenchStamped
    rclpy, node, qos = _probe_node('soak_probe')
    rows = [np.zeros((1 << 16, 2), np.int64), 0]
    clock = time.time_ns

    def record(msg: Any) -> None:
        table, count = rows
        if count == len(table):
            rows[0] = table = np.concatenate([table, np.zeros_like(table)])
        stamp = msg.header.stamp
        table[count] = (stamp.sec * 1_000_000_000 + stamp.nanosec, clock())
        rows[1] = count + 1
    node.create_subscription(WrenchStamped, NODE_OUTPUT, record, qos)
    _spin_until_stopped(rclpy, node, [NODE_OUTPUT], args.ready)
    np.save(args.out, rows[0][:rows[1]])
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


def soak_publish(args: argparse.Namespace) -> int:
    """
    Publish joint states and odometry to the node for ``--seconds``; write what was sent.

    The stamps are send times (system clock). Odometry goes out 0.3 ms after the
    joint state it coincides with (two clocks, as in the node section). Writes
    JSON: start and end send time, joint states and odometry sent, and the
    largest lateness behind the schedule.
    """
    rclpy = _rclpy()
    from nav_msgs.msg import Odometry
    from rclpy.qos import qos_profile_sensor_data
    from sensor_msgs.msg import JointState
    from reduced_dynamics.consistent_motion import ConsistentMotion
    from reduced_dynamics.geometry.quaternion import matrix_to_xyzw
    from reduced_dynamics.robot.model import load_robot
    robot = load_robot()
    rclpy.init()
    node = rclpy.create_node('soak_publisher')
    joints_pub = node.create_publisher(JointState, NODE_INPUTS[0], qos_profile_sensor_data)
    odom_pub = node.create_publisher(Odometry, NODE_INPUTS[1], qos_profile_sensor_data)
    if not _await_subscribers(rclpy, node, (joints_pub, odom_pub), args.discovery_timeout,
                              'soak publisher'):
        return 1
    # No external wrench in the stream: predictions run at their rate (soak.soak_messages).
    motion = ConsistentMotion(robot)
    inputs = _Inputs(robot)
    joint_msg, odom_msg = inputs.joint, inputs.odom
    clock = time.time_ns
    joint_period = 1.0 / args.joint_rate
    base_every = max(1, round(args.joint_rate / args.base_rate))
    count = int(args.seconds * args.joint_rate)
    sent = {'joint_states': 0, 'odometry': 0, 'late_max_s': 0.0}
    start = time.monotonic()
    sent['start_ns'] = clock()
    for k in range(count + 1):
        offset = k * joint_period
        # This instant's sample: the joint state now, the odometry 0.3 ms later.
        (qbar, qbar_dot), pose, twist = motion.shape(motion.t), motion.pose, motion.twist6()
        for kind in ((0, 1) if k % base_every == 0 else (0,)):
            # The last round: one odometry message after the last joint state (the
            # estimator processes a joint state once a base sample at or after it came).
            if kind == 0 and k == count:
                continue
            at = offset + (0.0003 if kind else 0.0)
            delay = start + at - time.monotonic()
            if delay > 0.0:
                time.sleep(delay)
            else:
                sent['late_max_s'] = max(sent['late_max_s'], -delay)
            stamp = clock()
            if kind == 0:
                joint_msg.header.stamp.sec, joint_msg.header.stamp.nanosec = divmod(
                    stamp, 1_000_000_000)
                joint_msg.position, joint_msg.velocity = qbar.tolist(), qbar_dot.tolist()
                joints_pub.publish(joint_msg)
                sent['joint_states'] += 1
            else:
                odom_msg.header.stamp.sec, odom_msg.header.stamp.nanosec = divmod(
                    stamp, 1_000_000_000)
                base = odom_msg.pose.pose
                base.position.x, base.position.y, base.position.z = pose.translation.tolist()
                (base.orientation.x, base.orientation.y, base.orientation.z,
                 base.orientation.w) = matrix_to_xyzw(pose.rotation).tolist()
                velocity = odom_msg.twist.twist
                velocity.linear.x, velocity.linear.y, velocity.linear.z = twist[:3].tolist()
                velocity.angular.x, velocity.angular.y, velocity.angular.z = twist[3:].tolist()
                odom_pub.publish(odom_msg)
                sent['odometry'] += 1
        motion.advance(joint_period)
    sent['end_ns'] = clock()
    with open(args.out, 'w', encoding='utf-8') as stream:
        json.dump(sent, stream)
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


def callbacks(args: argparse.Namespace) -> int:
    """Time the node's odometry callbacks in-process (see the module docstring)."""
    rclpy = _rclpy()
    from rclpy.serialization import serialize_message
    from reduced_dynamics.node import ReducedDynamicsNode
    rclpy.init(args=['--ros-args', '-p', 'prediction_rate:=0.0', '-p',
                     f'smoothing_lag:={args.smoothing_lag}'])
    node = ReducedDynamicsNode()
    try:
        inputs = _Inputs(node._estimator.robot)
        joint_ns = int(round(1e9 / args.joint_rate))
        every = max(1, int(round(args.joint_rate / args.base_rate)))
        count = int(round((args.warmup + args.seconds) * args.joint_rate))
        first = int(round(args.warmup * args.joint_rate))
        stamp0 = time.time_ns()
        clock = time.perf_counter
        start = clock()
        durations = []
        for k in range(count):
            # Real-time pace: the node idles between messages, as over DDS (its worker
            # threads run then), and sleeps, not spins, while it waits.
            wait = start + k * joint_ns * 1e-9 - clock()
            if wait > 0.0:
                time.sleep(wait)
            stamp = stamp0 + k * joint_ns
            data = serialize_message(inputs.joint_state(stamp, k * joint_ns * 1e-9))
            node._on_joint_state(data, {'received_timestamp': stamp})
            if k % every == 0:
                # Odometry 0.3 ms after its joint state, as the publisher role sends it.
                data = serialize_message(inputs.odometry(stamp + 300_000,
                                                         k * joint_ns * 1e-9 + 3e-4))
                began = clock()
                node._on_odometry(data, {'received_timestamp': stamp + 300_000})
                if k >= first:
                    durations.append(clock() - began)
        node.wait_for_predictions()
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    json.dump({'odometry_callback_s': durations}, sys.stdout)
    return 0


def main(argv: Optional[Sequence[str]] = None) -> int:
    """Run one role (see the module docstring)."""
    parser = argparse.ArgumentParser(prog='python -m reduced_dynamics.node_bench')
    roles = parser.add_subparsers(dest='role', required=True)
    roles.add_parser('relay').set_defaults(func=relay)
    p = roles.add_parser('probe')
    p.add_argument('--out', required=True)
    p.add_argument('--ready', required=True)
    p.set_defaults(func=probe)
    p = roles.add_parser('publish')
    p.add_argument('--out', required=True)
    p.add_argument('--joint-rates', default='1000',
                   help='comma-separated joint-state rates [Hz], windows at each')
    p.add_argument('--base-rate', type=float, default=200.0,
                   help='odometry rate [Hz] (at most the joint-state rate)')
    p.add_argument('--seconds', type=float, default=3.0)
    p.add_argument('--warmup', type=float, default=1.0)
    p.add_argument('--pause', type=float, default=0.5)
    p.add_argument('--repeats', type=int, default=3)
    p.add_argument('--discovery-timeout', type=float, default=60.0)
    p.set_defaults(func=publish)
    p = roles.add_parser('soak-probe')
    p.add_argument('--out', required=True)
    p.add_argument('--ready', required=True)
    p.set_defaults(func=soak_probe)
    p = roles.add_parser('soak-publish')
    p.add_argument('--out', required=True)
    p.add_argument('--seconds', type=float, default=60.0)
    p.add_argument('--joint-rate', type=float, default=1000.0)
    p.add_argument('--base-rate', type=float, default=200.0)
    p.add_argument('--discovery-timeout', type=float, default=60.0)
    p.set_defaults(func=soak_publish)
    p = roles.add_parser('callbacks')
    p.add_argument('--seconds', type=float, default=4.0)
    p.add_argument('--warmup', type=float, default=2.0)
    p.add_argument('--joint-rate', type=float, default=1000.0)
    p.add_argument('--base-rate', type=float, default=200.0)
    p.add_argument('--smoothing-lag', type=float, default=0.5)
    p.set_defaults(func=callbacks)
    args = parser.parse_args(argv)
    return args.func(args)


if __name__ == '__main__':
    sys.exit(main())
