"""
FreeRunEstimator (the estimator node's logic) without DDS.

Equality with offline simulate, initialisation, gap/NaN/range handling, output-range flag, running
error, re-anchoring.
"""
import math

import numpy as np
import pytest

from piezo_narx_ros.errors import ConfigError
from piezo_narx_ros.estimator.free_run import FreeRunEstimator
from piezo_narx_ros.estimator.toy import toy_narx

P = 500_000  # ns, 2 kHz


@pytest.fixture(scope='module')
def model():
    return toy_narx(nu=3, ny=2, hidden=6, fs=2000.0, seed=4)


def _u(n, seed=0):
    return np.random.default_rng(seed).uniform(-100.0, 100.0, n)


def _feed(est, u, t0=0, meas=None, skip=()):
    out = []
    for k, x in enumerate(u):
        if k in skip:
            continue
        out += est.on_command(t0 + k * P, float(x))
        if meas is not None:
            out += est.on_measurement(t0 + k * P, float(meas[k]))
    return out


def test_from_rest_equals_offline_simulate(model):
    u = _u(3000)
    est = FreeRunEstimator(model, init='rest')
    out = _feed(est, u)
    assert [t for t, _ in out] == [k * P for k in range(3000)]
    assert np.max(np.abs(np.array([y for _, y in out]) - model.simulate(u))) <= 1e-12
    assert est.stats.init == 'rest' and est.stats.estimates == 3000


def test_from_measurement_equals_simulate_with_measured_y0(model):
    u = _u(1000, 1)
    y_meas = model.simulate(u) + 3e-8          # a sensor offset: y0 differs from rest
    est = FreeRunEstimator(model, init='auto')
    est.start(measurement_available=True)
    out = _feed(est, u, meas=y_meas)
    assert est.stats.init == 'measurement'
    assert [t for t, _ in out] == [k * P for k in range(1000)]
    ref = model.simulate(u, y_meas[:model.n0])
    assert np.max(np.abs(np.array([y for _, y in out]) - ref)) <= 1e-12


def test_initialises_at_the_first_measured_window_when_early_measurements_are_lost(model):
    u = _u(500, 11)
    y_meas = model.simulate(u) + 1e-8
    est = FreeRunEstimator(model, init='measurement')
    out = []
    for k in range(500):
        out += est.on_command(k * P, float(u[k]))
        if k >= 30 and k != 31:                  # 0..29 and 31 never arrive
            out += est.on_measurement(k * P, float(y_meas[k]))
    j = 32                                        # first n0 = 3 consecutive measured: 32, 33, 34
    assert est.stats.init == 'measurement' and est.stats.unestimated == j
    assert [t for t, _ in out] == [k * P for k in range(j, 500)]
    ref = model.simulate(u[j:], y_meas[j:j + model.n0])
    assert np.max(np.abs(np.array([y for _, y in out]) - ref)) <= 1e-12


def test_measurement_that_never_comes_falls_back_to_rest_without_losing_samples(model):
    u = _u(400, 2)
    est = FreeRunEstimator(model, init='measurement', init_timeout=0.05)   # 100 samples
    out = _feed(est, u)
    assert est.stats.init == 'rest (no measurement)'
    assert len(out) == 400
    assert np.allclose([y for _, y in out], model.simulate(u), atol=1e-15, rtol=0)


def test_gaps_and_bad_commands_are_filled_by_holding_and_counted(model):
    u = _u(600, 3)
    bad = u.copy()
    bad[100] = math.nan
    bad[200] = math.inf
    bad[300] = 1e4                              # outside [u_min, u_max]
    skip = {400, 401, 402, 500}
    est = FreeRunEstimator(model, init='rest')
    out = _feed(est, bad, skip=skip)
    held = u.copy()
    for k in (100, 200, 300, 400, 401, 402, 500):
        held[k] = held[k - 1]
    assert [t for t, _ in out] == [k * P for k in range(600)]      # every stamp published
    assert np.max(np.abs(np.array([y for _, y in out]) - model.simulate(held))) <= 1e-12
    s = est.stats
    assert (s.rejected_nonfinite, s.rejected_range, s.gaps, s.filled) == (2, 1, 2, 7)
    assert s.commands == 596


def test_stale_stamps_refused_and_long_jump_restarts_once_confirmed(model):
    est = FreeRunEstimator(model, init='rest', max_fill=10)
    est.on_command(10 * P, 1.0)
    assert est.on_command(10 * P, 2.0) == [] and est.on_command(9 * P, 2.0) == []
    assert len(est.on_command(11 * P, 1.0)) == 1       # the stream goes on: both were outliers
    assert est.stats.stamp_outliers == 2
    out = []
    for k in range(100, 103):                  # 88 missing > max_fill: a new stream, 3 agree
        out += est.on_command(k * P, 5.0)
    assert [t for t, _ in out] == [100 * P, 101 * P, 102 * P]
    assert est.stats.stream_restarts == 1 and est.stats.filled == 0
    assert out[0][1] == pytest.approx(model.simulate(np.array([5.0]))[0], abs=1e-15)


