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
Tests of the rclpy TEST DOUBLE against the Jazzy semantics in docs/RCLPY_API_NOTES.md.

Tests using the ``ros`` fixture run on real rclpy when it is importable (conformance
check of the double); tests needing double-only helpers force or skip accordingly.
"""

import array
import sys

import numpy
import pytest

try:
    from rclpy_double import from_rosbags
    from rclpy_double import rclpy_backend
    from rclpy_double import to_rosbags
    from rclpy_double._messages import TYPESTORE
except ImportError:  # test/ imported as a package
    from test.rclpy_double import from_rosbags
    from test.rclpy_double import rclpy_backend
    from test.rclpy_double import to_rosbags
    from test.rclpy_double._messages import TYPESTORE


@pytest.fixture
def ros():
    with rclpy_backend() as backend:
        backend.rclpy.init()
        yield backend


@pytest.fixture
def double():
    with rclpy_backend(mode='double') as backend:
        backend.rclpy.init()
        yield backend


def _range_descriptor(low, high, step=0.0):
    from rcl_interfaces.msg import FloatingPointRange
    from rcl_interfaces.msg import ParameterDescriptor
    return ParameterDescriptor(
        description='test', floating_point_range=[
            FloatingPointRange(from_value=low, to_value=high, step=step)])


def test_double_is_installed_only_inside_context():
    before = sys.modules.get('rclpy')
    with rclpy_backend(mode='double') as backend:
        import rclpy
        from rclpy.node import Node
        from sensor_msgs.msg import JointState
        assert rclpy is backend.rclpy and rclpy.__rclpy_double__
        assert Node is rclpy.node.Node
        assert JointState is backend.msg('sensor_msgs/msg/JointState')
        assert not backend.is_real
    assert sys.modules.get('rclpy') is before


def test_messages_look_like_jazzy_rclpy(ros):
    from diagnostic_msgs.msg import DiagnosticStatus
    from nav_msgs.msg import Odometry
    from sensor_msgs.msg import JointState
    msg = JointState(name=['j1'], position=[1.0, 2.0])
    assert isinstance(msg.position, array.array) and msg.position.typecode == 'd'
    assert msg.velocity == array.array('d')
    msg.effort = [3.0]
    assert msg.effort == array.array('d', [3.0])
    assert DiagnosticStatus.ERROR == b'\x02' and DiagnosticStatus().level == b'\x00'
    covariance = Odometry().pose.covariance
    assert isinstance(covariance, numpy.ndarray) and covariance.shape == (36,)


def test_double_messages_are_strict(double):
    from std_msgs.msg import Float64
    with pytest.raises(TypeError):
        Float64(dat=1.0)
    node = double.rclpy.create_node('strict')
    pub = node.create_publisher(Float64, 'x', 10)
    with pytest.raises(TypeError, match="'data' field must be of type 'float'"):
        pub.publish(Float64(data=1))  # real Jazzy would publish garbage here
    with pytest.raises(TypeError, match='Expected'):
        pub.publish('not a message')


def test_names_and_private_topics(ros):
    from rclpy.node import Node
    node = Node('estimator', namespace='robot')
    assert node.get_name() == 'estimator' and node.get_namespace() == '/robot'
    assert node.resolve_topic_name('~/momentum') == '/robot/estimator/momentum'
    assert node.resolve_topic_name('joint_states') == '/robot/joint_states'
    assert node.resolve_topic_name('/clock') == '/clock'
    assert Node('root').resolve_topic_name('~/x') == '/root/x'
    node.destroy_node()


def test_overrides_ranges_types_and_read_only(ros):
    from rcl_interfaces.msg import ParameterDescriptor
    from rclpy.exceptions import InvalidParameterTypeException
    from rclpy.exceptions import InvalidParameterValueException
    from rclpy.node import Node
    from rclpy.parameter import Parameter
    node = Node('p', parameter_overrides=[
        Parameter('gain', value=2.0), Parameter('bad', value=9.0), Parameter('typed', value='x')])
    assert node.declare_parameter('gain', 1.0, _range_descriptor(0.0, 5.0)).value == 2.0
    with pytest.raises(InvalidParameterValueException, match='out of range'):
        node.declare_parameter('bad', 1.0, _range_descriptor(0.0, 5.0))
    with pytest.raises(InvalidParameterTypeException):
        node.declare_parameter('typed', 1.0)

    result, = node.set_parameters([Parameter('gain', value=7.0)])
    assert not result.successful
    assert result.reason == 'Parameter gain out of range Min: 0.0, Max: 5.0, value: 7.0'
    assert node.get_parameter('gain').value == 2.0
    assert node.set_parameters([Parameter('gain', value=5.0)])[0].successful  # edge is valid
    result, = node.set_parameters([Parameter('gain', value=3)])  # int is not a double
    assert result.reason == "Wrong parameter type, expected 'Type.DOUBLE' got 'Type.INTEGER'"
    assert not node.set_parameters([Parameter('gain', value='fast')])[0].successful

    node.declare_parameter('anything', 1.0, ParameterDescriptor(dynamic_typing=True))
    assert node.set_parameters([Parameter('anything', value='text')])[0].successful
    node.declare_parameter('frozen', 'a', ParameterDescriptor(read_only=True))
    result, = node.set_parameters([Parameter('frozen', value='b')])
    assert result.reason == 'Trying to set a read-only parameter: frozen.'
    assert node.get_parameter('frozen').get_parameter_value().string_value == 'a'


def test_empty_list_default_is_byte_array(ros):
    from rclpy.node import Node
    from rclpy.parameter import Parameter
    node = Node('lists')
    assert node.declare_parameter('names', []).type_ == Parameter.Type.BYTE_ARRAY
    assert not node.set_parameters([Parameter('names', value=['a'])])[0].successful
    node.declare_parameter('joints', Parameter.Type.STRING_ARRAY)
    assert node.set_parameters([Parameter('joints', value=['a'])])[0].successful


def test_on_set_post_set_and_pre_set_callbacks(ros):
    from rcl_interfaces.msg import SetParametersResult
    from rclpy.node import Node
    from rclpy.parameter import Parameter
    node = Node('cb')
    calls = []

    def on_set(params):
        calls.append(('on', [p.name for p in params]))
        ok = all(p.name != 'rate' or p.value > 0.0 for p in params)
        return SetParametersResult(successful=ok, reason='' if ok else 'rate must be > 0')

    node.add_on_set_parameters_callback(on_set)
    node.add_post_set_parameters_callback(lambda ps: calls.append(('post', [p.value for p in ps])))
    node.declare_parameter('rate', 10.0)  # declaration runs on-set and post-set too
    assert calls == [('on', ['rate']), ('post', [10.0])]

    calls.clear()
    result, = node.set_parameters([Parameter('rate', value=-1.0)])
    assert (result.successful, result.reason) == (False, 'rate must be > 0')
    assert node.get_parameter('rate').value == 10.0 and calls == [('on', ['rate'])]

    node.add_pre_set_parameters_callback(
        lambda ps: ps + [Parameter('rate', value=20.0)] if ps[0].name == 'use_sim_time' else ps)
    assert node.set_parameters_atomically([Parameter('use_sim_time', value=False)]).successful
    assert node.get_parameter('rate').value == 20.0


def test_sim_time_follows_clock(ros):
    from rclpy.node import Node
    from rclpy.parameter import Parameter
    wall = Node('wall')
    assert wall.get_parameter('use_sim_time').value is False
    assert wall.get_clock().now().nanoseconds > 0

    node = Node('sim', parameter_overrides=[Parameter('use_sim_time', value=True)])
    assert node.get_clock().now().nanoseconds == 0
    ros.set_sim_time(node, 12.5)
    assert node.get_clock().now().nanoseconds == 12_500_000_000
    assert node.get_clock().now().to_msg().sec == 12
    assert not node.set_parameters([Parameter('use_sim_time', value='yes')])[0].successful
    assert node.set_parameters([Parameter('use_sim_time', value=False)])[0].successful
    assert node.get_clock().now().nanoseconds > 12_500_000_000


def test_publish_deliver_and_timers(ros):
    from rclpy.node import Node
    from rclpy.parameter import Parameter
    from rclpy.qos import qos_profile_sensor_data
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Float64
    node = Node('io', namespace='ns', parameter_overrides=[Parameter('use_sim_time', value=True)])
    pub = node.create_publisher(Float64, '~/momentum', 10)
    received = []
    node.create_subscription(JointState, 'joint_states', received.append,
                             qos_profile_sensor_data)
    ticks = []
    node.create_timer(0.1, lambda: (ticks.append(1), pub.publish(Float64(data=1.5))))

    assert ros.deliver(node, 'joint_states', JointState(name=['a'])) == 1
    assert received[0].name == ['a']
    assert ros.fire_timers(node) == 1
    assert ros.published('/ns/io/momentum') == [Float64(data=1.5)]
    assert ros.published('~/momentum', node) == [Float64(data=1.5)]

    ros.set_sim_time(node, 0.05)
    ros.spin_ready(node)
    assert len(ticks) == 1  # period not elapsed on the sim clock
    ros.set_sim_time(node, 1.0)
    ros.spin_ready(node)
    assert len(ticks) == 2  # missed periods are skipped, like rcl_timer_call
    with pytest.raises(LookupError):
        ros.deliver(node, 'nobody_listens', JointState())


def test_init_shutdown_and_demo_main_pattern(double):
    rclpy = double.rclpy
    from rclpy.executors import ExternalShutdownException
    from rclpy.exceptions import NotInitializedException
    from rclpy.node import Node
    assert rclpy.ok()
    with pytest.raises(RuntimeError):
        rclpy.init()

    for interrupt in (KeyboardInterrupt, ExternalShutdownException):
        def stop(node, interrupt=interrupt):
            node.get_logger().info('spinning')
            raise interrupt()
        double.on_spin(stop)
        if not rclpy.ok():
            rclpy.init()
        node = Node('talker')
        try:
            rclpy.spin(node)
        except (KeyboardInterrupt, ExternalShutdownException):
            pass
        finally:
            node.destroy_node()
            rclpy.try_shutdown()
        assert not rclpy.ok() and double.logs(node) == [('INFO', 'spinning')]
        rclpy.try_shutdown()  # idempotent
    with pytest.raises(NotInitializedException):
        Node('late')


def test_rosbags_round_trip(ros):
    from diagnostic_msgs.msg import DiagnosticStatus
    from diagnostic_msgs.msg import KeyValue
    status = DiagnosticStatus(level=DiagnosticStatus.WARN, name='est',
                              values=[KeyValue(key='k', value='v')])
    raw = TYPESTORE.serialize_cdr(to_rosbags(status), 'diagnostic_msgs/msg/DiagnosticStatus')
    back = from_rosbags(TYPESTORE.deserialize_cdr(raw, 'diagnostic_msgs/msg/DiagnosticStatus'))
    assert back == status and back.level == b'\x01'
    obj = TYPESTORE.types['sensor_msgs/msg/JointState'](
        header=TYPESTORE.types['std_msgs/msg/Header'](
            stamp=TYPESTORE.types['builtin_interfaces/msg/Time'](sec=1, nanosec=2),
            frame_id='base'),
        name=['a'], position=numpy.array([0.5]), velocity=numpy.array([]),
        effort=numpy.array([]))
    msg = from_rosbags(obj)
    assert msg.position == array.array('d', [0.5]) and msg.header.stamp.nanosec == 2
