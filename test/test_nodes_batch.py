"""
Batched streams over DDS (DESIGN.md "High-rate streams"), node processes in an isolated domain.

Checked: command_node batch:=N stamps and batch sizes, simulator_node and estimator_node answering
each batch with a batch of the same stamps and the same numbers as the one-sample path offline;
a NaN, an out-of-range command, a stamp gap and refused batches (bad size, truncated) counted on
/diagnostics while the node keeps running; the controller and driver (protocol version 2 with
fake_rig) the same way; recorder_node batch:=N and player_node keep every stamp.
"""
import math
import socket
import threading
import time

import numpy as np
import pytest
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.node import Node
from test_estimator_node import start_node, stop, wait_matched
from trajectory_msgs.msg import JointTrajectory

from piezo_narx_ros.nodes.wire import decode_joint_trajectory, encode_joint_trajectory
from piezo_narx_ros.nodes.diagnostics import DIAG_WARN, diagnostic_values, status_node
from piezo_narx_ros.nodes.qos import sample_qos

T0 = 10**18


class BatchProbe:
    """In-process node: publishes raw batches on `pub_topic`, records every batch it hears."""

    def __init__(self, ns, topics, pub_topic=None):
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = Node('batch_probe', namespace=ns, context=self.context)
        self.batches = {t: [] for t in topics}
        self.diag = {}
        self.subs = [self.node.create_subscription(JointTrajectory, t, self.batches[t].append,
                                                   sample_qos(depth=10000), raw=True)
                     for t in topics]
        self.node.create_subscription(DiagnosticArray, '/diagnostics', self._on_diag, 100)
        self.pub = None if pub_topic is None else self.node.create_publisher(
            JointTrajectory, pub_topic, sample_qos(depth=10000))
        from rclpy.experimental import EventsExecutor
        self.executor = EventsExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._run = True
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()

    def _on_diag(self, arr):
        for st in arr.status:
            self.diag[status_node(st.name)] = (st.level, diagnostic_values(st))

    def _spin(self):
        while self._run and self.context.ok():
            self.executor.spin_once(timeout_sec=0.05)

    def wait_for(self, predicate, timeout):
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if predicate():
                return True
            time.sleep(0.05)
        return False

    def wait_matched(self, subscribers=1, timeout=30.0):
        """Wait until `pub_topic` reaches `subscribers` nodes and every recorded topic is heard."""
        return wait_matched(self.pub, self.subs, subscribers, timeout)

    def decoded(self, topic):
        return [decode_joint_trajectory(bytes(raw)) for raw in self.batches[topic]]

    def samples(self, topic, field):
        got = self.decoded(topic)
        if not got:
            return np.empty(0, np.int64), np.empty(0)
        return (np.concatenate([b.t_ns for b in got]),
                np.concatenate([getattr(b, field)[:, 0] for b in got]))

    def close(self):
        self._run = False
        self.thread.join(5)
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)


@pytest.fixture(scope='module')
def toy_model_file(tmp_path_factory):
    from piezo_narx_ros.estimator.toy import toy_narx
    from piezo_narx_ros.ident.model_io import save_model
    return save_model(toy_narx(fs=20000.0), tmp_path_factory.mktemp('model') / 'toy.json')


