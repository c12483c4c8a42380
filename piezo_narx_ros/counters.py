"""
Counter deltas between diagnostics ticks (ROS-free).

A node's hot path only bumps cumulative counters; once per /diagnostics tick, `Since.tick()` says
how much each grew since the previous tick, so the reported level reflects everything that
happened in between, not only the last sample, and returns to OK once the trouble has stopped.
"""
from __future__ import annotations

from typing import Any, Callable

OK, WARN, ERROR = 0, 1, 2   # DiagnosticStatus levels, as ints (nodes convert them to bytes)


class Since:
    """
    Growth of named cumulative counters between calls of `tick`.

    read: returns {name: cumulative count} now (e.g. lambda: vars(stats)). The first tick
    compares with zeros, so what happened before it counts too.
    """

    def __init__(self, read: Callable[[], dict[str, Any]], names):
        self._read = read
        self.names = tuple(names)
        self._last = dict.fromkeys(self.names, 0)

    def tick(self) -> dict[str, int]:
        """{name: growth since the previous tick} for every name."""
        now = self._read()
        delta = {n: int(now[n]) - self._last[n] for n in self.names}
        self._last = {n: int(now[n]) for n in self.names}
        return delta
