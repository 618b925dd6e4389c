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
SE(3) and its displacement subgroups as 4 x 4 arrays, compiled.

Twists are (v, omega), linear first, as in Pinocchio; ``exp6``/``log6`` follow
``pin.exp6``/``pin.log6`` (tested equal to 1e-12) and ``action`` is
``pin.SE3.action``. A subgroup with motion subspace S (6 x n) and its
pseudo-inverse S+ maps algebra coordinates eta to the twist S eta
(geometry/lie_group.py); ``whole`` skips S and S+ for SE(3) itself.
"""

import math

import numpy as np
from numba import njit


@njit(cache=True)
def _skew(w0: float, w1: float, w2: float) -> tuple:
    """Return [w] row by row as 9 floats (a tuple: no array allocated; zeros as 0.0)."""
    return (0.0, -w2, w1, w2, 0.0, -w0, -w1, w0, 0.0)


@njit(cache=True)
def _mul3(a: tuple, b: tuple) -> tuple:
    """
    Return a b of 3 x 3 matrices held row by row in 9-tuples.

    By the expressions of a loop over i, j of a[i, 0] b[0, j] + a[i, 1] b[1, j] +
    a[i, 2] b[2, j] (a BLAS call costs more than the product; a tuple, unlike an
    array, is not allocated).
    """
    return (a[0] * b[0] + a[1] * b[3] + a[2] * b[6],
            a[0] * b[1] + a[1] * b[4] + a[2] * b[7],
            a[0] * b[2] + a[1] * b[5] + a[2] * b[8],
            a[3] * b[0] + a[4] * b[3] + a[5] * b[6],
            a[3] * b[1] + a[4] * b[4] + a[5] * b[7],
            a[3] * b[2] + a[4] * b[5] + a[5] * b[8],
            a[6] * b[0] + a[7] * b[3] + a[8] * b[6],
            a[6] * b[1] + a[7] * b[4] + a[8] * b[7],
            a[6] * b[2] + a[7] * b[5] + a[8] * b[8])


@njit(cache=True)
def exp6_coefficients(t2: float) -> tuple:
    """
    Return exp6's coefficients (a, b, c) at ``t2 = |omega|^2``.

    ``R = 1 + a [w] + b [w]^2`` and ``V = 1 + b [w] + c [w]^2`` with ``a = sin t / t``,
    ``b = (1 - cos t) / t^2``, ``c = (t - sin t) / t^3`` (series below 1e-4 rad).
    """
    t = math.sqrt(t2)
    if t < 1e-4:
        # Series: the closed forms lose digits to cancellation at small angles.
        a = 1.0 - t2 / 6.0 * (1.0 - t2 / 20.0)
        b = 0.5 - t2 / 24.0 * (1.0 - t2 / 30.0)
        c = 1.0 / 6.0 - t2 / 120.0 * (1.0 - t2 / 42.0)
    else:
        s, half = math.sin(t), math.sin(0.5 * t)
        a = s / t
        b = 2.0 * half * half / t2          # (1 - cos t) / t^2 without cancellation
        c = (t - s) / (t2 * t)
    return a, b, c


@njit(cache=True)
def exp6(twist: np.ndarray) -> np.ndarray:
    """Return exp of a twist (v, omega) as a 4 x 4 homogeneous matrix."""
    v, w = twist[:3], twist[3:]
    a, b, c = exp6_coefficients(w[0] * w[0] + w[1] * w[1] + w[2] * w[2])
    k = _skew(w[0], w[1], w[2])
    k2 = _mul3(k, k)
    out = np.zeros((4, 4))
    for i in range(3):
        for j in range(3):
            out[i, j] = a * k[3 * i + j] + b * k2[3 * i + j]
        out[i, i] += 1.0
        # V v = v + b w x v + c w x (w x v)
        out[i, 3] = v[i] + b * (k[3 * i] * v[0] + k[3 * i + 1] * v[1] + k[3 * i + 2] * v[2]) \
            + c * (k2[3 * i] * v[0] + k2[3 * i + 1] * v[1] + k2[3 * i + 2] * v[2])
    out[3, 3] = 1.0
    return out


@njit(cache=True)
def _log3(r: np.ndarray) -> tuple:
    """Return (omega_0, omega_1, omega_2, angle) with exp([omega]) = r, angle in [0, pi]."""
    axis0, axis1, axis2 = r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]
    sine = 0.5 * math.sqrt(axis0 ** 2 + axis1 ** 2 + axis2 ** 2)
    cosine = 0.5 * (r[0, 0] + r[1, 1] + r[2, 2] - 1.0)
    t = math.atan2(sine, cosine)
    if cosine > -0.9:
        # t / (2 sin t) is smooth here (series below 1e-4).
        scale = 0.5 + t * t / 12.0 if t < 1e-4 else 0.5 * t / sine
        return axis0 * scale, axis1 * scale, axis2 * scale, t
    # Near pi: the symmetric part (1 - cos t) a a^T gives the axis, the skew part its sign.
    axis = np.array([axis0, axis1, axis2])
    best = 0
    for i in range(1, 3):
        if r[i, i] > r[best, best]:
            best = i
    column = np.empty(3)
    for i in range(3):
        column[i] = 0.5 * (r[i, best] + r[best, i])
    column[best] = r[best, best] - cosine
    norm = math.sqrt(column[0] ** 2 + column[1] ** 2 + column[2] ** 2)
    a = column / norm
    if a[0] * axis[0] + a[1] * axis[1] + a[2] * axis[2] < 0.0:
        a = -a
    return a[0] * t, a[1] * t, a[2] * t, t


@njit(cache=True)
def log6(g: np.ndarray) -> np.ndarray:
    """Return the twist (v, omega) of a 4 x 4 homogeneous matrix (``pin.log6``)."""
    w0, w1, w2, t = _log3(g[:3, :3])
    p = g[:3, 3]
    t2 = t * t
    if t < 1e-2:
        # Series: the closed form cancels to t^2 / 12 (1e-9 relative at 1 mrad).
        c = 1.0 / 12.0 + t2 / 720.0 + t2 * t2 / 30240.0
    else:
        c = (1.0 - 0.5 * t * math.sin(t) / (1.0 - math.cos(t))) / t2
    k = _skew(w0, w1, w2)
    k2 = _mul3(k, k)
    out = np.empty(6)
    for i in range(3):
        # V^-1 p = p - w x p / 2 + c w x (w x p)
        out[i] = p[i] - 0.5 * (k[3 * i] * p[0] + k[3 * i + 1] * p[1] + k[3 * i + 2] * p[2]) \
            + c * (k2[3 * i] * p[0] + k2[3 * i + 1] * p[1] + k2[3 * i + 2] * p[2])
    out[3], out[4], out[5] = w0, w1, w2
    return out


@njit(cache=True)
def inverse(g: np.ndarray) -> np.ndarray:
    """Return g^-1 of a 4 x 4 homogeneous matrix."""
    out = np.zeros((4, 4))
    for i in range(3):
        for j in range(3):
            out[i, j] = g[j, i]
        out[i, 3] = -(g[0, i] * g[0, 3] + g[1, i] * g[1, 3] + g[2, i] * g[2, 3])
    out[3, 3] = 1.0
    return out


@njit(cache=True)
def compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Return a b of 4 x 4 homogeneous matrices (rotation and translation only)."""
    out = np.zeros((4, 4))
    for i in range(3):
        for j in range(3):
            out[i, j] = a[i, 0] * b[0, j] + a[i, 1] * b[1, j] + a[i, 2] * b[2, j]
        out[i, 3] = a[i, 0] * b[0, 3] + a[i, 1] * b[1, 3] + a[i, 2] * b[2, 3] + a[i, 3]
    out[3, 3] = 1.0
    return out


