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
Bag replay: ``reduced-dynamics replay BAG -o OUT``.

Reads a rosbag2 bag (MCAP or sqlite3, any metadata version from Humble on) or
a bare .mcap, drives the estimator pipeline with its joint states and base
states, and writes a rosbag2 MCAP bag with exactly the node's output topics.
Other topics, custom types included, are ignored. Streaming: memory does not
grow with the bag's length.
"""

from __future__ import annotations

import argparse
from collections import Counter
import contextlib
from dataclasses import dataclass, field
import functools
import json
import os
import shutil
import sys
import time
from typing import Any, Callable, Optional, TextIO

import numpy as np

from reduced_dynamics.bag.damage import Damage
from reduced_dynamics.bag.errors import BagError
from reduced_dynamics.bag.reader import open_bag
from reduced_dynamics.bag.writer import BagWriter
from reduced_dynamics.blas_threads import limited_blas_threads
from reduced_dynamics.estimator.config import check_parameter, EstimatorConfig
from reduced_dynamics.estimator.core.warmup import compiling_notice
from reduced_dynamics.estimator.outputs import EstimatorBatch, OutputChunk
from reduced_dynamics.estimator.pipeline import Estimator
from reduced_dynamics.estimator.smoother import SmootherFiles
from reduced_dynamics.bag.reader import BagReader
from reduced_dynamics.messages import cdr
from reduced_dynamics.messages.convert import (
    command_from_ros, joint_state_from_ros, joint_trajectory_from_ros, odometry_from_ros,
    pose_stamped_from_ros, pose_with_covariance_stamped_from_ros)
from reduced_dynamics.messages.samples import JointTrajectorySample, with_receive_time
from reduced_dynamics.messages.types import RosbagsTypes
from reduced_dynamics.output_rows import RowWriter
from reduced_dynamics.output_spool import OutputSpool, SMOOTHED_FIELDS
from reduced_dynamics.params import defaults, load_params_file
from reduced_dynamics.plot_marks import read_marks
from reduced_dynamics.replay_plots import PlotInputs, write_plots
from reduced_dynamics.robot.model import load_robot, RobotModel
from reduced_dynamics.topics import (active_topics, cdr_encoder, EVENTS_TOPIC, FIXED_LAG_TOPICS,
                                     resolved_name)

JOINT_STATE_TYPE = 'sensor_msgs/msg/JointState'
#: Input messages handed to the estimator at once (its batched path).
REPLAY_BATCH = 512
ODOMETRY_TYPE = 'nav_msgs/msg/Odometry'
POSE_TYPE = 'geometry_msgs/msg/PoseStamped'
#: a base pose with its covariance (docs/message_covariance.md), taken like POSE_TYPE
POSE_COVARIANCE_TYPE = 'geometry_msgs/msg/PoseWithCovarianceStamped'
TRAJECTORY_TYPE = 'trajectory_msgs/msg/JointTrajectory'
WRENCH_TYPE = 'geometry_msgs/msg/WrenchStamped'
#: Exit status of a replay that completed but lost messages to a damaged bag.
EXIT_DAMAGED = 3


@dataclass
class ReplayOptions:
    """Inputs of a replay beside the bag paths (topics default from the params)."""

    params: dict = field(default_factory=defaults)
    joint_states_topic: Optional[str] = None
    odom_topic: Optional[str] = None
    base_pose_topic: Optional[str] = None
    #: planned trajectories (prediction_mode planned); default: the trajectory_topic param
    trajectory_topic: Optional[str] = None
    #: commanded body wrench (WrenchStamped); default: the commanded_wrench_topic param
    #: ('' = off; never guessed: it changes what drift/momentum_rate's events mean)
    commanded_wrench_topic: Optional[str] = None
    start: Optional[float] = None
    end: Optional[float] = None
    plots_dir: Optional[str] = None
    overwrite: bool = False
    progress: Optional[TextIO] = None
    #: refuse a damaged bag (BagError) instead of reading what is intact
    strict: bool = False
    #: fixed-interval (RTS) smoothing of the filter's estimates; False: exactly the
    #: causal outputs the node publishes (memory then stays flat in the bag's length)
    smooth: bool = True
    #: with ``smooth``: also write the causal outputs (what ``smooth=False`` writes, the
    #: same messages) into this bag, from the same pass over the input
    causal_out: Optional[str] = None
    #: rows at the base samples, the shape held from the latest joint state (at zero
    #: without any): a jointed robot without a JointState topic is refused otherwise
    base_driven: bool = False
    #: where the robot model came from, for messages (see :func:`robot_source`)
    robot_source: str = ''
    #: fixed-lag smoothing [s] as the node's smoothing_lag (0: off, the default here
    #: whatever the params say: a replay writes the fixed-lag topics only when asked)
    fixed_lag: float = 0.0
    #: command mapping YAML of a thruster command drawn on the plots (default: the
    #: shipped freeflyer2 one when the bag has its topic)
    thruster_map: Optional[str] = None


class _Series:
    """Decimated time series for plots: at most ~2 * limit points, whatever the length."""

    def __init__(self, limit: int = 5000) -> None:
        self.limit = limit
        self.stride = 1
        self.count = 0
        self.rows: list[tuple] = []

    def add(self, row: tuple) -> None:
        if self.count % self.stride == 0:
            self.rows.append(row)
            if len(self.rows) > 2 * self.limit:
                self.rows = self.rows[::2]
                self.stride *= 2
        self.count += 1


def _topic(name: str) -> str:
    return name if name.startswith('/') else '/' + name


InputChoice = tuple[Optional[str], str, bool]


def choose_inputs(topics: dict[str, str], options: ReplayOptions) -> InputChoice:
    """Return (joint-state topic or None, base topic, base topic is Odometry)."""
    params = options.params
    joint = _topic(options.joint_states_topic or params['joint_states_topic'])
    joint_topic = joint if topics.get(joint) == JOINT_STATE_TYPE else None
    if options.joint_states_topic and joint_topic is None:
        raise BagError(f'bag has no {JOINT_STATE_TYPE} topic {joint}')
    if options.odom_topic and options.base_pose_topic:
        raise ValueError('give --odom-topic or --base-pose-topic, not both')
    odom = _topic(options.odom_topic or params['odom_topic'])
    pose = _topic(options.base_pose_topic or params['base_pose_topic'])
    prefer_pose = bool(options.base_pose_topic) or (
        params['base_input'] in ('pose', 'pose_covariance') and not options.odom_topic)
    candidates = [(pose, POSE_TYPE), (odom, ODOMETRY_TYPE)] if prefer_pose \
        else [(odom, ODOMETRY_TYPE), (pose, POSE_TYPE)]
    if options.odom_topic:
        candidates = candidates[:1] if not prefer_pose else candidates
    for name, msgtype in candidates:
        if topics.get(name) == msgtype or (msgtype == POSE_TYPE
                                           and topics.get(name) == POSE_COVARIANCE_TYPE):
            return joint_topic, name, msgtype == ODOMETRY_TYPE
    wanted = ', '.join(f'{n} ({t})' for n, t in candidates)
    raise BagError(f'bag has no base state topic: looked for {wanted}; it has '
                   f'{sorted(topics)}')


Decoder = Callable[[bytes], Any]


def input_decoder(reader: BagReader, topic: str, msgtype: str, child_frame_id: str) -> Decoder:
    """
    Return raw CDR -> sample for an input topic (None: undecodable, counted by the reader).

    The fixed-layout decoder runs first when the bag's definition is the
    standard one; whatever it refuses goes through the typestore and the
    ``*_from_ros`` converter, so bad data gets the generic path's verdict and
    message: skipped if it does not deserialize, ValueError/TypeError if it
    deserializes into something invalid.
    """
    deserialize = reader.deserializer(topic, msgtype)
    if msgtype == JOINT_STATE_TYPE:
        convert, fast = joint_state_from_ros, cdr.decode_joint_state
    elif msgtype == ODOMETRY_TYPE:
        convert, fast = odometry_from_ros, cdr.decode_odometry
    elif msgtype == POSE_TYPE:
        convert = functools.partial(pose_stamped_from_ros, child_frame_id=child_frame_id)
        fast = functools.partial(cdr.decode_pose_stamped, child_frame_id=child_frame_id)
    elif msgtype == POSE_COVARIANCE_TYPE:
        convert = functools.partial(pose_with_covariance_stamped_from_ros,
                                    child_frame_id=child_frame_id)
        fast = functools.partial(cdr.decode_pose_with_covariance_stamped,
                                 child_frame_id=child_frame_id)
    elif msgtype == TRAJECTORY_TYPE:
        convert, fast = joint_trajectory_from_ros, None  # rare messages: the generic path
    elif msgtype == WRENCH_TYPE:
        convert, fast = command_from_ros, cdr.decode_wrench_stamped
    else:
        raise BagError(f'topic {topic}: cannot use {msgtype} as an input')
    if fast is not None and not cdr.fast_path_applies(reader.typestore_for(topic, msgtype),
                                                      msgtype):
        fast = None

    def decode(data: bytes) -> Any:
        if fast is not None:
            try:
                return fast(data)
            except cdr.CdrError:
                pass
        msg = deserialize(data)
        return None if msg is None else convert(msg)
    return decode


def _wrong_type(topic: str, msgtype: str, expected: str) -> Decoder:
    """Return a decoder rejecting a topic's messages of an unexpected type."""
    def reject(data: bytes) -> Any:
        raise ValueError(f'{topic} carries {msgtype}, expected {expected}')
    return reject


