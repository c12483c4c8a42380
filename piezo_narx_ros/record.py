"""
The input/output record every part of the package exchanges (files, bags, identification).

It lives here, below both `ident` (which loads files and fits models) and `bag` (which reads
bags), so that neither has to import the other for it.

Channels have an axis: `u` is (N, n_in) V and `y` (N, n_out) m, always 2-D, whatever the record
was built from (a 1-D array is the one-axis case and becomes one column). `inputs` / `outputs`
name the channels in column order. A model takes the one-axis case as 1-D arrays (that path is
bit-identical to the package before several axes): `channels_arg` gives a column block in the
form a model takes.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from piezo_narx_ros.errors import DataError

#: Names of the one channel of a one-axis record without names (and of a one-axis model file).
ONE_AXIS_INPUTS = ('u',)
ONE_AXIS_OUTPUTS = ('y',)


def default_names(prefix: str, n: int) -> tuple:
    """Channel names when a file gives none: ('u',) / ('y',) for one, else u1..un / y1..yn."""
    if n == 1:
        return (prefix,)
    return tuple(f'{prefix}{i + 1}' for i in range(n))


def as_columns(x, name: str = 'array') -> np.ndarray:
    """Return x as a C-contiguous float64 (N, n) array; a 1-D array becomes one column."""
    a = np.ascontiguousarray(x, dtype=np.float64)
    if a.ndim == 1:
        return a.reshape(-1, 1)
    if a.ndim != 2:
        raise DataError(f'{name} must be (N,) or (N, channels), got shape {a.shape}')
    return a


def channels_arg(a: np.ndarray | None):
    """
    Return a block of channels (N, n) in the form a model takes: (N,) for one channel.

    The one-channel column of a C-contiguous (N, 1) array is itself contiguous (a view), so the
    one-axis path hands models exactly the arrays it did before several axes.
    """
    if a is None:
        return None
    return a[:, 0] if a.ndim == 2 and a.shape[1] == 1 else a


def check_names(names, n: int, what: str, source: str) -> tuple:
    """Return names as a tuple of n distinct non-empty strings; DataError otherwise."""
    names = tuple(str(s) for s in names)
    if len(names) != n:
        raise DataError(f'{source}: {len(names)} {what} name(s) ({", ".join(names)}) for {n} '
                        f'{what} channel(s)')
    if any(not s.strip() for s in names) or len(set(names)) != n:
        raise DataError(f'{source}: {what} names must be distinct and non-empty, got '
                        f'{", ".join(map(repr, names))}')
    return names


@dataclass
class Record:
    """
    One experiment: input u (V; N for the Bouc-Wen benchmark) and measured output y (m).

    u (N, n_in) and y (N, n_out), 2-D always (1-D arrays given are stored as one column);
    inputs / outputs: the channel names (default ('u',), ('y',) for one channel, u1.. / y1..
    for several). A segment cut out of a longer recording keeps what came before it in that
    recording (`u_before`, `y_before`, from the recording's start): a model whose state depends
    on the whole input history (hysteresis operators, creep) is then scored on the segment by
    running from the recording's start, as it would have run live.
    """

    u: np.ndarray               # (N, n_in) input, V
    y: np.ndarray               # (N, n_out) measured output, m
    fs: float                   # sample rate, Hz
    source: str                 # file or bag it came from
    t: np.ndarray | None = None       # (N,) sample stamps, s
    y_true: np.ndarray | None = None  # (N, n_out) noise-free output when a simulator wrote it, m
    u_before: np.ndarray | None = None  # (M, n_in) inputs preceding this segment, V
    y_before: np.ndarray | None = None  # (M, n_out) outputs preceding it, m
    # How a model's free run on it starts: N > 0, the state that the first N measured samples of
    # its recording set (a recording that did not start at rest); 0: from rest; None: from the
    # first n0 measured outputs (lagged models, the paper's convention) or rest (the others).
    state_window: int | None = None
    # How the recording's unlogged past ended, for that state: 'any' or 'fade-out' (ident.state).
    state_past: str = 'any'
    # How that window is used (ident.start.START_POLICIES: 'rest', 'offset', 'state'); None: as
    # `state_window` says above (the presets' convention, the same as 'state' for the
    # hysteresis family).
    state_policy: str | None = None
    inputs: tuple | None = None       # n_in channel names (None: default_names)
    outputs: tuple | None = None      # n_out channel names

    def __post_init__(self):
        self.u = as_columns(self.u, 'u')
        self.y = as_columns(self.y, 'y')
        for name in ('y_true', 'u_before', 'y_before'):
            value = getattr(self, name)
            if value is not None:
                setattr(self, name, as_columns(value, name))
        if self.u.shape[0] != self.y.shape[0]:
            raise DataError(f'{self.source}: u has {self.u.shape[0]} samples but y has '
                            f'{self.y.shape[0]}')
        self.inputs = (default_names('u', self.n_in) if self.inputs is None
                       else check_names(self.inputs, self.n_in, 'input', self.source))
        self.outputs = (default_names('y', self.n_out) if self.outputs is None
                        else check_names(self.outputs, self.n_out, 'output', self.source))

    def __len__(self) -> int:
        return int(self.u.shape[0])

    @property
    def n_in(self) -> int:
        """Return the number of input channels."""
        return int(self.u.shape[1])

    @property
    def n_out(self) -> int:
        """Return the number of output channels."""
        return int(self.y.shape[1])

    def segment(self, start: int, stop: int, suffix: str = '') -> 'Record':
        """
        Return samples [start, stop) as a new Record (copies), `source` tagged with `suffix`.

        The samples before `start` become its u_before / y_before; the names are kept.
        """
        cut = slice(start, stop)
        before_u = (self.u[:start] if self.u_before is None
                    else np.concatenate([self.u_before, self.u[:start]]))
        before_y = (self.y[:start] if self.y_before is None
                    else np.concatenate([self.y_before, self.y[:start]]))
        return Record(u=self.u[cut].copy(), y=self.y[cut].copy(), fs=self.fs,
                      source=self.source + suffix,
                      t=None if self.t is None else self.t[cut].copy(),
                      y_true=None if self.y_true is None else self.y_true[cut].copy(),
                      u_before=before_u.copy() if before_u.size else None,
                      y_before=before_y.copy() if before_y.size else None,
                      state_window=self.state_window, state_past=self.state_past,
                      state_policy=self.state_policy, inputs=self.inputs, outputs=self.outputs)

    def split(self, fraction: float = 0.5) -> tuple['Record', 'Record']:
        """(estimation, validation): the first `fraction` of the samples and the rest."""
        cut = int(round(len(self) * fraction))
        return (self.segment(0, cut, '[estimation]'), self.segment(cut, len(self), '[validation]'))


def check_same_channels(records) -> None:
    """Raise DataError naming the first difference when records' channel names or order differ."""
    if not records:
        return
    first = records[0]
    for r in records[1:]:
        for what in ('inputs', 'outputs'):
            a, b = getattr(first, what), getattr(r, what)
            if a != b:
                diff = next((i for i in range(max(len(a), len(b)))
                             if i >= len(a) or i >= len(b) or a[i] != b[i]), 0)
                got_a = a[diff] if diff < len(a) else '(none)'
                got_b = b[diff] if diff < len(b) else '(none)'
                raise DataError(f'{r.source}: {what} {", ".join(b)} differ from '
                                f'{first.source}\'s {", ".join(a)} (channel {diff + 1}: '
                                f'{got_b!r} vs {got_a!r}); records fitted together need the '
                                'same channels in the same order')
