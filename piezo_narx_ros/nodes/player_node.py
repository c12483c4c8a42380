"""
player_node: publish a bag's topics with their recorded timing (like `ros2 bag play`).

Messages are published serialized, exactly as recorded, from a pacing thread that sleeps until
each message is due (recorded receive-time spacing / rate). Remap topics with --ros-args -r.
Each topic is republished with the reliability and durability its publishers offered when it was
recorded, as `ros2 bag play` does (keep-last 10000, the sample streams' depth), and with the
default sample QoS when the bag has no single offer for it; qos_overrides (docs/nodes.md) apply on
top. `clock:=true` publishes the recorded time reached on /clock (rosgraph_msgs/Clock,
`clock_rate` Hz), like `ros2 bag play --clock`, so nodes started with
use_sim_time:=true run on the bag's time.

    player_node --ros-args -p bag:=bags/run1 -p rate:=2.0 -p loop:=true \
        -p topics:="[/piezo/voltage_command]"
"""
from __future__ import annotations

import threading
import time

from rclpy.clock import Clock, ClockType
from rclpy.duration import Duration
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock as ClockMsg

from piezo_narx_ros.bag.player import (BagSchedule, PlaybackClock, replay_qos, topic_offered_qos,
                                       topic_types)
from piezo_narx_ros.errors import ConfigError
from piezo_narx_ros.nodes.diagnostics import DIAG_ERROR, DIAG_OK, DIAG_WARN, Diagnostics
from piezo_narx_ros.nodes.params import ParamSpec
from piezo_narx_ros.nodes.qos import SAMPLE_DEPTH, sample_qos
from piezo_narx_ros.nodes.runtime import PiezoNode, main_for
from piezo_narx_ros.nodes.recorder_node import message_class


