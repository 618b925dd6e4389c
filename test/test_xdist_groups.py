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
pytest-xdist's loadgroup keeps an ``xdist_group`` on one worker (scripts/test.sh relies on it).

It does so by appending ``@group`` to the test's node id at collection; pytest 9.2 moved the
id where pytest-xdist 3.8 no longer renames it, and the groups were silently ignored (the
bench's session fixture was made in both workers: ~200 s of CI). setup.py pins pytest < 9.2.
"""

import os

import pytest


@pytest.mark.xdist_group('xdist_groups_check')
def test_a_grouped_test_carries_its_group_in_its_node_id(request):
    if not os.environ.get('PYTEST_XDIST_WORKER') or not request.config.getvalue('loadgroup'):
        pytest.skip('runs only in a pytest-xdist worker with --dist loadgroup')
    assert request.node.nodeid.endswith('@xdist_groups_check'), (
        f'{request.node.nodeid}: pytest-xdist ignored the xdist_group mark (pytest '
        f'{pytest.__version__}); see setup.py\'s pin of pytest')


def test_a_plain_test_has_no_group_suffix(request):
    assert '@' not in request.node.nodeid
