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

"""The node's payload: payload_file, ~/identify_payload, ~/payload and diagnostics."""

import pytest

from reduced_dynamics.payload import Payload, with_payload
from reduced_dynamics.resources import paper_robot_urdf
from reduced_dynamics.robot.model import load_robot
from reduced_dynamics.simulator import simulate_bag, SimulationOptions

try:
    from ros_harness import real_ros, Ros
    from test_payload import REALISTIC
except ImportError:  # test/ imported as a package
    from test.ros_harness import real_ros, Ros
    from test.test_payload import REALISTIC

TRUTH = 'forearm,8,0.3,0.05,-0.02,0.12,0.2,0.25'
SENSORS = dict(pose_position_noise=0.001, pose_angle_noise=0.0005, pose_stamp_noise=0.0003,
               twist_linear_noise=0.002, twist_angular_noise=0.002,
               joint_velocity_noise=0.005)


@pytest.fixture
def ros():
    with real_ros() as backend:
        yield backend


@pytest.fixture
def make_node(ros):
    from rclpy.parameter import Parameter
    from reduced_dynamics.node import ReducedDynamicsNode
    nodes = []

    def make(**overrides):
        node = ReducedDynamicsNode(parameter_overrides=[
            Parameter(k, value=v) for k, v in {'urdf_path': str(paper_robot_urdf()),
                                               **overrides}.items()])
        nodes.append(node)
        node.logs = Ros.record_logs(node).records
        return node
    yield make
    for node in nodes:
        node.destroy_node()


def test_payload_file_loads_into_the_model(make_node, tmp_path):
    path = tmp_path / 'payload.yaml'
    Payload.parse(TRUTH).write(path)
    node = make_node(payload_file=str(path))
    assert node.estimator.robot.total_mass == pytest.approx(load_robot('').total_mass + 8.0)
    assert 'payload' in dict(node.node_status().values)


def test_identify_payload_service_applies_and_publishes(ros, make_node, tmp_path):
    from reduced_dynamics.bag.reader import open_bag
    bag = tmp_path / 'bag'
    # Seed 4's sinusoid takes j4 past its URDF range at 11.3 s: the run goes on, explicitly.
    simulate_bag(with_payload(load_robot(''), Payload.parse(TRUTH)), bag,
                 SimulationOptions(duration=20.0, rate=100.0, seed=4, joint_limits='ignore',
                                   **REALISTIC))
    node = make_node(payload_link='forearm', payload_window=20.0, **SENSORS)
    nominal_mass = node.estimator.robot.total_mass
    with open_bag(bag) as reader:
        for message in reader.raw_messages(['/joint_states', '/odom']):
            ros.deliver(node, message.topic, bytes(message.data), message.timestamp_ns)
    service = next(s for s in node.services if s.srv_name.endswith('/identify_payload'))
    from std_srvs.srv import Trigger
    response = service.callback(Trigger.Request(), Trigger.Response())
    assert response.success, response.message
    assert 'mass' in response.message
    assert node.estimator.robot.total_mass == pytest.approx(nominal_mass + 8.0, rel=0.003)
    published, = ros.published('~/payload', node)
    assert published.header.frame_id == 'forearm'
    assert published.inertia.m == pytest.approx(8.0, rel=0.03)
    assert 'payload' in dict(node.node_status().values)


def test_identify_payload_without_a_link_is_refused(make_node):
    node = make_node()
    ok, message = node.identify_payload()
    assert not ok and 'payload_link' in message
