"""estimator/stamp_table.py: a table of stamps keeping its newest entries, against a dict."""
from collections import deque

import numpy as np
import pytest

from piezo_narx_ros.estimator.stamp_table import StampTable


@pytest.mark.parametrize('vector', [False, True])
def test_stamp_table_agrees_with_a_dict_on_its_newest_entries(vector):
    rng = np.random.default_rng(5 + vector)
    keep = 50
    table, ref = StampTable(keep), {}
    at, count = {}, [0]      # each stamp's latest insertion (set again: none), insertions made
    recent = deque(maxlen=2 * keep)

    def newest(s):
        return s in at and at[s] >= count[0] - keep

    def value():
        return rng.normal(size=2) if vector else float(rng.normal())

    def put(t, v):
        if t not in ref:        # set again, a stamp keeps its place (a dict's order)
            at[t] = count[0]
            count[0] += 1
            recent.append(t)
        ref[t] = v
    t = 1000
    for step in range(1500):
        op = rng.random()
        if op < 0.45:        # a run's next stamps, one or a batch
            n = int(rng.integers(1, 8))
            stamps = list(range(t + 1, t + 1 + n))
            t += n
            values = [value() for _ in stamps]
            if n > 1 and rng.random() < 0.5:
                table.extend(stamps, values, True)
            else:
                for s, v in zip(stamps, values):
                    table[s] = v
            for s, v in zip(stamps, values):
                put(s, v)
        elif op < 0.55:      # an earlier stamp again, one never seen before the others, one far
            k = rng.random()  # ahead of them (what follows it is then out of order)
            s = int(t - rng.integers(0, 80)) if k < 0.6 else -int(rng.integers(1, 10**6)) \
                if k < 0.95 else int(t) * 10**6
            v = value()
            table[s] = v
            put(s, v)
        elif op < 0.75:      # pops, alone or many, in stamp order as measurements come
            stamps = sorted({int(t - rng.integers(0, 60)) for _ in range(int(rng.integers(1, 6)))})
            got = table.pop_many(stamps) if rng.random() < 0.5 else [table.pop(s) for s in stamps]
            for s, g in zip(stamps, got):
                want = ref.pop(s, None)
                if newest(s) or want is None:
                    assert (g is None) == (want is None) and (g is None or np.array_equal(g, want))
        elif op < 0.85:      # an unsorted increasing-flag-false extend
            stamps = [int(t + 3), int(t + 1), int(t + 2)]
            t += 3
            values = [value() for _ in stamps]
            table.extend(stamps, values, False)
            for s, v in zip(stamps, values):
                put(s, v)
        # Every stamp among the newest `keep` insertions (popped ones count) is there with its
        # value; older ones, if still there, have theirs.
        probe = list(recent) + [t + 5]
        got = table.get_many(probe)
        for s, g in zip(probe, got):
            want = ref.get(s)
            assert g is None or np.array_equal(g, want)
            if newest(s) and want is not None:
                assert g is not None and np.array_equal(g, want) and s in table, s
                assert np.array_equal(table[s], want) and np.array_equal(table.get(s), want)
    assert len(table) >= keep and table.get(t + 5) is None
    assert table.pop(t + 5, 'absent') == 'absent'
    with pytest.raises(KeyError):
        table[t + 5]
    assert table.get_many([]) == [] and table.pop_many([]) == []


def test_stamp_table_memory_stays_bounded():
    table = StampTable(100)
    for k in range(0, 100000, 20):
        table.extend(list(range(k, k + 20)), [1.0] * 20, True)
    for k in range(1000):
        table[-k] = 1.0         # out of order, each new
    assert len(table._t) < 200 and len(table._other) < 200 and len(table) >= 100
    with pytest.raises(ValueError):
        StampTable(0)


def test_stamp_table_pops_a_run_of_stamps_as_one_slice():
    table = StampTable(1000)
    table.extend(list(range(100)), [float(k) for k in range(100)], True)
    assert table.pop(12) == 12.0
    assert table.pop_many(list(range(10, 15))) == [10.0, 11.0, None, 13.0, 14.0]
    assert table.pop_many(list(range(10, 15))) == [None] * 5
    assert table.pop_many([20, 22, 21]) == [20.0, 22.0, 21.0]     # not a run: one by one
    assert table.pop_many(list(range(95, 105))) == [95.0, 96.0, 97.0, 98.0, 99.0] + [None] * 5
    assert 30 in table and 14 not in table and len(table) == 100 - 13
