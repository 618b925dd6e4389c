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
Property-based fuzzing of the estimator's input streams (Hypothesis).

Each case takes a window of the shipped ``paper_thruster`` bag (joint states
and odometry at 200 Hz, same stamps), damages it with one family of hostile
input, runs the estimator (batched or streaming, drawn) and asserts:

* no exception and no hang (faulthandler aborts a case stuck for 60 s with
  its traceback; the work per case is bounded by its sample count);
* no NaN or inf in any output;
* every rejection counted by reason, and the counts add up: joint states
  received = processed + rejected for a joint reason; base samples rejected
  for a base reason = the damaged base samples;
* nothing valid lost: every joint state that was not itself damaged produces
  exactly one output (unless no undamaged base sample lies within the sync
  tolerance: an explained drop), and none of the damaged ones do;
* same values: the shape state (qbar, qbar_dot, pbar: functions of the joint
  state alone) of every undamaged joint state equals the clean window's bit
  for bit; the filtered outputs (mu, body momentum, drift twist, momentum
  rate) equal it bit for bit up to the first damaged sample (the estimator is
  causal) and, once the transient is over (:data:`TRANSIENT_S` after the last
  damaged sample before it), to :data:`RELATIVE` of the clean run's largest
  value; after a clock jump back they equal those of a fresh estimator started
  at the jump bit for bit (the restart forgets the past). After a forward
  jump (a gap of 2-100 s) the filtered outputs are only checked finite.

Settings: ``max_examples`` per family, ``derandomize=True`` (reproducible),
no example database, ``deadline=None``. ``RD_FUZZ_STATS=file`` writes the
measured totals as JSON (the table of docs/fuzz.md).
"""

import bisect
from collections import Counter
from dataclasses import dataclass, field
from typing import Optional
import faulthandler
import functools
import json
import math
import os

from hypothesis import given, HealthCheck, note, settings, strategies as st
import numpy as np
import pytest

from reduced_dynamics.bag.reader import open_bag
from reduced_dynamics.estimator import Estimator
from reduced_dynamics.estimator.config import EstimatorConfig
from reduced_dynamics.messages.convert import joint_state_from_ros, odometry_from_ros
from reduced_dynamics.messages.samples import BaseStateSample, JointStateSample
from reduced_dynamics.robot.model import load_robot
from sim_samples import feed_stream

#: One pytest-xdist worker runs this module: the clean runs (_scales, CLEAN_RUNS) it
#: compares against are then computed once, not once per worker.
pytestmark = pytest.mark.xdist_group('fuzz_inputs')
DATA = os.path.join(os.path.dirname(__file__), 'data')
NS = 1_000_000_000
#: Samples per stream in a window (0.8 s at 200 Hz), and the windows' first samples
#: (a grid, so that the clean runs are computed once per window).
WINDOW = 160
STARTS = range(0, 801 - WINDOW, 40)
ROBOT = load_robot()
#: The bag is noise-free: a Kalman filter is told so (it then follows the sensors),
#: and its innovation gate is off (the damage is the intake gates' business here).
#: from_mapping ignores the settings an estimator does not have.
CONFIG = EstimatorConfig.from_mapping({
    'prediction_rate': 0.0, 'diagnostics_rate': 0.0, 'pose_position_noise': 1e-10,
    'pose_angle_noise': 1e-10, 'twist_linear_noise': 1e-10, 'twist_angular_noise': 1e-10,
    'joint_velocity_noise': 0.0, 'innovation_gate': 0.0, 'pose_stamp_noise': 0.0})
#: The estimator's transient after a missing sample: the filtered outputs may
#: differ from the clean run's until then. Measured: a single missing joint state
#: changes mu by <= 3e-8 and the rate by <= 1.3e-7 of their largest values with
#: the Kalman filter's default noise, 4e-9 and 3e-8 after 0.5 s; the former
#: momentum observer (dr/dt = K (w - r), K = 50 rad/s) forgot a rate error as
#: exp(-K t), to 1e-11 after 0.5 s.
TRANSIENT_S = 0.5
#: Largest difference to the clean run after the transient, relative to the clean
#: run's largest value of the quantity.
RELATIVE = 1e-6
#: Cases per family (the budget: >= 1000 in all within about a minute of CI).
EXAMPLES = {'values': 130, 'joints': 130, 'stamps_outliers': 130, 'clock_jumps': 130,
            'implausible': 130, 'quaternions': 130, 'mixed': 130}
#: Rejections of base samples (the rest are of joint states). innovation_gate: a base
#: measurement the filter found improbable (a garbled but plausible pose); counting it as a
#: joint state's once made the accounting fail by two on a garbled bag.
BASE_REASONS = {'non_finite_base', 'invalid_quaternion', 'missing_twist', 'quaternion_norm',
                'base_position_bound', 'base_twist_bound', 'base_stamp_backwards',
                'base_stamp_outlier', 'innovation_gate'}
STATS: dict = {}


def _fuzz_settings(family):
    return settings(max_examples=EXAMPLES[family], deadline=None, derandomize=True,
                    database=None, suppress_health_check=list(HealthCheck))


def _load():
    joints, bases = [], []
    with open_bag(os.path.join(DATA, 'paper_thruster')) as reader:
        for message in reader.messages(['/joint_states', '/odom']):
            if message.topic == '/joint_states':
                joints.append(joint_state_from_ros(message.msg))
            else:
                bases.append(odometry_from_ros(message.msg))
    assert [j.stamp_ns for j in joints] == [b.stamp_ns for b in bases]
    return joints, bases


JOINTS, BASES = _load()


def _filtered(output):
    """Return the filtered outputs of one sample: name -> array."""
    # (np.concatenate: np.r_'s values, at a tenth of its cost; this runs per compared row.)
    join = np.concatenate
    return {'mu': output.mu,
            'body_momentum': join((output.body_momentum.force, output.body_momentum.torque)),
            'drift': join((output.drift_twist.linear, output.drift_twist.angular)),
            'rate': join((output.momentum_rate.force, output.momentum_rate.torque))}


@functools.lru_cache(maxsize=None)
def _scales() -> dict:
    """
    Return the largest value of each filtered output over the clean bag (computed once).

    At first use, not at import: computed at import it replayed the bag in every
    pytest-xdist worker's collection, each compiling the kernels it met at the same time.
    """
    estimator = Estimator(ROBOT, CONFIG)
    stream = [s for pair in zip(JOINTS, BASES) for s in pair]
    outputs = estimator.add_samples(stream).outputs() + estimator.flush()
    assert len(outputs) == len(JOINTS) and not estimator.rejected
    rows = [_filtered(o) for o in outputs]
    return {name: max(np.abs(row[name]).max() for row in rows) for name in rows[0]}


CLEAN_RUNS: dict = {}


def _clean(start, restart=None):
    """Return the clean window's outputs by stamp (fresh estimators before/after ``restart``)."""
    key = (start, restart)
    if key not in CLEAN_RUNS:
        pairs = list(zip(JOINTS[start:start + WINDOW], BASES[start:start + WINDOW]))
        cut = WINDOW if restart is None else restart
        outputs = []
        for part in (pairs[:cut], pairs[cut:]):
            if part:
                outputs += _run([s for pair in part for s in pair], True)[1]
        CLEAN_RUNS[key] = {o.stamp_ns: o for o in outputs}
    return CLEAN_RUNS[key]


