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
URDF (file or string) to a Pinocchio model with a free base (section 3, Table 1).

The root link is the base body B1. Its joint to the world is either declared in
the URDF (a ``world`` link joined to the base by a ``floating`` or ``planar``
joint) or chosen by ``base_joint``. Shape joints are made one-dimensional so
that shape coordinates are plain numbers: ``revolute`` and ``continuous`` become
revolute joints (an unwrapped angle), ``prismatic`` stays prismatic, a
``planar`` shape joint becomes x, y, yaw and a ``floating`` one x, y, z, roll,
pitch, yaw (X-Y-Z angles, singular at pitch = +-90 deg), all about the joint
frame. ``fixed`` joints merge their child's inertia into the parent body.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import math
import os
from typing import Optional, Union
import xml.etree.ElementTree as ElementTree

import numpy as np
import pinocchio as pin

BASE_JOINT_TYPES = ('floating', 'planar')
WORLD_LINK = 'world'


class UrdfError(ValueError):
    """A URDF that cannot be turned into a free-floating model."""


@dataclass
class UrdfLink:
    """A link: name and inertia (mass, CoM and rotational inertia in the link frame)."""

    name: str
    mass: float = 0.0
    com: np.ndarray = field(default_factory=lambda: np.zeros(3))
    inertia: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)))

    def spatial_inertia(self) -> pin.Inertia:
        """Return the link's spatial inertia in its own frame."""
        return pin.Inertia(self.mass, self.com, self.inertia)


@dataclass(frozen=True)
class JointLimit:
    """
    A URDF ``<limit>``: position range (None for continuous joints), |velocity|, |effort|.

    Units are the joint's: rad, rad/s, N m (revolute) or m, m/s, N (prismatic).
    A velocity or effort of 0 means "not given" (URDF's default), stored as None.
    """

    lower: Optional[float]
    upper: Optional[float]
    velocity: Optional[float]
    effort: Optional[float]


@dataclass
class UrdfJoint:
    """A joint: type, parent/child link, origin placement, axis and limits."""

    name: str
    type: str
    parent: str
    child: str
    origin: pin.SE3
    axis: np.ndarray
    limit: Optional[JointLimit] = None


def _floats(text: Optional[str], count: int, what: str) -> np.ndarray:
    if text is None:
        return np.zeros(count)
    try:
        values = np.array([float(v) for v in text.split()])
    except ValueError as error:
        raise UrdfError(f'{what}: cannot read numbers from {text!r}') from error
    if values.shape != (count,) or not np.all(np.isfinite(values)):
        raise UrdfError(f'{what}: expected {count} finite numbers, got {text!r}')
    return values


def _origin(element: Optional[ElementTree.Element], what: str) -> pin.SE3:
    if element is None:
        return pin.SE3.Identity()
    xyz = _floats(element.get('xyz'), 3, f'{what} origin xyz')
    rpy = _floats(element.get('rpy'), 3, f'{what} origin rpy')
    return pin.SE3(pin.rpy.rpyToMatrix(*rpy), xyz)


def _parse_link(element: ElementTree.Element) -> UrdfLink:
    name = element.get('name')
    if not name:
        raise UrdfError('a <link> has no name')
    link = UrdfLink(name)
    inertial = element.find('inertial')
    if inertial is None:
        return link
    origin = _origin(inertial.find('origin'), f'link {name} inertial')
    mass_el = inertial.find('mass')
    inertia_el = inertial.find('inertia')
    if mass_el is None or inertia_el is None:
        raise UrdfError(f'link {name}: <inertial> needs <mass> and <inertia>')
    mass = float(_floats(mass_el.get('value'), 1, f'link {name} mass')[0])
    keys = ('ixx', 'ixy', 'ixz', 'iyy', 'iyz', 'izz')
    values = {}
    for key in keys:
        values[key] = float(_floats(inertia_el.get(key, '0'), 1, f'link {name} {key}')[0])
    rot = np.array([[values['ixx'], values['ixy'], values['ixz']],
                    [values['ixy'], values['iyy'], values['iyz']],
                    [values['ixz'], values['iyz'], values['izz']]])
    if mass < 0.0:
        raise UrdfError(f'link {name}: negative mass {mass}')
    # The inertia is given about the CoM in the inertial frame; express it in the link frame.
    link.mass = mass
    link.com = origin.translation.copy()
    link.inertia = origin.rotation @ rot @ origin.rotation.T
    return link


def _parse_joint(element: ElementTree.Element) -> UrdfJoint:
    name = element.get('name')
    jtype = element.get('type')
    if not name or not jtype:
        raise UrdfError('a <joint> lacks a name or a type')
    parent = element.find('parent')
    child = element.find('child')
    if parent is None or child is None or not parent.get('link') or not child.get('link'):
        raise UrdfError(f'joint {name}: needs <parent link=...> and <child link=...>')
    axis_el = element.find('axis')
    axis = _floats(axis_el.get('xyz') if axis_el is not None else '1 0 0', 3,
                   f'joint {name} axis')
    if jtype in ('revolute', 'continuous', 'prismatic', 'planar'):
        norm = np.linalg.norm(axis)
        if norm < 1e-12:
            raise UrdfError(f'joint {name}: zero axis')
        axis = axis / norm
    known = ('revolute', 'continuous', 'prismatic', 'fixed', 'floating', 'planar')
    if jtype not in known:
        raise UrdfError(f'joint {name}: unsupported type {jtype!r} (supported: {known})')
    return UrdfJoint(name, jtype, parent.get('link'), child.get('link'),
                     _origin(element.find('origin'), f'joint {name}'), axis,
                     _parse_limit(element.find('limit'), name, jtype))


