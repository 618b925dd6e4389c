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

Ported from rclpy 7.1.x (jazzy branch): node.py parameter logic (declare/set, descriptors,
ranges, read_only, type checks, pre/on/post-set callbacks), time_source.py (use_sim_time,
/clock), time.py, duration.py, qos.py profiles and utilities init/ok/try_shutdown.
There is no middleware: publish() records a deep copy, subscriptions are driven by the
harness (``deliver``), timers fire when the harness says so, spin() returns at once
(or runs ``SPIN_ACTION`` which may raise, e.g. KeyboardInterrupt).
See docs/RCLPY_API_NOTES.md for the real API.
"""

import array
from enum import Enum
from enum import IntEnum
import logging
import math
import time as _walltime
import warnings

from ._messages import check_message
from ._messages import get_class

ParameterDescriptor = get_class('rcl_interfaces/msg/ParameterDescriptor')
ParameterType = get_class('rcl_interfaces/msg/ParameterType')
ParameterValue = get_class('rcl_interfaces/msg/ParameterValue')
SetParametersResult = get_class('rcl_interfaces/msg/SetParametersResult')
TimeMsg = get_class('builtin_interfaces/msg/Time')
DurationMsg = get_class('builtin_interfaces/msg/Duration')
S_TO_NS = 1000 * 1000 * 1000
PARAMETER_SEPARATOR_STRING = '.'
SPIN_ACTION = [None]  # callable(node) run by spin(); may raise KeyboardInterrupt etc.


# ---------------------------------------------------------------- exceptions (rclpy.exceptions)
class NotInitializedException(Exception):
    """Raised when rclpy.init() has not been called."""

    def __init__(self, message=None):
        super().__init__(f'rclpy.init() has not been called. msg:{message}' if message
                         else 'rclpy.init() has not been called.')


class ParameterException(Exception):
    """Base exception for parameter-related errors."""

    def __init__(self, error_msg, parameters):
        super().__init__(f'{error_msg}: {parameters}')


class ParameterNotDeclaredException(ParameterException):
    """Raised when handling an undeclared parameter."""

    def __init__(self, parameters):
        super().__init__('Invalid access to undeclared parameter(s)', parameters)


class ParameterAlreadyDeclaredException(ParameterException):
    """Raised when declaring a parameter twice."""

    def __init__(self, parameters):
        super().__init__('Parameter(s) already declared', parameters)


class InvalidParameterTypeException(ParameterException):
    """Raised when a declared value has the wrong type."""

    def __init__(self, desired_parameter, expected_type):
        super().__init__(
            f"Trying to set parameter '{desired_parameter.name}' to '{desired_parameter.value}'"
            f" of type '{Parameter.Type.from_parameter_value(desired_parameter.value).name}'"
            f", expecting type '{expected_type}'", desired_parameter.name)


class InvalidParameterValueException(ParameterException):
    """Raised when a descriptor or callback rejects a declared value."""

    def __init__(self, parameter, value, reason):
        super().__init__(
            f'Invalid parameter value ({value}) for parameter. Reason: {reason}', parameter)


class ParameterUninitializedException(ParameterException):
    """Raised when reading a statically typed parameter without value."""

    def __init__(self, parameter_name):
        super().__init__(f"The parameter '{parameter_name}' is not initialized", parameter_name)


class ExternalShutdownException(Exception):
    """Context has been shutdown."""


# ------------------------------------------------------------------- context (rclpy.utilities)
class Context:
    """Init/shutdown state only (rclpy.context.Context)."""

    def __init__(self):
        self._state = 'new'

    def init(self, args=None, *, domain_id=None):
        if self._state != 'new':
            raise RuntimeError('Context.init() must only be called once')
        self._state = 'ok'

    def ok(self):
        return self._state == 'ok'

    def shutdown(self):
        if self._state == 'new':
            raise RuntimeError('Context must be initialized before it can be shutdown')
        if self._state == 'shutdown':
            raise RuntimeError('rcl_shutdown already called on the given context')
        self._state = 'shutdown'

    def try_shutdown(self):
        if self._state == 'ok':
            self._state = 'shutdown'


_DEFAULT_CONTEXT = [Context()]


def get_default_context():
    return _DEFAULT_CONTEXT[0]


def init(*, args=None, context=None, domain_id=None, signal_handler_options=None):
    (context or get_default_context()).init(args, domain_id=domain_id)


def ok(*, context=None):
    return (context or get_default_context()).ok()


def shutdown(*, context=None, uninstall_handlers=None):
    (context or get_default_context()).shutdown()


def try_shutdown(*, context=None):
    if context is not None:
        return context.try_shutdown()
    get_default_context().try_shutdown()
    if not get_default_context().ok():  # like rclpy: a fresh default context for re-init
        _DEFAULT_CONTEXT[0] = Context()


def spin(node, executor=None):
    """Return immediately (no middleware) unless SPIN_ACTION is set; it may raise."""
    if SPIN_ACTION[0] is not None:
        SPIN_ACTION[0](node)


def spin_once(node, *, executor=None, timeout_sec=None):
    for timer in list(node.timers):
        if timer.is_ready():
            timer._call()


def create_node(node_name, **kwargs):
    return Node(node_name, **kwargs)


class SingleThreadedExecutor:
    """Executor facade; spin() behaves like rclpy.spin for each node."""

    def __init__(self, *, context=None):
        self._nodes = []

    def add_node(self, node):
        self._nodes.append(node)
        return True

    def remove_node(self, node):
        self._nodes.remove(node)

    def spin(self):
        for node in list(self._nodes):
            spin(node)

    def shutdown(self, timeout_sec=None):
        return True


MultiThreadedExecutor = SingleThreadedExecutor


# ------------------------------------------------------------- time (time/duration/clock/qos)
class ClockType(IntEnum):
    UNINITIALIZED = 0
    ROS_TIME = 1
    SYSTEM_TIME = 2
    STEADY_TIME = 3


class Duration:
    """A signed span of time in nanoseconds (rclpy.duration.Duration)."""

    def __init__(self, *, seconds=0, nanoseconds=0):
        self._ns = int(seconds * S_TO_NS) + int(nanoseconds)

    nanoseconds = property(lambda self: self._ns)

    def __eq__(self, other):
        return isinstance(other, Duration) and self._ns == other._ns

    def __lt__(self, other):
        return self._ns < other._ns

    def __le__(self, other):
        return self._ns <= other._ns

    def __repr__(self):
        return f'Duration(nanoseconds={self._ns})'

    def to_msg(self):
        return DurationMsg(sec=self._ns // S_TO_NS, nanosec=self._ns % S_TO_NS)

    @classmethod
    def from_msg(cls, msg):
        return cls(seconds=msg.sec, nanoseconds=msg.nanosec)


class Time:
    """A time point with a clock type (rclpy.time.Time)."""

    def __init__(self, *, seconds=0, nanoseconds=0, clock_type=ClockType.SYSTEM_TIME):
        if not isinstance(clock_type, ClockType):
            raise TypeError('Clock type must be a ClockType enum')
        if seconds < 0 or nanoseconds < 0:
            raise ValueError('Seconds value must not be negative')
        self._ns = int(seconds * S_TO_NS) + int(nanoseconds)
        self._clock_type = clock_type

    nanoseconds = property(lambda self: self._ns)
    clock_type = property(lambda self: self._clock_type)

    def seconds_nanoseconds(self):
        return (self._ns // S_TO_NS, self._ns % S_TO_NS)

    def _same(self, other):
        if other.clock_type != self._clock_type:
            raise TypeError("Can't compare times with different clock types")
        return other._ns

    def __add__(self, other):
        if not isinstance(other, Duration):
            return NotImplemented
        return Time(nanoseconds=self._ns + other.nanoseconds, clock_type=self._clock_type)

    __radd__ = __add__

    def __sub__(self, other):
        if isinstance(other, Time):
            return Duration(nanoseconds=self._ns - self._same(other))
        if isinstance(other, Duration):
            return Time(nanoseconds=self._ns - other.nanoseconds, clock_type=self._clock_type)
        return NotImplemented

    def __eq__(self, other):
        return isinstance(other, Time) and self._ns == self._same(other)

    def __lt__(self, other):
        return self._ns < self._same(other)

    def __le__(self, other):
        return self._ns <= self._same(other)

    def __repr__(self):
        return f'Time(nanoseconds={self._ns}, clock_type={self._clock_type.name})'

    def to_msg(self):
        sec, nanosec = self.seconds_nanoseconds()
        return TimeMsg(sec=sec, nanosec=nanosec)

    @classmethod
    def from_msg(cls, msg, clock_type=ClockType.ROS_TIME):
        return cls(seconds=msg.sec, nanoseconds=msg.nanosec, clock_type=clock_type)


class Clock:
    """A clock reading the wall time (rclpy.clock.Clock)."""

    def __init__(self, *, clock_type=ClockType.SYSTEM_TIME):
        self.clock_type = clock_type

    def now(self):
        return Time(nanoseconds=_walltime.time_ns(), clock_type=self.clock_type)


class ROSClock(Clock):
    """The node clock: wall time, or the /clock override while use_sim_time is True."""

    def __init__(self):
        super().__init__(clock_type=ClockType.ROS_TIME)
        self._ros_time_is_active = False
        self._override = Time(clock_type=ClockType.ROS_TIME)

    ros_time_is_active = property(lambda self: self._ros_time_is_active)

    def _set_ros_time_is_active(self, enabled):
        self._ros_time_is_active = enabled

    def set_ros_time_override(self, time):
        self._override = time

    def now(self):
        return self._override if self._ros_time_is_active else super().now()


class HistoryPolicy(IntEnum):
    SYSTEM_DEFAULT = 0
    KEEP_LAST = 1
    KEEP_ALL = 2
    UNKNOWN = 3


class ReliabilityPolicy(IntEnum):
    SYSTEM_DEFAULT = 0
    RELIABLE = 1
    BEST_EFFORT = 2
    UNKNOWN = 3
    BEST_AVAILABLE = 4


class DurabilityPolicy(IntEnum):
    SYSTEM_DEFAULT = 0
    TRANSIENT_LOCAL = 1
    VOLATILE = 2
    UNKNOWN = 3
    BEST_AVAILABLE = 4


QoSHistoryPolicy = HistoryPolicy
QoSReliabilityPolicy = ReliabilityPolicy
QoSDurabilityPolicy = DurabilityPolicy


class InvalidQoSProfileException(Exception):
    pass


class QoSProfile:
    """QoS settings (history, depth, reliability, durability only)."""

    def __init__(self, **kwargs):
        if 'history' not in kwargs:
            if 'depth' not in kwargs:
                raise InvalidQoSProfileException('History and/or depth settings are required.')
            kwargs['history'] = HistoryPolicy.KEEP_LAST
        if kwargs['history'] == HistoryPolicy.KEEP_LAST and 'depth' not in kwargs:
            raise InvalidQoSProfileException('History set to KEEP_LAST without a depth setting.')
        self.history = kwargs.pop('history')
        self.depth = kwargs.pop('depth', 10)
        self.reliability = kwargs.pop('reliability', ReliabilityPolicy.RELIABLE)
        self.durability = kwargs.pop('durability', DurabilityPolicy.VOLATILE)
        assert not kwargs, 'Invalid arguments passed to constructor: %r' % kwargs.keys()

    def __eq__(self, other):
        return isinstance(other, QoSProfile) and vars(self) == vars(other)

    def __repr__(self):
        return f'QoSProfile({vars(self)})'


qos_profile_sensor_data = QoSProfile(depth=5, reliability=ReliabilityPolicy.BEST_EFFORT)
qos_profile_system_default = QoSProfile(depth=0, history=HistoryPolicy.SYSTEM_DEFAULT,
                                        reliability=ReliabilityPolicy.SYSTEM_DEFAULT,
                                        durability=DurabilityPolicy.SYSTEM_DEFAULT)
qos_profile_parameter_events = QoSProfile(depth=1000)


# ---------------------------------------------------------------------------------- parameter
class Parameter:
    class Type(Enum):
        NOT_SET = 0
        BOOL = 1
        INTEGER = 2
        DOUBLE = 3
        STRING = 4
        BYTE_ARRAY = 5
        BOOL_ARRAY = 6
        INTEGER_ARRAY = 7
        DOUBLE_ARRAY = 8
        STRING_ARRAY = 9

        @classmethod
        def from_parameter_value(cls, value):
            if value is None:
                return cls.NOT_SET
            for type_, py in ((cls.BOOL, bool), (cls.INTEGER, int), (cls.DOUBLE, float),
                              (cls.STRING, str)):
                if isinstance(value, py):
                    return type_
            if isinstance(value, (list, tuple, array.array)):
                for type_, py in ((cls.BYTE_ARRAY, bytes), (cls.BOOL_ARRAY, bool),
                                  (cls.INTEGER_ARRAY, int), (cls.DOUBLE_ARRAY, float),
                                  (cls.STRING_ARRAY, str)):
                    if all(isinstance(v, py) for v in value):
                        return type_
                raise TypeError('The given value is not a list of one of the allowed types'
                                f" '{value}'.")
            raise TypeError(f"The given value is not one of the allowed types '{value}'.")

        def check(self, value):
            seq, T = (list, tuple), Parameter.Type
            if self is T.NOT_SET:
                return value is None
            scalar = {T.BOOL: bool, T.INTEGER: int, T.DOUBLE: float, T.STRING: str}
            if self in scalar:
                return isinstance(value, scalar[self])
            if self is T.BYTE_ARRAY:
                return isinstance(value, seq) and all(
                    isinstance(v, bytes) and len(v) == 1 for v in value)
            item = {T.BOOL_ARRAY: bool, T.INTEGER_ARRAY: int, T.DOUBLE_ARRAY: float,
                    T.STRING_ARRAY: str}[self]
            if self in (T.INTEGER_ARRAY, T.DOUBLE_ARRAY):
                seq = (list, tuple, array.array)
            return isinstance(value, seq) and all(isinstance(v, item) for v in value)

    _FIELD = {Type.BOOL: 'bool_value', Type.INTEGER: 'integer_value',
              Type.DOUBLE: 'double_value', Type.STRING: 'string_value',
              Type.BYTE_ARRAY: 'byte_array_value', Type.BOOL_ARRAY: 'bool_array_value',
              Type.INTEGER_ARRAY: 'integer_array_value',
              Type.DOUBLE_ARRAY: 'double_array_value',
              Type.STRING_ARRAY: 'string_array_value'}

    def __init__(self, name, type_=None, value=None):
        if type_ is None:
            type_ = Parameter.Type.from_parameter_value(value)
        if not isinstance(type_, Parameter.Type):
            raise TypeError("type must be an instance of '{}'".format(repr(Parameter.Type)))
        if not type_.check(value):
            raise ValueError("Type '{}' and value '{}' do not agree".format(type_, value))
        self._type_, self._name, self._value = type_, name, value

    name = property(lambda self: self._name)
    type_ = property(lambda self: self._type_)
    value = property(lambda self: self._value)

    def get_parameter_value(self):
        msg = ParameterValue(type=self._type_.value)
        if self._type_ in self._FIELD:
            setattr(msg, self._FIELD[self._type_], self._value)
        return msg

    def __repr__(self):
        return f'Parameter({self._name!r}, {self._type_}, {self._value!r})'


# ------------------------------------------------------------------------ node and entities
class Logger:
    """Records (severity, message) in ``records`` and forwards to std logging."""

    def __init__(self, name):
        self.name = name
        self.records = []
        self._py = logging.getLogger('rclpy_double.' + name)

    def _log(self, severity, level, message):
        self.records.append((severity, message))
        self._py.log(level, message)
        return True

    def debug(self, message, **kwargs):
        return self._log('DEBUG', logging.DEBUG, message)

    def info(self, message, **kwargs):
        return self._log('INFO', logging.INFO, message)

    def warning(self, message, **kwargs):
        return self._log('WARN', logging.WARNING, message)

    warn = warning

    def error(self, message, **kwargs):
        return self._log('ERROR', logging.ERROR, message)

    def fatal(self, message, **kwargs):
        return self._log('FATAL', logging.CRITICAL, message)


def get_logger(name):
    return Logger(name)


class Publisher:
    """Publisher checking message types; records nothing itself (see harness)."""

    def __init__(self, msg_type, topic, topic_name, qos_profile):
        self.msg_type, self.topic, self.qos_profile = msg_type, topic, qos_profile
        self._topic_name = topic_name

    topic_name = property(lambda self: self._topic_name)

    def publish(self, msg):
        if not isinstance(msg, self.msg_type):
            raise TypeError('Expected {}, got {}'.format(self.msg_type, type(msg)))
        check_message(msg)  # no middleware; the harness records what is published

    def get_subscription_count(self):
        return 0


class Subscription:
    """Subscription whose callback the harness drives."""

    def __init__(self, msg_type, topic, topic_name, callback, qos_profile, raw):
        self.msg_type, self.topic, self.callback = msg_type, topic, callback
        self.qos_profile, self.raw, self._topic_name = qos_profile, raw, topic_name

    topic_name = property(lambda self: self._topic_name)

    def get_publisher_count(self):
        return 0


class Timer:
    """Timer fired by the harness or by spin_once() when its period elapsed."""

    def __init__(self, callback, period_ns, clock, autostart):
        self.callback, self.timer_period_ns, self._clock = callback, period_ns, clock
        self._canceled = not autostart
        self._next = clock.now().nanoseconds + period_ns

    clock = property(lambda self: self._clock)

    def is_canceled(self):
        return self._canceled

    def cancel(self):
        self._canceled = True

    def reset(self):
        self._canceled = False
        self._next = self._clock.now().nanoseconds + self.timer_period_ns

    def is_ready(self):
        return not self._canceled and self._clock.now().nanoseconds >= self._next

    def _call(self):
        """Like rcl_timer_call: advance one period, skip missed periods, then run callback."""
        now, period = self._clock.now().nanoseconds, self.timer_period_ns
        self._next += period
        if self._next < now:
            self._next = now if period == 0 else self._next + (
                1 + (now - self._next - 1) // period) * period
        self.callback()


class Node:
    """rclpy.node.Node double (parameters, pub/sub/timers, clock, logger, names)."""

    PARAM_REL_TOL = 1e-6

    def __init__(self, node_name, *, context=None, cli_args=None, namespace=None,
                 use_global_arguments=True, enable_rosout=True, start_parameter_services=True,
                 parameter_overrides=None, allow_undeclared_parameters=False,
                 automatically_declare_parameters_from_overrides=False,
                 enable_logger_service=False):
        self._context = context or get_default_context()
        if not self._context.ok():
            raise NotInitializedException('cannot create node')
        namespace = namespace or '/'
        self._name = node_name
        self._namespace = namespace if namespace.startswith('/') else '/' + namespace
        self._parameters, self._descriptors = {}, {}
        self._publishers, self._subscriptions, self._timers = [], [], []
        self._pre_set, self._on_set, self._post_set = [], [], []
        self._allow_undeclared_parameters = allow_undeclared_parameters
        self._parameter_overrides = {p.name: p for p in parameter_overrides or []}
        self._logger = Logger(self.get_fully_qualified_name()[1:].replace('/', '.'))
        self._clock = ROSClock()
        self._clock_sub = None
        self.destroyed = False
        if automatically_declare_parameters_from_overrides:
            self.declare_parameters('', [(name, p.value, ParameterDescriptor())
                                         for name, p in self._parameter_overrides.items()],
                                    ignore_override=True)
        # TimeSource.attach_node
        if not self.has_parameter('use_sim_time'):
            self.declare_parameter('use_sim_time', False)
        self._set_ros_time_active(self.get_parameter('use_sim_time').value)
        self.add_on_set_parameters_callback(self._time_source_on_set)

    # --- names / time / logging
    publishers = property(lambda self: iter(self._publishers))
    subscriptions = property(lambda self: iter(self._subscriptions))
    timers = property(lambda self: iter(self._timers))
    context = property(lambda self: self._context)

    def get_name(self):
        return self._name

    def get_namespace(self):
        return self._namespace

    def get_fully_qualified_name(self):
        return self._namespace.rstrip('/') + '/' + self._name

    def get_clock(self):
        return self._clock

    def get_logger(self):
        return self._logger

    def resolve_topic_name(self, topic, *, only_expand=False):
        if topic.startswith('~'):
            return self.get_fully_qualified_name() + topic[1:]
        if topic.startswith('/'):
            return topic
        return self._namespace.rstrip('/') + '/' + topic

    resolve_service_name = resolve_topic_name

    def _set_ros_time_active(self, enabled):
        self._clock._set_ros_time_is_active(enabled)
        if enabled and self._clock_sub is None:
            self._clock_sub = self.create_subscription(
                get_class('rosgraph_msgs/msg/Clock'), '/clock', self._on_clock,
                QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT))
        elif not enabled and self._clock_sub is not None:
            self.destroy_subscription(self._clock_sub)
            self._clock_sub = None

    def _on_clock(self, msg):
        self._clock.set_ros_time_override(Time.from_msg(msg.clock))

    def _time_source_on_set(self, parameter_list):
        for param in parameter_list:
            if param.name == 'use_sim_time':
                if param.type_ != Parameter.Type.BOOL:
                    return SetParametersResult(
                        successful=False,
                        reason='use_sim_time parameter set to something besides a bool')
                self._set_ros_time_active(param.value)
        return SetParametersResult(successful=True)

    # --- entities
    @staticmethod
    def _qos(qos_or_depth):
        if isinstance(qos_or_depth, QoSProfile):
            return qos_or_depth
        if isinstance(qos_or_depth, int):
            if qos_or_depth < 0:
                raise ValueError('history depth must be greater than or equal to zero')
            return QoSProfile(depth=qos_or_depth)
        raise TypeError('Expected QoSProfile or int, but received {!r}'.format(
            type(qos_or_depth)))

    def create_publisher(self, msg_type, topic, qos_profile, *, callback_group=None,
                         event_callbacks=None, qos_overriding_options=None,
                         publisher_class=None):
        pub = Publisher(msg_type, topic, self.resolve_topic_name(topic), self._qos(qos_profile))
        self._publishers.append(pub)
        return pub

    def create_subscription(self, msg_type, topic, callback, qos_profile, *, callback_group=None,
                            event_callbacks=None, qos_overriding_options=None, raw=False):
        sub = Subscription(msg_type, topic, self.resolve_topic_name(topic), callback,
                           self._qos(qos_profile), raw)
        self._subscriptions.append(sub)
        return sub

    def create_timer(self, timer_period_sec, callback, callback_group=None, clock=None,
                     autostart=True):
        timer = Timer(callback, int(float(timer_period_sec) * S_TO_NS), clock or self._clock,
                      autostart)
        self._timers.append(timer)
        return timer

    def destroy_publisher(self, publisher):
        return self._remove(self._publishers, publisher)

    def destroy_subscription(self, subscription):
        return self._remove(self._subscriptions, subscription)

    def destroy_timer(self, timer):
        return self._remove(self._timers, timer)

    @staticmethod
    def _remove(entities, entity):
        if entity in entities:
            entities.remove(entity)
            return True
        return False

    def destroy_node(self):
        self._publishers.clear()
        self._subscriptions.clear()
        self._timers.clear()
        self.destroyed = True

    # --- parameters (logic follows rclpy jazzy node.py)
    def declare_parameter(self, name, value=None, descriptor=None, ignore_override=False):
        if value is None and descriptor is None:
            args = (name,)
        else:
            args = (name, value, ParameterDescriptor() if descriptor is None else descriptor)
        return self.declare_parameters('', [args], ignore_override)[0]

    def declare_parameters(self, namespace, parameters, ignore_override=False):
        parameter_list, descriptors = [], {}
        for parameter_tuple in parameters:
            name = f'{namespace}.{parameter_tuple[0]}' if namespace else parameter_tuple[0]
            second = parameter_tuple[1] if len(parameter_tuple) > 1 else None
            descriptor = parameter_tuple[2] if len(parameter_tuple) > 2 else ParameterDescriptor()
            value = None
            if len(parameter_tuple) == 1:
                warnings.warn(f"when declaring parameter named '{name}', declaring a parameter "
                              'only providing its name is deprecated.')
                descriptor.dynamic_typing = True
            if isinstance(second, Parameter.Type):
                if second == Parameter.Type.NOT_SET:
                    raise ValueError(
                        f'Cannot declare parameter {{{name}}} as statically typed of type NOT_SET')
                descriptor.type = second.value
            else:
                value = second
                if not descriptor.dynamic_typing:
                    descriptor.type = Parameter.Type.from_parameter_value(value).value
                    if descriptor.type == ParameterType.PARAMETER_NOT_SET:
                        raise ValueError('Cannot declare a statically typed parameter with '
                                         'default value of type PARAMETER_NOT_SET')
            if not ignore_override and name in self._parameter_overrides:
                value = self._parameter_overrides[name].value
            parameter_list.append(Parameter(name, value=value))
            descriptors[name] = descriptor
        already = [p.name for p in parameter_list if p.name in self._parameters]
        if already:
            raise ParameterAlreadyDeclaredException(already)
        for param in parameter_list:
            result = self._set_common([param], descriptors)
            if not result.successful:
                if result.reason.startswith('Wrong parameter type'):
                    raise InvalidParameterTypeException(
                        param, Parameter.Type(descriptors[param.name].type).name)
                raise InvalidParameterValueException(param.name, param.value, result.reason)
        return [self._parameters[p.name] for p in parameter_list]

    def has_parameter(self, name):
        return name in self._parameters

    def get_parameter(self, name):
        if name in self._parameters:
            param = self._parameters[name]
            if param.type_ != Parameter.Type.NOT_SET or self._descriptors[name].dynamic_typing:
                return param
            raise ParameterUninitializedException(name)
        if self._allow_undeclared_parameters:
            return Parameter(name, Parameter.Type.NOT_SET, None)
        raise ParameterNotDeclaredException(name)

    def get_parameters(self, names):
        return [self.get_parameter(name) for name in names]

    def get_parameter_or(self, name, alternative_value=None):
        param = self._parameters.get(name)
        if param is None or param.type_ == Parameter.Type.NOT_SET:
            return alternative_value or Parameter(name, Parameter.Type.NOT_SET)
        return param

    def describe_parameter(self, name):
        if name in self._descriptors:
            return self._descriptors[name]
        if self._allow_undeclared_parameters:
            return ParameterDescriptor()
        raise ParameterNotDeclaredException(name)

    def set_parameters(self, parameter_list):
        return [self._set_atomically([param]) for param in parameter_list]

    def set_parameters_atomically(self, parameter_list):
        return self._set_atomically(parameter_list)

    def _set_atomically(self, parameter_list):
        if self._pre_set:
            parameter_list = [p for cb in self._pre_set for p in cb(parameter_list)]
            if not parameter_list:
                return SetParametersResult(
                    successful=False,
                    reason='parameter list cannot be empty, this might be due to '
                           'pre_set_parameters_callback modifying the original parameters list.')
        if not all(isinstance(p, Parameter) for p in parameter_list):
            raise TypeError("parameter must be instance of type '{}'".format(repr(Parameter)))
        undeclared = [p.name for p in parameter_list if p.name not in self._parameters]
        if undeclared and not self._allow_undeclared_parameters:
            raise ParameterNotDeclaredException(undeclared)
        return self._set_common(parameter_list)

    def _set_common(self, parameter_list, descriptors=None):
        for param in parameter_list:
            if descriptors is not None:
                result = self._apply_descriptor(param, descriptors[param.name], False)
            elif param.name in self._descriptors:
                result = self._apply_descriptor(param, self._descriptors[param.name], True)
            else:
                continue
            if not result.successful:
                return result
        for callback in self._on_set:
            result = callback(parameter_list)
            if not result.successful:
                return result
        for param in parameter_list:
            if descriptors is None and param.type_ == Parameter.Type.NOT_SET:
                self._parameters.pop(param.name, None)  # implicit undeclare
                self._descriptors.pop(param.name, None)
                continue
            if descriptors is not None:
                self._descriptors[param.name] = descriptors[param.name]
            elif param.name not in self._descriptors:
                self._descriptors[param.name] = ParameterDescriptor(dynamic_typing=True)
            self._parameters[param.name] = param
        for callback in self._post_set:
            callback(parameter_list)
        return SetParametersResult(successful=True)

    def _apply_descriptor(self, parameter, descriptor, check_read_only):
        descriptor.name = parameter.name
        if check_read_only and descriptor.read_only:
            return SetParametersResult(
                successful=False,
                reason='Trying to set a read-only parameter: {}.'.format(parameter.name))
        if descriptor.dynamic_typing:
            descriptor.type = parameter.type_.value
        elif self.has_parameter(parameter.name) and parameter.type_ == Parameter.Type.NOT_SET:
            return SetParametersResult(successful=False,
                                       reason='Static parameter cannot be undeclared')
        elif (parameter.type_ != Parameter.Type.NOT_SET and
              parameter.type_.value != descriptor.type):
            return SetParametersResult(
                successful=False,
                reason=('Wrong parameter type, expected '
                        f"'{Parameter.Type(descriptor.type)}' got '{parameter.type_}'"))
        if parameter.type_ == Parameter.Type.INTEGER and descriptor.integer_range:
            return self._apply_range(parameter, descriptor.integer_range[0], False)
        if parameter.type_ == Parameter.Type.DOUBLE and descriptor.floating_point_range:
            return self._apply_range(parameter, descriptor.floating_point_range[0], True)
        return SetParametersResult(successful=True)

    def _apply_range(self, parameter, value_range, floating):
        lo = min(value_range.from_value, value_range.to_value)
        hi = max(value_range.from_value, value_range.to_value)
        value, step = parameter.value, value_range.step

        def close(a, b):
            return math.isclose(a, b, rel_tol=self.PARAM_REL_TOL) if floating else a == b
        if close(value, lo) or close(value, hi):  # values on the edges are always OK
            return SetParametersResult(successful=True)
        if not lo < value < hi:
            return SetParametersResult(
                successful=False,
                reason='Parameter {} out of range{} Min: {}, Max: {}, value: {}'.format(
                    parameter.name, '' if floating else '.', lo, hi, value))
        on_step = (close(lo + round((value - lo) / step) * step, value) if floating
                   else (value - lo) % step == 0) if step != 0 else True
        if not on_step:
            what = 'is not close enough to a valid step' if floating else 'is not a valid step'
            return SetParametersResult(
                successful=False,
                reason='The parameter value for {} {}. Min: {}, max: {}, value: {}, step: {}'
                .format(parameter.name, what, lo, hi, value, step))
        return SetParametersResult(successful=True)

    def add_pre_set_parameters_callback(self, callback):
        self._pre_set.insert(0, callback)

    def add_on_set_parameters_callback(self, callback):
        self._on_set.insert(0, callback)

    def add_post_set_parameters_callback(self, callback):
        self._post_set.insert(0, callback)

    def remove_pre_set_parameters_callback(self, callback):
        self._pre_set.remove(callback)

    def remove_on_set_parameters_callback(self, callback):
        self._on_set.remove(callback)

    def remove_post_set_parameters_callback(self, callback):
        self._post_set.remove(callback)
