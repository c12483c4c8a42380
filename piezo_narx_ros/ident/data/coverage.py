"""
What the estimation data cover, compared with the validation data: input range and frequency band.

A model is identified where its estimation input went. When the validation records move the input
further, or faster or slower, the validation scores measure extrapolation, and selection on them
favours whatever extrapolates most gently (often a linear ARX). `coverage_warnings` says so in
words before the fit, so that a user can record what is missing.
"""
from __future__ import annotations

import numpy as np

#: Fraction of the validation input's span it may exceed the estimation range by without a warning.
RANGE_SLACK = 0.05
#: Factor by which a validation band edge may lie beyond the estimation band without a warning.
BAND_FACTOR = 2.0
#: Share of the input's variance below the lower / above the upper band edge.
BAND_TAIL = 0.05


#: A command moves slowly when the SLOW_QUANTILE of its steps is below this share of its range per
#: sample: a full-range sine of frequency f steps at most pi f / fs, so below 0.5 % it has more
#: than about 630 samples per cycle (a 1 Hz sine at 2 kHz 0.16 %, at 10 kHz 0.03 %; the
#: identification protocol at 2 kHz 5.3 %, at 10 kHz 1.1 %; the micromanipulator 1.6 %).
SLOW_STEP = 0.005
SLOW_QUANTILE = 0.95
#: Steps below this share of the range are holds (or a measured input's noise), not moves.
MOVING = 1e-6
#: A reversal of the input counts when it moves back by this fraction of its range (not noise).
REVERSAL_DEPTH = 0.05
#: ... and is "inner" (a minor loop) when this fraction of the range away from both extremes.
INNER_MARGIN = 0.1
#: A record's input has swept its range once it came within this share of its range of both ends
#: (a random-phase multisine reaches its crests rarely, 80 % of them often).
SWEEP_MARGIN = 0.2
#: `fit` warns when more than this share of the estimation samples came before that (late_sweep):
#: a sine of growing amplitude sweeps at about 64 % of its record, the identification protocol at
#: 2 %, multisines at 0-14 % (the 5 kHz wideband record and the FSM's 18 records), the
#: micromanipulator's file at 2 % (docs/real.md, "Records of the fit's own session").
LATE_SWEEP = 0.25


def inner_reversals(inputs) -> int:
    """
    Reversals of the input inside its previous loop, over records: how many minor loops.

    inputs: the records' input arrays (V), or Records.

    A reversal is a turning point the input then leaves by REVERSAL_DEPTH of the records' input
    range (so sensor or quantisation noise on a measured input is no reversal). It closes a minor
    loop when it lies inside the loop before it: a top below the previous top, or a bottom above
    the previous bottom, by REVERSAL_DEPTH, and INNER_MARGIN of the range away from both the
    smallest and the largest input. A full-range sine has none, and so has a sine of growing
    amplitude (each turn goes beyond the last and wipes it: it shows one loop, growing); a
    multisine, a fading sine or nested loops have many. Several input channels ((N, n_in)
    arrays): the fewest of any channel.
    """
    inputs = [np.asarray(getattr(x, 'u', x), dtype=np.float64) for x in inputs]
    if any(u.ndim == 2 for u in inputs):
        cols = [u.reshape(len(u), -1) for u in inputs]
        return min(_inner_reversals([c[:, i] for c in cols]) for i in range(cols[0].shape[1]))
    return _inner_reversals(inputs)


def step_share(inputs) -> float:
    """
    Return the SLOW_QUANTILE of the input's moving steps within records, as a share of its range.

    inputs: the records' input arrays (V), or Records. Steps are taken within each record (not
    across records), and only those where the input moves (above MOVING of the range): a
    piecewise-constant input (APRBS, steps, held levels) is as fast as its jumps, not as slow as
    its holds. Several input channels ((N, n_in)): the fastest channel. 0 for a constant input or
    records of one sample.
    """
    inputs = [np.asarray(getattr(x, 'u', x), dtype=np.float64) for x in inputs]
    cols = [u.reshape(len(u), -1) for u in inputs]
    share = 0.0
    for i in range(cols[0].shape[1]):
        steps = np.concatenate([np.abs(np.diff(c[:, i])) for c in cols])
        span = (max(float(np.max(c[:, i])) for c in cols)
                - min(float(np.min(c[:, i])) for c in cols))
        steps = steps[steps > MOVING * span]
        if steps.size and span > 0:
            share = max(share, float(np.quantile(steps, SLOW_QUANTILE)) / span)
    return share


def unswept_share(inputs) -> float:
    """
    Return the share of the samples recorded before each record's input reached both its ends.

    inputs: the records' input arrays (V), or Records; each record against its own range, an end
    reached within SWEEP_MARGIN of that range. A record starts after a past nobody logged, and
    until its input has been to both ends the operators' memory is partly that past's: the fit
    learns it as the model's own rest (docs/real.md). Several input channels ((N, n_in)): the
    latest channel. 0 for constant inputs.
    """
    inputs = [np.asarray(getattr(x, 'u', x), dtype=np.float64) for x in inputs]
    cols = [u.reshape(len(u), -1) for u in inputs]
    total = sum(len(c) for c in cols)
    late = 0
    for c in cols:
        first = 0
        for x in c.T:
            lo, hi = float(np.min(x)), float(np.max(x))
            if hi > lo:
                margin = SWEEP_MARGIN * (hi - lo)
                first = max(first, int(np.argmax(x >= hi - margin)),
                            int(np.argmax(x <= lo + margin)))
        late += first
    return late / total if total else 0.0


