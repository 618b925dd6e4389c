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
import shutil
import sys
from typing import Optional

#: How each linter gets there when it is missing (scripts/test.sh, docs/testing.md).
HOW = {
    'ament_flake8': "./scripts/test.sh pip-installs it into the venv (setup.py's [lint] extra)",
    'ament_pep257': "./scripts/test.sh pip-installs it into the venv (setup.py's [lint] extra)",
    'ament_copyright': 'not on PyPI: RD_APT=1 ./scripts/test.sh apt-installs '
                       'python3-ament-copyright, or source ROS 2',
    'ament_xmllint': 'not on PyPI: RD_APT=1 ./scripts/test.sh apt-installs '
                     'python3-ament-xmllint and libxml2-utils, or source ROS 2',
}


def search_path() -> str:
    """Return the venv's bin/ (this interpreter's directory), then PATH."""
    return os.pathsep.join([os.path.dirname(sys.executable), os.environ.get('PATH', '')])


def find_linter(name: str) -> Optional[str]:
    """Return the ``name`` executable: the venv's (pip [lint]) first, then PATH's."""
    return shutil.which(name, path=search_path())


def linter_env() -> dict:
    """Return the environment to run a linter in: the venv's bin/ first on PATH (xmllint)."""
    return dict(os.environ, PATH=search_path())