@dataclass
class Item:
    """One input sample of a case and what the test expects of it."""

    sample: object
    joint: bool
    origin_ns: int  # the clean stamp it came from
    damage: str = ''  # expected rejection reason ('' = valid)
    modified: bool = False  # valid, but its values may differ in the last bits


@dataclass
class Case:
    """A damaged window and its bookkeeping."""

    family: str
    items: list = field(default_factory=list)
    start: int = 0  # index of the window's first sample in the bag

    def __repr__(self) -> str:
        """Return the damage only (the samples are the bag's)."""
        first = self.items[0]
        damaged = [(i, 'joint' if item.joint else 'base', item.damage or 'modified',
                    item.sample.stamp_ns - item.origin_ns)
                   for i, item in enumerate(self.items)
                   if item.damage or item.modified or item.sample.stamp_ns != item.origin_ns]
        return (f'Case({self.family}, start {first.origin_ns}, receive '
                f'{first.sample.receive_ns is not None}, {len(damaged)} changed: '
                f'{damaged[:8]})')
    restarts: int = 0  # clock restarts expected (backwards jumps)
    jump: Optional[int] = None  # index (per stream) of the first sample after a jump


def _window(start, receive):
    items = []
    for k in range(start, start + WINDOW):
        for joint, sample in ((True, JOINTS[k]), (False, BASES[k])):
            if receive is not None:
                sample = _replace(sample, receive_ns=sample.stamp_ns + receive[k - start])
            items.append(Item(sample, joint, sample.stamp_ns))
    return items


