"""
The grid's 'auto' rules: which candidates are fitted on given estimation records.

Each rule reads the estimation input (coverage: minor loops, slow steps) and the number of axes,
and drops the candidates that do not belong there (ExperimentConfig's narx_beside,
without_increments, small_networks).
"""
from __future__ import annotations

from dataclasses import replace

from piezo_narx_ros.record import Record


def distinct_specs(specs: list, records: list) -> list:
    """
    Return the candidates that differ as fits on these records.

    On records of several axes the envelope family fits a deterministic structure that uses
    neither the network seed nor the drive increments (ident/hysteresis/mimo.py): its candidates
    would be the same fit several times (six with the envelope preset), so one is kept. With as
    many inputs as outputs every candidate is also fitted as one chain per axis
    (ident/hysteresis/chains.py: there seeds and increments matter, as for one axis).
    """
    if _one_axis(records):
        return list(specs)
    nets = [s for s in specs if s.kind == 'hysteresis_narx']
    square = all(getattr(r, 'n_in', 1) == getattr(r, 'n_out', 1) for r in records)
    chains = [replace(s, options=tuple(sorted(dict(s.options, structure='chains').items())))
              for s in nets] if square else []
    return nets[:1] + chains + [s for s in specs if s.kind != 'hysteresis_narx']


def _one_axis(records: list[Record]) -> bool:
    return all(getattr(r, 'n_in', 1) == 1 and getattr(r, 'n_out', 1) == 1 for r in records)


def _loop_rich(est: list[Record]) -> bool | None:
    """
    Tell whether the estimation input closes MINOR_LOOPS minor loops (coverage.inner_reversals).

    None on records of several axes, where neither 'auto' rule that asks was measured.
    """
    if not _one_axis(est):
        return None
    from ..data.coverage import inner_reversals
    from ..hysteresis.model import MINOR_LOOPS
    return inner_reversals(est) >= MINOR_LOOPS


def beside(specs: list, config, est: list[Record]) -> list:
    """
    Return specs without the paper's networks beside the envelope family where they do not belong.

    `narx_beside` 'auto': kept only on records of one axis whose estimation input closes
    MINOR_LOOPS minor loops (several axes: not measured, left as they were).
    """
    if config.family == 'narx' or config.narx_beside != 'auto':
        return list(specs)
    if _loop_rich(est):
        return list(specs)
    return [s for s in specs if s.kind != 'narx']


def increments(specs: list, config, est: list[Record]) -> list:
    """
    Return specs without the increment-free structure where it does not belong.

    `without_increments` 'auto': kept only on records of one axis whose estimation input moves
    slowly (coverage.SLOW_STEP; several axes: not measured, left as they were).
    """
    extra = config.increment_free()
    if extra is None or config.without_increments != 'auto':
        return list(specs)
    from ..data.coverage import SLOW_STEP, step_share
    if _one_axis(est) and step_share(est) < SLOW_STEP:
        return list(specs)

    def added(spec):
        options = {k: v for k, v in spec.options if k != 'structure'}
        return spec.kind == 'hysteresis_narx' and options == extra

    return [s for s in specs if not added(s)]


def small(specs: list, config, est: list[Record]) -> list:
    """
    Return specs without the small networks where they do not belong.

    `small_networks` 'auto': kept only on records of one axis whose estimation input closes
    fewer than MINOR_LOOPS minor loops (several axes: not measured, left out).
    """
    if len(config.hidden_sizes) == 1 or config.small_networks != 'auto':
        return list(specs)
    if _loop_rich(est) is False:
        return list(specs)
    return [s for s in specs if not (s.kind == 'hysteresis_narx'
                                     and s.hidden == config.small_hidden)]


def auto_grid(specs: list, config, est: list[Record]) -> list:
    """Return the specs fitted on estimation records est: every 'auto' rule applied."""
    return small(increments(beside(specs, config, est), config, est), config, est)
