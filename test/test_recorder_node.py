"""
recorder_node in its own process over DDS (isolated domain, see conftest).

Every published message lands in the bag unchanged and in order; SIGTERM closes it; SIGKILL leaves
a repairable bag; bad parameters refuse to start with one line.
"""
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import rclpy
import yaml
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import JointState

from piezo_narx_ros.bag.reader import bag_info, iter_raw, read_uy
from piezo_narx_ros.bag.repair import repair_bag
from piezo_narx_ros.bag.writer import typestore
from piezo_narx_ros.nodes.wire import make_joint_state
from piezo_narx_ros.nodes.qos import sample_qos

T0 = 1_700_000_000_000_000_000
P = 500_000  # ns, 2 kHz
TOPICS = ('voltage_command', 'deflection', 'deflection_estimate')


def start_recorder(out, ns, *params):
    args = [sys.executable, '-m', 'piezo_narx_ros.nodes.recorder_node', '--ros-args',
            '-r', f'__ns:={ns}', '-p', f'output:={out}', *params]
    return subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=dict(os.environ, PYTHONUNBUFFERED='1'))


class Publisher:
    """In-process node publishing JointState samples on the three sample topics."""

    def __init__(self, ns):
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = Node('test_pub', namespace=ns, context=self.context)
        # deflection_estimate offers transient_local: a recorder that stored its own
        # subscription's QoS (volatile) instead of the publisher's would be caught by the test.
        # Deeper than any test publishes: a recorder stalled by a loaded machine gets every
        # sample late rather than some never (keep-last drops the oldest unacknowledged ones).
        latched = sample_qos(depth=10000)
        latched.durability = DurabilityPolicy.TRANSIENT_LOCAL
        self.pubs = {t: self.node.create_publisher(
            JointState, t, latched if t == 'deflection_estimate' else sample_qos(depth=10000))
            for t in TOPICS}

    def wait_matched(self, timeout=20.0):
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if all(p.get_subscription_count() >= 1 for p in self.pubs.values()):
                return True
            time.sleep(0.02)
        return False

    def wait_acked(self, timeout=30.0):
        """Wait until the recorder's readers acknowledged every sample (reliable QoS)."""
        from rclpy.duration import Duration
        return all(p.wait_for_all_acked(Duration(seconds=timeout)) for p in self.pubs.values())

    def publish_samples(self, k_from, k_to):
        """Publish samples k in [k_from, k_to) on all topics at ~2 kHz; returns them per topic."""
        sent = {t: [] for t in TOPICS}
        start = time.monotonic()
        for k in range(k_from, k_to):
            t_k = T0 + k * P
            msgs = {'voltage_command': make_joint_state(t_k, ['x'], effort=[0.01 * k]),
                    'deflection': make_joint_state(t_k, ['x'], position=[1e-9 * k],
                                                   effort=[0.01 * k]),
                    'deflection_estimate': make_joint_state(t_k, ['x'], position=[2e-9 * k])}
            for topic, msg in msgs.items():
                self.pubs[topic].publish(msg)
                sent[topic].append(msg)
            lag = start + (k - k_from + 1) / 2000.0 - time.monotonic()
            if lag > 0.002:
                time.sleep(lag)
        return sent

    def close(self):
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)


def _messages_by_topic(bag, ns):
    # Compared decoded: CDR padding bytes are not defined, so the same message may differ there.
    got = {t: [] for t in TOPICS}
    for topic, msgtype, _, data in iter_raw(bag):
        assert msgtype == 'sensor_msgs/msg/JointState'
        got[topic[len(ns) + 1:]].append(deserialize_message(data, JointState))
    return got


