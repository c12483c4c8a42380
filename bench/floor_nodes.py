"""
Bare stand-ins for the pipeline's nodes: the floor that `bench_live.py --floor` measures against.

Each stand-in has its real node's name, topics, QoS (nodes.qos.sample_qos), executor and spin loop
(nodes.runtime.run_node), batch and message sizes, and decodes and encodes what the real node does
with the same codec (nodes.codec); it computes nothing:

- command: the real node's paced loop publishing a signal computed before the stream, `batch`
  samples per message, the same stamps t0 + k/fs;
- simulator: each command message answered with one deflection message of the same stamps, the
  commands copied into position and effort;
- estimator: each command message answered with one estimate message, the commands copied into
  position; the deflection stream taken and decoded as the estimator takes it once its free run
  is steady (the batches of the newest `window` samples held and decoded once a second, single
  messages one by one).

No /diagnostics, no timers, no checks. So a real node's CPU over its floor's is what the
package's own work costs above rclpy's and Fast DDS's for the same traffic.

    python bench/floor_nodes.py simulator --ros-args -r __ns:=/floor -p fs:=20000.0 -p batch:=20
"""
from __future__ import annotations

import math
import sys
import time

import numpy as np

from piezo_narx_ros.nodes.wire.batching import BATCH_PARAM, HeldBatches, batch_topic, sample_type
from piezo_narx_ros.nodes.wire import (decode_joint_state, decode_joint_trajectory,
                                       encode_joint_state, encode_joint_trajectory)
from piezo_narx_ros.nodes.params import ParamSpec
from piezo_narx_ros.nodes.runtime import PiezoNode, run_node
from piezo_narx_ros.nodes.topics import TOPIC_COMMAND, TOPIC_DEFLECTION, TOPIC_ESTIMATE

FS = ParamSpec('fs', 2000.0, 'sample rate, Hz', low=1.0, high=100000.0, read_only=True)
AXES = ParamSpec('axes', ['x'], 'axis names on the streams', read_only=True)
#: Measurement samples the floor estimator holds, decoded once a second: the estimator's
#: default running-error window, which its node holds the same way (HeldBatches keep).
WINDOW = 2000


