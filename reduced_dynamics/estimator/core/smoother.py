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
The Rauch-Tung-Striebel smoother's backward pass (error-state form), compiled, structured.

``C_k = P_k Phi_{k+1}^T (P^-_{k+1})^-1``; the smoothed correction at k is
``C_k (x^s_{k+1} - x^-_{k+1})`` with the pose difference taken as
``log(g^-_{k+1}^-1 g^s_{k+1})``; ``P^s_k = P_k + C_k (P^s_{k+1} - P^-_{k+1}) C_k^T``.
A step without a transition (a restart) does not depend on the one before: the
pass starts afresh from its filtered state.

The step is structured (docs/structured_step.md, "The smoother's backward step"):
(P Phi^T)^T skips Phi's zeros (the transitions of core/kernels.py are the identity
but for their pose rows and the mu-w chain: 3n, the mu rows [0 1 dt]; 5n, the mu
rows), G = C^T comes from one Cholesky factor of P^- (two triangular solves; LU,
then a pseudo-inverse, only if P^- is not positive definite), and P^s is the
symmetric part of P + G^T (D G) (these two d^3 products by BLAS). The other loops
run as row updates (axpy) on contiguous work arrays, allocated once per block of
steps (:func:`backward_block`), which runs a whole block of the disk-backed store
(estimator/smoother.py) per call. The dense step it replaced is
core/smoother_reference.py, equal to 1e-9 (test/test_structured_smoother.py).

:func:`smooth_arrays` takes the steps as stacked arrays and writes the smoothed
states into output arrays of the same shapes; :func:`smooth` is the
list-of-:class:`~.state.FilterStep` form; :func:`row_fields` turns smoothed states
into an output row's fields.
"""

from __future__ import annotations

import math
from typing import Optional, Sequence

import numpy as np
from numba import njit
import pinocchio as pin

from reduced_dynamics.estimator.core.kernels import form
from reduced_dynamics.estimator.core.lie import adjoint, compose, group_exp, group_log, inverse
from reduced_dynamics.estimator.core.state import FilterState, FilterStep
from reduced_dynamics.geometry.lie_group import BaseGroup


@njit(cache=True)
def workspace(dim: int) -> tuple:
    """Return the work arrays of :func:`step` for a filter of error dimension ``dim``."""
    return (np.empty((dim, dim)), np.empty((dim, dim)), np.empty((dim, dim)),
            np.empty((dim, dim)), np.empty((dim, dim)), np.empty(dim), np.empty(dim),
            np.empty((dim, dim), np.int64), np.empty(dim, np.int64))


# The loops below run along rows (an axpy per row, contiguous): the compiler vectorises
# those; the dot-product form (a sum per element) would be a chain of dependent adds.
@njit(cache=True)
def _cross_t(p: np.ndarray, phi: np.ndarray, pt: np.ndarray, index: np.ndarray,
             count: np.ndarray, out: np.ndarray) -> None:
    """Write (P Phi^T)^T = Phi P^T into ``out`` over Phi's non-zero entries (found per row)."""
    dim = p.shape[0]
    for i in range(dim):
        for k in range(dim):
            pt[k, i] = p[i, k]
    for j in range(dim):
        c = 0
        for k in range(dim):
            if phi[j, k] != 0.0:
                index[j, c] = k
                c += 1
        count[j] = c
    for j in range(dim):
        for i in range(dim):
            out[j, i] = 0.0
        for t in range(count[j]):
            k = index[j, t]
            v = phi[j, k]
            for i in range(dim):
                out[j, i] += v * pt[k, i]


@njit(cache=True)
def _cholesky_upper(a: np.ndarray, u: np.ndarray) -> bool:
    """Write U = L^T of A = L L^T into ``u``'s upper triangle (A's read); False if not PD."""
    m = a.shape[0]
    for i in range(m):
        for j in range(i, m):
            u[i, j] = a[i, j]
    for j in range(m):
        d = u[j, j]
        if not d > 0.0:
            return False
        root = math.sqrt(d)
        u[j, j] = root
        for k in range(j + 1, m):
            u[j, k] /= root
        for i in range(j + 1, m):
            v = u[j, i]
            for k in range(i, m):
                u[i, k] -= v * u[j, k]
    return True


