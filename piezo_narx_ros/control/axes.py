"""
Position control of several axes through a model of several inputs and outputs, ROS-free.

`VectorInverse` inverts the model one sample at a time: it keeps the model's free run (its
Stepper, fed with the commands actually sent) and finds the command vector u(k) (V, within the
voltage limits and the slew window of each axis) whose next model output equals the reference
vector (m), by Newton steps on the model's one-step map u(k) -> y(k) with a finite-difference
Jacobian, projected on the limits. The Jacobian's off-diagonal terms are the coupling: driving
axis j to move axis i is compensated, not ignored. A linear model (ARX) is inverted exactly in
one step.

`AxesController` is the controller of several axes: references in, commands out, with the same
stamp handling as PositionController (StampGate, RateMonitor, gaps held), per-axis reference
ranges and limits, and two modes: 'inverse' (sensorless) and 'linear', the per-axis baseline
(each axis's own static line u_i = (r_i - offset_i) / gain_i, coupling ignored: what a user does
axis by axis without a model of the stage).

A model of one actuator chain per axis (ident/hysteresis/chains.py, y = M z) is inverted in two
exact steps instead: the coupling by z* = M^-1 r (what each chain must do so that every axis is
where asked), then each chain by its own one-axis PositionController (`ChainAxes`): the
quasi-static inverse of its hysteresis and creep (docs/control.md), its limits, its static-gain
check, and its /diagnostics checks (control.health: anti-phase, tracking error with a sensor,
unreachable targets), so every reliability check of one axis holds on each axis. With a
deflection sensor the measured outputs are decoupled the same way (z = M^-1 y), which also gives
each chain the PI of 'inverse_feedback'.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from piezo_narx_ros.command.stamps import (RATE_TOLERANCE, SAMPLE, RateMonitor, StampGate,
                                           model_rate)
from piezo_narx_ros.control.controller import PositionController, bridge_gap
from piezo_narx_ros.control.health import (ANTI_PHASE, MIN_JUDGED, ControllerHealth,
                                           nonfinite_line)
from piezo_narx_ros.control.start import (NO_MEASUREMENT, MeasuredStart, measured_start,
                                          start_settings)
from piezo_narx_ros.counters import ERROR, OK
from piezo_narx_ros.errors import ConfigError, DataError

AXES_MODES = ('inverse', 'linear')
#: Modes of a model of one chain per axis (ChainAxes): the one-axis controller's, per chain.
CHAIN_MODES = ('inverse', 'inverse_feedback')


def _per_axis(value, n: int, name: str) -> np.ndarray:
    """Return a float or n floats as (n,) float64; ConfigError otherwise."""
    a = np.broadcast_to(np.asarray(value, dtype=np.float64), (n,)).copy() \
        if np.ndim(value) == 0 or np.size(value) == n else None
    if a is None or not np.isfinite(a).all():
        raise ConfigError(f'{name} must be a number or {n} finite numbers, got {value!r}')
    return a


def static_gains(model, fs: float | None = None, freq: float = 0.5, periods: int = 2):
    """
    Fit each output's line on each input alone: (gain (n_out, n_in) m/V, offset (n_out,) m).

    Input j swept by a slow full-range sine (`freq` Hz over its trained range), the others held
    at the middle of theirs; the last period's least-squares line per output. The diagonal is
    the per-axis baseline's scale; the off-diagonal terms are the static coupling.
    """
    from piezo_narx_ros.ident.base import channel_ranges
    fs = fs or model.fs
    u_rng, _ = channel_ranges(model)
    if u_rng is None:
        raise ConfigError('the model has no trained input range')
    mid, amp = u_rng.mean(axis=1), 0.5 * (u_rng[:, 1] - u_rng[:, 0])
    n = int(round(fs / freq))
    s = np.sin(2 * np.pi * freq * np.arange(periods * n) / fs)
    gains = np.empty((model.n_out, model.n_in))
    offsets = np.zeros(model.n_out)
    for j in range(model.n_in):
        u = np.tile(mid, (s.size, 1))
        u[:, j] += amp[j] * s
        y = np.asarray(model.simulate(u)).reshape(s.size, model.n_out)[-n:]
        for i in range(model.n_out):
            gains[i, j], off = np.polyfit(u[-n:, j], y[:, i], 1)
            if i == j:     # output i's own line (the other inputs at the middle of theirs)
                offsets[i] = off
    if not np.isfinite(gains).all():
        raise ConfigError('the model has no usable static gains')
    return gains, offsets


@dataclass(slots=True)
class VectorSolution:
    """One sample's answer: u (n_in,) V, achieved (n_out,) m, miss achieved - target, limit."""

    u: np.ndarray
    achieved: np.ndarray
    miss: np.ndarray
    limit: str          # 'reached', 'voltage', 'slew' or 'not_invertible'


