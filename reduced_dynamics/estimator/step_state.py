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
The wrench-step test's state in two buffers the compiled row step changes in place.

Every array of :class:`~.step_test.WrenchStepTest` (the onsets, their C, b0, J0,
J0^-1 and scores, Psi, Omega, beta, E, the transition since the last kept measurement,
the kept measurements) is a view of a float64 or an int64 buffer, its scalars are
slots of them, so that ``step_row.filter_step`` takes the test as three arguments
(with ``_bounded``) and needs nothing unpacked afterwards: numba checks every argument
and boxes every result of a call (docs/filter_row.md measures what each costs). The
int buffer carries the layout (n, dim, capacity, the float arrays' offsets), from
which ``step_row.test_views`` makes the same views inside the compiled code.
"""

from __future__ import annotations

from typing import Optional

import numpy as np

#: Measurements back at which a step of the pose measurement is hypothesised (one onset
#: each): a re-fit is seen at once, and a detection comes within a few samples of it.
POSE_STEP_HYPOTHESES = 32

# The int buffer starts with the scalars below, then n, dim and the capacity, then the
# float arrays' offsets (FLOAT_ARRAYS' order), then the onsets and the ring's innovation
# sizes.
#: ``_ints``: the last stamp (< 0: none), onsets alive, the window and the spacing [ns],
#: the settling end [ns] and whether it applies, whether ``_since`` is the identity, the
#: measurements kept (``recent``) and the ring slot the next one goes to
LAST_STAMP, COUNT, WINDOW, SPACING, SETTLE_UNTIL, SETTLING, SINCE_IDENTITY, RECENT, NEXT = \
    range(9)
#: the int buffer's layout header: n, dim, capacity, then the float arrays' offsets
SIZE_N, SIZE_DIM, SIZE_CAPACITY, OFFSETS = 9, 10, 11, 12
#: ``_floats`` (the float buffer's first array): the NIS average, its elapsed time, the last
#: step [s], the threshold, the outlier NIS of n and of 2n innovations, NIS_TIME
NIS_SCALE, ELAPSED, DT, THRESHOLD, OUTLIER_N, OUTLIER_2N, NIS_HORIZON = range(7)
#: the float buffer's arrays, in order (shapes: :func:`state_shapes`)
FLOAT_ARRAYS = ('floats', 'c', 'b0', 'j0', 'bound_inv', 'score', 'psi', 'omega', 'beta',
                'e', 'since', 'ring_since', 'ring_h', 'ring_s', 'ring_gain', 'ring_nu')
#: where the onsets start in the int buffer (the ring's sizes follow them)
ONSETS = OFFSETS + len(FLOAT_ARRAYS)


def state_shapes(n: int, dim: int, capacity: int) -> dict:
    """Return the shapes of the float buffer's arrays (step_row.test_views reads the same)."""
    slots, top = POSE_STEP_HYPOTHESES, 2 * n
    return {'floats': (7,), 'c': (capacity, dim, n), 'b0': (capacity, n),
            'j0': (capacity, n, n), 'bound_inv': (capacity, n, n), 'score': (capacity, n),
            'psi': (dim, dim), 'omega': (dim, dim), 'beta': (dim,), 'e': (dim, n),
            'since': (dim, dim), 'ring_since': (slots, dim, dim), 'ring_h': (slots, top, dim),
            'ring_s': (slots, top, top), 'ring_gain': (slots, dim, top),
            'ring_nu': (slots, top)}


class StepTestState:
    """
    The buffers of a wrench-step test and the arrays and scalars that are views of them.

    The scalars read as attributes (``nis_scale``, ``_count``, ``_stamp``, ...); the
    kept measurements go in a ring (:meth:`_keep`) and read back oldest first
    (:meth:`kept`).
    """

    def __init__(self, n: int, dim: int, capacity: int, window_ns: int, spacing_ns: int,
                 threshold: float, outlier_n: float, outlier_2n: float,
                 nis_time: float) -> None:
        """Allocate for wrenches of dimension n, error dimension dim, ``capacity`` onsets."""
        shapes = state_shapes(n, dim, capacity)
        sizes = [int(np.prod(shapes[name])) for name in FLOAT_ARRAYS]
        starts = np.concatenate(([0], np.cumsum(sizes)[:-1])).astype(np.int64)
        self._state = np.zeros(int(sum(sizes)))
        self._ints = ints = np.zeros(ONSETS + capacity + POSE_STEP_HYPOTHESES, dtype=np.int64)
        ints[SIZE_N], ints[SIZE_DIM], ints[SIZE_CAPACITY] = n, dim, capacity
        ints[OFFSETS:ONSETS] = starts
        self._bounded = np.zeros(capacity, dtype=np.bool_)
        self._identity = np.eye(dim)
        self._views()
        ints[LAST_STAMP] = -1
        ints[WINDOW], ints[SPACING] = window_ns, spacing_ns
        ints[SINCE_IDENTITY] = 1
        floats = self._floats
        floats[THRESHOLD], floats[NIS_HORIZON] = threshold, nis_time
        floats[OUTLIER_N], floats[OUTLIER_2N] = outlier_n, outlier_2n
        floats[NIS_SCALE] = 1.0
        self._psi[:] = self._identity
        self._e[2 * n:3 * n] = np.eye(n)
        self._since_buffer[:] = self._identity

    def _views(self) -> None:
        """Make the arrays views of the buffers (at the start, and after a copy or unpickling)."""
        ints = self._ints
        n, dim, capacity = (int(v) for v in ints[SIZE_N:OFFSETS])
        shapes = state_shapes(n, dim, capacity)
        views = {name: self._state[start:start + int(np.prod(shapes[name]))].reshape(
            shapes[name]) for name, start in zip(FLOAT_ARRAYS, ints[OFFSETS:ONSETS])}
        self._floats = views['floats']
        #: onset stamps [ns] of the hypotheses alive, oldest first (the first ``_count``)
        self._onsets = ints[ONSETS:ONSETS + capacity]
        self._c, self._b0, self._j0 = views['c'], views['b0'], views['j0']
        self._bound_inv, self._score = views['bound_inv'], views['score']
        # Psi, Omega and beta are changed in place, never replaced (views of the buffer).
        self._psi, self._omega, self._beta = views['psi'], views['omega'], views['beta']
        self._e = views['e']
        # The last measurements (Phi since the previous one, H, S, K, innovation), for the
        # pose-step hypotheses, in a ring of POSE_STEP_HYPOTHESES slots (innovations of up
        # to 2n coordinates; ``_ring_m`` says how many), and the transition accumulated
        # since the last one (``_since_buffer``; the identity while SINCE_IDENTITY).
        self._ring_since, self._ring_h = views['ring_since'], views['ring_h']
        self._ring_s, self._ring_gain = views['ring_s'], views['ring_gain']
        self._ring_nu = views['ring_nu']
        self._ring_m = ints[ONSETS + capacity:]
        self._since_buffer = views['since']
        #: the step test's state as step_row's compiled calls take it (fixed objects)
        self.compiled_arrays = (self._state, self._ints, self._bounded)

    #: the attributes :meth:`_views` makes (not copied or pickled: made again from the buffers)
    _VIEWS = ('_floats', '_onsets', '_c', '_b0', '_j0', '_bound_inv', '_score', '_psi',
              '_omega', '_beta', '_e', '_ring_since', '_ring_h', '_ring_s', '_ring_gain',
              '_ring_nu', '_ring_m', '_since_buffer', 'compiled_arrays')

    def __getstate__(self) -> dict:
        """Return the state to copy or pickle: the buffers, not their views (nor modules)."""
        state = {k: v for k, v in self.__dict__.items() if k not in self._VIEWS}
        state['_kernels'] = '_kernels' in state  # the compiled kernels' module: imported
        return state

    def __setstate__(self, state: dict) -> None:
        """Take a copied or unpickled state; make the views of its buffers again."""
        self.__dict__.update(state)
        if state['_kernels']:
            from reduced_dynamics.estimator import step_kernels
            self._kernels = step_kernels
        else:
            del self._kernels
        self._views()

    # --- the scalar state, kept in _ints and _floats ------------------------------------
    @property
    def _count(self) -> int:
        return int(self._ints[COUNT])

    @_count.setter
    def _count(self, value: int) -> None:
        self._ints[COUNT] = value

    @property
    def _stamp(self) -> Optional[int]:
        stamp = int(self._ints[LAST_STAMP])
        return None if stamp < 0 else stamp

    @_stamp.setter
    def _stamp(self, value: Optional[int]) -> None:
        self._ints[LAST_STAMP] = -1 if value is None else value

    @property
    def _settle_until(self) -> Optional[int]:
        return int(self._ints[SETTLE_UNTIL]) if self._ints[SETTLING] else None

    @_settle_until.setter
    def _settle_until(self, value: Optional[int]) -> None:
        self._ints[SETTLING] = value is not None
        self._ints[SETTLE_UNTIL] = 0 if value is None else value

    @property
    def nis_scale(self) -> float:
        """Return the exponential average of the NIS per measured coordinate."""
        return float(self._floats[NIS_SCALE])

    @nis_scale.setter
    def nis_scale(self, value: float) -> None:
        self._floats[NIS_SCALE] = value

    @property
    def _elapsed(self) -> float:
        return float(self._floats[ELAPSED])

    @_elapsed.setter
    def _elapsed(self, value: float) -> None:
        self._floats[ELAPSED] = value

    @property
    def _dt(self) -> float:
        return float(self._floats[DT])

    @_dt.setter
    def _dt(self, value: float) -> None:
        self._floats[DT] = value

    @property
    def _since(self) -> np.ndarray:
        """Return the transition since the last kept measurement (a view: copy to keep)."""
        return self._identity if self._ints[SINCE_IDENTITY] else self._since_buffer

    @property
    def recent(self) -> int:
        """Return the number of measurements kept for the pose-step hypotheses."""
        return int(self._ints[RECENT])

    def _keep(self, h: np.ndarray, s: np.ndarray, gain: np.ndarray, nu: np.ndarray) -> None:
        """Keep a measurement for the pose-step hypotheses (step_row.keep's, in Python)."""
        ints = self._ints
        slot = int(ints[NEXT])
        m = len(nu)
        self._ring_since[slot] = self._since
        self._ring_h[slot, :m] = h
        self._ring_s[slot, :m, :m] = s
        self._ring_gain[slot, :, :m] = gain
        self._ring_nu[slot, :m] = nu
        self._ring_m[slot] = m
        ints[NEXT] = (slot + 1) % POSE_STEP_HYPOTHESES
        ints[RECENT] = min(ints[RECENT] + 1, POSE_STEP_HYPOTHESES)
        ints[SINCE_IDENTITY] = 1

    def kept(self) -> list:
        """Return the kept measurements, oldest first: (Phi since the one before, H, S, K, nu)."""
        count, slots = self.recent, POSE_STEP_HYPOTHESES
        out = []
        for k in range(count):
            slot = (int(self._ints[NEXT]) - count + k) % slots
            m = int(self._ring_m[slot])
            # Copies: contiguous, and the ring's slots are written again.
            out.append((self._ring_since[slot].copy(), self._ring_h[slot, :m].copy(),
                        self._ring_s[slot, :m, :m].copy(), self._ring_gain[slot, :, :m].copy(),
                        self._ring_nu[slot, :m].copy()))
        return out
