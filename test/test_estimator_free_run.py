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


W = 0.005        # s: an init window of 10 samples at 2 kHz keeps these cases short


def _from_state(model, u, y, n):
    """Return the offline run of an estimator initialised from the window u[:n], y[:n]."""
    return model.simulate(u, state=model.estimate_state(u[:n], y[:n]))


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


def test_init_past_reaches_the_state_estimate(model, monkeypatch):
    seen = []
    estimate = type(model).estimate_state
    monkeypatch.setattr(type(model), 'estimate_state',
                        lambda self, u, y, prior=None, past='any':
                        seen.append(past) or estimate(self, u, y, prior, past))
    u = _u(200, 2)
    est = FreeRunEstimator(model, init='measurement', init_window=W, init_past='fade-out')
    _feed(est, u, meas=model.simulate(u))
    assert est.stats.init == 'measurement' and seen == ['fade-out']


def test_from_measurement_equals_simulate_from_the_estimated_state(model):
    u = _u(3000, 1)
    y_meas = model.simulate(u) + 3e-8          # a sensor offset: the state is not rest
    est = FreeRunEstimator(model, init='auto')  # the default window: 0.5 s = 1000 samples
    est.start(measurement_available=True)
    out = _feed(est, u, meas=y_meas)
    assert est.stats.init == 'measurement' and est.stats.state == 'estimated'
    assert [t for t, _ in out] == [k * P for k in range(3000)]
    ref = _from_state(model, u, y_meas, 1000)
    assert np.max(np.abs(np.array([y for _, y in out]) - ref)) <= 1e-12
    # The offset was found: after the lags' first samples (whose unmeasured past is taken as
    # held) the run is the measurement's.
    assert np.max(np.abs(ref - y_meas)[20:]) < 1e-12 and np.max(np.abs(ref - y_meas)) < 2e-9


def test_initialises_at_the_first_measured_window_when_early_measurements_are_lost(model):
    u = _u(500, 11)
    y_meas = model.simulate(u) + 1e-8
    est = FreeRunEstimator(model, init='measurement', init_window=W)
    out = []
    for k in range(500):
        out += est.on_command(k * P, float(u[k]))
        if k >= 30 and k != 31:                  # 0..29 and 31 never arrive
            out += est.on_measurement(k * P, float(y_meas[k]))
    j = 32                                        # the first 10 consecutive measured: 32..41
    assert est.stats.init == 'measurement' and est.stats.unestimated == j
    assert [t for t, _ in out] == [k * P for k in range(j, 500)]
    ref = _from_state(model, u[j:], y_meas[j:], 10)
    assert np.max(np.abs(np.array([y for _, y in out]) - ref)) <= 1e-12


def test_measurement_that_never_comes_falls_back_to_rest_without_losing_samples(model):
    u = _u(400, 2)
    est = FreeRunEstimator(model, init='measurement', init_timeout=0.05,   # 100 samples
                           init_window=W)
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
    from piezo_narx_ros.ident.arx.model import ARXModel
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
    from piezo_narx_ros.ident.arx.model import ARXModel
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
    with pytest.raises(ConfigError, match="init_past must be one of \\['any', 'fade-out'\\]"):
        FreeRunEstimator(model, init_past='ramped')
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
    est = FreeRunEstimator(model, init='auto', init_window=W)
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
    ref = _from_state(model, u[800:], y_meas[800:], 10)
    assert np.max(np.abs(np.array([y for _, y in out]) - ref)) <= 1e-12
    rest_only = FreeRunEstimator(model, init='rest')
    with pytest.raises(ConfigError, match="init is 'rest'"):
        rest_only.request_restart(from_measurement=True)


# ------------------------------------------------------------------ exact behaviour, small cases

class _Echo:
    """A stand-in model whose estimate is the (held) command itself, y(k) = u(k)."""

    nu, ny, n0, fs = 0, 1, 1, 2000.0
    output_range = (-1.0, 1.0)

    def stepper(self, u_past=None, y_past=None):
        return _EchoStepper()


class _EchoStepper:

    def step(self, u):
        return float(u)

    def reset(self, u_past=None, y_past=None):
        pass


def _ys(out):
    return [y for _, y in out]


