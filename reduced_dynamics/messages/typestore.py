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
The process's one ROS 2 Jazzy typestore (rosbags), shared by readers, writers and types.

A rosbags ``Typestore`` generates and compiles 14 functions per message type at its
first use of the type, and keeps them in that store only: ~60-75 ms of CPU for the
seven types a replay uses, again for each new store (docs/performance.md, stop 41).
Every bag reader, bag writer and :class:`~reduced_dynamics.messages.types.RosbagsTypes`
made without a store of its own used to create a fresh one, so a campaign's worker or a
test process paid it per bag. They now share :func:`jazzy_typestore`.

The shared store is never changed: a reader that must register a bag's own type
takes a private store first (``BagReader``), and code that registers types (the
simulator's status message, a command mapping's message) makes its own.
"""

from __future__ import annotations

import functools
from typing import Any


def private_jazzy_typestore() -> Any:
    """Return a new ROS 2 Jazzy typestore of the caller's own (free to ``register`` in)."""
    from rosbags.typesys import get_typestore, Stores
    return get_typestore(Stores.ROS2_JAZZY)


#: The process's shared ROS 2 Jazzy typestore (do not ``register`` in it).
jazzy_typestore = functools.lru_cache(maxsize=None)(private_jazzy_typestore)


@functools.lru_cache(maxsize=None)
def jazzy_hash(msgtype: str) -> str:
    """Return the RIHS01 hash of ROS 2 Jazzy's ``msgtype`` (made once per process)."""
    return jazzy_typestore().hash_rihs01(msgtype)


def _definition_text(typestore: Any, msgtype: str) -> str:
    return typestore.generate_msgdef(msgtype, ros_version=2)[0]


@functools.lru_cache(maxsize=None)
def _jazzy_definition_text(msgtype: str) -> str:
    return _definition_text(jazzy_typestore(), msgtype)


def rihs01(typestore: Any, msgtype: str) -> str:
    """Return the RIHS01 hash of ``msgtype`` in ``typestore`` (cached for the shared one)."""
    return jazzy_hash(msgtype) if is_shared(typestore) else typestore.hash_rihs01(msgtype)


def definition(typestore: Any, msgtype: str) -> tuple[str, str]:
    """
    Return ``msgtype``'s definition text and RIHS01 hash in ``typestore``.

    What a bag records per connection; rosbags makes both anew at each call, so for
    the shared store they are made once per process and type.
    """
    text = (_jazzy_definition_text(msgtype) if is_shared(typestore)
            else _definition_text(typestore, msgtype))
    return text, rihs01(typestore, msgtype)


def is_shared(typestore: Any) -> bool:
    """Tell whether ``typestore`` is :func:`jazzy_typestore`'s shared store."""
    return jazzy_typestore.cache_info().currsize > 0 and typestore is jazzy_typestore()
