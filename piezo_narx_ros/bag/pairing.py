"""
Pair command (u) and deflection (y) samples by their header stamps and check the sample clock.

Every node that answers sample k copies the command's stamp t_k, so u(k) and y(k) are matched by
equal stamps, not by arrival order. These functions are pure numpy: stamps are int64 nanoseconds.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from piezo_narx_ros.errors import BagError

# A period longer than GAP_FACTOR x the nominal one is a gap (missing samples), not jitter.
GAP_FACTOR = 1.5
# Periods (gaps excluded) varying by more than this fraction of the nominal period: irregular rate.
JITTER_TOLERANCE = 0.05
# Command samples before the first or after the last paired one, beyond this fraction of the
# command stream and this count, are reported: a deflection that stops halfway must not be trimmed
# silently (a few samples at the ends are the usual discovery race of a recorder).
END_TRIM_TOLERANCE = 0.01
END_TRIM_SAMPLES = 20


@dataclass
class StreamCheck:
    """What `clean_stream` found in one topic's stamps."""

    received: int = 0          # messages read
    reordered: int = 0         # messages whose stamp is earlier than the one received before
    duplicates: int = 0        # repeated stamps dropped (first occurrence kept)
    conflicting: int = 0       # of those, repeats whose value differed from the kept one
    malformed: int = 0         # messages without the expected field (dropped before pairing)
    missing_axes: dict = field(default_factory=dict)   # of those, {axis: samples without it}


@dataclass
class PairingReport:
    """Non-fatal findings of `pair_by_stamp`; `issues()` gives one line per finding."""

    command: StreamCheck = field(default_factory=StreamCheck)
    deflection: StreamCheck = field(default_factory=StreamCheck)
    paired: int = 0
    unmatched_command: int = 0        # command samples without a deflection of the same stamp
    unmatched_deflection: int = 0     # and the reverse
    interior_unmatched: int = 0       # of those, inside the paired time span (not at its ends)
    command_samples: int = 0          # command samples after cleaning
    dropped_deflection: int = 0       # command samples inside the paired span without deflection
    head_trimmed: int = 0             # command samples before the first paired one
    tail_trimmed: int = 0             # command samples after the last paired one
    fs: float = 0.0                   # Hz, the command stream's rate (median command period)
    gaps: list[tuple[float, int]] = field(default_factory=list)  # (time s from start, missing)
    jitter: float = 0.0               # max |period - 1/fs| * fs over periods that are not gaps
    t0_ns: int = 0                    # stamp of the first paired sample, ns since the epoch

    @property
    def missing_samples(self) -> int:
        """Count the samples absent inside the paired sequence (sum over gaps)."""
        return int(sum(n for _, n in self.gaps))

    def issues(self) -> list[str]:
        """One line per non-fatal finding (empty when the record is clean)."""
        out = []
        for name, s in (('command', self.command), ('deflection', self.deflection)):
            if s.malformed:
                axes = ', '.join(f'{a} in {m}' for a, m in s.missing_axes.items())
                out.append(f'{name}: {s.malformed} message(s) without the expected value, dropped'
                           + (f' (axis missing: {axes})' if axes else ''))
            if s.reordered:
                out.append(f'{name}: {s.reordered} message(s) arrived out of stamp order, sorted')
            if s.duplicates:
                extra = f' ({s.conflicting} with a different value)' if s.conflicting else ''
                out.append(f'{name}: {s.duplicates} duplicate stamp(s) dropped{extra}')
        if self.dropped_deflection:
            share = 100.0 * self.dropped_deflection / max(1, self.command_samples)
            out.append(f'deflection misses {self.dropped_deflection} of {self.command_samples} '
                       f'command samples inside the record ({share:.3g} %); the record keeps '
                       f'the command rate {self.fs:.6g} Hz and has gaps there')
        if self.interior_unmatched > self.dropped_deflection:
            out.append(f'{self.interior_unmatched - self.dropped_deflection} deflection '
                       'sample(s) inside the record have no command with the same stamp, dropped')
        limit = max(END_TRIM_SAMPLES, END_TRIM_TOLERANCE * self.command_samples)
        for n, where in ((self.head_trimmed, 'starts'), (self.tail_trimmed, 'ends')):
            if n > limit:
                out.append(f'deflection {where} {n / self.fs:.6g} s ({n} command samples) '
                           f'{"after" if where == "starts" else "before"} the command stream: '
                           'the record is trimmed to the paired part')
        if self.gaps:
            first_t, first_n = self.gaps[0]
            out.append(f'{len(self.gaps)} gap(s), {self.missing_samples} missing sample(s) in the '
                       f'paired record (first at t={first_t:.6g} s, {first_n} missing): lagged '
                       'regressors across a gap join non-adjacent samples')
        if self.jitter > JITTER_TOLERANCE:
            out.append(f'irregular sample rate: periods deviate by up to {100 * self.jitter:.3g}% '
                       f'from 1/fs (fs = {self.fs:.6g} Hz)')
        return out


