"""
The paper's identification experiment.

A grid of NARX networks and ARX baselines, judged on R² and the Billings correlation tests, and the
choice of one model.

Protocol
--------
* Each record is split 50/50: the first half estimates, the second half validates. With several
  records every model is fitted on the list of estimation halves: no regressor row, free-run
  segment or state crosses from one record to the next. Each validation half is predicted and
  simulated on its own, initialised from its first n0 measured outputs; a model whose state is a
  function of the whole input history (`state_from_input`, the hysteresis-operator NARX) is run
  from its recording's start instead and scored on the validation samples. Scores are given
  pooled over records (samples k >= n0) and per record.
* Every candidate is scored (R², RMSE, NRMSE, fit %) in one-step prediction and in free-run
  simulation, on estimation and on validation data.
* The correlation tests run on validation residuals of both modes, after a noise model (NARMAX,
  Billings ch. 5): a linear AR whitening filter fitted on the ESTIMATION residuals of the same
  mode (order by BIC, <= `noise_order`) and applied unchanged to the validation residuals
  (noise_model.py). The tests then judge the innovations of process model + noise model; the
  filter uses past residuals only, so what the input can still predict stays visible. The raw
  residuals' verdicts are kept too (`tests['raw']`). `noise_model='none'` tests raw residuals.
* Which residuals select (`residuals`): 'simulation' by default. The plant's noise is sensor
  (output) noise and the networks are refined on simulation error, so the process model's optimal
  predictor is its free run: with a correct process model the simulation residual is the white
  sensor noise. One-step residuals of such a plant carry that noise through the y-lags as a
  nonlinear moving average, which a linear noise model cannot whiten (docs/validation.md has the
  measurements). 'prediction' (Billings' equation-error view) stays available.
* Selection (`selection = 'tests'`, the paper's): among candidates whose tests pass, the fewest
  parameters; ties go to the best worst-case free-run R², the lowest of the pooled estimation
  halves and each validation record (so a network that is unstable when the excitation switches
  on at the start of a record, or that fails on one kind of record, cannot win). If none passes,
  the best such R², flagged `validated = False`. `selection = 'worst_case'` (the envelope
  preset) takes the best worst-case free-run R² whatever the tests say. The winner, if a paper
  network, is trained again with `final_training` and kept only when no worse.
* Presets (`PRESETS`): 'paper' is the paper's grid (NARX lags 1..4 x 1..4, 10 units, ARX
  1..10 x 1..10); 'envelope' is the hysteresis-operator NARX over several network seeds with a
  small ARX baseline, selected on the worst case (docs/envelope.md).

Runs candidates on `jobs` worker processes (spawn start, one torch/BLAS thread each) with a
tqdm bar on long grids. Results do not depend on `jobs`: each fit is seeded and independent.
"""
from __future__ import annotations

import os
import time
from dataclasses import asdict, dataclass, field, replace

import numpy as np

from piezo_narx_ros.errors import ConfigError, DataError, PiezoNarxError
from piezo_narx_ros.ident.data.records import check_length, check_scorable
from piezo_narx_ros.ident.selection.executor import Executor, LocalExecutor, TaskFailure, in_worker
from piezo_narx_ros.ident.selection.grid import auto_grid, distinct_specs
from piezo_narx_ros.ident.selection.scoring import RESIDUAL_KINDS, evaluate_model, fit_noise_models
from piezo_narx_ros.ident.state.estimate import check_past
from piezo_narx_ros.ident.validation.noise_model import NOISE_MODELS
from piezo_narx_ros.record import Record, channels_arg, check_same_channels

# Final training of the selected network (over the grid's `training`): a longer simulation-error
# refinement, early-stopped on the held-out free run. Measured on a 25 s plant record: NARX(4,3,10)
# validation free-run R² 0.99993 -> 0.99997, and 0.99989 -> 0.99995 live on a fresh multisine.
# The one-step stage is left as screened: 4x longer one-step training gave a network that fell into
# a limit cycle when the excitation switched on (R² -94 on its own estimation record).
FINAL_TRAINING = {'refine_iter': 300, 'refine_max_fail': 25}


FAMILIES = ('narx', 'hysteresis_narx')
SELECTIONS = ('tests', 'worst_case')
NARX_BESIDE = ('no', 'auto', 'yes')