@njit(cache=True)
def action(g: np.ndarray) -> np.ndarray:
    """Return Ad_g (6 x 6, ``pin.SE3.action``): [[R, [p] R], [0, R]]."""
    out = np.zeros((6, 6))
    r = (g[0, 0], g[0, 1], g[0, 2], g[1, 0], g[1, 1], g[1, 2], g[2, 0], g[2, 1], g[2, 2])
    pr = _mul3(_skew(g[0, 3], g[1, 3], g[2, 3]), r)
    for i in range(3):
        for j in range(3):
            out[i, j] = r[3 * i + j]
            out[3 + i, 3 + j] = r[3 * i + j]
            out[i, 3 + j] = pr[3 * i + j]
    return out


@njit(cache=True)
def group_exp(eta: np.ndarray, basis: np.ndarray, whole: bool) -> np.ndarray:
    """Return exp of algebra coordinates eta of the subgroup (S eta)."""
    # exp6 reads the twist only: no copy of eta when it is one already.
    return exp6(eta) if whole else exp6(basis @ eta)


@njit(cache=True)
def group_log(g: np.ndarray, pinv: np.ndarray, whole: bool) -> np.ndarray:
    """Return the algebra coordinates S+ log6(g) of g in the subgroup."""
    twist = log6(g)
    return twist if whole else pinv @ twist


@njit(cache=True)
def adjoint(g: np.ndarray, basis: np.ndarray, pinv: np.ndarray, whole: bool) -> np.ndarray:
    """Return Ad_g on the subalgebra (n x n): S+ Ad_g S."""
    full = action(g)
    return full if whole else pinv @ full @ basis


@njit(cache=True)
def plus(g: np.ndarray, eta: np.ndarray, basis: np.ndarray, whole: bool) -> np.ndarray:
    """Return g exp(eta) (right perturbation)."""
    return compose(g, group_exp(eta, basis, whole))


@njit(cache=True)
def minus(a: np.ndarray, b: np.ndarray, pinv: np.ndarray, whole: bool) -> np.ndarray:
    """Return log(b^-1 a) in algebra coordinates."""
    return group_log(compose(inverse(b), a), pinv, whole)
