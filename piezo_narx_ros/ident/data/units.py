"""
Units of recorded data: the user's stated units, their conversion to SI, and plausibility checks.

Every record is volts and metres inside the package (../shared/DESIGN.md). A file in µm, nm, mV
or raw sensor counts read as if it were SI fits without an error into a model that says metres
(an output range of ±40 m), so magnitudes no piezo actuator produces are refused with the option
that fixes them, unless the user stated the unit (then the stated unit is trusted).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from piezo_narx_ros.errors import ConfigError, DataError

# Unit name -> factor to SI (V, m, s). 'um' is the ASCII spelling of µm.
U_UNITS = {'V': 1.0, 'mV': 1e-3, 'kV': 1e3}
Y_UNITS = {'m': 1.0, 'mm': 1e-3, 'um': 1e-6, 'µm': 1e-6, 'nm': 1e-9}
T_UNITS = {'s': 1.0, 'ms': 1e-3, 'us': 1e-6, 'µs': 1e-6, 'ns': 1e-9}
# Largest |y| (m) and |u| (V) read as SI without a stated unit: a piezo deflects by well under a
# centimetre (the Bouc-Wen benchmark's shaker reaches 2.7 mm), amplifiers stay below 10 kV.
Y_PLAUSIBLE_M = 1e-2
U_PLAUSIBLE_V = 1e4
# Records fitted together whose spans differ by more than this factor are in different units
# (the unit steps are factors of 1000).
SPAN_RATIO_LIMIT = 300.0


@dataclass(frozen=True)
class Units:
    """
    How a record's columns are to be read: units of u, y and t, or a scale for y.

    y_scale: metres per recorded unit (e.g. a sensor's metres per count), instead of y.
    stated: the fields the user gave explicitly ('u', 'y', 't'); a stated unit is trusted even
    when the magnitudes look implausible for it.
    """

    u: str = 'V'
    y: str = 'm'
    t: str = 's'
    y_scale: float | None = None
    stated: frozenset = field(default_factory=frozenset)

    def __post_init__(self):
        for name, table, value in (('u', U_UNITS, self.u), ('y', Y_UNITS, self.y),
                                   ('t', T_UNITS, self.t)):
            if value not in table:
                raise ConfigError(f'--{name}-unit must be one of {", ".join(table)}, got '
                                  f'{value!r}')
        if self.y_scale is not None and not (math.isfinite(self.y_scale) and self.y_scale > 0):
            raise ConfigError(f'--y-scale must be a positive number of metres per recorded unit, '
                              f'got {self.y_scale}')

    @classmethod
    def from_options(cls, u_unit=None, y_unit=None, t_unit=None, y_scale=None) -> 'Units':
        """Units from command-line options (None: not given, the SI default)."""
        if y_unit is not None and y_scale is not None:
            raise ConfigError('give --y-unit or --y-scale, not both')
        stated = {n for n, v in (('u', u_unit), ('y', y_unit if y_scale is None else y_scale),
                                 ('t', t_unit)) if v is not None}
        return cls(u=u_unit or 'V', y=y_unit or 'm', t=t_unit or 's', y_scale=y_scale,
                   stated=frozenset(stated))

    @property
    def u_factor(self) -> float:
        """Volts per recorded unit of u."""
        return U_UNITS[self.u]

    @property
    def y_factor(self) -> float:
        """Metres per recorded unit of y."""
        return self.y_scale if self.y_scale is not None else Y_UNITS[self.y]

    @property
    def t_factor(self) -> float:
        """Seconds per recorded unit of t."""
        return T_UNITS[self.t]

    def describe(self) -> str:
        """Say what was stated, for messages and the model's provenance ('' when nothing was)."""
        parts = [f'u in {self.u}' if 'u' in self.stated else '',
                 (f'y x {self.y_scale:g} m' if self.y_scale is not None else f'y in {self.y}')
                 if 'y' in self.stated else '',
                 f't in {self.t}' if 't' in self.stated else '']
        return ', '.join(p for p in parts if p)


SI = Units()


def _peak(x) -> float:
    x = np.asarray(x, dtype=float)
    return float(np.max(np.abs(x))) if x.size else 0.0


def check_magnitudes(u, y, source: str, units: Units = SI) -> None:
    """
    Refuse u (V) and y (m), already converted, whose magnitudes no piezo rig produces.

    Skipped for a field whose unit the user stated. DataError names the value and the option.
    """
    if 'y' not in units.stated:
        peak = _peak(y)
        if peak > Y_PLAUSIBLE_M:
            raise DataError(
                f'{source}: y reaches {peak:.4g}, which as metres is {peak:.3g} m; a piezo '
                f'deflection stays below {Y_PLAUSIBLE_M:g} m. If y is in um pass --y-unit um '
                '(mm, nm likewise); sensor counts: --y-scale METRES_PER_COUNT; if it really is '
                'metres, say so with --y-unit m')
    if 'u' not in units.stated:
        peak = _peak(u)
        if peak > U_PLAUSIBLE_V:
            raise DataError(
                f'{source}: u reaches {peak:.4g}, which as volts is beyond the {U_PLAUSIBLE_V:g} '
                'V any piezo amplifier gives. If u is in mV pass --u-unit mV; if it really is '
                'volts, say so with --u-unit V')


def check_consistent(records) -> None:
    """
    Refuse records fitted together whose u or y spans differ by more than SPAN_RATIO_LIMIT.

    One in µm beside one in m is a factor of 10^6; honest records of one rig differ by far less.
    """
    for name, unit in (('y', 'm'), ('u', 'V')):
        spans = [(float(np.ptp(getattr(r, name))), r.source) for r in records]
        spans = [s for s in spans if s[0] > 0]
        if len(spans) < 2:
            continue
        (lo, lo_src), (hi, hi_src) = min(spans), max(spans)
        if hi > SPAN_RATIO_LIMIT * lo:
            raise DataError(
                f'{name} spans {hi:.3g} {unit} in {hi_src} but {lo:.3g} {unit} in {lo_src} (a '
                f'factor {hi / lo:.3g}): records in different units? Convert them to one unit '
                f'(--{name}-unit applies to every input) or fit them apart')


def model_unit_problem(model) -> str | None:
    """
    One phrase when a model's trained ranges are not plausible volts and metres, else None.

    A model fitted on µm or counts read as metres (before the checks above) says so only through
    its ranges.
    """
    problems = []
    # Ranges are (min, max) for one channel, ((min...), (max...)) for several: the widest counts.
    out = getattr(model, 'output_range', None)
    if out is not None and np.max(np.abs(np.asarray(out, dtype=float))) > Y_PLAUSIBLE_M:
        lo, hi = np.min(out[0]), np.max(out[1])
        problems.append(f'trained output range [{lo:.4g}, {hi:.4g}] m is not a piezo '
                        'deflection in metres (data in um, nm or counts?)')
    inp = getattr(model, 'input_range', None)
    if inp is not None and np.max(np.abs(np.asarray(inp, dtype=float))) > U_PLAUSIBLE_V:
        lo, hi = np.min(inp[0]), np.max(inp[1])
        problems.append(f'trained input range [{lo:.4g}, {hi:.4g}] V is not volts '
                        '(data in mV?)')
    if not problems:
        return None
    return "the model's " + ' and '.join(problems) + ': refit it with --y-unit / --u-unit'
