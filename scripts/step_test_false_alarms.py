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
Measure the wrench-step test's false alarms on simulated coasting (docs/step_test.md).

Simulates coasting bags with the realistic sensors of scripts/make_test_bags.sh (no
thruster, no push: every step taken is a false alarm), replays each with the bag's
sensor figures (test/data/*_realistic.sensors.yaml) at several ``event_significance``
values and prints steps taken, events and pose-step vetoes per hour, and the
multiplier k = false alarms per update / significance (the union bound over the
40 onsets is k <= 40). Usage::

    python scripts/step_test_false_alarms.py WORKDIR [--seconds 600] [--seeds 21 22]
"""

import argparse
from pathlib import Path
import shutil
import subprocess
import sys
import tempfile

from reduced_dynamics.params import defaults, load_params_file
from reduced_dynamics.replay import replay, ReplayOptions
from reduced_dynamics.resources import config_path
from reduced_dynamics.robot.model import load_robot

DATA = Path(__file__).resolve().parent.parent / 'test' / 'data'
#: make_test_bags.sh's realistic sensors, the firings left out; the paper robot's arm
#: tracks a sinusoid (PD: the open-loop sinusoid reaches a singular shape within minutes).
FLAGS = {
    'freeflyer': ['--urdf', str(config_path('robots/freeflyer.urdf')), '--rate', '120',
                  '--torque', 'zero', '--base-pose-only', '--noise-pose', '0.0005',
                  '--noise-orientation', '0.002', '--quantize', 'base_position=1e-4',
                  '--stamp-jitter', '0.0005', '--bunch-fraction', '0.01', '--latency', '0.003',
                  '--latency-jitter', '0.001', '--outage-rate', '0.2',
                  '--outage-duration', '0.04'],
    'paper': ['--rate', '100', '--torque', 'pd', '--noise-position', '1e-4',
              '--noise-velocity', '0.005', '--noise-effort', '0.05', '--noise-pose', '0.001',
              '--noise-orientation', '0.0005', '--noise-twist', '0.002', '--quantize',
              'joint_position=1e-5', '--stamp-jitter', '0.0003', '--latency', '0.004',
              '--latency-jitter', '0.001', '--drop-rate', '0.01'],
}
SENSORS = {'freeflyer': 'freeflyer_realistic.sensors.yaml',
           'paper': 'paper_realistic.sensors.yaml'}
RATE = {'freeflyer': 120.0, 'paper': 100.0}


def main() -> int:
    """Simulate, replay, print one row per robot, seed and significance."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[1])
    parser.add_argument('workdir')
    parser.add_argument('--seconds', type=float, default=600.0)
    parser.add_argument('--seeds', type=int, nargs='+', default=[21])
    parser.add_argument('--robots', nargs='+', default=list(FLAGS), choices=list(FLAGS))
    parser.add_argument('--significance', type=float, nargs='+',
                        default=[1e-6, 1e-5, 1e-4, 1e-3])
    args = parser.parse_args()
    work = Path(args.workdir)
    work.mkdir(parents=True, exist_ok=True)
    print('robot seed significance hours updates steps events pose_vetoes '
          'steps/h k=steps/(updates*significance)', flush=True)
    for robot_name in args.robots:
        urdf = FLAGS[robot_name][1] if robot_name == 'freeflyer' else None
        robot = load_robot(urdf) if urdf else load_robot()
        topics = {'base_pose_topic': '/base_pose'} if robot_name == 'freeflyer' else {}
        for seed in args.seeds:
            bag = work / f'{robot_name}_coast_{seed}'
            if not bag.exists():
                subprocess.run([sys.executable, '-m', 'reduced_dynamics.cli', 'simulate',
                                '-o', str(bag), '--duration', str(args.seconds), '--seed',
                                str(seed)] + FLAGS[robot_name], check=True,
                               stdout=subprocess.DEVNULL)
            for significance in args.significance:
                params = defaults()
                params.update(load_params_file(str(DATA / SENSORS[robot_name])))
                params['event_significance'] = significance
                out = tempfile.mkdtemp(dir=work)
                try:
                    summary = replay(str(bag), str(Path(out) / 'out'), robot,
                                     ReplayOptions(params=params, smooth=False, **topics))
                finally:
                    shutil.rmtree(out, ignore_errors=True)
                hours = args.seconds / 3600.0
                updates = args.seconds * RATE[robot_name]
                steps = summary['filter']['steps_taken']
                print(f"{robot_name} {seed} {significance:g} {hours:.3f} {updates:.0f} "
                      f"{steps} {len(summary['events'])} {summary['filter']['pose_steps']} "
                      f"{steps / hours:.2f} {steps / (updates * significance):.2f}",
                      flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())
