"""
Control of several axes (control/axes.py), without DDS.

A 2 x 2 ARX identified on the coupled two-axis cantilever: the vector inverse reaches its own
model's output on both axes at once (the coupling compensated: holding y at 0 while x moves
takes a y command), keeps every axis within its own limits and counts what it cannot reach; the
per-axis linear baseline ignores the coupling and misses by it. A model of one chain per axis is
inverted chain by chain after M^-1 (each chain its own one-axis controller): both axes tracked
with the coupling compensated, and every one-axis check (anti-phase, tracking) holds per axis.
"""
import numpy as np
import pytest

from piezo_narx_ros.control.axes import AxesController, AxisWatch, VectorInverse, static_gains
from piezo_narx_ros.counters import ERROR, OK
from piezo_narx_ros.errors import ConfigError

FS = 2000.0
T0 = 10**15


def test_static_gains_show_the_coupling_of_the_stage(arx2):
    gains, _ = static_gains(arx2)
    # config/plant_2axis.yaml: y moves by 0.12 of x's chain, x by 0.05 of y's.
    assert gains[1, 0] / gains[0, 0] == pytest.approx(0.12, abs=0.03)
    assert gains[0, 1] / gains[1, 1] == pytest.approx(0.05, abs=0.03)


def test_inverse_reaches_both_axes_and_compensates_the_coupling(arx2):
    inv = VectorInverse(arx2)
    for k in range(200):
        r = np.array([10e-6 * np.sin(k / 20.0), 0.0])      # move x, hold y still
        sol = inv.solve(r)
        assert sol.limit == 'reached'
        assert np.max(np.abs(inv.commit(sol.u) - r)) < 1e-15
    assert abs(sol.u[1]) > 1.0          # y is driven (V) to cancel what x does to it


def test_limits_per_axis_are_kept_and_misses_counted(arx2):
    ctl = AxesController(arx2, u_min=[-200.0, -5.0], u_max=[200.0, 5.0],
                         y_min=[-1e-4, -1e-4], y_max=[1e-4, 1e-4])
    out = [ctl.on_reference(T0 + k * 500_000, [0.0, 20e-6])[0][1] for k in range(50)]
    u = np.array(out)
    assert (u[:, 1] <= 5.0).all() and (u[:, 1] >= -5.0).all()
    assert ctl.stats.voltage_limited > 0 and ctl.stats.unreachable == ctl.stats.voltage_limited
    ctl.on_reference(T0 + 50 * 500_000, [np.nan, 0.0])      # a NaN axis: previous one held
    assert ctl.stats.rejected_nonfinite == 1


def test_inverse_tracks_its_model_and_the_linear_baseline_misses_the_coupling(arx2):
    n = 400
    ref = np.column_stack([10e-6 * np.sin(np.arange(n) / 15.0), 5e-6 * np.cos(np.arange(n) / 9.0)])
    miss = {}
    for mode in ('inverse', 'linear'):
        ctl = AxesController(arx2, mode=mode)
        u = np.array([ctl.on_reference(T0 + k * 500_000, ref[k])[0][1] for k in range(n)])
        y = arx2.simulate(u)                 # the model as the plant: sensorless, exact
        miss[mode] = np.sqrt(np.mean((y[100:] - ref[100:]) ** 2))
    assert miss['inverse'] < 1e-12
    assert miss['linear'] > 1e-7


def test_feedback_mode_is_refused_for_several_axes_without_chains(arx2):
    with pytest.raises(ConfigError, match='several axes.*one chain per axis'):
        AxesController(arx2, mode='inverse_feedback')
    with pytest.raises(ConfigError, match='only for a model of one chain per axis'):
        AxesController(arx2, mode='inverse', ki=10.0)


def _track(ctl, ref):
    return np.array([ctl.on_reference(T0 + k * 500_000, ref[k])[0][1] for k in range(len(ref))])


