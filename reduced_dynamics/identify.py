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
Payload identification from momentum conservation (docs/payload.md).

With no external wrench the momentum map is constant (Noether, Prop. 23;
REDUCED_MODEL.md 3). A payload of inertial parameters theta (Pinocchio's
dynamic parameters in the holding link's frame: m, m c, inertia about the link
origin) adds to the nominal model's mu a term linear in theta:

    mu_nom(g_k, xi_k, qbar_k, qbar_dot_k) + Y_k theta = mu_0      for every sample k,

where Y_k is the link's body regressor at zero velocity and acceleration equal
to the link's twist (a body's momentum is its inertia times its twist), carried
to the world frame about the origin (Ad_{g^-1}^T, 5.27) and restricted to the
base group's dual. The unknowns (theta, mu_0) are found by weighted least
squares, each sample weighted by the covariance the sensor noise gives mu, with
theta kept physical (positive mass, positive-definite inertia, triangle
inequalities) by the log-Cholesky parametrisation of the pseudo-inertia
(Rucker and Wensing 2022). Momentum-based identification of free-floating robots:
Rackl, Lampariello and Albu-Schaeffer (IFAC 2013).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import numpy as np
import pinocchio as pin
from scipy.optimize import least_squares

from reduced_dynamics.payload import link_frame, Payload, with_payload
from reduced_dynamics.robot.model import RobotModel

#: Names of Pinocchio's dynamic parameters (inertia about the link origin, link axes).
PARAMETER_NAMES = ('mass', 'm*cx', 'm*cy', 'm*cz', 'Ixx', 'Ixy', 'Iyy', 'Ixz', 'Iyz', 'Izz')
#: Default refusal threshold on the equilibrated regressor's condition number (beyond
#: it the weakest direction is seen 1000 times less than the best). The 20 s windows
#: of test/test_payload.py have 11 (paper robot), 23-32 (random tree) and 43-46
#: (planar two-link); an arm held still, infinity.
MAX_CONDITION = 1000.0
#: Refusal threshold on the weakest direction's signal-to-noise information ratio
#: (:func:`_signal_to_noise`). Measured with the realistic sensors: 162, 210 and 5.2 on
#: the 20 s windows of the paper robot, the random tree and the planar arm, 8.9 on 5 s
#: and 0.62 on 2 s of the paper robot; an arm held still: -0.1 (0.43 with the default
#: noise parameters instead of the sensors' figures).
MIN_SIGNAL_TO_NOISE = 2.0
#: Refusal threshold of :func:`momentum_step`'s F statistic. Measured on twelve
#: wrench-free 20 s windows with the realistic sensors (paper robot, random tree,
#: planar two-link; test/test_payload.py's cases, seeds 1-4): at most 3.4; with a
#: 20 N, 0.5 s pulse on the paper robot: 2.5e3.
MAX_STEP_RATIO = 20.0
#: Issue 22's accuracy bounds (relative mass, CoM in m, relative principal inertias): an
#: estimate whose 3 sigma exceeds one is reported weakly excited.
BOUND_MASS, BOUND_COM, BOUND_INERTIA = 0.03, 0.005, 0.15
#: Singular values this far below the largest are the base group's blind directions.
_STRUCTURAL_RTOL = 1e-8


class IdentificationError(ValueError):
    """A window the payload cannot be identified from (the message says why)."""


@dataclass
class Window:
    """Synchronised measurements: stamps (ns), base poses and twists, shape and rates."""

    stamps_ns: np.ndarray
    poses: list
    xi: np.ndarray
    qbar: np.ndarray
    qbar_dot: np.ndarray
    #: the input samples, in arrival order (to replay the window through the estimator)
    samples: list = field(default_factory=list)

    def __len__(self) -> int:
        """Return the number of synchronised samples."""
        return len(self.stamps_ns)


@dataclass(frozen=True)
class SensorNoise:
    """Standard deviations of the measurements (the estimator's noise parameters)."""

    pose_position: float
    pose_angle: float
    twist_linear: float
    twist_angular: float
    joint_velocity: float

    @classmethod
    def from_config(cls, config) -> 'SensorNoise':
        """Take the figures of an :class:`~reduced_dynamics.estimator.config.EstimatorConfig`."""
        return cls(config.pose_position_noise, config.pose_angle_noise,
                   config.twist_linear_noise, config.twist_angular_noise,
                   config.joint_velocity_noise)


