"""
The controller's /diagnostics status, ROS-free: what happened since the previous tick.

As for the estimator (estimator/health.py), the level covers every reference and command since the
last tick: a burst of unreachable references between two ticks is a WARN tick even if the sample
at the tick is fine, and the tick after the trouble is OK again.
"""
from __future__ import annotations

import math

from piezo_narx_ros.control.controller import FEEDBACK_MODES
from piezo_narx_ros.counters import OK, WARN, Since

# Counters whose growth since the last tick makes the tick a WARN, with the phrase that says so.
_WARN_ON = (
    ('unreachable', 'command(s) could not reach their target within the limits (closest input '
                    'sent)'),
    ('out_of_range', 'reference(s) outside [y_min, y_max] clamped'),
    ('rejected_nonfinite', 'non-finite reference(s): the previous one held'),
    ('stamp_outliers', 'reference stamp(s) refused as outliers (backwards, far in the future, '
                       'duplicate or a second writer): no command sent'),
    ('stream_restarts', 'reference stream restart(s) followed (the model kept its state)'),
    ('gaps', 'gap(s) in the reference stamps: the model held the last command'),
)
# Only meaningful when the mode uses the deflection.
_WARN_ON_FEEDBACK = (
    ('feedback_stale', 'command(s) without a recent deflection (proportional part off)'),
    ('measurements_rejected', 'deflection sample(s) ignored (non-finite, or no command with '
                              'that stamp)'),
    ('measurements_late', 'deflection sample(s) older than feedback_timeout: not integrated'),
)
_CUMULATIVE = ('references', 'commands', 'rejected_nonfinite', 'out_of_range', 'gaps', 'filled',
               'stamp_outliers', 'stream_restarts', 'unreachable', 'voltage_limited',
               'slew_limited', 'not_invertible', 'measurements', 'measurements_rejected',
               'measurements_late', 'feedback_stale', 'windup_holds', 'requested_resets')


class ControllerHealth:
    """Turns a PositionController's counters into one status per diagnostics tick."""

    def __init__(self, controller):
        self.ctl = controller
        self._warn = _WARN_ON + (_WARN_ON_FEEDBACK if controller.mode in FEEDBACK_MODES else ())
        self._since = Since(lambda: vars(controller.stats),
                            [name for name, _ in self._warn] + ['commands', 'voltage_limited',
                                                                'slew_limited',
                                                                'not_invertible'])

    def tick(self, reference_publishers: int | None = None) -> tuple[int, str, dict]:
        """
        (level OK/WARN, message, values) for the period since the previous call.

        reference_publishers: writers matched on the reference topic (None: unknown); more than
        one is a WARN, since their samples interleave.
        """
        d = self._since.tick()
        ctl, st = self.ctl, self.ctl.stats
        miss = ctl.take_peak_miss()
        problems = []
        if reference_publishers is not None and reference_publishers > 1:
            problems.append(f'{reference_publishers} publishers on the reference topic: their '
                            'samples interleave')
        for name, phrase in self._warn:
            if not d[name]:
                continue
            text = f'{d[name]} {phrase}'
            if name == 'unreachable':
                text = (f'{d[name]} of {d["commands"]} commands missed their target by up to '
                        f'{miss:.3g} m (voltage limit {d["voltage_limited"]}, slew limit '
                        f'{d["slew_limited"]}, model flat/folded {d["not_invertible"]}): '
                        'closest input sent')
            problems.append(text)
        values = {k: getattr(st, k) for k in _CUMULATIVE}
        values.update({f'{name}_since_last': d[name] for name, _ in self._warn})
        values.update(mode=ctl.mode, target=ctl.inverse.target, advance_samples=ctl.advance,
                      static_gain_m_per_v=ctl.gain, holding=ctl.holding, u_last=ctl.u_last,
                      y_model=ctl.y_model, y_min=ctl.y_min, y_max=ctl.y_max)
        if reference_publishers is not None:
            values['reference_publishers'] = reference_publishers
        rms, n = ctl.running_error()
        if n and not math.isnan(rms):
            values.update(tracking_rms_m=rms, tracking_window=n)
        if problems:
            message = problems[0] + (f' (+{len(problems) - 1} more)' if len(problems) > 1 else '')
            return WARN, message, values
        return OK, f'ok ({ctl.mode})', values