def robot_source(params: dict, urdf: str = '') -> str:
    """Return where :func:`load_robot_from_params` takes the robot from, for messages."""
    if urdf:
        return f'--urdf {urdf}'
    if params.get('robot_description'):
        return 'the robot_description parameter'
    if params.get('urdf_path'):
        return f'urdf_path {params["urdf_path"]}'
    return 'the built-in paper robot, no --urdf given'


def check_shape_input(reader: BagReader, joint_topic: Optional[str], robot: RobotModel,
                      options: ReplayOptions) -> None:
    """
    Refuse a replay whose joint states cannot drive ``robot``'s shape (BagError).

    A jointed robot without its JointState topic would run with the shape frozen
    at zero, and joint states naming other joints than the robot's would all be
    rejected: both give a wrong momentum without a word. ``--base-driven`` asks
    for the frozen shape explicitly.
    """
    source = options.robot_source or 'the given robot model'
    if joint_topic is None:
        if robot.m == 0 or options.base_driven:
            return
        topics = reader.topics()
        wanted = _topic(options.joint_states_topic
                        or options.params['joint_states_topic'])
        found = sorted(t for t, msgtype in topics.items() if msgtype == JOINT_STATE_TYPE)
        other = f' (it is {topics[wanted]})' if wanted in topics else ''
        raise BagError(
            f'robot {robot.model.name} ({source}) has {robot.m} shape joints but the bag '
            f'has no {JOINT_STATE_TYPE} topic {wanted}{other}; its JointState topics: '
            f'{", ".join(found) if found else "none"}. Pass --joint-states-topic NAME, or '
            '--base-driven to replay with the shape held at zero')
    names = _first_joint_names(reader, joint_topic, set(robot.shape_joint_names))
    if names is None:
        return
    raise BagError(
        f'the joint states on {joint_topic} name {_listing(names)} but robot '
        f'{robot.model.name} ({source}) has the shape joints '
        f'{_listing(robot.shape_joint_names)}: give this robot\'s description with --urdf')


