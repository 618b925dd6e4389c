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
The block test's arithmetic, compiled (numba): block means of measured momenta.

:class:`~reduced_dynamics.estimator.momentum_blocks.MomentumBlocks` keeps prefix sums
of every sample's information; a block (lo, hi] of samples is a difference of
two rows. Two kinds of sample enter a block's estimate of the momentum:

- the momenta the measured twists give (information C^-1, score C^-1 y);
- the measured centre of mass c_k (base pose and shape), which moves on a line
  at p / M without an external force (the linear momentum p = M c_dot, whatever
  the arm does). A weighted line fit over the block gives the slope b with
  information S2 - S1 S0^-1 S1 (S_j = sum Lambda_k t_k^j); M b joins the twists'
  estimate of the linear part. Positions pin a slow velocity far better than
  noisy velocities do: a 3 s block of 1 mm positions at 100 Hz gives the velocity
  to 0.07 mm/s, its 0.01 m/s twists to 0.6 mm/s (docs/multiscale_events.md).

Prefix rows: ``info`` (k, n, n), ``score`` (k, n); the positions' ``s0``, ``s1``,
``s2`` (k, d, d), ``y0`` (sum Lambda c), ``t1`` (sum Lambda t c) (k, d) and
``counts`` (k,) of position samples; ``linear`` (d,) the algebra coordinates of
the linear momentum. Index -1 is the empty prefix.
"""

import numpy as np
from numba import njit


@njit(cache=True)
def _between(prefix: np.ndarray, lo: int, hi: int) -> np.ndarray:
    """Return the sum over (lo, hi] of the samples whose prefix sums are ``prefix``."""
    if lo < 0:
        return prefix[hi].copy()
    return prefix[hi] - prefix[lo]


@njit(cache=True)
def block_information(info: np.ndarray, score: np.ndarray, s0: np.ndarray, s1: np.ndarray,
                      s2: np.ndarray, y0: np.ndarray, t1: np.ndarray, counts: np.ndarray,
                      lo: int, hi: int, mass: float,
                      linear: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return the information and score of the momentum over the block (lo, hi]."""
    lam = _between(info, lo, hi)
    sc = _between(score, lo, hi)
    d = linear.shape[0]
    if d == 0 or mass <= 0.0:
        return lam, sc
    count = counts[hi] - (counts[lo] if lo >= 0 else 0)
    if count < 2:
        return lam, sc
    a0 = _between(s0, lo, hi)
    a1 = _between(s1, lo, hi)
    a2 = _between(s2, lo, hi)
    b0 = _between(y0, lo, hi)
    b1 = _between(t1, lo, hi)
    inv0 = np.linalg.inv(a0)
    # The slope's information (Schur complement of the intercept) and its score.
    schur = a2 - a1 @ inv0 @ a1
    residual = b1 - a1 @ (inv0 @ b0)
    for i in range(d):
        sc[linear[i]] += residual[i] / mass
        for j in range(d):
            lam[linear[i], linear[j]] += 0.5 * (schur[i, j] + schur[j, i]) / (mass * mass)
    return lam, sc