@dataclass(frozen=True)
class CandidateSpec:
    """
    One model of the grid.

    For ARX, ny = na and nu = nb; `hidden` is None. For the hysteresis-operator NARX, `options`
    holds its constructor arguments besides hidden and seed (sorted (name, value) pairs) and nu, ny
    are its n_lags and na.
    """

    kind: str           # 'narx', 'arx' or 'hysteresis_narx'
    nu: int
    ny: int
    hidden: int | None = None
    seed: int = 0
    options: tuple = ()

    @property
    def label(self) -> str:
        """Short human-readable name, e.g. 'NARX(ny=2, nu=3, H=10)' or 'ARX(na=2, nb=3)'."""
        if self.kind == 'arx':
            return f'ARX(na={self.ny}, nb={self.nu})'
        if self.kind == 'ensemble':
            return f'mean of {len(self.options)}: ' + ' + '.join(self.options)
        if self.kind == 'hysteresis_narx':
            o = dict(self.options)
            lags = f', lags={o["n_lags"]}' if 'n_lags' in o else ''
            chains = ', chain per axis' if o.get('structure') == 'chains' else ''
            return (f'HNARX(H={self.hidden}, plays={o.get("n_plays", 12)}, '
                    f'duhem={o.get("n_duhem", 1)}{lags}, seed={self.seed}{chains})')
        seed = f', seed={self.seed}' if self.seed else ''
        return f'NARX(ny={self.ny}, nu={self.nu}, H={self.hidden}{seed})'

    def build(self, training_options: dict | None = None):
        """Return an unfitted model for this spec (imports the model classes lazily)."""
        if self.kind == 'arx':
            from piezo_narx_ros.ident.arx.model import ARXModel
            return ARXModel(na=self.ny, nb=self.nu)
        if self.kind == 'hysteresis_narx':
            from piezo_narx_ros.ident.hysteresis.model import HysteresisNARX
            options = dict(self.options)
            if options.pop('structure', None) == 'chains':     # several axes, see distinct_specs
                from piezo_narx_ros.ident.hysteresis.chains import HysteresisChains
                return HysteresisChains(hidden=self.hidden, seed=self.seed, **options)
            return HysteresisNARX(hidden=self.hidden, seed=self.seed, **options)
        if self.kind == 'narx':
            from piezo_narx_ros.ident.narx.model import NARXNetwork
            return NARXNetwork(nu=self.nu, ny=self.ny, hidden=self.hidden, seed=self.seed,
                               **(training_options or {}))
        raise ConfigError(f'unknown model kind {self.kind!r} (use narx, arx or '
                          f'hysteresis_narx)')


