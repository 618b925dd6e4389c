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
A rigid payload held by one link, and the robot model that holds it.

The payload is a spatial inertia (mass, centre of mass in the link frame,
rotational inertia about the centre of mass in the link frame's axes). Held by a
link, it is appended to the body inertia of the link's joint (Pinocchio
``appendBodyToJoint``), so every metric block, the reduction and the filter see
it (REDUCED_MODEL.md 2). The YAML written by ``reduced-dynamics identify`` and
read by ``replay --payload`` and the node's ``payload_file``::

    link: forearm
    mass: 7.0                       # kg
    com: [0.3, 0.0, 0.05]           # m, link frame
    inertia: [[...], [...], [...]]  # kg m^2 about the CoM, link axes
    sigma: {mass: ..., com: [...], principal_inertia: [...]}   # optional
"""

from __future__ import annotations

from dataclasses import dataclass, field
import math
from pathlib import Path
from typing import Any, Optional, Union

import numpy as np
import pinocchio as pin
import yaml

from reduced_dynamics.robot.model import RobotModel


class PayloadError(ValueError):
    """A payload that cannot be held (bad numbers, unknown link, bad file)."""


@dataclass(frozen=True)
class Payload:
    """A rigid payload on ``link``: mass (kg), CoM (m) and inertia about it (kg m^2)."""

    link: str
    mass: float
    com: np.ndarray
    inertia: np.ndarray
    #: one standard deviation of each estimate (identify's output; empty when given)
    sigma: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        """Check the numbers describe a physical body."""
        com = np.asarray(self.com, dtype=float).reshape(3)
        inertia = np.asarray(self.inertia, dtype=float).reshape(3, 3)
        object.__setattr__(self, 'com', com)
        object.__setattr__(self, 'inertia', 0.5 * (inertia + inertia.T))
        object.__setattr__(self, 'mass', float(self.mass))
        if not self.link:
            raise PayloadError('a payload needs the name of the link that holds it')
        if not (math.isfinite(self.mass) and self.mass > 0.0):
            raise PayloadError(f'payload mass must be a finite number > 0, got {self.mass!r}')
        if not (np.all(np.isfinite(com)) and np.all(np.isfinite(inertia))):
            raise PayloadError('payload centre of mass and inertia must be finite')
        principal = np.linalg.eigvalsh(self.inertia)
        # Triangle inequalities of the principal moments: a real mass distribution.
        tolerance = 1e-9 * max(float(principal[-1]), 1e-300)
        if principal[0] < -tolerance or principal[2] > principal[0] + principal[1] + tolerance:
            raise PayloadError(
                f'payload inertia is not physical: principal moments {principal} must be '
                '>= 0 and each at most the sum of the other two')

    @property
    def principal_inertia(self) -> np.ndarray:
        """Principal moments about the CoM, ascending."""
        return np.linalg.eigvalsh(self.inertia)

    def spatial_inertia(self) -> pin.Inertia:
        """Return the payload's spatial inertia in the link frame."""
        return pin.Inertia(self.mass, self.com, self.inertia)

    @classmethod
    def parse(cls, spec: str) -> 'Payload':
        """Parse ``LINK,MASS,CX,CY,CZ,IXX,IYY,IZZ[,IXY,IXZ,IYZ]`` (inertia about the CoM)."""
        parts = [p.strip() for p in spec.split(',')]
        if len(parts) not in (8, 11):
            raise PayloadError(f'payload {spec!r} must be LINK,MASS,CX,CY,CZ,IXX,IYY,IZZ'
                               f'[,IXY,IXZ,IYZ] (8 or 11 fields, got {len(parts)})')
        try:
            values = [float(p) for p in parts[1:]]
        except ValueError:
            raise PayloadError(f'payload {spec!r} holds a value that is not a number') \
                from None
        ixx, iyy, izz = values[4:7]
        ixy, ixz, iyz = values[7:10] if len(values) == 10 else (0.0, 0.0, 0.0)
        inertia = np.array([[ixx, ixy, ixz], [ixy, iyy, iyz], [ixz, iyz, izz]])
        return cls(parts[0], values[0], np.array(values[1:4]), inertia)

    def to_dict(self) -> dict[str, Any]:
        """Return the YAML document (plain lists and floats)."""
        document: dict[str, Any] = {
            'link': self.link, 'mass': float(self.mass),
            'com': [float(v) for v in self.com],
            'inertia': [[float(v) for v in row] for row in self.inertia]}
        if self.sigma:
            document['sigma'] = {k: (float(v) if np.ndim(v) == 0 else
                                     [float(x) for x in np.ravel(v)])
                                 for k, v in self.sigma.items()}
        return document

    def write(self, path: Union[str, Path]) -> None:
        """Write the payload YAML."""
        Path(path).write_text(yaml.safe_dump(self.to_dict(), sort_keys=False))


def load_payload(path: Union[str, Path], link: Optional[str] = None) -> Payload:
    """Read a payload YAML; ``link`` (when given) overrides or supplies the link."""
    try:
        document = yaml.safe_load(Path(path).read_text(encoding='utf-8'))
    except OSError as error:
        raise PayloadError(f'cannot read payload file {path}: {error}') from error
    except yaml.YAMLError as error:
        raise PayloadError(f'payload file {path} is not valid YAML: {error}') from error
    if not isinstance(document, dict):
        raise PayloadError(f'payload file {path}: expected a mapping')
    missing = [k for k in ('mass', 'com', 'inertia') if k not in document]
    if missing or not (link or document.get('link')):
        raise PayloadError(f'payload file {path}: needs link, mass, com and inertia '
                           f'(missing {missing or ["link"]})')
    try:
        return Payload(link or str(document['link']), document['mass'],
                       np.array(document['com'], dtype=float),
                       np.array(document['inertia'], dtype=float),
                       dict(document.get('sigma') or {}))
    except (TypeError, ValueError) as error:
        raise PayloadError(f'payload file {path}: {error}') from error


def link_frame(robot: RobotModel, link: str) -> int:
    """Return the Pinocchio frame id of URDF link ``link`` (PayloadError if unknown)."""
    model = robot.model
    if not model.existFrame(link, pin.FrameType.BODY):
        bodies = [f.name for f in model.frames if f.type == pin.FrameType.BODY]
        raise PayloadError(f'robot {model.name} has no link {link!r}; links: {bodies}')
    return model.getFrameId(link, pin.FrameType.BODY)


def with_payload(robot: RobotModel, payload: Payload) -> RobotModel:
    """
    Return a copy of ``robot`` whose link ``payload.link`` holds the payload.

    Everything computed from the Pinocchio model is rebuilt (metric blocks,
    mass, the cached symmetry report: the payload may break a symmetry); the
    URDF, joint names and base group are shared.
    """
    frame = robot.model.frames[link_frame(robot, payload.link)]
    model = pin.Model(robot.model)
    model.appendBodyToJoint(frame.parentJoint, payload.spatial_inertia(), frame.placement)
    held = object.__new__(RobotModel)
    held.__dict__.update(robot.__dict__)
    held.model = model
    held.data = model.createData()
    held._kinetic_model = pin.Model(model)
    held._kinetic_model.gravity = pin.Motion.Zero()
    held._kinetic_data = held._kinetic_model.createData()
    held._q_work = robot._q_work.copy()
    held._zero_v = robot._zero_v.copy()
    held.total_mass = float(pin.computeTotalMass(model))
    held._symmetry_report = None
    held.payload = payload
    return held
