"""
Structure search: family, structure, seeds and start policy, chosen on the validation records.

The paper closes with its future work: search the model's inputs and complexity globally instead
of over hand-picked grids. `run_search` is that search, an Optuna study over

* the family: ARX, the paper's NARX network, the hysteresis-operator NARX (and their several-axes
  forms: a record of several axes gives each family's several-axes model; the hysteresis family
  then also chooses between one joint model and one chain per axis where inputs and outputs pair);
* each family's structure (`SPACE`): lags, hidden units, play operators, Duhem states, drive
  increments, creep, output dynamics, training length, the network seed, and with several
  estimation records whether each has a sensor zero of its own (`OFFSETS_SPACE`);
* the start policy (ident/state/start.py): every fitted model is scored under each policy, so
  the policy costs no fit, and keeps `state` (a lagged family `offset` where that never loses to
  its measured lags; `start_scores` says why not the best score).

Every trial is fitted on the estimation records only and scored the way the model will be used:
a free run of each validation record after its first `init_samples` measured samples, the worst
case over records and outputs. Two objectives, that error (sqrt(1 - R²) of the worst record and
output: a relative RMSE) and the number of parameters; the study keeps the Pareto front and the
selection takes the fewest parameters within `tolerance` of the best error (ties: the correlation
tests pass, then the lower error), and says why.

Determinism: trials are asked in batches of `batch` (not of the worker count), the sampler of batch
b is a TPESampler seeded from (seed, b), and results are told in trial order once the batch is
done, so for a given seed and number of trials the study and the selected model are the same bits
on any executor and with any number of workers. The first batch is the seed design (`SEED_DESIGN`:
the envelope preset's structures, the paper's network and ARX orders): the search starts where the
presets are.

Storage: the study is an Optuna journal (DIR/study.journal); each finished trial's scores and model
are written to DIR/trials/ as it ends. An interrupted run (SIGINT, SIGTERM, a crash) continues with
`resume=True`: complete trials and finished fits are taken over, the rest of the interrupted batch
is fitted again (same parameters, same bits), and the run ends on the same model as an
uninterrupted one.
"""
from __future__ import annotations

import hashlib
import json
import math
import os
import time
from dataclasses import dataclass, field

import numpy as np

from piezo_narx_ros.errors import ConfigError, DataError, PiezoNarxError
from piezo_narx_ros.ident.base import Interval, Options
from piezo_narx_ros.ident.selection.executor import Executor, TaskFailure, in_worker
from piezo_narx_ros.ident.selection.experiment import (FINAL_TRAINING, CandidateResult,
                                                       CandidateSpec, ExperimentConfig,
                                                       fit_candidate)
from piezo_narx_ros.ident.selection.study import Study, sampler
from piezo_narx_ros.ident.state.estimate import MIN_WINDOW, PASTS
from piezo_narx_ros.ident.state.start import (START_POLICIES, check_window, lagged,
                                              policy_simulate)
from piezo_narx_ros.ident.validation import metrics
from piezo_narx_ros.record import Record, as_columns, channels_arg

SEARCH_FAMILIES = ('arx', 'narx', 'hysteresis_narx')
#: Error of a trial whose free run is not finite on some validation record (a finite number:
#: Optuna sorts the front on it).
DIVERGED = 1e6

# The search space: per family, each parameter's distribution. ('int', lo, hi) or
# ('cat', choices). The reference and the tests read this table.
SPACE = {
    'arx': {'arx_na': ('int', 1, 10), 'arx_nb': ('int', 1, 10)},
    'narx': {'narx_ny': ('int', 1, 10), 'narx_nu': ('int', 1, 10),
             'narx_hidden': ('int', 3, 24),
             'narx_seed': ('int', 0, 4), 'narx_training': ('cat', ('screen', 'final'))},
    'hysteresis_narx': {
        'hnarx_hidden': ('int', 3, 16), 'hnarx_plays': ('int', 4, 24),
        'hnarx_duhem': ('int', 0, 3), 'hnarx_lags': ('cat', (0, 3, 6, 10)),
        'hnarx_order': ('int', 1, 5), 'hnarx_creep': ('cat', ('none', 'excited', 'free')),
        'hnarx_seed': ('int', 0, 4), 'hnarx_iter': ('cat', (30, 60, 120))},
}
#: Several estimation records (one axis): whether the hysteresis family gives each record its
#: own sensor zero (HysteresisNARX record_offsets 'yes') or one zero for all ('no').
OFFSETS_SPACE = {'hnarx_offsets': ('cat', ('per_record', 'shared'))}
#: Several axes: the hysteresis family's form, and the joint form's dynamics order.
MIMO_SPACE = {'hnarx_structure': ('cat', ('joint', 'chains')),
              'hnarx_mimo_order': ('int', 8, 40)}
