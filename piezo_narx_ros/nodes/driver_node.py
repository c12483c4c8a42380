"""
driver_node: the simulator node's contract for a real rig, over UDP to a real-time target.

A managed (lifecycle) node, as ros2/demos' lifecycle talker:
  unconfigured  parameters checked, nothing open;
  configure     binds the UDP socket, starts the receive thread and pings the target; fails (back
                to unconfigured, socket closed) when the target does not answer within
                connect_timeout;
  activate      subscribes voltage_command and enables the output: each sample goes to the target
                (after the driver's voltage and slew limits) and the reply is published on
                deflection with the command's stamp (position = measured m, effort = V applied);
  deactivate    unsubscribes and ramps the output to 0 V at the slew limit;
  cleanup       closes the socket; shutdown (or SIGINT) ramps to 0 V first when active.
With autostart (the default) the node configures and activates itself, retrying configure until
the target answers, so launch files need no lifecycle manager. Services: ~/estop (Trigger) ramps
the output to 0 V at the slew limit and holds it there, whatever the commands say, until ~/arm
(Trigger). A watchdog ramps the output to 0 V when commands stop. All logic is in
piezo_narx_ros.rig.driver.RigDriver.
"""
from __future__ import annotations

import secrets
import time

from rclpy.lifecycle import LifecycleNode, TransitionCallbackReturn
from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger

from piezo_narx_ros.errors import ConfigError, DataError
from piezo_narx_ros.nodes.wire.batching import BATCH_PARAM, batch_topic, sample_type
from piezo_narx_ros.nodes.wire import (decode_joint_trajectory, encode_joint_trajectory,
                                       make_joint_state, parse_joint_state)
from piezo_narx_ros.nodes.diagnostics import Diagnostics
from piezo_narx_ros.nodes.params import ParamSpec
from piezo_narx_ros.nodes.runtime import PiezoNode, main_for
from piezo_narx_ros.nodes.topics import TOPIC_COMMAND, TOPIC_DEFLECTION
from piezo_narx_ros.rig.client import RigClient, check_reachable, resolve_target
from piezo_narx_ros.rig.driver import (DIAG_ERROR, DIAG_OK, DIAG_WARN, STATE_RAMPING,
                                       DriverConfig, RigDriver)   # levels as ints

_RAMP_MAX_S = 2.0        # longest a deactivation or shutdown waits for the output to reach 0 V
_PING_PERIOD_S = 0.05    # pings while configuring


def _nonempty(value: str) -> bool:
    return isinstance(value, str) and bool(value.strip())


