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

"""Lie-group geometry of the base: displacement subgroups, isotropy, coset charts."""

from reduced_dynamics.geometry.chart import CosetChart
from reduced_dynamics.geometry.isotropy import isotropy_algebra, IsotropyAlgebra, MomentumClass
from reduced_dynamics.geometry.lie_group import BaseGroup, SUBGROUPS

__all__ = [
    'BaseGroup', 'CosetChart', 'IsotropyAlgebra', 'MomentumClass', 'SUBGROUPS',
    'isotropy_algebra',
]
