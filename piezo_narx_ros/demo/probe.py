"""
A listener on /diagnostics, so the demo knows when nodes are up and when a run is complete.

The nodes publish one DiagnosticStatus each about once a second (nodes.diagnostics.Diagnostics);
the demo reads the command node's `published` count and state, and the recorder's `received` count.
This is the only ROS code of the demo process; it installs no signal handlers.
"""
from __future__ import annotations

import time


class DiagnosticsProbe:
    """Keeps the latest (message, {key: value}) of every node seen on /diagnostics."""

    def __init__(self, node_name: str = 'demo_probe'):
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.signals import SignalHandlerOptions

        from piezo_narx_ros.nodes.runtime import fastdds_profile

        fastdds_profile()     # the nodes' Fast DDS settings (docs/nodes.md), here and inherited
        self.latest: dict[str, tuple[str, dict[str, str], float]] = {}
        self._rclpy = rclpy
        self.context = rclpy.Context()
        rclpy.init(context=self.context, signal_handler_options=SignalHandlerOptions.NO)
        self.node = rclpy.create_node(node_name, context=self.context)
        self.node.create_subscription(DiagnosticArray, '/diagnostics', self._on_diag, 100)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)

    def _on_diag(self, arr) -> None:
        from piezo_narx_ros.nodes.diagnostics import status_node
        now = time.monotonic()
        for st in arr.status:
            # Statuses are named 'ns/node: task'; the demo asks by fully qualified node name.
            self.latest[status_node(st.name)] = (st.message,
                                                 {kv.key: kv.value for kv in st.values}, now)

    def spin(self, seconds: float) -> None:
        """Process incoming diagnostics for about `seconds` s."""
        end = time.monotonic() + seconds
        while True:
            left = end - time.monotonic()
            if left <= 0:
                return
            self.executor.spin_once(timeout_sec=min(left, 0.05))

    def status(self, name: str) -> tuple[str, dict[str, str]] | None:
        """(message, values) last published by the node with fully qualified `name`."""
        item = self.latest.get(name)
        return None if item is None else item[:2]

    def value(self, name: str, key: str, default: int = 0) -> int:
        """Return an integer diagnostic value of a node (default when absent or not an integer)."""
        st = self.status(name)
        try:
            return int(st[1][key]) if st else default
        except (KeyError, ValueError):
            return default

    def close(self) -> None:
        """Destroy the node and shut its context down."""
        self.executor.shutdown()
        self.node.destroy_node()
        self._rclpy.try_shutdown(context=self.context)
