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
Error-state Kalman filter of base pose, momentum and external wrench.

State x = (g, mu, w): base pose g in the base group G (SE(3) or SE(2), n
coordinates), momentum map mu (5.27, world frame, about the world origin) and
external wrench w = mu_dot. The process model is the reduced mechanics with the
joint states as inputs:

* reconstruction (REDUCED_MODEL.md 4): ``g_dot = g xi``,
  ``xi = I^-1 pi - A qbar_dot``, ``pi = Ad_g^T mu``;
* momentum balance: ``mu_dot = w`` (Noether: zero without external wrench);
* ``w_dot`` = white noise (a random walk), whose density is a body-frame
  acceleration-rate density scaled by the locked inertia I, so one default
  fits any mass: ``Q_w = Ad_{g^-1}^T I diag(s^2) I Ad_{g^-1}``.

The error state is (delta_g, delta_mu, delta_w) with ``g = g_hat exp(delta_g)``
(right perturbation, body-frame algebra coordinates), dimension 3n. Its
linearised dynamics (checked against finite differences in the tests) are::

    d delta_g/dt = -(ad_xi + I^-1 W(pi)) delta_g + I^-1 Ad_g^T delta_mu - A d qbar_dot
    d delta_mu/dt = delta_w,   d delta_w/dt = noise

with W(pi)[a, b] = <pi, [e_a, e_b]> (``BaseGroup.coadjoint_form``), because
``Ad_{g exp d}^T mu = pi + ad_d^T pi = pi - W(pi) d``. Encoder velocity noise
enters through A: ``A Sigma_qdot A^T`` on delta_g for the step it is held.

The joint states are the filter's inputs and its output rows; the base samples are
its measurements, each used once, at its own stamp (:meth:`MomentumFilter.row`):
between two joint-state rows the filter propagates to a measurement's stamp with
the joint inputs interpolated between the rows, updates, and propagates on to the
next row, as robot_localization orders measurements. Interpolating the base to
every joint-state stamp instead would use one measurement several times as if
independent (over-confident) and pay an update per row.

Measurements: a pose (PoseStamped), residual ``log(g_hat^-1 g_meas)``, H = [1 0 0];
a body twist (Odometry), ``h = I^-1 Ad_g^T mu - A qbar_dot``,
H = [-I^-1 W(pi), I^-1 Ad_g^T, 0], with the joint-velocity noise through A in R.
Innovations whose normalised square exceeds the gate are rejected (momentum
jumps no wrench of the random walk explains); after ``GATE_RESET`` rejections
in a row the filter re-initialises its momentum and wrench covariance (a real
impulse, e.g. a docking contact) and accepts. A run of rejected poses (pose
only) whose residuals are one constant offset, within their noise, is instead a
step of the measurement: motion capture re-fits its rigid body when a marker
drops out or returns, and the pose then jumps by a fraction of a millimetre
and a few milliradians and stays there (seen in the freeflyer2 recordings). A
momentum jump gated at the first sample makes residuals that grow with time;
the offset re-anchors the pose covariance only, and mu and w keep theirs.

A pose stamp off by dt from the instant the pose was measured (a mocap client
stamping on receipt) puts ``xi dt`` into the residual: the pose noise is
``R + xi xi^T sigma_t^2`` (``pose_stamp``), with xi the body twist averaged over
``STAMP_TWIST_TIME``. A GLR test of a step in w on the innovations
(:class:`~reduced_dynamics.estimator.events.WrenchStepTest`) lets the filter take
a thruster switching at once (``x += D Delta``, ``P += D J^-1 D^T``). A covariance
that loses positive definiteness restarts the filter from the measurement.

Each step may record what the fixed-interval (Rauch-Tung-Striebel) smoother
needs (:class:`FilterStep`); :func:`smooth` runs it on the group.

**Commanded wrench** (``command=True``; README "Commanded wrench"). With a
body-frame command u (what the thrusters were told to deliver, dual coordinates,
held from its last message: a zero-order hold) the momentum balance of
REDUCED_MODEL.md 3 (``mu_dot`` = the external wrench, world frame about the
origin) becomes::

    mu_dot = Ad_{g^-1}^T (k o u + b) + w

a body wrench mapped to the world like pi to mu (5.27), with per-axis gain k and
bias b of the delivered wrench (``o``: per axis; random walks of small density,
priors k = 1 +- ``command_gain_sigma``, b = 0 +- the bias acceleration scaled
by I) and w now the disturbance beyond the command. The state grows to
(g, mu, w, k, b), error dimension 5n; the new blocks of F are::

    d delta_mu/dt += Ad_{g^-1}^T W(c) delta_g + Ad_{g^-1}^T diag(u) delta_k
                     + Ad_{g^-1}^T delta_b,       c = k o u + b