@njit(cache=True)
def _solve_in_place(u: np.ndarray, b: np.ndarray) -> None:
    """Overwrite B by A^-1 B (A = U^T U): U^T Y = B, then U X = Y, a row at a time."""
    m, cols = b.shape
    for i in range(m):
        for k in range(i):
            v = u[k, i]
            for c in range(cols):
                b[i, c] -= v * b[k, c]
        d = u[i, i]
        for c in range(cols):
            b[i, c] /= d
    for i in range(m - 1, -1, -1):
        for k in range(i + 1, m):
            v = u[i, k]
            for c in range(cols):
                b[i, c] -= v * b[k, c]
        d = u[i, i]
        for c in range(cols):
            b[i, c] /= d


@njit(cache=True)
def _fallback_gain_t(cross_t: np.ndarray, p_pred: np.ndarray) -> np.ndarray:
    """Return (P^-)^-1 cross^T for a P^- that is not positive definite (LU, else pinv)."""
    a = np.ascontiguousarray(p_pred)
    try:
        return np.linalg.solve(a, cross_t)
    except Exception:  # exactly singular (numba raises a plain exception type)
        return np.linalg.pinv(a).T @ cross_t


@njit(cache=True)
def gain_t_into(p: np.ndarray, transition: np.ndarray, p_pred: np.ndarray,
                work: tuple) -> np.ndarray:
    """
    Write G = C^T = (P^-)^-1 Phi P^T into the workspace and return it (C = P Phi^T (P^-)^-1).

    P^- is symmetric (the filter symmetrises it), so C^T solves P^- G = (P Phi^T)^T.
    """
    pt, gain_t, upper = work[0], work[1], work[2]
    _cross_t(p, transition, pt, work[7], work[8], gain_t)
    if _cholesky_upper(p_pred, upper):
        _solve_in_place(upper, gain_t)
    else:
        gain_t[:, :] = _fallback_gain_t(gain_t.copy(), p_pred)
    return gain_t


@njit(cache=True)
def step(g_k: np.ndarray, x_k: np.ndarray, p_k: np.ndarray, transition: np.ndarray,
         pose_pred: np.ndarray, x_pred: np.ndarray, p_pred: np.ndarray, g_s: np.ndarray,
         x_s: np.ndarray, p_s: np.ndarray, basis: np.ndarray, pinv: np.ndarray, whole: bool,
         work: tuple) -> None:
    """
    Smooth step k in place: (g_s, x_s, P_s) from step k + 1's smoothed state to step k's.

    ``g_k``, ``x_k``, ``p_k``: step k's filtered state; ``transition``, ``pose_pred``,
    ``x_pred``, ``p_pred``: step k + 1's; ``work``: :func:`workspace`.
    """
    dim = p_k.shape[0]
    n = dim - x_k.shape[0]
    gain_t = gain_t_into(p_k, transition, p_pred, work)
    # The transpose's and the factor's arrays are free again.
    delta, product, outer, diff, dx = work[0], work[2], work[3], work[5], work[6]
    log = group_log(compose(inverse(pose_pred), g_s), pinv, whole)
    for i in range(n):
        diff[i] = log[i]
    for i in range(dim - n):
        diff[n + i] = x_s[i] - x_pred[i]
    for i in range(dim):
        dx[i] = 0.0
    for k in range(dim):
        v = diff[k]
        for i in range(dim):
            dx[i] += v * gain_t[k, i]
    g_s[:, :] = compose(g_k, group_exp(dx[:n], basis, whole))
    for i in range(dim - n):
        x_s[i] = x_k[i] + dx[n + i]
    # P^s = P + C D C^T = P + G^T (D G), D = P^s_{k+1} - P^-_{k+1}.
    for i in range(dim):
        for j in range(dim):
            delta[i, j] = p_s[i, j] - p_pred[i, j]
    # The two d^3 products by BLAS into the work arrays (half the loops' time, measured).
    np.dot(delta, gain_t, product)
    np.dot(gain_t.T, product, outer)
    for i in range(dim):
        for j in range(i, dim):
            v = 0.5 * (p_k[i, j] + p_k[j, i]) + 0.5 * (outer[i, j] + outer[j, i])
            p_s[i, j] = v
            p_s[j, i] = v


