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
Reading damaged storage files: every intact message, and a record of what was lost.

rosbags' storage readers stop at the first damaged byte. The readers here are
drop-in subclasses (rosbags' own code reads every intact file and chunk, so the
clean path is unchanged) that take over where rosbags gives up:

MCAP
  - **No summary** (a recording cut short: the end magic, footer or summary is
    missing or invalid): the data section is scanned record by record from the
    start; each chunk is parsed and, when it carries a CRC, validated with the
    ``mcap`` library (``Chunk.read``, ``breakup_chunk``); the message index
    records after a chunk give its per-channel counts. A record that does not
    parse (a damaged chunk length, compression or opcode) is skipped by
    resynchronising on the next plausible chunk: a consistent header (length,
    compression and data size agree, the record fits in the file) and contents
    that validate (the CRC when there is one, else every record parses). The
    time fields are not framing: a chunk whose records validate takes its times
    from them. Schemas and channels are kept from a lost chunk when they parse
    (writers define them in the first chunk only).
  - **A chunk that fails** (CRC mismatch, bad framing, cut by the end of the
    file): its messages are salvaged one by one, at the offsets of its message
    index when there is one (each must be a message record of that channel and
    log time), else by walking its records and resynchronising on the next
    plausible message record. A compressed chunk that does not decompress, or
    a chunk whose CRC does not match, is lost whole (its contents cannot be
    trusted). Messages whose framing is intact but whose payload is garbled
    cannot be told apart without a CRC (rosbags writes chunks without one):
    they reach the deserializer, which skips what does not decode.

sqlite3
  - A database sqlite cannot fully read (truncated file, corrupted page) is read
    by row-id ranges, bisecting around the ranges sqlite refuses, so every row
    sqlite can still return is returned (in log-time order within windows of
    rows, which rosbag2 inserts in time order).
  - A file cut short is read from two copies padded to its full page count, one
    with 0x00 bytes and one with 0xFF bytes; a row is delivered only when both
    copies return it identically, so a row whose payload (or the b-tree cell or
    overflow chain holding it) extends past the readable end is counted as lost,
    never delivered with fabricated bytes.

