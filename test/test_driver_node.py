"""
driver_node as a real process over DDS (isolated domain from conftest), against a UDP target.

The test process holds a probe node (publishes voltage_command, listens to deflection and
/diagnostics) and, for the watchdog test, plays the target itself so it can see every datagram.
"""
import os
import socket
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.executors import SingleThreadedExecutor
from sensor_msgs.msg import JointState

from piezo_narx_ros.nodes.wire import make_joint_state, stamp_to_ns
from piezo_narx_ros.nodes.diagnostics import DIAG_ERROR, DIAG_OK, DIAG_WARN, diagnostic_values
from piezo_narx_ros.nodes.qos import sample_qos
from piezo_narx_ros.plant import PiezoCantilever, load_plant_params
from piezo_narx_ros.rig import protocol as p

# A namespace of our own: ROS_DOMAIN_ID (pid % 100) can collide with another test session on the
# machine, and its command_node must not feed our driver.
NS = f'rigtest{os.getpid()}'
T0 = 1_700_000_000_000_000_000  # ns
DT = 500_000                     # ns, 2 kHz


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(('127.0.0.1', 0))
        return s.getsockname()[1]


def start_driver(**params) -> subprocess.Popen:
    args = [sys.executable, '-m', 'piezo_narx_ros.nodes.driver_node', '--ros-args',
            '-r', f'__ns:=/{NS}']
    for k, v in params.items():
        args += ['-p', f'{k}:={v}']
    return subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def stop(proc: subprocess.Popen) -> str:
    if proc.poll() is None:
        proc.terminate()
    try:
        out, _ = proc.communicate(timeout=10)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, _ = proc.communicate()
    return out


class Probe:
    """
    Test-side node in its own context, spun on a background thread.

    Publishes /NS/voltage_command with stamps T0 + k DT (k counts on across calls) and collects
    /NS/deflection (and the `extra` deflection topics) and the driver's /diagnostics.
    """

    def __init__(self, extra=()):
        self.ctx = rclpy.Context()
        rclpy.init(context=self.ctx)
        self.node = rclpy.create_node('probe', namespace=NS, context=self.ctx)
        self.pub = self.node.create_publisher(JointState, 'voltage_command',
                                              sample_qos(depth=1000))
        self.k = 0
        self.topics = [f'/{NS}/deflection', *extra]
        self.received = {t: [] for t in self.topics}
        self.deflection = self.received[self.topics[0]]
        self.status = []
        for topic in self.topics:
            self.node.create_subscription(JointState, topic, self.received[topic].append,
                                          sample_qos(depth=1000))
        self.node.create_subscription(DiagnosticArray, '/diagnostics', self._on_diag, 10)
        self.executor = SingleThreadedExecutor(context=self.ctx)
        self.executor.add_node(self.node)
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()

    def _spin(self):
        while self.ctx.ok():
            try:
                self.executor.spin_once(timeout_sec=0.05)
            except Exception:  # context shut down under us
                break

    def _on_diag(self, msg):
        self.status += [s for s in msg.status if s.name == f'{NS}/driver_node: rig link']

    def wait(self, predicate, timeout, what):
        deadline = time.monotonic() + timeout
        while not predicate():
            if time.monotonic() > deadline:
                what = what() if callable(what) else what
                raise AssertionError(f'timed out after {timeout} s waiting for {what}')
            time.sleep(0.01)

    def wait_connected(self, timeout=20.0):
        self.wait(lambda: self.pub.get_subscription_count() >= len(self.topics)
                  and all(self.node.count_publishers(t) > 0 for t in self.topics), timeout,
                  'discovery')

    def handshake(self, timeout=20.0):
        """
        Publish 0 V warm-up commands until every deflection topic answers.

        So that the real sequence starts after DDS matching has settled. Returns the first warm-up
        sample index answered on /NS/deflection: from there to the real sequence the plant sees 0
        V.
        """
        self.wait_connected(timeout)
        deadline = time.monotonic() + timeout
        while not all(self.received.values()):
            if time.monotonic() > deadline:
                raise AssertionError('no answer to the warm-up commands')
            self.send([0.0])
            time.sleep(0.05)
        time.sleep(0.2)
        first = (stamp_to_ns(self.deflection[0].header.stamp) - T0) // DT
        for msgs in self.received.values():
            msgs.clear()
        return first

    def send(self, volts, names=('x',)):
        """Publish one command per value, paced near 2 kHz in bursts of 20; returns stamps (ns)."""
        stamps = []
        for i, v in enumerate(volts):
            t = T0 + self.k * DT
            self.k += 1
            self.pub.publish(make_joint_state(t, list(names), effort=[v]))
            stamps.append(t)
            if i % 20 == 19:
                time.sleep(0.01)
        return stamps

    def close(self):
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.ctx)
        self.thread.join(timeout=2)