class VectorInverse:
    """
    Sample-by-sample inverse of a model of n_in inputs and n_out outputs (module docstring).

    u_min, u_max: V, one for every axis or one per input; slew_rate: V/s (inf: none); tol: the
    Newton iterations stop when every output is within tol m; reach_tol: a larger miss is
    reported as unreachable; max_iter: Newton steps per sample; du: finite-difference step, V.
    """

    def __init__(self, model, u_min=-200.0, u_max=200.0, slew_rate: float = math.inf,
                 fs: float | None = None, tol: float = 1e-12, reach_tol: float = 1e-9,
                 max_iter: int = 8, du: float = 1e-3):
        self.model = model
        self.fs = model_rate(model, fs)
        self.n_in, self.n_out = int(model.n_in), int(model.n_out)
        self.u_min = _per_axis(u_min, self.n_in, 'u_min')
        self.u_max = _per_axis(u_max, self.n_in, 'u_max')
        if not (self.u_min < self.u_max).all():
            raise ConfigError('u_min must be below u_max on every axis')
        if not slew_rate > 0:
            raise ConfigError(f'slew_rate must be > 0 V/s, got {slew_rate!r}')
        self.slew_rate = float(slew_rate)
        self.tol, self.reach_tol = float(tol), float(reach_tol)
        self.max_iter, self.du = int(max_iter), float(du)
        self.reset()

    def reset(self) -> None:
        """Restart at rest: the model's free run from rest, every input at 0 V."""
        self._stepper = self.model.stepper()
        self.u_prev = np.clip(np.zeros(self.n_in), self.u_min, self.u_max)
        self.y_model = np.zeros(self.n_out)   # the model's output for the last command, m

    def start_from(self, state, u_run, relag=None) -> None:
        """
        Continue from a measured start: `state` at the first row of u_run, then u_run stepped.

        state: a ModelState (ident.state.start.window_state); u_run (n, n_in) V: the commands
        sent from that sample to the last one; relag: (u, y) rows whose last samples become the
        lags once they are stepped (control.start.Start). The state's offsets stay in the
        model's outputs from now on.
        """
        from piezo_narx_ros.ident.state.start import replay_start
        self._stepper, y = replay_start(self.model, state, u_run, relag)
        if y is not None:
            self.u_prev = np.asarray(u_run[-1], dtype=np.float64).reshape(self.n_in).copy()
            self.y_model = np.array(y, dtype=np.float64).reshape(self.n_out)

    def _peek(self, u: np.ndarray) -> np.ndarray:
        return np.array(self._stepper.peek(u), dtype=np.float64).reshape(self.n_out)

    def window(self, dt: float | None) -> tuple[np.ndarray, np.ndarray]:
        """Reachable inputs (lo, hi) per axis, V: the limits and the slew over dt s."""
        if dt is None or math.isinf(self.slew_rate):
            return self.u_min, self.u_max
        step = self.slew_rate * max(dt, 0.0)
        return (np.maximum(self.u_min, self.u_prev - step),
                np.minimum(self.u_max, self.u_prev + step))

    def solve(self, target, dt: float | None = None) -> VectorSolution:
        """Find u within the window whose next model output is `target` (n_out,) m."""
        r = np.asarray(target, dtype=np.float64).reshape(self.n_out)
        lo, hi = self.window(dt)
        u = np.clip(self.u_prev, lo, hi)
        y = self._peek(u)
        clipped = False
        jac = None
        for _ in range(self.max_iter):
            if np.max(np.abs(y - r)) <= self.tol:
                break
            if jac is None:   # once per sample (chord method): exact for a linear model
                jac = np.column_stack([(self._peek(u + e) - y) / self.du
                                       for e in np.eye(self.n_in) * self.du])
                square = jac.shape[0] == jac.shape[1]
            if not (np.isfinite(jac).all() and np.isfinite(y).all()):
                break           # a model giving NaN/inf: no step to take, u stays finite
            try:
                step = np.linalg.solve(jac, r - y) if square else \
                    np.linalg.lstsq(jac, r - y, rcond=None)[0]
            except np.linalg.LinAlgError:       # singular: no input moves some output
                step = np.linalg.lstsq(jac, r - y, rcond=None)[0]
            u_new = np.clip(u + step, lo, hi)
            clipped = bool((u_new != u + step).any())
            if np.array_equal(u_new, u):
                break
            u = u_new
            y = self._peek(u)
        miss = y - r
        limit = 'reached'
        if not (np.abs(miss) <= self.reach_tol).all():      # NaN: not reached
            at_volts = (u <= self.u_min) | (u >= self.u_max)
            limit = ('voltage' if at_volts.any() else 'slew') if clipped else 'not_invertible'
        return VectorSolution(u, y, miss, limit)

    def clamp(self, u, dt: float | None = None) -> np.ndarray:
        """Return u (n_in,) V limited to the window of this sample."""
        lo, hi = self.window(dt)
        return np.clip(np.asarray(u, dtype=np.float64), lo, hi)

    def commit(self, u) -> np.ndarray:
        """Send u (n_in,) V: the model's free run advances with it; returns the model output."""
        u = np.asarray(u, dtype=np.float64).reshape(self.n_in)
        self.u_prev = u.copy()
        self.y_model = np.array(self._stepper.step(u), dtype=np.float64).reshape(self.n_out)
        return self.y_model


