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

"""Robot model, metric blocks and the momentum map against independent Pinocchio results."""

import numpy as np
import pinocchio as pin
import pytest

from conftest_robots import ROBOTS
from reduced_dynamics.robot.model import load_robot, ModelError
from reduced_dynamics.robot.momentum import momentum_state
from reduced_dynamics.robot.random_tree import random_tree_urdf


def _random_state(robot, seed):
    rng = np.random.default_rng(seed)
    g = robot.project_pose(pin.SE3.Random())
    return g, rng.standard_normal(robot.n), rng.uniform(-1, 1, robot.m), \
        rng.standard_normal(robot.m)


@pytest.mark.parametrize('name', sorted(ROBOTS))
def test_metric_blocks(name):
    robot = ROBOTS[name]()
    _, _, qbar, _ = _random_state(robot, 0)
    b = robot.metric_blocks(qbar)
    assert np.allclose(b.mass_matrix, b.mass_matrix.T)
    assert np.all(np.linalg.eigvalsh(b.mass_matrix) > 0)
    assert np.allclose(b.locked_inertia @ b.connection, b.coupling)
    assert np.allclose(b.reduced_metric, b.shape_inertia - b.coupling.T @ b.connection)
    # Block inversion (Lemma 53): the shape block of M^-1 is S^-1.
    assert np.allclose(np.linalg.inv(b.mass_matrix)[robot.n:, robot.n:],
                       np.linalg.inv(b.reduced_metric))


@pytest.mark.parametrize('name', sorted(ROBOTS))
def test_coriolis_matrix_gives_mass_matrix_rate_and_kinetic_gradient(name):
    # The free-flyer / planar root uses body velocities: check M_dot = C + C^T and
    # dT/dqbar = (C^T v)_qbar numerically rather than trust the convention.
    robot = ROBOTS[name]()
    rng = np.random.default_rng(4)
    qbar = rng.uniform(-0.5, 0.5, robot.m)
    v = rng.standard_normal(robot.n + robot.m)
    n, eps = robot.n, 1e-6
    coriolis = robot.coriolis_matrix(qbar, v).copy()
    m_dot = (robot.mass_matrix(qbar + eps * v[n:]) - robot.mass_matrix(qbar - eps * v[n:])) \
        / (2 * eps)
    assert np.abs(m_dot - coriolis - coriolis.T).max() <= 1e-7 * (1 + np.abs(m_dot).max())
    grad = np.array([(v @ robot.mass_matrix(qbar + eps * e) @ v
                      - v @ robot.mass_matrix(qbar - eps * e) @ v) / (4 * eps)
                     for e in np.eye(robot.m)])
    assert np.abs(grad - (coriolis.T @ v)[n:]).max() <= 1e-7 * (1 + np.abs(grad).max())
    upper = np.triu(robot.mass_matrix_upper(qbar))
    assert np.array_equal(upper, np.triu(robot.mass_matrix(qbar)))


@pytest.mark.parametrize('name', sorted(ROBOTS))
def test_left_invariance_lemma_52(name):
    robot = ROBOTS[name]()
    g, _, qbar, _ = _random_state(robot, 1)
    data = robot.model.createData()
    full = pin.crba(robot.model, data, robot.full_configuration(g, qbar))
    full = np.triu(full) + np.triu(full, 1).T
    assert np.allclose(full, robot.mass_matrix(qbar), atol=1e-10)


