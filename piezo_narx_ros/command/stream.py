"""
Drift-free sample clock and voltage-command streaming, ROS-free.

The command node asks `CommandStreamer.poll(now)` on every timer tick and publishes what it gets.
Sample k is stamped t_k = t0 + k/fs exactly (integer nanoseconds, no accumulated float error), and
is due once the monotonic clock has passed start + k/fs. A late tick returns every sample that has
become due (catch-up), so a slow tick never drops a sample or shifts later stamps.
"""
from __future__ import annotations

import math
from fractions import Fraction

import numpy as np

from piezo_narx_ros.errors import ConfigError

NS = 1_000_000_000


class SampleClock:
    """
    Map sample index <-> time for a rate fs (Hz).

    Anchored at stamp t0_ns (ns, the stamp of sample 0) and monotonic instant mono0_ns (ns, when
    sample 0 is due).

    fs is kept as an exact fraction so stamps stay exact for any run length.
    """

    def __init__(self, fs: float, t0_ns: int, mono0_ns: int):
        if not (isinstance(fs, (int, float)) and math.isfinite(fs) and fs > 0):
            raise ConfigError(f'sample rate fs must be a positive number of Hz, got {fs!r}')
        frac = Fraction(fs).limit_denominator(1_000_000)
        self.fs = float(fs)
        self._num, self._den = frac.numerator, frac.denominator  # fs = num/den
        self.t0_ns = int(t0_ns)
        self.mono0_ns = int(mono0_ns)
        # A period of whole ns (20 kHz: 50 us): a batch's stamps are a first one plus multiples
        # of it, one array addition (stamps_ns; the steps kept per batch size).
        self._period = NS * self._den // self._num if NS * self._den % self._num == 0 else 0
        self._steps: dict = {}

    def offset_ns(self, k: int) -> int:
        """k/fs in integer nanoseconds (rounded half up)."""
        return (2 * k * NS * self._den + self._num) // (2 * self._num)

    def stamp_ns(self, k: int) -> int:
        """Stamp of sample k, ns: t0 + k/fs."""
        return self.t0_ns + self.offset_ns(k)

    def stamps_ns(self, k: int, n: int) -> np.ndarray:
        """Stamps of samples k .. k+n-1, (n,) int64 ns: stamp_ns of each, in one array."""
        p = self._period
        if p and self.t0_ns + p * (k + n) < 2**62:
            steps = self._steps.get(n)
            if steps is None:
                if len(self._steps) > 16:      # catch-up polls of every size: keep a few
                    self._steps.clear()
                steps = self._steps[n] = np.arange(n, dtype=np.int64) * p
            return steps + (self.t0_ns + p * k)
        a, b = 2 * NS * self._den, 2 * self._num
        q, r = divmod(a * k + self._num, b)       # offset_ns(k + i) = q + (r + a*i) // b
        if a * n + r < 2**62 and self.t0_ns + q + NS * n < 2**62:
            return self.t0_ns + q + (r + a * np.arange(n, dtype=np.int64)) // b
        return np.fromiter((self.stamp_ns(k + i) for i in range(n)), dtype=np.int64, count=n)

    def due_ns(self, k: int) -> int:
        """Monotonic instant (ns) from which sample k is due: the first with due_count > k."""
        return self.mono0_ns - (-k * NS * self._den // self._num)   # ceil(k/fs)

    def due_count(self, now_mono_ns: int) -> int:
        """Count the samples due at monotonic time now (ns): samples 0..n-1 are due by then."""
        elapsed = int(now_mono_ns) - self.mono0_ns
        if elapsed < 0:
            return 0
        return elapsed * self._num // (NS * self._den) + 1


class CommandStreamer:
    """
    Streams a voltage signal at fs: clamp to [u_min, u_max], slew limit, loop or stop at the end.

    signal: (N, n_axes) or (N,) volts, one period/record of the excitation; the clamp is applied
    once, the slew limit (V/s) sample by sample from `u_start` (V, the amplifier at rest), also
    across the loop wrap. `start(t0_ns, mono0_ns)` anchors the clock; `poll(now_mono_ns)` returns
    the samples due since the last poll as (stamps (n,) int ns, volts (n, n_axes)); `stop()` pauses
    (the next start re-anchors the clock and resumes the signal where it stopped); `hold()` pauses
    the signal but not the stream: the last command is repeated at every stamp of the same clock
    until `resume()` (an amplifier holds its output; every listener then sees the hold).
    lead: (M,) or (M, n_axes) volts streamed once before the signal (a preamble, e.g. the fade-out
    of plant.signals.preamble); never repeated by the loop.
    """

    def __init__(self, signal, fs: float, loop: bool = True, u_min: float = -200.0,
                 u_max: float = 200.0, slew_rate: float = math.inf, u_start: float = 0.0,
                 max_burst: int = 10_000, lead=None):
        sig = np.asarray(signal, dtype=float)
        if sig.ndim == 1:
            sig = sig[:, None]
        if sig.ndim != 2 or sig.shape[0] < 1 or sig.shape[1] < 1:
            raise ConfigError(f'command signal must be (N,) or (N, axes) with N >= 1, got shape '
                              f'{np.shape(signal)}')
        lead = np.zeros((0, sig.shape[1])) if lead is None else np.asarray(lead, dtype=float)
        if lead.ndim == 1:
            lead = np.repeat(lead[:, None], sig.shape[1], axis=1)
        if lead.ndim != 2 or lead.shape[1] != sig.shape[1]:
            raise ConfigError(f'command preamble must be (M,) or (M, {sig.shape[1]}), got shape '
                              f'{lead.shape}')
        if not (np.all(np.isfinite(sig)) and np.all(np.isfinite(lead))):
            raise ConfigError('command signal contains NaN or infinite values')
        if not u_min < u_max:
            raise ConfigError(f'u_min ({u_min:g} V) must be below u_max ({u_max:g} V)')
        if not slew_rate > 0:
            raise ConfigError(f'slew_rate must be > 0 V/s, got {slew_rate:g}')
        if max_burst < 1:
            raise ConfigError(f'max_burst must be >= 1, got {max_burst}')
        SampleClock(fs, 0, 0)  # validates fs
        self.fs = float(fs)
        self.loop = bool(loop)
        self.signal = np.clip(sig, u_min, u_max)
        self.lead = np.clip(lead, u_min, u_max)
        self.n_axes = sig.shape[1]
        self.max_step = slew_rate / self.fs if math.isfinite(slew_rate) else math.inf
        self.max_burst = int(max_burst)
        self._last = np.full(self.n_axes, float(np.clip(u_start, u_min, u_max)))
        self.position = 0          # next index into the signal (total samples streamed so far)
        self.clock: SampleClock | None = None
        self._k = 0                # next sample index of the current clock segment
        self.holding = False       # hold(): the last command repeated, the signal paused
        self.late_polls = 0        # polls that returned more than one sample (catch-up)
        self.max_batch = 0         # largest number of samples one poll returned
        self.published = 0

    @property
    def running(self) -> bool:
        """Return True between start() and stop()/the end of a non-looping signal."""
        return self.clock is not None and not self.finished

    @property
    def finished(self) -> bool:
        """Return True when a non-looping signal has been streamed entirely."""
        return not self.loop and self.position >= self.lead.shape[0] + self.signal.shape[0]

    def start(self, t0_ns: int, mono0_ns: int) -> None:
        """Anchor a new clock segment: the next sample gets stamp t0_ns and is due at mono0_ns."""
        self.clock = SampleClock(self.fs, t0_ns, mono0_ns)
        self._k = 0

    def stop(self) -> None:
        """Pause; the signal position is kept."""
        self.clock = None
        self.holding = False

    def hold(self) -> None:
        """
        Pause the signal, not the stream: polls repeat the last command on the same clock.

        Nothing to hold before the first sample (the amplifier is at rest): then it is `stop()`.
        """
        if self.clock is None or self.published == 0:
            self.stop()
        else:
            self.holding = True

    def resume(self) -> None:
        """End a hold: the signal goes on where it stopped, on the same clock (no gap)."""
        self.holding = False

    def next_due_ns(self) -> int | None:
        """Monotonic instant (ns) the next sample is due, None when not running."""
        return self.clock.due_ns(self._k) if self.running else None

    def poll(self, now_mono_ns: int) -> tuple[np.ndarray, np.ndarray]:
        """
        Return the samples due at now (monotonic ns) not yet returned.

        (stamps (n,) int ns, volts (n, n_axes)). At most max_burst per call, so the caller stays
        responsive after a long stall; the rest comes out on the next call (nothing is dropped).
        """
        if not self.running:
            return np.empty(0, dtype=np.int64), np.empty((0, self.n_axes))
        return self._take(self._due(now_mono_ns))

    def poll_lists(self, now_mono_ns: int) -> tuple[list, list]:
        """
        Return what poll() returns as lists: ([stamp ns], [[V per axis]]).

        A one-message-per-sample stream's form: its usual single sample (no slew limit, no hold)
        without poll()'s arrays, whose half-dozen small numpy operations per poll cost more at
        2 kHz than the sample's message.
        """
        if not self.running:
            return [], []
        n = self._due(now_mono_ns)
        if n != 1 or self.holding or math.isfinite(self.max_step):
            stamps, volts = self._take(n)
            return stamps.tolist(), volts.tolist()
        pos, m = self.position, self.lead.shape[0]
        row = self.lead[pos] if pos < m else self.signal[(pos - m) % self.signal.shape[0]]
        self._last = row            # a row of the clamped signal, never written
        stamp = self.clock.stamp_ns(self._k)
        self._k += 1
        self.position += 1
        self.published += 1
        self.max_batch = max(self.max_batch, 1)
        return [stamp], [row.tolist()]

    def take_run(self, now_mono_ns: int, n: int) -> tuple[np.ndarray, np.ndarray] | None:
        """
        Return what poll() returns when exactly n samples are due, in one slice of the signal.

        None otherwise (not running, holding, a slew limit, the preamble, the loop's wrap, the
        end of a signal that does not loop, more or fewer than n due): then poll() returns them.
        A batched stream's usual wake (one message's samples) without poll()'s general case.
        The volts are a view of the clamped signal, never written.
        """
        clock = self.clock
        if clock is None or self.holding or self.max_step != math.inf or n > self.max_burst:
            return None
        start = self.position - self.lead.shape[0]
        size = self.signal.shape[0]
        if start < 0 or clock.due_count(now_mono_ns) - self._k != n:
            return None
        if self.loop:
            start %= size
        if start + n >= size:       # the wrap, or the end (finished: poll says so)
            return None
        stamps = clock.stamps_ns(self._k, n)
        volts = self.signal[start:start + n]
        self._last = volts[-1]
        self._count(n)
        return stamps, volts

    def _due(self, now_mono_ns: int) -> int:
        """Count the samples a poll at now returns: due, not returned yet, at most max_burst."""
        n = self.clock.due_count(now_mono_ns) - self._k
        if not self.loop and not self.holding:
            n = min(n, self.lead.shape[0] + self.signal.shape[0] - self.position)
        return max(0, min(n, self.max_burst))

    def _take(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        """Return the next n samples (stamps, volts) and count them (poll)."""
        m = self.lead.shape[0]
        stamps = self.clock.stamps_ns(self._k, n)
        if self.holding:
            self._k += n
            self.published += n
            return stamps, np.tile(self._last, (n, 1))
        start = self.position - m
        if start >= 0 and start % self.signal.shape[0] + n <= self.signal.shape[0]:
            start %= self.signal.shape[0]          # one stretch of the signal: a slice
            volts = self.signal[start:start + n].copy()
        else:
            pos = self.position + np.arange(n)
            volts = self.signal[(pos - m) % self.signal.shape[0]]
            if n and pos[0] < m:            # the preamble first, once
                volts[pos < m] = self.lead[pos[pos < m]]
        volts = self._slew(volts)
        self._count(n)
        return stamps, volts

    def _count(self, n: int) -> None:
        """Count n samples of the signal returned by a poll (take_run's and _take's)."""
        self._k += n
        self.position += n
        self.published += n
        if n > 1:
            self.late_polls += 1
        if n > self.max_batch:
            self.max_batch = n

    def _slew(self, u: np.ndarray) -> np.ndarray:
        if not math.isfinite(self.max_step) or u.shape[0] == 0:
            if u.shape[0]:
                self._last = u[-1].copy()
            return u
        out = np.empty_like(u)
        last = self._last
        for i in range(u.shape[0]):
            last = last + np.clip(u[i] - last, -self.max_step, self.max_step)
            out[i] = last
        self._last = last.copy()
        return out


def make_signal(kind: str, fs: float, seconds: float, amplitude: float, offset: float = 0.0,
                seed: int = 0, n_axes: int = 1, **options) -> np.ndarray:
    """
    (N, n_axes) volts from plant.signals.generate, axis i with seed + i.

    Options not used by `kind` are ignored (a node declares them all); None values mean "default".
    The protocol's slow sine is the same on every seed: on several axes axis i's protocol is
    rotated by i / n_axes of a cycle (`shift`), so that no section drives two axes alike and
    each axis's effect on the others can be told apart (identification of the coupling).
    """
    from piezo_narx_ros.plant.signals import COMMON, OPTIONS, generate
    if kind not in OPTIONS:
        raise ConfigError(f'unknown signal kind {kind!r}; choose one of {", ".join(OPTIONS)}')
    allowed = set(OPTIONS[kind]) | set(COMMON)
    opts = {k: v for k, v in options.items() if k in allowed and v is not None}
    cols = [generate(kind, fs, seconds, amplitude, offset, seed + i,
                     **({'shift': i / n_axes} if kind == 'protocol' and n_axes > 1 else {}),
                     **opts)
            for i in range(n_axes)]
    return np.stack(cols, axis=1)
