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
Helpers for the node tests on real rclpy (no double): call callbacks, record publications.

``Ros.deliver`` calls a node's subscription callbacks directly (serializing the
message for raw subscriptions, as rmw would hand it over); ``Ros.published``
returns what the node's publishers sent, deserialized. Everything else is
real rclpy. The DDS tests (test_node_dds.py) use real executors instead.
"""

import contextlib
import copy
import importlib
import inspect
import os
import struct
import threading
import time

#: A ROS domain of this test process's own, so parallel runs on one machine do not mix
#: (a pytest-xdist worker's is given by conftest.py: distinct from the other workers').
DOMAIN_ID = os.environ.get('RD_TEST_DOMAIN_ID') or str(1 + os.getpid() % 100)
os.environ['ROS_DOMAIN_ID'] = DOMAIN_ID

import rclpy  # noqa: E402
import rclpy.publisher  # noqa: E402
from rclpy.serialization import deserialize_message, serialize_message  # noqa: E402


class RecordingLogger:
    """Keep (severity, message) of what a node logs."""

    def __init__(self, logger):
        self._logger = logger
        self.records = []

    def _log(self, severity, method):
        # Not forwarded: rcutils identifies a log call by its source line and refuses
        # one line logging at several severities.
        def log(message, *args, **kwargs):
            self.records.append((severity, message))
            return True
        return log

    def __getattr__(self, name):
        names = {'debug': 'DEBUG', 'info': 'INFO', 'warning': 'WARN', 'warn': 'WARN',
                 'error': 'ERROR', 'fatal': 'FATAL'}
        if name in names:
            return self._log(names[name], name)
        return getattr(self._logger, name)


class Ros:
    """Uniform test helpers over real rclpy."""

    def __init__(self, records, raw):
        self.rclpy = rclpy
        self._records = records
        self._raw = raw

    def msg(self, msgtype):
        """Return the message class for 'pkg/msg/Name'."""
        package, _, name = msgtype.split('/')
        return getattr(importlib.import_module(package + '.msg'), name)

    def published(self, topic, node=None):
        """Return the messages published on ``topic`` (resolved against node), in order."""
        name = node.resolve_topic_name(topic) if node else topic
        return self._records.setdefault(name, [])

    def published_raw(self, topic, node=None):
        """Return the CDR bytes published on ``topic``."""
        name = node.resolve_topic_name(topic) if node else topic
        return self._raw.setdefault(name, [])

    def deliver(self, node, topic, msg, received_ns=None):
        """
        Call every subscription callback of ``node`` on ``topic`` with (a copy of) msg.

        Two-parameter callbacks get the message info as rclpy's executor gives it;
        its receive time is ``received_ns``, by default the header stamp (delivered
        at once), so that runs do not depend on how fast the test machine is.
        """
        resolved = node.resolve_topic_name(topic)
        subs = [sub for sub in node.subscriptions if sub.topic_name == resolved]
        if not subs:
            raise LookupError(f'{node.get_name()} has no subscription on {resolved}')
        for sub in subs:
            if sub.raw:
                args = (msg if isinstance(msg, bytes) else serialize_message(msg),)
            else:
                args = (copy.deepcopy(msg),)
            if _wants_message_info(sub.callback):
                if received_ns is None:
                    received_ns = _header_stamp(msg)
                args += ({'source_timestamp': 0, 'received_timestamp': received_ns},)
            sub.callback(*args)
        return len(subs)

    def fire_timers(self, node):
        """Run the callback of every non-canceled timer of ``node`` once."""
        timers = [timer for timer in node.timers if not timer.is_canceled()]
        for timer in timers:
            timer.callback()
        return len(timers)

    def set_sim_time(self, node, seconds):
        """Deliver rosgraph_msgs/Clock on /clock (needs use_sim_time)."""
        sec = int(seconds)
        stamp = self.msg('builtin_interfaces/msg/Time')(
            sec=sec, nanosec=int(round((seconds - sec) * 1e9)))
        self.deliver(node, '/clock', self.msg('rosgraph_msgs/msg/Clock')(clock=stamp))

    @staticmethod
    def record_logs(node):
        """Make node.get_logger() record; return the recorder (its ``records``)."""
        recorder = RecordingLogger(node.get_logger())
        node.get_logger = lambda: recorder
        return recorder


@contextlib.contextmanager
def real_ros():
    """Init rclpy, record every publication; yield a Ros; shut down afterwards."""
    records, raw = {}, {}
    original = rclpy.publisher.Publisher.publish
    lock = threading.Lock()  # the node's prediction worker publishes too

    def publish(self, msg):
        original(self, msg)
        data = msg if isinstance(msg, bytes) else serialize_message(msg)
        with lock:
            raw.setdefault(self.topic_name, []).append(data)
            records.setdefault(self.topic_name, []).append(
                deserialize_message(data, self.msg_type))
    rclpy.publisher.Publisher.publish = publish
    rclpy.init()
    try:
        yield Ros(records, raw)
    finally:
        rclpy.publisher.Publisher.publish = original
        rclpy.try_shutdown()


def _wants_message_info(callback):
    """Return whether rclpy would call ``callback`` with (message, message info)."""
    signature = inspect.signature(callback)
    try:
        signature.bind(object())
        return False
    except TypeError:
        signature.bind(object(), object())
        return True


def _header_stamp(msg):
    """Return the header stamp [ns] of a message or of its CDR bytes, else the system time."""
    if isinstance(msg, bytes):
        sec, nanosec = struct.unpack_from('<iI', msg, 4)
        return sec * 1_000_000_000 + nanosec
    stamp = getattr(getattr(msg, 'header', None), 'stamp', None)
    if stamp is None:
        return time.time_ns()
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)