@njit(cache=True)
def backward_step(g_k: np.ndarray, x_k: np.ndarray, p_k: np.ndarray, transition: np.ndarray,
                  pose_pred: np.ndarray, x_pred: np.ndarray, p_pred: np.ndarray,
                  g_s: np.ndarray, x_s: np.ndarray, p_s: np.ndarray, basis: np.ndarray,
                  pinv: np.ndarray, whole: bool) -> tuple:
    """Return :func:`step`'s smoothed (pose, x, P) as new arrays (the reference's signature)."""
    g, x, p = g_s.copy(), x_s.copy(), p_s.copy()
    # (Layout 'A', as backward_block calls step: one compiled step.)
    step(g_k[::1], x_k[::1], p_k[::1], transition[::1], pose_pred[::1], x_pred[::1],
         p_pred[::1], g, x, p, basis, pinv, whole, workspace(p_k.shape[0]))
    return g, x, p


@njit(cache=True)
def backward_block(restart: np.ndarray, transitions: np.ndarray, pose_pred: np.ndarray,
                   x_pred: np.ndarray, p_pred: np.ndarray, pose: np.ndarray, x: np.ndarray,
                   p: np.ndarray, after: bool, after_restart: np.ndarray,
                   after_transitions: np.ndarray, after_pose_pred: np.ndarray,
                   after_x_pred: np.ndarray, after_p_pred: np.ndarray, g_s: np.ndarray,
                   x_s: np.ndarray, p_s: np.ndarray, basis: np.ndarray, pinv: np.ndarray,
                   whole: bool, pose_out: np.ndarray, x_out: np.ndarray,
                   p_out: np.ndarray) -> None:
    """
    Run the backward pass over a block of K stacked steps, writing their smoothed states.

    ``restart[k]``: step k has no transition (``transitions[k]`` is then unused).
    Shapes: transitions, p_pred, p, p_out (K, d, d); pose_pred, pose, pose_out
    (K, 4, 4); x_pred, x, x_out (K, d - n). ``after``: a step follows the block, its
    ``after_*`` (arrays of one step) and its smoothed state in (g_s, x_s, p_s); else
    the block ends the run. (g_s, x_s, p_s) end as the block's first smoothed state,
    ready for the block before.
    """
    count = restart.shape[0]
    work = workspace(p.shape[1])
    for k in range(count - 1, -1, -1):
        last = k == count - 1
        if (last and (not after or after_restart[0])) or (not last and restart[k + 1]):
            g_s[:, :] = pose[k]
            x_s[:] = x[k]
            p_s[:, :] = p[k]
        elif last:
            # ([::1]: every step call of any block sees layout 'A', one compiled step;
            # the record fields of a block of several steps are strided, of one step not.)
            step(pose[k][::1], x[k][::1], p[k][::1], after_transitions[0][::1],
                 after_pose_pred[0][::1], after_x_pred[0][::1], after_p_pred[0][::1], g_s, x_s,
                 p_s, basis, pinv, whole, work)
        else:
            step(pose[k][::1], x[k][::1], p[k][::1], transitions[k + 1][::1],
                 pose_pred[k + 1][::1], x_pred[k + 1][::1], p_pred[k + 1][::1], g_s, x_s, p_s,
                 basis, pinv, whole, work)
        pose_out[k] = g_s
        x_out[k] = x_s
        p_out[k] = p_s


@njit(cache=True)
def smoother_gain(p: np.ndarray, transition: np.ndarray, p_pred: np.ndarray) -> np.ndarray:
    """Return the gain C_k of :func:`step` (step k's P, step k + 1's Phi and P^-)."""
    # (Layout 'A', as step calls gain_t_into: one compiled gain_t_into.)
    return np.ascontiguousarray(gain_t_into(p[::1], transition[::1], p_pred[::1],
                                            workspace(p.shape[0])).T)