class FloorCommand(PiezoNode):
    """command_node's traffic: `seconds` of samples at fs, `batch` per message, paced."""

    NODE_NAME = 'command_node'
    PARAMS = (FS, AXES, BATCH_PARAM,
              ParamSpec('seconds', 20.0, 'stream length, s', low=1e-3, high=3600.0),
              ParamSpec('amplitude', 100.0, 'peak command, V', low=0.0, high=1000.0),
              ParamSpec('wait_for_subscribers', 3, 'subscriptions matched before sample 0',
                        low=0, high=1000),
              ParamSpec('start_delay_s', 0.5, 'then this long before sample 0, s', low=0.0,
                        high=60.0))

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        from piezo_narx_ros.plant.signals import generate
        p = self.params
        self.fs, self.batch, self.axes = p['fs'], p['batch'], list(p['axes'])
        self.n = int(round(p['seconds'] * self.fs))
        u = np.column_stack([generate('multisine', self.fs, p['seconds'], p['amplitude'],
                                      seed=i)[:self.n] for i in range(len(self.axes))])
        self.u = u if self.batch > 1 else u.tolist()
        self.offsets = np.arange(self.n, dtype=np.int64) * 1_000_000_000 // int(self.fs) \
            if float(self.fs).is_integer() else np.round(np.arange(self.n) * 1e9 / self.fs)
        self.pub = self.sample_publisher(batch_topic(TOPIC_COMMAND, self.batch),
                                         sample_type(self.batch))
        self.k = 0
        self.start_ns = None
        self.matched_at = None

    def take_pacing(self) -> bool:
        return True

    def pace(self) -> float:
        """Publish the messages due; return the wait until the next one is due, s."""
        now = time.monotonic_ns()
        if self.start_ns is None:
            if not self._ready():
                return 0.005
            self.start_ns, self.stamps = now, self.get_clock().now().nanoseconds + self.offsets
        if self.k >= self.n:
            return 0.1
        due = min(self.n, (now - self.start_ns) * int(self.fs) // 1_000_000_000 + 1)
        b, pub, names = self.batch, self.pub, self.axes
        while self.k + b <= due or (due == self.n and self.k < self.n):
            j = min(self.k + b, self.n)
            if b > 1:
                pub.publish(encode_joint_trajectory(self.stamps[self.k:j], names,
                                                    effort=self.u[self.k:j]))
            else:
                pub.publish(encode_joint_state(int(self.stamps[self.k]), names,
                                               effort=self.u[self.k]))
            self.k = j
        # Wake when the sample that completes the next message is due.
        last = min(self.k + b, self.n) - 1
        wake = self.start_ns + math.ceil(last * 1e9 / self.fs)
        return min(max(wake - time.monotonic_ns(), 0) * 1e-9, 0.1)

    def _ready(self) -> bool:
        need = self.params['wait_for_subscribers']
        if self.pub.get_subscription_count() < need:
            self.matched_at = None
            return False
        if self.matched_at is None:
            self.matched_at = time.monotonic()
        return time.monotonic() - self.matched_at >= self.params['start_delay_s']


class FloorSimulator(PiezoNode):
    """simulator_node's traffic: every command message answered with one deflection message."""

    NODE_NAME = 'simulator_node'
    PARAMS = (FS, AXES, BATCH_PARAM)

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        b, self.names = self.params['batch'], list(self.params['axes'])
        self.pub = self.sample_publisher(batch_topic(TOPIC_DEFLECTION, b), sample_type(b))
        self.sub = self.sample_subscription(batch_topic(TOPIC_COMMAND, b),
                                            self.on_batch if b > 1 else self.on_one,
                                            sample_type(b))

    def on_one(self, raw: bytes) -> None:
        s = decode_joint_state(raw)
        self.pub.publish(encode_joint_state(s.t_ns, self.names, s.effort, s.effort))

    def on_batch(self, raw: bytes) -> None:
        b = decode_joint_trajectory(raw)
        self.pub.publish(encode_joint_trajectory(b.t_ns, self.names, b.effort, b.effort))


class FloorEstimator(PiezoNode):
    """estimator_node's traffic: commands in, one estimate message each; deflections taken."""

    NODE_NAME = 'estimator_node'
    PARAMS = (FS, AXES, BATCH_PARAM)

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        b, self.names = self.params['batch'], list(self.params['axes'])
        self.pub = self.sample_publisher(batch_topic(TOPIC_ESTIMATE, b), sample_type(b))
        self.sub_cmd = self.sample_subscription(batch_topic(TOPIC_COMMAND, b),
                                                self.on_batch if b > 1 else self.on_one,
                                                sample_type(b))
        self.held = HeldBatches(1, keep=WINDOW)
        self.sub_meas = self.sample_subscription(
            batch_topic(TOPIC_DEFLECTION, b),
            self.on_measurement_batch if b > 1 else decode_joint_state, sample_type(b))
        if b > 1:    # the estimator's diagnostics tick hands the held ones over
            self.take_timer = self.create_timer(1.0, self.held.take)

    def on_one(self, raw: bytes) -> None:
        s = decode_joint_state(raw)
        self.pub.publish(encode_joint_state(s.t_ns, self.names, position=s.effort))

    def on_batch(self, raw: bytes) -> None:
        b = decode_joint_trajectory(raw)
        self.pub.publish(encode_joint_trajectory(b.t_ns, self.names, position=b.effort))

    def on_measurement_batch(self, raw: bytes) -> None:
        if self.held.push(raw):
            self.held.take()


ROLES = {'command': FloorCommand, 'simulator': FloorSimulator, 'estimator': FloorEstimator}

if __name__ == '__main__':
    if len(sys.argv) < 2 or sys.argv[1] not in ROLES:
        print(f'usage: floor_nodes.py {{{",".join(ROLES)}}} --ros-args ...', file=sys.stderr)
        sys.exit(2)
    sys.exit(run_node(ROLES[sys.argv[1]], sys.argv[:1] + sys.argv[2:]))
