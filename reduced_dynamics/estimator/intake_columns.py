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
Validation of a batch of input messages by columns (the batched path's intake).

:meth:`~.intake.InputIntake._take_batch` asks these functions, before it takes
any message of a batch, which messages pass every value check (finite values,
the plausibility bounds of :mod:`.plausibility`, a usable quaternion) and what
each one queues: the joint states' own arrays, and base rows built for the whole
batch in one array with the same float operations, in the same order, as
:meth:`~.intake.InputIntake._take_base` does for one message (the same bits). A
message that fails gets None: the per-message path takes it in its place and
says why. The stamp policy and synchronisation stay per message (they carry
state from one sample to the next).
"""

from __future__ import annotations

from typing import Optional, Sequence

import numpy as np

from reduced_dynamics.estimator.plausibility import BaseBounds, JointBounds


def joint_columns(joints: list, model: Sequence[str], bounds: JointBounds,
                  zeros: np.ndarray, least: int) -> list:
    """
    Return per joint state its queued tuple (stamp, qbar, qbar_dot, tau), or None.

    Only joint states that list the model's joints in its order (``model``) with
    velocities are taken (at least ``least`` of them, or none); ``zeros`` (m,)
    stands for a missing effort, which is not checked, as per message. The
    arrays are the messages' own, by reference, as the per-message path queues them.
    """
    out: list = [None] * len(joints)
    index = [k for k, s in enumerate(joints)
             if (s.names is model or s.names == model) and s.velocity.size]
    if len(index) < least:
        return out
    taken = joints if len(index) == len(joints) else [joints[k] for k in index]
    count, m = len(taken), len(zeros)
    position = np.concatenate([s.position for s in taken]).reshape(count, m)
    velocity = np.concatenate([s.velocity for s in taken]).reshape(count, m)
    efforts = [s.effort for s in taken]
    effort = np.concatenate(efforts)
    no_effort = None
    if effort.size != count * m:
        # Some without effort (each has none or m): zeros, not checked, as per message.
        efforts = [e if e.size else zeros for e in efforts]
        no_effort = np.fromiter((e is zeros for e in efforts), bool, count)
        effort = np.concatenate(efforts)
    effort = effort.reshape(count, m)
    # (Bad rows may be NaN: they fail, and the per-message path says why.)
    with np.errstate(all='ignore'):
        ok = np.isfinite(position).all(axis=1)
        ok &= np.isfinite(velocity).all(axis=1)
        ok &= np.isfinite(effort).all(axis=1)
        ok &= bounds.passes(position, velocity, effort, no_effort)
    if taken is joints and ok.all():
        return [(s.stamp_ns, s.position, s.velocity, e) for s, e in zip(taken, efforts)]
    for k, s, e, passed in zip(index, taken, efforts, ok.tolist()):
        if passed:
            out[k] = (s.stamp_ns, s.position, s.velocity, e)
    return out


def base_columns(bases: list, odometry: bool, covariance: bool, bounds: BaseBounds,
                 least: int) -> tuple[list, Optional[list]]:
    """
    Return per base state its (stamp, row), or None; then which carry their own noise.

    For a floating base whose twists need no projection (the caller's test). With
    Odometry, samples with a twist are taken, in pose mode those without (at least
    ``least``, or none). The row holds the values the per-message path puts in its
    list (position, normalised quaternion, twist), the same bits:
    x / sqrt(x x + y y + z z + w w) in the same order; it is a row of one array (no
    list of floats per sample). Second: per base state whether its message
    covariance is to be read (``covariance``: use_message_covariance), or None.
    """
    out: list = [None] * len(bases)
    index = [k for k, s in enumerate(bases) if (s.twist_linear is not None) is odometry]
    count = len(index)
    if count < least:
        return out, None
    noisy = [s.pose_covariance is not None or s.twist_covariance is not None
             for s in bases] if covariance else None
    if noisy is not None and not any(noisy):
        noisy = None
    taken = bases if count == len(bases) else [bases[k] for k in index]
    width = 13 if odometry else 7
    # One (count, width) array: position, quaternion, twist (normalised in place below).
    arrays = [a for s in taken for a in (s.position, s.orientation_xyzw, s.twist_linear,
                                         s.twist_angular)] if odometry else \
        [a for s in taken for a in (s.position, s.orientation_xyzw)]
    rows = np.concatenate(arrays).reshape(count, width)
    position, quaternion = rows[:, :3], rows[:, 3:7]
    twist = rows[:, 7:] if odometry else None
    x, y, z, w = quaternion.T
    # (Bad rows may overflow or be NaN: they fail, and the per-message path says why.)
    with np.errstate(all='ignore'):
        norm = np.sqrt(x * x + y * y + z * z + w * w)
        ok = np.isfinite(rows).all(axis=1)
        ok &= norm >= 1e-6
        ok &= bounds.passes(position, norm, twist)
        quaternion /= norm[:, None]
    # The rows are views of one array (what the chunk stacks again in one call).
    if taken is bases and ok.all():
        return [(s.stamp_ns, row) for s, row in zip(taken, rows)], noisy
    for k, s, row, passed in zip(index, taken, rows, ok.tolist()):
        if passed:
            out[k] = (s.stamp_ns, row)
    return out, noisy
