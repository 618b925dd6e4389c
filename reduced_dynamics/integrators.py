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

* :func:`integrate_adaptive`: an adaptive high-order Runge-Kutta. DOP853 (the
  default) is :class:`Dop853`, scipy's tableau and step control without the
  per-step overhead of ``solve_ivp``; after an accepted step that ends with the
  chart coordinates past ``max_chart`` the system re-centres its charts and the
  integration goes on with the same step size.
* :class:`DiscreteGradient`: a fixed-step, energy-preserving scheme for
  ``z_dot = K(z) (grad H(z) - f)`` with ``K = Omega^-1`` skew
  (Gonzalez' midpoint discrete gradient): without forcing ``H(z1) = H(z0)`` up
  to the fixed-point tolerance, for any step, so long runs show no secular
  energy drift. Second order.
"""

from __future__ import annotations

from dataclasses import dataclass
import importlib.util
import os
import sys
import time
from types import ModuleType
from typing import Callable, Optional, Protocol, Sequence

import numpy as np
import scipy
from scipy.linalg.lapack import dgesv


def _dop853_tableau() -> ModuleType:
    """
    Return scipy's module of the DOP853 tableau without importing ``scipy.integrate``.

    The published tableau (Hairer, Norsett & Wanner; Fortran DOP853) as scipy ships
    it: reused rather than retyped, so the two implementations cannot differ. Its
    package's ``__init__`` imports all of scipy.integrate (a third of a second, most
    of ``reduced-dynamics predict``); the module itself needs only numpy.
    """
    name = 'scipy.integrate._ivp.dop853_coefficients'
    loaded = sys.modules.get(name)
    if loaded is not None:
        return loaded
    path = os.path.join(os.path.dirname(scipy.__file__), 'integrate', '_ivp',
                        'dop853_coefficients.py')
    spec = importlib.util.spec_from_file_location('_reduced_dynamics_dop853', path)
    if spec is None or spec.loader is None:  # an unexpected scipy layout: the package way
        return importlib.import_module(name)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


_dop853 = _dop853_tableau()

ADAPTIVE_METHODS = ('DOP853',)


class BudgetExceeded(RuntimeError):
    """An integration ran out of its evaluation or wall-time budget (``reason`` says which)."""

    def __init__(self, reason: str) -> None:
        """Keep the reason (also the message)."""
        super().__init__(reason)
        self.reason = reason


class Budget:
    """
    A cost limit shared by the integrations of one computation (e.g. one prediction).

    ``max_evaluations`` right-hand-side evaluations (or fixed-point iterations)
    and ``max_wall_time`` seconds from construction (None: unlimited).
    :meth:`charge` raises :class:`BudgetExceeded` once either is spent.
    """

    def __init__(self, max_evaluations: Optional[int] = None,
                 max_wall_time: Optional[float] = None) -> None:
        """Start the clock."""
        self.max_evaluations = max_evaluations
        self.max_wall_time = max_wall_time
        self.evaluations = 0
        self.started = time.perf_counter()
        self._deadline = None if max_wall_time is None else self.started + max_wall_time

    @property
    def elapsed(self) -> float:
        """Return the wall time [s] since the budget started."""
        return time.perf_counter() - self.started

    def charge(self, count: int = 1) -> None:
        """Count ``count`` evaluations; raise BudgetExceeded when a limit is passed."""
        self.evaluations += count
        if self.max_evaluations is not None and self.evaluations > self.max_evaluations:
            raise BudgetExceeded(f'evaluation budget exceeded ({self.max_evaluations} '
                                 'right-hand-side evaluations)')
        if self._deadline is not None and time.perf_counter() > self._deadline:
            raise BudgetExceeded(f'wall-time budget exceeded ({self.max_wall_time:g} s, '
                                 f'{self.evaluations} evaluations)')


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
                       max_evaluations: int = 1_000_000,
                       budget: Optional[Budget] = None) -> np.ndarray:
    """
    Integrate from t_eval[0] to t_eval[-1]; return observe() at each t_eval.

    Raises RuntimeError after ``max_evaluations`` right-hand-side calls: near a
    coordinate singularity (gimbal lock of three revolutes) the step size
    collapses and the run would otherwise not end. ``budget``: a shared cost
    limit (:class:`BudgetExceeded` when spent).
    """
    if method not in ADAPTIVE_METHODS:
        raise ValueError(f'unknown adaptive method {method!r}; choose from {ADAPTIVE_METHODS}')
    times = np.asarray(t_eval, dtype=float)
    if times.ndim != 1 or times.size == 0 or np.any(np.diff(times) < 0):
        raise ValueError('t_eval must be a non-empty, non-decreasing sequence')
    solver = Dop853(rtol, atol, max_step, max_evaluations, budget)
    return solver.integrate(system, y0, times, max_chart)


def integrate_pieces(system: ChartedSystem, y0: np.ndarray, t_eval: Sequence[float],
                     breakpoints: Sequence[float], rtol: float, atol: float,
                     budget: Optional[Budget] = None, max_chart: float = 0.5,
                     jump: Optional[Callable[[float, np.ndarray], np.ndarray]] = None
                     ) -> np.ndarray:
    """
    Like :func:`integrate_adaptive`, restarting at ``breakpoints`` inside the span.

    Where the right-hand side's derivatives jump (the knots of a piecewise
    polynomial input), one step across the jump would lose the method's order
    and collapse the step size; restarting there keeps both. ``jump(t, y)``
    maps the state across a breakpoint (an impulsive change), if given.
    """
    times = np.asarray(t_eval, dtype=float)
    if times.ndim != 1 or times.size == 0 or np.any(np.diff(times) < 0):
        raise ValueError('t_eval must be a non-empty, non-decreasing sequence')
    inside = sorted({float(b) for b in breakpoints if times[0] < b < times[-1]})
    edges = [float(times[0])] + inside + [float(times[-1])]
    solver = Dop853(rtol, atol, budget=budget)
    y = np.asarray(y0, dtype=float)
    records: list = []
    for piece, (start, end) in enumerate(zip(edges[:-1], edges[1:])):
        if piece and jump is not None:
            y = jump(start, y)
        # A sample on a breakpoint belongs to the piece it starts (after the jump).
        last = piece == len(edges) - 2
        wanted = times[(times >= start) & ((times <= end) if last else (times < end))]
        span = np.concatenate([[start], wanted, [end]])
        out = solver.integrate(system, y, span, max_chart)
        records.extend(out[1:1 + wanted.size])
        y = solver.final_state
    return np.array(records)


def _rms(x: np.ndarray) -> float:
    return float(np.sqrt(x @ x / x.size))


class Dop853:
    """
    Explicit Runge-Kutta of order 8 with a 5(3) error estimate and order-7 dense output.

    Hairer, Norsett & Wanner, Solving ODEs I, II.5 (DOP853) and II.4 (initial
    step): the algorithm of ``scipy.integrate.DOP853`` (same tableau, error
    norm, safety factors, initial-step rule), so for the same problem it takes
    the same steps up to round-off. What differs is the bookkeeping: stages in a
    preallocated array, no solver / event / ``OdeSolution`` objects, and the
    dense-output stages computed only for steps that hold a sample time.
    """

    SAFETY = 0.9
    MIN_FACTOR = 0.2
    MAX_FACTOR = 10.0
    #: The 5(3) estimate controls an error of order 8: h_new ~ err^(-1/8).
    ERROR_EXPONENT = -1.0 / 8.0

    def __init__(self, rtol: float, atol: float, max_step: float = np.inf,
                 max_evaluations: int = 1_000_000, budget: Optional[Budget] = None) -> None:
        """
        Set tolerances (scale ``atol + rtol |y|``), step bound and evaluation budget.

        ``rtol`` is raised to 100 machine epsilons, as scipy does: below that the
        error estimate is round-off. ``budget``: a cost limit shared with other
        integrations (charged per evaluation).
        """
        self.budget = budget
        #: the state at the end of the last :meth:`integrate` (in the system's charts)
        self.final_state: Optional[np.ndarray] = None
        self.rtol = max(rtol, 100.0 * np.finfo(float).eps)
        self.atol = atol
        self.max_step = max_step
        self.max_evaluations = max_evaluations
        self.evaluations = 0
        stages = _dop853.N_STAGES
        a = _dop853.A
        # Rows of the tableau restricted to the stages they use (12 + 3 dense).
        self._rows = [np.ascontiguousarray(a[s, :s]) for s in range(_dop853.N_STAGES_EXTENDED)]
        self._nodes = _dop853.C
        self._stages = stages
        self._weights = _dop853.B
        self._error5 = _dop853.E5
        self._error3 = _dop853.E3
        self._dense = _dop853.D

    def _call(self, system: 'ChartedSystem', t: float, y: np.ndarray) -> np.ndarray:
        self.evaluations += 1
        if self.evaluations > self.max_evaluations:
            raise RuntimeError(f'integration stalled at t={t:.6g} after {self.evaluations} '
                               'evaluations (a coordinate singularity?)')
        if self.budget is not None:
            self.budget.charge()
        return system.rhs(t, y)

    def _initial_step(self, system: 'ChartedSystem', t: float, y: np.ndarray, f: np.ndarray,
                      span: float) -> float:
        """Return the first step (Hairer II.4, as scipy's select_initial_step)."""
        scale = self.atol + np.abs(y) * self.rtol
        d0, d1 = _rms(y / scale), _rms(f / scale)
        h0 = 1e-6 if d0 < 1e-5 or d1 < 1e-5 else 0.01 * d0 / d1
        h0 = min(h0, span)
        f1 = self._call(system, t + h0, y + h0 * f)
        d2 = _rms((f1 - f) / scale) / h0
        if d1 <= 1e-15 and d2 <= 1e-15:
            h1 = max(1e-6, h0 * 1e-3)
        else:
            h1 = (0.01 / max(d1, d2)) ** (1.0 / 8.0)
        return min(100.0 * h0, h1, span, self.max_step)

    def _attempt(self, system: 'ChartedSystem', t: float, y: np.ndarray, h: float,
                 stages: np.ndarray) -> tuple[np.ndarray, float]:
        """One trial step; stages[0] holds f(t, y) and is filled up to row 12 (FSAL)."""
        rows, nodes = self._rows, self._nodes
        for s in range(1, self._stages):
            stages[s] = self._call(system, t + nodes[s] * h, y + h * (rows[s] @ stages[:s]))
        y_new = y + h * (self._weights @ stages[:self._stages])
        stages[self._stages] = self._call(system, t + h, y_new)
        scale = self.atol + np.maximum(np.abs(y), np.abs(y_new)) * self.rtol
        head = stages[:self._stages + 1]
        err5 = (self._error5 @ head) / scale
        err3 = (self._error3 @ head) / scale
        err5_2, err3_2 = float(err5 @ err5), float(err3 @ err3)
        if err5_2 == 0.0 and err3_2 == 0.0:
            return y_new, 0.0
        return y_new, h * err5_2 / np.sqrt((err5_2 + 0.01 * err3_2) * y.size)

    def _interpolant(self, system: 'ChartedSystem', t: float, y: np.ndarray,
                     y_new: np.ndarray, h: float, stages: np.ndarray) -> np.ndarray:
        """Coefficients F of the order-7 dense output on [t, t + h] (3 more stages)."""
        rows, nodes = self._rows, self._nodes
        for s in range(self._stages + 1, stages.shape[0]):
            stages[s] = self._call(system, t + nodes[s] * h, y + h * (rows[s] @ stages[:s]))
        coeffs = np.empty((_dop853.INTERPOLATOR_POWER, y.size))
        delta = y_new - y
        coeffs[0] = delta
        coeffs[1] = h * stages[0] - delta
        coeffs[2] = 2.0 * delta - h * (stages[self._stages] + stages[0])
        coeffs[3:] = h * (self._dense @ stages)
        return coeffs

    @staticmethod
    def _dense_value(coeffs: np.ndarray, y: np.ndarray, x: float) -> np.ndarray:
        """
        Evaluate the dense output at x = (t - t_old) / h in [0, 1].

        ``y + x (F0 + x'(F1 + x (F2 + x'(F3 + x (F4 + x'(F5 + x F6))))))`` with
        x' = 1 - x (Hairer's CONTD8), expanded into seven scalar weights: one
        product with F instead of fourteen vector operations.
        """
        x1 = 1.0 - x
        xx1 = x * x1
        weights = np.array([x, xx1, x * xx1, xx1 * xx1, x * xx1 * xx1, xx1 ** 3,
                            x * xx1 ** 3])
        return y + weights @ coeffs

    def integrate(self, system: 'ChartedSystem', y0: np.ndarray, times: np.ndarray,
                  max_chart: float) -> np.ndarray:
        """Integrate from times[0] to times[-1]; return observe() at each time."""
        self.evaluations = 0
        y = system.recentre(np.asarray(y0, dtype=float))
        t = float(times[0])
        t_end = float(times[-1])
        records = [system.observe(t, y)]
        index = 1
        while index < times.size and times[index] <= t:
            records.append(system.observe(float(times[index]), y))
            index += 1
        if index == times.size:
            self.final_state = y
            return np.array(records)
        stages = np.empty((_dop853.N_STAGES_EXTENDED, y.size))
        stages[0] = self._call(system, t, y)
        h_abs = self._initial_step(system, t, y, stages[0], t_end - t)
        while index < times.size:
            min_step = 10.0 * abs(np.nextafter(t, np.inf) - t)
            h_abs = min(h_abs, self.max_step)
            h_abs = max(h_abs, min_step)
            rejected = False
            while True:
                if h_abs < min_step:
                    raise RuntimeError(f'integration failed at t={t}: required step size is '
                                       'less than the spacing between numbers')
                t_new = min(t + h_abs, t_end)
                h = t_new - t
                y_new, error = self._attempt(system, t, y, h, stages)
                if error < 1.0:
                    factor = self.MAX_FACTOR if error == 0.0 else \
                        min(self.MAX_FACTOR, self.SAFETY * error ** self.ERROR_EXPONENT)
                    if rejected:
                        factor = min(1.0, factor)
                    h_next = h * factor
                    break
                h_abs = h * max(self.MIN_FACTOR, self.SAFETY * error ** self.ERROR_EXPONENT)
                rejected = True
            if times[index] <= t_new:
                coeffs = self._interpolant(system, t, y, y_new, h, stages)
                while index < times.size and times[index] <= t_new:
                    sample = float(times[index])
                    records.append(system.observe(sample,
                                                  self._dense_value(coeffs, y, (sample - t) / h)))
                    index += 1
            t, y, h_abs = t_new, y_new, h_next
            # FSAL: the last stage is f(t_new, y_new), unless the charts move.
            stages[0] = stages[self._stages]
            if index < times.size and system.chart_size(y) > max_chart:
                y = system.recentre(y)
                stages[0] = self._call(system, t, y)
        self.final_state = y
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
            # Right after evaluate(zm): a system may reuse that evaluation's buffers.
            forcing = self.forcing(t + 0.5 * h, zm)
            dz = z1 - z0
            norm2 = float(dz @ dz)
            dgrad = grad_m
            if norm2 > 0.0:
                dgrad = grad_m + (self.energy(z1) - energy0 - grad_m @ dz) / norm2 * dz
            # LAPACK's gesv directly (np.linalg.solve's routine, without its wrapper).
            _, _, step, info = dgesv(omega, dgrad - forcing)
            if info:
                raise np.linalg.LinAlgError('discrete gradient: singular structure matrix')
            new = z0 + h * step
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
