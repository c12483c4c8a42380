"""Identification core: regressors, ARX least squares, NARX training and free-run kernels."""
import numpy as np
import pytest
from scipy import signal

from piezo_narx_ros.errors import ConfigError, DataError
from piezo_narx_ros.ident.arx.model import ARXModel
from piezo_narx_ros.ident.validation.metrics import r2
from piezo_narx_ros.ident.narx.model import NARXNetwork
from piezo_narx_ros.ident.narx.regressors import lagged_regressors

# Light training budget: enough for the behaviours asserted here, a few seconds in all.
FAST = {'restarts': 2, 'restart_iter': 5, 'max_iter': 15, 'refine_iter': 10, 'n_segments': 20}


def multisine(n, fs, f_lo, f_hi, n_lines, seed):
    rng = np.random.default_rng(seed)
    t = np.arange(n) / fs
    f = np.linspace(f_lo, f_hi, n_lines)
    x = np.sin(2 * np.pi * f[None, :] * t[:, None] + rng.uniform(0, 2 * np.pi, n_lines)).sum(1)
    return x / np.abs(x).max()


def piezo_like(n, fs=2000.0, seed=0, amplitude=100.0):
    """
    Small stand-in for the piezo plant.

    Rate-independent Bouc-Wen hysteresis, two creep time constants and a lightly damped 765 Hz
    mode; multisine voltage (V) in, noiseless m out.
    """
    u = amplitude * multisine(n, fs, 1.0, 100.0, 50, seed)
    d_p, A, B, gamma = 5.2e-7, 0.35, 0.008, 0.004
    du = np.diff(u, prepend=0.0)
    h = np.empty(n)
    hk = 0.0
    for k in range(n):
        hk += A * d_p * du[k] - B * abs(du[k]) * hk - gamma * du[k] * abs(hk)
        h[k] = hk
    w = d_p * u - h
    z = w.copy()
    for gain, tau in ((0.008, 0.1), (0.008, 1.0)):
        a = np.exp(-1.0 / (fs * tau))
        z += gain * signal.lfilter([1 - a], [1, -a], w)
    wn, zeta = 2 * np.pi * 765.0, 0.02
    bd, ad, _ = signal.cont2discrete(([wn ** 2], [1, 2 * zeta * wn, wn ** 2]), 1 / fs,
                                     method='zoh')
    return u, signal.lfilter(np.squeeze(bd), ad, z)


# ---------------------------------------------------------------- regressors
def test_lagged_regressors_follow_eq1_order():
    u = np.arange(10.0)
    y = 100 + np.arange(10.0)
    X, t = lagged_regressors(u, y, nu=2, ny=3)
    assert X.shape == (7, 6) and t.shape == (7,)
    # first row is k = n0 = 3: u(3), u(2), u(1), y(2), y(1), y(0)
    np.testing.assert_array_equal(X[0], [3, 2, 1, 102, 101, 100])
    np.testing.assert_array_equal(X[-1], [9, 8, 7, 108, 107, 106])
    np.testing.assert_array_equal(t, y[3:])
    # Integer samples come back as float64 arrays (the kernels and torch expect doubles).
    Xi, ti = lagged_regressors([1, 2, 3, 4], [5, 6, 7, 8], nu=1, ny=1)
    assert Xi.dtype == ti.dtype == np.float64 and Xi.flags.c_contiguous
    np.testing.assert_array_equal(Xi, [[2, 1, 5], [3, 2, 6], [4, 3, 7]])


