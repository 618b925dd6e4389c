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
``warm_up()`` prepares every compiled kernel a node's run calls (docs/node.md).

The node calls ``warm_up()`` before its first message: after an install the kernels
compile there (minutes), not in a callback, which would hold the node that long. A
kernel the warm-up misses compiles in the middle of a run: measured on an empty cache,
the fixed-lag smoother's first pass held one sample for 8.9 s.

The check: a fresh interpreter runs ``warm_up()``, notes every numba dispatcher's
signatures, then runs what a node runs with its defaults (``EstimatorConfig()``:
fixed-lag smoothing, predictions, the event tests) on shipped bags, and lists each
signature that appeared after the warm-up. With a warm cache a signature appears when
it is loaded from the cache, so the check needs no compilation to see one: an empty
list means the warm-up had them all.
"""

import json
import os
import subprocess
import sys

from reduced_dynamics.resources import config_path

DATA = os.path.join(os.path.dirname(__file__), 'data')

PROBE = r'''
import json, sys
import numpy as np
from numba.core.registry import CPUDispatcher

def signatures():
    found = {}
    for name, module in list(sys.modules.items()):
        if not name.startswith('reduced_dynamics') or module is None:
            continue
        for value in vars(module).values():
            if isinstance(value, CPUDispatcher):
                key = value.py_func.__module__ + '.' + value.py_func.__qualname__
                found.setdefault(key, set()).update(str(s) for s in value.signatures)
    return found

from reduced_dynamics.estimator.core.warmup import warm_up
warm_up()
# Every module a run imports, imported before the first note of the signatures.
from reduced_dynamics.bag.reader import open_bag
from reduced_dynamics.estimator import Estimator
from reduced_dynamics.estimator.config import EstimatorConfig
from reduced_dynamics.messages.convert import joint_state_from_ros, odometry_from_ros
from reduced_dynamics.replay import replay, ReplayOptions
from reduced_dynamics.robot.model import load_robot
import reduced_dynamics.estimator.block_pulse, reduced_dynamics.estimator.fixed_lag  # noqa
data, out, freeflyer = sys.argv[1:4]
before = signatures()

# A node's streaming path with its defaults: an SE(3) base with odometry, a thruster
# pulse (an event), fixed-lag smoothing and predictions.
estimator = Estimator(load_robot(), EstimatorConfig())
with open_bag(data + '/paper_thruster') as reader:
    for message in reader.messages(['/joint_states', '/odom']):
        if message.topic == '/joint_states':
            estimator.add_joint_state(joint_state_from_ros(message.msg))
        else:
            estimator.add_base_state(odometry_from_ros(message.msg))
estimator.flush()
# The node's causal outputs and fixed-lag rows as replay writes them: a planar base
# measured by its pose alone, with a commanded wrench.
replay(data + '/freeflyer_realistic', out, load_robot(freeflyer),
       ReplayOptions(base_pose_topic='/base_pose', commanded_wrench_topic='/commanded_wrench',
                     smooth=False, fixed_lag=0.5, overwrite=True))

after = signatures()
print(json.dumps({name: sorted(sigs - before.get(name, set()))
                  for name, sigs in after.items() if sigs - before.get(name, set())}))
'''


def test_warm_up_prepares_every_kernel_a_node_run_calls(tmp_path):
    done = subprocess.run(
        [sys.executable, '-c', PROBE, DATA, str(tmp_path / 'out'),
         str(config_path('robots/freeflyer.urdf'))],
        capture_output=True, text=True, timeout=900)
    assert done.returncode == 0, done.stderr[-3000:]
    missed = json.loads(done.stdout.strip().splitlines()[-1])
    assert missed == {}, 'kernels first called after warm_up():\n' + '\n'.join(
        f'{name}: {sigs}' for name, sigs in missed.items())
