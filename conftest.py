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

import json
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


class CompileLog:
    """
    Which kernels numba compiles during which test: ``RD_COMPILE_LOG=PATH`` (opt-in).

    Each pytest process (xdist workers too) appends one JSON line per top-level compile
    to ``PATH``: the test (its setup, call and teardown), the kernel, its signature and
    the CPU seconds it took with its callees. A kernel the package's warm-up also
    compiles should load from the cache in a test; one that compiles there is a layout
    or a function only the test uses (docs/parallel_tests.md, "Stop 45").
    """

    def __init__(self, path: str) -> None:
        """Listen to numba's top-level compiles; write them to ``path``."""
        from numba.core import event
        from reduced_dynamics.compile_kernels import top_level_compiles
        self.path, self.test = path, ''
        event.register('numba:compile', top_level_compiles(self.write))

    def write(self, dispatcher, args, cpu: float) -> None:
        """Append one compile to the log."""
        function = getattr(dispatcher, 'py_func', None)
        record = {'test': self.test, 'cpu_s': round(cpu, 3), 'signature': str(args),
                  'kernel': f'{getattr(function, "__module__", "?")}.'
                            f'{getattr(function, "__qualname__", dispatcher)}'}
        with open(self.path, 'a') as out:
            out.write(json.dumps(record) + '\n')

    def pytest_runtest_logstart(self, nodeid: str, location) -> None:
        """Attribute what follows to this test."""
        self.test = nodeid


def pytest_configure(config) -> None:
    """
    In an xdist worker: this worker's ROS domain for rclpy, the tests and the bench.

    With ``RD_COMPILE_LOG`` set: :class:`CompileLog` in this process.
    """
    if os.environ.get('RD_COMPILE_LOG'):
        config.pluginmanager.register(CompileLog(os.environ['RD_COMPILE_LOG']),
                                      'rd_compile_log')
    domain = xdist_domain_id()
    if domain:
        # ros_harness takes RD_TEST_DOMAIN_ID; bench.node_domain_id RD_BENCH_DOMAIN_ID; a
        # test using rclpy without the harness the plain ROS_DOMAIN_ID.
        for name in ('RD_TEST_DOMAIN_ID', 'RD_BENCH_DOMAIN_ID', 'ROS_DOMAIN_ID'):
            os.environ[name] = domain
