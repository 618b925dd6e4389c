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
The Sphinx documentation in docs/ builds with warnings as errors, every page included.

Needs the [docs] extra (Sphinx, myst-parser; scripts/test.sh installs it): without it the
test fails, as the linter tests do without their linters, so CI cannot skip the build.
"""

from pathlib import Path
import re
import subprocess
import sys

import yaml

REPO = Path(__file__).resolve().parent.parent
DOCS = REPO / 'docs'


def test_docs_build_with_warnings_as_errors(tmp_path):
    out = tmp_path / 'html'
    proc = subprocess.run(
        [sys.executable, '-m', 'sphinx', '-W', '--keep-going', '-q', '-b', 'html',
         '-d', str(tmp_path / 'doctrees'), str(DOCS), str(out)],
        capture_output=True, text=True, timeout=600, cwd=REPO)
    assert proc.returncode == 0, \
        'sphinx-build failed (pip install ".[docs]"?):\n' + proc.stdout + proc.stderr
    # Every page of docs/ is built and reachable from the index (the glob toctree).
    index = (out / 'index.html').read_text()
    for page in DOCS.glob('*.md'):
        assert (out / f'{page.stem}.html').is_file(), page.name
        if page.stem != 'index':
            assert f'href="{page.stem}.html"' in index, page.name
    # The API reference documents the package's modules from their docstrings.
    api = (out / 'api.html').read_text()
    for module in ('reduced_dynamics.estimator.filter', 'reduced_dynamics.replay',
                   'reduced_dynamics.reduction.vector_field'):
        assert f'id="module-{module}"' in api, module
    assert re.search(r'id="reduced_dynamics\.estimator\.filter\.\w+"', api)


def test_rosdoc2_finds_the_sphinx_project():
    """rosdoc2 reads rosdoc2.yaml (exported in package.xml): its sphinx_sourcedir is docs/."""
    assert '<rosdoc2>rosdoc2.yaml</rosdoc2>' in (REPO / 'package.xml').read_text()
    attic, config = yaml.safe_load_all((REPO / 'rosdoc2.yaml').read_text())
    assert attic == {'type': 'rosdoc2 config', 'version': 1}
    (builder,) = [b['sphinx'] for b in config['builders'] if 'sphinx' in b]
    assert (REPO / builder['sphinx_sourcedir'] / 'conf.py').is_file()
    assert (REPO / config['settings']['python_source'] / '__init__.py').is_file()
