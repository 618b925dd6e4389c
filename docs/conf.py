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
Sphinx configuration of the user documentation (MyST Markdown) and the API reference.

Build: ``sphinx-build -W --keep-going docs docs/_build`` (``pip install ".[docs]"``).
rosdoc2 finds this folder through ``rosdoc2.yaml`` (``sphinx_sourcedir: docs``); it runs
this file inside its own wrapper, which adds its theme, intersphinx and sphinx-apidoc.
"""

import importlib
import os
import pkgutil
import re
import sys
from typing import Optional

from sphinx.domains.python import PythonDomain

ROOT = os.path.abspath(os.path.join(os.path.dirname(__file__), '..'))
# The checkout's sources, not an installed copy, are what the API reference documents
# (under rosdoc2, __file__ is its wrapper's: the package is found as rosdoc2 sets it up).
if os.path.isfile(os.path.join(ROOT, 'reduced_dynamics', '__init__.py')):
    sys.path.insert(0, ROOT)

project = 'reduced_dynamics'
author = 'reduced_dynamics developers'
copyright = '2026, reduced_dynamics developers'  # noqa: A001 (Sphinx's name)
release = importlib.import_module('reduced_dynamics').__version__

extensions = [
    'myst_parser',
    'sphinx.ext.autodoc',
    'sphinx.ext.napoleon',
]
source_suffix = {'.md': 'markdown', '.rst': 'restructuredtext'}
root_doc = 'index'
# COPYRIGHT_HEADER.txt is the header template of the source files, not a page.
exclude_patterns = ['_build', 'Thumbs.db', '.DS_Store']
myst_enable_extensions = ['colon_fence']
# A page may go from its title to a level-3 heading (moved text keeps its levels): a style
# matter, not a broken page. Broken links and references still fail the build.
suppress_warnings = ['myst.header']
# Headings become link targets (`[text](filter.md#re-timing)`) down to level 3.
myst_heading_anchors = 3

autodoc_member_order = 'bysource'
autodoc_default_options = {'members': True, 'show-inheritance': True}
# Type hints go into the description, where long numpy types stay readable.
autodoc_typehints = 'description'
napoleon_google_docstring = True
napoleon_numpy_docstring = True
# The node shell and the bench's node processes import rclpy: without it (a docs-only
# environment) they are documented from mocks.
autodoc_mock_imports = []
try:
    importlib.import_module('rclpy')
except ImportError:
    autodoc_mock_imports = ['rclpy', 'rosidl_runtime_py', 'diagnostic_msgs', 'geometry_msgs',
                            'lifecycle_msgs', 'nav_msgs', 'sensor_msgs', 'std_msgs',
                            'trajectory_msgs', 'rcl_interfaces', 'builtin_interfaces']

try:
    import sphinx_rtd_theme  # noqa: F401
    html_theme = 'sphinx_rtd_theme'
except ImportError:
    html_theme = 'alabaster'
html_title = 'reduced_dynamics'


def _modules() -> list[str]:
    """Return every module of the package, sorted (new modules are listed without edits)."""
    package = importlib.import_module('reduced_dynamics')
    names = ['reduced_dynamics']
    for info in pkgutil.walk_packages(package.__path__, 'reduced_dynamics.'):
        if not info.name.rsplit('.', 1)[-1].startswith('_'):
            names.append(info.name)
    return sorted(names)


def _api_page(app, docname: str, source: list[str]) -> None:
    """Append one automodule directive per module to the page ``api``."""
    if docname != 'api':
        return
    # :ignore-module-all: documents each object where it is defined, once: a package's
    # __all__ re-exports would otherwise be a second target for every cross-reference.
    blocks = [f'\n## `{name}`\n\n```{{eval-rst}}\n.. automodule:: {name}\n'
              f'   :ignore-module-all:\n```\n' for name in _modules()]
    source[0] += ''.join(blocks)


#: Inline literals (left alone) and |x| outside them: the docstrings write norms as in
#: plain text (|w|, |velocity|), which reStructuredText would read as substitutions.
_LITERAL = re.compile(r'(``.+?``)')
_NORM = re.compile(r'(?<![\\|\w])\|(?=[^\s|])([^|\n]*?)(?<=[^\s|])\|(?![|\w])')


def _escape_norms(app, what, name, obj, options, lines: list[str]) -> None:
    """Escape the bars of plain-text norms in a docstring (outside inline literals)."""
    for i, line in enumerate(lines):
        parts = _LITERAL.split(line)
        parts[::2] = [_NORM.sub(r'\\|\1\\|', part) for part in parts[::2]]
        lines[i] = ''.join(parts)


def _index_glob(app, docname: str, source: list[str]) -> None:
    """
    Drop the index's catch-all ``*`` while every page is listed by name.

    The toctree lists the pages in reading order, then ``*`` for every other page of
    docs/; Sphinx warns when a glob matches nothing, which is no fault here.
    """
    if docname != 'index':
        return
    listed = set(re.findall(r'^([\w/]+)$', source[0], re.M))
    if not set(app.env.found_docs) - listed - {'index'}:
        source[0] = re.sub(r'^\*\n', '', source[0], flags=re.M)


class _IndexedPythonDomain(PythonDomain):
    """
    The Python domain with its fuzzy search (``find_obj``, searchmode 1) by a suffix index.

    Sphinx resolves every typed field (``:type x: int``, which autodoc_typehints
    'description' writes for each annotated argument) in its fuzzy mode, and each lookup
    not found exactly scans every object's name (~17 000 scans of ~7 000 names here: 12.6 s
    of 110 s profiled, docs/parallel_tests.md "Stop 45"). The index holds each name under
    its dotted suffixes, in the objects' order: a lookup gives the names the scan gives, in
    the same order. Sphinx's own ``find_obj`` answers every other lookup.
    """

    _suffixes: Optional[dict] = None

    def note_object(self, *args, **kwargs):
        """Record an object (Sphinx's), and forget the index."""
        self._suffixes = None
        return super().note_object(*args, **kwargs)

    def clear_doc(self, docname: str) -> None:
        """Forget a document's objects (Sphinx's), and the index."""
        self._suffixes = None
        super().clear_doc(docname)

    def merge_domaindata(self, docnames, otherdata: dict) -> None:
        """Merge a parallel reader's objects (Sphinx's), and forget the index."""
        self._suffixes = None
        super().merge_domaindata(docnames, otherdata)

    def find_obj(self, env, modname: str, classname: str, name: str, type: Optional[str],
                 searchmode: int = 0) -> list:
        """Return Sphinx's matches; the fuzzy scan of searchmode 1 read from the index."""
        name = name.removesuffix('()')
        if searchmode != 1 or not name:
            return super().find_obj(env, modname, classname, name, type, searchmode)
        objects = self.objects
        objtypes = list(self.object_types) if type is None else self.objtypes_for_role(type)
        if objtypes is None:
            return []
        # Sphinx's order: module.class.name, module.name, name, then the fuzzy search.
        for candidate in (f'{modname}.{classname}.{name}' if modname and classname else '',
                          f'{modname}.{name}' if modname else '', name):
            if candidate in objects and objects[candidate].objtype in objtypes:
                return [(candidate, objects[candidate])]
        if self._suffixes is None:
            self._suffixes = {}
            for oname in objects:
                parts = oname.split('.')
                for start in range(1, len(parts)):
                    self._suffixes.setdefault('.' + '.'.join(parts[start:]), []).append(oname)
        return [(oname, objects[oname]) for oname in self._suffixes.get('.' + name, ())
                if objects[oname].objtype in objtypes]


def setup(app) -> dict:
    """Register the generated API page, the index's glob and the docstring filter."""
    app.add_domain(_IndexedPythonDomain, override=True)
    app.connect('source-read', _api_page)
    app.connect('source-read', _index_glob)
    app.connect('autodoc-process-docstring', _escape_norms)
    return {'parallel_read_safe': True}
