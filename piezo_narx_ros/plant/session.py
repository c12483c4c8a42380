"""
What a rig session adds to a record (docs/real.md): an unknown past and a sensor zero of its own.

A rig is switched on, driven, and recorded some time later: its first recorded sample finds the
hysteresis memory set by inputs nobody logged, creep still moving and the sensor reading off by a
zero that changes from one session (day, power-up, re-mounted sensor) to the next.

    u_hist = random_history(fs, seconds=20.0, amplitude=100.0, seed=7, end=u[0], hold=1.0)
    plant = PiezoCantilever(params, fs, seed=0, sensor_offset=session_offset(3, 2.5e-6))
    record = plant.run(u, history=u_hist)

Every random draw here has its own stream, tagged below, so that the history, the session's
offset, the signal and the sensor noise can be varied one at a time.
"""
from __future__ import annotations

import math

import numpy as np

from piezo_narx_ros.errors import ConfigError
from piezo_narx_ros.plant.signals import _n_samples, _num, _random_ramps

_HISTORY_STREAM = 0x4157  # tags the history's seed sequence
_OFFSET_STREAM = 0x5E55   # tags the session-offset seed sequence


def _seed(seed, name):
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ConfigError(f'{name} must be a non-negative integer, got {seed!r}')
    return int(seed)


def random_history(fs, seconds, amplitude, offset=0.0, seed=0, end=None,
                   hold=1.0) -> np.ndarray:
    """
    Return a random past input, (M,) V: `seconds` of ramps, a ramp to `end`, `hold` s there.

    From rest (0 V), ramps between random levels in offset ± amplitude V at random rates (0.2-30
    amplitudes/s, log-uniform) with short random holds, like the protocol's ramp section; so the
    reversal points that set the hysteresis memory are random. Then a ramp at a random rate to
    `end` V (None: the offset), from above or below as the last level falls, and `hold` s there:
    the creep of that past is still moving when a record that starts at `end` begins.
    fs: Hz; seed: the history's own seed (not the signal's or the noise's).
    """
    fs = _num('fs', fs, 0.0, lo_open=True)
    amplitude = _num('history amplitude', amplitude, 0.0, lo_open=True)
    offset = _num('offset', offset)
    end = offset if end is None else _num('history end', end)
    hold = _num('history hold', hold, 0.0)
    rng = np.random.Generator(np.random.PCG64([_seed(seed, 'history seed'), _HISTORY_STREAM]))
    n = _n_samples(seconds, fs)
    moves = offset + amplitude * _random_ramps(n, fs, rng, -offset / amplitude)
    rate = amplitude * 10.0 ** rng.uniform(math.log10(0.2), math.log10(30.0))   # V/s
    n_ramp = max(int(abs(end - moves[-1]) / rate * fs), 1)
    ramp = np.linspace(moves[-1], end, n_ramp + 1)[1:]
    return np.concatenate([moves, ramp, np.full(int(round(hold * fs)), end)])


def session_offset(session, spread) -> float:
    """
    Sensor offset of session `session`, m: uniform in [-spread, spread] (spread m).

    Sessions drawn with one spread differ by up to 2 * spread (the issue's rig: its zero moved
    by up to 4.7 um between days).
    """
    spread = _num('session offset spread', spread, 0.0)
    rng = np.random.Generator(np.random.PCG64([_seed(session, 'session'), _OFFSET_STREAM]))
    return float(rng.uniform(-spread, spread))
