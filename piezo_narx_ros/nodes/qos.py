"""
QoS of the per-sample streams.

The default profile, rclpy's standard overrides, and QosWatch (incompatible peers reported on
/diagnostics for as long as they exist).
"""
from __future__ import annotations

import copy
from typing import Any

from rclpy._rclpy_pybind11 import RCLError
from rclpy.duration import Duration, Infinite
from rclpy.event_handler import PublisherEventCallbacks, SubscriptionEventCallbacks
from rclpy.node import Node
from rclpy.qos import (DurabilityPolicy, HistoryPolicy, QoSCompatibility, QoSProfile,
                       ReliabilityPolicy, qos_check_compatible)
from rclpy.qos_overriding_options import QoSOverridingOptions

from piezo_narx_ros.errors import ConfigError

# Keep-last depth of the per-sample streams: 5 s at 2 kHz, so a stalled subscriber loses nothing
# (memory is used only while it is behind). With 1000, a CPU-starved estimator lost commands.
SAMPLE_DEPTH = 10000


def sample_qos(depth: int = SAMPLE_DEPTH) -> QoSProfile:
    """
    Return the QoS of the per-sample streams.

    Reliable, keep-last `depth`, volatile (identification must lose nothing). Users change it with
    the standard QoS overrides (see `qos_overriding`), not with per-node parameters.
    """
    if depth < 1:
        raise ConfigError(f'qos depth must be >= 1, got {depth}')
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=int(depth),
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.VOLATILE,
    )


def qos_overriding() -> QoSOverridingOptions:
    """
    Return rclpy's standard QoS overrides (history, depth, reliability) for one endpoint.

    One publisher or subscription: read-only parameters
    `qos_overrides./TOPIC.publisher.reliability` etc., set with `-p` or a params file like any
    parameter (docs/nodes.md).
    """
    return QoSOverridingOptions.with_default_policies()


def _unset_infinite(profile: QoSProfile) -> QoSProfile:
    """
    Copy `profile` with infinite deadline, lifespan and liveliness lease written as unset (0).

    The graph reports a peer's unset durations as Infinite while our own profiles hold 0; both mean
    'none', but rmw's compatibility check reads Infinite-against-0 as 'Subscription has a deadline,
    but publisher does not'.
    """
    out = copy.copy(profile)
    for name in ('deadline', 'lifespan', 'liveliness_lease_duration'):
        if getattr(out, name) == Infinite:
            setattr(out, name, Duration())
    return out


class QosWatch:
    """
    Incompatible QoS between a node's sample streams and their peers, for /diagnostics.

    Endpoints registered with `add` get rclpy's incompatible-QoS event callback, which logs the
    moment it happens, and are checked against the ROS graph at every diagnostics tick
    (`problems`), so the warning lasts as long as the incompatible peer exists rather than one
    tick: a best-effort publisher leaves a reliable subscriber with nothing, and only the graph
    says so while it lasts.
    """

    def __init__(self, node: Node):
        self._node = node
        self._endpoints: list[tuple[str, Any]] = []   # ('publisher' | 'subscription', entity)
        self.events = 0

    def callbacks(self, kind: str, topic: str):
        """Return the event callbacks to pass to create_publisher / create_subscription."""
        def on_incompatible(status) -> None:
            self.events += 1
            policy = getattr(status.last_policy_kind, 'name', str(status.last_policy_kind))
            self._node.get_logger().warning(
                f'incompatible QoS on {self._node.resolve_topic_name(topic)} ({kind}, policy '
                f'{policy.replace("RMW_QOS_POLICY_", "").lower()}): no messages flow between '
                'this node and that peer; set the qos_overrides parameters of one side')
        if kind == 'publisher':
            return PublisherEventCallbacks(incompatible_qos=on_incompatible)
        return SubscriptionEventCallbacks(incompatible_qos=on_incompatible)

    def add(self, kind: str, entity) -> None:
        """Watch a publisher or subscription (kind 'publisher' or 'subscription')."""
        self._endpoints.append((kind, entity))

    def remove(self, entity) -> None:
        """Stop watching an endpoint (before it is destroyed)."""
        self._endpoints = [(k, e) for k, e in self._endpoints if e is not entity]

    def problems(self) -> list[str]:
        """One line per (own endpoint, peer) pair whose QoS cannot match, from the graph now."""
        node, out = self._node, []
        me = (node.get_namespace(), node.get_name())
        for kind, ent in self._endpoints:
            topic = ent.topic_name
            if kind == 'subscription':
                peers = node.get_publishers_info_by_topic(topic)
            else:
                peers = node.get_subscriptions_info_by_topic(topic)
            for info in peers:
                if (info.node_namespace, info.node_name) == me:
                    continue
                mine, theirs = _unset_infinite(ent.qos_profile), _unset_infinite(info.qos_profile)
                pub, sub = (theirs, mine) if kind == 'subscription' else (mine, theirs)
                compat, reason = qos_check_compatible(pub, sub)
                if compat == QoSCompatibility.ERROR:
                    peer = f'{info.node_namespace.rstrip("/")}/{info.node_name}'
                    out.append(f'{topic}: {peer} cannot match this {kind} ({reason.strip()})')
        return out


class PublishFailures:
    """
    Samples a node could not hand to DDS, for /diagnostics, instead of the node ending.

    On an overloaded host a reliable writer's history fills while a reader lags, and Fast DDS
    then refuses a write ("Failed to publish: cannot publish data") after blocking: rclpy raises
    RCLError, which ended the command node of a soak run (issue 45). `guard(publisher)` makes that
    publisher count such a failure (that sample is lost) and go on; `take()` says what failed
    since the last call.
    """

    def __init__(self, log=None):
        self._log = log
        self.counts: dict[str, int] = {}
        self.last_error = ''
        self._reported: dict[str, int] = {}

    def guard(self, pub) -> None:
        """Replace pub.publish by one that counts a refused write instead of raising."""
        raw, topic = pub.publish, pub.topic_name

        def publish(msg) -> None:
            try:
                raw(msg)
            except RCLError as exc:
                self.note(topic, exc)
        pub.publish = publish

    def note(self, topic: str, exc: BaseException) -> None:
        """Count one sample DDS refused on `topic` (logged at most once a second)."""
        self.counts[topic] = self.counts.get(topic, 0) + 1
        self.last_error = ' '.join(str(exc).split())
        if self._log is not None:
            self._log.error(f'sample lost on {topic}: {self.last_error}',
                            throttle_duration_sec=1.0)

    def take(self) -> str:
        """Return the WARN phrase for the failures since the last call ('' when none)."""
        new = {t: n - self._reported.get(t, 0) for t, n in self.counts.items()}
        self._reported = dict(self.counts)
        new = {t: n for t, n in new.items() if n}
        if not new:
            return ''
        where = ', '.join(f'{n} on {t}' for t, n in new.items())
        return (f'samples lost: DDS refused {where} ({self.last_error}); a reader is not '
                'keeping up or the host is overloaded')