_HNARX_DEFAULT = {'family': 'hysteresis_narx', 'hnarx_hidden': 10, 'hnarx_plays': 12,
                  'hnarx_duhem': 1, 'hnarx_lags': 3, 'hnarx_order': 3,
                  'hnarx_creep': 'excited', 'hnarx_seed': 0, 'hnarx_iter': 60}
#: The first trials: the envelope preset's structures (increments 3, 6 and none; two seeds), the
#: paper's network at two lag orders and two ARX orders.
SEED_DESIGN = (
    _HNARX_DEFAULT,
    {**_HNARX_DEFAULT, 'hnarx_lags': 6},
    {**_HNARX_DEFAULT, 'hnarx_lags': 0},
    {**_HNARX_DEFAULT, 'hnarx_seed': 1},
    {'family': 'narx', 'narx_ny': 2, 'narx_nu': 2, 'narx_hidden': 10, 'narx_seed': 0,
     'narx_training': 'final'},
    {'family': 'narx', 'narx_ny': 4, 'narx_nu': 4, 'narx_hidden': 10, 'narx_seed': 0,
     'narx_training': 'final'},
    {'family': 'arx', 'arx_na': 4, 'arx_nb': 4},
    {'family': 'arx', 'arx_na': 8, 'arx_nb': 8},
)
_MIMO_SEED_DESIGN = (
    {'family': 'hysteresis_narx', 'hnarx_structure': 'joint', 'hnarx_plays': 12,
     'hnarx_duhem': 1, 'hnarx_mimo_order': 28, 'hnarx_creep': 'excited'},
    {**_HNARX_DEFAULT, 'hnarx_structure': 'chains'},
)


@dataclass
class SearchOptions:
    """
    Settings of the search (samples, seconds, fractions as named).

    trials: trials in the study (seed design included); budget_s: wall-time budget, s (no new
    batch starts when the last one would end past it; None: no budget); seed: the sampler's;
    batch: trials asked at once (the selected model depends on it, not on the workers);
    init_seconds: measured samples at each validation record's start, s, that its start policy
    may use (init_samples overrides it in samples); past: how the records' pasts ended
    (ident.state.PASTS); tolerance: relative error above the best within which the fewest
    parameters win, and within which the committee must score of the pick; committee: models
    averaged, the pick and the next best of its family (ident/selection/committee.py; 1: the
    pick alone); families: the families searched (None:
    every family, the paper's network only where the estimation input closes minor loops:
    `resolve_families`); split: estimation fraction of each record when there are no validation
    records; max_lag, max_outside_fraction, noise_model, noise_order: the correlation tests
    reported beside.
    """

    trials: int = 32
    budget_s: float | None = 540.0
    seed: int = 0
    batch: int = 8
    init_seconds: float = 0.5
    init_samples: int | None = None
    past: str = 'any'
    tolerance: float = 0.02
    committee: int = 3
    families: tuple | None = None
    split: float = 0.5
    max_lag: int = 20
    max_outside_fraction: float = 0.05
    noise_model: str = 'ar'
    noise_order: int = 20
    progress: bool | None = None

    _parameter_constraints = {
        'trials': Interval(int, 1, 100000), 'budget_s': Interval(float, 1.0, 1e7),
        'seed': Interval(int, 0, 2 ** 31 - 1), 'batch': Interval(int, 1, 1024),
        'init_seconds': Interval(float, 0.0, 600.0), 'init_samples': Interval(int, 0, 10 ** 9),
        'past': Options(PASTS), 'tolerance': Interval(float, 0.0, 1.0),
        'committee': Interval(int, 1, 16),
        'split': Interval(float, 0.1, 0.9), 'max_lag': Interval(int, 1, 10000),
        'max_outside_fraction': Interval(float, 0.0, 0.99),
        'noise_order': Interval(int, 0, 200), 'noise_model': Options(('ar', 'none'))}

    def validate(self) -> None:
        """Raise ConfigError naming the first bad setting."""
        for name, rule in self._parameter_constraints.items():
            value = getattr(self, name)
            if value is None and name in ('budget_s', 'init_samples'):
                continue
            setattr(self, name, rule.check(name, value))
        if self.families is None:
            return
        families = tuple(self.families)
        if not families or any(f not in SEARCH_FAMILIES for f in families) \
                or len(set(families)) != len(families):
            raise ConfigError(f'families must be distinct names among '
                              f'{", ".join(SEARCH_FAMILIES)}, got {list(families)}')
        self.families = families

    def window(self, fs: float) -> int:
        """Measured samples at each validation record's start (at fs Hz)."""
        if self.init_samples is not None:
            return int(self.init_samples)
        return int(round(self.init_seconds * fs))


