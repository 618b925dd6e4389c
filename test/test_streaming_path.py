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

"""The streaming path's one-row chunks: the kernel's buffers and the per-sample outputs."""

import dataclasses

import numpy as np
import pinocchio as pin

from reduced_dynamics import bench
from reduced_dynamics.estimator.config import EstimatorConfig
from reduced_dynamics.estimator.kernel import UpdateKernel
from reduced_dynamics.estimator.pipeline import Estimator
from reduced_dynamics.messages.samples import trusted_sample
from reduced_dynamics.robot.model import load_robot


def test_mass_matrices_reuse_their_buffers_across_chunk_lengths() -> None:
    """One row after a chunk and a chunk after one row: each crba's own M, base at e."""
    robot = load_robot()
    kernel = UpdateKernel(robot)
    reference = robot.model.createData()
    rng = np.random.default_rng(4)
    for count in (3, 1, 5, 1, 2):
        qbar = rng.uniform(-1.0, 1.0, (count, robot.m))
        stack = kernel.mass_matrices(qbar)
        assert stack.shape == (count, robot.model.nv, robot.model.nv)
        for k in range(count):
            q = robot.identity_configuration(qbar[k]).copy()
            # Some bindings fill the upper triangle only; the kernel mirrors it.
            expected = np.triu(pin.crba(robot.model, reference, q))
            expected = expected + np.triu(expected, 1).T
            np.testing.assert_array_equal(stack[k], expected)


def test_streaming_outputs_hold_the_samples_trusted_sample_builds() -> None:
    """Per-sample outputs hold the samples trusted_sample builds (the same instance dicts)."""
    robot = load_robot()
    joints, bases = bench.update_samples(robot, 60)
    estimator = Estimator(robot, EstimatorConfig(prediction_rate=0.0))
    outputs = []
    for joint, base in zip(joints, bases):
        outputs += estimator.add_joint_state(joint)
        outputs += estimator.add_base_state(base)
    assert len(outputs) == 60
    world, link = estimator.config.world_frame, robot.base_link
    for output in outputs:
        stamp = output.stamp_ns
        for name, frame, first, second in (('momentum', world, 'force', 'torque'),
                                           ('body_momentum', link, 'force', 'torque'),
                                           ('momentum_rate', world, 'force', 'torque'),
                                           ('drift_twist', link, 'linear', 'angular')):
            sample = getattr(output, name)
            expected = trusted_sample(type(sample), stamp, frame, getattr(sample, first),
                                      getattr(sample, second))
            assert vars(sample) == vars(expected), name  # the very arrays: identity
            assert list(vars(sample)) == [f.name for f in dataclasses.fields(sample)]
        shape = output.shape_state
        expected = trusted_sample(type(shape), stamp, '', robot.shape_joint_names,
                                  shape.position, shape.velocity, shape.effort)
        assert list(vars(shape)) == list(vars(expected))
        assert vars(shape) == vars(expected)
        assert shape.receive_ns is None
