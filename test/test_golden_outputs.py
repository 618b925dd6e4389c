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

The same code gives other last bits on another CPU or library build (OpenBLAS picks
its kernels by CPU; numba compiles for the host), and a detection's timing can carry
them into every later message: a second machine's outputs of unchanged code are added
as a *variant* of the key (``RD_BLESS_GOLDEN=variant``, recorded with the platform),
never in place of the primary hashes. A code change that moves numbers re-blesses the
primary and drops the variants, which that change invalidates.
"""

import hashlib
import json
import os
from pathlib import Path
import platform

import pytest

from reduced_dynamics.bag.reader import open_bag
from reduced_dynamics.params import defaults
from reduced_dynamics.replay import replay, ReplayOptions
from reduced_dynamics.resources import config_path
from reduced_dynamics.robot.model import load_robot

DATA = Path(__file__).parent / 'data'
GOLDEN = DATA / 'golden_outputs.json'
BLESS = os.environ.get('RD_BLESS_GOLDEN', '') not in ('', '0')
#: RD_BLESS_GOLDEN=variant: add this machine's hashes as a variant of unchanged code.
BLESS_VARIANT = os.environ.get('RD_BLESS_GOLDEN', '') == 'variant'

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


def platform_fingerprint() -> str:
    """Return what decides the last bits besides the code: CPU, BLAS kernels, libraries."""
    import numba
    import numpy
    from threadpoolctl import threadpool_info
    blas = sorted({f"{i.get('internal_api')} {i.get('architecture')} {i.get('version')}"
                   for i in threadpool_info() if i.get('user_api') == 'blas'})
    return (f'{platform.machine()} {platform.processor() or ""}'.strip()
            + f'; {"; ".join(blas)}; numpy {numpy.__version__}; numba {numba.__version__}')


def accepted_hashes(golden: dict, key: str) -> list[dict[str, str]]:
    """Return the primary hashes of ``key`` and its platform variants."""
    variants = golden.get('variants', {}).get(key, [])
    return [golden[key]] + [variant['hashes'] for variant in variants]


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
    if BLESS_VARIANT:
        if key in golden and hashes not in accepted_hashes(golden, key):
            golden.setdefault('variants', {}).setdefault(key, []).append(
                {'platform': platform_fingerprint(), 'hashes': hashes})
            GOLDEN.write_text(json.dumps(golden, indent=2, sort_keys=True) + '\n')
        return
    if BLESS:
        golden[key] = hashes
        golden.get('variants', {}).pop(key, None)
        GOLDEN.write_text(json.dumps(golden, indent=2, sort_keys=True) + '\n')
        return
    assert key in golden, f'no golden outputs for {key}: bless them (RD_BLESS_GOLDEN=1)'
    if hashes in accepted_hashes(golden, key):
        return
    changed = sorted(t for t in set(hashes) | set(golden[key])
                     if hashes.get(t) != golden[key].get(t))
    assert not changed, (f'{key}: outputs changed on {changed} (platform: '
                         f'{platform_fingerprint()}); if that is intended, re-bless with '
                         'RD_BLESS_GOLDEN=1, or for unchanged code on another machine '
                         'RD_BLESS_GOLDEN=variant (docs/estimator_modules.md; OpenBLAS '
                         'kernels: conftest.pin_blas_kernels)')


def test_openblas_runs_the_kernels_the_golden_outputs_were_recorded_with():
    """conftest.pin_blas_kernels took effect: OpenBLAS was loaded after it set its kernels."""
    from threadpoolctl import threadpool_info
    wanted = os.environ.get('OPENBLAS_CORETYPE', '')
    if not wanted:
        pytest.skip('OPENBLAS_CORETYPE unset: OpenBLAS picks its kernels (conftest.py)')
    loaded = [info for info in threadpool_info() if info.get('internal_api') == 'openblas']
    assert loaded, 'numpy and scipy load OpenBLAS'
    for info in loaded:
        assert info.get('architecture', '').lower() == wanted.lower(), info
