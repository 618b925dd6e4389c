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
Rosbag2 writer (MCAP storage by default) built on ``rosbags``.

The bag is a directory with ``metadata.yaml`` (rosbag2 metadata version 9,
the version ROS 2 Jazzy writes; 8 is available for Iron-era tools) and one
``<name>.mcap`` file that embeds ``ros2msg`` definitions and RIHS01 type
hashes, so it is self-describing for ``ros2 bag info/play``, Foxglove and the
``mcap`` tooling.  Messages must be rosbags typestore objects (see
:class:`reduced_dynamics.messages.RosbagsTypes`).
"""

from collections import defaultdict
from collections.abc import Mapping
from io import BytesIO
import operator
import os
from pathlib import Path
import shutil
import struct
from types import TracebackType
from typing import Any, Optional, Sequence, Union

import numpy as np
from rosbags.interfaces import (
    Connection,
    Qos,
    QosDurability,
    QosHistory,
    QosLiveliness,
    QosReliability,
    QosTime,
)
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.rosbag2.enums import CompressionMode
from rosbags.rosbag2.storage_mcap import McapWriter, PendingChunk

from reduced_dynamics.bag.errors import BagError, one_line
from reduced_dynamics.messages.typestore import definition, jazzy_typestore

PathLike = Union[str, 'os.PathLike[str]']

_ZERO = QosTime(0, 0)

#: Reliable, volatile, keep-last(10): the rclpy default publisher profile.
QOS_DEFAULT = Qos(
    QosHistory.KEEP_LAST, 10, QosReliability.RELIABLE, QosDurability.VOLATILE,
    _ZERO, _ZERO, QosLiveliness.AUTOMATIC, _ZERO, False)

#: Reliable, transient-local, keep-last(1): latched topics such as robot_description.
QOS_LATCHED = Qos(
    QosHistory.KEEP_LAST, 1, QosReliability.RELIABLE, QosDurability.TRANSIENT_LOCAL,
    _ZERO, _ZERO, QosLiveliness.AUTOMATIC, _ZERO, False)

_STORAGES = {'mcap': StoragePlugin.MCAP, 'sqlite3': StoragePlugin.SQLITE3}
_BAG_SUFFIXES = ('.mcap', '.db3', '.zstd', '.yaml', '.db3-shm', '.db3-wal', '.tmp')


def default_qos(topic: str, msgtype: str) -> Qos:
    """Return QOS_LATCHED for ``*robot_description`` strings, else QOS_DEFAULT."""
    if msgtype == 'std_msgs/msg/String' and topic.rstrip('/').endswith('robot_description'):
        return QOS_LATCHED
    return QOS_DEFAULT


def _remove_existing_bag(path: Path) -> None:
    """Delete ``path`` only if it is (or looks like) a bag directory."""
    if not path.is_dir():
        raise BagError(f'refusing to overwrite {path}: not a directory')
    foreign = [
        p.name for p in path.iterdir() if p.is_dir() or not p.name.endswith(_BAG_SUFFIXES)
    ]
    if foreign:
        raise BagError(
            f'refusing to overwrite {path}: it contains non-bag entries {sorted(foreign)[:5]}')
    shutil.rmtree(path)


#: MCAP Message record up to its data: opcode, record length, channel id,
#: sequence, log time, publish time (rosbags writes 0 and log time twice).
_MCAP_MESSAGE = struct.Struct('<BQHIQQ')
_CHUNK_BYTES = 2**20  # rosbags closes a chunk once it holds more than this


class _McapAppender:
    """
    Append messages straight into the open chunk of rosbags' MCAP storage.

    rosbags spends ~4 us per message (field-by-field BytesIO writes and a
    linear search comparing Connection dataclasses field by field); this does
    the same bookkeeping with one struct.pack. It touches McapWriter and
    Writer internals, so :meth:`attach` accepts only the layout it knows, and
    test_bag_io checks that both paths write byte-identical bags.
    """

    __slots__ = ('writer', 'storage')

    def __init__(self, writer: Writer, storage: McapWriter) -> None:
        self.writer = writer
        self.storage = storage

    @classmethod
    def attach(cls, writer: Writer) -> Optional['_McapAppender']:
        """Return an appender for ``writer``, or None when its internals are unexpected."""
        storage = getattr(writer, 'storage', None)
        chunk = getattr(storage, 'chunk', None)
        known = (
            type(storage) is McapWriter
            and writer.compression_mode in (CompressionMode.NONE, CompressionMode.STORAGE)
            and isinstance(getattr(chunk, 'bio', None), BytesIO)
            and all(hasattr(chunk, a) for a in ('msgs', 'message_start_time',
                                                'message_end_time'))
            and all(hasattr(storage, a) for a in ('channel_stats', 'message_start_time',
                                                  'message_end_time', 'close_chunk', 'bio',
                                                  'chunks', 'compressor', 'compression'))
            and isinstance(chunk, PendingChunk)
            and all(hasattr(writer, a) for a in ('counts', 'min_timestamp', 'max_timestamp')))
        return cls(writer, storage) if known else None

    def write(self, connection_id: int, timestamp: int, data: Union[bytes, memoryview]) -> None:
        """Do what ``Writer.write`` and ``McapWriter.write`` do, in one go."""
        storage, writer = self.storage, self.writer
        chunk = storage.chunk
        bio = chunk.bio
        chunk.msgs[connection_id].append((timestamp, bio.tell()))
        bio.write(_MCAP_MESSAGE.pack(0x05, 22 + len(data), connection_id, 0, timestamp,
                                     timestamp))
        bio.write(data)
        self._widen(timestamp, timestamp)
        storage.channel_stats[connection_id] += 1
        writer.counts[connection_id] += 1
        if bio.tell() > _CHUNK_BYTES:
            self.close_chunk()

    def close_chunk(self) -> None:
        """
        Do what ``McapWriter.close_chunk`` does, the message indexes packed by numpy.

        rosbags writes each index entry with two ``int.to_bytes`` calls (~0.5 us a
        message); here one array per channel. The records are the same bytes.
        """
        storage = self.storage
        chunk, bio = storage.chunk, storage.bio
        data = chunk.bio.getvalue()
        compressed = storage.compressor(data)
        compression = storage.compression.encode()
        packed = (struct.pack('<QQQII', chunk.message_start_time, chunk.message_end_time,
                              len(data), 0, len(compression)) + compression
                  + struct.pack('<Q', len(compressed)))
        chunk_start = bio.tell()
        bio.write(struct.pack('<BQ', 0x06, len(packed) + len(compressed)))
        bio.write(packed)
        bio.write(compressed)
        chunk_end = bio.tell()
        offsets = []
        for cid, msgs in chunk.msgs.items():
            offsets.append(struct.pack('<HQ', cid, bio.tell()))
            index = np.array(msgs, dtype='<u8').tobytes() if msgs else b''
            bio.write(struct.pack('<BQHI', 0x07, 6 + len(index), cid, len(index)))
            bio.write(index)
        record = BytesIO()  # the Chunk Index, written by McapWriter.close (a BytesIO there)
        record.write(struct.pack('<QQQQI', chunk.message_start_time, chunk.message_end_time,
                                 chunk_start, chunk_end - chunk_start, len(offsets) * 10))
        record.write(b''.join(offsets))
        record.write(struct.pack('<QI', bio.tell() - chunk_end, len(compression)))
        record.write(compression)
        record.write(struct.pack('<QQ', len(compressed), len(data)))
        storage.chunks.append(record)
        storage.chunk = PendingChunk(2**63 - 1, 0, BytesIO(), defaultdict(list))

    def write_rows(self, connection_ids: Sequence[int], stamps: np.ndarray,
                   records: Sequence[np.ndarray]) -> None:
        """
        Write row k of every ``records[t]`` on ``connection_ids[t]`` at ``stamps[k]``.

        The bytes and indexes of :meth:`write` called row by row, topic by topic:
        the Message records of whole rows are one array written at once, the chunk
        index gets their offsets by ``list.extend``; the row during which a chunk
        fills up goes message by message, so the chunk closes where it would.
        """
        count = len(stamps)
        heads, at = [], 0
        for cid, part in zip(connection_ids, records):
            heads.append((cid, at, part))
            at += _MCAP_MESSAGE.size + part.shape[1]
        row = at
        block = np.empty((count, row), np.uint8)
        for cid, at, part in heads:
            size = part.shape[1]
            block[:, at:at + _MCAP_MESSAGE.size] = np.frombuffer(
                _MCAP_MESSAGE.pack(0x05, 22 + size, cid, 0, 0, 0), np.uint8)
            block[:, at + 15:at + 23].view('<u8')[:, 0] = stamps  # log time
            block[:, at + 23:at + 31].view('<u8')[:, 0] = stamps  # publish time
            block[:, at + _MCAP_MESSAGE.size:at + _MCAP_MESSAGE.size + size] = part
        stamp_list = stamps.tolist()
        start = 0
        while start < count:
            tell = self.storage.chunk.bio.tell()
            # Whole rows that leave the chunk at or below its limit: no close among them.
            whole = min(count - start, max(0, (_CHUNK_BYTES - tell) // row))
            if whole:
                self._append_block(block[start:start + whole], stamp_list[start:start + whole],
                                   heads, row, tell)
                start += whole
            if start < count:
                # This row fills the chunk: message by message, closing where write does.
                for cid, at, part in heads:
                    self.write(cid, stamp_list[start], part[start].tobytes())
                start += 1

    def _append_block(self, block: np.ndarray, stamps: list, heads: list, row: int,
                      tell: int) -> None:
        """Append whole rows of Message records at chunk offset ``tell``."""
        storage, writer = self.storage, self.writer
        chunk = storage.chunk
        chunk.bio.write(block.tobytes())
        count = len(stamps)
        for cid, at, _ in heads:
            chunk.msgs[cid].extend(zip(stamps, range(tell + at, tell + at + count * row, row)))
            storage.channel_stats[cid] += count
            writer.counts[cid] += count
        self._widen(min(stamps), max(stamps))

    def _widen(self, low: int, high: int) -> None:
        """Widen the chunk's, the file's and the writer's time ranges to [low, high]."""
        for holder in (self.storage.chunk, self.storage):
            if low < holder.message_start_time:
                holder.message_start_time = low
            if high > holder.message_end_time:
                holder.message_end_time = high
        writer = self.writer
        if low < writer.min_timestamp:
            writer.min_timestamp = low
        if high > writer.max_timestamp:
            writer.max_timestamp = high