def _replace(sample, **changes):
    if isinstance(sample, JointStateSample):
        fields = dict(stamp_ns=sample.stamp_ns, frame_id=sample.frame_id, names=sample.names,
                      position=sample.position, velocity=sample.velocity,
                      effort=sample.effort, receive_ns=sample.receive_ns)
        fields.update(changes)
        return JointStateSample(**fields)
    fields = dict(stamp_ns=sample.stamp_ns, frame_id=sample.frame_id,
                  child_frame_id=sample.child_frame_id, position=sample.position,
                  orientation_xyzw=sample.orientation_xyzw, twist_linear=sample.twist_linear,
                  twist_angular=sample.twist_angular, receive_ns=sample.receive_ns)
    fields.update(changes)
    return BaseStateSample(**fields)


@st.composite
def _base_case(draw, family):
    start = draw(st.sampled_from(STARTS))
    receive = None
    if draw(st.booleans()):
        # Receive time: the stamp plus a transport latency of up to 5 ms.
        receive = draw(st.lists(st.integers(0, 5_000_000), min_size=WINDOW,
                                max_size=WINDOW))
    return Case(family, _window(start, receive), start)


def _indices(draw, case, joint=None, most=6, first=0):
    """Distinct item indices from ``first`` on to damage (of one kind when ``joint`` is given)."""
    pool = [i for i, item in enumerate(case.items)
            if i >= first and (joint is None or item.joint == joint)]
    return draw(st.lists(st.sampled_from(pool), min_size=1, max_size=most, unique=True))


# --- families --------------------------------------------------------------------------
@st.composite
def values_case(draw):
    """Put NaN / inf into any field of joint or base samples."""
    case = draw(_base_case('values'))
    bad = st.sampled_from([np.nan, np.inf, -np.inf])
    for index in _indices(draw, case):
        item = case.items[index]
        value = draw(bad)
        if item.joint:
            key = draw(st.sampled_from(['position', 'velocity', 'effort']))
            array = getattr(item.sample, key).copy()
            array[draw(st.integers(0, array.size - 1))] = value
            item.sample, item.damage = _replace(item.sample, **{key: array}), 'non_finite'
        else:
            key = draw(st.sampled_from(['position', 'orientation_xyzw', 'twist_linear',
                                        'twist_angular']))
            array = getattr(item.sample, key).copy()
            array[draw(st.integers(0, array.size - 1))] = value
            item.sample, item.damage = _replace(item.sample, **{key: array}), \
                'non_finite_base'
    return case


@st.composite
def joints_case(draw):
    """Name unknown, duplicate or missing joints, drop velocities, permute (valid)."""
    case = draw(_base_case('joints'))
    for index in _indices(draw, case, joint=True):
        item = case.items[index]
        sample = item.sample
        names, m = list(sample.names), len(sample.names)
        kind = draw(st.sampled_from(['unknown', 'duplicate', 'missing', 'no_velocity',
                                     'permuted']))
        k = draw(st.integers(0, m - 1))
        if kind == 'unknown':
            names[k] = draw(st.text(min_size=1, max_size=8).filter(lambda n: n not in names))
            item.sample, item.damage = _replace(sample, names=tuple(names)), 'unknown_joint'
        elif kind == 'duplicate':
            names[k] = names[(k + 1) % m]
            item.sample, item.damage = _replace(sample, names=tuple(names)), \
                'duplicate_joint'
        elif kind == 'missing':
            keep = [i for i in range(m) if i != k]
            item.sample = _replace(sample, names=tuple(names[i] for i in keep),
                                   position=sample.position[keep],
                                   velocity=sample.velocity[keep], effort=sample.effort[keep])
            item.damage = 'missing_joint'
        elif kind == 'no_velocity':
            item.sample, item.damage = _replace(sample, velocity=np.zeros(0)), \
                'missing_velocity'
        else:
            order = draw(st.permutations(range(m)))
            item.sample = _replace(sample, names=tuple(names[i] for i in order),
                                   position=sample.position[list(order)],
                                   velocity=sample.velocity[list(order)],
                                   effort=sample.effort[list(order)])
    return case


