"""
Free-run deflection estimator, ROS-free: the estimator node's whole logic.

`FreeRunEstimator.on_command(t_ns, u)` takes one voltage command (stamp in integer ns, volts) and
returns the estimates to publish as [(t_ns, y_hat_m), ...]; `on_measurement(t_ns, y)` takes a
measured deflection (m) when a sensor exists, for initialisation, running error and optional
re-anchoring. Nothing here imports torch: the model's Stepper (numpy/numba) does the arithmetic.

Conventions (so that the live estimate equals offline `model.simulate` to rounding):
- from rest: every u, y before the first command is 0, as `simulate(u, y0=None)`;
- from measurement: the model's state at the first of n_init consecutive measured commands
  (`init_window` seconds) is the one that best explains them (hysteresis memory, creep, output
  dynamics, sensor offset: `model.estimate_state`), and every command from there on is
  estimated by the free run from it, as `simulate(u, state=model.estimate_state(u[:n], y[:n]))`.
Started from rest, the estimate's unknown past is bracketed (`estimator.memory.MemoryBracket`):
`stats.state` says whether the state is determined yet and `stats.state_spread_m` by how much the
unknown past can still move the estimate.
A missing sample (stamp gap) or a rejected command (NaN/inf or outside [u_min, u_max]) is replaced
by the last good command (the amplifier holds its output), estimated, published and counted.

Stamps go through a `command.stamps.StampGate`: an isolated outlier stamp (future, past,
duplicate, a second writer's interleaved one) is refused (`stamp_outliers`), a gap of at most
`max_fill` samples is filled, and a real new stream (a player loop, a new run, a longer jump)
restarts the free run there (`stream_restarts`) once `confirm` commands agree. A stream whose
stamps step at another rate than the model's (`command.stamps.RateMonitor`) gets no estimate while
it lasts (`rate_withheld`): a model stepped at the wrong rate gives wrong numbers, not a slower
estimate.
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from piezo_narx_ros.command.stamps import (GRID_TOLERANCE, RATE_TOLERANCE, SAMPLE, RateMonitor,
                                           StampGate, checked_run_bounds, model_rate,
                                           pass_run_checked, pass_run_observed)
from piezo_narx_ros.errors import ConfigError, DataError
from piezo_narx_ros.estimator.memory import memory_bracket
from piezo_narx_ros.estimator.stamp_table import StampTable
from piezo_narx_ros.ident.state.window import FullWindow
from piezo_narx_ros.ident.state.estimate import MIN_WINDOW

INIT_MODES = ('auto', 'rest', 'measurement')


@dataclass
class EstimatorStats:
    """Counters shown on /diagnostics (samples unless said)."""

    commands: int = 0          # commands received
    estimates: int = 0         # estimates returned for publication
    rejected_nonfinite: int = 0
    rejected_range: int = 0
    # messages the node could not read (an axis missing, names repeated, malformed), and why
    # the last one was refused
    refused_messages: int = 0
    last_refusal: str = ''
    gaps: int = 0              # stamp gaps detected (events)
    filled: int = 0            # samples estimated from a held command (gaps + rejected)
    # commands refused: their stamp continues neither the running stream nor a new one
    # (future/past/duplicate/interleaved)
    stamp_outliers: int = 0
    stream_restarts: int = 0   # new streams recognised (loop, new run, jump beyond max_fill)
    out_of_range: int = 0      # estimates outside the model's trained output range (+ margin)
    nonfinite_estimates: int = 0   # of those, NaN or inf: the model's free run diverged
    reanchors: int = 0
    unestimated: int = 0       # commands before the first n0 measured ones (init from measurement)
    requested_restarts: int = 0   # restarts asked for (reset / reinitialize services)
    rate_withheld: int = 0     # estimates not published: the stream's rate is not the model's
    input_out_of_range: int = 0   # commands outside the model's trained input range (+ margin)
    init: str = 'waiting'      # 'waiting', 'rest', 'measurement', 'rest (no measurement)'
    # Whether the free run's state is known: 'estimated' (from measurement), 'determined' (its
    # unknown past no longer matters), 'undetermined' (it still may), '' before the run starts.
    state: str = ''
    state_spread_m: float = 0.0   # how far the unknown past can still move the estimate, m
    state_rms_m: float = 0.0      # residual of the measured window the state was set from, m


class FreeRunEstimator:
    """
    Runs `model` (any family: nu, ny, n0, stepper(), estimate_state(), output_range) in free run.

    fs: command rate, Hz (gap detection). init: 'rest', 'measurement' (wait for init_window s of
    consecutive measured samples, at most init_timeout s, then rest), or 'auto' (measurement when
    the caller says a deflection source exists, see `start`). bracket: started from rest, follow
    whether the state is determined yet (module docstring). u_min/u_max: accepted command range,
    V. max_fill: the
    longest gap (samples) bridged by holding the command; a longer one restarts the estimator.
    range_margin: fraction of the trained output span allowed beyond it before an estimate is
    flagged. window: samples in the running error (RMS, R²). reanchor_every: every that many
    samples, restart the recursion from the latest measured outputs (0 = never, the default).
    confirm: consecutive commands that must agree before a jump in the stamps (other than a gap
    of at most max_fill) is taken as a new stream rather than an outlier (module docstring).
    rate_tolerance: relative difference between the stream's stamp rate and fs beyond which the
    estimates are withheld (RateMonitor). fs must be the model's own rate when the model has one.
    init_past: how the unlogged past before the measured window ended ('any' or 'fade-out',
    ident.state.estimate step 5).
    """

    def __init__(self, model, fs: float | None = None, init: str = 'auto', u_min: float = -200.0,
                 u_max: float = 200.0, max_fill: int = 2000, range_margin: float = 0.1,
                 window: int = 2000, reanchor_every: int = 0, init_timeout: float = 1.0,
                 confirm: int = 3, rate_tolerance: float = RATE_TOLERANCE,
                 init_window: float | None = 0.5, bracket: bool = True, init_past: str = 'any',
                 start_policy: str | None = None):
        for attr in ('nu', 'ny', 'n0', 'stepper'):
            if not hasattr(model, attr):
                raise ConfigError(f'model has no {attr!r}: not a NARX/ARX model')
        fs = model_rate(model, fs)
        if init not in INIT_MODES:
            raise ConfigError(f'init must be one of {list(INIT_MODES)}, got {init!r}')
        if not u_min < u_max:
            raise ConfigError(f'u_min ({u_min:g} V) must be below u_max ({u_max:g} V)')
        if max_fill < 0 or window < 2 or reanchor_every < 0 or init_timeout < 0 or confirm < 1 \
                or not 0 < rate_tolerance < 1:
            raise ConfigError('max_fill, reanchor_every, init_timeout must be >= 0, window >= 2, '
                              'confirm >= 1 and rate_tolerance in (0, 1)')
        # The model file's start policy (fit --preset search) decides how the measured window
        # is used, and its window how long it is, unless the caller says otherwise.
        from piezo_narx_ros.ident.state.start import check_policy, model_start
        start = model_start(model)
        self.start_policy = start_policy if start_policy is not None else start.get('policy')
        if self.start_policy is not None:
            check_policy(self.start_policy, 'start_policy', ConfigError)
        if init_window is None:
            init_window = start['window_samples'] / fs if start else 0.5
            init_timeout = max(init_timeout, init_window)
        if init == 'auto' and self.start_policy == 'rest':
            init = 'rest'
        from piezo_narx_ros.ident.state.estimate import PASTS
        if init_past not in PASTS:
            raise ConfigError(f'init_past must be one of {list(PASTS)}, got {init_past!r}')
        self.init_past = init_past
        if not (math.isfinite(init_window) and 0 <= init_window <= init_timeout):
            raise ConfigError(f'init_window must be in [0, init_timeout = {init_timeout:g}] s, '
                              f'got {init_window:g}')
        self.model = model
        self.fs = float(fs)
        self.period_ns = 1e9 / self.fs
        self.init_mode = init
        self.u_min, self.u_max = float(u_min), float(u_max)
        self.max_fill = int(max_fill)
        self.confirm = int(confirm)
        self.window = int(window)
        self.reanchor_every = int(reanchor_every)
        # Measured samples that set the state (at least the model's lags and a few more).
        self.init_samples = max(int(round(init_window * self.fs)), int(model.n0), MIN_WINDOW)
        self.init_timeout_samples = max(int(round(init_timeout * self.fs)), self.init_samples)
        self.nu, self.ny, self.n0 = int(model.nu), int(model.ny), int(model.n0)
        # Several inputs or outputs (issue 20): commands are (n_in,) arrays, estimates (n_out,)
        # arrays; every check below holds per channel. One channel stays floats throughout.
        self.n_in = int(getattr(model, 'n_in', 1) or 1)
        self.n_out = int(getattr(model, 'n_out', 1) or 1)
        self.vector = self.n_in > 1 or self.n_out > 1
        # The brackets follow one input's extreme pasts; several axes have no such two.
        self.bracket = bool(bracket) and not self.vector
        if self.vector:
            from piezo_narx_ros.ident.base import channel_ranges
            u_rng, y_rng = channel_ranges(model)
            self.u_lo, self.u_hi = _padded(u_rng, range_margin, self.n_in)
            self.y_lo, self.y_hi = _padded(y_rng, range_margin, self.n_out)
        else:
            rng = getattr(model, 'output_range', None)
            if rng is not None:
                lo, hi = float(rng[0]), float(rng[1])
                pad = range_margin * (hi - lo)
                self.y_lo, self.y_hi = lo - pad, hi + pad
            else:
                self.y_lo, self.y_hi = -math.inf, math.inf
            rng = getattr(model, 'input_range', None)
            pad = range_margin * (rng[1] - rng[0]) if rng is not None else 0.0
            self.u_lo, self.u_hi = ((rng[0] - pad, rng[1] + pad) if rng is not None
                                    else (-math.inf, math.inf))
        self.u_excursion = 0.0    # largest command beyond the trained input range (V), per tick
        self.stats = EstimatorStats()
        self.excursion = 0.0      # largest distance beyond the range (m) since take_excursion()
        self.gate = StampGate(self.period_ns, self.max_fill, confirm)
        self.rate = RateMonitor(self.period_ns, rate_tolerance, max(self.window, 8))
        # One input: a batch's command checks run in the stamp kernel's call (on_commands).
        self._u_bounds = None if self.vector else checked_run_bounds(
            (self.u_min, self.u_max), (self.u_lo, self.u_hi))
        # u/t history kept for re-anchoring (only then), and the stamp tables' horizon
        self._hist = max(self.n0, 1) + 64 + self.reanchor_every + self.init_samples
        self._err = deque(maxlen=self.window)
        self._ymeas = deque(maxlen=self.window)
        # A caller that holds measurements back while `steady` (estimator_node decodes them in
        # bulk) sets this: called before anything that may depend on them (see `steady`).
        self.handover = None
        self._checked_of = self._checked = None     # _step_checked's Stepper and its method
        self.restart()

    # -------------------------------------------------------------------------------- state
    def restart(self, wait_for_measurement: bool | None = None) -> None:
        """Forget the past; the next command starts a new run (initialised per `init`)."""
        self._hand_over()
        self.gate.reset()
        self._new_run(wait_for_measurement)

    def _new_run(self, wait_for_measurement: bool | None) -> None:
        # Commands still waiting for their initial measurements get no estimate now: counted.
        self.stats.unestimated += len(getattr(self, '_pending', ()))
        if wait_for_measurement is None:
            wait_for_measurement = self.init_mode == 'measurement'
        self._wait = bool(wait_for_measurement) and self.init_mode != 'rest'
        self._decided = self.init_mode != 'auto'
        self._stepper = None
        self._pending: list[tuple[int, float, bool]] = []   # commands while the state waits
        self._window = FullWindow(self.init_samples)         # their first all measured
        self._last_t: int | None = None
        self._last_u = np.zeros(self.n_in) if self.vector else 0.0
        self._t_hist = deque(maxlen=self._hist)
        self._u_hist = deque(maxlen=self._hist)
        # t -> y_hat, for matching measurements; t -> y measured, not matched yet / for the state
        self._est = StampTable(2 * self._hist)
        self._meas = StampTable(2 * self._hist)
        self._since_anchor = 0
        self._relag = None    # (u, y) window whose last samples set the lags (_flush_init)
        self._memory = None
        self.out_of_range_now = False
        self.stats.init = 'waiting'
        self.stats.state, self.stats.state_spread_m, self.stats.state_rms_m = '', 0.0, 0.0

    def start(self, measurement_available: bool) -> None:
        """
        Tell an 'auto' estimator whether a deflection source exists.

        Call before the first command; later calls are ignored.
        """
        if not self._decided:
            self._wait = bool(measurement_available)
            self._decided = True

    def request_restart(self, from_measurement: bool) -> str:
        """
        Restart the free run at the next command; returns the one line that says how.

        From rest (all past u, y = 0), or from the next init_samples measured samples
        (`from_measurement`; still from rest after init_timeout without them). The estimator
        node's ~/reset and ~/reinitialize services.
        """
        if from_measurement and self.init_mode == 'rest':
            raise ConfigError("init is 'rest': this estimator never initialises from measurement")
        self.restart(from_measurement)
        self._wait = bool(from_measurement)
        self._decided = True
        self.stats.requested_restarts += 1
        if not from_measurement:
            return 'free run restarts from rest at the next command'
        n, wait = self.init_samples, self.init_timeout_samples
        return (f'free run restarts from the next {n} measured samples ({n / self.fs:g} s; '
                f'from rest if they do not come within {wait / self.fs:g} s)')

    @property
    def initialised(self) -> bool:
        return self._stepper is not None

    @property
    def steady(self) -> bool:
        """
        Say whether measurements only feed the running error now (they may be handed in late).

        The free run has started, no re-anchoring or memory bracket reads them and no command
        is held. A caller may hold measurements back while this holds, up to `pairing_horizon`
        samples, if it sets `handover` to a function that hands them in (on_measurements): the
        estimator calls it before it leaves this state's batch path (a command batch that is
        not the stream's next, a restart, a flush) and before `running_error`, so every result
        is the same as with each measurement handed in on arrival.
        """
        return (self._stepper is not None and self._memory is None and not self.reanchor_every
                and not self.gate.holding)

    @property
    def pairing_horizon(self) -> int:
        """Return how many samples of estimates are kept for late measurements to pair with."""
        return 2 * self._hist

    def _hand_over(self) -> None:
        """Have the caller hand in the measurements it holds back (see `steady`)."""
        if self.handover is not None:
            handover, self.handover = self.handover, None    # no re-entry while it runs
            try:
                handover()
            finally:
                self.handover = handover

    # ------------------------------------------------------------------------------- inputs
    def on_command(self, t_ns: int, u) -> list[tuple[int, float]]:
        """
        One command (stamp ns, volts) -> estimates to publish [(t_ns, y_hat m), ...].

        u: a float, or (n_in,) volts for a model of several inputs (then y_hat is (n_out,) m).
        """
        if self.vector:
            u = np.array(u, dtype=np.float64).reshape(self.n_in)   # kept: a copy
        self._hand_over()
        self.stats.commands += 1
        if not self._decided:
            self._decided = True
            self._wait = self.init_mode == 'measurement'
        out: list[tuple[int, float]] = []
        gate, last = self.gate, self._last_t
        if (type(u) is float and last is not None and last == gate.last and not gate.holding
                and self._stepper is not None and self._memory is None
                and not self.reanchor_every and self.u_min <= u <= self.u_max
                and self.u_lo <= u <= self.u_hi
                and abs((t_ns - last) / self.period_ns - 1.0) <= GRID_TOLERANCE):
            # The running stream's next command, clean (a 2 kHz stream's every command): what
            # gate.push, _apply, _accept, _advance and _step do with it, without their checks.
            gate.last = self._last_t = t_ns
            self._last_u = u
            off = self.rate.observe_next(t_ns)       # received, then accepted
            self._emit(t_ns, self._stepper.step(u), out, off)
            return out
        self.rate.received(t_ns)
        self._apply(gate.push(t_ns, u), out)
        return out

    def on_commands(self, t_ns, u) -> tuple[np.ndarray, np.ndarray]:
        """
        Estimate a batch: stamps (n,) int64 ns, volts (n,) -> (stamps (m,), y_hat (m,) m).

        The same estimates, counters and state as n on_command() calls. A batch of a running
        stream whose stamps are each the next on the grid, with every command finite and within
        [u_min, u_max], takes the fast path: the stamp and rate checks in one compiled call,
        the Stepper once per sample and the bookkeeping on whole lists. Anything else (a gap, an
        outlier, a rejected command, the start, re-anchoring, the memory bracket) goes sample by
        sample through on_command().
        """
        t = np.ascontiguousarray(t_ns, dtype=np.int64).ravel()
        fast = self._stepper is not None and self._memory is None and not self.reanchor_every
        passed = None
        if self.vector:     # rows of a copy: the Stepper and the history keep them
            v = np.array(u, dtype=np.float64).reshape(t.shape[0], self.n_in)
            ul = list(v)
            if fast and bool(((v >= self.u_min) & (v <= self.u_max)).all()):   # NaN: False
                passed = pass_run_observed(self.gate, self.rate, t)    # stamp and rate checks
                if passed is not None:
                    passed += (False,)   # within the trained range: checked per row
        else:
            v = np.ascontiguousarray(u, dtype=np.float64).ravel()   # the kernel's layout
            if t.shape != v.shape:
                raise DataError(f'{t.shape[0]} stamps for {v.shape[0]} commands')
            if fast:     # commands finite and accepted, then the stamp and rate checks
                passed = pass_run_checked(self.gate, self.rate, t, v, self._u_bounds)
            ul = None if passed is not None else v.tolist()
        if passed is not None:
            return self._run_batch(t, v, *passed)
        self._hand_over()
        out = [e for ti, vi in zip(t.tolist(), ul) for e in self.on_command(ti, vi)]
        return self.as_arrays(out)

    def on_measurements(self, t_ns, y) -> tuple[np.ndarray, np.ndarray]:
        """
        Take a batch of measured deflections: stamps (n,) int64 ns, m (n,) -> estimates ready.

        The same as n on_measurement() calls; (stamps (m,), y_hat (m,)) as on_commands. Once
        the free run has started, the pairing with the estimates runs on whole lists.
        """
        t = np.asarray(t_ns, dtype=np.int64).ravel()
        increasing = t.shape[0] < 2 or bool((t[1:] > t[:-1]).all())
        tl = t.tolist()
        if self.vector:
            yl = list(np.array(y, dtype=np.float64).reshape(len(tl), self.n_out))
        else:
            yl = np.asarray(y, dtype=np.float64).ravel().tolist()
        if len(tl) != len(yl):
            raise DataError(f'{len(tl)} stamps for {len(yl)} measurements')
        if self._stepper is None:
            return self.as_arrays([e for ti, yi in zip(tl, yl)
                                   for e in self.on_measurement(ti, yi)])
        if not _finite(sum(yl)):
            keep = [_finite(yi) for yi in yl]   # fewer stamps: still in order
            tl = [ti for ti, k in zip(tl, keep) if k]
            yl = [yi for yi, k in zip(yl, keep) if k]
        paired = self._est.pop_many(tl)
        if _any_value(paired):
            self._record_errors([(m, e) for m, e in zip(yl, paired) if e is not None])
        self._meas.extend(tl, yl, increasing)
        return self.as_arrays([])

    def _run_batch(self, t: np.ndarray, v: np.ndarray, off: np.ndarray, withheld: int,
                   inside: bool) -> tuple[np.ndarray, np.ndarray]:
        """
        Run the batch fast path of on_commands (its conditions hold: see there).

        The stamps passed the gate and the rate check: off (n,) bool and withheld, their verdict;
        inside: every command lies within the trained input range (False: look row by row).
        """
        st = self.stats
        n = t.shape[0]
        st.commands += n
        if not inside:
            # Estimated, but the model extrapolates there (finite here: no NaN to follow).
            beyond = _rows_beyond(v, self.u_lo, self.u_hi)
            if beyond.size:
                st.input_out_of_range += beyond.size
                self.u_excursion = max(self.u_excursion, float(beyond.max()))
        tl = t.tolist()
        self._last_t = tl[-1]
        # The inputs were checked finite and within [u_min, u_max] in on_commands.
        if self.vector:
            self._last_u = v[-1]
            y = self._stepper.step_many(v)
            yl = list(y)
        else:
            self._last_u = float(v[-1])
            y = self._step_checked(v)
            yl = y.tolist()
        st.rate_withheld += withheld
        st.estimates += n - withheld
        self.out_of_range_now = not _within(yl[-1], self.y_lo, self.y_hi)
        if self.vector or not (self.y_lo <= min(yl) and max(yl) <= self.y_hi
                               and math.isfinite(sum(yl))):
            beyond = _rows_beyond(y, self.y_lo, self.y_hi)      # NaN rows too, as in _emit
            if beyond.size:
                st.out_of_range += beyond.size
                self.excursion = _running_largest(self.excursion, beyond)
                st.nonfinite_estimates += int(np.count_nonzero(
                    ~np.isfinite(y.reshape(n, -1)).all(axis=1)))
        # Stamps in order: none measured yet is the steady stream's usual case (one comparison).
        measured = self._meas.get_many(tl) if self._meas.holds_from(tl[0]) else None
        if measured is not None and _any_value(measured):
            self._record_errors([(m, e) for m, e in zip(measured, yl) if m is not None])
            self._est.update((s, e) for s, m, e in zip(tl, measured, yl) if m is None)
        else:
            self._est.extend(tl, yl, True)     # each stamp the next on the grid
        if withheld:
            return t[~off], y[~off]
        return t, y

    def _step_checked(self, v: np.ndarray) -> np.ndarray:
        """Step a one-input batch already checked (finite, contiguous float64), V -> m."""
        stepper = self._stepper
        if stepper is not self._checked_of:     # looked up once per Stepper, not per batch
            self._checked_of = stepper
            self._checked = getattr(stepper, 'step_many_checked', stepper.step_many)
        return self._checked(v)

    def as_arrays(self, estimates: list) -> tuple[np.ndarray, np.ndarray]:
        """[(t_ns, y_hat), ...] -> (stamps (n,) int64, y_hat (n,) or (n, n_out) float64)."""
        if not estimates:
            shape = (0, self.n_out) if self.vector else (0,)
            return np.empty(0, dtype=np.int64), np.empty(shape)
        t, y = zip(*estimates)
        return np.array(t, dtype=np.int64), np.array(y, dtype=np.float64)

    @property
    def holding(self) -> int:
        """Commands held back while their stamps are ambiguous (see module docstring)."""
        return self.gate.holding

    def flush(self) -> list[tuple[int, float]]:
        """
        Decide on held commands when no more commands come (the stream stopped).

        A gap within max_fill is estimated, `confirm` or more agreeing commands start a new
        stream, anything else is refused as outliers. Returns the estimates that became ready.
        The node calls it when commands have stopped for a while.
        """
        self._hand_over()
        out: list[tuple[int, float]] = []
        self._apply(self.gate.flush(), out)
        return out

    def take_excursion(self) -> float:
        """
        Largest distance (m) of an estimate beyond the flagged range since the last call.

        Resets it (read once per diagnostics tick).
        """
        value, self.excursion = self.excursion, 0.0
        return value

    def take_input_excursion(self) -> float:
        """Largest distance (V) of a command beyond the trained input range since the last call."""
        value, self.u_excursion = self.u_excursion, 0.0
        return value

    def _apply(self, events, out: list) -> None:
        """Estimate the commands the stamp gate let through; restart on a new stream."""
        for kind, t, item in events:
            if kind == SAMPLE:
                self.rate.observe(t)
                self._accept(t, item, out)
            else:   # RESTART: item lists the new stream's stamps seen so far
                self.rate.reset()
                keep = {s: self._meas[s] for s in item if s in self._meas}
                decided = self._decided
                self._new_run(self._wait)
                # A new stream keeps the decision of an 'auto' estimator (sensor or not): the
                # node tells it only before the first command.
                self._decided = decided
                self._meas.update(keep.items())   # its measurements that arrived while it was held
        self.stats.stamp_outliers = self.gate.outliers
        self.stats.stream_restarts = self.gate.restarts

    def _accept(self, t_ns: int, u: float, out: list) -> None:
        """
        Estimate one command whose stamp is known to be on the stream.

        After _last_t, or the first; any gap is filled by holding the last good command.
        """
        st = self.stats
        good = True
        if not _finite(u):
            st.rejected_nonfinite += 1
            good = False
        elif not _within(u, self.u_min, self.u_max):
            st.rejected_range += 1
            good = False
        elif not _within(u, self.u_lo, self.u_hi):
            st.input_out_of_range += 1      # estimated, but the model extrapolates there
            beyond = _beyond(u, self.u_lo, self.u_hi)
            if beyond > self.u_excursion:
                self.u_excursion = beyond
        last = self._last_t
        if last is not None:
            missing = int(round((t_ns - last) / self.period_ns)) - 1
            if missing > 0:
                st.gaps += 1
                step = (t_ns - last) / (missing + 1)
                for i in range(1, missing + 1):
                    self._advance(last + int(round(i * step)), self._last_u, True, out)
        u_eff = u if good else self._last_u
        self._advance(t_ns, u_eff, not good, out)

    def on_measurement(self, t_ns: int, y: float) -> list[tuple[int, float]]:
        """
        One measured deflection (stamp ns, m) for initialisation, running error and re-anchoring.

        Returns the estimates that became ready (those held back while waiting for the initial
        measurements), usually none.
        """
        out: list[tuple[int, float]] = []
        if self.vector:
            y = np.array(y, dtype=np.float64).reshape(self.n_out)
        if not _finite(y):
            return out
        y_hat = self._est.pop(t_ns, None)
        if y_hat is not None:
            self._record_error(y, y_hat)
        self._meas[t_ns] = y
        if self._stepper is None and self._pending and \
                self._try_init_from_measurement(self._window.measurement(t_ns)):
            self._flush_init(out)
        return out

    # ------------------------------------------------------------------------------ outputs
    def running_error(self) -> tuple[float, float, int]:
        """(RMS error m, R², n) over the last `window` matched samples; NaN when too few."""
        self._hand_over()
        n = len(self._err)
        if n < 2:
            return math.nan, math.nan, n
        if self.vector:     # pooled over the outputs (docs/mimo.md), SST per output's mean
            e, y = np.array(self._err), np.array(self._ymeas)
            sse = float((e * e).sum())
            sst = float(((y - y.mean(axis=0)) ** 2).sum())
            return math.sqrt(sse / e.size), (1.0 - sse / sst) if sst > 0 else math.nan, n
        e = np.fromiter(self._err, float, n)
        y = np.fromiter(self._ymeas, float, n)
        sse = float(e @ e)
        sst = float(((y - y.mean()) ** 2).sum())
        return math.sqrt(sse / n), (1.0 - sse / sst) if sst > 0 else math.nan, n

    # ------------------------------------------------------------------------------ internals
    def _advance(self, t_ns: int, u: float, filled: bool, out: list) -> None:
        self._last_t = t_ns
        self._last_u = u
        if filled:
            self.stats.filled += 1
        if self.reanchor_every:
            self._t_hist.append(t_ns)
            self._u_hist.append(u)
        if self._stepper is None:
            if not self._wait:
                self._start_from_rest(u, 'rest')
            else:
                self._pending.append((t_ns, u, filled))
                start = self._window.command(t_ns, t_ns in self._meas)
                if not self._try_init_from_measurement(start) and \
                        len(self._pending) >= self.init_timeout_samples:
                    self._init_pending_from_rest(out)
                else:
                    self._flush_init(out)
                return
        self._step(t_ns, u, out)
        if self.reanchor_every:
            self._since_anchor += 1
            if self._since_anchor >= self.reanchor_every and self._reanchor():
                self._since_anchor = 0

    def _step(self, t_ns: int, u: float, out: list) -> None:
        """Estimate one command with the running Stepper; the memory brackets follow it."""
        self._emit(t_ns, self._stepper.step(u), out, self.rate.off)
        if self._memory is not None:
            st = self.stats
            st.state_spread_m = self._memory.step(u)
            if self._memory.determined:
                st.state, self._memory = 'determined', None

    def _start_from_rest(self, u0: float, how: str) -> None:
        """Start the Stepper from rest; bracket the unknown past from the first command u0 (V)."""
        self._stepper = self.model.stepper()
        self.stats.init = how
        self.stats.state = 'undetermined'
        if self.bracket:
            self._memory = memory_bracket(self.model, u0)

    def _emit(self, t_ns: int, y_hat: float, out: list, off: bool) -> None:
        """Publish y_hat (m) unless the stream is `off` rate; range checks; pair or keep it."""
        if off:                            # the model's state still follows the commands
            self.stats.rate_withheld += 1
        else:
            out.append((t_ns, y_hat))
            self.stats.estimates += 1
        # A float compared inline (NaN: out of range): _within's call cost 10 % of a sample.
        oor = not (self.y_lo <= y_hat <= self.y_hi if type(y_hat) is float
                   else _within(y_hat, self.y_lo, self.y_hi))
        self.out_of_range_now = oor
        if oor:
            self.stats.out_of_range += 1
            beyond = _beyond(y_hat, self.y_lo, self.y_hi)
            if not beyond <= self.excursion:   # also NaN: a diverged estimate
                self.excursion = beyond
            if not _finite(y_hat):
                self.stats.nonfinite_estimates += 1
        y = self._meas.get(t_ns)   # kept: re-anchoring reads it
        if y is not None:
            self._record_error(y, y_hat)
        else:
            self._est[t_ns] = y_hat

    def _record_error(self, y: float, y_hat: float) -> None:
        self._err.append(y - y_hat)
        self._ymeas.append(y)

    def _record_errors(self, pairs: list) -> None:
        """_record_error for each (y measured, y_hat) pair, m, in order."""
        self._err.extend([m - e for m, e in pairs])
        self._ymeas.extend([m for m, _ in pairs])

    def _try_init_from_measurement(self, start: int | None) -> bool:
        """
        Initialise at the first init_samples consecutive pending commands with a measurement.

        start: that window's first index in the pending commands (FullWindow), None while there
        is none. Usually the first ones; later ones when the first measurements were lost, e.g.
        while the deflection subscription was still being matched. Earlier commands get no
        estimate and are counted as `unestimated`. The state at the window's first command is
        the model's estimate_state of the window; a window no state explains is skipped (the
        next one is after it).
        """
        n, pending, meas = self.init_samples, self._pending, self._meas
        while start is not None:
            y_win = meas.get_many([t for t, _, _ in pending[start:start + n]])
            if any(y is None for y in y_win):   # forgotten since (a late hole filled): skip
                start = self._window.skip(start)
                continue
            u_win = np.array([u for _, u, _ in pending[start:start + n]])
            y_win = np.array(y_win)
            try:
                if self.start_policy is None:
                    state = self.model.estimate_state(u_win, y_win, past=self.init_past)
                else:
                    from piezo_narx_ros.ident.state.start import window_state
                    state = window_state(self.model, u_win, y_win, self.start_policy,
                                         self.init_past)
            except DataError:
                start = self._window.skip(start)
                continue
            break
        else:
            return False
        from piezo_narx_ros.ident.state.start import relag_window
        # A lagged family started by its policy from the measured lags: set once they are stepped.
        self._relag = relag_window(self.model, self.start_policy, u_win, y_win)
        self.stats.unestimated += start
        del pending[:start]
        self._stepper = self.model.stepper(state=state)
        self.stats.init = 'measurement'
        self.stats.state = 'estimated'
        self.stats.state_rms_m = float(state.info.get('rms_m', 0.0))
        return True

    def _flush_init(self, out: list) -> None:
        """After initialisation from measurement: estimate the queue from the window's start."""
        if self._stepper is None or not self._pending:
            return
        pending, self._pending = self._pending, []
        relag, self._relag = self._relag, None
        for i, (t, u, _) in enumerate(pending):
            self._step(t, u, out)
            if relag is not None and i == len(relag[0]) - 1:
                self._set_lags(*relag)

    def _set_lags(self, u_win, y_win) -> None:
        """Continue from the measured samples' last inputs and outputs (policy 'state')."""
        from piezo_narx_ros.ident.state.start import window_lags
        self._stepper.offset = np.zeros(self.n_out) if self.vector else 0.0
        self._stepper.reset(*window_lags(self.model, u_win, y_win))

    def _init_pending_from_rest(self, out: list) -> None:
        pending, self._pending = self._pending, []
        self._start_from_rest(pending[0][1], 'rest (no measurement)')
        for t, u, _ in pending:
            self._step(t, u, out)

    def _reanchor(self) -> bool:
        """
        Restart the recursion at the latest stamp s whose ny preceding outputs are measured.

        Then re-step the commands after s. Returns False when the measurements are not there.
        """
        ts, us = list(self._t_hist), list(self._u_hist)
        ny, nu = self.ny, self.nu
        for j in range(len(ts), max(nu, ny) - 1, -1):   # j: first sample to re-step
            ys = [self._meas.get(t) for t in ts[j - ny:j]]
            if any(v is None for v in ys):
                continue
            self._stepper.reset(us[j - nu:j] if nu else None, ys if ny else None)
            for u in us[j:]:
                self._stepper.step(u)
            self.stats.reanchors += 1
            return True
        return False


