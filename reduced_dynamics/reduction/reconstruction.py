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
Propagation of the reduced system with reconstruction of the base pose.

The reduced state z evolves by Theorem 54; the base pose follows
``g_dot = g xi`` with ``xi = I^-1 pi - A qbar_dot`` (REDUCED_MODEL.md 4), carried
in a re-centred exponential chart ``g = g_seg exp(eta)``. Two integrators:
adaptive DOP853 (accuracy) and the energy-preserving discrete gradient
(fixed step, long horizons).
"""

from __future__ import annotations

from typing import Optional, Sequence

import numpy as np
import pinocchio as pin

from reduced_dynamics.integrators import Budget, DiscreteGradient, integrate_adaptive
from reduced_dynamics.reduction.lean_field import LeanField
from reduced_dynamics.reduction.vector_field import ReducedSystem
from reduced_dynamics.robot.state import FreeFloatingState, TorqueLaw, zero_torque

INTEGRATORS = ('dop853', 'discrete_gradient')


class ReducedPropagator:
    """
    Reduced model plus base-pose reconstruction, as one integrable system.

    y = (q~1, qbar, pbar, eta): the reduced state and the base-pose chart.
    """

    def __init__(self, system: ReducedSystem, g0: pin.SE3,
                 torque: Optional[TorqueLaw] = None) -> None:
        """Propagate ``system`` from base pose g0 under a shape-torque law."""
        self.system = system
        self.group = system.group
        self.torque = torque or zero_torque(system.m)
        self.g_seg = pin.SE3(g0)
        self.nz = system.k + 2 * system.m
        self._lean: Optional[LeanField] = None

    @classmethod
    def from_full_state(cls, robot, state: FreeFloatingState,
                        torque: Optional[TorqueLaw] = None) -> tuple['ReducedPropagator',
                                                                     np.ndarray]:
        """Propagator through a full state and its initial y."""
        system, z = ReducedSystem.from_full_state(robot, state)
        return cls(system, state.g, torque), np.concatenate([z, np.zeros(robot.n)])

    def pose(self, y: np.ndarray) -> pin.SE3:
        """Reconstructed base pose of y."""
        return self.g_seg * self.group.exp(y[self.nz:])

    def _torque_at(self, t: float):
        return lambda qbar, qbar_dot: self.torque(t, qbar, qbar_dot)

    def rhs(self, t: float, y: np.ndarray) -> np.ndarray:
        """dy/dt: Theorem 54 (as :meth:`ReducedSystem.vector_field`) and g_dot = g xi."""
        # The compiled route (lean_field.py): the same field as vector_field, with
        # eta_dot = Jr(eta)^-1 xi for g = g_seg exp(eta).
        return self._lean_field()(t, y, self.torque)

    def _lean_field(self) -> LeanField:
        if self._lean is None or self._lean.system is not self.system:
            self._lean = LeanField(self.system)
        return self._lean

    def chart_size(self, y: np.ndarray) -> float:
        """Largest of the orbit-chart and base-chart coordinate norms."""
        return max(float(np.linalg.norm(y[:self.system.k])),
                   float(np.linalg.norm(y[self.nz:])))

    def recentre(self, y: np.ndarray) -> np.ndarray:
        """Re-centre the chart of Q1/G_mu and the base-pose chart."""
        self.g_seg = self.pose(y)
        out = y.copy()
        out[:self.nz] = self.system.recentre(y[:self.nz])
        out[self.nz:] = 0.0
        return out

    def observe(self, t: float, y: np.ndarray) -> np.ndarray:
        """[g (16), pi(q~1), qbar, qbar_dot, pbar, H~]."""
        _, qbar, pbar = self.system.split(y[:self.nz])
        pi, _, qbar_dot, energy = self._lean_field().kinematics(y)
        return np.concatenate([self.pose(y).homogeneous.ravel(), pi, qbar, qbar_dot, pbar,
                               [energy]])

    def propagate(self, y0: np.ndarray, times: Sequence[float], integrator: str = 'dop853',
                  rtol: float = 1e-11, atol: float = 1e-12,
                  step: float = 1e-3, budget: Optional[Budget] = None) -> 'ReducedTrajectory':
        """
        Integrate from times[0] and sample at ``times``.

        ``dop853``: adaptive with tolerances rtol/atol. ``discrete_gradient``:
        fixed ``step`` (the sample times should be multiples of it).
        ``budget``: a cost limit (evaluations, or fixed-point iterations).
        """
        times = np.asarray(times, dtype=float)
        if integrator == 'dop853':
            records = integrate_adaptive(self, y0, times, 'DOP853', rtol, atol, budget=budget)
        elif integrator == 'discrete_gradient':
            records = self._propagate_fixed(y0, times, step, budget)
        else:
            raise ValueError(f'unknown integrator {integrator!r}; choose from {INTEGRATORS}')
        return ReducedTrajectory(self.system, times, records)

    def fixed_step_integrator(self) -> DiscreteGradient:
        """
        Return the discrete-gradient integrator for this system's z (time set per step).

        H~, its gradient and the structure matrix come from the compiled route
        (:meth:`.LeanField.evaluate`, held equal to :meth:`.ReducedSystem.evaluate`
        in the tests); the forcing reads qbar_dot from the same buffers.
        """
        system = self.system
        # qbar_dot of the last evaluate(z): the integrator asks for the forcing at the
        # same z right after (identity checked), which then needs no crba of its own.
        last: list = [None, None]

        def evaluate(z: np.ndarray):
            lean = self._lean_field()
            out = lean.evaluate(z)
            last[0], last[1] = z, lean.v[system.robot.n:].copy()
            return out

        def energy(z: np.ndarray) -> float:
            return self._lean_field().energy(z)

        def forcing(t: float, z: np.ndarray) -> np.ndarray:
            out = np.zeros_like(z)
            if not self._has_torque:
                return out
            _, qbar, _ = system.split(z)
            if z is last[0]:
                qbar_dot = last[1]
            else:
                qbar_dot = self._lean_field().kinematics(z)[2]
            out[system.k:system.k + system.m] = self.torque(t, qbar, qbar_dot)
            return out

        return DiscreteGradient(evaluate, energy, forcing)

    @property
    def _has_torque(self) -> bool:
        return not getattr(self.torque, 'is_zero', False)

    def _propagate_fixed(self, y0: np.ndarray, times: np.ndarray, step: float,
                         budget: Optional[Budget] = None) -> np.ndarray:
        stepper = self.fixed_step_integrator()
        y = self.recentre(np.asarray(y0, dtype=float))
        t = float(times[0])
        records = [self.observe(t, y)]
        lean = self._lean_field()
        energy = lean.energy(y[:self.nz])
        for target in times[1:]:
            while t < target - 1e-12:
                h = min(step, target - t)
                z0 = y[:self.nz]
                before = stepper.stats.iterations
                # Start the fixed point from an explicit midpoint step (error O(h^3)
                # instead of O(h) from z0): fewer iterations to the same tolerance.
                half = y + 0.5 * h * self.rhs(t, y)
                guess = z0 + h * self.rhs(t + 0.5 * h, half)[:self.nz]
                z1 = stepper.step(t, z0, h, energy, guess)
                if budget is not None:
                    # The iterations and the two evaluations of the starting guess.
                    budget.charge(stepper.stats.iterations - before + 2)
                zm = 0.5 * (z0 + z1)
                xi_mid = lean.kinematics(zm)[1]
                # g_{n+1} = g_n exp(h xi(z_mid)): second order, like the scheme.
                self.g_seg = self.pose(y) * self.group.exp(h * xi_mid)
                y = np.concatenate([z1, np.zeros(self.group.dim)])
                energy = lean.energy(z1) if self._has_torque else energy
                t += h
                if self.chart_size(y) > 0.5:
                    y = self.recentre(y)
            records.append(self.observe(t, y))
        return np.array(records)


class ReducedTrajectory:
    """Samples of a reduced run: reconstructed poses, pi(q~1), shape, rates, pbar, H~."""

    def __init__(self, system: ReducedSystem, times: np.ndarray, records: np.ndarray) -> None:
        """Split observe() records into named arrays."""
        n, m = system.group.dim, system.m
        self.times = times
        self.poses = records[:, :16].reshape(-1, 4, 4)
        self.pi = records[:, 16:16 + n]
        self.qbar = records[:, 16 + n:16 + n + m]
        self.qbar_dot = records[:, 16 + n + m:16 + n + 2 * m]
        self.pbar = records[:, 16 + n + 2 * m:16 + n + 3 * m]
        self.energy = records[:, -1]

    def pose(self, index: int) -> pin.SE3:
        """Reconstructed base pose at sample ``index``."""
        return pin.SE3(self.poses[index])