@st.composite
def outliers_case(draw):
    """
    Move isolated stamps to the far future or past, slightly ahead or behind.

    Isolated: no two damaged stamps follow each other in a stream (three mutually
    consistent ones would be a clock jump). The first two stamps of a stream are
    kept: the first has no clock to be judged by, the second no cadence.
    """
    case = draw(_base_case('stamps_outliers'))
    joint = draw(st.booleans())
    prefix = '' if joint else 'base_'
    chosen = sorted(_indices(draw, case, joint=joint, most=4, first=4))
    chosen = [i for n, i in enumerate(chosen) if n == 0 or i - chosen[n - 1] > 2]
    for index in chosen:
        item = case.items[index]
        stamp = item.sample.stamp_ns
        kind = draw(st.sampled_from(['future', 'past', 'duplicate', 'ahead', 'behind']))
        previous = [i for i in range(index) if case.items[i].joint == joint]
        if kind == 'duplicate':
            if not previous or case.items[previous[-1]].damage:
                continue
            new = case.items[previous[-1]].sample.stamp_ns  # equal to the previous stamp
            item.damage = prefix + 'stamp_backwards'
        elif kind == 'future':
            new = draw(st.integers(stamp + 2 * NS, 2**31 * NS - 1))
            item.damage = prefix + 'stamp_outlier'
        elif kind == 'ahead':  # within the tolerance, far ahead of the cadence
            new = stamp + draw(st.integers(50_000_000, 900_000_000))
            item.damage = prefix + 'stamp_outlier'
        elif kind == 'behind':  # not after the previous one, within the tolerance
            new = case.items[previous[-1]].sample.stamp_ns - draw(st.integers(0, 900_000_000))
            item.damage = prefix + 'stamp_backwards'
        else:
            new = draw(st.integers(0, stamp - 2 * NS))
            item.damage = prefix + 'stamp_outlier'
        receive = item.sample.receive_ns
        item.sample = _replace(item.sample, stamp_ns=new)
        assert item.sample.receive_ns == receive  # the record time is not the header's
    return case


@st.composite
def jumps_case(draw):
    """Jump the clock of both streams (back or forward), receive time with it or not."""
    case = draw(_base_case('clock_jumps'))
    split = draw(st.integers(4, WINDOW - 4))
    shift = draw(st.integers(2 * NS, 100 * NS)) * draw(st.sampled_from([-1, 1]))
    receive_moves = draw(st.booleans())
    for item in case.items[2 * split:]:
        sample = item.sample
        changes = {'stamp_ns': sample.stamp_ns + shift}
        if receive_moves and sample.receive_ns is not None:
            changes['receive_ns'] = sample.receive_ns + shift
        item.sample = _replace(sample, **changes)
    case.restarts = int(shift < 0)
    case.jump = split
    return case


@st.composite
def implausible_case(draw):
    """Put values far beyond the URDF limits and the bounds (up to 1e300)."""
    case = draw(_base_case('implausible'))
    for index in _indices(draw, case):
        item = case.items[index]
        sample = item.sample
        scale = draw(st.sampled_from([1e300, 1e12, 1e7]))
        sign = draw(st.sampled_from([-1.0, 1.0]))
        if item.joint:
            key = draw(st.sampled_from(['position', 'velocity', 'effort']))
            array = getattr(sample, key).copy()
            k = draw(st.integers(0, array.size - 1))
            array[k] = sign * scale
            item.sample = _replace(sample, **{key: array})
            item.damage = {'position': 'joint_position_limit', 'velocity':
                           'joint_velocity_limit', 'effort': 'joint_effort_limit'}[key]
        else:
            key = draw(st.sampled_from(['position', 'twist_linear', 'twist_angular']))
            array = getattr(sample, key).copy()
            array[draw(st.integers(0, 2))] = sign * max(scale, 1e10)
            item.sample = _replace(sample, **{key: array})
            item.damage = 'base_position_bound' if key == 'position' else 'base_twist_bound'
    return case


@st.composite
def quaternions_case(draw):
    """Zero or scale quaternions (rejected), or scale them slightly (valid, normalised)."""
    case = draw(_base_case('quaternions'))
    tolerance = CONFIG.quaternion_norm_tolerance
    for index in _indices(draw, case, joint=False):
        item = case.items[index]
        kind = draw(st.sampled_from(['zero', 'scaled', 'slight']))
        q = item.sample.orientation_xyzw
        if kind == 'zero':
            item.sample, item.damage = _replace(item.sample, orientation_xyzw=np.zeros(4)), \
                'invalid_quaternion'
        elif kind == 'scaled':
            scale = draw(st.one_of(st.floats(1 + 2 * tolerance, 1e6),
                                   st.floats(1e-5, 1 - 2 * tolerance)))
            item.sample = _replace(item.sample, orientation_xyzw=q * scale)
            item.damage = 'quaternion_norm'
        else:
            scale = draw(st.floats(1 - 0.5 * tolerance, 1 + 0.5 * tolerance))
            item.sample = _replace(item.sample, orientation_xyzw=q * scale)
            item.modified = True
    return case


