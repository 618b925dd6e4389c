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

"""Where the linter tests find the ament linters: where scripts/test.sh put them."""

import os
from pathlib import Path
import shutil
import sys
from typing import Optional

#: Where scripts/linter_packages.sh unpacks the Debian packages pip cannot provide
#: (apt-get download + dpkg -x, not installed).
DEBS = Path(__file__).resolve().parent.parent / '.colcon' / 'debs'

#: How each linter gets there when it is missing (scripts/test.sh, docs/testing.md).
HOW = {
    'ament_flake8': "./scripts/test.sh pip-installs it into the venv (setup.py's [lint] extra)",
    'ament_pep257': "./scripts/test.sh pip-installs it into the venv (setup.py's [lint] extra)",
    'ament_copyright': 'not on PyPI: ./scripts/test.sh unpacks python3-ament-copyright into '
                       '.colcon/debs/root (apt-get download; its output says why not), '
                       'RD_APT=1 ./scripts/test.sh apt-installs it, or source ROS 2',
    'ament_xmllint': 'not on PyPI: ./scripts/test.sh unpacks python3-ament-xmllint and '
                     'libxml2-utils into .colcon/debs/root (apt-get download; its output says '
                     'why not), RD_APT=1 ./scripts/test.sh apt-installs them, or source ROS 2',
}


def search_path(debs: Path = DEBS) -> str:
    """Return the venv's bin/ (this interpreter's directory), PATH, then the unpacked debs'."""
    return os.pathsep.join([os.path.dirname(sys.executable), os.environ.get('PATH', ''),
                            str(debs / 'root' / 'usr' / 'bin')])


def find_linter(name: str, debs: Path = DEBS) -> Optional[str]:
    """Return the ``name`` executable: the venv's (pip [lint]), PATH's, the unpacked debs'."""
    return shutil.which(name, path=search_path(debs))


def linter_env(exe: Optional[str] = None, debs: Path = DEBS) -> dict:
    """
    Return the environment to run the linter ``exe`` in.

    The search path of :func:`search_path` (xmllint); for a linter from the unpacked debs,
    their Python modules (ament_copyright finds its licenses through their entry points) and
    the XML catalog that points package.xml's schema at their local copy.
    """
    env = dict(os.environ, PATH=search_path(debs))
    root = debs / 'root'
    if exe is None or not Path(exe).resolve().is_relative_to(root.resolve()):
        return env
    modules = root / 'usr' / 'lib' / 'python3' / 'dist-packages'
    env['PYTHONPATH'] = os.pathsep.join(
        p for p in (str(modules), os.environ.get('PYTHONPATH', '')) if p)
    catalog = debs / 'catalog.xml'
    if catalog.is_file():
        env['XML_CATALOG_FILES'] = str(catalog)
    return env