def _listing(names: tuple, limit: int = 8) -> str:
    shown = ', '.join(names[:limit]) or 'no joints'
    return shown + (f' (+{len(names) - limit} more)' if len(names) > limit else '')


def _first_joint_names(reader: BagReader, topic: str, wanted: set,
                       look: int = 50) -> Optional[tuple]:
    """
    Return the names of the first joint state when none of the first ``look`` match.

    None: one names exactly the ``wanted`` joints (a garbled message or two at the
    start are rejections of their own, not a reason to refuse the bag), or none
    decodes.
    """
    first = None
    # A second reader: the replay's own reader counts damage once, in its one pass.
    with open_bag(reader.path) as peek:
        decode = input_decoder(peek, topic, JOINT_STATE_TYPE, '')
        for count, message in enumerate(peek.raw_messages([topic])):
            if count >= look:
                break
            if message.msgtype != JOINT_STATE_TYPE:
                continue
            try:
                sample = decode(message.data)
            except (ValueError, TypeError, BagError):
                continue
            if sample is None:
                continue
            names = tuple(sample.names)
            if set(names) == wanted and len(names) == len(wanted):
                return None
            first = names if first is None else first
    return first


def load_robot_from_params(params: dict, urdf: str = '',
                           base_joint: Optional[str] = None,
                           gravity: Optional[list] = None,
                           xacro_args: Optional[list] = None) -> RobotModel:
    """
    Return the robot of the options or the parameter file (default: the paper robot).

    ``xacro_args``: ``name:=value`` items for a ``.xacro`` description.
    """
    from reduced_dynamics.robot.xacro_file import parse_xacro_args
    source = urdf or params.get('robot_description') or params.get('urdf_path') or ''
    joint = base_joint or params.get('base_joint')
    g = gravity if gravity is not None else params.get('gravity')
    return load_robot(source, joint, None if g is None else np.asarray(g, dtype=float),
                      parse_xacro_args(xacro_args))


def replay(bag_path: str, out_path: str, robot: RobotModel,
           options: Optional[ReplayOptions] = None) -> dict[str, Any]:
    """
    Replay ``bag_path`` through the estimator into ``out_path``; return the summary.

    With one BLAS thread (:mod:`reduced_dynamics.blas_threads`; the caller's counts
    are restored after it): the outputs do not depend on the machine's thread count.
    """
    options = options or ReplayOptions()
    _check_causal_out(out_path, options)
    with limited_blas_threads():
        return _replay(bag_path, out_path, robot, options)


def _check_causal_out(out_path: str, options: ReplayOptions) -> None:
    """Raise ValueError when ``options.causal_out`` cannot be written beside ``out_path``."""
    if options.causal_out is None:
        return
    if not options.smooth:
        raise ValueError('without smoothing the output bag holds the causal outputs already')
    if os.path.abspath(options.causal_out) == os.path.abspath(out_path):
        raise ValueError(f'{options.causal_out} is the output bag itself')


