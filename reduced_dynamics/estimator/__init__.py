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

"""The estimator pipeline shared by the replay tool and the node (ROS-free)."""

from typing import Any

__all__ = ['Estimator', 'EstimatorConfig', 'EstimatorOutput']

#: Names re-exported from their modules, imported on first use: a submodule (e.g.
#: base_motion for ``reduced-dynamics predict``) must not pull in the whole pipeline.
_EXPORTS = {'Estimator': 'pipeline', 'EstimatorOutput': 'pipeline', 'EstimatorConfig': 'config'}


def __getattr__(name: str) -> Any:
    """Import ``Estimator``, ``EstimatorConfig`` and ``EstimatorOutput`` on first use."""
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f'module {__name__!r} has no attribute {name!r}')
    from importlib import import_module
    return getattr(import_module(f'{__name__}.{module}'), name)
