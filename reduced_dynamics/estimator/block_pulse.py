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
The constant-force pulse that best explains a change the block test found.

Done at a detection only (:meth:`.momentum_blocks.MomentumBlocks.locate`): over
the detecting window's span the measured momenta (and centre of mass) are fitted
by a momentum constant before a start, a ramp to an end, constant after, on a
grid of starts and ends; the best fit dates the push and gives the momentum before.
"""

from __future__ import annotations

from typing import Any, NamedTuple, Optional

import numpy as np
from reduced_dynamics.estimator.core import blocks

#: Elements [float64] of the work space MomentumBlocks.locate keeps between detections
#: (8 MiB, allocated at the first): the pulse fits' ramps of windows up to ~0.15 s at 1 kHz.
FIT_SCRATCH = 1 << 20


class BlockDetection(NamedTuple):
    """A momentum change between two blocks of measured momenta."""

    #: the change's start and end [ns] (the gap between the blocks that fits it best)
    start_ns: int
    end_ns: int
    window: float
    statistic: float
    #: the mean measured momentum before the change and its covariance
    mu_before: np.ndarray
    cov_before: np.ndarray


def locate(bank: Any, stamp_ns: int, window: int, floor_ns: Optional[int],
           points: int = 40) -> BlockDetection:
    """
    Return the constant-force pulse that best explains the change the window found.

    Over the window's span (t-3L, t], the measured momenta are fitted by
    y_k = mu0 + J r_k, r_k = clip((t_k - s) / (e - s), 0, 1): constant before s,
    a ramp (a constant force) to e, constant after (e = t: still pushing). The
    start s and end e (on a grid of ``points``) maximise the GLR of J with mu0 a
    nuisance (with the measured centre of mass: :func:`position_rows`); mu0 and
    its covariance are the momentum before. The detecting
    window may hold the push in its after block (a strong push is flagged while it
    goes on), so its gap does not date it. Done at a detection only. ``bank``: the
    :class:`~reduced_dynamics.estimator.momentum_blocks.MomentumBlocks`.
    """
    stamps = bank._stamps[:bank._end]
    lag = int(bank._lags_ns[window])
    lo_ns = stamp_ns - 3 * lag
    if floor_ns is not None:
        lo_ns = max(lo_ns, floor_ns)
    lo = max(int(np.searchsorted(stamps, lo_ns, 'right')) - 1, -1)
    hi = bank._end - 1
    index = np.arange(lo + 1, hi + 1)
    previous = np.concatenate(([lo], index[:-1]))
    info_k = bank._info[index] - np.where(
        (previous < 0)[:, None, None], 0.0, bank._info[np.maximum(previous, 0)])
    score_k = bank._score[index] - np.where(
        (previous < 0)[:, None], 0.0, bank._score[np.maximum(previous, 0)])
    n = bank.n
    times = (stamps[index] - stamps[hi]) * 1e-9
    grid = np.unique(np.linspace(0, len(index) - 1, points).round().astype(int))
    starts, ends = np.meshgrid(times[grid], times[grid], indexing='ij')
    keep = ends > starts
    starts, ends = starts[keep], ends[keep]
    # clip((t - s) / (e - s), 0, 1) and its square, compiled (numpy's bits).
    ramp, ramp_square = work(bank, (len(starts), len(times)), (len(starts), len(times)))
    blocks.pulse_ramps(times, starts, ends, ramp, ramp_square)
    flat_info = info_k.reshape(len(index), n * n)
    # sum r Lambda and sum r Lambda y in one product (BLAS reads the ramps once; each
    # column the bits of its own product: test_multiscale_kernels.py), sum r^2 Lambda.
    both = ramp @ np.hstack((flat_info, score_k))
    cross, score_j = both[:, :n * n], both[:, n * n:]
    square = ramp_square @ flat_info
    # Unknowns (mu0, c0, J): the twists' rows, then the positions' (_position_rows).
    # The (mu0, c0) block and its right-hand side are the same in every fit.
    size = 2 * n + len(bank.linear)
    nuisance, jj = slice(0, size - n), slice(size - n, size)
    block = np.zeros((size - n, size - n))
    rhs_block = np.zeros(size - n)
    block[:n, :n] = flat_info.sum(axis=0).reshape(n, n)
    rhs_block[:n] = score_k.sum(axis=0)
    sums = position_rows(bank, index, previous, times, starts, ends, block, rhs_block)
    normal, rhs = work(bank, (len(starts), size, size), (len(starts), size))
    empty = np.zeros((0, 0))
    # (The sums contiguous, as the empty arrays are: one compiled pulse_normals.)
    blocks.pulse_normals(block, rhs_block, cross, square, score_j,
                         *(tuple(map(np.ascontiguousarray, sums)) if sums is not None
                           else (empty,) * 4), bank.linear,
                         bank.mass, bank.mass ** 2, sums is not None, normal, rhs)
    # The GLR of J with (mu0, c0) a nuisance: J^T S J, S the Schur complement;
    # the nuisance block, the same in every fit, is inverted once (numpy's inv per
    # matrix: the bits of the stacked call).
    try:
        inverse = np.linalg.inv(block)
        couple = normal[:, jj, nuisance]
        schur = normal[:, jj, jj] - couple @ inverse @ couple.transpose(0, 2, 1)
        residual = rhs[:, jj] - (couple @ (inverse @ rhs[:, nuisance, None]))[..., 0]
        impulse = np.linalg.solve(schur, residual[..., None])[..., 0]
    except np.linalg.LinAlgError:
        impulse = residual = np.zeros((len(starts), n))
    values = np.einsum('ij,ij->i', residual, impulse)
    best = int(np.argmax(values))
    try:
        joint = np.linalg.inv(normal[best])
    except np.linalg.LinAlgError:
        joint = np.linalg.pinv(normal[best])
    cov = joint[:n, :n]
    before = (joint @ rhs[best])[:n]
    start = int(stamps[hi] + round(starts[best] * 1e9))
    end = int(stamps[hi] + round(ends[best] * 1e9))
    return BlockDetection(start, end, float(bank.windows[window]), float(values[best]),
                          before, cov + bank._common[max(lo, 0)])


def work(bank: Any, *shapes: tuple) -> list[np.ndarray]:
    """
    Return arrays of ``shapes``, a pulse fit's work space (contents undefined).

    Fresh arrays of a few MB cost mostly their page faults (~0.5 ms per MB here, more
    than filling them): up to FIT_SCRATCH elements in all they are views of one
    buffer kept between detections; larger fits (long windows) allocate as numpy did.
    """
    sizes = [int(np.prod(shape)) for shape in shapes]
    if sum(sizes) > FIT_SCRATCH:
        return [np.empty(shape) for shape in shapes]
    if bank._fit_scratch is None:
        bank._fit_scratch = np.empty(FIT_SCRATCH)
    offsets = np.cumsum([0] + sizes)
    return [bank._fit_scratch[offsets[k]:offsets[k + 1]].reshape(shape)
            for k, shape in enumerate(shapes)]


def position_rows(bank: Any, index: np.ndarray, previous: np.ndarray, times: np.ndarray,
                  starts: np.ndarray, ends: np.ndarray, block: np.ndarray,
                  rhs: np.ndarray) -> Optional[tuple[np.ndarray, ...]]:
    """
    Add the measured centre of mass to the pulse fits of :func:`locate`.

    A pulse from s to e moves c by J R(t) / M, R the ramp's integral (0 before s,
    (t - s)^2 / 2 (e - s) during it, (e - s) / 2 + t - e after), so
    c_k = c0 + t_k E mu0 / M + R_k E J / M (E: the linear coordinates), with the
    sample's information P_k. Adds the (mu0, c0) part, the same in every fit, to
    ``block`` and ``rhs``; returns the per-fit sums blocks.pulse_normals takes
    (sum R P, sum R t P, sum R^2 P, sum R P c), None without positions.
    """
    d = len(bank.linear)
    if not d:
        return None
    s0, _, _, y0, _, counts = bank._positions
    low = np.maximum(previous, 0)
    first = (previous < 0)[:, None, None]
    lam = s0[index] - np.where(first, 0.0, s0[low])
    weighted = y0[index] - np.where(first[..., 0], 0.0, y0[low])
    present = (counts[index] - np.where(previous < 0, 0, counts[low])) > 0
    if present.sum() < 2:
        return None
    lam, weighted, t = lam[present], weighted[present], times[present]
    c = np.linalg.solve(lam, weighted[..., None])[..., 0]
    c = c - c.mean(axis=0)
    # R, R t and R^2 per fit and sample, compiled (numpy's expressions' bits), in
    # the work space locate's ramps used (no longer needed).
    ramp, timed, squared = work(bank, *[(len(starts), len(t))] * 3)
    blocks.position_ramps(t, starts, ends, ramp, timed, squared)
    flat = lam.reshape(len(t), d * d)
    pc = np.einsum('kij,kj->ki', lam, c)
    mass, n = bank.mass, bank.n
    both = ramp @ np.hstack((flat, pc))  # sum R P, sum R P c: one product, as above
    sums = [both[:, :d * d]] + [weights @ flat for weights in (timed, squared)]
    p0, p1, p2 = (((t ** j)[None, :] @ flat).reshape(d, d) for j in range(3))
    select = np.zeros((d, n))
    select[np.arange(d), bank.linear] = 1.0
    st = select.T
    mu0, c0 = slice(0, n), slice(n, n + d)
    block[mu0, mu0] += st @ p2 @ select / mass ** 2
    block[mu0, c0] += st @ p1 / mass
    block[c0, mu0] += p1 @ select / mass
    block[c0, c0] += p0
    rhs[mu0] += (st @ (t @ pc)) / mass
    rhs[c0] += pc.sum(axis=0)
    return (*sums, both[:, d * d:])