def _replay(bag_path: str, out_path: str, robot: RobotModel,
            options: ReplayOptions) -> dict[str, Any]:
    """Replay ``bag_path`` into ``out_path`` with the BLAS threads as they are."""
    # Offline, a prediction's budget is its evaluations alone: a wall-time budget would
    # make the output depend on the machine's load (the node keeps its own).
    config = EstimatorConfig.from_mapping(options.params).replaced(
        prediction_max_wall_time=0.0, smoothing_lag=options.fixed_lag)
    types = RosbagsTypes()
    started = time.perf_counter()
    with open_bag(bag_path, strict=options.strict) as reader:
        if options.strict:
            reader.verify()  # refuse before writing anything
        topics = reader.topics()
        joint_topic, base_topic, is_odom = choose_inputs(topics, options)
        check_shape_input(reader, joint_topic, robot, options)
        base_driven = joint_topic is None or robot.m == 0 or options.base_driven
        command_topic = options.commanded_wrench_topic \
            or options.params.get('commanded_wrench_topic', '')
        if command_topic:
            command_topic = _topic(command_topic)
            if topics.get(command_topic) != WRENCH_TYPE:
                raise BagError(f'bag has no {WRENCH_TYPE} topic {command_topic} (commanded '
                               f'wrench); it has {sorted(topics)}')
        estimator = Estimator(robot, config, use_odometry=is_odom, base_driven=base_driven,
                              cyclic_joints=options.params.get('cyclic_joints', ''),
                              commanded_wrench=bool(command_topic))
        start_ns = None if options.start is None else reader.start_ns + int(options.start * 1e9)
        end_ns = None if options.end is None else reader.start_ns + int(options.end * 1e9)
        trajectory_topic = _topic(options.trajectory_topic
                                  or options.params.get('trajectory_topic', 'joint_trajectory'))
        if options.trajectory_topic and topics.get(trajectory_topic) != TRAJECTORY_TYPE:
            raise BagError(f'bag has no {TRAJECTORY_TYPE} topic {trajectory_topic}')
        if topics.get(trajectory_topic) != TRAJECTORY_TYPE:
            trajectory_topic = None
        wanted = [t for t in (joint_topic, base_topic, trajectory_topic, command_topic) if t]
        total_ns = max(reader.duration_ns, 1)
        outputs = active_topics(bool(estimator.cyclic_joints), bool(command_topic))
        out_topics = {resolved_name(t): t.msgtype for t in outputs}
        # Per output: sample field, bag topic, sample -> CDR bytes (no message objects).
        encoders = [(t.field, resolved_name(t), cdr_encoder(t, types)) for t in outputs]
        lagged = [(t.field, resolved_name(t), cdr_encoder(t, types))
                  for t in (FIXED_LAG_TOPICS if options.fixed_lag > 0.0 else ())]
        out_topics.update({topic: t.msgtype for t, (_, topic, _) in zip(FIXED_LAG_TOPICS,
                                                                        lagged)})
        # Events go out when the detector issues them (causal, as the node publishes them).
        events_topic, encode_event = resolved_name(EVENTS_TOPIC), cdr_encoder(EVENTS_TOPIC,
                                                                              types)
        out_topics[events_topic] = EVENTS_TOPIC.msgtype
        base_type = topics[base_topic]
        inputs = {}
        for topic, msgtype in reader.connection_types(wanted):
            if (topic, msgtype) == (joint_topic, JOINT_STATE_TYPE):
                inputs[topic, msgtype] = input_decoder(reader, topic, msgtype, '')
            elif (topic, msgtype) == (base_topic, base_type):
                inputs[topic, msgtype] = input_decoder(reader, topic, msgtype,
                                                       robot.base_link)
            elif (topic, msgtype) == (trajectory_topic, TRAJECTORY_TYPE):
                inputs[topic, msgtype] = input_decoder(reader, topic, msgtype, '')
            elif (topic, msgtype) == (command_topic, WRENCH_TYPE):
                inputs[topic, msgtype] = input_decoder(reader, topic, msgtype, '')
            elif topic == command_topic:
                inputs[topic, msgtype] = _wrong_type(topic, msgtype, WRENCH_TYPE)
            else:
                expected = JOINT_STATE_TYPE if topic == joint_topic else base_type
                inputs[topic, msgtype] = _wrong_type(topic, msgtype, expected)
        read: Counter = Counter()
        series = {'mu': _Series(), 'rate': _Series(), 'shape': _Series(),
                  'residual': _Series(), 'disturbance': _Series()}
        if options.plots_dir:
            def residual_point(done: Any) -> None:
                # The residuals as predictions finish (the predictor keeps its last few).
                if done.compared:
                    series['residual'].add((done.start_ns, done.shape_residual,
                                            done.position_residual))
            estimator.predictor.on_finished = residual_point
        last_report = started
        # The first chunk loads the compiled kernels (a first run after an install compiles
        # them, minutes): said if it takes long, and only when progress is shown.
        notice = contextlib.nullcontext() if options.progress is None else compiling_notice(
            functools.partial(_say, options.progress))
        causal_bag = contextlib.nullcontext() if options.causal_out is None else \
            BagWriter(options.causal_out, out_topics, overwrite=options.overwrite)
        with BagWriter(out_path, out_topics, overwrite=options.overwrite) as writer, \
                causal_bag as causal, notice as compiling:
            write = writer.write_raw
            # What is causal whatever the smoothing (events, fixed-lag rows) goes to both bags.
            write_causal = write if causal is None else _both(write, causal.write_raw)
            causal_rows = None if causal is None else RowWriter(causal, encoders)
            spool = None
            if options.smooth:
                # The smoother's steps and the causal messages wait on disk, beside the
                # output bag (estimator/smoother.py, output_spool.py): memory stays flat.
                out = os.path.abspath(out_path)
                files = SmootherFiles(os.path.dirname(out),
                                      f'.{os.path.basename(out)}.smoothing-')
                estimator.enable_smoothing(files)
                spool = OutputSpool(files.file('outputs.bin'), encoders)

            def write_lagged(rows: list, record_ns: int) -> None:
                # Recorded when the node would publish them, stamped with their own time
                # (not spooled: smoothing does not change them).
                for row in rows:
                    for name, topic, encode in lagged:
                        write_causal(topic, record_ns, encode(getattr(row, name)))

            rows_out = RowWriter(writer, encoders)

            def emit(done: EstimatorBatch, final: bool = False) -> None:
                if compiling is not None:
                    compiling.cancel()  # a chunk is done: the kernels are loaded
                chunks = done.chunks
                for chunk in chunks:
                    for k in sorted(chunk.events or ()):
                        for event in chunk.row_events(k) or ():
                            write_causal(events_topic, int(chunk.stamps_ns[k]),
                                         encode_event(event))
                last = next((int(c.stamps_ns[-1]) for c in reversed(chunks) if len(c)), None)
                if last is not None:
                    last_event_ns[0] = last
                if final:
                    for event in estimator.finish_events():
                        write_causal(events_topic, last_event_ns[0], encode_event(event))
                if lagged:
                    for chunk in chunks:
                        for k in sorted(chunk.fixed_lag or ()):
                            if chunk.fixed_lag[k]:
                                write_lagged(chunk.fixed_lag[k], int(chunk.stamps_ns[k]))
                    if last is not None:
                        last_ns[0] = last
                    if final:
                        rows = estimator.flush_fixed_lag()
                        if rows:
                            write_lagged(rows, max(last_ns[0], rows[-1].stamp_ns))
                if spool is not None:
                    for chunk in chunks:
                        rows_out.hold_chunk(spool, chunk)
                        if causal_rows is not None:
                            causal_rows.write_chunk(chunk)
                        if options.plots_dir:
                            shape = chunk.qbar if chunk.cyclic is None else chunk.cyclic.qhat
                            for k, stamp in enumerate(chunk.stamps_ns.tolist()):
                                series['shape'].add((stamp, *shape[k]))
                    if final:
                        if rows_out.columns:
                            _write_smoothed_columns(spool, estimator, writer, series,
                                                    options.plots_dir)
                        else:
                            _write_smoothed(spool, estimator, write, series, options.plots_dir)
                        spool.close()
                        files.close()
                    return
                for chunk in chunks:
                    rows_out.write_chunk(chunk)
                    if options.plots_dir:
                        _plot_rows(series, chunk)

            batch: list = []
            last_ns = [0]  # stamp of the last output
            last_event_ns = [0]
            for count, message in enumerate(reader.raw_messages(wanted, start_ns, end_ns)):
                decode = inputs[message.topic, message.msgtype]
                sample = None
                try:
                    sample = decode(message.data)
                    if sample is not None:  # None: undecodable, in reader.skipped
                        read[message.topic] += 1
                        # The record time is the receive time the stamp policy compares
                        # header stamps with (estimator/stamps.py).
                        sample = with_receive_time(sample, message.timestamp_ns)
                        if sample.__class__ is JointTrajectorySample:
                            # A plan applies from its arrival: what came before is
                            # processed first, as the node's callbacks would.
                            emit(estimator.add_samples(batch))
                            batch = []
                            estimator.add_trajectory(sample)
                        else:
                            batch.append(sample)
                except BagError:
                    raise  # strict mode refusing a damaged message
                except (ValueError, TypeError) as error:
                    if sample is None:  # deserialized, but not into a valid sample
                        read[message.topic] += 1
                    estimator.rejected['malformed'] += 1
                    estimator.last_rejection = f'malformed: {error}'
                if len(batch) >= REPLAY_BATCH:
                    # The estimator's batched path: identical outputs, a fraction of the
                    # per-sample cost (one vectorised update per chunk).
                    emit(estimator.add_samples(batch))
                    batch = []
                if options.progress is not None and count % 256 == 0:
                    now = time.perf_counter()
                    if now - last_report >= 2.0:
                        last_report = now
                        done = (message.timestamp_ns - reader.start_ns) / total_ns
                        options.progress.write(f'\rreplay: {100 * done:5.1f}% '
                                               f'({sum(read.values())} messages)')
                        options.progress.flush()
            emit(estimator.add_samples(batch))
            emit(estimator.flush_batch(), final=True)
        written = {topic: count for topic, count in writer.message_counts.items() if count}
        skipped = dict(reader.skipped)
        # A --start/--end window reads part of the bag on purpose: no missing count then.
        damage = damage_report(reader, wanted, read,
                               whole=start_ns is None and end_ns is None)
    if options.progress is not None:
        options.progress.write('\rreplay: 100.0%\n')
    elapsed = time.perf_counter() - started
    summary = estimator.summary()
    summary.update({'input_bag': str(bag_path), 'output_bag': str(out_path),
                    'smoothed': options.smooth,
                    **({'causal_output_bag': str(options.causal_out)}
                       if options.causal_out is not None else {}),
                    'robot': robot.model.name, 'robot_source': options.robot_source,
                    'joint_states_topic': joint_topic,
                    'base_topic': base_topic, 'trajectory_topic': trajectory_topic,
                    'base_driven': base_driven,
                    **({'commanded_wrench': {'topic': command_topic,
                                             **summary['commanded_wrench']}}
                       if command_topic else {}),
                    'messages_in': dict(read), 'messages_out': dict(written),
                    'undecodable_skipped': skipped, 'damage': damage, 'seconds': elapsed,
                    'samples_per_second': estimator.processed / elapsed if elapsed else None})
    if options.plots_dir:
        try:
            marks = read_marks(str(bag_path), joint_topic, start_ns, end_ns)
        except (BagError, OSError, ValueError, AttributeError) as error:  # marks are optional
            marks = {'torque_steps': [], 'pulses': [], 'pulse_topic': None,
                     'error': str(error)}
        summary['plots'] = write_plots(options.plots_dir, series, robot, marks, PlotInputs(
            str(bag_path), base_topic, command_topic, options.thruster_map))
        t0 = series['mu'].rows[0][0] if series['mu'].rows else 0
        summary['plot_marks'] = {
            'torque_steps_s': [round((s - t0) * 1e-9, 6) for s in marks['torque_steps']],
            'thruster_pulses_s': [[round((a - t0) * 1e-9, 6), round((b - t0) * 1e-9, 6)]
                                  for a, b in marks['pulses']],
            'pulse_topic': marks['pulse_topic']}
    return summary