@pytest.mark.parametrize('u, y, nu, ny, match', [
    (np.zeros((5, 2, 1)), np.zeros(5), 1, 1, r'^u must be \(N,\) or \(N, channels\)'),
    (np.zeros(5), np.zeros(4), 1, 1, '^y has 4 samples, expected 5$'),
    (np.array([0, 1, np.nan, 2.0]), np.zeros(4), 1, 1, '^u contains NaN'),
    (np.zeros(4), np.array([0, 1, np.inf, 2.0]), 1, 1, '^y contains NaN or infinite'),
    (np.zeros(4), np.zeros((3, 2)), 1, 1, '^y has 3 samples, expected 4$'),
    (np.zeros(3), np.zeros(3), 4, 4, '^u has 3 samples, need at least 5$'),
    (np.zeros(9), np.zeros(9), 1, 0, 'ny >= 1'),
    (np.zeros(9), np.zeros(9), 1.5, 1, 'integers'),
    (np.zeros(9), np.zeros(9), 1, 2.5, 'integers'),
])
def test_lagged_regressors_reject_bad_input(u, y, nu, ny, match):
    with pytest.raises(DataError, match=match):
        lagged_regressors(u, y, nu, ny)


def test_predict_and_simulate_name_the_bad_argument():
    """
    Bad input to a fitted model's predict/simulate.

    One line naming the argument and what is wrong with it (ARX(2, 1): n0 = 2, a row needs 3
    samples).
    """
    model = ARXModel(na=2, nb=1).fit(*arx_system(200)[:2])
    u = np.zeros(10)
    cases = [
        (lambda: model.predict(u[:2], u[:2]), '^u has 2 samples, need at least 3$'),
        (lambda: model.predict(u, u[:9]), '^y has 9 samples, expected 10$'),
        (lambda: model.predict(u, np.r_[u[:9], np.nan]), '^y contains NaN'),
        (lambda: model.predict(np.r_[np.nan, u[1:]], u), '^u contains NaN'),
        (lambda: model.simulate(np.r_[u[:9], np.inf]), '^u contains NaN or infinite'),
        (lambda: model.simulate(np.r_[u[:9], np.inf], u[:2]), '^u contains NaN or infinite'),
        (lambda: model.simulate(u, u[:3]), '^y0 has 3 samples, expected 2$'),
        (lambda: model.simulate(u[:1], u[:2]), '^u has 1 samples, need at least 2$'),
    ]
    for call, match in cases:
        with pytest.raises(DataError, match=match):
            call()
    assert model.predict(u[:3], u[:3]).shape == (3,)     # exactly n0 + 1 samples is enough
    assert model.simulate(u[:2], u[:2]).shape == (2,)


# ---------------------------------------------------------------- ARX
def arx_system(n=3000, seed=1):
    a_true, b_true, c_true = np.array([-1.5, 0.7]), np.array([0.5, 0.3, -0.2]), 0.01
    u = np.random.default_rng(seed).standard_normal(n)
    y = signal.lfilter(b_true, np.r_[1.0, a_true], u) + c_true / (1 + a_true.sum())
    return u, y, a_true, b_true, c_true


def test_arx_recovers_true_coefficients_of_noiseless_system():
    u, y, a_true, b_true, c_true = arx_system()
    m = ARXModel(na=2, nb=2).fit(u, y, fs=100.0)
    np.testing.assert_allclose(m.a, a_true, atol=1e-9)
    np.testing.assert_allclose(m.b, b_true, atol=1e-9)
    assert m.c == pytest.approx(c_true, abs=1e-9)
    assert (m.nu, m.ny, m.n0, m.n_params, m.fs) == (2, 2, 2, 6, 100.0)
    assert m.input_range == (u.min(), u.max())
    # the noiseless system is reproduced in free run from measured initial outputs
    np.testing.assert_allclose(m.simulate(u, y[:2]), y, rtol=0, atol=1e-9)


def test_arx_without_intercept_and_rest_start():
    u, y, a_true, b_true, _ = arx_system()
    y = signal.lfilter(b_true, np.r_[1.0, a_true], u)      # from rest, no offset
    m = ARXModel(na=2, nb=2, fit_intercept=False).fit(u, y)
    assert m.c == 0.0 and m.n_params == 5
    np.testing.assert_allclose(m.simulate(u), y, atol=1e-9)  # y0=None: everything before k=0 is 0


