"""
One fit, whole: load the records, check and warn, fit, select, save the model and its report.

    job = FitJob(inputs=[...], out=Path('fit'), settings=merge_settings('envelope'))
    outcome = run_fit(job, executor)          # a FitOutcome, or a SearchOutcome for 'search'

The warnings (identifiability, coverage, saturation, a late sweep) go through `warnings.warn`, so
a caller chooses how to show them; errors are PiezoNarxError subclasses with one useful line.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path

from piezo_narx_ros.errors import ConfigError, DataError
from piezo_narx_ros.ident.pipeline.settings import experiment_config


@dataclass
class FitJob:
    """
    What one fit is asked to do.

    inputs: the estimation recordings (paths; folders stand for the recordings in them);
    out: the output folder; settings: merged settings (pipeline.settings.merge_settings);
    validate: validation recordings, which then score and select while the inputs estimate
    whole (None: each input is split); fs: sample rate, Hz, for inputs without one; resample:
    fit at this slower rate, Hz; init_samples: measured samples that set a model's state before
    its scored free run (None: the preset's init_seconds); reading: the loaders' reading options
    (units, columns, axis); report: write the figures; force: overwrite what `out` holds;
    progress: progress bars.
    """

    inputs: list
    out: Path
    settings: dict
    validate: list | None = None
    fs: float | None = None
    resample: float | None = None
    init_samples: int | None = None
    reading: dict = field(default_factory=dict)
    report: bool = True
    force: bool = False
    progress: bool = True

    def __post_init__(self):
        from piezo_narx_ros.ident.data.loaders import expand_inputs
        self.out = Path(self.out)
        if self.fs is not None and not self.fs > 0:
            raise ConfigError(f'--fs must be a positive number of Hz, got {self.fs}')
        if self.out.exists() and not self.out.is_dir():
            raise ConfigError(f'--out {self.out}: exists and is not a directory')
        self.inputs = expand_inputs(self.inputs)
        self.config = experiment_config(self.settings, progress=self.progress)

    @property
    def preset(self) -> str:
        return self.settings['preset']


@dataclass
class FitOutcome:
    """A grid fit's result (experiment.ExperimentResult), its model file and report paths."""

    result: object
    config: object
    model_path: Path
    paths: dict


@dataclass
class SearchOutcome:
    """A search's result (search.SearchResult), its options, model file and report paths."""

    result: object
    options: object
    model_path: Path
    paths: dict


def load_estimation(job: FitJob, paths=None, whole: bool = False) -> list:
    """
    Load the estimation records of `paths` (default the job's inputs), warning on each one.

    whole: the records estimate whole (validation records are given), so the split is not
    checked. Errors on the first record that cannot be read.
    """
    from piezo_narx_ros.ident.data.loaders import load_records
    from piezo_narx_ros.ident.data.records import check_identifiable
    records = load_records(job.inputs if paths is None else paths, fs=job.fs,
                           command_topic=job.settings['command_topic'],
                           deflection_topic=job.settings['deflection_topic'], **job.reading)
    if not whole:
        for record in records:
            for line in check_identifiable(record, job.config.split):
                warnings.warn(line)
    return records


def load_validation(job: FitJob, records: list) -> list:
    """
    Load the validation records: at the estimation rate, none of them an estimation record.

    With `resample` they are resampled as the estimation records were, before the rates are
    compared (records given at the rig's rate validate a model fitted at the slower one).
    Warns in words where the estimation data cover less than the validation data (coverage),
    and where a validation record's output sits at its sensor's full scale (saturation).
    """
    from piezo_narx_ros.ident.data.coverage import coverage_warnings
    from piezo_narx_ros.ident.data.loaders import expand_inputs, load_records
    from piezo_narx_ros.ident.data.saturation import saturation_warnings
    val_paths = expand_inputs(job.validate)
    est_paths = {p.resolve() for p in job.inputs}
    shared = [str(p) for p in val_paths if p.resolve() in est_paths]
    if shared:
        raise ConfigError(f'--validate {shared[0]} is also an estimation input: a record cannot '
                          'validate the model it estimates')
    validation = load_records(val_paths, fs=job.fs, command_topic=job.settings['command_topic'],
                              deflection_topic=job.settings['deflection_topic'], **job.reading)
    validation = resampled(validation, job.resample)
    fs = records[0].fs
    for r in validation:
        if abs(r.fs - fs) > 1e-6 * fs:
            raise DataError(f'{r.source}: sampled at {r.fs:g} Hz but the estimation records at '
                            f'{fs:g} Hz')
    for line in coverage_warnings(records, validation) + saturation_warnings(validation):
        warnings.warn(line)
    return validation


def load_job(job: FitJob) -> tuple:
    """Return (estimation records at the job's rate, validation records or None), warned on."""
    records = resampled(load_estimation(job, whole=bool(job.validate)), job.resample)
    return records, (load_validation(job, records) if job.validate else None)


def warn_about_estimation(records, config, name: str = '') -> None:
    """
    Warn where the estimation input itself limits the model (after the fit, beside its report).

    The paper's networks fitted on an input that never reverses in its range; an input that
    reaches both ends of its range late (coverage.LATE_SWEEP); an output at its sensor's full
    scale (saturation). `name` prefixes each line (fleet).
    """
    from piezo_narx_ros.ident.data.coverage import inner_reversals, late_sweep_warnings
    from piezo_narx_ros.ident.hysteresis.model import MINOR_LOOPS
    from piezo_narx_ros.ident.data.saturation import saturation_warnings
    lines = []
    if config.narx and config.family == 'narx' and inner_reversals(records) < MINOR_LOOPS:
        lines.append('the estimation input never reverses inside its range (no minor loops, '
                     "e.g. one full-range sine): nothing in these data decides how the paper's "
                     'networks behave inside the loop, and their validation scores cannot tell '
                     '(on the micromanipulator of docs/real.md the selected one scored R² -0.22 '
                     'on its test record); --preset envelope keeps its network monotone there')
    lines += late_sweep_warnings(records) + saturation_warnings(records)
    for line in lines:
        warnings.warn(f'{name}: {line}' if name else line)


def resampled(records, hz):
    """Return the records at `hz` (anti-aliased), or as they are for None."""
    if hz is None:
        return records
    from piezo_narx_ros.ident.data.resample import resample_record
    return [resample_record(r, hz) for r in records]


def with_init_samples(config, init_samples, fs):
    """init_samples N (at the records' rate fs, Hz) overrides the preset's init_seconds."""
    if init_samples is None:
        return config
    if init_samples < 0:
        raise ConfigError(f'--init-samples must be >= 0, got {init_samples}')
    return replace(config, init_seconds=init_samples / fs)


def data_info_line(records) -> dict | None:
    """Return the data's least-squares line, stored with the model (control.gain_check)."""
    from piezo_narx_ros.control.gain_check import data_line
    return data_line([r.u for r in records], [r.y for r in records])


def write_fit(out, result, records, config, preset: str, report: bool, validation=None):
    """
    DIR/model.json (+ .npz), DIR/candidates.json and, if `report`, DIR/report/.

    validation: the validation records (else the split halves of `records` are reported).
    Returns (model path, report paths).
    """
    from piezo_narx_ros.ident.model_io import save_model
    from piezo_narx_ros.ident.selection.experiment import split_records, with_state_window
    from piezo_narx_ros.ident.validation.report import write_json, write_report
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    best = result.best
    data_info = {'sources': result.sources, 'fs': result.fs,
                 'split': None if validation else config.split,
                 'validation_sources': result.validation_sources,
                 'init_seconds': config.init_seconds, 'preset': preset,
                 'n_estimation': result.n_estimation, 'n_validation': result.n_validation,
                 # Checked against the model's static gain before controller_node's linear
                 # mode uses it.
                 'line': data_info_line(records)}
    model_path = save_model(best.model, out / 'model.json', data=data_info,
                            metrics={**best.scores, 'selected_by': config.residuals,
                                     'noise_model': config.noise_model},
                            tests={**best.tests, 'validated': result.validated})
    write_json(result.to_dict(), out / 'candidates.json')
    paths = {}
    if report:
        scored = (with_state_window(validation, config) if validation else
                  split_records(with_state_window(records, config), config.split)[1])
        paths = write_report(result, scored, out / 'report')
    return model_path, paths


def fit_experiment(job: FitJob, executor) -> FitOutcome:
    """Fit a preset's grid ('paper', 'envelope'): load, warn, fit, select, save, report."""
    from piezo_narx_ros.ident.selection.experiment import run_experiment
    out = job.out
    if (out / 'model.json').exists() and not job.force:
        raise ConfigError(f'--out {out} already holds a model ({out / "model.json"}); choose '
                          'another directory or pass --force to overwrite it')
    records, validation = load_job(job)
    config = with_init_samples(job.config, job.init_samples, records[0].fs)
    with executor:
        result = run_experiment(records, config, executor, validation)
    warn_about_estimation(records, config)
    model_path, paths = write_fit(out, result, records, config, job.preset, job.report,
                                  validation)
    return FitOutcome(result, config, model_path, paths)


def search_options(job: FitJob, trials=None, budget_s=None, batch=None, tolerance=None,
                   committee=None, families=None):
    """
    Return the SearchOptions of a search job (ConfigError naming the option on a bad value).

    None leaves SearchOptions' default; budget_s 0 means no budget; families: comma-separated.
    """
    from piezo_narx_ros.ident.selection.search import SearchOptions
    settings, config = job.settings, job.config
    budget = SearchOptions.budget_s if budget_s is None else (budget_s or None)
    families = (tuple(f.strip() for f in families.split(',')) if families else None)
    given = {'trials': trials, 'batch': batch, 'tolerance': tolerance, 'committee': committee}
    options = SearchOptions(
        budget_s=budget, seed=int(settings['seed']), families=families,
        init_seconds=float(settings['init_seconds']), init_samples=job.init_samples,
        past=str(settings['init_past']), split=config.split, max_lag=config.max_lag,
        max_outside_fraction=config.max_outside_fraction, noise_model=config.noise_model,
        noise_order=config.noise_order, progress=None if job.progress else False,
        **{k: v for k, v in given.items() if v is not None})
    try:
        options.validate()
    except ConfigError as exc:
        raise ConfigError(f'--{str(exc).replace("_", "-")}') from None
    return options


def fit_search(job: FitJob, executor, resume: bool = False, announce=None,
               **search) -> SearchOutcome:
    """
    Run the structure search: load, warn, search, save the selected model, report.

    search: search_options' keywords (trials, budget_s, batch, tolerance, committee,
    families).
    announce(options): called once the options are known, before the first trial.
    KeyboardInterrupt passes through with the study stored in job.out (continue: resume=True).
    """
    from piezo_narx_ros.ident.selection.experiment import split_records
    from piezo_narx_ros.ident.selection.search import run_search
    from piezo_narx_ros.ident.selection.search_report import write_search
    records, validation = load_job(job)
    options = search_options(job, **search)
    est, val = (records, validation) if validation else split_records(records, job.config.split)
    if announce is not None:
        announce(options)
    with executor:
        result = run_search(est, val, options, executor, job.out, resume=resume,
                            force=job.force)
    warn_about_estimation(records, job.config)
    info = {'split': None if validation else job.config.split,
            'line': data_info_line(records)}
    model_path, paths = write_search(job.out, result, est, val, job.report, info)
    return SearchOutcome(result, options, model_path, paths)
