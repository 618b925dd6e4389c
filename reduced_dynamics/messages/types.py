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
Message class sources: rosbags typestore classes or rclpy-generated classes.

The ``*_to_ros`` converters build messages only through a :class:`MessageTypes`
object, so the same code produces rosbags dataclasses (for bag writing and
tests) or real rclpy messages (inside nodes).  The two sources differ in:

* ``float64[]`` (unbounded sequence) fields: rosbags wants numpy arrays, rclpy
  stores ``array.array('d')`` and rejects numpy arrays in its setters;
* ``byte`` fields (e.g. DiagnosticStatus.level): rosbags uses ``int``, rclpy
  uses a length-1 ``bytes``;
* constructors: rosbags requires every field, rclpy has defaults.  The
  converters therefore always pass every field as a keyword argument.

Fixed-size float arrays (e.g. covariance ``float64[36]``) are numpy float64
arrays in both sources.
"""

from abc import ABC, abstractmethod
import array
from collections.abc import Callable
import importlib
from types import ModuleType
from typing import Any, Optional

import numpy as np
from numpy.typing import ArrayLike


def split_msgtype(msgtype: str) -> tuple[str, str, str]:
    """Split ``'pkg/msg/Name'`` into its three parts (raises ValueError otherwise)."""
    parts = msgtype.split('/')
    if len(parts) != 3 or not all(parts):
        raise ValueError(f'message type must look like "pkg/msg/Name", got {msgtype!r}')
    return parts[0], parts[1], parts[2]


class MessageTypes(ABC):
    """Source of message classes plus the field-encoding conventions of that source."""

    def __init__(self) -> None:
        """Start with no class looked up."""
        # Classes found so far (a failed lookup is not kept): conversions create several
        # messages per sample, and a lookup with its name check cost as much as the rest.
        self._classes: dict[str, type] = {}

    def get(self, msgtype: str) -> type:
        """Return the message class for ``'pkg/msg/Name'`` (LookupError if unknown)."""
        cls = self._classes.get(msgtype)
        if cls is None:
            cls = self._classes[msgtype] = self._lookup(msgtype)
        return cls

    @abstractmethod
    def _lookup(self, msgtype: str) -> type:
        """Find the class of ``msgtype`` in the source (LookupError if unknown)."""

    @abstractmethod
    def float_seq(self, values: ArrayLike) -> Any:
        """Encode a 1-D float sequence for a ``float64[]`` field."""

    @abstractmethod
    def byte(self, value: int) -> Any:
        """Encode an integer 0..255 for a ``byte`` field."""

    def fixed_float_array(self, values: ArrayLike, size: int) -> np.ndarray:
        """Encode a fixed-size ``float64[size]`` field (numpy in both sources)."""
        arr = np.ascontiguousarray(values, dtype=np.float64).reshape(-1)
        if arr.size != size:
            raise ValueError(f'expected {size} values for fixed-size array, got {arr.size}')
        return arr

    def create(self, msgtype: str, **fields: Any) -> Any:
        """Instantiate ``msgtype`` with keyword fields (pass all fields)."""
        return self.get(msgtype)(**fields)


def _check_byte(value: int) -> int:
    """Validate a byte value."""
    value = int(value)
    if not 0 <= value <= 255:
        raise ValueError(f'byte value must be in 0..255, got {value}')
    return value


class RosbagsTypes(MessageTypes):
    """Classes from a rosbags typestore (default: the process's shared ROS 2 Jazzy store)."""

    def __init__(self, typestore: Optional[Any] = None) -> None:
        """Wrap ``typestore`` (a ``rosbags.typesys.store.Typestore``)."""
        if typestore is None:
            from reduced_dynamics.messages.typestore import jazzy_typestore
            typestore = jazzy_typestore()
        super().__init__()
        self.typestore = typestore

    def _lookup(self, msgtype: str) -> type:
        """Return the typestore class for ``msgtype``."""
        split_msgtype(msgtype)
        try:
            return self.typestore.types[msgtype]
        except KeyError:
            msg = f'message type {msgtype!r} is not in the rosbags typestore'
            raise LookupError(msg) from None

    def float_seq(self, values: ArrayLike) -> np.ndarray:
        """Return a contiguous 1-D float64 numpy array."""
        return np.ascontiguousarray(values, dtype=np.float64).reshape(-1)

    def byte(self, value: int) -> int:
        """Return the byte as a plain int."""
        return _check_byte(value)


class RclpyTypes(MessageTypes):
    """
    Classes from rclpy message packages (``sensor_msgs.msg`` ...), imported lazily.

    ``importer`` defaults to :func:`importlib.import_module`; tests inject a
    fake namespace so that no ROS installation is needed.
    """

    def __init__(self, importer: Callable[[str], ModuleType] = importlib.import_module) -> None:
        """Create a lazily importing class source."""
        super().__init__()
        self._importer = importer

    def _lookup(self, msgtype: str) -> type:
        """Import ``pkg.msg`` and return its ``Name`` attribute."""
        pkg, sub, name = split_msgtype(msgtype)
        try:
            return getattr(self._importer(f'{pkg}.{sub}'), name)
        except (ImportError, AttributeError) as exc:
            raise LookupError(f'cannot import message type {msgtype!r}: {exc}') from exc

    def float_seq(self, values: ArrayLike) -> array.array:
        """Return ``array.array('d')`` (rclpy rejects numpy arrays for ``float64[]``)."""
        arr = np.ascontiguousarray(values, dtype=np.float64).reshape(-1)
        out = array.array('d')
        out.frombytes(arr.tobytes())
        return out

    def byte(self, value: int) -> bytes:
        """Return a length-1 bytes object."""
        return bytes((_check_byte(value),))


def byte_to_int(value: Any) -> int:
    """Decode a ``byte`` field from either source (int or length-1 bytes)."""
    if isinstance(value, (bytes, bytearray, memoryview)):
        if len(value) != 1:
            raise ValueError(f'byte field must hold exactly one byte, got {bytes(value)!r}')
        return int(bytes(value)[0])
    return int(value)
