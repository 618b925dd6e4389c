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


"""Finished predictions keep their sampled paths only while diagnostics can read them."""

from pathlib import Path

from reduced_dynamics.bag.reader import open_bag
from reduced_dynamics.estimator.pipeline import Estimator
from reduced_dynamics.messages.convert import joint_state_from_ros, odometry_from_ros
from reduced_dynamics.robot.model import load_robot

BAG = Path(__file__).parent / 'data' / 'paper_realistic'


def test_only_the_last_compared_prediction_keeps_its_paths():
    estimator = Estimator(load_robot())
    with open_bag(str(BAG)) as reader:
        samples = [joint_state_from_ros(m.msg) if m.topic == '/joint_states'
                   else odometry_from_ros(m.msg)
                   for m in reader.messages(['/joint_states', '/odom'])]
    middle = len(samples) // 2
    estimator.add_samples(samples[:middle])
    first_last = estimator.predictor.last_finished
    assert first_last is not None and first_last.result.poses is not None
    estimator.add_samples(samples[middle:])
    estimator.flush()
    finished = estimator.predictor.finished
    last = estimator.predictor.last_finished
    assert len(finished) >= 4 and last is not first_last
    # The diagnostics' prediction status reads the last one's paths.
    assert last.result.poses is not None and last.result.drift is not None
    assert all(done.result.poses is None and done.result.drift is None
               for done in finished if done is not last)
    # What the summary reports of the others stays: mode, residuals, cost.
    summary = estimator.summary()
    assert summary['prediction_residuals'][last.mode]['predictions'] == len(finished)
    assert all(done.result.evaluations > 0 and done.compared for done in finished)
