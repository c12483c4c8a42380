"""
estimator_node: free-run deflection estimate from the voltage commands alone.

Loads a model file (JSON + .npz, never a pickle, never torch), runs it in free run on
voltage_command and publishes deflection_estimate with each command's stamp. When a deflection
source exists it initialises from the first measured samples, reports the running error (RMS, R²)
on /diagnostics and, if asked, re-anchors to the measurement. All logic is in
piezo_narx_ros.estimator.free_run.FreeRunEstimator.
"""
from __future__ import annotations

import math

from std_srvs.srv import Trigger

from piezo_narx_ros.command.stamps import RATE_TOLERANCE
from piezo_narx_ros.errors import ConfigError, PiezoNarxError
from piezo_narx_ros.estimator.free_run import INIT_MODES, FreeRunEstimator
from piezo_narx_ros.estimator.health import EstimatorHealth
from piezo_narx_ros.estimator.warm_up import warm_up
from piezo_narx_ros.ident.state.estimate import PASTS
from piezo_narx_ros.nodes.wire.batching import BATCH_PARAM, HeldBatches, batch_topic, sample_type
from piezo_narx_ros.nodes.wire import (decode_joint_state, decode_joint_trajectory,
                                       encode_joint_state, encode_joint_trajectory)
from piezo_narx_ros.nodes.diagnostics import Diagnostics
from piezo_narx_ros.nodes.graph import EpisodeLog, same_name_problem
from piezo_narx_ros.nodes.params import ParamSpec
from piezo_narx_ros.nodes.runtime import PiezoNode, main_for
from piezo_narx_ros.nodes.topics import TOPIC_COMMAND, TOPIC_DEFLECTION, TOPIC_ESTIMATE


