"""
player_node in its own process over DDS.

The recorded bytes come back on the selected topics, paced by the recorded timing / rate; loop
repeats; a bad bag exits 2 with one line.
"""
import os
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
import rclpy
from rclpy.node import Node
from sensor_msgs.msg import JointState

from piezo_narx_ros.bag.reader import iter_raw
from piezo_narx_ros.bag.writer import write_uy_bag
from piezo_narx_ros.nodes.qos import sample_qos

N = 400
FS = 2000.0


def start_player(*params):
    args = [sys.executable, '-m', 'piezo_narx_ros.nodes.player_node', '--ros-args',
            '-p', 'start_delay_s:=0.3', '-p', 'wait_for_subscribers:=1', *params]
    return subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=dict(os.environ, PYTHONUNBUFFERED='1'))


def communicate_or_dump(proc, timeout):
    """proc.communicate(timeout); a hung node is aborted so that its stacks say where."""
    try:
        return proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.send_signal(signal.SIGABRT)   # run_node's faulthandler prints every thread's stack
        _, err = proc.communicate(timeout=20)
        pytest.fail(f'the node did not exit within {timeout} s; its stderr:\n{err}')


class RawCollector:
    """
    In-process raw subscriptions: (DDS source timestamp s, bytes) per topic, spun in a thread.

    The source timestamp is the player's own write time: a span measured on it is the player's
    pacing, not this executor's (which, on a busy machine, can take the first messages late).
    """

    def __init__(self, topics):
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = Node('test_sink', context=self.context)
        self.data = {t: [] for t in topics}
        self.subs = [self.node.create_subscription(JointState, t, self._store(self.data[t]),
                                                   sample_qos(depth=5000), raw=True)
                     for t in topics]
        from rclpy.executors import SingleThreadedExecutor
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._run = True
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()

    @staticmethod
    def _store(into):
        def on_message(raw, info):
            into.append((info['source_timestamp'] * 1e-9, raw))
        return on_message

    def _spin(self):
        while self._run and self.context.ok():
            self.executor.spin_once(timeout_sec=0.05)

    def close(self):
        self._run = False
        self.thread.join(5)
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)


def _bag(tmp_path, name, topic_prefix, n=N):
    u = np.sin(np.arange(n) / 20.0)
    return write_uy_bag(tmp_path / name, u, 1e-6 * u, FS,
                        command_topic=f'{topic_prefix}/voltage_command',
                        deflection_topic=f'{topic_prefix}/deflection')


def test_plays_selected_topic_with_recorded_bytes_and_rate(tmp_path):
    # 1 s recorded (0.5 s played): a 0.1 s span, timed on arrival in this process, failed its
    # 0.8x-3x bounds by tens of ms when the 2-core machine was busy with other test runs.
    n = 2000
    bag = _bag(tmp_path, 'b', '/play1', n)
    expected = [d for t, _, _, d in iter_raw(bag) if t == '/play1/deflection']
    col = RawCollector(['/play1/voltage_command', '/play1/deflection'])
    try:
        proc = start_player('-p', f'bag:={bag}', '-p', 'rate:=2.0',
                            '-p', 'topics:=[/play1/deflection]')
        code = proc.wait(60)
        # The player has ended; this process may still be taking its samples from the queue
        # (in a full suite run under load, 518 of 2000 were still there 0.2 s later).
        end = time.monotonic() + 10.0
        while len(col.data['/play1/deflection']) < len(expected) and time.monotonic() < end:
            time.sleep(0.05)
        time.sleep(0.1)   # anything beyond the bag's messages would show up too
    finally:
        col.close()
    assert code == 0, proc.stderr.read()
    got = col.data['/play1/deflection']
    assert [b for _, b in got] == expected
    assert col.data['/play1/voltage_command'] == []   # not selected
    span = got[-1][0] - got[0][0]
    recorded = (n - 1) / FS / 2.0                      # 0.5 s at rate 2
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


SILENT_SUBSCRIBER = """
import signal, threading, time, rclpy
from sensor_msgs.msg import JointState
from piezo_narx_ros.nodes.qos import sample_qos
rclpy.init()
node = rclpy.create_node('silent_sink')
sub = node.create_subscription(JointState, '/play4/voltage_command', lambda m: None,
                               sample_qos(100))
while sub.get_publisher_count() < 1:
    time.sleep(0.02)
stop = threading.Event()
signal.signal(signal.SIGINT, lambda *_: stop.set())
print('matched', flush=True)
stop.wait()           # then a clean exit: the participant is destroyed, its port released
node.destroy_node()
rclpy.try_shutdown()
"""


