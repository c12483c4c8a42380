"""
The first run of n consecutive commands that all have their measurement, kept as they arrive.

The estimator and the controller start from that window (`first_full_window` in start.py
answers the same question for a finished list). Scanning the waiting commands again on every
command and every measurement cost O(n) each, O(n²) over the window: at 2 kHz and a 0.5 s
window the estimator took 0.8 s of CPU for 0.5 s of stream and fell behind the stream it had to
follow (20 kHz: 10 000 samples, 100 times worse). Here each command and each measurement costs
O(log holes), holes being the commands whose measurement has not (yet) come.
"""
from __future__ import annotations

from bisect import bisect_left


class FullWindow:
    """
    Index (in arrival order) of the first `n` consecutive commands all measured, or None.

    Feed `command(stamp, measured)` for each command in order (measured: its measurement is
    already there) and `measurement(stamp)` for each measurement that comes; each returns the
    window's first index as soon as there is one. `skip(start)`: the window found at `start`
    could not be used, look for one that begins after it.
    """

    __slots__ = ('n', '_count', '_holes', '_hole_at')

    def __init__(self, n: int):
        if n < 1:
            raise ValueError(f'n must be >= 1, got {n}')
        self.n = int(n)
        self.reset()

    def reset(self) -> None:
        """Forget every command: the next one has index 0."""
        self._count = 0
        self._holes: list[int] = []        # increasing indices of commands not measured
        self._hole_at: dict = {}           # their stamps -> index

    def command(self, stamp: int, measured: bool) -> int | None:
        """Take the next command; the window's first index if this one completes it."""
        i = self._count
        self._count = i + 1
        if not measured:
            self._holes.append(i)
            self._hole_at[stamp] = i
            return None
        # Every earlier run is shorter than n (or it was returned): only the last can be whole.
        last = self._holes[-1] if self._holes else -1
        return last + 1 if i - last >= self.n else None

    def measurement(self, stamp: int) -> int | None:
        """Take a measurement; the window's first index if it completes one."""
        i = self._hole_at.pop(stamp, None)
        if i is None:
            return None        # not a waiting command's: its command sees it when it comes
        holes = self._holes
        k = bisect_left(holes, i)
        del holes[k]
        before = holes[k - 1] if k else -1
        after = holes[k] if k < len(holes) else self._count
        return before + 1 if after - before - 1 >= self.n else None

    def skip(self, start: int) -> int | None:
        """
        Drop the window at `start`: from now on command start + n - 1 counts as never measured.

        Returns the next window's first index if the commands after it already make one.
        """
        end = min(start + self.n, self._count) - 1
        holes = self._holes
        k = bisect_left(holes, end)
        if k == len(holes) or holes[k] != end:
            holes.insert(k, end)
        after = holes[k + 1] if k + 1 < len(holes) else self._count
        return end + 1 if after - end - 1 >= self.n else None