def test_arx_predict_simulate_stepper_agree():
    u, y, *_ = arx_system(500)
    m = ARXModel(na=3, nb=1).fit(u, y + 0.01 * np.sin(np.arange(500)))
    n0 = m.n0
    p = m.predict(u, y)
    np.testing.assert_array_equal(p[:n0], y[:n0])
    X, _ = lagged_regressors(u, y, m.nu, m.ny)
    np.testing.assert_allclose(p[n0:], X @ np.r_[m.b, -m.a] + m.c, atol=1e-12)
    sim = m.simulate(u, y[:n0])
    st = m.stepper(u[n0 - m.nu:n0], y[n0 - m.ny:n0])
    stepped = np.array([st.step(x) for x in u[n0:]])
    np.testing.assert_allclose(stepped, sim[n0:], rtol=0, atol=1e-12)


@pytest.mark.parametrize('make', ['arx', 'narx'])
def test_step_many_gives_the_numbers_of_single_steps_and_refuses_before_stepping(make):
    u, y, *_ = arx_system(600)
    m = ARXModel(na=3, nb=2).fit(u, y) if make == 'arx' else random_network()
    one, many = m.stepper(), m.stepper()
    one.offset = many.offset = 2e-7
    expect = np.array([one.step(x) for x in u])
    got = np.concatenate([many.step_many(u[:7]), many.step_many(u[7:8]),
                          many.step_many(u[8:8]), many.step_many(u[8:])])
    assert np.array_equal(got, expect)                 # bit for bit, offset included
    assert np.array_equal(many.y_past, one.y_past) and np.array_equal(many.u_past, one.u_past)
    before = many.y_past
    with pytest.raises(DataError, match=r'finite voltage, got nan at index 2'):
        many.step_many([1.0, 2.0, np.nan])
    for bad in ([np.inf, -np.inf], np.r_[np.zeros(99), -np.inf]):   # short and long batches
        with pytest.raises(DataError, match='finite voltage, got -?inf at index'):
            many.step_many(bad)
    with pytest.raises(DataError, match=r'must be 1-D \(n,\), got shape \(2, 2\)'):
        many.step_many(np.zeros((2, 2)))
    assert np.array_equal(many.y_past, before)         # nothing stepped
    # Finite inputs whose sum overflows are inputs all the same.
    assert np.isfinite(m.stepper().step_many([1.7e308, 1.7e308])).shape == (2,)


@pytest.mark.parametrize('nu, ny, hidden', [(0, 1, 3), (4, 4, 10), (2, 6, 17)])
def test_narx_batches_give_the_free_runs_bits(nu, ny, hidden):
    # step_many's kernel sums input by input across the units (narx_run): the same bits as the
    # unit-by-unit evaluation of simulate and step, and the same histories after it.
    m = random_network(nu, ny, hidden, seed=nu + ny)
    u = np.random.default_rng(1).uniform(-2.0, 4.0, 500)
    one, many = m.stepper(), m.stepper()
    got = np.concatenate([many.step_many(u[k:k + 20]) for k in range(0, u.size, 20)])
    assert np.array_equal(got, m.simulate(u))
    assert np.array_equal(got, [one.step(x) for x in u])
    assert np.array_equal(many.y_past, one.y_past) and np.array_equal(many.u_past, one.u_past)


# ---------------------------------------------------------------- NARX: free-run kernels
def random_network(nu=3, ny=2, hidden=6, seed=0):
    rng = np.random.default_rng(seed)
    d = nu + 1 + ny
    W1 = rng.normal(0, 0.5, (hidden, d))
    W1[:, nu + 1:] *= 0.3                          # mild output feedback keeps the free run tame
    return NARXNetwork(nu, ny, hidden).set_weights(W1, rng.normal(0, 0.5, hidden),
                                                   rng.normal(0, 0.5, hidden), 0.1,
                                                   (1.0, 2.0, -3e-6, 4e-6))