class PlayerNode(PiezoNode):
    """Thin wiring: parameters -> BagSchedule, one raw publisher per topic, a pacing thread."""

    NODE_NAME = 'player_node'
    PARAMS = (
        ParamSpec('bag', '', 'bag directory, .mcap or .db3 file to play', read_only=True,
                  check=(bool, 'must name a bag')),
        ParamSpec('topics', [''], "topics to play (absolute, as in the bag); [''] = all",
                  read_only=True),
        ParamSpec('rate', 1.0, 'playback speed factor', low=1e-3, high=1e3, read_only=True),
        ParamSpec('loop', False, 'start over when the bag ends', read_only=True),
        ParamSpec('start_delay_s', 1.0, 'wait before the first message (after '
                  'wait_for_subscribers) so that subscribers have matched this player, s',
                  low=0.0, high=60.0, read_only=True),
        ParamSpec('wait_for_subscribers', 0, 'first wait until every topic has this many '
                  'matched subscribers (reliable, volatile QoS loses what is published before)',
                  low=0, high=1000, read_only=True),
        ParamSpec('exit_when_done', True, 'shut the node down after the last message',
                  read_only=True),
        ParamSpec('wait_for_all_acked_s', 5.0, 'after the last message, wait up to this long '
                  'until every reliable subscriber has acknowledged all of them (like ros2 bag '
                  'play --wait-for-all-acked); 0 = do not wait, s', low=0.0, high=600.0,
                  read_only=True),
        ParamSpec('clock', False, 'publish the recorded time reached on /clock (like ros2 bag '
                  'play --clock)', read_only=True),
        ParamSpec('clock_rate', 40.0, '/clock publication rate, Hz', low=0.1, high=10000.0,
                  read_only=True),
    )

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        p = self.params
        topics = [t for t in p['topics'] if t] or None
        types = topic_types(p['bag'], topics)  # BagError (one line) for a bad bag or topic
        offered = topic_offered_qos(p['bag'], topics)
        self._pubs = {}
        self.replay_qos = {}
        for topic, kind in types.items():
            rq = replay_qos(offered.get(topic, []), True, SAMPLE_DEPTH)
            qos = sample_qos(rq.depth)
            qos.reliability = ReliabilityPolicy(rq.reliability)
            qos.durability = DurabilityPolicy(rq.durability)
            try:   # the user's qos_overrides still apply on top of the recorded profile
                self._pubs[topic] = self.sample_publisher(topic, message_class(kind), qos=qos)
            except ConfigError as exc:
                self.get_logger().warning(f'skipping {topic}: {exc}')
                continue
            self.replay_qos[topic] = rq
            if not rq.recorded:
                self.get_logger().info(f'{topic}: no single recorded QoS, publishing with the '
                                       'default sample QoS')
        if not self._pubs:
            raise ConfigError(f'no playable topic in {p["bag"]}')
        self.schedule = BagSchedule(p['bag'], list(self._pubs), p['rate'], p['loop'])
        self.clock = None
        if p['clock']:
            from piezo_narx_ros.bag.reader import open_bag
            with open_bag(p['bag']) as reader:
                start_ns = reader.start_time
            self.clock = PlaybackClock(start_ns, p['rate'])
            # /clock QoS as rclcpp's ClockQoS (keep last 1, best effort); the timer runs on the
            # steady clock, so a player started with use_sim_time does not wait for itself.
            self._clock_pub = self.create_publisher(
                ClockMsg, '/clock', QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT))
            self._clock_timer = self.create_timer(1.0 / p['clock_rate'], self._publish_clock,
                                                  clock=Clock(clock_type=ClockType.STEADY_TIME))
        self.published = 0
        self.late_max_s = 0.0
        self.error = ''
        self.done = False
        self.state = 'starting'      # 'waiting for subscribers', 'playing' (for /diagnostics)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._play, name='bag-player', daemon=True)
        self._diag = Diagnostics(self, self._status, task='bag playback')
        if p['exit_when_done']:
            self._exit_timer = self.create_timer(0.25, self._exit_if_done)
        self._thread.start()

    def _play(self) -> None:
        need = self.params['wait_for_subscribers']
        self.state = 'waiting for subscribers'
        while need and any(p.get_subscription_count() < need for p in self._pubs.values()):
            if self._stop.wait(0.02):
                return
        # Then the delay: this writer has matched the subscription, but the subscription may not
        # have matched the writer yet, and a volatile reader drops what comes before (the likely
        # cause of a test that heard 0 of 2000 messages on a loaded machine, delay 0 s).
        self.state = 'starting'
        if need:
            self.get_logger().info(f'{need} subscriber(s) on every topic; playing in '
                                   f'{self.params["start_delay_s"]:g} s')
        if self._stop.wait(self.params['start_delay_s']):
            return
        self.state = 'playing'
        start = time.monotonic()
        try:
            for due, topic, _, data in self.schedule:
                if self.clock is not None:
                    self.clock.next_due(self.schedule.current_ns)
                wait = start + due - time.monotonic()
                if wait > 0:
                    if self._stop.wait(wait):
                        return
                else:
                    self.late_max_s = max(self.late_max_s, -wait)
                if self._stop.is_set():
                    return
                if self.clock is not None:
                    self.clock.anchor(start + due, self.schedule.current_ns)
                self._pubs[topic].publish(data)
                self.published += 1
        except Exception as exc:  # noqa: BLE001 - reported on /diagnostics and in the log
            self.error = str(exc)
            self.get_logger().error(f'playback stopped: {exc}')
        self.get_logger().info(f'played {self.published} message(s)')
        self._wait_for_all_acked()
        if self.clock is not None:
            self.clock.finish()
        self.done = True

    def _wait_for_all_acked(self) -> None:
        # Exiting while a reliable writer still holds unacknowledged samples loses the tail: a
        # sample dropped by the transport is only resent after the reader's next acknack.
        timeout_s = self.params['wait_for_all_acked_s']
        if timeout_s <= 0.0:
            return
        end = time.monotonic() + timeout_s
        for topic, pub in self._pubs.items():
            # In slices, so that a stop request (SIGINT) is not held up by the wait.
            while not pub.wait_for_all_acked(Duration(nanoseconds=100_000_000)):
                if self._stop.is_set():
                    return
                if time.monotonic() >= end:
                    self.get_logger().warning(f'{topic}: not every subscriber acknowledged '
                                              f'every message within {timeout_s:g} s')
                    break

    def _publish_clock(self) -> None:
        msg = ClockMsg()
        sec, nsec = divmod(self.clock.now(time.monotonic()), 1_000_000_000)
        msg.clock.sec, msg.clock.nanosec = sec, nsec
        self._clock_pub.publish(msg)

    def _exit_if_done(self) -> None:
        # From an executor callback: ending from the pacing thread deadlocks the EventsExecutor.
        # The timer period also lets reliable writers deliver the tail.
        if self.done:
            self.finish()

    def _status(self):
        values = {'bag': self.params['bag'], 'published': self.published,
                  'passes': self.schedule.passes, 'late_max_s': self.late_max_s}
        if self.error:
            return DIAG_ERROR, f'playback stopped: {self.error}', values
        if self.state == 'waiting for subscribers' and not self.done:
            need = self.params['wait_for_subscribers']
            return DIAG_WARN, f'waiting for {need} subscriber(s) on every topic', values
        return DIAG_OK, 'done' if self.done else self.state, values

    def close(self) -> None:
        """Stop the pacing thread."""
        self._stop.set()
        if self._thread.is_alive() and threading.current_thread() is not self._thread:
            self._thread.join(5.0)


main = main_for(PlayerNode)

if __name__ == '__main__':
    main()