@st.composite
def mixed_case(draw):
    """Combine two families (stamps, values, names, bounds, quaternions)."""
    family = draw(st.sampled_from([values_case, joints_case, outliers_case,
                                   implausible_case, quaternions_case]))
    case = draw(family())
    other = draw(st.sampled_from([values_case, joints_case, implausible_case,
                                  quaternions_case]))()
    extra = draw(other)
    # The previous sample of a stream is the reference of a duplicated or reordered stamp:
    # it stays valid.
    references = {i - 2 for i, item in enumerate(case.items) if 'backwards' in item.damage}
    for index, (mine, theirs) in enumerate(zip(case.items, extra.items)):
        if theirs.damage and not mine.damage and mine.origin_ns == theirs.origin_ns \
                and index not in references:
            mine.sample, mine.damage = _replace(theirs.sample, stamp_ns=mine.sample.stamp_ns,
                                                receive_ns=mine.sample.receive_ns), \
                theirs.damage
    case.family = 'mixed'
    return case


# --- running and checking ----------------------------------------------------------------
def _run(samples, batched):
    """Feed ``samples`` to a fresh estimator; return it and its outputs (flush included)."""
    estimator = Estimator(ROBOT, CONFIG)
    faulthandler.dump_traceback_later(60, exit=True)
    try:
        if batched:
            outputs = estimator.add_samples(samples).outputs() + estimator.flush()
        else:
            outputs = feed_stream(estimator, samples)
    finally:
        faulthandler.cancel_dump_traceback_later()
    return estimator, outputs


def _finite(output):
    arrays = [output.mu, output.momentum.force, output.momentum.torque,
              output.body_momentum.force, output.body_momentum.torque,
              output.shape_state.position, output.shape_state.velocity,
              output.shape_state.effort, output.momentum_rate.force,
              output.momentum_rate.torque, output.drift_twist.linear,
              output.drift_twist.angular]
    return all(np.isfinite(a).all() for a in arrays) and np.isfinite(output.energy)


def _explained(case, index, bases=None):
    """
    Return whether valid joint item ``index`` has no valid base within the sync tolerance.

    ``bases``: the sorted stamps of the case's valid base items (:func:`_valid_bases`),
    when the caller asks for many items (a bisection instead of a scan per item).
    """
    stamp = case.items[index].sample.stamp_ns
    # |base - stamp| <= tolerance for integer stamps, in integers (exact at ~1e18 ns).
    tolerance = math.floor(CONFIG.sync_tolerance * NS)
    if bases is None:
        bases = _valid_bases(case)
    # The first valid base not before stamp - tolerance: explained unless it is within
    # stamp + tolerance.
    first = bisect.bisect_left(bases, stamp - tolerance)
    return first == len(bases) or bases[first] > stamp + tolerance


def _valid_bases(case) -> list:
    """Return the sorted stamps of ``case``'s undamaged base items."""
    return sorted(item.sample.stamp_ns for item in case.items
                  if not item.joint and not item.damage)


def _record(case, **counts):
    stats = STATS.setdefault(case.family, Counter())
    stats['cases'] += 1
    stats.update(counts)


