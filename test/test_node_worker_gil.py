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

"""The prediction worker shortens the GIL switch interval (the input path's wait for it)."""

import sys

import pytest

pytest.importorskip('rclpy')

from reduced_dynamics import node  # noqa: E402


def test_the_prediction_worker_lowers_the_switch_interval():
    before = sys.getswitchinterval()
    try:
        sys.setswitchinterval(0.005)  # the interpreter's default
        worker = node._PredictionWorker(lambda messages: None, lambda text: None)
        assert sys.getswitchinterval() == pytest.approx(node.GIL_SWITCH_INTERVAL)
        worker.stop()
        # Never raised: an interval set lower by the application stays.
        sys.setswitchinterval(node.GIL_SWITCH_INTERVAL / 2)
        node._PredictionWorker(lambda messages: None, lambda text: None).stop()
        assert sys.getswitchinterval() == pytest.approx(node.GIL_SWITCH_INTERVAL / 2)
    finally:
        sys.setswitchinterval(before)
