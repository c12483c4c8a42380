"""
Sensorless position control (piezo_narx_ros/control/).

The one-sample inverse of every model family, its limits and bounded work, and the controller's
modes, bad references, stamps, gaps, feedback and anti-windup, on the simulated plant without DDS.
"""
import math

import numpy as np
import pytest

from piezo_narx_ros.control import kernels as ck
from piezo_narx_ros.control.controller import PositionController
from piezo_narx_ros.control.inverse import (NOT_INVERTIBLE, REACHED, SLEW, VOLTAGE,
                                            ModelInverse, static_gain)
from piezo_narx_ros.errors import ConfigError
from piezo_narx_ros.estimator.toy import toy_narx
from piezo_narx_ros.ident.hysteresis import kernels as hk
from piezo_narx_ros.ident.arx.model import ARXModel
from piezo_narx_ros.ident.hysteresis.model import HysteresisNARX
from piezo_narx_ros.ident.narx.model import NARXNetwork
from piezo_narx_ros.plant import PiezoCantilever, generate

FS = 2000.0
PERIOD = int(1e9 / FS)


def random_hysteresis(seed=0):
    """Return a HysteresisNARX with random (not fitted) parameters and stable output dynamics."""
    m = HysteresisNARX(hidden=4, n_plays=5, n_duhem=1, n_lags=2, na=2, nb=2,
                       creep_taus=(0.01, 0.5))
    rng = np.random.default_rng(seed)
    theta = rng.normal(0.0, 1.0, m.n_params)
    lay, _ = hk.layout(m.hidden, m.n_inputs, m.n_duhem, len(m.creep_taus), m.na, m.nb)
    theta[slice(*lay['a'])] = [-1.2, 0.5]
    m.set_theta(theta, u_scale=100.0, y_scale=1e-5, radii=(np.arange(5) / 5.0) ** 2, fs=FS)
    m.input_range, m.output_range = (-100.0, 100.0), (-3e-5, 3e-5)
    return m


def arx(b=(2e-7, 1e-7), a=(-0.5,), c=0.0):
    m = ARXModel(na=len(a), nb=len(b) - 1).set_coefficients(a=a, b=b, c=c)
    m.fs, m.input_range, m.output_range = FS, (-100.0, 100.0), (-6e-5, 6e-5)
    return m


@pytest.fixture(scope='module')
def fitted():
    """Return a small HysteresisNARX fitted on 8 s of the identification protocol."""
    u = generate('protocol', FS, 8.0, 100.0, seed=3)
    y = PiezoCantilever(fs=FS, seed=3).run(u).y
    return HysteresisNARX(hidden=6, n_plays=8, max_iter=25, seed=0).fit(u, y, fs=FS)


FAMILIES = {'hysteresis': random_hysteresis, 'narx': toy_narx, 'arx': arx}


# ------------------------------------------------------------------------------------- peek
@pytest.mark.parametrize('family', FAMILIES)
def test_peek_is_the_next_step_without_committing_it(family):
    model = FAMILIES[family]()
    a, b = model.stepper(), model.stepper()
    rng = np.random.default_rng(1)
    for u in rng.uniform(-90, 90, 200):
        for trial in rng.uniform(-90, 90, 3):
            a.peek(trial)                     # tried and dropped: must leave no trace
        assert a.peek(u) == b.step(u) == a.step(u)


# ------------------------------------------------------------------------------------ inverse
@pytest.mark.parametrize('family', FAMILIES)
def test_inverse_hits_reachable_targets_of_every_family(family):
    model = FAMILIES[family]()
    inv = ModelInverse(model, u_min=-100.0, u_max=100.0)
    probe = model.stepper()
    rng = np.random.default_rng(2)
    worst = 0.0
    for k in range(300):
        u_true = float(np.clip(40 * np.sin(k / 15.0) + rng.normal(0, 5), -100, 100))
        target = probe.peek(u_true)          # an output the model surely reaches from here
        sol = inv.solve(target)
        assert -100.0 <= sol.u <= 100.0
        assert sol.evaluations <= 1 + ck.LOCAL_TRIES + inv.n_grid + inv.max_iter
        assert sol.achieved == pytest.approx(inv.stepper.peek(sol.u), abs=1e-18)
        worst = max(worst, abs(sol.miss))
        if sol.limit == REACHED:
            assert abs(sol.miss) <= inv.reach_tol
        probe.step(u_true)
        inv.commit(u_true)                    # both follow the same input: same state
    assert worst <= inv.reach_tol            # a reachable target is always reached


