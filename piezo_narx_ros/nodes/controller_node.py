"""
controller_node: position_reference in, voltage_command out, through the identified model.

Loads a model file (JSON + .npz, never a pickle, never torch) and answers every position
reference (JointState, position = m) with a voltage command (effort = V) carrying the reference's
stamp. Modes (`mode`): linear (the model's static line), inverse (the model inverted sample by
sample, no sensor), inverse_feedback (inverse + PI on `deflection`). Limits, bad references,
stamps and gaps are handled by piezo_narx_ros.control.controller.PositionController; this node
only wires parameters, topics, the ~/reset service and /diagnostics to it.
"""
from __future__ import annotations

import math

import numpy as np
from std_srvs.srv import Trigger

from piezo_narx_ros.command.stamps import RATE_TOLERANCE
from piezo_narx_ros.control.controller import (MODES, PositionController, input_limits,
                                               safety_bounded)
from piezo_narx_ros.control.health import ControllerHealth
from piezo_narx_ros.control.inverse import TARGETS
from piezo_narx_ros.errors import ConfigError
from piezo_narx_ros.nodes.wire.batching import BATCH_PARAM, batch_topic, batch_values, sample_type
from piezo_narx_ros.nodes.wire import (decode_joint_state, decode_joint_trajectory,
                                       encode_joint_state, encode_joint_trajectory)
from piezo_narx_ros.nodes.diagnostics import DIAG_WARN, Diagnostics
from piezo_narx_ros.nodes.graph import EpisodeLog, same_name_problem
from piezo_narx_ros.nodes.params import ParamSpec
from piezo_narx_ros.nodes.runtime import PiezoNode, main_for
from piezo_narx_ros.nodes.topics import TOPIC_COMMAND, TOPIC_DEFLECTION, TOPIC_REFERENCE


