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
TEST DOUBLE - not rclpy; mimics the Jazzy API surface used by reduced_dynamics.node.

Select the implementation with ``rclpy_backend()`` (real rclpy when importable, else the
double; force with env ``REDUCED_DYNAMICS_RCLPY=real|double|auto``)::

    @pytest.fixture
    def ros():
        with rclpy_backend(purge=('reduced_dynamics.node',)) as backend:
            yield backend

    def test_x(ros):
        from reduced_dynamics.node import main  # imported against the chosen rclpy
        ros.rclpy.init()
        ...

While the double is installed, ``import rclpy``, ``from rclpy.node import Node`` and
``from sensor_msgs.msg import JointState`` (any rosbags ROS2_JAZZY package) resolve to it.
The ``Backend`` helpers use only public rclpy API, so they work on both implementations.
"""

import contextlib
import copy
import importlib
import inspect
import os
import sys
import time
import types

from . import _impl
from . import _messages
from ._messages import from_rosbags  # noqa: F401  re-exported
from ._messages import to_rosbags  # noqa: F401  re-exported

_RCLPY_MODULES = {
    'rclpy': 'init shutdown try_shutdown ok spin spin_once create_node get_default_context',
    'rclpy.node': 'Node',
    'rclpy.parameter': 'Parameter PARAMETER_SEPARATOR_STRING',
    'rclpy.exceptions': 'NotInitializedException ParameterException '
                        'ParameterNotDeclaredException ParameterAlreadyDeclaredException '
                        'InvalidParameterTypeException InvalidParameterValueException '
                        'ParameterUninitializedException',
    'rclpy.executors': 'ExternalShutdownException SingleThreadedExecutor MultiThreadedExecutor',
    'rclpy.qos': 'QoSProfile HistoryPolicy ReliabilityPolicy DurabilityPolicy QoSHistoryPolicy '
                 'QoSReliabilityPolicy QoSDurabilityPolicy InvalidQoSProfileException '
                 'qos_profile_sensor_data qos_profile_system_default '
                 'qos_profile_parameter_events',
    'rclpy.time': 'Time',
    'rclpy.duration': 'Duration',
    'rclpy.clock': 'Clock ROSClock ClockType',
    'rclpy.clock_type': 'ClockType',
    'rclpy.context': 'Context',
    'rclpy.logging': 'get_logger',
    'rclpy.publisher': 'Publisher',
    'rclpy.subscription': 'Subscription',
    'rclpy.timer': 'Timer',
    'rclpy.utilities': 'ok shutdown try_shutdown get_default_context',
}


def _message_module(package):
    module = types.ModuleType(package + '.msg', f'TEST DOUBLE of {package}.msg')

    def __getattr__(name):  # noqa: N807  PEP 562 lazy class creation
        if f'{package}/msg/{name}' not in _messages.TYPESTORE.fielddefs:
            raise AttributeError(f"module '{package}.msg' has no attribute '{name}'")
        return _messages.get_class(f'{package}/msg/{name}')
    module.__getattr__ = __getattr__
    return module


def build_double_modules():
    """Return {module name: module} for every rclpy and message module of the double."""
    modules = {}
    for name, attrs in _RCLPY_MODULES.items():
        module = types.ModuleType(name, 'TEST DOUBLE - not rclpy')
        for attr in attrs.split():
            setattr(module, attr, getattr(_impl, attr))
        modules[name] = module
    for package in _messages.PACKAGES:
        modules[package] = types.ModuleType(package, 'TEST DOUBLE - rosbags based')
        modules[package + '.msg'] = _message_module(package)
    for name, module in modules.items():
        module.__rclpy_double__ = True
        parent, _, child = name.rpartition('.')
        if parent:
            setattr(modules[parent], child, module)
    return modules


def real_rclpy_available():
    """Return True if the real rclpy (not this double) can be imported."""
    if getattr(sys.modules.get('rclpy'), '__rclpy_double__', False):
        return False
    try:
        import rclpy  # noqa: F401
    except ImportError:
        return False
    return True


class Backend:
    """Uniform test helpers over real rclpy or the double (public rclpy API only)."""

    def __init__(self, rclpy, is_real, records):
        self.rclpy = rclpy
        self.is_real = is_real
        self._records = records

    def msg(self, msgtype):
        """Return the message class for 'pkg/msg/Name' from the active implementation."""
        package, _, name = msgtype.split('/')
        return getattr(importlib.import_module(package + '.msg'), name)

    def published(self, topic, node=None):
        """Return deep copies of messages published on ``topic`` (resolved against node)."""
        return self._records.setdefault(
            node.resolve_topic_name(topic) if node else topic, [])

    def deliver(self, node, topic, msg):
        """Call every subscription callback of ``node`` on ``topic`` with a copy of msg."""
        resolved = node.resolve_topic_name(topic)
        subs = [sub for sub in node.subscriptions if sub.topic_name == resolved]
        if not subs:
            raise LookupError(f'{node.get_name()} has no subscription on {resolved}')
        for sub in subs:
            args = (copy.deepcopy(msg),)
            if _wants_message_info(sub.callback):
                # As rclpy's executor does for a two-parameter callback: the message
                # info. The receive time is the header stamp (delivered at once, latency
                # 0) so that runs do not depend on how fast the test machine is.
                args += ({'source_timestamp': 0, 'received_timestamp': _received(msg)},)
            sub.callback(*args)
        return len(subs)

    def fire_timers(self, node):
        """Run the callback of every non-canceled timer of ``node`` once."""
        timers = [timer for timer in node.timers if not timer.is_canceled()]
        for timer in timers:
            timer.callback()
        return len(timers)

    def set_sim_time(self, node, seconds):
        """Publish-like delivery of rosgraph_msgs/Clock on /clock (needs use_sim_time)."""
        sec = int(seconds)
        stamp = self.msg('builtin_interfaces/msg/Time')(
            sec=sec, nanosec=int(round((seconds - sec) * 1e9)))
        self.deliver(node, '/clock', self.msg('rosgraph_msgs/msg/Clock')(clock=stamp))

    def spin_ready(self, node):
        """Execute ready timers (those whose period elapsed on their clock)."""
        for _ in range(len(list(node.timers)) or 1):
            self.rclpy.spin_once(node, timeout_sec=0.0)

    def logs(self, node):
        """Return [(severity, message)] logged by node (double only)."""
        self._require_double('logs')
        return node.get_logger().records

    def on_spin(self, action):
        """Make rclpy.spin(node) call action(node); raise in it to end spin (double only)."""
        self._require_double('on_spin')
        _impl.SPIN_ACTION[0] = action

    def _require_double(self, what):
        if self.is_real:
            raise NotImplementedError(f'{what}() is only available with the rclpy double')


@contextlib.contextmanager
def _recording(publisher_class, records):
    original = publisher_class.publish

    def publish(self, msg):
        original(self, msg)
        records.setdefault(self.topic_name, []).append(copy.deepcopy(msg))
    publisher_class.publish = publish
    try:
        yield
    finally:
        publisher_class.publish = original


def _purge(names):
    for name in list(sys.modules):
        if any(name == p or name.startswith(p + '.') for p in names):
            del sys.modules[name]


@contextlib.contextmanager
def installed_rclpy_double(purge=()):
    """Install the double into sys.modules (restored on exit); yield a Backend."""
    modules = build_double_modules()
    saved = {name: sys.modules.get(name) for name in modules}
    _purge(purge)
    sys.modules.update(modules)
    _impl._DEFAULT_CONTEXT[0] = _impl.Context()
    records = {}
    try:
        with _recording(_impl.Publisher, records):
            yield Backend(modules['rclpy'], False, records)
    finally:
        _impl.SPIN_ACTION[0] = None
        _impl.try_shutdown()
        for name, module in saved.items():
            if module is None:
                sys.modules.pop(name, None)
            else:
                sys.modules[name] = module
        _purge(purge)


@contextlib.contextmanager
def rclpy_backend(mode=None, purge=()):
    """Yield a Backend on real rclpy if importable (or as forced by mode/env), else the double."""
    mode = mode or os.environ.get('REDUCED_DYNAMICS_RCLPY', 'auto')
    if mode == 'double' or (mode == 'auto' and not real_rclpy_available()):
        with installed_rclpy_double(purge) as backend:
            yield backend
        return
    import rclpy
    import rclpy.publisher
    records = {}
    _purge(purge)
    try:
        with _recording(rclpy.publisher.Publisher, records):
            yield Backend(rclpy, True, records)
    finally:
        rclpy.try_shutdown()
        _purge(purge)


def _wants_message_info(callback):
    """Return whether rclpy would call ``callback`` with (message, message info)."""
    signature = inspect.signature(callback)
    try:
        signature.bind(object())
        return False
    except TypeError:
        signature.bind(object(), object())
        return True


def _received(msg):
    """Return a receive time [ns] for ``msg``: its header stamp, else the system time."""
    header = getattr(msg, 'header', None)
    stamp = getattr(header, 'stamp', None)
    if stamp is None:
        return time.time_ns()
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)
