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
Settings of the estimator pipeline, with units, ranges and documentation.

One table serves the dataclass defaults, the node's ParameterDescriptors and
the params YAML: :data:`PARAMETERS`.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any, Mapping, NamedTuple, Optional


class ParameterSpec(NamedTuple):
    """A tunable setting: default, inclusive range (numbers) or choices, meaning."""

    default: Any
    low: Optional[float]
    high: Optional[float]
    choices: tuple
    description: str


PARAMETERS: dict[str, ParameterSpec] = {
    'world_frame': ParameterSpec('world', None, None, (),
                                 'frame_id of world-frame outputs (momentum, paths)'),
    'sync_tolerance': ParameterSpec(0.02, 1e-4, 1.0, (),
                                    'largest gap [s] between a joint-state stamp and the '
                                    'nearest base sample; beyond it the sample is rejected '
                                    'as stale'),
    # Kalman filter (estimator/filter.py); README "The filter". Sensor noise as
    # standard deviations, process noise as densities, all in physical units.
    'pose_position_noise': ParameterSpec(
        5e-4, 1e-12, 1e3, (),
        'standard deviation [m] of a measured base position (motion capture: 0.5 mm, '
        'sub-millimetre class)'),
    'pose_angle_noise': ParameterSpec(
        2e-3, 1e-12, 3.2, (),
        'standard deviation [rad] of a measured base orientation, per axis (motion '
        'capture: ~0.1 deg)'),
    'pose_stamp_noise': ParameterSpec(
        3e-3, 0.0, 1.0, (),
        'standard deviation [s] of a base pose header stamp about the instant the pose was '
        'measured (a mocap client stamping on receipt in a 100 Hz polling loop: 10 ms / '
        'sqrt(12)); the pose noise grows by the body twist times it'),
    'pose_retiming': ParameterSpec(
        'auto', None, None, ('auto', 'on', 'off'),
        'causal re-timing of a periodic pose source stamped on receipt (estimator/'
        'retiming.py): each pose gets the frame time of the lower envelope of its stamps; '
        'auto where the stream shows the signature (consecutive frames, bursts of frames '
        'delivered by one poll), on without the burst test, off keeps every stamp'),
    'pose_retimed_stamp_noise': ParameterSpec(
        5e-4, 0.0, 1.0, (),
        'standard deviation [s] of a re-timed pose stamp about its frame time (transport '
        'jitter of the frames against the envelope, sub-millisecond on a LAN); at most '
        'pose_stamp_noise is used'),
    'use_message_covariance': ParameterSpec(
        True, None, None, (),
        'use the covariance an input message carries (nav_msgs/Odometry pose and twist, '
        'geometry_msgs/PoseWithCovarianceStamped) as that sample\'s measurement noise; '
        'the noise parameters stay the fallback for a zero or unknown (-1) covariance and '
        'for a bad one (counted, docs/message_covariance.md); false: the parameters only'),
    'twist_linear_noise': ParameterSpec(
        1e-2, 1e-12, 1e3, (),
        'standard deviation [m/s] of an Odometry base linear velocity'),
    'twist_angular_noise': ParameterSpec(
        1e-2, 1e-12, 1e3, (),
        'standard deviation [rad/s] of an Odometry base angular velocity'),
    'joint_velocity_noise': ParameterSpec(
        1e-2, 0.0, 1e3, (),
        'standard deviation [rad/s or m/s] of a measured joint velocity (enters the base '
        'motion through the connection A)'),
    'wrench_jerk_linear': ParameterSpec(
        0.05, 1e-9, 1e6, (),
        'random-walk density [m/s^3/sqrt(Hz)] of the external force per unit mass: the '
        'external wrench w is a random walk whose body-frame acceleration changes by about '
        'this much in one second (scaled by the locked inertia, so one value fits any mass)'),
    'wrench_jerk_angular': ParameterSpec(
        0.25, 1e-9, 1e6, (),
        'random-walk density [rad/s^3/sqrt(Hz)] of the external torque per unit inertia '
        '(the linear density over a 0.2 m lever arm)'),
    # Commanded wrench (estimator/filter.py, README "Commanded wrench"): used only with
    # a commanded_wrench_topic.
    'command_gain_sigma': ParameterSpec(
        0.5, 1e-6, 10.0, (),
        'prior standard deviation of the per-axis gain (delivered / commanded wrench, '
        'prior mean 1) of the commanded wrench'),
    'command_gain_drift': ParameterSpec(
        2e-3, 0.0, 10.0, (),
        'random-walk density [1/sqrt(s)] of the gain of the commanded wrench (thruster '
        'wear: 0.1 in ~40 min); the bias drifts at this rate relative to its prior'),
    'command_bias_linear': ParameterSpec(
        5e-3, 1e-9, 1e3, (),
        'prior standard deviation [m/s^2] of the bias of the delivered body force per '
        'unit mass (leak, tilted table: 0.5 mrad of tilt; scaled by the locked inertia)'),
    'command_bias_angular': ParameterSpec(
        2.5e-2, 1e-9, 1e4, (),
        'prior standard deviation [rad/s^2] of the bias of the delivered body torque per '
        'unit inertia (the linear value over a 0.2 m lever arm)'),
    'disturbance_jerk_linear': ParameterSpec(
        1e-3, 1e-9, 1e6, (),
        'with a commanded wrench, the random-walk density [m/s^3/sqrt(Hz)] of the '
        'disturbance beyond the command per unit mass, in place of wrench_jerk_linear: '
        'the command carries the thruster switching, what is left changes slowly (table '
        'tilt, drag, cable: 0.01 m/s^2 in 100 s)'),
    'disturbance_jerk_angular': ParameterSpec(
        5e-3, 1e-9, 1e6, (),
        'with a commanded wrench, the random-walk density [rad/s^3/sqrt(Hz)] of the '
        'disturbance torque per unit inertia (the linear value over a 0.2 m lever arm)'),
    'command_acceleration_bound': ParameterSpec(
        1e3, 1e-3, 1e9, (),
        'a commanded wrench whose body acceleration I^-1 u (locked inertia at zero shape) '
        'exceeds this [m/s^2 or rad/s^2] on some axis is rejected (command_bound)'),
    'innovation_gate': ParameterSpec(
        1e-6, 0.0, 0.5, (),
        'false-alarm probability of the innovation chi-square gate: a base measurement '
        'less likely than this under the filter is rejected (innovation_gate), 3 in a '
        'row are accepted as a momentum jump (0: gate off)'),
    'event_significance': ParameterSpec(
        1e-6, 0.0, 0.5, (),
        'false-alarm probability per sample of the event tests: w^T P_ww^-1 w > chi2_n '
        'quantile, or the GLR statistic of a wrench step on the innovations above it (the '
        'step is then taken at once); a thruster/contact event starts on either '
        '(dimensionless, the same at any mass; 0: no events)'),
    'event_false_alarm_rate': ParameterSpec(
        1.0, 0.0, 3600.0, (),
        'false alarms per hour of the multi-scale event test (the filtered momentum\'s '
        'change over windows of 0.05-3 s against no wrench; its per-window, per-update '
        'significance is derived from it and the update rate; 0: off)'),
    'event_hold': ParameterSpec(0.1, 0.0, 10.0, (),
                                'quiet time [s] with w consistent with zero (chi-square '
                                'below its 99 % quantile) before an event ends and the model '
                                'is re-reduced at the new momentum'),
    'smoothing_lag': ParameterSpec(0.5, 0.0, 10.0, (),
                                   'online fixed-lag RTS smoothing (estimator/fixed_lag.py): '
                                   'momentum and momentum rate smoothed over at least this '
                                   'much [s] of later data, on ~/momentum_smoothed and '
                                   '~/drift/momentum_rate_smoothed stamped with the time '
                                   'they describe (0: off)'),
    'prediction_rate': ParameterSpec(1.0, 0.0, 100.0, (),
                                     'predictions per second of stamp time (0: off)'),
    'prediction_horizon': ParameterSpec(2.0, 0.0, 60.0, (), 'prediction horizon [s]'),
    'prediction_step': ParameterSpec(0.05, 1e-3, 1.0, (),
                                     'spacing [s] of predicted points (and the fixed step of '
                                     'the discrete-gradient integrator)'),
    'prediction_integrator': ParameterSpec('dop853', None, None,
                                           ('dop853', 'discrete_gradient'),
                                           'adaptive DOP853 (accuracy) or the energy-'
                                           'preserving discrete gradient (fixed step)'),
    'prediction_tolerance': ParameterSpec(1e-10, 1e-13, 1e-3, (),
                                          'relative and absolute tolerance of DOP853'),
    'prediction_mode': ParameterSpec(
        'planned', None, None, ('planned', 'coast', 'held_velocity', 'held_torque'),
        'what the arm does over a prediction: planned (follows the latest planned '
        'trajectory; held_velocity while there is none), coast (zero joint torques), '
        'held_velocity (joint velocities kept), held_torque (the estimated joint torques '
        'kept: held_torque_follow_time)'),
    'prediction_max_evaluations': ParameterSpec(
        20000.0, 10.0, 1e8, (),
        'budget of right-hand-side evaluations of one prediction (a 2 s horizon at '
        'tolerance 1e-10 takes 100-600); a prediction that exceeds it stops with the reason '
        'in diagnostics; a ~/predict_base_motion request gets it per prediction_horizon of '
        'its plan'),
    'prediction_max_wall_time': ParameterSpec(
        0.5, 0.0, 600.0, (),
        'budget of wall time [s] of one prediction (half the default prediction period); '
        'a prediction that exceeds it stops with the reason in diagnostics (0: none, only '
        'the evaluation budget; replay always runs so, its outputs must not depend on the '
        'machine\'s load); a ~/predict_base_motion request gets 4 times it per '
        'prediction_horizon of its plan'),
    'prediction_covariance': ParameterSpec(
        True, None, None, (),
        'propagate the start\'s uncertainty (filter covariance of pose, momentum and wrench; '
        'joint noise; held torque) through each prediction: ~/prediction/base_at_horizon, '
        '~/prediction/covariance_ellipsoids, ~/prediction/shape_covariance '
        '(docs/prediction_uncertainty.md)'),
    'joint_position_noise': ParameterSpec(
        1e-3, 0.0, 1e3, (),
        'standard deviation [rad or m] of a measured joint position (a prediction\'s '
        'start uncertainty)'),
    'joint_effort_noise': ParameterSpec(
        1e-2, 1e-9, 1e6, (),
        'standard deviation [N m or N] of a measured joint effort (the held-torque '
        'estimate of prediction_mode held_torque)'),
    'held_torque_follow_time': ParameterSpec(
        4.0, 1e-3, 1e4, (),
        'time constant [s] with which the held-torque estimate follows a slow change of the '
        'measured efforts (a local-level Kalman filter: its variance is about '
        'joint_effort_noise^2 dt / T); a change far beyond the noise is taken at once '
        '(CUSUM test)'),
    'diagnostics_rate': ParameterSpec(1.0, 0.0, 100.0, (),
                                      'diagnostics messages per second of stamp time (0: off)'),
    # Input gates (estimator/stamps.py, estimator/plausibility.py); README "Bad input".
    'stamp_outlier_tolerance': ParameterSpec(
        1.0, 1e-3, 3600.0, (),
        'largest departure [s] of a header stamp from its stream\'s clock (the receive time '
        'when known, else the previous stamp; at least 4 local periods) before it is held '
        'as an outlier; 3 consistent outliers in a row are a clock jump and are followed'),
    'joint_limit_margin': ParameterSpec(
        0.5, 0.0, 1e6, (),
        'joint positions beyond the URDF limits by more than this [rad or m] are rejected'),
    'limit_factor': ParameterSpec(
        10.0, 1.0, 1e6, (),
        'joint velocities and efforts above this multiple of the URDF velocity and effort '
        'limits are rejected'),
    'joint_position_bound': ParameterSpec(
        1e6, 1.0, 1e12, (),
        'largest absolute position [rad or m] of a joint without URDF position limits '
        '(continuous joints: unwrapped angles)'),
    'joint_velocity_bound': ParameterSpec(
        1e3, 1e-3, 1e9, (),
        'largest absolute velocity [rad/s or m/s] of a joint without a URDF velocity limit'),
    'joint_effort_bound': ParameterSpec(
        1e5, 1e-3, 1e12, (),
        'largest absolute effort [N m or N] of a joint without a URDF effort limit'),
    'quaternion_norm_tolerance': ParameterSpec(
        0.01, 1e-9, 1.0, (),
        'largest deviation from 1 of the base orientation quaternion\'s norm; within it '
        'the quaternion is normalised, beyond it the base sample is rejected'),
    'base_position_bound': ParameterSpec(
        1e9, 1.0, 1e15, (),
        'largest distance [m] of the base from the world origin'),
    'base_speed_bound': ParameterSpec(
        2e4, 1e-3, 1e9, (),
        'largest linear speed [m/s] of an Odometry base twist'),
    'base_rate_bound': ParameterSpec(
        35.0, 1e-3, 1e6, (),
        'largest angular rate [rad/s] of an Odometry base twist'),
}


