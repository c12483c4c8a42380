"""
Goodness-of-fit figures for one-step prediction and free-run simulation.

All functions take the measured output `y` and the model output `y_hat` as 1-D arrays of the same
length (metres, or any unit: R², NRMSE and fit % are unit-free, RMSE has the unit of `y`). `start`
drops the first samples from the score: a model initialised from measured outputs reproduces them
exactly for k < n0, so scoring them would flatter it (the paper scores k >= n0).
"""
from __future__ import annotations

import numpy as np

from piezo_narx_ros.errors import DataError


def _pair(y, y_hat, start: int) -> tuple[np.ndarray, np.ndarray]:
    y = np.asarray(y, dtype=np.float64)
    y_hat = np.asarray(y_hat, dtype=np.float64)
    if y.ndim != 1 or y.shape != y_hat.shape:
        raise DataError(f'metrics need two 1-D arrays of equal length, got shapes {y.shape} '
                        f'and {y_hat.shape}')
    if start < 0 or y.size - start < 2:
        raise DataError(f'metrics need at least 2 samples after start={start}, have {y.size}')
    return y[start:], y_hat[start:]


def r2(y, y_hat, start: int = 0) -> float:
    """
    Coefficient of determination, paper eq. (3): 1 - sum((y - y_hat)^2) / sum((y - mean y)^2).

    1 is a perfect fit, 0 is no better than the mean, negative is worse than the mean.
    """
    y, y_hat = _pair(y, y_hat, start)
    ss_res = float(np.sum((y - y_hat) ** 2))
    ss_tot = float(np.sum((y - y.mean()) ** 2))
    if ss_tot == 0.0:
        raise DataError('R² undefined: the measured output is constant')
    return 1.0 - ss_res / ss_tot


def rmse(y, y_hat, start: int = 0) -> float:
    """Root-mean-square error, in the unit of y (m)."""
    y, y_hat = _pair(y, y_hat, start)
    return float(np.sqrt(np.mean((y - y_hat) ** 2)))


def nrmse(y, y_hat, start: int = 0) -> float:
    """RMSE divided by the standard deviation of the measured output (unit-free)."""
    y, y_hat = _pair(y, y_hat, start)
    std = float(np.std(y))
    if std == 0.0:
        raise DataError('NRMSE undefined: the measured output is constant')
    return float(np.sqrt(np.mean((y - y_hat) ** 2))) / std


def fit_percent(y, y_hat, start: int = 0) -> float:
    """Normalised fit in percent, 100 (1 - ||y - y_hat|| / ||y - mean y||) (100 = perfect)."""
    y, y_hat = _pair(y, y_hat, start)
    den = float(np.sqrt(np.sum((y - y.mean()) ** 2)))
    if den == 0.0:
        raise DataError('fit % undefined: the measured output is constant')
    return 100.0 * (1.0 - float(np.sqrt(np.sum((y - y_hat) ** 2))) / den)


def scores(y, y_hat, start: int = 0) -> dict[str, float]:
    """All four figures at once: {'r2', 'rmse' (m), 'nrmse', 'fit_percent'}."""
    return {'r2': r2(y, y_hat, start), 'rmse': rmse(y, y_hat, start),
            'nrmse': nrmse(y, y_hat, start), 'fit_percent': fit_percent(y, y_hat, start)}