Every damaged region becomes a :class:`Damage` with its kind, file, byte offset,
length, chunk index and the messages lost (per topic when known).
"""

from __future__ import annotations

from dataclasses import dataclass, field
import heapq
import io
import mmap
import os
import struct
import tempfile
from typing import Any, Callable, Iterator, Optional
import zlib

import apsw
from mcap.data_stream import ReadDataStream
from mcap.records import Channel as McapChannel, Chunk, MessageIndex, Schema as McapSchema
from mcap.stream_reader import breakup_chunk
from rosbags.interfaces import Connection, ConnectionExtRosbag2
from rosbags.rosbag2 import Reader
from rosbags.rosbag2.errors import ReaderError
from rosbags.rosbag2.reader import DirectoryReader
from rosbags.rosbag2.storage_mcap import (
    Channel,
    ChunkInfo,
    get_msgdef,
    get_qos,
    McapReader,
    Msg,
    msgsrc,
    Schema,
    Statistics,
)
from rosbags.rosbag2.storage_sqlite3 import Sqlite3Reader

_RECORD = struct.Struct('<BQ')
_MESSAGE = struct.Struct('<BQHIQQ')  # opcode, length, channel, sequence, log, publish time
_CHUNK_HEAD = struct.Struct('<QQQII')  # start, end, uncompressed size, crc, compression length
_U64 = struct.Struct('<Q')
_OPCODE_MAX = 0x0F
_COMPRESSIONS = ('', 'lz4', 'zstd')
_SQLITE_WINDOW = 4096  # rows per range query in damaged sqlite files
_SQLITE_TAIL_WINDOWS = 4  # unreadable windows past the last readable row before giving up


@dataclass
class Damage:
    """One damaged region of a storage file."""

    file: str
    kind: str  #: truncated, corrupt_chunk, crc_mismatch, unparsable, sqlite_rows
    offset: Optional[int]  #: byte offset in the file (MCAP), None for sqlite
    length: int  #: bytes that could not be read (MCAP), 0 for sqlite
    detail: str
    chunk: Optional[int] = None  #: chunk index in file order (MCAP)
    #: messages lost, None when nothing says how many were there
    messages_lost: Optional[int] = None
    messages_recovered: int = 0  #: messages salvaged from inside the damaged region
    topics_lost: dict[str, int] = field(default_factory=dict)
    rows: Optional[tuple[int, int]] = None  #: first and last unreadable row id (sqlite)

    def to_dict(self) -> dict[str, Any]:
        """Return a JSON-ready dict."""
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in self.__dict__.items()}

    def text(self) -> str:
        """Return a one-line description."""
        where = f'offset {self.offset}' if self.offset is not None else ''
        if self.chunk is not None:
            where = f'chunk {self.chunk} at {where}'
        if self.rows is not None:
            where = f'rows {self.rows[0]}..{self.rows[1]}'
        lost = 'unknown number of messages' if self.messages_lost is None \
            else f'{self.messages_lost} messages'
        where = f' ({where})' if where else ''
        parts = [f'{self.kind} in {self.file}{where}: {lost} lost']
        if self.length:
            parts.append(f'{self.length} bytes lost')
        if self.messages_recovered:
            parts.append(f'{self.messages_recovered} salvaged')
        return ', '.join(parts) + f' [{self.detail}]'


def _describe(exc: BaseException) -> str:
    text = ' '.join(str(exc).split())
    return f'{type(exc).__name__}: {text}' if text else type(exc).__name__


# --------------------------------------------------------------------------- MCAP
class TolerantMcapReader(McapReader):
    """rosbags' MCAP storage reader that reads past damage and records it in ``damage``."""

    def __init__(self, path: Any) -> None:
        """Prepare to read ``path``."""
        super().__init__(path)
        self.damage: list[Damage] = []
        self._size = 0
        #: chunk start offset -> {channel id: [(log time, offset in the chunk)]}
        self._indexes: dict[int, dict[int, list[tuple[int, int]]]] = {}
        self._chunk_numbers: dict[int, int] = {}
        #: recovered chunks whose per-channel counts wait for their message index
        self._placeholders: set[int] = set()
        self._pending_loss: Optional[Damage] = None
        #: damage found while scanning, by chunk offset (the salvage completes it)
        self._found: dict[int, Damage] = {}
        #: called with each new Damage (BagReader's strict mode raises from it)
        self.on_damage: Optional[Callable[[Damage], None]] = None

    def _record(self, damage: Damage) -> None:
        self.damage.append(damage)
        if self.on_damage is not None:
            self.on_damage(damage)

    def _open(self) -> None:
        assert self.bio
        self._size = self.bio.seek(0, io.SEEK_END)
        self.bio.seek(0)
        try:
            super()._open()
        except Exception as exc:  # end magic, footer, summary, index: rebuild from the data
            if self.data_start == 0:
                raise  # not an MCAP file, or its header is gone: nothing to resync on
            self._recover(_describe(exc))
        self._chunk_numbers = {c.chunk_start_offset: i for i, c in enumerate(
            sorted(self.chunks, key=lambda c: c.chunk_start_offset))}

    # ------------------------------------------------------------------ scan
    def _recover(self, reason: str) -> None:
        """Rebuild schemas, channels, chunks and statistics by scanning the data section."""
        self.schemas.clear()
        self.channels.clear()
        self.chunks.clear()
        self.connections.clear()
        self.statistics = None
        self.data_end = self._size
        before = len(self.damage)
        with mmap.mmap(self.bio.fileno(), 0, access=mmap.ACCESS_READ) as data:
            self._scan(data, reason)
        if len(self.damage) == before:
            # Only the summary is gone (a recording stopped after its last chunk).
            self._record(Damage(self._name, 'no_summary', None, 0,
                                f'summary rebuilt by scanning the data ({reason})',
                                messages_lost=0))
        counts: dict[int, int] = {}
        for chunk in self.chunks:
            for cid, count in chunk.channel_count.items():
                counts[cid] = counts.get(cid, 0) + count
        total = sum(counts.values())
        self.statistics = Statistics(
            total, len(self.schemas), len(self.channels), 0, 0, len(self.chunks),
            min((c.message_start_time for c in self.chunks), default=0),
            max((c.message_end_time for c in self.chunks), default=0), counts)
        self.connections[:] = [c._replace(msgcount=counts.get(c.id, 0))
                               for c in self.connections]
        self.metadata = self.metadata._replace(
            duration=self.statistics.end_time - self.statistics.start_time + 1 if total else 0,
            start_time=self.statistics.start_time if total else 2**63 - 1,
            end_time=self.statistics.end_time + 1 if total else 0, message_count=total)

    def _scan(self, data: mmap.mmap, reason: str) -> None:
        size = len(data)
        pos = self.data_start
        last_chunk: Optional[int] = None
        number = 0
        while pos < size:
            if pos + 9 > size:
                self._lost_tail(pos, size, 'a record header is cut by the end of the file')
                return
            opcode, length = _RECORD.unpack_from(data, pos)
            end = pos + 9 + length
            header = self._chunk_header(data, pos) if opcode == 0x06 else None
            if header is not None and end > size:
                self._cut_chunk(data, pos, number, reason)
                return
            # A record whose framing is broken says nothing true about where the next
            # record starts (a damaged chunk length, a footer that is not one): resync.
            framed = 0x01 <= opcode <= _OPCODE_MAX and end <= size \
                and (opcode != 0x06 or header is not None) \
                and (opcode != 0x02 or length == 20) and (opcode != 0x0F or length == 4)
            content = bytes(data[pos + 9:end]) if framed else b''
            if framed and opcode in (0x03, 0x04):
                try:
                    record: Any = (McapSchema if opcode == 0x03 else McapChannel).read(
                        ReadDataStream(io.BytesIO(content)))
                except Exception:
                    framed = False
            if not framed:
                resume = self._resync(data, pos + 1)
                if opcode == 0x06 or self._chunk_header(data, pos) is not None:
                    # A chunk (perhaps with a damaged opcode): the schemas and channels may
                    # be defined only in it (the mcap and rosbags writers put them in the
                    # first chunk); keep those that parse, or every later chunk is unreadable.
                    self._definitions(pos + 9 + 40, resume if resume is not None else size)
                    number += 1
                if resume is None:
                    self._lost_tail(pos, size, f'unparsable record (opcode {opcode:#x}, '
                                    f'length {length}) and no chunk after it; {reason}')
                    return
                self._record(Damage(self._name, 'unparsable', pos, resume - pos,
                                    f'unparsable record (opcode {opcode:#x}, length {length})'))
                pos = resume
                continue
            if opcode in (0x02, 0x0F):
                return  # footer or data end: the data section is over
            if opcode == 0x03:
                self._schema(record)
            elif opcode == 0x04:
                self._channel(record)
            elif opcode == 0x06:
                last_chunk = self._chunk(data, pos, length, number, content)
                number += 1
            elif opcode == 0x07 and last_chunk is not None:
                self._message_index(last_chunk, pos, content)
            pos = end

    @property
    def _name(self) -> str:
        return getattr(self.path, 'name', str(self.path))

    def _chunk_header(self, data: Any, pos: int) -> Optional[tuple[int, int, int, int, str, int]]:
        """
        Return (start, end, uncompressed size, crc, compression, data size) if consistent.

        Only the framing is checked (length, compression, sizes): the time fields are
        not needed to read the chunk, and its records give them again (see _chunk).
        """
        size = len(data)
        if pos + 9 + 40 > size:
            return None
        length = _U64.unpack_from(data, pos + 1)[0]
        start, end, usize, crc, clen = _CHUNK_HEAD.unpack_from(data, pos + 9)
        if clen > 4 or pos + 9 + 32 + clen + 8 > size:
            return None
        compression = bytes(data[pos + 41:pos + 41 + clen]).decode('ascii', 'replace')
        csize = _U64.unpack_from(data, pos + 41 + clen)[0]
        if compression not in _COMPRESSIONS or 40 + clen + csize != length:
            return None
        if compression == '' and csize != usize:
            return None
        return start, end, usize, crc, compression, csize

    def _resync(self, data: Any, pos: int) -> Optional[int]:
        """
        Return the offset of the next plausible chunk record at or after ``pos``.

        Plausible: opcode 0x06, a consistent header (see _chunk_header), and contents
        that validate (the CRC matches when there is one, else every record parses);
        or a consistent header cut by the end of the file (the caller salvages it).
        """
        size = len(data)
        while True:
            pos = data.find(b'\x06', pos)
            if pos < 0 or pos + 9 > size:
                return None
            if self._chunk_header(data, pos) is not None:
                end = pos + 9 + _U64.unpack_from(data, pos + 1)[0]
                if end > size:
                    return pos
                try:
                    breakup_chunk(Chunk.read(ReadDataStream(io.BytesIO(
                        bytes(data[pos + 9:end])))), validate_crc=True)
                    return pos
                except Exception:  # not a chunk, or a damaged one: look further
                    pass
            pos += 1

    def _schema(self, schema: McapSchema) -> None:
        self.schemas[schema.id] = Schema(schema.id, schema.name, schema.encoding,
                                         schema.data.decode('utf-8', 'replace'))

    def _channel(self, channel: McapChannel) -> None:
        if channel.id in self.channels:
            return
        schema = self.schemas.get(channel.schema_id)
        name = schema.name if schema else '__schemaless__'
        metadata = b''.join(len(k.encode()).to_bytes(4, 'little') + k.encode()
                            + len(v.encode()).to_bytes(4, 'little') + v.encode()
                            for k, v in channel.metadata.items())
        self.channels[channel.id] = Channel(channel.id, name, channel.topic,
                                            channel.message_encoding, metadata)
        self.connections.append(Connection(
            channel.id, channel.topic, name, get_msgdef(schema), '', 0,
            ConnectionExtRosbag2(channel.message_encoding, get_qos(metadata)), self))

    def _chunk(self, data: Any, pos: int, length: int, number: int,
               content: bytes) -> Optional[int]:
        """Register a complete chunk record; return its offset, or None when it is lost."""
        header = self._chunk_header(data, pos)
        self._pending_loss = None
        try:
            if header is None:
                raise ValueError('inconsistent chunk header')
            chunk = Chunk.read(ReadDataStream(io.BytesIO(content)))
            records = breakup_chunk(chunk, validate_crc=True)
        except Exception as exc:  # CRC mismatch, decompression, framing
            if header is not None and header[3] == 0 and header[4] == '':
                # No CRC, not compressed: its intact messages are salvaged when read.
                self._placeholder(header, pos, length)
                self._found[pos] = Damage(self._name, 'corrupt_chunk', pos, 9 + length,
                                          _describe(exc), chunk=number)
                self._record(self._found[pos])
                return pos
            if header is not None and header[4] == '':
                # Its messages are lost, but not the definitions later chunks rely on.
                self._definitions(pos + 9 + 40, pos + 9 + length)
            kind = 'crc_mismatch' if 'CRC' in type(exc).__name__ else 'corrupt_chunk'
            self._pending_loss = Damage(self._name, kind, pos, 9 + length, _describe(exc),
                                        chunk=number)
            self._record(self._pending_loss)
            return pos if header is not None else None
        counts: dict[int, int] = {}
        times: list[int] = []
        for record in records:
            if isinstance(record, McapSchema):
                self._schema(record)
            elif isinstance(record, McapChannel):
                self._channel(record)
            else:
                counts[record.channel_id] = counts.get(record.channel_id, 0) + 1
                times.append(record.log_time)
        start, end, usize, _, compression, csize = header
        if times and (min(times), max(times)) != (start, end):
            # The header's time fields are damaged; the records (validated above) are not.
            self._record(Damage(self._name, 'corrupt_chunk', pos, 0,
                                f'chunk header times {start}..{end} disagree with its records '
                                f'({min(times)}..{max(times)}); the records\' times are used',
                                chunk=number, messages_lost=0))
            start, end = min(times), max(times)
        self.chunks.append(ChunkInfo(start, end, pos, 9 + length, {}, 0, compression, csize,
                                     usize, counts))
        return pos

    def _message_index(self, chunk_offset: int, pos: int, content: bytes) -> None:
        try:
            index = MessageIndex.read(ReadDataStream(io.BytesIO(content)))
        except Exception:  # a damaged index only costs the salvage its offsets
            return
        self._indexes.setdefault(chunk_offset, {})[index.channel_id] = index.records
        if chunk_offset in self._placeholders:
            chunk = next(c for c in self.chunks if c.chunk_start_offset == chunk_offset)
            if len(self._indexes[chunk_offset]) == 1:  # its first index: counts are known
                chunk.channel_count.clear()
            chunk.channel_count[index.channel_id] = len(index.records)
        pending = self._pending_loss
        if pending is not None and pending.offset == chunk_offset:
            # A lost chunk: its index says what was in it.
            channel = self.channels.get(index.channel_id)
            topic = channel.topic if channel else f'channel {index.channel_id}'
            pending.topics_lost[topic] = pending.topics_lost.get(topic, 0) + len(index.records)
            pending.messages_lost = sum(pending.topics_lost.values())

    def _cut_chunk(self, data: Any, pos: int, number: int, reason: str) -> None:
        """Keep a chunk cut by the end of the file for salvage (see messages())."""
        length = _U64.unpack_from(data, pos + 1)[0]
        self._placeholder(self._chunk_header(data, pos), pos, length)
        self._found[pos] = Damage(self._name, 'truncated', pos, 9 + length - (len(data) - pos),
                                  f'chunk cut by the end of the file; {reason}', chunk=number)
        self._record(self._found[pos])

    def _placeholder(self, header: tuple, pos: int, length: int) -> None:
        """Register a chunk to salvage on reading; every channel may have messages in it."""
        start, end, usize, _, compression, csize = header
        if start > end:  # damaged time fields: every time is possible
            start, end = 0, 2**64 - 1
        if compression == '':
            self._definitions(pos + 9 + 40, min(pos + 9 + length, self._size))
        self.chunks.append(ChunkInfo(start, end, pos, 9 + length, {}, 0, compression, csize,
                                     usize, {cid: 1 for cid in self.channels}))
        self._placeholders.add(pos)

    def _definitions(self, first: int, last: int) -> None:
        """Register the schemas and channels among the intact records of [first, last)."""
        self.bio.seek(first)
        payload = self.bio.read(last - first)
        q = 0
        while q + 9 <= len(payload):
            opcode, length = _RECORD.unpack_from(payload, q)
            end = q + 9 + length
            if not 0x01 <= opcode <= _OPCODE_MAX or end > len(payload):
                return  # damage or the cut: the definitions come first, so stop here
            try:
                if opcode == 0x03:
                    self._schema(McapSchema.read(ReadDataStream(io.BytesIO(payload[q + 9:end]))))
                elif opcode == 0x04:
                    self._channel(McapChannel.read(ReadDataStream(io.BytesIO(
                        payload[q + 9:end]))))
            except Exception:
                return
            q = end

    def _lost_tail(self, pos: int, size: int, detail: str) -> None:
        self._record(Damage(self._name, 'truncated', pos, size - pos, detail))

    # ------------------------------------------------------------------ messages
    def messages(self, connections: Any, start: Optional[int] = None,
                 stop: Optional[int] = None) -> Iterator[tuple[Connection, int, bytes]]:
        """Yield messages as rosbags does; a chunk that fails is salvaged and recorded."""
        assert self.bio
        if not self.chunks:
            yield from self._guarded_scan(connections, start, stop)
            return
        channel_map = {conn.id: conn for conn in connections}
        sources = [
            self._chunk_source(chunk, channel_map,
                               chunk.message_start_time if start is None else start,
                               chunk.message_end_time + 1 if stop is None else stop)
            for chunk in self.chunks
            if (start is None or start < chunk.message_end_time + 1)
            and (stop is None or chunk.message_start_time < stop)
            and any(chunk.channel_count.get(cid, 0) for cid in channel_map)]
        for timestamp, offset, connection, data in heapq.merge(*sources):
            if offset:
                yield connection, timestamp, data

    def _guarded_scan(self, connections: Any, start: Optional[int],
                      stop: Optional[int]) -> Iterator[tuple[Connection, int, bytes]]:
        try:
            yield from super().messages(connections, start, stop)
        except Exception as exc:  # an unchunked file: everything after the damage is lost
            self._record(Damage(self._name, 'unparsable', None, 0, _describe(exc)))

    def _chunk_source(self, chunk: ChunkInfo, channel_map: dict[int, Connection],
                      start: int, stop: int) -> Iterator[Msg]:
        source = msgsrc(chunk, channel_map, start, stop, self.bio)
        yield next(source)  # the chunk's start time, before any reading
        # msgsrc reads, checks and sorts the whole chunk before its first message, so a
        # damaged chunk fails here, before anything of it was yielded.
        try:
            messages = list(source)
        except Exception as exc:  # the chunk is damaged: take what is intact
            yield from self._salvage(chunk, channel_map, start, stop, _describe(exc))
            return
        if start <= chunk.message_start_time and chunk.message_end_time < stop \
                and chunk.chunk_start_offset not in self._placeholders:
            # A damaged channel id drops a message silently: the index says how many
            # there are.
            expected = sum(chunk.channel_count.get(cid, 0) for cid in channel_map)
            if len(messages) != expected:
                yield from self._salvage(chunk, channel_map, start, stop,
                                         f'{len(messages)} messages where the index has '
                                         f'{expected}')
                return
        yield from messages

    def _salvage(self, chunk: ChunkInfo, channel_map: dict[int, Connection], start: int,
                 stop: int, reason: str) -> Iterator[Msg]:
        """Yield the intact messages of a damaged chunk, sorted; record the damage."""
        number = self._chunk_numbers.get(chunk.chunk_start_offset)
        offset = chunk.chunk_start_offset
        data_start = offset + 9 + 40 + len(chunk.compression)
        self.bio.seek(offset + 9 + 24)
        crc = struct.unpack('<I', self.bio.read(4).ljust(4, b'\0'))[0]
        self.bio.seek(data_start)
        payload = self.bio.read(chunk.compressed_size)
        cut = len(payload) < chunk.compressed_size
        damage = self._found.get(offset)
        new = damage is None
        if new:
            damage = Damage(self._name, 'truncated' if cut else 'corrupt_chunk', offset,
                            chunk.chunk_length, reason, chunk=number)
        index = self._chunk_index(chunk)
        if chunk.compression or (crc and not cut and zlib.crc32(payload) != crc):
            # A compressed chunk does not decompress in part, and a CRC mismatch does not
            # say where the damage is: the chunk is lost whole.
            if not chunk.compression:
                damage.kind = 'crc_mismatch'
            if index:
                damage.topics_lost = {self._topic(c): len(e) for c, e in index.items()}
            damage.messages_lost = sum(len(e) for e in index.values()) if index else None
            if new:
                self._record(damage)
            return
        found: list[tuple[int, int, bytes]] = []
        if index:
            lost: dict[int, int] = {}
            for cid, entries in index.items():
                for log_time, where in entries:
                    message = _message_at(payload, where, cid, log_time)
                    if message is None:
                        lost[cid] = lost.get(cid, 0) + 1
                    else:
                        found.append(message)
            damage.topics_lost = {self._topic(cid): n for cid, n in lost.items()}
            damage.messages_lost = sum(lost.values())
            damage.length = 0
        else:
            found, skipped = _walk(payload, set(self.channels), chunk.message_start_time,
                                   chunk.message_end_time)
            damage.length = skipped + (chunk.chunk_length - 9 - 40 - len(chunk.compression)
                                       - len(payload))
            damage.messages_lost = None
        damage.messages_recovered = len(found)
        if new:
            self._record(damage)
        messages = [Msg(log_time, offset, channel_map[cid], body)
                    for log_time, cid, body in found
                    if cid in channel_map and start <= log_time < stop]
        yield from sorted(messages, key=lambda m: m.timestamp)

    def _topic(self, cid: int) -> str:
        channel = self.channels.get(cid)
        return channel.topic if channel else f'channel {cid}'

    def _chunk_index(self, chunk: ChunkInfo) -> dict[int, list[tuple[int, int]]]:
        """Return the chunk's message index {channel: [(log time, offset)]} if readable."""
        known = self._indexes.get(chunk.chunk_start_offset)
        if known is not None:
            return known
        out: dict[int, list[tuple[int, int]]] = {}
        for cid, where in chunk.message_index_offsets.items():
            try:
                self.bio.seek(where)
                opcode, length = _RECORD.unpack(self.bio.read(9))
                if opcode != 0x07:
                    continue
                index = MessageIndex.read(ReadDataStream(io.BytesIO(self.bio.read(length))))
            except Exception:
                continue
            if index.channel_id == cid:
                out[cid] = index.records
        return out

    def verify(self) -> None:
        """Read every chunk once (strict mode): damage is recorded (and raised by on_damage)."""
        everything = list(self.connections)
        for _ in self.messages(everything):
            pass