@njit(cache=True)
def backward_mean(restart: np.ndarray, gains: np.ndarray, pose_pred: np.ndarray,
                  x_pred: np.ndarray, pose: np.ndarray, x: np.ndarray, basis: np.ndarray,
                  pinv: np.ndarray, whole: bool, pose_out: np.ndarray,
                  x_out: np.ndarray) -> None:
    """
    Run the mean part of :func:`backward_block` over K stacked steps, the gains given.

    ``gains[k]``: C_k (:func:`smoother_gain`), which depends on the filtered steps
    alone, so a caller smoothing the same steps again (the fixed-lag smoother)
    computes it once. The smoothed means are :func:`step`'s, the same arithmetic;
    no covariance is propagated.
    """
    count = restart.shape[0]
    d = gains.shape[1]
    n = d - x.shape[1]
    pose_out[count - 1] = pose[count - 1]
    x_out[count - 1] = x[count - 1]
    g_s, x_s = pose[count - 1].copy(), x[count - 1].copy()
    diff = np.empty(d)
    dx = np.empty(d)
    for k in range(count - 2, -1, -1):
        if restart[k + 1]:
            g_s, x_s = pose[k].copy(), x[k].copy()
        else:
            log = group_log(compose(inverse(pose_pred[k + 1]), g_s), pinv, whole)
            for i in range(n):
                diff[i] = log[i]
            for i in range(d - n):
                diff[n + i] = x_s[i] - x_pred[k + 1, i]
            for i in range(d):
                acc = 0.0
                for j in range(d):
                    acc += gains[k, i, j] * diff[j]
                dx[i] = acc
            g_s = compose(pose[k], group_exp(dx[:n], basis, whole))
            x_s = x[k] + dx[n:]
        pose_out[k] = g_s
        x_out[k] = x_s


@njit(cache=True)
def row_fields(pose: np.ndarray, x: np.ndarray, p: np.ndarray, locked_inverse: np.ndarray,
               command: np.ndarray, output: np.ndarray, commanded: bool, basis: np.ndarray,
               pinv: np.ndarray, whole: bool, form_rows: np.ndarray, mu: np.ndarray,
               pi: np.ndarray, rate: np.ndarray, drift: np.ndarray, disturbance: np.ndarray,
               mu_cov: np.ndarray, w_cov: np.ndarray) -> None:
    """
    Write the fields of the smoothed states k with ``output[k]``, in order, one row each.

    mu, pi = Ad_g^T mu, the drift twist I^-1 pi (step k's ``locked_inverse``), the
    covariance of mu and the wrench with its covariance: w and P_ww, or with a
    commanded wrench the total w + Ad_{g^-1}^T (k o u + b) (``command[k]`` = u) and
    J P J^T, the disturbance w beside it (as ``MomentumFilter._total``).
    """
    n = locked_inverse.shape[1]
    row = 0
    for k in range(output.shape[0]):
        if not output[k]:
            continue
        g = pose[k]
        ad = adjoint(g, basis, pinv, whole)
        for i in range(n):
            mu[row, i] = x[k, i]
        for i in range(n):
            acc = 0.0
            for j in range(n):
                acc += ad[j, i] * x[k, j]
            pi[row, i] = acc
        for i in range(n):
            acc = 0.0
            for j in range(n):
                acc += locked_inverse[k, i, j] * pi[row, j]
            drift[row, i] = acc
        for i in range(n):
            for j in range(n):
                mu_cov[row, i, j] = p[k, n + i, n + j]
        if not commanded:
            for i in range(n):
                rate[row, i] = x[k, n + i]
                for j in range(n):
                    w_cov[row, i, j] = p[k, 2 * n + i, 2 * n + j]
        else:
            to_world = adjoint(inverse(g), basis, pinv, whole).T
            u = command[k]
            c = x[k, 2 * n:3 * n] * u + x[k, 3 * n:]
            jac = np.zeros((n, 5 * n))
            jac[:, :n] = to_world @ form(form_rows, c)
            for i in range(n):
                jac[i, 2 * n + i] = 1.0
                for j in range(n):
                    jac[i, 3 * n + j] = to_world[i, j] * u[j]
                    jac[i, 4 * n + j] = to_world[i, j]
            cov = jac @ np.ascontiguousarray(p[k]) @ jac.T
            total = to_world @ c
            for i in range(n):
                rate[row, i] = x[k, n + i] + total[i]
                disturbance[row, i] = x[k, n + i]
                for j in range(n):
                    w_cov[row, i, j] = 0.5 * (cov[i, j] + cov[j, i])
        row += 1