@dataclass
class ExperimentConfig:
    """Settings of the lag-grid experiment (orders in samples, fraction unit-free)."""

    ny: tuple = (1, 2, 3, 4)            # NARX output lags
    nu: tuple = (1, 2, 3, 4)            # NARX input lags
    hidden: int = 10                    # sigmoid units of the hidden layer
    seed: int = 0                       # first network seed
    n_seeds: int = 1                    # networks per structure, seeds seed .. seed + n_seeds - 1
    family: str = 'narx'                # networks of the grid: 'narx' (paper) | 'hysteresis_narx'
    hnarx: dict = field(default_factory=dict)  # HysteresisNARX options besides hidden and seed
    # HysteresisNARX structures to compare, each a mapping of options over `hnarx` fitted with
    # every seed; () = the one structure `hnarx`.
    hnarx_grid: tuple = ()
    # Family hysteresis_narx: also fit the paper's NARX grid (ny x nu, the first seed) beside it,
    # so that the selection can take the paper's network where it is better on the validation
    # records. 'auto': only where the estimation input closes MINOR_LOOPS minor loops (the
    # paper's networks fail on data without them, docs/real.md); 'yes', 'no'.
    narx_beside: str = 'no'
    # Family hysteresis_narx: also fit every seed of `hnarx` without drive increments (n_lags 0),
    # one more structure. 'auto': only on one-axis estimation inputs that move slowly
    # (coverage.SLOW_STEP): increments over a few samples then see no drive dynamics, and a
    # network fitted at one frequency reads them as a rate it extrapolates at another
    # (docs/real.md, "Drive increments on slow records"); 'yes', 'no'. Not added when the grid
    # has an n_lags 0 structure already.
    without_increments: str = 'no'
    # Family hysteresis_narx: also fit every structure and seed with `small_hidden` sigmoid units,
    # and the validation records choose. 'auto': only on one-axis estimation inputs that close
    # fewer than MINOR_LOOPS minor loops (one frequency, a full-range sine): there the ways the
    # operator states combine inside the loop are not in the data, and a network of `hidden`
    # units fills them in differently per seed; 'yes', 'no'. Not in a preset: measured on the
    # growing scenario it helped the seeds it was tried on and hurt two others (docs/real.md,
    # "Smaller networks").
    small_networks: str = 'no'
    small_hidden: int = 3
    selection: str = 'tests'            # 'tests' (paper) | 'worst_case' (see module docstring)
    arx_na: tuple = tuple(range(1, 11))  # empty = no ARX baseline
    arx_nb: tuple = tuple(range(1, 11))
    narx: bool = True
    split: float = 0.5                  # estimation fraction of each record
    # Seconds at the start of each recording whose measurement sets a model's initial state
    # before its free run is scored (recordings that do not start at rest); 0: from rest.
    init_seconds: float = 0.0
    # How the recordings' unlogged pasts ended, for those states: 'any' or 'fade-out'
    # (ident/state/estimate.py PASTS, step 5).
    init_past: str = 'any'
    max_lag: int = 20                   # correlation test lags
    max_outside_fraction: float = 0.05  # chance-rate tolerance (docs/validation.md); 0 = strict
    residuals: str = 'simulation'       # which residuals' tests select: simulation | prediction
    noise_model: str = 'ar'             # whitening before the tests: 'ar' | 'none'
    noise_order: int = 20               # largest AR order of the noise model (samples)
    jobs: int = 2
    progress: bool | None = None        # None: a bar when the grid has networks and a TTY
    training: dict = field(default_factory=dict)  # passed to NARXNetwork(**training)
    # The selected network is trained again with these options over `training` (empty: no final
    # fit). The grid screens 16 networks with fast settings; only the winner needs convergence.
    final_training: dict = field(default_factory=lambda: dict(FINAL_TRAINING))
    # The mean of the `ensemble` best candidates (ident/ensemble/model.py; 0: none) is one more
    # candidate, scored on the same validation records and kept only when its worst-case
    # free-run R² beats the selected model's by more than `ensemble_margin` (< 0: also when it
    # is that much worse; -1: always). docs/envelope.md "Ensembles": the mean of 5 lowers the
    # battery's median RMSE by ~15 % but rarely wins on validation, and costs K times the
    # inference: not in a preset.
    ensemble: int = 0
    ensemble_margin: float = 0.0

    @property
    def seeds(self) -> tuple:
        """Network seeds of every structure."""
        return tuple(range(int(self.seed), int(self.seed) + int(self.n_seeds)))

    def specs(self) -> list[CandidateSpec]:
        """Every candidate, networks first (the long fits start first on the pool)."""
        out = []
        if self.narx and self.family == 'hysteresis_narx':
            from piezo_narx_ros.ident.hysteresis.model import HysteresisNARX
            for structure in self.hnarx_structures():
                if self.init_past != 'any':   # the fit's own record starts are told it too
                    structure = {**structure, 'past': self.init_past}
                probe = HysteresisNARX(hidden=self.hidden, **structure)
                options = tuple(sorted(structure.items()))
                out += [CandidateSpec('hysteresis_narx', nu=probe.nu, ny=probe.ny,
                                      hidden=h, seed=s, options=options)
                        for h in self.hidden_sizes for s in self.seeds]
            if self.narx_beside != 'no':
                out += [CandidateSpec('narx', nu=nu, ny=ny, hidden=self.hidden, seed=self.seed)
                        for ny in self.ny for nu in self.nu]
        elif self.narx:
            out += [CandidateSpec('narx', nu=nu, ny=ny, hidden=self.hidden, seed=s)
                    for ny in self.ny for nu in self.nu for s in self.seeds]
        out += [CandidateSpec('arx', nu=nb, ny=na) for na in self.arx_na for nb in self.arx_nb]
        return out

    @property
    def hidden_sizes(self) -> tuple:
        """Sigmoid units of the hysteresis-operator networks: `hidden`, then the small ones."""
        small = self.small_networks != 'no' and self.small_hidden != self.hidden
        return (self.hidden, self.small_hidden) if small else (self.hidden,)

    def hnarx_structures(self) -> list[dict]:
        """Return the options of each HysteresisNARX structure (`hnarx_grid` over `hnarx`)."""
        extra = self.increment_free()
        return self._grid() + ([extra] if extra is not None else [])

    def _grid(self) -> list[dict]:
        return [{**self.hnarx, **g} for g in self.hnarx_grid] or [dict(self.hnarx)]

    def increment_free(self) -> dict | None:
        """Return the structure `without_increments` adds (`hnarx`, n_lags 0), or None."""
        if self.without_increments == 'no' or self.family != 'hysteresis_narx':
            return None
        extra = {**self.hnarx, 'n_lags': 0}
        return None if any(s.get('n_lags', -1) == 0 for s in self._grid()) else extra

    def validate(self) -> None:
        """Raise ConfigError naming the first bad setting."""
        # First: the network structures below are built told init_past.
        check_past(self.init_past, 'init_past', ConfigError)
        for name in ('ny', 'nu', 'arx_na', 'arx_nb'):
            vals = getattr(self, name)
            if any(int(v) != v or v < (0 if name in ('nu', 'arx_nb') else 1) for v in vals):
                raise ConfigError(f'{name} orders must be integers >= '
                                  f'{0 if name in ("nu", "arx_nb") else 1}, got {list(vals)}')
        if self.family not in FAMILIES:
            raise ConfigError(f'family must be one of {", ".join(FAMILIES)}, got {self.family!r}')
        for name in ('narx_beside', 'without_increments', 'small_networks'):
            if getattr(self, name) not in NARX_BESIDE:
                raise ConfigError(f'{name} must be one of {", ".join(NARX_BESIDE)}, got '
                                  f'{getattr(self, name)!r}')
        if int(self.small_hidden) != self.small_hidden or not 1 <= self.small_hidden <= 200:
            raise ConfigError(f'small_hidden must be an integer in [1, 200], got '
                              f'{self.small_hidden!r}')
        if self.selection not in SELECTIONS:
            raise ConfigError(f'selection must be one of {", ".join(SELECTIONS)}, got '
                              f'{self.selection!r}')
        if int(self.n_seeds) != self.n_seeds or not 1 <= self.n_seeds <= 1000:
            raise ConfigError(f'n_seeds must be an integer in [1, 1000], got {self.n_seeds}')
        if int(self.seed) != self.seed or self.seed < 0:
            raise ConfigError(f'seed must be an integer >= 0, got {self.seed}')
        if not isinstance(self.hnarx, dict):
            raise ConfigError('hnarx must be a mapping of HysteresisNARX options')
        if not isinstance(self.hnarx_grid, (tuple, list)) or \
                not all(isinstance(g, dict) for g in self.hnarx_grid):
            raise ConfigError('hnarx_grid must be a list of mappings of HysteresisNARX options')
        if self.narx and self.family == 'hysteresis_narx':
            from piezo_narx_ros.ident.hysteresis.model import HysteresisNARX
            for structure in self.hnarx_structures():
                bad = {'hidden', 'seed', 'past'} & set(structure)
                if bad:
                    raise ConfigError(f'hnarx: set {", ".join(sorted(bad))} with the top-level '
                                      f'settings (past: init_past), not inside hnarx or '
                                      f'hnarx_grid')
                HysteresisNARX(hidden=self.hidden, **structure)   # ConfigError on a bad option
        if self.narx and self.family == 'narx' and (not self.ny or not self.nu):
            raise ConfigError('NARX grid is empty: give at least one ny and one nu')
        if self.narx and (int(self.hidden) != self.hidden or self.hidden < 1):
            raise ConfigError(f'hidden must be an integer >= 1, got {self.hidden}')
        if not self.specs():
            raise ConfigError('nothing to fit: the NARX grid is off and the ARX grid is empty')
        if not 0.1 <= self.split <= 0.9:
            raise ConfigError(f'split must be in [0.1, 0.9], got {self.split}')
        if not (isinstance(self.init_seconds, (int, float)) and 0.0 <= self.init_seconds <= 600):
            raise ConfigError(f'init_seconds must be a number of seconds in [0, 600], got '
                              f'{self.init_seconds!r}')
        if self.residuals not in RESIDUAL_KINDS:
            raise ConfigError('residuals must be prediction or simulation, got '
                              f'{self.residuals!r}')
        if self.noise_model not in NOISE_MODELS:
            raise ConfigError(f'noise_model must be one of {", ".join(NOISE_MODELS)}, got '
                              f'{self.noise_model!r}')
        if int(self.noise_order) != self.noise_order or not 0 <= self.noise_order <= 200:
            raise ConfigError(f'noise_order must be an integer in [0, 200], got '
                              f'{self.noise_order}')
        if int(self.ensemble) != self.ensemble or not (self.ensemble == 0
                                                       or 2 <= self.ensemble <= 16):
            raise ConfigError(f'ensemble must be 0 (none) or an integer in [2, 16], got '
                              f'{self.ensemble}')
        if not (isinstance(self.ensemble_margin, (int, float))
                and -1.0 <= self.ensemble_margin < 1.0):
            raise ConfigError(f'ensemble_margin must be an R² difference in [-1, 1), got '
                              f'{self.ensemble_margin!r}')
        if int(self.jobs) != self.jobs or self.jobs < 1:
            raise ConfigError(f'jobs must be an integer >= 1, got {self.jobs}')
        if int(self.max_lag) != self.max_lag or self.max_lag < 1:
            raise ConfigError(f'max_lag must be an integer >= 1, got {self.max_lag}')
        if not 0.0 <= self.max_outside_fraction < 1.0:
            raise ConfigError(f'max_outside_fraction must be in [0, 1), got '
                              f'{self.max_outside_fraction}')
        if self.narx and self.fits_narx:
            # Fail here on a mistyped training option, not once per network inside the workers.
            for name, options in (('training', self.training),
                                  ('final_training', {**self.training, **self.final_training})):
                try:
                    next(s for s in self.specs() if s.kind == 'narx').build(options)
                except PiezoNarxError as exc:
                    raise ConfigError(f'{name}: {exc}') from None

    @property
    def fits_narx(self) -> bool:
        """Return True when the grid may hold the paper's NARX networks."""
        return self.family == 'narx' or self.narx_beside != 'no'

    @property
    def max_n0(self) -> int:
        """Deepest lag of the whole grid, samples."""
        specs = self.specs()
        lags = [s.nu for s in specs] + [s.ny for s in specs]
        lags += list(self.ny) + list(self.nu) if self.narx and self.fits_narx else []
        lags += list(self.arx_na) + list(self.arx_nb)
        return int(max(lags))