def test_quasi_static_target_is_reached_and_reported_exactly(fitted):
    inv = ModelInverse(fitted, target='quasi_static', slew_rate=1e5)
    probe = ModelInverse(fitted, target='quasi_static')
    for k in range(400):
        u_true = 70.0 * np.sin(k / 40.0)
        target = probe.value(u_true)
        sol = inv.solve(target)
        assert sol.achieved == inv.value(sol.u) and sol.limit == REACHED
        assert abs(sol.u - u_true) < 1e-3          # the quasi-static value is monotone in u
        inv.commit(u_true)
        probe.commit(u_true)


def test_the_advance_compensation_is_estimated_from_the_model_and_helps(fitted):
    tau = ModelInverse(fitted, target='quasi_static').estimate_advance()
    assert 0.1 < tau < 0.6              # measured 0.34: the sample is read after the hold
    assert ModelInverse(fitted, target='output').estimate_advance() == 0.0
    ref = 30e-6 * np.sin(2 * np.pi * 10.0 * np.arange(2000) / FS)
    err = {}
    for advance in (None, 0.0):
        ctl = PositionController(fitted, mode='inverse', slew_rate=1e5, advance=advance)
        _, y = drive(ctl, ref, PiezoCantilever(fs=FS, seed=7), measure=False)
        err[advance] = np.sqrt(np.mean((ref - y)[1000:] ** 2))
    assert err[None] < 0.5 * err[0.0]   # measured 49 vs 268 nm


def test_arx_inverse_is_the_closed_form():
    model = arx(b=(3e-7, -1e-7, 0.5e-7), a=(-0.6, 0.1), c=2e-7)
    inv = ModelInverse(model)
    rng = np.random.default_rng(3)
    for target in rng.uniform(-4e-5, 4e-5, 50):
        (ubuf, ybuf), _ = inv.stepper.kernel_state
        rest = model.c + model.b[1:] @ ubuf[::-1][:2] - model.a @ ybuf[::-1]
        u = (target - rest) / model.b[0]
        sol = inv.solve(target)
        assert sol.u == pytest.approx(u, rel=1e-6, abs=1e-6)
        inv.commit(sol.u)


def test_unreachable_targets_stop_at_the_limit_that_binds():
    inv = ModelInverse(arx(), u_min=-50.0, u_max=80.0, slew_rate=2e4)   # 10 V per sample
    sol = inv.solve(1.0)                    # one metre: beyond anything
    assert (sol.u, sol.limit) == (10.0, SLEW) and sol.miss < 0
    for _ in range(20):
        inv.commit(inv.solve(1.0).u)
    sol = inv.solve(1.0)
    assert (sol.u, sol.limit) == (80.0, VOLTAGE)
    assert inv.solve(-1.0).u == 70.0        # slew window below 80 V
    assert inv.solve(-1.0).limit == SLEW


def test_a_flat_model_keeps_the_input_and_says_so():
    inv = ModelInverse(arx(b=(0.0, 0.0), a=(-0.5,), c=1e-6))        # output ignores the input
    inv.commit(12.0)
    sol = inv.solve(5e-6)
    assert sol.u == 12.0 and sol.limit == NOT_INVERTIBLE
    assert sol.evaluations == 1 + inv.n_grid     # the grid found no bracket: stop there


def test_a_folding_model_takes_the_root_nearest_the_last_input():
    # y = u^2-like bump: NARX with two opposite sigmoids; the target is met at u ~ -40 and +40 V.
    m = NARXNetwork(nu=0, ny=1, hidden=2)
    m.set_weights(W1=[[4.0, 0.0], [-4.0, 0.0]], b1=[-1.6, -1.6], w2=[1.0, 1.0], b2=0.0,
                  normalisation=(0.0, 100.0, 0.0, 1e-6))
    m.fs = FS
    inv = ModelInverse(m, u_min=-100.0, u_max=100.0)
    target = float(m.stepper().peek(40.0))
    for start, sign in ((60.0, 1), (-70.0, -1)):
        inv.reset(u_past=None)
        inv.u_prev = start
        sol = inv.solve(target)
        assert sol.limit == REACHED and np.sign(sol.u) == sign
        assert abs(abs(sol.u) - 40.0) < 1e-3


