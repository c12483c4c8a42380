"""
Record building and the checks every loader applies.

Arrays to a checked Record (`checked`), the rate of a time column with its gaps and jitter
(`time_clock`), and the length and identifiability checks `fit` applies. Every problem raises
`DataError` with a one-line message that names the source and the problem.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import numpy as np

from piezo_narx_ros.errors import DataError
from piezo_narx_ros.ident.data.units import SI, Units, check_magnitudes
from piezo_narx_ros.ident.validation.metrics import is_constant as _constant
from piezo_narx_ros.record import Record, check_names

__all__ = ['MIN_SAMPLES', 'checked', 'check_length', 'check_identifiable', 'check_scorable',
           'time_clock', 'TimeClock']


# Fewest samples a record may have: below this neither a 50/50 split nor the correlation tests
# (20 lags) mean anything. `check_length` applies the stricter bound for given lags.
MIN_SAMPLES = 100


def _vector(name: str, value, source: str) -> np.ndarray:
    arr = np.asarray(value)
    if arr.dtype.kind not in 'fiu':
        raise DataError(f'{source}: {name} is not numeric (dtype {arr.dtype})')
    arr = arr.astype(np.float64)
    if arr.ndim == 2 and 1 in arr.shape:   # a column or row vector saved as 2-D
        arr = arr.reshape(-1)
    if arr.ndim != 1:
        raise DataError(f'{source}: {name} must be 1-D, got shape {arr.shape}')
    if not np.all(np.isfinite(arr)):
        bad = int(np.flatnonzero(~np.isfinite(arr))[0])
        raise DataError(f'{source}: {name} contains NaN or inf (first at sample {bad})')
    return arr


def _channels(name: str, value, source: str) -> np.ndarray:
    """
    Return a signal of one or more channels as a C-contiguous (N, k) float64 array.

    1-D (and a row vector saved as 2-D) is one channel; (N, k) is k channels.
    """
    arr = np.asarray(value)
    if arr.dtype.kind not in 'fiu':
        raise DataError(f'{source}: {name} is not numeric (dtype {arr.dtype})')
    arr = arr.astype(np.float64)
    if arr.ndim == 2 and arr.shape[0] == 1 and arr.shape[1] > 1:   # a row vector
        arr = arr.reshape(-1)
    if arr.ndim == 1:
        arr = arr.reshape(-1, 1)
    if arr.ndim != 2 or arr.shape[1] < 1:
        raise DataError(f'{source}: {name} must be (N,) or (N, channels), got shape {arr.shape}')
    if not np.all(np.isfinite(arr)):
        bad = int(np.flatnonzero(~np.all(np.isfinite(arr), axis=1))[0])
        raise DataError(f'{source}: {name} contains NaN or inf (first at sample {bad})')
    return np.ascontiguousarray(arr)


def _names_key(data: dict, key: str, source: str):
    """Channel names stored under `key` in an .npz (array of str), or None when absent."""
    if key not in data:
        return None
    arr = np.asarray(data[key])
    if arr.dtype.kind not in 'US' or arr.ndim > 1:
        raise DataError(f'{source}: {key} must be an array of channel names (str), got dtype '
                        f'{arr.dtype} shape {arr.shape}')
    return tuple(str(v) for v in arr.reshape(-1))


def _fs_value(fs, source: str) -> float:
    try:
        fs = float(np.asarray(fs).reshape(-1)[0]) if np.ndim(fs) else float(fs)
    except (TypeError, ValueError, IndexError):
        raise DataError(f'{source}: sample rate fs is not a number: {fs!r}') from None
    if not np.isfinite(fs) or fs <= 0:
        raise DataError(f'{source}: sample rate fs must be a positive number of Hz, got {fs}')
    return fs


def _make(u, y, fs, source, t=None, y_true=None, units: Units = SI, inputs=None,
          outputs=None) -> Record:
    u = _channels('u', u, source) * units.u_factor
    y = _channels('y', y, source) * units.y_factor
    n = u.shape[0]
    if y.shape[0] != n:
        raise DataError(f'{source}: u has {n} samples but y has {y.shape[0]}')
    if t is not None:
        t = _vector('t', t, source)
        if t.size != n:
            raise DataError(f'{source}: t has {t.size} samples but u has {n}')
    if y_true is not None:
        y_true = _channels('y_true', y_true, source) * units.y_factor
        if y_true.shape != y.shape:
            raise DataError(f'{source}: y_true has shape {y_true.shape} but y {y.shape}')
    if n < MIN_SAMPLES:
        raise DataError(f'{source}: only {n} samples, need at least {MIN_SAMPLES}')
    if inputs is not None:
        inputs = check_names(inputs, u.shape[1], 'input', source)
    if outputs is not None:
        outputs = check_names(outputs, y.shape[1], 'output', source)
    check_magnitudes(u, y, source, units)
    return Record(u=u, y=y, fs=_fs_value(fs, source), source=source, t=t, y_true=y_true,
                  inputs=inputs, outputs=outputs)


# ---------------------------------------------------------------------------- time columns
# A rate from a time column and a given one (--fs, an fs key) agree within this.
TIME_RATE_RTOL = 1e-3


# A time column in seconds whose rate falls outside this range is in another unit.
PLAUSIBLE_FS = (10.0, 1e6)


# Steps longer than GAP_FACTOR x the median are gaps (as for bags).
GAP_FACTOR = 1.5


JITTER_TOLERANCE = 0.05


@dataclass
class TimeClock:
    """What a time column says: rate, gaps, jitter (see `time_clock`)."""

    fs: float                                   # Hz
    gaps: list = field(default_factory=list)    # [(t from the first sample s, missing samples)]
    jitter: float = 0.0       # largest step deviation from 1/fs beyond the stamps' resolution
    resolution: float = 0.0   # s, the printing step of the stamps when they are quantised

    def issues(self, source: str) -> list[str]:
        """One warning line per finding (as bags report theirs)."""
        out = []
        if self.gaps:
            t0, n = self.gaps[0]
            missing = sum(m for _, m in self.gaps)
            out.append(f'{source}: {len(self.gaps)} gap(s), {missing} missing sample(s) in the '
                       f'time column (first at t={t0:.6g} s, {n} missing): the record is joined '
                       'across them, and lagged regressors there join non-adjacent samples')
        if self.jitter > JITTER_TOLERANCE:
            out.append(f'{source}: irregular sample rate: time steps deviate by up to '
                       f'{100 * self.jitter:.3g}% from 1/fs (fs = {self.fs:.6g} Hz); the record '
                       'is taken as evenly sampled')
        return out


def time_clock(t, source: str, name: str = 't', stated: bool = False,
               warn: bool = True) -> TimeClock:
    """
    Sample rate (Hz), gaps and jitter of a time column t (s), issuing its warnings.

    The rate is the mean of the steps that are not gaps (steps up to GAP_FACTOR x the median),
    not 1 / median step: stamps printed with few digits (3 kHz to 0.1 ms) step unevenly but
    average to the true period, and epoch-second stamps lose nothing. Raises DataError when t
    does not increase, and when the rate is not plausible in seconds (µs or ms stamps) unless
    the unit was `stated`.
    """
    t = np.asarray(t, dtype=np.float64)
    if t.size < 2:
        raise DataError(f'{source}: need at least 2 samples in {name}')
    t = t - t[0]                    # epoch stamps: keep the steps' precision
    d = np.diff(t)
    bad = np.flatnonzero(~(d > 0))
    if bad.size:
        raise DataError(f'{source}: time column {name} is not strictly increasing (sample '
                        f'{bad[0] + 1} is at or before the one before it)')
    med = float(np.median(d))
    is_gap = d > GAP_FACTOR * med
    regular = d[~is_gap]
    period = float(regular.mean())
    fs = 1.0 / period
    if not stated and not PLAUSIBLE_FS[0] <= fs <= PLAUSIBLE_FS[1]:
        raise DataError(f'{source}: the time column {name} steps by {period:.6g} (mean), i.e. '
                        f'{fs:.6g} Hz if it is in seconds; if it is in ms, us or ns pass '
                        '--t-unit ms|us|ns, or give --fs and leave t out (--columns)')
    gaps = [(float(t[i]), int(round(d[i] / period)) - 1) for i in np.flatnonzero(is_gap)]
    # Stamps printed with few digits step by a few multiples of their resolution (float noise
    # aside, hence the grouping at a millionth of the period).
    grain = 1e-6 * period
    steps = np.unique(np.round(regular / grain))
    resolution = float(np.min(np.diff(steps))) * grain if 1 < steps.size <= 4 else 0.0
    dev = float(np.max(np.abs(regular - period))) if regular.size else 0.0
    clock = TimeClock(fs, gaps, max(dev - resolution, 0.0) / period, resolution)
    if warn:
        for line in clock.issues(source):
            warnings.warn(line, stacklevel=3)
    return clock


def checked(record: Record, units: Units = SI) -> Record:
    """Return `record` converted by `units` and checked like every loaded record."""
    return _make(record.u, record.y, record.fs, record.source, record.t, record.y_true, units,
                 record.inputs, record.outputs)


def check_length(record: Record, n0: int, max_lag: int = 20, what: str = 'lags') -> None:
    """
    Raise DataError unless each half of `record` is long enough for the tests.

    Each half must hold n0 start-up samples (the deepest lag) plus the 4 * max_lag samples the
    correlation tests need.
    """
    need = max(MIN_SAMPLES, 2 * (n0 + 4 * max_lag))
    if len(record) < need:
        raise DataError(f'{record.source}: {len(record)} samples are too few for {what} up to '
                        f'{n0} (need at least {need})')


def check_scorable(record: Record, start: int = 0) -> None:
    """
    Raise DataError (naming the record) when an output it would score against is constant.

    R² against a flat output is undefined (validation.metrics.is_constant); before, a constant
    validation record scored R² -3.9e30. start: the first sample scored.
    """
    for j in range(record.n_out):
        y = record.y[start:, j]
        if len(y) and _constant(y):
            which = 'the measured output' if record.n_out == 1 else f'output {record.outputs[j]}'
            raise DataError(f'{record.source}: {which} is constant (y = {y[0]:.6g} m, spread '
                            f'{np.ptp(y):.3g} m): R² is undefined against it, so it cannot score '
                            'a model; score on a record where the deflection moves')


def check_identifiable(record: Record, split: float = 0.5) -> list[str]:
    """
    Refuse a record from which nothing can be identified; warn about a weak one.

    The first `split` of the samples estimates, the rest validates. Raises DataError when the
    estimation input is constant (an idle rig excites nothing: any model fits it) or the output of
    either part is constant to float rounding (a flat channel gives R² 1 or NaN, not a model).
    Returns warning lines when the estimation input moves much less than the validation input.
    Every message says how to fix the record.
    """
    est, val = record.split(split)
    fix = ('trim the idle part of the record or move the split (fit --split, now '
           f'{split:g})')
    if _constant(est.u):
        raise DataError(f'{record.source}: the input is constant over the estimation part '
                        f'(first {len(est)} samples, u = {est.u.flat[0]:.6g} V): it excites '
                        f'nothing, so no model can be identified from it; {fix}')
    for part, name in ((est, 'estimation'), (val, 'validation')):
        for j in range(part.n_out if len(part) else 0):   # a flat output channel: no model
            y = part.y[:, j]
            if _constant(y):
                which = 'the output' if part.n_out == 1 else f'output {part.outputs[j]}'
                raise DataError(f'{record.source}: {which} is constant in the {name} part '
                                f'(y = {y[0]:.6g} m, spread {np.ptp(y):.3g} m): '
                                'nothing to identify; check that y is the measured deflection')
    warnings = []
    s_est, s_val = float(np.std(est.u)), float(np.std(val.u))
    if s_est < 0.1 * s_val:
        warnings.append(f'{record.source}: the estimation part moves little (input std '
                        f'{s_est:.3g} V against {s_val:.3g} V in the validation part): the model '
                        f'will extrapolate; {fix}')
    return warnings
