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

"""Damaged bags: truncated and corrupted MCAP, damaged sqlite3; nothing intact is lost."""

import json
from pathlib import Path
import shutil
import sqlite3
import struct
from typing import Optional

from hypothesis import given, HealthCheck, settings, strategies as st
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer
import pytest

from reduced_dynamics.bag import BagError, BagWriter, open_bag
from reduced_dynamics.cli import main

REPO_ROOT = Path(__file__).resolve().parent.parent
BAG = REPO_ROOT / 'test' / 'data' / 'paper_thruster'
MCAP = BAG / 'paper_thruster.mcap'
CHUNK = 43  # the single chunk of the shipped bag (rosbags writes one chunk up to 1 MiB)
CHUNK_DATA = CHUNK + 9 + 40  # its records start here (uncompressed)


def read_all(path: Path) -> list[tuple[str, int, bytes]]:
    """Return (topic, log time, data) of every message, in the reader's order."""
    with open_bag(path) as bag:
        return [(m.topic, m.timestamp_ns, bytes(m.data))
                for m in bag.raw_messages(list(bag.topics()))]


def damage_of(path: Path) -> list:
    """Return the damage the reader reports after reading everything."""
    with open_bag(path) as bag:
        for _ in bag.raw_messages(list(bag.topics())):
            pass
        return bag.damage


def message_spans() -> list[tuple[int, int, tuple[str, int, bytes]]]:
    """Return (file start, file end, message) of every message record of the shipped bag."""
    data = MCAP.read_bytes()
    topics = {}
    with open(MCAP, 'rb') as stream:
        for _, channel, _ in make_reader(stream).iter_messages():
            topics[channel.id] = channel.topic
    spans, q = [], CHUNK_DATA
    end_of_chunk = CHUNK + 9 + struct.unpack_from('<Q', data, CHUNK + 1)[0]
    while q < end_of_chunk:
        opcode, length = struct.unpack_from('<BQ', data, q)
        if opcode == 0x05:
            channel, log = struct.unpack_from('<HxxxxQ', data, q + 9)
            spans.append((q, q + 9 + length, (topics[channel], log, data[q + 31:q + 9 + length])))
        q += 9 + length
    return spans


@pytest.fixture(scope='module')
def clean() -> list[tuple[str, int, bytes]]:
    """Return the clean bag's messages."""
    return read_all(MCAP)


@pytest.fixture(scope='module')
def chunked(tmp_path_factory: pytest.TempPathFactory, clean: list) -> Path:
    """Return paper_thruster rewritten by the mcap library: 64 KiB chunks with CRCs."""
    path = tmp_path_factory.mktemp('chunked') / 'chunked.mcap'
    with open(MCAP, 'rb') as stream:
        reader = make_reader(stream)
        summary = reader.get_summary()
        with open(path, 'wb') as out:
            writer = Writer(out, chunk_size=65536, compression=CompressionType.NONE)
            writer.start(profile='ros2')
            schema_ids = {sid: writer.register_schema(s.name, s.encoding, s.data)
                          for sid, s in summary.schemas.items()}
            channel_ids = {cid: writer.register_channel(c.topic, c.message_encoding,
                                                        schema_ids[c.schema_id], c.metadata)
                           for cid, c in summary.channels.items()}
            for _, channel, message in reader.iter_messages(log_time_order=False):
                writer.add_message(channel_ids[channel.id], message.log_time, message.data,
                                   message.publish_time)
            writer.finish()
    assert read_all(path) == clean
    return path


def chunk_table(path: Path) -> list[tuple[int, int, int]]:
    """Return (offset, length, messages) of every chunk, from the file's chunk index."""
    with open(path, 'rb') as stream:
        summary = make_reader(stream).get_summary()
    rows = []
    for index in summary.chunk_indexes:
        with open(path, 'rb') as stream:
            stream.seek(index.chunk_start_offset + index.chunk_length)
            count = 0
            for _ in index.message_index_offsets:
                opcode, length = struct.unpack('<BQ', stream.read(9))
                assert opcode == 0x07
                body = stream.read(length)
                count += struct.unpack_from('<I', body, 2)[0] // 16
        rows.append((index.chunk_start_offset, index.chunk_length, count))
    return rows


# --------------------------------------------------------------------------- truncated
@pytest.mark.parametrize('cut', [200_000, 532_832, 800_001, 1_006_900, 1_006_990, 1_060_000,
                                 1_065_655])