@pytest.mark.parametrize('name', sorted(ROBOTS))
def test_momentum_map_is_spatial_momentum_about_world_origin(name):
    robot = ROBOTS[name]()
    g, xi, qbar, qbar_dot = _random_state(robot, 2)
    state = momentum_state(robot.group, robot.metric_blocks(qbar), g, xi, qbar_dot)
    data = robot.model.createData()
    q = robot.full_configuration(g, qbar)
    h = pin.computeCentroidalMomentum(robot.model, data, q, np.r_[xi, qbar_dot])
    com = data.com[0]
    linear, angular_at_com = h.linear, h.angular
    about_origin = np.r_[linear, angular_at_com + np.cross(com, linear)]
    expected = robot.group.dual_coordinates(about_origin)
    assert np.allclose(state.mu, expected, atol=1e-10 * max(1.0, np.linalg.norm(expected)))
    # Energy splits into locked and shape parts: T = 1/2 pi I^-1 pi + 1/2 pbar S^-1 pbar.
    blocks = robot.metric_blocks(qbar)
    split = 0.5 * state.pi @ blocks.solve_locked(state.pi) + 0.5 * state.reduced_momentum @ \
        np.linalg.solve(blocks.reduced_metric, state.reduced_momentum)
    assert np.isclose(split, state.kinetic_energy, rtol=1e-12)
    # Reconstruction: drift + geometric phase = xi (REDUCED_MODEL.md 4).
    assert np.allclose(state.drift_twist + state.geometric_phase, xi, atol=1e-12)
    assert np.allclose(state.reduced_momentum,
                       state.shape_momentum - blocks.connection.T @ state.pi)


URDF_NO_FREE_BASE = """<robot name="bolted">
  <link name="world"/><link name="base"><inertial><mass value="1"/>
  <inertia ixx="1" ixy="0" ixz="0" iyy="1" iyz="0" izz="1"/></inertial></link>
  <joint name="bolt" type="fixed"><parent link="world"/><child link="base"/></joint>
</robot>"""


def test_urdf_without_free_base_is_rejected():
    with pytest.raises(ModelError, match='no free base: joint bolt'):
        load_robot(URDF_NO_FREE_BASE)


def test_world_joint_defines_base():
    text = URDF_NO_FREE_BASE.replace('type="fixed"', 'type="floating"')
    robot = load_robot(text)
    assert robot.group.name == 'SE(3)' and robot.m == 0
    with pytest.raises(ModelError, match='contradicts'):
        load_robot(text, 'planar')


def test_gravity_with_floating_base_is_rejected():
    with pytest.raises(ModelError, match='not invariant under SE\\(3\\)'):
        load_robot('', 'floating', np.array([0.0, 0.0, -9.81]))
    with pytest.raises(ModelError, match='normal to the plane'):
        load_robot('', 'planar', np.array([1.0, 0.0, -9.81]))


@pytest.mark.parametrize('text, message', [
    ('<robot><link name="a"/>', 'not valid XML'),
    ('<robt/>', 'expected <robot>'),
    ('/nonexistent/robot.urdf', 'not found'),
    ('<robot name="x"><link name="a"/><link name="b"/></robot>', 'exactly one root'),
])
def test_malformed_urdf(text, message):
    with pytest.raises(ModelError, match=message):
        load_robot(text)


def test_planar_and_floating_shape_joints_are_expanded():
    text = """<robot name="t"><link name="base"><inertial><mass value="10"/>
      <inertia ixx="1" ixy="0" ixz="0" iyy="1" iyz="0" izz="1"/></inertial></link>
      <link name="a"><inertial><mass value="1"/>
      <inertia ixx="0.1" ixy="0" ixz="0" iyy="0.1" iyz="0" izz="0.1"/></inertial></link>
      <link name="b"><inertial><mass value="1"/>
      <inertia ixx="0.1" ixy="0" ixz="0" iyy="0.1" iyz="0" izz="0.1"/></inertial></link>
      <joint name="p" type="planar"><parent link="base"/><child link="a"/>
      <axis xyz="1 0 0"/></joint>
      <joint name="f" type="floating"><parent link="a"/><child link="b"/></joint></robot>"""
    robot = load_robot(text)
    assert robot.shape_joint_names == ('p_x', 'p_y', 'p_yaw', 'f_x', 'f_y', 'f_z', 'f_roll',
                                       'f_pitch', 'f_yaw')


def test_random_tree_has_a_prismatic_joint_and_branches():
    robot = load_robot(random_tree_urdf(12, seed=5))
    assert 'prismatic' in robot.shape_joint_sources.values()
    parents = [robot.model.parents[j] for j in range(2, robot.model.njoints)]
    assert len(set(parents)) < len(parents)  # some link has two children: a tree
