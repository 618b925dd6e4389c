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
R is diagonal from the noise parameters, or the full covariance the sample's message
carried (:mod:`~reduced_dynamics.estimator.covariance`, docs/message_covariance.md).
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
a thruster switching at once (``x += D Delta``, ``P += D J^-1 D^T``). Frames a
stream delivers in a burst after a stall carry no timing and are left out
(:mod:`~reduced_dynamics.estimator.core.stalls`).

The arithmetic runs compiled (:mod:`~reduced_dynamics.estimator.core.kernels`,
docs/estimator_core.md). The covariance cannot break down: the process noise is a
sum of ``v Qc v^T`` terms and the update is P - K S K^T from a Cholesky factor of S
(docs/structured_step.md), both symmetric. A
covariance still not finite or with a negative variance (a corrupted input)
restarts the filter from the measurement, logged as a warning and counted by cause.

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

from collections import Counter
import logging
import math
from typing import Optional, Sequence

import numpy as np
import pinocchio as pin
from reduced_dynamics.chi_square import chi2

from reduced_dynamics.estimator import command_gain, step_row
from reduced_dynamics.estimator.core import kernels
from reduced_dynamics.estimator.core.smoother import smooth
from reduced_dynamics.estimator.core.stalls import StallDetector
from reduced_dynamics.estimator.core.state import (Command, FilterState, FilterStep,
                                                   Linearisation, Measurement, NoiseModel,
                                                   between)
from reduced_dynamics.estimator.events import StepDetection, WrenchStepTest
from reduced_dynamics.geometry.lie_group import BaseGroup

__all__ = ['Command', 'FilterState', 'FilterStep', 'Linearisation', 'Measurement',
           'MomentumFilter', 'NoiseModel', 'between', 'smooth']

LOG = logging.getLogger(__name__)

#: Consecutive gated measurements after which a momentum jump is accepted.
GATE_RESET = 3
#: False-alarm probability of the test that a run of gated poses is a constant offset
#: (a mocap body re-fitted to other markers) rather than a momentum jump.
OFFSET_PROBABILITY = 1e-3
#: Time constant [s] of the twist average that scales the pose stamp noise.
STAMP_TWIST_TIME = 0.5
#: The covariance cap of a coast [s]: a row whose filter went longer than this without a
#: base measurement restarts from the row's base state (restart cause ``coast``) instead
#: of propagating over the gap. Over a gap T the momentum's variance grows by the wrench
#: random walk integrated twice (~T^3): after a minute of lost odometry it reached ~1e8
#: times its steady value and, over ten minutes, lost positive definiteness
#: (test/test_mission_soak.py); a fresh start from the measurement says more.
MAX_COAST_S = 10.0
#: Re-linearisations of an update with a twist (iterated EKF).
ITERATIONS = kernels.ITERATIONS
LOG_2PI = math.log(2.0 * math.pi)
_EMPTY = np.zeros(0)
#: Restart causes by ``kernels.covariance_health`` code (0: healthy).
_HEALTH_CAUSES = (None, 'covariance not finite', 'negative variance')


def _axis_kinds(group: BaseGroup) -> np.ndarray:
    """Return True for algebra coordinates that rotate (angular), else False."""
    basis = group.algebra_basis
    return np.abs(basis[3:]).sum(axis=0) > 0.0


def _homogeneous(g: Optional[pin.SE3]) -> Optional[np.ndarray]:
    return None if g is None else np.ascontiguousarray(g.homogeneous)