@pytest.fixture
def probe():
    pr = Probe()
    yield pr
    pr.close()


def test_driver_with_fake_rig_reproduces_the_plant_stream(probe):
    rig_port, local_port = free_udp_port(), free_udp_port()
    rig = subprocess.Popen([sys.executable, '-m', 'piezo_narx_ros.rig.fake_rig', '--port',
                            str(rig_port), '--seed', '7'], stdout=subprocess.PIPE,
                           stderr=subprocess.STDOUT, text=True)
    # A watchdog ramp datagram would step the rig's plant too: keep the watchdog out of this test.
    driver = start_driver(target_port=rig_port, local_port=local_port, reply_timeout=0.5,
                          watchdog_timeout=30.0)
    try:
        assert 'listening' in rig.stdout.readline()
        first = probe.handshake()
        k0 = probe.k
        k = np.arange(600)
        u = (80.0 * np.sin(2 * np.pi * 3.0 * k / 2000.0)
             + 20.0 * np.sin(2 * np.pi * 41 * k / 2000.0))
        stamps = probe.send(u)
        probe.wait(lambda: len(probe.deflection) >= len(u), 20.0,
                   lambda: f'all deflection samples, got {len(probe.deflection)}')
        # Datagrams at the driver's reply port from another port than the target's are dropped,
        # counted and said (a WARN), and survived.
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as junk:
            for data in (b'x', b'PZRG' + bytes(20), p.pack_command(p.Command(1, 0, (1.0,)))):
                junk.sendto(data, ('127.0.0.1', local_port))
        probe.send([5.0])
        probe.wait(lambda: len(probe.deflection) > len(u), 10.0, 'a sample after the junk')
        probe.wait(lambda: any(diagnostic_values(s).get('datagrams_foreign') == '3'
                               and s.level == DIAG_WARN and '3 datagrams from an address other '
                               "than the target's" in s.message for s in probe.status), 5.0,
                   'foreign datagrams on /diagnostics')
    finally:
        out = stop(driver)
        stop(rig)
    msgs = probe.deflection[:len(u)]
    assert [stamp_to_ns(m.header.stamp) for m in msgs] == stamps, out
    assert all(list(m.name) == ['x'] for m in msgs)
    plant = PiezoCantilever(load_plant_params(), fs=2000.0, seed=7)
    for _ in range(first, k0):        # warm-ups answered, and gaps between them bridged at 0 V
        plant.step(0.0)
    expect = np.array([plant.step(v) for v in u])
    assert np.array_equal([m.position[0] for m in msgs], expect[:, 0])   # bit-identical
    assert np.array_equal([m.effort[0] for m in msgs], expect[:, 2])
    assert probe.status[-1].hardware_id == f'udp://127.0.0.1:{rig_port}'   # the rig's address
    last = diagnostic_values(probe.status[-1])
    # (reply_timeouts may count start-up pings sent before fake_rig was listening)
    assert int(last['replies']) >= len(u) and last['replies_duplicate'] == '0'
    assert last['receive_errors'] == '0' and last['datagrams_foreign'] == '3'
    assert last['replies_malformed'] == '0' and last['replies_mismatched'] == '0'


