"""recorder_node: record topics to a rosbag2 MCAP bag (like `ros2 bag record -s mcap`).

Subscriptions are raw (serialized CDR, never decoded); each message is stamped with its receive
time (system clock, ns) and handed to a BagRecorder, whose writer thread does the file work.
SIGINT/SIGTERM close the bag (summary and metadata.yaml); after SIGKILL,
`piezo-narx bag repair BAG` restores it.

    recorder_node --ros-args -p output:=bags/run1 \
        -p topics:="[voltage_command, deflection, deflection_estimate]"
"""
from __future__ import annotations

import importlib
import re
import time
from datetime import datetime

from rclpy.qos import ReliabilityPolicy

from piezo_narx_ros.bag.recorder import (AUTO_TYPE, BagRecorder, discovered_types,
                                         expand_types)
from piezo_narx_ros.errors import BagError, ConfigError
from piezo_narx_ros.nodes.common import (DIAG_ERROR, DIAG_OK, DIAG_WARN, Diagnostics, ParamSpec,
                                         PiezoNode, main_for)

_TYPE_NAME = re.compile(r'^([a-z][a-z0-9_]*)/msg/([A-Z][A-Za-z0-9]*)$')


def message_class(msgtype: str):
    """The installed rclpy message class of 'pkg/msg/Name'. Only names of that exact form are
    imported (from installed packages); ConfigError otherwise."""
    m = _TYPE_NAME.match(msgtype)
    if not m:
        raise ConfigError(f'not a ROS 2 message type name: {msgtype!r}')
    try:
        return getattr(importlib.import_module(f'{m.group(1)}.msg'), m.group(2))
    except (ImportError, AttributeError):
        raise ConfigError(f'message type {msgtype} is not installed') from None


class _Sink:
    """Raw subscription callback for one topic: bytes -> recorder queue, stamped on receipt.

    The receive time is taken here, not from MessageInfo: callbacks taking MessageInfo fail with
    a SystemError under the EventsExecutor of these rclpy wheels."""

    def __init__(self, recorder: BagRecorder, topic: str):
        self.recorder, self.topic = recorder, topic

    def __call__(self, data: bytes) -> None:
        self.recorder.put(self.topic, time.time_ns(), data)


class RecorderNode(PiezoNode):
    """Thin wiring: parameters -> BagRecorder, raw subscriptions, discovery timer, diagnostics."""

    NODE_NAME = 'recorder_node'
    PARAMS = (
        ParamSpec('output', '', 'bag directory to create (must not exist); '
                  'empty: bags/rec_YYYYmmdd_HHMMSS', read_only=True),
        ParamSpec('topics', ['voltage_command', 'deflection', 'deflection_estimate'],
                  'topics to record, relative to the node namespace or absolute', read_only=True,
                  check=(lambda v: len(v) > 0 and all(v), 'must list non-empty topic names')),
        ParamSpec('types', ['sensor_msgs/msg/JointState'],
                  "message type of every topic (1 entry) or of each topic; 'auto' = discover",
                  read_only=True),
        ParamSpec('chunk_period_s', 0.5, 'longest time between writes to disk (bounds the loss '
                  'on SIGKILL), s', low=0.01, high=60.0, read_only=True),
        ParamSpec('discovery_period_s', 0.2, "how often 'auto' topics are looked up, s",
                  low=0.01, high=10.0, read_only=True),
    )

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        p = self.params
        topics = [self.resolve_topic_name(t) for t in p['topics']]
        self._wanted = dict(zip(topics, expand_types(topics, p['types'])))
        for kind in set(self._wanted.values()) - {AUTO_TYPE}:
            message_class(kind)  # refuse unknown types at start-up
        output = p['output'] or datetime.now().strftime('bags/rec_%Y%m%d_%H%M%S')
        self.recorder = BagRecorder(output, chunk_period_s=p['chunk_period_s'],
                                    custom_data={'recorded_by': 'piezo_narx_ros recorder_node'})
        self._subs = {}
        self._discovery = None
        self._subscribe_known()
        if len(self._subs) < len(self._wanted):
            self._discovery = self.create_timer(p['discovery_period_s'], self._subscribe_known)
        self._diag = Diagnostics(self, self._status, task='bag recording')
        self.get_logger().info(f'recording {len(self._wanted)} topic(s) to {output}')

    def _subscribe_known(self) -> None:
        pending = {t: k for t, k in self._wanted.items() if t not in self._subs}
        graph = self.get_topic_names_and_types() if AUTO_TYPE in pending.values() else []
        for topic, kind in discovered_types(pending, graph).items():
            try:
                cls = message_class(kind)
                sub = self.sample_subscription(topic, _Sink(self.recorder, topic), cls)
                qos = sub.qos_profile   # after the user's qos_overrides
                try:
                    self.recorder.add_topic(topic, kind,
                                            qos.reliability == ReliabilityPolicy.RELIABLE,
                                            qos.depth)
                except BagError:
                    self.destroy_subscription(sub)
                    raise
            except (BagError, ConfigError) as exc:
                self.get_logger().error(f'cannot record {topic}: {exc}')
                self._wanted.pop(topic)
                continue
            self._subs[topic] = sub
            self.get_logger().info(f'subscribed {topic} [{kind}]')
        if self._discovery is not None and len(self._subs) == len(self._wanted):
            self._discovery.cancel()

    def pending_parameter_prefixes(self) -> list[str]:
        """QoS overrides of the topics whose type is not discovered yet (subscribed later)."""
        return [f'qos_overrides.{t}.subscription.' for t in self._wanted if t not in self._subs]

    def _status(self):
        s = self.recorder.stats
        values = {'path': str(self.recorder.path), 'received': self.recorder.received,
                  'written': s.written, 'backlog': self.recorder.backlog, 'queue_peak': s.queue_peak,
                  'topics': len(self._subs), 'waiting_for': len(self._wanted) - len(self._subs)}
        if s.error:
            return DIAG_ERROR, f'writer stopped: {s.error}', values
        if len(self._subs) < len(self._wanted):
            return DIAG_WARN, 'waiting for topic types', values
        return DIAG_OK, 'recording', values

    def close(self) -> None:
        """Stop recording: write the queue, the MCAP summary and metadata.yaml."""
        for sub in self._subs.values():
            self.destroy_subscription(sub)
        stats = self.recorder.close()
        print(f'recorder_node: wrote {stats.written} message(s) to {self.recorder.path}',
              flush=True)


main = main_for(RecorderNode)

if __name__ == '__main__':
    main()
