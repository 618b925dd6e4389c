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
A smoothed replay's causal outputs, held on disk until the smoothed estimates exist.

The smoother needs the whole bag before it can say anything, while most of an
output (shape state, predictions, diagnostics) is final at once: those messages
are encoded as they come and written to a file; at the end they are read back in
order and merged with the smoothed rows (:meth:`Estimator.smoothed_rows`), so
memory does not grow with the bag and the output bag holds the messages in the
order the outputs came.
"""

from __future__ import annotations

import struct
from typing import Any, Callable, Iterator, Sequence

#: EstimatorOutput fields the smoother replaces (never spooled: written at the end).
SMOOTHED_FIELDS = frozenset({'mu', 'momentum', 'body_momentum', 'momentum_rate',
                             'drift_twist', 'momentum_covariance', 'wrench_covariance',
                             'disturbance'})

#: An output topic: EstimatorOutput field, topic, sample -> CDR bytes.
Encoder = tuple[str, str, Callable[[Any], bytes]]

_ROW = struct.Struct('<qH')  # stamp, messages that follow
_MESSAGE = struct.Struct('<HI')  # index of the encoder, bytes that follow


class OutputSpool:
    """Encoded causal messages of each output, in a file: :meth:`hold`, then :meth:`rows`."""

    def __init__(self, path: str, encoders: Sequence[Encoder]) -> None:
        """Create the file at ``path`` for outputs written with ``encoders``."""
        self.encoders = list(encoders)
        self._spooled = [(index, name, encode) for index, (name, _, encode)
                         in enumerate(self.encoders) if name not in SMOOTHED_FIELDS]
        self._file = open(path, 'w+b')
        self.count = 0

    def hold(self, output: Any) -> None:
        """Encode and store the causal messages of ``output`` (an EstimatorOutput)."""
        parts = [b'']
        for index, name, encode in self._spooled:
            sample = getattr(output, name)
            if sample is not None:
                data = encode(sample)
                parts.append(_MESSAGE.pack(index, len(data)))
                parts.append(data)
        parts[0] = _ROW.pack(output.stamp_ns, (len(parts) - 1) // 2)
        self._file.write(b''.join(parts))
        self.count += 1

    def rows(self) -> Iterator[tuple[int, dict[int, bytes]]]:
        """Yield per held output its stamp and {encoder index: CDR bytes}, in order."""
        stream = self._file
        stream.flush()
        stream.seek(0)
        read = stream.read
        for _ in range(self.count):
            stamp, messages = _ROW.unpack(read(_ROW.size))
            found = {}
            for _ in range(messages):
                index, size = _MESSAGE.unpack(read(_MESSAGE.size))
                found[index] = read(size)
            yield stamp, found

    def close(self) -> None:
        """Close the file (its directory's owner removes it)."""
        self._file.close()