def test_narx_predict_matches_network_formula():
    m = random_network()
    rng = np.random.default_rng(3)
    u, y = rng.normal(1, 2, 300), rng.normal(-3e-6, 4e-6, 300)
    X, _ = lagged_regressors(u, y, m.nu, m.ny)
    um, us, ym, ys = m.normalisation
    n_u = m.nu + 1
    Xn = np.hstack([(X[:, :n_u] - um) / us, (X[:, n_u:] - ym) / ys])
    expected = ym + ys * (1 / (1 + np.exp(-(Xn @ m.W1.T + m.b1))) @ m.w2 + m.b2)
    p = m.predict(u, y)
    np.testing.assert_array_equal(p[:m.n0], y[:m.n0])
    np.testing.assert_allclose(p[m.n0:], expected, rtol=1e-12, atol=1e-20)


def test_narx_simulate_and_stepper_agree_to_1e12():
    m = random_network()
    u = 3 * multisine(2000, 2000.0, 1, 200, 20, 5)
    y = m.simulate(u)                                   # from rest
    n0 = m.n0
    sim = m.simulate(u, y[:n0])
    np.testing.assert_allclose(sim, y, rtol=0, atol=1e-12)
    st = m.stepper(u[n0 - m.nu:n0], y[n0 - m.ny:n0])
    stepped = np.array([st.step(x) for x in u[n0:]])
    np.testing.assert_allclose(stepped, sim[n0:], rtol=0, atol=1e-12)
    # from rest the stepper equals simulate(u, y0=None) over all N samples
    st.reset()
    np.testing.assert_allclose([st.step(x) for x in u], y, rtol=0, atol=1e-12)
    # free run feeds back its own outputs: the first simulated sample equals a one-step prediction
    assert m.predict(u, y)[n0] == pytest.approx(sim[n0], abs=1e-18)


def test_stepper_history_and_bad_input():
    m = random_network()
    st = m.stepper()
    st.step(1.0)
    st.step(2.0)
    np.testing.assert_array_equal(st.u_past, [0.0, 1.0, 2.0])
    assert st.y_past.shape == (2,)
    with pytest.raises(DataError, match='u_past must hold 3'):
        m.stepper(u_past=[1.0, 2.0])
    with pytest.raises(DataError, match='y_past contains NaN'):
        m.stepper(y_past=[np.nan, 0.0])
    before = st.y_past
    with pytest.raises(DataError, match='finite voltage'):
        st.step(float('nan'))
    np.testing.assert_array_equal(st.y_past, before)        # a bad sample leaves the state alone
    np.testing.assert_array_equal(st.u_past, [0.0, 1.0, 2.0])


def test_narx_rejects_bad_construction_and_unfitted_use():
    with pytest.raises(ConfigError, match='unknown training option'):
        NARXNetwork(restartz=3)
    with pytest.raises(ConfigError, match='segment_length must be an integer >= 1'):
        NARXNetwork(segment_length=0)
    with pytest.raises(ConfigError, match='val_fraction'):
        NARXNetwork(val_fraction=0.9)
    with pytest.raises(DataError, match='hidden must be a positive integer'):
        NARXNetwork(hidden=0)
    with pytest.raises(DataError, match='no weights yet'):
        NARXNetwork().simulate(np.zeros(10))
    with pytest.raises(DataError, match='W1'):
        NARXNetwork(2, 2, 3).set_weights(np.zeros((3, 4)), np.zeros(3), np.zeros(3), 0,
                                         (0, 1, 0, 1))
    with pytest.raises(DataError, match='constant'):
        NARXNetwork(**FAST).fit(np.ones(500), np.arange(500.0))
    with pytest.raises(DataError, match='NaN'):
        NARXNetwork(**FAST).fit(np.r_[np.nan, np.ones(499)], np.arange(500.0))
    with pytest.raises(DataError, match='both u_val and y_val'):
        NARXNetwork(**FAST).fit(np.arange(500.0), np.arange(500.0), u_val=np.arange(50.0))


