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
import math
from typing import Optional

import numpy as np
import pinocchio as pin
from reduced_dynamics.chi_square import chi2

from reduced_dynamics.estimator import step_row
from reduced_dynamics.estimator.core import kernels
from reduced_dynamics.estimator.core.smoother import smooth
from reduced_dynamics.estimator.core.stalls import StallDetector
from reduced_dynamics.estimator.core.state import (Command, FilterState, FilterStep,
                                                   Linearisation, Measurement, NoiseModel,
                                                   between)
from reduced_dynamics.estimator.events import StepDetection, WrenchStepTest
from reduced_dynamics.estimator.filter_model import _homogeneous, FilterModel
from reduced_dynamics.estimator.filter_rows import FilterRows, MAX_COAST_S
from reduced_dynamics.estimator.filter_update import (FilterUpdate, GATE_RESET, LOG_2PI,
                                                      OFFSET_PROBABILITY, STAMP_TWIST_TIME)
from reduced_dynamics.geometry.lie_group import BaseGroup

__all__ = ['Command', 'FilterState', 'FilterStep', 'GATE_RESET', 'LOG_2PI', 'Linearisation',
           'MAX_COAST_S', 'Measurement', 'MomentumFilter', 'NoiseModel', 'OFFSET_PROBABILITY',
           'STAMP_TWIST_TIME', 'between', 'smooth']

#: Re-linearisations of an update with a twist (iterated EKF).
ITERATIONS = kernels.ITERATIONS


def _axis_kinds(group: BaseGroup) -> np.ndarray:
    """Return True for algebra coordinates that rotate (angular), else False."""
    basis = group.algebra_basis
    return np.abs(basis[3:]).sum(axis=0) > 0.0


class MomentumFilter(FilterModel, FilterRows, FilterUpdate):
    """
    The error-state Kalman filter on G x R^n x R^n (see the module docstring).

    :meth:`row` processes one joint-state row with the base measurements
    stamped since the previous one (each updates once, at its own stamp);
    :meth:`step` is the row with one measurement at the row's stamp. ``record``
    keeps the steps for :func:`smooth`. The arithmetic is in
    :mod:`~reduced_dynamics.estimator.core.kernels` (compiled); this class holds
    the state, the gating decisions and the step test. Its parts are mixins, one
    concept each: the model (:mod:`~reduced_dynamics.estimator.filter_model`), the rows
    (:mod:`~reduced_dynamics.estimator.filter_rows`) and the update
    (:mod:`~reduced_dynamics.estimator.filter_update`); this module holds the state.

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

    # --- the start ---------------------------------------------------------------
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

    def state(self) -> FilterState:
        """Return the current estimate (copies)."""
        return FilterState(self.g, self.x.copy(), self.p.copy())
