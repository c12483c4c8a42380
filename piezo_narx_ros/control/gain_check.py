"""
Can a model's static line be trusted to scale commands? ROS-free checks of `inverse.static_gain`.

The `linear` mode sends u = (r - c) / g with (g, c) the straight line through the model's own free
run on a slow full-range sine. A model that runs away on slow moves (the paper's NARX fitted on a
short multisine does) gives a line of the wrong sign or size, and the stage is then driven in
anti-phase. `check_static_gain` says why a line cannot be vouched for:

- the free run that measures it leaves the model's trained output range by more than
  OUTPUT_MARGIN of its span (the model is extrapolating its own output: a runaway);
- the line explains less than MIN_LINE_R2 of that free run's variance (no line there);
- |g| x trained input span differs from the trained output span by more than a factor
  GAIN_FACTOR (the model's ranges are those of the data it was fitted on);
- the model file records the least-squares line of its training data (`fit` stores it as
  data.line since issue 19) and g has the other sign, or a size more than GAIN_FACTOR apart;
- an ARX model with a pole on or outside the unit circle (its DC gain means nothing).

`data_line(us, ys)` is that least-squares line of recorded data, for `fit` to store.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from piezo_narx_ros.errors import ConfigError

OUTPUT_MARGIN = 0.25
MIN_LINE_R2 = 0.8
GAIN_FACTOR = 2.0


@dataclass
class GainCheck:
    """The static line of a model and what speaks against it."""

    gain: float                     # m/V
    offset: float                   # m
    line_r2: float                  # share of the free run's variance the line explains
    free_run: tuple[float, float]   # (min, max) of the free run that measured it, m
    training_gain: float | None     # m/V, least-squares line of the training data (model file)
    problems: list[str] = field(default_factory=list)

    @property
    def trusted(self) -> bool:
        """Return True when nothing speaks against the line."""
        return not self.problems

    @property
    def plant_sign(self) -> int:
        """Sign of the plant's gain as far as it is known (0: unknown)."""
        if self.training_gain:
            return 1 if self.training_gain > 0 else -1
        return (1 if self.gain > 0 else -1) if self.trusted else 0


def data_line(us, ys) -> dict:
    """
    Least-squares line y = gain u + offset through recorded data.

    us, ys: one array or a list of arrays (records) of V and m. Returns {'gain_m_per_v',
    'offset_m', 'r2'}: what a user fits to a record by hand, stored with the model so that its
    own line can be checked against the data later. None for records of several inputs or
    outputs: a line is one input against one output (several axes are checked by
    control.axes.static_gains on the model itself).
    """
    us, ys = _as_list(us), _as_list(ys)
    if any(np.ndim(x) > 1 and np.shape(x)[1] != 1 for x in us + ys):
        return None
    u = np.concatenate([np.asarray(x, float).ravel() for x in us])
    y = np.concatenate([np.asarray(x, float).ravel() for x in ys])
    gain, offset = np.polyfit(u, y, 1)
    return {'gain_m_per_v': float(gain), 'offset_m': float(offset),
            'r2': _r2(y, gain * u + offset)}


def training_line(model) -> dict | None:
    """Return the least-squares line of the model's training data when its file has one."""
    data = (getattr(model, 'metadata', None) or {}).get('data')
    line = data.get('line') if isinstance(data, dict) else None
    if not isinstance(line, dict):
        return None
    gain = line.get('gain_m_per_v')
    if isinstance(gain, (int, float)) and not isinstance(gain, bool) and math.isfinite(gain) \
            and gain != 0:
        return line
    return None


