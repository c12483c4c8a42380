"""
command_node: the excitation signal streamed at the sample rate.

Streams voltage_command (JointState, effort = V) at the sample rate, or in position mode
(`output:=position`) position_reference (position = m) for controller_node.

The excitation comes from piezo_narx_ros.plant.signals.generate (kind and options from
parameters); the clock, catch-up, limits and looping live in command.stream.CommandStreamer. The
node only turns ticks into `poll()` calls and samples into messages: a timer's ticks, or, run
as a process on the monotonic clock, timed waits in run_node's spin loop (cheaper at kHz). In
position mode the same signal kinds are streamed in metres: amplitude, offset, u_min, u_max
(clamp) and slew_rate are then in m and m/s. `running` can be set at run time to pause/resume,
directly or through the ~/set_running service (std_srvs/SetBool); paused, the node keeps
publishing the last command at every sample (`hold_while_paused`, default true), as the amplifier
holds it, so that the simulator, a driver and the estimator see the hold instead of a stream
that stops and restarts; `wait_for_subscribers` holds the first sample until the listeners are
matched, so that a recording or an estimator sees sample 0.

`kind:=playback` replays a file as recorded (command.playback): its volts, at its own rate,
once; only the playback_* parameters and resample change it (amplitude, offset, seconds and loop
belong to the generated signals, and a launch file's params file sets them).

Time: stamps come from the node clock. With use_sim_time:=true the samples are also paced on it
(the /clock of a simulator or of `player_node clock:=true`): none is published before the first
/clock message, a frozen clock stops the stream, and a clock that jumps back (a looping bag)
restarts the sample clock there. Otherwise they are paced on the monotonic clock.
"""
from __future__ import annotations

import math
import time

import numpy as np
from rcl_interfaces.msg import SetParametersResult
from rclpy.parameter import Parameter
from std_srvs.srv import SetBool

from piezo_narx_ros.axis_names import AXES_CHECK
from piezo_narx_ros.command.playback import playback_signal
from piezo_narx_ros.command.stream import CommandStreamer, make_signal
from piezo_narx_ros.errors import ConfigError
from piezo_narx_ros.nodes.wire.batching import BATCH_PARAM, batch_topic, sample_type
from piezo_narx_ros.nodes.wire import encode_joint_state, encode_joint_trajectory
from piezo_narx_ros.nodes.diagnostics import DIAG_ERROR, DIAG_OK, DIAG_WARN, Diagnostics
from piezo_narx_ros.nodes.graph import same_name_problem
from piezo_narx_ros.nodes.params import ParamSpec
from piezo_narx_ros.nodes.runtime import PiezoNode, main_for
from piezo_narx_ros.nodes.topics import TOPIC_COMMAND, TOPIC_REFERENCE
from piezo_narx_ros.plant.signals import KINDS, PREAMBLES, preamble

OUTPUTS = ('voltage', 'position')


