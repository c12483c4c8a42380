"""UDP transport of the driver: command datagrams out, replies received on a background thread."""
from __future__ import annotations

import socket
import threading
import time
from typing import Callable

from piezo_narx_ros.errors import ConfigError

_MAX_DATAGRAM = 65535


class RigClient:
    """
    A UDP socket bound to (local_host, local_port) that talks to (target_host, target_port).

    `send(data)` may raise OSError (the driver counts it). `start(on_datagram)` runs a thread that
    calls on_datagram(data, t_monotonic_s) for every datagram received from the target's address
    and port; datagrams from anywhere else are ignored (counted in `foreign`). The socket binds
    loopback unless told otherwise, so nothing off the machine can reach it by default.
    """

    def __init__(self, target_host: str, target_port: int, local_port: int = 0,
                 local_host: str = '127.0.0.1'):
        self.target = resolve_target(target_host, target_port)
        check_reachable(local_host, self.target[0])
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        # Room for a burst of replies while the receive thread waits for the GIL.
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 21)
        try:
            self.sock.bind((local_host, local_port))
        except OSError as exc:
            self.sock.close()
            raise ConfigError(f'cannot bind UDP port {local_host}:{local_port}: '
                              f'{exc.strerror or exc}') from None
        # A short timeout lets the receive thread notice close() without a wake-up datagram.
        self.sock.settimeout(0.1)
        self.foreign = 0
        self.callback_errors = 0
        self.last_error = ''
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()

    @property
    def local_port(self) -> int:
        """Return the UDP port actually bound (useful when local_port=0 picked a free one)."""
        return self.sock.getsockname()[1]

    def send(self, data: bytes) -> None:
        """Send one datagram to the target (raises OSError on failure)."""
        self.sock.sendto(data, self.target)

    def start(self, on_datagram: Callable[[bytes, float], object]) -> None:
        """Start the receive thread (daemon; stopped by close())."""
        self._thread = threading.Thread(target=self._run, args=(on_datagram,), name='rig-rx',
                                        daemon=True)
        self._thread.start()

    def _run(self, on_datagram) -> None:
        target_ip, target_port = self.target
        while not self._stop.is_set():
            try:
                data, addr = self.sock.recvfrom(_MAX_DATAGRAM)
            except socket.timeout:
                continue
            except OSError:
                # ICMP port-unreachable from an earlier send surfaces here on Linux; the driver's
                # reply timeouts already report a silent target, so just keep listening.
                if self._stop.is_set():
                    break
                time.sleep(0.001)
                continue
            if addr[1] != target_port or (addr[0] != target_ip
                                          and not _both_loopback(addr[0], target_ip)):
                self.foreign += 1
                continue
            try:
                on_datagram(data, time.monotonic())
            except Exception as exc:  # noqa: BLE001 - one bad callback must not end reception
                self.callback_errors += 1
                self.last_error = f'{type(exc).__name__}: {exc}'

    def close(self) -> None:
        """Stop the receive thread and close the socket."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=1.0)
        self.sock.close()


def resolve_target(host: str, port: int) -> tuple[str, int]:
    """(IPv4 address, port) of the target; ConfigError (one line) when `host` does not resolve."""
    try:
        infos = socket.getaddrinfo(host, port, socket.AF_INET, socket.SOCK_DGRAM)
    except (socket.gaierror, UnicodeError) as exc:
        raise ConfigError(f'target_host {host!r} cannot be resolved: {exc}') from None
    return infos[0][4]


def check_reachable(local_host: str, target_ip: str) -> None:
    """Raise ConfigError (one line) when replies from target_ip can never reach local_host."""
    if _is_loopback(local_host) and not _is_loopback(target_ip):
        raise ConfigError(f'local_host {local_host} is a loopback address but the target '
                          f'{target_ip} is not: its replies cannot reach this socket; set '
                          'local_host to the address of the interface facing the target '
                          '(0.0.0.0: every interface)')


def _is_loopback(host: str) -> bool:
    return host.startswith('127.') or host == 'localhost'


def _both_loopback(a: str, b: str) -> bool:
    return a.startswith('127.') and b.startswith('127.')
