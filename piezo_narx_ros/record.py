"""
The input/output record every part of the package exchanges (files, bags, identification).

It lives here, below both `ident` (which loads files and fits models) and `bag` (which reads
bags), so that neither has to import the other for it.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Record:
    """
    One experiment: input u (V; N for the Bouc-Wen benchmark) and measured output y (m).

    A segment cut out of a longer recording keeps what came before it in that recording
    (`u_before`, `y_before`, from the recording's start): a model whose state depends on the
    whole input history (hysteresis operators, creep) is then scored on the segment by running
    from the recording's start, as it would have run live.
    """

    u: np.ndarray               # (N,) input, V
    y: np.ndarray               # (N,) measured output, m
    fs: float                   # sample rate, Hz
    source: str                 # file or bag it came from
    t: np.ndarray | None = None       # (N,) sample stamps, s
    y_true: np.ndarray | None = None  # (N,) noise-free output when a simulator wrote it, m
    u_before: np.ndarray | None = None  # inputs preceding this segment in its recording, V
    y_before: np.ndarray | None = None  # outputs preceding it, m
    # How a model's free run on it starts: N > 0, the state that the first N measured samples of
    # its recording set (a recording that did not start at rest); 0: from rest; None: from the
    # first n0 measured outputs (lagged models, the paper's convention) or rest (the others).
    state_window: int | None = None

    def __len__(self) -> int:
        return int(self.u.size)

    def segment(self, start: int, stop: int, suffix: str = '') -> 'Record':
        """
        Return samples [start, stop) as a new Record (copies), `source` tagged with `suffix`.

        The samples before `start` become its u_before / y_before.
        """
        cut = slice(start, stop)
        before_u = (self.u[:start] if self.u_before is None
                    else np.r_[self.u_before, self.u[:start]])
        before_y = (self.y[:start] if self.y_before is None
                    else np.r_[self.y_before, self.y[:start]])
        return Record(u=self.u[cut].copy(), y=self.y[cut].copy(), fs=self.fs,
                      source=self.source + suffix,
                      t=None if self.t is None else self.t[cut].copy(),
                      y_true=None if self.y_true is None else self.y_true[cut].copy(),
                      u_before=before_u.copy() if before_u.size else None,
                      y_before=before_y.copy() if before_y.size else None,
                      state_window=self.state_window)

    def split(self, fraction: float = 0.5) -> tuple['Record', 'Record']:
        """(estimation, validation): the first `fraction` of the samples and the rest."""
        cut = int(round(len(self) * fraction))
        return (self.segment(0, cut, '[estimation]'), self.segment(cut, len(self), '[validation]'))
