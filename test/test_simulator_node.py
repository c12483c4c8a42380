"""PlantResponder (the simulator node's logic) without DDS."""
import numpy as np
import pytest

from piezo_narx_ros.errors import DataError
from piezo_narx_ros.nodes.simulator_node import PlantResponder
from piezo_narx_ros.plant import PiezoCantilever

P = 500_000


def _responder(axes=('x',)):
    return PlantResponder({a: PiezoCantilever(fs=2000.0, seed=i) for i, a in enumerate(axes)},
                          2000.0)


def test_answers_equal_the_plant_run_on_the_same_commands():
    u = 100.0 * np.sin(np.linspace(0, 20, 400))
    r = _responder()
    got = np.array([r.on_command(k * P, {'x': x})[0][1][0] for k, x in enumerate(u)])
    ref = PiezoCantilever(fs=2000.0, seed=0).run(u)
    assert np.array_equal(got, ref.y)
    assert r.answered == 400


def test_gap_advances_the_plant_with_the_held_command():
    u = np.linspace(0, 80, 300)
    skip = set(range(100, 110))
    r = _responder()
    got = {}
    for k, x in enumerate(u):
        if k not in skip:
            for t, y, _ in r.on_command(k * P, {'x': x}):   # k=110 is answered with k=111
                got[t // P] = y[0]
    assert sorted(got) == sorted(set(range(300)) - skip)
    held = u.copy()
    held[100:110] = u[99]
    ref = PiezoCantilever(fs=2000.0, seed=0).run(held).y
    assert all(got[k] == ref[k] for k in got)
    assert (r.gaps, r.filled) == (1, 10)


def test_bad_commands_refused_and_state_untouched():
    r = _responder(('x', 'y'))
    r.on_command(0, {'x': 1.0, 'y': 2.0})
    with pytest.raises(DataError, match='not finite'):
        r.on_command(P, {'x': float('nan'), 'y': 0.0})
    with pytest.raises(DataError, match="axis 'y'"):
        r.on_command(P, {'x': 1.0})
    assert r.on_command(0, {'x': 1.0, 'y': 2.0}) == []     # a repeated stamp is held ...
    [(t, y, u)] = r.on_command(P, {'x': 1.0, 'y': 2.0})   # ... and refused: the stream goes on
    assert (r.rejected, r.stamp_outliers, r.answered) == (2, 1, 2)
    assert t == P and len(y) == len(u) == 2 and r.gaps == 0


def test_one_future_stamp_does_not_stop_the_answers():
    """
    Issue 10 item 1 on the simulator.

    A command stamped 1 h ahead made every later command 'not after the previous one'.
    """
    u = np.linspace(-50, 50, 200)
    r = _responder()
    answers = []
    for k, x in enumerate(u):
        answers += r.on_command(k * P, {'x': x})
        if k == 80:
            answers += r.on_command(k * P + 3_600_000_000_000, {'x': 0.0})
    assert [t for t, _, _ in answers] == [k * P for k in range(200)]
    ref = PiezoCantilever(fs=2000.0, seed=0).run(u).y
    assert np.array_equal([y[0] for _, y, _ in answers], ref)
    assert r.stamp_outliers == 1 and r.stream_restarts == 0
