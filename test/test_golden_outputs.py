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
Golden outputs: shipped bags replay to the very bytes recorded in golden_outputs.json.

A guard for refactors that must not change a number (splitting the estimator, the
bounded-memory smoother): every output message of a replay, causal and smoothed, is
hashed per topic (stamp and CDR bytes, in bag order). A change that is meant to move
the numbers (a new kernel, new defaults) re-blesses the file, see docs/golden_outputs.md::

    RD_BLESS_GOLDEN=1 python -m pytest test/test_golden_outputs.py

and says so in its commit.
"""

import hashlib
import json
import os
from pathlib import Path

import pytest

from reduced_dynamics.bag.reader import open_bag
from reduced_dynamics.params import defaults
from reduced_dynamics.replay import replay, ReplayOptions
from reduced_dynamics.resources import config_path
from reduced_dynamics.robot.model import load_robot

DATA = Path(__file__).parent / 'data'
GOLDEN = DATA / 'golden_outputs.json'
BLESS = os.environ.get('RD_BLESS_GOLDEN', '') not in ('', '0')

#: name -> (bag, URDF ('' = the paper robot), replay options beside ``smooth``)
CASES = {
    # SE(3), Odometry, shape joints, predictions, diagnostics.
    'paper_realistic': ('paper_realistic', '', {}),
    # The same with the noise parameters alone (use_message_covariance false): the bytes
    # of before the message covariances (docs/message_covariance.md).
    'paper_realistic_parameters': ('paper_realistic', '',
                                   {'params': {**defaults(), 'use_message_covariance': False}}),
    # SE(2), poses with a stall and bunched frames, the commanded-wrench filter.
    'freeflyer_testbed': ('freeflyer_testbed', 'robots/freeflyer.urdf',
                          {'base_pose_topic': '/base_pose',
                           'commanded_wrench_topic': '/commanded_wrench'}),
}


def output_hashes(out: Path) -> dict[str, str]:
    """Return sha256 per output topic over (stamp, CDR bytes) of its messages, in bag order."""
    digests: dict[str, 'hashlib._Hash'] = {}
    with open_bag(str(out)) as reader:
        topics = sorted(reader.topics())
        for message in reader.raw_messages(topics):
            digest = digests.setdefault(message.topic, hashlib.sha256())
            digest.update(message.timestamp_ns.to_bytes(8, 'little'))
            digest.update(bytes(message.data))
    return {topic: digest.hexdigest() for topic, digest in sorted(digests.items())}


def _replay_hashes(tmp_path: Path, case: str, smooth: bool) -> dict[str, str]:
    bag, urdf, extra = CASES[case]
    robot = load_robot(str(config_path(urdf)) if urdf else '')
    out = tmp_path / 'out'
    replay(str(DATA / bag), str(out), robot, ReplayOptions(smooth=smooth, **extra))
    return output_hashes(out)


@pytest.mark.parametrize('smooth', [False, True], ids=['causal', 'smoothed'])
@pytest.mark.parametrize('case', sorted(CASES))
def test_replay_outputs_are_the_golden_bytes(tmp_path, case, smooth):
    key = f'{case}/{"smoothed" if smooth else "causal"}'
    hashes = _replay_hashes(tmp_path, case, smooth)
    golden = json.loads(GOLDEN.read_text()) if GOLDEN.exists() else {}
    if BLESS:
        golden[key] = hashes
        GOLDEN.write_text(json.dumps(golden, indent=2, sort_keys=True) + '\n')
        return
    assert key in golden, f'no golden outputs for {key}: bless them (RD_BLESS_GOLDEN=1)'
    changed = sorted(t for t in set(hashes) | set(golden[key])
                     if hashes.get(t) != golden[key].get(t))
    assert not changed, (f'{key}: outputs changed on {changed}; if that is intended, '
                         're-bless with RD_BLESS_GOLDEN=1 (docs/golden_outputs.md)')
