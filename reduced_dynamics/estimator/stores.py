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
The sizes of every store an estimator holds: the check that its memory is bounded.

:func:`store_sizes` walks the object graph from an estimator (or a node's
bookkeeping) and reports, per attribute path, the length of every list,
deque, dict and set and the bytes of every numpy array (a view counts its
base: it keeps that alive). A test feeds many horizons' worth of samples and
checks that no store grows without a documented bound (test_bounded_stores.py,
docs/soak.md); ``reduced-dynamics bench --sections soak`` reports the largest.
"""

from __future__ import annotations

from collections import deque
from typing import Any, NamedTuple, Optional

import numpy as np

#: Objects of these modules are walked into (others, e.g. Pinocchio's, are leaves).
WALKED = ('reduced_dynamics',)
_ATOMS = (str, bytes, int, float, complex, bool, type(None), type)


class Store(NamedTuple):
    """A container's size (items, or bytes for arrays) and its maxlen if it has one."""

    size: int
    maxlen: Optional[int]
    kind: str


def _fields(obj: Any) -> Optional[dict]:
    """Return the attributes of an object of this package (None: not walked into)."""
    if not type(obj).__module__.startswith(WALKED):
        return None
    if hasattr(obj, '_asdict'):
        return obj._asdict()
    out = dict(getattr(obj, '__dict__', {}))
    for cls in type(obj).__mro__:
        for name in getattr(cls, '__slots__', ()):
            if hasattr(obj, name):
                out[name] = getattr(obj, name)
    return out


def store_sizes(root: Any, name: str = 'estimator') -> dict[str, Store]:
    """
    Return every container reachable from ``root``, by attribute path.

    Items of a sequence share one path (``[*]``) and report the largest; an
    object reached twice is reported at the first path found.
    """
    out: dict[str, Store] = {}
    seen: set[int] = set()
    stack: list[tuple[str, Any]] = [(name, root)]

    def report(path: str, size: int, maxlen: Optional[int], kind: str) -> None:
        old = out.get(path)
        if old is None or size > old.size:
            out[path] = Store(size, maxlen, kind)

    while stack:
        path, obj = stack.pop()
        if isinstance(obj, _ATOMS) or id(obj) in seen:
            continue
        seen.add(id(obj))
        if isinstance(obj, np.ndarray):
            base = obj
            while isinstance(base.base, np.ndarray):
                base = base.base
            report(path, int(base.nbytes), None, 'array')
            continue
        if isinstance(obj, (list, tuple, deque, set, frozenset)):
            if not isinstance(obj, tuple):
                report(path, len(obj), getattr(obj, 'maxlen', None), type(obj).__name__)
            stack.extend((f'{path}[*]', item) for item in obj)
            continue
        if isinstance(obj, dict):
            report(path, len(obj), None, 'dict')
            stack.extend((f'{path}[{key!r}]' if isinstance(key, str) else f'{path}[*]', value)
                         for key, value in obj.items())
            continue
        fields = _fields(obj)
        if fields:
            stack.extend((f'{path}.{key}', value) for key, value in fields.items())
    return out