#: Named settings of the experiment (changes to ExperimentConfig's defaults). `piezo-narx fit
#: --preset NAME` starts from them; docs/envelope.md has the measurements behind 'envelope'.
PRESETS = {
    # The paper's experiment: NARX lags 1..4 x 1..4 with 10 sigmoid units, ARX 1..10 x 1..10,
    # selected by the correlation tests (then by worst-case free-run R²).
    'paper': {},
    # Accurate across the operating envelope (fast, slow, steps, holds): the hysteresis-operator
    # NARX over several network seeds, a small ARX baseline, selection on the worst case. Two
    # structures: 6 drive increments win where the drive's rate shapes the output (a wideband
    # record at 5 kHz: free-run R² 0.9919 -> 0.9972, docs/real.md).
    # The paper's NARX grid beside it ('auto'), its selected network trained to convergence as
    # the paper preset does: the preset does not lose to the paper's network on validation
    # records (issue 18's 5 kHz bench: R² 0.99890 against the paper network's 0.99997).
    # On slow records a third structure without increments ('auto'): a 10 kHz growing sine
    # selected an ARX (validation R² 0.926, its networks 0.816-0.905); without increments 0.994.
    'envelope': {'family': 'hysteresis_narx', 'hidden': 10, 'n_seeds': 3, 'hnarx': {},
                 'hnarx_grid': ({}, {'n_lags': 6}), 'narx_beside': 'auto',
                 'without_increments': 'auto',
                 'arx_na': (2, 3, 4), 'arx_nb': (2, 3, 4), 'selection': 'worst_case',
                 'init_seconds': 0.5},
}


