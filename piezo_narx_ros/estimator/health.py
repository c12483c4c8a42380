"""
The estimator's /diagnostics status, ROS-free: what happened since the previous tick.

The level reflects every estimate and command since the last tick, not the last sample: a runaway
that leaves the trained output range for 2,807 samples between two ticks is a WARN tick even if
the sample at the tick happens to be back in range, and the tick after the trouble is OK again.
A command stream at another rate than the model's is an ERROR for as long as it lasts (its
estimates are withheld), and so is a second node publishing on the same estimate topic. A free
run started from rest whose state is not yet determined (the actuator's unknown past can still
move it, estimator.memory) is a WARN with that bound, until it is.
"""
from __future__ import annotations

from piezo_narx_ros.counters import ERROR, OK, WARN, Since
from piezo_narx_ros.ident.data.units import model_unit_problem

# Counters whose growth since the last tick makes the tick a WARN, with the phrase that says so.
_WARN_ON = (
    ('out_of_range', 'estimate(s) outside the trained output range'),
    ('stamp_outliers', 'command stamp(s) refused as outliers (out of order, future/past, '
                       'duplicate, a second writer, or commands faster than fs)'),
    ('stream_restarts', 'command stream restart(s) (a loop, a new run or a long jump): free '
                        'run restarted'),
    ('rejected_nonfinite', 'non-finite command(s) held'),
    ('refused_messages', 'message(s) refused'),
    ('rejected_range', 'command(s) outside [u_min, u_max] held'),
    ('gaps', 'gap(s) in the command stamps, filled by holding'),
    ('input_out_of_range', 'command(s) outside the trained input range: the model extrapolates'),
)
_CUMULATIVE = ('commands', 'estimates', 'rejected_nonfinite', 'rejected_range',
               'refused_messages', 'gaps', 'filled', 'nonfinite_estimates',
               'stamp_outliers', 'stream_restarts', 'out_of_range', 'reanchors', 'unestimated',
               'init', 'rate_withheld', 'input_out_of_range')


class EstimatorHealth:
    """
    Turns a FreeRunEstimator's counters into one status per diagnostics tick.

    `notes`: standing problems of the set-up (a model whose trained ranges are not volts and
    metres), a WARN on every tick while the estimator runs.
    """

    def __init__(self, estimator):
        self.est = estimator
        note = model_unit_problem(estimator.model)
        self.notes = [note] if note else []
        self._since = Since(lambda: vars(estimator.stats),
                            [name for name, _ in _WARN_ON] + ['estimates', 'commands',
                                                              'rate_withheld',
                                                              'nonfinite_estimates'])

    def rate_line(self) -> str:
        """Return the one line that says why estimates are withheld (the stream's rate)."""
        return (f'{self.est.rate.describe("command")}: estimates withheld, the model runs only '
                f'at {self.est.fs:g} Hz (stream at that rate, or fit a model at the stream rate)')

    def tick(self, command_publishers: int | None = None,
             estimate_publishers: int | None = None, errors=()) -> tuple[int, str, dict]:
        """
        (level OK/WARN/ERROR, message, values) for the period since the previous call.

        command_publishers: writers matched on the command topic (None: unknown); more than one
        is a WARN, since their samples interleave. estimate_publishers: writers on this node's
        own estimate topic, itself included; more than one is an ERROR (two estimators, e.g. of
        the same name, interleave their estimates there). errors: further ERROR phrases found by
        the caller (e.g. a second node of the same name).
        """
        d = self._since.tick()
        st = self.est.stats
        excursion = self.est.take_excursion()
        u_beyond = self.est.take_input_excursion()
        errors, problems = list(errors), []
        if d['nonfinite_estimates']:
            errors.append(f"{d['nonfinite_estimates']} of {d['estimates']} estimates are not "
                          "finite (NaN/inf): the model's free run diverged and cannot stand in "
                          'for the sensor (evaluate refuses such a model file); refit it')
        if self.est.rate.off or d['rate_withheld']:
            errors.append(f'{self.rate_line()} ({d["rate_withheld"]} withheld since the last '
                          'report)')
        if estimate_publishers is not None and estimate_publishers > 1:
            errors.append(f'{estimate_publishers} publishers on the estimate topic (another '
                          'estimator, maybe of the same name): their estimates interleave')
        if command_publishers is not None and command_publishers > 1:
            problems.append(f'{command_publishers} publishers on the command topic: their '
                            'samples interleave')
        for name, phrase in _WARN_ON:
            if d[name]:
                text = f'{d[name]} {phrase}'
                if name == 'out_of_range':
                    text = (f'{d[name]} of {d["estimates"]} estimates outside the trained output '
                            f'range (up to {excursion:.3g} m beyond it)')
                elif name == 'input_out_of_range':
                    text += f' (up to {u_beyond:.3g} V beyond it)'
                elif name == 'refused_messages':
                    text += f' (the last: {st.last_refusal})'
                problems.append(text)
        problems += self.notes
        if st.state == 'undetermined' and st.state_spread_m > 0:
            # Started from rest without a sensor: until the input sweeps its range the unknown
            # past of the actuator (hysteresis memory, creep) is an offset nobody measured.
            problems.append(f"state undetermined: the actuator's unknown past can still shift "
                            f'the estimate by up to {st.state_spread_m:.3g} m (until the input '
                            'sweeps its range, or init from measurement)')
        values = {k: getattr(st, k) for k in _CUMULATIVE}
        values.update(state=st.state, state_spread_m=st.state_spread_m,
                      state_rms_m=st.state_rms_m, init_samples=self.est.init_samples)
        values.update({f'{name}_since_last': d[name] for name, _ in _WARN_ON})
        values['holding'] = self.est.holding
        values['fs'] = self.est.fs
        if self.est.rate.ratio == self.est.rate.ratio:      # measured (not NaN)
            values['stream_rate_hz'] = self.est.fs / self.est.rate.ratio
        if command_publishers is not None:
            values['command_publishers'] = command_publishers
        if estimate_publishers is not None:
            values['estimate_publishers'] = estimate_publishers
        found = errors + problems
        if found:
            more = f' (+{len(found) - 1} more)' if len(found) > 1 else ''
            return (ERROR if errors else WARN), found[0] + more, values
        return OK, f'ok (init {st.init}, state {st.state or "waiting"})', values