def test_estimate_outside_trained_range_is_flagged():
    from piezo_narx_ros.ident.arx import ARXModel
    m = ARXModel(na=1, nb=0).set_coefficients(a=[-0.5], b=[1e-8])      # 2e-8 m/V static gain
    m.fs, m.output_range = 2000.0, (-1e-6, 1e-6)                        # trained on +-50 V
    est = FreeRunEstimator(m, init='rest', range_margin=0.1)
    _feed(est, np.full(100, 50.0))
    assert est.stats.out_of_range == 0 and not est.out_of_range_now
    _feed(est, np.full(100, 100.0), t0=100 * P)                         # 2e-6 m > 1.1e-6 m
    assert est.stats.out_of_range > 90 and est.out_of_range_now
    _feed(est, np.full(100, 0.0), t0=200 * P)
    assert not est.out_of_range_now


def test_running_error_rms_and_r2_over_window(model):
    u = _u(800, 5)
    y = model.simulate(u)
    noise = np.random.default_rng(6).normal(0, 1e-8, u.size)
    est = FreeRunEstimator(model, init='rest', window=500)
    _feed(est, u, meas=y + noise)
    rms, r2, n = est.running_error()
    assert n == 500
    assert rms == pytest.approx(np.sqrt(np.mean(noise[-500:] ** 2)), rel=1e-9)
    assert 0.99 < r2 < 1.0


def test_reanchoring_removes_a_wrong_initial_state():
    from piezo_narx_ros.ident.arx import ARXModel
    slow = ARXModel(na=1, nb=0).set_coefficients(a=[-0.995], b=[1e-9])   # long memory
    slow.fs, slow.output_range = 2000.0, (-1e-3, 1e-3)
    u = _u(2000, 7)
    y_meas = slow.simulate(u, y0=[5e-6])          # the plant did not start from rest
    plain = FreeRunEstimator(slow, init='rest', window=500)
    anchored = FreeRunEstimator(slow, init='rest', window=500, reanchor_every=20)
    _feed(plain, u, meas=y_meas)
    _feed(anchored, u, meas=y_meas)
    assert plain.stats.reanchors == 0 and anchored.stats.reanchors >= 99
    assert plain.running_error()[0] > 1e-9
    assert anchored.running_error()[0] < 1e-6 * plain.running_error()[0]


def test_measurement_arriving_before_command_is_matched(model):
    est = FreeRunEstimator(model, init='rest')
    est.on_measurement(0, 1e-7)
    est.on_command(0, 0.0)
    est.on_measurement(P, 2e-7)
    est.on_command(P, 0.0)
    assert est.running_error()[2] == 2


def test_bad_configuration_refused(model):
    with pytest.raises(ConfigError, match='init'):
        FreeRunEstimator(model, init='sometimes')
    with pytest.raises(ConfigError, match='u_min'):
        FreeRunEstimator(model, u_min=1.0, u_max=0.0)
    with pytest.raises(ConfigError, match='not a NARX'):
        FreeRunEstimator(object())
    m = toy_narx(nu=1, ny=1, hidden=2)
    m.fs = None
    with pytest.raises(ConfigError, match='sample rate'):
        FreeRunEstimator(m)


def test_requested_restart_from_rest_and_from_measurement(model):
    """
    The ~/reset and ~/reinitialize services.

    The run after the request equals an offline simulate of the later commands alone, from rest or
    from the measured outputs there.
    """
    u = _u(1200, 21)
    y_meas = model.simulate(u) + 2e-8
    est = FreeRunEstimator(model, init='auto')
    est.start(measurement_available=True)
    _feed(est, u[:400], meas=y_meas[:400])
    est.request_restart(from_measurement=False)
    out = _feed(est, u[400:800], t0=400 * P, meas=y_meas[400:800])
    assert est.stats.init == 'rest' and est.stats.requested_restarts == 1
    assert [t for t, _ in out] == [k * P for k in range(400, 800)]
    assert np.max(np.abs(np.array([y for _, y in out]) - model.simulate(u[400:800]))) <= 1e-12
    est.request_restart(from_measurement=True)
    out = _feed(est, u[800:], t0=800 * P, meas=y_meas[800:])
    assert est.stats.init == 'measurement' and est.stats.requested_restarts == 2
    ref = model.simulate(u[800:], y_meas[800:800 + model.n0])
    assert np.max(np.abs(np.array([y for _, y in out]) - ref)) <= 1e-12
    rest_only = FreeRunEstimator(model, init='rest')
    with pytest.raises(ConfigError, match="init is 'rest'"):
        rest_only.request_restart(from_measurement=True)