def clean_stream(stamps_ns: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray,
                                                                     StreamCheck]:
    """
    Sort one topic's samples by stamp and drop repeated stamps (first received kept).

    stamps_ns: (n,) int64 header stamps in arrival order; values: (n,) or (n, axes) float64.
    Returns (stamps (m,) strictly increasing, values (m,) or (m, axes), StreamCheck).
    """
    stamps_ns = np.asarray(stamps_ns, dtype=np.int64)
    values = np.asarray(values, dtype=np.float64)
    check = StreamCheck(received=int(stamps_ns.size))
    if stamps_ns.size == 0:
        return stamps_ns, values, check
    check.reordered = int(np.count_nonzero(np.diff(stamps_ns) < 0))
    order = np.argsort(stamps_ns, kind='stable')  # stable: the first received of a repeat is kept
    s, v = stamps_ns[order], values[order]
    repeat = np.concatenate(([False], np.diff(s) == 0))
    check.duplicates = int(np.count_nonzero(repeat))
    if check.duplicates:
        # Compare each repeat with the kept sample of its stamp (the first of its run).
        keep_index = np.maximum.accumulate(np.where(~repeat, np.arange(s.size), 0))
        same = (v == v[keep_index]) | (np.isnan(v) & np.isnan(v[keep_index]))
        if same.ndim > 1:   # several axes: a repeat conflicts when any axis differs
            same = np.all(same, axis=1)
        differs = repeat & ~same
        check.conflicting = int(np.count_nonzero(differs))
    return s[~repeat], v[~repeat], check


def sample_clock(stamps_ns: np.ndarray, period_ns: float | None = None
                 ) -> tuple[float, list[tuple[float, int]], float]:
    """
    Nominal rate, gaps and jitter of a strictly increasing stamp sequence (int64 ns, n >= 2).

    period_ns: the nominal period (ns) when known (e.g. the command stream's); by default the
    median period of these stamps. Returns (fs Hz = 1 / period, [(t s from the first stamp,
    missing samples)], jitter = max |period - T| / T over the periods that are not gaps).
    """
    d = np.diff(np.asarray(stamps_ns, dtype=np.int64))
    if d.size == 0:
        raise BagError('need at least 2 samples to infer the sample rate')
    period = float(np.median(d)) if period_ns is None else float(period_ns)
    if period <= 0:
        raise BagError('stamps do not increase: cannot infer the sample rate')
    is_gap = d > GAP_FACTOR * period
    gaps = [(float(stamps_ns[i] - stamps_ns[0]) * 1e-9, int(round(d[i] / period)) - 1)
            for i in np.flatnonzero(is_gap)]
    regular = d[~is_gap]
    jitter = float(np.max(np.abs(regular - period)) / period) if regular.size else 0.0
    return 1e9 / period, gaps, jitter


def pair_by_stamp(t_u_ns: np.ndarray, u: np.ndarray, t_y_ns: np.ndarray, y: np.ndarray,
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, PairingReport]:
    """
    Match command samples u (V) and deflection samples y (m) with equal header stamps.

    Inputs are in arrival order (int64 ns stamps, float64 values (n,) or (n, axes)). Returns
    (t_ns (N,) int64 sorted, u (N,) or (N, axes), y likewise, PairingReport). The rate is the
    command stream's (the clock every node copies), so a deflection that lost every other sample
    gives a record at the command rate with gaps, not a record at half the rate. Raises BagError
    when fewer than 2 samples pair up.
    """
    tu, uu, cu = clean_stream(t_u_ns, u)
    ty, yy, cy = clean_stream(t_y_ns, y)
    report = PairingReport(command=cu, deflection=cy)
    if tu.size == 0 or ty.size == 0:
        which = 'command' if tu.size == 0 else 'deflection'
        raise BagError(f'no {which} samples to pair')
    t, iu, iy = np.intersect1d(tu, ty, assume_unique=True, return_indices=True)
    if t.size < 2:
        raise BagError(f'only {t.size} command/deflection stamp(s) match ({tu.size} command, '
                       f'{ty.size} deflection): the deflection must carry the stamp t_k of the '
                       'command it answers')
    report.paired = int(t.size)
    report.unmatched_command = int(tu.size - t.size)
    report.unmatched_deflection = int(ty.size - t.size)
    inside = ((tu > t[0]) & (tu < t[-1])).sum() + ((ty > t[0]) & (ty < t[-1])).sum()
    report.interior_unmatched = int(inside - 2 * (t.size - 2))
    report.command_samples = int(tu.size)
    report.dropped_deflection = int(((tu > t[0]) & (tu < t[-1])).sum() - (t.size - 2))
    report.head_trimmed = int((tu < t[0]).sum())
    report.tail_trimmed = int((tu > t[-1]).sum())
    period = float(np.median(np.diff(tu))) if tu.size >= 2 else None
    report.fs, report.gaps, report.jitter = sample_clock(t, period)
    report.t0_ns = int(t[0])
    return t, uu[iu], yy[iy], report