@dataclass
class CandidateResult:
    """Scores of one fitted candidate; `model` is the fitted object (not serialised)."""

    spec: CandidateSpec
    n_params: int | None = None
    scores: dict = field(default_factory=dict)  # [estimation|validation][prediction|simulation]
    tests: dict = field(default_factory=dict)   # [prediction|simulation] -> CorrelationResult dict
    validated: bool = False
    fit_seconds: float = 0.0
    error: str | None = None
    final_fit: dict | None = None   # set on the selected network: screening vs final training
    model: object = None

    def r2(self, data: str = 'validation', mode: str = 'simulation') -> float:
        """R² for data set and mode; -inf when unavailable (failed fit or diverged simulation)."""
        value = self.scores.get(data, {}).get(mode, {}).get('r2')
        return -np.inf if value is None else value

    def free_run_r2(self) -> float:
        """
        Worst-case free-run R².

        The lowest of the pooled estimation halves and of each validation record. The estimation
        half starts from rest with the excitation switching on, a start the validation half never
        shows; a network that falls into a limit cycle there (measured: R² -119 on its own
        estimation data with 0.99993 on validation) must not win on the validation half alone; nor
        may a model that is good on most records and fails one (a kind of move the user makes).
        """
        val = self.scores.get('validation', {})
        blocks = [self.scores.get('estimation', {}).get('simulation', {}),
                  val.get('simulation', {})]
        blocks += [r['simulation'] for r in val.get('records', [])]
        # Several outputs: every output of every block counts (the worst axis decides).
        blocks += [o for b in list(blocks) for o in b.get('per_output', [])]
        return min(-np.inf if b.get('r2') is None else b['r2'] for b in blocks)

    def to_dict(self) -> dict:
        """JSON-ready form, without the model."""
        return {'label': self.spec.label, **asdict(self.spec), 'n_params': self.n_params,
                'scores': self.scores, 'tests': self.tests, 'validated': self.validated,
                'fit_seconds': self.fit_seconds, 'error': self.error,
                'final_fit': self.final_fit}


