"""Goodness-of-fit figures on hand-computed values."""
import numpy as np
import pytest

from piezo_narx_ros.errors import DataError
from piezo_narx_ros.ident import metrics


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


@pytest.mark.parametrize('y, y_hat, start', [
    (np.ones(5), np.ones(4), 0),             # length mismatch
    (np.ones((2, 3)), np.ones((2, 3)), 0),   # not 1-D
    (np.arange(5.0), np.arange(5.0), 4),     # fewer than 2 samples left
])
def test_bad_shapes_raise(y, y_hat, start):
    with pytest.raises(DataError):
        metrics.r2(y, y_hat, start)


def test_constant_output_raises():
    with pytest.raises(DataError, match='constant'):
        metrics.r2(np.ones(10), np.zeros(10))