def _any_value(items: list) -> bool:
    """Whether a list of looked-up values (float, array or None) holds any that is not None."""
    try:
        return items.count(None) != len(items)   # floats: compared in C
    except ValueError:                           # arrays: no truth value of ==
        return any(v is not None for v in items)


def _finite(x) -> bool:
    """Whether a value (float) or every channel of one ((n,) array) is finite."""
    if isinstance(x, float):
        return math.isfinite(x)
    return bool(np.isfinite(x).all())


def _within(x, lo, hi) -> bool:
    """Whether x (float, or (n,) per channel against floats or (n,) bounds) is in [lo, hi]."""
    if isinstance(x, float):
        return lo <= x <= hi
    return bool(((x >= lo) & (x <= hi)).all())     # NaN: False


def _beyond(x, lo, hi) -> float:
    """How far x lies beyond [lo, hi] (largest over the channels; NaN for a NaN channel)."""
    if isinstance(x, float):
        return lo - x if x < lo else x - hi
    d = np.maximum(lo - x, x - hi)
    return float(d.max()) if not np.isnan(d).any() else math.nan


def _rows_beyond(x: np.ndarray, lo, hi) -> np.ndarray:
    """
    How far each sample outside [lo, hi] lies beyond it, in order ((k,) m or V; NaN for NaN).

    x: (n,) or (n, channels) (largest over the channels); samples inside are left out.
    """
    d = np.maximum(lo - x, x - hi)
    if d.ndim == 2:
        d = d.max(axis=1)
    return d[~(d <= 0.0)]


def _running_largest(current: float, values: np.ndarray) -> float:
    """
    Return `current` after `if not b <= current: current = b` for each b of values, in order.

    A NaN (a diverged estimate) replaces the running value and is replaced by the next one.
    """
    nan = np.flatnonzero(np.isnan(values))
    if nan.size:
        rest = values[nan[-1] + 1:]
        return float(rest.max()) if rest.size else math.nan
    m = float(values.max())
    return m if not m <= current else current


def _padded(rows, margin: float, n: int) -> tuple:
    """Per-channel (lo (n,), hi (n,)) of channel_ranges rows (n, 2) widened by margin × span."""
    if rows is None:
        return np.full(n, -math.inf), np.full(n, math.inf)
    pad = margin * (rows[:, 1] - rows[:, 0])
    return rows[:, 0] - pad, rows[:, 1] + pad
