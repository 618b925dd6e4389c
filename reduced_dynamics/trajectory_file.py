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
Planned joint trajectories from files (``predict --trajectory``, ``simulate --trajectory``).

YAML::

    joint_names: [j2_x, j2_y]        # optional: every shape joint, in model order
    points:
      - {time: 0.0, positions: [0.0, 0.1], velocities: [0, 0]}   # velocities and
      - {time: 2.0, positions: [0.5, 0.2], velocities: [0, 0]}   # accelerations optional

CSV: a header ``time,<joint>,...`` then one row per point; optional columns
``<joint>:velocity`` and ``<joint>:acceleration`` (for every planned joint).
Times are seconds from the trajectory's start. Interpolation follows
joint_trajectory_controller (:mod:`reduced_dynamics.reduction.shape_path`).
"""

from __future__ import annotations

import csv
from pathlib import Path
from typing import Any, Optional, Sequence

import numpy as np
import yaml

from reduced_dynamics.messages.samples import JointTrajectorySample

NS = 1_000_000_000


class TrajectoryFileError(ValueError):
    """A trajectory file that cannot be used (the message says why and where)."""


def load_trajectory(path: str, default_names: Sequence[str] = ()) -> JointTrajectorySample:
    """Read a YAML or CSV trajectory file (by extension; .csv is CSV, anything else YAML)."""
    source = Path(path)
    try:
        text = source.read_text(encoding='utf-8')
    except OSError as error:
        raise TrajectoryFileError(f'cannot read trajectory {path}: {error}') from error
    if source.suffix.lower() == '.csv':
        return _from_csv(text, path)
    try:
        document = yaml.safe_load(text)
    except yaml.YAMLError as error:
        raise TrajectoryFileError(f'trajectory {path} is not valid YAML: {error}') from error
    return _from_yaml(document, path, tuple(default_names))


def _from_yaml(document: Any, path: str, default_names: tuple[str, ...]
               ) -> JointTrajectorySample:
    if not isinstance(document, dict) or not isinstance(document.get('points'), list):
        raise TrajectoryFileError(f'{path}: expected a mapping with a list "points"')
    names = tuple(document.get('joint_names') or default_names)
    points = document['points']
    if not names or not points:
        raise TrajectoryFileError(f'{path}: needs joint_names and at least one point')
    times, columns = [], {'positions': [], 'velocities': [], 'accelerations': []}
    for i, point in enumerate(points):
        if not isinstance(point, dict) or 'time' not in point or 'positions' not in point:
            raise TrajectoryFileError(f'{path}: point {i} needs "time" and "positions"')
        times.append(point['time'])
        for key, values in columns.items():
            values.append(point.get(key))
    return _sample(path, names, times, *(_column(path, key, values, len(names))
                                         for key, values in columns.items()))


def _column(path: str, key: str, values: list, width: int) -> Optional[np.ndarray]:
    present = [v is not None for v in values]
    if not any(present):
        if key == 'positions':
            raise TrajectoryFileError(f'{path}: points need positions')
        return None
    if not all(present):
        raise TrajectoryFileError(f'{path}: {key} on some points only')
    try:
        array = np.array(values, dtype=float)
    except (TypeError, ValueError) as error:
        raise TrajectoryFileError(f'{path}: {key} are not numbers: {error}') from error
    if array.shape != (len(values), width):
        raise TrajectoryFileError(f'{path}: every point needs {width} {key}')
    return array


def _from_csv(text: str, path: str) -> JointTrajectorySample:
    rows = [row for row in csv.reader(text.splitlines()) if row and any(c.strip() for c in row)]
    if len(rows) < 2:
        raise TrajectoryFileError(f'{path}: needs a header and at least one row')
    header = [c.strip() for c in rows[0]]
    if header[0] != 'time':
        raise TrajectoryFileError(f'{path}: the first column must be "time"')
    try:
        data = np.array([[float(c) for c in row] for row in rows[1:]])
    except ValueError as error:
        raise TrajectoryFileError(f'{path}: a value is not a number: {error}') from error
    if data.shape[1] != len(header):
        raise TrajectoryFileError(f'{path}: rows must have {len(header)} columns')
    names = tuple(c for c in header[1:] if ':' not in c)

    def pick(suffix: str) -> Optional[np.ndarray]:
        wanted = [f'{n}{suffix}' for n in names]
        if not any(w in header for w in wanted):
            return None
        missing = [w for w in wanted if w not in header]
        if missing:
            raise TrajectoryFileError(f'{path}: missing columns {missing}')
        return data[:, [header.index(w) for w in wanted]]
    return _sample(path, names, data[:, 0], pick(''), pick(':velocity'), pick(':acceleration'))


def _sample(path: str, names: tuple[str, ...], times: Sequence[float],
            positions: np.ndarray, velocities: Optional[np.ndarray],
            accelerations: Optional[np.ndarray]) -> JointTrajectorySample:
    try:
        seconds = np.array(times, dtype=float)
    except (TypeError, ValueError) as error:
        raise TrajectoryFileError(f'{path}: times are not numbers: {error}') from error
    arrays = [a for a in (seconds, positions, velocities, accelerations) if a is not None]
    if not all(np.all(np.isfinite(a)) for a in arrays):
        raise TrajectoryFileError(f'{path}: NaN or inf in the trajectory')
    try:
        return JointTrajectorySample(0, '', names, np.round(seconds * NS).astype(np.int64),
                                     positions, velocities, accelerations)
    except ValueError as error:
        raise TrajectoryFileError(f'{path}: {error}') from error