def test_narx_defaults_and_option_limits():
    m = NARXNetwork()
    assert (m.nu, m.ny, m.hidden, m.seed, m.n0) == (4, 4, 10, 0, 4)   # the paper's 4/4/10
    assert m.training_info_ == {}
    assert NARXNetwork(hidden=1).hidden == 1
    for ok in (0.0, 0.5):
        assert NARXNetwork(val_fraction=ok).training_options['val_fraction'] == ok
    for bad in ({'restarts': True}, {'val_fraction': False}, {'val_fraction': 0.51},
                {'max_iter': 2.0}):
        with pytest.raises(ConfigError, match='training option'):
            NARXNetwork(**bad)


def test_narx_weights_are_checked_one_by_one():
    H, good = 3, {'W1': np.zeros((3, 4)), 'b1': np.zeros(3), 'w2': np.zeros(3), 'b2': 0.5,
                  'normalisation': (0.0, 1.0, 0.0, 1.0)}
    m = NARXNetwork(1, 2, H).set_weights(**good)
    assert m.b2 == 0.5
    for name, value, match in (('b1', np.zeros(4), 'b1'), ('w2', np.zeros(2), 'w2'),
                               ('b2', np.zeros(2), 'b2 size 2'),
                               ('normalisation', (0.0, 0.0, 0.0, 1.0), 'u_std > 0'),
                               ('normalisation', (0.0, 1.0, 0.0, 0.0), 'y_std > 0')):
        with pytest.raises(DataError, match=match):
            NARXNetwork(1, 2, H).set_weights(**{**good, name: value})
    for name in ('W1', 'b1', 'w2', 'normalisation'):
        bad = np.array(good[name], dtype=float)
        bad.flat[-1] = np.nan
        with pytest.raises(DataError, match=f'NARX weight {name} contains NaN'):
            NARXNetwork(1, 2, H).set_weights(**{**good, name: bad})


def test_narx_weights_given_as_integers_are_kept_as_float64(tmp_path):
    # A model file holds float64 arrays only: weights typed as integers must not produce a file
    # that its own loader refuses.
    from piezo_narx_ros.ident.model_io import load_model, save_model
    m = NARXNetwork(0, 1, 2).set_weights([[1, 0], [0, 1]], [1, 2], [3, 4], 1, (0, 1, 0, 2))
    for name in ('W1', 'b1', 'w2', 'normalisation'):
        assert getattr(m, name).dtype == np.float64, name
    back = load_model(save_model(m, tmp_path / 'int.json'))
    assert np.array_equal(back.simulate(np.arange(5.0)), m.simulate(np.arange(5.0)))


def test_narx_fit_record_length_several_records_and_validation_scores():
    u, y = piezo_like(4000, seed=5)
    n0 = 2
    with pytest.raises(DataError, match='need at least 22'):
        NARXNetwork(2, 2, 3, **FAST).fit(u[:21], y[:21])
    NARXNetwork(2, 2, 3, **FAST).fit(u[:22], y[:22])                 # n0 + 20 samples
    alt = np.tile([1.0, -1.0], 100)                                   # std exactly 1
    NARXNetwork(2, 2, 3, **FAST).fit(np.sin(np.arange(200.0)), alt)
    # Two records are both trained on: not the first alone.
    both = NARXNetwork(2, 2, 3, **FAST).fit([u[:2000], u[2000:]], [y[:2000], y[2000:]])
    first = NARXNetwork(2, 2, 3, **FAST).fit([u[:2000]], [y[:2000]])
    assert not np.array_equal(both.W1, first.W1)
    info = both.training_info_
    assert info['n_records'] == 2 and info['n_train'] + info['n_holdout'] == 4000
    t0 = __import__('time').perf_counter()
    m = NARXNetwork(2, 2, 3, **FAST).fit(u[:3000], y[:3000], u_val=u[3000:], y_val=y[3000:])
    wall = __import__('time').perf_counter() - t0
    info = m.training_info_
    assert 0.0 < info['fit_seconds'] <= wall
    assert info['val_r2_predict'] == pytest.approx(
        r2(y[3000 + n0:], m.predict(u[3000:], y[3000:])[n0:]), rel=1e-12)
    assert info['val_r2_simulate'] == pytest.approx(
        r2(y[3000 + n0:], m.simulate(u[3000:], y[3000:3000 + n0])[n0:]), rel=1e-12)
    with np.errstate(divide='ignore', invalid='ignore'):   # one scored sample: R² undefined
        m.fit(u[:3000], y[:3000], u_val=u[3000:3000 + n0 + 1], y_val=y[3000:3000 + n0 + 1])
    for u_val, y_val, match in ((u[3000:3000 + n0], y[3000:3000 + n0], 'u_val has 2 samples'),
                                (np.r_[np.nan, u[3001:3100]], y[3000:3100], 'u_val contains'),
                                (u[3000:3100], y[3000:3099], 'y_val has 99 samples')):
        with pytest.raises(DataError, match=match):
            NARXNetwork(2, 2, 3, **FAST).fit(u[:3000], y[:3000], u_val=u_val, y_val=y_val)


