"""
A fake real-time target: a UDP server that answers command datagrams with the simulated plant.

Each command datagram advances one PiezoCantilever per axis by one step (so the stream is
deterministic for a seed, whatever the wall-clock timing) and is answered with the measured
deflection (m) and the volts the plant applied. Like simulator_node, a gap in the command stamps
(commands lost upstream) is bridged by stepping the plant with the held voltage, so that driver +
fake rig and simulator_node give the same stream for the same commands; watchdog ramp datagrams are
stepped once each and end the gap bridging until the next command. A ping datagram is answered
with the last measurement without stepping anything. A repeated datagram (same
sequence number and volts as the previous one) is answered again from a cache without stepping
the plant, as an idempotent target would. Malformed datagrams are counted and dropped. It speaks
both protocol versions and answers each datagram in its own version: a version-2 command steps
the plant once per sample (the same rules per sample) and gets one version-2 reply.

    fake_rig --port 50000 --seed 0
"""
from __future__ import annotations

import argparse
import signal
import socket
import sys
import threading

from piezo_narx_ros.errors import ConfigError, PiezoNarxError
from piezo_narx_ros.rig import protocol

_MAX_DATAGRAM = 65535


class FakeRig:
    """UDP server on (host, port) wrapping n_axes PiezoCantilever plants (axis i uses seed + i)."""

    def __init__(self, host: str = '127.0.0.1', port: int = 50000, seed: int = 0,
                 fs: float = 2000.0, n_axes: int = 1, plant_config: str | None = None,
                 max_fill: int = 20000):
        from piezo_narx_ros.plant import PiezoCantilever, load_plant_params  # heavy: numba kernels

        if not 1 <= n_axes <= protocol.MAX_AXES:
            raise ConfigError(f'axes must be 1..{protocol.MAX_AXES}, got {n_axes}')
        if not fs > 0:
            raise ConfigError(f'fs must be > 0 Hz, got {fs}')
        params = load_plant_params(plant_config)
        self.plants = [PiezoCantilever(params, fs=fs, seed=seed + i) for i in range(n_axes)]
        for plant in self.plants:
            # Pay the JIT compilation now, not on the first datagram (it would stall the replies).
            plant.step(0.0)
            plant.reset()
        self.n_axes = n_axes
        self.period_ns = 1e9 / fs
        self.max_fill = max_fill
        self._last_stamp: int | None = None
        self._held = [0.0] * n_axes
        self.filled = 0
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        # Room for a burst of a few thousand datagrams if this process is descheduled for a while.
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 21)
        try:
            self.sock.bind((host, port))
        except OSError as exc:
            self.sock.close()
            raise ConfigError(f'cannot bind UDP {host}:{port}: {exc.strerror or exc}') from None
        self.sock.settimeout(0.1)
        self.commands = 0
        self.malformed = 0
        self.repeats = 0
        self.pings = 0
        self._position = (0.0,) * n_axes   # last measured m and applied V, for ping replies
        self._applied = (0.0,) * n_axes
        self._last: tuple[int, tuple, bytes] | None = None  # (seq, volts, reply)
        self._stop = threading.Event()

    @property
    def address(self) -> tuple[str, int]:
        """(host, port) actually bound."""
        return self.sock.getsockname()

    def handle(self, data: bytes) -> bytes | None:
        """Return the reply datagram for one received datagram, or None when it is malformed."""
        if protocol.datagram_version(data) == protocol.VERSION_BATCH:
            return self._handle_batch(data)
        try:
            cmd = protocol.unpack_command(data, self.n_axes)
        except protocol.DatagramError:
            self.malformed += 1
            return None
        if cmd.flags & protocol.FLAG_PING:
            # Report the present state without applying anything or advancing the plant.
            self.pings += 1
            return protocol.pack_reply(protocol.Reply(cmd.seq, cmd.stamp_ns, self._position,
                                                      self._applied))
        if self._last is not None and self._last[0] == cmd.seq and self._last[1] == cmd.volts:
            self.repeats += 1
            return self._last[2]
        if cmd.flags & protocol.FLAG_RAMP:
            self._last_stamp = None
        else:
            self._bridge_gap(cmd.stamp_ns)
            self._last_stamp = cmd.stamp_ns
        self._step(cmd.volts)
        reply = protocol.pack_reply(protocol.Reply(cmd.seq, cmd.stamp_ns, self._position,
                                                   self._applied))
        self.commands += 1
        self._last = (cmd.seq, cmd.volts, reply)
        return reply

    def _step(self, volts) -> None:
        """Apply one sample's volts: step every plant once, keep the measurement."""
        self._held = list(volts)
        position, applied = [], []
        for plant, v in zip(self.plants, volts):
            y_meas, _y_true, u_applied = plant.step(v)
            position.append(float(y_meas))
            applied.append(float(u_applied))
        self._position, self._applied = tuple(position), tuple(applied)

    def _handle_batch(self, data: bytes) -> bytes | None:
        """Answer a version-2 datagram: each sample as a version-1 command, one reply."""
        try:
            cmd = protocol.unpack_command_batch(data, self.n_axes)
        except protocol.DatagramError:
            self.malformed += 1
            return None
        if cmd.flags & protocol.FLAG_PING:
            self.pings += 1
            return protocol.pack_reply_batch(protocol.ReplyBatch(
                cmd.seq, cmd.stamps_ns[:1], (self._position,), (self._applied,)))
        if self._last is not None and self._last[0] == cmd.seq and self._last[1] == cmd.volts:
            self.repeats += 1
            return self._last[2]
        positions, applied = [], []
        for stamp, volts in zip(cmd.stamps_ns, cmd.volts):
            if cmd.flags & protocol.FLAG_RAMP:
                self._last_stamp = None
            else:
                self._bridge_gap(stamp)
                self._last_stamp = stamp
            self._step(volts)
            positions.append(self._position)
            applied.append(self._applied)
            self.commands += 1
        reply = protocol.pack_reply_batch(protocol.ReplyBatch(
            cmd.seq, cmd.stamps_ns, tuple(positions), tuple(applied)))
        self._last = (cmd.seq, cmd.volts, reply)
        return reply

    def _bridge_gap(self, stamp_ns: int) -> None:
        if self._last_stamp is None or stamp_ns <= self._last_stamp:
            return
        missing = int(round((stamp_ns - self._last_stamp) / self.period_ns)) - 1
        n = min(missing, self.max_fill)
        if n <= 0:
            return
        self.filled += n
        for plant, held in zip(self.plants, self._held):
            for _ in range(n):
                plant.step(held)

    def serve(self) -> None:
        """Answer datagrams until stop() is called."""
        while not self._stop.is_set():
            try:
                data, addr = self.sock.recvfrom(_MAX_DATAGRAM)
            except socket.timeout:
                continue
            except OSError:
                if self._stop.is_set():
                    break
                continue
            reply = self.handle(data)
            if reply is not None:
                try:
                    self.sock.sendto(reply, addr)
                except OSError:
                    pass  # the driver went away; keep serving

    def start(self) -> threading.Thread:
        """Serve on a daemon thread (for tests and embedding); returns the thread."""
        thread = threading.Thread(target=self.serve, name='fake-rig', daemon=True)
        thread.start()
        return thread

    def stop(self) -> None:
        """Make serve() return and close the socket."""
        self._stop.set()

    def close(self) -> None:
        """Close the socket (after serve() has returned)."""
        self.sock.close()