def check(case, batched, values=True):
    """Run ``case`` and assert the properties of the module docstring."""
    note(repr(case))
    estimator, outputs = _run([item.sample for item in case.items], batched)
    assert all(_finite(o) for o in outputs)
    rejected = estimator.rejected
    joint_rejections = sum(n for r, n in rejected.items() if r not in BASE_REASONS)
    base_rejections = sum(n for r, n in rejected.items() if r in BASE_REASONS)
    received = estimator.received
    assert received['joint_states'] == estimator.processed + joint_rejections
    assert received['joint_states'] + received['base'] == len(case.items)
    damaged_bases = sum(1 for i in case.items if not i.joint and i.damage)
    assert base_rejections == damaged_bases
    valid = {i: item for i, item in enumerate(case.items) if item.joint and not item.damage}
    bases = _valid_bases(case)
    explained = {i for i in valid if _explained(case, i, bases)}
    expected = Counter(item.damage for item in case.items if item.damage)
    expected['stale_base_state'] += len(explained)
    expected = +expected
    assert Counter(rejected) == expected, (rejected, expected)
    by_stamp = {o.stamp_ns: o for o in outputs}
    assert len(by_stamp) == len(outputs) == estimator.processed
    wanted = {item.sample.stamp_ns: item for i, item in valid.items() if i not in explained}
    assert set(by_stamp) == set(wanted)
    compared = transients = 0
    if values:
        backwards = case.jump is not None and case.restarts
        clean_run = _clean(case.start, case.jump if backwards else None)
        damage_ns = [item.origin_ns for item in case.items if item.damage or item.modified]
        jump_ns = None if case.jump is None or backwards \
            else JOINTS[case.start + case.jump].stamp_ns
        for stamp, item in wanted.items():
            output, clean = by_stamp[stamp], clean_run[item.origin_ns]
            for part in ('position', 'velocity', 'effort'):
                assert np.array_equal(getattr(output.shape_state, part),
                                      getattr(clean.shape_state, part))
            if jump_ns is not None and item.origin_ns >= jump_ns:
                continue  # after a forward jump: a gap the clean run does not have
            since = [item.origin_ns - d for d in damage_ns if d <= item.origin_ns]
            mine, theirs = _filtered(output), _filtered(clean)
            if not since:
                for name in mine:
                    assert np.array_equal(mine[name], theirs[name]), name
            elif min(since) >= TRANSIENT_S * NS:
                for name in mine:
                    error = np.abs(mine[name] - theirs[name]).max()
                    assert error <= RELATIVE * _scales()[name], (name, error, _scales()[name])
                transients += 1
            else:
                continue
            compared += 1
    _record(case, samples=len(case.items), valid_joint_states=len(valid),
            lost=len(set(wanted) - set(by_stamp)), explained_drops=len(explained),
            rejected=sum(rejected.values()), compared=compared, after_transient=transients,
            restarts=estimator.clock_resets)
    return estimator


@_fuzz_settings('values')
@given(values_case(), st.booleans())
def test_fuzz_non_finite_values(case, batched):
    check(case, batched)


@_fuzz_settings('joints')
@given(joints_case(), st.booleans())
def test_fuzz_joint_names_and_arrays(case, batched):
    check(case, batched)


@_fuzz_settings('stamps_outliers')
@given(outliers_case(), st.booleans())
def test_fuzz_stamp_outliers_and_backwards(case, batched):
    check(case, batched)


@_fuzz_settings('clock_jumps')
@given(jumps_case(), st.booleans())
def test_fuzz_clock_jumps(case, batched):
    estimator = check(case, batched)
    assert estimator.clock_resets == case.restarts


@_fuzz_settings('implausible')
@given(implausible_case(), st.booleans())
def test_fuzz_implausible_values(case, batched):
    check(case, batched)


@_fuzz_settings('quaternions')
@given(quaternions_case(), st.booleans())
def test_fuzz_quaternions(case, batched):
    check(case, batched)


@_fuzz_settings('mixed')
@given(mixed_case(), st.booleans())
def test_fuzz_mixed_damage(case, batched):
    check(case, batched)


@pytest.fixture(scope='module', autouse=True)
def _write_stats():
    yield
    path = os.environ.get('RD_FUZZ_STATS')
    if path and STATS:
        with open(path, 'w', encoding='utf-8') as stream:
            json.dump({k: dict(v) for k, v in STATS.items()}, stream, indent=2)


# --- hostile bags through the replay tool -----------------------------------------------------
BAG_WINDOW = 60
OUTPUT_TOPICS = ('/reduced_dynamics/momentum', '/reduced_dynamics/drift/momentum_rate')


def _raw_window():
    with open_bag(os.path.join(DATA, 'paper_thruster')) as reader:
        topics = {t: m for t, m in reader.topics().items() if t in ('/joint_states', '/odom')}
        items = [(m.topic, m.timestamp_ns, bytes(m.data))
                 for _, m in zip(range(2 * BAG_WINDOW), reader.raw_messages(list(topics)))]
    return topics, items


BAG_TOPICS, BAG_ITEMS = _raw_window()


def _write_bag(path, items):
    """Write ``items`` with 4 KiB chunks (many chunks, as long recordings have)."""
    from reduced_dynamics.bag import writer as bag_writer
    chunk = bag_writer._CHUNK_BYTES
    bag_writer._CHUNK_BYTES = 4096
    try:
        with bag_writer.BagWriter(path, BAG_TOPICS) as writer:
            for topic, stamp, data in items:
                writer.write_raw(topic, stamp, data)
    finally:
        bag_writer._CHUNK_BYTES = chunk


