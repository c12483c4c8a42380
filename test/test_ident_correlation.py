"""Billings residual correlation tests: white residuals pass, residuals that keep dynamics fail;
the AR noise model whitens what noise colours and hides nothing the input explains."""
import json
from math import comb

import numpy as np
import pytest

from piezo_narx_ros.errors import DataError
from piezo_narx_ros.ident.arx import ARXModel
from piezo_narx_ros.ident.correlation import TEST_NAMES, correlation_tests, cross_correlation
from piezo_narx_ros.ident.noise_model import ARNoiseModel, fit_ar_noise_model


def chance_pass_probability(n_tested, fraction=0.05):
    """P(a test of white residuals passes): at most floor(fraction n) lags beyond 1.96/sqrt(N)
    (probability 0.05 each) and none of them beyond 3.29/sqrt(N) (0.001)."""
    m = int(np.floor(fraction * n_tested))
    return sum(comb(n_tested, j) * 0.049 ** j * 0.95 ** (n_tested - j) for j in range(m + 1))


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


def test_white_residuals_pass_at_the_chance_rate_by_default():
    # Default rule: at most floor(0.05 x lags) excursions (1 of 20, 2 of 40), none beyond the
    # 99.9 % band. Each test of white residuals should then pass with the binomial probability
    # (0.73 over 20 lags, 0.66 over 40); strict passes far less often. Measured with 200 seeds:
    # 0.73, 0.69, 0.65, 0.70, 0.76 per test.
    n_runs = 60
    passes = dict.fromkeys(TEST_NAMES, 0)
    strict = tolerant = 0
    for seed in range(n_runs):
        rng = np.random.default_rng(100 + seed)
        e, u = rng.standard_normal(5000), rng.uniform(0, 100, 5000)
        res = correlation_tests(e, u)
        assert res.max_outside_fraction == 0.05
        for name, ok in res.verdicts().items():
            passes[name] += ok
        tolerant += res.passed
        strict += correlation_tests(e, u, max_outside_fraction=0.0).passed
    for name in TEST_NAMES:
        expected = chance_pass_probability(20 if name in ('phi_ee', 'phi_e_eu') else 40)
        # 3.3 standard errors of a binomial proportion over 60 runs
        assert abs(passes[name] / n_runs - expected) < 3.3 * np.sqrt(0.25 / n_runs), name
    assert strict < tolerant


def test_one_large_excursion_fails_strict_and_tolerant_rules():
    rng = np.random.default_rng(7)
    n = 20000
    u = rng.uniform(-1, 1, n)
    e = rng.standard_normal(n) + 0.1 * np.concatenate([np.zeros(5), u[:-5]])  # leak at lag 5
    strict = correlation_tests(e, u, max_outside_fraction=0.0)
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


# ------------------------------------------------------------------ noise model (noise_model.py)

def _oe_system(n, seed, nonlinear=0.8, noise=0.05):
    """Output-error system: x(k) = 0.5 x(k-1) + u(k-1) + c u(k-1)^2, measured y = x + white v."""
    rng = np.random.default_rng(seed)
    u = rng.uniform(-1, 1, n)
    x = np.zeros(n)
    for k in range(1, n):
        x[k] = 0.5 * x[k - 1] + u[k - 1] + nonlinear * u[k - 1] ** 2
    return u, x + noise * rng.standard_normal(n)


def _true_one_step(u, y, c=0.8):
    """One-step prediction of the TRUE structure from measured (noisy) past outputs."""
    pred = np.zeros_like(y)
    pred[1:] = 0.5 * y[:-1] + u[:-1] + c * u[:-1] ** 2
    return pred