def test_configuration_limits_are_inclusive_and_each_bad_value_refused(model):
    import copy
    no_rate = copy.copy(model)
    no_rate.fs = None                  # a model file without fs: the node's fs is used
    est = FreeRunEstimator(no_rate, fs=0.5, max_fill=0, window=2, reanchor_every=0,
                           init_timeout=0.0, init_window=0.0, confirm=1)
    assert est.fs == 0.5 and est.period_ns == 2e9
    for bad in ({'fs': -2000.0}, {'fs': math.inf}, {'u_min': 1.0, 'u_max': 1.0},
                {'max_fill': -1}, {'window': 1}, {'reanchor_every': -1}, {'init_timeout': -0.1},
                {'confirm': 0}, {'init_window': -0.1}, {'init_window': 2.0, 'init_timeout': 1.0},
                {'init_window': math.nan}):
        with pytest.raises(ConfigError):
            FreeRunEstimator(model, **bad)

    class NoRate:                      # no fs attribute at all, and none given
        nu, ny, n0 = 1, 1, 1

        def stepper(self):
            pass
    with pytest.raises(ConfigError, match='sample rate unknown'):
        FreeRunEstimator(NoRate())


def test_defaults_are_the_estimator_nodes():
    # One set of defaults: the class used as a library behaves as the node started without
    # parameters.
    from piezo_narx_ros.nodes.estimator_node import EstimatorNode
    node = {spec.name: spec.default for spec in EstimatorNode.PARAMS}
    est = FreeRunEstimator(_Echo())
    span = _Echo.output_range[1] - _Echo.output_range[0]
    assert (est.init_mode, est.u_min, est.u_max, est.max_fill, est.window,
            est.reanchor_every) == (node['init'], node['u_min'], node['u_max'],
                                    node['max_fill'], node['window'], node['reanchor_every'])
    assert est.init_timeout_samples == round(node['init_timeout'] * _Echo.fs)
    assert est.init_past == node['init_past'] == 'any'
    assert est.y_hi == pytest.approx(_Echo.output_range[1] + node['range_margin'] * span)


def test_command_limits_are_inclusive_and_rejections_counted():
    est = FreeRunEstimator(_Echo(), init='rest', u_min=-1.0, u_max=1.0)
    out = _feed(est, [-1.0, 1.0, 1.5, -2.0, math.nan, 0.5])
    assert _ys(out) == [-1.0, 1.0, 1.0, 1.0, 1.0, 0.5]       # rejected ones hold the last
    s = est.stats
    assert (s.rejected_range, s.rejected_nonfinite, s.filled) == (2, 1, 3)


def test_a_bad_first_command_is_held_at_rest_also_after_a_restart():
    est = FreeRunEstimator(_Echo(), init='rest')
    assert _ys(est.on_command(0, math.nan)) == [0.0]
    est.on_command(P, 0.5)
    est.restart()
    assert _ys(est.on_command(2 * P, math.nan)) == [0.0]      # not the 0.5 of the last run


def test_output_range_flag_boundaries_and_excursion():
    est = FreeRunEstimator(_Echo(), init='rest', u_min=-10.0, u_max=10.0, range_margin=0.1)
    assert (est.y_lo, est.y_hi) == (pytest.approx(-1.2), pytest.approx(1.2))
    _feed(est, [est.y_hi, est.y_lo])                          # on the limits: not flagged
    assert est.stats.out_of_range == 0 and not est.out_of_range_now
    _feed(est, [1.5, -2.0, 1.3], t0=2 * P)
    assert est.stats.out_of_range == 3 and est.out_of_range_now
    assert est.take_excursion() == pytest.approx(0.8)         # -2.0 is 0.8 below -1.2
    assert est.take_excursion() == 0.0                        # reset by reading it
    _feed(est, [1.7], t0=5 * P)
    assert est.take_excursion() == pytest.approx(0.5)         # above: 1.7 - 1.2
    est.restart()
    assert not est.out_of_range_now and est.stats.init == 'waiting'


def test_a_model_without_a_trained_range_flags_nothing():
    class Unranged:
        nu, ny, n0, fs = 0, 1, 1, 2000.0
        stepper = _Echo.stepper
    est = FreeRunEstimator(Unranged(), init='rest', u_min=-1e12, u_max=1e12)
    _feed(est, [1e9, -1e9])
    assert est.stats.out_of_range == 0 and est.take_excursion() == 0.0


def test_confirm_sets_how_many_commands_make_a_new_stream():
    # A jump is held until a second command continues it: with confirm <= 2 that pair is a new
    # stream at once, with the default 3 it waits for a third.
    for confirm, held in ((1, 0), (3, 2)):
        est = FreeRunEstimator(_Echo(), init='rest', max_fill=10, confirm=confirm)
        est.on_command(0, 0.1)
        out = est.on_command(1000 * P, 0.2) + est.on_command(1001 * P, 0.3)
        assert est.holding == held and len(out) == 2 - held


