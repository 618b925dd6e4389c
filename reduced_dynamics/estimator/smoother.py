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
The fixed-interval smoother's memory: recorded filter steps and smoothed rows on disk.

A smoothed replay needs every filter step for the backward (Rauch-Tung-Striebel)
pass: at ~8 KiB a step (three 3n x 3n matrices), an hour at 1 kHz joint states
plus 200 Hz odometry is ~35 GB, so the steps go to files, not lists:

* :class:`StepStore` takes :class:`~.filter.FilterStep` s in time order (the
  filter's ``steps``), writes them a block at a time and reads them back by
  index or a block at a time, last first (:meth:`StepStore.blocks_backward`);
* :func:`smooth_rows` runs the backward pass over it, one compiled call per block
  (:func:`~.core.smoother.backward_block`, the row fields by
  :func:`~.core.smoother.row_fields`), and writes, per output row, what replaces
  the causal estimate (:class:`RowStore`), which is then read forwards a block at
  a time.

Memory stays a few blocks whatever the length; the files live in a directory
(beside the output bag in replay) removed by :meth:`SmootherFiles.close`. Values
round-trip exactly (float64 bytes, poses as rotation and translation).
"""

from __future__ import annotations

import os
import shutil
import tempfile
from typing import Any, Iterator, Optional, Sequence
import weakref

import numpy as np

from reduced_dynamics.estimator.core import smoother as kernels
from reduced_dynamics.estimator.filter import FilterStep
from reduced_dynamics.estimator.outputs import EstimatorOutput
from reduced_dynamics.estimator.smoothed_outputs import smoothed_fields, SmoothedColumns
from reduced_dynamics.geometry.lie_group import BaseGroup

#: Steps per block: ~8 MiB for the paper robot (3n = 18), big enough for large writes.
BLOCK_STEPS = 1024
#: Output rows per block of the smoothed rows.
BLOCK_ROWS = 4096


class SmootherFiles:
    """A private directory for the smoother's files, removed on :meth:`close` (or exit)."""

    def __init__(self, directory: Optional[str] = None, prefix: str = '.smoother-') -> None:
        """Create it inside ``directory`` (default: the system's temporary directory)."""
        self.path = tempfile.mkdtemp(prefix=prefix, dir=directory)
        self._finalizer = weakref.finalize(self, shutil.rmtree, self.path, True)

    def file(self, name: str) -> str:
        """Return the path of ``name`` inside the directory."""
        return os.path.join(self.path, name)

    def close(self) -> None:
        """Remove the directory and its files (idempotent)."""
        self._finalizer()


class StepStore:
    """
    Filter steps on disk: ``append`` in time order, ``len`` and ``store[k]`` to read.

    The list interface :class:`~.filter.MomentumFilter` records into;
    :func:`smooth_rows` reads it a block at a time (:meth:`blocks_backward`);
    ``outputs`` counts the steps that are rows (``FilterStep.output``).
    """

    def __init__(self, files: SmootherFiles, n: int, dim: int, command: bool,
                 name: str = 'steps.bin', block: Optional[int] = None) -> None:
        """Open an empty store for steps of a filter of algebra dimension n, error dim."""
        self.n, self.dim, self.command = n, dim, command
        self.dtype = kernels.step_dtype(n, dim, command)
        #: steps per block (of the file, of :meth:`blocks_backward`)
        self.block = self._block = block = block or BLOCK_STEPS
        self._path = files.file(name)
        self._file = open(self._path, 'w+b')
        self._buffer = np.zeros(block, self.dtype)
        # One view per field: item assignment into an ndarray is several times cheaper
        # than into the fields of a structured record (np.void).
        self._fields = tuple(self._buffer[name] for name in (
            'stamp_ns', 'output', 'has_transition', 'transition', 'pose_pred', 'x_pred',
            'p_pred', 'pose', 'x', 'p', 'locked_inverse'))
        self._command = self._buffer['command'] if command else None
        self._filled = 0  # records in _buffer (not yet written)
        self._written = 0  # records in the file
        self.outputs = 0
        # Two blocks read back (k and k + 1 may straddle a boundary): index -> records.
        self._cache: dict[int, np.ndarray] = {}

    def __len__(self) -> int:
        """Return the number of steps."""
        return self._written + self._filled

    def append(self, step: FilterStep) -> None:
        """Store ``step`` (its arrays are copied)."""
        k = self._filled
        (stamp, output, has_transition, transition, pose_pred, x_pred, p_pred, pose, x, p,
         locked_inverse) = self._fields
        stamp[k] = step.stamp_ns
        output[k] = step.output
        if step.transition is None:
            # (The buffer is reused: a stale transition stays, unread, as before.)
            has_transition[k] = False
        else:
            has_transition[k] = True
            transition[k] = step.transition
        pose_pred[k] = step.pose_pred
        x_pred[k], p_pred[k] = step.x_pred, step.p_pred
        pose[k] = step.pose
        x[k], p[k] = step.x, step.p
        locked_inverse[k] = step.locked_inverse
        if self._command is not None:
            self._command[k] = step.command
        self.outputs += bool(step.output)
        self._filled += 1
        if self._filled == self._block:
            self._flush()

    def _flush(self) -> None:
        self._file.seek(self._written * self.dtype.itemsize)
        self._file.write(self._buffer[:self._filled].tobytes())
        self._written += self._filled
        self._filled = 0

    def _records(self, index: int) -> np.ndarray:
        """Return the block of records holding step ``index`` (read from disk if needed)."""
        block = index // self._block
        records = self._cache.get(block)
        if records is None:
            if len(self._cache) >= 2:
                self._cache.pop(max(self._cache, key=lambda b: abs(b - block)))
            self._file.flush()
            self._file.seek(block * self._block * self.dtype.itemsize)
            count = min(self._block, self._written - block * self._block)
            records = np.fromfile(self._file, self.dtype, count)
            self._cache[block] = records
        return records

    def blocks_backward(self) -> Iterator[np.ndarray]:
        """Yield the steps as blocks of records, the last block first (one in memory)."""
        if self._filled:
            yield self._buffer[:self._filled]
        self._cache.clear()
        self._file.flush()
        for block in range((self._written - 1) // self._block, -1, -1):
            self._file.seek(block * self._block * self.dtype.itemsize)
            yield np.fromfile(self._file, self.dtype,
                              min(self._block, self._written - block * self._block))

    def record(self, index: int) -> np.void:
        """Return the raw record of step ``index`` (negative: from the end)."""
        if index < 0:
            index += len(self)
        if not 0 <= index < len(self):
            raise IndexError(f'step {index} of {len(self)}')
        if index >= self._written:
            return self._buffer[index - self._written]
        return self._records(index)[index % self._block]

    def __getitem__(self, index: int) -> FilterStep:
        """Return step ``index`` as a :class:`~.filter.FilterStep` (copies)."""
        record = self.record(index)
        return FilterStep(
            int(record['stamp_ns']),
            record['transition'].copy() if record['has_transition'] else None,
            record['pose_pred'].copy(), record['x_pred'].copy(), record['p_pred'].copy(),
            record['pose'].copy(),
            record['x'].copy(), record['p'].copy(), record['locked_inverse'].copy(),
            bool(record['output']), record['command'].copy() if self.command else None)

    def close(self) -> None:
        """Close the file (the directory's owner removes it)."""
        self._file.close()
        self._cache.clear()


def _row_dtype(n: int) -> np.dtype:
    """Return the record of one smoothed row (world-frame momentum and wrench, covariances)."""
    return np.dtype([('stamp_ns', '<i8'), ('mu', '<f8', (n,)), ('pi', '<f8', (n,)),
                     ('rate', '<f8', (n,)), ('drift', '<f8', (n,)),
                     ('disturbance', '<f8', (n,)), ('mu_cov', '<f8', (n, n)),
                     ('w_cov', '<f8', (n, n))])


class RowStore:
    """Smoothed output rows on disk: written backwards by index, read forwards in blocks."""

    def __init__(self, files: SmootherFiles, n: int, rows: int,
                 name: str = 'rows.bin', block: Optional[int] = None) -> None:
        """Open a store of ``rows`` rows for an algebra of dimension n."""
        self.dtype = _row_dtype(n)
        self.rows = rows
        self._block = block or BLOCK_ROWS
        self._file = open(files.file(name), 'w+b')
        self._file.truncate(rows * self.dtype.itemsize)

    def write(self, first: int, records: np.ndarray) -> None:
        """Write ``records`` as rows ``first``, ``first + 1``..."""
        self._file.seek(first * self.dtype.itemsize)
        self._file.write(records.tobytes())

    def blocks(self) -> Iterator[np.ndarray]:
        """Yield the rows in order, a block of records at a time."""
        self._file.flush()
        for first in range(0, self.rows, self._block):
            self._file.seek(first * self.dtype.itemsize)
            yield np.fromfile(self._file, self.dtype, min(self._block, self.rows - first))

    def close(self) -> None:
        """Close the file."""
        self._file.close()


def smooth_rows(group: BaseGroup, steps: StepStore, files: SmootherFiles,
                form_rows: np.ndarray) -> RowStore:
    """
    Run the backward pass over ``steps``; return the smoothed rows (one per output step).

    One compiled call per block of the store (:func:`~.core.smoother.backward_block`,
    the smoothed state carried from block to block), then one for the block's rows
    (:func:`~.core.smoother.row_fields`): mu, pi = Ad_g^T mu, the drift twist I^-1 pi,
    the wrench (the disturbance and the total with a commanded wrench) and the
    covariances, as :meth:`Estimator.smooth_outputs` reports them. ``form_rows``: the
    filter's structure constants (the commanded wrench's Jacobian).
    """
    n, dim = steps.n, steps.dim
    basis = np.ascontiguousarray(group.algebra_basis)
    pinv = np.ascontiguousarray(group.algebra_pinv)
    whole = group.is_whole
    rows = RowStore(files, n, steps.outputs)
    carry = (np.zeros((4, 4)), np.zeros(dim - n), np.zeros((dim, dim)))
    size = steps.block
    out = (np.empty((size, 4, 4)), np.empty((size, dim - n)), np.empty((size, dim, dim)))
    no_command = absent_command(n)
    after: Optional[np.ndarray] = None  # the first step of the block after (a copy)
    row = steps.outputs  # rows [row, outputs) are written
    for records in steps.blocks_backward():
        count = len(records)
        restart = ~records['has_transition']
        if after is None:
            following = (False, restart[:1], records['transition'][:1],
                         records['pose_pred'][:1], records['x_pred'][:1], records['p_pred'][:1])
        else:
            following = (True, ~after['has_transition'], after['transition'],
                         after['pose_pred'], after['x_pred'], after['p_pred'])
        pose_out, x_out, p_out = (o[:count] for o in out)
        fields = strided(records)
        kernels.backward_block(restart, fields['transition'], fields['pose_pred'],
                               fields['x_pred'], fields['p_pred'], fields['pose'],
                               fields['x'], fields['p'], *following, *carry, basis, pinv,
                               whole, pose_out, x_out, p_out)
        after = records[:1].copy()
        output = records['output']
        chosen = int(np.count_nonzero(output))
        if not chosen:
            continue
        block = strided(np.zeros(chosen, rows.dtype))
        block['stamp_ns'][:chosen] = records['stamp_ns'][output]
        kernels.row_fields(pose_out, x_out, p_out, fields['locked_inverse'],
                           fields['command'] if steps.command else no_command,
                           fields['output'], steps.command, basis, pinv, whole, form_rows,
                           block['mu'], block['pi'], block['rate'], block['drift'],
                           block['disturbance'], block['mu_cov'], block['w_cov'])
        row -= chosen
        rows.write(row, block[:chosen])
    return rows


def absent_command(n: int) -> np.ndarray:
    """
    Return what :func:`~.core.smoother.row_fields` is given for a filter without a command.

    Never read, but strided like the records' ``command`` field, so that numba compiles one
    variant of the kernel, not a second one for a C-contiguous stand-in.
    """
    return np.zeros((2, 2 * n))[:, :n]


def strided(records: np.ndarray) -> np.ndarray:
    """
    Return ``records``, followed by a blank record when it holds one.

    A lone record's field views are C-contiguous, a longer block's strided, and numba
    compiles :func:`~.core.smoother.backward_block` and :func:`~.core.smoother.row_fields`
    once per layout (~14 s of CPU at level 1, mid-replay, for the block that happens to
    hold one step). The kernels stop at ``restart``'s length and skip the blank record
    (its ``output`` is False), so the results are the same.
    """
    if len(records) != 1:
        return records
    padded = np.zeros(2, records.dtype)
    padded[:1] = records
    return padded


class Smoothing:
    """Fixed-interval smoothing of a whole run (a part of :class:`~.pipeline.Estimator`)."""

    def enable_smoothing(self, files: Optional[SmootherFiles] = None) -> None:
        """
        Record the filter's steps from now on, for :meth:`smoothed_rows` (replay).

        The steps go to disk in ``files`` (default: a temporary directory of the
        estimator's own, removed when it is collected).
        """
        self.record_steps = True
        self.smoother_files = files if files is not None else SmootherFiles()
        self.filter.record = True
        self.step_store = StepStore(self.smoother_files, self.robot.n, self.filter.dim,
                                    self.commanded_wrench)
        if self.fixed_lag is not None:
            self.fixed_lag.downstream = self.step_store  # the fixed-lag smoother passes it on
        else:
            self.filter.steps = self.step_store

    def smoothed_rows(self) -> Iterator[dict[str, Any]]:
        """
        Yield, per output since :meth:`enable_smoothing`, its RTS-smoothed fields.

        :func:`~.smoothed_outputs.smoothed_fields` lists them; the shape state,
        predictions, diagnostics and events stay those of the causal run.
        Memory stays a block of rows whatever the length.
        """
        rows = smooth_rows(self.robot.group, self.step_store, self.smoother_files,
                           self.filter._form_rows)
        try:
            yield from smoothed_fields(self.kernel, rows.blocks(), self.config.world_frame,
                                       self.robot.base_link, self.commanded_wrench)
        finally:
            rows.close()

    def smoothed_columns(self) -> Iterator[SmoothedColumns]:
        """
        Yield once the smoothed rows as :class:`~.smoothed_outputs.SmoothedColumns` (replay).

        The same rows as :meth:`smoothed_rows`, as CDR columns; the files are
        closed when the generator is.
        """
        rows = smooth_rows(self.robot.group, self.step_store, self.smoother_files,
                           self.filter._form_rows)
        try:
            yield SmoothedColumns(self.kernel, rows.blocks(), self.config.world_frame,
                                  self.robot.base_link, self.commanded_wrench)
        finally:
            rows.close()

    def smooth_outputs(self, outputs: Sequence[EstimatorOutput]) -> None:
        """
        Replace the filtered estimates of ``outputs`` by the RTS-smoothed ones, in place.

        ``outputs`` are all outputs since :meth:`enable_smoothing`, in order (one
        recorded filter row each); :meth:`smoothed_rows` says what changes.
        """
        recorded = self.step_store.outputs
        if recorded != len(outputs):
            raise ValueError(f'{len(outputs)} outputs for {recorded} recorded filter rows')
        for output, fields in zip(outputs, self.smoothed_rows()):
            for name, value in fields.items():
                setattr(output, name, value)
