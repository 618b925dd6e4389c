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
What the replay plots mark: joint-torque steps and thruster pulses found in a bag.

Both explain the residuals on the plots: a torque change breaks ``held_torque``
predictions, a thruster pulse changes the momentum. Torque steps come from the
measured efforts of the joint states (a step of at least :data:`STEP_FRACTION`
of a joint's range over the record within one sample, so smooth or noisy torques
mark nothing); thruster pulses from the simulator's ground-truth external wrench
(``/ground_truth/external_wrench``) or, without it, the commanded wrench
(``/commanded_wrench``), as the intervals where it is nonzero.
"""

from __future__ import annotations

from typing import Any, Optional, Sequence

import numpy as np

#: Smallest effort step, relative to the joint's effort range, marked as a torque change.
STEP_FRACTION = 0.25
#: More steps than this are not marked (continuous control, not held torques).
MAX_STEPS = 50
#: Wrench topics giving thruster pulses, in order of preference.
WRENCH_TOPICS = ('/ground_truth/external_wrench', '/commanded_wrench')


def torque_steps(stamps_ns: Sequence[int], efforts: np.ndarray) -> list[int]:
    """Return the stamps at which some joint's effort steps (see the module docstring)."""
    efforts = np.asarray(efforts, dtype=float)
    if efforts.ndim != 2 or efforts.shape[0] < 2 or efforts.shape[1] == 0:
        return []
    span = np.nanmax(efforts, axis=0) - np.nanmin(efforts, axis=0)
    jumps = np.abs(np.diff(efforts, axis=0))
    big = np.any((jumps >= STEP_FRACTION * span) & (span > 0.0), axis=1)
    steps = [int(stamps_ns[i + 1]) for i in np.flatnonzero(big)]
    return steps if len(steps) <= MAX_STEPS else []


def pulse_intervals(stamps_ns: Sequence[int], wrenches: np.ndarray) -> list[tuple[int, int]]:
    """Return the [start, end] stamps of the runs of samples with a nonzero wrench."""
    wrenches = np.asarray(wrenches, dtype=float)
    if wrenches.ndim != 2 or not len(stamps_ns):
        return []
    on = np.any(wrenches != 0.0, axis=1)
    intervals, start = [], None
    for stamp, active in zip(stamps_ns, on):
        if active and start is None:
            start = int(stamp)
        elif not active and start is not None:
            intervals.append((start, int(stamp)))
            start = None
    if start is not None:
        intervals.append((start, int(stamps_ns[-1])))
    return intervals


def read_marks(bag_path: str, joint_topic: Optional[str], start_ns: Optional[int] = None,
               end_ns: Optional[int] = None) -> dict[str, Any]:
    """Return ``{'torque_steps': [ns], 'pulses': [(ns, ns)], 'pulse_topic': str}`` of a bag."""
    from reduced_dynamics.bag.reader import open_bag
    marks: dict[str, Any] = {'torque_steps': [], 'pulses': [], 'pulse_topic': None}
    with open_bag(bag_path) as reader:
        topics = reader.topics()
        if joint_topic and joint_topic in topics:
            stamps, efforts = [], []
            for message in reader.messages([joint_topic], start_ns, end_ns):
                msg = message.msg
                if len(msg.effort) and (not efforts or len(msg.effort) == len(efforts[0])):
                    stamps.append(msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec)
                    efforts.append(np.asarray(msg.effort, dtype=float))
            if efforts:
                marks['torque_steps'] = torque_steps(stamps, np.array(efforts))
        for topic in WRENCH_TOPICS:
            if topic in topics:
                stamps, wrenches = [], []
                for message in reader.messages([topic], start_ns, end_ns):
                    wrench = message.msg.wrench
                    stamps.append(message.timestamp_ns)
                    wrenches.append((wrench.force.x, wrench.force.y, wrench.force.z,
                                     wrench.torque.x, wrench.torque.y, wrench.torque.z))
                marks['pulses'] = pulse_intervals(stamps, np.array(wrenches))
                marks['pulse_topic'] = topic
                break
    return marks


def draw_marks(ax: Any, marks: dict[str, Any], t0_ns: int, legend: bool = True) -> None:
    """Shade thruster pulses and draw torque changes on a time axis [s from t0_ns]."""
    source = 'ground truth' if marks.get('pulse_topic') == WRENCH_TOPICS[0] else 'commanded'
    for k, (start, end) in enumerate(marks.get('pulses', ())):
        ax.axvspan((start - t0_ns) * 1e-9, (end - t0_ns) * 1e-9, color='tab:orange', alpha=0.2,
                   label=f'thruster on ({source})' if legend and k == 0 else None)
    for k, stamp in enumerate(marks.get('torque_steps', ())):
        ax.axvline((stamp - t0_ns) * 1e-9, color='0.4', linestyle='--', linewidth=0.8,
                   label='joint torque change' if legend and k == 0 else None)
