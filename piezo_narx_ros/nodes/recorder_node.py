"""
recorder_node: record topics to a rosbag2 MCAP bag (like `ros2 bag record -s mcap`).

Subscriptions are raw (serialized CDR, never decoded); each message is stamped with its receive
time (system clock, ns) and handed to a BagRecorder, whose writer thread does the file work. A
topic enters the bag at its first message, with the QoS profiles its publishers offer (from the
ROS graph, as `ros2 bag record` stores them) so that a player can republish with the same QoS.
SIGINT/SIGTERM/SIGHUP close the bag (summary and metadata.yaml) after taking what DDS already
delivered; after SIGKILL,
`piezo-narx bag repair BAG` restores it.

    recorder_node --ros-args -p output:=bags/run1 \
        -p topics:="[voltage_command, deflection, deflection_estimate]"
"""
from __future__ import annotations

import importlib
import os
import re
import sys
import time
from datetime import datetime
from functools import partial


from piezo_narx_ros.bag.recorder import (AUTO_TYPE, BagRecorder, discovered_types,
                                         expand_types)
from piezo_narx_ros.bag.writer import (JOINT_STATE, JOINT_TRAJECTORY, check_type,
                                       qos_from_rclpy, typestore)
from piezo_narx_ros.errors import BagError, ConfigError
from piezo_narx_ros.nodes.wire.batching import BATCH_PARAM, batch_topic
from piezo_narx_ros.nodes.diagnostics import DIAG_ERROR, DIAG_OK, DIAG_WARN, Diagnostics
from piezo_narx_ros.nodes.params import ParamSpec
from piezo_narx_ros.nodes.runtime import PiezoNode, main_for

_TYPE_NAME = re.compile(r'^([a-z][a-z0-9_]*)/msg/([A-Z][A-Za-z0-9]*)$')


def message_class(msgtype: str):
    """
    Return the installed rclpy message class of 'pkg/msg/Name'.

    Only names of that exact form are imported (from installed packages); ConfigError otherwise.
    """
    m = _TYPE_NAME.match(msgtype)
    if not m:
        raise ConfigError(f'not a ROS 2 message type name: {msgtype!r}')
    try:
        return getattr(importlib.import_module(f'{m.group(1)}.msg'), m.group(2))
    except (ImportError, AttributeError):
        raise ConfigError(f'message type {msgtype} is not installed') from None


class _Sink:
    """
    Raw subscription callback for one topic: bytes -> recorder queue, stamped on receipt.

    The first message registers the topic in the bag (`register()` -> its bag name): by then its
    publisher has been discovered, so its offered QoS is known. The receive time is taken here,
    not from MessageInfo: callbacks taking MessageInfo fail with a SystemError under the
    EventsExecutor of these rclpy wheels.
    """

    def __init__(self, recorder: BagRecorder, register):
        self.recorder, self.register, self.name = recorder, register, None

    def __call__(self, data: bytes) -> None:
        t_ns = time.time_ns()
        if self.name is None:
            self.name = self.register()
        self.recorder.put(self.name, t_ns, data)


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
        ParamSpec('batch', 1, 'batch > 1: record the batched streams of nodes run with that '
                  'batch: each JointState topic becomes <topic>_batch, JointTrajectory',
                  low=BATCH_PARAM.low, high=BATCH_PARAM.high, read_only=True),
    )

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        p = self.params
        topics = [self.resolve_topic_name(t) for t in p['topics']]
        self._wanted = dict(zip(topics, expand_types(topics, p['types'])))
        if p['batch'] > 1:      # the nodes' batched streams (DESIGN.md "High-rate streams")
            self._wanted = {(batch_topic(t, p['batch']) if k == JOINT_STATE else t):
                            (JOINT_TRAJECTORY if k == JOINT_STATE else k)
                            for t, k in self._wanted.items()}
        for kind in set(self._wanted.values()) - {AUTO_TYPE}:
            message_class(kind)  # refuse unknown types at start-up
        # `output:=~/x` reaches the node unexpanded (no shell expands a ~ after ':='): a folder
        # named '~' in the working directory was created.
        output = os.path.expanduser(p['output'] or
                                    datetime.now().strftime('bags/rec_%Y%m%d_%H%M%S'))
        self.recorder = BagRecorder(output, chunk_period_s=p['chunk_period_s'],
                                    custom_data={'recorded_by': 'piezo_narx_ros recorder_node'})
        self._subs = {}
        self._sinks: dict[str, _Sink] = {}
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
                check_type(kind)
                cls = message_class(kind)
            except (BagError, ConfigError) as exc:
                self.get_logger().error(f'cannot record {topic}: {exc}')
                self._wanted.pop(topic)
                continue
            # The topic enters the bag at its first message (see _Sink, _register).
            self._sinks[topic] = _Sink(self.recorder, partial(self._register, topic, kind))
            self._subs[topic] = self.sample_subscription(topic, self._sinks[topic], cls)
            self.get_logger().info(f'subscribed {topic} [{kind}]')
        if self._discovery is not None and len(self._subs) == len(self._wanted):
            self._discovery.cancel()

    def pending_parameter_prefixes(self) -> list[str]:
        """Return the QoS overrides of the topics whose type is not discovered yet."""
        return [f'qos_overrides.{t}.subscription.' for t in self._wanted if t not in self._subs]

    def _register(self, topic: str, kind: str) -> str:
        """Add `topic` to the bag with the QoS its publishers offer now; returns its bag name."""
        infos = self.get_publishers_info_by_topic(topic)
        expected = typestore().hash_rihs01(kind)
        for info in infos:
            advertised = str(info.topic_type_hash)
            if advertised not in (expected, 'INVALID'):
                # The bag embeds the Kilted definition; a publisher built from another one
                # writes bytes that definition may not decode.
                self.get_logger().warning(
                    f'{topic}: publisher {info.node_namespace}/{info.node_name} has type hash '
                    f'{advertised}, the recorded definition has {expected}')
        return self.recorder.add_topic(topic, kind, offered=[qos_from_rclpy(i.qos_profile)
                                                             for i in infos])

    def _status(self):
        s = self.recorder.stats
        values = {'path': str(self.recorder.path), 'received': self.recorder.received,
                  'written': s.written, 'backlog': self.recorder.backlog,
                  'queue_peak': s.queue_peak, 'topics': len(self._subs),
                  'waiting_for': len(self._wanted) - len(self._subs)}
        if s.error:
            return DIAG_ERROR, f'writer stopped: {s.error}', values
        if len(self._subs) < len(self._wanted):
            return DIAG_WARN, 'waiting for topic types', values
        return DIAG_OK, 'recording', values

    def drain_count(self) -> int:
        """Messages received so far (run_node drains the queues on a stop signal)."""
        return self.recorder.received

    def close(self) -> None:
        """Stop recording: write the queue, the MCAP summary and metadata.yaml."""
        for sub in self._subs.values():
            self.destroy_subscription(sub)
        for sink in self._sinks.values():   # subscribed, never received: in the bag, empty
            if sink.name is None:
                sink.name = sink.register()
        stats = self.recorder.close()
        print(f'recorder_node: wrote {stats.written} message(s) to {self.recorder.path}',
              flush=True)
        if stats.error:
            print(f'recorder_node: error: writer stopped: {stats.error} ({stats.failed} '
                  f'message(s) not written); `piezo-narx bag repair {self.recorder.path}` '
                  'recovers what was', file=sys.stderr, flush=True)


main = main_for(RecorderNode)

if __name__ == '__main__':
    main()
