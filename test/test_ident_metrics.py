"""Goodness-of-fit figures on hand-computed values."""
import numpy as np
import pytest

from piezo_narx_ros.errors import DataError
from piezo_narx_ros.ident.validation import metrics


def test_known_values_by_hand():
    y = np.array([1.0, 2.0, 3.0, 4.0])          # mean 2.5, sum of squares about mean 5
    y_hat = np.array([1.0, 2.0, 3.0, 5.0])      # one error of 1
    assert metrics.r2(y, y_hat) == pytest.approx(1 - 1 / 5)
    assert metrics.rmse(y, y_hat) == pytest.approx(0.5)
    assert metrics.nrmse(y, y_hat) == pytest.approx(0.5 / np.sqrt(5 / 4))
    assert metrics.fit_percent(y, y_hat) == pytest.approx(100 * (1 - 1 / np.sqrt(5)))
    s = metrics.scores(y, y_hat)
    assert set(s) == {'r2', 'rmse', 'nrmse', 'fit_percent'}
    assert s['r2'] == pytest.approx(0.8)


def test_perfect_mean_and_worse_than_mean():
    y = np.sin(np.linspace(0, 6, 50))
    assert metrics.r2(y, y) == 1.0
    assert metrics.fit_percent(y, y) == 100.0
    assert metrics.r2(y, np.full_like(y, y.mean())) == pytest.approx(0.0, abs=1e-12)
    assert metrics.r2(y, -y) < 0


def test_start_skips_initialised_samples():
    # A model initialised from measurements copies y[:n0]; scoring from n0 must ignore them.
    y = np.array([10.0, -10.0, 1.0, 2.0, 3.0])
    y_hat = np.array([10.0, -10.0, 1.0, 2.0, 4.0])
    assert metrics.rmse(y, y_hat, start=2) == pytest.approx(np.sqrt(1 / 3))
    assert metrics.r2(y, y_hat, start=2) == pytest.approx(1 - 1 / 2)
    assert metrics.r2(y, y_hat) != pytest.approx(metrics.r2(y, y_hat, start=2))


def test_scores_apply_start_to_every_figure():
    y = np.array([10.0, -10.0, 1.0, 2.0, 3.0, 5.0])
    y_hat = np.array([0.0, 0.0, 1.0, 2.0, 4.0, 5.0])
    s = metrics.scores(y, y_hat, start=2)
    assert s == {'r2': metrics.r2(y, y_hat, 2), 'rmse': metrics.rmse(y, y_hat, 2),
                 'nrmse': metrics.nrmse(y, y_hat, 2),
                 'fit_percent': metrics.fit_percent(y, y_hat, 2)}
    full = metrics.scores(y, y_hat)
    assert all(s[k] != pytest.approx(full[k]) for k in s)


def test_single_and_integer_precision_inputs_are_scored_in_double():
    rng = np.random.default_rng(0)
    y = rng.standard_normal(1000).astype(np.float32)
    y_hat = (y + np.float32(1e-3) * rng.standard_normal(1000)).astype(np.float32)
    for name in ('r2', 'rmse', 'nrmse', 'fit_percent'):
        f = getattr(metrics, name)
        assert f(y, y_hat) == f(y.astype(np.float64), y_hat.astype(np.float64)), name
    yi, yhi = np.array([1, 2, 3, 4], dtype=np.int8), np.array([1, 2, 3, 127], dtype=np.int8)
    assert metrics.rmse(yi, yhi) == metrics.rmse(yi.astype(float), yhi.astype(float))


def test_two_samples_after_start_are_enough():
    y, y_hat = np.array([5.0, 1.0, 2.0]), np.array([0.0, 1.0, 3.0])
    assert metrics.rmse(y, y_hat, start=1) == pytest.approx(np.sqrt(0.5))
    assert metrics.r2(y, y_hat, start=1) == pytest.approx(1 - 1 / 0.5)


@pytest.mark.parametrize('y, y_hat, start, message', [
    (np.ones(5), np.ones(4), 0,
     r'metrics need two 1-D arrays of equal length, got shapes \(5,\) and \(4,\)'),
    (np.ones((2, 3)), np.ones((2, 3)), 0, r'got shapes \(2, 3\) and \(2, 3\)'),
    (np.arange(5.0), np.arange(5.0), 4, 'metrics need at least 2 samples after start=4, have 5'),
    (np.arange(5.0), np.arange(5.0), -1, 'after start=-1, have 5'),
])
@pytest.mark.parametrize('name', ['r2', 'rmse', 'nrmse', 'fit_percent'])
def test_bad_shapes_raise_with_the_problem(y, y_hat, start, message, name):
    anchored = f'^{message}$' if message.startswith('metrics') else message
    with pytest.raises(DataError, match=anchored):
        getattr(metrics, name)(y, y_hat, start)


@pytest.mark.parametrize('name, message', [
    ('r2', 'R² undefined: the measured output is constant'),
    ('nrmse', 'NRMSE undefined: the measured output is constant'),
    ('fit_percent', 'fit % undefined: the measured output is constant'),
])
def test_constant_output_raises(name, message):
    f = getattr(metrics, name)
    with pytest.raises(DataError) as exc:
        f(np.ones(10), np.zeros(10))
    assert str(exc.value) == message + ' (it has no variance to explain)'
    with pytest.raises(DataError):       # constant but for rounding: undefined too (issue 45)
        f(np.full(4000, 1e-6), np.zeros(4000))
    y = np.r_[np.ones(5), 2.0]          # constant except one sample: defined
    assert np.isfinite(f(y, y * 0.9))
