"""
Replay timing for a bag (no ROS here): which messages are due at a given time.

Messages keep their recorded spacing (receive times) divided by `rate`; with `loop`, the bag
starts over one mean message period after its last message.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

from piezo_narx_ros.bag.reader import iter_raw
from piezo_narx_ros.errors import BagError


class BagSchedule:
    """
    Iterate (due time s from the start of playback, topic, type, CDR bytes) of a bag.

    topics: only these (None = all); rate: speed factor (> 0); loop: repeat forever.
    The bag is streamed, never loaded whole.
    """

    def __init__(self, path: str | Path, topics: list[str] | None = None, rate: float = 1.0,
                 loop: bool = False):
        if not rate > 0:
            raise BagError(f'rate must be > 0, got {rate}')
        self.path = Path(path)
        self.topics = list(topics) if topics else None
        self.rate = float(rate)
        self.loop = bool(loop)
        self.passes = 0   # completed passes through the bag
        self.current_ns: int | None = None   # recorded time (ns) of the message last yielded

    def __iter__(self) -> Iterator[tuple[float, str, str, bytes]]:
        offset_s = 0.0
        while True:
            first = last = None
            count = 0
            for topic, msgtype, t_ns, data in iter_raw(self.path, self.topics):
                if first is None:
                    first = t_ns
                last = t_ns
                count += 1
                self.current_ns = t_ns
                yield offset_s + (t_ns - first) * 1e-9 / self.rate, topic, msgtype, data
            self.passes += 1
            if count == 0:
                raise BagError(f'bag {self.path} has no message to play')
            if not self.loop:
                return
            span = (last - first) * 1e-9 / self.rate
            offset_s += span + (span / (count - 1) if count > 1 else 1e-3)


def topic_types(path: str | Path, topics: list[str] | None = None) -> dict[str, str]:
    """{absolute topic: type} of the bag's topics (only `topics` when given)."""
    from piezo_narx_ros.bag.reader import find_topic, open_bag
    from piezo_narx_ros.bag.writer import absolute_topic
    with open_bag(path) as reader:
        conns = reader.connections
        if topics:
            conns = [c for t in topics for c in find_topic(reader, t, None, path)]
        return {absolute_topic(c.topic): c.msgtype for c in conns}


def topic_offered_qos(path: str | Path, topics: list[str] | None = None) -> dict[str, list]:
    """
    Return the publishers' offered QoS profiles as recorded, per topic.

    {absolute topic: [rosbags Qos, ...]}; an empty list when the bag has none.
    """
    from piezo_narx_ros.bag.reader import find_topic, open_bag
    from piezo_narx_ros.bag.writer import absolute_topic
    out: dict[str, list] = {}
    with open_bag(path) as reader:
        conns = reader.connections
        if topics:
            conns = [c for t in topics for c in find_topic(reader, t, None, path)]
        for c in conns:
            profiles = getattr(c.ext, 'offered_qos_profiles', None) or []
            out.setdefault(absolute_topic(c.topic), []).extend(profiles)
    return out


@dataclass(frozen=True)
class ReplayQos:
    """The QoS to republish a topic with (rclpy-free numbers: rmw enum values, depth)."""

    reliability: int     # rmw value: 1 reliable, 2 best effort
    durability: int      # rmw value: 1 transient local, 2 volatile
    depth: int
    recorded: bool       # False: no usable recorded profile, the fallback was used


def replay_qos(offered: list, fallback_reliable: bool, depth: int) -> ReplayQos:
    """
    Return the QoS `ros2 bag play` replays with, given the recorded offers.

    As rosbag2_transport's adapt_offer_to_recorded_offers: when every publisher offered the same
    reliability and durability, republish with them; otherwise (different offers, or none recorded)
    reliable or best effort per `fallback_reliable`, volatile. The depth is not taken from the
    recording (the middleware does not report a remote publisher's depth, and a small recorded one
    would drop samples for a slow subscriber): it is `depth`.
    """
    known = [q for q in offered if q.reliability.value in (1, 2) and q.durability.value in (1, 2)]
    if not known or len({(q.reliability, q.durability) for q in known}) != 1:
        return ReplayQos(1 if fallback_reliable else 2, 2, int(depth), False)
    return ReplayQos(known[0].reliability.value, known[0].durability.value, int(depth), True)


class PlaybackClock:
    """
    The recorded time (ns) that playback has reached, for /clock (`ros2 bag play --clock`).

    `anchor(mono_s, bag_ns)` when the message recorded at bag_ns goes out at monotonic mono_s;
    `now(mono_s)` extrapolates at `rate` recorded seconds per second, but not past the next
    message (`next_due(bag_ns)`) while it has not gone out, nor past the anchor while the next
    message is unknown (a stalled player or a loop reopening the bag must not run the clock ahead
    of the messages, or backwards when they catch up); before the first anchor it holds
    `start_ns`, after `finish()` the last anchored time.
    """

    def __init__(self, start_ns: int, rate: float = 1.0):
        self.rate = float(rate)
        self._anchor: tuple[float, int] | None = None
        self._held: int | None = int(start_ns)
        self._next: int | None = None

    def anchor(self, mono_s: float, bag_ns: int) -> None:
        """Note that the message recorded at bag_ns (ns) is published at monotonic mono_s (s)."""
        self._anchor = (float(mono_s), int(bag_ns))
        self._held = None
        self._next = int(bag_ns)   # held there until the next message is known

    def next_due(self, bag_ns: int) -> None:
        """
        Note that the next message to go out was recorded at bag_ns (ns).

        When it lies before the last anchor (a loop starts over) the clock holds there.
        """
        self._next = int(bag_ns)

    def finish(self) -> None:
        """Playback ended: hold the last anchored time."""
        if self._anchor is not None:
            self._held = self._anchor[1]

    def now(self, mono_s: float) -> int:
        """Return the recorded time (ns) reached at monotonic mono_s (s)."""
        if self._held is not None or self._anchor is None:
            return int(self._held)
        t0, ns0 = self._anchor
        ns = ns0 + max(0, int(round((mono_s - t0) * self.rate * 1e9)))
        return ns if self._next is None else min(ns, max(ns0, self._next))