@dataclass
class AxesStats:
    """Counters of an AxesController (samples)."""

    references: int = 0
    commands: int = 0
    rejected_nonfinite: int = 0     # references with a NaN/inf axis: the previous one held
    out_of_range: int = 0           # references clamped to [y_min, y_max] on some axis
    unreachable: int = 0
    voltage_limited: int = 0
    slew_limited: int = 0
    not_invertible: int = 0
    gaps: int = 0
    filled: int = 0
    stamp_outliers: int = 0
    stream_restarts: int = 0
    rate_refused: int = 0
    measurements_rejected: int = 0  # deflections without every axis (chains: the rest pass on)
    model_nonfinite: int = 0        # commands after which the model's output was NaN/inf
    refused_messages: int = 0       # reference messages the node could not read (axis missing)
    measurements: int = 0           # deflection vectors the vector inverse took
    last_refusal: str = ''          # and why the last one was refused
    start: str = 'rest'             # rest, waiting, measurement or 'rest (no measurement)'


#: AxesStats fields that are words, not counters.
_WORDS = ('last_refusal', 'start')


class AxesController:
    """
    References of several axes in, command vectors out (module docstring).

    mode: 'inverse' or 'linear'; u_min/u_max: V (one, or one per input); slew_rate: V/s;
    y_min/y_max: accepted references per output, m (None: the model's trained output ranges
    widened by range_margin of their span); max_fill, confirm: see StampGate.
    start_policy, start_window: as PositionController's (None: the model file's start): while
    the window fills the model runs from rest, then it continues from the state the measured
    deflection vectors give (stats.start); a model of one chain per axis gives each chain the
    same policy and window over its decoupled motion.
    """

    def __init__(self, model, mode: str = 'inverse', fs: float | None = None, u_min=-200.0,
                 u_max=200.0, slew_rate: float = math.inf, y_min=None, y_max=None,
                 range_margin: float = 0.05, max_fill: int = 2000, confirm: int = 3,
                 rate_tolerance: float = RATE_TOLERANCE, start_policy: str | None = None,
                 start_window: int | None = None, **chain_options):
        chains = getattr(model, 'chains_', None) is not None and mode in CHAIN_MODES
        if mode not in AXES_MODES and not chains:
            extra = (f'; {list(CHAIN_MODES)} with a model of one chain per axis'
                     if mode not in CHAIN_MODES else ' (inverse_feedback needs a model of one '
                     'chain per axis: fit --preset envelope)')
            raise ConfigError(f'mode must be one of {list(AXES_MODES)} for several axes, got '
                              f'{mode!r}{extra}')
        if chain_options and not chains:
            raise ConfigError(f'{", ".join(sorted(chain_options))}: only for a model of one '
                              'chain per axis')
        self.mode = mode
        self.start_policy, self.start_window = start_settings(model, start_policy, start_window)
        self.inverse = VectorInverse(model, u_min, u_max, slew_rate, fs)
        if chains:
            chain_options.update(start_policy=self.start_policy, start_window=self.start_window)
        self.chains = ChainAxes(model, mode, self.inverse, range_margin, max_fill, confirm,
                                rate_tolerance, **chain_options) if chains else None
        self.model = model
        self.fs = self.inverse.fs
        self.n_out = self.inverse.n_out
        self.period_ns = 1e9 / self.fs
        if mode == 'linear':
            if model.n_in != model.n_out:
                raise ConfigError('mode linear pairs input i with output i: needs as many '
                                  'inputs as outputs')
            gains, self.offset = static_gains(model, self.fs)
            self.gain = np.diag(gains).copy()
        from piezo_narx_ros.ident.base import channel_ranges
        _, y_rng = channel_ranges(model)
        if (y_min is None or y_max is None) and y_rng is None:
            raise ConfigError('the model has no trained output range: give y_min and y_max')
        pad = range_margin * (y_rng[:, 1] - y_rng[:, 0]) if y_rng is not None else 0.0
        self.y_min = _per_axis(y_rng[:, 0] - pad if y_min is None else y_min, self.n_out,
                               'y_min')
        self.y_max = _per_axis(y_rng[:, 1] + pad if y_max is None else y_max, self.n_out,
                               'y_max')
        self.stats = AxesStats()
        self.gate = StampGate(self.period_ns, int(max_fill), int(confirm))
        self.rate = RateMonitor(self.period_ns, rate_tolerance)
        self._last_t: int | None = None
        self._last_ref: np.ndarray | None = None
        self._last_values: dict = {}
        self.watch = AxisWatch(self.n_out, self.y_max - self.y_min,
                               None if self.chains else _gain_signs(model, self.fs))
        self._begin_start()

    def _begin_start(self) -> None:
        """Wait for the start window (the vector inverse; the chains wait each on their own)."""
        policy = 'rest' if self.chains else self.start_policy
        self._start = MeasuredStart(self.model, policy, self.start_window)
        self.stats.start = 'waiting' if self.start_policy != 'rest' else 'rest'

    @property
    def holding(self) -> int:
        """Count the references held back while their stamps are ambiguous."""
        return self.chains.holding if self.chains else self.gate.holding

    def request_reset(self) -> None:
        """Restart from rest (the actuator is at 0 V now) and forget the stream."""
        if self.chains:
            self.chains.request_reset()
        self.inverse.reset()
        self.gate.reset()
        self._last_t = None
        self._start.stop()
        self.stats.start = 'rest'

    def warm_up(self) -> None:
        """Load the compiled solvers now, not on the first reference, and go back to rest."""
        for inv in [c.inverse for c in self.chains.axes] if self.chains else [self.inverse]:
            inv.solve(0.0 if self.chains else np.zeros(self.n_out))
            inv.reset()

    def on_measurement(self, t_ns: int, y) -> None:
        """
        Take a measured deflection vector (stamp of its command, (n_out,) m).

        The chains' start and feedback, or the vector inverse's start window; a vector with a
        NaN/inf axis or of another length is counted in measurements_rejected.
        """
        if self.chains:
            self.chains.on_measurement(t_ns, y)
            self.stats.start = self.chains.start_word()
            return
        y = np.asarray(y, dtype=np.float64)
        if y.shape != (self.n_out,) or not np.isfinite(y).all():
            self.stats.measurements_rejected += 1
            return
        self.stats.measurements += 1
        if self._start.waiting:
            self.stats.start = measured_start(self._start, self.inverse, t_ns, y,
                                              self.stats.start)

    def status(self) -> tuple[int, str, dict]:
        """
        (level 0 OK / 1 WARN / 2 ERROR, message, counters) for /diagnostics.

        WARN when a target was unreachable, a reference refused or clamped, or a stamp refused
        since the previous call; ERROR while the reference stream is at another rate.
        """
        if self.chains:
            return self.chains.status()
        values = dict(vars(self.stats))
        values['u_last'] = [round(float(v), 6) for v in self.inverse.u_prev]
        grew = {k: v - self._last_values.get(k, 0) for k, v in vars(self.stats).items()
                if k not in _WORDS}
        self._last_values = dict(vars(self.stats))
        if self.rate.off:
            return 2, self.rate.describe('reference') + ': no commands sent', values
        errors = self.watch.problems()
        if grew['model_nonfinite']:
            errors.insert(0, nonfinite_line(grew['model_nonfinite'], grew['commands']))
        if errors:
            return ERROR, errors[0] + (f' (+{len(errors) - 1} more)' if len(errors) > 1
                                       else ''), values
        words = [f'{grew[k]} {what}' for k, what in (
            ('unreachable', 'reference(s) out of reach (limits or not invertible)'),
            ('rejected_nonfinite', 'non-finite reference(s) held'),
            ('out_of_range', 'reference(s) clamped to [y_min, y_max]'),
            ('stamp_outliers', 'reference stamp(s) refused'),
            ('refused_messages', f'reference message(s) refused (the last: '
                                 f'{self.stats.last_refusal})')) if grew[k]]
        if words:
            return 1, '; '.join(words) + ' since the last report', values
        return 0, f'ok ({self.mode}, {self.n_out} axes)', values

    def on_reference(self, t_ns: int, r) -> list[tuple[int, np.ndarray]]:
        """One reference (stamp ns, (n_out,) m) -> commands [(t_ns, u (n_in,) V), ...]."""
        r = np.array(r, dtype=np.float64)
        if r.shape != (self.n_out,):
            raise DataError(f'reference must have {self.n_out} axes, got shape {r.shape}')
        if self.chains:
            return self._from_chains(self.chains.on_reference(t_ns, self._checked(r)))
        self.stats.references += 1
        self.rate.received(t_ns)
        return self._apply(self.gate.push(t_ns, r))

    def flush(self) -> list[tuple[int, np.ndarray]]:
        """Decide on held references once they stopped (StampGate.flush)."""
        if self.chains:
            return self._from_chains(self.chains.flush())
        return self._apply(self.gate.flush())

    def _apply(self, events) -> list[tuple[int, np.ndarray]]:
        """Commands for the references the stamp gate let through; a new stream restarts."""
        out: list = []
        for kind, t, item in events:
            if kind == SAMPLE:
                if self.rate.observe(t):
                    self.stats.rate_refused += 1
                    self._last_t = t
                    continue
                self._accept(t, item, out)
            else:
                self._last_t = None
                self.rate.reset()
        self.stats.stamp_outliers = self.gate.outliers
        self.stats.stream_restarts = self.gate.restarts
        return out

    def _checked(self, r: np.ndarray) -> np.ndarray:
        """Count a reference; clamp it to [y_min, y_max] per axis (NaN kept: it is held)."""
        self.stats.references += 1
        if not np.isfinite(r).all():
            self.stats.rejected_nonfinite += 1
            return r
        if ((r < self.y_min) | (r > self.y_max)).any():
            self.stats.out_of_range += 1
            return np.clip(r, self.y_min, self.y_max)
        return r

    def _from_chains(self, out: list) -> list:
        """Commands of the chains: the model follows them; the counters follow the chains'."""
        for _, u in out:
            self.inverse.u_prev = u      # the chains' own models follow the commands
        self.chains.count(self.stats)
        return out

    def _accept(self, t_ns: int, r: np.ndarray, out: list) -> None:
        st, inv = self.stats, self.inverse
        if not np.isfinite(r).all():
            st.rejected_nonfinite += 1
            r = self._last_ref
        elif ((r < self.y_min) | (r > self.y_max)).any():
            st.out_of_range += 1
            r = np.clip(r, self.y_min, self.y_max)
        dt = bridge_gap(self, t_ns)
        if r is None:
            u = inv.u_prev
        else:
            self._last_ref = r
            u = self._command(r, dt)
            if not np.isfinite(u).all():     # never send what the solver could not decide
                u = inv.u_prev
        if not np.isfinite(inv.commit(u)).all():
            st.model_nonfinite += 1
        st.commands += 1
        if r is not None:
            self.watch.add(r, u)
        out.append((t_ns, u))
        if self._start.waiting and not self._start.sent(t_ns, u.copy()):
            st.start = NO_MEASUREMENT

    def _command(self, r: np.ndarray, dt: float | None) -> np.ndarray:
        inv = self.inverse
        if self.mode == 'linear':
            wanted = (r - self.offset) / self.gain
            u = inv.clamp(wanted, dt)
            if (u != wanted).any():
                self._count('voltage' if ((u <= inv.u_min) | (u >= inv.u_max)).any()
                            else 'slew')
            return u
        sol = inv.solve(r, dt)
        if sol.limit != 'reached' and np.isfinite(sol.miss).all():    # NaN: model_nonfinite
            self._count(sol.limit)
        return sol.u

    def _count(self, why: str) -> None:
        st = self.stats
        st.unreachable += 1
        name = {'voltage': 'voltage_limited', 'slew': 'slew_limited'}.get(why, 'not_invertible')
        setattr(st, name, getattr(st, name) + 1)