@dataclass
class ExperimentResult:
    """Every candidate, the selected one, and what the experiment ran on."""

    config: ExperimentConfig
    candidates: list[CandidateResult]
    selected: int                 # index into candidates
    validated: bool               # the selected model passed the tests
    sources: list[str]
    fs: float
    n_estimation: int             # samples used to fit
    n_validation: int
    wall_seconds: float
    validation_sources: list[str] | None = None   # --validate records; None: split halves

    @property
    def best(self) -> CandidateResult:
        """Return the selected candidate."""
        return self.candidates[self.selected]

    def rule(self) -> str:
        """Return the selection rule in words."""
        worst = ('free-run R² in the worst case (the lowest of the pooled estimation halves '
                 'and each validation record)')
        if self.config.selection == 'worst_case':
            return f'best {worst}; correlation tests reported, not used to select'
        return ('fewest parameters among candidates passing all five tests on '
                f'{self.config.residuals} residuals (noise model: {self.config.noise_model}), '
                f'ties by {worst}; else the best such R² (not validated)')

    def to_dict(self) -> dict:
        """JSON-ready summary: settings, data, every candidate, the selection."""
        cfg = asdict(self.config)
        cfg = {k: list(v) if isinstance(v, tuple) else v for k, v in cfg.items()}
        return {'config': cfg, 'data': {'sources': self.sources, 'fs': self.fs,
                                        'n_estimation': self.n_estimation,
                                        'n_validation': self.n_validation,
                                        'validation_sources': self.validation_sources},
                'selection': {'index': self.selected, 'label': self.best.spec.label,
                              'validated': self.validated,
                              'rule': self.rule()},
                'wall_seconds': self.wall_seconds,
                'candidates': [c.to_dict() for c in self.candidates]}


def with_state_window(records: list[Record], config: ExperimentConfig) -> list[Record]:
    """
    Return copies of records whose free runs start from config.init_seconds measured.

    Their pasts ended as config.init_past says.
    """
    if not config.init_seconds:
        return list(records)
    return [replace(r, state_window=max(1, int(round(config.init_seconds * r.fs))),
                    state_past=config.init_past) for r in records]


def split_records(records: list[Record],
                  fraction: float = 0.5) -> tuple[list[Record], list[Record]]:
    """(estimation halves, validation halves) of every record."""
    halves = [r.split(fraction) for r in records]
    return [h[0] for h in halves], [h[1] for h in halves]


def fit_candidate(spec: CandidateSpec, est: list[Record], val: list[Record],
                  config: ExperimentConfig) -> CandidateResult:
    """
    Fit one candidate on the estimation records and score it on both.

    The same code on every executor; a PiezoNarxError becomes the result's `error`.
    """
    res = CandidateResult(spec=spec)
    t0 = time.perf_counter()
    try:
        model = spec.build(config.training)
        check_same_channels(est + val)
        us, ys = [channels_arg(r.u) for r in est], [channels_arg(r.y) for r in est]
        if len(est) == 1:
            us, ys = us[0], ys[0]
        model.fit(us, ys, fs=est[0].fs)
        if model.n_in == est[0].n_in and model.n_out == est[0].n_out:
            model.inputs, model.outputs = est[0].inputs, est[0].outputs
        res.fit_seconds = time.perf_counter() - t0
        score_candidate(res, model, est, val, config)
    except PiezoNarxError as exc:
        res.error = str(exc)
        res.fit_seconds = time.perf_counter() - t0
    return res


def score_candidate(res: CandidateResult, model, est: list[Record], val: list[Record],
                    config: ExperimentConfig) -> CandidateResult:
    """Fill res with a fitted model's scores on both data sets and its tests; returns res."""
    res.n_params = int(model.n_params)
    res.scores['estimation'] = evaluate_model(model, est, with_tests=False)
    # The validation records' state windows are then judged as evaluate and estimator_node
    # judge the saved model's: with its own free-run error as the window's floor
    # (ident.state.estimate, step 4). Here that is the estimation records' error; the file gets
    # both after selection.
    model.metadata = {**(getattr(model, 'metadata', None) or {}),
                      'metrics': {'estimation': res.scores['estimation']}}
    noise = None
    if config.noise_model == 'ar':
        noise = fit_noise_models(model, est, config.noise_order, config.max_lag)
    val_eval = evaluate_model(model, val, config.max_lag, config.max_outside_fraction,
                              noise_models=noise)
    res.tests = val_eval.pop('tests')
    res.tests['noise_model'] = config.noise_model
    res.tests['residuals'] = config.residuals
    res.scores['validation'] = val_eval
    res.validated = bool(res.tests[config.residuals]['passed'])
    res.model = model
    return res