# ---------------------------------------------------------------- NARX: training
def test_narx_identifies_known_nonlinear_narx_system():
    """
    Data from a known NARX network (teacher).

    A student of the same size must reproduce it in free run on fresh input.
    """
    teacher = random_network(nu=2, ny=2, hidden=4, seed=7)
    u = 2 * multisine(6000, 1000.0, 0.5, 150, 40, 11) + 1.0
    y = teacher.simulate(u)
    u_val = 2 * multisine(3000, 1000.0, 0.5, 150, 40, 12) + 1.0
    y_val = teacher.simulate(u_val)
    m = NARXNetwork(2, 2, 4, seed=0, **FAST).fit(u, y, u_val, y_val, fs=1000.0)
    y_sim = m.simulate(u_val, y_val[:2])         # started from measured outputs, as in the paper
    assert r2(y_val[2:], y_sim[2:]) > 0.99999
    assert m.training_info_['val_r2_simulate'] == pytest.approx(r2(y_val[2:], y_sim[2:]))
    assert m.fs == 1000.0 and m.n_params == 4 * 7 + 1


def test_narx_fits_hysteretic_piezo_like_plant_in_free_run():
    """
    Hysteresis + creep + lightly damped mode at 2 kHz.

    The default (fast) training reaches a free-run R^2 of 0.9999 on a held-out half, where the best
    linear ARX model stays far below.
    """
    u, y = piezo_like(24000)
    ue, ye, uv, yv = u[:12000], y[:12000], u[12000:], y[12000:]
    m = NARXNetwork(4, 4, 10, seed=0).fit(ue, ye)
    r2_narx = r2(yv[4:], m.simulate(uv, yv[:4])[4:])
    arx = ARXModel(4, 4).fit(ue, ye)
    r2_arx = r2(yv[4:], arx.simulate(uv, yv[:4])[4:])
    assert r2_narx > 0.9999, r2_narx
    assert r2_arx < 0.999
    assert m.training_info_['selected_stage'] in ('one-step', 'simulation')


def test_narx_fit_is_deterministic_for_a_seed():
    u, y = piezo_like(4000, seed=3)
    a = NARXNetwork(2, 2, 5, seed=4, **FAST).fit(u, y)
    b = NARXNetwork(2, 2, 5, seed=4, **FAST).fit(u, y)
    c = NARXNetwork(2, 2, 5, seed=5, **FAST).fit(u, y)
    for name in ('W1', 'b1', 'w2', 'normalisation'):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert a.b2 == b.b2
    assert not np.array_equal(a.W1, c.W1)


