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
A thruster vehicle's command message as a body wrench, described by data (YAML).

A mapping names the command topic, its message type (with its definition when
the bags do not carry it), the message field holding one value per thruster
(bool switches, or numbers: duty cycles, throttles) and each thruster's body-frame
direction, position and force. Thruster ``i`` with value ``v_i`` pushes with
``v_i * force_i * d_i`` at ``r_i``; the body wrench about the body origin is the
sum of ``(f, r x f)``. The freeflyer2 testbed's mapping ships as
``config/thrusters/freeflyer2.yaml`` (:func:`freeflyer2_mapping`).
"""

from __future__ import annotations

from dataclasses import dataclass
import os
from typing import Any, Callable, Optional

import numpy as np
import yaml

from reduced_dynamics.bag.reader import open_bag
from reduced_dynamics.resources import config_path

#: The shipped example: freeflyer2's ff_msgs/msg/ThrusterCommand (8 switches).
FREEFLYER2 = 'thrusters/freeflyer2.yaml'


@dataclass(frozen=True)
class Thruster:
    """One thruster: body-frame unit direction, position [m] and force [N] at value 1."""

    direction: tuple[float, float, float]
    position: tuple[float, float, float]
    force: float

    def unit_wrench(self) -> np.ndarray:
        """Return the body wrench (fx, fy, fz, tx, ty, tz) at value 1, about the origin."""
        force = self.force * np.array(self.direction)
        return np.concatenate([force, np.cross(self.position, force)])


def _vector(value: Any, what: str) -> tuple[float, float, float]:
    try:
        vector = np.array(value, dtype=float).reshape(3)
    except (TypeError, ValueError):
        raise ValueError(f'{what} must be 3 numbers, got {value!r}') from None
    if not np.all(np.isfinite(vector)):
        raise ValueError(f'{what} must be finite, got {value!r}')
    return tuple(float(v) for v in vector)


@dataclass(frozen=True)
class CommandMapping:
    """A command message type and the thrusters its values switch (see the module doc)."""

    topic: str
    msgtype: str
    field: str
    thrusters: tuple[Thruster, ...]
    definition: str = ''
    name: str = ''

    @classmethod
    def from_mapping(cls, data: Any, source: str = 'command mapping') -> 'CommandMapping':
        """Return the mapping of a parsed YAML document; ValueError names what is wrong."""
        if not isinstance(data, dict):
            raise ValueError(f'{source}: expected a mapping with command and thrusters')
        command = data.get('command')
        if not isinstance(command, dict):
            raise ValueError(f'{source}: needs a "command" entry (topic, type, field)')
        missing = [k for k in ('topic', 'type', 'field') if not command.get(k)]
        if missing:
            raise ValueError(f'{source}: command needs {", ".join(missing)}')
        entries = data.get('thrusters')
        if not isinstance(entries, list) or not entries:
            raise ValueError(f'{source}: needs a non-empty "thrusters" list')
        thrusters = []
        for i, entry in enumerate(entries):
            what = f'{source}: thruster {i}'
            if not isinstance(entry, dict):
                raise ValueError(f'{what}: expected direction, position and force')
            unknown = sorted(set(entry) - {'direction', 'position', 'force'})
            if unknown:
                raise ValueError(f'{what}: unknown keys {unknown}')
            direction = np.array(_vector(entry.get('direction'), f'{what} direction'))
            norm = float(np.linalg.norm(direction))
            if norm == 0.0:
                raise ValueError(f'{what}: direction must not be zero')
            try:
                force = float(entry.get('force'))
            except (TypeError, ValueError):
                raise ValueError(f'{what}: force must be a number, got '
                                 f'{entry.get("force")!r}') from None
            if not (np.isfinite(force) and force > 0.0):
                raise ValueError(f'{what}: force must be finite and > 0, got {force!r}')
            thrusters.append(Thruster(tuple(float(v) for v in direction / norm),
                                      _vector(entry.get('position'), f'{what} position'),
                                      force))
        topic = str(command['topic'])
        return cls(topic if topic.startswith('/') else '/' + topic, str(command['type']),
                   str(command['field']), tuple(thrusters),
                   str(command.get('definition') or ''), str(data.get('name') or ''))

    @classmethod
    def load(cls, path: str | os.PathLike) -> 'CommandMapping':
        """Return the mapping of a YAML file."""
        with open(path, encoding='utf-8') as stream:
            try:
                data = yaml.safe_load(stream)
            except yaml.YAMLError as error:
                raise ValueError(f'{path}: not valid YAML: {error}') from None
        return cls.from_mapping(data, str(path))

    @property
    def units(self) -> np.ndarray:
        """Return the (thrusters, 6) body wrenches at value 1."""
        return np.array([t.unit_wrench() for t in self.thrusters])

    def wrench(self, values: Any) -> np.ndarray:
        """Return the body wrench [fx fy fz tx ty tz] of one message's thruster values."""
        values = np.asarray(values, dtype=float).reshape(-1)
        if len(values) != len(self.thrusters):
            raise ValueError(f'{self.msgtype}.{self.field} has {len(values)} values, the '
                             f'mapping {len(self.thrusters)} thrusters')
        return values @ self.units

    def typestore(self) -> Any:
        """Return a Jazzy typestore knowing the command type (from ``definition``)."""
        from rosbags.typesys import get_types_from_msg, get_typestore, Stores
        store = get_typestore(Stores.ROS2_JAZZY)
        if self.definition and self.msgtype not in store.fielddefs:
            store.register(get_types_from_msg(self.definition, self.msgtype))
        return store

    def decoder(self, reader: Any) -> Callable[[bytes], Any]:
        """
        Return CDR bytes -> message (None: undecodable, counted by ``reader``).

        With ``definition`` the messages are decoded by it; without, by the
        definition the bag carries.
        """
        if not self.definition:
            return reader.deserializer(self.topic, self.msgtype)
        store = self.typestore()
        return lambda data: store.deserialize_cdr(data, self.msgtype)

    def stamp(self, msg: Any, record_ns: int) -> int:
        """Return the header stamp [ns], or the record time without a header or at 0."""
        header = getattr(msg, 'header', None)
        stamp = 0 if header is None else \
            header.stamp.sec * 1_000_000_000 + header.stamp.nanosec
        return stamp or record_ns

    def read_commands(self, bag: str, start_ns: Optional[int] = None,
                      end_ns: Optional[int] = None) -> tuple[np.ndarray, np.ndarray]:
        """
        Return the command stamps [ns] and body wrenches (rows) of ``bag``, in stamp order.

        The stamp is :meth:`stamp`'s; messages are decoded by :meth:`decoder`.
        """
        stamps, wrenches = [], []
        with open_bag(bag) as reader:
            if reader.topics().get(self.topic) is None:
                raise ValueError(f'{bag}: no command topic {self.topic} ({self.msgtype})')
            decode = self.decoder(reader)
            for message in reader.raw_messages([self.topic], start_ns, end_ns):
                if message.msgtype != self.msgtype:
                    raise ValueError(f'{bag}: {self.topic} carries {message.msgtype}, '
                                     f'the mapping expects {self.msgtype}')
                msg = decode(bytes(message.data))
                if msg is None:  # undecodable: counted by the reader
                    continue
                stamps.append(self.stamp(msg, message.timestamp_ns))
                wrenches.append(self.wrench(getattr(msg, self.field)))
        order = np.argsort(stamps, kind='stable')
        return (np.array(stamps, dtype=np.int64)[order],
                np.array(wrenches).reshape(-1, 6)[order])


def freeflyer2_mapping() -> CommandMapping:
    """Return the shipped freeflyer2 mapping (config/thrusters/freeflyer2.yaml)."""
    return CommandMapping.load(config_path(FREEFLYER2))
