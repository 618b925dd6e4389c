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

"""Rosbag2 reading (directory, bare .mcap, .db3) and writing (MCAP) without ROS."""

from reduced_dynamics.bag.errors import BagError
from reduced_dynamics.bag.reader import BagMessage, BagReader, open_bag, RawBagMessage
from reduced_dynamics.bag.writer import BagWriter, default_qos, QOS_DEFAULT, QOS_LATCHED

__all__ = [
    'BagError',
    'BagMessage',
    'BagReader',
    'BagWriter',
    'QOS_DEFAULT',
    'QOS_LATCHED',
    'RawBagMessage',
    'default_qos',
    'open_bag',
]