def _gain_signs(model, fs: float) -> np.ndarray | None:
    """Sign of each axis's own static gain (input i on output i), None when not square."""
    if model.n_in != model.n_out:
        return None
    try:
        gains, _ = static_gains(model, fs)
    except ConfigError:
        return None
    return np.sign(np.diag(gains))


class AxisWatch:
    """
    The anti-phase check of control.health, per axis, for the vector inverse and the baseline.

    Over the last `window` commands: on an axis whose reference moves (more than HOLD_SPAN of
    its span), commands whose correlation with that axis's reference has the other sign than
    the axis's own static gain (below ANTI_PHASE) drive it against the reference: an ERROR.
    """

    def __init__(self, n: int, span: np.ndarray, signs: np.ndarray | None, window: int = 2000):
        from collections import deque
        self.span, self.signs = np.asarray(span, dtype=np.float64), signs
        self._pairs = deque(maxlen=int(window))
        self.n = n

    def add(self, r: np.ndarray, u: np.ndarray) -> None:
        """Record one command u (n,) V sent for reference r (n,) m."""
        if self.signs is not None:
            self._pairs.append(np.r_[r, u])

    def correlations(self) -> np.ndarray:
        """Return corr(u_i, r_i) per axis over the window (NaN where nothing moves)."""
        from piezo_narx_ros.control.health import HOLD_SPAN
        out = np.full(self.n, math.nan)
        if len(self._pairs) < MIN_JUDGED:
            return out
        a = np.array(self._pairs)
        r, u = a[:, :self.n], a[:, self.n:]
        for i in range(self.n):
            if r[:, i].std() > HOLD_SPAN * self.span[i] and u[:, i].std() > 0:
                out[i] = float(np.corrcoef(r[:, i], u[:, i])[0, 1])
        return out

    def problems(self) -> list[str]:
        """Return one ERROR phrase per axis driven against its reference."""
        if self.signs is None:
            return []
        return [f'axis {i}: commands move against the reference (correlation {c:.3f}; the '
                f'axis gain is {"positive" if s > 0 else "negative"}): anti-phase'
                for i, (c, s) in enumerate(zip(self.correlations(), self.signs))
                if s and c == c and s * c < ANTI_PHASE]