@njit(cache=True)
def block_mean(info: np.ndarray, score: np.ndarray, s0: np.ndarray, s1: np.ndarray,
               s2: np.ndarray, y0: np.ndarray, t1: np.ndarray, counts: np.ndarray,
               lo: int, hi: int, mass: float,
               linear: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return the block's mean momentum and its covariance (the inverse information)."""
    lam, sc = block_information(info, score, s0, s1, s2, y0, t1, counts, lo, hi, mass, linear)
    cov = np.linalg.inv(lam)
    return cov @ sc, 0.5 * (cov + cov.T)


@njit(cache=True)
def window_statistics(info: np.ndarray, score: np.ndarray, s0: np.ndarray, s1: np.ndarray,
                      s2: np.ndarray, y0: np.ndarray, t1: np.ndarray, counts: np.ndarray,
                      common: np.ndarray, rows: np.ndarray, mass: float,
                      linear: np.ndarray) -> np.ndarray:
    """
    Return T_L per window: rows (k, 4) bound the before (r0, r1] and after (r2, r3] blocks.

    T_L = (m_after - m_before)^T (V_after + V_before)^-1 (m_after - m_before) (M2);
    each block keeps the slow common error of its last sample whole.
    """
    out = np.zeros(rows.shape[0])
    for w in range(rows.shape[0]):
        before, cov_before = block_mean(info, score, s0, s1, s2, y0, t1, counts,
                                        rows[w, 0], rows[w, 1], mass, linear)
        after, cov_after = block_mean(info, score, s0, s1, s2, y0, t1, counts,
                                      rows[w, 2], rows[w, 3], mass, linear)
        v = cov_before + common[rows[w, 1]] + cov_after + common[rows[w, 3]]
        d = after - before
        out[w] = d @ np.linalg.solve(v, d)
    return out


@njit(cache=True)
def accumulate(info: np.ndarray, score: np.ndarray, k: int, sample_info: np.ndarray,
               mu: np.ndarray) -> None:
    """Write prefix row ``k`` of the twists' information and score from row k - 1."""
    if k:
        info[k] = info[k - 1] + sample_info
        score[k] = score[k - 1] + sample_info @ mu
    else:
        info[k] = sample_info
        score[k] = sample_info @ mu


@njit(cache=True)
def accumulate_position(s0: np.ndarray, s1: np.ndarray, s2: np.ndarray, y0: np.ndarray,
                        t1: np.ndarray, counts: np.ndarray, k: int, lam: np.ndarray,
                        t: float, c: np.ndarray, present: bool) -> None:
    """Write prefix row ``k`` of the positions' moments (``present`` False: none here)."""
    if k:
        s0[k] = s0[k - 1]
        s1[k] = s1[k - 1]
        s2[k] = s2[k - 1]
        y0[k] = y0[k - 1]
        t1[k] = t1[k - 1]
        counts[k] = counts[k - 1]
    else:
        s0[k] = 0.0
        s1[k] = 0.0
        s2[k] = 0.0
        y0[k] = 0.0
        t1[k] = 0.0
        counts[k] = 0
    if present:
        s0[k] += lam
        s1[k] += lam * t
        s2[k] += lam * (t * t)
        weighted = lam @ c
        y0[k] += weighted
        t1[k] += weighted * t
        counts[k] += 1


@njit(cache=True)
def bank_statistics(info: np.ndarray, score: np.ndarray, s0: np.ndarray, s1: np.ndarray,
                    s2: np.ndarray, y0: np.ndarray, t1: np.ndarray, counts: np.ndarray,
                    common: np.ndarray, stamps: np.ndarray, end: int, lags: np.ndarray,
                    stamp_ns: int, first: int, mass: float,
                    linear: np.ndarray) -> tuple[int, np.ndarray]:
    """
    Return how many windows are covered and T_L per window (0 where not covered).

    Window L's blocks: before (t-3L, t-2L], after (t-L, t] (prefix rows from the
    stamps up to ``end``); covered when both hold samples and the before block
    starts at or after ``first`` (the data's start or the last event's end).
    """
    count = lags.shape[0]
    index = np.empty((count, 4), dtype=np.int64)
    covered = np.zeros(count, dtype=np.bool_)
    found = 0
    for w in range(count):
        for j in range(4):
            index[w, j] = np.searchsorted(stamps[:end], stamp_ns - lags[w] * (3 - j),
                                          'right') - 1
        covered[w] = stamp_ns - lags[w] * 3 >= first and index[w, 1] > index[w, 0] and \
            index[w, 3] > index[w, 2]
        found += covered[w]
    out = np.zeros(count)
    if not found:
        return 0, out
    rows = np.empty((found, 4), dtype=np.int64)
    k = 0
    for w in range(count):
        if covered[w]:
            rows[k] = index[w]
            k += 1
    values = window_statistics(info, score, s0, s1, s2, y0, t1, counts, common, rows, mass,
                               linear)
    k = 0
    for w in range(count):
        if covered[w]:
            out[w] = values[k]
            k += 1
    return found, out


@njit(cache=True)
def learn_excess(raw: np.ndarray, mu: np.ndarray, cov: np.ndarray, last_mu: np.ndarray,
                 last_cov: np.ndarray, divisor: float) -> None:
    """Move ``raw`` towards 1/2 (d d^T - C_k - C_k-1), d = mu - last_mu (in place)."""
    n = mu.shape[0]
    for i in range(n):
        di = mu[i] - last_mu[i]
        for j in range(n):
            sample = 0.5 * (di * (mu[j] - last_mu[j]) - cov[i, j] - last_cov[i, j])
            raw[i, j] += (sample - raw[i, j]) / divisor


@njit(cache=True)
def sample_information(cov: np.ndarray, excess: np.ndarray,
                       position_cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return (C + excess)^-1 and the position's information (an empty one: none)."""
    n = cov.shape[0]
    # solve(A, I): what numpy's inv computes (LAPACK gesv), bit for bit; in C order, as
    # numpy returns it (a product with an F-ordered matrix sums in another order).
    info = np.ascontiguousarray(np.linalg.solve(cov + excess, np.eye(n)))
    d = position_cov.shape[0]
    if d == 0:
        return info, np.zeros((0, 0))
    return info, np.ascontiguousarray(np.linalg.solve(position_cov, np.eye(d)))


@njit(cache=True)
def add_sample(raw: np.ndarray, mu: np.ndarray, cov: np.ndarray, last_mu: np.ndarray,
               last_cov: np.ndarray, divisor: float, excess: np.ndarray,
               position_cov: np.ndarray, info: np.ndarray, score: np.ndarray,
               common_ring: np.ndarray, common: np.ndarray, stamps: np.ndarray,
               stamp_ns: int, k: int, s0: np.ndarray, s1: np.ndarray, s2: np.ndarray,
               y0: np.ndarray, t1: np.ndarray, counts: np.ndarray, t: float, c: np.ndarray,
               with_positions: bool) -> None:
    """
    Take one measured momentum into prefix row ``k`` (k > 0): the calls it replaces in turn.

    :func:`learn_excess`, :func:`sample_information`, the sample's stamp and common
    covariance, :func:`accumulate` and (``with_positions``: a position present)
    :func:`accumulate_position`. A singular covariance raises after the excess was
    learnt and before the row is written, as the separate calls did.
    """
    learn_excess(raw, mu, cov, last_mu, last_cov, divisor)
    sample_info, lam = sample_information(cov, excess, position_cov)
    stamps[k] = stamp_ns
    common_ring[k] = common
    accumulate(info, score, k, sample_info, mu)
    if with_positions:
        # (with_positions, True here, not a constant: one compiled accumulate_position.)
        accumulate_position(s0, s1, s2, y0, t1, counts, k, lam, t, c, with_positions)


@njit(cache=True)
def pulse_ramps(times: np.ndarray, starts: np.ndarray, ends: np.ndarray, ramp: np.ndarray,
                square: np.ndarray) -> None:
    """
    Write the ramps r (fits x samples) of MomentumBlocks.locate's pulse fits, and r^2.

    r = clip((t - s) / (e - s), 0, 1), numpy's expression element by element in one
    pass into the caller's arrays (numpy made ~5 passes over fresh (fits, samples)
    arrays, mostly page faults): the same IEEE operations in the same order, so the
    bits are numpy's (test_multiscale_kernels.py).
    """
    for i in range(starts.shape[0]):
        start, span = starts[i], ends[i] - starts[i]
        for k in range(times.shape[0]):
            r = (times[k] - start) / span
            # np.clip(r, 0, 1): NaN kept, -0.0 made 0.0, as numpy's max then min.
            if r <= 0.0:
                r = 0.0
            if r >= 1.0:
                r = 1.0
            ramp[i, k] = r
            square[i, k] = r * r


@njit(cache=True)
def position_ramps(times: np.ndarray, starts: np.ndarray, ends: np.ndarray, ramp: np.ndarray,
                   timed: np.ndarray, square: np.ndarray) -> None:
    """
    Write the ramp integrals R (fits x samples) of block_pulse.position_rows, R t, R^2.

    R = clip(t - s, 0, e - s)^2 / (2 (e - s)) + max(t - e, 0), numpy's expression
    element by element in one pass (the same operations in the same order).
    """
    for i in range(starts.shape[0]):
        start, end = starts[i], ends[i]
        span = end - start
        twice = 2.0 * span
        for k in range(times.shape[0]):
            t = times[k]
            during = t - start
            if during <= 0.0:  # np.clip(during, 0, span), as above
                during = 0.0
            if during >= span:
                during = span
            after = t - end
            if after < 0.0:  # np.maximum(after, 0): NaN and -0.0 kept
                after = 0.0
            r = during * during / twice + after
            ramp[i, k] = r
            timed[i, k] = r * t
            square[i, k] = r * r


@njit(cache=True)
def _selected(x: float, mapped: bool, scale: float) -> float:
    """Return an entry of E^T X E / scale as numpy's products give it (E selects coordinates)."""
    # A 0/1 selection product is exact: the entry plus +0.0 (a -0.0 turns +0.0) where
    # selected, +0.0 elsewhere; then divided as numpy divided it.
    return ((x + 0.0) if mapped else 0.0) / scale


@njit(cache=True)
def pulse_normals(block: np.ndarray, rhs_block: np.ndarray, cross: np.ndarray,
                  square: np.ndarray, score: np.ndarray, moment: np.ndarray,
                  timed: np.ndarray, moment2: np.ndarray, pulled: np.ndarray,
                  linear: np.ndarray, mass: float, mass2: float, with_positions: bool,
                  normal: np.ndarray, rhs: np.ndarray) -> None:
    """
    Write MomentumBlocks.locate's normal equations, one per pulse fit, as numpy wrote them.

    Unknowns (mu0, c0, J): ``block`` and ``rhs_block`` are the (mu0, c0) part, the
    same in every fit; per fit f the twists' sums ``cross`` (sum r Lambda), ``square``
    (sum r^2 Lambda) (flat n x n) and ``score`` (sum r Lambda y), and with positions
    the ramp integrals' sums ``moment`` (sum R P), ``timed`` (sum R t P), ``moment2``
    (sum R^2 P) (flat d x d) and ``pulled`` (sum R P c). Each entry is the sum numpy's
    assignments and in-place additions formed, in their order (the same bits).
    """
    n = score.shape[1]
    d = linear.shape[0]
    m = block.shape[0]
    jj = n + d
    where = np.full(n, -1, dtype=np.int64)  # the linear coordinate's index, -1: none
    for i in range(d):
        where[linear[i]] = i
    for f in range(cross.shape[0]):
        for a in range(m):
            for b in range(m):
                normal[f, a, b] = block[a, b]
            rhs[f, a] = rhs_block[a]
        for a in range(n):
            ia = where[a]
            for b in range(n):
                ib = where[b]
                up = cross[f, b * n + a]  # the (mu0, J) block: cross transposed
                low = cross[f, a * n + b]
                both = square[f, a * n + b]
                if with_positions:
                    mapped = ia >= 0 and ib >= 0
                    k = ia * d + ib
                    coupling = _selected(timed[f, k] if mapped else 0.0, mapped, mass2)
                    up += coupling
                    low += coupling
                    both += _selected(moment2[f, k] if mapped else 0.0, mapped, mass2)
                normal[f, a, jj + b] = up
                normal[f, jj + a, b] = low
                normal[f, jj + a, jj + b] = both
            value = score[f, a]
            if with_positions:
                value += _selected(pulled[f, ia] if ia >= 0 else 0.0, ia >= 0, mass)
            rhs[f, jj + a] = value
            for c in range(d):
                column = row = 0.0
                if with_positions:
                    column += _selected(moment[f, c * d + ia] if ia >= 0 else 0.0, ia >= 0,
                                        mass)
                    row += _selected(moment[f, ia * d + c] if ia >= 0 else 0.0, ia >= 0, mass)
                normal[f, n + c, jj + a] = column
                normal[f, jj + a, n + c] = row