def _message_at(payload: bytes, where: int, cid: int, log_time: int
                ) -> Optional[tuple[int, int, bytes]]:
    """Return (log time, channel, data) of the message record indexed at ``where``."""
    if where < 0 or where + _MESSAGE.size > len(payload):
        return None
    opcode, length, channel, _, log, _ = _MESSAGE.unpack_from(payload, where)
    if opcode != 0x05 or channel != cid or log != log_time or length < 22 \
            or where + 9 + length > len(payload):
        return None
    return log, channel, payload[where + _MESSAGE.size:where + 9 + length]


def _plausible_message(payload: bytes, q: int, channels: set, first: int, last: int) -> bool:
    if q + _MESSAGE.size > len(payload):
        return False
    opcode, length, channel, _, log, _ = _MESSAGE.unpack_from(payload, q)
    end = q + 9 + length
    return (opcode == 0x05 and length >= 22 and channel in channels and first <= log <= last
            and end <= len(payload)
            and (end == len(payload) or 0x01 <= payload[end] <= _OPCODE_MAX))


def _walk(payload: bytes, channels: set, first: int, last: int
          ) -> tuple[list[tuple[int, int, bytes]], int]:
    """Walk a chunk's records; resync past damage; return the messages and bytes skipped."""
    found: list[tuple[int, int, bytes]] = []
    skipped = 0
    q, size = 0, len(payload)
    while q + 9 <= size:
        opcode, length = _RECORD.unpack_from(payload, q)
        end = q + 9 + length
        if opcode == 0x05 and _plausible_message(payload, q, channels, first, last):
            channel, log = struct.unpack_from('<HxxxxQ', payload, q + 9)
            found.append((log, channel, payload[q + _MESSAGE.size:end]))
            q = end
        elif opcode in (0x03, 0x04) and end <= size:
            q = end
        elif end > size and 0x01 <= opcode <= _OPCODE_MAX and length < 2**32:
            break  # the last record is cut (a truncated chunk)
        else:
            nxt = q + 1
            while nxt + 9 <= size and not _plausible_message(
                    payload, nxt, channels, first, last):
                nxt = payload.find(b'\x05', nxt + 1)
                if nxt < 0:
                    nxt = size
            skipped += nxt - q
            q = nxt
    return found, skipped + max(0, size - q)


