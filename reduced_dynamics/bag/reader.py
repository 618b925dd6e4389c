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
Streaming rosbag2 reader built on ``rosbags`` (no ROS installation needed).

Accepted inputs: a rosbag2 directory (``metadata.yaml`` + ``.mcap`` or
``.db3`` files, metadata versions up to 9, i.e. Humble..Jazzy and later), a
bare ``.mcap`` file (ros2 profile, no metadata.yaml needed) or a bare ``.db3``
file.  Messages are streamed in log-time order; only requested topics are
deserialized, so unrelated topics with unknown (custom) types are harmless.
Types missing from the typestore are registered from the definitions
embedded in the bag when a requested topic needs them. Damaged storage files
(a truncated or partly corrupted MCAP, a damaged sqlite3 database) are read
as far as they are intact (:mod:`reduced_dynamics.bag.damage`); what was lost
is listed in :attr:`BagReader.damage`, and ``strict=True`` refuses them.
"""

from collections.abc import Callable, Iterable, Iterator
import logging
import os
from pathlib import Path
from types import TracebackType
from typing import Any, NamedTuple, Optional, Union

from rosbags.interfaces import Connection, MessageDefinitionFormat, QosDurability
from rosbags.typesys import (
    get_types_from_idl,
    get_types_from_msg,
    get_typestore,
    Stores,
    TypesysError,
)

from reduced_dynamics.bag.damage import Damage, TolerantReader
from reduced_dynamics.bag.errors import BagError, one_line
from reduced_dynamics.messages.typestore import (is_shared, jazzy_typestore,
                                                 private_jazzy_typestore, rihs01)

_LOG = logging.getLogger(__name__)

MCAP_MAGIC = b'\x89MCAP0\r\n'
SQLITE_MAGIC = b'SQLite format 3\x00'
_IDL_SEP = '=' * 80 + '\n'

PathLike = Union[str, 'os.PathLike[str]']
Deserializer = Callable[[bytes], Any]


class BagMessage(NamedTuple):
    """A deserialized message; unpacks as ``(topic, msgtype, timestamp_ns, msg)``."""

    topic: str
    msgtype: str
    timestamp_ns: int
    msg: Any


class RawBagMessage(NamedTuple):
    """A serialized (CDR) message; unpacks as ``(topic, msgtype, timestamp_ns, data)``."""

    topic: str
    msgtype: str
    timestamp_ns: int
    data: bytes


def _describe(exc: BaseException) -> str:
    """Return a one-line description of an exception raised by rosbags or the OS."""
    text = one_line(exc)
    if type(exc).__name__ in ('ReaderError', 'BagError'):
        return text or type(exc).__name__
    return f'{type(exc).__name__}: {text}' if text else type(exc).__name__


def _check_path(path: Path) -> Path:
    """Validate ``path`` cheaply and return the path rosbags should open."""
    if not path.exists():
        raise BagError(f'bag path does not exist: {path}')
    if path.is_file() and path.name == 'metadata.yaml':
        path = path.parent
    if path.is_dir():
        if not (path / 'metadata.yaml').is_file():
            entries = sorted(p.name for p in path.iterdir())
            if not entries:
                raise BagError(f'not a rosbag2 bag: directory {path} is empty')
            storage = [n for n in entries if n.endswith(('.mcap', '.db3'))]
            hint = f'; to read the storage file alone, open {path / storage[0]}' if storage else ''
            raise BagError(f'not a rosbag2 bag: {path} has no metadata.yaml{hint}')
        return path
    if not path.is_file():
        raise BagError(f'not a bag: {path} is neither a directory nor a regular file')
    try:
        with path.open('rb') as stream:
            head = stream.read(16)
    except OSError as exc:
        raise BagError(f'cannot read {path}: {_describe(exc)}') from exc
    if not head:
        raise BagError(f'not a bag: file {path} is empty')
    suffix = path.suffix.lower()
    if suffix == '.mcap' and not head.startswith(MCAP_MAGIC):
        raise BagError(f'not an MCAP file (bad magic bytes): {path}')
    if suffix == '.db3' and not head.startswith(SQLITE_MAGIC):
        raise BagError(f'not an SQLite3 bag file (bad header): {path}')
    if suffix not in ('.mcap', '.db3'):
        raise BagError(
            f'not a bag: {path} (expected a rosbag2 directory, a .mcap or a .db3 file)')
    return path


def _parse_definition(conn: Connection) -> dict[str, Any]:
    """Parse the message definition embedded in the bag for ``conn``."""
    fmt, text = conn.msgdef.format, conn.msgdef.data
    if fmt == MessageDefinitionFormat.MSG:
        return dict(get_types_from_msg(text, conn.msgtype))
    typs: dict[str, Any] = {}
    if text.startswith(_IDL_SEP + 'IDL: '):
        for section in text.split(_IDL_SEP)[1:]:
            _, idl = section.split('\n', 1)
            typs.update(get_types_from_idl(idl))
    else:
        typs.update(get_types_from_idl(text))
    return typs


class BagReader:
    """
    Open rosbag2 bag; use as a context manager (see :func:`open_bag`).

    Public attributes: ``path`` (the opened directory or storage file),
    ``typestore`` (rosbags typestore used for deserialization; types missing
    from it are registered from the bag on demand), ``skipped`` (count of
    skipped messages per reason), ``skip_details`` (last error text per
    reason) and :attr:`damage` (damaged regions of the storage files).
    With ``strict``, any damage raises BagError instead (at open, or when
    reading reaches it; :meth:`verify` reads everything up front).
    """

    def __init__(self, path: PathLike, *, typestore: Optional[Any] = None,
                 strict: bool = False) -> None:
        """Open the bag at ``path`` (raises BagError with a one-line reason)."""
        self._closed_damage: list[Damage] = []
        self.path = _check_path(Path(path))
        self.strict = strict
        self.typestore = jazzy_typestore() if typestore is None else typestore
        self.skipped: dict[str, int] = {}
        self.skip_details: dict[str, str] = {}
        self._stores: dict[tuple[str, str], Any] = {}
        self._embedded_stores: dict[str, Any] = {}
        self._reader: Optional[TolerantReader] = None
        try:
            reader = TolerantReader(self.path)
            reader.open()
        except Exception as exc:  # rosbags raises many exception kinds on bad input
            hint = ''
            text = str(exc).lower()
            if self.path.suffix == '.mcap' and any(
                k in text for k in ('magic', 'truncat', 'footer', 'summary')
            ):
                hint = (' (truncated or corrupted MCAP; an interrupted recording can be'
                        ' repaired with "mcap recover" or "ros2 bag reindex")')
            raise BagError(f'cannot open bag {self.path}: {_describe(exc)}{hint}') from exc
        self._reader = reader
        self._connections: list[Connection] = list(reader.connections)
        #: whether message_count() describes the bag as recorded (metadata.yaml, or a
        #: storage index that needed no repair), so that missing messages can be counted
        self.counts_trusted = self.path.is_dir() or not self.damage
        if strict:
            if self.damage:
                text = self.damage[0].text()
                self.close()
                raise BagError(f'damaged bag {self.path}: {text}')
            for storage in reader.storages():
                storage.on_damage = self._refuse

    def _refuse(self, damage: Damage) -> None:
        raise BagError(f'damaged bag {self.path}: {damage.text()}')

    @property
    def damage(self) -> list[Damage]:
        """Return the damaged regions found so far, in file order of discovery."""
        reader = self._reader
        if reader is None:
            return list(self._closed_damage)
        return [d for storage in reader.storages() for d in getattr(storage, 'damage', [])]

    def verify(self) -> list[Damage]:
        """Read every chunk / row once and return the damage (strict mode raises at the first)."""
        reader = self._open_reader()
        for storage in reader.storages():
            try:
                storage.verify()
            except BagError:
                raise
            except Exception as exc:
                raise BagError(f'error while reading {self.path}: {_describe(exc)}') from exc
        return self.damage

    # ------------------------------------------------------------ lifecycle

    def close(self) -> None:
        """Close the underlying storage (idempotent); :attr:`damage` stays readable."""
        if self._reader is not None:
            self._closed_damage = self.damage
        reader, self._reader = self._reader, None
        if reader is not None:
            reader.close()

    @property
    def closed(self) -> bool:
        """Return True once closed."""
        return self._reader is None

    def __enter__(self) -> 'BagReader':
        """Return self."""
        return self

    def __exit__(
        self,
        exc_type: Optional[type[BaseException]],
        exc_val: Optional[BaseException],
        exc_tb: Optional[TracebackType],
    ) -> None:
        """Close the bag."""
        self.close()

    def _open_reader(self) -> TolerantReader:
        """Return the rosbags reader or raise if closed."""
        if self._reader is None:
            raise BagError(f'bag {self.path} is closed')
        return self._reader

    # ------------------------------------------------------------ metadata

    def topics(self) -> dict[str, str]:
        """Return ``{topic: msgtype}`` for every topic in the bag (incl. unknown types)."""
        out: dict[str, str] = {}
        for conn in self._connections:
            out.setdefault(conn.topic, conn.msgtype)
        return out

    def latched_topics(self) -> set[str]:
        """Return the topics recorded from transient-local ("latched") publishers."""
        return {c.topic for c in self._connections
                if any(getattr(q, 'durability', None) == QosDurability.TRANSIENT_LOCAL
                       for q in getattr(c.ext, 'offered_qos_profiles', None) or [])}

    def message_count(self, topic: Optional[str] = None) -> int:
        """Return the message count of ``topic`` (or of the whole bag when None)."""
        reader = self._open_reader()
        if topic is None:
            return int(reader.message_count)
        conns = [c for c in self._connections if c.topic == topic]
        if not conns:
            raise BagError(f'topic {topic!r} is not in bag {self.path}')
        return sum(int(c.msgcount) for c in conns)

    @property
    def start_ns(self) -> int:
        """Log time of the first message (0 for an empty bag)."""
        reader = self._open_reader()
        return int(reader.start_time) if reader.message_count else 0

    @property
    def end_ns(self) -> int:
        """Log time of the last message, inclusive (0 for an empty bag)."""
        reader = self._open_reader()
        return int(reader.end_time) - 1 if reader.message_count else 0

    @property
    def duration_ns(self) -> int:
        """Return ``end_ns - start_ns``."""
        return self.end_ns - self.start_ns

    @property
    def duration(self) -> float:
        """Duration in seconds."""
        return self.duration_ns * 1e-9

    # ------------------------------------------------------------ messages

    def _select(self, topics: Iterable[str], ignore_missing: bool) -> list[Connection]:
        """Return connections of the requested topics."""
        wanted = [topics] if isinstance(topics, str) else list(topics)
        conns = [c for c in self._connections if c.topic in set(wanted)]
        missing = sorted(set(wanted) - {c.topic for c in conns})
        if missing and not ignore_missing:
            raise BagError(
                f'topics not in bag {self.path}: {missing}; available: {sorted(self.topics())}')
        return conns

    def _iterate(
        self, conns: list[Connection], start_ns: Optional[int], end_ns: Optional[int]
    ) -> Iterator[tuple[Connection, int, bytes]]:
        """Stream raw messages, translating storage errors into BagError."""
        reader = self._open_reader()
        if not conns:
            return  # rosbags treats "no connections" as "all connections"
        if start_ns is not None and end_ns is not None and end_ns < start_ns:
            raise BagError(f'end_ns ({end_ns}) is before start_ns ({start_ns})')
        source = reader.messages(
            connections=self._with_storage_connections(conns), start=start_ns, stop=end_ns)
        while True:
            try:
                item = next(source)
            except StopIteration:
                return
            except BagError:
                raise
            except Exception as exc:  # what the damage-tolerant readers could not handle
                raise BagError(f'error while reading {self.path}: {_describe(exc)}') from exc
            yield item

    def _with_storage_connections(self, conns: list[Connection]) -> list[Connection]:
        """
        Add the storage files' own connections for the requested topics.

        rosbags matches metadata.yaml connections to storage connections by
        comparing QoS profiles and hashes too; when metadata.yaml and the
        storage disagree (hand-edited or converted bags) nothing would be
        yielded.  Passing the storage connections as well always matches.
        """
        wanted = {(c.topic, c.msgtype) for c in conns}
        storages = getattr(getattr(self._reader, 'storage', None), 'storages', None) or []
        extra = [
            x for storage in storages for x in getattr(storage, 'connections', [])
            if (x.topic, x.msgtype) in wanted
        ]
        return conns + extra

    def _embedded_store(self, conn: Connection, typs: dict[str, Any]) -> Any:
        """Return a typestore holding only the bag's own definitions for ``conn``."""
        store = self._embedded_stores.get(conn.msgtype)
        if store is None:
            store = get_typestore(Stores.EMPTY)
            store.register(typs)
            self._embedded_stores[conn.msgtype] = store
        return store

    def _registrable_store(self) -> Any:
        """Return ``typestore``, made this reader's own first if it is the shared one."""
        if is_shared(self.typestore):
            shared, self.typestore = self.typestore, private_jazzy_typestore()
            # Topics resolved before deserialize alike in either store; they follow it so
            # that ``typestore_for`` stays ``typestore`` for every Jazzy-defined topic.
            self._stores = {key: self.typestore if store is shared else store
                            for key, store in self._stores.items()}
        return self.typestore

    def _store_for(self, conn: Connection) -> Any:
        """Return the typestore able to deserialize ``conn`` (BagError if none)."""
        store = self._stores.get((conn.topic, conn.msgtype))
        if store is not None:
            return store
        fmt = getattr(conn.ext, 'serialization_format', 'cdr')
        if fmt != 'cdr':
            raise BagError(f'topic {conn.topic!r}: unsupported serialization format {fmt!r}')
        has_def = conn.msgdef.format != MessageDefinitionFormat.NONE
        known = conn.msgtype in self.typestore.fielddefs
        store = self.typestore
        try:
            if known and has_def and conn.digest.startswith('RIHS01_'):
                if rihs01(self.typestore, conn.msgtype) != conn.digest:
                    # Same name, different definition (other distro): trust the bag.
                    store = self._embedded_store(conn, _parse_definition(conn))
            elif not known:
                if not has_def:
                    raise BagError(
                        f'topic {conn.topic!r}: message type {conn.msgtype!r} is not in the'
                        ' typestore and the bag embeds no definition for it')
                typs = _parse_definition(conn)
                try:
                    store = self._registrable_store()
                    store.register(typs)
                except TypesysError:
                    store = self._embedded_store(conn, typs)
        except BagError:
            raise
        except Exception as exc:
            raise BagError(
                f'topic {conn.topic!r}: cannot load definition of {conn.msgtype!r}:'
                f' {_describe(exc)}') from exc
        self._stores[(conn.topic, conn.msgtype)] = store
        return store

    def _deserializers(self, conns: list[Connection]) -> dict[tuple[str, str], Deserializer]:
        """Resolve a deserializer per (topic, msgtype) before streaming starts."""
        out: dict[tuple[str, str], Deserializer] = {}
        for conn in conns:
            store, msgtype = self._store_for(conn), conn.msgtype
            out[(conn.topic, msgtype)] = (
                lambda data, _store=store, _type=msgtype: _store.deserialize_cdr(data, _type))
        return out

    def connection_types(self, topics: Iterable[str]) -> list[tuple[str, str]]:
        """Return the distinct ``(topic, msgtype)`` pairs of ``topics`` in the bag."""
        wanted = {topics} if isinstance(topics, str) else set(topics)
        pairs = {(c.topic, c.msgtype): None for c in self._connections if c.topic in wanted}
        return list(pairs)

    def _connection(self, topic: str, msgtype: str) -> Connection:
        """Return the first connection of ``topic`` with ``msgtype`` (BagError if none)."""
        for conn in self._connections:
            if conn.topic == topic and conn.msgtype == msgtype:
                return conn
        raise BagError(f'bag {self.path} has no topic {topic!r} of type {msgtype!r}')

    def typestore_for(self, topic: str, msgtype: str) -> Any:
        """Return the typestore that deserializes ``msgtype`` on ``topic`` (see messages())."""
        return self._store_for(self._connection(topic, msgtype))

    def deserializer(self, topic: str, msgtype: str) -> Callable[[bytes], Optional[Any]]:
        """
        Return a function deserializing raw messages of ``topic`` / ``msgtype``.

        For callers that decode :meth:`raw_messages` themselves (e.g. with a
        faster decoder first): the function returns None for data that does
        not deserialize and counts it in :attr:`skipped`, as :meth:`messages`
        does. Type resolution errors raise BagError here, not later.
        """
        conn = self._connection(topic, msgtype)
        deserialize = self._deserializers([conn])[(topic, msgtype)]

        def run(data: bytes) -> Optional[Any]:
            try:
                return deserialize(data)
            except Exception as exc:  # SerdeError, struct.error, ...
                self._skip(conn, exc)
                return None
        return run

    def _skip(self, conn: Connection, exc: Exception) -> None:
        """Count a skipped message (strict mode: refuse the bag)."""
        reason = f'deserialization failed: {conn.topic} ({conn.msgtype})'
        if self.strict:
            raise BagError(f'damaged bag {self.path}: a message of {conn.topic} does not '
                           f'deserialize ({_describe(exc)})')
        if reason not in self.skipped:
            _LOG.warning('%s: skipping message(s): %s', reason, _describe(exc))
        self.skipped[reason] = self.skipped.get(reason, 0) + 1
        self.skip_details[reason] = _describe(exc)

    def messages(
        self,
        topics: Iterable[str],
        start_ns: Optional[int] = None,
        end_ns: Optional[int] = None,
        *,
        ignore_missing: bool = False,
    ) -> Iterator[BagMessage]:
        """
        Stream deserialized messages of ``topics`` with log time in ``[start_ns, end_ns)``.

        Topics absent from the bag raise BagError unless ``ignore_missing``.
        Messages that fail to deserialize are skipped and counted in
        :attr:`skipped`.  Type resolution happens before the first yield.
        """
        conns = self._select(topics, ignore_missing)
        deserialize = self._deserializers(conns)
        return self._messages(conns, deserialize, start_ns, end_ns)

    def _messages(
        self,
        conns: list[Connection],
        deserialize: dict[tuple[str, str], Deserializer],
        start_ns: Optional[int],
        end_ns: Optional[int],
    ) -> Iterator[BagMessage]:
        """Generate BagMessage items (helper so that errors surface at call time)."""
        for conn, timestamp, data in self._iterate(conns, start_ns, end_ns):
            try:
                msg = deserialize[(conn.topic, conn.msgtype)](data)
            except Exception as exc:  # SerdeError, struct.error, ...
                self._skip(conn, exc)
                continue
            yield BagMessage(conn.topic, conn.msgtype, int(timestamp), msg)

    def raw_messages(
        self,
        topics: Iterable[str],
        start_ns: Optional[int] = None,
        end_ns: Optional[int] = None,
        *,
        ignore_missing: bool = False,
    ) -> Iterator[RawBagMessage]:
        """Stream serialized messages (no deserialization; e.g. for benchmarking)."""
        conns = self._select(topics, ignore_missing)
        return (
            RawBagMessage(conn.topic, conn.msgtype, int(timestamp), data)
            for conn, timestamp, data in self._iterate(conns, start_ns, end_ns)
        )


def open_bag(path: PathLike, *, typestore: Optional[Any] = None,
             strict: bool = False) -> BagReader:
    """Open a rosbag2 directory, bare .mcap or bare .db3 file for streaming reads."""
    return BagReader(path, typestore=typestore, strict=strict)
