"""
ROS-free logic of driver_node: limits, watchdog ramp, datagrams out, replies matched back.

RigDriver is driven by three calls, each given the monotonic time `now` (s) so tests control time:
  command(volts, stamp_ns, now)  a command sample arrived: limit it and send it to the target;
  receive(data, now)             a datagram arrived from the target: the Sample to publish, or
                                 None;
  tick(now)                      periodic: expire unanswered commands, run the watchdog ramp.
command_batch(volts, stamps_ns, now) and receive_batch(data, now) do the same for several
samples: in protocol version 2 one datagram carries them all (docs/driver.md).
Outgoing datagrams go through the `send(bytes)` callable (a UDP socket in the node, a list in
tests).
The three calls may come from different threads (the node receives on its own thread), so each one
holds a lock.
"""
from __future__ import annotations

import math
import threading
from collections import OrderedDict, deque
from dataclasses import dataclass
from typing import Callable

import numpy as np

from piezo_narx_ros.command.stamps import RateMonitor
from piezo_narx_ros.errors import ConfigError, DataError
from piezo_narx_ros.rig import protocol
from piezo_narx_ros.rig.limits import SlewLimiter, Watchdog

DIAG_OK, DIAG_WARN, DIAG_ERROR = 0, 1, 2  # diagnostic_msgs/DiagnosticStatus levels

STATE_IDLE = 'idle'            # no command yet; output at rest (0 V), only pings sent
STATE_STREAMING = 'streaming'  # commands arriving
STATE_RAMPING = 'ramping'      # watchdog tripped: output slewing to 0 V
STATE_PARKED = 'parked'        # watchdog ramp finished: output held at 0 V


@dataclass(frozen=True)
class DriverConfig:
    """Driver limits and timing; every field in SI units."""

    n_axes: int = 1
    v_min: float = -200.0          # V, lowest voltage ever sent
    v_max: float = 200.0           # V, highest voltage ever sent
    max_slew_rate: float = 2.0e5   # V/s, largest rate of change ever sent
    sample_rate: float = 2000.0    # Hz, nominal command rate; slew step max_slew_rate/sample_rate
    watchdog_timeout: float = 0.1  # s without a command before the ramp to 0 V starts
    ramp_rate: float = 1000.0      # Hz, datagrams per second while ramping
    reply_timeout: float = 0.01    # s after which an unanswered command counts as a reply timeout
    protocol_version: int = 1      # datagrams sent: 1 (one sample each) or 2 (several samples)

    def validate(self) -> None:
        """Raise ConfigError naming the first bad field."""
        if not 1 <= self.n_axes <= protocol.MAX_AXES:
            raise ConfigError(f'n_axes must be 1..{protocol.MAX_AXES}, got {self.n_axes}')
        for name in ('max_slew_rate', 'sample_rate', 'watchdog_timeout', 'ramp_rate',
                     'reply_timeout'):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ConfigError(f'{name} must be a positive finite number, got {value}')
        if self.protocol_version not in protocol.VERSIONS:
            raise ConfigError(f'protocol_version must be one of {list(protocol.VERSIONS)}, got '
                              f'{self.protocol_version}')
        # SlewLimiter checks the voltage window.
        SlewLimiter(self.v_min, self.v_max, self.max_slew_rate, self.n_axes)


@dataclass(frozen=True)
class Sample:
    """One measured sample to publish on deflection: the stamp of the command it answers."""

    seq: int
    stamp_ns: int
    position_m: tuple[float, ...]
    applied_volts: tuple[float, ...]
    late: bool
    target_fault: bool


@dataclass
class _Pending:
    sent_at: float               # monotonic s
    publish: bool                # False for watchdog ramp datagrams (no command stamp to answer)
    stamps: tuple[int, ...]      # ns, the stamps this datagram carried: a reply must echo them


class _BoundedSeqMap:
    """The last `size` sequence numbers seen with a value each (old ones forgotten)."""

    def __init__(self, size: int = 4096):
        self._items: OrderedDict[int, object] = OrderedDict()
        self._size = size

    def add(self, seq: int, value=None) -> None:
        self._items[seq] = value
        self._items.move_to_end(seq)
        while len(self._items) > self._size:
            self._items.popitem(last=False)

    def discard(self, seq: int) -> None:
        self._items.pop(seq, None)

    def get(self, seq: int):
        return self._items.get(seq)

    def __contains__(self, seq: int) -> bool:
        return seq in self._items


