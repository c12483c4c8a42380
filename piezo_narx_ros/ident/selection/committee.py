"""
The search's committee: the mean of the pick and the next best trials of its family.

A search scores tens of networks on one or two validation records and picks the best of them; the
best score of many is partly luck (the winner's curse), and a network's random start decides as
much as its structure. On the simulators' battery of moves (docs/envelope.md) the single pick of
the search was worse than the envelope preset's on every plant (fresh multisine R² worst 0.99975
against 0.99993), and the mean of the pick and the two next best trials of its family was better
than the pick on each of the four searches checked (0.99990-0.99996). There the committee also
scored better on the validation half (error 0.0087-0.0123 against the pick's 0.0104-0.0130). On
the Bouc-Wen benchmark the mean of three paper networks scored 0.0253 against its pick's 0.0145
(its third member 0.041) and more than doubled the test error (7.6e-6 -> 1.8e-5 m). So the
committee is the model only where it scores within the search's tolerance of the pick on the
validation records: the band in which two models count as equally good.

Only families whose fits start from random weights (the paper's NARX, the hysteresis-operator
NARX) and one-axis models: an ARX fit is a least-squares solution with nothing to average, and
a model of several axes must keep its one-model stepper cost (the FSM's 3 x 3 per-sample
target). The live cost is K steps a sample instead of one.
"""
from __future__ import annotations

from piezo_narx_ros.errors import PiezoNarxError
from piezo_narx_ros.ident.selection.experiment import CandidateResult, ensemble_of

#: Families whose trials differ by their random start: the committee averages them.
COMMITTEE_FAMILIES = ('narx', 'hysteresis_narx')


def members(trials: list[CandidateResult], errors: list[float], usable, pick: int,
            size: int) -> list[int]:
    """Return the pick and the size - 1 usable trials of its family with the lowest errors."""
    kind = trials[pick].spec.kind
    others = sorted((i for i in usable if i != pick and trials[i].model is not None
                     and trials[i].spec.kind == kind), key=lambda i: (errors[i], i))
    return [pick] + others[:max(0, size - 1)]


def eligible(trial: CandidateResult, size: int) -> bool:
    """Return True when a pick gets a committee: one-axis, of COMMITTEE_FAMILIES, size >= 2."""
    model = trial.model
    return (size >= 2 and trial.spec.kind in COMMITTEE_FAMILIES
            and int(getattr(model, 'n_in', 1)) == 1 and int(getattr(model, 'n_out', 1)) == 1)


def form_committee(trials: list[CandidateResult], errors: list[float], usable, pick: int,
                   size: int, tolerance: float, score) -> tuple[CandidateResult | None, list, str]:
    """
    Return (the committee's result or None, its member indices, a sentence for the report).

    errors: each trial's search error; usable: the indices of trials fitted and scored;
    score(model, spec) -> (CandidateResult, error) of that model scored as every trial is. The
    committee is returned only when its error is within `tolerance` (relative) of the pick's.
    """
    if not eligible(trials[pick], size):
        return None, [], ''
    chosen = members(trials, errors, usable, pick, size)
    kind = trials[pick].spec.kind
    if len(chosen) < 2:
        return None, [], f'no committee: no other {kind} trial was fitted'
    try:
        res, err = score(*ensemble_of([trials[i] for i in chosen]))
    except PiezoNarxError as exc:
        return None, [], f'no committee: {exc}'
    limit = errors[pick] * (1.0 + tolerance)
    what = (f'the mean of it and the {len(chosen) - 1} next best {kind} trial(s) (members '
            f'{min(errors[i] for i in chosen):.4g}-{max(errors[i] for i in chosen):.4g})')
    if res.error is not None or not err <= limit:
        got = res.error or f'validation error {err:.4g}'
        return None, [], (f'{what} scored {got}, more than {100 * tolerance:g} % above the '
                          'pick: the pick alone is the model')
    return res, chosen, (f'the model is {what}: validation error {err:.4g}, within '
                         f'{100 * tolerance:g} % of the pick, {res.n_params} parameters')
