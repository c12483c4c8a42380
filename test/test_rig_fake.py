"""Fake rig over real UDP sockets (no DDS): PiezoCantilever.step's numbers, malformed survived."""
import socket
import subprocess
import sys
import time

import numpy as np
import pytest

from piezo_narx_ros.plant import PiezoCantilever, load_plant_params
from piezo_narx_ros.rig import protocol as p
from piezo_narx_ros.rig.client import RigClient
from piezo_narx_ros.rig.driver import DriverConfig, RigDriver
from piezo_narx_ros.rig.fake_rig import FakeRig


@pytest.fixture
def rig():
    r = FakeRig(port=0, seed=3)
    thread = r.start()
    yield r
    r.stop()
    thread.join(timeout=2)
    r.close()


def _exchange(sock, addr, data, timeout=2.0):
    sock.sendto(data, addr)
    sock.settimeout(timeout)
    return sock.recvfrom(65535)[0]


def test_driver_over_udp_matches_plant_step_for_same_seed(rig):
    u = 60.0 * np.sin(2 * np.pi * 5.0 * np.arange(300) / 2000.0)   # 1.9 kV/s << slew limit
    got = []
    client = RigClient('127.0.0.1', rig.address[1], 0)
    driver = RigDriver(DriverConfig(reply_timeout=1.0), client.send)
    client.start(lambda data, now: got.append(driver.receive(data, now)))
    try:
        for k, v in enumerate(u):
            driver.command([v], stamp_ns=10_000 + 500_000 * k, now=time.monotonic())
            # Lockstep keeps the test deterministic on a loaded machine (no socket buffer overrun).
            deadline = time.monotonic() + 2.0
            while len(got) <= k and time.monotonic() < deadline:
                time.sleep(1e-4)
    finally:
        client.close()
    assert len(got) == len(u) and all(s is not None for s in got)
    plant = PiezoCantilever(load_plant_params(), fs=2000.0, seed=3)
    expect = [plant.step(v) for v in u]
    assert [s.position_m[0] for s in got] == [e[0] for e in expect]     # bit-identical float64
    assert [s.applied_volts[0] for s in got] == [e[2] for e in expect]
    assert [s.stamp_ns for s in got] == [10_000 + 500_000 * k for k in range(len(u))]
    assert driver.counts['replies'] == len(u) and driver.counts['reply_timeouts'] == 0


def test_malformed_datagrams_are_counted_and_the_rig_keeps_serving(rig):
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        for junk in (b'', b'hello', p.pack_reply(p.Reply(1, 0, (0.0,), (0.0,))),
                     p.pack_command(p.Command(1, 0, (1.0, 2.0)))):   # wrong axis count
            sock.sendto(junk, rig.address)
        cmd = p.pack_command(p.Command(5, 42, (10.0,)))
        reply = p.unpack_reply(_exchange(sock, rig.address, cmd))
        assert reply.seq == 5 and reply.stamp_ns == 42 and reply.applied_volts[0] != 0.0
        # A retransmitted datagram is answered from cache without stepping the plant again.
        again = p.unpack_reply(_exchange(sock, rig.address, cmd))
        assert again == reply
    assert rig.malformed == 4 and rig.commands == 1 and rig.repeats == 1


