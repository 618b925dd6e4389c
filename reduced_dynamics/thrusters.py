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
Binary (on/off) thrusters: a fixed set of body-frame unit wrenches switched on and off.

A thruster ``i`` that is on pushes the base with ``force * units[i]`` (body frame,
(fx, fy, fz, tx, ty, tz) per newton of thrust: its direction and its moment arm).
The *commanded* wrench is the sum over the thrusters that are on at their nominal
force; the *delivered* wrench, which acts on the body, is ``gain * command + bias``
per axis (a weak thruster, a misaligned nozzle, a leak or a tilted table), so a
thruster-health estimate has a known answer. ``bias`` acts whenever it is nonzero,
firing or not: it is the constant term of the linear map command -> delivered wrench.
"""

from __future__ import annotations

from dataclasses import dataclass
import math
from typing import Optional, Sequence

import numpy as np

#: Lever arm [m] of the freeflyer2 testbed's thrusters (../shared/data/freeflyer2/README.md).
FREEFLYER_ARM = 0.11461
#: Nominal thrust [N] of one freeflyer2 thruster.
FREEFLYER_FORCE = 0.2
#: Body-frame (fx, fy, tz) per newton of the 8 freeflyer2 thrusters, from the README's
#: switch table: Fx = s2 + s5 - s1 - s6, Fy = s4 + s7 - s0 - s3,
#: Mz / arm = s1 + s3 + s5 + s7 - s0 - s2 - s4 - s6.
_FREEFLYER_PLANAR = (
    (0.0, -1.0, -1.0), (-1.0, 0.0, 1.0), (1.0, 0.0, -1.0), (0.0, -1.0, 1.0),
    (0.0, 1.0, -1.0), (1.0, 0.0, 1.0), (-1.0, 0.0, -1.0), (0.0, 1.0, 1.0),
)
LAYOUTS = {
    'freeflyer': tuple((fx, fy, 0.0, 0.0, 0.0, FREEFLYER_ARM * tz)
                       for fx, fy, tz in _FREEFLYER_PLANAR),
}
#: Nominal thrust [N] of each named layout (the default of ``thruster_force``).
LAYOUT_FORCE = {'freeflyer': FREEFLYER_FORCE}


@dataclass(frozen=True)
class ThrusterFiring:
    """Thrusters ``thrusters`` (indices into the layout) on during [start, start + duration)."""

    start: float
    duration: float
    thrusters: tuple[int, ...]

    def __post_init__(self) -> None:
        """Validate the firing."""
        object.__setattr__(self, 'start', float(self.start))
        object.__setattr__(self, 'duration', float(self.duration))
        object.__setattr__(self, 'thrusters', tuple(int(i) for i in self.thrusters))
        if not (math.isfinite(self.start) and math.isfinite(self.duration)):
            raise ValueError('thruster firing times must be finite')
        if self.start < 0.0:
            raise ValueError(f'thruster firing start must be >= 0, got {self.start:g}')
        if self.duration <= 0.0:
            raise ValueError(f'thruster firing duration must be > 0, got {self.duration:g}')
        if not self.thrusters or min(self.thrusters) < 0:
            raise ValueError(f'a firing needs thruster indices >= 0, got {self.thrusters}')

    @property
    def end(self) -> float:
        """End time of the firing (exclusive)."""
        return self.start + self.duration

    @classmethod
    def parse(cls, spec: str) -> 'ThrusterFiring':
        """Parse ``T,DURATION,I[,J...]`` (thruster indices from 0)."""
        parts = [p.strip() for p in spec.split(',')]
        if len(parts) < 3:
            raise ValueError(f'firing spec {spec!r} must be T,DURATION,I[,J...] (start, '
                             f'duration, then at least one thruster index)')
        try:
            start, duration = float(parts[0]), float(parts[1])
            indices = tuple(int(p) for p in parts[2:])
        except ValueError:
            raise ValueError(f'firing spec {spec!r}: T and DURATION must be numbers and the '
                             f'thruster indices integers') from None
        return cls(start, duration, indices)


@dataclass(frozen=True)
class ThrusterSet:
    """A thruster layout, its nominal force and the delivered-wrench gain and bias."""

    units: np.ndarray
    force: float = 1.0
    gain: Optional[np.ndarray] = None
    bias: Optional[np.ndarray] = None

    def __post_init__(self) -> None:
        """Validate and freeze the arrays."""
        units = np.array(self.units, dtype=float).reshape(-1, 6)
        gain = np.ones(6) if self.gain is None else np.array(self.gain, dtype=float).reshape(6)
        bias = np.zeros(6) if self.bias is None else np.array(self.bias, dtype=float).reshape(6)
        for name, value in (('units', units), ('gain', gain), ('bias', bias)):
            if not np.all(np.isfinite(value)):
                raise ValueError(f'thruster {name} must be finite')
            value.setflags(write=False)
        if not (math.isfinite(self.force) and self.force > 0.0):
            raise ValueError(f'thruster force must be a finite number > 0, got {self.force!r}')
        object.__setattr__(self, 'units', units)
        object.__setattr__(self, 'gain', gain)
        object.__setattr__(self, 'bias', bias)
        object.__setattr__(self, 'force', float(self.force))

    @property
    def count(self) -> int:
        """Return the number of thrusters."""
        return len(self.units)

    def on(self, firings: Sequence[ThrusterFiring], t: float) -> tuple[int, ...]:
        """Return the sorted indices of the thrusters on at time ``t`` (binary: no doubling)."""
        return tuple(sorted({i for f in firings if f.start <= t < f.end for i in f.thrusters}))

    def command(self, on: Sequence[int]) -> np.ndarray:
        """Return the commanded body wrench (fx, fy, fz, tx, ty, tz) of the thrusters ``on``."""
        if not len(on):
            return np.zeros(6)
        return self.force * self.units[list(on)].sum(axis=0)

    def delivered(self, command: np.ndarray) -> np.ndarray:
        """Return the body wrench that acts: ``gain * command + bias``, per axis."""
        return self.gain * command + self.bias