def build_parser() -> argparse.ArgumentParser:
    """Command-line options of fake_rig."""
    p = argparse.ArgumentParser(prog='fake_rig', description=__doc__.strip().split('\n\n')[0])
    p.add_argument('--host', default='127.0.0.1', help='address to listen on (default 127.0.0.1)')
    p.add_argument('--port', type=int, default=50000, help='UDP port to listen on (default 50000)')
    p.add_argument('--seed', type=int, default=0, help='plant noise seed (axis i uses seed+i)')
    p.add_argument('--fs', type=float, default=2000.0, help='plant sample rate, Hz (default 2000)')
    p.add_argument('--axes', type=int, default=1, help='number of axes (default 1)')
    p.add_argument('--plant-config', default=None, help='plant YAML (default config/plant.yaml)')
    p.add_argument('--max-fill', type=int, default=20000,
                   help='longest stamp gap (samples) bridged by holding the voltage '
                   '(default 20000)')
    return p


def main(argv: list[str] | None = None) -> None:
    """Serve until SIGINT/SIGTERM (console script); a bad option or busy port exits 2, one line."""
    args = build_parser().parse_args(argv)
    try:
        if not 0 <= args.port <= 65535:
            raise ConfigError(f'port must be 0..65535, got {args.port}')
        rig = FakeRig(args.host, args.port, args.seed, args.fs, args.axes, args.plant_config,
                      args.max_fill)
    except (PiezoNarxError, FileNotFoundError) as exc:
        print(f'fake_rig: error: {exc}', file=sys.stderr)
        sys.exit(2)

    def stop(_signum, _frame):
        rig.stop()

    signal.signal(signal.SIGINT, stop)
    signal.signal(signal.SIGTERM, stop)
    host, port = rig.address
    print(f'fake_rig: listening on {host}:{port} (udp), seed {args.seed}, fs {args.fs:g} Hz, '
          f'{args.axes} axis(es)', flush=True)
    rig.serve()
    rig.close()
    print(f'fake_rig: stopped after {rig.commands} commands, {rig.malformed} malformed datagrams',
          flush=True)
    sys.exit(0)


if __name__ == '__main__':
    main()