def _garble(draw, data):
    """
    Overwrite, truncate, extend or zero ``data`` (bytes) as drawn.

    Returns (damaged bytes, kind, damaged byte ranges [(start, end)] of the original).
    """
    data = bytearray(data)
    size = len(data)
    kind = draw(st.sampled_from(['overwrite', 'truncate', 'extend', 'zero']))
    ranges = []
    if kind == 'overwrite' and data:
        for _ in range(draw(st.integers(1, 16))):
            at = draw(st.integers(0, size - 1))
            data[at] = draw(st.integers(0, 255))
            ranges.append((at, at + 1))
    elif kind == 'truncate':
        cut = draw(st.integers(0, max(size - 1, 0)))
        data, ranges = data[:cut], [(cut, size)]
    elif kind == 'extend':
        data += draw(st.binary(min_size=1, max_size=64))
    elif data:
        start = draw(st.integers(0, size - 1))
        end = min(size, start + draw(st.integers(1, 256)))
        data[start:end] = bytes(end - start)
        ranges.append((start, end))
    return bytes(data), kind, ranges


@st.composite
def garbled_messages(draw):
    """Damage the CDR bytes of a few messages of a bag."""
    items = list(BAG_ITEMS)
    for index in draw(st.lists(st.integers(0, len(items) - 1), min_size=1, max_size=5,
                               unique=True)):
        topic, stamp, data = items[index]
        items[index] = (topic, stamp, _garble(draw, data)[0])
    return items


def _replay_checked(bag, out, family):
    """Replay ``bag``; assert a clean error or a consistent summary with finite outputs."""
    from reduced_dynamics.bag.errors import BagError
    from reduced_dynamics.params import defaults
    from reduced_dynamics.replay import replay, ReplayOptions
    options = ReplayOptions(params={**defaults(), 'prediction_rate': 0.0})
    faulthandler.dump_traceback_later(60, exit=True)
    try:
        summary = replay(str(bag), str(out), ROBOT, options)
    except BagError as error:
        text = str(error)
        assert text and '\n' not in text
        STATS.setdefault(family, Counter()).update(cases=1, bag_errors=1)
        return None
    finally:
        faulthandler.cancel_dump_traceback_later()
    rejected = Counter(summary['rejected'])
    malformed = rejected.pop('malformed', 0)
    received = summary['received']
    assert sum(summary['messages_in'].values()) == sum(received.values()) + malformed
    joint_rejections = sum(n for r, n in rejected.items() if r not in BASE_REASONS)
    assert received.get('joint_states', 0) == summary['processed'] + joint_rejections
    with open_bag(str(out)) as reader:
        rows = [m.msg.wrench for m in reader.messages(list(OUTPUT_TOPICS))]
    values = np.array([[w.force.x, w.force.y, w.force.z, w.torque.x, w.torque.y, w.torque.z]
                       for w in rows]).reshape(-1, 6)
    assert np.isfinite(values).all()
    assert len(values) == 2 * summary['processed']
    STATS.setdefault(family, Counter()).update(
        cases=1, processed=summary['processed'], rejected=sum(summary['rejected'].values()),
        undecodable=sum(summary['undecodable_skipped'].values()))
    return summary


def _template():
    """Return the clean bag's (metadata.yaml text, storage file name, storage bytes)."""
    import tempfile
    with tempfile.TemporaryDirectory() as directory:
        path = os.path.join(directory, 'bag')
        _write_bag(path, BAG_ITEMS)
        storage = next(n for n in os.listdir(path) if n.endswith('.mcap'))
        with open(os.path.join(path, 'metadata.yaml'), 'rb') as stream:
            metadata = stream.read()
        with open(os.path.join(path, storage), 'rb') as stream:
            return metadata, storage, stream.read()


TEMPLATE = _template()


def _chunks():
    """Return the template's chunks: [(start, end)] and [(start, end, first, last stamp)]."""
    import io
    from mcap.reader import make_reader
    summary = make_reader(io.BytesIO(TEMPLATE[2])).get_summary()
    times = [(c.chunk_start_offset, c.chunk_start_offset + c.chunk_length,
              c.message_start_time, c.message_end_time) for c in summary.chunk_indexes]
    return [t[:2] for t in times], times


CHUNKS, CHUNK_TIMES = _chunks()


