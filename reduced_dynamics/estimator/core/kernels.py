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
The filter's propagation and update, compiled (numba), on arrays.

The model is the one of estimator/filter.py's module docstring; the functions
here are its arithmetic, written once for the interpreter and the compiler. A
call returns fresh state arrays (the filter's recorded steps share them) and
allocates nothing else the caller sees. Constants of the base group and the
noise are packed once per filter into :class:`Model`-like tuples by the caller:

``basis`` S (6 x n), ``pinv`` S+ (n x 6), ``whole`` (S = 1), ``ad_rows``
(n x n^2) and ``form_rows`` (n^2 x n) the structure constants as matrices
(``ad(eta) = (eta ad_rows).reshape(n, n)``, ``W(pi) = (form_rows pi).reshape(n, n)``).

Covariances are symmetrised after every operation that could make them drift
apart (propagation, update, a step's compensation).

The step is structured (docs/structured_step.md): of the transition only the
pose block row and the mu-w chain are formed, Phi P Phi^T + Q by blocks; H enters
by its blocks (pose rows select, w columns zero), one Cholesky factor of S gives
the gain, the NIS and log det S, and P is updated as P - K S K^T. The dense step
it replaced is ``core/reference.py``, equal to 1e-9 (test/test_structured_step.py).

The arithmetic is in four modules, one concept each: :mod:`.products` (small dense
products as loops), :mod:`.transition` (the propagation: mean, Phi, Q),
:mod:`.factor` (S by blocks, its Cholesky factor, the gain) and :mod:`.update` (the
innovation and the iterated correction). This module holds the one-call step
(:func:`propagate_update`), the covariance's checks and a step's compensation, and
re-exports the others' names, so that ``kernels.<name>`` stays the one place the
filter, the tests and the references call them by.
"""

import numpy as np
from numba import njit

from reduced_dynamics.estimator.core.factor import (  # noqa: F401 (re-exported)
    _cholesky, _cross, _downdate, _factor, _gain_from, _innovation_covariance, _whiten, gain_of)
from reduced_dynamics.estimator.core.lie import (  # noqa: F401 (re-exported)
    adjoint, compose, group_exp, group_log, inverse)
from reduced_dynamics.estimator.core.products import (  # noqa: F401 (re-exported)
    _ad, _form, _mat_vec, _mul, _mul_into, _mul_t, _mul_t_into, form, symmetric)
from reduced_dynamics.estimator.core.transition import (  # noqa: F401 (re-exported)
    _GAUSS_NODES, _GAUSS_WEIGHTS, _predicted_covariance, delivered, propagate, propagate_mean,
    transition, transition_commanded, twist)
from reduced_dynamics.estimator.core.update import (  # noqa: F401 (re-exported)
    CONVERGED, ITERATIONS, _corrected, _dense_h, _twist_blocks, converged, correct, innovation,
    pose_noise, update, update_noise)


@njit(cache=True)
def compensate(g: np.ndarray, x: np.ndarray, p: np.ndarray, correction: np.ndarray,
               covariance: np.ndarray, basis: np.ndarray, whole: bool) -> tuple:
    """Return the state after a detected wrench step: g exp(d_g), x + d_x, P + D J^-1 D^T."""
    n = p.shape[0] - x.shape[0]
    return (compose(g, group_exp(correction[:n], basis, whole)), x + correction[n:],
            symmetric(p + covariance))


@njit(cache=True)
def significance(x: np.ndarray, p: np.ndarray, n: int) -> float:
    """Return w^T P_ww^-1 w (chi-square with n degrees of freedom when w = 0)."""
    w = x[n:2 * n].copy()
    block = np.ascontiguousarray(p[2 * n:3 * n, 2 * n:3 * n])
    return w @ np.linalg.solve(block, w)


@njit(cache=True)
def covariance_health(p: np.ndarray) -> int:
    """Return 0 for a usable covariance, 1 when not finite, 2 with a negative variance."""
    dim = p.shape[0]
    for i in range(dim):
        for j in range(dim):
            if not np.isfinite(p[i, j]):
                return 1
    for i in range(dim):
        if not p[i, i] >= 0.0:
            return 2
    return 0


@njit(cache=True)
def propagate_update(g: np.ndarray, x: np.ndarray, p: np.ndarray, locked: np.ndarray,
                     step_inverse: np.ndarray, step_connection_qd: np.ndarray,
                     step_joint_cov: np.ndarray, dt: float, jerk_var: np.ndarray,
                     pose: np.ndarray, measured: np.ndarray, with_twist: bool,
                     inverse_locked: np.ndarray, connection_qd: np.ndarray,
                     joint_cov: np.ndarray, pose_var: np.ndarray, stamp_twist: np.ndarray,
                     stamp_sigma: float, twist_var: np.ndarray, gate: float,
                     twist_weight: float, basis: np.ndarray, pinv: np.ndarray, whole: bool,
                     ad_rows: np.ndarray, form_rows: np.ndarray) -> tuple:
    """
    Propagate (3n filter, ``step_*`` the step's inputs) and update: one call per step.

    The same operations as :func:`propagate` then :func:`update`, in one compiled
    call (the filter's common step: a measurement at the step's end). Return
    (g, x, P, Phi) predicted, then :func:`update`'s eleven results, then the
    health of the resulting covariance (:func:`covariance_health`: of the update's
    P when accepted, else of the prediction's), the stamp-noise twist average
    moved ``twist_weight`` towards the updated twist (accepted and
    ``twist_weight`` >= 0; else ``stamp_twist``) and :func:`significance` of the
    resulting state (NaN when its covariance is not healthy).
    """
    phi, q = transition(g, x, locked, step_inverse, step_connection_qd, step_joint_cov, dt,
                        jerk_var, basis, pinv, whole, ad_rows, form_rows)
    # No command (u empty); commanded as u's size, a runtime bool: a constant False would
    # compile propagate_mean once more (numba specialises a callee on literal arguments).
    u = np.empty(0)
    g0, x0 = propagate_mean(g, x, step_inverse, step_connection_qd, dt, u, u.shape[0] > 0,
                            basis, pinv, whole)
    p0 = _predicted_covariance(phi, p, q, dt)
    accepted, nis, logdet, nu, r, g1, x1, p1, h, s, gain = update(
        g0, x0, p0, pose, measured, with_twist, inverse_locked, connection_qd, joint_cov,
        pose_var, stamp_twist, stamp_sigma, twist_var, gate, basis, pinv, whole, form_rows)
    health = covariance_health(p1 if accepted else p0)
    # w^T P_ww^-1 w of the result (the event detector reads it after each row).
    wrench_test = significance(x1, p1, inverse_locked.shape[0]) if health == 0 else np.nan
    averaged = stamp_twist
    if accepted and twist_weight >= 0.0:
        n = inverse_locked.shape[0]
        averaged = stamp_twist + twist_weight * (
            twist(g1, x1[:n], inverse_locked, connection_qd, basis, pinv, whole) - stamp_twist)
    return (g0, x0, p0, phi, accepted, nis, logdet, nu, r, g1, x1, p1, h, s, gain, health,
            averaged, wrench_test)
