"""/diagnostics: one DiagnosticStatus per node about once a second, named as diagnostic_updater."""
from __future__ import annotations

from typing import Any, Callable

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.node import Node

from piezo_narx_ros.nodes.topics import TOPIC_DIAGNOSTICS

DIAG_OK = DiagnosticStatus.OK
DIAG_WARN = DiagnosticStatus.WARN
DIAG_ERROR = DiagnosticStatus.ERROR


class Diagnostics:
    """
    Publishes one DiagnosticStatus for `node` on /diagnostics every `period` s.

    `provider()` returns (level, message, {key: value}); level is DIAG_OK/WARN/ERROR. The provider
    is read only at publication time, so the nodes' hot paths just bump counters.

    The status is named `NODE: TASK` as ros/diagnostics' diagnostic_updater names it (NODE is the
    fully qualified node name without its leading slash, e.g. `piezo/driver_node: rig link`), so
    aggregators and rqt_robot_monitor group it like any other node's. `hardware_id` names the
    device the status is about (the rig address for the driver); 'none' when there is none, as
    diagnostic_updater asks.
    """

    def __init__(self, node: Node, provider: Callable[[], tuple[bytes, str, dict]],
                 task: str, hardware_id: str = 'none', period: float = 1.0):
        self._node = node
        self._provider = provider
        self.name = status_name(node.get_fully_qualified_name(), task)
        self.hardware_id = hardware_id
        self._pub = node.create_publisher(DiagnosticArray, TOPIC_DIAGNOSTICS, 10)
        self._timer = node.create_timer(period, self.publish)

    def build(self) -> DiagnosticArray:
        """
        Return the DiagnosticArray that would be published now.

        The provider's status, raised to WARN while a QoS incompatibility with a peer lasts (see
        QosWatch) and for a tick in which DDS refused samples (PublishFailures).
        """
        level, message, values = self._provider()
        failures = getattr(self._node, 'publish_failures', None)
        lost = failures.take() if failures is not None else ''
        if lost:
            level = max(level, DIAG_WARN)
            message = f'{lost}; {message}'
            values = {**values, 'publish_failures': sum(failures.counts.values())}
        watch = getattr(self._node, 'qos_watch', None)
        problems = watch.problems() if watch is not None else []
        if problems:
            level = max(level, DIAG_WARN)
            more = f' (+{len(problems) - 1} more)' if len(problems) > 1 else ''
            message = f'incompatible QoS: {problems[0]}{more}; ' + message
            values = {**values, 'incompatible_qos': len(problems)}
        status = DiagnosticStatus(level=level, name=self.name,
                                  message=message, hardware_id=self.hardware_id,
                                  values=[KeyValue(key=str(k), value=_fmt(v))
                                          for k, v in values.items()])
        arr = DiagnosticArray(status=[status])
        arr.header.stamp = self._node.get_clock().now().to_msg()
        return arr

    def publish(self) -> None:
        """Publish one status now (also called by the timer)."""
        self._pub.publish(self.build())


def status_name(node_fqn: str, task: str) -> str:
    """
    Name a status as diagnostic_updater does.

    '/piezo/driver_node', 'rig link' -> 'piezo/driver_node: rig link'.
    """
    return f'{node_fqn.lstrip("/")}: {task}'


def status_node(name: str) -> str:
    """Return the node of a status named by `status_name` ('/piezo/driver_node')."""
    return '/' + name.split(': ', 1)[0].lstrip('/')


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return f'{v:.6g}'
    return str(v)


def diagnostic_values(status: DiagnosticStatus) -> dict[str, str]:
    """{key: value} of one DiagnosticStatus (for tests and tools)."""
    return {kv.key: kv.value for kv in status.values}