def _definitions():
    """Return the template's (start, end) bytes of the schema and channel records."""
    import struct
    content = TEMPLATE[2]
    start = q = CHUNKS[0][0] + 9 + 40  # uncompressed: the first chunk's records
    while content[q] in (0x03, 0x04):
        q += 9 + struct.unpack_from('<Q', content, q + 1)[0]
    return start, q


DEFINITIONS = _definitions()
BAG_STAMPS = sorted({stamp for topic, stamp, _ in BAG_ITEMS if topic == '/joint_states'})
EXAMPLES.update({'bag_messages': 60, 'bag_files': 90})


def test_a_gated_base_measurement_is_a_base_rejection(tmp_path):
    """A plausible but wrong odometry pose (0.2 m off) is gated: the joint states all count."""
    from rosbags.typesys import get_typestore, Stores
    store = get_typestore(Stores.ROS2_JAZZY)
    items = list(BAG_ITEMS)
    index = [i for i, (topic, _, _) in enumerate(items) if topic == '/odom'][len(items) // 4]
    topic, stamp, data = items[index]
    odometry = store.deserialize_cdr(data, 'nav_msgs/msg/Odometry')
    odometry.pose.pose.position.x += 0.2
    items[index] = (topic, stamp, bytes(store.serialize_cdr(odometry, 'nav_msgs/msg/Odometry')))
    _write_bag(tmp_path / 'bag', items)
    summary = _replay_checked(tmp_path / 'bag', tmp_path / 'out', 'bag_messages')
    assert summary['rejected'].get('innovation_gate', 0) >= 1


@_fuzz_settings('bag_messages')
@given(garbled_messages())
def test_fuzz_garbled_messages_in_a_bag(items):
    import tempfile
    with tempfile.TemporaryDirectory() as directory:
        _write_bag(os.path.join(directory, 'bag'), items)
        summary = _replay_checked(os.path.join(directory, 'bag'),
                                  os.path.join(directory, 'out'), 'bag_messages')
    assert summary is not None  # intact storage: the bag opens and replays


@_fuzz_settings('bag_files')
@given(st.data())
def test_fuzz_damaged_bag_files(data):
    import tempfile
    metadata, storage, content = TEMPLATE
    target = data.draw(st.sampled_from(['storage'] * 4 + ['metadata']), label='target')
    intact = None
    if target == 'storage':
        content, kind, ranges = _garble(data.draw, content)
        # Stamps all of whose messages lie in chunks the damage did not touch.
        hit = [(a, b) for a, b in CHUNKS if any(lo < b and a < hi for lo, hi in ranges)]
        intact = {t for t in BAG_STAMPS
                  if not any(t0 <= t <= t1 for a, b, t0, t1 in CHUNK_TIMES if (a, b) in hit)}
        note(f'{kind} {ranges}: {len(hit)} of {len(CHUNKS)} chunks hit')
        # With the summary gone (scan mode), a damaged chunk header costs that chunk only:
        # the scan resyncs on the next chunk that validates (bag/damage.py). What the
        # reader cannot recover: damaged schema or channel records, which the writer puts
        # in the first chunk only (the summary's copy is gone too). Counted, not asserted.
        summary_hit = any(hi > CHUNKS[-1][1] for _, hi in ranges)
        if summary_hit and any(lo < DEFINITIONS[1] and DEFINITIONS[0] < hi
                               for lo, hi in ranges):
            STATS.setdefault('bag_files', Counter()).update(definitions_hit=1)
            intact = None
    else:
        metadata, kind, _ = _garble(data.draw, metadata)
        note(f'metadata: {kind}')
    with tempfile.TemporaryDirectory() as directory:
        bag = os.path.join(directory, 'bag')
        os.makedirs(bag)
        with open(os.path.join(bag, 'metadata.yaml'), 'wb') as stream:
            stream.write(metadata)
        with open(os.path.join(bag, storage), 'wb') as stream:
            stream.write(content)
        out = os.path.join(directory, 'out')
        summary = _replay_checked(bag, out, 'bag_files')
        if summary is None or intact is None:
            return
        # Nothing intact lost: every stamp whose joint state and odometry sit in
        # undamaged chunks has its output (the reader may salvage more).
        with open_bag(out) as reader:
            produced = {m.timestamp_ns for m in reader.raw_messages([OUTPUT_TOPICS[0]])}
        assert intact <= produced, sorted(intact - produced)[:5]
        STATS['bag_files'].update(intact_stamps=len(intact), produced=len(produced))