def test_command_and_simulator_batches_carry_every_stamp_and_the_offline_plant(tmp_path):
    from fractions import Fraction

    from piezo_narx_ros.plant import PiezoCantilever, load_plant_params
    fs, n, batch = 20000.0, 1000, 7
    probe = BatchProbe('/bcs', ('voltage_command_batch', 'deflection_batch'))
    procs = [start_node('simulator_node', '-p', f'fs:={fs}', '-p', f'batch:={batch}', ns='/bcs')]
    try:
        assert wait_matched(None, probe.subs[1:], 0, 30.0)
        procs.append(start_node('command_node', '-p', f'fs:={fs}', '-p', f'batch:={batch}',
                                '-p', 'loop:=false', '-p', f'seconds:={n / fs}', '-p',
                                'wait_for_subscribers:=2', '-p', 'amplitude:=50.0',
                                ns='/bcs'))
        assert probe.wait_for(lambda: sum(map(len, probe.decoded('deflection_batch'))) >= n,
                              30.0)
    finally:
        codes = stop(procs)
        probe.close()
    assert codes == [0, 0]
    cmd = probe.decoded('voltage_command_batch')
    assert [len(b) for b in cmd] == [batch] * (n // batch) + [n % batch]   # the rest flushed
    t_u, u = probe.samples('voltage_command_batch', 'effort')
    t0 = int(t_u[0])
    period = Fraction(10**9) / Fraction(fs)
    assert t_u.tolist() == [t0 + int(k * period) for k in range(n)]            # exact grid
    dfl = probe.decoded('deflection_batch')
    assert [b.t_ns.tolist() for b in dfl] == [b.t_ns.tolist() for b in cmd]   # same batches
    assert all(b.names == ['x'] for b in cmd + dfl)
    plant = PiezoCantilever(load_plant_params(), fs=fs, seed=0)
    ref = np.array([plant.step(v)[0] for v in u])
    assert np.array_equal(np.concatenate([b.position[:, 0] for b in dfl]), ref)


# The estimator scenario: 400 commands 50 us apart in batches of 5, and the stamps answered.
EST_PERIOD_NS, EST_BATCH = 50_000, 5
EST_STAMPS = [T0 + k * EST_PERIOD_NS for k in range(400)]


class LateMatch(Exception):
    """Nothing but a tail of the answers arrived: the node's writer matched the probe late."""


def _estimator_batches(toy_model_file, ns):
    """
    Run the estimator scenario below once in namespace `ns`; return (u, probe data, exit codes).

    LateMatch when the answers that arrived are only the last ones (none included): the node's
    writer matched the probe's reader after it had answered the first batches. The probe sees its
    own side of that match only (wait_matched's settle covers the usual delay).
    """
    period, batch = EST_PERIOD_NS, EST_BATCH
    probe = BatchProbe(ns, ('deflection_estimate_batch',), 'voltage_command_batch')
    est = start_node('estimator_node', '-p', f'model:={toy_model_file}', '-p', 'init:=rest',
                     '-p', f'batch:={batch}', ns=ns)
    try:
        assert probe.wait_matched()
        u = np.random.default_rng(3).uniform(-100, 100, 400)
        sent = u.copy()
        sent[100], sent[150], sent[151] = math.nan, 1e4, math.inf
        keep = [k for k in range(400) if not 200 <= k < 205]      # a gap of 5 samples
        for i in range(0, len(keep), batch):
            ks = keep[i:i + batch]
            probe.pub.publish(encode_joint_trajectory([T0 + k * period for k in ks], ['x'],
                                                      effort=sent[ks, None]))
            if i == 50:   # two refused batches: points of the wrong size, truncated bytes
                probe.pub.publish(encode_joint_trajectory([T0, T0 + 1], ['x'],
                                                          effort=np.ones((2, 2))))
                probe.pub.publish(encode_joint_trajectory([T0], ['x'], effort=[[1.0]])[:30])
            time.sleep(0.002)
        answered = probe.wait_for(
            lambda: sum(map(len, probe.decoded('deflection_estimate_batch'))) >= 400, 20.0)
        assert probe.wait_for(lambda: probe.diag.get(f'{ns}/estimator_node', (0, {}))[1]
                              .get('commands') == '395', 5.0)
        assert est.poll() is None                            # still running
        got = probe.decoded('deflection_estimate_batch')
        t, y_hat = probe.samples('deflection_estimate_batch', 'position')
        values = probe.diag[f'{ns}/estimator_node'][1]
    finally:
        codes = stop([est])
        probe.close()
    if not answered and t.tolist() == EST_STAMPS[len(EST_STAMPS) - len(t):]:
        raise LateMatch(f'{len(t)} of 400 answers, all at the end')
    assert answered, f'{len(t)} of 400 answers; stamps from {t[:3].tolist()}'
    return u, got, t, y_hat, values, codes


def test_estimator_answers_batches_and_survives_nan_gap_and_bad_batches(toy_model_file):
    from piezo_narx_ros.ident.model_io import load_model
    model = load_model(toy_model_file)
    period, batch = EST_PERIOD_NS, EST_BATCH
    try:
        u, got, t, y_hat, values, codes = _estimator_batches(toy_model_file, '/best')
    except LateMatch:
        # Once in a clean-clone suite run the probe heard fewer than 400 answers in 20 s; a
        # match completed late on the node's side is retried once, anything else fails.
        u, got, t, y_hat, values, codes = _estimator_batches(toy_model_file, '/best2')
    assert t.tolist() == EST_STAMPS
    # Before any anomaly, each batch is answered by one batch of the same stamps.
    assert [b.t_ns.tolist() for b in got[:19]] == \
        [[T0 + k * period for k in range(i, i + batch)] for i in range(0, 95, batch)]
    held = u.copy()
    for k in [100, 150, 151, *range(200, 205)]:
        held[k] = held[k - 1]
    assert np.max(np.abs(y_hat - model.simulate(held))) <= 1e-12
    assert values['rejected_nonfinite'] == '2' and values['rejected_range'] == '1'
    assert values['refused_messages'] == '2'        # the two refused batches, said as such
    assert values['gaps'] == '1' and values['filled'] == '8'
    assert codes == [0]


def test_controller_answers_reference_batches_like_the_one_sample_path(toy_model_file):
    """Mode inverse: the controller refuses mode linear with the toy model's gain (issue 19)."""
    from piezo_narx_ros.control.controller import PositionController, input_limits
    from piezo_narx_ros.ident.model_io import load_model
    model = load_model(toy_model_file)
    period, batch = 50_000, 8
    probe = BatchProbe('/bctl', ('voltage_command_batch',), 'position_reference_batch')
    ctl = start_node('controller_node', '-p', f'model:={toy_model_file}', '-p', 'mode:=inverse',
                     '-p', 'use_deflection:=false', '-p', f'batch:={batch}', ns='/bctl')
    lo, hi = model.output_range
    r = lo + (hi - lo) * (0.5 + 0.3 * np.sin(np.arange(160) / 9.0))
    try:
        assert probe.wait_matched()
        for i in range(0, r.size, batch):
            probe.pub.publish(encode_joint_trajectory(
                [T0 + k * period for k in range(i, i + batch)], ['x'],
                position=r[i:i + batch, None]))
            time.sleep(0.002)
        assert probe.wait_for(lambda: sum(map(len, probe.decoded('voltage_command_batch')))
                              >= r.size, 20.0)
    finally:
        codes = stop([ctl])
        probe.close()
    assert codes == [0]
    ref = PositionController(model, mode='inverse', fs=20000.0, slew_rate=1e5,   # the node's
                             **input_limits(model, 0.05))
    want = [c for k, rk in enumerate(r) for c in ref.on_reference(T0 + k * period, rk)]
    t, u = probe.samples('voltage_command_batch', 'effort')
    assert t.tolist() == [c[0] for c in want] and np.array_equal(u, [c[1] for c in want])


def _free_port():
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(('127.0.0.1', 0))
        return s.getsockname()[1]


def test_driver_negotiates_version2_with_fake_rig_and_answers_batches():
    from piezo_narx_ros.plant import PiezoCantilever, load_plant_params
    from piezo_narx_ros.rig import protocol as p
    from piezo_narx_ros.rig.fake_rig import FakeRig
    fs, period, batch = 20000.0, 50_000, 10
    versions = []

    class Rig(FakeRig):

        def handle(self, data):
            versions.append(p.datagram_version(data))
            return FakeRig.handle(self, data)

    rig = Rig(port=0, seed=2, fs=fs)
    thread = rig.start()
    probe = BatchProbe('/bdrv', ('deflection_batch',), 'voltage_command_batch')
    drv = start_node('driver_node', '-p', f'target_port:={rig.address[1]}', '-p',
                     f'local_port:={_free_port()}', '-p', 'protocol_version:=0', '-p',
                     f'batch:={batch}', '-p', f'sample_rate:={fs}', '-p', 'reply_timeout:=1.0',
                     # a >0.1 s stall of this publisher under load would rightly ramp the
                     # plant to 0 V and break the bit-exact comparison below
                     '-p', 'watchdog_timeout:=30.0', ns='/bdrv')
    u = 50.0 * np.sin(np.arange(200) / 15.0)          # well inside the slew limit
    try:
        assert probe.wait_matched()
        for i in range(0, u.size, batch):
            probe.pub.publish(encode_joint_trajectory(
                [T0 + k * period for k in range(i, i + batch)], ['x'],
                effort=u[i:i + batch, None]))
            time.sleep(0.002)
        assert probe.wait_for(lambda: sum(map(len, probe.decoded('deflection_batch'))) >= u.size,
                              20.0)
        assert probe.wait_for(lambda: probe.diag.get('/bdrv/driver_node', (0, {}))[1]
                              .get('protocol_version') == '2', 5.0)
    finally:
        codes = stop([drv])
        probe.close()
        rig.stop()
        thread.join(2)
        rig.close()
    assert codes == [0]
    assert 2 in versions and rig.commands >= u.size
    got = probe.decoded('deflection_batch')
    assert [b.t_ns.tolist() for b in got] == \
        [[T0 + k * period for k in range(i, i + batch)] for i in range(0, u.size, batch)]
    plant = PiezoCantilever(load_plant_params(), fs=fs, seed=2)
    ref = [plant.step(v)[0] for v in u]
    assert np.concatenate([b.position[:, 0] for b in got]).tolist() == ref


def test_recorder_and_player_keep_every_batched_stamp(tmp_path):
    from piezo_narx_ros.bag.reader import bag_info, read_uy_report
    fs, n, batch = 20000.0, 4000, 20
    ns = '/brec'
    rec_a = start_node('recorder_node', '-p', f'output:={tmp_path / "a"}', '-p',
                       f'batch:={batch}', '-p', 'topics:=[voltage_command, deflection]', ns=ns)
    sim = start_node('simulator_node', '-p', f'fs:={fs}', '-p', f'batch:={batch}', ns=ns)
    probe = BatchProbe(ns, ('deflection_batch',))
    try:
        assert probe.wait_for(lambda: probe.subs[0].get_publisher_count() >= 1, 30.0)
        time.sleep(1.0)
        cmd = start_node('command_node', '-p', f'fs:={fs}', '-p', f'batch:={batch}', '-p',
                         'loop:=false', '-p', f'seconds:={n / fs}', '-p',
                         'wait_for_subscribers:=2', ns=ns)     # recorder, simulator
        assert probe.wait_for(lambda: sum(map(len, probe.decoded('deflection_batch'))) >= n,
                              30.0)
        time.sleep(0.5)
    finally:
        codes = stop([cmd, sim, rec_a])
        probe.close()
    assert codes == [0, 0, 0]
    topics = (f'{ns}/voltage_command', f'{ns}/deflection')
    a, report = read_uy_report(tmp_path / 'a', *topics)
    assert a.u.size == n and report.issues() == [] and a.fs == fs
    info = {t.name: t for t in bag_info(tmp_path / 'a').topics}
    assert info[f'{ns}/voltage_command_batch'].count == n // batch
    # Played back into a second recorder: the same samples with the same stamps.
    rec_b = start_node('recorder_node', '-p', f'output:={tmp_path / "b"}', '-p',
                       f'batch:={batch}', '-p', 'topics:=[voltage_command, deflection]', ns=ns)
    time.sleep(1.0)
    player = start_node('player_node', '-p', f'bag:={tmp_path / "a"}', '-p',
                        'wait_for_subscribers:=1', '-p', 'rate:=4.0', ns=ns)
    try:
        player.wait(60)
        time.sleep(0.5)
    finally:
        codes = stop([player, rec_b])
    assert codes == [0, 0]
    b, report_b = read_uy_report(tmp_path / 'b', *topics)
    assert np.array_equal(a.u, b.u) and np.array_equal(a.y, b.y) and np.array_equal(a.t, b.t)
    assert report_b.t0_ns == report.t0_ns


def test_simulator_node_counts_refused_batches_and_answers_the_rest_in_process():
    """The simulator's batch callback without DDS traffic: bad batches counted, NaN refused."""
    from rclpy.parameter import Parameter

    from piezo_narx_ros.nodes.simulator_node import SimulatorNode
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    node = SimulatorNode(context=ctx, parameter_overrides=[Parameter('batch', value=4),
                                                           Parameter('fs', value=20000.0)])
    try:
        assert node.pub.topic_name == '/piezo/deflection_batch'
        sent = []
        node.pub.publish = sent.append
        stamps = [T0 + k * 50_000 for k in range(4)]
        node.on_command_batch(encode_joint_trajectory(stamps, ['x'], effort=np.ones((4, 2))))
        node.on_command_batch(b'\x00\x01\x00\x00\x01')
        node.on_command_batch(encode_joint_trajectory(stamps, ['x'],
                                                      effort=[[1.0], [np.nan], [2.0], [3.0]]))
        r = node.responder
        assert (r.rejected, r.answered) == (2 + 1, 3)
        assert [b.t_ns.tolist() for b in map(decode_joint_trajectory, sent)] == \
            [[stamps[0], stamps[2], stamps[3]]]
        level, message, values = node.status()
        assert level == DIAG_WARN and 'refused' in message and values['rejected'] == 3
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)
