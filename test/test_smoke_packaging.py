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

"""Smoke checks for the packaging scaffolding (version, metadata, config lookup)."""

from pathlib import Path
import xml.etree.ElementTree as ET

import reduced_dynamics

REPO_ROOT = Path(__file__).resolve().parent.parent


def test_version_matches_package_xml():
    root = ET.parse(REPO_ROOT / 'package.xml').getroot()
    assert root.findtext('name') == 'reduced_dynamics'
    assert root.findtext('version') == reduced_dynamics.__version__ == '0.1.0'


def test_ament_resource_marker_exists():
    assert (REPO_ROOT / 'resource' / 'reduced_dynamics').is_file()
