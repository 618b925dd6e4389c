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
``reduced-dynamics play BAG``: publish a bag over DDS with rclpy, as ``ros2 bag play``.

The second ROS shell of the package (the node, :mod:`reduced_dynamics.node`, is the
first): rosbag2 has no PyPI wheels, so a user with the rclpy wheels but no ros2cli
plays bags with this. What to publish and when is ROS-free
(:mod:`reduced_dynamics.bag.playback`); this module only creates the publishers,
the ``/clock`` timer, the ``~/pause`` / ``~/resume`` services, and publishes. rclpy
is imported inside :func:`run` only, so ``reduced-dynamics play --help`` is cheap.
The raw CDR of each message is published as it is (rclpy publishes bytes); only
``--restamp`` deserializes, to move the header stamps.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import signal
import sys
import threading
import time
from typing import Any, Optional

from reduced_dynamics.bag.errors import BagError
from reduced_dynamics.bag.playback import (
    clock_time_ns, DEFAULT_CLOCK_HZ, DEFAULT_QOS_DEPTH, definition_problems, NS_PER_S,
    parse_remap, play_messages, PlaybackClock, PlayOptions, played_topics, restamp_offset_ns,
    shift_stamps)
from reduced_dynamics.bag.reader import open_bag, RawBagMessage

PROG = 'reduced-dynamics play'
NODE_NAME = 'reduced_dynamics_player'
CLOCK_TOPIC = '/clock'
NO_RCLPY = (f'{PROG}: rclpy is not importable; source /opt/ros/jazzy/setup.bash, or '
            'install the rclpy wheels: pip install ".[ros]"')
#: Seconds the end of playback waits for the subscribers' acknowledgements (a guard).
ACK_TIMEOUT = 30.0


def register_command(commands: Any) -> None:
    """Add the ``play`` subcommand."""
    parser = commands.add_parser(
        'play', help='publish a bag over DDS with rclpy, as ros2 bag play does',
        description='Publish the messages of a rosbag2 bag (MCAP or sqlite3) at their '
                    'recorded times, as "ros2 bag play" does, without ros2cli (docs/play.md).')
    parser.add_argument('bag', help='rosbag2 directory, .mcap or .db3 file')
    parser.add_argument('-r', '--rate', type=float, default=1.0,
                        help='playback rate: 2 plays twice as fast (default 1)')
    parser.add_argument('--topics', nargs='+', default=[], metavar='TOPIC',
                        help='play only these topics (default: all)')
    parser.add_argument('-l', '--loop', action='store_true', help='play again when done')
    parser.add_argument('--clock', type=float, nargs='?', const=DEFAULT_CLOCK_HZ, default=0.0,
                        metavar='HZ', help='publish /clock (rosgraph_msgs/Clock) for '
                                           f'use_sim_time, at HZ (default {DEFAULT_CLOCK_HZ:g})')
    parser.add_argument('--restamp', action='store_true',
                        help='move every header stamp by (now - bag start): stamps of now, '
                             'their spacing kept (default: stamps as recorded)')
    parser.add_argument('--start-paused', action='store_true',
                        help='wait for Enter (on a terminal) or the ~/resume service '
                             '(std_srvs/Trigger) before playing')
    parser.add_argument('--wait-for-subscribers', nargs='+', default=[], metavar='TOPIC',
                        help='start only when each of these topics has a subscriber (e.g. '
                             'the node\'s inputs; topics not in the bag are not waited for)')
    parser.add_argument('--wait-timeout', type=float, default=0.0, metavar='S',
                        help='give up waiting for subscribers after S seconds (exit 1; '
                             'default 0: wait for ever)')
    parser.add_argument('--ack-timeout', type=float, default=ACK_TIMEOUT, metavar='S',
                        help='at the end, wait at most S seconds for every reliable '
                             'subscriber to acknowledge what was published (0: for ever; '
                             f'default {ACK_TIMEOUT:g}; a starved subscriber may need more)')
    parser.add_argument('--qos-depth', type=int, default=DEFAULT_QOS_DEPTH,
                        help='history depth of the reliable publishers, 0: keep all '
                             f'(default {DEFAULT_QOS_DEPTH})')
    parser.add_argument('--remap', nargs='+', default=[], metavar='FROM:=TO', type=_remap,
                        help='publish bag topic FROM as TO (e.g. into a namespace)')
    parser.set_defaults(func=_run)


