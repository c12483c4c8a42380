"""
Bags written by bag.writer.

Exact round trip, and independent reads with mcap/mcap-ros2 and rosbags; read_uy on bags from other
writers (sqlite3 storage, a lone .mcap from mcap-ros2).
"""
import numpy as np
import pytest
import yaml

from piezo_narx_ros.bag.reader import bag_info, iter_raw, read_joint_series, read_uy
from piezo_narx_ros.bag.writer import (JOINT_STATE, BagWriter, joint_state_cdr, typestore,
                                       write_uy_bag)
from piezo_narx_ros.errors import BagError

FS = 2000.0
T0 = 1_700_000_000_123_456_789


def _signals(n=600, seed=3):
    rng = np.random.default_rng(seed)
    return rng.uniform(-5, 5, n), rng.normal(0, 1e-6, n)


@pytest.fixture(scope='module')
def uy_bag(tmp_path_factory):
    u, y = _signals()
    path = tmp_path_factory.mktemp('io') / 'run1'
    write_uy_bag(path, u, y, FS, t0_ns=T0, latency_ns=40_000)
    return path, u, y


def test_round_trip_exact_bytes_times_and_stamps(tmp_path):
    stamps = [T0 + k * 500_000 for k in range(50)]
    payloads = {}
    with BagWriter(tmp_path / 'b') as bag:
        cmd = bag.add_topic('piezo/voltage_command', JOINT_STATE)
        diag = bag.add_topic('/diagnostics', 'diagnostic_msgs/msg/DiagnosticArray', depth=10)
        for k, t in enumerate(stamps):
            data = joint_state_cdr(t, ('x',), effort=(0.1 * k,))
            payloads[(cmd, t + 7)] = data
            bag.write(cmd, t + 7, data)
        empty_diag = bytes(typestore().serialize_cdr(
            typestore().types['diagnostic_msgs/msg/DiagnosticArray'](
                header=typestore().types['std_msgs/msg/Header'](
                    stamp=typestore().types['builtin_interfaces/msg/Time'](sec=1, nanosec=2),
                    frame_id='f'), status=[]), 'diagnostic_msgs/msg/DiagnosticArray'))
        bag.write(diag, stamps[-1] + 99, empty_diag)
    got = list(iter_raw(tmp_path / 'b'))
    assert len(got) == 51
    for topic, msgtype, t, data in got[:-1]:
        assert (topic, msgtype) == ('/piezo/voltage_command', JOINT_STATE)
        assert data == payloads[(topic, t)]
    assert got[-1] == ('/diagnostics', 'diagnostic_msgs/msg/DiagnosticArray', stamps[-1] + 99,
                       empty_diag)
    series = read_joint_series(tmp_path / 'b', {'/piezo/voltage_command': 'effort'})
    s = series['/piezo/voltage_command']
    np.testing.assert_array_equal(s.stamps_ns, stamps)
    np.testing.assert_array_equal(s.log_ns, np.array(stamps) + 7)
    np.testing.assert_array_equal(s.values, 0.1 * np.arange(50))


def test_read_uy_gives_the_written_record(uy_bag):
    path, u, y = uy_bag
    rec = read_uy(path)
    np.testing.assert_array_equal(rec.u[:, 0], u)
    np.testing.assert_array_equal(rec.y[:, 0], y)
    assert rec.fs == FS
    assert rec.t[0] == 0.0 and rec.t[-1] == pytest.approx((u.size - 1) / FS, abs=1e-12)
    assert rec.source == str(path)
    # leading '/' or not, directory or the .mcap file inside it: same record
    rec2 = read_uy(path / f'{path.name}.mcap', '/piezo/voltage_command', 'piezo/deflection/')
    np.testing.assert_array_equal(rec2.y[:, 0], y)


def test_independent_read_with_mcap_and_mcap_ros2(uy_bag):
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory
    path, u, y = uy_bag
    with open(path / f'{path.name}.mcap', 'rb') as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        header = reader.get_header()
        summary = reader.get_summary()
        assert header.profile == 'ros2'
        assert {s.name: s.encoding for s in summary.schemas.values()} == {JOINT_STATE: 'ros2msg'}
        chans = {c.topic: c for c in summary.channels.values()}
        assert set(chans) == {'/piezo/voltage_command', '/piezo/deflection'}
        for c in chans.values():
            assert c.message_encoding == 'cdr'
            qos = yaml.safe_load(c.metadata['offered_qos_profiles'])
            assert qos[0]['reliability'] == 'reliable' and qos[0]['depth'] == 100
        stats = summary.statistics
        assert stats.message_count == 2 * u.size
        assert sorted(stats.channel_message_counts.values()) == [u.size, u.size]
        metas = {m.name: m.metadata for m in reader.iter_metadata()}
        info = yaml.safe_load(metas['rosbag2']['serialized_metadata'])
        assert info['message_count'] == 2 * u.size and info['storage_identifier'] == 'mcap'
        ys = [decoded.position[0] for _, _, _, decoded in
              reader.iter_decoded_messages(topics=['/piezo/deflection'])]
    np.testing.assert_array_equal(ys, y)