def step_dtype(n: int, dim: int, command: bool) -> np.dtype:
    """
    Return the record of one step: stamp, flags, matrices and vectors (float64).

    Aligned (the flags padded): :func:`backward_block` reads the fields in place, as
    the replay's store (estimator/smoother.py) and :func:`smooth` give them, so both
    run the one compiled variant of the pass (numba compiles one per array layout).
    """
    fields = [('stamp_ns', '<i8'), ('has_transition', '?'), ('output', '?'),
              ('transition', '<f8', (dim, dim)),
              ('pose_pred', '<f8', (4, 4)),
              ('x_pred', '<f8', (dim - n,)), ('p_pred', '<f8', (dim, dim)),
              ('pose', '<f8', (4, 4)),
              ('x', '<f8', (dim - n,)), ('p', '<f8', (dim, dim)),
              ('locked_inverse', '<f8', (n, n))]
    if command:
        fields.append(('command', '<f8', (n,)))
    return np.dtype(fields, align=True)


def smooth_arrays(group: BaseGroup, restart: np.ndarray, transitions: np.ndarray,
                  pose_pred: np.ndarray, x_pred: np.ndarray, p_pred: np.ndarray,
                  pose: np.ndarray, x: np.ndarray, p: np.ndarray,
                  out: Optional[tuple] = None) -> tuple:
    """
    Return the smoothed (poses, x, P) of stacked steps (see :func:`backward_block`).

    ``out``: (pose, x, P) arrays to write into (e.g. memmaps); default new arrays.
    """
    if out is None:
        out = (np.empty_like(pose), np.empty_like(x), np.empty_like(p))
    if len(restart):
        dim = p.shape[1]
        carry = (np.zeros((4, 4)), np.zeros(x.shape[1]), np.zeros((dim, dim)))
        restart = np.asarray(restart, dtype=np.bool_)
        backward_block(restart, transitions, pose_pred, x_pred, p_pred, pose, x, p, False,
                       restart[:1], transitions[:1], pose_pred[:1], x_pred[:1], p_pred[:1],
                       *carry, np.ascontiguousarray(group.algebra_basis),
                       np.ascontiguousarray(group.algebra_pinv), group.is_whole, *out)
    return out


def smooth(group: BaseGroup, steps: Sequence[FilterStep]) -> list[FilterState]:
    """Run the RTS smoother backwards over recorded steps; return one state per step."""
    count = len(steps)
    if not count:
        return []
    dim = steps[0].p.shape[0]
    n = dim - steps[0].x.shape[0]
    # The steps as the store's records (step_dtype): the pass reads the same layouts.
    records = np.zeros(count, step_dtype(n, dim, False))
    identity = np.eye(dim)
    records['has_transition'] = [step.transition is not None for step in steps]
    records['transition'] = [identity if step.transition is None else step.transition
                             for step in steps]
    for name in ('pose_pred', 'x_pred', 'p_pred', 'pose', 'x', 'p'):
        records[name] = [getattr(step, name) for step in steps]
    pose, x, p = smooth_arrays(
        group, ~records['has_transition'], records['transition'], records['pose_pred'],
        records['x_pred'], records['p_pred'], records['pose'], records['x'], records['p'])
    return [FilterState(pin.SE3(pose[k]), x[k], p[k]) for k in range(count)]
