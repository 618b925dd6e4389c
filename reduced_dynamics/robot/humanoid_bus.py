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
A 29-joint humanoid mounted on a spacecraft bus, as URDF text.

The joint layout is that of a 29-degree-of-freedom humanoid (Unitree G1's: waist
yaw, roll, pitch; per arm shoulder pitch, roll, yaw, elbow, wrist roll, pitch, yaw;
per leg hip pitch, roll, yaw, knee, ankle pitch, roll). Segment masses are the
fractions of body mass of Winter, "Biomechanics and Motor Control of Human
Movement" (4th ed., table 4.1): pelvis 14.2 %, trunk and head 43.6 %, upper arm
2.8 %, forearm 1.6 %, hand 0.6 %, thigh 10 %, shank 4.65 %, foot 1.45 %.
Segments are uniform boxes of human proportions (1.75 m standing height). The
pelvis is fixed on a post on the bus's top face; the bus is a uniform cube. Not a
model of a particular robot: a humanoid-scale tree for the event tests.
"""

from __future__ import annotations

import numpy as np

#: Fractions of body mass (Winter, table 4.1).
MASS_FRACTIONS = {'pelvis': 0.142, 'torso': 0.436, 'upper_arm': 0.028, 'forearm': 0.016,
                  'hand': 0.006, 'thigh': 0.100, 'shank': 0.0465, 'foot': 0.0145}
#: Box dimensions [m] of each segment (x, y, z), z along the segment.
DIMENSIONS = {'pelvis': (0.20, 0.30, 0.15), 'torso': (0.22, 0.36, 0.60),
              'upper_arm': (0.09, 0.09, 0.29), 'forearm': (0.07, 0.07, 0.27),
              'hand': (0.03, 0.09, 0.18), 'thigh': (0.14, 0.14, 0.43),
              'shank': (0.10, 0.10, 0.43), 'foot': (0.25, 0.09, 0.06)}
#: Mass [kg] of the links between the joints of one multi-axis joint (motor housings).
HOUSING = 0.3


def _inertial(name: str, mass: float, dims: tuple, com_z: float) -> str:
    a, b, c = dims
    i = mass / 12.0 * np.array([b * b + c * c, a * a + c * c, a * a + b * b])
    return (f'  <link name="{name}">\n    <inertial>\n'
            f'      <origin xyz="0 0 {com_z:.4f}" rpy="0 0 0"/>\n'
            f'      <mass value="{mass:.6f}"/>\n'
            f'      <inertia ixx="{i[0]:.8f}" ixy="0" ixz="0" iyy="{i[1]:.8f}" iyz="0" '
            f'izz="{i[2]:.8f}"/>\n    </inertial>\n  </link>\n')


def _joint(name: str, parent: str, child: str, xyz: tuple, axis: tuple,
           limit: float) -> str:
    return (f'  <joint name="{name}" type="revolute">\n'
            f'    <parent link="{parent}"/>\n    <child link="{child}"/>\n'
            f'    <origin xyz="{xyz[0]:.4f} {xyz[1]:.4f} {xyz[2]:.4f}" rpy="0 0 0"/>\n'
            f'    <axis xyz="{axis[0]} {axis[1]} {axis[2]}"/>\n'
            f'    <limit lower="{-limit}" upper="{limit}" effort="100" velocity="4"/>\n'
            f'  </joint>\n')


def humanoid_on_bus_urdf(bus_mass: float = 500.0, body_mass: float = 70.0,
                         bus_size: float = 1.6) -> str:
    """Return the URDF of a ``body_mass`` kg, 29-joint humanoid on a ``bus_mass`` kg bus."""
    parts = ['<?xml version="1.0"?>\n<robot name="humanoid_on_bus">\n']
    side = bus_size
    inertia = bus_mass * side * side / 6.0
    parts.append(f'  <link name="bus">\n    <inertial>\n      <origin xyz="0 0 0" rpy="0 0 0"/>\n'
                 f'      <mass value="{bus_mass:.6f}"/>\n'
                 f'      <inertia ixx="{inertia:.6f}" ixy="0" ixz="0" iyy="{inertia:.6f}" '
                 f'iyz="0" izz="{inertia:.6f}"/>\n    </inertial>\n  </link>\n')

    def segment(name: str, kind: str, down: bool) -> None:
        dims = DIMENSIONS[kind]
        parts.append(_inertial(name, MASS_FRACTIONS[kind] * body_mass, dims,
                               -dims[2] / 2 if down else dims[2] / 2))

    def housing(name: str) -> None:
        parts.append(_inertial(name, HOUSING, (0.06, 0.06, 0.06), 0.0))

    def chain(prefix: str, parent: str, at: tuple, axes: list, limits: list,
              child: str) -> None:
        """Joints about ``axes`` at one point, housings between, ending in ``child``."""
        for k, (axis, limit) in enumerate(zip(axes, limits)):
            name = child if k == len(axes) - 1 else f'{prefix}_housing_{k}'
            if k < len(axes) - 1:
                housing(name)
            parts.append(_joint(f'{prefix}_{k}', parent, name, at if k == 0 else (0, 0, 0),
                                axis, limit))
            parent = name

    # The pelvis on a 0.95 m post on the top face (legs hang above the face).
    segment('pelvis', 'pelvis', False)
    parts.append('  <joint name="post" type="fixed">\n    <parent link="bus"/>\n'
                 '    <child link="pelvis"/>\n'
                 f'    <origin xyz="0 0 {side / 2 + 0.95:.4f}" rpy="0 0 0"/>\n  </joint>\n')
    segment('torso', 'torso', False)
    chain('waist', 'pelvis', (0, 0, 0.15), [(0, 0, 1), (1, 0, 0), (0, 1, 0)],
          [2.6, 0.5, 0.5], 'torso')
    for side_name, y in (('left', 1.0), ('right', -1.0)):
        for kind in ('upper_arm', 'forearm', 'hand'):
            segment(f'{side_name}_{kind}', kind, True)
        chain(f'{side_name}_shoulder', 'torso', (0, 0.22 * y, 0.55),
              [(0, 1, 0), (1, 0, 0), (0, 0, 1)], [2.8, 1.5, 2.6], f'{side_name}_upper_arm')
        chain(f'{side_name}_elbow', f'{side_name}_upper_arm', (0, 0, -0.29), [(0, 1, 0)],
              [1.6], f'{side_name}_forearm')
        chain(f'{side_name}_wrist', f'{side_name}_forearm', (0, 0, -0.27),
              [(1, 0, 0), (0, 1, 0), (0, 0, 1)], [1.9, 1.6, 1.6], f'{side_name}_hand')
        for kind in ('thigh', 'shank', 'foot'):
            segment(f'{side_name}_{kind}', kind, True)
        chain(f'{side_name}_hip', 'pelvis', (0, 0.1 * y, -0.05),
              [(0, 1, 0), (1, 0, 0), (0, 0, 1)], [2.5, 0.5, 2.7], f'{side_name}_thigh')
        chain(f'{side_name}_knee', f'{side_name}_thigh', (0, 0, -0.43), [(0, 1, 0)], [2.8],
              f'{side_name}_shank')
        chain(f'{side_name}_ankle', f'{side_name}_shank', (0, 0, -0.43),
              [(0, 1, 0), (1, 0, 0)], [0.9, 0.26], f'{side_name}_foot')
    parts.append('</robot>\n')
    return ''.join(parts)