def test_chains_are_inverted_with_the_coupling_compensated(chains2):
    """Move x, hold y at 0: y needs a command against x's pull, the baseline leaves it."""
    n = 3000
    t = np.arange(n) / FS
    ref = np.column_stack([15e-6 * np.sin(2 * np.pi * 1.0 * t), np.zeros(n)])
    ctl = AxesController(chains2, mode='inverse')
    assert ctl.chains is not None and ctl.status()[0] == OK
    ctl.warm_up()                # leaves no trace: the same commands as without it
    u = _track(ctl, ref)
    assert np.array_equal(u, _track(AxesController(chains2, mode='inverse'), ref))
    y = chains2.simulate(u)                  # the model as the plant
    err = np.sqrt(np.mean((y[200:] - ref[200:]) ** 2, axis=0))
    base = AxesController(chains2, mode='linear')
    y_lin = chains2.simulate(_track(base, ref))
    err_lin = np.sqrt(np.mean((y_lin[200:] - ref[200:]) ** 2, axis=0))
    assert (err < 0.1 * err_lin).all(), (err, err_lin)
    assert err[1] < 0.02 * 0.12 * 15e-6 / np.sqrt(2)      # y held against 0.12 of x's motion
    assert np.std(u[:, 1]) > 0.5                        # by driving y (V)
    assert ctl.stats.commands == n and ctl.stats.unreachable == 0
    level, message, values = ctl.status()
    assert level == OK and 'coupling compensated' in message
    assert 'x.corr_ur' in values and 'y.static_gain_trusted' in values


def test_limits_per_axis_hold_for_chains(chains2):
    ctl = AxesController(chains2, u_min=[-200.0, -5.0], u_max=[200.0, 5.0], slew_rate=1e5)
    ref = np.column_stack([np.zeros(400), np.full(400, 20e-6)])
    u = _track(ctl, ref)
    assert (np.abs(u[:, 1]) <= 5.0).all() and (np.abs(np.diff(u[:, 0])) <= 50.0 + 1e-9).all()
    assert ctl.stats.voltage_limited > 0
    assert ctl.status()[0] > OK                 # the misses are a WARN, named by axis
    ctl.on_reference(T0 + 400 * 500_000, [np.nan, 0.0])
    assert ctl.stats.rejected_nonfinite == 1 and ctl.stats.commands == 401


def test_anti_phase_on_one_axis_is_an_error_naming_it(chains2):
    """A deflection sensor that reads y against its reference (wired backwards): ERROR on y."""
    n = 1200
    t = np.arange(n) / FS
    ref = np.column_stack([10e-6 * np.sin(2 * np.pi * 2.0 * t), 8e-6 * np.sin(2 * np.pi * 3 * t)])
    ctl = AxesController(chains2, mode='inverse')
    u = _track(ctl, ref)
    y = chains2.simulate(u)
    for k in range(n):
        ctl.on_measurement(T0 + k * 500_000, [y[k, 0], -y[k, 1]])
    level, message, values = ctl.status()
    assert level == ERROR and message.startswith('axis y: anti-phase'), message
    assert values['x.corr_ry'] > 0.9 and values['y.corr_ry'] < -0.9


def test_inverse_feedback_runs_a_pi_per_chain(chains2):
    """A stage 5 % stiffer than the model on both axes: the PI per chain removes the error."""
    n = 4000
    ref = np.column_stack([np.full(n, 10e-6), np.full(n, -6e-6)])
    out = {}
    for mode in ('inverse', 'inverse_feedback'):
        ctl = AxesController(chains2, mode=mode, ki=100.0)
        st = chains2.stepper()
        for k in range(n):
            (_, u), = ctl.on_reference(T0 + k * 500_000, ref[k])
            y = 0.95 * st.step(u)
            ctl.on_measurement(T0 + k * 500_000, y)
        out[mode] = np.abs(y - ref[-1])
    assert (out['inverse'] > 2e-7).all() and (out['inverse_feedback'] < 0.1 * out['inverse']).all()


def test_axis_watch_flags_commands_against_an_axis_gain():
    watch = AxisWatch(2, np.array([1e-4, 1e-4]), np.array([1.0, 1.0]), window=500)
    for k in range(400):
        r = np.array([1e-5 * np.sin(k / 20), 1e-5 * np.cos(k / 30)])
        watch.add(r, np.array([3e5 * r[0], -3e5 * r[1]]))
    problems = watch.problems()
    assert len(problems) == 1 and problems[0].startswith('axis 1: commands move against')


def test_vector_inverse_status_stays_ok_when_commands_follow_the_gain(arx2):
    ctl = AxesController(arx2, mode='inverse')
    k = np.arange(600)
    _track(ctl, np.column_stack([10e-6 * np.sin(k / 15.0), 5e-6 * np.cos(k / 9.0)]))
    assert ctl.status()[0] == OK and ctl.watch.signs.tolist() == [1.0, 1.0]


