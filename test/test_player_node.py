"""player_node in its own process over DDS: the recorded bytes come back on the selected topics,
paced by the recorded timing / rate; loop repeats; a bad bag exits 2 with one line."""
import os
import subprocess
import sys
import threading
import time

import numpy as np
import rclpy
from rclpy.node import Node
from sensor_msgs.msg import JointState

from piezo_narx_ros.bag.reader import iter_raw
from piezo_narx_ros.bag.writer import write_uy_bag
from piezo_narx_ros.nodes.common import sample_qos

N = 400
FS = 2000.0


def start_player(*params):
    args = [sys.executable, '-m', 'piezo_narx_ros.nodes.player_node', '--ros-args',
            '-p', 'start_delay_s:=0.0', '-p', 'wait_for_subscribers:=1', *params]
    return subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=dict(os.environ, PYTHONUNBUFFERED='1'))


class RawCollector:
    """In-process raw subscriptions: (receive time s, bytes) per topic, spun in a thread."""

    def __init__(self, topics):
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = Node('test_sink', context=self.context)
        self.data = {t: [] for t in topics}
        self.subs = [self.node.create_subscription(
            JointState, t, lambda b, t=t: self.data[t].append((time.monotonic(), b)),
            sample_qos(depth=5000), raw=True) for t in topics]
        from rclpy.executors import SingleThreadedExecutor
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._run = True
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()

    def _spin(self):
        while self._run and self.context.ok():
            self.executor.spin_once(timeout_sec=0.05)

    def close(self):
        self._run = False
        self.thread.join(5)
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)


def _bag(tmp_path, name, topic_prefix):
    u = np.sin(np.arange(N) / 20.0)
    return write_uy_bag(tmp_path / name, u, 1e-6 * u, FS,
                        command_topic=f'{topic_prefix}/voltage_command',
                        deflection_topic=f'{topic_prefix}/deflection')


def test_plays_selected_topic_with_recorded_bytes_and_rate(tmp_path):
    bag = _bag(tmp_path, 'b', '/play1')
    col = RawCollector(['/play1/voltage_command', '/play1/deflection'])
    try:
        proc = start_player('-p', f'bag:={bag}', '-p', 'rate:=2.0',
                            '-p', 'topics:=[/play1/deflection]')
        code = proc.wait(60)
        time.sleep(0.2)
    finally:
        col.close()
    assert code == 0, proc.stderr.read()
    expected = [d for t, _, _, d in iter_raw(bag) if t == '/play1/deflection']
    got = col.data['/play1/deflection']
    assert [b for _, b in got] == expected
    assert col.data['/play1/voltage_command'] == []   # not selected
    span = got[-1][0] - got[0][0]
    recorded = (N - 1) / FS / 2.0                      # 0.1 s at rate 2
    assert 0.8 * recorded < span < 3.0 * recorded, span


def test_loop_repeats_until_stopped(tmp_path):
    bag = _bag(tmp_path, 'b', '/play2')
    col = RawCollector(['/play2/voltage_command'])
    proc = start_player('-p', f'bag:={bag}', '-p', 'loop:=true', '-p', 'rate:=4.0',
                        '-p', 'topics:=[/play2/voltage_command]')
    try:
        end = time.monotonic() + 30
        while len(col.data['/play2/voltage_command']) < 2 * N + 10 and time.monotonic() < end:
            time.sleep(0.05)
        assert proc.poll() is None   # still looping
    finally:
        proc.terminate()
        code = proc.wait(20)
        col.close()
    assert code == 0
    got = [b for _, b in col.data['/play2/voltage_command']]
    assert len(got) >= 2 * N + 10
    assert got[N:2 * N] == got[:N]   # second pass identical to the first


def test_bad_bag_exits_2_with_one_line(tmp_path):
    proc = start_player('-p', f'bag:={tmp_path / "missing"}')
    _, err = proc.communicate(timeout=30)
    assert proc.returncode == 2
    assert err.strip() == f'player_node: error: bag not found: {tmp_path / "missing"}'
