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

"""Robots shared by the model tests: paper robot, random tree, planar testbed."""

import functools

import numpy as np

from reduced_dynamics.resources import config_path
from reduced_dynamics.robot.model import load_robot
from reduced_dynamics.robot.random_tree import random_tree_urdf


@functools.lru_cache(maxsize=None)
def paper_robot():
    """Return the paper's case study (section 6) on a floating base."""
    return load_robot()


@functools.lru_cache(maxsize=None)
def tree_robot():
    """Return a random 7-joint tree with a prismatic joint on a floating base."""
    return load_robot(random_tree_urdf(7, seed=3))


@functools.lru_cache(maxsize=None)
def planar_robot():
    """Return the air-bearing testbed: planar base, gravity normal to the plane."""
    return load_robot(config_path('robots/planar_testbed.urdf'), 'planar',
                      np.array([0.0, 0.0, -9.81]))


ROBOTS = {'paper': paper_robot, 'tree': tree_robot, 'planar': planar_robot}