def test_a_subscriber_that_stops_acknowledging_costs_the_wait_and_a_warning(tmp_path):
    """A frozen reliable reader (SIGSTOP: its DDS threads stop too) never acknowledges."""
    bag = _bag(tmp_path, 'b', '/play4')
    sink = subprocess.Popen([sys.executable, '-c', SILENT_SUBSCRIBER], stdout=subprocess.PIPE,
                            text=True)
    proc = None
    try:
        # Matched on both sides, then frozen during the player's start delay. Both sides: a sink
        # frozen before the player has matched it is never seen (its discovery data is not
        # resent), and the player waits for it until killed (a CI run did).
        proc = start_player('-p', f'bag:={bag}', '-p', 'rate:=4.0', '-p', 'start_delay_s:=3.0',
                            '-p', 'wait_for_all_acked_s:=1.0',
                            '-p', 'topics:=[/play4/voltage_command]')
        assert sink.stdout.readline().strip() == 'matched'
        lines, matched = [], threading.Event()

        def read_stderr():
            for line in proc.stderr:
                lines.append(line)
                if 'subscriber(s) on every topic; playing in' in line:
                    matched.set()
        reader = threading.Thread(target=read_stderr, daemon=True)
        reader.start()
        assert matched.wait(30), ''.join(lines)
        sink.send_signal(signal.SIGSTOP)
        try:
            proc.wait(30)
        except subprocess.TimeoutExpired:
            proc.send_signal(signal.SIGABRT)   # run_node's faulthandler prints every stack
            proc.wait(20)
        reader.join(20)
        err = ''.join(lines)
    finally:
        # Thawed, the sink drains what was sent to it and exits cleanly. It used to be killed
        # right after SIGCONT, and twice in CI the next DDS test's probe then received nothing
        # from a best-effort writer it had discovered; suspected: a participant killed with a
        # full shared-memory port leaves that port to the next participant given its id.
        sink.send_signal(signal.SIGCONT)
        time.sleep(0.5)
        sink.send_signal(signal.SIGINT)
        try:
            sink.wait(20)
        except subprocess.TimeoutExpired:
            sink.kill()
            sink.wait()
        if proc is not None and proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, err
    assert ('/play4/voltage_command: not every subscriber acknowledged every message within '
            '1 s') in err


def test_bad_bag_exits_2_with_one_line(tmp_path):
    proc = start_player('-p', f'bag:={tmp_path / "missing"}')
    _, err = communicate_or_dump(proc, 30)
    assert proc.returncode == 2
    assert err.strip() == f'player_node: error: bag not found: {tmp_path / "missing"}'


def test_bag_without_a_playable_topic_exits_2_with_one_line(tmp_path):
    from piezo_narx_ros.bag.writer import BagWriter
    with BagWriter(tmp_path / 'empty'):
        pass                                           # a valid bag with no topic at all
    proc = start_player('-p', f'bag:={tmp_path / "empty"}')
    _, err = communicate_or_dump(proc, 30)
    assert proc.returncode == 2
    assert err.strip() == f'player_node: error: no playable topic in {tmp_path / "empty"}'


def _qos(reliability, durability, depth=0, history=3):
    from rosbags.interfaces import (Qos, QosDurability, QosHistory, QosLiveliness,
                                    QosReliability, QosTime)
    inf = QosTime(9223372036, 854775807)
    return Qos(QosHistory(history), depth, QosReliability(reliability), QosDurability(durability),
               inf, inf, QosLiveliness.AUTOMATIC, inf, False)


def test_replay_qos_follows_ros2_bag_play_rules():
    from piezo_narx_ros.bag.player import ReplayQos, replay_qos
    # one offer (depth unknown, as rmw reports remote publishers): its policies, fallback depth
    assert replay_qos([_qos(1, 1)], False, 77) == ReplayQos(1, 1, 77, True)
    assert replay_qos([_qos(2, 2), _qos(2, 2)], True, 5) == ReplayQos(2, 2, 5, True)
    # a recorded depth is not used (ros2 bag play neither): the subscriber may be slow
    assert replay_qos([_qos(1, 2, depth=30, history=1)], False, 5) == ReplayQos(1, 2, 5, True)
    # publishers disagreed, or nothing recorded: the fallback
    assert replay_qos([_qos(1, 2), _qos(2, 2)], True, 9) == ReplayQos(1, 2, 9, False)
    assert replay_qos([], False, 9) == ReplayQos(2, 2, 9, False)


def test_playback_clock_holds_then_follows_the_recorded_time():
    from piezo_narx_ros.bag.player import PlaybackClock
    c = PlaybackClock(start_ns=10**18, rate=2.0)
    assert c.now(123.0) == 10**18                       # before the first message
    c.anchor(5.0, 10**18 + 1000)
    assert c.now(5.5) == 10**18 + 1000                   # the next message not known yet
    c.next_due(10**18 + 1000 + 3 * 10**9)
    assert c.now(5.5) == 10**18 + 1000 + 10**9           # 0.5 s wall at rate 2 = 1 s recorded
    assert c.now(9.0) == 10**18 + 1000 + 3 * 10**9       # not past the message not yet out
    c.anchor(10.0, 10**18)                                # a loop starts over
    c.next_due(10**18 + 2000)                             # the next message is 2 us later
    assert c.now(10.25) == 10**18 + 2000
    c.anchor(11.0, 10**18 + 2000)
    c.next_due(10**18 + 500)                              # the loop starts over next
    assert c.now(13.0) == 10**18 + 2000                  # held until its first message is out
    c.finish()
    assert c.now(100.0) == 10**18 + 2000                 # held after the end