class MomentumFilter:
    """
    The error-state Kalman filter on G x R^n x R^n (see the module docstring).

    :meth:`row` processes one joint-state row with the base measurements
    stamped since the previous one (each updates once, at its own stamp);
    :meth:`step` is the row with one measurement at the row's stamp. ``record``
    keeps the steps for :func:`smooth`. The arithmetic is in
    :mod:`~reduced_dynamics.estimator.core.kernels` (compiled); this class holds
    the state, the gating decisions and the step test.

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
        #: the pose as a 4 x 4 homogeneous array (``g`` is its pin.SE3 view)
        self._g: Optional[np.ndarray] = None
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
        self._command_density = np.zeros((2 * n, 2 * n))
        if command:
            self._bias_var = np.where(angular, noise.command_bias_angular ** 2,
                                      noise.command_bias_linear ** 2)
            self._jerk_var = np.where(angular, noise.disturbance_angular ** 2,
                                      noise.disturbance_linear ** 2)
            self._command = np.zeros(n)
            self._command_zero = np.zeros(n)
        #: prior sigmas of (k, b) (commanded wrench; set at initialisation)
        self.command_prior_sigma = np.zeros(2 * n)
        #: updates whose gain estimate was projected onto k >= command_gain.GAIN_FLOOR
        self.gain_projections = 0
        #: sum of the innovations' log-likelihoods, of their NIS and of their dimensions
        self.log_likelihood = 0.0
        self.nis_sum = 0.0
        self.nis_dof = 0
        self._lin: Optional[Linearisation] = None
        # Structure constants as matrices: ad(eta) = (eta @ ad_rows).reshape(n, n) and
        # W(pi) = (form_rows @ pi).reshape(n, n) (kernels.form).
        structure = group.structure_constants
        self._ad_rows = np.ascontiguousarray(structure.reshape(n, n * n))
        self._form_rows = np.ascontiguousarray(structure.transpose(0, 2, 1).reshape(n * n, n))
        self._whole = group.is_whole
        self._basis = np.ascontiguousarray(group.algebra_basis)
        self._pinv = np.ascontiguousarray(group.algebra_pinv)
        self._r_pose = np.diag(self._pose_var)
        self._r_twist = np.diag(self._twist_var)
        self._twist_zero = np.zeros(n)
        self.step_test = WrenchStepTest(n, step_significance, dim)
        #: the wrench step taken since the last row (None: none detected)
        self.step_detected: Optional[StepDetection] = None
        self.steps_taken = 0
        #: re-initialisations (last resort: the covariance broke down), and by cause
        self.diverged = 0
        self.restart_causes: Counter = Counter()
        # Body twist averaged over STAMP_TWIST_TIME (pose stamp noise) and its time.
        self._stamp_twist = np.zeros(n)
        self._stamp_twist_ns: Optional[int] = None
        #: stalls of the base stream and their bursts (core/stalls.py)
        self.stalls = StallDetector()
        #: measurements left out as a burst after a stall of their stream
        self.burst_skipped = 0
        # H of a pose measurement, [1 0 0] (the step test's signatures need it).
        self._h_pose = np.zeros((n, dim))
        self._h_pose[:, :n] = np.eye(n)
        # The row step's outputs the filter reads only on a rare outcome or to record a
        # step (step_row.filter_step): the prediction g, x, P, Phi, then nu, R, H, S, K
        # (top-left corners: innovations of n or 2n coordinates). Written in place by every
        # row: what is kept is copied out.
        self._work_buffer = np.zeros(step_row.work_size(n, dim))
        self._work = step_row.work_views(self._work_buffer, n, dim)
        #: (the step test they are of, filter_step's fixed arguments): built at the first row
        self._row_fixed: tuple = (None, ())
        #: (P, x, w^T P_ww^-1 w) of the last fused step (kernels.propagate_update)
        self._fused_significance: Optional[tuple] = None

    # --- the pose -----------------------------------------------------------------
    @property
    def g(self) -> Optional[pin.SE3]:
        """Return the base pose estimate (None before the first measurement)."""
        return None if self._g is None else pin.SE3(self._g)

    @g.setter
    def g(self, value: Optional[pin.SE3]) -> None:
        self._g = _homogeneous(value)

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

    @property
    def gain(self) -> np.ndarray:
        """Return the per-axis gain k of the delivered wrench (commanded wrench only)."""
        return self.x[2 * self.n:3 * self.n]

    @property
    def bias(self) -> np.ndarray:
        """Return the per-axis bias b of the delivered body wrench (commanded wrench only)."""
        return self.x[3 * self.n:]

    def body_momentum(self) -> np.ndarray:
        """Return pi = Ad_g^T mu (the momentum in the base frame) of the current estimate."""
        return kernels.adjoint(self._g, self._basis, self._pinv, self._whole).T @ self.mu

    def delivered(self, g: pin.SE3, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Return the delivered wrench Ad_{g^-1}^T (k o u + b) in the world frame."""
        return kernels.delivered(_homogeneous(g), x, u, self._basis, self._pinv, self._whole)

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
        """
        Return w^T P_ww^-1 w (chi-square with n degrees of freedom when w = 0).

        Commanded wrench: an unidentified gain on an axis being commanded adds
        the wrench it may be off by to P_ww (command_gain.mismatch_covariance):
        its error is not an external wrench.
        """
        if self.command and self._g is not None and self._command.any():
            unidentified = ~command_gain.gains_identified(
                self.p, self.n, self.command_prior_sigma) & (self._command != 0.0)
            if unidentified.any():
                n = self.n
                w = self.x[n:2 * n]
                cov = self.p[2 * n:3 * n, 2 * n:3 * n] + command_gain.mismatch_covariance(
                    self.p, n, self._adjoint_inverse(self.g).T, self._command, unidentified)
                return float(w @ np.linalg.solve(cov, w))
        fused = self._fused_significance
        if fused is not None and self.p is fused[0] and self.x is fused[1]:
            return fused[2]  # computed by the last fused step, for this very state
        return kernels.significance(self.x, self.p, self.n)

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

    def twist(self, g: pin.SE3, mu: np.ndarray, lin: Linearisation) -> np.ndarray:
        """Return xi = I^-1 Ad_g^T mu - A qbar_dot (reconstruction)."""
        return kernels.twist(_homogeneous(g), mu, lin.locked_inverse, lin.connection_qd,
                             self._basis, self._pinv, self._whole)

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

    def twist_jacobian(self, g: pin.SE3, mu: np.ndarray, lin: Linearisation) -> np.ndarray:
        """Return H of the twist measurement (n x 3n)."""
        x = np.zeros(self.dim - self.n)
        x[:self.n] = mu
        h, _ = kernels.twist_measurement(_homogeneous(g), x, _homogeneous(g), np.zeros(self.n),
                                         lin.locked_inverse, lin.connection_qd, self.dim,
                                         self._basis, self._pinv, self._whole,
                                         self._form_rows)
        return h[self.n:]

    def wrench_density(self, g: pin.SE3, locked: np.ndarray) -> np.ndarray:
        """Return the spectral density of w_dot: Ad_{g^-1}^T I diag(s^2) I Ad_{g^-1}."""
        scaled = self._adjoint_inverse(g).T @ locked
        return (scaled * self._jerk_var) @ scaled.T

    def _command_input(self, u: Optional[np.ndarray]) -> np.ndarray:
        return _EMPTY if u is None else np.asarray(u, dtype=float)

    def _densities(self, lin: Linearisation) -> np.ndarray:
        """Return the random-walk density of (k, b) (commanded wrench; else unused)."""
        if not self.command:
            return self._command_density
        n = self.n
        drift = self.noise.command_gain_drift ** 2
        out = np.zeros((2 * n, 2 * n))
        out[:n, :n] = np.eye(n) * drift
        out[n:, n:] = (lin.locked * (self._bias_var * drift)) @ lin.locked.T
        return out

    def propagate_mean(self, g: pin.SE3, x: np.ndarray, lin: Linearisation,
                       dt: float, u: Optional[np.ndarray] = None
                       ) -> tuple[pin.SE3, np.ndarray]:
        """
        Return (g, x) after dt: midpoint rule on the group, mu exact for constant w.

        ``u`` (commanded wrench): the command's mean over the step; the
        delivered wrench is taken at the pose of the step's middle.
        """
        g1, x1 = kernels.propagate_mean(_homogeneous(g), x, lin.locked_inverse,
                                        lin.connection_qd, dt, self._command_input(u),
                                        u is not None, self._basis, self._pinv, self._whole)
        return pin.SE3(g1), x1

    def _transition(self, g: pin.SE3, x: np.ndarray, lin: Linearisation,
                    dt: float, u: Optional[np.ndarray] = None
                    ) -> tuple[np.ndarray, np.ndarray]:
        """Return Phi = exp(F dt) (third order) and Q (kernels.transition and _commanded)."""
        if u is not None:
            return kernels.transition_commanded(
                _homogeneous(g), x, lin.locked, lin.locked_inverse, lin.connection_qd,
                lin.joint_cov, dt, np.asarray(u, dtype=float), self._jerk_var,
                self._densities(lin), self._basis, self._pinv, self._whole, self._ad_rows,
                self._form_rows)
        return kernels.transition(_homogeneous(g), x, lin.locked, lin.locked_inverse,
                                  lin.connection_qd, lin.joint_cov, dt, self._jerk_var,
                                  self._basis, self._pinv, self._whole, self._ad_rows,
                                  self._form_rows)

    def _command_prior(self, locked: np.ndarray) -> np.ndarray:
        """Return the prior covariance of (k, b): k = 1 +- gain, b = 0 +- I bias."""
        n = self.n
        out = np.zeros((2 * n, 2 * n))
        out[:n, :n] = np.eye(n) * self.noise.command_gain ** 2
        out[n:, n:] = (locked * self._bias_var) @ locked.T
        return out

    # --- the recursion ----------------------------------------------------------------
    def initialise(self, stamp_ns: int, g: pin.SE3, lin: Linearisation,
                   twist: Optional[np.ndarray], output: bool = True,
                   noise: Optional[tuple] = None) -> None:
        """
        Start from a first measurement (pose, and the body twist with Odometry).

        ``output``: the recorded restart step is a row's (False: a measurement
        between rows, see :class:`FilterStep`). ``noise``: the measurement's own
        (:attr:`Measurement.noise`; None: the noise parameters).
        """
        n = self.n
        self._g = pose = _homogeneous(g)
        self.stamp_ns = stamp_ns
        self._lin = lin
        to_world = self._adjoint_inverse(g).T @ lin.locked  # body velocity -> mu
        p = np.zeros((self.dim, self.dim))
        own_pose, own_twist = (None, None) if noise is None else noise
        p[:n, :n] = np.diag(self._pose_var) if own_pose is None else own_pose
        if twist is None:
            mu = np.zeros(n)
            p[n:2 * n, n:2 * n] = (to_world * self._speed_var) @ to_world.T
        else:
            mu = to_world @ (twist + lin.connection_qd)
            if own_twist is None:
                p[n:2 * n, n:2 * n] = (to_world * self._twist_var) @ to_world.T \
                    + to_world @ lin.joint_cov @ to_world.T
            else:
                p[n:2 * n, n:2 * n] = to_world @ (lin.joint_cov + own_twist) @ to_world.T
        p[2 * n:3 * n, 2 * n:3 * n] = (to_world * self._accel_var) @ to_world.T
        self.x = np.concatenate((mu, np.zeros(n)))
        if self.command:
            p[3 * n:, 3 * n:] = self._command_prior(lin.locked)
            self.command_prior_sigma = np.sqrt(np.diag(p[3 * n:, 3 * n:]))
            self.x = np.concatenate((self.x, np.ones(n), np.zeros(n)))
        self.p = p
        self._stamp_twist = np.zeros(n) if twist is None else np.array(twist, dtype=float)
        self._stamp_twist_ns = stamp_ns
        self.step_test.reset(settle_from_ns=stamp_ns)
        if self.record:
            self.steps.append(FilterStep(stamp_ns, None, pose, self.x, p, pose, self.x, p,
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
        u = _EMPTY
        if self.command:
            u = self._command_zero if command is None else command.mean
            self._command = self._command_zero if command is None else command.now
        dt = (stamp_ns - self.stamp_ns) * 1e-9
        if dt <= 0.0:
            self.step_test.propagate(stamp_ns, self._eye)
            return self._eye
        test = self.step_test
        if not self.command and test.active:
            # The step test's propagate in the same compiled call (step_row.py).
            out = step_row.propagate_step(
                self._g, self.x, self.p, lin.locked, lin.locked_inverse, lin.connection_qd,
                lin.joint_cov, dt, u, self._jerk_var, self._densities(lin), self._basis,
                self._pinv, self._whole, self._ad_rows, self._form_rows, stamp_ns,
                *test.compiled_arrays, self._work_buffer)
            self._g, self.x, self.p = out
            self.stamp_ns = stamp_ns
            # Phi in the work arrays: read only to record the step (a copy: written again).
            return self._work[3].copy() if self.record else self._work[3]
        self._g, self.x, self.p, transition = kernels.propagate(
            self._g, self.x, self.p, lin.locked, lin.locked_inverse, lin.connection_qd,
            lin.joint_cov, dt, u, self.command, self._jerk_var, self._densities(lin),
            self._basis, self._pinv, self._whole, self._ad_rows, self._form_rows)
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
        if self._g is None:
            if prior is not None:
                if self.command and commands:
                    self._command = commands[-1].now
                self.initialise(stamp_ns, prior.pose, lin, prior.twist, True, prior.noise)
            return []
        if prior is not None and self._coasted(stamp_ns, measurements):
            self.restart_causes['coast'] += 1
            LOG.warning('momentum filter restarted at %d ns: %.3g s without a base '
                        'measurement (more than %g s)', stamp_ns,
                        (stamp_ns - self.stamp_ns) * 1e-9, MAX_COAST_S)
            self.initialise(stamp_ns, prior.pose, lin, prior.twist, True, prior.noise)
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
            self._step_to(stamp, between(before, lin, 0.5 * (done + fraction)),
                          None if commands is None else commands[index], measurement,
                          between(before, lin, fraction), False, gated)
            done = fraction
        # A measurement at the row with none before it in the interval: the step's
        # inputs are the rows' mean, which the compiled row step forms itself.
        midway = done == 0.0 and last is not None
        self._step_to(stamp_ns, None if midway else between(before, lin, 0.5 * (done + 1.0)),
                      None if commands is None else commands[-1], last, lin, True, gated,
                      before if midway else None)
        return gated

    def _step_to(self, stamp_ns: int, step: Optional[Linearisation],
                 command: Optional[Command], measurement: Optional[Measurement],
                 lin: Linearisation, output: bool, gated: list,
                 before: Optional[Linearisation] = None) -> None:
        """
        Propagate to ``stamp_ns`` with inputs ``step``, then measure (:meth:`_measure`).

        The common step (no commanded wrench, the noise parameters, not a burst) runs
        as one compiled call (``kernels.propagate_update``) doing the same operations
        as :meth:`_propagate` and :meth:`_update` one after the other; with the step
        test on and ``before`` given (``step`` None: the mean of ``before`` and
        ``lin``), the step test's share of the step joins that call
        (:mod:`~reduced_dynamics.estimator.step_row`).
        """
        burst = None
        if measurement is not None and not self.command and measurement.noise is None \
                and stamp_ns > self.stamp_ns:
            burst = self.stalls.in_burst(measurement.stamp_ns) \
                and measurement.stamp_sigma is None
            if not burst and before is not None and self.step_test.active \
                    and self._row_measured(stamp_ns, before, measurement, lin, output, gated):
                return
            if step is None:
                step = between(before, lin, 0.5)
            if not burst:
                fused = self._fused_step(stamp_ns, step, measurement, lin)
                if fused is not None:
                    self._measure(stamp_ns, fused[3], measurement, lin, output, gated,
                                  burst=False, fused=fused)
                    return
        if step is None:
            step = between(before, lin, 0.5)
        transition = self._propagate(stamp_ns, step, command)
        self._measure(stamp_ns, transition, measurement, lin, output, gated, burst=burst)

    def _stamp_noise(self, stamp_ns: int, measurement: Measurement) -> tuple[float, float]:
        """Return the stamp sigma and the stamp twist's average weight of a fused step."""
        if not self.noise.pose_stamp > 0.0:
            return 0.0, -1.0
        sigma = self.noise.pose_stamp if measurement.stamp_sigma is None \
            else measurement.stamp_sigma
        # The stamp twist's average weight of _update (the time since its last move).
        last = self._stamp_twist_ns
        dt = 0.0 if last is None else max(stamp_ns - last, 0) * 1e-9
        return sigma, min(1.0, dt / STAMP_TWIST_TIME)

    def _row_measured(self, stamp_ns: int, before: Linearisation, measurement: Measurement,
                      lin: Linearisation, output: bool, gated: list) -> bool:
        """
        Run ``step_row.filter_step`` (:meth:`_fused_step` and the step test's share) and measure.

        The common outcome (accepted into a healthy covariance, the step test's bank
        open) is taken here with :meth:`_update`'s bookkeeping in the same order; any
        other goes on to :meth:`_measure` with the call's results, as before. Return
        False when the call raised (nothing changed: the caller takes the separate calls).
        """
        twist = measurement.twist
        with_twist = twist is not None
        size = 2 * self.n if with_twist else self.n
        noise = self.noise
        if noise.pose_stamp > 0.0:
            # _stamp_noise's arithmetic, inline (a row's hot path).
            sigma = noise.pose_stamp if measurement.stamp_sigma is None \
                else measurement.stamp_sigma
            last = self._stamp_twist_ns
            dt = 0.0 if last is None else max(stamp_ns - last, 0) * 1e-9
            weight = min(1.0, dt / STAMP_TWIST_TIME)
        else:
            sigma, weight = 0.0, -1.0
        test = self.step_test
        fixed = self._row_fixed
        if fixed[0] is not test:
            fixed = self._row_fixed = self._fixed_arguments()
        try:
            (g1, x1, p1, accepted, nis, logdet, health, wrench_test, tested, evidence, best,
             statistic, top, evaluated) = step_row.filter_step(
                self._g, self.x, self.p, lin.locked, before.locked_inverse,
                before.connection_qd, (stamp_ns - self.stamp_ns) * 1e-9,
                np.ascontiguousarray(measurement.pose.homogeneous),
                _EMPTY if twist is None else np.asarray(twist, dtype=float), with_twist,
                lin.locked_inverse, lin.connection_qd, lin.joint_cov, self._stamp_twist, sigma,
                self._gates[size], weight, stamp_ns, *fixed[1])
        except (np.linalg.LinAlgError, ZeroDivisionError):
            return False
        self.stamp_ns = stamp_ns
        self._fused_significance = (p1, x1, wrench_test)
        if not tested:
            # Gated, a broken covariance or no onset open: the general path, with
            # propagate_update's results as _fused_step gives them (copies of the work
            # arrays; when gated, the update's state is the prediction itself).
            if accepted:
                work = self._work
                self._g, self.x, self.p = work[0].copy(), work[1].copy(), work[2].copy()
            else:
                self._g, self.x, self.p = g1, x1, p1
            fused = self._work_results(size, accepted, nis, logdet, g1, x1, p1, health,
                                       wrench_test)
            self._measure(stamp_ns, fused[3], measurement, lin, output, gated, burst=False,
                          fused=fused)
            return True
        # _update's bookkeeping of an accepted fused update, in its order.
        self.last_nis = nis
        self.log_likelihood -= 0.5 * (nis + logdet + size * LOG_2PI)
        self.nis_sum += nis
        self.nis_dof += size
        self._gated_run = 0
        self._gated_residuals = []
        self._g, self.x, self.p = g1, x1, p1
        if noise.pose_stamp > 0.0:
            self._stamp_twist_ns = stamp_ns  # the average moved in place (filter_step)
        cause = None
        if evidence:
            # The step test took the update (filter_step); its outcome, from Python.
            try:
                detection = test._evaluated(best, statistic, top, evaluated)
                if detection is not None:
                    self._take_step(detection)
                    cause = self._health_cause()
            except (np.linalg.LinAlgError, ZeroDivisionError) as error:
                cause = 'covariance not finite' if not np.isfinite(self.p).all() \
                    else f'singular matrix ({error})'
        if cause is not None:
            self._restart(stamp_ns, cause, measurement, lin, output)
        elif self.record:
            # Copies: the work arrays are written again by the next row.
            work_g, work_x, work_p, work_phi = self._work[:4]
            self.steps.append(FilterStep(stamp_ns, work_phi.copy(), work_g.copy(),
                                         work_x.copy(), work_p.copy(), self._g, self.x,
                                         self.p, lin.locked_inverse, output,
                                         self._held_command()))
        return True

    def _fixed_arguments(self) -> tuple:
        """Return (the step test, step_row.filter_step's arguments fixed for the filter)."""
        test = self.step_test
        return test, (self._jerk_var, self._pose_var, self._twist_var, self._basis,
                      self._pinv, self._whole, self._ad_rows, self._form_rows, self._h_pose,
                      *test.compiled_arrays, self._work_buffer)

    def _work_results(self, size: int, accepted: bool, nis: float, logdet: float,
                      g1: np.ndarray, x1: np.ndarray, p1: np.ndarray, health: int,
                      wrench_test: float) -> tuple:
        """Return ``kernels.propagate_update``'s results from a row step's work arrays."""
        g0, x0, p0 = self._g, self.x, self.p
        _, _, _, phi, nu, r, h, s, gain = self._work
        if not accepted:
            g1, x1, p1 = g0, x0, p0
        return (g0, x0, p0, phi.copy(), accepted, nis, logdet, nu[:size].copy(),
                r[:size, :size].copy(), g1, x1, p1, h[:size].copy(), s[:size, :size].copy(),
                gain[:, :size].copy(), health, self._stamp_twist, wrench_test)

    def _take_step(self, detection: StepDetection) -> None:
        """Take a detected wrench step (Willsky-Jones compensation); forget the hypotheses."""
        # A wrench step (thruster on/off: a jump, not a random walk): take its
        # maximum-likelihood size and its uncertainty.
        self._g, self.x, self.p = kernels.compensate(
            self._g, self.x, self.p, detection.correction, detection.covariance,
            self._basis, self._whole)
        self.step_test.reset()
        self.step_detected = detection
        self.steps_taken += 1

    def _health_cause(self) -> Optional[str]:
        """Return why the covariance is unusable (a restart's cause), or None."""
        if not np.isfinite(self.p).all():
            return 'covariance not finite'
        if not (np.diag(self.p) >= 0.0).all():
            return 'negative variance'
        return None

    def _restart(self, stamp_ns: int, cause: str, measurement: Measurement,
                 lin: Linearisation, output: bool) -> None:
        """Start again from ``measurement``: the last resort, logged and counted by cause."""
        # The update keeps P positive semi-definite (measured over long runs,
        # docs/structured_step.md), so this takes a covariance corrupted before the
        # update (a non-finite input, an overflow), or an S that is not positive definite.
        self.diverged += 1
        self.restart_causes[cause] += 1
        LOG.warning('momentum filter restarted at %d ns: %s (restart %d)',
                    stamp_ns, cause, self.diverged)
        self.initialise(stamp_ns, measurement.pose, lin, measurement.twist, output,
                        measurement.noise)

    def _fused_step(self, stamp_ns: int, step: Linearisation, measurement: Measurement,
                    lin: Linearisation) -> Optional[tuple]:
        """
        Run ``kernels.propagate_update``; take its prediction as :meth:`_propagate` does.

        Return its results, or None when it raised (the caller then takes the two
        steps one by one, which raise or restart as they always did).
        """
        twist = measurement.twist
        with_twist = twist is not None
        values = _EMPTY if twist is None else np.asarray(twist, dtype=float)
        sigma, weight = self._stamp_noise(stamp_ns, measurement)
        try:
            fused = kernels.propagate_update(
                self._g, self.x, self.p, step.locked, step.locked_inverse,
                step.connection_qd, step.joint_cov, (stamp_ns - self.stamp_ns) * 1e-9,
                self._jerk_var, np.ascontiguousarray(measurement.pose.homogeneous), values,
                with_twist, lin.locked_inverse, lin.connection_qd, lin.joint_cov,
                self._pose_var, self._stamp_twist, sigma, self._twist_var,
                self._gates[2 * self.n if with_twist else self.n], weight, self._basis,
                self._pinv, self._whole, self._ad_rows, self._form_rows)
        except (np.linalg.LinAlgError, ZeroDivisionError):
            return None
        self._g, self.x, self.p = fused[0], fused[1], fused[2]
        self.stamp_ns = stamp_ns
        self._fused_significance = (fused[11], fused[10], fused[17])
        self.step_test.propagate(stamp_ns, fused[3])
        return fused

    def _coasted(self, stamp_ns: int, measurements: Sequence[Measurement]) -> bool:
        """Whether the filter would go more than MAX_COAST_S without a base measurement."""
        cap = MAX_COAST_S * 1e9
        if stamp_ns - self.stamp_ns <= cap:
            return False  # the hot path: one comparison
        times = [self.stamp_ns] + [m.stamp_ns for m in measurements
                                   if m is not None and m.stamp_ns > self.stamp_ns] + [stamp_ns]
        return max(b - a for a, b in zip(times, times[1:])) > cap

    def _measure(self, stamp_ns: int, transition: np.ndarray,
                 measurement: Optional[Measurement], lin: Linearisation, output: bool,
                 gated: list, burst: Optional[bool] = None,
                 fused: Optional[tuple] = None) -> None:
        """
        Update with ``measurement`` (if any) at the current time and record the step.

        ``burst``: whether the measurement is a burst's (None: ask the stall detector).
        ``fused``: ``kernels.propagate_update``'s results (the update already done).
        """
        g_pred, x_pred, p_pred = self._g, self.x, self.p
        if burst is None:
            burst = measurement is not None and self.stalls.in_burst(measurement.stamp_ns) \
                and measurement.stamp_sigma is None
        if burst:
            # A frame of a burst after a stall (core/stalls.py): its stamp says nothing of
            # when it was taken. A re-timed stamp (its own sigma) is a frame time: kept.
            self.burst_skipped += 1
            measurement = None
        if measurement is not None:
            cause = None
            try:
                accepted = self._update(measurement.pose, measurement.twist, lin,
                                        measurement.stamp_sigma, measurement.noise, fused)
                if fused is not None and self.p is fused[11]:
                    # The compiled call checked this covariance already.
                    cause = _HEALTH_CAUSES[fused[15]]
                else:
                    cause = self._health_cause()
            except (np.linalg.LinAlgError, ZeroDivisionError) as error:
                accepted = False
                cause = 'covariance not finite' if not np.isfinite(self.p).all() \
                    else f'singular matrix ({error})'
            if cause is not None:
                self._restart(stamp_ns, cause, measurement, lin, output)
                return
            if not accepted:
                gated.append((measurement.stamp_ns, self.last_nis))
        if self.record:
            self.steps.append(FilterStep(stamp_ns, transition, g_pred, x_pred, p_pred,
                                         self._g, self.x, self.p, lin.locked_inverse, output,
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
        if self._g is None:
            self.row(stamp_ns, lin, measurement, (), commands)
            return True
        return not self.row(stamp_ns, lin, None, () if measurement is None else (measurement,),
                            commands)

    def _update(self, pose: pin.SE3, twist: Optional[np.ndarray],
                lin: Linearisation, stamp_sigma: Optional[float] = None,
                noise: Optional[tuple] = None, fused: Optional[tuple] = None) -> bool:
        """Update with a measurement (``fused``: the compiled call's results, already done)."""
        n = self.n
        g0, x0, p0 = self._g, self.x, self.p
        measured = np.ascontiguousarray(pose.homogeneous)
        with_twist = twist is not None
        values = _EMPTY if twist is None else np.asarray(twist, dtype=float)
        sigma = 0.0
        if self.noise.pose_stamp > 0.0:
            # Stamp error dt: the measured pose is g exp(xi dt), so R += xi xi^T sigma_t^2,
            # with xi the body twist averaged over STAMP_TWIST_TIME: the estimate's own
            # transients (after a gate reset) must not weaken the poses that correct them.
            # A re-timed stamp (a frame time, estimator/retiming.py) carries its own.
            sigma = self.noise.pose_stamp if stamp_sigma is None else stamp_sigma
        size = 2 * n if with_twist else n
        if fused is not None:
            accepted, nis, logdet, nu, r, g1, x1, p1, h, s, gain = fused[4:15]
        elif noise is None:
            accepted, nis, logdet, nu, r, g1, x1, p1, h, s, gain = kernels.update(
                g0, x0, p0, measured, values, with_twist, lin.locked_inverse,
                lin.connection_qd, lin.joint_cov, self._pose_var, self._stamp_twist, sigma,
                self._twist_var, self._gates[size], self._basis, self._pinv, self._whole,
                self._form_rows)
        else:
            # The message's own covariances (estimator/covariance.py), full matrices; a
            # part the message left unknown keeps the noise parameters.
            r_pose = self._r_pose if noise[0] is None else noise[0]
            if sigma > 0.0:
                xi = self._stamp_twist * sigma
                r_pose = r_pose + np.outer(xi, xi)
            joint_cov, twist_var = lin.joint_cov, self._twist_var
            if with_twist and noise[1] is not None:
                joint_cov, twist_var = joint_cov + noise[1], self._twist_zero
            accepted, nis, logdet, nu, r, g1, x1, p1, h, s, gain = kernels.update_noise(
                g0, x0, p0, measured, values, with_twist, lin.locked_inverse,
                lin.connection_qd, joint_cov, r_pose, twist_var, self._gates[size],
                self._basis, self._pinv, self._whole, self._form_rows)
        self.last_nis = nis
        # Innovation log-likelihood (what `reduced-dynamics tune` maximises) and NIS sums.
        self.log_likelihood -= 0.5 * (nis + logdet + size * LOG_2PI)
        self.nis_sum += nis
        self.nis_dof += size
        if not accepted:
            self._gated_run += 1
            if not with_twist:
                self._gated_residuals.append((nu, r))
            if self._gated_run < GATE_RESET:
                # Counted only when rejected: ``gated`` is the measurements not used (the
                # pipeline's innovation_gate rejections), not those over the gate.
                self.gated += 1
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
                to_world = self._adjoint_inverse(pin.SE3(g0)).T @ lin.locked
                p0[n:2 * n, n:2 * n] += (to_world * self._speed_var) @ to_world.T
                p0[2 * n:3 * n, 2 * n:3 * n] += (to_world * self._accel_var) @ to_world.T
            self.p = p0
            # The step hypotheses described the filter before the jump: start afresh.
            self.step_test.reset()
            g1, x1, p1, h, s, gain = kernels.correct(
                g0, x0, p0, measured, values, with_twist, h, nu, r,
                kernels.gain_of(p0, h, r), lin.locked_inverse, lin.connection_qd,
                self._basis, self._pinv, self._whole, self._form_rows)
        self._gated_run = 0
        self._gated_residuals = []
        self._g, self.x, self.p = g1, x1, p1
        if self.noise.pose_stamp > 0.0 and fused is not None and p1 is fused[11]:
            # Accepted at once: the compiled call moved the average (same operations).
            self._stamp_twist_ns = self.stamp_ns
            self._stamp_twist = fused[16]
        elif self.noise.pose_stamp > 0.0:
            last, self._stamp_twist_ns = self._stamp_twist_ns, self.stamp_ns
            dt = 0.0 if last is None else max(self.stamp_ns - last, 0) * 1e-9
            weight = min(1.0, dt / STAMP_TWIST_TIME)
            self._stamp_twist = self._stamp_twist + weight * (kernels.twist(
                g1, x1[:n], lin.locked_inverse, lin.connection_qd, self._basis, self._pinv,
                self._whole) - self._stamp_twist)
        detection = self.step_test.update(self._h_pose if not with_twist else h, s, gain, nu)
        if detection is not None:
            self._take_step(detection)
        if self.command:
            self._constrain_gains()
        return True

    def _constrain_gains(self) -> None:
        """Project the gains onto k >= GAIN_FLOOR (command_gain.py: Simon & Chia)."""
        correction = command_gain.project_gains(self.x, self.p, self.n)
        if correction is None:
            return
        self._g, self.x, self.p = kernels.compensate(
            self._g, self.x, self.p, correction, np.zeros_like(self.p), self._basis,
            self._whole)
        self.gain_projections += 1

    def command_identified(self) -> tuple[np.ndarray, np.ndarray]:
        """Return per axis whether the gain and the bias are identified (command_gain.py)."""
        return command_gain.identified(self.p, self.n, self.command_prior_sigma)

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

    def state(self) -> FilterState:
        """Return the current estimate (copies)."""
        return FilterState(self.g, self.x.copy(), self.p.copy())