@dataclass
class EstimatorConfig:
    """Settings of :class:`reduced_dynamics.estimator.Estimator` (see :data:`PARAMETERS`)."""

    world_frame: str = PARAMETERS['world_frame'].default
    sync_tolerance: float = PARAMETERS['sync_tolerance'].default
    pose_position_noise: float = PARAMETERS['pose_position_noise'].default
    pose_angle_noise: float = PARAMETERS['pose_angle_noise'].default
    pose_stamp_noise: float = PARAMETERS['pose_stamp_noise'].default
    pose_retiming: str = PARAMETERS['pose_retiming'].default
    pose_retimed_stamp_noise: float = PARAMETERS['pose_retimed_stamp_noise'].default
    use_message_covariance: bool = PARAMETERS['use_message_covariance'].default
    twist_linear_noise: float = PARAMETERS['twist_linear_noise'].default
    twist_angular_noise: float = PARAMETERS['twist_angular_noise'].default
    joint_velocity_noise: float = PARAMETERS['joint_velocity_noise'].default
    wrench_jerk_linear: float = PARAMETERS['wrench_jerk_linear'].default
    wrench_jerk_angular: float = PARAMETERS['wrench_jerk_angular'].default
    command_gain_sigma: float = PARAMETERS['command_gain_sigma'].default
    command_gain_drift: float = PARAMETERS['command_gain_drift'].default
    command_bias_linear: float = PARAMETERS['command_bias_linear'].default
    command_bias_angular: float = PARAMETERS['command_bias_angular'].default
    disturbance_jerk_linear: float = PARAMETERS['disturbance_jerk_linear'].default
    disturbance_jerk_angular: float = PARAMETERS['disturbance_jerk_angular'].default
    command_acceleration_bound: float = PARAMETERS['command_acceleration_bound'].default
    innovation_gate: float = PARAMETERS['innovation_gate'].default
    event_significance: float = PARAMETERS['event_significance'].default
    event_false_alarm_rate: float = PARAMETERS['event_false_alarm_rate'].default
    event_hold: float = PARAMETERS['event_hold'].default
    smoothing_lag: float = PARAMETERS['smoothing_lag'].default
    prediction_rate: float = PARAMETERS['prediction_rate'].default
    prediction_horizon: float = PARAMETERS['prediction_horizon'].default
    prediction_step: float = PARAMETERS['prediction_step'].default
    prediction_integrator: str = PARAMETERS['prediction_integrator'].default
    prediction_tolerance: float = PARAMETERS['prediction_tolerance'].default
    prediction_mode: str = PARAMETERS['prediction_mode'].default
    prediction_max_evaluations: float = PARAMETERS['prediction_max_evaluations'].default
    prediction_max_wall_time: float = PARAMETERS['prediction_max_wall_time'].default
    prediction_covariance: bool = PARAMETERS['prediction_covariance'].default
    joint_position_noise: float = PARAMETERS['joint_position_noise'].default
    joint_effort_noise: float = PARAMETERS['joint_effort_noise'].default
    held_torque_follow_time: float = PARAMETERS['held_torque_follow_time'].default
    diagnostics_rate: float = PARAMETERS['diagnostics_rate'].default
    stamp_outlier_tolerance: float = PARAMETERS['stamp_outlier_tolerance'].default
    joint_limit_margin: float = PARAMETERS['joint_limit_margin'].default
    limit_factor: float = PARAMETERS['limit_factor'].default
    joint_position_bound: float = PARAMETERS['joint_position_bound'].default
    joint_velocity_bound: float = PARAMETERS['joint_velocity_bound'].default
    joint_effort_bound: float = PARAMETERS['joint_effort_bound'].default
    quaternion_norm_tolerance: float = PARAMETERS['quaternion_norm_tolerance'].default
    base_position_bound: float = PARAMETERS['base_position_bound'].default
    base_speed_bound: float = PARAMETERS['base_speed_bound'].default
    base_rate_bound: float = PARAMETERS['base_rate_bound'].default

    def __post_init__(self) -> None:
        """Validate every field against its range or choices."""
        for item in fields(self):
            check_parameter(item.name, getattr(self, item.name))

    @classmethod
    def from_mapping(cls, values: Mapping[str, Any]) -> 'EstimatorConfig':
        """Build from a mapping, ignoring keys that are not estimator settings."""
        known = {f.name for f in fields(cls)}
        return cls(**{k: v for k, v in values.items() if k in known})

    def replaced(self, **changes: Any) -> 'EstimatorConfig':
        """Return a validated copy with some fields changed."""
        values = {f.name: getattr(self, f.name) for f in fields(self)}
        values.update(changes)
        return EstimatorConfig(**values)


def check_parameter(name: str, value: Any) -> None:
    """Raise ValueError unless ``value`` is acceptable for estimator setting ``name``."""
    spec = PARAMETERS.get(name)
    if spec is None:
        raise ValueError(f'unknown estimator parameter {name!r}')
    if isinstance(spec.default, str):
        if not isinstance(value, str):
            raise ValueError(f'{name} must be a string, got {value!r}')
        if spec.choices and value not in spec.choices:
            raise ValueError(f'{name} must be one of {spec.choices}, got {value!r}')
        return
    if isinstance(spec.default, bool):
        if not isinstance(value, bool):
            raise ValueError(f'{name} must be true or false, got {value!r}')
        return
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueError(f'{name} must be a number, got {value!r}')
    if not spec.low <= float(value) <= spec.high:
        raise ValueError(f'{name} = {value} is outside [{spec.low}, {spec.high}]')
