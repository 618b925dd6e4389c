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

"""The real recording shipped in test/data/freeflyer2: unchanged, licensed, readable."""

import hashlib
from pathlib import Path
import re

import pytest

from reduced_dynamics.bag.reader import open_bag

FOLDER = Path(__file__).resolve().parent / 'data' / 'freeflyer2'
BAG = FOLDER / 'rosbag2_2024_03_14-14_17_23'
SHARED = Path(__file__).resolve().parent.parent.parent / 'shared' / 'data' / 'freeflyer2'


def _checksums() -> dict[str, str]:
    """Return the SHA-256 sums the folder's README states, by file name."""
    text = (FOLDER / 'README.md').read_text()
    return {name: digest for digest, name in re.findall(r'^([0-9a-f]{64})  (\S+)$', text, re.M)}


def test_the_shipped_recording_is_the_one_its_readme_describes():
    """The bag is there, byte for byte as the README's checksums say, with its license."""
    sums = _checksums()
    assert set(sums) == {p.name for p in BAG.iterdir()}
    for name, digest in sums.items():
        assert hashlib.sha256((BAG / name).read_bytes()).hexdigest() == digest, name
    license_text = (FOLDER / 'LICENSE').read_text()
    assert license_text.startswith('MIT License')
    assert 'Copyright (c) 2023 Stanford Autonomous Systems Lab' in license_text
    readme = (FOLDER / 'README.md').read_text()
    assert 'StanfordASL/freeflyer2' in readme and 'LICENSE' in readme


def test_the_shipped_recording_holds_what_the_walkthrough_replays():
    """The mocap poses and thruster commands the README's walkthrough and the tests use."""
    with open_bag(str(BAG)) as bag:
        poses = sum(1 for _ in bag.raw_messages(['/vrpn_mocap/robot/pose']))
        commands = sum(1 for _ in bag.raw_messages(['/robot/commands/binary_thrust']))
    assert (poses, commands) == (6569, 3535)


@pytest.mark.skipif(not SHARED.is_dir(), reason=f'shared real data absent ({SHARED})')
def test_the_shipped_recording_equals_the_shared_copy():
    """Where the shared data set is beside the clone, the shipped bag is its copy."""
    for path in BAG.iterdir():
        assert path.read_bytes() == (SHARED / BAG.name / path.name).read_bytes()
