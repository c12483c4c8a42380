"""
Which received command stamps belong to the stream, ROS-free.

Every command of a stream sits on one sample grid, t_k = t0 + k/fs. A receiver (the estimator,
the simulator) must tell apart a stamp that is merely off (a command stamped in the future or the
past, a duplicate, the interleaved stamps of a second writer) from a real change of the stream
(a gap, a player loop, a new run). One stamp alone cannot say which; the next ones can.

`StampGate.push(t, item)` passes a command whose stamp is the next one on the grid straight
through. Any other stamp is held back until the following commands decide:
- they continue the running stream: the held commands were outliers and are dropped (counted);
- they continue from the held ones: a gap of at most `max_fill` samples is accepted after one
  confirming command; anything else (a loop back, a new run, a longer jump) is a new stream once
  `confirm` consecutive commands agree, announced by a RESTART event before its samples.
So normal samples are never delayed, an abnormal one by at most `confirm` samples, and a single
bad stamp can no longer make a receiver refuse every later, correct command.
"""
from __future__ import annotations

from typing import Any

SAMPLE = 'sample'     # (SAMPLE, t_ns, item): the next command of the stream (maybe after a gap)
RESTART = 'restart'   # (RESTART, t_ns, [stamps]): a new stream starts at t_ns with these stamps

# A stamp within this fraction of a period from a grid point is on the grid.
GRID_TOLERANCE = 0.25


class StampGate:
    """
    Classifies command stamps (integer ns) of a stream with period `period_ns` (ns).

    max_fill: longest gap (samples) accepted as a gap of the running stream; confirm: commands
    that must agree before a jump is a new stream. `outliers` and `restarts` count the verdicts.
    """

    def __init__(self, period_ns: float, max_fill: int, confirm: int = 3):
        self.period_ns = float(period_ns)
        self.max_fill = int(max_fill)
        self.confirm = int(confirm)
        self.outliers = 0
        self.restarts = 0
        self.last: int | None = None            # stamp of the last command passed through
        self._held: list[tuple[int, Any]] = []

    @property
    def holding(self) -> int:
        """Commands held back while their stamps are ambiguous."""
        return len(self._held)

    def reset(self) -> None:
        """Forget the stream: the next command is accepted as the first of a new one."""
        self.last = None
        self._held = []

    def steps(self, t_from: int, t_to: int) -> int | None:
        """Sample periods from t_from to t_to when t_to lies ahead on the same grid, else None."""
        d = (t_to - t_from) / self.period_ns
        k = round(d)
        return k if k >= 1 and abs(d - k) <= GRID_TOLERANCE else None

    def push(self, t_ns: int, item: Any = None) -> list[tuple]:
        """
        One received command.

        Returns the events now decided, in order (often just [(SAMPLE, t_ns, item)], [] while a
        stamp is held).
        """
        if self.last is None or self.steps(self.last, t_ns) == 1:   # first, or it continues
            self._drop_held()
            self.last = t_ns
            return [(SAMPLE, t_ns, item)]
        if self._held:
            k = self.steps(self._held[-1][0], t_ns)
            if k is not None and k - 1 <= self.max_fill:
                self._held.append((t_ns, item))    # it continues the held candidate
                return self._resolve()
            self._drop_held()                      # neither: the held ones were outliers
        self._held.append((t_ns, item))            # a new candidate: gap, new stream, outlier
        return []

    def flush(self) -> list[tuple]:
        """
        Decide now (no more commands are coming).

        Held commands that are a gap within max_fill pass, others are outliers.
        """
        if not self._held:
            return []
        k = self.steps(self.last, self._held[0][0])
        if k is not None and k - 1 <= self.max_fill:
            return self._release([])
        self._drop_held()
        return []

    def _drop_held(self) -> None:
        self.outliers += len(self._held)
        self._held = []

    def _resolve(self) -> list[tuple]:
        k = self.steps(self.last, self._held[0][0])
        if k is not None and k - 1 <= self.max_fill:
            return self._release([])         # a gap of the running stream
        if len(self._held) >= self.confirm:
            self.restarts += 1
            return self._release([(RESTART, self._held[0][0], [t for t, _ in self._held])])
        return []

    def _release(self, events: list) -> list[tuple]:
        held, self._held = self._held, []
        events += [(SAMPLE, t, item) for t, item in held]
        self.last = held[-1][0]
        return events
