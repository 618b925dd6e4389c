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

"""Writing a chunk's rows from its columns gives the bag of writing them one by one."""

from pathlib import Path

import numpy as np
import pytest

from reduced_dynamics.bag import writer as bag_writer
from reduced_dynamics.bag.errors import BagError
from reduced_dynamics.bag.writer import BagWriter
from reduced_dynamics import output_rows
from reduced_dynamics.output_spool import OutputSpool
from reduced_dynamics.replay import replay, ReplayOptions
from reduced_dynamics.resources import config_path
from reduced_dynamics.robot.model import load_robot

DATA = Path(__file__).parent / 'data'
TOPICS = {'/a': 'geometry_msgs/msg/WrenchStamped', '/b': 'sensor_msgs/msg/JointState',
          '/c': 'std_msgs/msg/String'}


def _bag_bytes(path: Path) -> bytes:
    (mcap,) = path.glob('*.mcap')
    return mcap.read_bytes()


def _write(path: Path, rows: bool, stamps, parts, interleaved: int = 0) -> bytes:
    with BagWriter(path, TOPICS) as bag:
        if interleaved:
            bag.write_raw('/c', 5, b'\x00\x01\x00\x00' + bytes(interleaved))
        if rows:
            bag.write_rows(['/a', '/b'], stamps, parts)
        else:
            for k, stamp in enumerate(stamps.tolist()):
                for topic, part in zip(('/a', '/b'), parts):
                    bag.write_raw(topic, stamp, part[k].tobytes())
        if interleaved:
            bag.write_raw('/c', 7, b'\x00\x01\x00\x00' + bytes(interleaved))
    return _bag_bytes(path)


@pytest.mark.parametrize('chunk_bytes', [2**20, 1000, 97])
@pytest.mark.parametrize('appender', [True, False], ids=['appender', 'rosbags'])
def test_write_rows_writes_the_bag_of_write_raw(tmp_path, monkeypatch, chunk_bytes, appender):
    # Small chunks: a chunk fills up inside a block, inside a row, many times over.
    monkeypatch.setattr(bag_writer, '_CHUNK_BYTES', chunk_bytes)
    if not appender:
        monkeypatch.setattr(bag_writer._McapAppender, 'attach', classmethod(lambda c, w: None))
    rng = np.random.default_rng(0)
    count = 300
    stamps = np.sort(rng.integers(0, 10**12, count))
    stamps[5] = stamps[4]  # equal stamps, out-of-order ones: kept as given
    stamps[7], stamps[8] = stamps[8], stamps[7]
    parts = [rng.integers(0, 256, (count, 60), dtype=np.uint8),
             rng.integers(0, 256, (count, 37), dtype=np.uint8)]
    for interleaved in (0, 50):
        expected = _write(tmp_path / f'raw{interleaved}' / 'bag', False, stamps, parts,
                          interleaved)
        got = _write(tmp_path / f'rows{interleaved}' / 'bag', True, stamps, parts,
                     interleaved)
        assert got == expected


def test_write_rows_refuses_what_write_raw_refuses(tmp_path):
    parts = [np.zeros((2, 10), np.uint8)]
    with BagWriter(tmp_path / 'bag', TOPICS) as bag:
        with pytest.raises(BagError, match='not declared'):
            bag.write_rows(['/x'], np.array([1, 2]), parts)
        with pytest.raises(BagError, match='out of range'):
            bag.write_rows(['/a'], np.array([-1, 2]), parts)
        with pytest.raises(BagError, match='integers'):
            bag.write_rows(['/a'], np.array([1.0, 2.0]), parts)
        with pytest.raises(BagError, match='one record per row'):
            bag.write_rows(['/a'], np.array([1, 2, 3]), parts)
        bag.write_rows(['/a'], np.zeros(0, np.int64), [np.zeros((0, 10), np.uint8)])
        assert bag.message_counts['/a'] == 0


CASES = {
    # SE(3), Odometry, predictions (every 1 s) and diagnostics on some rows
    'paper_realistic': ('paper_realistic', '', {}),
    # SE(2), poses, a commanded wrench: the disturbance topic
    'freeflyer_testbed': ('freeflyer_testbed', 'robots/freeflyer.urdf',
                          {'base_pose_topic': '/base_pose',
                           'commanded_wrench_topic': '/commanded_wrench'}),
}


@pytest.mark.parametrize('smooth', [False, True], ids=['causal', 'smoothed'])
@pytest.mark.parametrize('case', sorted(CASES))
def test_replay_from_columns_writes_the_bag_of_outputs_one_by_one(
        tmp_path, monkeypatch, case, smooth):
    bag, urdf, extra = CASES[case]
    robot = load_robot(str(config_path(urdf)) if urdf else '')
    monkeypatch.setattr(bag_writer, '_CHUNK_BYTES', 20_000)
    written = {}
    for columns in (False, True):
        if not columns:
            monkeypatch.setattr(output_rows, 'columns_apply', lambda encoders: False)
        else:
            monkeypatch.undo()
            monkeypatch.setattr(bag_writer, '_CHUNK_BYTES', 20_000)
            calls = []
            name = 'hold_chunk' if smooth else 'write_chunk'
            original = getattr(output_rows.RowWriter, name)

            def counted(self, *args):
                calls.append(self.columns)
                return original(self, *args)
            monkeypatch.setattr(output_rows.RowWriter, name, counted)
        out = tmp_path / ('columns' if columns else 'reference') / 'out'
        summary = replay(str(DATA / bag), str(out), robot, ReplayOptions(smooth=smooth,
                                                                         **extra))
        written[columns] = _bag_bytes(out)
    assert calls and all(calls)
    assert summary['predictions'] and summary['messages_out']
    assert written[True] == written[False]


def test_spool_gives_back_runs_and_single_rows_in_order(tmp_path):
    encode = lambda sample: b'<' + sample + b'>'  # noqa: E731
    encoders = [('momentum', '/m', encode), ('shape_state', '/s', encode),
                ('diagnostics', '/d', encode)]
    spool = OutputSpool(str(tmp_path / 'spool'), encoders)
    spool.hold_rows(np.array([5, 6]), {'shape_state': np.array([[1, 2], [3, 4]], np.uint8),
                                       'momentum': np.zeros((2, 3), np.uint8)})
    spool.hold_fields(7, {'diagnostics': b'x'}, {'shape_state': b'\x05\x06'})
    spool.hold_rows(np.zeros(0, np.int64), {})
    spool.hold_rows(np.array([2**40]), {'shape_state': np.array([[9, 9]], np.uint8)})
    assert spool.count == 4
    assert list(spool.rows()) == [(5, {1: b'\x01\x02'}), (6, {1: b'\x03\x04'}),
                                  (7, {1: b'\x05\x06', 2: b'<x>'}), (2**40, {1: b'\t\t'})]
    segments = list(spool.segments())
    assert [type(s[0]) for s in segments] == [np.ndarray, int, np.ndarray]
    spool.close()
