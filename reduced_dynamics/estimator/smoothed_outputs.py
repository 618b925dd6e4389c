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
The smoothed rows as outputs: per row the fields they replace, or CDR columns.

The smoother (:mod:`~reduced_dynamics.estimator.smoother`) stores its rows in
blocks of records; :func:`smoothed_fields` turns them into the
:class:`~.outputs.EstimatorOutput` fields they replace (per sample), and
:class:`SmoothedColumns` into the every-row messages as CDR columns (replay),
stamped and framed as the causal ones.
"""

from __future__ import annotations

from typing import Any, Iterable, Iterator

import numpy as np

from reduced_dynamics.estimator.kernel import UpdateKernel
from reduced_dynamics.messages.cdr_columns import (COLUMN_ENCODERS, stamp_columns,
                                                   vector6_records)
from reduced_dynamics.messages.samples import trusted_sample, TwistSample, WrenchSample


def smoothed_fields(kernel: UpdateKernel, blocks: Iterable[np.ndarray], world: str, base: str,
                    command: bool) -> Iterator[dict[str, Any]]:
    """
    Yield per smoothed row (blocks of :class:`~.smoother.RowStore` records) its fields.

    Each a dict of :class:`EstimatorOutput` fields: ``mu``, ``momentum``,
    ``body_momentum``, ``momentum_rate``, ``drift_twist``, ``momentum_covariance``,
    ``wrench_covariance`` (and ``disturbance`` with a commanded wrench), the
    samples stamped and framed as the causal ones.
    """
    wrench_sample, twist_sample = WrenchSample, TwistSample
    for block in blocks:
        # Contiguous columns: the kernel's row products are then those of the causal run.
        mu = np.ascontiguousarray(block['mu'])
        momentum = kernel.wrenches(mu)
        body = kernel.wrenches(np.ascontiguousarray(block['pi']))
        rate = kernel.wrenches(np.ascontiguousarray(block['rate']))
        drift = kernel.twists(np.ascontiguousarray(block['drift']))
        disturbance = kernel.wrenches(np.ascontiguousarray(block['disturbance'])) \
            if command else None
        mu_cov, w_cov = block['mu_cov'], block['w_cov']
        for k, stamp in enumerate(block['stamp_ns'].tolist()):
            fields = {
                'mu': mu[k],
                'momentum': trusted_sample(wrench_sample, stamp, world,
                                           momentum[k, :3], momentum[k, 3:]),
                'body_momentum': trusted_sample(wrench_sample, stamp, base,
                                                body[k, :3], body[k, 3:]),
                'momentum_rate': trusted_sample(wrench_sample, stamp, world,
                                                rate[k, :3], rate[k, 3:]),
                'drift_twist': trusted_sample(twist_sample, stamp, base,
                                              drift[k, :3], drift[k, 3:]),
                'momentum_covariance': mu_cov[k], 'wrench_covariance': w_cov[k]}
            if disturbance is not None:
                fields['disturbance'] = trusted_sample(
                    wrench_sample, stamp, world, disturbance[k, :3], disturbance[k, 3:])
            yield fields


class SmoothedColumns:
    """
    The smoothed rows (blocks of :class:`~.smoother.RowStore` records) as CDR columns.

    :meth:`take` returns the next n rows whatever the blocks' sizes: ``records``
    (field -> (n, size) uint8, the smoothed fields of :func:`smoothed_fields`
    that are messages, each row the bytes ``cdr.ENCODERS`` gives for that
    field's sample), ``mu``, ``rate`` and ``disturbance`` (n, 6) for the plots.
    """

    def __init__(self, kernel: UpdateKernel, blocks: Iterable[np.ndarray], world: str,
                 base: str, command: bool) -> None:
        """Read ``blocks`` (in order) lazily, as :meth:`take` needs them."""
        self._kernel, self._world, self._base, self._command = kernel, world, base, command
        self._blocks = iter(blocks)
        self._pending: list[dict[str, Any]] = []
        self._offset = 0

    def _convert(self, block: np.ndarray) -> dict[str, Any]:
        kernel, world, base = self._kernel, self._world, self._base
        stamps = block['stamp_ns']
        columns = stamp_columns(stamps)
        if columns is None:  # not a ROS Time: the per-message encoder says why
            bad = next(s for s in stamps.tolist() if not 0 <= s < 2**31 * 10**9)
            COLUMN_ENCODERS[0](trusted_sample(WrenchSample, bad, world, np.zeros(3),
                                              np.zeros(3)))
            raise ValueError(f'ROS Time out of range: {bad} ns')  # (the encoder raised)
        # Contiguous columns: the kernel's row products are then those of the causal run.
        mu = np.ascontiguousarray(block['mu'])
        rate = kernel.wrenches(np.ascontiguousarray(block['rate']))
        out = {'mu': mu, 'rate': rate, 'disturbance': None, 'records': {
            'momentum': vector6_records(columns, world, kernel.wrenches(mu)),
            'body_momentum': vector6_records(columns, base, kernel.wrenches(
                np.ascontiguousarray(block['pi']))),
            'momentum_rate': vector6_records(columns, world, rate),
            'drift_twist': vector6_records(columns, base, kernel.twists(
                np.ascontiguousarray(block['drift'])))}}
        if self._command:
            out['disturbance'] = kernel.wrenches(np.ascontiguousarray(block['disturbance']))
            out['records']['disturbance'] = vector6_records(columns, world,
                                                            out['disturbance'])
        out['count'] = len(stamps)
        return out

    def take(self, count: int) -> dict[str, Any]:
        """Return the next ``count`` rows (ValueError if the blocks end before)."""
        pieces = []
        need = count
        while need:
            if not self._pending:
                block = next(self._blocks, None)
                if block is None:
                    raise ValueError(f'the smoothed rows ended {need} rows early')
                if len(block):
                    self._pending.append(self._convert(block))
                continue
            head = self._pending[0]
            start = self._offset
            stop = min(head['count'], start + need)
            pieces.append((head, start, stop))
            need -= stop - start
            if stop == head['count']:
                self._pending.pop(0)
                self._offset = 0
            else:
                self._offset = stop

        def cut(get: Any) -> Any:
            parts = [get(head)[a:b] for head, a, b in pieces]
            return parts[0] if len(parts) == 1 else np.concatenate(parts)
        first = pieces[0][0]
        return {'mu': cut(lambda h: h['mu']), 'rate': cut(lambda h: h['rate']),
                'disturbance': None if first['disturbance'] is None
                else cut(lambda h: h['disturbance']),
                'records': {name: cut(lambda h, name=name: h['records'][name])
                            for name in first['records']}}
