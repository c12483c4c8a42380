"""
Excitation signals (volts) for the plant, the command node and offline data sets.

generate(kind, fs, seconds, amplitude, offset=0.0, seed=0, **options) returns (N,) volts with
N = round(seconds*fs), deterministic for a given seed. Every kind takes the amplifier limits
u_min, u_max (V, clamp) and slew_rate (V/s, sample-to-sample limit, starting from the first sample
so that the array loops without a ramp-in). Kind-specific options and their defaults are in
OPTIONS.
"""
from __future__ import annotations

import math

import numpy as np

from piezo_narx_ros.errors import ConfigError

COMMON = {'u_min': -200.0, 'u_max': 200.0, 'slew_rate': math.inf}
OPTIONS = {
    'sine': {'freq': 1.0, 'phase': 0.0},
    'triangle': {'freq': 1.0},
    # f_res: line spacing, Hz (None: 1/seconds, so the record is one period); spectrum: flat (equal
    # line amplitudes), pink (amplitude ~ f^-1/2) or brown (amplitude ~ 1/f).
    'multisine': {'f_min': 0.1, 'f_max': 100.0, 'f_res': None, 'spectrum': 'flat'},
    'chirp': {'f0': 1.0, 'f1': None, 'method': 'linear'},          # f1 None: 0.45*fs
    'aprbs': {'min_hold': 0.01, 'max_hold': 0.5},                   # s
    # levels x amplitude; hold None: even split
    'steps': {'levels': (0.0, 1.0, 0.0, -1.0, 0.0), 'hold': None},
    'playback': {'path': None, 'key': 'u', 'column': None, 'file_fs': None, 'resample': False,
                 'loop': False},
    # The identification protocol (docs/envelope.md): `cycles` repeats of [hold, multisine up to
    # f_max, slow sine at slow_freq decaying from full to a fifth of the amplitude, steps held
    # 0.15-1 s, ramps at 0.2-30 amplitudes/s], each repeat with fresh random draws. shift: the
    # moves after each hold rotated by this fraction (several axes: axis i of n by i/n, so that
    # the slow sine, the same on every seed, never drives two axes at once).
    'protocol': {'cycles': 2, 'f_max': 100.0, 'slow_freq': 0.5, 'shift': 0.0},
    # A rig's identification record (docs/real.md): `hold` s at the offset, then one sine at
    # `freq` Hz whose amplitude grows from start_fraction to 1 (linear or exponential growth).
    'growing_sine': {'freq': 1.0, 'hold': 0.0, 'growth': 'linear', 'start_fraction': 0.05},
    # Held levels (creep): random levels, the largest at the amplitude, each reached by a ramp of
    # `ramp` s from the previous one (from the offset for the first) and held `hold` s.
    'holds': {'hold': 1.0, 'ramp': 0.01},
}
KINDS = tuple(OPTIONS)
#: Moves played once before a record so that the actuator's memory is known when it starts
#: (docs/real.md, "... a fade-out before the record"): 'none', or 'fade-out': sine cycles about the
#: offset whose amplitude falls linearly from the record's amplitude to 0, which wipes whatever
#: the unlogged past left and lets a state window over it tell the memory from a moved zero.
PREAMBLES = ('none', 'fade-out')
SPECTRA = ('flat', 'pink', 'brown')
CHIRP_METHODS = ('linear', 'logarithmic')
GROWTHS = ('linear', 'exponential')
# A default identification record (the paper's 25 s at 2 kHz): band 0.1-100 Hz, peak 100 V.
IDENT_DEFAULTS = {'kind': 'multisine', 'seconds': 25.0, 'fs': 2000.0, 'amplitude': 100.0,
                  'f_min': 0.1, 'f_max': 100.0, 'spectrum': 'flat'}


def _num(name, value, lo=None, hi=None, lo_open=False):
    """Validate a float; ConfigError names the parameter."""
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise ConfigError(f'signal parameter {name} must be a number, got {value!r}')
    value = float(value)
    if math.isnan(value) or (math.isinf(value) and name != 'slew_rate'):
        raise ConfigError(f'signal parameter {name} must be finite, got {value!r}')
    if lo is not None and (value <= lo if lo_open else value < lo):
        raise ConfigError(f'signal parameter {name} must be {">" if lo_open else ">="} {lo:g}, '
                          f'got {value:g}')
    if hi is not None and value > hi:
        raise ConfigError(f'signal parameter {name} must be <= {hi:g}, got {value:g}')
    return value