def _both(first: Callable, second: Callable) -> Callable:
    """Return a ``write(topic, stamp_ns, data)`` that writes with ``first``, then ``second``."""
    def write(topic: str, stamp_ns: int, data: Any) -> None:
        first(topic, stamp_ns, data)
        second(topic, stamp_ns, data)
    return write


def _say(stream: TextIO, text: str) -> None:
    """Write ``text`` on its own line of the progress stream."""
    stream.write(f'\nreplay: {text}\n')
    stream.flush()


def _plot_rows(series: dict, chunk: OutputChunk) -> None:
    """Add a chunk's causal rows to the plots' series (what its outputs carry)."""
    kernel = chunk.kernel
    rate = kernel.wrenches(chunk.momentum_rate)
    shape = chunk.qbar if chunk.cyclic is None else chunk.cyclic.qhat
    disturbance = None if chunk.disturbance is None else kernel.wrenches(chunk.disturbance)
    for k, stamp in enumerate(chunk.stamps_ns.tolist()):
        series['mu'].add((stamp, *chunk.mu[k]))
        series['rate'].add((stamp, *rate[k]))
        series['shape'].add((stamp, *shape[k]))
        if disturbance is not None:
            series['disturbance'].add((stamp, *disturbance[k]))


def _write_smoothed_columns(spool: OutputSpool, estimator: Estimator, writer: BagWriter,
                            series: dict, plots: Optional[str]) -> None:
    """
    Write the held outputs in order, their smoothed fields from the estimator's columns.

    The bag of :func:`_write_smoothed` (output by output): the held runs of rows
    go out as blocks (:meth:`BagWriter.write_rows`), merged topic by topic with
    as many smoothed rows.
    """
    recorded = estimator.step_store.outputs
    if recorded != spool.count:
        raise ValueError(f'{spool.count} outputs for {recorded} recorded filter rows')
    encoders = spool.encoders
    for smoothed in estimator.smoothed_columns():
        for stamps, held in spool.segments():
            one = isinstance(stamps, int)
            rows = smoothed.take(1 if one else len(stamps))
            records = rows['records']
            topics, parts = [], []
            for index, (name, topic, _) in enumerate(encoders):
                part = records.get(name) if name in SMOOTHED_FIELDS else held.get(index)
                if part is not None:
                    topics.append(topic)
                    parts.append(part)
            if one:
                for topic, part in zip(topics, parts):
                    writer.write_raw(topic, stamps, part if isinstance(part, bytes)
                                     else part[0].tobytes())
            else:
                writer.write_rows(topics, stamps, parts)
            if plots:
                rate, disturbance = rows['rate'], rows['disturbance']
                for k, stamp in enumerate([stamps] if one else stamps.tolist()):
                    series['mu'].add((stamp, *rows['mu'][k]))
                    series['rate'].add((stamp, *rate[k]))
                    if disturbance is not None:
                        series['disturbance'].add((stamp, *disturbance[k]))