def _probe_clock_player(bag):
    """
    Play `bag` with clock:=true beside a /clock probe; return (exit code, stderr, QoS, clocks).

    QoS: the offered profiles of the two played topics; clocks: (wall s, /clock ns) received.
    """
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from rosgraph_msgs.msg import Clock
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    node = Node('clock_probe', context=ctx)
    clocks = []
    node.create_subscription(Clock, '/clock', lambda m: clocks.append(
        (time.monotonic(), m.clock.sec * 10**9 + m.clock.nanosec)),
        QoSProfile(depth=100, reliability=ReliabilityPolicy.BEST_EFFORT))
    from rclpy.executors import SingleThreadedExecutor
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    proc = subprocess.Popen(
        [sys.executable, '-m', 'piezo_narx_ros.nodes.player_node', '--ros-args',
         '-p', f'bag:={bag}', '-p', 'loop:=true', '-p', 'rate:=0.25',
         '-p', 'clock:=true', '-p', 'clock_rate:=50.0', '-p', 'start_delay_s:=0.0'],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        end = time.monotonic() + 30
        while time.monotonic() < end and not (
                len(clocks) >= 60 and node.get_publishers_info_by_topic('/play3/deflection')):
            ex.spin_once(timeout_sec=0.05)
        info = {t: node.get_publishers_info_by_topic(t)[0].qos_profile
                for t in ('/play3/voltage_command', '/play3/deflection')}
        # What the probe saw, for a failure message: is the player alive, is its /clock writer
        # discovered, with what QoS, and which nodes share the domain.
        writers = [(i.node_name, i.qos_profile.reliability.name)
                   for i in node.get_publishers_info_by_topic('/clock')]
        shm = (sum(1 for f in os.listdir('/dev/shm') if f.startswith('fastdds_'))
               if os.path.isdir('/dev/shm') else None)
        seen = (f'player exit {proc.poll()}; /clock writers {writers}; '
                f'nodes {node.get_node_names()}; fastdds shm files {shm}')
    finally:
        proc.terminate()
        code = proc.wait(20)
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)
    return code, seen + '\n' + proc.stderr.read(), info, clocks


def test_republishes_with_recorded_qos_and_publishes_clock(tmp_path):
    """
    Check that each topic is replayed with its recorded QoS, and /clock.

    A bag whose command publisher offered reliable + transient_local and whose deflection publisher
    offered best effort is replayed with exactly those; clock:=true publishes the recorded time on
    /clock at clock_rate.
    """
    from rclpy.qos import DurabilityPolicy, ReliabilityPolicy

    from piezo_narx_ros.bag.writer import JOINT_STATE, BagWriter, joint_state_cdr
    t0, n = 1_700_000_000_000_000_000, 400
    with BagWriter(tmp_path / 'q') as bag:
        cmd = bag.add_topic('/play3/voltage_command', JOINT_STATE, offered=[_qos(1, 1)])
        dfl = bag.add_topic('/play3/deflection', JOINT_STATE, offered=[_qos(2, 2)])
        for k in range(n):
            t = t0 + k * 500_000
            bag.write(cmd, t, joint_state_cdr(t, effort=(1.0,)))
            bag.write(dfl, t, joint_state_cdr(t, position=(1e-6,)))
    code, err, info, clocks = _probe_clock_player(tmp_path / 'q')
    if not clocks:
        # Not one /clock sample in 30 s while the player's endpoints were discovered: a
        # transport that lost the probe (seen once in a full suite run, never on its own), not
        # the player; one more probe on a new participant.
        code, err, info, clocks = _probe_clock_player(tmp_path / 'q')
    assert clocks, err
    assert code == 0, err
    cmd_qos, dfl_qos = info['/play3/voltage_command'], info['/play3/deflection']
    assert (cmd_qos.reliability, cmd_qos.durability) == (ReliabilityPolicy.RELIABLE,
                                                         DurabilityPolicy.TRANSIENT_LOCAL)
    assert (dfl_qos.reliability, dfl_qos.durability) == (ReliabilityPolicy.BEST_EFFORT,
                                                         DurabilityPolicy.VOLATILE)
    times = np.array([c for _, c in clocks])
    last = t0 + (n - 1) * 500_000
    assert times.min() >= t0 and times.max() <= last                # inside the recording
    assert np.any(np.diff(times) > 0) and np.any(np.diff(times) < 0)   # advances, loops back
    wall = clocks[-1][0] - clocks[0][0]
    assert 20.0 < (len(clocks) - 1) / wall < 80.0                      # ~clock_rate
    # while playing, recorded time advances at `rate` recorded seconds per wall second
    steps = [(b[1] - a[1]) / 1e9 / (b[0] - a[0]) for a, b in zip(clocks, clocks[1:])
             if 0 < b[1] - a[1] and b[0] - a[0] > 0.01]
    assert 0.15 < float(np.median(steps)) < 0.4
