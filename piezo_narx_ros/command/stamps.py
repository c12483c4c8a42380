"""
Which received command stamps belong to the stream, ROS-free.

Every command of a stream sits on one sample grid, t_k = t0 + k/fs. A receiver (the estimator,
the simulator) must tell apart a stamp that is merely off (a command stamped in the future or the
past, a duplicate, the interleaved stamps of a second writer) from a real change of the stream
(a gap, a player loop, a new run). One stamp alone cannot say which; the next ones can.

`StampGate.push(t, item)` passes a command whose stamp is the next one on the grid straight
through. Any other stamp is held back until the following commands decide:
- they continue the running stream: the held commands were outliers and are dropped (counted);
- they continue from the held ones: a gap of at most `max_fill` samples is accepted after one
  confirming command; anything else (a loop back, a new run, a longer jump) is a new stream once
  `confirm` consecutive commands agree, announced by a RESTART event before its samples.
  A candidate off the running grid and within `INTERLEAVE_S` of its last stamp is, in addition,
  held until it has moved beyond that: it is most likely a second writer whose commands arrived
  in a burst (DDS delivers two writers' samples in its own order), and a burst of three must not
  make the receiver restart on it.
So normal samples are never delayed, an abnormal one by at most `confirm` samples (a new stream
within INTERLEAVE_S of the old one by at most that long), and a single bad stamp can no longer
make a receiver refuse every later, correct command.

The gate's quarter-period tolerance lets a stream at another rate through sample by sample (a
2.5 kHz stream on a 2 kHz grid); `RateMonitor` measures the rate of the accepted stamps and says
when it is not the receiver's, and `model_rate` refuses a node rate that is not the model's.
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np

from piezo_narx_ros.command import stamp_kernels as sk
from piezo_narx_ros.errors import ConfigError

SAMPLE = 'sample'     # (SAMPLE, t_ns, item): the next command of the stream (maybe after a gap)
RESTART = 'restart'   # (RESTART, t_ns, [stamps]): a new stream starts at t_ns with these stamps

# A stamp within this fraction of a period from a grid point is on the grid.
GRID_TOLERANCE = 0.25
# A candidate stream within this time of the running one's last stamp is not confirmed yet, s:
# longer than a writer's samples are plausibly delayed behind another's on a loaded host, shorter
# than any real restart (a command node or player starting again takes ~1 s).
INTERLEAVE_S = 0.05


class StampGate:
    """
    Classifies command stamps (integer ns) of a stream with period `period_ns` (ns).

    max_fill: longest gap (samples) accepted as a gap of the running stream; confirm: commands
    that must agree before a jump is a new stream. `outliers` and `restarts` count the verdicts.
    """

    def __init__(self, period_ns: float, max_fill: int, confirm: int = 3):
        self.period_ns = float(period_ns)
        self.max_fill = int(max_fill)
        self.confirm = int(confirm)
        self.outliers = 0
        self.restarts = 0
        self.last: int | None = None            # stamp of the last command passed through
        self._held: list[tuple[int, Any]] = []

    @property
    def holding(self) -> int:
        """Commands held back while their stamps are ambiguous."""
        return len(self._held)

    def reset(self) -> None:
        """Forget the stream: the next command is accepted as the first of a new one."""
        self.last = None
        self._held = []

    def steps(self, t_from: int, t_to: int) -> int | None:
        """Sample periods from t_from to t_to when t_to lies ahead on the same grid, else None."""
        d = (t_to - t_from) / self.period_ns
        k = round(d)
        return k if k >= 1 and abs(d - k) <= GRID_TOLERANCE else None

    def push(self, t_ns: int, item: Any = None) -> list[tuple]:
        """
        One received command.

        Returns the events now decided, in order (often just [(SAMPLE, t_ns, item)], [] while a
        stamp is held).
        """
        if self.last is None or self.steps(self.last, t_ns) == 1:   # first, or it continues
            self._drop_held()
            self.last = t_ns
            return [(SAMPLE, t_ns, item)]
        if self._held:
            k = self.steps(self._held[-1][0], t_ns)
            if k is not None and k - 1 <= self.max_fill:
                self._held.append((t_ns, item))    # it continues the held candidate
                return self._resolve()
            self._drop_held()                      # neither: the held ones were outliers
        self._held.append((t_ns, item))            # a new candidate: gap, new stream, outlier
        return []

    def pass_run(self, t_ns: np.ndarray) -> bool:
        """
        Let a batch of stamps (n,) int64 ns through at once when each is the next on the grid.

        The batch fast path: True (and the gate is where n push() calls would leave it, every one
        a SAMPLE) when nothing is held and every stamp is one period after the previous one (the
        first after `last`); otherwise False and nothing changed (push them one by one).
        """
        if self._held or self.last is None or t_ns.shape[0] == 0 or \
                not sk.on_grid_run(t_ns, self.last, self.period_ns, GRID_TOLERANCE):
            return False
        self.last = int(t_ns[-1])
        return True

    def flush(self) -> list[tuple]:
        """
        Decide now (no more commands are coming).

        Held commands that are a gap within max_fill pass; `confirm` or more that agree are a
        new stream (the running one has stopped too); others are outliers.
        """
        if not self._held:
            return []
        k = self.steps(self.last, self._held[0][0])
        if k is not None and k - 1 <= self.max_fill:
            return self._release([])
        if len(self._held) >= self.confirm:
            return self._restart()
        self._drop_held()
        return []

    def _drop_held(self) -> None:
        self.outliers += len(self._held)
        self._held = []

    def _resolve(self) -> list[tuple]:
        k = self.steps(self.last, self._held[0][0])
        if k is not None and k - 1 <= self.max_fill:
            return self._release([])         # a gap of the running stream
        if len(self._held) >= self.confirm and not self._interleaved():
            return self._restart()
        return []

    def _interleaved(self) -> bool:
        """Tell whether the held candidate is off the running grid and within INTERLEAVE_S."""
        dt = self._held[-1][0] - self.last
        d = dt / self.period_ns
        return abs(dt) <= INTERLEAVE_S * 1e9 and abs(d - round(d)) > GRID_TOLERANCE

    def _restart(self) -> list[tuple]:
        self.restarts += 1
        return self._release([(RESTART, self._held[0][0], [t for t, _ in self._held])])

    def _release(self, events: list) -> list[tuple]:
        held, self._held = self._held, []
        events += [(SAMPLE, t, item) for t, item in held]
        self.last = held[-1][0]
        return events


# Relative difference between a stream's stamp rate and the rate a node runs at that is refused.
# Clocks of two machines differ by parts per million; a stream 1 % off is another rate.
RATE_TOLERANCE = 0.01
# The first verdict needs this many sample periods of stamps (a few ms at kHz rates).
RATE_MIN_STEPS = 3
# A received command counts as an arrival of the stream (one writer sending more commands than
# grid points) only when its stamp lies this many periods after the last accepted one: the
# in-between stamps of a faster stream do, the outliers of a burst (stamps seconds or hours
# away, duplicates of past ones) do not, so a burst cannot make a good stream look too fast.
ARRIVAL_AFTER = (GRID_TOLERANCE, 2.5)


_KERNELS_LOADED = False


def _load_kernels() -> None:
    """
    Compile or load the stamp kernels once per process, when the first monitor is made.

    Not on the first command: loading them took long enough there for a rig reply to time out.
    """
    global _KERNELS_LOADED
    if not _KERNELS_LOADED:
        t = np.zeros(1, dtype=np.int64)
        ring = np.zeros((RATE_MIN_STEPS + 1, 3), dtype=np.int64)
        st = np.zeros(sk.N_INT_STATE, dtype=np.int64)
        st[sk.I_MIN_STEPS] = RATE_MIN_STEPS
        fst = np.zeros(sk.N_FLOAT_STATE)
        fst[sk.F_PERIOD], fst[sk.F_TOLERANCE] = 1.0, 0.01
        off = np.zeros(1, dtype=np.bool_)
        sk.observe_run(t, 0, 1, ring, st, fst, off)
        sk.on_grid_run(t, 0, 1.0, GRID_TOLERANCE)
        sk.observe_one(0, 0, ring, st, fst)
        sk.pass_and_observe(t, 0, GRID_TOLERANCE, 0, ring, st, fst, off)
        bounds = np.array([-1.0, 1.0, -1.0, 1.0, GRID_TOLERANCE])
        sk.check_pass_and_observe(t, np.zeros(1), bounds, 0, 0, ring, st, fst, off)
        _KERNELS_LOADED = True


class RateMonitor:
    """
    Tell whether a stream's stamp rate matches the rate `period_ns` (ns) a node runs at.

    The stamp gate accepts a stamp within a quarter period of the next grid point, so a 2.5 kHz
    stream passes a 2 kHz gate sample by sample; this measures the rate itself. `observe(t_ns)` is
    called for every sample the gate accepts (in order), `received()` for every command that came
    in (accepted or not), `reset()` at a new stream. Over the last `window` accepted samples the
    stamps span `n` periods of the node's clock (gaps count their missing samples); the stream is
    `off` when its mean period differs from the node's by more than `tolerance` plus the half
    period that stamp jitter can move the two ends of the window (0.5 / n), so that jittered
    stamps of the right rate never trip it and an exact stream 25 % off is recognised within 4
    samples. It clears once the window agrees again.
    """

    __slots__ = ('period_ns', 'tolerance', 'window', '_ring', '_st', '_fst',
                 '_received', '_near', '_last')

    def __init__(self, period_ns: float, tolerance: float = RATE_TOLERANCE, window: int = 2000):
        if not (period_ns > 0 and tolerance > 0 and window >= RATE_MIN_STEPS + 1):
            raise ConfigError(f'rate check: need period_ns > 0, tolerance > 0 and window > '
                              f'{RATE_MIN_STEPS}')
        self.period_ns = float(period_ns)
        self.tolerance = float(tolerance)
        self.window = int(window)
        self._near = (ARRIVAL_AFTER[0] * self.period_ns, ARRIVAL_AFTER[1] * self.period_ns)
        # The state lives in arrays that one compiled kernel (stamp_kernels.observe_run) updates
        # for a sample or a batch alike.
        self._st = np.zeros(sk.N_INT_STATE, dtype=np.int64)
        # stream period / node period over the window; commands received per node period
        self._fst = np.full(sk.N_FLOAT_STATE, np.nan)
        # The settings beside the state: the kernels read them there (fewer arguments).
        self._st[sk.I_MIN_STEPS] = RATE_MIN_STEPS
        self._fst[sk.F_PERIOD], self._fst[sk.F_TOLERANCE] = self.period_ns, self.tolerance
        self.single_writer = False
        self.reset()
        _load_kernels()

    @property
    def single_writer(self) -> bool:
        """
        Whether one publisher feeds the stream, set by a node that knows it.

        More commands than grid points are then a faster stream, not a second writer.
        """
        return bool(self._st[sk.I_SINGLE])

    @single_writer.setter
    def single_writer(self, value: bool) -> None:
        self._st[sk.I_SINGLE] = 1 if value else 0

    @property
    def off(self) -> bool:
        """Return whether the stream's rate is not the node's (over the window)."""
        return bool(self._st[sk.I_OFF])

    @property
    def episodes(self) -> int:
        """Count the times the stream went off rate."""
        return int(self._st[sk.I_EPISODES])

    @property
    def ratio(self) -> float:
        """Stream period / node period over the window (NaN before the first verdict)."""
        return float(self._fst[sk.F_RATIO])

    @property
    def arrival_ratio(self) -> float:
        """Commands received per node period of stamp time (NaN before the first verdict)."""
        return float(self._fst[sk.F_ARRIVAL])

    def reset(self) -> None:
        """
        Forget the stream's stamps (a new one starts).

        The verdict stands until the new stream has given its own (RATE_MIN_STEPS periods), so a
        player looping a file at the wrong rate is not trusted again for its first samples.
        """
        # ring of (stamp, cumulative steps, received) per accepted sample
        self._ring = np.zeros((self.window, 3), dtype=np.int64)
        st = self._st
        st[sk.I_N] = st[sk.I_COUNT] = st[sk.I_HEAD] = st[sk.I_LAST] = st[sk.I_HAS_LAST] = 0
        self._received = 0                  # received() calls not yet passed to the kernel
        self._last: int | None = None       # the last accepted stamp (the kernel's I_LAST)

    def received(self, t_ns: int | None = None) -> None:
        """
        Count one incoming command (accepted or refused by the gate), stamped t_ns (ns).

        With its stamp, it counts only when that lies ARRIVAL_AFTER periods after the last
        accepted stamp (or there is none yet): where a faster stream's commands lie.
        """
        if t_ns is not None and self._last is not None:
            d = t_ns - self._last
            if not self._near[0] <= d <= self._near[1]:
                return
        self._received += 1

    def observe(self, t_ns: int) -> bool:
        """One sample the gate accepted (stamp ns); returns `off`."""
        got, self._received, self._last = self._received, 0, t_ns
        return sk.observe_one(t_ns, got, self._ring, self._st, self._fst)

    def observe_next(self, t_ns: int) -> bool:
        """received(t_ns) then observe(t_ns), for a command the gate accepts; returns `off`."""
        last, got = self._last, self._received
        if last is None or self._near[0] <= t_ns - last <= self._near[1]:
            got += 1
        self._received, self._last = 0, t_ns
        return sk.observe_one(t_ns, got, self._ring, self._st, self._fst)

    def observe_run(self, t_ns: np.ndarray) -> np.ndarray:
        """
        Receive and accept a batch of samples at once (stamps (n,) int64 ns, in order).

        The same as received() then observe(t) for each stamp in turn (one compiled call):
        returns the `off` verdict after each sample, (n,) bool.
        """
        t = np.ascontiguousarray(t_ns, dtype=np.int64)
        offs = np.empty(t.shape[0], dtype=np.bool_)
        if not t.shape[0]:
            return offs
        got, self._received, self._last = self._received, 0, int(t[-1])
        sk.observe_run(t, got, 1, self._ring, self._st, self._fst, offs)
        return offs

    def describe(self, what: str = 'stream') -> str:
        """One phrase: the stream's rate against the node's, e.g. for /diagnostics."""
        fs = 1e9 / self.period_ns
        stream = fs / self.ratio if self.ratio > 0 else float('nan')
        text = (f'{what} stamps step {self.ratio * self.period_ns * 1e-3:.4g} us, i.e. '
                f'{stream:.6g} Hz, not {fs:.6g} Hz ({100 * (stream / fs - 1):+.3g} %)')
        arrivals = self.arrival_ratio * fs
        if not abs(self.ratio - 1.0) > self.tolerance:      # on the grid, but too many
            return (f'{what}s arrive at {arrivals:.6g} per second from one publisher, not '
                    f'{fs:g} (the ones between the grid points are refused)')
        if arrivals > 1.25 * stream:
            text += f'; {arrivals:.6g} commands/s arrive (the others are off the grid)'
        return text


def pass_run_observed(gate: StampGate, rate: RateMonitor, t_ns: np.ndarray):
    """
    Return gate.pass_run(t_ns) and, when it passes, rate.observe_run(t_ns), in one compiled call.

    t_ns: (n,) int64 ns, C-contiguous. None when the batch does not pass (nothing changed);
    else (the `off` verdict after each sample (n,) bool, how many are off): a batch path's
    stamp and rate checks at the price of one.
    """
    if not _run_may_pass(gate, t_ns):
        return None
    offs = np.empty(t_ns.shape[0], dtype=np.bool_)
    n_off = sk.pass_and_observe(t_ns, gate.last, GRID_TOLERANCE, rate._received, rate._ring,
                                rate._st, rate._fst, offs)
    if n_off < 0:
        return None
    _run_passed(gate, rate, t_ns)
    return offs, n_off


def _run_may_pass(gate: StampGate, t_ns: np.ndarray) -> bool:
    """Tell whether a batch can take the compiled path (nothing held, a last stamp, samples)."""
    return not (gate._held or gate.last is None or t_ns.shape[0] == 0)


def _run_passed(gate: StampGate, rate: RateMonitor, t_ns: np.ndarray) -> None:
    """Commit a batch the compiled checks passed: its last stamp in the gate and the monitor."""
    gate.last = rate._last = int(t_ns[-1])
    rate._received = 0


def checked_run_bounds(accepted: tuple, trained: tuple) -> np.ndarray:
    """
    Return pass_run_checked's bounds: (lo, hi) accepted and (lo, hi) trained commands, V.

    With the grid tolerance (the rate's settings are in its monitor's state arrays).
    """
    return np.array([*accepted, *trained, GRID_TOLERANCE], dtype=np.float64)


def pass_run_checked(gate: StampGate, rate: RateMonitor, t_ns: np.ndarray, v: np.ndarray,
                     bounds: np.ndarray):
    """
    Return pass_run_observed(gate, rate, t_ns) of a batch whose commands must pass too.

    v: (n,) float64 V, C-contiguous, one per stamp; bounds: checked_run_bounds. None when a
    command is NaN, infinite or outside the accepted range, or the stamps do not pass (nothing
    changed); else (off (n,) bool, how many are off, whether every command lies within the
    trained range): the Python checks of a batch's commands (a list, its min, max and sum)
    folded into the stamp and rate kernel's one call.
    """
    if not _run_may_pass(gate, t_ns):
        return None
    offs = np.empty(t_ns.shape[0], dtype=np.bool_)
    n_off, inside = sk.check_pass_and_observe(t_ns, v, bounds, gate.last, rate._received,
                                              rate._ring, rate._st, rate._fst, offs)
    if n_off < 0:
        return None
    _run_passed(gate, rate, t_ns)
    return offs, n_off, inside


def model_rate(model, fs: float | None = None) -> float:
    """
    Return the rate (Hz) a node runs `model` at: its own fs; a given `fs` must agree with it.

    ConfigError when neither is known, or when they differ: a model identified at one rate gives
    wrong numbers at another (its lags are samples, not seconds).
    """
    own = getattr(model, 'fs', None)
    for value in (fs, own):
        if value is not None and value != 0 and not (math.isfinite(value) and value > 0):
            raise ConfigError(f'sample rate must be a positive number of Hz, got {value!r}')
    if fs and own and abs(fs / own - 1.0) > 1e-9:
        raise ConfigError(f"fs {fs:g} Hz differs from the model's {own:g} Hz: a model runs only "
                          "at the rate it was identified at (leave fs at 0 for the model's; "
                          'for another rate, fit a model on data sampled at it)')
    fs = fs or own
    if not fs:
        raise ConfigError('sample rate unknown: the model file has no fs and none was given')
    return float(fs)