class BagWriter:
    """
    Write a rosbag2 bag; use as a context manager.

    Example::

        with BagWriter(out, {'/joint_states': 'sensor_msgs/msg/JointState'}) as bag:
            bag.write('/joint_states', t_ns, msg)

    """

    def __init__(
        self,
        path: PathLike,
        topics: Mapping[str, str],
        *,
        typestore: Optional[Any] = None,
        overwrite: bool = False,
        storage: str = 'mcap',
        version: int = 9,
        qos: Optional[Mapping[str, Qos]] = None,
    ) -> None:
        """
        Prepare a writer for ``topics`` (``{topic: 'pkg/msg/Type'}``).

        ``typestore`` must know every type (default: the process's shared Jazzy store,
        which holds no custom type: pass a store of your own with them registered).  ``qos``
        overrides the offered QoS recorded per topic (see :func:`default_qos`).
        An existing ``path`` raises BagError unless ``overwrite`` is True, in
        which case only a directory holding nothing but bag files is removed.
        """
        self.path = Path(path)
        self.typestore = jazzy_typestore() if typestore is None else typestore
        if storage not in _STORAGES:
            raise BagError(f'unknown storage {storage!r}; expected one of {sorted(_STORAGES)}')
        if version not in (8, 9):
            raise BagError(f'unsupported rosbag2 metadata version {version}; expected 8 or 9')
        if not topics:
            raise BagError('no topics given')
        unknown = sorted({t for t in topics.values() if t not in self.typestore.fielddefs})
        if unknown:
            raise BagError(f'message types not in the typestore: {unknown}')
        qos = dict(qos or {})
        extra = sorted(set(qos) - set(topics))
        if extra:
            raise BagError(f'qos given for unknown topics: {extra}')
        self.topics = dict(topics)
        self._qos = {t: qos.get(t, default_qos(t, m)) for t, m in self.topics.items()}
        self._storage = storage
        self._version = version
        self._overwrite = overwrite
        self._writer: Optional[Writer] = None
        self._appender: Optional[_McapAppender] = None
        self._connections: dict[str, Connection] = {}
        self.message_counts: dict[str, int] = {t: 0 for t in self.topics}
        if self.path.exists() and not overwrite:
            raise BagError(f'output {self.path} exists already (pass overwrite=True to replace)')

    def open(self) -> 'BagWriter':
        """Create the bag directory and register all topics."""
        if self._writer is not None:
            raise BagError(f'bag {self.path} is already open')
        if self.path.exists():
            if not self._overwrite:
                raise BagError(f'output {self.path} exists already')
            _remove_existing_bag(self.path)
        try:
            writer = Writer(
                self.path, version=self._version, storage_plugin=_STORAGES[self._storage])
            writer.open()
        except Exception as exc:
            raise BagError(f'cannot create bag {self.path}: {one_line(exc)}') from exc
        try:
            for topic, msgtype in self.topics.items():
                msgdef, rihs01 = definition(self.typestore, msgtype)
                self._connections[topic] = writer.add_connection(
                    topic, msgtype, msgdef=msgdef, rihs01=rihs01,
                    offered_qos_profiles=[self._qos[topic]])
        except Exception as exc:
            writer.abort()
            raise BagError(f'cannot register topics in {self.path}: {one_line(exc)}') from exc
        self._writer = writer
        self._appender = _McapAppender.attach(writer)
        return self

    def write(self, topic: str, timestamp_ns: int, msg: Any) -> None:
        """Serialize ``msg`` (a typestore object) to CDR and write it at ``timestamp_ns``."""
        msgtype = self.topics.get(topic)
        if msgtype is None:
            raise BagError(f'topic {topic!r} was not declared for {self.path}')
        have = getattr(msg, '__msgtype__', None)
        if have != msgtype:
            raise BagError(f'topic {topic!r} expects {msgtype}, got {have or type(msg).__name__}')
        try:
            data = self.typestore.serialize_cdr(msg, msgtype)
        except Exception as exc:
            raise BagError(f'cannot serialize {msgtype} for {topic!r}: {one_line(exc)}') from exc
        self.write_raw(topic, timestamp_ns, data)

    def write_raw(self, topic: str, timestamp_ns: int, data: Union[bytes, memoryview]) -> None:
        """Write already serialized CDR ``data`` (including the 4-byte header)."""
        if self._writer is None:
            raise BagError(f'bag {self.path} is not open')
        conn = self._connections.get(topic)
        if conn is None:
            raise BagError(f'topic {topic!r} was not declared for {self.path}')
        if type(timestamp_ns) is not int:  # plain ints (the hot path) need no conversion
            try:
                if isinstance(timestamp_ns, bool):
                    raise TypeError
                timestamp_ns = operator.index(timestamp_ns)
            except TypeError:
                raise BagError(
                    f'timestamp_ns must be an integer, got {timestamp_ns!r}') from None
        if not 0 <= timestamp_ns < 2**63:
            raise BagError(f'timestamp_ns out of range: {timestamp_ns}')
        if self._appender is not None:
            self._appender.write(conn.id, timestamp_ns, data)
        else:
            self._writer.write(conn, timestamp_ns, data)
        self.message_counts[topic] += 1

    def write_rows(self, topics: Sequence[str], stamps_ns: np.ndarray,
                   records: Sequence[np.ndarray]) -> None:
        """
        Write K rows of serialized messages: row k of ``records[t]`` on ``topics[t]``.

        ``records[t]``: (K, size_t) uint8, one CDR message per row (header included;
        :mod:`reduced_dynamics.messages.cdr_columns`); ``stamps_ns`` (K,) integers.
        The same bag as :meth:`write_raw` called for each row, topic by topic.
        """
        if self._writer is None:
            raise BagError(f'bag {self.path} is not open')
        connections = []
        for topic in topics:
            conn = self._connections.get(topic)
            if conn is None:
                raise BagError(f'topic {topic!r} was not declared for {self.path}')
            connections.append(conn)
        stamps = np.asarray(stamps_ns)
        if stamps.dtype.kind not in 'iu':
            raise BagError(f'timestamps must be integers, got {stamps.dtype}')
        count = len(stamps)
        if any(part.shape[0] != count for part in records) or len(records) != len(topics):
            raise BagError('one record per row and topic expected')
        if count == 0:
            return
        if int(stamps.min()) < 0 or int(stamps.max()) >= 2**63:
            raise BagError(f'timestamp_ns out of range: {stamps.min()}..{stamps.max()}')
        if self._appender is not None:
            self._appender.write_rows([c.id for c in connections],
                                      stamps.astype(np.int64, copy=False), records)
        else:
            for k, stamp in enumerate(stamps.tolist()):
                for conn, part in zip(connections, records):
                    self._writer.write(conn, stamp, part[k].tobytes())
        for topic in topics:
            self.message_counts[topic] += count

    def close(self) -> None:
        """Finish the storage file and write metadata.yaml (idempotent)."""
        writer, self._writer, self._appender = self._writer, None, None
        if writer is not None:
            try:
                writer.close()
            except Exception as exc:
                raise BagError(f'cannot finalize bag {self.path}: {one_line(exc)}') from exc

    def abort(self) -> None:
        """Close without writing the index or metadata (leaves a partial bag)."""
        writer, self._writer, self._appender = self._writer, None, None
        if writer is not None:
            writer.abort()

    def __enter__(self) -> 'BagWriter':
        """Open (if needed) and return self."""
        if self._writer is None:
            self.open()
        return self

    def __exit__(
        self,
        exc_type: Optional[type[BaseException]],
        exc_val: Optional[BaseException],
        exc_tb: Optional[TracebackType],
    ) -> None:
        """Close normally, or finalize what was written if the block raised."""
        self.close()
