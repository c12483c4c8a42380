"""driver_node: the simulator node's contract for a real rig, over UDP to a real-time target.

Subscribes voltage_command, sends each sample (after the driver's own voltage and slew limits) to
the target, and publishes the target's reply on deflection with the command's stamp (position =
measured m, effort = volts applied). A watchdog ramps the output to 0 V when commands stop; the
output is also ramped to 0 V on shutdown. voltage_command is subscribed only once the target has
answered a ping, so a command node waiting for subscribers does not stream into the void. All logic
is in piezo_narx_ros.rig.driver.RigDriver.
"""
from __future__ import annotations

import math
import time

from sensor_msgs.msg import JointState

from piezo_narx_ros.errors import ConfigError, DataError
from piezo_narx_ros.nodes.common import (TOPIC_COMMAND, TOPIC_DEFLECTION, Diagnostics, ParamSpec,
                                         PiezoNode, main_for, make_joint_state, parse_joint_state)
from piezo_narx_ros.rig.client import RigClient
from piezo_narx_ros.rig.driver import STATE_RAMPING, DriverConfig, RigDriver

_SHUTDOWN_RAMP_MAX_S = 2.0  # longest a shutdown waits for the output to reach 0 V
_PING_PERIOD_S = 0.1        # start-up pings until the target answers


def _nonempty(value: str) -> bool:
    return isinstance(value, str) and bool(value.strip())