@dataclass(frozen=True)
class SpaceContext:
    """What the space depends on: the records' channels and the number of estimation records."""

    n_in: int = 1
    n_out: int = 1
    n_records: int = 1
    #: Whether the hysteresis family is searched without drive increments (hnarx_lags 0): on
    #: one axis only where the estimation input moves slowly (`increment_free`).
    without_increments: bool = True

    @property
    def one_axis(self) -> bool:
        """Return True for one input and one output."""
        return self.n_in == 1 and self.n_out == 1

    @property
    def offsets(self) -> bool:
        """Return True when the hysteresis family chooses per-record or shared sensor zeros."""
        return self.one_axis and self.n_records > 1

    @property
    def square(self) -> bool:
        """Return True when every output pairs with one input (one chain per axis possible)."""
        return self.n_in == self.n_out


def space(context: SpaceContext, families=SEARCH_FAMILIES) -> dict:
    """Return {family: {parameter: distribution}} for records of `context`'s channels."""
    out = {f: dict(SPACE[f]) for f in families}
    if 'hysteresis_narx' in out and not context.one_axis:
        out['hysteresis_narx'].update(MIMO_SPACE if context.square
                                      else {'hnarx_mimo_order': MIMO_SPACE['hnarx_mimo_order']})
    if 'hysteresis_narx' in out and context.offsets:
        out['hysteresis_narx'].update(OFFSETS_SPACE)
    if 'hysteresis_narx' in out and not context.without_increments:
        lags = SPACE['hysteresis_narx']['hnarx_lags']
        out['hysteresis_narx']['hnarx_lags'] = (lags[0], tuple(v for v in lags[1] if v))
    return out


def seed_design(context: SpaceContext, families=SEARCH_FAMILIES) -> list[dict]:
    """Return the first trials' parameters for records of `context` (families kept)."""
    design = SEED_DESIGN if context.one_axis else _MIMO_SEED_DESIGN + tuple(
        p for p in SEED_DESIGN if p['family'] != 'hysteresis_narx')
    out = []
    for params in design:
        if params['family'] not in families:
            continue
        if (not context.one_axis and params.get('hnarx_structure') == 'chains'
                and not context.square):
            continue
        if params.get('hnarx_lags') == 0 and not context.without_increments:
            continue
        if context.offsets and params['family'] == 'hysteresis_narx':
            params = {**params, 'hnarx_offsets': 'per_record'}   # the presets' fit
        out.append(dict(params))
    return out


def _suggest(trial, name: str, dist: tuple):
    if dist[0] == 'int':
        return trial.suggest_int(name, dist[1], dist[2])
    return trial.suggest_categorical(name, list(dist[1]))


def suggest(trial, context: SpaceContext, families=SEARCH_FAMILIES) -> dict:
    """Draw one trial's parameters (define-by-run: only the family's own are drawn)."""
    table = space(context, families)
    family = trial.suggest_categorical('family', list(families))
    dists = table[family]
    params = {'family': family}
    if family == 'hysteresis_narx' and not context.one_axis:
        structure = (_suggest(trial, 'hnarx_structure', dists['hnarx_structure'])
                     if 'hnarx_structure' in dists else 'joint')
        params['hnarx_structure'] = structure
        names = (('hnarx_plays', 'hnarx_duhem', 'hnarx_mimo_order', 'hnarx_creep')
                 if structure == 'joint' else tuple(SPACE['hysteresis_narx']))
        for name in names:
            params[name] = _suggest(trial, name, dists[name])
        return params
    for name, dist in dists.items():
        params[name] = _suggest(trial, name, dist)
    return params


def spec_from_params(params: dict) -> tuple[CandidateSpec, dict]:
    """Return (CandidateSpec, NARX training options) of one trial's parameters."""
    family = params['family']
    if family == 'arx':
        return CandidateSpec('arx', nu=int(params['arx_nb']), ny=int(params['arx_na'])), {}
    if family == 'narx':
        training = dict(FINAL_TRAINING) if params['narx_training'] == 'final' else {}
        return CandidateSpec('narx', nu=int(params['narx_nu']), ny=int(params['narx_ny']),
                             hidden=int(params['narx_hidden']),
                             seed=int(params['narx_seed'])), training
    if family != 'hysteresis_narx':
        raise ConfigError(f'unknown family {family!r}')
    from piezo_narx_ros.ident.hysteresis.model import DEFAULT_CREEP_TAUS, HysteresisNARX
    creep = params['hnarx_creep']
    options = {'n_plays': int(params['hnarx_plays']), 'n_duhem': int(params['hnarx_duhem'])}
    if creep == 'none':
        options['creep_taus'] = ()
    else:
        options.update(creep=creep, creep_taus=DEFAULT_CREEP_TAUS)
    if 'hnarx_offsets' in params:
        options['record_offsets'] = 'yes' if params['hnarx_offsets'] == 'per_record' else 'no'
    structure = params.get('hnarx_structure')
    hidden, seed = 10, 0
    if structure == 'joint':
        options['mimo_order'] = int(params['hnarx_mimo_order'])
    else:
        order = int(params['hnarx_order'])
        options.update(n_lags=int(params['hnarx_lags']), na=order, nb=order,
                       max_iter=int(params['hnarx_iter']))
        hidden, seed = int(params['hnarx_hidden']), int(params['hnarx_seed'])
    probe = HysteresisNARX(hidden=hidden, seed=seed, **options)
    if structure == 'chains':
        options['structure'] = 'chains'
    return CandidateSpec('hysteresis_narx', nu=probe.nu, ny=probe.ny, hidden=hidden, seed=seed,
                         options=tuple(sorted(options.items()))), {}


