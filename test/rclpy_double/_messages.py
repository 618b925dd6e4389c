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
TEST DOUBLE - not rosidl_generator_py; rclpy-style message classes from rosbags.

Classes are generated lazily from the rosbags ROS2_JAZZY typestore and behave like the
Jazzy generated Python classes (rosidl_generator_py ``_msg.py.em``):

* keyword-only constructor, every field optional with the rosidl default;
* ``float64[]`` / ``int32[]`` / ``uint8[]`` ... sequences are ``array.array`` (assigning a
  list converts), fixed-size numeric arrays (``float64[36]``) are ``numpy.ndarray``;
* ``byte`` fields and constants are ``bytes`` of length 1 (``DiagnosticStatus.OK == bytes([0])``);
* std_msgs/Empty hides the ``structure_needs_at_least_one_member`` placeholder.

Deliberately stricter than Jazzy (where ROS_PYTHON_CHECK_FIELDS is off by default):
unknown constructor keywords raise TypeError, and ``check_message`` (run on every
double ``publish``) rejects values that the real C conversion would corrupt or refuse,
e.g. an ``int`` in a ``float64`` field.
"""

import array
import importlib

import numpy
from rosbags.typesys import get_typestore
from rosbags.typesys import Stores

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
PACKAGES = sorted({name.split('/')[0] for name in TYPESTORE.fielddefs})
_HIDDEN = 'structure_needs_at_least_one_member'
_CODES = {'float64': 'd', 'float32': 'f', 'int8': 'b', 'uint8': 'B', 'char': 'B',
          'int16': 'h', 'uint16': 'H', 'int32': 'i', 'uint32': 'I', 'int64': 'q',
          'uint64': 'Q'}
_PYTYPES = {'bool': bool, 'string': str, 'wstring': str, 'byte': bytes,
            'float32': float, 'float64': float}
_CLASSES = {}


def _pytype(base):
    return _PYTYPES.get(base, int)


def _default(kind, detail):
    if kind == 'base':
        return b'\x00' if detail == 'byte' else _pytype(detail)()
    if kind == 'msg':
        return get_class(detail)()
    inner_kind, inner, size = detail
    if kind == 'seq':
        return array.array(_CODES[inner], []) if inner in _CODES else []
    if inner_kind == 'base' and inner in _CODES:
        return numpy.zeros(size, dtype=numpy.dtype(_CODES[inner]))
    return [_default(inner_kind, inner) for _ in range(size)]


def _convert(kind, detail, value):
    """Mimic the conversions done by rosidl setters even with field checks off."""
    if kind in ('seq', 'array') and detail[0] == 'base' and detail[1] in _CODES:
        code = _CODES[detail[1]]
        if kind == 'array':
            return numpy.array(value, dtype=numpy.dtype(code))
        if isinstance(value, array.array) and value.typecode == code:
            return value
        return array.array(code, value.tolist() if hasattr(value, 'tolist') else value)
    return value


def _spec(node):
    nodetype, detail = node
    if nodetype == 1:
        return 'base', detail[0]
    if nodetype == 2:
        return 'msg', detail
    inner_kind, inner = _spec(detail[0])
    return ('array' if nodetype == 3 else 'seq'), (inner_kind, inner, detail[1])


class MessageBase:
    """Common behaviour of the generated double message classes."""

    __slots__ = ()
    _FIELDS = ()

    def __init__(self, **kwargs):
        unknown = sorted(set(kwargs) - {name for name, _, _ in self._FIELDS})
        if unknown:
            raise TypeError('Invalid arguments passed to constructor: ' + ', '.join(unknown))
        for name, kind, detail in self._FIELDS:
            setattr(self, name, kwargs[name] if name in kwargs else _default(kind, detail))

    @classmethod
    def get_fields_and_field_types(cls):
        """Return field names and (rosbags-style) type names, like rosidl classes do."""
        return {name: str(detail) for name, _, detail in cls._FIELDS}

    def __eq__(self, other):
        if not isinstance(other, self.__class__):
            return False
        for name, _, _ in self._FIELDS:
            mine, theirs = getattr(self, name), getattr(other, name)
            if isinstance(mine, numpy.ndarray):
                if not numpy.array_equal(mine, theirs):
                    return False
            elif mine != theirs:
                return False
        return True

    def __repr__(self):
        args = ', '.join(f'{name}={getattr(self, name)!r}' for name, _, _ in self._FIELDS)
        return f'{self.__module__}.{type(self).__name__}({args})'


def _make_property(name, kind, detail):
    def getter(self):
        return getattr(self, '_' + name)

    def setter(self, value):
        setattr(self, '_' + name, _convert(kind, detail, value))
    return property(getter, setter, doc=f"Message field '{name}'.")


def get_class(msgtype):
    """Return the double class for e.g. ``'sensor_msgs/msg/JointState'``."""
    if msgtype not in _CLASSES:
        consts, fields = TYPESTORE.fielddefs[msgtype]
        package, _, name = msgtype.split('/')
        specs = tuple((fname, *_spec(node)) for fname, node in fields if fname != _HIDDEN)
        namespace = {'__slots__': tuple('_' + f for f, _, _ in specs),
                     '__module__': package + '.msg', '_FIELDS': specs, '_TYPE': msgtype}
        for cname, ctype, cvalue in consts:
            namespace[cname] = bytes([cvalue]) if ctype == 'byte' else cvalue
        for fname, kind, detail in specs:
            namespace[fname] = _make_property(fname, kind, detail)
        _CLASSES[msgtype] = type(name, (MessageBase,), namespace)
    return _CLASSES[msgtype]


def check_message(msg, path=''):
    """Raise TypeError where real rclpy would refuse or corrupt the message on publish."""
    for name, kind, detail in type(msg)._FIELDS:
        value, where = getattr(msg, name), f'{path}{name}'
        items = [value]
        if kind in ('seq', 'array'):
            if isinstance(value, (str, bytes)) or not hasattr(value, '__len__'):
                raise TypeError(f"The '{where}' field must be a set or sequence")
            if kind == 'array' and len(value) != detail[2]:
                raise TypeError(f"The '{where}' field must have length {detail[2]}")
            if detail[0] == 'base' and detail[1] in _CODES:
                continue  # already converted to array.array / numpy.ndarray
            kind, detail, items = detail[0], detail[1], list(value)
        for item in items:
            if kind == 'msg':
                if not isinstance(item, get_class(detail)):
                    raise TypeError(f"The '{where}' field must be a sub message of type "
                                    f"'{detail}'")
                check_message(item, where + '.')
            elif not isinstance(item, _pytype(detail)) or (
                    detail == 'byte' and len(item) != 1):
                raise TypeError(f"The '{where}' field must be of type "
                                f"'{_pytype(detail).__name__}', got {item!r}")


def msgtype_of(msg):
    """Return 'pkg/msg/Name' for a real rclpy or a double message instance."""
    return f'{type(msg).__module__.split(".")[0]}/msg/{type(msg).__name__}'


def _lookup(msgtype):
    package, _, name = msgtype.split('/')
    return getattr(importlib.import_module(package + '.msg'), name)


def from_rosbags(obj):
    """Convert a rosbags message object to the active ``<pkg>.msg`` class (real or double)."""
    msg = _lookup(obj.__msgtype__)()
    for fname, node in TYPESTORE.fielddefs[obj.__msgtype__][1]:
        if fname == _HIDDEN:
            continue
        kind, detail = _spec(node)
        value = getattr(obj, fname)
        if kind == 'msg':
            value = from_rosbags(value)
        elif kind == 'base' and detail == 'byte':
            value = bytes([value])
        elif kind in ('seq', 'array') and detail[0] == 'msg':
            value = [from_rosbags(item) for item in value]
        elif kind in ('seq', 'array') and detail[1] == 'byte':
            value = [bytes([item]) for item in value]
        elif kind == 'seq' and detail[1] in _CODES:
            value = array.array(_CODES[detail[1]], numpy.asarray(value).tolist())
        elif kind == 'array' and detail[1] in _CODES:
            value = numpy.array(value, dtype=numpy.dtype(_CODES[detail[1]]))
        else:
            value = list(value) if kind in ('seq', 'array') else value
        setattr(msg, fname, value)
    return msg


def to_rosbags(msg, msgtype=None):
    """Convert a real rclpy or double message to a rosbags object (for serialize_cdr)."""
    msgtype = msgtype or msgtype_of(msg)
    values = {}
    for fname, node in TYPESTORE.fielddefs[msgtype][1]:
        if fname == _HIDDEN:
            values[fname] = 0
            continue
        kind, detail = _spec(node)
        value = getattr(msg, fname)
        if kind == 'msg':
            value = to_rosbags(value, detail)
        elif kind == 'base' and detail == 'byte':
            value = value[0]
        elif kind in ('seq', 'array') and detail[0] == 'msg':
            value = [to_rosbags(item, detail[1]) for item in value]
        elif kind in ('seq', 'array') and detail[1] == 'byte':
            value = numpy.array([item[0] for item in value], dtype=numpy.uint8)
        elif kind in ('seq', 'array') and detail[1] in _CODES:
            value = numpy.array(value, dtype=numpy.dtype(_CODES[detail[1]]))
        elif kind in ('seq', 'array'):
            value = list(value)
        values[fname] = value
    return TYPESTORE.types[msgtype](**values)
