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
The filter core: arrays in, arrays out (no messages, no ROS, no bags).

:mod:`.lie` has the base group's maps, :mod:`.kernels` the compiled propagation
and update, :mod:`.smoother` the compiled RTS backward pass. Every function is a
numba ``@njit(cache=True)`` function; its ``py_func`` is the same source run by
the interpreter (the reference the tests compare with, docs/estimator_core.md).
"""
