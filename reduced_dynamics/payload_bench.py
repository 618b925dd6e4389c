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

"""Bench section ``payload``: one identification against a replay of the same window."""

from __future__ import annotations

import os
import shutil
import time
from typing import Any

#: The paper robot's payload of docs/payload.md (8 kg on the forearm, 24 % of the arm).
BENCH_PAYLOAD = 'forearm,8,0.3,0.05,-0.02,0.12,0.2,0.25'
#: The realistic sensors of test/data/paper_realistic and the matching noise parameters.
SENSOR_OPTIONS = dict(noise_position=1e-4, noise_velocity=0.005, noise_pose=0.001,
                      noise_orientation=0.0005, noise_twist=0.002,
                      quantize=(('joint_position', 1e-5),), stamp_jitter=0.0003,
                      latency=0.004, latency_jitter=0.001, drop_rate=0.01)
SENSOR_PARAMETERS = dict(pose_position_noise=0.001, pose_angle_noise=0.0005,
                         pose_stamp_noise=0.0003, twist_linear_noise=0.002,
                         twist_angular_noise=0.002, joint_velocity_noise=0.005)


def bench_payload(report: Any, robot: Any, settings: Any, workdir: str) -> None:
    """Time ``identify`` (read, fit, step test) and a causal replay of the same bag."""
    from reduced_dynamics.bench import make_figure
    from reduced_dynamics.identify import identify_bag
    from reduced_dynamics.params import defaults
    from reduced_dynamics.payload import Payload, with_payload
    from reduced_dynamics.replay import replay, ReplayOptions
    from reduced_dynamics.simulator import simulate_bag, SimulationOptions
    payload = Payload.parse(BENCH_PAYLOAD)
    bag = os.path.join(workdir, 'payload_input')
    simulate_bag(with_payload(robot, payload), bag,
                 SimulationOptions(duration=settings.payload_seconds, rate=100.0, seed=4,
                                   **SENSOR_OPTIONS))
    params = {**defaults(), **SENSOR_PARAMETERS}
    out = os.path.join(workdir, 'payload_replay')
    identifies, replays, ratios = [], [], []
    for _ in range(settings.repeats):
        started = time.perf_counter()
        estimate = identify_bag(bag, robot, payload.link, params)
        identifies.append(time.perf_counter() - started)
        started = time.perf_counter()
        replay(bag, out, robot, ReplayOptions(params=params, smooth=False, overwrite=True))
        replays.append(time.perf_counter() - started)
        ratios.append(identifies[-1] / replays[-1])
    shutil.rmtree(out, ignore_errors=True)
    error = abs(estimate.payload.mass / payload.mass - 1.0)
    report.add(make_figure(
        'payload', 'one payload identification (read, fit, step test)', 's', identifies,
        'causal replay of the same bag', replays, ratios,
        note=f'paper robot, {settings.payload_seconds:g} s at 100 Hz, realistic sensors, '
             f'{estimate.samples} samples; mass error {100 * error:.2f} %'))
