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


"""The smoother's disk-backed store: exact round trips, block seams, flat replay memory."""

import os
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest

from reduced_dynamics.bag.reader import open_bag
from reduced_dynamics.bench import replay_memory, tile_bag
from reduced_dynamics.estimator import smoother
from reduced_dynamics.estimator.filter import FilterStep, smooth
from reduced_dynamics.estimator.pipeline import Estimator
from reduced_dynamics.estimator.smoother import SmootherFiles, StepStore
from reduced_dynamics.messages.convert import joint_state_from_ros, odometry_from_ros
from reduced_dynamics.robot.model import load_robot
from reduced_dynamics.simulator import (simulate_bag, SimulationOptions, TOPIC_JOINT_STATES,
                                        TOPIC_ODOM)

DATA = Path(__file__).parent / 'data'


def _random_step(rng, n: int, dim: int, command: bool, k: int) -> FilterStep:
    def pose():
        return pin.SE3(pin.exp3(rng.normal(size=3)), rng.normal(size=3))
    return FilterStep(1_000 + k, None if k % 5 == 0 else rng.normal(size=(dim, dim)), pose(),
                      rng.normal(size=dim - n), rng.normal(size=(dim, dim)), pose(),
                      rng.normal(size=dim - n), rng.normal(size=(dim, dim)),
                      rng.normal(size=(n, n)), bool(k % 3), rng.normal(size=n) if command
                      else None)


def _same(a: FilterStep, b: FilterStep) -> bool:
    arrays = ('x_pred', 'p_pred', 'x', 'p', 'locked_inverse')
    return (a.stamp_ns == b.stamp_ns and a.output == b.output
            and (a.transition is None) == (b.transition is None)
            and (a.transition is None or np.array_equal(a.transition, b.transition))
            and all(np.array_equal(getattr(a, f), getattr(b, f)) for f in arrays)
            and all(np.array_equal(getattr(a, g).homogeneous, getattr(b, g).homogeneous)
                    for g in ('g', 'g_pred'))
            and ((a.command is None and b.command is None)
                 or np.array_equal(a.command, b.command)))


@pytest.mark.parametrize('command', [False, True])
def test_steps_round_trip_bit_for_bit_across_blocks(command):
    rng = np.random.default_rng(3)
    n, dim = 3, 5 * 3 if command else 3 * 3
    files = SmootherFiles()
    store = StepStore(files, n, dim, command, block=4)
    steps = [_random_step(rng, n, dim, command, k) for k in range(23)]
    for step in steps:
        store.append(step)
    assert len(store) == 23 and store.outputs == sum(s.output for s in steps)
    # Backwards, as the smoother reads, then at random: every field the same bits.
    assert all(_same(store[k], steps[k]) for k in range(22, -1, -1))
    assert all(_same(store[int(k)], steps[int(k)]) for k in rng.integers(0, 23, 30))
    assert _same(store[-1], steps[-1])
    with pytest.raises(IndexError):
        store[23]
    store.close()
    path = files.path
    assert os.path.isdir(path)
    files.close()
    assert not os.path.exists(path)


def _bag_samples(bag: Path) -> list:
    with open_bag(str(bag)) as reader:
        return [joint_state_from_ros(m.msg) if m.topic == TOPIC_JOINT_STATES
                else odometry_from_ros(m.msg)
                for m in reader.messages([TOPIC_JOINT_STATES, TOPIC_ODOM])]


def test_smoothed_rows_equal_the_list_smoother_whatever_the_blocks(monkeypatch):
    # Blocks of a few steps and rows: every seam of the store and of the row buffer is
    # crossed; the rows must equal the in-memory smoother over the same steps.
    monkeypatch.setattr(smoother, 'BLOCK_STEPS', 7)
    monkeypatch.setattr(smoother, 'BLOCK_ROWS', 5)
    robot = load_robot()
    estimator = Estimator(robot)
    estimator.enable_smoothing()
    samples = _bag_samples(DATA / 'paper_realistic')[:300]
    outputs = estimator.add_samples(samples).outputs() + estimator.flush()
    store = estimator.step_store
    steps = [store[k] for k in range(len(store))]
    reference = smooth(robot.group, steps)
    rows = [state for state, step in zip(reference, steps) if step.output]
    smoothed = list(estimator.smoothed_rows())
    assert len(smoothed) == len(rows) == len(outputs) > 100
    n = robot.n
    for fields, state, output in zip(smoothed, rows, outputs):
        assert np.array_equal(fields['mu'], state.x[:n])
        assert np.array_equal(fields['momentum_covariance'], state.p[n:2 * n, n:2 * n])
        assert np.array_equal(fields['wrench_covariance'], state.p[2 * n:, 2 * n:])
        assert fields['momentum'].stamp_ns == output.stamp_ns
    estimator.smooth_outputs(outputs)
    assert np.array_equal(outputs[-1].mu, rows[-1].x[:n])
    with pytest.raises(ValueError):
        estimator.smooth_outputs(outputs[:-1])