class CommandNode(PiezoNode):
    """Thin wiring: parameters -> CommandStreamer; timer -> poll -> publish."""

    NODE_NAME = 'command_node'
    PARAMS = (
        ParamSpec('output', 'voltage', 'voltage: voltage_command (effort, V); position: '
                  'position_reference (position, m) for controller_node', choices=OUTPUTS,
                  read_only=True),
        ParamSpec('fs', 2000.0, "sample rate, Hz (playback: the file's own rate; fs for a file "
                  'without one, or as the target of resample)', low=1.0, high=100000.0,
                  read_only=True),
        ParamSpec('axes', ['x'], 'axis names (one signal per axis, axis i seeded seed + i)',
                  read_only=True, check=AXES_CHECK),
        ParamSpec('kind', 'multisine', 'signal kind', choices=KINDS, read_only=True),
        ParamSpec('amplitude', 100.0, 'peak deviation from offset, V (m in position mode)',
                  low=0.0, high=1000.0, read_only=True),
        ParamSpec('offset', 0.0, 'signal offset, V (m in position mode)', low=-1000.0,
                  high=1000.0, read_only=True),
        ParamSpec('seconds', 25.0, 'length of one period of the signal, s', low=1e-3, high=3600.0,
                  read_only=True),
        ParamSpec('seed', 0, 'seed of the random parts of the signal', low=0, high=2**31 - 1,
                  read_only=True),
        ParamSpec('freq', 1.0, 'sine/triangle frequency, Hz', low=1e-6, high=50000.0,
                  read_only=True),
        ParamSpec('f_min', 0.1, 'multisine lowest line, Hz', low=1e-6, high=50000.0,
                  read_only=True),
        ParamSpec('f_max', 100.0, 'multisine highest line, Hz', low=1e-6, high=50000.0,
                  read_only=True),
        ParamSpec('spectrum', 'flat', 'multisine line amplitudes',
                  choices=('flat', 'pink', 'brown'), read_only=True),
        ParamSpec('f0', 1.0, 'chirp start frequency, Hz', low=1e-6, high=50000.0, read_only=True),
        ParamSpec('f1', 0.0, 'chirp end frequency, Hz (0: 0.45 fs)', low=0.0, high=50000.0,
                  read_only=True),
        ParamSpec('min_hold', 0.01, 'APRBS shortest hold, s', low=1e-6, high=3600.0,
                  read_only=True),
        ParamSpec('max_hold', 0.5, 'APRBS longest hold, s', low=1e-6, high=3600.0, read_only=True),
        ParamSpec('path', '', 'playback: the recording to replay (.npz, .mat, or a text table '
                  'read as fit reads it)', read_only=True),
        ParamSpec('column', '', 'playback: the table column (or .mat variable) to play, a name '
                  'or 1-based number (empty: the u column)', read_only=True),
        ParamSpec('key', 'u', 'playback: the .npz key (or .mat variable) to play',
                  read_only=True),
        ParamSpec('resample', False, 'playback: resample a file recorded at another rate to fs '
                  '(linear); false plays it at its own rate', read_only=True),
        ParamSpec('playback_scale', 1.0, 'playback: factor on the recorded values (1: as '
                  'recorded)', low=-1e6, high=1e6, read_only=True),
        ParamSpec('playback_offset', 0.0, 'playback: added to the recorded values, V (m in '
                  'position mode)', low=-1000.0, high=1000.0, read_only=True),
        ParamSpec('playback_loop', False, 'playback: repeat the file (it jumps from its last '
                  'sample to its first); false: play it once', read_only=True),
        ParamSpec('cycles', 2, 'protocol: repeats of its section sequence', low=1, high=1000,
                  read_only=True),
        ParamSpec('slow_freq', 0.5, 'protocol: slow-loop frequency, Hz', low=1e-6, high=50000.0,
                  read_only=True),
        ParamSpec('u_min', -200.0, 'lowest command, V (clamp)', low=-10000.0, high=10000.0,
                  read_only=True),
        ParamSpec('u_max', 200.0, 'highest command, V (clamp)', low=-10000.0, high=10000.0,
                  read_only=True),
        ParamSpec('slew_rate', 0.0, 'largest command rate of change, V/s (0: no limit)',
                  low=0.0, high=1e12, read_only=True),
        ParamSpec('loop', True, 'repeat the signal; false: stop after one period (playback: see '
                  'playback_loop)', read_only=True),
        ParamSpec('preamble', 'none', 'moves streamed once before the signal: fade-out, sine '
                  'cycles about the offset fading from the amplitude to 0, wipe the memory an '
                  "unlogged past left, so an estimator's init_window over them sets its state "
                  '(docs/real.md)', choices=PREAMBLES, read_only=True),
        ParamSpec('preamble_seconds', 2.0, 'length of the preamble, s', low=1e-3, high=3600.0,
                  read_only=True),
        ParamSpec('preamble_cycles', 20.0, 'sine cycles of the preamble', low=1e-3, high=1e6,
                  read_only=True),
        ParamSpec('running', True, 'stream now; set false to pause, true to resume'),
        ParamSpec('hold_while_paused', True, 'paused, publish the last command at every sample '
                  '(the amplifier holds it); false: publish nothing (listeners see the stream '
                  'stop, and a new one when it resumes)', read_only=True),
        ParamSpec('wait_for_subscribers', 0, 'start only when this many subscriptions are matched',
                  low=0, high=1000, read_only=True),
        ParamSpec('start_delay_s', 0.5, 'with wait_for_subscribers: then wait this long before '
                  'sample 0, since a subscription may match this writer a little after this '
                  'writer matched it and a volatile reader drops what came before, s',
                  low=0.0, high=60.0, read_only=True),
        ParamSpec('publish_period', 0.0, 'publishing period, s (0: one tick per sample; larger '
                  'values publish the due samples in batches)', low=0.0, high=1.0, read_only=True),
        ParamSpec('max_burst', 10000, 'most samples published in one tick (the rest follow on '
                  'the next ones; nothing is dropped)', low=1, high=10**7, read_only=True),
        BATCH_PARAM,
    )

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        p = self.params
        if p['u_min'] >= p['u_max']:
            raise ConfigError(f"parameter u_min ({p['u_min']} V) must be below u_max "
                              f"({p['u_max']} V)")
        self.axes = list(p['axes'])
        fs, loop = p['fs'], p['loop']
        if p['kind'] == 'playback':
            play = playback_signal(p['path'], len(self.axes), p['fs'], p['column'] or None,
                                   p['key'], p['resample'], p['playback_scale'],
                                   p['playback_offset'], p['playback_loop'], p['u_min'],
                                   p['u_max'])
            signal, fs, loop = play.signal, play.fs, play.loop
            for note in play.notes:
                self.get_logger().warning(note)
        else:
            options = {k: p[k] for k in ('freq', 'f_min', 'f_max', 'spectrum', 'f0', 'min_hold',
                                         'max_hold', 'u_min', 'u_max', 'cycles', 'slow_freq')}
            options['f1'] = p['f1'] or None
            signal = make_signal(p['kind'], fs, p['seconds'], p['amplitude'], p['offset'],
                                 p['seed'], len(self.axes), **options)
        self.fs = fs
        # About the signal's offset, at its peak deviation (a played file: about its mean).
        centre = p['offset'] if p['kind'] != 'playback' else float(np.mean(signal))
        lead = preamble(p['preamble'], fs, p['preamble_seconds'],
                        float(np.max(np.abs(signal - centre))), centre,
                        p['preamble_cycles'])
        self.streamer = CommandStreamer(signal, fs, loop=loop, u_min=p['u_min'],
                                        u_max=p['u_max'],
                                        slew_rate=p['slew_rate'] or float('inf'),
                                        max_burst=p['max_burst'], lead=lead)
        self.want_running = p['running']
        self.sim_time = bool(self.get_parameter('use_sim_time').value)
        self.clock_jumps = 0
        self._last_pace: int | None = None
        self._matched_at: float | None = None   # monotonic s when wait_for_subscribers was met
        self.position = p['output'] == 'position'
        b = self.batch = p['batch']
        self.pub = self.sample_publisher(
            batch_topic(TOPIC_REFERENCE if self.position else TOPIC_COMMAND, b), sample_type(b))
        # batch > 1: samples wait here until `batch` of them make a message.
        self._held_t = np.empty(0, dtype=np.int64)
        self._held_v = np.empty((0, len(self.axes)))
        self.add_post_set_parameters_callback(self._on_set)
        self.add_on_set_parameters_callback(self._keep_clock)
        self.srv_running = self.create_service(SetBool, '~/set_running', self.on_set_running)
        period = p['publish_period'] or 1.0 / fs
        self._period_ns = int(p['publish_period'] * 1e9)
        self._next_wake = 0      # monotonic ns; used when run_node paces the node (pace())
        self._field = 'position' if self.position else 'effort'     # of a batch message
        self.timer = self.create_timer(period, self.on_tick)
        self.diagnostics = Diagnostics(self, self.status, task='command stream')
        unit = 'm' if self.position else 'V'
        self.get_logger().info(
            f"{p['kind']} {p['output']} on {self.axes} at {fs:g} Hz, {signal.shape[0]} "
            f"samples per {'loop' if loop else 'run'}"
            + (f" after a {p['preamble']} of {lead.size} samples"
               if lead.size else '') + f", limits [{p['u_min']:g}, "
            f"{p['u_max']:g}] {unit}")

    def _keep_clock(self, params) -> SetParametersResult:
        """Refuse use_sim_time at run time: pacing (and /diagnostics) follow the start's clock."""
        for q in params:
            if q.name == 'use_sim_time' and bool(q.value) != self.sim_time:
                return SetParametersResult(
                    successful=False, reason='use_sim_time is read at start-up (the samples are '
                    'paced on that clock); restart the node with -p use_sim_time:=...')
        return SetParametersResult(successful=True)

    def _on_set(self, params) -> None:
        for q in params:
            if q.name == 'running':
                self.want_running = bool(q.value)
                if not self.want_running and self.params['hold_while_paused']:
                    self.streamer.hold()
                elif not self.want_running:
                    self.streamer.stop()
                else:
                    self.streamer.resume()

    def on_set_running(self, request, response):
        """
        ~/set_running (std_srvs/SetBool).

        The same as setting the `running` parameter, so the parameter always tells the state.
        """
        result = self.set_parameters([Parameter('running', value=bool(request.data))])[0]
        response.success = result.successful
        response.message = self.status()[1] if result.successful else result.reason
        return response

    def _pace_ns(self) -> int | None:
        """
        Return the clock the samples are due on (ns).

        The node clock under use_sim_time (None until the first /clock), else the monotonic clock.
        """
        if not self.sim_time:
            return time.monotonic_ns()
        now = self.get_clock().now().nanoseconds
        return now if now > 0 else None

    def take_pacing(self) -> bool:
        """
        On the monotonic clock, run_node's loop paces the samples (the timer is cancelled).

        Under use_sim_time the timer on the node clock stays: it follows /clock.
        """
        if self.sim_time:
            return False
        self.timer.cancel()
        return True

    def pace(self) -> float:
        """Publish what is due; return the wait until the next sample (or the next batch), s."""
        # The steady batched stream's wake: one message's samples due, none held, published
        # as on_tick would, without its general case.
        got = (self.streamer.take_run(time.monotonic_ns(), self.batch)
               if self.batch > 1 and not self._held_t.size else None)
        if got is not None:
            self.pub.publish(encode_joint_trajectory(got[0], self.axes, **{self._field: got[1]}))
        else:
            self.on_tick()
        now = time.monotonic_ns()
        due = self.streamer.next_due_ns()
        if due is None:      # paused, waiting for listeners or finished: look again soon
            return 0.005
        if self.batch > 1:   # wake when the sample that completes the batch is due
            need = self.batch - self._held_t.size
            due += math.ceil((need - 1) * 1e9 / self.streamer.fs)
        # publish_period > 1/fs: wake once per period and publish the samples due by then.
        self._next_wake = max(due, self._next_wake + self._period_ns)
        return min(max(self._next_wake - now, 0) * 1e-9, 0.1)

    def on_tick(self) -> None:
        """Publish every sample due now (several after a late tick)."""
        s = self.streamer
        pace = self._pace_ns()
        if pace is None:
            return   # use_sim_time and no /clock yet
        if self.sim_time and self._last_pace is not None and pace < self._last_pace and s.running:
            self.clock_jumps += 1
            back = (self._last_pace - pace) * 1e-9
            self.get_logger().warning(f'/clock jumped back by {back:.3f} s: the sample clock '
                                      'restarts there')
            s.start(pace, pace)
        self._last_pace = pace
        if not s.running:
            self._publish_batches(flush=True)      # a pause or the end: nothing waits
            if not self.want_running or s.finished:
                return
            if not self._listeners_ready():
                return
            s.start(self.get_clock().now().nanoseconds, pace)
        names, pub = self.axes, self.pub
        if self.batch > 1:
            stamps, volts = s.poll(pace)
            if self._held_t.size:
                stamps = np.concatenate((self._held_t, stamps))
                volts = np.concatenate((self._held_v, volts))
            self._held_t, self._held_v = stamps, volts
            self._publish_batches(flush=s.finished)
        else:
            stamps, volts = s.poll_lists(pace)
            if self.position:
                for t, r in zip(stamps, volts):
                    pub.publish(encode_joint_state(t, names, position=r))
            else:
                for t, u in zip(stamps, volts):
                    pub.publish(encode_joint_state(t, names, effort=u))   # CDR: 2x cheaper
        if s.finished and len(stamps):
            self.get_logger().info(f'signal finished after {s.published} samples')

    def _listeners_ready(self) -> bool:
        """wait_for_subscribers subscriptions matched, start_delay_s ago (at once when 0)."""
        need = self.params['wait_for_subscribers']
        if need == 0:
            return True
        if self.pub.get_subscription_count() < need:
            self._matched_at = None
            return False
        if self._matched_at is None:
            self._matched_at = time.monotonic()
        return time.monotonic() - self._matched_at >= self.params['start_delay_s']

    def _publish_batches(self, flush: bool) -> None:
        """Publish the held samples `batch` at a time (and the rest too when `flush`)."""
        n, t, v = self.batch, self._held_t, self._held_v
        full = t.size if flush else t.size - t.size % n
        for k in range(0, full, n):
            self.pub.publish(encode_joint_trajectory(t[k:k + n], self.axes,
                                                     **{self._field: v[k:k + n]}))
        self._held_t, self._held_v = t[full:], v[full:]

    def status(self):
        s = self.streamer
        state = ('finished' if s.finished else
                 'paused, holding the last command' if s.holding else
                 'running' if s.running else
                 'paused' if not self.want_running else
                 'waiting for /clock' if self._pace_ns() is None else 'waiting for subscribers')
        level = DIAG_WARN if state.startswith('waiting') else DIAG_OK
        clash = same_name_problem(self, TOPIC_REFERENCE if self.position else TOPIC_COMMAND)
        if clash:
            level, state = DIAG_ERROR, f'{clash}; {state}'
        return level, state, {'published': s.published, 'position': s.position,
                              'late_ticks': s.late_polls, 'max_batch': s.max_batch,
                              'fs': s.fs, 'subscribers': self.pub.get_subscription_count(),
                              'holding': s.holding,
                              'clock': 'sim' if self.sim_time else 'steady',
                              'output': self.params['output'], 'batch': self.batch,
                              'clock_jumps': self.clock_jumps}


main = main_for(CommandNode)

if __name__ == '__main__':
    main()