def _parse_limit(element: Optional[ElementTree.Element], name: str,
                 jtype: str) -> Optional[JointLimit]:
    """Read a joint's <limit> (URDF: lower/upper default 0, ignored for continuous joints)."""
    if element is None or jtype not in ('revolute', 'continuous', 'prismatic'):
        return None

    def number(key: str) -> float:
        return float(_floats(element.get(key, '0'), 1, f'joint {name} limit {key}')[0])

    lower, upper = number('lower'), number('upper')
    velocity, effort = abs(number('velocity')), abs(number('effort'))
    if jtype == 'continuous':
        lower = upper = None
    elif lower > upper:
        raise UrdfError(f'joint {name}: limit lower {lower} > upper {upper}')
    return JointLimit(lower, upper, velocity or None, effort or None)


@dataclass
class UrdfRobot:
    """Parsed URDF: links, joints and the free base they hang from."""

    name: str
    links: dict[str, UrdfLink]
    joints: list[UrdfJoint]
    base_link: str
    base_joint_type: str
    base_joint_name: str

    def children(self, link: str) -> list[UrdfJoint]:
        """Joints whose parent is ``link``, in document order."""
        return [j for j in self.joints if j.parent == link]


def read_urdf_text(source: Union[str, os.PathLike]) -> str:
    """Return URDF XML from a path or from the XML text itself."""
    source = str(source)
    stripped = source.lstrip()
    if stripped.startswith('<'):
        return source
    if not os.path.isfile(source):
        raise UrdfError(f'URDF file not found: {source}')
    with open(source, encoding='utf-8') as stream:
        return stream.read()


def parse_urdf(source: str, base_joint: Optional[str] = None) -> UrdfRobot:
    """
    Parse URDF text or a file and find its free base.

    ``base_joint`` ('floating' or 'planar') is used when the URDF has no world
    joint; when it has one, ``base_joint`` must agree with it.
    """
    text = read_urdf_text(source)
    try:
        root = ElementTree.fromstring(text)
    except ElementTree.ParseError as error:
        raise UrdfError(f'URDF is not valid XML: {error}') from error
    if root.tag != 'robot':
        raise UrdfError(f'URDF root element is <{root.tag}>, expected <robot>')
    links = {}
    for element in root.findall('link'):
        link = _parse_link(element)
        if link.name in links:
            raise UrdfError(f'duplicate link {link.name}')
        links[link.name] = link
    joints = [_parse_joint(e) for e in root.findall('joint')]
    names = [j.name for j in joints]
    if len(set(names)) != len(names):
        raise UrdfError('duplicate joint names')
    child_of = {}
    for joint in joints:
        for end in (joint.parent, joint.child):
            if end not in links:
                raise UrdfError(f'joint {joint.name} refers to unknown link {end}')
        if joint.child in child_of:
            raise UrdfError(f'link {joint.child} has two parent joints: not a tree')
        child_of[joint.child] = joint
    roots = [name for name in links if name not in child_of]
    if len(roots) != 1:
        raise UrdfError(f'URDF must have exactly one root link, found {roots}')
    root_link = roots[0]
    if base_joint is not None and base_joint not in BASE_JOINT_TYPES:
        raise UrdfError(f'base_joint must be one of {BASE_JOINT_TYPES}, got {base_joint!r}')
    robot_name = root.get('name', 'robot')
    if root_link == WORLD_LINK:
        world_joints = [j for j in joints if j.parent == WORLD_LINK]
        if len(world_joints) != 1:
            raise UrdfError('the world link must have exactly one child joint (the free base)')
        wj = world_joints[0]
        if wj.type not in BASE_JOINT_TYPES:
            raise UrdfError(
                f'URDF has no free base: joint {wj.name} attaches the robot to the world as '
                f'{wj.type!r}; a free-floating robot needs a floating or planar base joint')
        if base_joint is not None and base_joint != wj.type:
            raise UrdfError(f'base_joint={base_joint!r} contradicts the URDF world joint '
                            f'{wj.name} of type {wj.type!r}')
        if wj.type == 'planar' and np.abs(np.abs(wj.axis) - np.array([0, 0, 1])).max() > 1e-9:
            raise UrdfError(f'planar base joint {wj.name}: the plane normal must be z')
        if not np.allclose(wj.origin.homogeneous, np.eye(4)):
            raise UrdfError(f'base joint {wj.name}: origin must be identity')
        joints = [j for j in joints if j is not wj]
        del links[WORLD_LINK]
        return UrdfRobot(robot_name, links, joints, wj.child, wj.type, wj.name)
    return UrdfRobot(robot_name, links, joints, root_link, base_joint or 'floating',
                     'base_joint')