def _controlled_axes(model, ref, shift, measure=True):
    """Drive an AxesController on `model` whose plant is the model + a sensor offset per axis."""
    ctl = AxesController(model, mode='inverse')
    plant = model.stepper()
    u, y, y_model = [], [], []
    for k, r in enumerate(ref):
        (t, uk), = ctl.on_reference(T0 + k * 500_000, r)
        u.append(uk)
        y.append(np.asarray(plant.step(uk)) + shift)
        if measure:
            ctl.on_measurement(t, y[-1])
        y_model.append(ctl.inverse.y_model.copy())
    return ctl, np.array(u), np.array(y), np.array(y_model)


@pytest.mark.parametrize('policy', ['rest', 'offset', 'state'])
def test_the_vector_inverse_follows_the_stored_start_policy(tmp_path, arx2, policy):
    from piezo_narx_ros.ident.model_io import load_model, save_model
    from piezo_narx_ros.ident.state.start import policy_simulate
    model = load_model(save_model(arx2, tmp_path / 'a.json',
                                  start={'policy': policy, 'window_samples': 40}))
    n = 1500
    t = np.arange(n) / FS
    ref = np.column_stack([8e-6 * np.sin(2 * np.pi * 2.0 * t), 4e-6 * np.cos(2 * np.pi * t)])
    shift = np.array([1.5e-6, -1e-6])         # each sensor's zero moved since the fit
    ctl, u, y, y_model = _controlled_axes(model, ref, shift)
    assert (ctl.start_policy, ctl.start_window) == (policy, 0 if policy == 'rest' else 40)
    assert ctl.stats.start == ('rest' if policy == 'rest' else 'measurement')
    assert ctl.stats.unreachable == 0
    # From the window's last sample on, the controller's model is the offline free run of
    # what it sent under that policy.
    offline = policy_simulate(model, u, y, 40, policy)
    np.testing.assert_allclose(y_model[39:], offline[39:], rtol=0, atol=1e-15)
    # Only the offset policy sees the moved zeros: the deflection then follows the reference.
    miss = np.sqrt(np.mean((y - ref)[300:] ** 2, axis=0))
    if policy == 'offset':
        assert (miss < 1e-3 * np.abs(shift)).all()
    else:
        assert (miss > 0.5 * np.abs(shift)).all()
    assert ctl.status()[2]['start'] == ctl.stats.start


def test_axes_without_deflections_stay_from_rest_and_a_reset_stops_the_wait(tmp_path, arx2):
    from piezo_narx_ros.control.start import START_PATIENCE
    from piezo_narx_ros.ident.model_io import load_model, save_model
    model = load_model(save_model(arx2, tmp_path / 'a.json',
                                  start={'policy': 'offset', 'window_samples': 40}))
    ref = np.full((START_PATIENCE * 40 + 5, 2), 3e-6)
    ctl, _, _, _ = _controlled_axes(model, ref, np.array([1e-6, 1e-6]), measure=False)
    assert ctl.stats.start == 'rest (no measurement)'
    assert ctl.status()[0] == OK                  # a word in the counters, not a counter
    waiting = AxesController(model)
    assert waiting.stats.start == 'waiting'
    waiting.on_measurement(T0, [np.nan, 0.0])
    assert waiting.stats.measurements_rejected == 1
    waiting.request_reset()
    assert waiting.stats.start == 'rest' and not waiting._start.waiting
    assert AxesController(model, start_policy='rest').stats.start == 'rest'
    with pytest.raises(ConfigError, match='start_window must be at least'):
        AxesController(model, start_window=3)


def test_each_chain_starts_from_its_decoupled_window(tmp_path, chains2):
    from piezo_narx_ros.ident.model_io import load_model, save_model
    model = load_model(save_model(chains2, tmp_path / 'c.json',
                                  start={'policy': 'offset', 'window_samples': 40}))
    n = 600
    t = np.arange(n) / FS
    ref = np.column_stack([10e-6 * np.sin(2 * np.pi * t), 5e-6 * np.sin(2 * np.pi * 0.5 * t)])
    shift = np.array([1e-6, 2e-6])
    ctl, u, y, _ = _controlled_axes(model, ref, shift)
    assert [c.start_policy for c in ctl.chains.axes] == ['offset', 'offset']
    assert ctl.stats.start == 'measurement'
    # The chains' offsets are the decoupled shift (z = M^-1 y): the tracking error after the
    # window is far below the shift.
    offsets = np.array([c.inverse.offset for c in ctl.chains.axes])
    np.testing.assert_allclose(model.coupling_ @ offsets, shift, rtol=0.05)
    miss = np.sqrt(np.mean((y - ref)[300:] ** 2, axis=0))
    assert (miss < 0.2 * np.abs(shift)).all()