class DriverNode(PiezoNode, LifecycleNode):
    """
    Thin wiring: lifecycle transitions -> RigClient/RigDriver; topics and timers -> driver calls.

    Every parameter is read-only: the limits are safety settings, the socket is bound by configure.
    """

    NODE_NAME = 'driver_node'
    PARAMS = (
        ParamSpec('target_host', '127.0.0.1', 'address of the real-time target (rig)',
                  check=(_nonempty, 'must not be empty'), read_only=True),
        ParamSpec('target_port', 50000, 'UDP port of the target', low=1, high=65535,
                  read_only=True),
        ParamSpec('local_host', '127.0.0.1', 'local address the reply socket binds (loopback by '
                  'default; the interface facing a remote target, or 0.0.0.0 for every one)',
                  check=(_nonempty, 'must not be empty'), read_only=True),
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
        ParamSpec('reply_timeout', 0.01, 'time after which an unanswered command counts as a '
                  'reply timeout, s', low=1e-5, high=10.0, read_only=True),
        ParamSpec('connect_timeout', 1.0, 'configure: how long to ping the target for an '
                  'answer, s', low=0.01, high=60.0, read_only=True),
        ParamSpec('autostart', True, 'configure and activate without a lifecycle manager (retry '
                  'configure until the target answers); false: wait for lifecycle transitions',
                  read_only=True),
        ParamSpec('protocol_version', 1, 'UDP datagrams: 1 (one sample each), 2 (several samples '
                  'each, docs/driver.md) or 0 (negotiate: 2 when the target answers a version-2 '
                  'ping, else 1)', low=0, high=2, read_only=True),
        BATCH_PARAM,
    )

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        p = self.params
        if p['v_min'] >= p['v_max']:
            raise ConfigError(f"parameter v_min ({p['v_min']} V) must be below v_max "
                              f"({p['v_max']} V)")
        self.config = DriverConfig(
            n_axes=1, v_min=p['v_min'], v_max=p['v_max'], max_slew_rate=p['max_slew_rate'],
            sample_rate=p['sample_rate'], watchdog_timeout=p['watchdog_timeout'],
            ramp_rate=p['ramp_rate'], reply_timeout=p['reply_timeout'],
            protocol_version=p['protocol_version'] or 1)
        self.config.validate()
        # Refuse a bad host, or a bind address the target's replies cannot reach, at start-up.
        check_reachable(p['local_host'], resolve_target(p['target_host'], p['target_port'])[0])
        self.axis = p['axis']
        self.address = f"{p['target_host']}:{p['target_port']}"
        self.client: RigClient | None = None
        self.driver: RigDriver | None = None
        self.sub = None
        self.timer = self.ramp_timer = None
        self.lifecycle = 'unconfigured'
        self.estopped = False
        self.problem = ''        # why the last configure failed, for /diagnostics
        # deflection is advertised from the start; it carries samples only while active.
        self.batch = p['batch']
        self.pub = self.sample_publisher(batch_topic(TOPIC_DEFLECTION, self.batch),
                                         sample_type(self.batch))
        self.srv_arm = self.create_service(Trigger, '~/arm', self.on_arm)
        self.srv_estop = self.create_service(Trigger, '~/estop', self.on_estop)
        self.diagnostics = Diagnostics(self, self.provide_diagnostics, task='rig link',
                                       hardware_id=f'udp://{self.address}')
        self._autostart = self.create_timer(0.01, self._autostart_step) if p['autostart'] \
            else None
        self.get_logger().info(
            f"axis {self.axis!r}, target {self.address}; limits [{p['v_min']:g}, "
            f"{p['v_max']:g}] V, {p['max_slew_rate']:g} V/s; watchdog "
            f"{p['watchdog_timeout']:g} s; {'autostart' if p['autostart'] else 'unconfigured'}")

    # ----------------------------------------------------------------------------- lifecycle
    def _autostart_step(self) -> None:
        if self.lifecycle == 'unconfigured':
            self.trigger_configure()
        if self.lifecycle == 'inactive':
            self.trigger_activate()
        if self.lifecycle == 'active':
            self._autostart.cancel()

    def on_configure(self, state) -> TransitionCallbackReturn:
        """Bind the socket, start receiving, ping the target until it answers."""
        p = self.params
        try:
            self.client = RigClient(p['target_host'], p['target_port'], p['local_port'],
                                    p['local_host'])
        except ConfigError as exc:
            return self._configure_failed(str(exc))
        # A random first seq: a blind spoofer cannot guess which numbers are in flight.
        self.driver = RigDriver(self.config, self.client.send, seq0=secrets.randbits(32))
        self.client.start(self.on_datagram)
        deadline = time.monotonic() + p['connect_timeout']
        # protocol_version 0: ping in both versions; a version-2 answer selects version 2.
        versions = (2, 1) if p['protocol_version'] == 0 else (None,)
        while not self.driver.connected and time.monotonic() < deadline:
            for version in versions:
                self.driver.ping(time.monotonic(), self.get_clock().now().nanoseconds, version)
            time.sleep(_PING_PERIOD_S)
        if not self.driver.connected:
            return self._configure_failed(f'target {self.address} did not answer a ping within '
                                          f"{p['connect_timeout']:g} s")
        if p['protocol_version'] == 0:
            time.sleep(_PING_PERIOD_S)      # the version-2 answer of the same round, if any
            self.driver.use_version(max(self.driver.versions_seen))
        # A slow supervision tick notices the watchdog; the fast ramp timer runs only while
        # ramping (a 1 kHz timer all the time costs ~10 % of a core in rclpy).
        supervision = min(max(p['watchdog_timeout'] / 4.0, 1e-3), 0.05)
        self.timer = self.create_timer(supervision, self.on_tick)
        self.ramp_timer = self.create_timer(1.0 / p['ramp_rate'], self.on_tick)
        self.ramp_timer.cancel()
        self.problem = ''
        self.lifecycle = 'inactive'
        self.get_logger().info(f'configured: target {self.address} answered (UDP port '
                               f'{self.client.local_port}, protocol version '
                               f'{self.driver.version})')
        return TransitionCallbackReturn.SUCCESS

    def _configure_failed(self, why: str) -> TransitionCallbackReturn:
        self.problem = why
        self._close_link()
        self.get_logger().error(f'configure failed: {why}', throttle_duration_sec=5.0)
        return TransitionCallbackReturn.FAILURE

    def on_activate(self, state) -> TransitionCallbackReturn:
        """Subscribe voltage_command and enable the output (unless e-stopped)."""
        if not self.estopped:
            self.driver.enable_output()
        if self.batch > 1:
            self.sub = self.sample_subscription(batch_topic(TOPIC_COMMAND, self.batch),
                                                self.on_command_batch, sample_type(self.batch))
        else:
            self.sub = self.sample_subscription(TOPIC_COMMAND, self.on_command, raw=False)
        self.lifecycle = 'active'
        self.get_logger().info('active: subscribed to voltage_command'
                               + (' (e-stopped: output held at 0 V until ~/arm)'
                                  if self.estopped else ''))
        return super().on_activate(state)

    def on_deactivate(self, state) -> TransitionCallbackReturn:
        """Unsubscribe, then ramp the output to 0 V at the slew limit."""
        self._unsubscribe()
        self._ramp_to_zero('deactivate')
        self.lifecycle = 'inactive'
        return super().on_deactivate(state)

    def on_cleanup(self, state) -> TransitionCallbackReturn:
        """Close the socket; back to unconfigured."""
        self._close_link()
        self.lifecycle = 'unconfigured'
        return TransitionCallbackReturn.SUCCESS

    def on_shutdown(self, state) -> TransitionCallbackReturn:
        self.close()
        return TransitionCallbackReturn.SUCCESS

    def on_error(self, state) -> TransitionCallbackReturn:
        self.close()
        return TransitionCallbackReturn.SUCCESS

    def close(self) -> None:
        """Shutdown: ramp the output to 0 V at the slew limit (bounded wait), close the socket."""
        self._unsubscribe()
        if self.driver is not None and self.client is not None:
            self._ramp_to_zero('shutdown')
        self._close_link()
        self.lifecycle = 'finalized'

    def _unsubscribe(self) -> None:
        if self.sub is not None:
            self.qos_watch.remove(self.sub)
            self.destroy_subscription(self.sub)
            self.sub = None

    def _ramp_to_zero(self, why: str) -> None:
        self.driver.stop_output()
        deadline = time.monotonic() + _RAMP_MAX_S
        period = 1.0 / self.params['ramp_rate']
        while not self.driver.parked and time.monotonic() < deadline:
            self.driver.tick(time.monotonic(), time.time_ns())
            time.sleep(period)
        if not self.driver.parked:
            self.get_logger().error(
                f'{why}: output still at {self.driver.limiter.output[0]:g} V after '
                f'{_RAMP_MAX_S:g} s of ramp; the target must park it')

    def _close_link(self) -> None:
        for timer in (self.timer, self.ramp_timer):
            if timer is not None:
                self.destroy_timer(timer)
        self.timer = self.ramp_timer = None
        if self.client is not None:
            self.client.close()
        self.client = self.driver = None

    # ------------------------------------------------------------------------------ services
    def on_estop(self, _request, response):
        """~/estop: ramp to 0 V at the slew limit now and hold it until ~/arm."""
        self.estopped = True
        if self.driver is not None:
            self.driver.stop_output()
            self.on_tick()   # the first ramp step goes out now, the ramp timer does the rest
        self.get_logger().warning('e-stop: output ramping to 0 V, held until ~/arm')
        response.success, response.message = True, 'e-stop: output ramps to 0 V and stays there'
        return response

    def on_arm(self, _request, response):
        """~/arm: clear the e-stop; the output follows the commands again when active."""
        self.estopped = False
        if self.driver is not None and self.lifecycle == 'active':
            self.driver.enable_output()
        response.success = True
        response.message = f'armed ({self.lifecycle})'
        self.get_logger().info(response.message)
        return response

    # --------------------------------------------------------------------------- data path
    def on_command(self, msg: JointState) -> None:
        """One command sample -> the target (limits applied by the driver)."""
        now = time.monotonic()
        driver = self.driver
        if driver is None:
            return
        try:
            sample = parse_joint_state(msg)
            volts = sample.value('effort', self.axis)
        except DataError as exc:
            driver.reject()
            self.get_logger().warning(f'command rejected: {exc}', throttle_duration_sec=1.0)
            return
        try:
            driver.command([volts], sample.t_ns, now)
        except DataError as exc:
            self.get_logger().warning(f'command rejected: {exc}', throttle_duration_sec=1.0)

    def on_command_batch(self, msg: bytes) -> None:
        """Send a batch of command samples to the target (protocol version 2: one datagram)."""
        now = time.monotonic()
        driver = self.driver
        if driver is None:
            return
        try:
            batch = decode_joint_trajectory(msg)
            volts = batch.column('effort', self.axis)
        except DataError as exc:
            driver.reject()
            self.get_logger().warning(f'command batch rejected: {exc}',
                                      throttle_duration_sec=1.0)
            return
        driver.command_batch(volts[:, None], batch.t_ns.tolist(), now)

    def on_datagram(self, data: bytes, now: float) -> None:
        """Receive thread: a reply that answers commands becomes deflection message(s)."""
        driver = self.driver
        if driver is None:
            return
        samples = driver.receive_batch(data, now)
        if not samples or self.lifecycle != 'active':
            return
        if self.batch > 1:     # the samples of one datagram make one batch
            self.pub.publish(encode_joint_trajectory(
                [s.stamp_ns for s in samples], [self.axis], [s.position_m for s in samples],
                [s.applied_volts for s in samples]))
            return
        for sample in samples:
            self.pub.publish(make_joint_state(sample.stamp_ns, [self.axis], sample.position_m,
                                              sample.applied_volts))

    def on_tick(self) -> None:
        """Watchdog ramp and reply-timeout bookkeeping; starts/stops the ramp timer."""
        if self.driver is None:
            return
        self.driver.tick(time.monotonic(), self.get_clock().now().nanoseconds)
        ramping = self.driver.state == STATE_RAMPING
        if ramping and self.ramp_timer.is_canceled():
            self.ramp_timer.reset()
        elif not ramping and not self.ramp_timer.is_canceled():
            self.ramp_timer.cancel()

    def pending_parameter_prefixes(self) -> list[str]:
        """voltage_command is subscribed on activation: its QoS overrides are declared then."""
        topic = batch_topic(TOPIC_COMMAND, self.params['batch'])
        return [f'qos_overrides.{self.resolve_topic_name(topic)}.subscription.']

    def provide_diagnostics(self):
        values = {'lifecycle': self.lifecycle, 'estop': self.estopped}
        if self.driver is None:
            level = DIAG_ERROR if self.problem else DIAG_OK
            return bytes([level]), self.problem or self.lifecycle, values
        level, message, report = self.driver.report(time.monotonic(), self.client.foreign)
        values.update(report)
        values['protocol_version'] = self.driver.version
        values['receive_errors'] = self.client.callback_errors
        if self.client.callback_errors:
            values['last_receive_error'] = self.client.last_error
        if self.estopped:
            level = max(level, DIAG_WARN)
            message = 'e-stop: output held at 0 V until ~/arm; ' + message
        elif self.lifecycle != 'active':
            message = f'{self.lifecycle}; {message}'
        # DiagnosticStatus.level is a byte field: an int would be serialised as garbage.
        return bytes([level]), message, values


main = main_for(DriverNode)

if __name__ == '__main__':
    main()