class DriverNode(PiezoNode):
    """Thin wiring: parameters -> RigDriver + RigClient; topics and timers -> driver calls.

    Every parameter is read-only: the limits are safety settings and the socket is bound once.
    """

    NODE_NAME = 'driver_node'
    PARAMS = (
        ParamSpec('target_host', '127.0.0.1', 'address of the real-time target (rig)',
                  check=(_nonempty, 'must not be empty'), read_only=True),
        ParamSpec('target_port', 50000, 'UDP port of the target', low=1, high=65535,
                  read_only=True),
        ParamSpec('local_port', 50001, 'local UDP port the replies come back to (0 = any free '
                  'port)', low=0, high=65535, read_only=True),
        ParamSpec('axis', 'x', 'axis name taken from voltage_command and written on deflection',
                  check=(_nonempty, 'must not be empty'), read_only=True),
        ParamSpec('v_min', -200.0, 'lowest voltage ever sent to the target, V (must be <= 0)',
                  low=-1000.0, high=0.0, read_only=True),
        ParamSpec('v_max', 200.0, 'highest voltage ever sent to the target, V (must be >= 0)',
                  low=0.0, high=1000.0, read_only=True),
        ParamSpec('max_slew_rate', 2.0e5, 'largest rate of change of the output, V/s', low=1e-3,
                  high=1e9, read_only=True),
        ParamSpec('sample_rate', 2000.0, 'nominal command rate, Hz: one command may move the '
                  'output by max_slew_rate / sample_rate V', low=1.0, high=100000.0,
                  read_only=True),
        ParamSpec('watchdog_timeout', 0.1, 'time without a command before the output ramps to '
                  '0 V, s', low=1e-3, high=60.0, read_only=True),
        ParamSpec('ramp_rate', 1000.0, 'datagrams per second while ramping to 0 V, Hz', low=1.0,
                  high=20000.0, read_only=True),
        ParamSpec('reply_timeout', 0.01, 'time after which an unanswered command counts as a reply '
                  'timeout, s', low=1e-5, high=10.0, read_only=True),
    )

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        p = self.params
        if p['v_min'] >= p['v_max']:
            raise ConfigError(f"parameter v_min ({p['v_min']} V) must be below v_max "
                              f"({p['v_max']} V)")
        config = DriverConfig(n_axes=1, v_min=p['v_min'], v_max=p['v_max'],
                              max_slew_rate=p['max_slew_rate'], sample_rate=p['sample_rate'],
                              watchdog_timeout=p['watchdog_timeout'], ramp_rate=p['ramp_rate'],
                              reply_timeout=p['reply_timeout'])
        self.client = RigClient(p['target_host'], p['target_port'], p['local_port'])
        self.driver = RigDriver(config, self.client.send)
        self.axis = p['axis']
        self._closing = False  # set on shutdown: replies are still counted, no longer published
        self.pub = self.sample_publisher(TOPIC_DEFLECTION)
        self.sub = None  # created once the target answers (on_tick)
        self._last_ping = -math.inf
        # A slow supervision tick notices the watchdog; the fast ramp timer runs only while
        # ramping (a 1 kHz timer all the time costs ~10 % of a core in rclpy).
        supervision = min(max(p['watchdog_timeout'] / 4.0, 1e-3), 0.05)
        self.timer = self.create_timer(supervision, self.on_tick)
        self.ramp_timer = self.create_timer(1.0 / p['ramp_rate'], self.on_tick)
        self.ramp_timer.cancel()
        self.diagnostics = Diagnostics(
            self, self.provide_diagnostics, task='rig link',
            hardware_id=f"udp://{p['target_host']}:{p['target_port']}")
        self.client.start(self.on_datagram)
        self.get_logger().info(
            f"driving axis {self.axis!r} on {p['target_host']}:{p['target_port']} from UDP port "
            f"{self.client.local_port}; limits [{p['v_min']:g}, {p['v_max']:g}] V, "
            f"{p['max_slew_rate']:g} V/s; watchdog {p['watchdog_timeout']:g} s")

    def on_command(self, msg: JointState) -> None:
        """One command sample -> the target (limits applied by the driver)."""
        now = time.monotonic()
        try:
            sample = parse_joint_state(msg)
            volts = sample.value('effort', self.axis)
        except DataError as exc:
            self.driver.reject()
            self.get_logger().warning(f'command rejected: {exc}', throttle_duration_sec=1.0)
            return
        try:
            self.driver.command([volts], sample.t_ns, now)
        except DataError as exc:
            self.get_logger().warning(f'command rejected: {exc}', throttle_duration_sec=1.0)

    def on_datagram(self, data: bytes, now: float) -> None:
        """Receive thread: a reply that answers a command becomes a deflection message."""
        sample = self.driver.receive(data, now)
        if sample is not None and not self._closing:
            self.pub.publish(make_joint_state(sample.stamp_ns, [self.axis], sample.position_m,
                                              sample.applied_volts))

    def on_tick(self) -> None:
        """Watchdog ramp and reply-timeout bookkeeping; starts/stops the ramp timer."""
        now = time.monotonic()
        self.driver.tick(now, self.get_clock().now().nanoseconds)
        if self.sub is None:
            self._connect(now)
        ramping = self.driver.state == STATE_RAMPING
        if ramping and self.ramp_timer.is_canceled():
            self.ramp_timer.reset()
        elif not ramping and not self.ramp_timer.is_canceled():
            self.ramp_timer.cancel()

    def _connect(self, now: float) -> None:
        if self.driver.connected:
            self.sub = self.sample_subscription(TOPIC_COMMAND, self.on_command, raw=False)
            self.get_logger().info('target answered; subscribed to voltage_command')
        elif now - self._last_ping >= _PING_PERIOD_S:
            self._last_ping = now
            self.driver.ping(now, self.get_clock().now().nanoseconds)

    def pending_parameter_prefixes(self) -> list[str]:
        """voltage_command is subscribed once the target answers: its QoS overrides are
        declared then."""
        return [f'qos_overrides.{self.resolve_topic_name(TOPIC_COMMAND)}.subscription.']

    def provide_diagnostics(self):
        level, message, values = self.driver.report(time.monotonic())
        values.update(datagrams_foreign=self.client.foreign,
                      receive_errors=self.client.callback_errors)
        if self.client.callback_errors:
            values['last_receive_error'] = self.client.last_error
        # DiagnosticStatus.level is a byte field: an int would be serialised as garbage.
        return bytes([level]), message, values

    def close(self) -> None:
        """Ramp the output to 0 V at the slew limit (bounded wait), then close the socket."""
        self._closing = True
        self.driver.stop_output()
        deadline = time.monotonic() + _SHUTDOWN_RAMP_MAX_S
        period = 1.0 / self.params['ramp_rate']
        while not self.driver.parked and time.monotonic() < deadline:
            self.driver.tick(time.monotonic(), time.time_ns())
            time.sleep(period)
        if not self.driver.parked:
            self.get_logger().error(
                f'output still at {self.driver.limiter.output[0]:g} V after '
                f'{_SHUTDOWN_RAMP_MAX_S:g} s of shutdown ramp; the target must park it')
        self.client.close()


main = main_for(DriverNode)

if __name__ == '__main__':
    main()