def _write_smoothed(spool: OutputSpool, estimator: Estimator, write: Callable,
                    series: dict, plots: Optional[str]) -> None:
    """Write the held outputs in order, their smoothed fields from the estimator."""
    recorded = estimator.step_store.outputs
    if recorded != spool.count:
        raise ValueError(f'{spool.count} outputs for {recorded} recorded filter rows')
    encoders = spool.encoders
    for (stamp, causal), smoothed in zip(spool.rows(), estimator.smoothed_rows()):
        for index, (name, topic, encode) in enumerate(encoders):
            if name in SMOOTHED_FIELDS:
                sample = smoothed.get(name)
                if sample is not None:
                    write(topic, stamp, encode(sample))
            else:
                data = causal.get(index)
                if data is not None:
                    write(topic, stamp, data)
        if plots:
            rate, disturbance = smoothed['momentum_rate'], smoothed.get('disturbance')
            series['mu'].add((stamp, *smoothed['mu']))
            series['rate'].add((stamp, *rate.force, *rate.torque))
            if disturbance is not None:
                series['disturbance'].add((stamp, *disturbance.force, *disturbance.torque))


def damage_report(reader: BagReader, topics: list[str], read: Counter,
                  whole: bool = True) -> dict[str, Any]:
    """
    Return what the damaged parts of the bag cost: regions, messages and bytes lost.

    ``missing_vs_index`` / ``extra_vs_index`` compare the messages read per input
    topic (decoded or not) with the counts of metadata.yaml or of an intact storage
    index, on every whole read: damaged or not, a bag whose file holds other counts
    than its metadata states is reported. Missing messages are damage; extra ones
    (stale metadata) are reported only.
    """
    regions = reader.damage
    undecodable = sum(reader.skipped.values())
    missing: dict[str, int] = {}
    extra: dict[str, int] = {}
    if whole and reader.counts_trusted:
        for topic in topics:
            got = read[topic] + sum(n for reason, n in reader.skipped.items()
                                    if reason.split(': ', 1)[-1].startswith(topic + ' ('))
            expected = reader.message_count(topic)
            if expected > got:
                missing[topic] = expected - got
            elif got > expected and not regions:
                # (Not past damage: a record walk may salvage what no index counted.)
                extra[topic] = got - expected
    known = [r.messages_lost for r in regions if r.messages_lost is not None]
    return {
        'damaged': bool(regions or undecodable or missing),
        'regions': [r.to_dict() for r in regions],
        'messages_lost': sum(known) + undecodable,
        'messages_lost_unknown': any(r.messages_lost is None for r in regions),
        'messages_salvaged': sum(r.messages_recovered for r in regions),
        'bytes_lost': sum(r.length for r in regions),
        'undecodable': undecodable,
        'missing_vs_index': missing,
        'extra_vs_index': extra,
    }


