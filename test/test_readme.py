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
README.md is a user's guide that reads in ten minutes, and what it shows works.

Checked: its length; the sections a newcomer looks for, as headings; one picture, shipped
and small; the two commands; every subcommand of the CLI named; every relative link
resolving; and the real-data walkthrough run as written from the clone, on the shipped
recording only.
"""

import os
from pathlib import Path
import re
import shlex
import subprocess
import sys

from reduced_dynamics.cli import build_parser

REPO = Path(__file__).resolve().parent.parent
README = (REPO / 'README.md').read_text()
MAX_LINES = 300
#: The guide's sections, in order (issue 21, item 19).
HEADINGS = ['## Two commands', '## The ROS 2 path', '## The node',
            '## Replay and the other subcommands', '## Real data walkthrough',
            '## Documentation']


def _section(heading: str) -> str:
    """Return the text under a ``## `` heading, up to the next one."""
    start = README.index(f'\n{heading}\n')
    end = README.find('\n## ', start + 1)
    return README[start:end if end >= 0 else None]


def _bash_blocks(text: str) -> list[str]:
    return re.findall(r'^```bash\n(.*?)^```$', text, re.M | re.S)


def test_readme_is_a_short_guide_with_the_sections_a_newcomer_needs():
    assert README.count('\n') <= MAX_LINES
    headings = [line for line in README.splitlines() if line.startswith('## ')]
    assert [h for h in headings if h in HEADINGS] == HEADINGS


def test_readme_shows_one_shipped_picture_under_200_kb():
    images = re.findall(r'!\[[^\]]+\]\(([^)]+)\)', README)
    assert len(images) == 1
    picture = REPO / images[0]
    assert picture.suffix == '.png' and picture.is_file()
    assert picture.stat().st_size < 200_000
    assert picture.read_bytes()[:8] == b'\x89PNG\r\n\x1a\n'


def test_readme_gives_the_two_commands_as_written():
    block = _bash_blocks(_section('## Two commands'))[0]
    commands = [line.split('#')[0].strip() for line in block.splitlines()]
    assert commands == ['./scripts/demo.sh', './scripts/test.sh']
    for command in commands:
        assert os.access(REPO / command, os.X_OK)


def test_readme_keeps_the_install_blocks_check_readme_install_runs():
    section = _section('## The ROS 2 path')
    for marker in ('ros-apt', 'ros-wheels'):
        after = section.split(f'<!-- readme-ci: {marker} -->\n', 1)[1]
        assert after.startswith('```bash\n')


def test_readme_names_every_subcommand_and_the_node_topics():
    subparsers = next(a for a in build_parser()._actions if a.dest == 'command')
    section = _section('## Replay and the other subcommands')
    for name in subparsers.choices:
        assert f'`{name}' in section, name
    node = _section('## The node')
    for topic in ('~/momentum', '~/drift/momentum_rate', '~/predict_base_motion/request',
                  'joint_states', '/diagnostics'):
        assert f'`{topic}`' in node, topic


def test_readme_links_resolve():
    links = re.findall(r'\]\(([^)#]+)(?:#[^)]*)?\)', README)
    local = [link for link in links if '://' not in link]
    assert local
    for link in local:
        assert (REPO / link).exists(), link


def test_real_data_walkthrough_runs_from_the_clone_alone(tmp_path):
    """The walkthrough's commands, run as written on the shipped recording."""
    section = _section('## Real data walkthrough')
    assert '../shared' not in section
    script = _bash_blocks(section)[0]
    bag = re.search(r'test/data/freeflyer2/\S+', script).group(0).rstrip("',")
    assert (REPO / bag / 'metadata.yaml').is_file()
    # The commands as a user types them, with this interpreter for `python` and for the
    # `reduced-dynamics` entry point, and the outputs in a temporary folder.
    cli = f'{shlex.quote(sys.executable)} -m reduced_dynamics.cli'
    script = script.replace('reduced-dynamics ', cli + ' ', 1)
    script = re.sub(r'^python ', shlex.quote(sys.executable) + ' ', script, flags=re.M)
    script = script.replace('out/', f'{tmp_path}/out/')
    env = {**os.environ, 'PYTHONPATH': os.pathsep.join(
        [str(REPO)] + [p for p in os.environ.get('PYTHONPATH', '').split(os.pathsep) if p])}
    proc = subprocess.run(['bash', '-e', '-o', 'pipefail', '-c', script], cwd=REPO, env=env,
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert 'rejected: none' in proc.stdout
    figures = re.search(r'Fx (\S+)  Fy (\S+)  Mz (\S+)', proc.stdout)
    # The figures the guide quotes, as measured (smoothed, the replay default).
    quoted = re.search(r'\*\*(\S+) / (\S+) / (\S+)\*\*', section).groups()
    assert figures.groups() == quoted
    assert (tmp_path / 'out' / 'freeflyer2' / 'plots' / 'drift.png').is_file()