because ``Ad_{(g exp d)^-1}^T c = Ad_{g^-1}^T (c + W(c) d)``. Over a step the
command enters by its mean over the step (its hold integrated exactly; g at the
middle of the step, like the midpoint rule of the pose). Without a command the
filter is the 3n one above, operation for operation.
"""

from __future__ import annotations

from dataclasses import dataclass
import math
from typing import Iterator, NamedTuple, Optional, Sequence

import numpy as np
import pinocchio as pin
from reduced_dynamics.chi_square import chi2

from reduced_dynamics.estimator.events import StepDetection, WrenchStepTest
from reduced_dynamics.geometry.lie_group import BaseGroup

#: Consecutive gated measurements after which a momentum jump is accepted.
GATE_RESET = 3
#: False-alarm probability of the test that a run of gated poses is a constant offset
#: (a mocap body re-fitted to other markers) rather than a momentum jump.
OFFSET_PROBABILITY = 1e-3
#: Time constant [s] of the twist average that scales the pose stamp noise.
STAMP_TWIST_TIME = 0.5
#: Re-linearisations of an update with a twist (iterated EKF).
ITERATIONS = 2
LOG_2PI = math.log(2.0 * math.pi)


@dataclass(frozen=True)
class NoiseModel:
    """
    Sensor and process noise in physical units (standard deviations).

    ``pose_position`` [m], ``pose_angle`` [rad]: pose measurement noise;
    ``twist_linear`` [m/s], ``twist_angular`` [rad/s]: Odometry twist noise;
    ``joint_velocity`` [rad/s or m/s]: encoder velocity noise;
    ``jerk_linear`` [m/s^3/sqrt(Hz)], ``jerk_angular`` [rad/s^3/sqrt(Hz)]: density
    of the body acceleration random walk that drives w (scaled by I);
    ``initial_speed`` [m/s], ``initial_rate`` [rad/s], ``initial_acceleration``
    [m/s^2 and rad/s^2]: prior spread of the motion before the first update.
    Commanded wrench only: ``command_gain`` prior spread of the gain (about 1),
    ``command_gain_drift`` [1/sqrt(s)] its random-walk density;
    ``command_bias_linear`` [m/s^2], ``command_bias_angular`` [rad/s^2] prior
    spread of the bias as a body acceleration (scaled by I), which drifts at
    ``command_gain_drift`` times that per sqrt(s); ``disturbance_linear``
    [m/s^3/sqrt(Hz)], ``disturbance_angular`` [rad/s^3/sqrt(Hz)]: the density
    of w's random walk in place of ``jerk_*`` (w is then the disturbance beyond
    the command, which no longer carries the thruster switching).
    """

    pose_position: float = 1e-3
    pose_angle: float = 2e-3
    twist_linear: float = 1e-2
    twist_angular: float = 1e-2
    joint_velocity: float = 1e-2
    jerk_linear: float = 0.05
    jerk_angular: float = 0.5
    initial_speed: float = 1.0
    initial_rate: float = 1.0
    initial_acceleration: float = 1.0
    command_gain: float = 0.5
    command_gain_drift: float = 2e-3
    command_bias_linear: float = 5e-3
    command_bias_angular: float = 2.5e-2
    disturbance_linear: float = 1e-3
    disturbance_angular: float = 5e-3
    pose_stamp: float = 0.0


class Linearisation(NamedTuple):
    """Per-sample inputs of the process model: I, I^-1, A qbar_dot, A Sigma A^T."""

    locked: np.ndarray
    locked_inverse: np.ndarray
    connection_qd: np.ndarray
    joint_cov: np.ndarray


def between(before: Linearisation, after: Linearisation, fraction: float) -> Linearisation:
    """
    Return the inputs ``fraction`` of the way from ``before`` to ``after``.

    I^-1 and A qbar_dot are interpolated linearly (the trapezoid of the step's
    inputs); I and A Sigma A^T are those of ``after``. ``fraction`` 0.5 is the
    middle of a joint-state interval, written as the plain mean.
    """
    if fraction == 0.5:
        return Linearisation(after.locked,
                             0.5 * (before.locked_inverse + after.locked_inverse),
                             0.5 * (before.connection_qd + after.connection_qd), after.joint_cov)
    return Linearisation(
        after.locked,
        before.locked_inverse + fraction * (after.locked_inverse - before.locked_inverse),
        before.connection_qd + fraction * (after.connection_qd - before.connection_qd),
        after.joint_cov)


class Measurement(NamedTuple):
    """A base measurement at its own stamp: the pose, and the body twist with Odometry."""

    stamp_ns: int
    pose: pin.SE3
    twist: Optional[np.ndarray]
    #: the stamp's standard deviation [s] when it differs from ``NoiseModel.pose_stamp``
    #: (a re-timed frame time, estimator/retiming.py); None: ``pose_stamp`` (used only
    #: when ``pose_stamp`` > 0)
    stamp_sigma: Optional[float] = None


@dataclass
class FilterStep:
    """
    What the RTS smoother needs from one step (predicted and filtered).

    ``output``: the step is a joint-state row (an output of the estimator);
    False for a base measurement between two rows.
    """

    stamp_ns: int
    transition: Optional[np.ndarray]
    g_pred: pin.SE3
    x_pred: np.ndarray
    p_pred: np.ndarray
    g: pin.SE3
    x: np.ndarray
    p: np.ndarray
    locked_inverse: np.ndarray
    output: bool = True
    #: commanded wrench only: the command held at this step's end
    command: Optional[np.ndarray] = None


class Command(NamedTuple):
    """
    The commanded body wrench over a step (dual coordinates, body frame).

    ``mean``: its mean over the step (what the propagation integrates);
    ``now``: the value held at the step's end (what the total wrench reports).
    """

    mean: np.ndarray
    now: np.ndarray


class FilterState(NamedTuple):
    """A state estimate: pose, [mu; w] (and [k; b]), covariance (3n or 5n square)."""

    g: pin.SE3
    x: np.ndarray
    p: np.ndarray


def _axis_kinds(group: BaseGroup) -> np.ndarray:
    """Return True for algebra coordinates that rotate (angular), else False."""
    basis = group.algebra_basis
    return np.abs(basis[3:]).sum(axis=0) > 0.0


class MomentumFilter:
    """
    The error-state Kalman filter on G x R^n x R^n (see the module docstring).

    :meth:`row` processes one joint-state row with the base measurements
    stamped since the previous one (each updates once, at its own stamp);
    :meth:`step` is the row with one measurement at the row's stamp. ``record``
    keeps the steps for :func:`smooth`.

    Arrays of the state (``x``, ``p``) are replaced, never modified in place, so
    that recorded steps can share them.
    """

    def __init__(self, group: BaseGroup, noise: NoiseModel, gate_probability: float,
                 record: bool = False, command: bool = False,
                 step_significance: float = 0.0) -> None:
        """
        Set up for ``group``; ``gate_probability``: innovation gate (0: off).

        ``command``: the commanded-wrench model (gain and bias states, 5n).
        ``step_significance``: false-alarm probability of the GLR test of a wrench
        step (:class:`~reduced_dynamics.estimator.events.WrenchStepTest`; 0: off).
        """
        self.group = group
        self.n = n = group.dim
        self.command = command
        #: error-state dimension: 3n, or 5n with the commanded wrench
        self.dim = dim = 5 * n if command else 3 * n
        self.noise = noise
        angular = _axis_kinds(group)
        self._angular = angular
        self._pose_var = np.where(angular, noise.pose_angle ** 2, noise.pose_position ** 2)
        self._twist_var = np.where(angular, noise.twist_angular ** 2, noise.twist_linear ** 2)
        self._jerk_var = np.where(angular, noise.jerk_angular ** 2, noise.jerk_linear ** 2)
        self._speed_var = np.where(angular, noise.initial_rate ** 2, noise.initial_speed ** 2)
        self._accel_var = np.full(n, noise.initial_acceleration ** 2)
        self._gates = {}
        self.gate_probability = gate_probability
        for size in (n, 2 * n):
            self._gates[size] = math.inf if gate_probability <= 0.0 \
                else float(chi2.isf(gate_probability, size))
        self.g: Optional[pin.SE3] = None
        self.x = np.zeros(dim - n)
        self.p = np.zeros((dim, dim))
        self.stamp_ns: Optional[int] = None
        self.record = record
        self.steps: list[FilterStep] = []
        self.gated = 0
        self._gated_run = 0
        #: pose residuals and their noise (R) of the current run of gated poses
        self._gated_residuals: list[tuple[np.ndarray, np.ndarray]] = []
        #: runs of gated poses taken as a pose offset rather than a momentum jump
        self.pose_offsets = 0
        self._offset_threshold = {k: float(chi2.isf(OFFSET_PROBABILITY, n * (k - 1)))
                                  for k in range(2, GATE_RESET + 1)}
        self.last_nis: float = 0.0
        self._eye = np.eye(dim)
        self._eye_n = np.eye(n)
        if command:
            self._bias_var = np.where(angular, noise.command_bias_angular ** 2,
                                      noise.command_bias_linear ** 2)
            self._jerk_var = np.where(angular, noise.disturbance_angular ** 2,
                                      noise.disturbance_linear ** 2)
            self._command = np.zeros(n)
            self._command_zero = np.zeros(n)
        #: sum of the innovations' log-likelihoods, of their NIS and of their dimensions
        self.log_likelihood = 0.0
        self.nis_sum = 0.0
        self.nis_dof = 0
        self._lin: Optional[Linearisation] = None
        # Structure constants as matrices: ad(eta) = (eta @ ad_rows).reshape(n, n) and
        # W(pi) = (form_rows @ pi).reshape(n, n) (one matmul each, no einsum).
        structure = group.structure_constants
        self._ad_rows = np.ascontiguousarray(structure.reshape(n, n * n))
        self._form_rows = np.ascontiguousarray(structure.transpose(0, 2, 1).reshape(n * n, n))
        self._whole = group.is_whole
        self._basis, self._pinv = group.algebra_basis, group.algebra_pinv
        # Phi has the identity on its diagonal and dt I from w to mu (set per step).
        self._chain = (np.arange(n, 2 * n), np.arange(2 * n, 3 * n))
        # Coefficients of the series terms of Phi's top block row (see _transition).
        self._series1 = np.r_[np.full(2 * n, 0.5), np.full(n, 1.0 / 3.0)]
        self._series2 = np.r_[np.full(2 * n, 1.0 / 6.0), np.zeros(n)]
        self._r_pose = np.diag(self._pose_var)
        self._r_twist = np.diag(self._twist_var)
        self.step_test = WrenchStepTest(n, step_significance, self.dim)
        #: the wrench step taken since the last row (None: none detected)
        self.step_detected: Optional[StepDetection] = None
        self.steps_taken = 0
        #: re-initialisations after the covariance lost positive definiteness
        self.diverged = 0
        # Body twist averaged over STAMP_TWIST_TIME (pose stamp noise) and its time.
        self._stamp_twist = np.zeros(n)
        self._stamp_twist_ns: Optional[int] = None
        # H of a pose measurement, [1 0 0] (the step test's signatures need it).
        self._h_pose = np.zeros((n, self.dim))
        self._h_pose[:, :n] = np.eye(n)

    # --- pieces of the model ----------------------------------------------------------
    @property
    def mu(self) -> np.ndarray:
        """Return the momentum-map estimate (world frame, about the origin)."""
        return self.x[:self.n]

    @property
    def wrench(self) -> np.ndarray:
        """
        Return the wrench estimate w (world frame, about the origin).

        The external wrench; with the commanded wrench, the disturbance beyond it.
        """
        return self.x[self.n:2 * self.n]

    @property
    def wrench_cov(self) -> np.ndarray:
        """Return the covariance of w."""
        n = self.n
        return self.p[2 * n:3 * n, 2 * n:3 * n]

    # --- commanded wrench -------------------------------------------------------------
    @property
    def gain(self) -> np.ndarray:
        """Return the per-axis gain k of the delivered wrench (commanded wrench only)."""
        return self.x[2 * self.n:3 * self.n]

    @property
    def bias(self) -> np.ndarray:
        """Return the per-axis bias b of the delivered body wrench (commanded wrench only)."""
        return self.x[3 * self.n:]

    def delivered(self, g: pin.SE3, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Return the delivered wrench Ad_{g^-1}^T (k o u + b) in the world frame."""
        n = self.n
        return self.group.Ad(g.inverse()).T @ (x[2 * n:3 * n] * u + x[3 * n:])

    def total_wrench(self) -> tuple[np.ndarray, np.ndarray]:
        """
        Return the total external wrench w + delivered and its covariance (n, n x n).

        The command is the one held at the last step's end. Without the
        commanded wrench: w and its covariance.
        """
        if not self.command:
            return self.wrench, self.wrench_cov
        return self._total(self.g, self.x, self.p, self._command)

    def _total(self, g: pin.SE3, x: np.ndarray, p: np.ndarray,
               u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        n = self.n
        to_world = self.group.Ad(g.inverse()).T
        c = x[2 * n:3 * n] * u + x[3 * n:]
        jac = np.zeros((n, 5 * n))
        jac[:, :n] = to_world @ self.group.coadjoint_form(c)
        jac[:, 2 * n:3 * n] = np.eye(n)
        jac[:, 3 * n:4 * n] = to_world * u
        jac[:, 4 * n:] = to_world
        cov = jac @ p @ jac.T
        return x[n:2 * n] + to_world @ c, 0.5 * (cov + cov.T)

    def wrench_significance(self) -> float:
        """Return w^T P_ww^-1 w (chi-square with n degrees of freedom when w = 0)."""
        w = self.wrench
        return float(w @ np.linalg.solve(self.wrench_cov, w))

    def _adjoint(self, g: pin.SE3) -> np.ndarray:
        """Return Ad_g on the subalgebra (n x n)."""
        if self._whole:
            return g.action
        return self._pinv @ g.action @ self._basis

    def _adjoint_inverse(self, g: pin.SE3) -> np.ndarray:
        """Return Ad_{g^-1} on the subalgebra (n x n)."""
        if self._whole:
            return g.actionInverse
        return self._pinv @ g.actionInverse @ self._basis

    def _form(self, covector: np.ndarray) -> np.ndarray:
        """Return W(covector)[a, b] = <covector, [e_a, e_b]> (``coadjoint_form``)."""
        n = self.n
        return (self._form_rows @ covector).reshape(n, n)

    def twist(self, g: pin.SE3, mu: np.ndarray, lin: Linearisation) -> np.ndarray:
        """Return xi = I^-1 Ad_g^T mu - A qbar_dot (reconstruction)."""
        return lin.locked_inverse @ (self._adjoint(g).T @ mu) - lin.connection_qd

    def jacobian(self, g: pin.SE3, mu: np.ndarray, lin: Linearisation) -> np.ndarray:
        """Return F of the error dynamics at (g, mu) (3n x 3n)."""
        n, group = self.n, self.group
        ad_t = group.Ad(g).T
        pi = ad_t @ mu
        xi = lin.locked_inverse @ pi - lin.connection_qd
        f = np.zeros((self.dim, self.dim))
        f[:n, :n] = -group.ad(xi) - lin.locked_inverse @ group.coadjoint_form(pi)
        f[:n, n:2 * n] = lin.locked_inverse @ ad_t
        f[n:2 * n, 2 * n:3 * n] = np.eye(n)
        return f

    def command_jacobian(self, f: np.ndarray, g: pin.SE3, x: np.ndarray,
                         u: np.ndarray) -> None:
        """Add the commanded wrench's blocks (module docstring) to F, in place."""
        n = self.n
        to_world = self.group.Ad(g.inverse()).T
        c = x[2 * n:3 * n] * u + x[3 * n:]
        f[n:2 * n, :n] = to_world @ self.group.coadjoint_form(c)
        f[n:2 * n, 3 * n:4 * n] = to_world * u
        f[n:2 * n, 4 * n:] = to_world

    def twist_jacobian(self, g: pin.SE3, mu: np.ndarray, lin: Linearisation) -> np.ndarray:
        """Return H of the twist measurement (n x 3n)."""
        n = self.n
        ad_t = self._adjoint(g).T
        pi = ad_t @ mu
        h = np.zeros((n, self.dim))
        h[:, :n] = -lin.locked_inverse @ self._form(pi)
        h[:, n:2 * n] = lin.locked_inverse @ ad_t
        return h

    def wrench_density(self, g: pin.SE3, locked: np.ndarray) -> np.ndarray:
        """Return the spectral density of w_dot: Ad_{g^-1}^T I diag(s^2) I Ad_{g^-1}."""
        scaled = self._adjoint_inverse(g).T @ locked
        return (scaled * self._jerk_var) @ scaled.T

    def propagate_mean(self, g: pin.SE3, x: np.ndarray, lin: Linearisation,
                       dt: float, u: Optional[np.ndarray] = None
                       ) -> tuple[pin.SE3, np.ndarray]:
        """
        Return (g, x) after dt: midpoint rule on the group, mu exact for constant w.

        ``u`` (commanded wrench): the command's mean over the step; the
        delivered wrench is taken at the pose of the step's middle.
        """
        if u is not None:
            return self._propagate_commanded(g, x, lin, dt, u)
        n, exp = self.n, self.group.exp
        mu, w = x[:n], x[n:]
        half = exp(self.twist(g, mu, lin) * (0.5 * dt))
        xi = self.twist(g * half, mu + w * (0.5 * dt), lin)
        out = x.copy()
        out[:n] = mu + w * dt
        return g * exp(xi * dt), out

    def _propagate_commanded(self, g: pin.SE3, x: np.ndarray, lin: Linearisation,
                             dt: float, u: np.ndarray) -> tuple[pin.SE3, np.ndarray]:
        n, group = self.n, self.group
        mu = x[:n]
        middle = g * group.exp(self.twist(g, mu, lin) * (0.5 * dt))
        rate = x[n:2 * n] + self.delivered(middle, x, u)
        xi = self.twist(middle, mu + rate * (0.5 * dt), lin)
        out = x.copy()
        out[:n] = mu + rate * dt
        return g * group.exp(xi * dt), out

    def _transition(self, g: pin.SE3, x: np.ndarray, lin: Linearisation,
                    dt: float, u: Optional[np.ndarray] = None
                    ) -> tuple[np.ndarray, np.ndarray]:
        """
        Return Phi = exp(F dt) (third order) and the discrete process noise Q.

        F has two non-trivial blocks only, F_gg = -(ad_xi + I^-1 W(pi)) and
        F_gmu = I^-1 Ad_g^T, at mu in the middle of the step; the mu-w chain is
        nilpotent. With a = F_gg dt, b = F_gmu dt the series gives, blockwise,
        Phi_gg = 1 + a + a^2/2 + a^3/6, Phi_gmu = b + ab/2 + a^2 b/6,
        Phi_gw = (b/2 + ab/6) dt, Phi_muw = dt. Van Loan's integral
        int_0^dt Phi(s) Qc Phi(s)^T ds as its Taylor series to fourth order in F dt
        (exact for the mu-w chain), with q = Q_w dt: Q_ww = q, Q_muw = q dt/2,
        Q_mumu = q dt^2/3, Q_gw = (b/6 + ab/24) q dt, Q_gmu = b q dt^2/8, and
        Q_gg = A Sigma_qdot A^T dt^2 (encoder velocity noise held over the step).
        With the commanded wrench (``u``: its mean over the step) F has more blocks
        (module docstring): the series is then evaluated on the dense 5n matrices.
        """
        if u is not None:
            return self._transition_commanded(g, x, lin, dt, u)
        n = self.n
        ad_t = self._adjoint(g).T
        pi = ad_t @ (x[:n] + x[n:] * (0.5 * dt))
        inverse = lin.locked_inverse
        xi = inverse @ pi - lin.connection_qd
        a = ((xi @ self._ad_rows).reshape(n, n) + inverse @ self._form(pi)) * -dt
        b = (inverse @ ad_t) * dt
        # The top block row of Phi - 1 from t = [a, b, b dt/2]: t + (a t) c1 + (a a t) c2
        # with c1 = 1/2 (1/3 in the last block) and c2 = 1/6 (0): the series above.
        t = np.concatenate((a, b, b * (0.5 * dt)), axis=1)
        at = a @ t
        phi = self._eye.copy()
        phi[:n] += t + at * self._series1 + (a @ at) * self._series2
        phi[self._chain] = dt
        # Q_w = Ad_{g^-1}^T I diag(s^2) I Ad_{g^-1}; Ad_{g^-1} = Ad_g^-1 on the subgroup.
        scaled = self._adjoint_inverse(g).T @ lin.locked
        qa = ((scaled * self._jerk_var) @ scaled.T) * dt
        q = np.empty((3 * n, 3 * n))
        q[:n, :n] = lin.joint_cov * (dt * dt)
        # [Q_gmu, Q_gw] = [b dt^2/8, (b/6 + ab/24) dt] (1 x 2 blocks) times q.
        q[:n, n:] = (np.concatenate((b * (dt * dt / 8.0),
                                     (b / 6.0 + at[:, n:2 * n] / 24.0) * dt)) @ qa
                     ).reshape(2, n, n).transpose(1, 0, 2).reshape(n, 2 * n)
        q[n:, :n] = q[:n, n:].T
        # [[Q_mumu, Q_muw], [Q_wmu, Q_ww]] = [[dt^2/3, dt/2], [dt/2, 1]] (x) q.
        q[n:, n:] = (np.array([[dt * dt / 3.0, 0.5 * dt], [0.5 * dt, 1.0]])[:, None, :, None]
                     * qa[None, :, None, :]).reshape(2 * n, 2 * n)
        return phi, q

    def _transition_commanded(self, g: pin.SE3, x: np.ndarray, lin: Linearisation,
                              dt: float, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Return Phi and Q of the commanded-wrench filter (dense series, see _transition)."""
        n = self.n
        mu_mid = x[:n] + (x[n:2 * n] + self.delivered(g, x, u)) * (0.5 * dt)
        f = self.jacobian(g, mu_mid, lin)
        self.command_jacobian(f, g, x, u)
        fdt = f * dt
        f2 = fdt @ fdt
        phi = self._eye + fdt + 0.5 * f2 + (f2 @ fdt) / 6.0
        qc = np.zeros((self.dim, self.dim))
        qc[2 * n:3 * n, 2 * n:3 * n] = self.wrench_density(g, lin.locked)
        qc[3 * n:, 3 * n:] = self._command_density(lin.locked)
        # Van Loan's integral int_0^dt Phi(s) Qc Phi(s)^T ds as its Taylor series:
        # exact for the mu-w chain (nilpotent), fourth order in dt otherwise.
        a = qc * dt
        fa = fdt @ a
        f2a = fdt @ fa
        f3a = fdt @ f2a
        f2af = f2a @ fdt.T
        q = a + 0.5 * (fa + fa.T) + (f2a + f2a.T + 2.0 * fa @ fdt.T) / 6.0 \
            + (f3a + f3a.T + 3.0 * (f2af + f2af.T)) / 24.0
        # Encoder velocity noise held over the step: A Sigma A^T dt^2 on delta_g.
        q[:n, :n] += lin.joint_cov * (dt * dt)
        return phi, 0.5 * (q + q.T)

    def _command_density(self, locked: np.ndarray) -> np.ndarray:
        """Return the random-walk density of (k, b): gain drift, bias drift (body, by I)."""
        n = self.n
        drift = self.noise.command_gain_drift ** 2
        out = np.zeros((2 * n, 2 * n))
        out[:n, :n] = np.eye(n) * drift
        out[n:, n:] = (locked * (self._bias_var * drift)) @ locked.T
        return out

    def _command_prior(self, locked: np.ndarray) -> np.ndarray:
        """Return the prior covariance of (k, b): k = 1 +- gain, b = 0 +- I bias."""
        n = self.n
        out = np.zeros((2 * n, 2 * n))
        out[:n, :n] = np.eye(n) * self.noise.command_gain ** 2
        out[n:, n:] = (locked * self._bias_var) @ locked.T
        return out

    # --- the recursion ----------------------------------------------------------------
    def initialise(self, stamp_ns: int, g: pin.SE3, lin: Linearisation,
                   twist: Optional[np.ndarray], output: bool = True) -> None:
        """
        Start from a first measurement (pose, and the body twist with Odometry).

        ``output``: the recorded restart step is a row's (False: a measurement
        between rows, see :class:`FilterStep`).
        """
        n = self.n
        self.g = g
        self.stamp_ns = stamp_ns
        self._lin = lin
        to_world = self._adjoint_inverse(g).T @ lin.locked  # body velocity -> mu
        p = np.zeros((self.dim, self.dim))
        p[:n, :n] = np.diag(self._pose_var)
        if twist is None:
            mu = np.zeros(n)
            p[n:2 * n, n:2 * n] = (to_world * self._speed_var) @ to_world.T
        else:
            mu = to_world @ (twist + lin.connection_qd)
            p[n:2 * n, n:2 * n] = (to_world * self._twist_var) @ to_world.T \
                + to_world @ lin.joint_cov @ to_world.T
        p[2 * n:3 * n, 2 * n:3 * n] = (to_world * self._accel_var) @ to_world.T
        self.x = np.concatenate((mu, np.zeros(n)))
        if self.command:
            p[3 * n:, 3 * n:] = self._command_prior(lin.locked)
            self.x = np.concatenate((self.x, np.ones(n), np.zeros(n)))
        self.p = p
        self._stamp_twist = np.zeros(n) if twist is None else np.array(twist, dtype=float)
        self._stamp_twist_ns = stamp_ns
        self.step_test.reset(settle_from_ns=stamp_ns)
        if self.record:
            self.steps.append(FilterStep(stamp_ns, None, g, self.x, p, g, self.x, p,
                                         lin.locked_inverse, output, self._held_command()))

    def _held_command(self) -> Optional[np.ndarray]:
        """Return a copy of the command held now (commanded wrench only, else None)."""
        return self._command.copy() if self.command else None

    def _propagate(self, stamp_ns: int, lin: Linearisation,
                   command: Optional[Command]) -> np.ndarray:
        """
        Propagate mean and covariance to ``stamp_ns`` with inputs ``lin``; return Phi.

        ``command``: the commanded wrench over the step (commanded-wrench filters;
        None there: zero).
        """
        u = None
        if self.command:
            u = self._command_zero if command is None else command.mean
            self._command = self._command_zero if command is None else command.now
        dt = (stamp_ns - self.stamp_ns) * 1e-9
        if dt <= 0.0:
            self.step_test.propagate(stamp_ns, self._eye)
            return self._eye
        transition, q = self._transition(self.g, self.x, lin, dt, u)
        self.g, self.x = self.propagate_mean(self.g, self.x, lin, dt, u)
        p = transition @ self.p @ transition.T + q
        self.p = 0.5 * (p + p.T)
        self.stamp_ns = stamp_ns
        self.step_test.propagate(stamp_ns, transition)
        return transition

    def row(self, stamp_ns: int, lin: Linearisation, prior: Optional[Measurement],
            measurements: Sequence[Measurement] = (),
            commands: Optional[Sequence[Optional[Command]]] = None
            ) -> list[tuple[int, float]]:
        """
        Process one joint-state row at ``stamp_ns`` with its inputs ``lin``.

        Each base measurement stamped since the previous row updates the filter
        once, at its own stamp: the filter propagates to it with the joint inputs
        interpolated between the bracketing rows, updates, and propagates on to
        the row (robot_localization's order); a row without a measurement only
        propagates. A measurement at the row's stamp updates at the row.
        Measurements not after the filter's time (late) are skipped. Before the
        first row the filter starts from ``prior`` (the base state at the row's
        stamp) and skips the measurements it came from. ``commands``
        (commanded-wrench filters): the command over each step, one per
        measurement before the row's stamp, then the one of the step that ends at
        the row. Return the gated measurements as (stamp, NIS).
        """
        self.step_detected = None
        if self.g is None:
            if prior is not None:
                if self.command and commands:
                    self._command = commands[-1].now
                self.initialise(stamp_ns, prior.pose, lin, prior.twist)
            return []
        before = self._lin if self._lin is not None else lin
        self._lin = lin
        start = self.stamp_ns
        span = stamp_ns - start
        gated: list[tuple[int, float]] = []
        last: Optional[Measurement] = None
        done = 0.0  # fraction of the row's interval already propagated
        for index, measurement in enumerate(measurements):
            stamp = measurement.stamp_ns
            if stamp >= stamp_ns:
                if stamp == stamp_ns:
                    last = measurement
                break
            if stamp <= self.stamp_ns:
                continue
            fraction = (stamp - start) / span
            transition = self._propagate(stamp, between(before, lin, 0.5 * (done + fraction)),
                                         None if commands is None else commands[index])
            done = fraction
            self._measure(stamp, transition, measurement, between(before, lin, fraction),
                          False, gated)
        transition = self._propagate(stamp_ns, between(before, lin, 0.5 * (done + 1.0)),
                                     None if commands is None else commands[-1])
        self._measure(stamp_ns, transition, last, lin, True, gated)
        return gated

    def _measure(self, stamp_ns: int, transition: np.ndarray,
                 measurement: Optional[Measurement], lin: Linearisation, output: bool,
                 gated: list) -> None:
        """Update with ``measurement`` (if any) at the current time and record the step."""
        g_pred, x_pred, p_pred = self.g, self.x, self.p
        if measurement is not None:
            try:
                accepted = self._update(measurement.pose, measurement.twist, lin,
                                        measurement.stamp_sigma)
                broken = not (np.isfinite(self.p).all() and (np.diag(self.p) >= 0.0).all())
            except np.linalg.LinAlgError:
                accepted, broken = False, True
            if broken:
                # The covariance lost positive definiteness (noise settings far below
                # what the data do, e.g. tuned on stamps that are off by milliseconds):
                # start again from this measurement (a restart step) instead of failing.
                self.diverged += 1
                self.initialise(stamp_ns, measurement.pose, lin, measurement.twist, output)
                return
            if not accepted:
                gated.append((measurement.stamp_ns, self.last_nis))
        if self.record:
            self.steps.append(FilterStep(stamp_ns, transition, g_pred, x_pred, p_pred,
                                         self.g, self.x, self.p, lin.locked_inverse, output,
                                         self._held_command()))

    def step(self, stamp_ns: int, lin: Linearisation, pose: Optional[pin.SE3],
             twist: Optional[np.ndarray], command: Optional[Command] = None) -> bool:
        """
        Propagate to ``stamp_ns`` and update with the pose (and twist) when given.

        ``command``: the commanded wrench over the step (filters built with
        ``command=True``; None there means no command: zero).
        Return False when the measurement was gated out (counted in ``gated``).
        """
        measurement = None if pose is None else Measurement(stamp_ns, pose, twist)
        commands = None if command is None else (command,)
        if self.g is None:
            self.row(stamp_ns, lin, measurement, (), commands)
            return True
        return not self.row(stamp_ns, lin, None, () if measurement is None else (measurement,),
                            commands)

    def _update(self, pose: pin.SE3, twist: Optional[np.ndarray],
                lin: Linearisation, stamp_sigma: Optional[float] = None) -> bool:
        n, group = self.n, self.group
        g0, x0, p0 = self.g, self.x, self.p
        residual = group.log(g0.inverse() * pose)
        r_pose = self._r_pose
        if self.noise.pose_stamp > 0.0:
            # Stamp error dt: the measured pose is g exp(xi dt), so R += xi xi^T sigma_t^2,
            # with xi the body twist averaged over STAMP_TWIST_TIME: the estimate's own
            # transients (after a gate reset) must not weaken the poses that correct them.
            # A re-timed stamp (a frame time, estimator/retiming.py) carries its own.
            sigma = self.noise.pose_stamp if stamp_sigma is None else stamp_sigma
            xi = self._stamp_twist * sigma
            r_pose = r_pose + np.outer(xi, xi)
        if twist is None:
            # H = [1 0 0]: P H^T and H P H^T are blocks of P.
            h = None
            nu = residual
            r = r_pose
            ph = p0[:, :n]
            s = p0[:n, :n] + r
        else:
            h, nu = self._twist_measurement(g0, x0, pose, twist, lin, residual)
            r = np.zeros((2 * n, 2 * n))
            r[:n, :n] = r_pose
            r[n:, n:] = self._r_twist + lin.joint_cov
            ph = p0 @ h.T
            s = h @ ph + r
        s = 0.5 * (s + s.T)
        size = len(nu)
        # One solve for the gain and the NIS: S^-1 [(P H^T)^T, nu].
        solved = np.linalg.solve(s, np.column_stack((ph.T, nu)))
        nis = float(nu @ solved[:, -1])
        self.last_nis = nis
        # Innovation log-likelihood (what `reduced-dynamics tune` maximises) and NIS sums.
        sign, logdet = np.linalg.slogdet(s)
        self.log_likelihood -= 0.5 * (nis + logdet + size * LOG_2PI)
        self.nis_sum += nis
        self.nis_dof += size
        if nis > self._gates[size]:
            self.gated += 1
            self._gated_run += 1
            if h is None:
                self._gated_residuals.append((nu, r))
            if self._gated_run < GATE_RESET:
                return False
            p0 = p0.copy()
            offset = self._pose_offset()
            if offset is not None:
                # The sensor's pose stepped (see the module docstring): re-anchor the
                # pose by the offset's size; the momentum and the wrench are untouched.
                p0[:n, :n] += np.diag(offset ** 2)
                self.pose_offsets += 1
            else:
                # A momentum jump no wrench of the random walk explains, seen 3 times
                # in a row: believe it, with the prior spread of mu and w added.
                to_world = self._adjoint_inverse(g0).T @ lin.locked
                p0[n:2 * n, n:2 * n] += (to_world * self._speed_var) @ to_world.T
                p0[2 * n:3 * n, 2 * n:3 * n] += (to_world * self._accel_var) @ to_world.T
            self.p = p0
            # The step hypotheses described the filter before the jump: start afresh.
            self.step_test.reset()
            if h is None:
                ph = p0[:, :n]
                s = p0[:n, :n] + r
            else:
                ph = p0 @ h.T
                s = h @ ph + r
            solved = np.linalg.solve(s, ph.T)
        self._gated_run = 0
        self._gated_residuals = []
        gain = solved[:, :self.dim].T
        dx = gain @ nu
        if h is not None:
            # Iterated EKF (Gauss-Newton on the posterior): the twist is bilinear in
            # (g, mu), so one linearisation leaves a second-order miss where w steps.
            for _ in range(ITERATIONS):
                g_i = g0 * group.exp(dx[:n])
                h, nu_i = self._twist_measurement(g_i, x0 + dx[n:], pose, twist, lin, None)
                ph = p0 @ h.T
                s = h @ ph + r
                gain = np.linalg.solve(0.5 * (s + s.T), ph.T).T
                dx = gain @ (nu_i + h @ dx)
        self.g = g0 * group.exp(dx[:n])
        self.x = x0 + dx[n:]
        if h is None:
            keep = self._eye.copy()
            keep[:, :n] -= gain
        else:
            keep = self._eye - gain @ h
        p = keep @ p0 @ keep.T + gain @ r @ gain.T
        self.p = 0.5 * (p + p.T)
        if self.noise.pose_stamp > 0.0:
            last, self._stamp_twist_ns = self._stamp_twist_ns, self.stamp_ns
            dt = 0.0 if last is None else max(self.stamp_ns - last, 0) * 1e-9
            weight = min(1.0, dt / STAMP_TWIST_TIME)
            self._stamp_twist = self._stamp_twist + weight * (
                self.twist(self.g, self.x[:n], lin) - self._stamp_twist)
        detection = self.step_test.update(self._h_pose if h is None else h, s, gain, nu)
        if detection is not None:
            # A wrench step (thruster on/off: a jump, not a random walk): take its
            # maximum-likelihood size and its uncertainty (Willsky-Jones compensation).
            self.g = self.g * group.exp(detection.correction[:n])
            self.x = self.x + detection.correction[n:]
            p = self.p + detection.covariance
            self.p = 0.5 * (p + p.T)
            self.step_test.reset()
            self.step_detected = detection
            self.steps_taken += 1
        return True

    def _pose_offset(self) -> Optional[np.ndarray]:
        """
        Return the mean residual of the gated run when it is one constant pose offset.

        Offset hypothesis: every gated pose residual is the same offset plus its
        measurement noise R_k, so ``sum (r_k - r_mean)^T R_k^-1 (r_k - r_mean)`` is
        chi-square with n (K - 1) degrees of freedom (the prediction's own error is
        common to the run and cancels). A momentum jump large enough to be gated at
        its first pose moves the later residuals by several sigma per sample.
        None: not pose-only residuals, or not constant (a momentum jump).
        """
        runs = self._gated_residuals
        if len(runs) < 2 or len(runs) != self._gated_run:
            return None
        residuals = np.array([r for r, _ in runs])
        mean = residuals.mean(axis=0)
        spread = sum(float(d @ np.linalg.solve(noise, d))
                     for d, (_, noise) in zip(residuals - mean, runs))
        return mean if spread <= self._offset_threshold[len(runs)] else None

    def _twist_measurement(self, g: pin.SE3, x: np.ndarray, pose: pin.SE3,
                           twist: np.ndarray, lin: Linearisation,
                           residual: Optional[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """Return H and the innovation of pose and twist at (g, x) (``residual``: the pose's)."""
        n = self.n
        if residual is None:
            residual = self.group.log(g.inverse() * pose)
        ad_t = self._adjoint(g).T
        pi = ad_t @ x[:n]
        inverse = lin.locked_inverse
        h = np.zeros((2 * n, self.dim))
        h[:n, :n] = self._eye_n
        h[n:, :n] = -inverse @ self._form(pi)
        h[n:, n:2 * n] = inverse @ ad_t
        predicted = inverse @ pi - lin.connection_qd
        return h, np.concatenate((residual, twist - predicted))

    def state(self) -> FilterState:
        """Return the current estimate (copies)."""
        return FilterState(self.g, self.x.copy(), self.p.copy())


def smooth(group: BaseGroup, steps: Sequence[FilterStep]) -> list[FilterState]:
    """Return the smoothed state of every recorded step (:func:`smooth_backward`, in order)."""
    out: list[Optional[FilterState]] = [None] * len(steps)
    for k, state in smooth_backward(group, steps):
        out[k] = state
    return out  # type: ignore[return-value]


def smooth_backward(group: BaseGroup,
                    steps: Sequence[FilterStep]) -> Iterator[tuple[int, FilterState]]:
    """
    Run the Rauch-Tung-Striebel smoother backwards over recorded steps (error-state form).

    ``C_k = P_k Phi_{k+1}^T (P^-_{k+1})^-1``; the smoothed correction at k is
    ``C_k (x^s_{k+1} - x^-_{k+1})`` with the pose difference taken as
    ``log(g^-_{k+1}^-1 g^s_{k+1})``; ``P^s_k = P_k + C_k (P^s_{k+1} - P^-_{k+1}) C_k^T``.
    Yield (k, smoothed state) from the last step to the first; ``steps`` is read
    by index, backwards (a list, or the disk-backed store of .smoother).
    """
    count = len(steps)
    if not count:
        return
    n = group.dim
    last = steps[-1]
    g_s, x_s, p_s = state = FilterState(last.g, last.x.copy(), last.p.copy())
    yield count - 1, state
    for k in range(count - 2, -1, -1):
        step, after = steps[k], steps[k + 1]
        if after.transition is None:
            # A restart: the next step does not depend on this one.
            g_s, x_s, p_s = state = FilterState(step.g, step.x.copy(), step.p.copy())
            yield k, state
            continue
        cross = step.p @ after.transition.T
        try:
            gain = np.linalg.solve(after.p_pred, cross.T).T
        except np.linalg.LinAlgError:
            gain = cross @ np.linalg.pinv(after.p_pred)
        diff = np.concatenate((group.log(after.g_pred.inverse() * g_s), x_s - after.x_pred))
        dx = gain @ diff
        g_k = step.g * group.exp(dx[:n])
        x_k = step.x + dx[n:]
        p_k = step.p + gain @ (p_s - after.p_pred) @ gain.T
        g_s, x_s, p_s = g_k, x_k, 0.5 * (p_k + p_k.T)
        yield k, FilterState(g_s, x_s, p_s)