def _frame_with_z_along(axis: np.ndarray) -> np.ndarray:
    """Return a rotation whose z column is ``axis`` (for planar joints of any normal)."""
    z = axis / np.linalg.norm(axis)
    helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    return np.column_stack([x, np.cross(z, x), z])


def _axis_joint(kind: str, axis: np.ndarray) -> pin.JointModel:
    """Return a 1-dof Pinocchio joint about/along ``axis`` (aligned variants when possible)."""
    for index, letter in enumerate('XYZ'):
        unit = np.zeros(3)
        unit[index] = 1.0
        if np.allclose(axis, unit, atol=1e-12):
            return getattr(pin, f'JointModel{"R" if kind == "revolute" else "P"}{letter}')()
    if kind == 'revolute':
        return pin.JointModelRevoluteUnaligned(axis)
    return pin.JointModelPrismaticUnaligned(axis)


@dataclass
class BuiltModel:
    """A Pinocchio model plus what the URDF said about its base and shape joints."""

    model: pin.Model
    urdf: UrdfRobot
    shape_joint_names: tuple[str, ...]
    shape_joint_sources: dict[str, str]
    #: URDF limits of the shape joints that have them (1-dof URDF joints only)
    shape_joint_limits: dict[str, JointLimit] = field(default_factory=dict)


def build_pinocchio_model(robot: UrdfRobot) -> BuiltModel:
    """Build the Pinocchio model: free base joint 1, then 1-dof shape joints."""
    model = pin.Model()
    model.name = robot.name
    root = pin.JointModelFreeFlyer() if robot.base_joint_type == 'floating' \
        else pin.JointModelPlanar()
    base_id = model.addJoint(0, root, pin.SE3.Identity(), robot.base_joint_name)
    shape_names: list[str] = []
    sources: dict[str, str] = {}

    def attach(link: UrdfLink, joint_id: int, placement: pin.SE3,
               previous_frame: int) -> None:
        model.appendBodyToJoint(joint_id, placement.act(link.spatial_inertia()),
                                pin.SE3.Identity())
        frame = pin.Frame(link.name, joint_id, previous_frame, placement, pin.FrameType.BODY)
        frame_id = model.addFrame(frame, False)
        for joint in robot.children(link.name):
            add_joint(joint, joint_id, placement, frame_id)

    def add_chain(steps: list[tuple[str, pin.JointModel]], parent_id: int,
                  placement: pin.SE3, source: str) -> int:
        joint_id = parent_id
        for index, (name, joint_model) in enumerate(steps):
            joint_id = model.addJoint(joint_id, joint_model,
                                      placement if index == 0 else pin.SE3.Identity(), name)
            shape_names.append(name)
            sources[name] = source
        return joint_id

    def add_joint(joint: UrdfJoint, parent_id: int, parent_placement: pin.SE3,
                  parent_frame: int) -> None:
        child = robot.links[joint.child]
        placement = parent_placement * joint.origin
        if joint.type == 'fixed':
            attach(child, parent_id, placement, parent_frame)
            return
        if joint.type in ('revolute', 'continuous', 'prismatic'):
            kind = 'prismatic' if joint.type == 'prismatic' else 'revolute'
            jid = add_chain([(joint.name, _axis_joint(kind, joint.axis))], parent_id,
                            placement, joint.type)
            attach(child, jid, pin.SE3.Identity(), parent_frame)
            return
        if joint.type == 'planar':
            rot = _frame_with_z_along(joint.axis)
            frame = pin.SE3(rot, np.zeros(3))
            jid = add_chain([(f'{joint.name}_x', pin.JointModelPX()),
                             (f'{joint.name}_y', pin.JointModelPY()),
                             (f'{joint.name}_yaw', pin.JointModelRZ())],
                            parent_id, placement * frame, 'planar')
            attach(child, jid, frame.inverse(), parent_frame)
            return
        jid = add_chain([(f'{joint.name}_x', pin.JointModelPX()),
                         (f'{joint.name}_y', pin.JointModelPY()),
                         (f'{joint.name}_z', pin.JointModelPZ()),
                         (f'{joint.name}_roll', pin.JointModelRX()),
                         (f'{joint.name}_pitch', pin.JointModelRY()),
                         (f'{joint.name}_yaw', pin.JointModelRZ())],
                        parent_id, placement, 'floating')
        attach(child, jid, pin.SE3.Identity(), parent_frame)

    attach(robot.links[robot.base_link], base_id, pin.SE3.Identity(), 0)
    for joint_id in range(2, model.njoints):
        if model.joints[joint_id].nq != 1:
            raise UrdfError('internal: shape joints must be one-dimensional')
    model.lowerPositionLimit[:] = -math.inf
    model.upperPositionLimit[:] = math.inf
    limits = {j.name: j.limit for j in robot.joints
              if j.limit is not None and j.name in sources}
    return BuiltModel(model, robot, tuple(shape_names), sources, limits)