def late_sweep_warnings(estimation) -> list[str]:
    """
    One line when the estimation records reach both ends of their input range late (LATE_SWEEP).

    Until then part of the operators' memory is the unlogged past before each record, and the fit
    learns it as the model's rest: on the growing scenario such models free-ran records of the
    same session better from rest than from a window's state estimate (docs/real.md).
    """
    share = unswept_share(estimation)
    if share <= LATE_SWEEP:
        return []
    return [f'the estimation input reaches both ends of its range only after {share:.0%} of its '
            'samples (e.g. a hold, then a growing amplitude): until then part of the operator '
            'memory is the unlogged past before the record, which the fit learns as the '
            "model's rest. Start such recordings with one full-range cycle. A model fitted on "
            'them may free-run records of the same session better from rest than from a '
            "measured window (docs/real.md, section \"Records of the fit's own session\")"]


def _inner_reversals(inputs) -> int:
    lo = min(float(np.min(u)) for u in inputs)
    hi = max(float(np.max(u)) for u in inputs)
    span = hi - lo
    if not span > 0:
        return 0
    depth, margin = REVERSAL_DEPTH * span, INNER_MARGIN * span
    count = 0
    for u in inputs:
        top = bottom = u[0]
        rising = None
        last_top = last_bottom = None     # the previous turning points (None: none yet)
        for x in u[1:]:
            top, bottom = max(top, x), min(bottom, x)
            if rising is not False and x < top - depth:       # turned down at `top`
                if rising is not None:
                    count += (lo + margin < top < hi - margin and last_top is not None
                              and top < last_top - depth)
                    last_top = top
                rising, bottom = False, x
            elif rising is not True and x > bottom + depth:   # turned up at `bottom`
                if rising is not None:
                    count += (lo + margin < bottom < hi - margin and last_bottom is not None
                              and bottom > last_bottom + depth)
                    last_bottom = bottom
                rising, top = True, x
    return int(count)


def input_band(u: np.ndarray, fs: float) -> tuple[float, float]:
    """
    (low, high) Hz: the frequencies that bound the central 90 % of u's variance (V, mean removed).

    From a Welch periodogram; (0, 0) for a constant input.
    """
    from scipy.signal import welch
    u = np.asarray(u, dtype=np.float64)
    if u.size < 16 or not np.ptp(u) > 0:
        return 0.0, 0.0
    f, p = welch(u - u.mean(), fs=fs, nperseg=min(u.size, 8192), detrend=False)
    c = np.cumsum(p)
    if not c[-1] > 0:
        return 0.0, 0.0
    c /= c[-1]
    low = float(f[np.searchsorted(c, BAND_TAIL)])
    high = float(f[min(np.searchsorted(c, 1.0 - BAND_TAIL), f.size - 1)])
    return low, high


def coverage(records) -> dict:
    """Input range (V) and band (Hz) over several records: the union of theirs."""
    # Every input channel of every record (one axis: the record's one input).
    lows, highs = zip(*(input_band(r.u[:, i], r.fs) for r in records for i in range(r.n_in)))
    return {'u_min': float(min(r.u.min() for r in records)),
            'u_max': float(max(r.u.max() for r in records)),
            'f_low': float(min(lows)), 'f_high': float(max(highs))}


def coverage_warnings(estimation, validation) -> list[str]:
    """One line per way the estimation records cover less than the validation records."""
    est, val = coverage(estimation), coverage(validation)
    out = []
    span = val['u_max'] - val['u_min']
    if est['u_min'] > val['u_min'] + RANGE_SLACK * span or \
            est['u_max'] < val['u_max'] - RANGE_SLACK * span:
        out.append(f'the validation records move the input over [{val["u_min"]:.4g}, '
                   f'{val["u_max"]:.4g}] V but the estimation records only over '
                   f'[{est["u_min"]:.4g}, {est["u_max"]:.4g}] V: beyond that the model '
                   'extrapolates, and its validation scores measure the extrapolation; record '
                   'an estimation input that covers the whole range')
    if est['f_high'] > 0 and val['f_high'] > BAND_FACTOR * est['f_high']:
        out.append(f'the validation input reaches {val["f_high"]:.3g} Hz but the estimation '
                   f'input only {est["f_high"]:.3g} Hz (90 % of its variance): faster moves than '
                   'the model was identified on; add faster excitation to the estimation data')
    if val['f_low'] > 0 and est['f_low'] > BAND_FACTOR * val['f_low']:
        out.append(f'the validation input moves as slowly as {val["f_low"]:.3g} Hz but the '
                   f'estimation input only down to {est["f_low"]:.3g} Hz: slower moves (creep, '
                   'drift) than the model was identified on; add slow moves or holds to the '
                   'estimation data')
    return out