def _remap(text: str) -> tuple[str, str]:
    try:
        return parse_remap(text)
    except ValueError as error:
        raise argparse.ArgumentTypeError(str(error)) from None


def _names(values: list[str]) -> tuple[str, ...]:
    """Split topic lists given as one word each or as one 'a b' / 'a,b' word (launch)."""
    return tuple(n for v in values for n in v.replace(',', ' ').split())


def options_from_args(args: argparse.Namespace) -> PlayOptions:
    """Return the PlayOptions of parsed arguments."""
    return PlayOptions(
        bag=args.bag, rate=args.rate, topics=_names(args.topics), loop=args.loop,
        start_paused=args.start_paused, clock_hz=args.clock, restamp=args.restamp,
        wait_for_subscribers=_names(args.wait_for_subscribers), qos_depth=args.qos_depth,
        wait_timeout=args.wait_timeout, ack_timeout=args.ack_timeout,
        remap=tuple(getattr(args, 'remap', ())))


class _StopOnSignal:
    """SIGINT / SIGTERM end playback cleanly; installed first, so at any moment of start-up."""

    def __init__(self) -> None:
        self.stopped = False
        self.clock: Optional[PlaybackClock] = None
        self._previous = {sig: signal.signal(sig, self._on_signal)
                          for sig in (signal.SIGINT, signal.SIGTERM)}

    def _on_signal(self, _signum: int, _frame: Any) -> None:
        self.stopped = True
        if self.clock is not None:
            self.clock.stop()

    def watch(self, clock: PlaybackClock) -> None:
        """Stop ``clock`` at a signal (at once if one came already)."""
        self.clock = clock
        if self.stopped:
            clock.stop()

    def restore(self) -> None:
        """Put the previous handlers back."""
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)


def _run(args: argparse.Namespace) -> int:
    stopper = _StopOnSignal()
    try:
        return _checked_run(args, stopper)
    finally:
        stopper.restore()


def _checked_run(args: argparse.Namespace, stopper: _StopOnSignal) -> int:
    options = options_from_args(args)
    problems = options.problems()
    try:
        with open_bag(options.bag) as reader:  # bad bag or topics: one line, before rclpy
            topics = played_topics(reader, options)
            start_ns = reader.start_ns
            latched = reader.latched_topics()
            refused = definition_problems(reader, topics)
    except (BagError, ValueError) as error:
        problems.append(str(error))
        topics, start_ns, latched, refused = {}, 0, set(), {}
    if problems:
        for problem in problems:
            print(f'{PROG}: error: {problem}', file=sys.stderr)
        return 2
    unplayed = [t for t in options.wait_for_subscribers if t not in topics]
    if unplayed:  # nothing is published there, so nothing waits for them (launch defaults)
        print(f'{PROG}: not waiting for {", ".join(unplayed)}: not played from this bag',
              flush=True)
        options = dataclasses.replace(options, wait_for_subscribers=tuple(
            t for t in options.wait_for_subscribers if t in topics))
    if stopper.stopped:
        return 0
    return run(options, topics, start_ns, latched, refused, stopper)