def test_smoothed_replay_peak_memory_does_not_grow_with_the_bag(tmp_path):
    # 1 kHz joint states + 200 Hz odometry; 4 s against 16 s (tiled). Holding every step
    # and output in memory (the earlier smoother) grows ~16 MiB per 1000 samples: 1.8x
    # between these two; disk-backed, the peak is the same within a few MiB.
    bag = tmp_path / 'bag'
    simulate_bag(load_robot(), str(bag), SimulationOptions(duration=4.0, rate=1000.0,
                                                           base_rate=200.0, torque='pd',
                                                           overwrite=True))
    long_bag = tmp_path / 'long'
    tile_bag(str(bag), str(long_bag), 16.0, (TOPIC_JOINT_STATES, TOPIC_ODOM))
    short = replay_memory(str(bag), str(tmp_path / 'out_short'))
    long = replay_memory(str(long_bag), str(tmp_path / 'out_long'))
    assert long['processed'] > 3.5 * short['processed']
    assert long['peak_rss_mib'] <= 1.2 * short['peak_rss_mib'], (short, long)
    # The smoother's files beside the output bags are gone.
    assert sorted(p.name for p in tmp_path.iterdir()) == ['bag', 'long', 'out_long',
                                                          'out_short']


def test_warm_up_loads_the_backward_pass_replay_runs() -> None:
    """A fresh process: after warm_up, smoothed replays compile no new backward pass."""
    from filter_helpers import fresh_process_words
    code = f"""
import os, tempfile
from reduced_dynamics.estimator.core.warmup import warm_up
warm_up()
from reduced_dynamics.estimator.core import smoother
from reduced_dynamics.replay import replay, ReplayOptions
from reduced_dynamics.resources import config_path
from reduced_dynamics.robot.model import load_robot
kernels = (smoother.backward_block, smoother.row_fields)
before = [len(k.signatures) for k in kernels]
for bag, urdf in (('paper_thruster', ''), ('freeflyer_testbed', 'robots/freeflyer.urdf')):
    robot = load_robot(str(config_path(urdf)) if urdf else '')
    with tempfile.TemporaryDirectory() as out:
        replay(os.path.join({str(DATA)!r}, bag), os.path.join(out, 'o'), robot,
               ReplayOptions(smooth=True))
print(min(before) > 0, before == [len(k.signatures) for k in kernels])
"""
    assert fresh_process_words(code) == ['True', 'True']


def test_blocks_of_one_step_compile_nothing_new_and_smooth_the_same() -> None:
    """
    Blocks of one step compile nothing after warm_up and smooth to the same bits.

    A fresh process: a store whose blocks hold one step (and one output) smooths with the
    kernels warm_up loaded, to the bits of one block of all the steps.
    """
    from filter_helpers import fresh_process_words
    code = """
import numpy as np
from reduced_dynamics.estimator.core.warmup import warm_up
warm_up()
import pinocchio as pin
from reduced_dynamics.estimator.core import smoother
from reduced_dynamics.estimator.core.state import Linearisation, NoiseModel
from reduced_dynamics.estimator.filter import MomentumFilter
from reduced_dynamics.estimator.smoother import SmootherFiles, smooth_rows, StepStore
from reduced_dynamics.geometry.lie_group import SUBGROUPS
kernels = (smoother.backward_block, smoother.row_fields)
before = [len(k.signatures) for k in kernels]
group = SUBGROUPS['SE(3)']
locked = np.diag(np.linspace(2.0, 3.0, 6))
lin = Linearisation(locked, np.linalg.inv(locked), np.full(6, 0.01), np.eye(6) * 1e-6)
flt = MomentumFilter(group, NoiseModel(), 1e-6, record=True)
for k in range(9):  # odometry at every other row: blocks of 2 hold one output
    pose = group.exp(np.full(6, 1e-3 * k)) if k % 2 == 0 else None
    flt.step(k * 10_000_000, lin, pose, np.full(6, 1e-3) if k % 4 == 0 else None)
rows = []
for block in (2, None):  # 9 steps in blocks of 2: the newest block holds one
    files = SmootherFiles()
    store = StepStore(files, 6, flt.dim, False, block=block)
    for step in flt.steps:
        store.append(step)
    smoothed = smooth_rows(group, store, files, flt._form_rows)
    rows.append(np.concatenate(list(smoothed.blocks())))
    smoothed.close()
    store.close()
    files.close()
print(min(before) > 0, before == [len(k.signatures) for k in kernels],
      len(flt.steps) == 9 and len(rows[0]) > 4, rows[0].tobytes() == rows[1].tobytes())
"""
    assert fresh_process_words(code) == ['True'] * 4


def test_warm_up_goes_on_without_a_temporary_directory(monkeypatch) -> None:
    """No writable temporary directory (a node's read-only disk): that warm-up is skipped."""
    from reduced_dynamics.estimator.core import envelope, warmup
    tried = []

    def unwritable(*args, **kwargs):
        tried.append(args)
        raise PermissionError('read-only file system')
    monkeypatch.setattr(smoother, 'SmootherFiles', unwritable)
    warmup.warm_up()  # does not raise
    # Tried once per filter (SE(3), SE(2), SE(2) with a command), and went on to the end
    # (the re-timer's scan is its last kernel).
    assert len(tried) == 3 and envelope.scan.signatures
