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

"""Pytest root: its folder goes first on sys.path, so tests import this checkout's package."""

import os

#: Fast DDS maps a domain to ports 7400 + 250 * id (+ offsets): ids up to 101 stay below
#: Linux's ephemeral ports; 0 (everyone's default) is left out.
DOMAINS = 100


def xdist_domain_id() -> str:
    """
    Return a ROS_DOMAIN_ID of this pytest-xdist worker's own, or '' outside a worker.

    Workers of one run get consecutive ids from a random base (the run's uid), so the
    DDS tests of two workers never see each other, and two runs side by side rarely do.
    """
    worker = os.environ.get('PYTEST_XDIST_WORKER', '')  # 'gw0', 'gw1', ... (set by xdist)
    run = os.environ.get('PYTEST_XDIST_TESTRUNUID', '')
    if not worker.startswith('gw') or not run:
        return ''
    return str(1 + (int(run, 16) + int(worker[2:])) % DOMAINS)


def pytest_configure(config) -> None:
    """In an xdist worker: this worker's ROS domain for rclpy, the tests and the bench."""
    domain = xdist_domain_id()
    if domain:
        # ros_harness takes RD_TEST_DOMAIN_ID; bench.node_domain_id RD_BENCH_DOMAIN_ID; a
        # test using rclpy without the harness the plain ROS_DOMAIN_ID.
        for name in ('RD_TEST_DOMAIN_ID', 'RD_BENCH_DOMAIN_ID', 'ROS_DOMAIN_ID'):
            os.environ[name] = domain