class _Shell:
    """The rclpy side: node, publishers, /clock, services, executor thread."""

    def __init__(self, rclpy: Any, options: PlayOptions, topics: dict[str, str],
                 latched: set[str], refused: dict[str, str], clock: PlaybackClock) -> None:
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import (DurabilityPolicy, HistoryPolicy, QoSProfile,
                               ReliabilityPolicy)
        from rclpy.serialization import deserialize_message

        from reduced_dynamics.messages.types import RclpyTypes
        self.rclpy, self.options, self.clock = rclpy, options, clock
        self._deserialize = deserialize_message
        self.node = rclpy.create_node(NODE_NAME)
        self.offset_ns = 0
        self._pass_start: Optional[int] = None
        self.failed: dict[str, int] = {}
        types = RclpyTypes()
        self.topics = dict(topics)
        self.publishers: dict[str, Any] = {}
        self.classes: dict[str, type] = {}
        for topic, msgtype in topics.items():
            if topic in refused:
                print(f'{PROG}: skipping {topic}: {refused[topic]}', file=sys.stderr)
                continue
            try:
                cls = types.get(msgtype)
            except LookupError as error:
                print(f'{PROG}: skipping {topic}: message type {msgtype} is not installed '
                      f'({error})', file=sys.stderr)
                continue
            if topic in latched:
                qos = QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST,
                                 reliability=ReliabilityPolicy.RELIABLE,
                                 durability=DurabilityPolicy.TRANSIENT_LOCAL)
            elif options.qos_depth == 0:
                qos = QoSProfile(depth=1, history=HistoryPolicy.KEEP_ALL,
                                 reliability=ReliabilityPolicy.RELIABLE)
            else:
                qos = QoSProfile(depth=options.qos_depth, history=HistoryPolicy.KEEP_LAST,
                                 reliability=ReliabilityPolicy.RELIABLE)
            self.publishers[topic] = self.node.create_publisher(
                cls, options.published_name(topic), qos)
            self.classes[topic] = cls
        self._clock_publisher = None
        if options.clock_hz > 0:
            from rosgraph_msgs.msg import Clock
            self._clock_msg = Clock()
            # rclcpp's ClockQoS, as ros2 bag play: the newest time is what matters.
            self._clock_publisher = self.node.create_publisher(
                Clock, CLOCK_TOPIC, QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST,
                                               reliability=ReliabilityPolicy.BEST_EFFORT))
            self.node.create_timer(1.0 / options.clock_hz, self.publish_clock)
        from std_srvs.srv import Trigger
        self.node.create_service(Trigger, '~/pause', self._on_pause)
        self.node.create_service(Trigger, '~/resume', self._on_resume)
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(self.node)
        self._thread = threading.Thread(target=self._spin, name='player-executor', daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        from rclpy.executors import ExternalShutdownException
        try:
            self.executor.spin()
        except (ExternalShutdownException, KeyboardInterrupt):
            pass

    def _on_pause(self, _request: Any, response: Any) -> Any:
        response.success = self.clock.pause()
        response.message = 'paused' if response.success else 'already paused'
        return response

    def _on_resume(self, _request: Any, response: Any) -> Any:
        response.success = self.clock.resume()
        response.message = 'playing' if response.success else 'already playing'
        return response

    def publish_clock(self) -> None:
        """Publish the bag time (moved like the stamps when restamping) on /clock."""
        sec, nanosec = divmod(clock_time_ns(self.clock, self.offset_ns), NS_PER_S)
        self._clock_msg.clock.sec, self._clock_msg.clock.nanosec = sec, nanosec
        self._clock_publisher.publish(self._clock_msg)

    def start_pass(self, _index: int, start_ns: int) -> None:
        """Move the restamp offset at the pass's first message: each pass starts at now."""
        self._pass_start = start_ns

    def publish(self, message: RawBagMessage, _index: int) -> bool:
        """Publish one bag message; False when its topic is skipped or it cannot be moved."""
        publisher = self.publishers.get(message.topic)
        if publisher is None:
            return False
        if not self.options.restamp:
            return self._publish(publisher, message.topic, bytes(message.data))
        if self._pass_start is not None:  # the first message of a pass: playing now
            self.offset_ns = restamp_offset_ns(self.clock, self._pass_start, time.time_ns())
            self._pass_start = None
        try:
            msg = self._deserialize(bytes(message.data), self.classes[message.topic])
            shift_stamps(msg, self.offset_ns)
        except Exception as error:  # a message that does not deserialize or shift
            self._fail(message.topic, f'cannot restamp: {error}')
            return False
        return self._publish(publisher, message.topic, msg)

    def _publish(self, publisher: Any, topic: str, message: Any) -> bool:
        try:
            publisher.publish(message)
        except Exception as error:  # rclpy's RCLError (e.g. a full keep-all history)
            self._fail(topic, f'cannot publish: {error}')
            return False
        return True

    def _fail(self, topic: str, reason: str) -> None:
        """Say once per topic why its messages are skipped (the summary counts them)."""
        if topic not in self.failed:
            print(f'{PROG}: skipping messages of {topic}: {reason}'.replace('\n', ' '),
                  file=sys.stderr, flush=True)
        self.failed[topic] = self.failed.get(topic, 0) + 1

    def wait_for_subscribers(self, topics: tuple[str, ...], timeout: float) -> bool:
        """Wait until each topic's publisher is matched by a subscription (False: timed out)."""
        waited = [self.publishers[t] for t in topics if t in self.publishers]
        end = None if timeout <= 0 else time.monotonic() + timeout
        while not all(p.get_subscription_count() for p in waited):
            if self.clock.stopped or (end is not None and time.monotonic() >= end):
                return False
            time.sleep(0.02)  # graph polling: rmw gives no matched-event wait from Python
        return True

    def wait_for_acknowledgements(self, timeout: float) -> bool:
        """
        Wait until every reliable subscriber has acknowledged what was published.

        At most ``timeout`` seconds (0: for ever): at a load of 15-18 a recorder of 6 569
        messages played at rate 200 had not acknowledged them all after 30 s (issue 24).
        """
        from rclpy.duration import Duration
        end = math.inf if timeout <= 0 else time.monotonic() + timeout
        # In slices: a signal is handled between them (the wait itself is in C).
        step = Duration(nanoseconds=100_000_000)
        for publisher in self.publishers.values():
            while not publisher.wait_for_all_acked(step):
                if self.clock.stopped or time.monotonic() >= end:
                    return False
        return True

    def close(self) -> None:
        """Stop the executor and destroy the node."""
        self.executor.shutdown(timeout_sec=1.0)
        self._thread.join(timeout=5.0)
        self.node.destroy_node()


def _resume_on_enter(clock: PlaybackClock) -> None:
    """Resume playback when Enter is pressed (a daemon thread reading a terminal)."""
    def read() -> None:
        try:
            sys.stdin.readline()
        except (OSError, ValueError):
            return
        clock.resume()
    threading.Thread(target=read, name='player-enter', daemon=True).start()


def run(options: PlayOptions, topics: dict[str, str], start_ns: int,
        latched: Optional[set[str]] = None, refused: Optional[dict[str, str]] = None,
        stopper: Optional[_StopOnSignal] = None) -> int:
    """Publish the bag until it ends (or Ctrl-C / SIGTERM); return the exit code."""
    own_stopper = stopper is None
    stopper = _StopOnSignal() if stopper is None else stopper
    clock = PlaybackClock(start_ns, options.rate, paused=True)
    stopper.watch(clock)
    try:
        try:
            import rclpy
            from rclpy.signals import SignalHandlerOptions
        except ImportError:
            print(NO_RCLPY, file=sys.stderr)
            return 1
        if clock.stopped:  # a signal while rclpy loaded
            return 0
        # No command-line arguments for rcl: it would take FROM:=TO words as remaps.
        rclpy.init(args=[PROG], signal_handler_options=SignalHandlerOptions.NO)
        shell = None
        try:
            shell = _Shell(rclpy, options, topics, latched or set(), refused or {}, clock)
            return _play(shell, options, clock)
        finally:
            if shell is not None:
                shell.close()
            rclpy.try_shutdown()
    finally:
        if own_stopper:
            stopper.restore()


def _play(shell: _Shell, options: PlayOptions, clock: PlaybackClock) -> int:
    """Wait for subscribers, start (or wait for resume), play; print a summary line."""
    if options.wait_for_subscribers:
        print(f'{PROG}: waiting for subscribers on {", ".join(options.wait_for_subscribers)}',
              flush=True)
        if not shell.wait_for_subscribers(options.wait_for_subscribers,
                                          options.wait_timeout):
            if clock.stopped:
                return 0
            print(f'{PROG}: error: no subscriber on {list(options.wait_for_subscribers)} '
                  f'after {options.wait_timeout:g} s', file=sys.stderr)
            return 1
    if options.start_paused:
        how = 'press Enter or call' if sys.stdin is not None and sys.stdin.isatty() else 'call'
        print(f'{PROG}: paused; {how} the {shell.node.get_fully_qualified_name()}/resume '
              'service (std_srvs/srv/Trigger) to start', flush=True)
        if sys.stdin is not None and sys.stdin.isatty():
            _resume_on_enter(clock)
    else:
        clock.resume()
    began = time.monotonic()
    print(f'{PROG}: playing {len(shell.publishers)} of {len(shell.topics)} topic(s) at rate '
          f'{options.rate:g}',
          flush=True)
    stats = play_messages(options, clock, shell.publish,
                          topics=shell.topics,
                          on_pass=shell.start_pass)
    acked = stats.stopped or shell.wait_for_acknowledgements(options.ack_timeout)
    elapsed = time.monotonic() - began
    skipped = sum(stats.skipped.values())
    median, worst = stats.lateness_ms()
    print(f'{PROG}: published {stats.total()} messages on {len(stats.published)} topic(s) in '
          f'{elapsed:.2f} s ({stats.passes} pass(es), behind schedule by {median:.2f} ms '
          f'median, {worst:.1f} ms at most'
          + (f', {skipped} skipped' if skipped else '')
          + (', stopped' if stats.stopped or clock.stopped else '')
          + ('' if acked or clock.stopped
             else f', not all acknowledged within {options.ack_timeout:g} s') + ')',
          flush=True)
    return 0
