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
from typing import Any, Callable, Iterator, Optional, Sequence

import numpy as np

#: EstimatorOutput fields the smoother replaces (never spooled: written at the end).
SMOOTHED_FIELDS = frozenset({'mu', 'momentum', 'body_momentum', 'momentum_rate',
                             'drift_twist', 'momentum_covariance', 'wrench_covariance',
                             'disturbance'})

#: An output topic: EstimatorOutput field, topic, sample -> CDR bytes.
Encoder = tuple[str, str, Callable[[Any], bytes]]

_KIND = struct.Struct('<BI')  # segment: kind, rows
_ROW = struct.Struct('<qH')  # stamp, messages that follow
_MESSAGE = struct.Struct('<HI')  # index of the encoder, bytes that follow
_FIELD = struct.Struct('<HI')  # a run's message: index of the encoder, its size
_ONE, _RUN = 0, 1


class OutputSpool:
    """
    Encoded causal messages of each output, in a file: hold, then :meth:`segments`.

    The file is a sequence of segments: one output's messages (:meth:`hold`, a
    row with predictions or diagnostics), or a run of rows that carry the same
    fixed-size messages (:meth:`hold_rows`: the rows between those, from a
    chunk's columns), stored as one array.
    """

    def __init__(self, path: str, encoders: Sequence[Encoder]) -> None:
        """Create the file at ``path`` for outputs written with ``encoders``."""
        self.encoders = list(encoders)
        self._spooled = [(index, name, encode) for index, (name, _, encode)
                         in enumerate(self.encoders) if name not in SMOOTHED_FIELDS]
        self._file = open(path, 'w+b')
        self.count = 0

    def hold(self, output: Any) -> None:
        """Encode and store the causal messages of ``output`` (an EstimatorOutput)."""
        self.hold_fields(output.stamp_ns, {name: getattr(output, name)
                                           for _, name, _ in self._spooled})

    def hold_fields(self, stamp_ns: int, fields: dict[str, Any],
                    encoded: Optional[dict[str, bytes]] = None) -> None:
        """Store one output's causal messages: samples by field, or ``encoded`` bytes."""
        parts = [_KIND.pack(_ONE, 1), b'']
        for index, name, encode in self._spooled:
            data = encoded.get(name) if encoded else None
            if data is None:
                sample = fields.get(name)
                if sample is None:
                    continue
                data = encode(sample)
            parts.append(_MESSAGE.pack(index, len(data)))
            parts.append(data)
        parts[1] = _ROW.pack(stamp_ns, (len(parts) - 2) // 2)
        self._file.write(b''.join(parts))
        self.count += 1

    def hold_rows(self, stamps_ns: np.ndarray, records: dict[str, np.ndarray]) -> None:
        """Store a run of rows: ``records`` field -> (K, size) messages, the spooled ones."""
        count = len(stamps_ns)
        if not count:
            return
        present = [(index, records[name]) for index, name, _ in self._spooled
                   if name in records]
        head = [_KIND.pack(_RUN, count), struct.pack('<H', len(present))]
        head += [_FIELD.pack(index, part.shape[1]) for index, part in present]
        block = np.concatenate([np.asarray(stamps_ns, '<i8').view(np.uint8).reshape(count, 8),
                                *(part for _, part in present)], axis=1)
        self._file.write(b''.join(head))
        self._file.write(block.tobytes())
        self.count += count

    def segments(self) -> Iterator[tuple]:
        """
        Yield the held outputs in order, as segments.

        ``(stamp, {encoder index: CDR bytes})`` for one output, or ``(stamps (K,),
        {encoder index: (K, size) uint8})`` for a run of rows.
        """
        stream = self._file
        stream.flush()
        stream.seek(0)
        read = stream.read
        while True:
            head = read(_KIND.size)
            if not head:
                return
            kind, count = _KIND.unpack(head)
            if kind == _ONE:
                stamp, messages = _ROW.unpack(read(_ROW.size))
                found = {}
                for _ in range(messages):
                    index, size = _MESSAGE.unpack(read(_MESSAGE.size))
                    found[index] = read(size)
                yield stamp, found
                continue
            (fields,) = struct.unpack('<H', read(2))
            layout = [_FIELD.unpack(read(_FIELD.size)) for _ in range(fields)]
            width = 8 + sum(size for _, size in layout)
            block = np.frombuffer(read(width * count), np.uint8).reshape(count, width)
            stamps = block[:, :8].copy().view('<i8')[:, 0]
            found, at = {}, 8
            for index, size in layout:
                found[index] = block[:, at:at + size]
                at += size
            yield stamps, found

    def rows(self) -> Iterator[tuple[int, dict[int, bytes]]]:
        """Yield per held output its stamp and {encoder index: CDR bytes}, in order."""
        for stamp, found in self.segments():
            if isinstance(stamp, int):
                yield stamp, found
                continue
            for k, one in enumerate(stamp.tolist()):
                yield one, {index: part[k].tobytes() for index, part in found.items()}

    def close(self) -> None:
        """Close the file (its directory's owner removes it)."""
        self._file.close()
