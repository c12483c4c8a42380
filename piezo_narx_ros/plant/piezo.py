"""
Simulated piezoelectric unimorph cantilever: amplifier, hysteresis, creep, first mode, sensor.

Signal chain (continuous time, integrated per sample with sub-steps):

    u_cmd (V, zero-order hold) -> amplifier: clamp, slew-limited first order -> v (V, "applied")
    v -> Bouc-Wen hysteresis -> w = d_p*v - h (m)
    w -> creep (parallel slow first-order elements) -> z (m)
    z -> first bending mode (2nd order, unit static gain) -> y_true (m, tip deflection)
    y_true -> sensor: first-order low-pass, white noise, offset, quantisation, full scale
           -> y (m, measured)

Sample k holds u_cmd[k] over [t_k, t_k + 1/fs] and reports y, y_true and v at the end of that
period, so y[k] depends on u[k] (the NARX regressor includes u(k)).
"""
from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from scipy.linalg import expm

from piezo_narx_ros.errors import ConfigError, DataError
from piezo_narx_ros.plant import kernels
from piezo_narx_ros.plant.params import PlantParams, load_plant_params

_NOISE_STREAM = 0x5E50  # tags the sensor-noise seed sequence (see reset())

# Standard normals drawn at a time by step(); the stream does not depend on the block size.
_NOISE_BLOCK = 4096


class PlantRun(NamedTuple):
    """Result of PiezoCantilever.run(): (N,) arrays."""

    u_applied: np.ndarray  # V, amplifier output at the end of each sample period
    y: np.ndarray          # m, measured deflection (sensor: low-pass, noise, quantisation)
    y_true: np.ndarray     # m, true tip deflection


def linear_system(p: PlantParams):
    """
    Continuous state-space (A, B) of the linear part, input w (m) from the hysteresis.

    States: creep x_1..x_m (m; none when creep acts on the voltage), tip deflection y (m), tip
    velocity (m/s), sensor output (m).
    """
    m = len(p.creep_gains) if p.creep_input == 'hysteresis' else 0
    n = m + 3
    a = np.zeros((n, n))
    b = np.zeros(n)
    iy, iv, isens = m, m + 1, m + 2
    wn = 2.0 * math.pi * p.mode_frequency
    ws = 2.0 * math.pi * p.sensor_bandwidth
    for i, tau in enumerate(p.creep_time_constants[:m]):
        a[i, i] = -1.0 / tau
        b[i] = 1.0 / tau
    # y'' = wn^2 * (w + sum k_i x_i - y) - 2 zeta wn y'
    a[iy, iv] = 1.0
    a[iv, :m] = wn ** 2 * np.asarray(p.creep_gains, dtype=float)[:m]
    a[iv, iy] = -wn ** 2
    a[iv, iv] = -2.0 * p.mode_damping * wn
    b[iv] = wn ** 2
    a[isens, iy] = ws
    a[isens, isens] = -ws
    return a, b


def foh_discretise(a, b, h):
    """
    Exact discretisation for an input linear in time over a step of h s (first-order hold).

    Returns (phi, g0, g1) with x(t+h) = phi x(t) + g0 w(t) + g1 (w(t+h) - w(t)).
    """
    n = a.shape[0]
    aug = np.zeros((n + 2, n + 2))
    aug[:n, :n] = a
    aug[:n, n] = b
    aug[n, n + 1] = 1.0 / h  # d/dt w = (w1 - w0)/h, carried as unit ramp scaled below
    e = expm(aug * h)
    return e[:n, :n].copy(), e[:n, n].copy(), e[:n, n + 1].copy()


