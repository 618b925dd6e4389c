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
The momenta measured twists give, for the multi-scale test's block bank.

mu = Ad_{g^-1}^T I (xi + A qbar_dot) per accepted twist (:func:`twist_momentum`),
with its white and common covariances, and where the base pose comes with it the
measured centre of mass (:func:`centre_of_mass`); :func:`twist_momenta` gives a
row's, the common one as a :class:`TwistSample` whose momentum the banks' compiled
call computes (docs/multiscale_events.md).
"""

from __future__ import annotations

from typing import Any, NamedTuple, Optional

import numpy as np
from reduced_dynamics.estimator.core import impulse


def twist_momentum(ad_inverse: np.ndarray, locked: np.ndarray, connection_qd: np.ndarray,
                   twist: np.ndarray, twist_cov: np.ndarray, joint_cov: np.ndarray,
                   pose_cov: np.ndarray, kirillov: Any
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """
    Return the momentum one measured body twist gives, and two covariances.

    mu = Ad_{g^-1}^T pi with pi = I (xi + A qbar_dot) (REDUCED_MODEL.md, the twist
    measurement h = I^-1 Ad_g^T mu - A qbar_dot turned around), g the filter's pose.
    Its noise: the twist's and the joint velocities' (``joint_cov``, body twist
    coordinates) through I, white; and the filter's pose error (``pose_cov``)
    through Ad, Ad_{(g exp d)^-1}^T pi = Ad_{g^-1}^T (pi + W(pi) d) (``kirillov``:
    pi -> W(pi), BaseGroup.coadjoint_form), which changes slowly: averaging does
    not reduce it.
    """
    pi = locked @ (twist + connection_qd)
    # The products in one compiled call, in numpy's order (core/impulse.py).
    return impulse.twist_momentum(ad_inverse, locked, pi, twist_cov, joint_cov, pose_cov,
                                  kirillov(pi))


class TwistSample(NamedTuple):
    """
    One measured twist of an SE(3) base, not yet turned into a momentum.

    The arguments of :func:`.impulse.measured_momentum_se3`: the row's locked inertia
    for the momentum, and for the centre of mass the one at the sample's stamp
    (``com_locked``: the row's own at the row, interpolated between two rows, as
    :func:`twist_momenta` does). :class:`.MultiScaleTest` turns it into
    the momentum inside the banks' compiled call (core/bank_step.twist_step);
    :meth:`momentum` gives the (stamp, mu, white, common, position) tuple
    :func:`twist_momenta` gives for other samples, the same bits.
    """

    stamp_ns: int
    ad_inverse: np.ndarray
    locked: np.ndarray
    twist: np.ndarray
    connection_qd: np.ndarray
    twist_cov: np.ndarray
    joint_cov: np.ndarray
    pose_cov: np.ndarray
    structure: np.ndarray
    rotation: np.ndarray
    translation: np.ndarray
    com_pose_cov: np.ndarray
    com_locked: np.ndarray

    def momentum(self) -> tuple:
        """Return (stamp, mu, white covariance, common covariance, position)."""
        mu, white, common, world, cov, mass = impulse.measured_momentum_se3(
            self.ad_inverse, self.locked, self.twist, self.connection_qd, self.twist_cov,
            self.joint_cov, self.pose_cov, self.structure, self.com_locked, self.rotation,
            self.translation, self.com_pose_cov)
        return self.stamp_ns, mu, white, common, (world, cov, mass, _LINEAR_SE3)


def twist_momenta(flt: Any, before: Any, lin: Any, start_ns: Optional[int], stamp_ns: int,
                  measurements: list, gated: list, g: Any = None) -> list[tuple]:
    """
    Return (stamp, mu, covariance) of a row's accepted twist measurements.

    An SE(3) base's with the filter's noise as a :class:`TwistSample`, at the row or
    between two (inputs interpolated): the multi-scale test computes its momentum in its
    own compiled call.

    ``before``, ``lin``: the linearisations of the previous row (at ``start_ns``)
    and of this one (at ``stamp_ns``); A qbar_dot is interpolated to each
    measurement's stamp, as the filter does (a moving arm's A qbar_dot changes within
    a row interval by more than a precise twist's noise). ``gated``: stamps the
    filter refused. The filter's pose maps them to the world (``g``: that pose as a
    pin.SE3 when the caller has it; None: taken from the filter).
    """
    if flt._g is None:
        return []
    # To the world with the filter's pose, not each sample's: a measured pose's noise
    # would weigh the samples by their own error (C depends on it), biasing the means.
    n = lin.locked.shape[0]
    ad_inverse = flt._adjoint_inverse(flt.g if g is None else g)
    pose_cov = flt.p[:n, :n]
    out = []
    span = None if start_ns is None or before is None else stamp_ns - start_ns
    se3 = flt.group.name == 'SE(3)'
    for measurement in measurements:
        if measurement is None or measurement.twist is None or \
                measurement.stamp_ns in gated:
            continue
        connection, locked = lin.connection_qd, lin.locked
        if span and measurement.stamp_ns < stamp_ns:
            fraction = (measurement.stamp_ns - start_ns) / span
            connection = before.connection_qd + fraction * (lin.connection_qd
                                                            - before.connection_qd)
            locked = before.locked + fraction * (lin.locked - before.locked)
        own_pose, own = (None, None) if measurement.noise is None else measurement.noise
        twist_cov = flt._r_twist if own is None else own
        com_cov = flt._r_pose if own_pose is None else own_pose
        if se3:
            pose = measurement.pose
            # tuple.__new__: the fields as they are (the NamedTuple's own __new__ is a
            # Python function, ~0.5 us a row).
            sample = tuple.__new__(TwistSample, (
                measurement.stamp_ns, ad_inverse, lin.locked, measurement.twist,
                connection, twist_cov, lin.joint_cov, pose_cov,
                flt.group.structure_constants, pose.rotation, pose.translation, com_cov,
                locked))
            # The filter's noise (at the row, or between two rows: sensors on their own
            # clocks): the banks' compiled call computes its momentum. A message's own
            # noise: computed here (its covariances' layouts would compile that call again).
            out.append(sample if measurement.noise is None else sample.momentum())
            continue
        out.append((measurement.stamp_ns, *twist_momentum(
            ad_inverse, lin.locked, connection, measurement.twist, twist_cov,
            lin.joint_cov, pose_cov, flt.group.coadjoint_form), centre_of_mass(
                flt.group.name, measurement.pose, locked, com_cov)))
    return out


#: The algebra coordinates of the linear momentum, per base group whose measured
#: centre of mass the block test reads (world x, y, z; x, y in the plane).
LINEAR = {'SE(3)': (0, 1, 2), 'SE(2)': (0, 1)}
_LINEAR_SE3 = LINEAR['SE(3)']


def centre_of_mass(group: str, pose: Any, locked: np.ndarray, pose_cov: np.ndarray
                   ) -> Optional[tuple]:
    """
    Return the measured centre of mass in the world, its covariance, the mass, the axes.

    The locked inertia holds the first moment: its linear-angular block is -M [c]x
    for SE(3) (c in the base frame), -M c_y, M c_x in the plane for SE(2). With the
    measured pose g = (R, p): c_world = p + R c, and a pose error exp(d) (body
    coordinates: translation d_v, rotation d_w) moves it by R (d_v - [c]x d_w).
    None for other base groups (the linear momentum is not the slope of a point).
    """
    axes = LINEAR.get(group)
    if axes is None:
        return None
    if group == 'SE(3)':
        # Compiled (core/impulse.py); SE(2) below.
        world, cov, mass = impulse.centre_of_mass_se3(locked, pose.rotation, pose.translation,
                                                      pose_cov)
        return world, cov, mass, axes
    mass = float(locked[0, 0])
    c = np.array([locked[1, 2], -locked[0, 2]]) / mass
    rotation = pose.rotation[:2, :2]
    jacobian = np.zeros((2, 3))
    jacobian[:, :2] = rotation
    jacobian[:, 2] = rotation @ np.array([-c[1], c[0]])
    world = pose.translation[:2] + rotation @ c
    return world, jacobian @ pose_cov @ jacobian.T, mass, axes
