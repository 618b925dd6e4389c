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

"""Random free-floating tree robots as URDF text (for tests, validation and scaling)."""

from __future__ import annotations

import numpy as np

JOINT_TYPES = ('revolute', 'continuous', 'prismatic')


def _box_inertia(mass: float, dims: np.ndarray) -> np.ndarray:
    a, b, c = dims
    return mass / 12.0 * np.array([b * b + c * c, a * a + c * c, a * a + b * b])


def _rotation_matrix(rpy: np.ndarray) -> np.ndarray:
    cr, sr = np.cos(rpy[0]), np.sin(rpy[0])
    cp, sp = np.cos(rpy[1]), np.sin(rpy[1])
    cy, sy = np.cos(rpy[2]), np.sin(rpy[2])
    rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    return rz @ ry @ rx


def _link_xml(name: str, mass: float, com: np.ndarray, inertia: np.ndarray) -> str:
    i = inertia
    return (f'  <link name="{name}">\n    <inertial>\n'
            f'      <origin xyz="{com[0]:.6f} {com[1]:.6f} {com[2]:.6f}" rpy="0 0 0"/>\n'
            f'      <mass value="{mass:.6f}"/>\n'
            f'      <inertia ixx="{i[0, 0]:.8f}" ixy="{i[0, 1]:.8f}" ixz="{i[0, 2]:.8f}" '
            f'iyy="{i[1, 1]:.8f}" iyz="{i[1, 2]:.8f}" izz="{i[2, 2]:.8f}"/>\n'
            f'    </inertial>\n  </link>\n')


def random_tree_urdf(num_joints: int, seed: int = 0, planar_axes: bool = False,
                     prismatic: bool = True) -> str:
    """
    URDF of a random tree: a heavy base and ``num_joints`` 1-dof joints.

    Parents are drawn at random among earlier links (a tree, not a chain).
    With ``prismatic`` at least one joint is prismatic. With ``planar_axes``
    every revolute axis is z and every prismatic axis lies in the xy-plane, as
    on an air-bearing table. Inertias are of random boxes, randomly rotated.
    """
    rng = np.random.default_rng(seed)
    parts = [f'<?xml version="1.0"?>\n<robot name="random_tree_{num_joints}_{seed}">\n']
    base_dims = rng.uniform(0.8, 1.4, 3)
    base_mass = float(rng.uniform(80.0, 200.0))
    base_inertia = np.diag(_box_inertia(base_mass, base_dims))
    parts.append(_link_xml('base', base_mass, np.zeros(3), base_inertia))
    types = [JOINT_TYPES[int(rng.integers(0, 2))] for _ in range(num_joints)]
    if prismatic and num_joints:
        types[int(rng.integers(0, num_joints))] = 'prismatic'
    links = ['base']
    for index in range(num_joints):
        parent = links[int(rng.integers(0, len(links)))]
        name = f'link_{index + 1}'
        dims = np.array([0.08, 0.08, 0.08]) + rng.uniform(0.0, 0.5, 3)
        mass = float(rng.uniform(1.0, 8.0))
        rot = _rotation_matrix(rng.uniform(-np.pi, np.pi, 3))
        inertia = rot @ np.diag(_box_inertia(mass, dims)) @ rot.T
        com = rng.uniform(-0.2, 0.2, 3)
        parts.append(_link_xml(name, mass, com, inertia))
        jtype = types[index]
        if planar_axes:
            axis = np.array([0.0, 0.0, 1.0]) if jtype != 'prismatic' \
                else np.r_[rng.standard_normal(2), 0.0]
        else:
            axis = rng.standard_normal(3)
        axis /= np.linalg.norm(axis)
        origin = rng.uniform(-0.4, 0.4, 3)
        rpy = rng.uniform(-0.5, 0.5, 3) if not planar_axes else np.r_[0.0, 0.0,
                                                                      rng.uniform(-1, 1)]
        limit = '    <limit lower="-1" upper="1" effort="50" velocity="2"/>\n' \
            if jtype != 'continuous' else ''
        parts.append(
            f'  <joint name="joint_{index + 1}" type="{jtype}">\n'
            f'    <parent link="{parent}"/>\n    <child link="{name}"/>\n'
            f'    <origin xyz="{origin[0]:.6f} {origin[1]:.6f} {origin[2]:.6f}" '
            f'rpy="{rpy[0]:.6f} {rpy[1]:.6f} {rpy[2]:.6f}"/>\n'
            f'    <axis xyz="{axis[0]:.6f} {axis[1]:.6f} {axis[2]:.6f}"/>\n{limit}'
            f'  </joint>\n')
        links.append(name)
    parts.append('</robot>\n')
    return ''.join(parts)