def adc_grid(bits: int, span: float) -> tuple[float, float, float]:
    """
    Quantisation step and full scale of a `bits`-bit converter over `span` m centred on 0.

    Returns (step m, lowest code m, highest code m): 2**bits codes, step = span / 2**bits, codes
    -span/2 .. span/2 - step (the grid holds 0, like the plant's own quantisation).
    """
    if isinstance(bits, bool) or not isinstance(bits, (int, np.integer)) or not 1 <= bits <= 32:
        raise ConfigError(f'sensor bits must be an integer in 1..32, got {bits!r}')
    if (isinstance(span, bool) or not isinstance(span, (int, float)) or not math.isfinite(span)
            or span <= 0):
        raise ConfigError(f'sensor span must be a positive number of metres, got {span!r}')
    step = float(span) / 2.0 ** int(bits)
    return step, -0.5 * float(span), 0.5 * float(span) - step


class PiezoCantilever:
    """
    The plant, with a per-sample interface (step) and an array interface (run) on one state.

    params: PlantParams (None: config/plant.yaml); fs: sample rate, Hz; seed: seed of the sensor
    noise. run(u) advances the state exactly as len(u) calls of step() would (same numbers to the
    last bit).
    A rig's sensor (docs/real.md): sensor_offset (m) is added to every measured sample (a sensor
    zero that differs per session); sensor_bits and sensor_span (m) replace params.quantisation
    by a sensor_bits converter over sensor_span centred on 0, whose codes also clip the output
    (adc_grid). All off by default: the numbers are then those of the plant without them.
    """

    def __init__(self, params: PlantParams | None = None, fs: float = 2000.0, seed: int = 0,
                 sensor_offset: float = 0.0, sensor_bits: int | None = None,
                 sensor_span: float | None = None):
        if params is None:
            params = load_plant_params()
        if not isinstance(params, PlantParams):
            raise ConfigError(f'params must be a PlantParams, got {type(params).__name__}')
        if (isinstance(fs, bool) or not isinstance(fs, (int, float)) or not math.isfinite(fs)
                or fs <= 0):
            raise ConfigError(f'plant sample rate fs must be a positive number of Hz, got {fs!r}')
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
            raise ConfigError(f'plant seed must be a non-negative integer, got {seed!r}')
        if (params.hysteresis == 'preisach') != (params.creep_input == 'voltage'):
            raise ConfigError(f'creep_input: {params.creep_input} is not implemented for the '
                              f'{params.hysteresis} plant (bouc_wen takes hysteresis, preisach '
                              f'takes voltage)')
        if (isinstance(sensor_offset, bool) or not isinstance(sensor_offset, (int, float))
                or not math.isfinite(sensor_offset)):
            raise ConfigError(f'sensor offset must be a finite number of metres, got '
                              f'{sensor_offset!r}')
        if (sensor_bits is None) != (sensor_span is None):
            raise ConfigError('sensor bits and sensor span go together: give both or neither')
        self.params = params
        self.fs = float(fs)
        self.seed = int(seed)
        self.sensor_offset = float(sensor_offset)
        h = 1.0 / (self.fs * params.substeps)
        a, b = linear_system(params)
        self._phi, self._g0, self._g1 = foh_discretise(a, b, h)
        consts = np.zeros(kernels.N_CONSTS)
        consts[kernels.C_VMIN] = params.v_min
        consts[kernels.C_VMAX] = params.v_max
        consts[kernels.C_SLEW] = params.slew_rate
        consts[kernels.C_AMP_W] = 2.0 * math.pi * params.amp_bandwidth
        consts[kernels.C_H] = h
        consts[kernels.C_DP] = params.d_p
        consts[kernels.C_A] = params.A
        consts[kernels.C_B] = params.B
        consts[kernels.C_GAMMA] = params.gamma
        consts[kernels.C_NOISE] = params.noise_std
        consts[kernels.C_QUANT] = params.quantisation
        consts[kernels.C_OFFSET] = self.sensor_offset
        consts[kernels.C_YMIN], consts[kernels.C_YMAX] = -math.inf, math.inf
        if sensor_bits is not None:
            consts[kernels.C_QUANT], consts[kernels.C_YMIN], consts[kernels.C_YMAX] = adc_grid(
                sensor_bits, sensor_span)
        self._consts = consts
        self._preisach = None
        if params.hysteresis == 'preisach':
            self._setup_preisach(params, h, consts)
        n_hyst = (kernels.S_LIN if self._preisach is None
                  else 1 + len(params.creep_gains) + params.preisach_radii)
        self._state = np.zeros(n_hyst + self._phi.shape[0])
        self._work = np.zeros(self._phi.shape[0])
        # One-sample buffers reused by step() so that it allocates no arrays per call.
        self._u1 = np.zeros(1)
        self._n1 = np.zeros(1)
        self._y1 = np.zeros(1)
        self._yt1 = np.zeros(1)
        self._ua1 = np.zeros(1)
        self._y_true = np.zeros(0)   # run_into's scratch
        self.reset()

    def _setup_preisach(self, p: PlantParams, h: float, consts: np.ndarray) -> None:
        """Set the relay radii (V), weights (m) and centres (V) of the Preisach variant."""
        n = p.preisach_radii
        radii = (np.arange(n) + 0.5) * (p.preisach_r_max / n)
        weights = np.exp(-radii / p.preisach_r0)
        weights *= p.preisach_gain / weights.sum()
        centres = p.preisach_centre + p.preisach_centre_slope * radii
        consts[kernels.C_DP] = p.preisach_d_rev
        consts[kernels.C_B] = p.preisach_spread
        consts[kernels.C_A] = kernels.preisach_output(np.zeros(n), weights, centres,
                                                      p.preisach_spread)
        gains = np.asarray(p.creep_gains, dtype=float)
        decay = np.exp(-h / np.asarray(p.creep_time_constants, dtype=float))
        self._preisach = (radii, weights, centres, gains, decay)

    def _advance(self, u, noise, y, y_true, u_app) -> None:
        args = (u, noise, self.params.substeps, self._consts, self._phi, self._g0, self._g1,
                self._state, self._work, y, y_true, u_app)
        if self._preisach is None:
            kernels.advance(*args)
        else:
            kernels.advance_preisach(*args, *self._preisach)

    def reset(self) -> None:
        """Back to rest (all states zero, amplifier at 0 V) and the noise generator re-seeded."""
        self._state[:] = 0.0
        # Its own stream: seeding PCG64 with the bare seed would replay the bits that generate()
        # turns into multisine phases for the same seed, correlating noise with the input.
        self._rng = np.random.Generator(np.random.PCG64([self.seed, _NOISE_STREAM]))
        self._noise = np.empty(0)
        self._noise_pos = 0

    @property
    def state(self) -> np.ndarray:
        """
        Copy of the state.

        Bouc-Wen: [v (V), h (m), creep states (m)..., y (m), dy/dt (m/s), sensor (m)]; Preisach: [v
        (V), voltage creep lags (V)..., plays (V)..., y, dy/dt, sensor].
        """
        return self._state.copy()

    @property
    def u_applied(self) -> float:
        """Amplifier output now, V."""
        return float(self._state[kernels.S_V])

    @staticmethod
    def _check_commands(u_cmd, what: str) -> np.ndarray:
        """(N,) float64 contiguous volts; DataError naming the first bad index otherwise."""
        try:
            u = np.ascontiguousarray(u_cmd, dtype=float)
        except (TypeError, ValueError):
            raise DataError(f'{what} array must hold numbers (volts)') from None
        if u.ndim != 1:
            raise DataError(f'{what} array must be 1-D, got shape {u.shape}')
        bad = np.flatnonzero(~np.isfinite(u))
        if bad.size:
            raise DataError(f'{what} has a non-finite value at index {bad[0]}: {u[bad[0]]}')
        return u

    def _draw(self, n: int) -> np.ndarray:
        """
        Next n standard normals of the noise stream (buffered block first).

        A short draw (a node's batch) refills the block, a long one takes what it needs: the
        stream is drawn in order either way, so the numbers do not depend on how it is cut.
        """
        left = self._noise[self._noise_pos:]
        if n <= left.size:
            self._noise_pos += n
            return left[:n]
        if n - left.size > _NOISE_BLOCK:
            fresh = self._rng.standard_normal(n - left.size)
            self._noise = np.empty(0)
            self._noise_pos = 0
            return np.concatenate([left, fresh])
        self._noise = np.concatenate([left, self._rng.standard_normal(_NOISE_BLOCK)])
        self._noise_pos = n
        return self._noise[:n]

    def run_into(self, u: np.ndarray, y: np.ndarray, u_applied: np.ndarray) -> None:
        """
        run() for commands already checked: u (N,) C-contiguous float64 V, all finite.

        Writes the measured y (N,) m and u_applied (N,) V in place (C-contiguous, float64); the
        tip deflection is not kept. The same numbers and state as run(u), without its checks and
        allocations: the batch path of a node that has checked its commands.
        """
        n = u.shape[0]
        if self._y_true.shape[0] < n:
            self._y_true = np.empty(n)
        self._advance(u, self._draw(n), y, self._y_true[:n], u_applied)

    def step(self, u_cmd: float) -> tuple[float, float, float]:
        """
        Apply command u_cmd (V) for one sample period; returns (y_meas m, y_true m, u_applied V).

        A non-finite command raises DataError and leaves the state untouched.
        """
        try:
            u = float(u_cmd)
        except (TypeError, ValueError):
            raise DataError(f'plant command must be a finite voltage, got {u_cmd!r}') from None
        if not math.isfinite(u):
            raise DataError(f'plant command must be a finite voltage, got {u_cmd!r}')
        if self._noise_pos >= self._noise.size:
            self._noise = self._rng.standard_normal(_NOISE_BLOCK)
            self._noise_pos = 0
        noise = self._noise[self._noise_pos]
        self._noise_pos += 1
        if self._preisach is None:      # one compiled call, no arrays to fill and read back
            y_true, y_meas, u_app = kernels.advance_one(
                u, noise, self.params.substeps, self._consts, self._phi, self._g0, self._g1,
                self._state, self._work)
            return y_meas, y_true, u_app
        self._u1[0] = u
        self._n1[0] = noise
        self._advance(self._u1, self._n1, self._y1, self._yt1, self._ua1)
        return float(self._y1[0]), float(self._yt1[0]), float(self._ua1[0])

    @property
    def sensor_quantisation(self) -> float:
        """Quantisation step of the measured output, m (0: none)."""
        return float(self._consts[kernels.C_QUANT])

    @property
    def sensor_full_scale(self) -> tuple[float, float]:
        """Lowest and highest measured value, m (-inf, inf without sensor_bits)."""
        return float(self._consts[kernels.C_YMIN]), float(self._consts[kernels.C_YMAX])

    def prime(self, u_history) -> None:
        """
        Drive the plant through u_history (N,) V before a record starts, recording nothing.

        The history leaves the hysteresis memory, creep and mode where that past input put them,
        as on a rig switched on long before the record. It draws no sensor noise: the record's
        noise is the same with or without a history (the two have separate seeds).
        """
        u = self._check_commands(u_history, 'plant history')
        n = u.size
        self._advance(u, np.zeros(n), np.empty(n), np.empty(n), np.empty(n))

    def run(self, u_cmd, history=None) -> PlantRun:
        """
        Apply a whole command array u_cmd (N,) V from the current state; returns a PlantRun.

        history: (M,) V applied first through prime() (None: start from the current state).
        Non-finite or non-1-D input raises DataError (naming the first bad index) before any
        change.
        """
        u = self._check_commands(u_cmd, 'plant command')
        if history is not None:
            self.prime(history)
        n = u.size
        noise = self._draw(n)
        y = np.empty(n)
        y_true = np.empty(n)
        u_app = np.empty(n)
        self._advance(u, noise, y, y_true, u_app)
        return PlantRun(u_applied=u_app, y=y, y_true=y_true)
