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
The smoother's backward step of main 3a3a89e, dense: the reference of core/smoother.py.

``C = P Phi^T (P^-)^-1`` by an LU solve (a pseudo-inverse if P^- is exactly
singular) and ``P^s = P + C (P^s_{k+1} - P^-) C^T`` by two dense products,
operation for operation as it was, so that a test can pin the structured step
against it (test/test_structured_smoother.py). :func:`backward_block` has the
signature of :func:`~.smoother.backward_block`. Not used by the smoother.

Plain numpy, not compiled (a test oracle: see core/reference.py).
"""

import numpy as np

from reduced_dynamics.estimator.core.kernels import symmetric
from reduced_dynamics.estimator.core.lie import compose, group_exp, group_log, inverse


def gain(p: np.ndarray, transition: np.ndarray, p_pred: np.ndarray) -> np.ndarray:
    """Return C = P Phi^T (P^-)^-1 (a least-squares solve if P^- is singular)."""
    cross = p @ transition.T
    try:
        return np.linalg.solve(p_pred, cross.T).T.copy()
    except np.linalg.LinAlgError:  # exactly singular
        return cross @ np.linalg.pinv(p_pred)


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
    c = gain(p_k, transition, p_pred)
    diff = np.empty(p_k.shape[0])
    diff[:n] = group_log(compose(inverse(pose_pred), g_s), pinv, whole)
    diff[n:] = x_s - x_pred
    dx = c @ diff
    return (compose(g_k, group_exp(dx[:n], basis, whole)), x_k + dx[n:],
            symmetric(p_k + c @ (p_s - p_pred) @ c.T))


def backward_block(restart: np.ndarray, transitions: np.ndarray, pose_pred: np.ndarray,
                   x_pred: np.ndarray, p_pred: np.ndarray, pose: np.ndarray, x: np.ndarray,
                   p: np.ndarray, after: bool, after_restart: np.ndarray,
                   after_transitions: np.ndarray, after_pose_pred: np.ndarray,
                   after_x_pred: np.ndarray, after_p_pred: np.ndarray, g_s: np.ndarray,
                   x_s: np.ndarray, p_s: np.ndarray, basis: np.ndarray, pinv: np.ndarray,
                   whole: bool, pose_out: np.ndarray, x_out: np.ndarray,
                   p_out: np.ndarray) -> None:
    """:func:`~.smoother.backward_block` with the dense step (:func:`backward_step`)."""
    count = restart.shape[0]
    for k in range(count - 1, -1, -1):
        last = k == count - 1
        if (last and (not after or after_restart[0])) or (not last and restart[k + 1]):
            g_s[:, :] = pose[k]
            x_s[:] = x[k]
            p_s[:, :] = p[k]
        elif last:
            g1, x1, p1 = backward_step(
                pose[k].copy(), x[k].copy(), p[k].copy(), after_transitions[0].copy(),
                after_pose_pred[0].copy(), after_x_pred[0].copy(), after_p_pred[0].copy(),
                g_s.copy(), x_s.copy(), p_s.copy(), basis, pinv, whole)
            g_s[:, :] = g1
            x_s[:] = x1
            p_s[:, :] = p1
        else:
            g1, x1, p1 = backward_step(
                pose[k].copy(), x[k].copy(), p[k].copy(), transitions[k + 1].copy(),
                pose_pred[k + 1].copy(), x_pred[k + 1].copy(), p_pred[k + 1].copy(),
                g_s.copy(), x_s.copy(), p_s.copy(), basis, pinv, whole)
            g_s[:, :] = g1
            x_s[:] = x1
            p_s[:, :] = p1
        pose_out[k] = g_s
        x_out[k] = x_s
        p_out[k] = p_s
