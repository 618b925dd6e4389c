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

"""Symmetry detection (section 5.1): cyclic joints by (5.43), Prop. 56 and (5.46)."""

import numpy as np
import pytest

from conftest_robots import paper_robot, planar_robot, tree_robot
from reduced_dynamics.cli import main
from reduced_dynamics.resources import config_path
from reduced_dynamics.robot.model import load_robot
from reduced_dynamics.robot.symmetry import detect_symmetries, rotor_residual

WHEELS = ('wheel_x', 'wheel_y', 'wheel_z')


def wheel_urdf() -> str:
    """Return the shipped wheel robot's URDF text."""
    with open(config_path('robots/paper_robot_wheels.urdf')) as handle:
        return handle.read()


def test_wheel_robot_detects_exactly_the_three_rotors():
    report = detect_symmetries(load_robot(wheel_urdf()))
    assert report.cyclic_joints == WHEELS
    assert report.group == 'SO(2)^3'
    for joint in report.joints:
        if joint.cyclic:
            assert joint.extremity and joint.certificate == '(5.46)'
            assert joint.invariance_residual < 1e-14
            assert joint.rotor_residual < 1e-14
            assert 'axisymmetric' in joint.explanation
        else:
            assert joint.invariance_residual > 1e-2


@pytest.mark.parametrize('robot', [paper_robot, planar_robot, tree_robot])
def test_no_symmetry_on_the_other_robots(robot):
    report = detect_symmetries(robot())
    assert report.cyclic_joints == ()
    assert report.group == 'trivial'
    assert all(joint.explanation.startswith('not cyclic') for joint in report.joints)


def test_rotor_with_centre_of_mass_off_axis_is_not_cyclic():
    urdf = wheel_urdf().replace('<origin xyz="0 0.02 0"', '<origin xyz="0.001 0.02 0"')
    report = detect_symmetries(load_robot(urdf))
    assert report.cyclic_joints == ('wheel_x', 'wheel_z')
    wheel_y = next(j for j in report.joints if j.name == 'wheel_y')
    assert 'centre of mass is 1 mm off the joint axis' in wheel_y.explanation
    assert wheel_y.rotor_residual > 1e-6 and wheel_y.invariance_residual > 1e-6


def test_rotor_with_unequal_transverse_moments_is_not_cyclic():
    urdf = wheel_urdf().replace(
        'ixx="0.0291667" ixy="0" ixz="0" iyy="0.0291667" iyz="0" izz="0.05625"',
        'ixx="0.0291667" ixy="0" ixz="0" iyy="0.0300000" iyz="0" izz="0.05625"', 1)
    report = detect_symmetries(load_robot(urdf))
    assert report.cyclic_joints == ('wheel_y', 'wheel_z')
    wheel_x = report.joints[[j.name for j in report.joints].index('wheel_x')]
    assert 'not axisymmetric' in wheel_x.explanation


PLANAR_LIFT = """<?xml version="1.0"?>
<robot name="lift">
  <link name="platform"><inertial><mass value="20"/>
    <inertia ixx="1" ixy="0" ixz="0" iyy="1" iyz="0" izz="1.5"/></inertial></link>
  <link name="carriage"><inertial><origin xyz="0.2 0.1 0"/><mass value="3"/>
    <inertia ixx="0.1" ixy="0" ixz="0" iyy="0.2" iyz="0" izz="0.3"/></inertial></link>
  <link name="arm"><inertial><origin xyz="0.3 0 0"/><mass value="1"/>
    <inertia ixx="0.01" ixy="0" ixz="0" iyy="0.02" iyz="0" izz="0.02"/></inertial></link>
  <joint name="lift" type="prismatic"><parent link="platform"/><child link="carriage"/>
    <origin xyz="0.4 0 0"/><axis xyz="0 0 1"/></joint>
  <joint name="swing" type="continuous"><parent link="carriage"/><child link="arm"/>
    <origin xyz="0.2 0 0"/><axis xyz="0 0 1"/></joint>
</robot>
"""


def test_proposition56_vertical_lift_on_a_planar_base():
    report = detect_symmetries(load_robot(PLANAR_LIFT, 'planar'))
    lift = report.joints[0]
    assert lift.proposition56 is True and lift.cyclic and not lift.extremity
    assert lift.certificate == 'Proposition 56'
    assert report.cyclic_joints == ('lift',)
    assert report.group == 'R'


def test_gravity_breaks_the_lift_symmetry():
    robot = load_robot(PLANAR_LIFT, 'planar', np.array([0.0, 0.0, -9.81]))
    lift = detect_symmetries(robot).joints[0]
    assert not lift.cyclic and lift.invariance_residual < 1e-12
    assert 'gravity depends on it' in lift.explanation


def test_rotor_residual_is_zero_for_a_disc_about_its_axis():
    import pinocchio as pin
    disc = pin.Inertia(5.0, np.array([0.0, 0.0, 0.3]), np.diag([0.03, 0.03, 0.05]))
    assert rotor_residual(disc, np.r_[0, 0, 0, 0, 0, 1.0]) < 1e-15
    assert rotor_residual(disc, np.r_[0, 0, 0, 1.0, 0, 0]) > 0.1


def test_symmetries_command_prints_the_report(capsys):
    urdf = str(config_path('robots/paper_robot_wheels.urdf'))
    assert main(['symmetries', '--urdf', urdf]) == 0
    out = capsys.readouterr().out
    assert out.startswith('robot paper_robot_wheels: base group SE(3), 9 shape joints')
    assert 'wheel_x  cyclic' in out
    assert 'N = SO(2)^3' in out and 'Theorem 57 applies' in out
    assert main(['symmetries']) == 0
    assert 'no further reduction' in capsys.readouterr().out
