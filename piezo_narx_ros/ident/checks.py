"""
Checks of the arrays every model family takes (below base.py and regressors.py: imports neither).

A bad array raises DataError with one line naming the argument and the problem.
"""
import numpy as np

from ..errors import DataError


def as_signal(x, name, n=None, min_len=1):
    """Return ``x`` as a contiguous 1-D float64 array, raising DataError on bad shape or values."""
    try:
        a = np.ascontiguousarray(x, dtype=np.float64)
    except (TypeError, ValueError):
        raise DataError(f'{name} must be a 1-D array of numbers') from None
    if a.ndim != 1:
        raise DataError(f'{name} must be 1-D, got shape {a.shape}')
    if n is not None and a.size != n:
        raise DataError(f'{name} has {a.size} samples, expected {n}')
    if a.size < min_len:
        raise DataError(f'{name} has {a.size} samples, need at least {min_len}')
    if not np.all(np.isfinite(a)):
        raise DataError(f'{name} contains NaN or infinite values')
    return a
