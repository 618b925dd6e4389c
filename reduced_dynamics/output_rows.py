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
A processed chunk's per-row messages into a bag, from its columns.

Every row of an :class:`~reduced_dynamics.estimator.outputs.OutputChunk` carries
the same fixed-layout messages (momentum, body momentum, shape state, momentum
rate, drift twist, and the disturbance or cyclic momenta when on); a few rows
also carry predictions or diagnostics. The every-row messages are encoded for
the whole chunk at once (:meth:`OutputChunk.records`) and the rows between two
occasional ones go into the bag as one block (:meth:`BagWriter.write_rows`); a
row with predictions or diagnostics is written message by message. The bag is
byte for byte the one :meth:`RowWriter.write_output` writes output by output
(test_output_rows.py).
"""

from __future__ import annotations

from typing import Any, Callable, Sequence

from reduced_dynamics.bag.writer import BagWriter
from reduced_dynamics.estimator.outputs import COLUMN_FIELDS, EstimatorOutput, OutputChunk
from reduced_dynamics.output_spool import OutputSpool
from reduced_dynamics.messages.cdr_columns import COLUMN_ENCODERS

#: An output topic: EstimatorOutput field, bag topic, sample -> CDR bytes.
Encoder = tuple[str, str, Callable[[Any], bytes]]


def columns_apply(encoders: Sequence[Encoder]) -> bool:
    """
    Tell whether a chunk's rows can be written from its columns with ``encoders``.

    The every-row fields must come first (a row's messages are its columns, then
    its occasional ones) and be encoded by the fixed-layout encoders.
    """
    names = [name for name, _, _ in encoders]
    lead = 0
    while lead < len(names) and names[lead] in COLUMN_FIELDS:
        lead += 1
    return (not any(name in COLUMN_FIELDS for name in names[lead:])
            and all(encode in COLUMN_ENCODERS for _, _, encode in encoders[:lead]))


class RowWriter:
    """Write chunks' per-row outputs (not events or fixed-lag rows) into a bag."""

    def __init__(self, writer: BagWriter, encoders: Sequence[Encoder]) -> None:
        """Write with ``encoders`` (topic order) into the open ``writer``."""
        self.writer = writer
        self.encoders = list(encoders)
        self.columns = columns_apply(self.encoders)
        lead = 0
        while lead < len(self.encoders) and self.encoders[lead][0] in COLUMN_FIELDS:
            lead += 1
        self._column_encoders = self.encoders[:lead]
        self._occasional = self.encoders[lead:]

    def write_output(self, output: EstimatorOutput) -> None:
        """Write one output's messages, topic by topic (the reference path)."""
        write, stamp = self.writer.write_raw, output.stamp_ns
        for name, topic, encode in self.encoders:
            sample = getattr(output, name)
            if sample is not None:
                write(topic, stamp, encode(sample))

    def hold_chunk(self, spool: OutputSpool, chunk: OutputChunk) -> None:
        """Hold ``chunk``'s causal messages in ``spool`` (smoothed replay): runs of rows."""
        records = chunk.records() if self.columns else None
        if records is None:
            for output in chunk.outputs():
                spool.hold(output)
            return
        stamps, count = chunk.stamps_ns, len(chunk)
        extras = chunk.extras
        occasional = sorted(k for k, extra in extras.items() if extra) if extras else []
        start = 0
        for k in (*occasional, count):
            if k > start:
                spool.hold_rows(stamps[start:k], {name: part[start:k]
                                                  for name, part in records.items()})
            if k == count:
                break
            spool.hold_fields(int(stamps[k]), chunk.extra_fields(k),
                              {name: part[k].tobytes() for name, part in records.items()})
            start = k + 1

    def write_chunk(self, chunk: OutputChunk) -> None:
        """Write every row of ``chunk`` as :meth:`write_output` would, output by output."""
        records = chunk.records() if self.columns else None
        if records is None:
            for output in chunk.outputs():
                self.write_output(output)
            return
        present = [(topic, records[name]) for name, topic, _ in self._column_encoders
                   if name in records]
        topics = [topic for topic, _ in present]
        parts = [part for _, part in present]
        stamps = chunk.stamps_ns
        extras = chunk.extras
        occasional = sorted(k for k, extra in extras.items() if extra) if extras else []
        start = 0
        writer, write = self.writer, self.writer.write_raw
        for k in (*occasional, len(stamps)):
            if k > start:
                writer.write_rows(topics, stamps[start:k], [part[start:k] for part in parts])
            if k == len(stamps):
                break
            stamp = int(stamps[k])
            for topic, part in present:
                write(topic, stamp, part[k].tobytes())
            fields = chunk.extra_fields(k)
            for name, topic, encode in self._occasional:
                sample = fields.get(name)
                if sample is not None:
                    write(topic, stamp, encode(sample))
            start = k + 1