def test_truncated_mcap_yields_every_complete_message(cut: int, clean: list,
                                                      tmp_path: Path) -> None:
    path = tmp_path / 'cut.mcap'
    path.write_bytes(MCAP.read_bytes()[:cut])
    got = read_all(path)
    # Every message whose record lies wholly before the cut, in the clean bag's order.
    complete = {m for _, end, m in message_spans() if end <= cut}
    assert got == [m for m in clean if m in complete]
    damage = damage_of(path)
    assert len(damage) >= 1
    if cut < CHUNK_DATA + 1_006_890:  # inside the chunk
        assert damage[0].kind == 'truncated' and damage[0].chunk == 0
        assert damage[0].messages_recovered == len(got) and damage[0].offset == CHUNK
        # Unread: the partial record at the cut and whatever the cut removed.
        last = max(end for _, end, _ in message_spans() if end <= cut)
        assert damage[0].length == CHUNK + 9 + 1_006_930 - last
    else:  # the chunk is whole: only the index or the summary is lost
        assert got == clean


def test_truncated_inside_the_header_is_refused(tmp_path: Path) -> None:
    path = tmp_path / 'cut.mcap'
    path.write_bytes(MCAP.read_bytes()[:20])
    with pytest.raises(BagError, match='cannot open bag'):
        open_bag(path)


@pytest.mark.parametrize('fraction', [0.2, 0.45, 0.7, 0.95])
def test_truncated_chunked_mcap(fraction: float, chunked: Path, clean: list,
                                tmp_path: Path) -> None:
    data = chunked.read_bytes()
    cut = int(len(data) * fraction)
    path = tmp_path / 'cut.mcap'
    path.write_bytes(data[:cut])
    got = read_all(path)
    table = chunk_table(chunked)
    whole = sum(n for offset, length, n in table if offset + length <= cut)
    # Every message of the complete chunks, plus whatever is whole in the cut one,
    # and nothing that was not in the clean bag.
    assert whole <= len(got) and set(got) <= set(clean)
    assert got == [m for m in clean if m in set(got)]
    assert len(got) >= whole + 1 or all(offset + length <= cut for offset, length, _ in table)
    kinds = {d.kind for d in damage_of(path)}
    assert 'truncated' in kinds or 'no_summary' in kinds