def fit_task(payload: tuple, data: tuple) -> CandidateResult:
    """Executor task: payload (spec, config), data (estimation, validation records)."""
    spec, config = payload
    if spec.kind == 'narx' and in_worker():
        # One torch thread per worker, as many workers as cores (see executor.py).
        import torch
        torch.set_num_threads(1)
    return fit_candidate(spec, data[0], data[1], config)


def _as_result(spec: CandidateSpec, outcome) -> CandidateResult:
    """Return a task's CandidateResult: a TaskFailure becomes the candidate's error."""
    if isinstance(outcome, TaskFailure):
        return CandidateResult(spec=spec, error=outcome.message)
    return outcome


def select(candidates: list[CandidateResult], rule: str = 'tests') -> tuple[int, bool]:
    """
    (index, validated) by the selection rule of this module ('tests' or 'worst_case').

    DataError when nothing fitted.
    """
    ok = [i for i, c in enumerate(candidates) if c.error is None]
    if not ok:
        raise DataError('no candidate model could be fitted: ' + (candidates[0].error or '?'))
    if rule == 'worst_case':
        best = max(ok, key=lambda i: candidates[i].free_run_r2())
        return best, candidates[best].validated
    passing = [i for i in ok if candidates[i].validated]
    if passing:
        best = min(passing, key=lambda i: (candidates[i].n_params, -candidates[i].free_run_r2()))
        return best, True
    best = max(ok, key=lambda i: candidates[i].free_run_r2())
    return best, False


def ensemble_of(members: list[CandidateResult]) -> tuple:
    """Return (the EnsembleModel of fitted candidates, its spec naming them in order)."""
    from ..ensemble.model import EnsembleModel
    model = EnsembleModel([c.model for c in members])
    return model, CandidateSpec('ensemble', nu=model.nu, ny=model.ny,
                                options=tuple(c.spec.label for c in members))


def consider_ensemble(candidates: list[CandidateResult], chosen: tuple, data: tuple,
                      config: ExperimentConfig) -> tuple:
    """
    Add the mean of the `config.ensemble` best candidates; return the (index, validated) kept.

    The ensemble (ident/ensemble/) is scored on the same estimation and validation records as
    every candidate and replaces the selected model only when its worst-case free-run R² is
    higher by more than `config.ensemble_margin`; it is listed among the candidates either way.
    """
    ranked = sorted((c for c in candidates if c.error is None and c.model is not None),
                    key=lambda c: -c.free_run_r2())[:config.ensemble]
    if config.ensemble < 2 or len(ranked) < 2:
        return chosen
    model, spec = ensemble_of(ranked)
    res = CandidateResult(spec=spec)
    try:
        score_candidate(res, model, data[0], data[1], config)
    except PiezoNarxError as exc:
        res.error = str(exc)
    candidates.append(res)
    best = candidates[chosen[0]]
    margin = config.ensemble_margin
    if res.error is None and (margin <= -1.0
                              or res.free_run_r2() > best.free_run_r2() + margin):
        return len(candidates) - 1, res.validated
    return chosen


def _final_config(config: ExperimentConfig) -> ExperimentConfig:
    return replace(config, training={**config.training, **config.final_training})


def keep_final(screened: CandidateResult, final: CandidateResult,
               config: ExperimentConfig) -> CandidateResult:
    """
    Return the final fit if it is at least as good as the screened one, else the screened fit.

    At least as good: its free-run R² on both halves (the worse of the two) is at least the
    screened one's and its test verdict is no worse. The returned result records both fits under
    'final_fit'.
    """
    keep = (final.error is None and final.free_run_r2() >= screened.free_run_r2()
            and (final.validated or not screened.validated))
    chosen = final if keep else screened
    chosen.final_fit = {'options': dict(config.final_training), 'kept': keep,
                        'screening': {'r2_validation_simulation': screened.r2(),
                                      'r2_estimation_simulation': screened.r2('estimation'),
                                      'validated': screened.validated,
                                      'fit_seconds': screened.fit_seconds},
                        'final': {'r2_validation_simulation': final.r2(),
                                  'r2_estimation_simulation': final.r2('estimation'),
                                  'validated': final.validated,
                                  'fit_seconds': final.fit_seconds, 'error': final.error}}
    return chosen