def test_solve_never_leaves_the_window_for_any_target():
    inv = ModelInverse(random_hysteresis(4), u_min=-30.0, u_max=60.0, slew_rate=1e5)
    rng = np.random.default_rng(5)
    u_last = 0.0
    for target in np.r_[rng.normal(0, 3e-5, 300), [1e3, -1e3, 0.0]]:
        sol = inv.solve(target)
        assert -30.0 <= sol.u <= 60.0 and abs(sol.u - u_last) <= 50.0 + 1e-9
        u_last = inv.u_prev = sol.u
        inv.commit(sol.u)


def test_bad_inverse_settings_are_refused():
    with pytest.raises(ConfigError, match='quasi_static'):
        ModelInverse(arx(), target='quasi_static')
    with pytest.raises(ConfigError, match='u_min'):
        ModelInverse(arx(), u_min=5.0, u_max=5.0)
    with pytest.raises(ConfigError, match='target must be'):
        ModelInverse(arx(), target='exact')


def test_static_gain_is_the_line_through_the_model():
    g, c = static_gain(arx(b=(2e-7, 1e-7), a=(-0.5,), c=1e-7))
    assert g == pytest.approx(6e-7) and c == pytest.approx(2e-7)
    model = random_hysteresis(0)
    g, c = static_gain(model)
    u = 100.0 * np.sin(2 * np.pi * 0.5 * np.arange(8000) / FS)
    y = model.simulate(u)[4000:]
    fit = np.polyfit(u[4000:], y, 1)
    assert (g, c) == pytest.approx(tuple(fit))


def test_kernel_state_machine_bounds_evaluations():
    # A pathological output (NaN everywhere) still ends, at the previous input.
    sv, cand, g = ck.work_arrays()
    n = ck.begin(sv, cand, 1.0, -1.0, 1.0, 0.3, 1e-9, 1e-12, 30, 6)
    calls = 0
    while n:
        g[:n] = np.nan
        calls += n
        n = ck.update(sv, cand, g, n)
    u, miss, nev = ck.result(sv)
    assert u == 0.3 and math.isnan(miss) and nev == calls == 1 + 6


# --------------------------------------------------------------------------------- controller
def drive(ctl, ref, plant=None, measure=True, t0=0):
    """Run references through the controller (and the plant); returns (u, y_true) arrays."""
    u = np.empty(len(ref))
    y = np.full(len(ref), np.nan)
    for i, r in enumerate(ref):
        (t, u[i]), = ctl.on_reference(t0 + i * PERIOD, r)
        assert t == t0 + i * PERIOD
        if plant is not None:
            ym, y[i], _ = plant.step(u[i])
            if measure:
                ctl.on_measurement(t, ym)
    return u, y


def test_inverse_tracks_the_plant_far_better_than_the_static_line(fitted):
    ref = 30e-6 * np.sin(2 * np.pi * 1.0 * np.arange(4000) / FS)
    err = {}
    for mode in ('linear', 'inverse'):
        ctl = PositionController(fitted, mode=mode, slew_rate=1e5)
        _, y = drive(ctl, ref, PiezoCantilever(fs=FS, seed=7), measure=False)
        err[mode] = np.sqrt(np.mean((ref - y)[2000:] ** 2))
    # Measured with this 8 s model: linear 2.34 um, inverse 33 nm.
    assert err['linear'] > 1.5e-6
    assert err['inverse'] < err['linear'] / 8