# --------------------------------------------------------------------------- regressor
class MomentumRegressor:
    """Y_k (n x 10) and the nominal mu_k for a payload on ``link`` of ``robot``."""

    def __init__(self, robot: RobotModel, link: str) -> None:
        """Prepare a zero-gravity copy of the model (the regressor reads a_gf = a - g)."""
        self.robot = robot
        self.link = link
        self.frame_id = link_frame(robot, link)
        self._model = pin.Model(robot.model)
        self._model.gravity = pin.Motion.Zero()
        self._data = self._model.createData()
        self._zero = np.zeros(self._model.nv)
        self._joint = self._model.frames[self.frame_id].parentJoint
        self._placement = self._model.frames[self.frame_id].placement

    def basis(self, g: pin.SE3, qbar: np.ndarray) -> np.ndarray:
        """
        Y(e_j) for each velocity coordinate j (nv x n x 10): Y(v) = sum_j v_j Y(e_j).

        The momentum is linear in the velocity, so one evaluation per coordinate
        gives the regressor of any velocity, the measured one and its noise alike.
        """
        robot, model, data = self.robot, self._model, self._data
        q = robot.full_configuration(g, qbar)
        group = robot.group
        out = np.empty((model.nv, robot.n, 10))
        unit = np.zeros(model.nv)
        for j in range(model.nv):
            unit[:] = 0.0
            unit[j] = 1.0
            # RNEA at zero velocity and acceleration e_j: the link's a_gf is its twist,
            # and the body regressor there maps theta to the link-frame momentum.
            pin.rnea(model, data, q, self._zero, unit)
            local = pin.frameBodyRegressor(model, data, self.frame_id)
            if j == 0:
                pin.updateGlobalPlacements(model, data)  # RNEA fills liMi only
                world = (data.oMi[self._joint] * self._placement).toDualActionMatrix()
            out[j] = group.dual_coordinates(world @ local)
        return out

    def rows(self, g: pin.SE3, xi: np.ndarray, qbar: np.ndarray,
             qbar_dot: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Return (Y (n x 10), nominal mu (n)) at one measured state."""
        v = np.concatenate([xi, qbar_dot])
        return np.tensordot(v, self.basis(g, qbar), axes=1), self.nominal_mu(g, qbar, v)

    def nominal_mu(self, g: pin.SE3, qbar: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Return mu = Ad_{g^-1}^T M_top v of the nominal model (5.27)."""
        robot = self.robot
        return robot.group.Ad(g.inverse()).T @ (robot.mass_matrix(qbar)[:robot.n] @ v)

    def velocity_sigma(self, noise: SensorNoise) -> np.ndarray:
        """Return the standard deviation of each velocity coordinate (xi, then qbar_dot)."""
        robot = self.robot
        angular = np.abs(robot.group.algebra_basis[3:]).sum(axis=0) > 0.0
        twist = np.where(angular, noise.twist_angular, noise.twist_linear)
        return np.concatenate([twist, np.full(robot.m, noise.joint_velocity)])

    def covariance(self, g: pin.SE3, xi: np.ndarray, qbar: np.ndarray,
                   qbar_dot: np.ndarray, noise: SensorNoise) -> np.ndarray:
        """
        Covariance of the measured mu from the sensor noise (n x n).

        mu = Ad_{g^-1}^T M_top v (5.27): twist and joint-rate noise enter through
        M_top; a body-frame pose error delta moves mu by Ad_{g^-1}^T W(pi) delta,
        W the Kirillov form at pi (pi' = pi - ad_delta^T pi).
        """
        robot = self.robot
        group, n = robot.group, robot.n
        angular = np.abs(group.algebra_basis[3:]).sum(axis=0) > 0.0
        pose = np.where(angular, noise.pose_angle, noise.pose_position)
        top = robot.mass_matrix(qbar)[:n]
        pi = top @ np.concatenate([xi, qbar_dot])
        ad = group.Ad(g.inverse()).T
        a = ad @ (top * self.velocity_sigma(noise))
        b = ad @ (group.coadjoint_form(pi) * pose)
        return a @ a.T + b @ b.T


@dataclass
class NormalEquations:
    """
    The whitened least-squares problem of a window, reduced to its normal equations.

    ``information`` (10 + n square) and ``rhs`` of [theta; mu_0]; ``noise_quadratic``
    (10 x 10) and ``noise_linear`` (10): the expected contribution of the velocity
    noise to the cost, sum_k E|L_k^-1 (M_nom + Y) delta_k|^2 as a function of theta.
    The noise sits in the regressor too (errors in variables): minimising the raw
    cost would shrink the payload to shrink that term (a mass 10 % low at the
    realistic sensors), so the estimator subtracts it (bias-compensated least squares).
    """

    phi: np.ndarray
    y: np.ndarray
    noise_quadratic: np.ndarray
    noise_linear: np.ndarray
    noise_constant: float
    #: the noise terms per sample (K x 10 x 10, K x 10), for the robust covariance
    sample_quadratic: Optional[np.ndarray] = None
    sample_linear: Optional[np.ndarray] = None

    @property
    def n(self) -> int:
        """Return the dimension of mu."""
        return self.phi.shape[1] - 10


def regressor_stack(regressor: MomentumRegressor, window: Window, noise: SensorNoise
                    ) -> NormalEquations:
    """
    Whitened stack of the window: Phi (K n x 10 + n), y (K n) and the noise terms.

    Rows: L_k^-1 [Y_k, -1] [theta; mu_0] = -L_k^-1 mu_nom_k, L_k the Cholesky
    factor of sample k's mu covariance.
    """
    robot = regressor.robot
    n = robot.n
    count = len(window)
    phi = np.empty((count * n, 10 + n))
    y = np.empty(count * n)
    eye = np.eye(n)
    sigma = regressor.velocity_sigma(noise)
    quadratic = np.zeros((count, 10, 10))
    linear = np.zeros((count, 10))
    constant = 0.0
    for k in range(count):
        g, qbar = window.poses[k], window.qbar[k]
        v = np.concatenate([window.xi[k], window.qbar_dot[k]])
        basis = regressor.basis(g, qbar)
        rows = np.tensordot(v, basis, axes=1)
        ad = robot.group.Ad(g.inverse()).T
        top = robot.mass_matrix(qbar)[:n]
        mu = ad @ (top @ v)
        factor = np.linalg.cholesky(regressor.covariance(g, window.xi[k], qbar,
                                                         window.qbar_dot[k], noise))
        block = slice(k * n, (k + 1) * n)
        phi[block, :10] = np.linalg.solve(factor, rows)
        phi[block, 10:] = -np.linalg.solve(factor, eye)
        y[block] = -np.linalg.solve(factor, mu)
        # Noise columns: delta = sigma_j e_j moves the residual by
        # sigma_j (A M e_j + Y(e_j) theta).
        white_b = np.linalg.solve(factor, (basis * sigma[:, None, None]).transpose(1, 0, 2)
                                  .reshape(n, -1)).reshape(n, len(sigma), 10)
        white_a = np.linalg.solve(factor, ad @ (top * sigma))
        quadratic[k] = np.einsum('ijk,ijl->kl', white_b, white_b)
        linear[k] = np.einsum('ijk,ij->k', white_b, white_a)
        constant += float(np.sum(white_a ** 2))
    return NormalEquations(phi, y, quadratic.sum(axis=0), linear.sum(axis=0), constant,
                           quadratic, linear)


def structural_null_space(regressor: MomentumRegressor, seed: int = 0,
                          samples: int = 40) -> np.ndarray:
    """
    Parameter directions no motion of this robot can reveal (10 x k, orthonormal).

    The regressor at random states: what stays in its null space (beside mu_0)
    is blind by structure, e.g. a planar base sees only m, m cx, m cy and Izz.
    """
    robot = regressor.robot
    rng = np.random.default_rng(seed)
    n = robot.n
    blocks = []
    for _ in range(samples):
        g = robot.project_pose(pin.SE3.Random())
        rows, _ = regressor.rows(g, rng.standard_normal(n), rng.uniform(-np.pi, np.pi, robot.m),
                                 rng.standard_normal(robot.m))
        blocks.append(np.hstack([rows, -np.eye(n)]))
    stack = np.vstack(blocks)
    stack = stack / np.maximum(np.linalg.norm(stack, axis=0), 1e-300)
    _, singular, vt = np.linalg.svd(stack, full_matrices=False)
    null = vt[singular < _STRUCTURAL_RTOL * singular[0]]
    if len(singular) < vt.shape[0]:
        null = np.vstack([null, vt[len(singular):]])
    if not len(null):
        return np.zeros((10, 0))
    # Only the theta part matters: mu_0 is always seen.
    basis, s, _ = np.linalg.svd(null[:, :10].T, full_matrices=False)
    return basis[:, s > 1e-6]


# --------------------------------------------------------------------------- identifiability
@dataclass
class Identifiability:
    """Conditioning of a window's regressor on the directions the robot can see."""

    condition: float
    #: parameter directions the robot can never see (10 x k)
    structural: np.ndarray
    #: the weakest seen direction, as (parameter name, weight) largest first
    weakest: list[tuple[str, float]]
    #: relative singular values of the seen parameter directions, ascending
    relative_singular_values: np.ndarray
    #: the weakest seen direction's signal over its noise information (see _signal_to_noise)
    signal_to_noise: float = float('inf')

    def weak_text(self) -> str:
        """Name the parameters of the weakest direction."""
        return ', '.join(f'{name} ({weight:+.2f})' for name, weight in self.weakest)

    def blind_names(self) -> list[str]:
        """Parameters that have a component in the structural null space."""
        if not self.structural.shape[1]:
            return []
        share = np.linalg.norm(self.structural, axis=1)
        return [name for name, s in zip(PARAMETER_NAMES, share) if s > 0.3]


def identifiability(equations: 'NormalEquations', structural: np.ndarray,
                    noise_scale: float = 1.0) -> Identifiability:
    """
    Condition number of the window's regressor on the directions the robot can see.

    Taken from the noise-compensated information H' = Phi^T Phi - C (equilibrated
    by the diagonal of Phi^T Phi): the signal's own conditioning, sqrt(cond H').
    Noise excites the raw regressor even when the arm is still; H' discounts it,
    and is singular (infinite condition) when the motion does not rise above it.
    ``noise_scale``: the noise measured by the fit, in units of the figures.
    """
    phi = equations.phi
    n = equations.n
    seen = _complement(structural)
    reduce = np.zeros((10 + n, seen.shape[1] + n))
    reduce[:10, :seen.shape[1]] = seen
    reduce[10:, seen.shape[1]:] = np.eye(n)
    information = phi.T @ phi
    compensated = information.copy()
    compensated[:10, :10] -= noise_scale * equations.noise_quadratic
    raw = reduce.T @ information @ reduce
    reduced = reduce.T @ compensated @ reduce
    scale = np.sqrt(np.maximum(np.diag(raw), 1e-300))
    values, vectors = np.linalg.eigh(reduced / np.outer(scale, scale))
    condition = float(np.sqrt(values[-1] / values[0])) if values[0] > 0.0 else float('inf')
    direction = vectors[:seen.shape[1], 0] / scale[:seen.shape[1]]
    theta = seen @ direction
    norm = np.linalg.norm(theta)
    weakest = []
    if norm > 0.0:
        theta = theta / norm
        order = np.argsort(-np.abs(theta))
        weakest = [(PARAMETER_NAMES[i], float(theta[i])) for i in order[:3]
                   if abs(theta[i]) > 0.2]
    relative = np.sqrt(np.maximum(values, 0.0) / values[-1])
    return Identifiability(condition, structural, weakest, relative,
                           _signal_to_noise(equations, seen, noise_scale))


def _signal_to_noise(equations: 'NormalEquations', seen: np.ndarray,
                     noise_scale: float) -> float:
    """
    Smallest ratio of the motion's information to the noise's, over the seen directions.

    Generalised eigenvalues of the compensated information (mu_0 eliminated)
    against the noise term C: below 1 the weakest direction moves less than the
    sensor noise does; an arm held still gives about 0.
    """
    phi = equations.phi
    information = phi.T @ phi
    theta_block = information[:10, :10] - noise_scale * equations.noise_quadratic
    cross = information[:10, 10:]
    schur = theta_block - cross @ np.linalg.solve(information[10:, 10:], cross.T)
    signal = seen.T @ schur @ seen
    noise = noise_scale * (seen.T @ equations.noise_quadratic @ seen)
    values, vectors = np.linalg.eigh(noise)
    if values[-1] <= 0.0:
        return float('inf')
    keep = values > 1e-12 * values[-1]
    root = vectors[:, keep] / np.sqrt(values[keep])
    return float(np.linalg.eigvalsh(root.T @ signal @ root)[0])


def _complement(null: np.ndarray) -> np.ndarray:
    """Orthonormal basis of the complement of span(null) in R^10."""
    if not null.shape[1]:
        return np.eye(10)
    u, _, _ = np.linalg.svd(null, full_matrices=True)
    return u[:, null.shape[1]:]


# --------------------------------------------------------------------------- solve
def log_cholesky_from_dynamic(theta: np.ndarray) -> np.ndarray:
    """Log-Cholesky parameters of a physical theta (pseudo-inertia J = U U^T, U upper)."""
    pseudo = pin.PseudoInertia.FromDynamicParameters(np.asarray(theta, dtype=float))
    flip = np.eye(4)[::-1]
    lower = np.linalg.cholesky(flip @ pseudo.toMatrix() @ flip)
    upper = flip @ lower @ flip
    alpha = np.log(upper[3, 3])
    u = upper / upper[3, 3]
    return np.array([alpha, np.log(u[0, 0]), np.log(u[1, 1]), np.log(u[2, 2]),
                     u[0, 1], u[1, 2], u[0, 2], u[0, 3], u[1, 3], u[2, 3]])


def physical_completion(theta: np.ndarray, floor: float = 1e-3) -> np.ndarray:
    """
    Return the nearest simple physical body to a possibly unphysical theta.

    Mass at least ``floor`` of |m| (or 1e-3 kg); principal moments about the CoM
    raised until non-negative and satisfying the triangle inequalities (a flat
    disc where only the normal moment is known, as on a planar base).
    """
    mass = max(abs(float(theta[0])), 1e-3)
    com = np.asarray(theta[1:4]) / mass
    about_origin = pin.Inertia.FromDynamicParameters(
        np.r_[mass, mass * com, theta[4:]]).inertia if theta[0] > 0.0 else None
    if about_origin is None:
        inertia = np.zeros((3, 3))
    else:
        inertia = about_origin
    values, vectors = np.linalg.eigh(0.5 * (inertia + inertia.T))
    top = max(float(values[-1]), floor * mass * 1e-2)
    low, mid = max(values[0], 0.0), max(values[1], 0.0)
    mid = max(mid, 0.5 * top)
    # Strictly inside the triangle inequalities: the log-Cholesky start needs J > 0.
    low = max(low, top - mid + 0.01 * top)
    fixed = vectors @ np.diag([low, mid, top]) @ vectors.T
    return pin.Inertia(mass, com, fixed).toDynamicParameters()


@dataclass
class PayloadEstimate:
    """The identified payload with one-sigma uncertainties and the fit's statistics."""

    payload: Payload
    theta: np.ndarray
    theta_covariance: np.ndarray
    mu0: np.ndarray
    mass_sigma: float
    com_sigma: np.ndarray
    principal_sigma: np.ndarray
    inertia_sigma: np.ndarray
    identifiability: Identifiability
    chi2_per_dof: float
    samples: int
    #: parameters the base group cannot see: held at a physical completion, not measured
    blind: list[str]

    def text(self) -> str:
        """Return the printed report."""
        p = self.payload
        lines = [
            f'payload on {p.link} from {self.samples} samples '
            f'(condition {self.identifiability.condition:.3g}, residual '
            f'{self.chi2_per_dof:.3g} x what the noise figures predict)',
            f'  mass {p.mass:.6g} +- {self.mass_sigma:.2g} kg',
            '  com  [' + ', '.join(f'{c:+.5f} +- {s:.2g}' for c, s in
                                   zip(p.com, self.com_sigma)) + '] m (link frame)',
            '  principal inertia about the CoM [' + ', '.join(
                f'{c:.5g} +- {s:.2g}' for c, s in zip(p.principal_inertia,
                                                      self.principal_sigma)) + '] kg m^2',
            '  inertia about the CoM (link axes) '
            + np.array2string(p.inertia, precision=5, suppress_small=True).replace('\n', ''),
        ]
        if self.blind:
            lines.append('  not identifiable with this base group (held at a physical '
                         'completion, not measured): ' + ', '.join(self.blind))
        weak = self.weakly_excited()
        if weak:
            lines.append('  weakly excited (3 sigma beyond the accuracy bounds: mass 3 %, '
                         'CoM 5 mm, principal inertia 15 %): ' + ', '.join(weak)
                         + '; identify over a longer or livelier motion')
        return '\n'.join(lines)

    def weakly_excited(self) -> list[str]:
        """
        Quantities whose 3 sigma exceeds the accuracy bounds (issue 22's acceptance).

        Mass 3 %, CoM 5 mm per axis, principal inertias 15 %; blind quantities of a
        planar base are left out (only the CoM's x, y and Izz are seen there).
        """
        p = self.payload
        planar = bool(self.blind)
        weak = []
        if 3.0 * self.mass_sigma > BOUND_MASS * p.mass:
            weak.append('mass')
        for axis, name in enumerate('xyz'[:2 if planar else 3]):
            if 3.0 * self.com_sigma[axis] > BOUND_COM:
                weak.append(f'com {name}')
        if planar:
            if 3.0 * self.inertia_sigma[2, 2] > BOUND_INERTIA * p.inertia[2, 2]:
                weak.append('Izz')
        else:
            for i, (value, sigma) in enumerate(zip(p.principal_inertia,
                                                   self.principal_sigma)):
                if 3.0 * sigma > BOUND_INERTIA * value:
                    weak.append(f'principal inertia {i + 1}')
        return weak


def _derived(theta: np.ndarray) -> np.ndarray:
    """(m, c, principal moments ascending, inertia entries about the CoM) of theta."""
    inertia = pin.Inertia.FromDynamicParameters(np.asarray(theta, dtype=float))
    about = inertia.inertia
    return np.concatenate([[inertia.mass], inertia.lever, np.linalg.eigvalsh(about),
                           about[np.triu_indices(3)]])


def solve(equations: NormalEquations, link: str, structural: np.ndarray,
          check: Identifiability, iterations: int = 5,
          first: Optional['PayloadEstimate'] = None) -> PayloadEstimate:
    """
    Identify with the noise compensation scaled to the noise the fit shows.

    The compensation is as good as the noise figures: when the fit's chi2/dof
    says the noise is s^2 times what they claim, the compensation is redone with
    s^2 (a fixed point reached in a few steps; 0 for noise-free data).
    """
    # From no compensation up (``first``, if given, is that fit): the raw fit's cost,
    # over the cost the figures predict, measures the noise; an over-compensated
    # start could run away instead.
    estimate = first or _solve(equations, link, structural, check, 0.0)
    for _ in range(iterations):
        scale = estimate.chi2_per_dof
        estimate = _solve(equations, link, structural, check, scale)
        if abs(estimate.chi2_per_dof - scale) <= 0.01 * max(scale, 1e-3):
            break
    return estimate


def _solve(equations: NormalEquations, link: str, structural: np.ndarray,
           check: Identifiability, noise_scale: float) -> PayloadEstimate:
    """
    Bias-compensated weighted least squares over physical payloads.

    The compensated normal equations H' = Phi^T Phi - C (C the noise term of
    :class:`NormalEquations`) are factored, H' = R^T R, and ``least_squares``
    minimises |R x - d|^2 over x = (log-Cholesky parameters, mu_0) (Rucker and
    Wensing 2022: every x is a physical body). Directions the base group cannot
    see are pinned softly to the physical completion of the linear solution;
    their uncertainty is not reported as measured.
    """
    phi, y = equations.phi, equations.y
    n = equations.n
    information = phi.T @ phi
    compensated = information.copy()
    compensated[:10, :10] -= noise_scale * equations.noise_quadratic
    rhs = phi.T @ y
    rhs[:10] += noise_scale * equations.noise_linear
    seen = _complement(structural)
    # The linear solution on the seen directions (blind ones at zero).
    reduce = np.zeros((10 + n, seen.shape[1] + n))
    reduce[:10, :seen.shape[1]] = seen
    reduce[10:, seen.shape[1]:] = np.eye(n)
    reduced = reduce.T @ compensated @ reduce
    if np.linalg.eigvalsh(reduced)[0] <= 0.0:
        raise IdentificationError(
            f'poor excitation: the payload on {link} is not identifiable from this window: '
            'the sensor noise dominates the arm\'s motion (the noise-compensated normal '
            'equations are not positive definite). Move the arm (the joints that carry the '
            'link) faster or longer, e.g. the proposed excitation trajectory, and identify '
            'over that window.')
    linear = reduce @ np.linalg.solve(reduced, reduce.T @ rhs)
    reference = physical_completion(linear[:10])
    scale = _parameter_scale(reference)
    prior_rows = (structural.T / scale) if structural.shape[1] else np.zeros((0, 10))
    # Blind directions get the prior's information, so the factor exists.
    factor_of = compensated.copy()
    factor_of[:10, :10] += prior_rows.T @ prior_rows
    upper = np.linalg.cholesky(factor_of).T
    target = np.linalg.solve(upper.T, rhs + np.r_[prior_rows.T @ (prior_rows @ reference),
                                                  np.zeros(n)])

    def theta_of(x: np.ndarray) -> np.ndarray:
        return pin.LogCholeskyParameters(x[:10]).toDynamicParameters()

    def residual(x: np.ndarray) -> np.ndarray:
        return upper @ np.concatenate([theta_of(x), x[10:]]) - target

    def jacobian(x: np.ndarray) -> np.ndarray:
        dtheta = pin.LogCholeskyParameters(x[:10]).calculateJacobian()
        return np.hstack([upper[:, :10] @ dtheta, upper[:, 10:]])

    start = np.concatenate([log_cholesky_from_dynamic(reference), linear[10:]])
    # Trial steps far out overflow exp() in the parametrisation; the solver backs off.
    with np.errstate(over='ignore', invalid='ignore'):
        result = least_squares(residual, start, jac=jacobian, method='trf', x_scale='jac',
                               xtol=1e-14, ftol=1e-14, gtol=1e-14, max_nfev=500)
    theta = theta_of(result.x)
    estimate = np.concatenate([theta, result.x[10:]])
    # The cost the noise figures predict at theta (not the sample count: the
    # regressor's own noise grows with the payload); 1 when the figures are right.
    expected = float(theta @ equations.noise_quadratic @ theta
                     + 2.0 * equations.noise_linear @ theta + equations.noise_constant)
    chi2 = float(np.sum((phi @ estimate - y) ** 2)) / max(expected, 1e-300)
    # Robust (sandwich) covariance F^-1 S F^-1 from the per-sample scores of the
    # compensated cost: it carries the regressor's own noise, which H^-1 misses.
    inverse = np.linalg.inv(factor_of)
    covariance = inverse @ _score_covariance(equations, estimate, noise_scale) @ inverse
    theta_cov = covariance[:10, :10]
    derived = _derived(theta)
    jac = np.empty((len(derived), 10))
    for i in range(10):
        step = 1e-6 * max(abs(theta[i]), scale[i])
        plus, minus = theta.copy(), theta.copy()
        plus[i] += step
        minus[i] -= step
        jac[:, i] = (_derived(plus) - _derived(minus)) / (2.0 * step)
    sigma = np.sqrt(np.maximum(np.diag(jac @ theta_cov @ jac.T), 0.0))
    inertia = pin.Inertia.FromDynamicParameters(theta)
    upper_sigma = np.zeros((3, 3))
    upper_sigma[np.triu_indices(3)] = sigma[7:]
    inertia_sigma = upper_sigma + np.triu(upper_sigma, 1).T
    payload = Payload(link, inertia.mass, inertia.lever.copy(), inertia.inertia.copy(),
                      sigma={'mass': sigma[0], 'com': sigma[1:4],
                             'principal_inertia': sigma[4:7], 'inertia': inertia_sigma,
                             'condition': check.condition})
    return PayloadEstimate(payload, theta, theta_cov, result.x[10:], float(sigma[0]),
                           sigma[1:4], sigma[4:7], inertia_sigma, check, chi2,
                           len(y) // max(n, 1), check.blind_names())


def _score_covariance(equations: NormalEquations, estimate: np.ndarray,
                      noise_scale: float) -> np.ndarray:
    """Sum over samples of s_k s_k^T, s_k the gradient of sample k's compensated cost."""
    phi, y, n = equations.phi, equations.y, equations.n
    count = len(y) // n
    residual = (phi @ estimate - y).reshape(count, n)
    blocks = phi.reshape(count, n, 10 + n)
    scores = np.einsum('kij,ki->kj', blocks, residual)
    if equations.sample_quadratic is not None:
        theta = estimate[:10]
        scores[:, :10] -= noise_scale * (equations.sample_quadratic @ theta
                                         + equations.sample_linear)
    return scores.T @ scores


def _parameter_scale(theta: np.ndarray) -> np.ndarray:
    """Natural size of each dynamic parameter (kg, kg m, kg m^2) for a body like theta."""
    mass = max(float(theta[0]), 1e-3)
    length = max(float(np.linalg.norm(theta[1:4])) / mass, 0.1)
    return np.array([mass] + [mass * length] * 3 + [mass * length ** 2] * 6)


# --------------------------------------------------------------------------- top level
def identify_window(robot: RobotModel, link: str, window: Window, noise: SensorNoise,
                    max_condition: float = MAX_CONDITION,
                    max_step_ratio: float = MAX_STEP_RATIO) -> PayloadEstimate:
    """
    Identify the payload on ``link`` from a wrench-free window of measurements.

    Raises :class:`IdentificationError` when the window is too short, does
    not excite the parameters (condition number above ``max_condition``) or
    holds a step in mu (:func:`momentum_step` above ``max_step_ratio``).
    """
    regressor = MomentumRegressor(robot, link)
    if len(window) < 20:
        raise IdentificationError(f'the window holds {len(window)} synchronised samples; '
                                  'identification needs at least 20')
    structural = structural_null_space(regressor)
    equations = regressor_stack(regressor, window, noise)
    # The raw regressor first (noise excites it too), then, after the fit, with the
    # noise it measured discounted.
    check = _excited(identifiability(equations, structural, 0.0), link, max_condition)
    estimate = solve(equations, link, structural, check)
    # A step in mu inflates the noise the fit measures: test for it before judging
    # the excitation against that noise.
    _conserved(equations, estimate, window.stamps_ns, max_step_ratio)
    check = _excited(identifiability(equations, structural, estimate.chi2_per_dof), link,
                     max_condition)
    estimate.identifiability = check
    estimate.payload.sigma['condition'] = check.condition
    return estimate


def _conserved(equations: 'NormalEquations', estimate: 'PayloadEstimate',
               stamps_ns: np.ndarray, max_step_ratio: float) -> None:
    """Refuse a window whose fit leaves a step in mu (an external-wrench event)."""
    step = momentum_step(equations, estimate, stamps_ns)
    if step is not None and step[1] > max_step_ratio:
        when = (step[0] - int(stamps_ns[0])) * 1e-9
        raise IdentificationError(
            f'momentum is not conserved in the window: the fitted model leaves a step in '
            f'mu at {when:.2f} s into the window (F = {step[1]:.3g} > {max_step_ratio:g}), '
            'an external-wrench event; choose --start/--end free of thruster firings '
            'and contacts')


#: Spacing of the split points tried, and the shortest segment on either side (s).
_STEP_GRID, _STEP_MARGIN = 0.25, 1.0


def momentum_step(equations: 'NormalEquations', estimate: 'PayloadEstimate',
                  stamps_ns: np.ndarray) -> Optional[tuple[int, float]]:
    """
    Return (stamp, F) of the most likely step in mu after the fit, or None if too short.

    A second mu_0 after each candidate split: the drop of the whitened cost per
    added parameter, over the cost per degree of freedom with the split (an F
    test, so free of the noise figures' scale). An external wrench is a step.
    """
    n = equations.n
    count = len(equations.y) // n
    x = np.concatenate([estimate.theta, estimate.mu0])
    residual = (equations.phi @ x - equations.y).reshape(count, n)
    column = -equations.phi[:, 10:].reshape(count, n, n)
    a = np.einsum('kij,kil->kjl', column, column)
    b = np.einsum('kij,ki->kj', column, residual)
    cum_a, cum_b = np.cumsum(a, axis=0), np.cumsum(b, axis=0)
    total_a, total_b = cum_a[-1], cum_b[-1]
    seconds = (stamps_ns - stamps_ns[0]) * 1e-9
    if seconds[-1] < 2.0 * _STEP_MARGIN:
        return None
    cost = float(np.sum(residual ** 2))
    best = None
    for split_time in np.arange(_STEP_MARGIN, seconds[-1] - _STEP_MARGIN + 1e-9, _STEP_GRID):
        k = int(np.searchsorted(seconds, split_time))
        a1, b1 = cum_a[k - 1], cum_b[k - 1]
        a2, b2 = total_a - a1, total_b - b1
        drop = float(b1 @ np.linalg.solve(a1, b1) + b2 @ np.linalg.solve(a2, b2)
                     - total_b @ np.linalg.solve(total_a, total_b))
        ratio = (drop / n) / max((cost - drop) / max(count * n - 10 - 2 * n, 1), 1e-300)
        if best is None or ratio > best[1]:
            best = (int(stamps_ns[k]), ratio)
    return best


def _excited(check: Identifiability, link: str, max_condition: float) -> Identifiability:
    """Return ``check`` if the window is excited enough, else refuse with what it misses."""
    if check.condition <= max_condition and check.signal_to_noise >= MIN_SIGNAL_TO_NOISE:
        return check
    raise IdentificationError(
        f'poor excitation: the payload on {link} is not identifiable from this window '
        f'(regressor condition number {check.condition:.3g}, at most {max_condition:g}; '
        f'the weakest direction\'s motion {check.signal_to_noise:.3g} times its noise, '
        f'at least {MIN_SIGNAL_TO_NOISE:g}); '
        f'the window cannot see: {check.weak_text() or "every parameter"}. '
        'Move the arm (the joints that carry the link) through a varied motion, e.g. '
        'the proposed excitation trajectory, and identify over that window.')


def apply_payload(robot: RobotModel, estimate_or_payload) -> RobotModel:
    """Return the robot holding the identified (or given) payload."""
    payload = getattr(estimate_or_payload, 'payload', estimate_or_payload)
    return with_payload(robot, payload)


def carrying_joints(robot: RobotModel, link: str) -> list[int]:
    """Shape indices of the joints between the base and ``link`` (they move it)."""
    model = robot.model
    joint = model.frames[link_frame(robot, link)].parentJoint
    indices = []
    while joint > 1:
        indices.append(model.joints[joint].idx_v - robot.n)
        joint = model.parents[joint]
    return sorted(indices)


def excitation_trajectory(robot: RobotModel, link: str, qbar0: np.ndarray,
                          duration: float = 20.0, amplitude: float = 2.0,
                          candidates: int = 24, seed: int = 0,
                          step: float = 0.1) -> dict:
    """
    Propose a joint trajectory exciting the payload's parameters (``predict --trajectory``).

    Each carrying joint follows q0 + sum_h a_h (1 - cos(h w t)), w = 2 pi / duration,
    over four harmonics h of its own between about 1 and 5 rad/s: it starts and ends
    at rest at the current shape. Among ``candidates`` random
    amplitude sets, the one whose regressor (base reacting through the connection,
    xi = -A qbar_dot) is best conditioned is kept.
    """
    joints = carrying_joints(robot, link)
    if not joints:
        raise IdentificationError(f'no shape joint moves link {link}: a payload on the base '
                                  'is seen only through the base, move the arm to excite it')
    regressor = MomentumRegressor(robot, link)
    structural = structural_null_space(regressor)
    times = np.arange(0.0, duration + 1e-9, step)
    omega = 2.0 * np.pi / duration
    # Four harmonics per joint drawn from those of about 1-5 rad/s (at least the 2nd):
    # distinct frequencies per joint turn the link about varied axes, and the faster
    # ones give the inertia the angular rate it is seen through (docs/payload.md).
    harmonics = np.arange(max(2, int(round(1.0 / omega))), max(6, int(round(5.0 / omega))) + 1)
    per_joint = min(4, len(harmonics))
    rng = np.random.default_rng(seed)
    limits = robot.shape_joint_limits
    names = robot.shape_joint_names
    noise = SensorNoise(1e-3, 1e-3, 1e-3, 1e-3, 1e-3)
    best = None
    for _ in range(candidates):
        coeffs = np.zeros((robot.m, len(harmonics)))
        for j in joints:
            chosen = rng.choice(len(harmonics), per_joint, replace=False)
            coeffs[j, chosen] = rng.uniform(-1.0, 1.0, per_joint)
            coeffs[j] *= amplitude / (2.0 * np.abs(coeffs[j]).sum())
            limit = limits.get(names[j])
            if limit is not None and limit.lower is not None:
                room = min(qbar0[j] - limit.lower, limit.upper - qbar0[j])
                coeffs[j] *= min(1.0, 0.45 * max(room, 0.0) / max(amplitude, 1e-12))
        arguments = np.outer(times, harmonics) * omega
        positions = qbar0 + (1.0 - np.cos(arguments)) @ coeffs.T
        velocities = (np.sin(arguments) * harmonics * omega) @ coeffs.T
        accelerations = (np.cos(arguments) * (harmonics * omega) ** 2) @ coeffs.T
        poses, xis = [], []
        for q, qd in zip(positions[::5], velocities[::5]):
            blocks = robot.metric_blocks(q)
            poses.append(pin.SE3.Identity())
            xis.append(-blocks.connection @ qd)
        window = Window(times[::5], poses, np.array(xis), positions[::5], velocities[::5])
        condition = identifiability(regressor_stack(regressor, window, noise),
                                    structural).condition
        if best is None or condition < best[0]:
            best = (condition, positions, velocities, accelerations)
    condition, positions, velocities, accelerations = best
    return {
        'joint_names': list(names),
        'points': [{'time': round(float(t), 6),
                    'positions': [float(v) for v in p],
                    'velocities': [float(v) for v in qd],
                    'accelerations': [float(v) for v in qdd]}
                   for t, p, qd, qdd in zip(times, positions, velocities, accelerations)],
        'predicted_condition': float(condition),
    }


# --------------------------------------------------------------------------- measurements
#: Largest gap between the two base samples a joint state is interpolated between (s).
MAX_BASE_GAP = 0.1


def synchronise(robot: RobotModel, joints: list, bases: list) -> Window:
    """
    Pair each joint state with the base state interpolated at its stamp.

    Poses are interpolated on SE(3) (position linearly, attitude by slerp), twists
    linearly; joint states outside the base samples, or between two base samples
    more than :data:`MAX_BASE_GAP` apart, are left out. Joint states without
    velocities, or missing a shape joint, are left out.
    """
    bases = sorted((b for b in bases if b.twist_linear is not None), key=lambda b: b.stamp_ns)
    if not bases:
        raise IdentificationError('identification needs the base twist (nav_msgs/Odometry): '
                                  'the window has no base sample with a twist')
    base_ns = np.array([b.stamp_ns for b in bases], dtype=np.int64)
    names = robot.shape_joint_names
    stamps, poses, xis, qbars, rates = [], [], [], [], []
    group = robot.group
    for sample in sorted(joints, key=lambda s: s.stamp_ns):
        if len(sample.velocity) != len(sample.names):
            continue
        index = {name: i for i, name in enumerate(sample.names)}
        if any(name not in index for name in names):
            continue
        after = int(np.searchsorted(base_ns, sample.stamp_ns))
        if after == 0 or after == len(bases):
            if after < len(bases) and base_ns[after] == sample.stamp_ns:
                before = after
            else:
                continue
        else:
            before = after - 1
        a, b = bases[before], bases[after]
        if (b.stamp_ns - a.stamp_ns) * 1e-9 > MAX_BASE_GAP:
            continue
        span = b.stamp_ns - a.stamp_ns
        s = 0.0 if span == 0 else (sample.stamp_ns - a.stamp_ns) / span
        qa = pin.Quaternion(a.orientation_xyzw[3], *a.orientation_xyzw[:3]).normalized()
        qb = pin.Quaternion(b.orientation_xyzw[3], *b.orientation_xyzw[:3]).normalized()
        pose = pin.SE3(qa.slerp(s, qb).toRotationMatrix(),
                       (1 - s) * a.position + s * b.position)
        twist6 = np.concatenate([(1 - s) * a.twist_linear + s * b.twist_linear,
                                 (1 - s) * a.twist_angular + s * b.twist_angular])
        order = [index[name] for name in names]
        stamps.append(sample.stamp_ns)
        poses.append(robot.project_pose(pose))
        xis.append(group.coordinates(twist6))
        qbars.append(sample.position[order])
        rates.append(sample.velocity[order])
    m = robot.m
    return Window(np.array(stamps, dtype=np.int64), poses,
                  np.array(xis).reshape(-1, robot.n), np.array(qbars).reshape(-1, m),
                  np.array(rates).reshape(-1, m))


def read_window(bag_path: str, robot: RobotModel, params: dict,
                start: Optional[float] = None, end: Optional[float] = None,
                joint_states_topic: Optional[str] = None,
                odom_topic: Optional[str] = None) -> Window:
    """Read joint states and Odometry of ``bag_path`` in [start, end) s from its start."""
    from reduced_dynamics.bag.reader import open_bag
    from reduced_dynamics.messages.samples import JointStateSample, with_receive_time
    from reduced_dynamics.replay import choose_inputs, input_decoder, ReplayOptions
    options = ReplayOptions(params=params, joint_states_topic=joint_states_topic,
                            odom_topic=odom_topic)
    joints, bases, samples = [], [], []
    with open_bag(bag_path) as reader:
        joint_topic, base_topic, is_odom = choose_inputs(reader.topics(), options)
        if joint_topic is None:
            raise IdentificationError('identification needs joint states (the arm\'s motion '
                                      'is what reveals the payload)')
        if not is_odom:
            raise IdentificationError(f'identification needs the base twist: {base_topic} is '
                                      'a PoseStamped topic; record nav_msgs/Odometry')
        start_ns = None if start is None else reader.start_ns + int(round(start * 1e9))
        end_ns = None if end is None else reader.start_ns + int(round(end * 1e9))
        decoders = {}
        for topic, msgtype in reader.connection_types([joint_topic, base_topic]):
            decoders[topic, msgtype] = input_decoder(reader, topic, msgtype, robot.base_link)
        for message in reader.raw_messages([joint_topic, base_topic], start_ns, end_ns):
            decode = decoders.get((message.topic, message.msgtype))
            if decode is None:
                continue
            try:
                sample = decode(message.data)
            except (ValueError, TypeError):
                continue  # malformed: the estimator's gates count these in a replay
            if sample is None:
                continue
            sample = with_receive_time(sample, message.timestamp_ns)
            samples.append(sample)
            (joints if isinstance(sample, JointStateSample) else bases).append(sample)
    window = synchronise(robot, joints, bases)
    window.samples = samples
    return window


# --------------------------------------------------------------------------- CLI
def identify_bag(bag_path: str, robot: RobotModel, link: str, params: dict,
                 start: Optional[float] = None, end: Optional[float] = None,
                 max_condition: float = MAX_CONDITION) -> PayloadEstimate:
    """
    Identify the payload on ``link`` over [start, end) of a bag.

    Raises :class:`IdentificationError` for a window with too few samples,
    poor excitation, or a step in mu (an external-wrench event,
    :func:`momentum_step`). The estimator's own event detector is not the judge:
    on 20 s windows with the realistic sensors it flagged events in two of
    three wrench-free windows even with the true payload (docs/payload.md).
    """
    from reduced_dynamics.estimator.config import EstimatorConfig
    noise = SensorNoise.from_config(EstimatorConfig.from_mapping(params))
    window = read_window(bag_path, robot, params, start, end)
    return identify_window(robot, link, window, noise, max_condition)


def _run(args) -> int:
    import sys
    from reduced_dynamics.cli import load_robot_from_args
    from reduced_dynamics.params import defaults, load_params_file
    params = load_params_file(args.params) if args.params else defaults()
    robot = load_robot_from_args(args)
    try:
        estimate = identify_bag(args.bag, robot, args.link, params, args.start, args.end,
                                args.max_condition)
    except IdentificationError as error:
        print(f'reduced-dynamics identify: refused: {error}', file=sys.stderr)
        if 'poor excitation' in str(error):
            window = read_window(args.bag, robot, params, args.start, args.end)
            qbar0 = window.qbar[-1] if len(window) else np.zeros(robot.m)
            proposal = excitation_trajectory(robot, args.link, qbar0,
                                             duration=args.excitation_duration)
            path = args.propose or 'excitation.yaml'
            import yaml
            with open(path, 'w', encoding='utf-8') as stream:
                yaml.safe_dump(proposal, stream, sort_keys=False)
            print(f'proposed excitation ({args.excitation_duration:g} s, predicted condition '
                  f'{proposal["predicted_condition"]:.3g}) written to {path}: play it '
                  '(e.g. simulate/predict --trajectory) and identify over it',
                  file=sys.stderr)
        return 4
    print(estimate.text())
    if args.output:
        estimate.payload.write(args.output)
        print(f'written to {args.output}')
    return 0


def register_command(commands) -> None:
    """Add the ``identify`` subcommand."""
    from reduced_dynamics.cli import add_robot_arguments
    parser = commands.add_parser(
        'identify', help='identify a payload held by a link from momentum conservation',
        description='Estimate the mass, centre of mass (link frame) and inertia about it of '
                    'a rigid payload on LINK from a window of joint states and Odometry with '
                    'no external wrench (docs/payload.md).')
    parser.add_argument('bag', help='rosbag2 directory (MCAP or sqlite3) or .mcap file')
    add_robot_arguments(parser)
    parser.add_argument('--link', required=True, help='the URDF link holding the payload')
    parser.add_argument('--params', help='parameters YAML (sensor noise: the node\'s format)')
    parser.add_argument('--start', type=float, help='window start, seconds from the bag start')
    parser.add_argument('--end', type=float, help='window end, seconds from the bag start')
    parser.add_argument('-o', '--output', help='write the payload YAML (replay --payload, '
                                               'the node\'s payload_file)')
    parser.add_argument('--max-condition', type=float, default=MAX_CONDITION,
                        help='refuse a window whose equilibrated regressor condition number '
                             f'exceeds this (default {MAX_CONDITION:g})')
    parser.add_argument('--propose', metavar='FILE',
                        help='where a refused window\'s proposed excitation trajectory goes '
                             '(default excitation.yaml)')
    parser.add_argument('--excitation-duration', type=float, default=20.0,
                        help='length of the proposed excitation trajectory, s (default 20)')
    parser.set_defaults(func=_run)


def momentum_quality(robot: RobotModel, window: Window, params: dict,
                     settle: float = 2.0) -> dict[str, float]:
    """
    How well ``robot``'s model conserves momentum over a wrench-free window.

    Runs the causal estimator; returns the RMS spread of its mu about the mean
    and the RMS of its external-wrench estimate averaged over 1 s (the false
    drift wrench), after ``settle`` seconds. A wrong payload shows in both while the arm moves.
    """
    from reduced_dynamics.estimator.config import EstimatorConfig
    from reduced_dynamics.estimator.pipeline import Estimator
    estimator = Estimator(robot, EstimatorConfig.from_mapping(params), use_odometry=True)
    batches = [estimator.add_samples(window.samples), estimator.flush_batch()]
    stamps = np.concatenate([b.column('stamps_ns') for b in batches if len(b)])
    mu = np.vstack([b.column('mu') for b in batches if len(b)])
    rate = np.vstack([b.column('momentum_rate') for b in batches if len(b)])
    keep = stamps >= stamps[0] + int(settle * 1e9)
    spread = mu[keep] - mu[keep].mean(axis=0)
    # The drift wrench averaged over 1 s bins: the filter's sample-to-sample noise
    # averages out, a wrong model's false wrench (it follows the arm) does not.
    bins = (stamps[keep] - stamps[keep][0]) // 1_000_000_000
    means = np.array([rate[keep][bins == b].mean(axis=0) for b in np.unique(bins)])
    return {'mu_spread': float(np.sqrt(np.mean(np.sum(spread ** 2, axis=1)))),
            'drift_wrench': float(np.sqrt(np.mean(np.sum(means ** 2, axis=1))))}