class ChainAxes:
    """
    Control a model of one chain per axis (module docstring).

    One PositionController per chain, fed z* = M^-1 r; their commands, stamps and counters put
    together.

    model: a HysteresisChains; mode: CHAIN_MODES; inverse: the AxesController's VectorInverse
    (its limits per axis and slew rate); options: the one-axis controller's (target, advance,
    kp, ki, feedback_timeout, window).
    """

    def __init__(self, model, mode, inverse: VectorInverse, range_margin, max_fill, confirm,
                 rate_tolerance, **options):
        self.M = np.array(model.coupling_, dtype=np.float64)
        self.names = tuple(model.outputs)
        self.axes = [PositionController(
            chain, mode=mode, fs=inverse.fs, u_min=float(inverse.u_min[j]),
            u_max=float(inverse.u_max[j]), slew_rate=inverse.slew_rate,
            range_margin=range_margin, max_fill=max_fill, confirm=confirm,
            rate_tolerance=rate_tolerance, **options) for j, chain in enumerate(model.chains_)]
        self.health = [ControllerHealth(c) for c in self.axes]

    @property
    def holding(self) -> int:
        """Count the references held back for their stamps (every chain holds the same)."""
        return self.axes[0].holding

    def targets(self, r: np.ndarray) -> np.ndarray:
        """Return what each chain must do, z* = M^-1 r (n,) m."""
        return np.linalg.solve(self.M, r)

    def on_reference(self, t_ns: int, r: np.ndarray) -> list:
        """One reference vector (n,) m -> [(t_ns, command (n,) V)], usually one."""
        z = self.targets(r)
        return self._join([c.on_reference(t_ns, float(z[j])) for j, c in enumerate(self.axes)])

    def flush(self) -> list:
        """Decide on held references (every chain the same)."""
        return self._join([c.flush() for c in self.axes])

    def on_measurement(self, t_ns: int, y) -> None:
        """Take a measured deflection vector: each chain gets its decoupled motion."""
        y = np.asarray(y, dtype=np.float64).reshape(self.M.shape[0])
        z = self.targets(y) if np.isfinite(y).all() else y
        for j, c in enumerate(self.axes):
            c.on_measurement(t_ns, float(z[j]))

    def request_reset(self) -> None:
        """Every chain restarts from rest."""
        for c in self.axes:
            c.request_reset()

    def start_word(self) -> str:
        """Return the chains' start: their common word, else each chain's, by axis name."""
        words = [c.stats.start for c in self.axes]
        if len(set(words)) == 1:
            return words[0]
        return ', '.join(f'{n}: {w}' for n, w in zip(self.names, words))

    @staticmethod
    def _join(outs: list) -> list:
        """Put the chains' commands together; they answer the same stamps (same gates)."""
        stamps = [[t for t, _ in o] for o in outs]
        if any(s != stamps[0] for s in stamps[1:]):
            raise DataError(f'the chains answered different stamps: {stamps}')
        return [(t, np.array([o[k][1] for o in outs])) for k, t in enumerate(stamps[0])]

    def count(self, stats: AxesStats) -> None:
        """Copy the chains' counters into the AxesController's (limits summed over axes)."""
        first = self.axes[0].stats
        for key in ('commands', 'gaps', 'filled', 'stamp_outliers', 'stream_restarts',
                    'rate_refused'):
            setattr(stats, key, getattr(first, key))
        for key in ('unreachable', 'voltage_limited', 'slew_limited', 'not_invertible',
                    'model_nonfinite'):
            setattr(stats, key, sum(getattr(c.stats, key) for c in self.axes))

    def status(self) -> tuple[int, str, dict]:
        """Every axis's ControllerHealth tick; the worst level, its first phrase named by axis."""
        level, message, values = OK, '', {}
        for name, health in zip(self.names, self.health):
            lv, msg, vals = health.tick()
            values.update({f'{name}.{k}': v for k, v in vals.items()})
            if lv > level:
                level, message = lv, f'axis {name}: {msg}'
        if level == OK:
            message = f'ok ({self.axes[0].mode}, {len(self.axes)} chains, coupling compensated)'
        return level, message, values