def test_independent_read_with_rosbags_anyreader(uy_bag):
    from rosbags.highlevel import AnyReader
    path, u, _ = uy_bag
    with AnyReader([path]) as reader:
        assert reader.message_count == 2 * u.size
        conns = [c for c in reader.connections if c.topic == '/piezo/voltage_command']
        assert conns[0].ext.offered_qos_profiles[0].depth == 100
        us = [reader.deserialize(raw, c.msgtype).effort[0]
              for c, _, raw in reader.messages(connections=conns)]
    np.testing.assert_array_equal(us, u)


def test_info_reports_topics_counts_rate(uy_bag):
    path, u, _ = uy_bag
    info = bag_info(path)
    assert info.storage == 'mcap' and info.message_count == 2 * u.size
    by = {t.name: t for t in info.topics}
    assert by['/piezo/deflection'].count == u.size
    assert by['/piezo/deflection'].rate_hz == FS and by['/piezo/deflection'].gaps == 0
    assert by['/piezo/deflection'].duration_s == pytest.approx((u.size - 1) / FS)


def test_sqlite3_bag_like_ros2_bag_record(tmp_path):
    from rosbags.rosbag2 import StoragePlugin, Writer
    u, y = _signals(200)
    store = typestore()
    with Writer(tmp_path / 'sq', version=8, storage_plugin=StoragePlugin.SQLITE3) as w:
        c_u = w.add_connection('/piezo/voltage_command', JOINT_STATE, typestore=store)
        c_y = w.add_connection('/piezo/deflection', JOINT_STATE, typestore=store)
        for k in range(u.size):
            t = T0 + k * 1_000_000
            w.write(c_u, t + 10, joint_state_cdr(t, ('x',), effort=(u[k],)))
            w.write(c_y, t + 20, joint_state_cdr(t, ('x',), position=(y[k],), effort=(u[k],)))
    rec = read_uy(tmp_path / 'sq')
    assert rec.fs == 1000.0
    np.testing.assert_array_equal(rec.u[:, 0], u)
    np.testing.assert_array_equal(rec.y[:, 0], y)
    assert bag_info(tmp_path / 'sq').storage == 'sqlite3'


def test_lone_mcap_from_mcap_ros2_writer(tmp_path):
    from mcap_ros2.writer import Writer
    u, y = _signals(100)
    msgdef, _ = typestore().generate_msgdef(JOINT_STATE, ros_version=2)
    path = tmp_path / 'foreign.mcap'
    with open(path, 'wb') as f:
        w = Writer(f)
        schema = w.register_msgdef(JOINT_STATE, msgdef)
        for k in range(u.size):
            t = T0 + k * 500_000
            stamp = {'sec': t // 10**9, 'nanosec': t % 10**9}
            w.write_message('/piezo/voltage_command', schema, {
                'header': {'stamp': stamp, 'frame_id': ''}, 'name': ['x'], 'position': [],
                'velocity': [], 'effort': [u[k]]}, log_time=t)
            w.write_message('/piezo/deflection', schema, {
                'header': {'stamp': stamp, 'frame_id': ''}, 'name': ['x'], 'position': [y[k]],
                'velocity': [], 'effort': [u[k]]}, log_time=t + 1)
        w.finish()
    rec = read_uy(path)
    np.testing.assert_array_equal(rec.u[:, 0], u)
    np.testing.assert_array_equal(rec.y[:, 0], y)


def test_writer_refuses_existing_path_and_unknown_type(tmp_path):
    (tmp_path / 'exists').mkdir()
    with pytest.raises(BagError, match='already exists'):
        BagWriter(tmp_path / 'exists')
    with BagWriter(tmp_path / 'b') as bag:
        with pytest.raises(BagError, match="unknown message type 'my_pkg/msg/Foo'"):
            bag.add_topic('foo', 'my_pkg/msg/Foo')
        with pytest.raises(BagError, match='was not added'):
            bag.write('/bar', 1, b'')


def test_rclpy_serialized_payloads_with_trailing_bytes_are_read(tmp_path):
    """
    Check that rclpy's serialize_message returns 8 bytes more than the message.

    Such bytes, republished and recorded, must still decode.
    """
    from rclpy.serialization import serialize_message

    from piezo_narx_ros.nodes.wire import make_joint_state
    with BagWriter(tmp_path / 'b') as bag:
        c = bag.add_topic('piezo/voltage_command', JOINT_STATE)
        d = bag.add_topic('piezo/deflection', JOINT_STATE)
        for k in range(20):
            t = T0 + k * 500_000
            raw_u = serialize_message(make_joint_state(t, ['x'], effort=[0.5 * k]))
            assert len(raw_u) > len(joint_state_cdr(t, effort=(0.5 * k,))) + 3
            bag.write(c, t, raw_u)
            bag.write(d, t, serialize_message(make_joint_state(t, ['x'], position=[1e-6 * k])))
    rec = read_uy(tmp_path / 'b')
    np.testing.assert_array_equal(rec.u[:, 0], 0.5 * np.arange(20))
    np.testing.assert_array_equal(rec.y[:, 0], 1e-6 * np.arange(20))
