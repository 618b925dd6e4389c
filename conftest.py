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
import platform


def pin_blas_kernels() -> str:
    """
    Have OpenBLAS run its Haswell kernels on any x86-64 CPU with AVX2 and FMA; return them.

    The golden outputs and the tests that compare compiled kernels with numpy bit for
    bit hold with those kernels (AVX2 Intel and AMD CPUs run them anyway). On a CPU with
    AVX-512 OpenBLAS picks its SkylakeX kernels, whose sums round differently in the last
    bits: measured on a Xeon with AVX-512, 8 such tests failed (the golden outputs, the
    block test's and the pulse fit's numpy comparisons) and all passed with
    ``OPENBLAS_CORETYPE=Haswell``. Set here, before anything imports numpy (pytest's
    plugins do not), so this process and every process the tests start read it. A
    value already set is kept; ``RD_NATIVE_BLAS=1`` leaves OpenBLAS its own choice.
    """
    if 'OPENBLAS_CORETYPE' in os.environ or os.environ.get('RD_NATIVE_BLAS') == '1' or \
            platform.machine() != 'x86_64':
        return os.environ.get('OPENBLAS_CORETYPE', '')
    try:
        with open('/proc/cpuinfo') as info:
            flags = next((line.split(':', 1)[1].split() for line in info
                          if line.startswith('flags')), [])
    except OSError:  # not Linux: OpenBLAS's own choice
        return ''
    if 'avx2' in flags and 'fma' in flags:
        os.environ['OPENBLAS_CORETYPE'] = 'Haswell'
    return os.environ.get('OPENBLAS_CORETYPE', '')


pin_blas_kernels()

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