def test_feedback_removes_a_model_error_the_inverse_alone_keeps(fitted):
    # A plant 10 % stiffer than the model: the inverse alone misses by ~10 % of the reference.
    ref = np.full(3000, 20e-6)
    err = {}
    for mode in ('inverse', 'inverse_feedback'):
        ctl = PositionController(fitted, mode=mode, slew_rate=1e5)
        plant = PiezoCantilever(fs=FS, seed=7)
        u = np.empty(ref.size)
        for i, r in enumerate(ref):
            (t, u[i]), = ctl.on_reference(i * PERIOD, r)
            ym, _, _ = plant.step(u[i])
            ctl.on_measurement(t, 1.1 * ym)
        err[mode] = abs(ref[-1] - 1.1 * ym)
    assert err['inverse'] > 1.5e-6
    assert err['inverse_feedback'] < 0.1e-6


def test_voltages_stay_in_the_limits_whatever_the_references(fitted):
    rng = np.random.default_rng(8)
    bad = rng.normal(0, 1e-4, 3000)
    bad[::7] = np.nan
    bad[::11] = np.inf
    bad[::13] = -1.0
    for mode in ('linear', 'inverse', 'inverse_feedback'):
        ctl = PositionController(fitted, mode=mode, u_min=-60.0, u_max=90.0, slew_rate=4e4)
        u, _ = drive(ctl, bad, PiezoCantilever(fs=FS, seed=1))
        assert np.all(np.isfinite(u)) and u.min() >= -60.0 and u.max() <= 90.0
        assert np.max(np.abs(np.diff(np.r_[0.0, u]))) <= 20.0 + 1e-9
        st = ctl.stats
        assert st.rejected_nonfinite == np.count_nonzero(~np.isfinite(bad))
        assert st.out_of_range == np.count_nonzero(np.isfinite(bad) &
                                                   ((bad < ctl.y_min) | (bad > ctl.y_max)))
        assert st.commands == bad.size


def test_a_nonfinite_reference_holds_the_previous_one(fitted):
    ctl = PositionController(fitted, mode='linear')
    (_, u1), = ctl.on_reference(0, 10e-6)
    (_, u2), = ctl.on_reference(PERIOD, float('nan'))
    assert u2 == u1 and ctl.stats.rejected_nonfinite == 1
    first = PositionController(fitted, mode='inverse')
    assert first.on_reference(0, float('nan')) == [(0, 0.0)]    # nothing to hold yet: 0 V


def test_bad_stamps_get_no_command_and_are_counted(fitted):
    ctl = PositionController(fitted, mode='inverse')
    t = [k * PERIOD for k in range(10)]
    out = []
    for k in range(5):
        out += ctl.on_reference(t[k], 5e-6)
    out += ctl.on_reference(t[2], 5e-6)                 # backwards
    out += ctl.on_reference(t[4] + 3600 * 10**9, 5e-6)  # an hour in the future
    for k in range(5, 10):
        out += ctl.on_reference(t[k], 5e-6)
    assert [s for s, _ in out] == t
    assert ctl.stats.stamp_outliers == 2 and ctl.stats.stream_restarts == 0


def test_a_gap_advances_the_model_with_the_held_command(fitted):
    ctl = PositionController(fitted, mode='inverse')
    twin = fitted.stepper()
    ref = 10e-6 * np.sin(np.arange(40) / 5.0)
    stamps = [k for k in range(40) if not 10 <= k < 15]      # 5 samples missing
    out = []
    for k in stamps:
        got = ctl.on_reference(k * PERIOD, ref[k])
        # The reference after the gap waits for the next one to confirm it (StampGate).
        assert len(got) == (0 if k == 15 else 2 if k == 16 else 1)
        out += got
    assert [t for t, _ in out] == [k * PERIOD for k in stamps]
    held = None
    for t, u in out:
        if t == 15 * PERIOD:
            for _ in range(5):
                twin.step(held)
        y_twin = twin.step(u)
        held = u
    assert ctl.stats.gaps == 1 and ctl.stats.filled == 5
    assert ctl.y_model == y_twin