COUNTERS = (
    'commands',            # valid commands received
    'commands_rejected',   # commands refused (wrong axis count, NaN/inf)
    'commands_clamped',    # commands changed by the voltage window
    'commands_slewed',     # commands changed by the slew limit
    'commands_blocked',    # commands ignored while the output is stopped (deactivated, e-stop)
    'datagrams_sent',
    'send_errors',         # the socket refused a datagram (target unreachable, ...)
    'replies',             # replies matched to a command within reply_timeout
    'replies_late',        # replies that arrived after reply_timeout
    'replies_duplicate',   # a second reply to the same command
    'replies_unknown',     # a reply to a command never sent (or long forgotten)
    'replies_mismatched',  # a reply whose stamps are not those of the command its seq names
    'replies_malformed',   # datagrams that failed validation (bad magic, size, ...)
    'reply_timeouts',      # commands unanswered after reply_timeout
    'target_faults',       # replies carrying the target's fault flag
    'watchdog_trips',
    'samples_answered',    # command samples answered (one per v1 reply, several per v2 reply)
)


class RigDriver:
    """Enforces limits, runs the watchdog and matches replies to commands by sequence number."""

    def __init__(self, config: DriverConfig, send: Callable[[bytes], object], seq0: int = 1):
        config.validate()
        self.config = config
        self._send_bytes = send
        self.limiter = SlewLimiter(config.v_min, config.v_max, config.max_slew_rate, config.n_axes)
        self.watchdog = Watchdog(config.watchdog_timeout)
        # The commands' stamp rate against sample_rate: only reported (an ERROR while they
        # differ); the rig keeps being driven, since refusing commands would trip the watchdog.
        self.rate = RateMonitor(1e9 / config.sample_rate)
        self._last_stamp: int | None = None
        self.state = STATE_IDLE
        self.counts = dict.fromkeys(COUNTERS, 0)
        self._seq = seq0 % protocol.SEQ_MODULO
        self._pending: OrderedDict[int, _Pending] = OrderedDict()
        self._answered = _BoundedSeqMap()
        self._expired = _BoundedSeqMap()   # seq -> its _Pending, for a late reply
        self._ignored = _BoundedSeqMap()   # negotiation pings left unanswered on purpose
        self._foreign_reported = 0
        self._last_send: float | None = None
        self._last_reply: float | None = None
        self._latencies: deque[float] = deque(maxlen=2000)
        self._last_position: tuple[float, ...] = (math.nan,) * config.n_axes
        self._report_counts = dict(self.counts)
        self._stopping = False
        self._lock = threading.Lock()
        self.version = config.protocol_version
        self.versions_seen: set[int] = set()   # versions of the replies received (negotiation)

    # ----------------------------------------------------------------------------- commands
    def command(self, volts, stamp_ns: int, now: float) -> np.ndarray:
        """
        Limit one command sample (V per axis) and send it; returns the volts sent.

        Raises DataError (and counts it) for a wrong axis count or a non-finite value; the caller
        logs it and carries on.
        """
        v = np.asarray(volts, dtype=float).ravel()
        with self._lock:
            if self._stopping:
                self.counts['commands_blocked'] += 1
                return self.limiter.output.copy()
            out = self._limit(v, int(stamp_ns), now)
            self._send(out, int(stamp_ns), now, flags=0, publish=True)
            return out

    def command_batch(self, volts, stamps_ns, now: float) -> np.ndarray:
        """
        Limit several command samples ((n, n_axes) V, stamps (n,) ns) and send them.

        Each sample goes through the same checks and limits as in `command`, in order; a refused
        sample (wrong axis count, NaN/inf) is counted and left out, the others are sent. Protocol
        version 2: one datagram per MAX_SAMPLES samples; version 1: one datagram per sample.
        Returns the volts sent, (m, n_axes).
        """
        rows = np.asarray(volts, dtype=float).reshape(len(stamps_ns), -1)
        with self._lock:
            if self._stopping:
                self.counts['commands_blocked'] += len(rows)
                return np.empty((0, self.config.n_axes))
            sent, stamps = [], []
            for row, stamp in zip(rows, stamps_ns):
                try:
                    sent.append(self._limit(row, int(stamp), now))
                except DataError:
                    continue          # counted in commands_rejected
                stamps.append(int(stamp))
            if self.version == protocol.VERSION_BATCH:
                for k in range(0, len(sent), protocol.MAX_SAMPLES):
                    self._send_batch(sent[k:k + protocol.MAX_SAMPLES],
                                     stamps[k:k + protocol.MAX_SAMPLES], now)
            else:
                for out, stamp in zip(sent, stamps):
                    self._send(out, stamp, now, flags=0, publish=True)
            return np.array(sent).reshape(-1, self.config.n_axes)

    def _limit(self, v: np.ndarray, stamp_ns: int, now: float) -> np.ndarray:
        """Check and limit one sample (lock held); DataError (counted) when it is refused."""
        if v.size != self.config.n_axes:
            self.counts['commands_rejected'] += 1
            raise DataError(f'command has {v.size} values, the driver drives '
                            f'{self.config.n_axes} axes')
        if not np.all(np.isfinite(v)):
            self.counts['commands_rejected'] += 1
            raise DataError(f'command volts {v.tolist()} are not finite')
        out, clamped, slewed = self.limiter.apply(v, 1.0 / self.config.sample_rate)
        self.counts['commands'] += 1
        self.counts['commands_clamped'] += clamped
        self.counts['commands_slewed'] += slewed
        self.watchdog.feed(now)
        self.state = STATE_STREAMING
        self._observe_stamp(stamp_ns)
        return out

    def _observe_stamp(self, t_ns: int) -> None:
        """Feed the rate check; a stamp going back or jumping far starts a new stream."""
        last, self._last_stamp = self._last_stamp, t_ns
        if last is not None and not 0 < t_ns - last <= 100 * self.rate.period_ns:
            self.rate.reset()
        self.rate.observe(t_ns)

    @property
    def connected(self) -> bool:
        """Return True once the target has answered any datagram (a ping, typically)."""
        return self._last_reply is not None

    def ping(self, now: float, stamp_ns: int = 0, version: int | None = None) -> None:
        """
        Ask the target for its current measurement without applying anything.

        A start-up check that it is there; the reply is accounted like any other but not published.
        `version`: the datagram version of this ping (default: the driver's); a target answers in
        the version it understands, so pings of both versions negotiate it (`versions_seen`).
        """
        with self._lock:
            self._send(self.limiter.output.copy(), int(stamp_ns), now, flags=protocol.FLAG_PING,
                       publish=False, version=version)

    def use_version(self, version: int) -> None:
        """Send datagrams of protocol `version` (1 or 2) from now on."""
        if version not in protocol.VERSIONS:
            raise ConfigError(f'protocol version must be one of {list(protocol.VERSIONS)}, got '
                              f'{version}')
        with self._lock:
            self.version = version
            # The pings still pending (the version the target ignores) will never be answered:
            # not reply timeouts; an answer that still comes is ignored too.
            for seq in [s for s, pending in self._pending.items() if not pending.publish]:
                del self._pending[seq]
                self._ignored.add(seq)

    def reject(self) -> None:
        """Count a command message refused before it reached command() (e.g. axis missing)."""
        with self._lock:
            self.counts['commands_rejected'] += 1

    def stop_output(self) -> None:
        """
        Ramp to 0 V from now on, as if the watchdog had tripped.

        tick() ramps down and commands are ignored (counted in commands_blocked) until
        enable_output(). `parked` tells when the output has reached 0 V.
        """
        with self._lock:
            self._stopping = True

    def enable_output(self) -> None:
        """
        Undo stop_output().

        Commands are applied again (from the output where it is, within the slew limit).
        """
        with self._lock:
            self._stopping = False

    @property
    def output_enabled(self) -> bool:
        """Return False after stop_output() until enable_output()."""
        return not self._stopping

    @property
    def parked(self) -> bool:
        """Return True when the output is at 0 V on every axis."""
        return not np.any(self.limiter.output)

    def tick(self, now: float, stamp_ns: int = 0) -> None:
        """
        Expire unanswered commands; when the watchdog has tripped, send the next ramp step.

        stamp_ns is put in ramp datagrams (there is no command stamp to copy).
        """
        with self._lock:
            self._expire(now)
            if not (self.watchdog.expired(now) or self._stopping):
                return
            self.counts['watchdog_trips'] = self.watchdog.trips
            if self.state in (STATE_PARKED, STATE_IDLE) and self.parked:
                return
            period = 1.0 / self.config.ramp_rate
            if self.state != STATE_RAMPING:
                self.state = STATE_RAMPING
                elapsed = period
            elif self._last_send is not None and now - self._last_send < 0.75 * period:
                # About ramp_rate datagrams/s; the margin keeps a slightly early timer tick from
                # being skipped (which would halve the ramp speed).
                return
            else:
                elapsed = now - self._last_send if self._last_send is not None else period
            # Never more than one period's worth of slew per datagram, even after a late tick.
            out = self.limiter.toward(0.0, min(elapsed, period))
            self._send(out, int(stamp_ns), now, flags=protocol.FLAG_RAMP, publish=False)
            if not np.any(out):
                self.state = STATE_PARKED

    def _send(self, volts: np.ndarray, stamp_ns: int, now: float, flags: int,
              publish: bool, version: int | None = None) -> None:
        seq = self._seq
        if (version or self.version) == protocol.VERSION_BATCH:
            data = protocol.pack_command_batch(protocol.CommandBatch(
                seq, (stamp_ns,), (tuple(volts.tolist()),), flags))
        else:
            data = protocol.pack_command(protocol.Command(seq, stamp_ns, tuple(volts.tolist()),
                                                          flags))
        self._transmit(seq, data, now, publish, (stamp_ns,))

    def _send_batch(self, volts: list, stamps: list, now: float) -> None:
        if not stamps:
            return
        seq = self._seq
        data = protocol.pack_command_batch(protocol.CommandBatch(
            seq, tuple(stamps), tuple(tuple(v.tolist()) for v in volts)))
        self._transmit(seq, data, now, True, tuple(stamps))

    def _transmit(self, seq: int, data: bytes, now: float, publish: bool,
                  stamps: tuple[int, ...]) -> None:
        self._seq = (self._seq + 1) % protocol.SEQ_MODULO
        self._last_send = now
        self._answered.discard(seq)  # after a wrap-around the number is new again
        self._expired.discard(seq)
        try:
            self._send_bytes(data)
        except OSError:
            self.counts['send_errors'] += 1
            return
        self.counts['datagrams_sent'] += 1
        self._pending[seq] = _Pending(now, publish, stamps)

    # ------------------------------------------------------------------------------ replies
    def receive(self, data: bytes, now: float) -> Sample | None:
        """
        Account for one datagram from the target; the Sample to publish, or None.

        A reply is published only when it answers a command sample this driver sent: its seq is
        one sent and not answered yet, and it echoes that command's stamp (published with the
        stamp the driver sent, never one the target made up). Replies are published even when
        late (the measurement and its stamp are still right); duplicates, unknown sequence
        numbers, mismatched stamps, ramp replies and malformed datagrams are not.
        """
        with self._lock:
            try:
                reply = protocol.unpack_reply(data, self.config.n_axes)
            except protocol.DatagramError:
                self.counts['replies_malformed'] += 1
                return None
            got = self._account(reply.seq, (reply.stamp_ns,), reply.flags, reply.position_m,
                                now)
            if got is None:
                return None
            stamps, late, fault = got
            return Sample(reply.seq, stamps[0], tuple(reply.position_m),
                          tuple(reply.applied_volts), late, fault)

    def receive_batch(self, data: bytes, now: float) -> list[Sample]:
        """
        Account for one datagram of either version; the Samples to publish, in datagram order.

        A version-1 reply gives at most one (as `receive`), a version-2 reply one per sample of
        the command it answers (it must echo exactly that command's stamps), all sharing the
        datagram's seq, lateness and fault flag.
        """
        if protocol.datagram_version(data) != protocol.VERSION_BATCH:
            sample = self.receive(data, now)
            return [] if sample is None else [sample]
        with self._lock:
            try:
                reply = protocol.unpack_reply_batch(data, self.config.n_axes)
            except protocol.DatagramError:
                self.counts['replies_malformed'] += 1
                return []
            got = self._account(reply.seq, tuple(reply.stamps_ns), reply.flags,
                                reply.position_m[-1], now, protocol.VERSION_BATCH)
            if got is None:
                return []
            stamps, late, fault = got
            return [Sample(reply.seq, t, tuple(pos), tuple(app), late, fault) for t, pos, app in
                    zip(stamps, reply.position_m, reply.applied_volts)]

    def _account(self, seq: int, stamps: tuple[int, ...], flags: int, position, now: float,
                 version: int = protocol.VERSION) -> tuple[tuple[int, ...], bool, bool] | None:
        """
        Match a valid reply to its command (lock held): (stamps, late, target fault) to publish.

        None when it is not to be published (duplicate, unknown seq, stamps other than the
        command's, ping or ramp reply). A reply with the right seq but the wrong stamps leaves
        the command waiting for its real answer: it is counted, not paired.
        """
        if seq in self._ignored:
            self._ignored.discard(seq)
            return None
        pending = self._pending.get(seq)
        if pending is not None:
            if stamps != pending.stamps:
                self.counts['replies_mismatched'] += 1
                return None
            del self._pending[seq]
            late = now - pending.sent_at > self.config.reply_timeout
            if late:
                # Not expired by tick() yet, but late all the same.
                self.counts['reply_timeouts'] += 1
                self.counts['replies_late'] += 1
            else:
                self.counts['replies'] += 1
                self._latencies.append(now - pending.sent_at)
            publish = pending.publish
        elif seq in self._expired:
            expired = self._expired.get(seq)
            if stamps != expired.stamps:
                self.counts['replies_mismatched'] += 1
                return None
            self._expired.discard(seq)
            late, publish = True, expired.publish
            self.counts['replies_late'] += 1
        elif seq in self._answered:
            self.counts['replies_duplicate'] += 1
            return None
        else:
            self.counts['replies_unknown'] += 1
            return None
        self.versions_seen.add(version)
        self._answered.add(seq)
        self._last_reply = now
        self._last_position = tuple(position)
        fault = bool(flags & protocol.FLAG_TARGET_FAULT)
        self.counts['target_faults'] += fault
        if not publish:
            return None
        self.counts['samples_answered'] += len(stamps)
        return stamps, late, fault

    def _expire(self, now: float) -> None:
        limit = now - self.config.reply_timeout
        # Pending is in send order, so the oldest are first.
        while self._pending:
            seq, pending = next(iter(self._pending.items()))
            if pending.sent_at >= limit:
                break
            del self._pending[seq]
            self._expired.add(seq, pending)
            self.counts['reply_timeouts'] += 1

    # -------------------------------------------------------------------------- diagnostics
    def report(self, now: float, foreign: int = 0) -> tuple[int, str, dict]:
        """
        Return (level, one-line message, {key: value}) for /diagnostics, since the last call.

        foreign: datagrams received so far from an address other than the target's (the socket
        drops them; counted by RigClient), a WARN while more arrive.
        """
        with self._lock:
            self._expire(now)
            c = self.counts
            delta = {k: c[k] - self._report_counts[k] for k in c}
            self._report_counts = dict(c)
            values = dict(c)
            values.update(state=self.state, output_volts=self._fmt_axes(self.limiter.output),
                          last_position_m=self._fmt_axes(self._last_position),
                          pending_replies=len(self._pending))
            if self._latencies:
                lat = np.asarray(self._latencies)
                values.update(reply_latency_p50_s=float(np.median(lat)),
                              reply_latency_max_s=float(lat.max()))
            problems = []
            level = DIAG_OK
            if delta['reply_timeouts']:
                answered = delta['replies'] + delta['replies_late']
                if answered == 0:
                    level = DIAG_ERROR
                    problems.append(f'target not replying: {delta["reply_timeouts"]} reply '
                                    f'timeouts (> {self.config.reply_timeout:g} s)')
                else:
                    level = max(level, DIAG_WARN)
                    problems.append(f'reply timeout: {delta["reply_timeouts"]} replies later '
                                    f'than {self.config.reply_timeout:g} s or lost')
            if delta['send_errors']:
                level = DIAG_ERROR
                problems.append(f"{delta['send_errors']} datagrams could not be sent")
            if delta['target_faults']:
                level = DIAG_ERROR
                problems.append(f"target reports a fault in {delta['target_faults']} replies")
            if self.state == STATE_RAMPING:
                level = max(level, DIAG_WARN)
                problems.append('watchdog: no command, ramping output to 0 V')
            if self.rate.off and self.state == STATE_STREAMING:
                level = DIAG_ERROR
                problems.append(f'{self.rate.describe("command")}: the rig samples at '
                                'sample_rate; set it to the stream rate or stream at its own')
            if self.rate.ratio == self.rate.ratio:
                values['stream_rate_hz'] = self.config.sample_rate / self.rate.ratio
            for key, what in (('replies_malformed', 'malformed datagrams'),
                              ('replies_duplicate', 'duplicate replies'),
                              ('replies_unknown', 'replies to unknown commands'),
                              ('replies_mismatched', 'replies whose stamps are not those of '
                               'their command (not published: a spoofed or confused target)'),
                              ('commands_rejected', 'commands rejected')):
                if delta[key]:
                    level = max(level, DIAG_WARN)
                    problems.append(f'{delta[key]} {what}')
            new_foreign, self._foreign_reported = foreign - self._foreign_reported, foreign
            values['datagrams_foreign'] = foreign
            if new_foreign > 0:
                level = max(level, DIAG_WARN)
                problems.append(f'{new_foreign} datagrams from an address other than the '
                                "target's (ignored)")
            message = '; '.join(problems) if problems else f'{self.state}'
            return level, message, values

    @staticmethod
    def _fmt_axes(values) -> str:
        return ' '.join(f'{float(v):.6g}' for v in values)
