"""
The identified model inverted one sample at a time, ROS-free.

`ModelInverse` keeps the model's own free run (its Stepper, fed with the inputs actually sent) as
the state, and at each sample finds the input u(k) (V) within the voltage limits and the slew
window around u(k-1) whose model output equals the target (m). Two targets (docs/control.md has
the measurements behind the default):

- 'output': the model's next output y(k) itself (the exact one-step inverse);
- 'quasi_static' (HysteresisNARX only): the output the model would settle to if the input held
  at u(k): its rate-independent operators moved to u(k), input increments 0, creep advanced, times
  the output dynamics' DC gain G. The hysteresis and the creep are inverted; the fast dynamics
  (drive, mode) pass with unit DC gain instead of being cancelled.

`static_gain(model)` gives the `linear` mode its scale: what a user without this package does.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from piezo_narx_ros.command.stamps import model_rate
from piezo_narx_ros.control import kernels as ck
from piezo_narx_ros.errors import ConfigError
from piezo_narx_ros.ident.hysteresis import kernels as hk
from piezo_narx_ros.ident.narx.kernels import arx_step, narx_step

TARGETS = ('output', 'quasi_static')

# Why an input did not reach its target (Solution.limit).
REACHED, VOLTAGE, SLEW, NOT_INVERTIBLE = 'reached', 'voltage', 'slew', 'not_invertible'


@dataclass(slots=True)
class Solution:
    """
    One sample's answer.

    u (V), the model's achieved value for it (m, in the target's sense), the signed miss achieved -
    target (m), why it missed (`limit`: REACHED, VOLTAGE, SLEW or NOT_INVERTIBLE) and the model
    evaluations it took.
    """

    u: float
    achieved: float
    miss: float
    limit: str
    evaluations: int


class ModelInverse:
    """
    Sample-by-sample inverse of `model` (ARXModel, NARXNetwork or HysteresisNARX).

    u_min, u_max: voltage limits, V; slew_rate: largest change of u, V/s (inf: none), applied
    over the stamp interval of each command (`window(dt)`); fs: sample rate, Hz (the model's when
    None; a given one must equal the model's); target: 'output' or 'quasi_static' (module
    docstring); tol: output tolerance of the solve, m; reach_tol: a miss larger than this is
    reported as unreachable, m; max_iter: regula falsi iterations; n_grid: grid points of the
    bracket search (bounded time: at most 1 + kernels.LOCAL_TRIES + n_grid + max_iter model
    evaluations per sample).
    """

    def __init__(self, model, u_min: float = -200.0, u_max: float = 200.0,
                 slew_rate: float = math.inf, fs: float | None = None, target: str = 'output',
                 tol: float = 1e-11, reach_tol: float = 1e-9, max_iter: int = 30,
                 n_grid: int = 6):
        if target not in TARGETS:
            raise ConfigError(f'target must be one of {list(TARGETS)}, got {target!r}')
        kind = getattr(model, 'kind', None)
        if kind not in ('arx', 'narx', 'hysteresis_narx'):
            raise ConfigError(f'cannot invert a model of kind {kind!r} (arx, narx or '
                              'hysteresis_narx)')
        if target == 'quasi_static' and kind != 'hysteresis_narx':
            raise ConfigError("target 'quasi_static' needs a hysteresis_narx model (its input "
                              'chain is separate from its output dynamics); this one is '
                              f'{kind}')
        if not u_min < u_max:
            raise ConfigError(f'u_min ({u_min:g} V) must be below u_max ({u_max:g} V)')
        if not slew_rate > 0:
            raise ConfigError(f'slew_rate must be > 0 V/s, got {slew_rate:g}')
        fs = model_rate(model, fs)
        if not (tol > 0 and reach_tol >= tol and max_iter >= 1 and 2 <= n_grid <= ck.MAX_GRID):
            raise ConfigError(f'need tol > 0, reach_tol >= tol, max_iter >= 1 and n_grid in '
                              f'[2, {ck.MAX_GRID}]')
        self.model = model
        self.kind = kind
        self.target = target
        self.fs = float(fs)
        self.u_min, self.u_max = float(u_min), float(u_max)
        self.slew_rate = float(slew_rate)
        self.max_step = slew_rate / self.fs if math.isfinite(slew_rate) else math.inf
        self.tol, self.reach_tol = float(tol), float(reach_tol)
        self.max_iter, self.n_grid = int(max_iter), int(n_grid)
        self._sv, self._cand, self._g = ck.work_arrays()
        self.stepper = model.stepper()
        self.reset()

    # ------------------------------------------------------------------------------- state
    def reset(self, u_past=None, y_past=None) -> None:
        """
        Back to the model's rest (or the given histories, as Stepper.reset).

        u(k-1) = 0 V or the last of u_past.
        """
        self.stepper.reset(u_past, y_past)
        self._sv[:] = 0.0          # also the remembered slope: a reset run repeats a fresh one
        self.u_prev = float(u_past[-1]) if u_past is not None and len(u_past) else 0.0
        self.y_model = 0.0
        self.offset = 0.0          # sensor offset of a measured start, m (start_from)
        self._bind()

    def start_from(self, state, u_run, relag=None) -> None:
        """
        Continue from a measured start: `state` at the first of u_run, then u_run stepped.

        state: a ModelState (ident.state.start.window_state); u_run: the commands sent from that
        sample to the last one, V; relag: (u, y), measured commands and outputs from that sample
        on, whose last samples become the lags once they are stepped (start policy 'state' on a
        lagged family: ident.state.start.relag_window). The state's offset shifts every output
        from now on.
        """
        from piezo_narx_ros.ident.state.start import replay_start
        stepper, y = replay_start(self.model, state, u_run, relag)
        self.offset = float(stepper.offset)
        stepper.offset = 0.0       # the kernels run without it; solve and commit add it
        self.stepper = stepper
        self._sv[:] = 0.0
        self.u_prev = float(u_run[-1]) if len(u_run) else 0.0
        self.y_model = float(y) if y is not None else 0.0
        self._bind()

    def _bind(self) -> None:
        """Argument tuple of the family's solve kernel (the stepper's live arrays)."""
        arrays, params = self.stepper.kernel_state
        work = (self._sv, self._cand, self._g)
        # commit() advances the stepper's arrays with the compiled step itself: the stepper's
        # Python step() also keeps u_past/y_past copies, which cost more than the step here.
        if self.kind == 'hysteresis_narx':
            u_scale, y_scale, step, full = (float(self.model.u_scale_),
                                            float(self.model.y_scale_), hk.step, params)
            self._advance = lambda u: step(u / u_scale, arrays[0], *full) * y_scale
        else:
            step = narx_step if self.kind == 'narx' else arx_step
            self._advance = lambda u: step(u, arrays[0], arrays[1], *params)
        if self.kind == 'hysteresis_narx':
            radii, n_lags, dh, rho, kap, W1, b1, w2, c, w_rest, g, lam, a, b, y_off = params
            static = self.target == 'quasi_static'
            if static:
                b = np.array([np.sum(b) / (1.0 + np.sum(a))])    # [G], the DC gain
            st = arrays[0]
            self._solve = ck.solve_hysteresis
            self._args = work + (static, st, np.zeros(st.size), np.zeros(st.size),
                                 float(self.model.u_scale_), float(self.model.y_scale_), radii,
                                 n_lags, dh, rho, kap, W1, b1, w2, c, w_rest, g, lam, a, b,
                                 y_off)
        else:
            ubuf, ybuf = arrays
            self._solve = ck.solve_narx if self.kind == 'narx' else ck.solve_arx
            self._args = work + (ubuf, ybuf, np.zeros(ubuf.size)) + tuple(params)

    # ------------------------------------------------------------------------------ solving
    def window(self, dt: float | None = None) -> tuple[float, float]:
        """
        Return the inputs allowed now: voltage limits intersected with the slew window, V.

        dt: seconds of stamp time since the previous command (None: one period); the slew rate
        is per second of it, and never allows more than one period's worth in one command (after
        a gap the amplifier held, so the next step is still one step).
        """
        step = self.max_step
        if dt is not None and dt * self.fs < 1.0 and math.isfinite(step):
            step = self.slew_rate * max(dt, 0.0)
        return (max(self.u_min, self.u_prev - step), min(self.u_max, self.u_prev + step))

    def solve(self, target: float, dt: float | None = None) -> Solution:
        """
        Return the input (V) whose model value is closest to `target` (m) in the allowed window.

        dt: stamp time since the previous command, s (`window`). The model state is not changed
        (call `commit`).
        """
        lo, hi = self.window(dt)
        u, miss, nev = self._solve(float(target) - self.offset, lo, hi, self.u_prev, 1e-9,
                                   self.tol, self.max_iter, self.n_grid, *self._args)
        limit = REACHED
        if not abs(miss) <= self.reach_tol:
            limit = NOT_INVERTIBLE
            if u == lo or u == hi:
                at_voltage = (u == self.u_min) if u == lo else (u == self.u_max)
                limit = VOLTAGE if at_voltage else SLEW
        return Solution(u, float(target) + miss, miss, limit, nev)

    def value(self, u: float) -> float:
        """Return the model's value for input u (V) in the target's sense (m), state untouched."""
        if self.kind == 'hysteresis_narx':
            (static, st, s1, s2, u_scale, y_scale, radii, n_lags, dh, rho, kap, W1, b1, w2, c,
             w_rest, g, lam, a, b, y_off) = self._args[3:]
            un = float(u) / u_scale
            if static:
                return y_scale * hk.peek_static(un, st, s1, s2, radii, n_lags, dh, rho, kap, W1,
                                                b1, w2, c, w_rest, g, lam, b, y_off) + self.offset
        return self.stepper.peek(u) + self.offset

    def estimate_advance(self, freq: float = 5.0, seconds: float = 1.0) -> float:
        """
        How far the model's output leads its quasi-static value, samples.

        Tau in y(k) ~ y_qs(k) + tau (y_qs(k) - y_qs(k-1)), least squares over a `freq` Hz sine of
        half the trained input range (second half of `seconds`). The fast dynamics the quasi-static
        target lets pass shift the output by about this much; the controller compensates it. 0 for
        the 'output' target. The inverse is reset afterwards.
        """
        if self.target == 'output':
            return 0.0
        lo, hi = getattr(self.model, 'input_range', None) or (self.u_min, self.u_max)
        n = int(round(seconds * self.fs))
        u = 0.5 * (lo + hi) + 0.25 * (hi - lo) * np.sin(2 * np.pi * freq * np.arange(n) / self.fs)
        y_qs, y = np.empty(n), np.empty(n)
        self.reset()
        for k in range(n):
            y_qs[k] = self.value(u[k])
            y[k] = self.commit(u[k])
        self.reset()
        d = np.diff(y_qs[n // 2 - 1:])
        lead = (y - y_qs)[n // 2:]
        tau = float(d @ lead / (d @ d)) if d @ d > 0 else 0.0
        return tau if math.isfinite(tau) else 0.0

    def clamp(self, u: float, dt: float | None = None) -> float:
        """Limit u (V) to the allowed window (for modes that do not solve); dt as `window`."""
        lo, hi = self.window(dt)
        return min(max(u, lo), hi)

    def commit(self, u: float) -> float:
        """
        Send u (V, finite): the model advances one sample.

        Returns its free-run output y(k) (m), as the model's Stepper.step would (its state arrays
        are the ones advanced; its u_past / y_past copies are not kept up to date).
        """
        self.y_model = self._advance(float(u)) + self.offset
        self.u_prev = float(u)
        return self.y_model


def static_gain(model, fs: float | None = None, freq: float = 0.5, periods: int = 2):
    """
    Fit a straight line y = gain*u + offset to the model's free run: (gain m/V, offset m).

    On a slow full-range sine (`freq` Hz over its trained input range, last period used): the scale
    a user applies without an inverse. ARX: its exact DC gain and offset.
    """
    if getattr(model, 'kind', None) == 'arx':
        den = 1.0 + float(np.sum(model.a))
        return float(np.sum(model.b)) / den, float(model.c) / den
    fs = fs or model.fs
    lo, hi = model.input_range
    mid, amp = 0.5 * (lo + hi), 0.5 * (hi - lo)
    n = int(round(fs / freq))
    t = np.arange(periods * n) / fs
    u = mid + amp * np.sin(2 * np.pi * freq * t)
    y = model.simulate(u)[-n:]
    gain, offset = np.polyfit(u[-n:], y, 1)
    if not (np.isfinite(gain) and np.isfinite(offset)) or gain == 0.0:
        raise ConfigError(f'the model has no usable static gain (fitted {gain:g} m/V)')
    return float(gain), float(offset)
