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

"""Exceptions raised by the bag reader and writer."""


class BagError(ValueError):
    """A bag cannot be opened, read or written; the message is a single line."""

    def __init__(self, message: str) -> None:
        """Collapse ``message`` to one line (long parser errors included)."""
        super().__init__(one_line(message))


def one_line(text: object, limit: int = 400) -> str:
    """Collapse whitespace/newlines and truncate to ``limit`` characters."""
    flat = ' '.join(str(text).split())
    return flat if len(flat) <= limit else flat[:limit - 3] + '...'