# --------------------------------------------------------------------------- corrupted
def test_corrupted_chunk_with_crc_loses_only_that_chunk(chunked: Path, clean: list,
                                                        tmp_path: Path) -> None:
    table = chunk_table(chunked)
    assert len(table) >= 10
    offset, length, count = table[len(table) // 2]
    data = bytearray(chunked.read_bytes())
    data[offset + length // 2:offset + length // 2 + 8] = b'\xde\xad\xbe\xef' * 2
    path = tmp_path / 'corrupt.mcap'
    path.write_bytes(bytes(data))
    got = read_all(path)
    lost = [m for m in clean if m not in set(got)]
    assert len(lost) == count and got == [m for m in clean if m not in set(lost)]
    damage = damage_of(path)
    assert [(d.kind, d.chunk, d.offset, d.messages_lost) for d in damage] == [
        ('crc_mismatch', len(table) // 2, offset, count)]
    assert sum(damage[0].topics_lost.values()) == count


def test_corrupted_chunk_length_without_summary_resyncs(chunked: Path, clean: list,
                                                        tmp_path: Path) -> None:
    table = chunk_table(chunked)
    offset, length, count = table[3]
    data = bytearray(chunked.read_bytes())
    data[offset + 1:offset + 9] = struct.pack('<Q', 16_777_314)  # a wrong record length
    last_chunk_end = table[-1][0] + table[-1][1]
    path = tmp_path / 'corrupt.mcap'
    path.write_bytes(bytes(data[:last_chunk_end + 100]))  # and no summary
    got = read_all(path)
    table_messages = sum(n for _, _, n in table)
    assert len(got) == table_messages - count and set(got) <= set(clean)
    damage = damage_of(path)
    assert damage[0].kind == 'unparsable' and damage[0].offset == offset


@pytest.fixture(scope='module')
def chunked_no_crc(tmp_path_factory: pytest.TempPathFactory, clean: list) -> Path:
    """Return paper_thruster rewritten by rosbags (no chunk CRCs) in 64 KiB chunks."""
    from reduced_dynamics.bag import writer as bag_writer
    path = tmp_path_factory.mktemp('nocrc') / 'bag'
    chunk = bag_writer._CHUNK_BYTES
    bag_writer._CHUNK_BYTES = 65536
    try:
        with open_bag(BAG) as bag:
            topics = bag.topics()
            with BagWriter(path, topics) as writer:
                for message in bag.raw_messages(list(topics)):
                    writer.write_raw(message.topic, message.timestamp_ns, message.data)
    finally:
        bag_writer._CHUNK_BYTES = chunk
    storage = next(path.glob('*.mcap'))
    assert read_all(storage) == clean and len(chunk_table(storage)) >= 10
    return storage


def chunk_messages(path: Path, offset: int) -> list[tuple[str, int, bytes]]:
    """Return (topic, log time, data) of the message records of the chunk at ``offset``."""
    data = path.read_bytes()
    with open(path, 'rb') as stream:
        topics = {c.id: c.topic for c in make_reader(stream).get_summary().channels.values()}
    end = offset + 9 + struct.unpack_from('<Q', data, offset + 1)[0]
    q = offset + 9 + 40 + struct.unpack_from('<I', data, offset + 9 + 36)[0]
    out = []
    while q < end:
        opcode, length = struct.unpack_from('<BQ', data, q)
        if opcode == 0x05:
            channel, log = struct.unpack_from('<HxxxxQ', data, q + 9)
            out.append((topics[channel], log, data[q + 31:q + 9 + length]))
        q += 9 + length
    return out


@pytest.mark.parametrize('writer', ['mcap', 'rosbags'])
def test_damaged_first_chunk_times_without_summary(writer: str, chunked: Path,
                                                   chunked_no_crc: Path, clean: list,
                                                   tmp_path: Path) -> None:
    # The reproducer of the fuzz suite's bag_files family: byte 62 (in chunk 0's time
    # fields) and the end magic overwritten. Chunk 0 holds the only schema and channel
    # records, so losing it lost every message; its records still validate (CRC, or
    # every record parses) and give its times again.
    source = chunked if writer == 'mcap' else chunked_no_crc
    table = chunk_table(source)
    data = bytearray(source.read_bytes())
    offset = table[0][0]
    assert offset + 9 <= 62 < offset + 9 + 16  # a time field of chunk 0's header
    data[62] = 0xff
    data[-8:] = b'\0' * 8
    path = tmp_path / 'damaged.mcap'
    path.write_bytes(bytes(data))
    assert read_all(path) == clean
    damage = damage_of(path)
    assert [(d.kind, d.chunk, d.offset, d.messages_lost) for d in damage] == [
        ('corrupt_chunk', 0, offset, 0)]


@pytest.mark.parametrize('writer', ['mcap', 'rosbags'])
@pytest.mark.parametrize('field', [1, 9 + 36, 0])  # record length, compression length, opcode
def test_damaged_chunk_header_in_the_middle_without_summary(
        writer: str, field: int, chunked: Path, chunked_no_crc: Path, clean: list,
        tmp_path: Path) -> None:
    # A damaged length used to send the scan into the next chunk, losing it too; a
    # damaged opcode or compression length made the chunk unparsable. Now the scan
    # resyncs on the next chunk that validates: only the damaged chunk is lost.
    source = chunked if writer == 'mcap' else chunked_no_crc
    table = chunk_table(source)
    middle = len(table) // 2
    offset = table[middle][0]
    data = bytearray(source.read_bytes())
    data[offset + field] ^= 0x24
    path = tmp_path / 'damaged.mcap'
    path.write_bytes(bytes(data[:table[-1][0] + table[-1][1]]))  # the summary is gone
    lost = set(chunk_messages(source, offset))
    assert len(lost) == table[middle][2]
    assert read_all(path) == [m for m in clean if m not in lost]
    damage = damage_of(path)
    assert [(d.kind, d.offset) for d in damage] == [('unparsable', offset)]
    assert damage[0].length == table[middle][1] + (table[middle + 1][0] - offset
                                                   - table[middle][1])


@pytest.mark.parametrize('which', [[5], [100, 101], [7, 1500, 3000]])
def test_corrupted_headers_in_a_crc_less_chunk(which: list, clean: list,
                                               tmp_path: Path) -> None:
    spans = message_spans()
    data = bytearray(MCAP.read_bytes())
    for index in which:  # overwrite the record length of these messages
        start = spans[index][0]
        data[start + 1:start + 9] = b'\xff' * 8
    path = tmp_path / 'corrupt.mcap'
    path.write_bytes(bytes(data))
    got = read_all(path)
    lost = {spans[i][2] for i in which}
    assert got == [m for m in clean if m not in lost]
    damage = damage_of(path)
    assert len(damage) == 1 and damage[0].kind == 'corrupt_chunk'
    assert damage[0].messages_lost == len(which) and damage[0].messages_recovered == len(got)


def test_corrupted_channel_id_is_caught_by_the_index(clean: list, tmp_path: Path) -> None:
    spans = message_spans()
    data = bytearray(MCAP.read_bytes())
    data[spans[42][0] + 9:spans[42][0] + 11] = b'\xff\xff'
    path = tmp_path / 'corrupt.mcap'
    path.write_bytes(bytes(data))
    assert read_all(path) == [m for m in clean if m != spans[42][2]]
    assert [d.messages_lost for d in damage_of(path)] == [1]


# --------------------------------------------------------------------------- sqlite3
@pytest.fixture(scope='module')
def sqlite_bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Return paper_thruster converted to a sqlite3 bag."""
    path = tmp_path_factory.mktemp('sqlite') / 'bag'
    with open_bag(BAG) as bag:
        topics = bag.topics()
        with BagWriter(path, topics, storage='sqlite3') as writer:
            for message in bag.raw_messages(list(topics)):
                writer.write_raw(message.topic, message.timestamp_ns, message.data)
    return path


def _copy(bag: Path, tmp_path: Path) -> tuple[Path, Path]:
    out = tmp_path / 'bag'
    shutil.copytree(bag, out)
    return out, next(out.glob('*.db3'))


def test_sqlite_garbled_rows_are_skipped_and_counted(sqlite_bag: Path, tmp_path: Path,
                                                     clean: list) -> None:
    out, db = _copy(sqlite_bag, tmp_path)
    with sqlite3.connect(db) as conn:
        conn.execute('UPDATE messages SET data = substr(data, 1, 20) WHERE id IN (SELECT id '
                     'FROM messages WHERE topic_id IN (1, 2) ORDER BY id LIMIT 3 OFFSET 40)')
    code = main(['replay', str(out), '-o', str(tmp_path / 'o'), '--quiet',
                 '--summary-json', str(tmp_path / 's.json')])
    summary = json.loads((tmp_path / 's.json').read_text())
    assert code == 3 and summary['damage']['undecodable'] == 3
    assert sum(summary['messages_in'].values()) == 1602 - 3
    assert main(['replay', str(out), '-o', str(tmp_path / 'strict'), '--quiet',
                 '--strict']) == 2
    assert not (tmp_path / 'strict').exists()


@pytest.mark.parametrize('keep', [0.5, 0.8])
def test_sqlite_truncated_file_reads_what_sqlite_can(keep: float, sqlite_bag: Path,
                                                     tmp_path: Path, clean: list) -> None:
    out, db = _copy(sqlite_bag, tmp_path)
    data = db.read_bytes()
    db.write_bytes(data[:int(len(data) * keep) // 4096 * 4096])
    got = read_all(out)
    assert 0 < len(got) < len(clean) and set(got) <= set(clean)
    assert [t for _, t, _ in got] == sorted(t for _, t, _ in got)
    assert damage_of(out)


def test_sqlite_corrupted_page_in_the_middle(sqlite_bag: Path, tmp_path: Path,
                                             clean: list) -> None:
    out, db = _copy(sqlite_bag, tmp_path)
    data = bytearray(db.read_bytes())
    page = 4096
    middle = len(data) // page // 2 * page
    data[middle:middle + page] = b'\x00\x13' * (page // 2)
    db.write_bytes(bytes(data))
    got = read_all(out)
    assert set(got) <= set(clean) and len(got) > len(clean) // 2
    # Rows on both sides of the damaged page are read.
    times = [t for _, t, _ in got]
    assert times[-1] == clean[-1][1]


# --------------------------------------------------------------------------- replay
def test_replay_reports_damage_and_exit_status(tmp_path: Path) -> None:
    bag = tmp_path / 'bag'
    bag.mkdir()
    shutil.copy(BAG / 'metadata.yaml', bag)
    (bag / 'paper_thruster.mcap').write_bytes(MCAP.read_bytes()[:600_000])
    code = main(['replay', str(bag), '-o', str(tmp_path / 'out'), '--quiet',
                 '--summary-json', str(tmp_path / 's.json')])
    summary = json.loads((tmp_path / 's.json').read_text())
    damage = summary['damage']
    assert code == 3 and damage['damaged']
    assert damage['regions'][0]['kind'] == 'truncated'
    got = sum(summary['messages_in'].values())
    assert damage['messages_salvaged'] >= got  # salvaged counts every topic
    assert sum(damage['missing_vs_index'].values()) == 1602 - got
    assert main(['replay', str(bag), '-o', str(tmp_path / 'strict'), '--quiet',
                 '--strict']) == 2
    assert not (tmp_path / 'strict').exists()


def test_clean_replay_exits_0_with_empty_damage(tmp_path: Path,
                                                capsys: pytest.CaptureFixture) -> None:
    assert main(['replay', str(BAG), '-o', str(tmp_path / 'out'), '--quiet', '--strict',
                 '--summary-json', str(tmp_path / 's.json')]) == 0
    damage = json.loads((tmp_path / 's.json').read_text())['damage']
    assert not damage['damaged'] and damage['regions'] == [] and damage['messages_lost'] == 0
    assert 'DAMAGED' not in capsys.readouterr().out


def test_strict_error_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    path = tmp_path / 'cut.mcap'
    path.write_bytes(MCAP.read_bytes()[:300_000])
    assert main(['replay', str(path), '-o', str(tmp_path / 'out'), '--quiet',
                 '--strict']) == 2
    err = capsys.readouterr().err.strip()
    assert err.count('\n') == 0 and 'damaged bag' in err and 'truncated' in err


# --------------------------------------------------------------------------- fuzz
@settings(max_examples=200, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(cut=st.one_of(st.none(), st.integers(9, 1_065_665)),
       hits=st.lists(st.tuples(st.integers(8, 1_065_600), st.binary(min_size=1, max_size=16)),
                     max_size=4))
def test_fuzz_damaged_mcap_never_crashes(cut: Optional[int], hits: list, clean: list,
                                         tmp_path_factory: pytest.TempPathFactory) -> None:
    data = bytearray(MCAP.read_bytes())
    for where, junk in hits:
        data[where:where + len(junk)] = junk
    data = data[:cut] if cut is not None else data
    path = tmp_path_factory.mktemp('fuzz') / 'bag.mcap'
    path.write_bytes(bytes(data))
    try:
        bag = open_bag(path)
    except BagError as error:  # a clear one-line refusal is allowed (e.g. the header is hit)
        assert '\n' not in str(error)
        return
    with bag:
        got = [(m.topic, m.timestamp_ns, bytes(m.data))
               for m in bag.raw_messages(list(bag.topics()))]
        damage = bag.damage
    # Messages come in log-time order; a message that was not damaged is one of the clean
    # bag's (damaged payloads without a CRC cannot be told apart, hence only a bound).
    assert [t for _, t, _ in got] == sorted(t for _, t, _ in got)
    intact = set(clean)
    assert sum(m in intact for m in got) >= len(got) - 4 * max(1, len(hits))
    if not hits and cut is not None and cut < len(MCAP.read_bytes()):
        assert damage  # a truncation is always reported


@settings(max_examples=40, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(keep=st.one_of(st.none(), st.floats(0.0, 1.0)),
       hits=st.lists(st.tuples(st.floats(0.0, 1.0), st.binary(min_size=1, max_size=64)),
                     max_size=4))
def test_fuzz_damaged_sqlite_never_crashes(keep: Optional[float], hits: list, clean: list,
                                           sqlite_bag: Path,
                                           tmp_path_factory: pytest.TempPathFactory) -> None:
    out, db = _copy(sqlite_bag, tmp_path_factory.mktemp('fuzz'))
    data = bytearray(db.read_bytes())
    for where, junk in hits:
        at = int(where * (len(data) - 1))
        data[at:at + len(junk)] = junk
    if keep is not None:
        data = data[:int(keep * len(data))]
    db.write_bytes(bytes(data))
    try:
        bag = open_bag(out)
    except BagError as error:  # e.g. the schema page is hit: one clear line
        assert '\n' not in str(error)
        return
    with bag:
        try:
            got = [(m.topic, m.timestamp_ns, bytes(m.data))
                   for m in bag.raw_messages(list(bag.topics()))]
        except BagError as error:
            assert '\n' not in str(error)
            return
    assert [t for _, t, _ in got] == sorted(t for _, t, _ in got) or bag.damage


def test_replay_window_on_a_damaged_bag_counts_no_missing(tmp_path: Path) -> None:
    bag = tmp_path / 'bag'
    bag.mkdir()
    shutil.copy(BAG / 'metadata.yaml', bag)
    (bag / 'paper_thruster.mcap').write_bytes(MCAP.read_bytes()[:600_000])
    assert main(['replay', str(bag), '-o', str(tmp_path / 'out'), '--quiet', '--start', '0.5',
                 '--end', '1.0', '--summary-json', str(tmp_path / 's.json')]) == 3
    damage = json.loads((tmp_path / 's.json').read_text())['damage']
    assert damage['regions'] and damage['missing_vs_index'] == {}
