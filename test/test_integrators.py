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

"""The lean DOP853 against scipy's, and chart re-centring inside an integration."""

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from reduced_dynamics.integrators import Dop853, integrate_adaptive


class Pendulum:
    """theta'' = -sin(theta) with the angle in a chart theta = centre + y[0]."""

    def __init__(self, charted=True):
        self.centre = 0.0
        self.recentres = 0
        self.charted = charted

    def rhs(self, t, y):
        return np.array([y[1], -np.sin(self.centre + y[0])])

    def chart_size(self, y):
        return abs(y[0])

    def recentre(self, y):
        if not self.charted:
            return np.array(y, dtype=float)
        self.recentres += 1
        self.centre += y[0]
        return np.array([0.0, y[1]])

    def observe(self, t, y):
        return np.array([self.centre + y[0], y[1]])


def _scipy_reference(y0, times, rtol, atol):
    solution = solve_ivp(lambda t, y: [y[1], -np.sin(y[0])], (times[0], times[-1]), y0,
                         method='DOP853', rtol=rtol, atol=atol, t_eval=times)
    return solution.y.T, solution.nfev


@pytest.mark.parametrize('tol', [1e-6, 1e-10])
def test_dop853_takes_scipys_steps(tol):
    # Without charts the algorithm is scipy's: same evaluations, same samples up to
    # round-off.
    times = np.linspace(0.0, 10.0, 23)
    y0 = np.array([1.0, 0.3])
    expected, nfev = _scipy_reference(y0, times, tol, tol)
    stepper = Dop853(tol, tol)
    got = stepper.integrate(Pendulum(charted=False), y0, times, max_chart=np.inf)
    assert np.abs(got - expected).max() <= 1e-12
    # solve_ivp also builds the dense output of the first step to sample t0 itself
    # (3 stages); otherwise the evaluations are the same.
    assert stepper.evaluations in (nfev, nfev - 3)


def test_recentring_keeps_the_trajectory():
    # A rotating pendulum crosses many charts; the samples must not notice.
    times = np.linspace(0.0, 6.0, 31)
    y0 = np.array([0.0, 2.5])
    expected, _ = _scipy_reference(y0, times, 1e-12, 1e-12)
    system = Pendulum()
    got = integrate_adaptive(system, y0, times, 'DOP853', 1e-12, 1e-12, max_chart=0.5)
    assert system.recentres > 10
    assert np.abs(got - expected).max() <= 1e-9


def test_samples_at_the_start_and_repeated_times():
    times = np.array([0.0, 0.0, 0.5, 0.5, 1.0])
    got = integrate_adaptive(Pendulum(), np.array([1.0, 0.0]), times, 'DOP853', 1e-10, 1e-10)
    assert got.shape == (5, 2)
    assert np.array_equal(got[0], got[1]) and np.array_equal(got[2], got[3])
    single = integrate_adaptive(Pendulum(), np.array([1.0, 0.0]), [2.0], 'DOP853')
    assert np.array_equal(single, [[1.0, 0.0]])


def test_evaluation_budget_stops_a_stalled_run():
    with pytest.raises(RuntimeError, match='stalled'):
        integrate_adaptive(Pendulum(), np.array([1.0, 0.0]), [0.0, 100.0], 'DOP853',
                           1e-12, 1e-12, max_evaluations=50)


def test_max_step_is_respected():
    stepper = Dop853(1e-6, 1e-6, max_step=0.01)
    stepper.integrate(Pendulum(), np.array([1.0, 0.0]), np.array([0.0, 1.0]), np.inf)
    # At least 100 steps of 12 stages (plus the first-step probe).
    assert stepper.evaluations >= 1200
