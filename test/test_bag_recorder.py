"""BagRecorder (queue + writer thread) without DDS, and the recorder's topic-type rules."""
import threading

import numpy as np
import pytest

from piezo_narx_ros.bag.reader import iter_raw, read_joint_series
from piezo_narx_ros.bag.recorder import BagRecorder, discovered_types, expand_types
from piezo_narx_ros.bag.writer import JOINT_STATE, joint_state_cdr
from piezo_narx_ros.errors import BagError

T0 = 1_700_000_000_000_000_000


def test_concurrent_puts_are_all_written_in_order_per_thread(tmp_path):
    n = 3000
    with BagRecorder(tmp_path / 'b', chunk_period_s=0.05) as rec:
        topics = [rec.add_topic(f'piezo/t{i}', JOINT_STATE) for i in range(3)]

        def produce(topic):
            for k in range(n):
                rec.put(topic, T0 + k, joint_state_cdr(T0 + k * 500_000, effort=(float(k),)))
        threads = [threading.Thread(target=produce, args=(t,)) for t in topics]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    assert rec.received == rec.stats.written == 3 * n and not rec.stats.error
    series = read_joint_series(tmp_path / 'b', dict.fromkeys(topics, 'effort'))
    for t in topics:
        np.testing.assert_array_equal(series[t].values, np.arange(n))
    assert rec.close() is rec.stats   # second close is a no-op


def test_write_error_is_reported_not_raised_in_the_thread(tmp_path):
    rec = BagRecorder(tmp_path / 'b')
    rec.put('/never/added', T0, b'x')
    stats = rec.close()
    assert stats.written == 0 and stats.failed == rec.received == 1
    assert 'was not added' in stats.error
    assert list(iter_raw(tmp_path / 'b')) == []


def test_disk_full_stops_the_writer_with_the_reason_and_counts_the_rest(tmp_path, monkeypatch):
    from piezo_narx_ros.bag import writer
    original, calls = writer.BagWriter.write, []

    def write(self, *args):
        calls.append(1)
        if len(calls) > 5:
            raise OSError(28, 'No space left on device')
        return original(self, *args)
    monkeypatch.setattr(writer.BagWriter, 'write', write)
    rec = BagRecorder(tmp_path / 'b')
    topic = rec.add_topic('piezo/t', JOINT_STATE)
    for k in range(20):
        rec.put(topic, T0 + k, joint_state_cdr(T0 + k * 500_000, effort=(float(k),)))
    stats = rec.close()
    assert (stats.written, stats.failed) == (5, 15) and len(calls) == 6
    assert stats.error == '[Errno 28] No space left on device'


def test_type_rules():
    assert expand_types(['/a', '/b'], ['x/msg/Y']) == ['x/msg/Y', 'x/msg/Y']
    assert expand_types(['/a', '/b'], ['x/msg/Y', '']) == ['x/msg/Y', 'auto']
    with pytest.raises(BagError, match='types must have 1 or 2 entries'):
        expand_types(['/a', '/b'], ['a', 'b', 'c'])
    graph = [('/a', ['sensor_msgs/msg/JointState']), ('/c', ['std_msgs/msg/Float64'])]
    assert discovered_types({'/a': 'auto', '/b': 'auto', '/c': 'x/msg/Y'}, graph) == {
        '/a': 'sensor_msgs/msg/JointState', '/c': 'x/msg/Y'}
