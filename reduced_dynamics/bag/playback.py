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
The ROS-free half of ``reduced-dynamics play``: what to publish, and when.

A bag is played as ``ros2 bag play`` does: each message at its log time, scaled by
the rate, relative to when playback starts (after a pause, time stands still).
This module chooses the messages (topic filter, loops), keeps the schedule
(:class:`PlaybackClock`: bag time <-> monotonic time, pause, resume, rate) and
moves header stamps to now (:func:`shift_stamps`). Publishing over DDS is the
shell's (:mod:`reduced_dynamics.player_node`); it hands in a ``publish``
function, so everything here runs and is tested without rclpy.
"""

from collections.abc import Callable
import dataclasses
from dataclasses import dataclass
import math
import threading
import time
from typing import Any, Optional

from reduced_dynamics.bag.errors import BagError
from reduced_dynamics.bag.reader import BagReader, open_bag, RawBagMessage

NS_PER_S = 1_000_000_000
_INT32_MAX = 2**31 - 1
#: /clock rate of ``ros2 bag play --clock`` without a value (rosbag2's default).
DEFAULT_CLOCK_HZ = 40.0
#: Default history depth of the players' publishers (0 would mean keep all).
DEFAULT_QOS_DEPTH = 1000


@dataclass(frozen=True)
class PlayOptions:
    """What ``reduced-dynamics play`` does (its command-line options)."""

    bag: str
    rate: float = 1.0
    topics: tuple[str, ...] = ()  # empty: every topic of the bag
    loop: bool = False
    start_paused: bool = False
    clock_hz: float = 0.0  # 0: no /clock
    restamp: bool = False
    wait_for_subscribers: tuple[str, ...] = ()
    qos_depth: int = DEFAULT_QOS_DEPTH  # 0: keep all
    wait_timeout: float = 0.0  # seconds waiting for subscribers, 0: for ever
    ack_timeout: float = 30.0  # seconds waiting at the end for acknowledgements, 0: for ever
    remap: tuple[tuple[str, str], ...] = ()  # (bag topic, published topic)

    def problems(self) -> list[str]:
        """Return what is wrong with the options (empty when usable)."""
        out = []
        if not (math.isfinite(self.rate) and self.rate > 0):
            out.append(f'--rate must be a positive number, got {self.rate}')
        if not (math.isfinite(self.clock_hz) and self.clock_hz >= 0):
            out.append(f'--clock must be a positive rate in Hz, got {self.clock_hz}')
        if self.qos_depth < 0:
            out.append(f'--qos-depth must be >= 0 (0: keep all), got {self.qos_depth}')
        if not (math.isfinite(self.wait_timeout) and self.wait_timeout >= 0):
            out.append(f'--wait-timeout must be >= 0 s, got {self.wait_timeout}')
        if not (math.isfinite(self.ack_timeout) and self.ack_timeout >= 0):
            out.append(f'--ack-timeout must be >= 0 s, got {self.ack_timeout}')
        for source, target in self.remap:
            if not source or not target:
                out.append(f'--remap takes FROM:=TO, got {source}:={target}')
        return out

    def published_name(self, topic: str) -> str:
        """Return the name ``topic`` is published under (after --remap)."""
        return dict(self.remap).get(topic, topic)


def parse_remap(text: str) -> tuple[str, str]:
    """Split ``FROM:=TO`` (ValueError otherwise)."""
    source, sep, target = text.partition(':=')
    if not sep or not source.strip() or not target.strip():
        raise ValueError(f'--remap takes FROM:=TO, got {text!r}')
    return source.strip(), target.strip()


def played_topics(reader: BagReader, options: PlayOptions) -> dict[str, str]:
    """Return ``{topic: msgtype}`` to play (ValueError naming topics not in the bag)."""
    available = reader.topics()
    if not options.topics:
        return dict(available)
    missing = sorted(set(options.topics) - set(available))
    if missing:
        raise ValueError(f'topics not in bag {reader.path}: {missing}; '
                         f'available: {sorted(available)}')
    return {t: available[t] for t in options.topics}


def definition_problems(reader: BagReader, topics: dict[str, str]) -> dict[str, str]:
    """
    Return ``{topic: reason}`` for topics recorded with another definition than Jazzy's.

    The raw bytes of such a topic would not decode as the installed (Jazzy) type: a bag
    from another distribution whose message changed, or a type of the same name
    defined differently. Found by the type hash (RIHS01) the bag records against the
    ROS 2 Jazzy definition (Iron-era and later bags record one; older bags cannot be
    checked, nor can types Jazzy does not define).
    """
    out = {}
    for topic, msgtype in topics.items():
        try:
            store = reader.typestore_for(topic, msgtype)
        except BagError:
            continue  # no definition in the bag and not a Jazzy type: nothing to check
        if store is not reader.typestore:
            out[topic] = (f'the bag defines {msgtype} differently from ROS 2 Jazzy '
                          '(its type hash differs): its bytes would not decode as the '
                          'installed type')
    return out


class PlaybackClock:
    """
    Bag time against a monotonic clock: anchored at a start, scaled by the rate.

    While running, bag time ``b`` is due at ``wall0 + (b - bag0) / rate``; a pause
    freezes bag time and a resume re-anchors it at the moment of resuming, so no
    message is published in a burst to catch up. ``now_ns`` is injectable for tests.
    Waiters are woken by pause, resume and stop (a Condition), never by polling.
    """

    def __init__(self, bag_start_ns: int, rate: float = 1.0, *, paused: bool = False,
                 now_ns: Callable[[], int] = time.monotonic_ns) -> None:
        """Start at ``bag_start_ns`` (paused, or running from now)."""
        self.rate = float(rate)
        self._now_ns = now_ns
        self._changed = threading.Condition()
        self._bag0 = int(bag_start_ns)
        self._wall0 = now_ns()
        self.paused = paused
        self.stopped = False

    def now_ns(self) -> int:
        """Return the monotonic time the schedule uses."""
        return self._now_ns()

    def _bag_time(self) -> int:
        """Return the bag time of now (callers hold the lock)."""
        if self.paused:
            return self._bag0
        return self._bag0 + round((self._now_ns() - self._wall0) * self.rate)

    def _due(self, bag_ns: int) -> Optional[int]:
        """Return when ``bag_ns`` is due (callers hold the lock; None while paused)."""
        if self.paused:
            return None
        return self._wall0 + math.ceil((int(bag_ns) - self._bag0) / self.rate)

    def bag_time_ns(self) -> int:
        """Return the bag time of now (frozen while paused)."""
        with self._changed:
            return self._bag_time()

    def due_ns(self, bag_ns: int) -> Optional[int]:
        """Return the monotonic time at which ``bag_ns`` is due (None while paused)."""
        with self._changed:
            return self._due(bag_ns)

    def pause(self) -> bool:
        """Freeze bag time; return whether it was running."""
        with self._changed:
            if self.paused:
                return False
            self._bag0 = self._bag_time()
            self.paused = True
            self._changed.notify_all()
            return True

    def resume(self) -> bool:
        """Run bag time on from where it stood; return whether it was paused."""
        with self._changed:
            if not self.paused:
                return False
            self._wall0 = self._now_ns()
            self.paused = False
            self._changed.notify_all()
            return True

    def jump(self, bag_ns: int) -> None:
        """Make ``bag_ns`` the bag time of now (a loop's restart)."""
        with self._changed:
            self._bag0 = int(bag_ns)
            self._wall0 = self._now_ns()
            self._changed.notify_all()

    def stop(self) -> None:
        """End every wait (Ctrl-C, shutdown)."""
        with self._changed:
            self.stopped = True
            self._changed.notify_all()

    def wait_for(self, bag_ns: int) -> bool:
        """Block until ``bag_ns`` is due (running, not paused); return False when stopped."""
        with self._changed:
            while not self.stopped:
                due, now = self._due(bag_ns), self._now_ns()
                if due is not None and now >= due:
                    return True
                self._changed.wait(None if due is None else (due - now) / NS_PER_S)
            return False


@dataclass
class PlayStats:
    """What a playback did: messages published per topic, loops, skipped topics."""

    published: dict[str, int] = dataclasses.field(default_factory=dict)
    skipped: dict[str, int] = dataclasses.field(default_factory=dict)  # topic -> messages
    passes: int = 0
    stopped: bool = False
    late_ns: list[int] = dataclasses.field(default_factory=list)  # behind schedule, per message

    def total(self) -> int:
        """Return the number of messages published."""
        return sum(self.published.values())

    def lateness_ms(self) -> tuple[float, float]:
        """Return the median and the largest delay behind the schedule, ms (0, 0: none)."""
        if not self.late_ns:
            return 0.0, 0.0
        ordered = sorted(self.late_ns)
        return ordered[len(ordered) // 2] / 1e6, ordered[-1] / 1e6


def play_messages(
    options: PlayOptions,
    clock: PlaybackClock,
    publish: Callable[[RawBagMessage, int], bool],
    *,
    topics: Optional[dict[str, str]] = None,
    on_pass: Optional[Callable[[int, int], None]] = None,
    reader_factory: Callable[[str], BagReader] = open_bag,
) -> PlayStats:
    """
    Play the bag: call ``publish(message, pass index)`` for each message when it is due.

    ``publish`` returns False for a message it did not publish (a topic whose type
    is not installed: counted in :attr:`PlayStats.skipped`). ``topics`` defaults to
    :func:`played_topics`; ``on_pass(index, bag start)`` runs as each pass starts
    (the shell moves the restamp offset there). Stops early when ``clock.stop()`` is called.
    """
    stats = PlayStats()
    passes = 0
    while True:
        with reader_factory(options.bag) as reader:
            names = list(played_topics(reader, options) if topics is None else topics)
            start = reader.start_ns
            if passes:
                clock.jump(start)
            if on_pass is not None:
                on_pass(passes, start)
            empty = True
            for message in reader.raw_messages(names):
                empty = False
                if not clock.wait_for(message.timestamp_ns):
                    stats.stopped = True
                    stats.passes = passes + 1
                    return stats
                due = clock.due_ns(message.timestamp_ns)
                if publish(message, passes):
                    counts = stats.published
                    if due is not None:  # (paused meanwhile: not a delay of the player's)
                        stats.late_ns.append(clock.now_ns() - due)
                else:
                    counts = stats.skipped
                counts[message.topic] = counts.get(message.topic, 0) + 1
        passes += 1
        stats.passes = passes
        if not options.loop or empty or clock.stopped:
            stats.stopped = clock.stopped
            return stats


# --------------------------------------------------------------------- stamps
def _is_time(value: Any) -> bool:
    return hasattr(value, 'sec') and hasattr(value, 'nanosec')


def _is_header(value: Any) -> bool:
    """Return whether ``value`` is a std_msgs/Header (rclpy or rosbags), by its fields."""
    return hasattr(value, 'frame_id') and _is_time(getattr(value, 'stamp', None))


def _field_names(msg: Any) -> list[str]:
    """Return the field names of an rclpy message or a rosbags dataclass ([] otherwise)."""
    fields = getattr(type(msg), 'get_fields_and_field_types', None)
    if fields is not None:
        return list(fields())
    if dataclasses.is_dataclass(msg):
        return [f.name for f in dataclasses.fields(msg) if not f.name.startswith('__')]
    return []


def _is_message(value: Any) -> bool:
    return bool(_field_names(value))


def shift_time(stamp: Any, offset_ns: int) -> None:
    """Add ``offset_ns`` to a builtin_interfaces/Time in place (ValueError if out of range)."""
    ns = int(stamp.sec) * NS_PER_S + int(stamp.nanosec) + int(offset_ns)
    sec, nanosec = divmod(ns, NS_PER_S)
    if not 0 <= sec <= _INT32_MAX:
        raise ValueError(f'a shifted stamp ({ns} ns) is outside builtin_interfaces/Time')
    stamp.sec, stamp.nanosec = sec, nanosec


def shift_stamps(msg: Any, offset_ns: int) -> int:
    """
    Add ``offset_ns`` to every ``header.stamp`` in ``msg`` (nested too); return how many.

    Works on rclpy messages and on rosbags dataclasses alike (found by their fields,
    so any message with a std_msgs/Header is moved: the top-level one, the headers of
    a TFMessage's transforms, ...). A zero stamp (unset) stays zero, as recorded.
    Only headers are moved: other Time fields (e.g. a plan's start time) are data.
    """
    shifted = 0
    stack = [msg]
    while stack:
        value = stack.pop()
        if _is_header(value):
            if value.stamp.sec or value.stamp.nanosec:
                shift_time(value.stamp, offset_ns)
                shifted += 1
            continue
        for name in _field_names(value):
            field = getattr(value, name)
            if isinstance(field, (list, tuple)):
                if field and _is_message(field[0]):
                    stack.extend(field)
            elif _is_message(field):
                stack.append(field)
    return shifted


def restamp_offset_ns(clock: PlaybackClock, bag_start_ns: int, epoch_now_ns: int) -> int:
    """
    Return the stamp shift of a pass: bag start to the system time it was due at.

    The bag time of now is ``(now - due of the start) * rate`` past the start, so the
    start was due ``(bag time - start) / rate`` before ``epoch_now_ns`` (also while
    paused: bag time stands still). A message whose stamp is its log time is then
    stamped with the moment it is due (at rate 1).
    """
    elapsed = round((clock.bag_time_ns() - int(bag_start_ns)) / clock.rate)
    return int(epoch_now_ns) - elapsed - int(bag_start_ns)


def clock_time_ns(clock: PlaybackClock, offset_ns: int = 0) -> int:
    """Return the /clock value of now: bag time, moved like the stamps when restamping."""
    return max(clock.bag_time_ns() + int(offset_ns), 0)
