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
Integrators for systems that live partly on Lie groups through re-centred charts.

* :func:`integrate_adaptive`: an adaptive high-order Runge-Kutta (DOP853 by
  default, scipy) run in segments; a segment ends when the chart coordinates
  grow past ``max_chart`` and the system re-centres its charts.
* :class:`DiscreteGradient`: a fixed-step, energy-preserving scheme for
  ``z_dot = K(z) (grad H(z) - f)`` with ``K = Omega^-1`` skew
  (Gonzalez' midpoint discrete gradient): without forcing ``H(z1) = H(z0)`` up
  to the fixed-point tolerance, for any step, so long runs show no secular
  energy drift. Second order.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Protocol, Sequence

import numpy as np
from scipy.integrate import solve_ivp

ADAPTIVE_METHODS = ('DOP853', 'RK45', 'Radau')


class ChartedSystem(Protocol):
    """An ODE whose state holds chart coordinates the system can re-centre."""

    def rhs(self, t: float, y: np.ndarray) -> np.ndarray:
        """Time derivative of y."""

    def chart_size(self, y: np.ndarray) -> float:
        """How far y's chart coordinates are from the chart centre."""

    def recentre(self, y: np.ndarray) -> np.ndarray:
        """Re-centre the charts at y; return y in the new charts."""

    def observe(self, t: float, y: np.ndarray) -> np.ndarray:
        """Return a chart-independent record of the state (what callers compare)."""


def integrate_adaptive(system: ChartedSystem, y0: np.ndarray, t_eval: Sequence[float],
                       method: str = 'DOP853', rtol: float = 1e-11, atol: float = 1e-12,
                       max_chart: float = 0.5, max_step: float = np.inf,
                       max_evaluations: int = 1_000_000) -> np.ndarray:
    """
    Integrate from t_eval[0] to t_eval[-1]; return observe() at each t_eval.

    Raises RuntimeError after ``max_evaluations`` right-hand-side calls: near a
    coordinate singularity (gimbal lock of three revolutes) the step size
    collapses and the run would otherwise not end.
    """
    if method not in ADAPTIVE_METHODS:
        raise ValueError(f'unknown adaptive method {method!r}; choose from {ADAPTIVE_METHODS}')
    times = np.asarray(t_eval, dtype=float)
    if times.ndim != 1 or times.size == 0 or np.any(np.diff(times) < 0):
        raise ValueError('t_eval must be a non-empty, non-decreasing sequence')
    y = system.recentre(np.asarray(y0, dtype=float))
    t = float(times[0])
    records = [system.observe(t, y)]
    index = 1

    def leaves_chart(_t: float, state: np.ndarray) -> float:
        return max_chart - system.chart_size(state)
    leaves_chart.terminal = True
    leaves_chart.direction = -1

    evaluations = 0

    def rhs(t_now: float, state: np.ndarray) -> np.ndarray:
        nonlocal evaluations
        evaluations += 1
        if evaluations > max_evaluations:
            raise RuntimeError(f'integration stalled at t={t_now:.6g} after {evaluations} '
                               'evaluations (a coordinate singularity?)')
        return system.rhs(t_now, state)

    while index < times.size:
        end = float(times[-1])
        solution = solve_ivp(rhs, (t, end), y, method=method, rtol=rtol, atol=atol,
                             dense_output=True, events=leaves_chart, max_step=max_step)
        if solution.status < 0:
            raise RuntimeError(f'integration failed at t={t}: {solution.message}')
        t_reached = float(solution.t[-1])
        while index < times.size and times[index] <= t_reached:
            records.append(system.observe(times[index], solution.sol(times[index])))
            index += 1
        t = t_reached
        y = system.recentre(solution.y[:, -1])
    return np.array(records)


@dataclass
class DiscreteGradientStats:
    """Counters of the fixed-point iterations (for benchmarks and diagnostics)."""

    steps: int = 0
    iterations: int = 0
    max_residual: float = 0.0


class DiscreteGradient:
    """
    Energy-preserving fixed-step integrator (Gonzalez discrete gradient).

    ``evaluate(z)`` must return ``(H, grad H, Omega)`` with Omega skew and
    ``z_dot = Omega^-1 (grad H - f)``; ``forcing(t, z)`` returns f (zero for a
    conservative system). Each step solves
    ``z1 = z0 + h Omega(zm)^-1 (dgrad(z0, z1) - f(t + h/2, zm))`` by fixed-point
    iteration, ``zm = (z0 + z1) / 2``.
    """

    def __init__(self, evaluate: Callable[[np.ndarray], tuple[float, np.ndarray, np.ndarray]],
                 energy: Callable[[np.ndarray], float],
                 forcing: Callable[[float, np.ndarray], np.ndarray],
                 tol: float = 1e-13, max_iterations: int = 50) -> None:
        """Wrap the system's evaluation, energy and forcing callbacks."""
        self.evaluate = evaluate
        self.energy = energy
        self.forcing = forcing
        self.tol = tol
        self.max_iterations = max_iterations
        self.stats = DiscreteGradientStats()

    def step(self, t: float, z0: np.ndarray, h: float, h0: float | None = None,
             z1_guess: np.ndarray | None = None) -> np.ndarray:
        """One step of size h from (t, z0)."""
        energy0 = self.energy(z0) if h0 is None else h0
        z1 = z0.copy() if z1_guess is None else z1_guess.copy()
        scale = 1.0 + np.abs(z0)
        residual = np.inf
        for iteration in range(1, self.max_iterations + 1):
            zm = 0.5 * (z0 + z1)
            _, grad_m, omega = self.evaluate(zm)
            dz = z1 - z0
            norm2 = float(dz @ dz)
            dgrad = grad_m
            if norm2 > 0.0:
                dgrad = grad_m + (self.energy(z1) - energy0 - grad_m @ dz) / norm2 * dz
            new = z0 + h * np.linalg.solve(omega, dgrad - self.forcing(t + 0.5 * h, zm))
            previous = residual
            residual = float(np.max(np.abs(new - z1) / scale))
            z1 = new
            # Converged, or stalled at the round-off floor just above the tolerance.
            if residual <= self.tol or (residual <= 1e3 * self.tol and residual >= previous):
                break
        else:
            raise RuntimeError(f'discrete gradient: no convergence at t={t} (residual '
                               f'{residual:.2e}); reduce the step')
        self.stats.steps += 1
        self.stats.iterations += iteration
        self.stats.max_residual = max(self.stats.max_residual, residual)
        return z1