def generate(kind, fs, seconds, amplitude, offset=0.0, seed=0, **options) -> np.ndarray:
    """
    Excitation signal, (N,) V, N = round(seconds*fs).

    kind: one of KINDS; fs: sample rate, Hz; seconds: duration, s (playback: None = file length);
    amplitude: peak deviation from offset, V (playback: None = as recorded, else rescaled to this
    peak); offset: V; seed: seed of the random parts (multisine phases, APRBS levels and holds).
    Options: see OPTIONS[kind] and COMMON (u_min, u_max in V; slew_rate in V/s).
    """
    if kind not in OPTIONS:
        raise ConfigError(f'unknown signal kind {kind!r}; choose one of {", ".join(KINDS)}')
    allowed = {**COMMON, **OPTIONS[kind]}
    unknown = sorted(set(options) - set(allowed))
    if unknown:
        raise ConfigError(f'unknown option {unknown[0]!r} for signal {kind!r}; '
                          f'options: {", ".join(sorted(allowed))}')
    opt = {**allowed, **{k: v for k, v in options.items() if v is not None}}
    fs = _num('fs', fs, 0.0, lo_open=True)
    offset = _num('offset', offset)
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ConfigError(f'signal parameter seed must be a non-negative integer, got {seed!r}')
    if kind == 'playback':
        amp = None if amplitude is None else _num('amplitude', amplitude, 0.0)
        n = None if seconds is None else _n_samples(seconds, fs)
        base = _playback(fs, n, opt)
        if amp is not None:  # rescale the deviation from the file's mean to the requested peak
            peak = np.max(np.abs(base - base.mean()))
            base = (base - base.mean()) * (amp / peak if peak > 0 else 0.0)
        u = base + offset
    else:
        amp = _num('amplitude', amplitude, 0.0)
        n = _n_samples(seconds, fs)
        t = np.arange(n) / fs
        rng = np.random.Generator(np.random.PCG64(int(seed)))
        u = offset + amp * _SHAPES[kind](t, fs, opt, rng)
    return apply_limits(u, fs, opt['u_min'], opt['u_max'], opt['slew_rate'])


def preamble(kind, fs, seconds, amplitude, offset=0.0, cycles=20) -> np.ndarray:
    """
    Return the moves (M,) V played once before a record, M = round(seconds*fs) (none: empty).

    kind: one of PREAMBLES; 'fade-out': `cycles` sine cycles about offset (V) over `seconds` s,
    their amplitude falling linearly from `amplitude` (V) to 0, so it ends at the offset with the
    hysteresis memory demagnetised about it, whatever came before.
    """
    if kind not in PREAMBLES:
        raise ConfigError(f'unknown preamble {kind!r}; choose one of {", ".join(PREAMBLES)}')
    if kind == 'none':
        return np.zeros(0)
    fs = _num('fs', fs, 0.0, lo_open=True)
    amp = _num('amplitude', amplitude, 0.0)
    cycles = _num('preamble cycles', cycles, 0.0, lo_open=True)
    n = _n_samples(_num('preamble seconds', seconds, 0.0, lo_open=True), fs)
    frac = np.arange(n) / n
    return _num('offset', offset) + amp * (1.0 - frac) * np.sin(2.0 * np.pi * cycles * frac)


def apply_limits(u, fs, u_min=-200.0, u_max=200.0, slew_rate=math.inf) -> np.ndarray:
    """Clamp u (V) to [u_min, u_max] V, then limit its change to slew_rate/fs V per sample."""
    u_min = _num('u_min', u_min)
    u_max = _num('u_max', u_max)
    if not u_min < u_max:
        raise ConfigError(f'signal parameter u_min ({u_min:g}) must be below u_max ({u_max:g})')
    slew_rate = _num('slew_rate', slew_rate, 0.0, lo_open=True)
    u = np.clip(np.asarray(u, dtype=float), u_min, u_max)
    if math.isfinite(slew_rate) and u.size:
        from piezo_narx_ros.plant.kernels import slew_limit
        u = slew_limit(u, slew_rate / float(fs), u[0])
    return u


# Longest signal generated at once (400 MB of float64): a typo such as --seconds 1e7 must end in
# one line, not in a MemoryError after minutes of swapping.
MAX_SAMPLES = 50_000_000


def _n_samples(seconds, fs):
    seconds = _num('seconds', seconds, 0.0, lo_open=True)
    _check_size(seconds * fs, seconds, fs)
    n = int(round(seconds * fs))
    if n < 1:
        raise ConfigError(f'signal parameter seconds ({seconds:g}) gives no sample at '
                          f'fs = {fs:g} Hz')
    return n