class EstimatorNode(PiezoNode):
    """Thin wiring: voltage_command / deflection -> FreeRunEstimator -> deflection_estimate."""

    NODE_NAME = 'estimator_node'
    PARAMS = (
        ParamSpec('model', '', 'model file (.json with its .npz beside it)', read_only=True,
                  check=(lambda v: bool(v.strip()), 'must name a model file (.json)')),
        ParamSpec('axis', 'x', 'axis read from voltage_command/deflection and published (a '
                  'model of several axes maps its own input and output names instead)',
                  read_only=True, check=(lambda v: bool(v.strip()), 'must not be empty')),
        ParamSpec('fs', 0.0, "command sample rate, Hz (0: the model file's fs; any other value "
                  'must equal it)', low=0.0, high=100000.0, read_only=True),
        ParamSpec('rate_tolerance', RATE_TOLERANCE, 'relative difference between the command '
                  "stream's stamp rate and the model's beyond which estimates are withheld "
                  '(ERROR on /diagnostics)', low=1e-6, high=0.5, read_only=True),
        ParamSpec('init', 'auto', 'initial state: rest, measurement (the first init_window s of '
                  "measured samples, used as the model file's start policy says, else the "
                  'state that explains them: hysteresis memory, creep, sensor offset), or auto '
                  "(the model file's start policy: rest, or measurement when deflection has a "
                  'publisher)', choices=INIT_MODES, read_only=True),
        ParamSpec('init_window', -1.0, 'measured samples that set the initial state, s (-1: the '
                  "model file's window, 0.5 s for a file without a start policy)",
                  low=-1.0, high=60.0, read_only=True),
        ParamSpec('init_past', 'any', "how the actuator's unlogged past ended, for init: "
                  'measurement: any (histories of up to two turning points) or fade-out (a move '
                  'ended by fading its amplitude out: the memory demagnetised about the first '
                  'command)', choices=PASTS, read_only=True),
        ParamSpec('init_timeout', 1.0, 'longest wait for the initial measurements, s (then '
                  'from rest); at least init_window', low=0.0, high=60.0, read_only=True),
        ParamSpec('u_min', -200.0, 'lowest accepted command, V (lower ones are rejected)',
                  low=-10000.0, high=10000.0, read_only=True),
        ParamSpec('u_max', 200.0, 'highest accepted command, V', low=-10000.0, high=10000.0,
                  read_only=True),
        ParamSpec('max_fill', 2000, 'longest gap bridged by holding the last command, samples '
                  '(longer: restart)', low=0, high=10**7, read_only=True),
        ParamSpec('range_margin', 0.1, 'fraction of the trained output span tolerated beyond it '
                  'before an estimate is flagged', low=0.0, high=100.0, read_only=True),
        ParamSpec('window', 2000, 'samples in the running error (RMS, R²)', low=2, high=10**7,
                  read_only=True),
        ParamSpec('reanchor_every', 0, 're-anchor the recursion to the measurement every that '
                  'many samples (0: never)', low=0, high=10**9, read_only=True),
        BATCH_PARAM,
    )

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        from piezo_narx_ros.ident.validation.usable import load_runnable
        p = self.params
        self.model = load_runnable(p['model'])
        config = {
            'fs': p['fs'] or None, 'init': p['init'], 'u_min': p['u_min'], 'u_max': p['u_max'],
            'max_fill': p['max_fill'], 'range_margin': p['range_margin'],
            'window': p['window'], 'reanchor_every': p['reanchor_every'],
            'init_timeout': p['init_timeout'],
            'init_window': p['init_window'] if p['init_window'] >= 0 else None,
            'init_past': p['init_past'], 'rate_tolerance': p['rate_tolerance']}
        self.est = FreeRunEstimator(self.model, **config)    # a setting refused: one line
        # Compile/load every kernel before the first sample, on an estimator thrown away.
        try:
            warm_up(FreeRunEstimator(self.model, **config), batch=max(2, p['batch']))
        except PiezoNarxError as exc:    # the live stream compiles what is left: slower start
            self.get_logger().warning(f'warm-up on a synthetic stream failed: {exc}')
        self.axis = p['axis']
        # Axis names on the topics: a model of several axes is mapped by its own names (the
        # command's for its inputs, the deflection's for its outputs); one axis by `axis`.
        if self.est.vector:
            self._in_names = list(self.model.inputs)
            self._out_names = list(self.model.outputs)
        else:
            self._in_names = self._out_names = [self.axis]
        b = self.batch = p['batch']
        self.pub = self.sample_publisher(batch_topic(TOPIC_ESTIMATE, b), sample_type(b))
        # The callbacks get CDR bytes (see nodes.codec.decode_joint_state: 8x cheaper).
        self.sub_cmd = self.sample_subscription(
            batch_topic(TOPIC_COMMAND, b), self.on_command_batch if b > 1 else self.on_command,
            sample_type(b))
        self.sub_meas = self.sample_subscription(
            batch_topic(TOPIC_DEFLECTION, b),
            self.on_measurement_batch if b > 1 else self.on_measurement, sample_type(b))
        self.health = EstimatorHealth(self.est)
        # Measurement batches held back while the free run is steady and decoded together. They
        # only feed the running error then, over its last `window` pairs: the batches of the
        # newest `window` samples are kept and older ones dropped unread, when their estimates
        # stay well inside the ones kept for pairing; else at most a quarter of those, and 50
        # messages, all decoded.
        horizon = self.est.pairing_horizon
        self._held = HeldBatches(max(1, min(50, horizon // (4 * b))),
                                 keep=self.est.window if self.est.window + b <= horizon // 2
                                 else None)
        self.est.handover = self._take_held
        self._error_log = EpisodeLog(self.get_logger())
        # A command held back for its ambiguous stamp is decided when commands stop (the stream
        # ended right after a gap); checked a few times a second, nothing to do otherwise.
        self._commands_at_last_check = 0
        self.flush_timer = self.create_timer(0.2, self.on_idle_check)
        self.srv_reset = self.create_service(Trigger, '~/reset', self.on_reset)
        self.srv_reinitialize = self.create_service(Trigger, '~/reinitialize',
                                                    self.on_reinitialize)
        self.diagnostics = Diagnostics(self, self.status, task='free-run estimate',
                                       hardware_id=f"model {p['model']}")
        self.get_logger().info(
            f"model {p['model']} ({type(self.model).__name__} nu={self.model.nu} "
            f"ny={self.model.ny}) at {self.est.fs:g} Hz, init {p['init']}")

    def on_reset(self, _request, response):
        """~/reset (std_srvs/Trigger): the free run restarts from rest at the next command."""
        response.message = self.est.request_restart(from_measurement=False)
        response.success = True
        self.get_logger().info(response.message)
        return response

    def on_reinitialize(self, _request, response):
        """
        ~/reinitialize (std_srvs/Trigger): restart from the next n0 measured samples.

        Refused when nothing publishes deflection.
        """
        if self.sub_meas.get_publisher_count() == 0:
            response.success = False
            response.message = 'no deflection publisher to initialise from (~/reset restarts ' \
                               'from rest)'
            return response
        try:
            response.message = self.est.request_restart(from_measurement=True)
        except ConfigError as exc:
            response.success, response.message = False, str(exc)
            return response
        response.success = True
        self.get_logger().info(response.message)
        return response

    def _value(self, msg: bytes, field: str) -> tuple[int, float] | None:
        names = self._in_names if field == 'effort' else self._out_names
        try:
            sample = decode_joint_state(msg)
            if self.est.vector:
                return sample.t_ns, sample.values(field, names)
            return sample.t_ns, sample.value(field, self.axis)
        except Exception as exc:  # noqa: BLE001 - a malformed message must not stop the node
            self._refused(field, 'message', exc)
            return None

    def _values(self, msg: bytes, field: str):
        """(stamps (n,) int64 ns, `field` of the axis (n,)) of a batch; None when refused."""
        try:
            batch = decode_joint_trajectory(msg)
        except Exception as exc:  # noqa: BLE001 - refused below, like a batch without the axis
            batch = exc
        return self._batch_values(batch, field)

    def _batch_values(self, batch, field: str):
        """_values of a decoded batch, or of the exception that refused it (warned, None)."""
        try:
            if isinstance(batch, Exception):
                raise batch
            if self.est.vector:
                names = self._in_names if field == 'effort' else self._out_names
                return batch.t_ns, batch.columns(field, names)
            return batch.t_ns, batch.column(field, self.axis)
        except Exception as exc:  # noqa: BLE001 - a malformed message must not stop the node
            self._refused(field, 'batch', exc)
            return None

    def _refused(self, field: str, what: str, exc: Exception) -> None:
        """Count and log a message that cannot be read, saying why (for /diagnostics)."""
        topic = 'command' if field == 'effort' else 'deflection'
        self.est.stats.refused_messages += 1
        self.est.stats.last_refusal = f'{topic} {what}: {exc}'
        self.get_logger().warning(f'{topic} {what} ignored: {exc}', throttle_duration_sec=1.0)

    def on_command(self, msg: bytes) -> None:
        got = self._value(msg, 'effort')
        if got is None:
            return      # counted in refused_messages; the next command sees a gap
        self.publish(self._command(*got))

    def _command(self, t_ns: int, volts: float):
        if self.est.stats.commands == 0:
            self._command_start()
        return self.est.on_command(t_ns, volts)

    def _command_start(self) -> None:
        """Before the first command, tell the estimator whether a sensor and one writer exist."""
        self.est.start(self.sub_meas.get_publisher_count() > 0)
        self.est.rate.single_writer = self.sub_cmd.get_publisher_count() == 1

    def on_command_batch(self, msg: bytes) -> None:
        """Answer a batch with one batch (FreeRunEstimator.on_commands: one-sample numbers)."""
        got = self._values(msg, 'effort')
        if got is None:
            return      # counted in refused_messages, as in on_command
        if self.est.stats.commands == 0:
            self._command_start()
        self._publish_batch(*self.est.on_commands(*got))

    def _publish_batch(self, t, y) -> None:
        if t.shape[0]:
            self.pub.publish(encode_joint_trajectory(t, self._out_names,
                                                     position=y.reshape(t.shape[0], -1)))

    def on_measurement(self, msg: bytes) -> None:
        got = self._value(msg, 'position')
        if got is not None:
            ready = self.est.on_measurement(*got)
            if ready:            # estimates that waited for the initial measurements: rarely
                self.publish(ready)

    def on_measurement_batch(self, msg: bytes) -> None:
        if self.est.steady:
            if self._held.push(msg):
                self._take_held()
            return
        self._take_held()
        got = self._values(msg, 'position')
        if got is not None:
            self._publish_batch(*self.est.on_measurements(*got))

    def _take_held(self) -> None:
        """Hand the held measurement batches to the estimator (FreeRunEstimator.handover)."""
        for _, batch in self._held.take():
            got = self._batch_values(batch, 'position')
            if got is not None:
                self._publish_batch(*self.est.on_measurements(*got))

    def on_idle_check(self) -> None:
        """Commands stopped while one was held back: decide on it now."""
        n = self.est.stats.commands
        if n == self._commands_at_last_check and self.est.holding:
            self.publish(self.est.flush())
        self._commands_at_last_check = n

    def publish(self, estimates) -> None:
        names, pub = self._out_names, self.pub
        if self.batch > 1:
            self._publish_batch(*self.est.as_arrays(estimates))
            return
        vector = self.est.vector
        for t, y in estimates:
            pub.publish(encode_joint_state(t, names, position=y.tolist() if vector else (y,)))

    def status(self):
        """Everything since the previous tick (EstimatorHealth), plus the running error."""
        writers = self.sub_cmd.get_publisher_count()
        self.est.rate.single_writer = writers == 1
        clash = same_name_problem(self, TOPIC_ESTIMATE)
        level, msg, values = self.health.tick(
            writers, self.count_publishers(self.pub.topic_name), [clash] if clash else [])
        self._error_log.status(level, msg)
        rms, r2, n = self.est.running_error()
        # Matched deflection publishers: a launcher waits for 1 before streaming, so that the
        # first measured samples (the initial values) are not published before this matches.
        values['measurement_publishers'] = self.sub_meas.get_publisher_count()
        values['requested_restarts'] = self.est.stats.requested_restarts   # ~/reset, ~/reinit.
        if n >= 2 and not math.isnan(rms):
            values.update(rms_error_m=rms, r2=r2, error_window=n)
        return bytes([level]), msg, values


main = main_for(EstimatorNode)

if __name__ == '__main__':
    main()
