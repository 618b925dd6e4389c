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
A node without a robot model says so on /diagnostics (issue 24 item 5).

The plain node as a process (``python -m reduced_dynamics.node``), a recorder of
/diagnostics in a second process, over real DDS in this module's own domain.
"""

import json
import os
from pathlib import Path
import queue
import signal
import subprocess
import sys
import threading
import time

import pytest

try:
    from ros_harness import DOMAIN_ID
except ImportError:  # test/ imported as a package
    from test.ros_harness import DOMAIN_ID

from reduced_dynamics.node import NODE_STATUS_NAME

REPO_ROOT = Path(__file__).resolve().parent.parent
#: Prints one JSON line per status of /diagnostics: [level, name, message].
RECORDER = '''
import json, sys
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
rclpy.init()
node = rclpy.create_node('diagnostics_recorder')

def record(msg):
    for status in msg.status:
        print(json.dumps([status.level[0], status.name, status.message]), flush=True)
node.create_subscription(DiagnosticArray, '/diagnostics', record, 10)
print('ready', flush=True)
try:
    rclpy.spin(node)
except Exception:
    pass
'''
#: Readiness and collection deadlines: generous, they only bound a hung run.
DEADLINE = 120.0


def _env():
    return dict(os.environ, ROS_DOMAIN_ID=DOMAIN_ID, PYTHONUNBUFFERED='1',
                PYTHONPATH=os.pathsep.join([str(REPO_ROOT), os.environ.get('PYTHONPATH', '')]))


def _lines(stream, into: queue.Queue) -> None:
    for line in stream:
        into.put(line.rstrip('\n'))


def _reader(stream) -> tuple[queue.Queue, threading.Thread]:
    lines: queue.Queue = queue.Queue()
    thread = threading.Thread(target=_lines, args=(stream, lines), daemon=True)
    thread.start()
    return lines, thread


def _wait_for(lines: queue.Queue, predicate, kept: list) -> bool:
    end = time.monotonic() + DEADLINE
    while time.monotonic() < end:
        try:
            line = lines.get(timeout=1.0)
        except queue.Empty:
            continue
        kept.append(line)
        if predicate(line):
            return True
    return False


@pytest.mark.parametrize('args, reason', [
    (['-p', 'urdf_path:=/nonexistent/robot.urdf'], 'URDF file not found'),
    (['-p', 'robot_description:=<robot name="x"><link name='], 'URDF is not valid XML'),
    # ROS time stands still without /clock; the status must not.
    (['-p', 'urdf_path:=/nonexistent/robot.urdf', '-p', 'use_sim_time:=true'],
     'URDF file not found'),
    # diagnostics_rate 0 turns the routine status off, not the news that nothing runs.
    (['-p', 'urdf_path:=/nonexistent/robot.urdf', '-p', 'diagnostics_rate:=0.0'],
     'URDF file not found'),
])
def test_node_without_a_model_reports_error_until_stopped(args, reason):
    recorder = subprocess.Popen([sys.executable, '-c', RECORDER], env=_env(),
                                stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
                                start_new_session=True)
    node = None
    try:
        statuses, _ = _reader(recorder.stdout)
        seen: list = []
        assert _wait_for(statuses, lambda line: line == 'ready', seen), 'no recorder'
        node = subprocess.Popen([sys.executable, '-m', 'reduced_dynamics.node', '--ros-args',
                                 *args], cwd=REPO_ROOT, env=_env(), stdout=subprocess.PIPE,
                                stderr=subprocess.STDOUT, text=True, start_new_session=True)
        output, reading = _reader(node.stdout)
        logged: list = []
        # Readiness: the node's ERROR line (it is then spinning).
        assert _wait_for(output, lambda line: '[ERROR]' in line, logged), logged
        ours = []

        def error_status(line: str) -> bool:
            level, name, message = json.loads(line)
            if name == NODE_STATUS_NAME:
                ours.append((level, message))
            return len(ours) >= 3
        # Periodically: three statuses in a row, each ERROR with the reason.
        assert _wait_for(statuses, error_status, seen), seen
        assert all(level == 2 and 'cannot use the robot model' in message
                   and reason in message for level, message in ours), ours
        node.send_signal(signal.SIGINT)
        code = node.wait(timeout=DEADLINE)
        reading.join(timeout=DEADLINE)  # to the end of its output
        while not output.empty():
            logged.append(output.get())
    finally:
        for proc in (node, recorder):
            if proc is not None and proc.poll() is None:
                proc.kill()
                proc.wait()
    assert code == 0, logged
    errors = [line for line in logged if '[ERROR]' in line or 'Traceback' in line]
    assert len(errors) == 1 and reason in errors[0], logged


def test_a_model_arriving_later_returns_the_status_to_node_time():
    """The paper robot cannot stand in (gravity with a floating base); a URDF then arrives."""
    try:
        from ros_harness import real_ros
    except ImportError:  # test/ imported as a package
        from test.ros_harness import real_ros
    from rclpy.clock import ClockType
    from rclpy.parameter import Parameter
    from std_msgs.msg import String
    from reduced_dynamics.node import ReducedDynamicsNode
    from reduced_dynamics.resources import config_path
    with real_ros() as ros:
        node = ReducedDynamicsNode(parameter_overrides=[
            Parameter('gravity', value=[0.0, 0.0, -9.81])])
        try:
            assert node.estimator is None and 'gravity' in node.model_error
            [timer] = node.timers
            assert timer.clock.clock_type == ClockType.STEADY_TIME
            ros.fire_timers(node)
            [status] = ros.published('/diagnostics')[-1].status
            assert status.level == b'\x02' and 'gravity' in status.message
            urdf = Path(config_path('robots/freeflyer.urdf')).read_text()
            ros.deliver(node, '/robot_description', String(data=urdf))
            assert node.model_error is None and node.estimator is not None
            [timer] = node.timers
            assert timer.clock.clock_type == ClockType.ROS_TIME
            assert timer.timer_period_ns == 1_000_000_000  # diagnostics_rate 1.0
        finally:
            node.destroy_node()