def test_initial_measurement_timeout_is_counted_in_samples():
    est = FreeRunEstimator(_Echo(), init='measurement', init_timeout=0.005,    # 10 samples
                           init_window=0.0)
    out = _feed(est, [0.1] * 9)
    assert out == [] and est.stats.init == 'waiting'
    out = est.on_command(9 * P, 0.2)
    assert out == [(k * P, 0.1) for k in range(9)] + [(9 * P, 0.2)]
    assert est.stats.init == 'rest (no measurement)'


def test_measurements_before_their_commands_initialise_at_the_window_s_last_command(model):
    u = _u(50, 12)
    y_meas = model.simulate(u) + 2e-8
    est = FreeRunEstimator(model, init='measurement', init_window=W)
    out = []
    for k in range(50):
        out += est.on_measurement(k * P, float(y_meas[k]))
        got = est.on_command(k * P, float(u[k]))
        if k == 9:                              # the 10th command completes the window
            assert [t for t, _ in got] == [j * P for j in range(10)]
        out += got
    assert [t for t, _ in out] == [k * P for k in range(50)]
    assert np.max(np.abs(np.array(_ys(out)) - _from_state(model, u, y_meas, 10))) <= 1e-12


def test_measurements_lagging_their_commands_release_the_held_estimates(model):
    # The sensor's first samples arrive after several commands: the measurement that completes
    # the window releases every command held so far, in order.
    u = _u(60, 13)
    y_meas = model.simulate(u) + 2e-8
    est = FreeRunEstimator(model, init='measurement', init_window=W)
    assert _feed(est, u[:15]) == []
    out = []
    for k in range(10):
        out += est.on_measurement(k * P, float(y_meas[k]))
    assert [t for t, _ in out] == [k * P for k in range(15)]
    out += _feed(est, u[15:], t0=15 * P)
    ref = _from_state(model, u, y_meas, 10)
    assert np.max(np.abs(np.array(_ys(out)) - ref)) <= 1e-12


def test_commands_without_measurement_are_counted_over_every_initialisation(model):
    u = _u(40, 14)
    y_meas = model.simulate(u)
    est = FreeRunEstimator(model, init='measurement', init_window=W)
    for k in range(20):
        est.on_command(k * P, float(u[k]))
        if k >= 2:                                      # the first 2 never measured
            est.on_measurement(k * P, float(y_meas[k]))
    assert est.stats.unestimated == 2
    est.request_restart(from_measurement=True)
    for k in range(20, 40):
        est.on_command(k * P, float(u[k]))
        if k >= 23:                                     # 3 more lost after the restart
            est.on_measurement(k * P, float(y_meas[k]))
    assert est.stats.unestimated == 5 and est.stats.init == 'measurement'


def test_how_each_init_mode_decides():
    # auto: the first command decides (rest) unless start() came first, and start() after it is
    # ignored; measurement: start() never changes it; rest: never waits, whatever is asked.
    auto = FreeRunEstimator(_Echo(), init='auto', max_fill=10, confirm=1)
    assert _ys(auto.on_command(0, 0.3)) == [0.3]
    auto.start(measurement_available=True)                   # too late: ignored
    assert _ys(auto.on_command(P, 0.4)) == [0.4]
    auto.on_command(1000 * P, 0.5)                            # a new stream: still from rest
    assert _ys(auto.on_command(1001 * P, 0.6)) == [0.5, 0.6]
    meas = FreeRunEstimator(_Echo(), init='measurement')
    meas.start(measurement_available=False)                  # not 'auto': ignored
    assert meas.on_command(0, 0.3) == []
    rest = FreeRunEstimator(_Echo(), init='rest')
    rest.restart(wait_for_measurement=True)
    assert _ys(rest.on_command(0, 0.3)) == [0.3]
    from_rest = FreeRunEstimator(_Echo(), init='measurement')
    from_rest.restart(wait_for_measurement=False)
    assert _ys(from_rest.on_command(0, 0.3)) == [0.3] and from_rest.stats.init == 'rest'


