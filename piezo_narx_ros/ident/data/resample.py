"""
A record at another sample rate: anti-aliased polyphase resampling (`fit --resample HZ`).

A rig sampled at 10 kHz may want a model that runs at 2 kHz (a slower loop, a cheaper
estimator). Both the input and the output are low-pass filtered at the new Nyquist frequency and
decimated (scipy.signal.resample_poly, a Kaiser-window FIR), so what the model sees at the slow
rate is what a slow rig would have recorded, not the aliases of the fast dynamics. Only slower
rates: a faster model cannot learn what the record never sampled.
"""
from __future__ import annotations

from dataclasses import replace
from fractions import Fraction

import numpy as np

from piezo_narx_ros.errors import DataError
from piezo_narx_ros.record import Record

#: Largest denominator of the rate ratio (up/down factors of the polyphase filter).
MAX_FACTOR = 1000


def resample_record(record: Record, fs: float) -> Record:
    """
    `record` at the sample rate fs (Hz, below the record's): u, y (and y_true) resampled.

    The ratio fs / record.fs must be a fraction with denominator <= MAX_FACTOR (to 1e-6
    relative); DataError when fs is not positive, not slower, is a rate the filter cannot make
    (the message names the nearest one it can), or leaves fewer than 100 samples. Stamps t
    (when the record had them) restart at the first sample's time with a step of 1/fs. A segment
    of a longer recording is resampled alone (its history is dropped).
    """
    fs = float(fs)
    if not np.isfinite(fs) or fs <= 0:
        raise DataError(f'--resample must be a positive number of Hz, got {fs!r}')
    if fs >= record.fs:
        raise DataError(f"{record.source}: --resample {fs:g} Hz is not below the record's "
                        f'{record.fs:g} Hz (only slower models: a faster one cannot learn what '
                        'the record never sampled)')
    from scipy.signal import resample_poly
    ratio = Fraction(fs / record.fs).limit_denominator(MAX_FACTOR)
    if ratio.numerator == 0:
        raise DataError(f'{record.source}: --resample {fs:g} Hz is below 1/{MAX_FACTOR} of the '
                        f"record's {record.fs:g} Hz")
    made = record.fs * ratio.numerator / ratio.denominator
    if abs(made - fs) > 1e-6 * fs:
        # e.g. 1999 Hz from 2000 Hz: the nearest ratio was 1/1, and the model would silently
        # have been fitted at 2000 Hz while the user asked for 1999 Hz.
        if ratio >= 1:
            ratio = Fraction(MAX_FACTOR - 1, MAX_FACTOR)
        near = record.fs * ratio.numerator / ratio.denominator
        raise DataError(f'{record.source}: --resample {fs:g} Hz cannot be made from '
                        f"the record's {record.fs:g} Hz (rate ratios p/q with q <= {MAX_FACTOR}); "
                        f'the nearest slower rate it can make is {near:.8g} Hz: pass that, or a '
                        f'rate in a simple ratio to {record.fs:g} Hz')

    def down(x):
        if x is None:
            return None
        # padtype='line': the record's ends are continued, not taken as zeros (no edge ringing).
        return resample_poly(x, ratio.numerator, ratio.denominator, padtype='line')
    u, y = down(record.u), down(record.y)
    if len(u) < 100:
        raise DataError(f'{record.source}: only {len(u)} samples at {fs:g} Hz (need 100)')
    new_fs = record.fs * ratio.numerator / ratio.denominator
    t = None if record.t is None else record.t[0] + np.arange(len(u)) / new_fs
    return replace(record, u=u, y=y, y_true=down(record.y_true), fs=new_fs, t=t,
                   source=f'{record.source}@{new_fs:g}Hz', u_before=None, y_before=None)
