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
The filter step of main 6a526f4, dense: the reference of the structured kernels.

``kernels.propagate_update`` and the update it calls exploit the structure of the
transition and of H (docs/estimator_core.md, "The structured step"); this module keeps
the dense algebra they replaced (the third-order transition with dense blocks, two
re-linearisations, LU solves, the Joseph form), operation for operation as it was, so
that a test can pin the new kernels against it (test/test_structured_step.py). Not used
by the filter.

Plain numpy, not compiled: a test oracle runs a few hundred times, and compiling it
(with the bench's loop over it) cost ~70 s of CPU in every fresh CI run, more than
the tests that call it. The compiled helpers it shares with the filter (Lie group,
measurement model) stay compiled. Its results differ from the compiled dense step's
by rounding only, far inside the 1e-9 the structured step is held to.
"""

import numpy as np

from reduced_dynamics.estimator.core.kernels import (
    _GAUSS_NODES, _GAUSS_WEIGHTS, converged, covariance_health, form, pose_noise, propagate_mean,
    significance, symmetric, transition_commanded, twist)
from reduced_dynamics.estimator.core.lie import adjoint, compose, group_exp, group_log, inverse

#: Re-linearisations of an update with a twist, as on main 6a526f4 (at most: the
#: structured step's convergence stop, kernels.converged, applies here too).
ITERATIONS = 2


def twist_measurement(g: np.ndarray, x: np.ndarray, pose: np.ndarray, measured: np.ndarray,
                      inverse_locked: np.ndarray, connection_qd: np.ndarray, dim: int,
                      basis: np.ndarray, pinv: np.ndarray, whole: bool,
                      form_rows: np.ndarray) -> tuple:
    """
    Return H (2n x dim) and the innovation of a pose and a body twist at (g, x).

    The dense measurement model the structured update (core/update.py ``_twist_blocks``)
    replaced; plain numpy around the compiled Lie helpers, as the rest of this module.
    """
    n = inverse_locked.shape[0]
    residual = group_log(compose(inverse(g), pose), pinv, whole)
    ad_t = adjoint(g, basis, pinv, whole).T
    pi = ad_t @ x[:n]
    h = np.zeros((2 * n, dim))
    for i in range(n):
        h[i, i] = 1.0
    h[n:, :n] = -inverse_locked @ form(form_rows, pi)
    h[n:, n:2 * n] = inverse_locked @ ad_t
    nu = np.empty(2 * n)
    nu[:n] = residual
    nu[n:] = measured - (inverse_locked @ pi - connection_qd)
    return h, nu


def transition(g: np.ndarray, x: np.ndarray, locked: np.ndarray, inverse_locked: np.ndarray,
               connection_qd: np.ndarray, joint_cov: np.ndarray, dt: float,
               jerk_var: np.ndarray, basis: np.ndarray, pinv: np.ndarray, whole: bool,
               ad_rows: np.ndarray, form_rows: np.ndarray) -> tuple:
    """
    Return Phi = exp(F dt) (third order) and the discrete process noise Q (3n).

    F has two non-trivial blocks only, F_gg = -(ad_xi + I^-1 W(pi)) and
    F_gmu = I^-1 Ad_g^T, at mu in the middle of the step; the mu-w chain is
    nilpotent. With a = F_gg dt, b = F_gmu dt the series gives, blockwise,
    Phi_gg = 1 + a + a^2/2 + a^3/6, Phi_gmu = b + ab/2 + a^2 b/6,
    Phi_gw = (b/2 + ab/6) dt, Phi_muw = dt. Q is Van Loan's integral of the wrench
    density through Phi(s)'s w column (3-point Gauss-Legendre; with q = Q_w dt it
    gives Q_ww = q, Q_muw = q dt/2, Q_mumu = q dt^2/3, Q_gw = (b/6 + ab/24) q dt,
    Q_gmu = b q dt^2/8 + O(dt^5), Q_gg = b q b^T dt^2/20 + O(dt^6)), plus
    Q_gg += A Sigma_qdot A^T dt^2 (encoder velocity noise held over the step).
    """
    n = locked.shape[0]
    ad_t = adjoint(g, basis, pinv, whole).T
    pi = ad_t @ (x[:n] + x[n:2 * n] * (0.5 * dt))
    xi = inverse_locked @ pi - connection_qd
    a = ((xi @ ad_rows).reshape(n, n) + inverse_locked @ form(form_rows, pi)) * -dt
    b = (inverse_locked @ ad_t) * dt
    ab = a @ b
    aa = a @ a
    phi = np.eye(3 * n)
    phi[:n, :n] += a + 0.5 * aa + (a @ aa) / 6.0
    phi[:n, n:2 * n] = b + 0.5 * ab + (a @ ab) / 6.0
    phi[:n, 2 * n:] = (0.5 * b + ab / 6.0) * dt
    for i in range(n):
        phi[n + i, 2 * n + i] = dt
    # Q_w = Ad_{g^-1}^T I diag(s^2) I Ad_{g^-1} (a density: per second).
    scaled = adjoint(inverse(g), basis, pinv, whole).T @ locked
    density = (scaled * jerk_var) @ scaled.T
    # Van Loan's integral int_0^dt Phi(s) L Qc L^T Phi(s)^T ds by 3-point Gauss-Legendre:
    # a sum of terms v Qc v^T, so Q is positive semi-definite by construction (the
    # truncated series was not: after a 1 s stall its Q_gg = 0 beside Q_gw != 0 made P
    # indefinite). Exact for the mu-w chain (polynomials of degree <= 5 in s).
    # With r = s/dt the w column is [g_r; s 1; 1], g_r = (b r/2 + ab r^2/6) s, so the
    # blocks are sums over the nodes of g D g^T, s g D, g D, s^2 D, s D and D.
    q = np.zeros((3 * n, 3 * n))
    for node in range(3):
        r = 0.5 * (1.0 + _GAUSS_NODES[node])
        s = r * dt
        weight = 0.5 * dt * _GAUSS_WEIGHTS[node]
        g_r = (0.5 * r) * b + (r * r / 6.0) * ab
        gd = (g_r * s) @ density
        q[:n, :n] += weight * (gd @ (g_r * s).T)
        q[:n, n:2 * n] += (weight * s) * gd
        q[:n, 2 * n:] += weight * gd
        q[n:2 * n, n:2 * n] += (weight * s * s) * density
        q[n:2 * n, 2 * n:] += (weight * s) * density
        q[2 * n:, 2 * n:] += weight * density
    q[n:, :n] = q[:n, n:].T
    q[2 * n:, n:2 * n] = q[n:2 * n, 2 * n:].T
    q[:n, :n] += joint_cov * (dt * dt)
    q = symmetric(q)
    return phi, q


def _chain_product(phi: np.ndarray, p: np.ndarray, dt: float) -> np.ndarray:
    """
    Return Phi P Phi^T for the 3n transition, whose lower block rows are [0 1 dt; 0 0 1].

    Phi P's rows: the pose block row is a product, the mu row is P_mu + dt P_w, the w
    row P_w; the same again on the columns (a third of the dense products' work).
    """
    n = p.shape[0] // 3
    m = np.empty_like(p)
    m[:n] = phi[:n] @ p
    m[n:2 * n] = p[n:2 * n] + dt * p[2 * n:]
    m[2 * n:] = p[2 * n:]
    out = np.empty_like(p)
    out[:, :n] = m @ phi[:n].T
    out[:, n:2 * n] = m[:, n:2 * n] + dt * m[:, 2 * n:]
    out[:, 2 * n:] = m[:, 2 * n:]
    return out


def propagate(g: np.ndarray, x: np.ndarray, p: np.ndarray, locked: np.ndarray,
              inverse_locked: np.ndarray, connection_qd: np.ndarray, joint_cov: np.ndarray,
              dt: float, u: np.ndarray, commanded: bool, jerk_var: np.ndarray,
              command_density: np.ndarray, basis: np.ndarray, pinv: np.ndarray, whole: bool,
              ad_rows: np.ndarray, form_rows: np.ndarray) -> tuple:
    """Return (g, x, P, Phi) after dt: the mean, and P = Phi P Phi^T + Q symmetrised."""
    if commanded:
        phi, q = transition_commanded(g, x, locked, inverse_locked, connection_qd, joint_cov,
                                      dt, u, jerk_var, command_density, basis, pinv, whole,
                                      ad_rows, form_rows)
    else:
        phi, q = transition(g, x, locked, inverse_locked, connection_qd, joint_cov, dt,
                            jerk_var, basis, pinv, whole, ad_rows, form_rows)
    g1, x1 = propagate_mean(g, x, inverse_locked, connection_qd, dt, u, commanded, basis, pinv,
                            whole)
    if commanded:
        p1 = phi @ p @ phi.T + q
    else:
        p1 = _chain_product(phi, p, dt) + q
    return g1, x1, symmetric(p1), phi


def gain_of(p: np.ndarray, h: np.ndarray, r: np.ndarray) -> np.ndarray:
    """Return K = P H^T S^-1 with S = H P H^T + R symmetrised."""
    ph = p @ h.T
    s = symmetric(h @ ph + r)
    return np.linalg.solve(s, ph.T).T.copy()


def innovation(g: np.ndarray, x: np.ndarray, p: np.ndarray, pose: np.ndarray,
               measured: np.ndarray, with_twist: bool, inverse_locked: np.ndarray,
               connection_qd: np.ndarray, joint_cov: np.ndarray, r_pose: np.ndarray,
               twist_var: np.ndarray, basis: np.ndarray, pinv: np.ndarray, whole: bool,
               form_rows: np.ndarray) -> tuple:
    """
    Return (H, nu, R, S, S^-1 [(P H^T)^T, nu], NIS, log det S) of a measurement.

    A pose alone has H = [1 0 0]; with a twist the H and innovation of
    :func:`twist_measurement`, and R holds the joint-velocity noise through A.
    """
    n = inverse_locked.shape[0]
    dim = p.shape[0]
    if with_twist:
        h, nu = twist_measurement(g, x, pose, measured, inverse_locked, connection_qd, dim,
                                  basis, pinv, whole, form_rows)
        r = np.zeros((2 * n, 2 * n))
        r[:n, :n] = r_pose
        r[n:, n:] = joint_cov
        for i in range(n):
            r[n + i, n + i] += twist_var[i]
    else:
        h = np.zeros((n, dim))
        for i in range(n):
            h[i, i] = 1.0
        nu = group_log(compose(inverse(g), pose), pinv, whole)
        r = r_pose.copy()
    if with_twist:
        ph = p @ h.T
        s = symmetric(h @ ph + r)
    else:
        ph = p[:, :n].copy()
        s = symmetric(p[:n, :n] + r)
    m = nu.shape[0]
    rhs = np.empty((m, dim + 1))
    rhs[:, :dim] = ph.T
    rhs[:, dim] = nu
    solved = np.linalg.solve(s, rhs)
    nis = nu @ solved[:, dim]
    _, logdet = np.linalg.slogdet(s)
    return h, nu, r, s, solved, nis, logdet


def correct(g: np.ndarray, x: np.ndarray, p: np.ndarray, pose: np.ndarray,
            measured: np.ndarray, with_twist: bool, h: np.ndarray, nu: np.ndarray,
            r: np.ndarray, gain: np.ndarray, inverse_locked: np.ndarray,
            connection_qd: np.ndarray, basis: np.ndarray, pinv: np.ndarray, whole: bool,
            form_rows: np.ndarray) -> tuple:
    """
    Return (g, x, P, H, S, K) after the update with gain K (dim x m) from the prior.

    With a twist the update is iterated (Gauss-Newton on the posterior: the twist
    is bilinear in (g, mu)). P is the Joseph form (1 - K H) P (1 - K H)^T + K R K^T,
    symmetrised: positive semi-definite for any K, so rounding cannot make it
    indefinite as the short form P - K H P can.
    """
    n = inverse_locked.shape[0]
    dim = p.shape[0]
    dx = gain @ nu
    s = np.empty((0, 0))
    if with_twist:
        x_len = x.shape[0]
        for iteration in range(ITERATIONS):
            previous = dx
            g_i = compose(g, group_exp(dx[:n], basis, whole))
            x_i = x + dx[n:n + x_len]
            h, nu_i = twist_measurement(g_i, x_i, pose, measured, inverse_locked,
                                        connection_qd, dim, basis, pinv, whole, form_rows)
            ph = p @ h.T
            s = symmetric(h @ ph + r)
            gain = np.linalg.solve(s, ph.T).T.copy()
            dx = gain @ (nu_i + h @ dx)
            # The structured step's stop (kernels.converged), so both take the same branch.
            if iteration + 1 < ITERATIONS and converged(previous, dx, p):
                break
    else:
        s = symmetric(p[:n, :n] + r)
    g1 = compose(g, group_exp(dx[:n], basis, whole))
    x1 = x + dx[n:]
    if with_twist:
        keep = np.eye(dim) - gain @ h
        p1 = keep @ p @ keep.T + gain @ r @ gain.T
    else:
        # H = [1 0 0]: (1 - K H) P = P - K P_g. (rows), then times (1 - K H)^T on the
        # right: the same product form with the identity blocks skipped.
        left = p - gain @ p[:n]
        p1 = left - left[:, :n] @ gain.T + gain @ r @ gain.T
    return g1, x1, symmetric(p1), h, s, gain


def update(g: np.ndarray, x: np.ndarray, p: np.ndarray, pose: np.ndarray,
           measured: np.ndarray, with_twist: bool, inverse_locked: np.ndarray,
           connection_qd: np.ndarray, joint_cov: np.ndarray, pose_var: np.ndarray,
           stamp_twist: np.ndarray, stamp_sigma: float, twist_var: np.ndarray,
           gate: float, basis: np.ndarray, pinv: np.ndarray, whole: bool,
           form_rows: np.ndarray) -> tuple:
    """
    Update with a pose (and twist) unless its NIS exceeds ``gate``: one call per sample.

    Return (accepted, nis, logdet, nu, R, g, x, P, H, S, K); when gated (NIS above
    ``gate``) the state is the prior's and H, S, K those of the innovation.
    """
    return update_noise(g, x, p, pose, measured, with_twist, inverse_locked, connection_qd,
                        joint_cov, pose_noise(pose_var, stamp_twist, stamp_sigma), twist_var,
                        gate, basis, pinv, whole, form_rows)


def update_noise(g: np.ndarray, x: np.ndarray, p: np.ndarray, pose: np.ndarray,
                 measured: np.ndarray, with_twist: bool, inverse_locked: np.ndarray,
                 connection_qd: np.ndarray, joint_cov: np.ndarray, r_pose: np.ndarray,
                 twist_var: np.ndarray, gate: float, basis: np.ndarray, pinv: np.ndarray,
                 whole: bool, form_rows: np.ndarray) -> tuple:
    """
    Return what :func:`update` does, with the pose noise R given as a full matrix.

    For a sample that carries its own covariance (estimator/covariance.py): the
    twist's goes in with ``joint_cov``, ``twist_var`` then zeros.
    """
    h, nu, r, s, solved, nis, logdet = innovation(
        g, x, p, pose, measured, with_twist, inverse_locked, connection_qd, joint_cov, r_pose,
        twist_var, basis, pinv, whole, form_rows)
    dim = p.shape[0]
    gain = solved[:, :dim].T.copy()
    if nis > gate:
        return False, nis, logdet, nu, r, g, x, p, h, s, gain
    g1, x1, p1, h1, s1, gain1 = correct(g, x, p, pose, measured, with_twist, h, nu, r, gain,
                                        inverse_locked, connection_qd, basis, pinv, whole,
                                        form_rows)
    return True, nis, logdet, nu, r, g1, x1, p1, h1, s1, gain1


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
    u = np.empty(0)  # no command: commanded a runtime bool, as in kernels.propagate_update
    g0, x0 = propagate_mean(g, x, step_inverse, step_connection_qd, dt, u, u.shape[0] > 0,
                            basis, pinv, whole)
    p0 = symmetric(_chain_product(phi, p, dt) + q)
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