# --------------------------------------------------------------------------- sqlite3
class TolerantSqlite3Reader(Sqlite3Reader):
    """rosbags' sqlite3 storage reader that reads every row sqlite can still return."""

    def __init__(self, path: Any) -> None:
        """Prepare to read ``path``."""
        super().__init__(path)
        self.damage: list[Damage] = []
        self.on_damage: Optional[Callable[[Damage], None]] = None
        self._damaged = False
        self._ranges: list[tuple[int, int]] = []
        self._reported: set[tuple[int, int]] = set()
        self._temporary: list[str] = []
        #: the 0xFF-padded copy of a file cut short (see _padded)
        self._shadow: Optional[apsw.Connection] = None

    def _record(self, damage: Damage) -> None:
        self.damage.append(damage)
        if self.on_damage is not None:
            self.on_damage(damage)

    @property
    def _name(self) -> str:
        return getattr(self.path, 'name', str(self.path))

    def open(self) -> None:
        """Open as rosbags does; if sqlite refuses part of the file, open what is readable."""
        try:
            super().open()
        except ReaderError as exc:
            if 'missing tables' in str(exc):
                raise  # not a rosbag2 database at all
            cause = exc.__cause__ if isinstance(exc.__cause__, apsw.Error) else exc
            try:
                self._open_damaged(_describe(cause))
            except Exception:
                raise exc from None

    def _rows_lost(self, first: int, last: int, detail: str) -> None:
        """Record unreadable rows once (the open scan and the read find the same ones)."""
        if any(a <= first and last <= b for a, b in self._reported):
            return
        self._reported.add((first, last))
        self._record(Damage(self._name, 'sqlite_rows', None, 0, detail,
                            messages_lost=last - first + 1, rows=(first, last)))

    def _padded(self) -> tuple[str, Optional[str]]:
        """
        Return the file to open and, if the file is cut short, its 0xFF-padded twin.

        sqlite refuses a database shorter than its header's page count outright (even
        its schema on page 1); padded, only the rows on the missing pages are refused.
        Padding invents bytes, though: a row whose payload runs into the padding reads
        as valid with the padding's bytes. Every such byte differs between a 0x00 and
        a 0xFF padding, so a row both copies return identically needs none of them.
        """
        with open(self.path, 'rb') as stream:
            data = stream.read()
        page = int.from_bytes(data[16:18], 'big') if len(data) >= 100 else 0
        page = 65536 if page == 1 else page
        pages = int.from_bytes(data[28:32], 'big') if len(data) >= 100 else 0
        if not page or len(data) >= page * pages and len(data) % page == 0:
            return str(self.path), None
        size = max(page * pages, -(-len(data) // page) * page)
        names = []
        for fill in (b'\x00', b'\xff'):
            handle, name = tempfile.mkstemp(suffix='.db3')
            self._temporary.append(name)
            with os.fdopen(handle, 'wb') as out:
                out.write(data + fill * (size - len(data)))
            names.append(name)
        self._record(Damage(self._name, 'truncated', len(data), size - len(data),
                            f'file cut at {len(data)} of {size} bytes'))
        return names[0], names[1]

    def close(self) -> None:
        """Close the database and remove a padded copy."""
        try:
            if self._shadow is not None:
                self._shadow.close()
                self._shadow = None
            super().close()
        finally:
            for name in self._temporary:
                os.unlink(name)
            self._temporary = []

    def _open_damaged(self, reason: str) -> None:
        flags = apsw.SQLITE_OPEN_READONLY | apsw.SQLITE_OPEN_URI
        try:
            path, shadow = self._padded()
            self.dbconn = apsw.Connection(f'file:{path}?immutable=1', flags=flags)
            if shadow is not None:
                self._shadow = apsw.Connection(f'file:{shadow}?immutable=1', flags=flags)
            self._open_topics()
        except apsw.Error as exc:
            raise ReaderError(f'Cannot open database {self.path}: {_describe(exc)}') from exc
        self._damaged = True
        rows = self._readable_rows(reason)
        known = {c.id for c in self.connections}
        garbled = [r[0] for r in rows if not (type(r[2]) is int and r[1] in known)]
        for first, last in _runs([i for i in garbled if type(i) is int]):
            self._rows_lost(first, last, 'rows with a garbled topic id or timestamp')
        rows = [r for r in rows if type(r[2]) is int and r[1] in known]
        counts: dict[int, int] = {}
        first, last = 2**63 - 1, 0
        for _, topic_id, timestamp in rows:
            counts[topic_id] = counts.get(topic_id, 0) + 1
            first, last = min(first, timestamp), max(last, timestamp)
        self.connections = [c._replace(msgcount=counts.get(c.id, 0)) for c in self.connections]
        total = len(rows)
        self.metadata = self.metadata._replace(
            duration=last + 1 - first if total else 0, start_time=first if total else 2**63 - 1,
            end_time=last + 1 if total else 0, message_count=total)

    def _open_topics(self) -> None:
        """Read the topics (and message definitions) tables, which are small and first."""
        cur = self.dbconn.cursor()
        columns = {row[1] for row in cur.execute('PRAGMA table_info(topics)')}
        wanted = ['id', 'name', 'type', 'serialization_format']
        for optional in ('offered_qos_profiles', 'type_description_hash'):
            wanted.append(optional if optional in columns else "''")
        definitions: dict[str, tuple[str, str]] = {}
        try:
            for name, encoding, text in cur.execute(
                    'SELECT topic_type, encoding, encoded_message_definition '
                    'FROM message_definitions'):
                definitions[name] = (encoding, text)
        except apsw.Error:
            pass
        from rosbags.interfaces import MessageDefinition, MessageDefinitionFormat
        from rosbags.rosbag2.metadata import parse_qos
        formats = {'ros2msg': MessageDefinitionFormat.MSG, 'ros2idl': MessageDefinitionFormat.IDL}
        self.connections = []
        for cid, topic, msgtype, fmt, qos, digest in cur.execute(
                f'SELECT {", ".join(wanted)} FROM topics ORDER BY id'):
            try:
                profiles = parse_qos(qos) if qos else []
            except Exception:  # a garbled QoS string costs only the QoS
                profiles = []
            encoding, text = definitions.get(msgtype, ('', ''))
            msgdef = MessageDefinition(formats[encoding], text) if encoding in formats \
                else MessageDefinition(MessageDefinitionFormat.NONE, '')
            self.connections.append(Connection(
                cid, topic, msgtype, msgdef, digest or '', 0,
                ConnectionExtRosbag2(fmt, profiles), self))

    def _query(self, lo: int, hi: int, columns: str, extra: str = '', args: tuple = ()
               ) -> list[tuple]:
        return list(self.dbconn.execute(
            f'SELECT {columns} FROM messages WHERE id BETWEEN ? AND ? {extra}',
            (lo, hi) + args))

    def _bisect(self, lo: int, hi: int, columns: str, extra: str, args: tuple,
                bad: list[int], conn: Optional[apsw.Connection] = None) -> list[tuple]:
        """Return the rows of [lo, hi] sqlite can read; collect the unreadable row ids."""
        try:
            if conn is None:
                return self._query(lo, hi, columns, extra, args)
            return list(conn.execute(
                f'SELECT {columns} FROM messages WHERE id BETWEEN ? AND ? {extra}',
                (lo, hi) + args))
        except apsw.Error:
            if lo == hi:
                bad.append(lo)
                return []
            mid = (lo + hi) // 2
            return self._bisect(lo, mid, columns, extra, args, bad, conn) \
                + self._bisect(mid + 1, hi, columns, extra, args, bad, conn)

    def _intact(self, lo: int, hi: int, columns: str, extra: str, args: tuple,
                bad: list[int], cut: list[int]) -> list[tuple]:
        """
        Return the rows of [lo, hi] that need no byte past the end of a cut file.

        ``columns`` starts with ``id``; ids of rows the twin copies disagree on go
        to ``cut``, ids sqlite refuses to ``bad``.
        """
        rows = self._bisect(lo, hi, columns, extra, args, bad)
        if self._shadow is None:
            return rows
        twin = {row[0]: row for row in self._bisect(lo, hi, columns, extra, args, [],
                                                    self._shadow)}
        kept = []
        for row in rows:
            if twin.get(row[0]) == row:
                kept.append(row)
            elif type(row[0]) is int:
                cut.append(row[0])
        return kept

    def _rows_cut(self, cut: list[int]) -> None:
        for first, last in _runs(cut):
            self._rows_lost(first, last, 'rows that extend past the readable end of the file')

    def _id_bounds(self) -> tuple[int, Optional[int]]:
        low = 1
        try:
            low = self.dbconn.execute('SELECT min(id) FROM messages').fetchone()[0] or 1
        except apsw.Error:
            pass
        try:
            high = self.dbconn.execute('SELECT max(id) FROM messages').fetchone()[0]
        except apsw.Error:
            high = None
        return low, high

    def _readable_rows(self, reason: str) -> list[tuple[int, int, int]]:
        """Return (id, topic id, timestamp) of every readable row; record unreadable ids."""
        low, high = self._id_bounds()
        rows: list[tuple[int, int, int]] = []
        bad: list[int] = []
        lo, empty_run = low, 0
        while high is None or lo <= high:
            window_bad: list[int] = []
            cut: list[int] = []
            got = self._intact(lo, lo + _SQLITE_WINDOW - 1, 'id, topic_id, timestamp', '',
                               (), window_bad, cut)
            self._rows_cut(cut)
            rows.extend(got)
            bad.extend(window_bad)
            if high is None:
                empty_run = 0 if got else empty_run + 1
                if empty_run >= _SQLITE_TAIL_WINDOWS:
                    break
            lo += _SQLITE_WINDOW
        last_good = max((r[0] for r in rows), default=low - 1)
        lost = [i for i in bad if i <= last_good or high is not None]
        self._ranges = [(low, last_good if high is None else high)]
        if lost or high is None:
            for first, last in _runs(lost):
                self._rows_lost(first, last, f'sqlite cannot read these rows ({reason})')
            if high is None:
                self._record(Damage(self._name, 'truncated', None, 0,
                                    f'rows after id {last_good} unreadable ({reason})',
                                    rows=(last_good + 1, last_good + 1)))
        return rows

    def messages(self, connections: Any, start: Optional[int] = None,
                 stop: Optional[int] = None) -> Iterator[tuple[Connection, int, bytes]]:
        """Yield messages in log-time order; past sqlite errors, row windows in time order."""
        assert self.dbconn
        ids = tuple({x.id for x in connections})
        connmap = {x.id: x for x in self.connections}
        where = f'AND topic_id IN ({",".join("?" for _ in ids)})'
        args: tuple = ids
        if start is not None:
            where += ' AND timestamp >= ?'
            args += (start,)
        if stop is not None:
            where += ' AND timestamp < ?'
            args += (stop,)
        last: tuple[int, int] = (-1, -1)
        if not self._damaged:
            query = (f'SELECT timestamp, id, topic_id, data FROM messages WHERE 1 {where} '
                     f'ORDER BY timestamp, id')
            try:
                for timestamp, rowid, cid, data in self.dbconn.execute(query, args):
                    if type(timestamp) is not int or type(data) is not bytes:
                        self._rows_lost(rowid, rowid, 'a row with a garbled timestamp or blob')
                        continue
                    last = (timestamp, rowid)
                    yield connmap[cid], timestamp, data
                return
            except apsw.Error as exc:  # a damaged page mid-way: continue past it
                self._damaged = True
                self._readable_rows(_describe(exc))
        for lo, hi in self._ranges:
            for window in range(lo, hi + 1, _SQLITE_WINDOW):
                bad: list[int] = []
                cut: list[int] = []
                rows = self._intact(window, min(hi, window + _SQLITE_WINDOW - 1),
                                    'id, timestamp, topic_id, data', where, args, bad, cut)
                for first, end in _runs(bad):
                    self._rows_lost(first, end, 'sqlite cannot read these rows')
                self._rows_cut(cut)
                good = []
                for rowid, timestamp, cid, data in rows:
                    if type(timestamp) is int and cid in connmap and type(data) is bytes:
                        good.append((timestamp, rowid, cid, data))
                    elif type(rowid) is int:
                        self._rows_lost(rowid, rowid, 'a row with a garbled timestamp or blob')
                for timestamp, rowid, cid, data in sorted(good):
                    if (timestamp, rowid) > last:
                        yield connmap[cid], timestamp, data

    def verify(self) -> None:
        """Check the whole file (strict mode): sqlite's quick_check, then a full read."""
        try:
            result = [row[0] for row in self.dbconn.execute('PRAGMA quick_check')]
        except apsw.Error as exc:
            result = [_describe(exc)]
        if result != ['ok']:
            self._record(Damage(self._name, 'sqlite_rows', None, 0,
                                'sqlite quick_check: ' + '; '.join(result[:3])))
        for _ in self.messages(list(self.connections)):
            pass


def _runs(values: list[int]) -> list[tuple[int, int]]:
    """Return the runs of consecutive integers in ``values`` as (first, last)."""
    out: list[tuple[int, int]] = []
    for value in sorted(values):
        if out and value == out[-1][1] + 1:
            out[-1] = (out[-1][0], value)
        else:
            out.append((value, value))
    return out


# --------------------------------------------------------------------------- readers
class TolerantDirectoryReader(DirectoryReader):
    """rosbags' rosbag2 directory reader with the tolerant storage readers."""

    STORAGE_PLUGINS = {'mcap': TolerantMcapReader, 'sqlite3': TolerantSqlite3Reader}


class TolerantReader(Reader):
    """rosbags' unified reader (directory, .mcap, .db3) with the tolerant storage readers."""

    STORAGE_PLUGINS = {'dir': TolerantDirectoryReader, '.mcap': TolerantMcapReader,
                       '.db3': TolerantSqlite3Reader}

    def storages(self) -> list[Any]:
        """Return the open storage readers."""
        storage = self.storage
        return list(getattr(storage, 'storages', None) or [storage])
