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

"""Locate the files the package ships (parameters, example robot URDF)."""

from __future__ import annotations

import importlib.util
import os
from pathlib import Path

PACKAGE = 'reduced_dynamics'
# Install-only mirror of the top-level config/ folder (see setup.py: package_dir maps
# it onto config/ so `pip install .` wheels carry the files).  Never in the source tree.
_DATA_PACKAGE = 'reduced_dynamics._data'
ENV_CONFIG_DIR = 'REDUCED_DYNAMICS_CONFIG_DIR'


def _ament_share_dir() -> Path | None:
    """Return share/reduced_dynamics of the first AMENT_PREFIX_PATH prefix registering it."""
    try:
        from ament_index_python.packages import get_package_share_directory
    except ImportError:
        get_package_share_directory = None
    if get_package_share_directory is not None:
        try:
            return Path(get_package_share_directory(PACKAGE))
        except Exception:  # PackageNotFoundError, or AMENT_PREFIX_PATH unset
            return None
    # Same lookup as ament_index_python, without depending on it.
    for prefix in os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep):
        marker = Path(prefix, 'share', 'ament_index', 'resource_index', 'packages', PACKAGE)
        if prefix and marker.is_file():
            return Path(prefix, 'share', PACKAGE)
    return None


def config_dirs() -> list[Path]:
    """Return the candidate config/ directories, most specific first."""
    dirs = []
    if os.environ.get(ENV_CONFIG_DIR):
        dirs.append(Path(os.environ[ENV_CONFIG_DIR]))
    # 1. package data next to the imported code: `pip install .`, non-symlink colcon,
    #    PEP 660 editable installs.
    try:
        spec = importlib.util.find_spec(_DATA_PACKAGE)
    except ImportError:
        spec = None
    if spec is not None and spec.submodule_search_locations:
        dirs.extend(Path(p) for p in spec.submodule_search_locations)
    # 2. source checkout: `pip install -e .` (setup.py develop), colcon --symlink-install.
    dirs.append(Path(__file__).resolve().parent.parent / 'config')
    # 3. ament share directory of a sourced colcon/ROS install.
    share = _ament_share_dir()
    if share is not None:
        dirs.append(share / 'config')
    return dirs


def config_path(relative: str | os.PathLike) -> Path:
    """Return the absolute path of ``config/<relative>`` (e.g. 'robots/paper_robot.urdf')."""
    for directory in config_dirs():
        candidate = directory / relative
        if candidate.is_file():
            return candidate.resolve()
    raise FileNotFoundError(
        f'{PACKAGE}: config/{relative} not found in ' +
        ', '.join(str(d) for d in config_dirs()))


def params_yaml() -> Path:
    """Return the path of the default node parameter file."""
    return config_path('params.yaml')


def paper_robot_urdf() -> Path:
    """Return the path of the paper's case-study robot (section 6)."""
    return config_path(Path('robots', 'paper_robot.urdf'))
