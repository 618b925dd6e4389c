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


"""The detected events an estimator keeps: the most recent ones, and how many there were."""

from __future__ import annotations

from collections import deque
from typing import Any, Iterable

#: Events kept (summaries, diagnostics); older ones are counted only. Each is ~1 kB.
EVENTS_KEEP = 1000


class EventLog(deque):
    """
    The last :data:`EVENTS_KEEP` detected events, oldest first, and the count of all.

    Memory bound: ``maxlen`` events (a deque that drops the oldest). ``detected``
    counts every event ever appended (published as they were detected, so a
    node loses none by forgetting old ones here).
    """

    def __init__(self, events: Iterable[Any] = (), maxlen: int = EVENTS_KEEP) -> None:
        """Start with ``events`` (the newest ``maxlen`` of them kept)."""
        events = list(events)
        super().__init__(events, maxlen)
        self.detected = len(events)

    def append(self, event: Any) -> None:
        """Keep ``event`` (dropping the oldest when full) and count it."""
        super().append(event)
        self.detected += 1
