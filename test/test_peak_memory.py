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

import subprocess
import sys

from reduced_dynamics.peak_memory import peak_resident_kib

_CHILD = """
import resource
from reduced_dynamics.peak_memory import peak_resident_kib
print(peak_resident_kib(), resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)
"""


def test_a_fresh_interpreter_reads_its_own_peak_not_its_parents():
    # The parent holds 300 MiB when it starts the child: ru_maxrss of the child
    # reads at least that (carried across execve), its own peak stays small.
    ballast = bytearray(300 * 1024 * 1024)
    ballast[::4096] = b'\x01' * len(ballast[::4096])
    result = subprocess.run([sys.executable, '-c', _CHILD], capture_output=True, text=True,
                            check=True)
    own, inherited = (int(value) for value in result.stdout.split())
    assert inherited >= 290 * 1024
    assert own < 150 * 1024
    del ballast


def _resident_kib() -> int:
    with open('/proc/self/status', encoding='ascii') as status:
        return next(int(line.split()[1]) for line in status if line.startswith('VmRSS:'))


def test_the_peak_rises_with_what_this_process_touches():
    # Touch enough to pass the high-water mark so far (another test may have raised it).
    before = peak_resident_kib()
    ballast = bytearray((before - _resident_kib() + 64 * 1024) * 1024)
    ballast[::4096] = b'\x01' * len(ballast[::4096])
    assert peak_resident_kib() >= before + 60 * 1024
    del ballast


def test_replay_peak_figures_are_the_replays_own(tmp_path):
    # The bench's replay memory figures (soak and smoothed) start fresh interpreters
    # from a parent that may be large; the parent here holds 900 MiB, more than a
    # short replay needs: with ru_maxrss both figures read the parent's 900 MiB.
    from reduced_dynamics.bench import replay_memory
    from reduced_dynamics.robot.model import load_robot
    from reduced_dynamics.simulator import simulate_bag, SimulationOptions
    from reduced_dynamics.soak import replay_peak
    bag = tmp_path / 'bag'
    simulate_bag(load_robot(), str(bag), SimulationOptions(duration=0.5, rate=1000.0,
                                                           base_rate=200.0, overwrite=True))
    ballast = bytearray(900 * 1024 * 1024)
    ballast[::4096] = b'\x01' * len(ballast[::4096])
    soak = replay_peak(str(bag), str(tmp_path / 'out'))
    smoothed = replay_memory(str(bag), str(tmp_path / 'out_smoothed'))
    del ballast
    assert soak['processed'] == smoothed['processed'] > 0
    for figures in (soak, smoothed):
        assert 0 < figures['rss_before_mib'] <= figures['peak_rss_mib'] < 800
