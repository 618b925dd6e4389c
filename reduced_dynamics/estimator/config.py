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
    'observer_bandwidth': ParameterSpec(50.0, 0.1, 1000.0, (),
                                        'bandwidth K [rad/s] of the momentum observer: the '
                                        'external-wrench estimate r obeys dr/dt = K (w - r)'),
    'event_threshold': ParameterSpec(1.0, 1e-9, 1e6, (),
                                     'norm of the estimated external wrench [N, N m] above '
                                     'which a thruster/contact event is flagged'),
    'event_hold': ParameterSpec(0.1, 0.0, 10.0, (),
                                'quiet time [s] below half the threshold before an event '
                                'ends and the model is re-reduced at the new momentum'),
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
    'diagnostics_rate': ParameterSpec(1.0, 0.0, 100.0, (),
                                      'diagnostics messages per second of stamp time (0: off)'),
}


@dataclass
class EstimatorConfig:
    """Settings of :class:`reduced_dynamics.estimator.Estimator` (see :data:`PARAMETERS`)."""

    world_frame: str = PARAMETERS['world_frame'].default
    sync_tolerance: float = PARAMETERS['sync_tolerance'].default
    observer_bandwidth: float = PARAMETERS['observer_bandwidth'].default
    event_threshold: float = PARAMETERS['event_threshold'].default
    event_hold: float = PARAMETERS['event_hold'].default
    prediction_rate: float = PARAMETERS['prediction_rate'].default
    prediction_horizon: float = PARAMETERS['prediction_horizon'].default
    prediction_step: float = PARAMETERS['prediction_step'].default
    prediction_integrator: str = PARAMETERS['prediction_integrator'].default
    prediction_tolerance: float = PARAMETERS['prediction_tolerance'].default
    diagnostics_rate: float = PARAMETERS['diagnostics_rate'].default

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
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueError(f'{name} must be a number, got {value!r}')
    if not spec.low <= float(value) <= spec.high:
        raise ValueError(f'{name} = {value} is outside [{spec.low}, {spec.high}]')
