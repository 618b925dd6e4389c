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
A recorder process of the DDS tests: raw CDR of some topics, to a JSON file.

``python test/dds_recorder.py OUT.json TOPIC:TYPE[:COUNT] ... [--exclude TEXT]``

Subscribes (reliable, keep all, volatile) to each topic with ``raw=True``, prints
``ready`` once every subscription is matched by a publisher, ``recorded N on TOPIC``
every PROGRESS_EVERY messages of a topic, and writes
``{topic: [hex of each message]}`` to OUT.json when each topic with a COUNT has at
least that many messages, or at SIGINT/SIGTERM (the test's failure guard).
Messages containing ``--exclude`` bytes (e.g. the node's own status name) are
dropped. A process of its own: one process both publishing and recording lost
most of the outputs on a loaded machine.
"""

import argparse
import importlib
import json
import signal
import sys

import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions

#: A line ``recorded N on TOPIC`` every this many messages of a topic: the test's guard
#: waits while the recorder makes progress (a loaded machine is slow, a lost message stops).
PROGRESS_EVERY = 256


def _class(msgtype: str) -> type:
    package, sub, name = msgtype.split('/')
    return getattr(importlib.import_module(f'{package}.{sub}'), name)


def main() -> int:
    """Record until the wanted counts are in or a signal comes; write the file."""
    parser = argparse.ArgumentParser()
    parser.add_argument('output')
    parser.add_argument('topics', nargs='+', help='TOPIC:TYPE[:COUNT]')
    parser.add_argument('--exclude', default='')
    args = parser.parse_args()
    stopping = []
    signal.signal(signal.SIGINT, lambda *_: stopping.append(True))
    signal.signal(signal.SIGTERM, lambda *_: stopping.append(True))
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node('dds_recorder')
    qos = QoSProfile(history=HistoryPolicy.KEEP_ALL, depth=1,
                     reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.VOLATILE)
    got: dict = {}
    wanted: dict = {}
    subscriptions = []
    exclude = args.exclude.encode()
    for spec in args.topics:
        topic, msgtype, *count = spec.split(':')
        got[topic] = []
        if count:
            wanted[topic] = int(count[0])

        def keep(data: bytes, topic: str = topic) -> None:
            if not exclude or exclude not in data:
                got[topic].append(data.hex())
                if len(got[topic]) % PROGRESS_EVERY == 0:
                    print(f'recorded {len(got[topic])} on {topic}', flush=True)
        subscriptions.append(node.create_subscription(_class(msgtype), topic, keep, qos,
                                                      raw=True))
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    ready = False
    try:
        while not stopping:
            executor.spin_once(timeout_sec=0.05)
            if not ready and all(s.get_publisher_count() for s in subscriptions):
                ready = True
                print('ready', flush=True)
            if wanted and all(len(got[t]) >= n for t, n in wanted.items()):
                break
    except ExternalShutdownException:
        pass
    with open(args.output, 'w') as stream:
        json.dump(got, stream)
    executor.shutdown()
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


if __name__ == '__main__':
    sys.exit(main())
