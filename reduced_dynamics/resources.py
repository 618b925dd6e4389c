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

"""Locate the files the package ships (example robot URDF, parameters)."""

from __future__ import annotations

import os


def _candidates(relative: str) -> list[str]:
    here = os.path.dirname(os.path.abspath(__file__))
    paths = [os.path.join(os.path.dirname(here), 'config', relative)]
    try:
        from ament_index_python.packages import get_package_share_directory
        paths.append(os.path.join(get_package_share_directory('reduced_dynamics'),
                                  'config', relative))
    except Exception:  # noqa: BLE001 - ament index absent or package not installed there
        pass
    return paths


def config_path(relative: str) -> str:
    """Absolute path of ``config/<relative>`` in the source tree or the ament share dir."""
    for path in _candidates(relative):
        if os.path.exists(path):
            return path
    raise FileNotFoundError(f'reduced_dynamics: cannot find config/{relative}')


def paper_robot_urdf() -> str:
    """Path of the embedded default robot: the paper's case study (section 6)."""
    return config_path(os.path.join('robots', 'paper_robot.urdf'))
