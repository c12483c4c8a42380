"""
Samples that measured the sensor, not the actuator: an output held at its full scale.

A displacement sensor or its converter clips at the end of its range. The record then shows the
output flat at one value while the actuator, still driven, moves on. A model fitted on such
samples learns a flat top that the actuator does not have, and a score against them measures the
sensor. A converter clips to one code, so the test is exact: the output repeats its extreme value
for a run of samples while the input moves by more than the sensor could have missed.
"""
from __future__ import annotations

import numpy as np

#: A run counts when the input moves by at least this share of its record's span during it. An
#: actuator that reverses at a peak moves on at a sizeable share of its average slope (the
#: hysteresis loop has no flat branch), so a working sensor leaves its extreme code within a
#: small fraction of the span.
MOVES = 0.03
#: ... and by at least this many of the output's codes (its finest step), for coarse sensors.
CODES = 3.0
#: Shortest run, samples.
MIN_RUN = 3


def _resolution(y: np.ndarray) -> float:
    """Return the finest step between the distinct values of y (its code, if quantised), m."""
    steps = np.diff(np.unique(y))
    return float(steps.min()) if steps.size else 0.0


def clipped_runs(u: np.ndarray, y: np.ndarray) -> list[tuple[int, int, str]]:
    """
    Return the runs [start, stop) where y (N,) m sits at its maximum or minimum as u moves.

    u: (N,) or (N, n_in) V; the input moves when any channel moves by MOVES of its span and by
    CODES output steps' worth of the output's span over the run. Each run is tagged 'maximum' or
    'minimum'. Empty for a constant y or a constant u.
    """
    u = np.asarray(u, dtype=np.float64).reshape(len(y), -1)
    y = np.asarray(y, dtype=np.float64)
    span_u = np.ptp(u, axis=0)
    span_y = float(np.ptp(y))
    if span_y == 0.0 or not np.any(span_u > 0.0):
        return []
    share = max(MOVES, CODES * _resolution(y) / span_y)
    out = []
    for side, value in (('maximum', y.max()), ('minimum', y.min())):
        edges = np.diff(np.r_[0, (y == value).astype(np.int8), 0])
        for start, stop in zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)):
            if stop - start < MIN_RUN:
                continue
            moved = np.ptp(u[start:stop], axis=0)
            if np.any((span_u > 0.0) & (moved >= share * span_u)):
                out.append((int(start), int(stop), side))
    return out


def saturation_warnings(records) -> list[str]:
    """
    One line per record output that sits at its full scale while the input moves (clipped_runs).

    records: Records (u V, y m, `source`, `outputs`). Says how many samples, in how many runs,
    and what to do: those samples measure the sensor, and nothing in the fit or the scores
    leaves them out.
    """
    out = []
    for r in records:
        for j in range(r.y.shape[1]):
            runs = clipped_runs(r.u, r.y[:, j])
            if not runs:
                continue
            n = sum(stop - start for start, stop, _ in runs)
            sides = sorted({side for _, _, side in runs})
            what = 'output' if r.y.shape[1] == 1 else f'output {r.outputs[j]}'
            where = ' and '.join(
                f'{side} ({r.y[:, j].max() if side == "maximum" else r.y[:, j].min():.6g} m)'
                for side in sides)
            out.append(f'{r.source}: the {what} sits at its {where} on {n} samples '
                       f'({n / len(r.y):.2%}) in {len(runs)} runs while the input moves: a '
                       'sensor at the end of its range? Those samples measure the sensor, not '
                       'the actuator, and are fitted and scored as they are; record within the '
                       "sensor's range (a smaller amplitude or a wider span)")
    return out
