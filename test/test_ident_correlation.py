"""Billings residual correlation tests: white residuals pass, residuals that keep dynamics fail."""
import numpy as np
import pytest

from piezo_narx_ros.errors import DataError
from piezo_narx_ros.ident.arx import ARXModel
from piezo_narx_ros.ident.correlation import TEST_NAMES, correlation_tests, cross_correlation


def test_cross_correlation_matches_direct_sum():
    rng = np.random.default_rng(1)
    a = rng.standard_normal(300)
    b = 0.7 * np.concatenate([np.zeros(3), a[:-3]]) + rng.standard_normal(300)
    lags, vals = cross_correlation(a, b, 6)
    a0, b0 = a - a.mean(), b - b.mean()
    den = np.sqrt(np.sum(a0 ** 2) * np.sum(b0 ** 2))
    for tau, v in zip(lags, vals):
        direct = sum(a0[k - tau] * b0[k] for k in range(300) if 0 <= k - tau < 300) / den
        assert v == pytest.approx(direct, abs=1e-12)
    assert lags[np.argmax(vals)] == 3      # b follows a by 3 samples


def test_band_is_calibrated_for_white_residuals():
    # Independent white sequences: about 5 % of tested lags fall outside ±1.96/sqrt(N).
    outside = tested = 0
    for seed in range(30):
        rng = np.random.default_rng(seed)
        res = correlation_tests(rng.standard_normal(4000), rng.uniform(-1, 1, 4000))
        assert res.band == pytest.approx(1.96 / np.sqrt(4000))
        outside += sum(t.n_outside for t in res.tests.values())
        tested += sum(t.n_tested for t in res.tests.values())
    assert tested == 30 * (20 + 40 + 40 + 40 + 20)
    assert 0.035 < outside / tested < 0.065


def test_white_residuals_pass_with_chance_tolerance():
    # With the 5 % of excursions expected by chance allowed (floor: 1 of 20, 2 of 40 lags) white
    # residuals pass almost always; strict passes far less often (0.95**140 for all five tests).
    tolerant = strict = 0
    for seed in range(20):
        rng = np.random.default_rng(100 + seed)
        e, u = rng.standard_normal(5000), rng.uniform(0, 100, 5000)
        tolerant += correlation_tests(e, u, max_outside_fraction=0.1).passed
        strict += correlation_tests(e, u).passed
    assert tolerant >= 15
    assert strict < tolerant


def test_one_large_excursion_fails_strict_and_tolerant_rules():
    rng = np.random.default_rng(7)
    n = 20000
    u = rng.uniform(-1, 1, n)
    e = rng.standard_normal(n) + 0.1 * np.concatenate([np.zeros(5), u[:-5]])  # leak at lag 5
    strict = correlation_tests(e, u)
    test = strict.tests['phi_ue']
    assert not test.passed and not strict.passed
    assert abs(test.values[test.lags == 5][0]) > 3.29 / np.sqrt(n)
    tolerant = correlation_tests(e, u, max_outside_fraction=0.1)
    assert tolerant.hard_band == pytest.approx(3.29 / np.sqrt(n))
    assert tolerant.tests['phi_ue'].n_outside <= 4      # within the count allowed ...
    assert not tolerant.tests['phi_ue'].passed          # ... but beyond the 99.9 % band


def test_coloured_residuals_fail_autocorrelation():
    rng = np.random.default_rng(3)
    w = rng.standard_normal(5000)
    e = w.copy()
    for k in range(1, e.size):
        e[k] += 0.5 * e[k - 1]
    res = correlation_tests(e, rng.uniform(-1, 1, 5000), max_outside_fraction=0.1)
    assert not res.tests['phi_ee'].passed
    assert res.tests['phi_ee'].values[1] == pytest.approx(0.5, abs=0.05)
    assert not res.passed


def test_linear_model_of_nonlinear_system_fails_nonlinear_tests():
    # y(k) = 0.5 y(k-1) + u(k-1) + 0.8 u(k-1)^2 + noise: an ARX fits the linear part only, so its
    # one-step residuals carry u^2 (Billings' motivating case) while a linear test alone is blind.
    rng = np.random.default_rng(5)
    n = 6000
    u = rng.uniform(-1, 1, n)
    y = np.zeros(n)
    for k in range(1, n):
        y[k] = 0.5 * y[k - 1] + u[k - 1] + 0.8 * u[k - 1] ** 2 + 0.05 * rng.standard_normal()
    model = ARXModel(na=1, nb=1).fit(u, y)
    resid = (y - model.predict(u, y))[1:]
    res = correlation_tests(resid, u[1:], max_outside_fraction=0.1)
    assert res.tests['phi_ue'].passed                  # linear test sees nothing
    assert not res.tests['phi_u2e'].passed             # u^2 left in the residual
    assert not res.passed


def test_correct_model_residuals_pass():
    rng = np.random.default_rng(11)
    n = 6000
    u = rng.uniform(-1, 1, n)
    y = np.zeros(n)
    for k in range(2, n):
        y[k] = 1.2 * y[k - 1] - 0.5 * y[k - 2] + u[k - 1] + 0.05 * rng.standard_normal()
    model = ARXModel(na=2, nb=1).fit(u, y)
    resid = (y - model.predict(u, y))[2:]
    res = correlation_tests(resid, u[2:], max_outside_fraction=0.1)
    assert res.passed, res.to_dict(with_values=False)
    assert set(res.verdicts()) == set(TEST_NAMES)


def test_constant_input_makes_input_tests_undefined():
    rng = np.random.default_rng(0)
    res = correlation_tests(rng.standard_normal(1000), np.ones(1000))
    assert not res.tests['phi_ue'].passed
    assert np.all(np.isnan(res.tests['phi_ue'].values))
    assert res.to_dict()['tests']['phi_ue']['values'][0] is None


@pytest.mark.parametrize('e, u, kwargs, match', [
    (np.zeros(100), np.zeros(99), {}, 'equal 1-D shape'),
    (np.r_[np.nan, np.zeros(199)], np.zeros(200), {}, 'NaN'),
    (np.zeros(50), np.zeros(50), {}, 'too few'),
    (np.zeros(200), np.zeros(200), {'max_lag': 0}, 'max_lag'),
    (np.zeros(200), np.zeros(200), {'max_outside_fraction': 1.0}, 'max_outside_fraction'),
])
def test_bad_input_raises(e, u, kwargs, match):
    with pytest.raises(DataError, match=match):
        correlation_tests(e, u, **kwargs)