@pytest.mark.parametrize('sensor', [True, False])
def test_a_new_stream_initialises_as_the_first_did(model, sensor):
    # An 'auto' estimator told whether a sensor exists keeps that choice for a new stream (a
    # player loop, a new run): from the measured outputs again, or from rest at once. Before,
    # the choice was forgotten at the new stream: with a sensor the estimator went on from rest
    # and never published the commands held while the new stream was confirmed.
    u = _u(40, 15)
    y_meas = model.simulate(u) + 1e-8
    est = FreeRunEstimator(model, init='auto', max_fill=10, confirm=1, init_window=W)
    est.start(measurement_available=sensor)
    _feed(est, u[:20], meas=y_meas[:20] if sensor else None)
    t1 = 10_000 * P                                            # far beyond max_fill
    out = _feed(est, u[20:], t0=t1, meas=y_meas[20:] if sensor else None)
    assert est.stats.stream_restarts == 1
    assert [t for t, _ in out] == [t1 + k * P for k in range(20)]
    ref = _from_state(model, u[20:], y_meas[20:], 10) if sensor else model.simulate(u[20:])
    assert np.max(np.abs(np.array(_ys(out)) - ref)) <= 1e-12
    assert est.stats.init == ('measurement' if sensor else 'rest')


def test_running_error_from_two_samples_over_the_last_window_exactly():
    est = FreeRunEstimator(_Echo(), init='rest', window=3, u_min=-10.0, u_max=10.0)
    est.on_command(0, 0.0)
    est.on_measurement(0, 0.5)
    assert math.isnan(est.running_error()[0])                 # one sample: too few
    y_meas = [0.5, 1.0, 3.0, 2.0]
    u = [0.0, 1.5, 2.0, 2.5]
    for k in range(1, 4):
        est.on_command(k * P, u[k])
        est.on_measurement(k * P, y_meas[k])
        if k == 1:
            rms, r2, n = est.running_error()
            assert n == 2 and rms == pytest.approx(math.sqrt((0.25 + 0.25) / 2))
            assert r2 == pytest.approx(1 - 0.5 / 0.125)
    e = np.subtract(y_meas[1:], u[1:])                        # the last 3 only
    y = np.array(y_meas[1:])
    rms, r2, n = est.running_error()
    assert n == 3 and rms == pytest.approx(np.sqrt(np.mean(e ** 2)))
    assert r2 == pytest.approx(1 - np.sum(e ** 2) / np.sum((y - y.mean()) ** 2))
    flat = FreeRunEstimator(_Echo(), init='rest')
    _feed(flat, [0.1, 0.2], meas=[0.3, 0.3])                  # constant measurement: no R²
    rms, r2, n = flat.running_error()
    assert n == 2 and rms == pytest.approx(math.sqrt((0.04 + 0.01) / 2)) and math.isnan(r2)


@pytest.mark.parametrize('first_measured, first_anchor', [(0, 6), (10, 12)])
def test_reanchoring_schedule_and_state_equal_an_offline_free_run(first_measured, first_anchor):
    # Every `reanchor_every` estimates (retrying at every sample while the measured outputs are
    # not there), the recursion restarts from the measured outputs before the newest sample and
    # re-steps that sample: later estimates are the offline free run from those measurements.
    from piezo_narx_ros.ident.arx.model import ARXModel
    m = ARXModel(na=2, nb=2).set_coefficients(a=[-1.2, 0.5], b=[1e-8, 5e-9, -2e-9])
    m.fs, m.output_range = 2000.0, (-1e-3, 1e-3)
    n, every = 80, 7
    u = _u(n, 16)
    y_meas = m.simulate(u) + 4e-8 * np.sin(np.arange(n) / 5.0)   # the plant is not the model
    est = FreeRunEstimator(m, init='rest', reanchor_every=every)
    out = []
    for k in range(n):
        out += est.on_command(k * P, float(u[k]))
        if k >= first_measured:
            est.on_measurement(k * P, float(y_meas[k]))
    anchors, since = [], 0                  # the documented schedule, sample by sample
    for k in range(n):
        since += 1
        measured = all(j >= first_measured for j in range(k - m.ny, k))
        if since >= every and measured:
            anchors.append(k)
            since = 0
    assert est.stats.reanchors == len(anchors) and anchors[0] == first_anchor
    for k in range(n):
        before = [a for a in anchors if a < k]
        if not before:
            ref = m.simulate(u[:k + 1])[-1]
        else:
            a = before[-1]
            ref = m.simulate(u[a - m.n0:k + 1], y_meas[a - m.n0:a])[-1]
        assert out[k][1] == pytest.approx(ref, abs=1e-18, rel=1e-12), k
    FreeRunEstimator(m, init='rest', reanchor_every=1000)    # a long interval is a valid one
