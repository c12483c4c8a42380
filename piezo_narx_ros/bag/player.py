"""Replay timing for a bag (no ROS here): which messages are due at a given time.

Messages keep their recorded spacing (receive times) divided by `rate`; with `loop`, the bag
starts over one mean message period after its last message.
"""
from __future__ import annotations

from pathlib import Path
from typing import Iterator

from piezo_narx_ros.bag.reader import iter_raw
from piezo_narx_ros.errors import BagError


class BagSchedule:
    """Iterate (due time s from the start of playback, topic, type, CDR bytes) of a bag.

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
