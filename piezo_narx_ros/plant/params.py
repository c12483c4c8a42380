"""
Physical parameters of the simulated PZT/nickel unimorph cantilever and their validation.

Every value lives in config/plant.yaml (SI units), where each is documented with its source or
reason; docs/plant.md derives the beam-theory figures. This module only reads and checks them.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path

from piezo_narx_ros.errors import ConfigError


@dataclass(frozen=True)
class PlantParams:
    """
    Parameters of the plant; SI units (V, m, s, Hz).

    Amplifier: output clamped to [v_min, v_max] V, slew-limited to slew_rate V/s, first-order
    small-signal bandwidth amp_bandwidth Hz.
    Hysteresis, `hysteresis` = 'bouc_wen' (Rakotondrabe's form): w = d_p*v - h,
    dh/dt = A*d_p*dv/dt - B*|dv/dt|*h - gamma*dv/dt*|h|; d_p in m/V, A dimensionless, B and gamma
    in 1/V.
    Or 'preisach' (a structurally different plant for checking model families, docs/envelope.md):
    w = preisach_d_rev*v + sum over preisach_radii relay half-widths r_i (uniform up to
    preisach_r_max V) of weights_i*erf((play_r_i(v) - c_i)/(preisach_spread*sqrt2)), weights_i
    proportional to exp(-r_i/preisach_r0) and summing to preisach_gain m, relay centres
    c_i = preisach_centre + preisach_centre_slope*r_i V; zero at rest.
    Creep: `creep_input` = 'hysteresis': z = w + sum_i creep_gains[i]*x_i with
    tau_i dx_i/dt = w - x_i (gains dimensionless, s); 'voltage': the hysteresis is driven by
    v + sum_i creep_gains[i]*(x_i - v) with tau_i dx_i/dt = v - x_i, so creep passes through it.
    Mode: tip deflection y obeys y'' + 2*zeta*wn*y' + wn^2*y = wn^2*z, wn = 2*pi*mode_frequency.
    Sensor: first-order low-pass sensor_bandwidth Hz, white noise noise_std m, quantisation step m.
    substeps: integration sub-steps per sample (linear parts are exact per sub-step).
    """

    v_min: float = -200.0
    v_max: float = 200.0
    slew_rate: float = 1.0e5
    amp_bandwidth: float = 3000.0
    d_p: float = 4.8e-7
    A: float = 0.30
    B: float = 0.011
    gamma: float = 0.004
    hysteresis: str = 'bouc_wen'
    preisach_d_rev: float = 2.0e-7
    preisach_gain: float = 2.0e-5
    preisach_radii: int = 48
    preisach_r_max: float = 200.0
    preisach_r0: float = 40.0
    preisach_centre: float = 0.0
    preisach_centre_slope: float = 0.0
    preisach_spread: float = 120.0
    creep_input: str = 'hysteresis'
    creep_gains: tuple = field(default=(0.008, 0.008, 0.008, 0.008))
    creep_time_constants: tuple = field(default=(0.1, 1.0, 10.0, 100.0))
    mode_frequency: float = 765.0
    mode_damping: float = 0.02
    sensor_bandwidth: float = 5000.0
    noise_std: float = 3.3e-8
    quantisation: float = 5.0e-9
    substeps: int = 16

    def __post_init__(self):
        validate(self)

    def replace(self, **changes) -> 'PlantParams':
        """Return a copy with some fields changed (validated), e.g. noise_std=0.0."""
        return dataclasses.replace(self, **changes)

    def as_dict(self) -> dict:
        """Plain dict (lists for the creep tuples) for YAML/JSON metadata."""
        out = dataclasses.asdict(self)
        out['creep_gains'] = list(self.creep_gains)
        out['creep_time_constants'] = list(self.creep_time_constants)
        return out


def _finite(name, value, lo=None, hi=None, lo_open=False):
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ConfigError(f'plant parameter {name} must be a number, got {value!r}')
    value = float(value)
    if not math.isfinite(value):
        raise ConfigError(f'plant parameter {name} must be finite, got {value!r}')
    if lo is not None and (value <= lo if lo_open else value < lo):
        raise ConfigError(f'plant parameter {name} must be {">" if lo_open else ">="} {lo}, '
                          f'got {value!r}')
    if hi is not None and value > hi:
        raise ConfigError(f'plant parameter {name} must be <= {hi}, got {value!r}')
    return value


HYSTERESIS_KINDS = ('bouc_wen', 'preisach')
CREEP_INPUTS = ('hysteresis', 'voltage')
_STRING_FIELDS = ('hysteresis', 'creep_input')


def validate(p: PlantParams) -> None:
    """Raise ConfigError naming the first invalid parameter."""
    if p.hysteresis not in HYSTERESIS_KINDS:
        raise ConfigError('plant parameter hysteresis must be one of '
                          f'{", ".join(HYSTERESIS_KINDS)}, got {p.hysteresis!r}')
    if p.creep_input not in CREEP_INPUTS:
        raise ConfigError(f'plant parameter creep_input must be one of {", ".join(CREEP_INPUTS)}, '
                          f'got {p.creep_input!r}')
    _finite('preisach_d_rev', p.preisach_d_rev, 0.0)
    _finite('preisach_gain', p.preisach_gain, 0.0)
    for name in ('preisach_r_max', 'preisach_r0', 'preisach_spread'):
        _finite(name, getattr(p, name), 0.0, lo_open=True)
    _finite('preisach_centre', p.preisach_centre)
    _finite('preisach_centre_slope', p.preisach_centre_slope)
    if (isinstance(p.preisach_radii, bool) or not isinstance(p.preisach_radii, int)
            or not 1 <= p.preisach_radii <= 1000):
        raise ConfigError(f'plant parameter preisach_radii must be an integer in 1..1000, '
                          f'got {p.preisach_radii!r}')
    for name in ('v_min', 'v_max', 'd_p', 'A', 'B', 'gamma'):
        _finite(name, getattr(p, name))
    if not p.v_min < p.v_max:
        raise ConfigError(f'plant parameter v_min ({p.v_min}) must be below v_max ({p.v_max})')
    if not (isinstance(p.slew_rate, (int, float)) and p.slew_rate > 0
            and not math.isnan(p.slew_rate)):
        raise ConfigError('plant parameter slew_rate must be > 0 V/s (.inf for none), got '
                          f'{p.slew_rate!r}')
    for name in ('amp_bandwidth', 'mode_frequency', 'sensor_bandwidth'):
        _finite(name, getattr(p, name), 0.0, lo_open=True)
    _finite('d_p', p.d_p, 0.0, lo_open=True)
    _finite('A', p.A, 0.0)
    # B > 0 and |gamma| <= B keep the Bouc-Wen state bounded and the loop passive.
    if not (p.B > 0 and abs(p.gamma) <= p.B):
        raise ConfigError(f'plant parameters B ({p.B}) and gamma ({p.gamma}) must satisfy B > 0 '
                          'and |gamma| <= B')
    _finite('mode_damping', p.mode_damping, 0.0, lo_open=True)
    _finite('noise_std', p.noise_std, 0.0)
    _finite('quantisation', p.quantisation, 0.0)
    if (isinstance(p.substeps, bool) or not isinstance(p.substeps, int)
            or not 1 <= p.substeps <= 1000):
        raise ConfigError('plant parameter substeps must be an integer in 1..1000, got '
                          f'{p.substeps!r}')
    gains, taus = p.creep_gains, p.creep_time_constants
    if not isinstance(gains, (tuple, list)) or not isinstance(taus, (tuple, list)):
        raise ConfigError('plant parameters creep_gains and creep_time_constants must be lists')
    if len(gains) != len(taus):
        raise ConfigError(f'plant parameters creep_gains ({len(gains)}) and creep_time_constants '
                          f'({len(taus)}) must have the same length')
    for i, (g, tau) in enumerate(zip(gains, taus)):
        _finite(f'creep_gains[{i}]', g, 0.0)
        _finite(f'creep_time_constants[{i}]', tau, 0.0, lo_open=True)


def read_yaml_mapping(path, what: str = 'plant config') -> dict:
    """Read a YAML file holding a mapping; ConfigError naming the file and the problem."""
    import yaml

    path = Path(path)
    try:
        text = path.read_text(encoding='utf-8')
    except OSError as exc:
        raise ConfigError(f'cannot read {what} {path}: {exc.strerror or exc}') from None
    except UnicodeDecodeError as exc:
        raise ConfigError(f'{what} {path} must be UTF-8 text (byte {exc.start} is '
                          'not)') from None
    try:
        doc = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ConfigError(f'{what} {path} is not valid YAML: '
                          f'{str(exc).splitlines()[0]}') from None
    if not isinstance(doc, dict):
        raise ConfigError(f'{what} {path} must hold a mapping')
    return doc


def load_plant_params(path=None) -> PlantParams:
    """
    Read plant parameters from a YAML file (config/plant.yaml by default).

    The file holds a mapping `plant:` of PlantParams fields (SI units); fields it leaves out keep
    their defaults. Unknown keys, wrong types and out-of-range values raise ConfigError naming the
    key.
    """
    if path is None:
        # config/plant.yaml of this copy: share/piezo_narx_ros when installed, else the source tree
        from piezo_narx_ros.share import config_path
        path = config_path('plant.yaml')
    try:
        doc = read_yaml_mapping(path)
    except ConfigError as exc:
        if 'must hold a mapping' not in str(exc):
            raise
        doc = None
    if isinstance(doc, dict) and 'axes' in doc:
        # A stage file's `plant:` holds only the fields its axes share: read as one cantilever
        # it would silently simulate something else than the file describes.
        raise ConfigError(f'plant config {path} describes a stage of several axes (axes: '
                          f'{doc["axes"]}); this needs one cantilever\'s parameters '
                          '(config/plant.yaml); stages are for simulate and simulator_node')
    if isinstance(doc, dict) and 'plant' in doc:
        doc = doc['plant']
    if not isinstance(doc, dict):
        raise ConfigError(f'plant config {path} must hold a mapping of parameters under "plant:"')
    return plant_params_from(doc, f'plant config {path}')


def plant_params_from(doc: dict, where: str, base: PlantParams | None = None) -> PlantParams:
    """
    Build PlantParams from a mapping of fields (SI units), the others from `base` (or defaults).

    where: names the source in errors ('plant config FILE'). Unknown keys, wrong types and
    out-of-range values raise ConfigError naming the key.
    """
    known = {f.name for f in dataclasses.fields(PlantParams)}
    unknown = sorted(set(doc) - known)
    if unknown:
        raise ConfigError(f'{where}: unknown parameter {unknown[0]!r}')
    values = dict(doc)
    for key in ('creep_gains', 'creep_time_constants'):
        if key in values:
            if not isinstance(values[key], (list, tuple)):
                raise ConfigError(f'{where}: {key} must be a list, got '
                                  f'{values[key]!r}')
            values[key] = tuple(values[key])
    for key, value in values.items():
        # YAML reads `1e5` (no dot) as a string; accept numeric strings for float fields.
        if isinstance(value, str) and key not in ('substeps', 'preisach_radii') + _STRING_FIELDS:
            try:
                values[key] = float(value)
            except ValueError:
                raise ConfigError(f'{where}: {key} must be a number, got '
                                  f'{value!r}') from None
    try:
        if base is not None:
            return dataclasses.replace(base, **values)
        return PlantParams(**values)
    except ConfigError as exc:
        raise ConfigError(f'{where}: {exc}') from None