def test_noise_model_whitens_output_noise_seen_through_the_output_lag():
    # The correct structure's one-step residual is v(k) - 0.5 v(k-1): coloured although nothing
    # is missing. An AR noise model fitted on the estimation half whitens the validation half to
    # within the test's resolution. (Not exactly: the AR truncation leaves 0.5^(p+1) at lag p+1,
    # and the filter's coefficient error adds ~1/sqrt(N_est) at lags <= p, so this whitened φεε
    # still fails the 0.05 rule in 34 of 40 seeds measured; docs/validation.md.)
    u, y = _oe_system(12000, seed=1)
    resid = (y - _true_one_step(u, y))[1:]
    est, val, u_val = resid[:6000], resid[6000:], u[1:][6000:]
    raw = correlation_tests(val, u_val).tests['phi_ee']
    assert raw.values[1] == pytest.approx(-0.4, abs=0.05)     # -θ/(1+θ²), θ = 0.5
    nm = fit_ar_noise_model(est, max_order=20)
    assert 2 <= nm.order <= 20
    assert nm.coef[0] == pytest.approx(-0.5, abs=0.1)   # AR expansion of 1/(1 - 0.5 q^-1)
    innov = nm.whiten(val)
    assert innov.size == val.size - nm.order
    res = correlation_tests(innov, u_val[nm.order:])
    whitened = np.abs(res.tests['phi_ee'].values[1:])
    assert whitened.max() < res.hard_band
    assert np.abs(raw.values[1:]).max() > 10 * whitened.max()


def test_noise_model_of_white_residuals_is_no_filter():
    for seed in range(5):
        nm = fit_ar_noise_model(np.random.default_rng(seed).standard_normal(5000), 20)
        assert nm.order == 0
        x = np.arange(10.0)
        np.testing.assert_array_equal(nm.whiten(x), x)


def test_noise_model_keeps_the_missing_nonlinear_term_visible():
    # ARX(1, 1) of the system above misses u^2: after whitening (process + noise model, as in
    # NARMAX) the input tests still see it, in free run and in one-step prediction alike.
    u, y = _oe_system(12000, seed=2)
    uest, yest, uval, yval = u[:6000], y[:6000], u[6000:], y[6000:]
    model = ARXModel(na=1, nb=1).fit(uest, yest)
    for resid_of in (lambda uu, yy: yy - model.simulate(uu, yy[:1]),
                     lambda uu, yy: yy - model.predict(uu, yy)):
        nm = fit_ar_noise_model(resid_of(uest, yest)[1:], 20)
        innov = nm.whiten(resid_of(uval, yval)[1:])
        res = correlation_tests(innov, uval[1 + nm.order:])
        assert not res.tests['phi_u2e'].passed
        assert not res.passed


def test_noise_model_cannot_absorb_an_input_leak():
    # A residual that the input explains stays correlated with it after any AR filter on the
    # residual alone: e = white + 0.1 u(k-5).
    rng = np.random.default_rng(7)
    n = 20000
    u = rng.uniform(-1, 1, n)
    e = rng.standard_normal(n) + 0.1 * np.concatenate([np.zeros(5), u[:-5]])
    nm = fit_ar_noise_model(e[:n // 2], 20)
    res = correlation_tests(nm.whiten(e[n // 2:]), u[n // 2 + nm.order:])
    assert not res.tests['phi_ue'].passed


def test_noise_model_round_trips_through_its_json_description():
    u, y = _oe_system(4000, seed=3)
    nm = fit_ar_noise_model((y - _true_one_step(u, y))[1:], 10)
    back = ARNoiseModel.from_dict(json.loads(json.dumps(nm.to_dict())))
    np.testing.assert_array_equal(back.coef, nm.coef)
    x = np.random.default_rng(0).standard_normal(100)
    np.testing.assert_array_equal(back.whiten(x), nm.whiten(x))
    for bad in ({**nm.to_dict(), 'order': nm.order + 1}, {**nm.to_dict(), 'coef': ['os']},
                {**nm.to_dict(), 'kind': 'ma'}, [1, 2]):
        with pytest.raises(DataError, match='malformed'):
            ARNoiseModel.from_dict(bad)


@pytest.mark.parametrize('e, kwargs, match', [
    (np.zeros((10, 10)), {}, '1-D'),
    (np.r_[np.nan, np.zeros(999)], {}, 'finite'),
    (np.zeros(100), {'max_order': 20}, 'too few'),
    (np.zeros(1000), {'max_order': -1}, 'max_order'),
    (np.zeros(1000), {'criterion': 'hq'}, 'criterion'),
])
def test_noise_model_bad_input_raises(e, kwargs, match):
    with pytest.raises(DataError, match=match):
        fit_ar_noise_model(e, **kwargs)
