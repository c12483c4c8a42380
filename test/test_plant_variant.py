"""
The Preisach plant variant (config/plant_preisach.yaml).

A structurally different actuator used to check that model families are not tuned to the default
plant's Bouc-Wen equations.
"""
from pathlib import Path

import numpy as np
import pytest

from piezo_narx_ros.errors import ConfigError
from piezo_narx_ros.plant import PiezoCantilever, generate, load_plant_params
from piezo_narx_ros.plant.figures import loop_width, sine_period

FS = 2000.0
CONFIG = Path(__file__).resolve().parents[1] / 'config' / 'plant_preisach.yaml'


@pytest.fixture(scope='module')
def params():
    return load_plant_params(CONFIG)


def _ramps(points, volts_per_s=20.0):
    """Piecewise-linear slow ramps through `points` (V), then a 0.5 s hold."""
    parts = []
    for a, b in zip(points[:-1], points[1:]):
        n = max(2, int(abs(b - a) / volts_per_s * FS))
        parts.append(np.linspace(a, b, n, endpoint=False))
    parts.append(np.full(int(0.5 * FS), points[-1]))
    return np.concatenate(parts)


def test_step_and_run_agree_and_rest_is_zero(params):
    u = generate('aprbs', FS, 1.0, 150.0, seed=3, min_hold=0.002, max_hold=0.05)
    a = PiezoCantilever(params, FS, seed=4).run(u)
    b = PiezoCantilever(params, FS, seed=4)
    stepped = np.array([b.step(v) for v in u])
    assert np.array_equal(stepped[:, 0], a.y)
    assert np.array_equal(stepped[:, 1], a.y_true)
    b.reset()
    assert b.run(np.zeros(10)).y_true == pytest.approx(np.zeros(10), abs=1e-15)


def test_loop_width_and_stroke_as_configured(params):
    u, y, _ = sine_period(params, 100.0, 0.2)
    width, _, up, down = loop_width(u, y)
    assert 0.13 <= width <= 0.17, width            # 14.6 % measured (config comment)
    assert np.all(down - up > 0)                    # counter-clockwise like the default plant
    assert 0.34e-6 <= np.ptp(y) / np.ptp(u) <= 0.42e-6
    # Asymmetric: the configured off-centre relays make the two extremes differ by > 1 um.
    assert abs(y.max() + y.min()) > 1e-6


def test_return_point_memory_holds_for_preisach_not_for_bouc_wen(params):
    # Wiping-out property: after the minor loop 20 -> 50 -> 20 V, the output at 20 V is the one it
    # had on first reaching 20 V. Exact for a Preisach operator, not for Bouc-Wen: the structural
    # difference this variant exists for. Creep and noise off, slow ramps so the mode is settled.
    u = _ramps([0.0, 80.0, 20.0, 50.0, 20.0])
    peak = int(np.argmax(u))
    first = peak + np.flatnonzero(u[peak:] <= 20.0)[0]   # first arrival at 20 V, descending

    def miss(p):
        y = PiezoCantilever(p.replace(noise_std=0.0, quantisation=0.0, creep_gains=(0.0,) * 3,
                                      creep_time_constants=(1.0,) * 3), FS).run(u).y_true
        return abs(y[-1] - y[first]) / np.ptp(y)

    # Measured: 4.5e-5 of the stroke (the hold ends 0.5 s after the ramp) against 5.8e-3 for
    # Bouc-Wen.
    assert miss(params) < 3e-4
    bouc_wen = load_plant_params().replace(noise_std=0.0, quantisation=0.0,
                                           creep_gains=(0.0,) * 4)
    assert miss(bouc_wen) > 3e-3


def test_creep_continues_after_a_step(params):
    u = generate('steps', FS, 20.0, 50.0, levels=[1.0])
    y = PiezoCantilever(params.replace(noise_std=0.0), FS).run(u).y_true
    drift = y[-1] / y[int(0.05 * FS)] - 1.0
    assert 0.005 < drift < 0.05, drift


@pytest.mark.parametrize('change, word', [
    ({'hysteresis': 'jiles'}, 'hysteresis'),
    ({'creep_input': 'charge'}, 'creep_input'),
    ({'preisach_radii': 0}, 'preisach_radii'),
    ({'preisach_spread': 0.0}, 'preisach_spread'),
])
def test_bad_variant_parameters_are_refused(params, change, word):
    with pytest.raises(ConfigError, match=word):
        params.replace(**change)


def test_mismatched_creep_placement_is_refused(params):
    with pytest.raises(ConfigError, match='creep_input'):
        PiezoCantilever(params.replace(creep_input='hysteresis'), FS)
    with pytest.raises(ConfigError, match='creep_input'):
        PiezoCantilever(load_plant_params().replace(creep_input='voltage'), FS)