def output_error_system(n, seed, noise):
    """
    Simulate a saturating nonlinearity into a lightly damped second-order filter.

    Then white sensor noise of `noise` x the output's std: (u, noiseless x, measured y). Its
    one-step regressors hold noisy past outputs, so a one-step (equation-error) fit is biased; a
    simulation-error fit is not: the textbook case where the refinement must help.
    """
    rng = np.random.default_rng(seed)
    u = signal.lfilter([0.5], [1, -0.5], rng.uniform(-1, 1, n))
    x = signal.lfilter([0, 0.3], [1, -1.5, 0.7], np.tanh(2 * u))
    return u, x, x + noise * np.std(x) * rng.standard_normal(n)


@pytest.mark.parametrize('seed', [0, 1, 2])
def test_simulation_refinement_is_selected_where_one_step_training_is_biased(seed):
    # Measured (4 seeds): one-step fits run free at 40-41 % NRMSE against the noiseless output
    # of fresh data, refined ones at 4-7 %; the held-out free-run MSE falls 0.24 -> 0.085, the
    # sensor-noise floor 0.09 (normalised). A training change that never keeps the refinement,
    # or a refinement that does not lower the free-run error, fails here.
    u, _, y = output_error_system(4000, seed, noise=0.3)
    u_new, x_new, _ = output_error_system(4000, 100 + seed, noise=0.0)
    one = NARXNetwork(2, 2, 4, seed=seed, **{**FAST, 'refine_iter': 0}).fit(u, y)
    ref = NARXNetwork(2, 2, 4, seed=seed, **{**FAST, 'refine_iter': 15}).fit(u, y)
    i1, i2 = one.training_info_, ref.training_info_
    assert i1['selected_stage'] == 'one-step' and 'refine_iterations' not in i1
    assert i2['selected_stage'] == 'simulation' and i2['refine_iterations'] >= 1
    assert i2['holdout_mse_freerun'] < 0.5 * i2['holdout_mse_freerun_stage1']
    assert i2['holdout_mse_freerun_stage1'] == pytest.approx(i1['holdout_mse_freerun'])

    def nrmse(model):
        return np.sqrt(np.mean((model.simulate(u_new) - x_new) ** 2)) / np.std(x_new)
    assert nrmse(one) > 0.25 and nrmse(ref) < 0.15, (nrmse(one), nrmse(ref))


def test_training_jacobians_match_finite_differences():
    """The one-step Jacobian and the recursive free-run sensitivity used by LM are exact."""
    from piezo_narx_ros.ident.narx import training

    rng = np.random.default_rng(0)
    nu, ny, H = 2, 3, 4
    d = nu + 1 + ny
    P = training._n_params(H, d)
    theta = rng.normal(0, 0.6, P)
    un, yn = rng.standard_normal(400), 0.3 * rng.standard_normal(400)
    starts, L = np.array([5, 60, 200]), 30

    def free_run(th):
        J, e = np.empty((starts.size * L, P)), np.empty(starts.size * L)
        training._segments(un, yn, starts, L, nu, ny, th, H, J, e, True)
        return J, e

    def one_step(th):
        X, t = lagged_regressors(un, yn, nu, ny)
        J, e = np.empty((X.shape[0], P)), np.empty(X.shape[0])
        training._onestep_jac(X, t, th, H, J, e)
        return J, e

    for fn in (free_run, one_step):
        J, _ = fn(theta)
        num = np.empty_like(J)
        for p in range(P):
            step = np.zeros(P)
            step[p] = 1e-6
            # e = y - yhat, so d yhat / d theta = -(d e / d theta)
            num[:, p] = -(fn(theta + step)[1] - fn(theta - step)[1]) / 2e-6
        np.testing.assert_allclose(J, num, rtol=1e-5, atol=1e-7)
    # the free-run errors equal the model's own free run from measured outputs
    _, e = free_run(theta)
    W1, b1, w2, b2 = training._unpack(theta, H, d)
    m = NARXNetwork(nu, ny, H).set_weights(W1, b1, w2, b2, (0.0, 1.0, 0.0, 1.0))
    s = starts[1]
    sim = m.simulate(un[s - 3:s + L], yn[s - 3:s])[3:]
    np.testing.assert_allclose(yn[s:s + L] - sim, e[L:2 * L], atol=1e-12)
