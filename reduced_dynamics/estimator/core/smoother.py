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
The Rauch-Tung-Striebel smoother's backward pass (error-state form), compiled.

``C_k = P_k Phi_{k+1}^T (P^-_{k+1})^-1``; the smoothed correction at k is
``C_k (x^s_{k+1} - x^-_{k+1})`` with the pose difference taken as
``log(g^-_{k+1}^-1 g^s_{k+1})``; ``P^s_k = P_k + C_k (P^s_{k+1} - P^-_{k+1}) C_k^T``.
A step without a transition (a restart) does not depend on the one before: the
pass starts afresh from its filtered state.

:func:`smooth_arrays` takes the steps as stacked arrays (any array-like that
indexes like numpy, e.g. ``numpy.memmap`` of a disk-backed store) and writes the
smoothed states into output arrays of the same shapes; :func:`smooth` is the
list-of-:class:`~.state.FilterStep` form.
"""

from __future__ import annotations

from typing import Iterator, Optional, Sequence

import numpy as np
from numba import njit
import pinocchio as pin

from reduced_dynamics.estimator.core.lie import compose, group_exp, inverse, group_log
from reduced_dynamics.estimator.core.kernels import symmetric
from reduced_dynamics.estimator.core.state import FilterState, FilterStep
from reduced_dynamics.geometry.lie_group import BaseGroup


@njit(cache=True)
def _gain(p: np.ndarray, transition: np.ndarray, p_pred: np.ndarray) -> np.ndarray:
    """Return C = P Phi^T (P^-)^-1 (a least-squares solve if P^- is singular)."""
    cross = p @ transition.T
    try:
        return np.linalg.solve(p_pred, cross.T).T.copy()
    except Exception:  # exactly singular (numba raises a plain exception type)
        return cross @ np.linalg.pinv(p_pred)


@njit(cache=True)
def backward_step(g_k: np.ndarray, x_k: np.ndarray, p_k: np.ndarray, transition: np.ndarray,
                  pose_pred: np.ndarray, x_pred: np.ndarray, p_pred: np.ndarray,
                  g_s: np.ndarray, x_s: np.ndarray, p_s: np.ndarray, basis: np.ndarray,
                  pinv: np.ndarray, whole: bool) -> tuple:
    """
    Return the smoothed (pose, x, P) of step k from its filtered state and step k + 1.

    ``transition``, ``pose_pred``, ``x_pred``, ``p_pred``: step k + 1's; ``g_s``,
    ``x_s``, ``p_s``: its smoothed state.
    """
    n = p_k.shape[0] - x_k.shape[0]
    gain = _gain(p_k, transition, p_pred)
    diff = np.empty(p_k.shape[0])
    diff[:n] = group_log(compose(inverse(pose_pred), g_s), pinv, whole)
    diff[n:] = x_s - x_pred
    dx = gain @ diff
    return (compose(g_k, group_exp(dx[:n], basis, whole)), x_k + dx[n:],
            symmetric(p_k + gain @ (p_s - p_pred) @ gain.T))


@njit(cache=True)
def backward(restart: np.ndarray, transitions: np.ndarray, pose_pred: np.ndarray,
             x_pred: np.ndarray, p_pred: np.ndarray, pose: np.ndarray, x: np.ndarray,
             p: np.ndarray, basis: np.ndarray, pinv: np.ndarray, whole: bool,
             pose_out: np.ndarray, x_out: np.ndarray, p_out: np.ndarray) -> None:
    """
    Run the backward pass over K stacked steps, writing the smoothed states.

    ``restart[k]``: step k has no transition (``transitions[k]`` is then unused).
    Shapes: transitions, p_pred, p, p_out (K, d, d); pose_pred, pose, pose_out
    (K, 4, 4); x_pred, x, x_out (K, d - n).
    """
    count = restart.shape[0]
    pose_out[count - 1] = pose[count - 1]
    x_out[count - 1] = x[count - 1]
    p_out[count - 1] = p[count - 1]
    g_s, x_s, p_s = pose[count - 1].copy(), x[count - 1].copy(), p[count - 1].copy()
    for k in range(count - 2, -1, -1):
        if restart[k + 1]:
            g_s, x_s, p_s = pose[k].copy(), x[k].copy(), p[k].copy()
        else:
            g_s, x_s, p_s = backward_step(
                pose[k].copy(), x[k].copy(), p[k].copy(), transitions[k + 1].copy(),
                pose_pred[k + 1].copy(), x_pred[k + 1].copy(), p_pred[k + 1].copy(),
                g_s, x_s, p_s, basis, pinv, whole)
        pose_out[k] = g_s
        x_out[k] = x_s
        p_out[k] = p_s


@njit(cache=True)
def smoother_gain(p: np.ndarray, transition: np.ndarray, p_pred: np.ndarray) -> np.ndarray:
    """Return the gain C_k of :func:`backward_step` (step k's P, step k + 1's Phi and P^-)."""
    return _gain(p, transition, p_pred)


@njit(cache=True)
def backward_mean(restart: np.ndarray, gains: np.ndarray, pose_pred: np.ndarray,
                  x_pred: np.ndarray, pose: np.ndarray, x: np.ndarray, basis: np.ndarray,
                  pinv: np.ndarray, whole: bool, pose_out: np.ndarray,
                  x_out: np.ndarray) -> None:
    """
    Run the mean part of :func:`backward` over K stacked steps, the gains given.

    ``gains[k]``: C_k (:func:`smoother_gain`), which depends on the filtered steps
    alone, so a caller smoothing the same steps again (the fixed-lag smoother)
    computes it once. The smoothed means are :func:`backward`'s, the same
    arithmetic; no covariance is propagated.
    """
    count = restart.shape[0]
    d = gains.shape[1]
    n = d - x.shape[1]
    pose_out[count - 1] = pose[count - 1]
    x_out[count - 1] = x[count - 1]
    g_s, x_s = pose[count - 1].copy(), x[count - 1].copy()
    diff = np.empty(d)
    for k in range(count - 2, -1, -1):
        if restart[k + 1]:
            g_s, x_s = pose[k].copy(), x[k].copy()
        else:
            diff[:n] = group_log(compose(inverse(pose_pred[k + 1].copy()), g_s), pinv, whole)
            diff[n:] = x_s - x_pred[k + 1]
            dx = gains[k].copy() @ diff
            g_s = compose(pose[k].copy(), group_exp(dx[:n], basis, whole))
            x_s = x[k] + dx[n:]
        pose_out[k] = g_s
        x_out[k] = x_s


def smooth_arrays(group: BaseGroup, restart: np.ndarray, transitions: np.ndarray,
                  pose_pred: np.ndarray, x_pred: np.ndarray, p_pred: np.ndarray,
                  pose: np.ndarray, x: np.ndarray, p: np.ndarray,
                  out: Optional[tuple] = None) -> tuple:
    """
    Return the smoothed (poses, x, P) of stacked steps (see :func:`backward`).

    ``out``: (pose, x, P) arrays to write into (e.g. memmaps); default new arrays.
    """
    if out is None:
        out = (np.empty_like(pose), np.empty_like(x), np.empty_like(p))
    if len(restart):
        backward(np.asarray(restart, dtype=np.bool_), transitions, pose_pred, x_pred, p_pred,
                 pose, x, p, group.algebra_basis, group.algebra_pinv, group.is_whole, *out)
    return out


def smooth_backward(group: BaseGroup,
                    steps: Sequence[FilterStep]) -> Iterator[tuple[int, FilterState]]:
    """
    Yield (k, smoothed state) from the last step to the first (:func:`backward_step`).

    ``steps`` is read by index, backwards, two at a time: a list, or the disk-backed
    store of :mod:`reduced_dynamics.estimator.smoother` (memory bounded by the store).
    Equal to :func:`smooth` (the same compiled step).
    """
    count = len(steps)
    if not count:
        return
    basis, pinv, whole = group.algebra_basis, group.algebra_pinv, group.is_whole
    after = steps[count - 1]
    g_s, x_s, p_s = after.pose.copy(), after.x.copy(), after.p.copy()
    yield count - 1, FilterState(pin.SE3(g_s), x_s, p_s)
    for k in range(count - 2, -1, -1):
        step = steps[k]
        if after.transition is None:
            g_s, x_s, p_s = step.pose.copy(), step.x.copy(), step.p.copy()
        else:
            g_s, x_s, p_s = backward_step(
                np.ascontiguousarray(step.pose), np.ascontiguousarray(step.x),
                np.ascontiguousarray(step.p), np.ascontiguousarray(after.transition),
                np.ascontiguousarray(after.pose_pred), np.ascontiguousarray(after.x_pred),
                np.ascontiguousarray(after.p_pred), g_s, x_s, p_s, basis, pinv, whole)
        yield k, FilterState(pin.SE3(g_s), x_s, p_s)
        after = step


def smooth(group: BaseGroup, steps: Sequence[FilterStep]) -> list[FilterState]:
    """Run the RTS smoother backwards over recorded steps; return one state per step."""
    count = len(steps)
    if not count:
        return []
    dim = steps[0].p.shape[0]
    restart = np.array([step.transition is None for step in steps])
    identity = np.eye(dim)
    transitions = np.array([identity if step.transition is None else step.transition
                            for step in steps])
    pose, x, p = smooth_arrays(
        group, restart, transitions, np.array([s.pose_pred for s in steps]),
        np.array([s.x_pred for s in steps]), np.array([s.p_pred for s in steps]),
        np.array([s.pose for s in steps]), np.array([s.x for s in steps]),
        np.array([s.p for s in steps]))
    return [FilterState(pin.SE3(pose[k]), x[k], p[k]) for k in range(count)]