def check_static_gain(model, fs: float | None = None, freq: float = 0.5,
                      periods: int = 2) -> GainCheck:
    """
    Measure the model's static line (as `inverse.static_gain`) and check it (module docstring).

    fs: Hz (the model's when None); freq: the slow sine, Hz, over the trained input range; the
    last of `periods` periods is used. ConfigError when the model has no input range or rate.
    """
    fs = fs or getattr(model, 'fs', None)
    rng_in = getattr(model, 'input_range', None)
    if not fs or rng_in is None:
        raise ConfigError('the model has no sample rate or no trained input range: its static '
                          'gain cannot be measured')
    lo, hi = rng_in
    n = int(round(fs / freq))
    t = np.arange(periods * n) / fs
    u = 0.5 * (lo + hi) + 0.5 * (hi - lo) * np.sin(2 * np.pi * freq * t)
    with np.errstate(all='ignore'):
        y = np.asarray(model.simulate(u), dtype=float)[-n:]
    u = u[-n:]
    problems = []
    if not np.all(np.isfinite(y)):
        gain = offset = r2 = math.nan
        span = (math.nan, math.nan)
        problems.append('its free run on a slow full-range sine diverges (non-finite output)')
    else:
        gain, offset = (float(v) for v in np.polyfit(u, y, 1))
        r2 = _r2(y, gain * u + offset)
        span = (float(y.min()), float(y.max()))
    if getattr(model, 'kind', None) == 'arx':
        a = np.asarray(model.a, dtype=float)
        poles = np.roots(np.concatenate(([1.0], a))) if a.size else np.array([])
        if poles.size and np.max(np.abs(poles)) >= 1.0:
            problems.append(f'the ARX model is unstable (a pole of modulus '
                            f'{np.max(np.abs(poles)):.4f} >= 1): its DC gain means nothing')
        den = 1.0 + float(np.sum(model.a))
        if den != 0:
            gain, offset = float(np.sum(model.b)) / den, float(model.c) / den
    line = training_line(model)
    check = GainCheck(gain, offset, r2, span, line['gain_m_per_v'] if line else None, problems)
    if problems:
        return check
    rng_out = getattr(model, 'output_range', None)
    if rng_out is not None:
        ylo, yhi = rng_out
        width = yhi - ylo
        beyond = max(ylo - span[0], span[1] - yhi)
        if width > 0 and beyond > OUTPUT_MARGIN * width:
            problems.append(
                f'its free run on a slow full-range sine reaches [{span[0]:.4g}, {span[1]:.4g}] '
                f'm, {beyond / width:.0%} of the trained output span beyond the trained range '
                f'[{ylo:.4g}, {yhi:.4g}] m (the model runs away on slow moves)')
        ratio = abs(gain) * (hi - lo) / width if width > 0 else math.nan
        if width > 0 and not 1 / GAIN_FACTOR <= ratio <= GAIN_FACTOR:
            problems.append(f'|gain| x trained input span is {ratio:.3g} x the trained output '
                            'span (should be about 1)')
    if not gain or not math.isfinite(gain):
        problems.append(f'the fitted gain is {gain:g} m/V')
    elif not r2 >= MIN_LINE_R2:
        problems.append(f'a line explains only {max(r2, 0.0):.0%} of its free run on a slow '
                        'full-range sine (no static line there)')
    if line and gain and math.isfinite(gain):
        ratio = gain / line['gain_m_per_v']
        if ratio < 0:
            problems.append(f"its sign is opposite to the training data's line "
                            f'({line["gain_m_per_v"] * 1e6:.4g} um/V): it would drive the stage '
                            'in anti-phase')
        elif not 1 / GAIN_FACTOR <= ratio <= GAIN_FACTOR:
            problems.append(f"it is {ratio:.3g} x the training data's line "
                            f'({line["gain_m_per_v"] * 1e6:.4g} um/V)')
    return check


def _as_list(x) -> list:
    return list(x) if isinstance(x, (list, tuple)) else [x]


def _r2(y, fit) -> float:
    sst = float(((y - y.mean()) ** 2).sum())
    return 1.0 - float(((y - fit) ** 2).sum()) / sst if sst > 0 else math.nan
