"""
Values by sample stamp, the newest kept: the free-run estimator's estimate and measurement tables.

FreeRunEstimator pairs estimates and measurements by stamp in either arrival order, so each side
waits in a table until the other comes. Within one run the estimator's stamps only increase, and
so do a sensor's, so a StampTable keeps them as two lists in stamp order (stamps, values),
appended at the end and searched by bisection, with a dict for a stamp that comes out of order.
A dict of every stamp cost more: about 9 us to insert a 20-sample batch and 11 us to look one up
when the caches are cold (a node woken 1000 times a second), against 3 us for the lists, and it
had to be rebuilt to forget its oldest entries.
"""
from __future__ import annotations

from bisect import bisect_left


class StampTable:
    """
    {stamp (int ns): value} keeping every entry among the newest `keep` inserted.

    The newest `keep` insertions, popped ones included: an entry stays for `keep` samples of a
    stream, however many of them were paired and popped meanwhile.

    Values are floats or arrays, never None (None stands for "absent"). Setting a stamp again
    replaces its value and keeps its place in the insertion order, as in a dict; `pop` removes
    it (set after that, it is the newest).
    """

    __slots__ = ('keep', '_t', '_v', '_hint', '_other')

    def __init__(self, keep: int):
        if keep < 1:
            raise ValueError(f'keep must be >= 1, got {keep}')
        self.keep = int(keep)
        self._t: list = []        # increasing stamps
        self._v: list = []        # their values, None once popped
        self._hint = 0            # where the next pop is likely (pops come in stamp order)
        self._other: dict = {}    # stamps that came after a later one, by insertion order

    def __len__(self) -> int:
        return sum(v is not None for v in self._v) + len(self._other)

    def _index(self, t: int) -> int:
        """Return the index of stamp t in the lists, or -1."""
        ts = self._t
        i = self._hint
        if i < len(ts) and ts[i] == t:
            return i
        i = bisect_left(ts, t)
        return i if i < len(ts) and ts[i] == t else -1

    def get(self, t: int, default=None):
        """Return the value of stamp t, or `default`."""
        ts = self._t
        if ts and t <= ts[-1]:
            i = self._index(t)
            if i >= 0 and self._v[i] is not None:
                return self._v[i]
        return self._other.get(t, default) if self._other else default

    def __contains__(self, t: int) -> bool:
        return self.get(t) is not None

    def __getitem__(self, t: int):
        v = self.get(t)
        if v is None:
            raise KeyError(t)
        return v

    def __setitem__(self, t: int, value) -> None:
        ts = self._t
        if not ts or t > ts[-1]:
            ts.append(t)
            self._v.append(value)
            if len(ts) >= 2 * self.keep:
                self._trim()
            return
        i = self._index(t)
        if i >= 0 and self._v[i] is not None:    # set again: it keeps its place, as in a dict
            self._v[i] = value
            return
        other = self._other
        other[t] = value
        if len(other) >= 2 * self.keep:
            self._other = dict(list(other.items())[-self.keep:])

    def update(self, pairs) -> None:
        """Set every (stamp, value) of `pairs`, in order."""
        for t, v in pairs:
            self[t] = v

    def extend(self, stamps: list, values: list, increasing: bool) -> None:
        """Set stamps to values in order (`increasing`: the caller knows each follows the last)."""
        ts = self._t
        if increasing and stamps and (not ts or stamps[0] > ts[-1]):
            ts.extend(stamps)
            self._v.extend(values)
            if len(ts) >= 2 * self.keep:
                self._trim()
        else:
            self.update(zip(stamps, values))

    def pop(self, t: int, default=None):
        """Remove stamp t; return its value, or `default` when absent."""
        ts = self._t
        if ts and t <= ts[-1]:
            i = self._index(t)
            if i >= 0:
                v = self._v[i]
                if v is not None:
                    self._v[i] = None
                    self._hint = i + 1
                    return v
        return self._other.pop(t, default) if self._other else default

    def holds_from(self, t: int) -> bool:
        """Tell whether a stamp at or after t may be held (False: none is, get_many is Nones)."""
        return bool(self._other) or bool(self._t) and self._t[-1] >= t

    def get_many(self, stamps: list) -> list:
        """Return [value or None] of each stamp of `stamps`."""
        ts = self._t
        if not stamps or not self._other and (not ts or min(stamps) > ts[-1]):
            return [None] * len(stamps)     # all newer than anything held: a run's usual case
        return [self.get(t) for t in stamps]

    def pop_many(self, stamps: list) -> list:
        """Remove each stamp of `stamps`; return [value or None] of each."""
        ts = self._t
        if not stamps or not self._other and (not ts or min(stamps) > ts[-1]):
            return [None] * len(stamps)
        if not self._other:     # a sensor's run of stamps, each an estimate's in turn: one slice
            i = bisect_left(ts, stamps[0])
            j = i + len(stamps)
            if ts[i:j] == stamps:
                got = self._v[i:j]
                self._v[i:j] = [None] * len(stamps)
                self._hint = j
                return got
        return [self.pop(t) for t in stamps]

    def _trim(self) -> None:
        """Keep the newest `keep` stamps of the lists."""
        drop = len(self._t) - self.keep
        del self._t[:drop]
        del self._v[:drop]
        self._hint = max(0, self._hint - drop)