def test_integrator_does_not_wind_up_against_a_limit(fitted):
    # A reference the voltage limit cannot reach for 1 s, then a reachable one.
    ref = np.r_[np.full(2000, 25e-6), np.full(1000, 5e-6)]
    ctl = PositionController(fitted, mode='inverse_feedback', u_min=-40.0, u_max=40.0,
                             slew_rate=1e5)
    _, y = drive(ctl, ref, PiezoCantilever(fs=FS, seed=2))
    assert ctl.stats.voltage_limited > 1500 and ctl.stats.windup_holds > 1500
    # Back in range: settled once the step's ringing has gone (0.1 s); an integrator wound up
    # by 1 s of ~10 um error at 100/s would hold ~1 mm (or its clamp) and take seconds to unwind.
    assert np.max(np.abs(ref[2200:] - y[2200:])) < 0.3e-6


def test_late_deflections_are_not_integrated(fitted):
    # Deflections arriving 50 samples (25 ms) late, as from a starved machine: integrating them
    # is feedback through a 50-sample delay, unstable at ki = 100/s (limit ki/fs < 0.031).
    ref = 20e-6 * np.sin(2 * np.pi * 2.0 * np.arange(6000) / FS)
    peak = {}
    for timeout in (10, 1000):
        ctl = PositionController(fitted, mode='inverse_feedback', slew_rate=1e5,
                                 feedback_timeout=timeout)
        plant = PiezoCantilever(fs=FS, seed=3)
        late, y = [], np.empty(ref.size)
        for i, r in enumerate(ref):
            (t, u), = ctl.on_reference(i * PERIOD, r)
            ym, y[i], _ = plant.step(u)
            late.append((t, ym))
            if len(late) > 50:
                ctl.on_measurement(*late.pop(0))
        peak[timeout] = np.max(np.abs(ref - y)[3000:])
        if timeout == 10:
            assert ctl.stats.measurements_late == ref.size - 50
    assert peak[10] < 0.5e-6            # measured 94 nm: the inverse alone, no oscillation
    assert peak[1000] > 5e-6            # measured 100 um: what integrating them did


def test_feedback_without_measurements_is_reported_stale(fitted):
    ctl = PositionController(fitted, mode='inverse_feedback')
    drive(ctl, np.full(50, 5e-6))
    assert ctl.stats.feedback_stale == 50
    ctl = PositionController(fitted, mode='inverse')
    drive(ctl, np.full(50, 5e-6))
    assert ctl.stats.feedback_stale == 0


def test_reset_restarts_the_model_from_rest(fitted):
    ctl = PositionController(fitted, mode='inverse')
    drive(ctl, np.full(100, 20e-6))
    ctl.request_reset()
    fresh = PositionController(fitted, mode='inverse')
    a, _ = drive(ctl, np.full(30, -5e-6), t0=100 * PERIOD)
    b, _ = drive(fresh, np.full(30, -5e-6))
    assert np.array_equal(a, b) and ctl.stats.requested_resets == 1


def test_bad_controller_settings_are_refused(fitted):
    with pytest.raises(ConfigError, match='mode must be'):
        PositionController(fitted, mode='exact')
    with pytest.raises(ConfigError, match='y_min'):
        PositionController(fitted, y_min=1e-5, y_max=-1e-5)
    with pytest.raises(ConfigError, match='kp, ki'):
        PositionController(fitted, ki=-1.0)


def test_health_reports_each_tick_since_the_last(fitted):
    from piezo_narx_ros.control.health import ControllerHealth
    from piezo_narx_ros.counters import OK, WARN
    ctl = PositionController(fitted, mode='inverse', u_max=30.0, advance=0.0)
    health = ControllerHealth(ctl)
    drive(ctl, np.full(20, 5e-6))
    assert health.tick(1)[0] == OK
    # Beyond 30 V, then a NaN: 35 um is held, so 11 commands miss.
    drive(ctl, np.r_[np.full(10, 35e-6), [np.nan]], t0=20 * PERIOD)
    level, message, values = health.tick(1)
    assert level == WARN and message.startswith('11 of 11 commands missed their target')
    assert '(+1 more)' in message and values['voltage_limited'] == 11
    assert values['rejected_nonfinite_since_last'] == 1
    drive(ctl, np.full(5, 5e-6), t0=31 * PERIOD)
    level, message, values = health.tick(1)
    assert level == OK and values['unreachable'] == 11, message   # cumulative count stays
    assert health.tick(2)[0] == WARN                           # two reference writers
