"""
A recorded voltage file replayed by command_node, ROS-free: as recorded unless asked otherwise.

A replay is the recording: its volts, at its own rate, once. `playback_signal` reads the file with
the column rules `fit` uses (ident.data.read_signal: a headerless t,u,y table plays its u column,
never its time column) and changes it only where a parameter explicitly asks: `fs` other than
the file's rate (refused unless `resample`), `amplitude` (the deviation from the file's mean
rescaled to that peak), `offset` (added), `seconds` (cut; longer only with `loop`), `loop`.
Everything it did or could not vouch for is returned as `notes`, one line each, for the node to
log.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from piezo_narx_ros.errors import ConfigError

UNLIMITED = 1e300


@dataclass
class Playback:
    """What to stream: the signal (N, n_axes) V or m, its rate (Hz) and the lines to log."""

    signal: np.ndarray
    fs: float
    loop: bool
    notes: list = field(default_factory=list)


def playback_signal(path: str, n_axes: int = 1, fs: float | None = None,
                    default_fs: float = 2000.0, column: str | None = None, key: str = 'u',
                    resample: bool = False, amplitude: float | None = None,
                    offset: float | None = None, seconds: float | None = None,
                    loop: bool = False, u_min: float = -200.0,
                    u_max: float = 200.0) -> Playback:
    """
    Read `path` and return what command_node streams (module docstring for the rules).

    fs: the rate asked for, Hz (None: the file's own; `default_fs` when the file has none);
    amplitude, offset: V (m in position mode), None = not asked; seconds: s, None = the file;
    u_min, u_max: the node's clamp (samples beyond it are counted in a note). Every axis plays
    the same file.
    """
    from piezo_narx_ros.ident.data import read_signal
    from piezo_narx_ros.plant.signals import generate
    if not path:
        raise ConfigError('kind playback needs path (the .npz or text table to replay)')
    rec = read_signal(path, column, key)
    notes = list(rec.issues)
    if fs is None:
        fs = rec.fs
        if fs is None:
            fs = default_fs
            notes.append(f'{path} records no rate (no fs, no time column): streamed at '
                         f'{fs:g} Hz; set fs if it was recorded at another')
    elif rec.fs is not None and abs(rec.fs - fs) > 1e-9 * fs and resample:
        notes.append(f'{path} was recorded at {rec.fs:g} Hz: resampled to {fs:g} Hz (linear)')
    # Unclamped here (the limits are the streamer's, CommandStreamer), so that they are counted.
    u = generate('playback', fs, seconds, amplitude, 0.0 if offset is None else offset,
                 path=path, column=column, key=key, resample=resample, loop=loop,
                 u_min=-UNLIMITED, u_max=UNLIMITED)
    clamped = int(np.count_nonzero((u < u_min) | (u > u_max)))
    if clamped:
        notes.append(f'{clamped} sample(s) of {path} beyond [{u_min:g}, {u_max:g}] are '
                     'clamped to the limits')
    if amplitude is not None:
        notes.append(f'{path} rescaled to +-{amplitude:g} about its mean (amplitude)')
    if loop and u.size > 1:
        jump = abs(float(u[-1] - u[0]))
        if jump > 0.01 * max(float(np.ptp(u)), 1e-12):
            notes.append(f'looping {path} jumps {jump:.4g} from its last sample to its first')
    return Playback(np.repeat(u[:, None], n_axes, axis=1), float(fs), bool(loop), notes)