def test_records_everything_and_closes_on_sigterm(tmp_path):
    ns, bag, n = '/rec1', tmp_path / 'run', 2000
    proc = start_recorder(bag, ns)
    pub = Publisher(ns)
    try:
        assert pub.wait_matched(), 'recorder never subscribed'
        sent = pub.publish_samples(0, n)
        assert pub.wait_acked(), 'recorder did not acknowledge every sample'
        time.sleep(0.5)
        proc.send_signal(signal.SIGTERM)
        code = proc.wait(20)
    finally:
        pub.close()
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert code == 0, proc.stderr.read()
    assert (bag / 'metadata.yaml').is_file()
    got = _messages_by_topic(bag, ns)
    for topic in TOPICS:
        assert got[topic] == sent[topic], topic   # nothing lost or reordered, same content
    rec = read_uy(bag, f'{ns}/voltage_command', f'{ns}/deflection')
    assert rec.fs == 2000.0 and len(rec.u) == n
    # Each topic carries its publisher's offered QoS, the type hash and the distro, in the MCAP
    # channel metadata as rosbag2_storage_mcap writes them, and in metadata.yaml.
    from mcap.reader import make_reader
    with open(bag / 'run.mcap', 'rb') as f:
        summary = make_reader(f).get_summary()
    chans = {c.topic: c.metadata for c in summary.channels.values()}
    expect_hash = typestore().hash_rihs01('sensor_msgs/msg/JointState')
    for topic in TOPICS:
        meta = chans[f'{ns}/{topic}']
        assert meta['topic_type_hash'] == expect_hash
        offered = yaml.safe_load(meta['offered_qos_profiles'])
        assert len(offered) == 1 and offered[0]['reliability'] == 'reliable'
        assert offered[0]['durability'] == ('transient_local' if topic == 'deflection_estimate'
                                            else 'volatile'), topic
    info = yaml.safe_load((bag / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    assert info['ros_distro'] == 'kilted'
    durability = {t['topic_metadata']['name']: t['topic_metadata']['offered_qos_profiles'][0]
                  ['durability'] for t in info['topics_with_message_count']}
    assert durability[f'{ns}/deflection_estimate'] == 'transient_local'
    np.testing.assert_allclose(rec.u[:, 0], 0.01 * np.arange(n))
    np.testing.assert_allclose(rec.y[:, 0], 1e-9 * np.arange(n))


def test_sigkill_leaves_a_repairable_bag(tmp_path):
    ns, bag = '/rec2', tmp_path / 'killed'
    # types:=[auto] also exercises discovery: the topics exist only once the publisher is up
    proc = start_recorder(bag, ns, '-p', 'chunk_period_s:=0.1', '-p', 'types:=[auto]')
    pub = Publisher(ns)
    try:
        assert pub.wait_matched(), 'recorder never subscribed'
        pub.publish_samples(0, 600)
        assert pub.wait_acked(), 'recorder did not acknowledge every sample'
        time.sleep(1.0)          # >> chunk period: these 600 samples are on disk
        pub.publish_samples(600, 800)
        proc.send_signal(signal.SIGKILL)
        proc.wait(10)
    finally:
        pub.close()
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert not (bag / 'metadata.yaml').exists()
    rep = repair_bag(bag)
    counts = {t[len(ns) + 1:]: c for t, c in rep.topics.items()}
    assert all(600 <= counts[t] <= 800 for t in TOPICS), counts
    rec = read_uy(bag, f'{ns}/voltage_command', f'{ns}/deflection')
    assert len(rec.u) >= 600
    np.testing.assert_allclose(rec.u[:, 0], 0.01 * np.arange(len(rec.u)))


def test_bad_parameter_refuses_to_start(tmp_path):
    proc = start_recorder(tmp_path / 'x', '/rec3', '-p', 'types:=[a/msg/B, c/msg/D]')
    _, err = proc.communicate(timeout=30)
    assert proc.returncode == 2
    assert err.strip() == ('recorder_node: error: types must have 1 or 3 entries '
                           '(one per topic), got 2')


@pytest.mark.parametrize('types, expected', [
    ('[std_msgs/msg/Nope]', 'message type std_msgs/msg/Nope is not installed'),
    ("['os.system(1)']", "not a ROS 2 message type name: 'os.system(1)'"),
])
def test_unknown_or_malformed_type_is_refused(tmp_path, types, expected):
    proc = start_recorder(tmp_path / 'x', '/rec4', '-p', f'types:={types}')
    _, err = proc.communicate(timeout=30)
    assert proc.returncode == 2 and expected in err


def test_status_reports_waiting_topics_then_closes_the_bag(tmp_path):
    """In-process, no traffic: an 'auto' topic nobody publishes keeps the node in WARN."""
    from rclpy.parameter import Parameter

    from piezo_narx_ros.nodes.diagnostics import DIAG_WARN
    from piezo_narx_ros.nodes.recorder_node import RecorderNode
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    try:
        node = RecorderNode(context=ctx, namespace='/rec5', parameter_overrides=[
            Parameter('output', value=str(tmp_path / 'b')),
            Parameter('topics', value=['voltage_command', 'nobody_publishes']),
            Parameter('types', value=['sensor_msgs/msg/JointState', 'auto'])])
        level, message, values = node._status()
        assert level == DIAG_WARN and message == 'waiting for topic types'
        assert values['topics'] == 1 and values['waiting_for'] == 1 and values['received'] == 0
        node.close()
        node.destroy_node()
    finally:
        rclpy.try_shutdown(context=ctx)
    assert [t.name for t in bag_info(tmp_path / 'b').topics] == ['/rec5/voltage_command']
