"""
A recorded voltage file replayed by command_node, ROS-free: as recorded unless asked otherwise.

A replay is the recording: its volts, at its own rate, once. `playback_signal` reads the file with
the column rules `fit` uses (ident/data read_signal: a headerless t,u,y table plays its u column,
never its time column) and changes it only where a playback parameter explicitly asks: `scale`
and `offset` (u * scale + offset), `loop`, and `resample` (linear, to `fs`). The node's `fs` is
used only for a file that records no rate, or as the target of `resample`; a file at another rate
is played at its own, said in a note. These are playback's own parameters, not the generated
signals' amplitude/offset/seconds/loop, whose defaults (and the values a launch file's params
file gives them) must not touch a recording. Everything done or not vouched for is returned as
`notes`, one line each, for the node to log.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from piezo_narx_ros.errors import ConfigError


@dataclass
class Playback:
    """What to stream: the signal (N, n_axes) V or m, its rate (Hz) and the lines to log."""

    signal: np.ndarray
    fs: float
    loop: bool
    notes: list = field(default_factory=list)


def playback_signal(path: str, n_axes: int = 1, fs: float = 2000.0, column: str | None = None,
                    key: str = 'u', resample: bool = False, scale: float = 1.0,
                    offset: float = 0.0, loop: bool = False, u_min: float = -200.0,
                    u_max: float = 200.0) -> Playback:
    """
    Read `path` and return what command_node streams (module docstring for the rules).

    fs: Hz, for a file without a rate or as the target of `resample`; scale (1), offset (V, or m
    in position mode): applied as u * scale + offset; u_min, u_max: the node's clamp (samples
    beyond it are counted in a note). Every axis plays the same file.
    """
    from piezo_narx_ros.ident.data.loaders import read_signal
    from piezo_narx_ros.plant.signals import generate
    if not path:
        raise ConfigError('kind playback needs path (the .npz or text table to replay)')
    if not (np.isfinite(scale) and np.isfinite(offset)):
        raise ConfigError('playback scale and offset must be finite')
    rec = read_signal(path, column, key)
    notes = list(rec.issues)
    if rec.fs is None:
        rate = fs
        notes.append(f'{path} records no rate (no fs, no time column): streamed at {fs:g} Hz '
                     '(fs); set fs if it was recorded at another')
    elif abs(rec.fs - fs) <= 1e-9 * fs or not resample:
        rate = rec.fs
        if abs(rec.fs - fs) > 1e-9 * fs:
            notes.append(f'{path} was recorded at {rec.fs:g} Hz: streamed at that rate, as '
                         f'recorded, not at fs {fs:g} Hz (resample:=true resamples it to fs)')
    else:
        rate = fs
        notes.append(f'{path} was recorded at {rec.fs:g} Hz: resampled to {fs:g} Hz (linear)')
    u = generate('playback', rate, None, None, 0.0, path=path, column=column, key=key,
                 resample=resample, u_min=-UNLIMITED, u_max=UNLIMITED)
    if scale != 1.0 or offset != 0.0:
        u = u * scale + offset
        notes.append(f'{path} played as u * {scale:g} + {offset:g} (scale, offset)')
    # Not clamped here (the limits are the streamer's, CommandStreamer), so that they are counted.
    clamped = int(np.count_nonzero((u < u_min) | (u > u_max)))
    if clamped:
        notes.append(f'{clamped} sample(s) of {path} beyond [{u_min:g}, {u_max:g}] are '
                     'clamped to the limits')
    if loop and u.size > 1:
        jump = abs(float(u[-1] - u[0]))
        if jump > 0.01 * max(float(np.ptp(u)), 1e-12):
            notes.append(f'looping {path} jumps {jump:.4g} from its last sample to its first')
    return Playback(np.repeat(u[:, None], n_axes, axis=1), float(rate), bool(loop), notes)


UNLIMITED = 1e300