class ControllerNode(PiezoNode):
    """Thin wiring: position_reference / deflection -> PositionController -> voltage_command."""

    NODE_NAME = 'controller_node'
    PARAMS = (
        ParamSpec('model', '', 'model file (.json with its .npz beside it)', read_only=True,
                  check=(lambda v: bool(v.strip()), 'must name a model file (.json)')),
        ParamSpec('mode', 'inverse', 'linear (static gain), inverse (model inverted, no sensor) '
                  'or inverse_feedback (inverse + PI on deflection)', choices=MODES,
                  read_only=True),
        ParamSpec('axis', 'x', 'axis read from position_reference/deflection and commanded',
                  read_only=True, check=(lambda v: bool(v.strip()), 'must not be empty')),
        ParamSpec('fs', 0.0, "reference sample rate, Hz (0: the model file's fs; any other "
                  'value must equal it)', low=0.0, high=100000.0, read_only=True),
        ParamSpec('rate_tolerance', RATE_TOLERANCE, 'relative difference between the reference '
                  "stream's stamp rate and the model's beyond which no command is sent (ERROR)",
                  low=1e-6, high=0.5, read_only=True),
        ParamSpec('target', 'auto', 'what the inverse solves for: output (the next model '
                  'output), quasi_static (hysteresis + creep only) or auto (quasi_static for a '
                  'hysteresis_narx model, else output)', choices=('auto',) + TARGETS,
                  read_only=True),
        ParamSpec('compensate_advance', True, 'ask for the lead of the output over the '
                  'quasi-static target (estimated from the model) to be taken off',
                  read_only=True),
        ParamSpec('u_min', 0.0, "lowest command, V (u_min = u_max = 0: the model's trained "
                  'input range widened by range_margin, so that no command leaves what the '
                  'model was fitted on)', low=-10000.0, high=10000.0, read_only=True),
        ParamSpec('u_max', 0.0, 'highest command, V', low=-10000.0, high=10000.0,
                  read_only=True),
        ParamSpec('v_min', -200.0, 'lowest voltage this node ever commands, V, whatever the model '
                  "file's trained range or u_min say (the amplifier's range)", low=-10000.0,
                  high=0.0, read_only=True),
        ParamSpec('v_max', 200.0, 'highest voltage this node ever commands, V, whatever the '
                  "model file's trained range or u_max say", low=0.0, high=10000.0,
                  read_only=True),
        ParamSpec('slew_rate', 1e5, 'largest command rate of change, V/s (0: no limit)',
                  low=0.0, high=1e12, read_only=True),
        ParamSpec('y_min', 0.0, "lowest accepted reference, m (y_min = y_max = 0: the model's "
                  'trained output range widened by range_margin)', low=-1.0, high=1.0,
                  read_only=True),
        ParamSpec('y_max', 0.0, 'highest accepted reference, m', low=-1.0, high=1.0,
                  read_only=True),
        ParamSpec('range_margin', 0.05, 'fraction of the trained output (input) span accepted '
                  'beyond it when y_min = y_max = 0 (u_min = u_max = 0)', low=0.0, high=10.0,
                  read_only=True),
        ParamSpec('kp', 0.0, 'inverse_feedback: proportional gain on reference - deflection '
                  '(m/m)', low=0.0, high=100.0, read_only=True),
        ParamSpec('ki', 100.0, 'inverse_feedback: integral gain, 1/s', low=0.0, high=1e6,
                  read_only=True),
        ParamSpec('feedback_timeout', 10, 'samples after which the last deflection is too old '
                  'for the proportional part', low=1, high=10**7, read_only=True),
        ParamSpec('max_fill', 2000, 'longest reference gap bridged by holding the command, '
                  'samples', low=0, high=10**7, read_only=True),
        ParamSpec('window', 2000, 'samples in the running tracking error (with a deflection)',
                  low=2, high=10**7, read_only=True),
        ParamSpec('use_deflection', True, 'subscribe to deflection (the PI of inverse_feedback, '
                  'and the tracking error on /diagnostics); false saves the callbacks (about '
                  '13 % of a core at 2 kHz here) in the other modes', read_only=True),
        ParamSpec('start', 'auto', "how the model's state is set: auto (the start policy the "
                  'model file stores, from the first measured deflections; rest without '
                  'use_deflection or a stored policy) or rest (the actuator is at rest)',
                  choices=('auto', 'rest'), read_only=True),
        ParamSpec('wait_for_subscribers', 0, 'subscribe to position_reference only once '
                  'voltage_command has this many subscriptions (so the first commands are '
                  'heard; a reference streamer waiting for this node then waits for them too)',
                  low=0, high=1000, read_only=True),
        BATCH_PARAM,
    )

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        from piezo_narx_ros.ident.validation.usable import load_runnable
        p = self.params
        trained_u = p['u_min'] == p['u_max'] == 0.0
        if p['u_min'] >= p['u_max'] and not trained_u:
            raise ConfigError(f"parameter u_min ({p['u_min']} V) must be below u_max "
                              f"({p['u_max']} V)")
        if p['mode'] == 'inverse_feedback' and not p['use_deflection']:
            raise ConfigError('mode inverse_feedback needs use_deflection:=true (its PI acts on '
                              'the measured deflection)')
        limits = ({} if p['y_min'] == p['y_max'] == 0.0
                  else {'y_min': p['y_min'], 'y_max': p['y_max']})
        self.model = load_runnable(p['model'])
        # A model of several axes (issue 20): AxesController, references and commands are
        # vectors mapped by the model's output and input names.
        self.vector = int(getattr(self.model, 'n_in', 1)) > 1 or \
            int(getattr(self.model, 'n_out', 1)) > 1
        if self.vector:
            self._init_axes(p, trained_u, limits)
            return
        u_limits = self._safe(p, {'u_min': p['u_min'], 'u_max': p['u_max']} if not trained_u
                              else input_limits(self.model, p['range_margin']))
        self.ctl = PositionController(
            self.model, mode=p['mode'], fs=p['fs'] or None, **u_limits,
            slew_rate=p['slew_rate'] or math.inf, range_margin=p['range_margin'],
            target=None if p['target'] == 'auto' else p['target'],
            advance=None if p['compensate_advance'] else 0.0, kp=p['kp'], ki=p['ki'],
            feedback_timeout=p['feedback_timeout'], max_fill=p['max_fill'],
            window=p['window'], rate_tolerance=p['rate_tolerance'],
            start_policy=None if p['start'] == 'auto' and p['use_deflection'] else 'rest',
            **limits)
        self.ctl.inverse.solve(0.0)   # compile/load the solver kernel before the first sample
        self.ctl.inverse.reset()      # ...and forget that solve (its remembered slope)
        self.axis = p['axis']
        self._names = self._ref_names = [self.axis]
        self._wire(p)
        self.health = ControllerHealth(self.ctl)
        c = self.ctl
        self.get_logger().info(
            f'{p["mode"]} with {type(self.model).__name__} ({p["model"]}) at {c.fs:g} Hz, '
            f'target {c.inverse.target}, advance {c.advance:.3f} samples, static gain '
            f'{c.gain * 1e6:.4g} um/V, references [{c.y_min * 1e6:.1f}, {c.y_max * 1e6:.1f}] '
            f'um, commands [{u_limits["u_min"]:g}, {u_limits["u_max"]:g}] V, start '
            + start_words(c))
        if c.model_note:
            self.get_logger().info(c.model_note)
        for note in c.notes:
            self.get_logger().warning(note)

    def _safe(self, p, u_limits: dict) -> dict:
        """Return the command limits within the node's safety window [v_min, v_max]; log a cut."""
        if not p['v_min'] < p['v_max']:
            raise ConfigError(f"parameter v_min ({p['v_min']} V) must be below v_max "
                              f"({p['v_max']} V)")
        bounded, note = safety_bounded(u_limits, p['v_min'], p['v_max'])
        if note:
            self.get_logger().warning(note)
        return bounded

    def _init_axes(self, p, trained_u: bool, limits: dict) -> None:
        """Several axes: AxesController (modes inverse and linear; limits on every axis)."""
        from piezo_narx_ros.control.axes import AxesController
        from piezo_narx_ros.ident.base import channel_ranges
        if trained_u:
            u_rng, _ = channel_ranges(self.model)
            pad = p['range_margin'] * (u_rng[:, 1] - u_rng[:, 0])
            u_limits = {'u_min': u_rng[:, 0] - pad, 'u_max': u_rng[:, 1] + pad}
        else:
            u_limits = {'u_min': p['u_min'], 'u_max': p['u_max']}
        u_limits = self._safe(p, u_limits)
        # A model of one chain per axis: each chain gets the one-axis controller's options.
        chain = {} if getattr(self.model, 'chains_', None) is None or p['mode'] == 'linear' \
            else {'target': None if p['target'] == 'auto' else p['target'],
                  'advance': None if p['compensate_advance'] else 0.0, 'kp': p['kp'],
                  'ki': p['ki'], 'feedback_timeout': p['feedback_timeout'],
                  'window': p['window']}
        self.ctl = AxesController(
            self.model, mode=p['mode'], fs=p['fs'] or None, **u_limits,
            slew_rate=p['slew_rate'] or math.inf, range_margin=p['range_margin'],
            max_fill=p['max_fill'], rate_tolerance=p['rate_tolerance'],
            start_policy=None if p['start'] == 'auto' and p['use_deflection'] else 'rest',
            **limits, **chain)
        self.ctl.warm_up()       # compile/load the solvers before the first sample
        self.axis = p['axis']
        self._names = list(self.model.inputs)        # commands: the model's inputs
        self._ref_names = list(self.model.outputs)   # references, deflections: its outputs
        self._wire(p)
        self.health = None
        how = ('one chain per axis, coupling compensated' if self.ctl.chains else
               'vector inverse' if p['mode'] != 'linear' else 'static line per axis')
        self.get_logger().info(
            f"{p['mode']} of {self._ref_names} with {type(self.model).__name__} "
            f"({p['model']}, {how}) at {self.ctl.fs:g} Hz, commands on {self._names}, start "
            + start_words(self.ctl))

    def _wire(self, p) -> None:
        """Create the publisher, subscriptions, timers, services and diagnostics."""
        b = self.batch = p['batch']
        self.pub = self.sample_publisher(batch_topic(TOPIC_COMMAND, b), sample_type(b))
        # The callbacks get CDR bytes (see nodes.codec.decode_joint_state: 8x cheaper).
        self.sub_ref = None
        self._wait_timer = self.create_timer(0.05, self.on_wait_check)
        self.on_wait_check()
        self.sub_meas = (self.sample_subscription(
            batch_topic(TOPIC_DEFLECTION, b),
            self.on_measurement_batch if b > 1 else self.on_measurement, sample_type(b))
            if p['use_deflection'] else None)
        self._error_log = EpisodeLog(self.get_logger())
        # A reference held back for its ambiguous stamp is decided when references stop.
        self._references_at_last_check = 0
        self.flush_timer = self.create_timer(0.2, self.on_idle_check)
        self.srv_reset = self.create_service(Trigger, '~/reset', self.on_reset)
        self.diagnostics = Diagnostics(self, self.status, task='position control',
                                       hardware_id=f"model {p['model']}")

    def on_wait_check(self) -> None:
        """Subscribe to the references once the commands have their listeners."""
        if self.sub_ref is None and \
                self.pub.get_subscription_count() >= self.params['wait_for_subscribers']:
            b = self.batch
            self.sub_ref = self.sample_subscription(
                batch_topic(TOPIC_REFERENCE, b),
                self.on_reference_batch if b > 1 else self.on_reference, sample_type(b))
            self._wait_timer.cancel()

    def pending_parameter_prefixes(self) -> list[str]:
        """position_reference may be subscribed after construction: its QoS overrides too."""
        topic = batch_topic(TOPIC_REFERENCE, self.params['batch'])
        return [f'qos_overrides.{self.resolve_topic_name(topic)}.subscription.']

    def on_reset(self, _request, response):
        """
        ~/reset (std_srvs/Trigger).

        The actuator is at rest now (0 V): the model restarts from rest and the integrator is
        cleared.
        """
        self.ctl.request_reset()
        response.success = True
        response.message = 'model restarted from rest (actuator at 0 V), integrator cleared'
        self.get_logger().info(response.message)
        return response

    def _value(self, msg: bytes, what: str) -> tuple[int, float] | None:
        try:
            sample = decode_joint_state(msg)
            if self.vector:
                return sample.t_ns, sample.values('position', self._ref_names)
            return sample.t_ns, sample.value('position', self.axis)
        except Exception as exc:  # noqa: BLE001 - a malformed message must not stop the node
            self._refused(what, 'message', exc)
            return None

    def _refused(self, what: str, kind: str, exc: Exception) -> None:
        """Log a message that cannot be read; a reference one is counted with its reason."""
        if what == 'reference':
            self.ctl.stats.refused_messages += 1
            self.ctl.stats.last_refusal = str(exc)
        self.get_logger().warning(f'{what} {kind} ignored: {exc}', throttle_duration_sec=1.0)

    def on_reference(self, msg: bytes) -> None:
        got = self._value(msg, 'reference')
        if got is None:
            return      # counted in refused_messages; the next reference sees a gap
        self.publish(self.ctl.on_reference(*got))

    def on_measurement(self, msg: bytes) -> None:
        got = self._value(msg, 'deflection')
        if got is None:
            self.ctl.stats.measurements_rejected += 1
            return
        self.ctl.on_measurement(*got)

    def _values(self, msg: bytes, what: str) -> list[tuple[int, float]] | None:
        try:
            if self.vector:
                b = decode_joint_trajectory(msg)
                return list(zip(b.t_ns.tolist(), b.columns('position', self._ref_names)))
            return batch_values(msg, 'position', self.axis)
        except Exception as exc:  # noqa: BLE001 - a malformed message must not stop the node
            self._refused(what, 'batch', exc)
            return None

    def on_reference_batch(self, msg: bytes) -> None:
        """Feed a batch sample by sample through the one-sample call; answer with one batch."""
        got = self._values(msg, 'reference')
        if got is None:
            return      # counted in refused_messages, as in on_reference
        self.publish([c for t, r in got for c in self.ctl.on_reference(t, r)])

    def on_measurement_batch(self, msg: bytes) -> None:
        got = self._values(msg, 'deflection')
        if got is None:
            self.ctl.stats.measurements_rejected += 1
            return
        for t, y in got:
            self.ctl.on_measurement(t, y)

    def on_idle_check(self) -> None:
        """Decide on a held-back reference now that references have stopped coming."""
        n = self.ctl.stats.references
        if n == self._references_at_last_check and self.ctl.holding:
            self.publish(self.ctl.flush())
        self._references_at_last_check = n

    def publish(self, commands) -> None:
        names, pub = self._names, self.pub
        if self.batch > 1:
            if commands:
                pub.publish(encode_joint_trajectory(
                    [t for t, _ in commands], names,
                    effort=np.array([u for _, u in commands]).reshape(len(commands), -1)))
            return
        for t, u in commands:
            pub.publish(encode_joint_state(t, names,
                                           effort=u.tolist() if self.vector else (u,)))

    def status(self):
        """Everything since the previous tick (ControllerHealth)."""
        waiting = self.sub_ref is None
        writers = None if waiting else self.sub_ref.get_publisher_count()
        self.ctl.rate.single_writer = writers == 1
        clash = same_name_problem(self, TOPIC_COMMAND)
        if self.vector:
            level, msg, values = self.ctl.status()
            if clash:
                level, msg = 2, clash
        else:
            level, msg, values = self.health.tick(writers, [clash] if clash else [])
        self._error_log.status(level, msg)
        if self.sub_meas is not None:
            values['measurement_publishers'] = self.sub_meas.get_publisher_count()
        values['command_subscribers'] = self.pub.get_subscription_count()
        if waiting:
            values['waiting_for_subscribers'] = self.params['wait_for_subscribers']
            if level == 0:
                return DIAG_WARN, (f"waiting for {self.params['wait_for_subscribers']} "
                                   'voltage_command subscriber(s)'), values
        return bytes([level]), msg, values


def start_words(ctl) -> str:
    """How a controller's model starts, for the log: its policy and window."""
    if ctl.start_policy == 'rest':
        return 'rest'
    return f'{ctl.start_policy} from the first {ctl.start_window} measured deflections'


main = main_for(ControllerNode)

if __name__ == '__main__':
    main()
