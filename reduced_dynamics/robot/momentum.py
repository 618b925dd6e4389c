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

"""Momenta of the free-floating system (5.27, 5.29, 5.35; REDUCED_MODEL.md 3-4)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from reduced_dynamics.geometry.lie_group import BaseGroup
from reduced_dynamics.robot.model import MetricBlocks


def body_momentum(blocks: MetricBlocks, xi: np.ndarray, qbar_dot: np.ndarray) -> np.ndarray:
    """Compute pi = I xi + B qbar_dot: momentum of the whole system in the base frame."""
    return blocks.locked_inertia @ xi + blocks.coupling @ qbar_dot


def momentum_map(group: BaseGroup, g: pin.SE3, pi: np.ndarray) -> np.ndarray:
    """Compute mu = Ad_{g^-1}^T pi (5.27): spatial momentum about the world origin."""
    return group.Ad(g.inverse()).T @ pi


def body_momentum_from_spatial(group: BaseGroup, g: pin.SE3, mu: np.ndarray) -> np.ndarray:
    """Compute pi = Ad_g^T mu, the inverse of :func:`momentum_map`."""
    return group.Ad(g).T @ mu


def shape_momentum(blocks: MetricBlocks, xi: np.ndarray, qbar_dot: np.ndarray) -> np.ndarray:
    """Compute p = B^T xi + Mr qbar_dot: momentum conjugate to the shape."""
    return blocks.coupling.T @ xi + blocks.shape_inertia @ qbar_dot


def reduced_momentum(blocks: MetricBlocks, qbar_dot: np.ndarray) -> np.ndarray:
    """Compute pbar = p - A^T pi = S qbar_dot (5.35, Lemma 53)."""
    return blocks.reduced_metric @ qbar_dot


def drift_twist(blocks: MetricBlocks, pi: np.ndarray) -> np.ndarray:
    """I^-1 pi: the base twist momentum alone causes (the dynamic phase)."""
    return blocks.solve_locked(pi)


def geometric_phase(blocks: MetricBlocks, qbar_dot: np.ndarray) -> np.ndarray:
    """Return -A qbar_dot: the base twist the shape motion causes (5.29)."""
    return -blocks.connection @ qbar_dot


def base_twist(blocks: MetricBlocks, pi: np.ndarray, qbar_dot: np.ndarray) -> np.ndarray:
    """Reconstruction xi = I^-1 pi - A qbar_dot (REDUCED_MODEL.md 4)."""
    return drift_twist(blocks, pi) + geometric_phase(blocks, qbar_dot)


def kinetic_energy(blocks: MetricBlocks, xi: np.ndarray, qbar_dot: np.ndarray) -> float:
    """T = 1/2 [xi; qbar_dot]^T M [xi; qbar_dot]."""
    v = np.concatenate([xi, qbar_dot])
    return 0.5 * float(v @ blocks.mass_matrix @ v)


@dataclass(frozen=True)
class MomentumState:
    """Everything the momentum map gives at one instant."""

    mu: np.ndarray
    pi: np.ndarray
    shape_momentum: np.ndarray
    reduced_momentum: np.ndarray
    drift_twist: np.ndarray
    geometric_phase: np.ndarray
    kinetic_energy: float


def momentum_state(group: BaseGroup, blocks: MetricBlocks, g: pin.SE3, xi: np.ndarray,
                   qbar_dot: np.ndarray) -> MomentumState:
    """mu, pi, p, pbar, drift and geometric phase from one evaluation of the metric."""
    pi = body_momentum(blocks, xi, qbar_dot)
    return MomentumState(
        mu=momentum_map(group, g, pi), pi=pi,
        shape_momentum=shape_momentum(blocks, xi, qbar_dot),
        reduced_momentum=reduced_momentum(blocks, qbar_dot),
        drift_twist=drift_twist(blocks, pi), geometric_phase=geometric_phase(blocks, qbar_dot),
        kinetic_energy=kinetic_energy(blocks, xi, qbar_dot))
