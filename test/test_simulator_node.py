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
    got = np.array([r.on_command(k * P, {'x': x})[0][0] for k, x in enumerate(u)])
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
            got[k] = r.on_command(k * P, {'x': x})[0][0]
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
    with pytest.raises(DataError, match='not after'):
        r.on_command(0, {'x': 1.0, 'y': 2.0})
    assert (r.rejected, r.out_of_order, r.answered) == (2, 1, 1)
    y, u = r.on_command(P, {'x': 1.0, 'y': 2.0})
    assert len(y) == len(u) == 2 and r.gaps == 0