def params_key(params: dict) -> str:
    """Return a canonical text of a trial's parameters (equal parameters, equal fits)."""
    return json.dumps(params, sort_keys=True)


# ------------------------------------------------------------------ scoring a fitted model
def _worst(score: dict) -> float | None:
    """Return the lowest R² of a channel_scores block over its outputs (None: not finite)."""
    values = [o['r2'] for o in score.get('per_output', [])] or [score['r2']]
    return None if any(v is None for v in values) else min(values)


def _policy_error(model, records: list[Record], n: int, policy: str, past: str) -> dict:
    """Return {'r2_worst', 'error', 'records'} of one policy with the first n samples measured."""
    rows, worst = [], math.inf
    for r in records:
        sim = as_columns(policy_simulate(model, channels_arg(r.u), channels_arg(r.y), n,
                                         policy, past))[n:]
        if np.all(np.isfinite(sim)):
            score = metrics.channel_scores(r.y[n:], sim, r.outputs)
            w = _worst(score)
        else:
            score, w = {'r2': None, 'rmse': None, 'diverged': True}, None
        rows.append({'source': r.source, 'samples': int(len(r) - n), **score})
        worst = -math.inf if w is None else min(worst, w)
    error = DIVERGED if not math.isfinite(worst) else math.sqrt(max(0.0, 1.0 - worst))
    return {'r2_worst': worst if math.isfinite(worst) else None, 'error': min(error, DIVERGED),
            'records': rows}


