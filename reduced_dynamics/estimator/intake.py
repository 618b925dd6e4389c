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
Input intake and validation: samples in, validated rows or counted rejections out.

Part of :class:`~.pipeline.Estimator` (its state is set up there): joint states
are mapped onto the model's joints and checked (finite, URDF limits and bounds,
:mod:`.plausibility`), base states normalised and projected onto the base group,
commanded wrenches bounded, planned trajectories checked; then the stamp policy
(:mod:`~reduced_dynamics.estimator.stamps`) decides, and :mod:`.timing` takes
what it accepts. Bad input is rejected with a reason and counted; it never raises.

A batch (:meth:`InputIntake._take_batch`, the batched path) is validated by
columns first (:mod:`.intake_columns`): the joint states in the model's joint
order and the base states of a floating base are stacked, checked for finite
values and plausibility with numpy, and their base rows built in one pass (the
same float operations as per message, the same bits). Then every message goes,
in arrival order, through the stamp policy and synchronisation as on the
streaming path; one that failed a column check takes the per-message path, which
rejects it with its reason and text, in its place in the order.
"""

from __future__ import annotations

import math
from typing import Optional, Sequence, Union

import numpy as np
import pinocchio as pin

from reduced_dynamics.estimator import intake_columns as columns
from reduced_dynamics.estimator.covariance import CovarianceReader, NoisyRow
from reduced_dynamics.estimator.outputs import EstimatorOutput
from reduced_dynamics.estimator.plausibility import JointBounds
from reduced_dynamics.estimator.prediction import Plan
from reduced_dynamics.estimator.stamps import ACCEPTED
from reduced_dynamics.messages.samples import (BaseStateSample, CommandSample, JointStateSample,
                                               JointTrajectorySample)


class _Identity:
    """Name-mapping marker: the joint state lists the joints in model order."""


_IDENTITY = _Identity()
#: Joint-name lists whose mapping to the model is cached (memory bound of that cache).
NAME_MAPS_KEEP = 64
#: Fewer messages of a kind in a batch than this are validated one by one (the column
#: checks' numpy calls cost more than they save).
COLUMN_MIN = 8


def _all_finite(*arrays: np.ndarray) -> bool:
    """Return whether every entry is finite (the exact test behind a non-finite sum)."""
    return all(bool(np.isfinite(array).all()) for array in arrays)


Sample = Union[JointStateSample, BaseStateSample, CommandSample]


class InputIntake:
    """
    Input intake and validation of the estimator (a part of :class:`~.pipeline.Estimator`).

    Every rejection is counted by reason (``rejected``) with the last one's text.
    """

    def reject(self, reason: str, detail: str) -> list[EstimatorOutput]:
        """Count an input rejected before it reached the pipeline (e.g. malformed)."""
        return self._reject(reason, detail)

    def _reject(self, reason: str, detail: str) -> list[EstimatorOutput]:
        self.rejected[reason] += 1
        self._period_rejected += 1
        self.last_rejection = f'{reason}: {detail}'
        self._rejected_at = len(self._chunk.rows)
        return []

    def _take_joint(self, sample: JointStateSample) -> None:
        # Hot path (every message): locals over repeated attribute lookups.
        self._received_joints += 1
        self._period_joints += 1
        names = sample.names
        mapping = self._name_maps.get(names)
        if mapping is None:
            if len(self._name_maps) >= NAME_MAPS_KEEP:
                # A stream of ever new name lists (bad input) must not grow the cache.
                self._name_maps.clear()
            mapping = self._name_maps[names] = self._map_names(names)
        if mapping.__class__ is str:
            reason, _, detail = mapping.partition(':')
            self._reject(reason, detail.strip())
            return
        m = self._m
        stamp = sample.stamp_ns
        position, velocity, effort = sample.position, sample.velocity, sample.effort
        if m and not velocity.size:
            self._reject('missing_velocity', 'joint state has no velocities')
            return
        if m:
            # Names match the model one to one, so checking whole arrays is checking qbar.
            # A finite sum proves every entry finite; otherwise the exact test decides
            # (finite values can overflow the sum).
            values = position.tolist(), velocity.tolist(), effort.tolist()
            if not math.isfinite(sum(values[0]) + sum(values[1]) + sum(values[2])) \
                    and not _all_finite(position, velocity, effort):
                self._reject('non_finite', f'NaN or inf in joint state at {stamp}')
                return
            # Plausibility gate (estimator/plausibility.py): URDF limits and bounds.
            bounds = self._joint_bounds.get(names)
            if bounds is None:
                bounds = self._joint_bounds[names] = JointBounds(self.robot, self.config,
                                                                 names)
            verdict = bounds.check(*values)
            if verdict is not None:
                self._reject(*verdict)
                return
        if not m:
            empty = self._empty
            pending = (stamp, empty, empty, empty)
        elif mapping is _IDENTITY:
            # Kept by reference: the chunk copies them when it stacks its rows.
            pending = (stamp, position, velocity, effort if effort.size else self._zeros_m)
        else:
            pending = (stamp, position[mapping], velocity[mapping],
                       effort[mapping] if effort.size else self._zeros_m)
        # Stamp policy (estimator/stamps.py): outliers dropped, clock jumps followed.
        result = self._joint_gate.offer(stamp, sample.receive_ns, pending)
        if result is not ACCEPTED:
            self._stamp_result(result, True)
            return
        self._accept_joint(pending)

    def _take_batch(self, samples: Sequence) -> None:
        """Take samples in arrival order, validated by columns where that is valid."""
        joint_class, base_class = JointStateSample, BaseStateSample
        joints = [s for s in samples if s.__class__ is joint_class]
        bases = [s for s in samples if s.__class__ is base_class]
        joint_items = self._joint_columns(joints)
        base_items, noisy = self._base_columns(bases)
        take_joint, take_base = self._take_joint, self._take_base
        joint_offer, base_offer = self._joint_gate.offer, self._base_gate.offer
        accept_joint, accept_base = self._accept_joint, self._accept_base
        stamp_result = self._stamp_result
        joint_index = base_index = 0
        for sample in samples:
            kind = sample.__class__
            if kind is joint_class:
                pending = joint_items[joint_index]
                joint_index += 1
                if pending is None:
                    take_joint(sample)
                    continue
                # _take_joint for a sample the columns passed: counted, then the stamp.
                self._received_joints += 1
                self._period_joints += 1
                result = joint_offer(pending[0], sample.receive_ns, pending)
                if result is ACCEPTED:
                    accept_joint(pending)
                else:
                    stamp_result(result, True)
            elif kind is base_class:
                item = base_items[base_index]
                if item is None:
                    base_index += 1
                    take_base(sample)
                    continue
                if noisy is not None and noisy[base_index]:
                    # The message's own noise, in its place in the order (its fallbacks
                    # are counted as _take_base counts them): the row as a list.
                    row = item[1]
                    item = (item[0], self._with_message_noise(row.tolist(), sample,
                                                              tuple(row[3:7].tolist())))
                base_index += 1
                self._received_bases += 1
                self._period_bases += 1
                result = base_offer(item[0], sample.receive_ns, item)
                if result is ACCEPTED:
                    accept_base(item)
                else:
                    stamp_result(result, False)
            elif isinstance(sample, JointStateSample):
                take_joint(sample)
            elif kind is CommandSample:
                self._take_command(sample)
            else:
                take_base(sample)

    def _joint_columns(self, joints: list) -> list:
        """Return per joint state its queued tuple if it passes every check, else None."""
        model = self.robot.shape_joint_names
        if not self._m or len(joints) < COLUMN_MIN:
            return [None] * len(joints)
        bounds = self._joint_bounds.get(model)
        if bounds is None:
            bounds = self._joint_bounds[model] = JointBounds(self.robot, self.config, model)
        return columns.joint_columns(joints, model, bounds, self._zeros_m, COLUMN_MIN)

    def _base_columns(self, bases: list) -> tuple[list, Optional[list]]:
        """Return per base state its (stamp, row) if it passes every check, and the noisy."""
        odometry = self.use_odometry
        if len(bases) < COLUMN_MIN or not self._floating or odometry and self._project_twists:
            return [None] * len(bases), None
        return columns.base_columns(bases, odometry, self.config.use_message_covariance,
                                    self._base_bounds, COLUMN_MIN)

    def _map_names(self, names: tuple[str, ...]):
        if len(set(names)) != len(names):
            return 'duplicate_joint: joint names repeat'
        unknown = [n for n in names if n not in self._index]
        if unknown:
            return f'unknown_joint: {", ".join(unknown[:5])} not in the robot model'
        missing = [n for n in self.robot.shape_joint_names if n not in names]
        if missing:
            return f'missing_joint: {", ".join(missing[:5])} absent from the joint state'
        if names == self.robot.shape_joint_names:
            return _IDENTITY
        order = {n: i for i, n in enumerate(names)}
        return np.array([order[n] for n in self.robot.shape_joint_names], dtype=int)

    def _take_base(self, sample: BaseStateSample) -> None:
        # Hot path (every message): plain floats and locals, few numpy calls.
        self._received_bases += 1
        self._period_bases += 1
        stamp = sample.stamp_ns
        row = sample.position.tolist()
        x, y, z, w = quaternion = sample.orientation_xyzw.tolist()
        linear = sample.twist_linear
        twist = [] if linear is None else linear.tolist() + sample.twist_angular.tolist()
        if not math.isfinite(sum(row) + sum(quaternion) + sum(twist)) \
                and not all(map(math.isfinite, row + quaternion + twist)):
            self._reject('non_finite_base', f'NaN or inf in base state at {stamp}')
            return
        norm = math.sqrt(x * x + y * y + z * z + w * w)
        if norm < 1e-6:
            self._reject('invalid_quaternion', f'zero quaternion at {stamp}')
            return
        odometry = self.use_odometry
        if odometry and linear is None:
            self._reject('missing_twist', 'base sample without twist (use pose mode)')
            return
        # Plausibility gate (estimator/plausibility.py): quaternion norm, position, twist.
        verdict = self._base_bounds.check(row, norm, twist)
        if verdict is not None:
            self._reject(*verdict)
            return
        row += (x / norm, y / norm, z / norm, w / norm)
        if not self._floating:
            pose = self.robot.project_pose(pin.XYZQUATToSE3(np.array(row)))
            row = pin.SE3ToXYZQUAT(pose).tolist()
        if odometry:
            if self._project_twists:
                # Only the part of the twist inside the base group's algebra is kept.
                kernel = self.kernel
                twist = kernel.twists(kernel.coordinates(np.array([twist])))[0].tolist()
            row += twist
        if (sample.pose_covariance is not None or sample.twist_covariance is not None) \
                and self.config.use_message_covariance:
            row = self._with_message_noise(row, sample, (x / norm, y / norm, z / norm,
                                                         w / norm))
        # Stamp policy (estimator/stamps.py): outliers dropped, clock jumps followed.
        result = self._base_gate.offer(stamp, sample.receive_ns, (stamp, row))
        if result is not ACCEPTED:
            self._stamp_result(result, False)
            return
        self._accept_base((stamp, row))

    def _with_message_noise(self, row: list, sample: BaseStateSample,
                            xyzw: tuple[float, float, float, float]) -> list:
        """Return the row carrying the sample's own noise (estimator/covariance.py)."""
        reader = self._covariance_reader
        if reader is None:
            reader = self._covariance_reader = CovarianceReader(self.robot.group.algebra_pinv)
        x, y, z, w = xyzw
        rotation = pin.Quaternion(w, x, y, z).toRotationMatrix()
        noise, reasons = reader.read(sample.pose_covariance,
                                     sample.twist_covariance if self.use_odometry else None,
                                     rotation)
        for reason in reasons:
            # Not a rejection: the sample is used, with the noise parameters.
            self.covariance_fallbacks[reason] += 1
            self._period_covariance_fallbacks += 1
            self.last_covariance_fallback = (
                f'{reason}: base sample at {sample.stamp_ns} carries a bad covariance; '
                'the noise parameters are used')
        return row if noise is None else NoisyRow(row, noise)

    def _take_command(self, sample: CommandSample) -> None:
        """Validate a commanded wrench (finite, plausible, stamp policy) and hold it."""
        self._received_commands += 1
        stamp = sample.stamp_ns
        if not self.commanded_wrench:
            self._reject('command_unused', 'commanded wrench given to an estimator '
                                           'without commanded_wrench')
            return
        wrench = np.concatenate((sample.force, sample.torque))
        if not _all_finite(wrench):
            self._reject('non_finite_command', f'NaN or inf in commanded wrench at {stamp}')
            return
        u = self.robot.group.dual_coordinates(wrench)
        if self._command_scale is None:
            # I^-1 at zero shape: the bound is an acceleration, the same at any mass.
            zero = np.zeros((1, self.robot.m))
            locked = self.kernel.mass_matrices(zero)[0][:self.robot.n, :self.robot.n]
            self._command_scale = np.linalg.inv(locked)
        acceleration = np.abs(self._command_scale @ u)
        if float(acceleration.max(initial=0.0)) > self.config.command_acceleration_bound:
            self._reject('command_bound', f'commanded wrench at {stamp} asks for a body '
                                          f'acceleration of {acceleration.max():.3g} '
                                          f'(bound {self.config.command_acceleration_bound:g})')
            return
        result = self._command_gate.offer(stamp, sample.receive_ns, (stamp, u))
        if result is not ACCEPTED:
            self._stamp_result(result, None)
            return
        self._accept_command((stamp, u))

    def add_trajectory(self, sample: JointTrajectorySample) -> None:
        """
        Take a planned joint trajectory (prediction_mode planned follows the latest).

        Its times count from its header stamp; stamp 0 means "from now" (the
        newest joint-state stamp), as joint_trajectory_controller starts such
        a trajectory on arrival. Joints must be shape joints of the model (a
        subset: the others keep their velocities); bad trajectories are
        counted as rejections (``trajectory_*``) and the previous plan stays.
        """
        self.trajectories_received += 1
        names = sample.joint_names
        unknown = [n for n in names if n not in self._index]
        if not names or not sample.times_from_start_ns.size:
            self._reject('trajectory_empty', 'planned trajectory without joints or points')
            return
        if unknown:
            self._reject('trajectory_unknown_joint',
                         f'{", ".join(unknown[:5])} not in the robot model')
            return
        if len(set(names)) != len(names):
            self._reject('trajectory_duplicate_joint', 'joint names repeat')
            return
        arrays = [a for a in (sample.positions, sample.velocities, sample.accelerations)
                  if a is not None]
        if not _all_finite(*arrays):
            self._reject('trajectory_non_finite', 'NaN or inf in a planned trajectory')
            return
        start = sample.stamp_ns
        if start == 0:
            start = self._last_joint_ns if self._last_joint_ns is not None else 0
        index = np.array([self._index[n] for n in names], dtype=int)
        self.predictor.set_plan(Plan(start, index, sample.times_from_start_ns,
                                     sample.positions, sample.velocities,
                                     sample.accelerations, self.robot.m))