def format_summary(summary: dict[str, Any]) -> str:
    """Return a human-readable summary of a replay."""
    lines = [f'replayed {summary["input_bag"]} -> {summary["output_bag"]} '
             f'(robot {summary["robot"]}'
             + (f' from {summary["robot_source"]}' if summary.get('robot_source') else '')
             + f', {summary["seconds"]:.2f} s, '
             f'{summary["samples_per_second"] or 0:.0f} samples/s)']
    if summary.get('causal_output_bag'):
        lines.append(f'causal outputs (as --no-smooth writes them): '
                     f'{summary["causal_output_bag"]}')
    lines.append(f'inputs: joint states {summary["joint_states_topic"]}, base '
                 f'{summary["base_topic"]}' + (' (base-driven)' if summary['base_driven']
                                               else ''))
    lines.append('messages in:  ' + ', '.join(f'{k} {v}' for k, v in
                                              sorted(summary['messages_in'].items())))
    lines.append('messages out: ' + ', '.join(f'{k} {v}' for k, v in
                                              sorted(summary['messages_out'].items())))
    rejected = summary['rejected']
    lines.append('rejected: ' + (', '.join(f'{k} {v}' for k, v in sorted(rejected.items()))
                                 if rejected else 'none'))
    mean = ' '.join(f'{v:+.6g}' for v in summary['mu_mean'])
    spread = ' '.join(f'{v:.2e}' for v in summary['mu_spread'])
    lines.append(f'mu mean [{mean}]  spread [{spread}]')
    lines.append(f'events detected: {len(summary["events"])}')
    for event in summary['events']:
        impulse = 'n/a' if event['impulse'] is None else \
            ' '.join(f'{v:+.4g}' for v in event['impulse'])
        lines.append(f'  t={event["start_s"]:.3f} s after start: peak |w| '
                     f'{event["peak_wrench"]:.3g}, impulse [{impulse}]')
    command = summary.get('commanded_wrench')
    if command and command.get('gain') is not None:
        lines.append(f'commanded wrench {command["topic"]} ({command["samples"]} commands): '
                     + ', '.join(f'{axis} gain {_shown(g, ".4f")} +- {gs:.2g} '
                                 f'bias {_shown(b, "+.3g")} +- {bs:.2g}'
                                 for axis, g, gs, b, bs in zip(
                                     command['axes'], command['gain'], command['gain_sigma'],
                                     command['bias'], command['bias_sigma'])))
    residual = summary['prediction_shape_residual_max']
    if summary.get('cyclic_joints'):
        lines.append('second stage (Theorem 57) by the cyclic joints '
                     + ', '.join(summary['cyclic_joints']))
    lines.append(f'predictions: {summary["predictions"]}, shape residual max '
                 + ('n/a' if residual is None else f'{residual:.2e} rad, median '
                    f'{summary["prediction_shape_residual_median"]:.2e} rad'))
    for mode, entry in summary.get('prediction_residuals', {}).items():
        # Prescribed modes are judged by the base path, torque modes by the shape.
        if entry['compared'] == 0:
            lines.append(f'  {mode}: {entry["predictions"]} predictions, none compared')
            continue
        lines.append(
            f'  {mode}: {entry["predictions"]} predictions ({entry["failed"]} stopped), '
            f'judged by the {entry["judged_by"]}: position residual median '
            f'{entry["position_residual_median"]:.2e} m, attitude '
            f'{entry["attitude_residual_median"]:.2e} rad, shape '
            f'{entry["shape_residual_median"]:.2e} rad')
    if summary.get('plots'):
        lines.append('plots: ' + ', '.join(summary['plots']))
    damage = summary.get('damage') or {}
    if damage.get('damaged'):
        lost = f'{damage["messages_lost"]}' + (' + an unknown number'
                                               if damage['messages_lost_unknown'] else '')
        lines.append(f'DAMAGED INPUT: {len(damage["regions"])} damaged region(s), '
                     f'{damage["bytes_lost"]} bytes lost; messages lost {lost} '
                     f'({damage["undecodable"]} undecodable), '
                     f'{damage["messages_salvaged"]} salvaged from damaged regions')
        for region in damage['regions']:
            lines.append('  ' + Damage(**{k: tuple(v) if k == 'rows' and v else v
                                          for k, v in region.items()}).text())
        if damage['missing_vs_index']:
            lines.append('  missing against the bag\'s own counts: ' + ', '.join(
                f'{t} {n}' for t, n in sorted(damage['missing_vs_index'].items())))
    if damage.get('extra_vs_index'):
        lines.append('more messages than the bag\'s own counts (metadata.yaml stale?): '
                     + ', '.join(f'{t} {n}'
                                 for t, n in sorted(damage['extra_vs_index'].items())))
    return '\n'.join(lines)