def _check_size(n, seconds, fs):
    if n > MAX_SAMPLES:
        raise ConfigError(f'{seconds:g} s at {fs:g} Hz is {n:.3g} samples, more than the '
                          f'{MAX_SAMPLES:.0e} one signal may hold; shorten it or lower fs')


def _check_freq(name, f, fs):
    return _num(name, f, 0.0, fs / 2.0, lo_open=True)


def _sine(t, fs, opt, rng):
    f = _check_freq('freq', opt['freq'], fs)
    return np.sin(2.0 * np.pi * f * t + _num('phase', opt['phase']))


def _triangle(t, fs, opt, rng):
    from scipy.signal import sawtooth
    f = _check_freq('freq', opt['freq'], fs)
    # Phase pi/2 starts at 0 going up, like the sine.
    return sawtooth(2.0 * np.pi * f * t + np.pi / 2.0, 0.5)


def _multisine(t, fs, opt, rng):
    """
    Random-phase multisine on the lines k*f_res inside [f_min, f_max], spanning exactly [-1, 1].

    Scaled by its span rather than its peak so that BOTH extremes reach the amplitude: a model
    identified on it has then seen the whole commanded range (peak scaling left one side at ~84 %,
    and a fresh multisine of the same amplitude then drove the model outside what it was fitted
    on).
    The price is a small DC offset, (max + min) / (max - min) of the amplitude.
    """
    n = t.size
    f_min = _check_freq('f_min', opt['f_min'], fs)
    f_max = _check_freq('f_max', opt['f_max'], fs)
    if not f_min < f_max:
        raise ConfigError(f'signal parameter f_min ({f_min:g} Hz) must be below '
                          f'f_max ({f_max:g} Hz)')
    spectrum = opt['spectrum']
    if spectrum not in SPECTRA:
        raise ConfigError(f'signal parameter spectrum must be one of {", ".join(SPECTRA)}, '
                          f'got {spectrum!r}')
    f_res = fs / n if opt['f_res'] is None else _num('f_res', opt['f_res'], 0.0, lo_open=True)
    # The period must be a whole number of samples for an exact periodic signal (IFFT on one
    # period).
    period = max(int(round(fs / f_res)), 2)
    lines = np.arange(period // 2 + 1) * fs / period
    on = (lines >= f_min - 1e-9) & (lines <= f_max + 1e-9) & (lines > 0)
    if not on.any():
        raise ConfigError(f'signal parameter f_res ({f_res:g} Hz) puts no line in '
                          f'{f_min:g}-{f_max:g} Hz')
    mag = np.zeros(lines.size)
    mag[on] = {'flat': 1.0, 'pink': lines[on] ** -0.5, 'brown': 1.0 / lines[on]}[spectrum]
    phases = rng.uniform(0.0, 2.0 * np.pi, size=lines.size)
    one = np.fft.irfft(mag * np.exp(1j * phases), n=period)
    x = np.resize(one, n)  # repeats the period to n samples
    lo, hi = np.min(x), np.max(x)
    return (2.0 * x - (hi + lo)) / (hi - lo)


def _chirp(t, fs, opt, rng):
    from scipy.signal import chirp
    f0 = _check_freq('f0', opt['f0'], fs)
    f1 = _check_freq('f1', 0.45 * fs if opt['f1'] is None else opt['f1'], fs)
    method = opt['method']
    if method not in CHIRP_METHODS:
        raise ConfigError('signal parameter method must be one of '
                          f'{", ".join(CHIRP_METHODS)}, got {method!r}')
    duration = t[-1] if t.size > 1 else 1.0 / fs
    # phi=-90 deg starts the sweep at 0 V (a sine), not with a jump to the peak.
    return chirp(t, f0=f0, t1=duration, f1=f1, method=method, phi=-90.0)


# Share of one protocol cycle taken by each section, in order.
PROTOCOL_SECTIONS = (('hold', 0.02), ('multisine', 0.36), ('slow loops', 0.20), ('steps', 0.22),
                     ('ramps', 0.20))


def _protocol(t, fs, opt, rng):
    """
    Return the operating envelope in one record, in units of the amplitude (within [-1, 1]).

    A positioning stage sees fast small moves, slow full-range moves, nested minor loops, holds
    and steps; a model identified on one kind only is not trustworthy on the others
    (docs/excitation.md). Each cycle holds 0, then plays a random-phase multisine (the paper's fast
    excitation), a slow sine whose amplitude decays linearly from 1 to 0.2 (nested loops at every
    amplitude), random levels held 0.15-1 s (steps and creep), and ramps between random levels at
    random rates (0.2-30 amplitudes/s, log-uniform) with random holds up to 0.3 s. Repeating the
    cycle puts every kind of move in both halves of a 50/50 estimation/validation split. `shift`
    rotates each cycle's moves after its hold (the record still starts at rest, then jumps into
    a section and ends where that section began).
    """
    cycles = opt['cycles']
    if isinstance(cycles, bool) or not isinstance(cycles, (int, np.integer)) or cycles < 1:
        raise ConfigError(f'signal parameter cycles must be an integer >= 1, got {cycles!r}')
    slow = _check_freq('slow_freq', opt['slow_freq'], fs)
    shift = _num('shift', opt['shift'], 0.0, 1.0)
    n = t.size
    bounds = np.linspace(0, n, int(cycles) + 1).astype(int)
    out = np.empty(n)
    for c in range(int(cycles)):
        m = bounds[c + 1] - bounds[c]
        sizes = (np.array([f for _, f in PROTOCOL_SECTIONS]) * m).astype(int)
        sizes[-1] = m - sizes[:-1].sum()
        parts = [np.zeros(sizes[0])]
        n_ms = sizes[1]
        parts.append(_multisine(np.arange(n_ms) / fs, fs, {**OPTIONS['multisine'],
                                'f_min': fs / max(n_ms, 2), 'f_max': opt['f_max']}, rng)
                     if n_ms >= 4 else np.zeros(n_ms))
        tt = np.arange(sizes[2]) / fs
        parts.append(np.linspace(1.0, 0.2, tt.size) * np.sin(2.0 * np.pi * slow * tt))
        parts.append(_random_holds(sizes[3], fs, rng))
        parts.append(_random_ramps(sizes[4], fs, rng, parts[-1][-1] if sizes[3] else 0.0))
        moves = np.concatenate(parts[1:])       # the hold stays first: each cycle starts at rest
        if shift:
            moves = np.roll(moves, -int(round(shift * moves.size)))
        out[bounds[c]:bounds[c + 1]] = np.r_[parts[0], moves]
    return out


def _random_holds(n, fs, rng):
    """Return n samples of levels uniform in [-1, 1] held 0.15-1 s each."""
    out = np.empty(n)
    k = 0
    while k < n:
        hold = max(int(rng.uniform(0.15, 1.0) * fs), 1)
        out[k:k + hold] = rng.uniform(-1.0, 1.0)
        k += hold
    return out


def _random_ramps(n, fs, rng, start):
    """Return n samples of ramps from `start` between random levels, rates and holds."""
    out = np.empty(n)
    k, cur = 0, start
    while k < n:
        level = rng.uniform(-1.0, 1.0)
        rate = 10.0 ** rng.uniform(np.log10(0.2), np.log10(30.0))   # amplitudes per second
        m = max(int(abs(level - cur) / rate * fs), 1)
        seg = np.concatenate([np.linspace(cur, level, m + 1)[1:],
                              np.full(int(rng.uniform(0.0, 0.3) * fs), level)])
        out[k:k + seg.size] = seg[:n - k]
        k += seg.size
        cur = level
    return out


def _aprbs(t, fs, opt, rng):
    """Return steps of random level in [-1, 1] held for random times in [min_hold, max_hold] s."""
    lo = _num('min_hold', opt['min_hold'], 1.0 / fs)
    hi = _num('max_hold', opt['max_hold'], lo)
    n = t.size
    out = np.empty(n)
    k = 0
    while k < n:
        hold = max(int(round(rng.uniform(lo, hi) * fs)), 1)
        out[k:k + hold] = rng.uniform(-1.0, 1.0)
        k += hold
    return out


def _steps(t, fs, opt, rng):
    levels = opt['levels']
    if isinstance(levels, str):
        try:
            levels = [float(x) for x in levels.split(',')]
        except ValueError:
            raise ConfigError('signal parameter levels must be numbers separated by commas, '
                              f'got {levels!r}') from None
    levels = [_num(f'levels[{i}]', v) for i, v in enumerate(levels)]
    if not levels:
        raise ConfigError('signal parameter levels must hold at least one level')
    n = t.size
    hold = n / len(levels) / fs if opt['hold'] is None else _num('hold', opt['hold'], 1.0 / fs)
    idx = np.minimum((t / hold).astype(int), len(levels) - 1)
    return np.asarray(levels)[idx]


def _playback(fs, n, opt):
    """
    Return the signal of a file as recorded: volts untouched, at its own rate.

    The same column rules as `fit` (ident.data.loaders.read_signal). A file whose rate (fs key or
    time column, or the file_fs option) is not `fs` is refused unless the `resample` option asks
    for linear resampling; n samples (seconds given) shorter than the file cut it, longer ones need
    the `loop` option (the file repeated, with whatever jump its ends make).
    """
    from piezo_narx_ros.ident.data.loaders import read_signal
    path = opt['path']
    if not path:
        raise ConfigError('signal parameter path (the file to play back) is required for playback')
    rec = read_signal(path, opt['column'], opt['key'])
    u, file_fs = rec.u, rec.fs
    if opt['file_fs'] is not None:
        given = _num('file_fs', opt['file_fs'], 0.0, lo_open=True)
        if file_fs is not None and abs(given - file_fs) > 1e-9 * given:
            raise ConfigError(f'playback file {path} is at {file_fs:g} Hz, not file_fs = '
                              f'{given:g} Hz')
        file_fs = given
    if file_fs is not None and abs(file_fs - fs) > 1e-9 * fs:
        if not opt['resample']:
            raise ConfigError(f'playback file {path} was recorded at {file_fs:g} Hz, not at fs = '
                              f'{fs:g} Hz: play it at its own rate, or ask for linear '
                              'resampling (resample)')
        t_file = np.arange(u.size) / file_fs
        _check_size(t_file[-1] * fs, t_file[-1], fs)
        u = np.interp(np.arange(int(round(t_file[-1] * fs)) + 1) / fs, t_file, u)
    if n is None or n == u.size:
        return u
    if n < u.size:
        return u[:n]
    if not opt['loop']:
        raise ConfigError(f'playback: {n} samples asked for but {path} holds {u.size}; ask for '
                          'loop to repeat it')
    return np.resize(u, n)  # the file repeated


def _growing_sine(t, fs, opt, rng):
    """
    Return a hold at 0, then a sine whose amplitude grows to 1 at the end of the record.

    The usual record of a rig (docs/real.md): it holds a voltage, then sweeps one frequency with
    a growing amplitude, so that its early part covers a fraction of the range only. The sine
    starts at 0 going up (no jump after the hold); its envelope grows from start_fraction to 1,
    linearly or exponentially (equal ratios per second) in time.
    """
    f = _check_freq('freq', opt['freq'], fs)
    hold = _num('hold', opt['hold'], 0.0)
    start = _num('start_fraction', opt['start_fraction'], 0.0, 1.0)
    growth = opt['growth']
    if growth not in GROWTHS:
        raise ConfigError(f'signal parameter growth must be one of {", ".join(GROWTHS)}, '
                          f'got {growth!r}')
    if growth == 'exponential' and start <= 0.0:
        raise ConfigError('signal parameter start_fraction must be > 0 for exponential growth')
    n_hold = min(int(round(hold * fs)), t.size)
    ts = t[n_hold:] - (t[n_hold] if n_hold < t.size else 0.0)
    frac = ts / ts[-1] if ts.size > 1 else np.ones(ts.size)
    env = start + (1.0 - start) * frac if growth == 'linear' else start ** (1.0 - frac)
    return np.concatenate([np.zeros(n_hold), env * np.sin(2.0 * np.pi * f * ts)])


def _holds(t, fs, opt, rng):
    """Return random levels, the largest of magnitude 1, each ramped to and then held."""
    hold = _num('hold', opt['hold'], 1.0 / fs)
    ramp = _num('ramp', opt['ramp'], 0.0)
    n = t.size
    n_ramp, n_hold = int(round(ramp * fs)), max(int(round(hold * fs)), 1)
    n_levels = -(-n // (n_ramp + n_hold))
    levels = rng.uniform(-1.0, 1.0, size=n_levels)
    levels /= np.max(np.abs(levels))
    out, prev = [], 0.0
    for level in levels:
        out.append(np.linspace(prev, level, n_ramp + 1)[1:])
        out.append(np.full(n_hold, level))
        prev = level
    return np.concatenate(out)[:n]


_SHAPES = {'sine': _sine, 'triangle': _triangle, 'multisine': _multisine, 'chirp': _chirp,
           'aprbs': _aprbs, 'steps': _steps, 'protocol': _protocol,
           'growing_sine': _growing_sine, 'holds': _holds}
