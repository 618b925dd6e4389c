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
A process's own peak resident memory (the replay and fleet memory figures).

``resource.getrusage(RUSAGE_SELF).ru_maxrss`` is not it on Linux: the kernel
carries the high-water mark of the process that forked across ``execve``, so a
fresh interpreter started by a large parent reports the parent's peak (measured:
a child of a 513 MiB parent read 513 MiB, its own ``VmHWM`` 13 MiB; the stop-23
soak's replay figures read the bench process's 454 MiB for both bags). ``VmHWM``
in ``/proc/self/status`` belongs to the process's own address space.
"""

from __future__ import annotations

import resource


def peak_resident_kib() -> int:
    """Return this process's peak resident set [KiB]: ``VmHWM``, else ``ru_maxrss``."""
    try:
        with open('/proc/self/status', encoding='ascii') as status:
            for line in status:
                if line.startswith('VmHWM:'):
                    return int(line.split()[1])
    except OSError:  # no procfs (not Linux): ru_maxrss is the process's own there
        pass
    return int(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)