def _run(args: argparse.Namespace) -> int:
    params = load_params_file(args.params) if args.params else defaults()
    if args.cyclic_joints is not None:
        params['cyclic_joints'] = args.cyclic_joints
    if args.prediction_mode is not None:
        params['prediction_mode'] = args.prediction_mode
    robot = load_robot_from_params(params, args.urdf, args.base_joint, args.gravity,
                                   args.xacro_arg)
    payload_file = args.payload or params.get('payload_file')
    if payload_file:
        from reduced_dynamics.payload import load_payload, with_payload
        robot = with_payload(robot, load_payload(payload_file,
                                                 params.get('payload_link') or None))
    options = ReplayOptions(params=params, joint_states_topic=args.joint_states_topic,
                            odom_topic=args.odom_topic, base_pose_topic=args.base_pose_topic,
                            trajectory_topic=args.trajectory_topic,
                            commanded_wrench_topic=args.commanded_wrench_topic,
                            start=args.start, end=args.end, plots_dir=args.plots,
                            overwrite=args.overwrite, strict=args.strict,
                            smooth=not args.no_smooth, causal_out=args.causal_output,
                            base_driven=args.base_driven,
                            fixed_lag=args.fixed_lag, thruster_map=args.thruster_map,
                            robot_source=robot_source(params, args.urdf),
                            progress=None if args.quiet else sys.stderr)
    try:
        check_parameter('smoothing_lag', args.fixed_lag)
    except ValueError as error:
        print(f'reduced-dynamics replay: error: --fixed-lag: {error}', file=sys.stderr)
        return 2
    if args.causal_output is not None:
        try:
            _check_causal_out(args.output, options)
        except ValueError as error:
            print(f'reduced-dynamics replay: error: --causal-output: {error}', file=sys.stderr)
            return 2
    existed = {path: os.path.exists(path) for path in (args.output, args.causal_output)
               if path is not None}
    for path, exists in existed.items():
        if exists and not args.overwrite:
            # Before reading the bag; the library's own message names its Python argument.
            print(f'reduced-dynamics replay: error: output {path} exists already '
                  '(pass --overwrite to replace it)', file=sys.stderr)
            return 2
    try:
        summary = replay(args.bag, args.output, robot, options)
    except BagError as error:
        if options.strict:
            for path, exists in existed.items():
                if not exists and os.path.isdir(path):
                    shutil.rmtree(path, ignore_errors=True)  # no half-written output
        print(f'reduced-dynamics replay: error: {error}', file=sys.stderr)
        return 2
    print(format_summary(summary))
    if args.summary_json:
        with open(args.summary_json, 'w', encoding='utf-8') as stream:
            json.dump(summary, stream, indent=2)
    return EXIT_DAMAGED if summary['damage']['damaged'] else 0


def register_command(commands: Any) -> None:
    """Add the ``replay`` subcommand."""
    from reduced_dynamics.cli import add_robot_arguments
    parser = commands.add_parser('replay', help='run the estimator over a recorded bag')
    parser.add_argument('bag', help='rosbag2 directory (MCAP or sqlite3) or .mcap file')
    parser.add_argument('-o', '--output', required=True, help='output bag directory')
    add_robot_arguments(parser)
    parser.add_argument('--params', help='parameters YAML (the node\'s format)')
    parser.add_argument('--payload', metavar='YAML',
                        help='the robot holds this payload (reduced-dynamics identify -o; '
                             'default: the payload_file parameter)')
    parser.add_argument('--joint-states-topic')
    parser.add_argument('--trajectory-topic',
                        help='trajectory_msgs/JointTrajectory topic of planned arm motions '
                             '(default: the trajectory_topic parameter, used when present)')
    parser.add_argument('--commanded-wrench-topic', metavar='T',
                        help='geometry_msgs/WrenchStamped topic of the commanded body wrench '
                             '(thrusters): estimate its per-axis gain and bias and the '
                             'disturbance beyond it (default: the commanded_wrench_topic '
                             'parameter, empty = off; never auto-detected)')
    group = parser.add_mutually_exclusive_group()
    group.add_argument('--odom-topic')
    group.add_argument('--base-pose-topic')
    parser.add_argument('--cyclic-joints', metavar='NAMES',
                        help='second-stage reduction: "auto" or comma-separated cyclic '
                             'joints (overrides the parameters file)')
    parser.add_argument('--prediction-mode',
                        choices=('planned', 'coast', 'held_velocity', 'held_torque'),
                        help='what the arm does over a prediction (overrides the parameters '
                             'file; default planned, held_velocity while there is no plan)')
    parser.add_argument('--start', type=float, help='seconds from the bag start')
    parser.add_argument('--end', type=float, help='seconds from the bag start')
    parser.add_argument('--plots', metavar='DIR', help='write PNG plots into DIR')
    parser.add_argument('--thruster-map', metavar='FILE',
                        help='command mapping YAML whose thruster command the plots draw '
                             '(default: config/thrusters/freeflyer2.yaml when the bag has '
                             'its topic)')
    parser.add_argument('--summary-json', metavar='FILE', help='write the summary as JSON')
    parser.add_argument('--overwrite', action='store_true', help='replace an existing output')
    parser.add_argument('--strict', action='store_true',
                        help='refuse a damaged bag (truncated or corrupted storage, messages '
                             'that do not deserialize) instead of replaying what is intact '
                             f'and exiting {EXIT_DAMAGED}')
    parser.add_argument('--quiet', action='store_true', help='no progress display')
    parser.add_argument('--base-driven', action='store_true',
                        help='one estimate per base sample, the shape held from the latest '
                             'joint state (at zero when the bag has none); without it a '
                             'jointed robot needs the bag\'s JointState topic')
    parser.add_argument('--no-smooth', action='store_true',
                        help='write the causal filter\'s estimates, exactly what the node '
                             'publishes (default: fixed-interval RTS smoothing over the bag)')
    parser.add_argument('--causal-output', metavar='DIR',
                        help='also write the causal estimates (what --no-smooth writes) into '
                             'the bag DIR, from the same pass: both in one replay')
    parser.add_argument('--fixed-lag', type=float, default=0.0, metavar='S',
                        help='also write the node\'s fixed-lag smoothed topics '
                             '(momentum_smoothed, drift/momentum_rate_smoothed) at a lag of S '
                             'seconds, as its smoothing_lag parameter (default 0: not written)')
    parser.set_defaults(func=_run)


def _shown(value, spec: str) -> str:
    """Return a gain or bias formatted by ``spec``, or 'unidentified' as it is."""
    return value if isinstance(value, str) else format(value, spec)
