"""
The estimator's /diagnostics status, ROS-free: what happened since the previous tick.

The level reflects every estimate and command since the last tick, not the last sample: a runaway
that leaves the trained output range for 2,807 samples between two ticks is a WARN tick even if
the sample at the tick happens to be back in range, and the tick after the trouble is OK again.
"""
from __future__ import annotations

from piezo_narx_ros.counters import OK, WARN, Since

# Counters whose growth since the last tick makes the tick a WARN, with the phrase that says so.
_WARN_ON = (
    ('out_of_range', 'estimate(s) outside the trained output range'),
    ('stamp_outliers', 'command stamp(s) refused as outliers (out of order, future/past, '
                       'duplicate, a second writer, or commands faster than fs)'),
    ('stream_restarts', 'command stream restart(s) (a loop, a new run or a long jump): free '
                        'run restarted'),
    ('rejected_nonfinite', 'non-finite command(s) held'),
    ('rejected_range', 'command(s) outside [u_min, u_max] held'),
    ('gaps', 'gap(s) in the command stamps, filled by holding'),
)
_CUMULATIVE = ('commands', 'estimates', 'rejected_nonfinite', 'rejected_range', 'gaps', 'filled',
               'stamp_outliers', 'stream_restarts', 'out_of_range', 'reanchors', 'unestimated',
               'init')


class EstimatorHealth:
    """Turns a FreeRunEstimator's counters into one status per diagnostics tick."""

    def __init__(self, estimator):
        self.est = estimator
        self._since = Since(lambda: vars(estimator.stats),
                            [name for name, _ in _WARN_ON] + ['estimates', 'commands'])

    def tick(self, command_publishers: int | None = None) -> tuple[int, str, dict]:
        """
        (level OK/WARN, message, values) for the period since the previous call.

        command_publishers: writers matched on the command topic (None: unknown); more than one
        is a WARN, since their samples interleave.
        """
        d = self._since.tick()
        st = self.est.stats
        excursion = self.est.take_excursion()
        problems = []
        if command_publishers is not None and command_publishers > 1:
            problems.append(f'{command_publishers} publishers on the command topic: their '
                            'samples interleave')
        for name, phrase in _WARN_ON:
            if d[name]:
                text = f'{d[name]} {phrase}'
                if name == 'out_of_range':
                    text = (f'{d[name]} of {d["estimates"]} estimates outside the trained output '
                            f'range (up to {excursion:.3g} m beyond it)')
                problems.append(text)
        values = {k: getattr(st, k) for k in _CUMULATIVE}
        values.update({f'{name}_since_last': d[name] for name, _ in _WARN_ON})
        values['holding'] = self.est.holding
        if command_publishers is not None:
            values['command_publishers'] = command_publishers
        if problems:
            message = problems[0] + (f' (+{len(problems) - 1} more)' if len(problems) > 1 else '')
            return WARN, message, values
        return OK, f'ok (init {st.init})', values
