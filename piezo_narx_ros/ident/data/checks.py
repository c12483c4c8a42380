"""
Checks of the arrays every model family takes (below base.py and regressors.py: imports neither).

A bad array raises DataError with one line naming the argument and the problem.
"""
import numpy as np

from ...errors import DataError


def as_signal(x, name, n=None, min_len=1):
    """
    Return ``x`` as a contiguous 1-D float64 array, raising DataError on bad shape or values.

    An (N, 1) column (one channel of a Record) is taken as its N samples.
    """
    try:
        a = np.ascontiguousarray(x, dtype=np.float64)
    except (TypeError, ValueError):
        raise DataError(f'{name} must be a 1-D array of numbers') from None
    if a.ndim == 2 and a.shape[1] == 1:
        a = a[:, 0]
    if a.ndim != 1:
        raise DataError(f'{name} must be 1-D, got shape {a.shape}')
    if n is not None and a.size != n:
        raise DataError(f'{name} has {a.size} samples, expected {n}')
    if a.size < min_len:
        raise DataError(f'{name} has {a.size} samples, need at least {min_len}')
    if not np.all(np.isfinite(a)):
        raise DataError(f'{name} contains NaN or infinite values')
    return a


def as_channels(x, name, n=None, width=None, min_len=1):
    """
    Return ``x`` as a C-contiguous (N, k) float64 array of k channels; 1-D is one channel.

    n: required samples; width: required channels. DataError (one line naming the argument) on a
    bad shape, too few samples or non-finite values.
    """
    try:
        a = np.ascontiguousarray(x, dtype=np.float64)
    except (TypeError, ValueError):
        raise DataError(f'{name} must be an array of numbers, (N,) or (N, channels)') from None
    if a.ndim == 1:
        a = a.reshape(-1, 1)
    if a.ndim != 2:
        raise DataError(f'{name} must be (N,) or (N, channels), got shape {a.shape}')
    if width is not None and a.shape[1] != width:
        raise DataError(f'{name} has {a.shape[1]} channel(s), expected {width} (shape '
                        f'{a.shape})')
    if n is not None and a.shape[0] != n:
        raise DataError(f'{name} has {a.shape[0]} samples, expected {n}')
    if a.shape[0] < min_len:
        raise DataError(f'{name} has {a.shape[0]} samples, need at least {min_len}')
    if not np.all(np.isfinite(a)):
        raise DataError(f'{name} contains NaN or infinite values')
    return a


def input_vector(u_k, n_in):
    """Return one sample of a several-input Stepper, u_k (n_in,) V, as float64 (else DataError)."""
    u = np.asarray(u_k, dtype=np.float64)
    if u.shape != (n_in,):
        raise DataError(f'stepper input must be {n_in} voltages (one per input), got '
                        f'shape {u.shape}')
    return u
