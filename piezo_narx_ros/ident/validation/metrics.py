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
    # One channel of a Record ((N, 1)) is its N samples; several go through channel_scores.
    y = _one_column(np.asarray(y, dtype=np.float64))
    y_hat = _one_column(np.asarray(y_hat, dtype=np.float64))
    if y.ndim != 1 or y.shape != y_hat.shape:
        raise DataError(f'metrics need two 1-D arrays of equal length, got shapes {y.shape} '
                        f'and {y_hat.shape}')
    if start < 0 or y.size - start < 2:
        raise DataError(f'metrics need at least 2 samples after start={start}, have {y.size}')
    return y[start:], y_hat[start:]


def _one_column(a: np.ndarray) -> np.ndarray:
    return a[:, 0] if a.ndim == 2 and a.shape[1] == 1 else a


def is_constant(x) -> bool:
    """
    Return True when x does not vary beyond float rounding (spread <= 1e-9 of its magnitude).

    A flat record's mean is not exactly its value (rounding), so sum((y - mean)^2) is a tiny
    positive number, not 0: R² against it came out as -3.9e30 (issue 45). Such a record has no
    variance to explain: R², NRMSE and fit % are undefined.
    """
    x = np.asarray(x, dtype=np.float64)
    return bool(np.ptp(x) <= 1e-9 * np.max(np.abs(x)))


_CONSTANT = 'undefined: the measured output is constant (it has no variance to explain)'


def r2(y, y_hat, start: int = 0) -> float:
    """
    Coefficient of determination, paper eq. (3): 1 - sum((y - y_hat)^2) / sum((y - mean y)^2).

    1 is a perfect fit, 0 is no better than the mean, negative is worse than the mean.
    """
    y, y_hat = _pair(y, y_hat, start)
    ss_res = float(np.sum((y - y_hat) ** 2))
    ss_tot = float(np.sum((y - y.mean()) ** 2))
    if ss_tot == 0.0 or is_constant(y):
        raise DataError(f'R² {_CONSTANT}')
    return 1.0 - ss_res / ss_tot


def rmse(y, y_hat, start: int = 0) -> float:
    """Root-mean-square error, in the unit of y (m)."""
    y, y_hat = _pair(y, y_hat, start)
    return float(np.sqrt(np.mean((y - y_hat) ** 2)))


def nrmse(y, y_hat, start: int = 0) -> float:
    """RMSE divided by the standard deviation of the measured output (unit-free)."""
    y, y_hat = _pair(y, y_hat, start)
    std = float(np.std(y))
    if std == 0.0 or is_constant(y):
        raise DataError(f'NRMSE {_CONSTANT}')
    return float(np.sqrt(np.mean((y - y_hat) ** 2))) / std


def fit_percent(y, y_hat, start: int = 0) -> float:
    """Normalised fit in percent, 100 (1 - ||y - y_hat|| / ||y - mean y||) (100 = perfect)."""
    y, y_hat = _pair(y, y_hat, start)
    den = float(np.sqrt(np.sum((y - y.mean()) ** 2)))
    if den == 0.0 or is_constant(y):
        raise DataError(f'fit % {_CONSTANT}')
    return 100.0 * (1.0 - float(np.sqrt(np.sum((y - y_hat) ** 2))) / den)


def scores(y, y_hat, start: int = 0) -> dict[str, float]:
    """All four figures at once: {'r2', 'rmse' (m), 'nrmse', 'fit_percent'}."""
    return {'r2': r2(y, y_hat, start), 'rmse': rmse(y, y_hat, start),
            'nrmse': nrmse(y, y_hat, start), 'fit_percent': fit_percent(y, y_hat, start)}


def channel_scores(y, y_hat, names=None, per_output: bool | None = None) -> dict:
    """
    Scores of several outputs: y and y_hat (N, n_out) (or (N,) for one), names per output.

    One output: `scores` of that output (the one-axis figures, bit for bit). Several: pooled over
    outputs, R² = 1 - sum SSE / sum SST (each output's SST about its own mean), RMSE over every
    sample of every output (m), NRMSE = sqrt(sum SSE / sum SST), fit % = 100 (1 - NRMSE); and
    'per_output': [{'name', 'r2', 'rmse', 'nrmse', 'fit_percent'}] in output order.
    per_output: force the list on (True) or off (False); None: only for several outputs.
    """
    y = np.asarray(y, dtype=np.float64)
    y_hat = np.asarray(y_hat, dtype=np.float64)
    if y.ndim == 1:
        y, y_hat = y.reshape(-1, 1), y_hat.reshape(-1, 1)
    if y.ndim != 2 or y.shape != y_hat.shape:
        raise DataError(f'metrics need y and y_hat of equal shape (N, outputs), got {y.shape} '
                        f'and {y_hat.shape}')
    n_out = y.shape[1]
    names = list(names) if names is not None else [f'y{j + 1}' for j in range(n_out)]
    rows = [{'name': names[j], **scores(y[:, j], y_hat[:, j])} for j in range(n_out)]
    if n_out == 1:
        out = {k: v for k, v in rows[0].items() if k != 'name'}
    else:
        _pair(y[:, 0], y_hat[:, 0], 0)
        sse = np.sum((y - y_hat) ** 2, axis=0)
        sst = np.sum((y - y.mean(axis=0)) ** 2, axis=0)
        if float(sst.sum()) == 0.0 or all(is_constant(y[:, j]) for j in range(n_out)):
            raise DataError('R² undefined: every measured output is constant')
        ratio = float(sse.sum() / sst.sum())
        out = {'r2': 1.0 - ratio, 'rmse': float(np.sqrt(sse.sum() / y.size)),
               'nrmse': float(np.sqrt(ratio)), 'fit_percent': 100.0 * (1.0 - np.sqrt(ratio))}
    if per_output or (per_output is None and n_out > 1):
        out['per_output'] = rows
    return out