def test_fake_rig_cli_serves_and_refuses_bad_options():
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(('127.0.0.1', 0))
        port = s.getsockname()[1]
    cmd = [sys.executable, '-m', 'piezo_narx_ros.rig.fake_rig', '--port', str(port)]
    proc = subprocess.Popen(cmd + ['--seed', '0'], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    try:
        assert 'listening on 127.0.0.1:%d' % port in proc.stdout.readline()
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
            reply = p.unpack_reply(_exchange(sock, ('127.0.0.1', port),
                                             p.pack_command(p.Command(1, 0, (50.0,))), timeout=10))
        expect = PiezoCantilever(load_plant_params(), fs=2000.0, seed=0).step(50.0)
        assert reply.position_m[0] == expect[0]
        # A second rig on the same port is refused in one line.
        busy = subprocess.run(cmd, capture_output=True, text=True, timeout=60)
        assert busy.returncode == 2
        assert busy.stderr.startswith('fake_rig: error: cannot bind')
        assert busy.stderr.count('\n') == 1
    finally:
        proc.terminate()
        out, _ = proc.communicate(timeout=10)
    assert proc.returncode == 0 and 'stopped after 1 commands' in out


def test_stamp_gaps_are_bridged_with_the_held_voltage_like_the_simulator(rig):
    ks = [0, 1, 2, 5, 6]                          # samples 3 and 4 lost upstream
    volts = [10.0, 20.0, 30.0, 40.0, 50.0]
    replies = []
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        for i, (k, v) in enumerate(zip(ks, volts)):
            cmd = p.Command(i, 1_000 + k * 500_000, (v,))
            replies.append(p.unpack_reply(_exchange(sock, rig.address, p.pack_command(cmd))))
        # A watchdog ramp datagram is stepped once and ends the bridging: no fill after it.
        ramp = p.Command(5, 123, (45.0,), p.FLAG_RAMP)
        replies.append(p.unpack_reply(_exchange(sock, rig.address, p.pack_command(ramp))))
        late = p.Command(6, 1_000 + 100 * 500_000, (44.0,))
        replies.append(p.unpack_reply(_exchange(sock, rig.address, p.pack_command(late))))
    plant = PiezoCantilever(load_plant_params(), fs=2000.0, seed=3)
    applied = [10.0, 20.0, 30.0, 30.0, 30.0, 40.0, 50.0, 45.0, 44.0]
    y = [plant.step(v)[0] for v in applied]
    assert [r.position_m[0] for r in replies] == [y[i] for i in (0, 1, 2, 5, 6, 7, 8)]
    assert rig.filled == 2


def test_ping_reports_the_last_measurement_without_stepping(rig):
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        first = p.unpack_reply(_exchange(sock, rig.address, p.pack_command(
            p.Command(1, 0, (0.0,), p.FLAG_PING))))
        cmd = p.unpack_reply(_exchange(sock, rig.address, p.pack_command(
            p.Command(2, 0, (80.0,)))))
        ping = p.unpack_reply(_exchange(sock, rig.address, p.pack_command(
            p.Command(3, 9, (0.0,), p.FLAG_PING))))
        nxt = p.unpack_reply(_exchange(sock, rig.address, p.pack_command(
            p.Command(4, 0, (80.0,)))))
    assert (first.position_m, first.applied_volts) == ((0.0,), (0.0,))
    assert (ping.seq, ping.stamp_ns, ping.position_m, ping.applied_volts) == \
        (3, 9, cmd.position_m, cmd.applied_volts)
    plant = PiezoCantilever(load_plant_params(), fs=2000.0, seed=3)
    assert [cmd.position_m[0], nxt.position_m[0]] == [plant.step(80.0)[0], plant.step(80.0)[0]]
    assert rig.pings == 2 and rig.commands == 2


def test_client_binds_loopback_and_drops_datagrams_from_another_port():
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as target:
        target.bind(('127.0.0.1', 0))
        client = RigClient('127.0.0.1', target.getsockname()[1], 0)
        got = []
        client.start(lambda data, now: got.append(data))
        try:
            assert client.sock.getsockname()[0] == '127.0.0.1'
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as spoof:   # same IP, other port
                spoof.sendto(b'spoofed', ('127.0.0.1', client.local_port))
            target.sendto(b'real', ('127.0.0.1', client.local_port))
            deadline = time.monotonic() + 2.0
            while not got and time.monotonic() < deadline:
                time.sleep(1e-3)
        finally:
            client.close()
    assert got == [b'real'] and client.foreign == 1


def test_a_loopback_bind_with_a_remote_target_is_refused_in_one_line():
    from piezo_narx_ros.errors import ConfigError
    with pytest.raises(ConfigError, match='local_host 127.0.0.1 is a loopback address but the '
                       'target 192.0.2.7 is not'):
        RigClient('192.0.2.7', 50000, 0)
