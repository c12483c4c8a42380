"""
Sensorless position control, ROS-free: the controller node's whole logic.

`PositionController.on_reference(t_ns, r)` takes one position reference (stamp in integer ns,
metres) and returns the voltage commands to publish, [(t_ns, u V)], with the reference's stamp;
`on_measurement(t_ns, y)` takes a measured deflection (m) when a sensor exists (feedback, and the
tracking error shown on /diagnostics). Modes:

- 'linear': u = (r - offset) / gain, the model's static line (`inverse.static_gain`): what a user
  has without this package;
- 'inverse': the identified model inverted sample by sample (`inverse.ModelInverse`) with its own
  free run as the state: sensorless feed-forward;
- 'inverse_feedback': the inverse, its target corrected by a PI on the measured error r - y;
- 'feedback' (the benchmark's sensor-only baseline, not a node mode): u = (PI - offset) / gain.

Every mode sends its commands through the model, so the model's free run follows what the plant
was really given. `linear` refuses a model whose static line cannot be vouched for
(`gain_check.check_static_gain`: a runaway free run, no line, a size or sign that disagrees with
the model's ranges or its training data); the inverse modes note that an ARX or the paper's NARX
is no inverse-quality model (`notes`, a WARN on /diagnostics while it runs).

Limits: u in [u_min, u_max] and within slew_rate (per second of stamp time) of the previous
command; references outside [y_min, y_max] are clamped and counted; a target the inverse cannot
reach (voltage or slew limit, or a model flat there) gives the closest input and is counted; the
PI's integrator stops while the command is limited in the direction it pushes (anti-windup).

Stamps go through a `command.stamps.StampGate` like the estimator's: an isolated outlier stamp
(backwards, far in the future, duplicate, interleaved) is refused and gets no command; a gap of at
most max_fill samples advances the model with the held command (the amplifier holds its output,
as the simulator and a real rig do); a new stream (a planner restarted) is followed without
resetting the model, since the actuator itself has not moved. A reference stream whose stamps step
at another rate than the model's (`command.stamps.RateMonitor`) gets no command while it lasts
(`rate_refused`): the stage holds, and the model with it.

`tracking()` gives the figures that say whether the loop works: the RMS error and the correlation
of the measured deflection with the reference (a sensor), and the correlation of the commands with
the reference (always); control.health turns them into WARN/ERROR levels.
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from piezo_narx_ros.command.stamps import RATE_TOLERANCE, SAMPLE, RateMonitor, StampGate
from piezo_narx_ros.control.gain_check import check_static_gain
from piezo_narx_ros.control.inverse import REACHED, SLEW, TARGETS, VOLTAGE, ModelInverse
from piezo_narx_ros.control.start import (NO_MEASUREMENT, MeasuredStart, measured_start,
                                          start_settings)
from piezo_narx_ros.errors import ConfigError

MODES = ('linear', 'inverse', 'inverse_feedback')
BASELINE = 'feedback'            # sensor-only PI: the benchmark's comparison, not a node mode
FEEDBACK_MODES = ('inverse_feedback', BASELINE)


@dataclass
class ControllerStats:
    """Counters shown on /diagnostics (samples unless said)."""

    references: int = 0          # references received
    commands: int = 0            # commands returned for publication
    rejected_nonfinite: int = 0  # NaN/inf references: the previous reference is held
    out_of_range: int = 0        # references clamped to [y_min, y_max]
    gaps: int = 0                # stamp gaps (events); the model held the last command
    filled: int = 0              # samples the model advanced with a held command
    stamp_outliers: int = 0      # references refused for their stamp (no command sent)
    stream_restarts: int = 0     # new reference streams followed
    unreachable: int = 0         # commands that missed their target (next three: why)
    voltage_limited: int = 0
    slew_limited: int = 0
    not_invertible: int = 0      # the model is flat or folds back in the allowed window
    measurements: int = 0        # deflection samples matched to a command
    measurements_rejected: int = 0   # non-finite, or no command with that stamp
    measurements_late: int = 0   # older than feedback_timeout samples: not integrated
    feedback_stale: int = 0      # feedback commands without a measurement of the last samples
    windup_holds: int = 0        # integrator steps skipped by the anti-windup
    requested_resets: int = 0    # ~/reset
    rate_refused: int = 0        # references refused: their stream's rate is not the model's
    model_nonfinite: int = 0     # commands after which the model's output was NaN/inf
    refused_messages: int = 0    # reference messages the node could not read (axis missing...)
    last_refusal: str = ''       # and why the last one was refused
    start: str = 'rest'          # rest, waiting (for the start window), measurement, or
    #                              'rest (no measurement)' when the window never came


class PositionController:
    """
    Position reference in, voltage command out, through `model` (ARX, NARX, HysteresisNARX).

    mode: MODES or 'feedback'; fs: sample rate, Hz (the model's when None); u_min, u_max: V;
    slew_rate: V/s (inf: none); y_min, y_max: accepted references, m (None: the model's trained
    output range widened by range_margin of its span); target: the inverse's target
    ('output' or 'quasi_static', see inverse.py; None: quasi_static for a HysteresisNARX, else
    output); advance: samples by which the output leads the target (None: estimated from the
    model, ModelInverse.estimate_advance), compensated as r(k) - advance*(r(k) - r(k-1));
    kp (m/m) and ki (1/s): the PI on r - y;
    feedback_timeout: samples after which a measurement is too old for the PI (its delay
    bounds the loop's: stable for ki/fs < 2 sin(pi / (2 (2 timeout + 1))), 0.149 at 10);
    max_fill, confirm: see StampGate; window: samples in the running tracking error and the
    correlations; rate_tolerance: see RateMonitor.
    start_policy: how the first measured deflections set the model's state (ident.state.start:
    rest, offset, state; None: the policy the model file stores, else rest), over the model's
    stored window of `start_window` samples (None: the file's, else the policy's least). While
    the window fills the model runs from rest; once every command of it has its measured
    deflection the model continues from the state they give (stats.start 'measurement'), and
    without them after START_PATIENCE windows it stays from rest ('rest (no measurement)').
    """

    def __init__(self, model, mode: str = 'inverse', fs: float | None = None,
                 u_min: float = -200.0, u_max: float = 200.0, slew_rate: float = math.inf,
                 y_min: float | None = None, y_max: float | None = None,
                 range_margin: float = 0.05, target: str | None = None,
                 advance: float | None = None, kp: float = 0.0,
                 ki: float = 100.0, feedback_timeout: int = 10, max_fill: int = 2000,
                 confirm: int = 3, window: int = 2000, rate_tolerance: float = RATE_TOLERANCE,
                 start_policy: str | None = None, start_window: int | None = None, **solver):
        if mode not in MODES + (BASELINE,):
            raise ConfigError(f'mode must be one of {list(MODES)}, got {mode!r}')
        model, lead = lead_member(model)
        if target is None:
            target = 'quasi_static' if getattr(model, 'kind', None) == 'hysteresis_narx' \
                else 'output'
        if target not in TARGETS:
            raise ConfigError(f'target must be one of {list(TARGETS)}, got {target!r}')
        if not (kp >= 0 and ki >= 0 and feedback_timeout >= 1 and max_fill >= 0 and
                confirm >= 1 and window >= 2 and range_margin >= 0):
            raise ConfigError('kp, ki, max_fill and range_margin must be >= 0, '
                              'feedback_timeout and confirm >= 1, window >= 2')
        self.mode = mode
        self.inverse = ModelInverse(model, u_min=u_min, u_max=u_max, slew_rate=slew_rate, fs=fs,
                                    target=target, **solver)
        self.model = model
        self.fs = self.inverse.fs
        self.period_ns = 1e9 / self.fs
        self.gain_check = check_static_gain(model, self.fs)
        self.gain, self.offset = self.gain_check.gain, self.gain_check.offset
        if mode in ('linear', BASELINE) and not self.gain_check.trusted:
            raise ConfigError(f"mode {mode} refused: the model's static gain "
                              f'{self.gain * 1e6:.4g} um/V cannot be trusted: '
                              f'{self.gain_check.problems[0]}; use mode inverse with a '
                              'hysteresis_narx model, or refit')
        self.notes = []                 # standing problems, a WARN on every diagnostics tick
        self.model_note = lead          # what is inverted, when not the model itself (a log line)
        kind = getattr(model, 'kind', None)
        if mode in ('inverse', 'inverse_feedback') and kind in ('arx', 'narx'):
            self.notes.append(
                f'mode {mode} with a {kind} model: no inverse-quality model (docs/control.md: '
                f'{"93" if kind == "arx" else "46"} um RMS on a +-30 um move, commands swinging '
                'to the limits); use a hysteresis_narx model (fit --preset envelope)')
        self.advance = self.inverse.estimate_advance() if advance is None else float(advance)
        if y_min is None or y_max is None:
            rng = getattr(model, 'output_range', None)
            if rng is None:
                raise ConfigError('the model has no trained output range: give y_min and y_max')
            pad = range_margin * (rng[1] - rng[0])
            y_min = rng[0] - pad if y_min is None else y_min
            y_max = rng[1] + pad if y_max is None else y_max
        if not y_min < y_max:
            raise ConfigError(f'y_min ({y_min:g} m) must be below y_max ({y_max:g} m)')
        self.y_min, self.y_max = float(y_min), float(y_max)
        self.kp, self.ki_step = float(kp), float(ki) / self.fs
        self.feedback_timeout = int(feedback_timeout)
        self.stats = ControllerStats()
        self.gate = StampGate(self.period_ns, int(max_fill), int(confirm))
        self.rate = RateMonitor(self.period_ns, rate_tolerance, max(int(window), 8))
        self.peak_miss = 0.0          # largest |miss| of an unreachable target since read, m
        self._err = deque(maxlen=int(window))
        self._err_ref = deque(maxlen=int(window))      # the reference of each measured error
        self._cmd_ref = deque(maxlen=int(window))      # (u V, r m) of each command sent
        self._refs: dict[int, float] = {}     # stamp -> reference, for matching measurements
        # References kept for matching measurements: 1 s, so a controller running behind (a
        # loaded machine) still matches the deflections that arrive late.
        self._keep = max(4 * self.feedback_timeout + 64, int(self.fs))
        self.start_policy, self.start_window = start_settings(model, start_policy, start_window)
        self._reset_state()
        self._begin_start()

    # ------------------------------------------------------------------------------- state
    def _reset_state(self) -> None:
        self.inverse.reset()
        self._last_t: int | None = None
        self._last_ref: float | None = None
        self._integral = 0.0
        self._e: float | None = None          # last measured error r - y, m
        self._e_t = 0                         # and its stamp
        self._limited = 0                     # +1/-1: the last command could not go higher/lower
        self._r_prev: float | None = None     # previous reference (advance compensation)
        self._refs.clear()
        self._start = MeasuredStart(self.model, 'rest', 0)    # not waiting (see _begin_start)

    def _begin_start(self) -> None:
        if self.start_policy != 'rest':
            self._start = MeasuredStart(self.model, self.start_policy, self.start_window)
            self.stats.start = 'waiting'

    def request_reset(self) -> None:
        """
        Note that the actuator is at rest now (amplifier at 0 V, e.g. after it was switched off).

        The model restarts from rest and the integrator is cleared (the node's ~/reset); a
        start still waiting for its window is dropped, since the state is known now.
        """
        self._reset_state()
        self.stats.start = 'rest'
        self.stats.requested_resets += 1

    @property
    def holding(self) -> int:
        """Count the references held back while their stamps are ambiguous (StampGate)."""
        return self.gate.holding

    @property
    def y_model(self) -> float:
        """Return the model's free-run output for the last command, m (a sensorless estimate)."""
        return self.inverse.y_model

    @property
    def u_last(self) -> float:
        """Return the last command, V."""
        return self.inverse.u_prev

    # ------------------------------------------------------------------------------- inputs
    def on_reference(self, t_ns: int, r: float) -> list[tuple[int, float]]:
        """
        One reference (stamp ns, m) -> commands to publish [(t_ns, u V)], usually one.

        None while the stamp is held, several when held references are released.
        """
        self.stats.references += 1
        self.rate.received(t_ns)
        out: list[tuple[int, float]] = []
        self._apply(self.gate.push(t_ns, r), out)
        return out

    def flush(self) -> list[tuple[int, float]]:
        """Decide on held references when no more come (the node calls it when idle)."""
        out: list[tuple[int, float]] = []
        self._apply(self.gate.flush(), out)
        return out

    def on_measurement(self, t_ns: int, y: float) -> None:
        """
        One measured deflection (stamp of the command it answers, m).

        Tracking error and, in the feedback modes, the PI update.
        """
        r = self._refs.pop(t_ns, None)
        if r is None or not math.isfinite(y):
            self.stats.measurements_rejected += 1
            return
        if self._start.waiting:
            self.stats.start = measured_start(self._start, self.inverse, t_ns, y,
                                              self.stats.start)
        self.stats.measurements += 1
        e = r - y
        self._err.append(e)
        self._err_ref.append(r)
        if t_ns >= self._e_t or self._e is None:
            self._e, self._e_t = e, t_ns
        if self.mode not in FEEDBACK_MODES:
            return
        if self._last_t is not None and \
                self._last_t - t_ns > self.feedback_timeout * self.period_ns:
            # Integrating an error many samples old is feedback through a long delay: on a
            # starved machine (deflections 50 ms late) it drove the loop into oscillation.
            self.stats.measurements_late += 1
            return
        if self._limited and (e > 0) == (self._limited > 0):
            self.stats.windup_holds += 1    # pushing further into a limit: do not integrate
            return
        span = self.y_max - self.y_min
        self._integral = min(max(self._integral + self.ki_step * e, -span), span)

    # ------------------------------------------------------------------------------ outputs
    def running_error(self) -> tuple[float, int]:
        """(RMS of r - y over the last `window` measurements m, n); NaN when none."""
        n = len(self._err)
        if n == 0:
            return math.nan, 0
        e = np.fromiter(self._err, float, n)
        return math.sqrt(float(e @ e) / n), n

    def tracking(self) -> dict:
        """
        Figures over the last `window` samples that say whether the loop works.

        measured: deflections matched to a command; rms_m: RMS of r - y; reference_std_m: the
        references' own standard deviation over the same samples; corr_ry: correlation of the
        measured y with r (-1: anti-phase); commands, corr_ur: the same for the commands (V)
        against their references (its sign is the plant gain's when the loop works), and
        command_reference_std_m the references' standard deviation over those. NaN where there is
        nothing to compute.
        """
        out = {'measured': len(self._err), 'commands': len(self._cmd_ref)}
        rms, n = self.running_error()
        out['rms_m'] = rms
        out['reference_std_m'] = out['corr_ry'] = out['corr_ur'] = math.nan
        out['command_reference_std_m'] = math.nan
        if n >= 2:
            e = np.fromiter(self._err, float, n)
            r = np.fromiter(self._err_ref, float, n)
            out['reference_std_m'] = float(r.std())
            out['corr_ry'] = _corr(r, r - e)
        if len(self._cmd_ref) >= 2:
            ur = np.array(self._cmd_ref, dtype=float)
            out['corr_ur'] = _corr(ur[:, 0], ur[:, 1])
            out['command_reference_std_m'] = float(ur[:, 1].std())
        return out

    def take_peak_miss(self) -> float:
        """Largest miss of an unreachable target since the last call, m; resets it."""
        value, self.peak_miss = self.peak_miss, 0.0
        return value

    # ---------------------------------------------------------------------------- internals
    def _apply(self, events, out: list) -> None:
        for kind, t, r in events:
            if kind == SAMPLE:
                if self.rate.observe(t):       # a stream at another rate: no command, stage holds
                    self.stats.rate_refused += 1
                    self._last_t = t
                    continue
                self._accept(t, r, out)
            else:   # RESTART: a new stream; the actuator has not moved, so no reset
                self._last_t = None
                self.rate.reset()
        self.stats.stamp_outliers = self.gate.outliers
        self.stats.stream_restarts = self.gate.restarts

    def _accept(self, t_ns: int, r: float, out: list) -> None:
        st = self.stats
        if not math.isfinite(r):
            st.rejected_nonfinite += 1
            r = self._last_ref
        elif not self.y_min <= r <= self.y_max:
            st.out_of_range += 1
            r = min(max(r, self.y_min), self.y_max)
        inv = self.inverse
        dt = bridge_gap(self, t_ns)
        if r is None:               # nothing valid received yet: hold the actuator
            u = inv.u_prev
            self._limited = 0
        else:
            self._last_ref = r
            u = self._command(t_ns, r, dt)
            self._cmd_ref.append((u, r))
            self._refs[t_ns] = r
            if len(self._refs) > self._keep:
                del self._refs[next(iter(self._refs))]
        if not math.isfinite(u):       # never send what the solver could not decide
            u = inv.u_prev
        inv.commit(u)
        if not math.isfinite(inv.y_model):
            st.model_nonfinite += 1
        st.commands += 1
        out.append((t_ns, u))
        if self._start.waiting and not self._start.sent(t_ns, u):
            self.stats.start = NO_MEASUREMENT

    def _correction(self, t_ns: int) -> float:
        """PI output, m: P on the latest measured error while it is recent, plus the integral."""
        fresh = (self._e is not None and
                 t_ns - self._e_t <= self.feedback_timeout * self.period_ns)
        if not fresh:
            self.stats.feedback_stale += 1
            return self._integral
        return self.kp * self._e + self._integral

    def _command(self, t_ns: int, r: float, dt: float | None) -> float:
        inv, mode = self.inverse, self.mode
        if mode == 'linear' or mode == BASELINE:
            want = r if mode == 'linear' else self._correction(t_ns)
            u_wanted = (want - self.offset) / self.gain
            u = inv.clamp(u_wanted, dt)
            self._limited = 0
            if u != u_wanted:   # +1: it could not go as high as wanted (in metres)
                self._limited = 1 if (u_wanted > u) == (self.gain > 0) else -1
                self._count_limit(VOLTAGE if u in (inv.u_min, inv.u_max) else SLEW,
                                  abs(u_wanted - u) * abs(self.gain))
            return u
        target = r + (self._correction(t_ns) if mode == 'inverse_feedback' else 0.0)
        # The output leads the quasi-static value by `advance` samples: ask for that much less.
        r_prev = self._r_prev if self._r_prev is not None else r
        self._r_prev = r
        target -= self.advance * (r - r_prev)
        sol = inv.solve(target, dt)
        self._limited = 0
        if not math.isfinite(sol.miss):
            return sol.u        # a model that gives NaN/inf misses nothing: model_nonfinite
        if sol.limit != REACHED:
            self._limited = 1 if sol.miss < 0 else -1
            self._count_limit(sol.limit, abs(sol.miss))
        return sol.u

    def _count_limit(self, why: str, miss: float) -> None:
        st = self.stats
        st.unreachable += 1
        if why == VOLTAGE:
            st.voltage_limited += 1
        elif why == SLEW:
            st.slew_limited += 1
        else:
            st.not_invertible += 1
        if miss > self.peak_miss:
            self.peak_miss = miss


def lead_member(model) -> tuple:
    """
    Return (the model to invert, a note): a committee's first member (the search's pick).

    A committee (ident/ensemble: the mean of several networks) has no inverse of its own; its
    first member does, and follows the committee's start policy. Any other model: (model, '').
    """
    if getattr(model, 'kind', None) != 'ensemble':
        return model, ''
    lead = model.members[0]
    meta = dict(getattr(model, 'metadata', None) or {})
    lead.metadata = {**meta, **(getattr(lead, 'metadata', None) or {}),
                     'start': meta.get('start') or {}}
    return lead, (f'the model is a committee of {len(model.members)}: the controller inverts its '
                  "first member (the search's pick); estimator_node runs the whole committee")


def bridge_gap(ctl, t_ns: int) -> float | None:
    """
    Advance a controller to the reference stamped t_ns (ns): returns dt (s) since the last one.

    A gap (missing references) advances the model with the command held, as the amplifier holds
    it (counted in `gaps`, `filled`). ctl: PositionController or AxesController (its _last_t,
    period_ns, stats and inverse).
    """
    dt = None
    if ctl._last_t is not None:
        dt = (t_ns - ctl._last_t) * 1e-9
        missing = int(round((t_ns - ctl._last_t) / ctl.period_ns)) - 1
        if missing > 0:
            ctl.stats.gaps += 1
            ctl.stats.filled += missing
            for _ in range(missing):
                ctl.inverse.commit(ctl.inverse.u_prev)
    ctl._last_t = t_ns
    return dt


def safety_bounded(limits: dict, v_min, v_max) -> tuple[dict, str]:
    """
    Intersect command limits {'u_min', 'u_max'} (V, scalars or per axis) with the safety window.

    The node's own [v_min, v_max] bounds every command whatever a model file's trained range
    (or u_min/u_max) says. Returns (limits, note): the note says what was cut, '' when nothing.
    ConfigError (one line) when nothing of the limits lies inside the window.
    """
    lo, hi = np.asarray(limits['u_min'], float), np.asarray(limits['u_max'], float)
    b_lo, b_hi = np.maximum(lo, v_min), np.minimum(hi, v_max)
    if not (b_lo < b_hi).all():
        raise ConfigError(f'the command limits [{_volts(lo)}, {_volts(hi)}] V lie outside the '
                          f'safety limits [{v_min:g}, {v_max:g}] V (v_min, v_max)')
    note = ''
    if (b_lo != lo).any() or (b_hi != hi).any():
        note = (f'the command limits [{_volts(lo)}, {_volts(hi)}] V (the trained input range '
                f'the model file claims, or u_min/u_max) exceed the safety limits '
                f'[{v_min:g}, {v_max:g}] V: every command is bounded by them')
    if lo.ndim == 0:
        return {'u_min': float(b_lo), 'u_max': float(b_hi)}, note
    return {'u_min': b_lo, 'u_max': b_hi}, note


def _volts(v: np.ndarray) -> str:
    return ' '.join(f'{x:g}' for x in np.atleast_1d(v))


def input_limits(model, margin: float = 0.05, fallback: float = 200.0) -> dict:
    """
    {'u_min', 'u_max'} (V): the model's trained input range widened by `margin` of its span.

    The controller's default limits, so that no command leaves what the model was fitted on by
    more than that (a model extrapolates there); +-fallback V for a model without a range.
    """
    rng = getattr(model, 'input_range', None)
    if rng is None or not rng[1] > rng[0]:
        return {'u_min': -float(fallback), 'u_max': float(fallback)}
    pad = margin * (rng[1] - rng[0])
    return {'u_min': float(rng[0] - pad), 'u_max': float(rng[1] + pad)}


def _corr(a: np.ndarray, b: np.ndarray) -> float:
    """Pearson correlation of two equally long arrays; NaN when either is constant."""
    a, b = a - a.mean(), b - b.mean()
    den = math.sqrt(float(a @ a) * float(b @ b))
    return float(a @ b) / den if den > 0 else math.nan
