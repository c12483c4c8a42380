"""
The controller's /diagnostics status, ROS-free: what happened since the previous tick.

As for the estimator (estimator/health.py), the level covers every reference and command since the
last tick: a burst of unreachable references between two ticks is a WARN tick even if the sample
at the tick is fine, and the tick after the trouble is OK again.

What the loop achieves is judged on every tick too (`PositionController.tracking`), so the status
never says ok while the controller's own figures are far off: with a deflection, a tracking error
above TRACKING_WARN of the reference's own motion is a WARN, above TRACKING_ERROR (worse than
standing still) or a deflection that moves against the reference (correlation below ANTI_PHASE)
an ERROR; without one, commands that move against the reference (their correlation with it has
the other sign than the plant's gain, when that sign is known) are an ERROR. A reference stream
at another rate than the model's is an ERROR while it lasts (no command is sent).
"""
from __future__ import annotations

import math

from piezo_narx_ros.control.controller import FEEDBACK_MODES
from piezo_narx_ros.counters import ERROR, OK, WARN, Since

# Fewest samples in the window before the tracking figures are judged.
MIN_JUDGED = 200
ANTI_PHASE = -0.3
TRACKING_WARN = 0.25      # RMS error / reference standard deviation
TRACKING_ERROR = 1.0
# A reference that holds (moves less than this share of the trained output span): the error is
# judged against the span instead.
HOLD_SPAN = 0.01
HOLD_WARN = 0.05

# Counters whose growth since the last tick makes the tick a WARN, with the phrase that says so.
_WARN_ON = (
    ('unreachable', 'command(s) could not reach their target within the limits (closest input '
                    'sent)'),
    ('out_of_range', 'reference(s) outside [y_min, y_max] clamped'),
    ('rejected_nonfinite', 'non-finite reference(s): the previous one held'),
    ('refused_messages', 'reference message(s) refused'),
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
               'measurements_late', 'feedback_stale', 'windup_holds', 'requested_resets',
               'rate_refused', 'model_nonfinite', 'refused_messages')


def nonfinite_line(n: int, commands: int) -> str:
    """Return the ERROR phrase for commands after which the model's output was NaN/inf."""
    return (f"{n} of {commands} commands: the model's output is not finite (NaN/inf), so it "
            'cannot be inverted and no target is met (commands held); the model file is '
            'unusable (piezo-narx evaluate refuses it): refit or load another')


class ControllerHealth:
    """Turns a PositionController's counters into one status per diagnostics tick."""

    def __init__(self, controller):
        self.ctl = controller
        self._warn = _WARN_ON + (_WARN_ON_FEEDBACK if controller.mode in FEEDBACK_MODES else ())
        self._since = Since(lambda: vars(controller.stats),
                            [name for name, _ in self._warn] + ['commands', 'voltage_limited',
                                                                'slew_limited',
                                                                'not_invertible',
                                                                'rate_refused',
                                                                'model_nonfinite'])

    def rate_line(self) -> str:
        """Return the one line that says why no command is sent (the reference stream's rate)."""
        return (f'{self.ctl.rate.describe("reference")}: no command sent (the stage holds), the '
                f'model runs only at {self.ctl.fs:g} Hz')

    def judge_tracking(self, values: dict) -> tuple[list[str], list[str]]:
        """(errors, warnings) from PositionController.tracking(); fills `values`."""
        ctl = self.ctl
        tr = ctl.tracking()
        errors, warnings = [], []
        for key in ('rms_m', 'reference_std_m', 'corr_ry', 'corr_ur'):
            if not math.isnan(tr[key]):
                values[key.replace('rms_m', 'tracking_rms_m')] = tr[key]
        span = ctl.y_max - ctl.y_min
        if tr['measured'] >= MIN_JUDGED:
            rms, ref = tr['rms_m'], tr['reference_std_m']
            values['tracking_window'] = tr['measured']
            if ref > HOLD_SPAN * span:
                if tr['corr_ry'] < ANTI_PHASE:
                    errors.append(f'anti-phase: the deflection correlates {tr["corr_ry"]:.3f} '
                                  f'with the reference (tracking error {rms:.3g} m RMS): the '
                                  'stage moves against the reference; stop it and check the '
                                  "model's gain")
                elif rms > TRACKING_ERROR * ref:
                    errors.append(f"tracking error {rms:.3g} m RMS exceeds the reference's own "
                                  f'motion ({ref:.3g} m RMS): worse than holding still')
                elif rms > TRACKING_WARN * ref:
                    warnings.append(f'tracking error {rms:.3g} m RMS is {rms / ref:.0%} of the '
                                    "reference's motion")
            elif rms > HOLD_WARN * span:
                warnings.append(f'tracking error {rms:.3g} m RMS on a holding reference '
                                f'({rms / span:.0%} of the output span)')
        sign = ctl.gain_check.plant_sign
        # Only on a moving reference: on a hold the commands follow creep and noise, not it.
        if tr['commands'] >= MIN_JUDGED and sign and not math.isnan(tr['corr_ur']) \
                and tr['command_reference_std_m'] > HOLD_SPAN * span \
                and sign * tr['corr_ur'] < ANTI_PHASE:
            errors.append(f'commands move against the reference (correlation '
                          f'{tr["corr_ur"]:.3f}; the plant gain is '
                          f'{"positive" if sign > 0 else "negative"}): anti-phase')
        return errors, warnings

    def tick(self, reference_publishers: int | None = None, errors=()) -> tuple[int, str, dict]:
        """
        (level OK/WARN/ERROR, message, values) for the period since the previous call.

        reference_publishers: writers matched on the reference topic (None: unknown); more than
        one is a WARN, since their samples interleave. errors: further ERROR phrases found by
        the caller (e.g. a second node of the same name).
        """
        d = self._since.tick()
        ctl, st = self.ctl, self.ctl.stats
        miss = ctl.take_peak_miss()
        values = {}
        errors = list(errors)
        if ctl.rate.off or d['rate_refused']:
            errors.append(f'{self.rate_line()} ({d["rate_refused"]} references refused since '
                          'the last report)')
        if d['model_nonfinite']:
            errors.append(nonfinite_line(d['model_nonfinite'], d['commands']))
        tracking_errors, problems = self.judge_tracking(values)
        errors += tracking_errors
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
            elif name == 'refused_messages':
                text += f' (the last: {st.last_refusal})'
            problems.append(text)
        problems += ctl.notes
        values.update({k: getattr(st, k) for k in _CUMULATIVE})
        values.update({f'{name}_since_last': d[name] for name, _ in self._warn})
        values.update(mode=ctl.mode, target=ctl.inverse.target, advance_samples=ctl.advance,
                      static_gain_m_per_v=ctl.gain, holding=ctl.holding, u_last=ctl.u_last,
                      y_model=ctl.y_model, y_min=ctl.y_min, y_max=ctl.y_max)
        values['static_gain_trusted'] = ctl.gain_check.trusted
        if ctl.rate.ratio == ctl.rate.ratio:     # measured (not NaN)
            values['stream_rate_hz'] = ctl.fs / ctl.rate.ratio
        if reference_publishers is not None:
            values['reference_publishers'] = reference_publishers
        found = errors + problems
        if found:
            message = found[0] + (f' (+{len(found) - 1} more)' if len(found) > 1 else '')
            return (ERROR if errors else WARN), message, values
        return OK, f'ok ({ctl.mode})', values