def test_driver_with_fake_rig_equals_simulator_node_across_lost_commands():
    """
    Both answer the same /NS/voltage_command.

    Samples the driver never sees (a stamp gap, as after a DDS loss) are bridged the same way by
    the fake rig and the simulator node.
    """
    rig_port = free_udp_port()
    rig = subprocess.Popen([sys.executable, '-m', 'piezo_narx_ros.rig.fake_rig', '--port',
                            str(rig_port), '--seed', '5'], stdout=subprocess.PIPE,
                           stderr=subprocess.STDOUT, text=True)
    sim = subprocess.Popen([sys.executable, '-m', 'piezo_narx_ros.nodes.simulator_node',
                            '--ros-args', '-r', f'__ns:=/{NS}', '-p', 'seed:=5'],
                           stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    driver = subprocess.Popen([sys.executable, '-m', 'piezo_narx_ros.nodes.driver_node',
                               '--ros-args', '-r', f'__ns:=/{NS}_rig',
                               '-r', f'voltage_command:=/{NS}/voltage_command',
                               '-p', f'target_port:={rig_port}', '-p', 'local_port:=0',
                               '-p', 'watchdog_timeout:=30.0', '-p', 'reply_timeout:=0.5'],
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    probe = Probe(extra=(f'/{NS}_rig/deflection',))
    try:
        assert 'listening' in rig.stdout.readline()
        probe.handshake()
        k = np.arange(400)
        u = 100.0 * np.sin(2 * np.pi * 7.0 * k / 2000.0)
        probe.send(u[:200])
        probe.k += 37                                           # 37 commands lost upstream
        probe.send(u[200:])
        probe.wait(lambda: min(map(len, probe.received.values())) >= len(u), 20.0,
                   lambda: f'both streams, got {[len(m) for m in probe.received.values()]}')
    finally:
        probe.close()
        outs = [stop(proc) for proc in (driver, sim, rig)]
    sim_msgs = probe.received[f'/{NS}/deflection']
    rig_msgs = probe.received[f'/{NS}_rig/deflection']
    assert len(sim_msgs) == len(rig_msgs) == len(u), outs
    for a, b in zip(sim_msgs, rig_msgs):
        assert (a.header.stamp, list(a.position), list(a.effort)) == \
            (b.header.stamp, list(b.position), list(b.effort))
    assert np.ptp([m.position[0] for m in rig_msgs]) > 1e-6   # a real signal, not zeros


class EchoTarget:
    """
    A UDP target in the test.

    Records (arrival s, Command), replies position = 1e-7 m/V, skips the replies to samples k in
    `drop` and answers samples in `dup` twice (k from stamps).
    """

    def __init__(self):
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(('127.0.0.1', 0))
        self.sock.settimeout(0.05)
        self.port = self.sock.getsockname()[1]
        self.got, self.peer = [], None
        self.drop, self.dup = set(), set()
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self):
        while not self._stop.is_set():
            try:
                data, addr = self.sock.recvfrom(65535)
            except socket.timeout:
                continue
            cmd = p.unpack_command(data)
            i = (cmd.stamp_ns - T0) // DT if not cmd.flags & p.FLAG_RAMP else None
            self.got.append((time.monotonic(), cmd))
            self.peer = addr
            if i in self.drop:
                continue
            reply = p.pack_reply(p.Reply(cmd.seq, cmd.stamp_ns, (cmd.volts[0] * 1e-7,), cmd.volts))
            for _ in range(2 if i in self.dup else 1):
                self.sock.sendto(reply, addr)

    def close(self):
        self._stop.set()
        self.thread.join(timeout=2)
        self.sock.close()


def test_limits_clamp_and_watchdog_ramps_to_zero_at_the_slew_limit(probe):
    slew, ramp_rate, timeout = 400.0, 200.0, 0.3        # 0.2 V per command, 2 V per ramp datagram
    target = EchoTarget()
    driver = start_driver(target_port=target.port, local_port=0, v_max=40.0, max_slew_rate=slew,
                          sample_rate=2000.0, watchdog_timeout=timeout, ramp_rate=ramp_rate,
                          reply_timeout=0.5)   # long: only the dropped replies may time out
    try:
        probe.handshake()
        k0 = probe.k
        target.drop, target.dup = {k0 + i for i in range(10, 15)}, {k0 + 20}
        n = 300
        probe.send([1000.0] * n)                                  # asks far beyond the limits
        bad = make_joint_state(T0, ['y'], effort=[1.0])           # wrong axis
        probe.pub.publish(bad)
        probe.pub.publish(make_joint_state(T0, ['x'], effort=[float('nan')]))
        probe.wait(lambda: target.got and target.got[-1][1].volts == (0.0,), 10.0, 'ramp to 0 V')
        probe.wait(lambda: any(diagnostic_values(s).get('state') == 'parked'
                               for s in probe.status), 5.0, 'parked state on /diagnostics')
    finally:
        out = stop(driver)
        target.close()
    cmds = [c for _, c in target.got if not c.flags and c.stamp_ns >= T0 + k0 * DT]
    last_cmd_t = max(t for t, c in target.got if not c.flags)
    ramp = [(t, c) for t, c in target.got if c.flags & p.FLAG_RAMP and t > last_cmd_t]
    sent = np.array([c.volts[0] for c in cmds])
    assert len(cmds) == n, out
    assert sent.max() == 40.0                                            # clamped to v_max
    assert np.all(np.diff(np.r_[0.0, sent]) <= slew / 2000.0 + 1e-9)     # slew-limited per command
    assert sent[199] == pytest.approx(40.0) and sent[198] < 40.0
    # Ramp: starts about watchdog_timeout after the last command, 2 V steps down to exactly 0 V.
    volts = np.array([c.volts[0] for _, c in ramp])
    assert timeout - 0.02 <= ramp[0][0] - last_cmd_t <= timeout + 0.5
    assert volts[0] == pytest.approx(38.0) and volts[-1] == 0.0
    assert np.all(np.diff(np.r_[40.0, volts]) >= -slew / ramp_rate - 1e-9)
    assert np.all(np.diff(volts) <= 0)
    # Real time, not a jump: ramp datagrams carry the node's clock at sending (arrival times
    # would bunch if this test process stalls).
    assert (ramp[-1][1].stamp_ns - ramp[0][1].stamp_ns) * 1e-9 >= 38.0 / slew * (1 - 1e-6)
    # The published stream has every command's reply except the 5 dropped, and no ramp samples.
    assert len(probe.deflection) == n - 5
    assert [m.effort[0] for m in probe.deflection] == [v for i, v in enumerate(sent)
                                                       if i not in range(10, 15)]
    levels = [s.level for s in probe.status]
    assert set(levels) <= {DIAG_OK, DIAG_WARN, DIAG_ERROR} and DIAG_WARN in levels, levels
    values = diagnostic_values(probe.status[-1])
    assert values['reply_timeouts'] == '5' and values['replies_duplicate'] == '1'
    assert values['commands_rejected'] == '2' and values['commands_clamped'] == str(n)
    assert int(values['watchdog_trips']) >= 1


@pytest.mark.parametrize('params, reason', [
    ({'v_min': 10.0}, 'parameter v_min must be <= 0.0, got 10.0'),
    ({'v_min': 0.0, 'v_max': 0.0}, 'v_min (0.0 V) must be below v_max (0.0 V)'),
    ({'reply_timeout': -1.0}, 'parameter reply_timeout must be >= 1e-05'),
    ({'target_host': 'no.such.host.invalid'},
     "target_host 'no.such.host.invalid' cannot be resolved"),
    ({'target_host': '192.0.2.7'}, 'local_host 127.0.0.1 is a loopback address but the target '
     '192.0.2.7 is not'),
])
def test_bad_parameters_are_refused_with_a_reason(params, reason):
    proc = start_driver(local_port=0, **params)
    out, _ = proc.communicate(timeout=60)
    assert proc.returncode == 2, out
    lines = out.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith('driver_node: error: '), out
    assert reason in lines[0], out


def test_rig_launch_file_starts_fake_rig_then_driver_then_command_node():
    from piezo_narx_ros.cli.bringup import load_launch
    specs = load_launch('rig.launch.yaml')
    assert [s.name for s in specs] == ['fake_rig', 'driver_node', 'command_node']
    rig, driver, command = (s.argv for s in specs)
    assert 'piezo_narx_ros.rig.fake_rig' in rig and '--ros-args' not in rig
    assert rig[-4:] == ['--port', '50000', '--seed', '0']
    assert 'piezo_narx_ros.nodes.driver_node' in driver and 'target_port:=50000' in driver
    assert any(a.endswith('driver_node.yaml') for a in driver)
    assert 'wait_for_subscribers:=1' in command


class RecordingRig:
    """fake_rig in this process (a thread), logging every command datagram it handles."""

    def __init__(self, port):
        from piezo_narx_ros.rig.fake_rig import FakeRig

        class _Rig(FakeRig):

            def handle(inner, data):
                try:
                    self.log.append(p.unpack_command(data))
                except p.DatagramError:
                    pass
                return FakeRig.handle(inner, data)

        self.log = []
        self.rig = _Rig(port=port, seed=3)
        self.thread = self.rig.start()

    def commands(self):
        return [c for c in self.log if not c.flags]

    def ramps(self):
        return [c for c in self.log if c.flags & p.FLAG_RAMP]

    def close(self):
        self.rig.stop()
        self.thread.join(2)
        self.rig.close()


def test_lifecycle_transitions_estop_and_arm_against_the_fake_rig(probe):
    """
    autostart:=false.

    Each transition does what it says, checked on the rig's side (the datagrams it receives) and on
    the ROS side (subscription, deflection, /diagnostics).
    """
    from lifecycle_msgs.msg import Transition
    from lifecycle_msgs.srv import ChangeState, GetState
    from std_srvs.srv import Trigger
    rig_port = free_udp_port()
    slew, ramp_rate = 400.0, 200.0      # 0.2 V per command at 2 kHz, 2 V per ramp datagram
    driver = start_driver(target_port=rig_port, local_port=0, autostart='false',
                          connect_timeout=0.3, max_slew_rate=slew, ramp_rate=ramp_rate,
                          watchdog_timeout=30.0, reply_timeout=0.5)
    node = probe.node
    change = node.create_client(ChangeState, f'/{NS}/driver_node/change_state')
    get = node.create_client(GetState, f'/{NS}/driver_node/get_state')
    arm = node.create_client(Trigger, f'/{NS}/driver_node/arm')
    estop = node.create_client(Trigger, f'/{NS}/driver_node/estop')

    def call(client, request):
        assert client.wait_for_service(timeout_sec=30.0)
        future = client.call_async(request)
        probe.wait(future.done, 20.0, 'a service reply')
        return future.result()

    def transition(tid):
        return call(change, ChangeState.Request(transition=Transition(id=tid))).success

    def state():
        return call(get, GetState.Request()).current_state.label

    def diag(key):
        return diagnostic_values(probe.status[-1]).get(key) if probe.status else None

    rig = None
    try:
        assert state() == 'unconfigured'
        # configure fails while nothing answers: still unconfigured, reason on /diagnostics
        assert not transition(Transition.TRANSITION_CONFIGURE)
        assert state() == 'unconfigured'
        probe.wait(lambda: probe.status and probe.status[-1].level == DIAG_ERROR
                   and 'did not answer' in probe.status[-1].message, 5.0, 'configure error')
        rig = RecordingRig(rig_port)
        # configure: pings the target, subscribes nothing, sends no command
        assert transition(Transition.TRANSITION_CONFIGURE) and state() == 'inactive'
        assert rig.rig.pings >= 1 and rig.commands() == []
        probe.send([50.0] * 20)
        time.sleep(0.3)
        assert probe.pub.get_subscription_count() == 0 and rig.commands() == []
        # activate: subscribes, commands reach the rig (slew-limited) and come back
        assert transition(Transition.TRANSITION_ACTIVATE) and state() == 'active'
        probe.wait(lambda: probe.pub.get_subscription_count() == 1, 10.0, 'subscription')
        time.sleep(0.3)
        probe.send([100.0] * 300)
        probe.wait(lambda: len(probe.deflection) >= 300, 20.0, 'deflection while active')
        sent = [c.volts[0] for c in rig.commands()]
        assert len(sent) == 300 and sent[-1] == pytest.approx(60.0)
        # e-stop: ramps to 0 V at the slew limit, then commands are blocked until arm
        assert call(estop, Trigger.Request()).success
        probe.wait(lambda: rig.ramps() and rig.ramps()[-1].volts == (0.0,), 10.0, 'e-stop ramp')
        ramp = [c.volts[0] for c in rig.ramps()]
        assert ramp[0] == pytest.approx(58.0) and 30 <= len(ramp) <= 45   # <= 2 V per datagram
        assert np.all(np.diff(np.r_[60.0, ramp]) >= -slew / ramp_rate - 1e-9)
        probe.send([100.0] * 50)
        probe.wait(lambda: diag('commands_blocked') == '50', 10.0, 'blocked commands')
        assert len(rig.commands()) == 300 and diag('estop') == 'True'
        assert probe.status[-1].level == DIAG_WARN and 'e-stop' in probe.status[-1].message
        assert call(arm, Trigger.Request()).success
        probe.send([100.0] * 20)
        probe.wait(lambda: len(rig.commands()) == 320, 10.0, 'commands after arm')
        after = [c.volts[0] for c in rig.commands()[300:]]
        assert after[0] == pytest.approx(0.2) and after[-1] == pytest.approx(4.0)   # from 0 V
        # deactivate: unsubscribes and ramps the 4 V to 0 V at the slew limit
        n_ramps = len(rig.ramps())
        assert transition(Transition.TRANSITION_DEACTIVATE) and state() == 'inactive'
        ramp = [c.volts[0] for c in rig.ramps()[n_ramps:]]
        assert ramp == pytest.approx([2.0, 0.0])
        probe.wait(lambda: probe.pub.get_subscription_count() == 0, 10.0, 'unsubscribed')
        probe.send([100.0] * 20)
        time.sleep(0.3)
        assert len(rig.commands()) == 320
        # cleanup: the socket is closed, nothing more reaches the rig
        assert transition(Transition.TRANSITION_CLEANUP) and state() == 'unconfigured'
        n = len(rig.log)
        time.sleep(0.3)
        assert len(rig.log) == n
    finally:
        out = stop(driver)
        if rig is not None:
            rig.close()
    assert driver.returncode == 0, out