def check_windows(model, n: int) -> tuple:
    """
    Return the windows (samples) a lagged model's policies are compared on: n, n/2, n/4, n/8.

    A rig may give its estimator fewer samples than the search scored with (`--init-samples`
    says how many there are; the stored policy decides how they are used): a policy that only
    beats the measured lags with the whole window, e.g. from rest once the start-up transient
    has died (Bouc-Wen: 3x the paper start's error with 10 samples), is not stored.
    """
    least = max(MIN_WINDOW, int(model.n0))
    return tuple(sorted({w for w in (n // 8, n // 4, n // 2) if w >= least} | {n}))


def start_scores(model, records: list[Record], n: int, past: str = 'any') -> dict:
    """
    Score the free run of every record after its first n samples, under each start policy.

    Returns {'policies': {policy: {'r2_worst', 'error', 'records', 'windows'}}, 'policy': the
    chosen one, 'window', 'r2_worst', 'error'}; error = sqrt(1 - worst R²) over records and
    outputs (DIVERGED when a free run is not finite). Every policy is scored and reported; the
    one kept is `state` (ties: START_POLICIES order), except that a family whose state is its
    lags takes `offset` where that is no worse with n samples nor with any of
    `check_windows(model, n)`: the paper's start is what no policy may lose to, also for a rig
    that gives its estimator fewer samples.

    Why not the best score: the validation records share the estimation session's sensor zero
    and the model's idea of what a record's unknown past left in it; a rig's next day shares
    neither, and no record of one session shows what a start that ignores them then costs. In
    bench_real's session scenario (seed 0, other sessions' records, zeros moved by up to 5 um)
    the best-scoring start on the same session's validation record was `rest` (Bouc-Wen by 6 %
    over `state`, Preisach by 42 %) and scored R² 0.930 / 0.989 / 0.985 and 0.915 / 0.989 /
    0.989 on the other sessions' multisine, triangle and held levels; `offset` (the zero from
    the window, the memory assumed at rest; 1.5 % behind `rest` on Bouc-Wen) 0.99993 / 0.99477 /
    0.99307; `state`, which estimates memory and zero together, 0.99992 / 0.99994 / 0.99993.
    """
    for r in records:
        for policy in START_POLICIES:
            check_window(model, policy, n, len(r), r.source)
    windows = check_windows(model, n) if lagged(model) else (n,)
    result = {}
    for policy in START_POLICIES:
        result[policy] = _policy_error(model, records, n, policy, past)
        shorter = {w: _policy_error(model, records, w, policy, past)['error']
                   for w in windows if w != n}
        result[policy]['windows'] = {**{str(w): e for w, e in shorter.items()},
                                     str(n): result[policy]['error']}
    state = result['state']['windows']
    eligible = [p for p in START_POLICIES if p == 'state' or lagged(model) and p != 'rest'
                and all(result[p]['windows'][w] <= state[w] for w in state)]
    best = min(eligible, key=lambda p: (result[p]['error'], START_POLICIES.index(p)))
    return {'policies': result, 'policy': best, 'window': int(n),
            'r2_worst': result[best]['r2_worst'], 'error': result[best]['error']}


def _experiment_config(options: SearchOptions, training: dict) -> ExperimentConfig:
    """Return the settings fit_candidate scores with (the tests reported beside the score)."""
    return ExperimentConfig(training=training, final_training={}, max_lag=options.max_lag,
                            max_outside_fraction=options.max_outside_fraction,
                            noise_model=options.noise_model, noise_order=options.noise_order,
                            jobs=1, progress=False)


def trial_task(payload: tuple, data: tuple) -> CandidateResult:
    """Executor task: payload (params, options, window n), data (estimation, validation)."""
    params, options, n = payload
    spec, training = spec_from_params(params)
    if spec.kind == 'narx' and in_worker():
        import torch        # one torch thread per worker, as many workers as cores
        torch.set_num_threads(1)
    est, val = data
    res = fit_candidate(spec, est, val, _experiment_config(options, training))
    if res.error is None:
        try:
            res.scores['start'] = start_scores(res.model, val, n, options.past)
        except PiezoNarxError as exc:
            res.error = str(exc)
    return res


def trial_error(res: CandidateResult) -> float:
    """Return a trial's search error (DIVERGED for a failed fit)."""
    if res.error is not None:
        return DIVERGED
    return float(res.scores['start']['error'])


# ------------------------------------------------------------------ selection
def pareto_front(points: list[tuple[float, int]]) -> list[int]:
    """Return the indices of the points (error, n_params) no other point beats (ties once)."""
    front = []
    for i, (e, p) in enumerate(points):
        dominated = any((e2 <= e and p2 <= p and (e2 < e or p2 < p)) or
                        (e2 == e and p2 == p and j < i)
                        for j, (e2, p2) in enumerate(points))
        if not dominated:
            front.append(i)
    return front


def select_simplest(trials: list[CandidateResult], tolerance: float) -> tuple[int, str]:
    """
    Return (index, why): the fewest parameters within `tolerance` of the best error.

    Ties in parameters: the correlation tests' verdict, then the lower error, then the earlier
    trial. DataError when no trial was fitted.
    """
    ok = [i for i, t in enumerate(trials) if t.error is None and trial_error(t) < DIVERGED]
    if not ok:
        first = next((t.error for t in trials if t.error), 'every free run diverged')
        raise DataError(f'no trial of the search could be fitted and scored: {first}')
    best = min(ok, key=lambda i: (trial_error(trials[i]), i))
    limit = trial_error(trials[best]) * (1.0 + tolerance)
    within = [i for i in ok if trial_error(trials[i]) <= limit]
    pick = min(within, key=lambda i: (trials[i].n_params, not trials[i].validated,
                                      trial_error(trials[i]), i))
    t, b = trials[pick], trials[best]
    r2 = t.scores['start']['r2_worst']
    why = (f'{t.spec.label}: the fewest parameters ({t.n_params}) among the {len(within)} '
           f'trial(s) within {100 * tolerance:g} % of the best worst-case validation error '
           f'({b.spec.label}, error {trial_error(b):.4g}); its worst-case validation R² '
           f'{r2:.6f} with the {t.scores["start"]["policy"]!r} start; correlation tests '
           f'{"pass" if t.validated else "fail"}')
    return pick, why


@dataclass
class SearchResult:
    """Every trial (trial order), the selected one and why, and how the run went."""

    trials: list[CandidateResult]
    numbers: list[int]               # Optuna trial numbers, per trial
    selected: int
    why: str
    front: list[int]
    options: SearchOptions
    window: int
    wall_seconds: float
    taken_over: int = 0              # trials a resumed run took over from the journal or disk
    stopped: str = 'trials'          # 'trials' or 'budget'
    notes: list = field(default_factory=list)   # what the search decided on its own, in words
    sources: list = field(default_factory=list)
    validation_sources: list | None = None
    fs: float = 0.0
    n_estimation: int = 0
    n_validation: int = 0
    committee: CandidateResult | None = None   # the mean of `members` (committee.py), if kept
    members: list = field(default_factory=list)   # its trials (indices), the pick first

    @property
    def best(self) -> CandidateResult:
        """Return the model the search gives: the committee when kept, else the selected trial."""
        return self.committee if self.committee is not None else self.trials[self.selected]

    def family_table(self) -> list[dict]:
        """Per family: its best trial (lowest error) and how many trials it had."""
        rows = []
        for family in SEARCH_FAMILIES:
            idx = [i for i, t in enumerate(self.trials) if t.spec.kind == family]
            ok = [i for i in idx if self.trials[i].error is None]
            if not idx:
                continue
            row = {'family': family, 'trials': len(idx), 'failed': len(idx) - len(ok)}
            if ok:
                i = min(ok, key=lambda j: (trial_error(self.trials[j]), j))
                t = self.trials[i]
                row.update(best=t.spec.label, trial=self.numbers[i], n_params=t.n_params,
                           r2_worst=t.scores['start']['r2_worst'],
                           policy=t.scores['start']['policy'], error=trial_error(t))
            rows.append(row)
        return rows

    def to_dict(self) -> dict:
        """JSON-ready summary: options, every trial, the front and the selection."""
        from dataclasses import asdict
        opts = asdict(self.options)
        opts['families'] = list(opts['families'])
        return {'search': {'options': opts, 'window_samples': self.window,
                           'wall_seconds': self.wall_seconds, 'taken_over': self.taken_over,
                           'stopped': self.stopped,
                           'front': [self.numbers[i] for i in self.front],
                           'families': self.family_table()},
                'data': {'sources': self.sources, 'fs': self.fs,
                         'validation_sources': self.validation_sources,
                         'n_estimation': self.n_estimation, 'n_validation': self.n_validation},
                'selection': {'trial': self.numbers[self.selected],
                              'label': self.best.spec.label, 'why': self.why,
                              'validated': self.best.validated,
                              'committee': [self.numbers[i] for i in self.members],
                              'error': trial_error(self.best),
                              'n_params': self.best.n_params},
                'candidates': [{'trial': n, 'error': trial_error(t), **t.to_dict()}
                               for n, t in zip(self.numbers, self.trials)]}


# ------------------------------------------------------------------ the study
def fingerprint(est: list[Record], val: list[Record], options: SearchOptions) -> str:
    """SHA-256 of what decides every trial: the records' samples and rate, and the options."""
    h = hashlib.sha256()
    for r in list(est) + ['|'] + list(val):
        if isinstance(r, str):
            h.update(r.encode())
            continue
        for a in (r.u, r.y):
            arr = np.ascontiguousarray(a, dtype=np.float64)
            h.update(f'{arr.shape};'.encode())
            h.update(arr.tobytes())
        h.update(f'{r.fs!r};'.encode())
    keys = ('seed', 'batch', 'init_seconds', 'init_samples', 'past', 'families', 'max_lag',
            'max_outside_fraction', 'noise_model', 'noise_order')
    h.update(json.dumps({k: getattr(options, k) for k in keys}, sort_keys=True,
                        default=list).encode())
    return h.hexdigest()


def _values(res: CandidateResult) -> list[float]:
    return [trial_error(res), float(res.n_params if res.n_params is not None else 1e12)]


def resolve_families(est: list[Record], families) -> tuple[tuple, list[str]]:
    """
    Return (families, notes): the families given, or for None every family but the paper's.

    The paper's network takes part only where the estimation input closes MINOR_LOOPS minor
    loops (several axes: always): on one full-range sine nothing in the data decides how it
    behaves inside the loop and the validation records cannot tell either (the real
    micromanipulator: the search's pick among such networks, validation R² 0.99985, scored 0.21
    on its test record; the envelope preset's rule, docs/real.md).
    """
    if families is not None:
        return tuple(families), []
    from piezo_narx_ros.ident.data.coverage import inner_reversals
    from piezo_narx_ros.ident.hysteresis.model import MINOR_LOOPS
    one_axis = all(r.n_in == 1 and r.n_out == 1 for r in est)
    loops = inner_reversals(est) if one_axis else None
    if loops is None or loops >= MINOR_LOOPS:
        return SEARCH_FAMILIES, []
    return (tuple(f for f in SEARCH_FAMILIES if f != 'narx'),
            [f"the paper's NARX is left out: the estimation input closes {loops} minor loop(s) "
             f'(fewer than {MINOR_LOOPS}), so neither it nor the validation records decide how '
             'such a network behaves inside the loop (--families arx,narx,hysteresis_narx '
             'searches it anyway)'])


def increment_free(est: list[Record]) -> tuple[bool, str]:
    """
    Return (whether networks without drive increments are searched, a note when they are not).

    Only on one-axis estimation inputs that move slowly (coverage.SLOW_STEP; several axes: always),
    the envelope preset's rule (ExperimentConfig.without_increments 'auto'): on a fast input the
    increments carry the drive's rate, and one validation record does not tell what a network
    without them loses: on the simulators' battery the searches that picked such networks scored
    R² 0.99976-0.99983 on a fresh multisine, the envelope structure 0.99994 (docs/search.md).
    """
    from piezo_narx_ros.ident.data.coverage import SLOW_QUANTILE, SLOW_STEP, step_share
    if not all(r.n_in == 1 and r.n_out == 1 for r in est):
        return True, ''
    share = step_share(est)
    if share < SLOW_STEP:
        return True, ''
    return False, ('the hysteresis NARX is searched with drive increments only: the estimation '
                   f'input moves fast ({100 * SLOW_QUANTILE:g} % of its moving steps up to '
                   f'{100 * share:.3g} % of its range a sample, slow below {100 * SLOW_STEP:g} %)')


def run_search(est: list[Record], val: list[Record], options: SearchOptions,
               executor: Executor, out, resume: bool = False,
               force: bool = False) -> SearchResult:
    """
    Search family, structure, seed and start policy; return every trial and the selection.

    est: estimation records (fitted whole), val: validation records (scored only; no sample of
    theirs reaches a fit). The study and the trials are stored in `out`. DataError when the
    validation records are too short for the window or constant; KeyboardInterrupt passes
    through with the finished trials stored (continue with resume=True).
    """
    options.validate()
    if not est or not val:
        raise DataError('the search needs estimation and validation records')
    options.families, notes = resolve_families(est, options.families)
    n = options.window(val[0].fs)
    for r in val:
        if float(np.std(r.y[n:])) == 0.0:
            raise DataError(f'{r.source}: the output is constant after the first {n} samples: '
                            'it cannot score a model (R² undefined)')
        if len(r) < n + 2:
            raise DataError(f'{r.source}: {len(r)} samples, too short for a window of {n} '
                            'measured samples and a scored free run after it')
    free, note = increment_free(est)
    notes += [note] if note else []
    context = SpaceContext(getattr(est[0], 'n_in', 1), getattr(est[0], 'n_out', 1), len(est),
                           without_increments=free)
    store = Study(out, resume, force)
    study = store.open(fingerprint(est, val, options))
    optuna = store.optuna
    t0 = time.perf_counter()
    before_s = float(study.user_attrs.get('elapsed_s', 0.0)) if resume else 0.0
    data = {0: (est, val)}
    done_params: dict[str, CandidateResult] = {}
    results: dict[int, CandidateResult] = {}
    numbers_params: dict[int, dict] = {}
    taken_over, stopped, batch_s = 0, 'trials', []
    show = options.progress
    if show is None:
        show = os.isatty(2)
    from tqdm import tqdm
    bar = tqdm(total=options.trials, desc='search', unit='trial', disable=not show)
    try:
        b = 0
        while b * options.batch < options.trials:
            size = min(options.batch, options.trials - b * options.batch)
            trials = [t for t in study.get_trials(deepcopy=False)
                      if t.user_attrs.get('batch') == b]
            complete = [t for t in trials if t.state == optuna.trial.TrialState.COMPLETE]
            if len(complete) == size:
                for t in sorted(complete, key=lambda t: t.number):
                    res = store.load_trial(t.number, dict(t.params),
                                           spec_from_params(dict(t.params))[0])
                    if res is None:
                        raise DataError(f'{store.trial_path(t.number)}: missing or changed; the '
                                        'study cannot be continued (start again with --force)')
                    results[t.number], numbers_params[t.number] = res, dict(t.params)
                    done_params.setdefault(params_key(t.params), res)
                taken_over += size
                bar.update(size)
                b += 1
                continue
            elapsed = before_s + time.perf_counter() - t0
            guess = max(batch_s) if batch_s else 0.0
            if options.budget_s is not None and b > 0 and elapsed + guess > options.budget_s:
                stopped = 'budget'
                break
            tb = time.perf_counter()
            live = _batch_trials(study, optuna, store, options, context, b, size, trials)
            todo, tasks = [], []
            for trial_number, params in live:
                numbers_params[trial_number] = params
                res = store.load_trial(trial_number, params, spec_from_params(params)[0])
                if res is not None:
                    taken_over += 1
                elif params_key(params) in done_params:
                    res = done_params[params_key(params)]
                if res is not None:
                    results[trial_number] = res
                    bar.update(1)
                    continue
                todo.append((trial_number, params))
                tasks.append((0, (params, options, n)))

            def finished(i, out_, todo=todo):
                number, params = todo[i]
                res = _as_result(params, out_)
                results[number] = res
                store.save_trial(number, params, res)
                bar.update(1)

            executor.map(trial_task, tasks, data, finished)
            by_number = {t.number: t for t in study.get_trials(deepcopy=False)}
            for trial_number, params in live:
                res = results[trial_number]
                done_params.setdefault(params_key(params), res)
                if by_number[trial_number].state == optuna.trial.TrialState.COMPLETE:
                    continue      # told before an interruption inside this loop
                # A Trial handle on the stored trial (also one a previous process asked): user
                # attributes can only be set while it runs.
                handle = optuna.trial.Trial(study, by_number[trial_number]._trial_id)
                for key, value in _trial_attrs(res).items():
                    handle.set_user_attr(key, value)
                study.tell(trial_number, _values(res))
            batch_s.append(time.perf_counter() - tb)
            study.set_user_attr('elapsed_s', before_s + time.perf_counter() - t0)
            b += 1
    finally:
        bar.close()
    order = sorted(results)
    trials = [results[k] for k in order]
    points = [(trial_error(t), t.n_params if t.n_params is not None else 10 ** 12)
              for t in trials]
    ok_points = [i for i, t in enumerate(trials) if t.error is None]
    front = [ok_points[i] for i in pareto_front([points[i] for i in ok_points])]
    selected, why = select_simplest(trials, options.tolerance)
    committee, members, said = _committee(trials, selected, options, est, val, n)
    if said:
        why = f'{why}; {said}'
    return SearchResult(trials=trials, numbers=order, selected=selected, why=why, front=front,
                        committee=committee, members=members,
                        options=options, window=n,
                        wall_seconds=before_s + time.perf_counter() - t0,
                        taken_over=taken_over, stopped=stopped, notes=notes,
                        sources=[r.source for r in est], fs=est[0].fs,
                        validation_sources=[r.source for r in val],
                        n_estimation=sum(len(r) for r in est),
                        n_validation=sum(len(r) for r in val))


def _committee(trials: list[CandidateResult], pick: int, options: SearchOptions,
               est: list[Record], val: list[Record], n: int) -> tuple:
    """Form the committee of the pick (committee.form_committee), scored as a trial is."""
    from piezo_narx_ros.ident.selection.committee import form_committee
    from piezo_narx_ros.ident.selection.experiment import score_candidate
    errors = [trial_error(t) for t in trials]
    usable = [i for i, t in enumerate(trials) if t.error is None and errors[i] < DIVERGED]

    def score(model, spec):
        res = score_candidate(CandidateResult(spec=spec), model, est, val,
                              _experiment_config(options, {}))
        res.scores['start'] = start_scores(model, val, n, options.past)
        return res, trial_error(res)
    return form_committee(trials, errors, usable, pick, options.committee, options.tolerance,
                          score)


def _as_result(params: dict, outcome) -> CandidateResult:
    if isinstance(outcome, TaskFailure):
        return CandidateResult(spec=spec_from_params(params)[0], error=outcome.message)
    return outcome


def _trial_attrs(res: CandidateResult) -> dict:
    """Return what optuna-dashboard shows beside a trial's values."""
    attrs = {'label': res.spec.label, 'error_text': res.error or ''}
    if res.error is None:
        start = res.scores['start']
        attrs.update(policy=start['policy'], r2_worst=start['r2_worst'],
                     validated=bool(res.validated))
    return attrs


def _batch_trials(study, optuna, store: Study, options: SearchOptions, context: SpaceContext,
                  b: int, size: int, existing: list) -> list[tuple[int, dict]]:
    """
    Return batch b's (trial number, params): the ones asked before an interruption, or new.

    A batch interrupted while it was being asked is failed and asked again: batch b's sampler is
    seeded from (seed, b) and sees only the complete batches before it, so it asks the same. A
    batch interrupted after it was asked (while fitting, or while its results were told) keeps
    its trials, the ones told and the ones still running: asking again would let the sampler
    see the told ones and ask something else (seen under load: another model after resume).
    """
    state = optuna.trial.TrialState
    kept = [t for t in existing if t.state in (state.RUNNING, state.COMPLETE)]
    if len(kept) == size and len({t.number for t in kept}) == size:
        return [(t.number, dict(t.params)) for t in sorted(kept, key=lambda t: t.number)]
    # Every trial not complete here belongs to batch b's interrupted asking, also one asked
    # before its batch number was written: fail them all, or the sampler would count them.
    for t in study.get_trials(deepcopy=False, states=(state.RUNNING,)):
        study.tell(t.number, state=state.FAIL)
    # Enqueued seed-design trials not asked yet: a waiting trial cannot be told, so ask it
    # (the oldest waiting one comes first) and fail it; the batch enqueues its own again.
    for _ in study.get_trials(deepcopy=False, states=(state.WAITING,)):
        study.tell(study.ask(), state=state.FAIL)
    study.sampler = sampler(optuna, options.seed, options.batch, b)
    # The seed design fills the first batches, whatever their size.
    design = seed_design(context, options.families)[b * options.batch:][:size]
    for params in design:
        study.enqueue_trial(params)
    out = []
    for _ in range(size):
        trial = study.ask()
        params = suggest(trial, context, options.families)
        # Written last: a trial with its batch number has all its parameters.
        trial.set_user_attr('batch', b)
        out.append((trial.number, params))
    return out