def final_fit(screened: CandidateResult, est: list[Record], val: list[Record],
              config: ExperimentConfig) -> CandidateResult:
    """
    Train the selected network again with `config.final_training` (longer, to convergence).

    In this process; the better fit is kept (`keep_final`).
    """
    final = fit_candidate(screened.spec, est, val, _final_config(config))
    return keep_final(screened, final, config)


def run_experiment(records: list[Record], config: ExperimentConfig | None = None,
                   executor: Executor | None = None,
                   validation: list[Record] | None = None) -> ExperimentResult:
    """
    Fit and score the whole grid on records and select one model.

    Without `validation`, each record is split per `config.split`; with it, the records estimate
    whole and only the validation records score and select (no validation sample reaches a fit).
    The fits run on `executor` (default: a LocalExecutor of `config.jobs` processes, closed at
    the end); the result does not depend on the executor.
    """
    result = run_experiments([records], config, executor, validation)[0]
    if isinstance(result, PiezoNarxError):
        raise result
    return result


def run_experiments(groups: list[list[Record]], config: ExperimentConfig | None = None,
                    executor: Executor | None = None,
                    validation: list[Record] | None = None) -> list:
    """
    Run one experiment per group of records (e.g. one per recording of a fleet).

    All candidate fits of every group in one pass over the executor, then the final fits in a
    second.

    Returns, per group, its ExperimentResult or the PiezoNarxError that stopped it (too short,
    nothing fitted); the other groups complete. `wall_seconds` is the time of the whole call.
    `validation` (one group only): records that score and select instead of split halves.
    """
    config = config or ExperimentConfig()
    config.validate()
    if validation is not None and len(groups) != 1:
        raise ConfigError('validation records serve one group of estimation records, got '
                          f'{len(groups)} groups')
    owned = executor is None
    executor = executor or LocalExecutor(config.jobs)
    t0 = time.perf_counter()
    outcome, data = {}, {}
    for g, records in enumerate(groups):
        try:
            if not records:
                raise DataError('no records to identify from')
            if validation is None:
                for r in records:
                    check_length(r, config.max_n0, config.max_lag)
                data[g] = split_records(with_state_window(records, config), config.split)
            else:
                for r in validation:
                    check_length(r, config.max_n0, config.max_lag)
                    check_scorable(r)
                data[g] = (with_state_window(records, config),
                           with_state_window(validation, config))
        except PiezoNarxError as exc:
            outcome[g] = exc
    every = [r for g in groups for r in g] + list(validation or [])
    specs = distinct_specs(config.specs(), every)
    show = config.progress
    if show is None:
        show = config.narx and len(specs) * len(data) > 20 and os.isatty(2)
    tasks = [(g, (spec, config)) for g in data for spec in
             auto_grid(specs, config, data[g][0])]
    candidates = {g: [] for g in data}
    chosen = {}
    try:
        for (g, (spec, _)), out in zip(tasks, _map(executor, tasks, data, show)):
            candidates[g].append(_as_result(spec, out))
        for g, cands in candidates.items():
            try:
                chosen[g] = select(cands, config.selection)
            except PiezoNarxError as exc:
                outcome[g] = exc
        finals = [(g, (candidates[g][i].spec, _final_config(config)))
                  for g, (i, _) in chosen.items()
                  if config.final_training and candidates[g][i].spec.kind == 'narx']
        for (g, (spec, _)), out in zip(finals, _map(executor, finals, data, False)):
            i = chosen[g][0]
            candidates[g][i] = keep_final(candidates[g][i], _as_result(spec, out), config)
            chosen[g] = (i, candidates[g][i].validated)
        for g in chosen:
            chosen[g] = consider_ensemble(candidates[g], chosen[g], data[g], config)
    finally:
        if owned:
            executor.close()
    wall = time.perf_counter() - t0
    for g, (index, validated) in chosen.items():
        est, val = data[g]
        records = groups[g]
        outcome[g] = ExperimentResult(
            config=config, candidates=candidates[g], selected=index, validated=validated,
            sources=[r.source for r in records], fs=records[0].fs,
            n_estimation=sum(len(r) for r in est), n_validation=sum(len(r) for r in val),
            wall_seconds=wall,
            validation_sources=None if validation is None else [r.source for r in validation])
    return [outcome[g] for g in range(len(groups))]


def _map(executor: Executor, tasks: list, data: dict, show: bool) -> list:
    """executor.map of fit_task with a tqdm bar when `show`."""
    if not tasks:
        return []
    from tqdm import tqdm
    with tqdm(total=len(tasks), desc='fitting', unit='model', disable=not show) as bar:
        return executor.map(fit_task, tasks, data, lambda i, r: bar.update())
