"""
`piezo-narx fit`: run the identification experiment and save the selected model.

    piezo-narx fit INPUT... --out DIR [--validate VAL...] [--preset search|paper|envelope] ...

`--preset search` (the default) searches family, structure, seed and start policy on the
validation records (ident/selection/search.py, docs/search.md); `--preset paper` is the paper's
lag grid; `--preset envelope` fits the
hysteresis-operator NARX over several network seeds and selects on the worst case over records
(ident.selection.experiment.PRESETS, docs/envelope.md). Several INPUTs are fitted together:
no regressor or state crosses from one record to the next, each is split, and the report gives
each record's scores.

Writes DIR/model.json (+ DIR/model.npz) for the selected model, DIR/candidates.json with every
candidate's metrics and test verdicts, and DIR/report/ (metrics.json and the figures). A folder
INPUT stands for the recordings in it. `--per-record` fits each recording on its own instead
(a fleet of rigs or bags): DIR/NAME/ per recording, with the files above, and DIR/summary.csv.

`--executor ray [--ray-address ADDR]` runs the candidate fits as Ray tasks (a local Ray of
--jobs CPUs without an address); the selected model, its weights and the report are the same
as with the default `--executor local` (piezo_narx_ros.ident.selection.executor).
Settings come from, in increasing precedence: the preset's built-in values (ExperimentConfig's
defaults with the preset's changes; config/fit.yaml spells out the paper preset), `--config FILE`,
then the command-line options.
"""
import contextlib

# Keys a --config YAML file may hold (config/fit.yaml lists them all with their defaults).
CONFIG_KEYS = ('preset', 'family', 'ny', 'nu', 'hidden', 'seed', 'n_seeds', 'hnarx', 'hnarx_grid',
               'narx_beside', 'without_increments', 'small_networks', 'small_hidden',
               'arx_na', 'arx_nb', 'arx', 'split', 'max_lag', 'max_outside_fraction', 'residuals',
               'noise_model', 'noise_order', 'selection', 'jobs', 'training', 'final_training',
               'init_seconds', 'init_past', 'ensemble', 'ensemble_margin', 'command_topic',
               'deflection_topic')
# Settings that belong to the command line, not to ExperimentConfig, with their defaults.
CLI_DEFAULTS = {'arx': True, 'command_topic': 'piezo/voltage_command',
                'deflection_topic': 'piezo/deflection'}
PRESET_NAMES = ('search', 'paper', 'envelope')


def add_parser(subparsers):
    """Register the `fit` subcommand (argparse only; heavy imports wait for run)."""
    p = subparsers.add_parser(
        'fit', help='identify NARX/ARX models from recorded data and select one',
        description='Identify a model from recorded data: by default a structure search over '
                    'ARX, NARX and hysteresis-operator NARX models scored on the validation '
                    "records (or each input's second half); --preset paper fits the paper's grid. "
                    'Saves the selected model and a report.')
    p.add_argument('inputs', nargs='+', metavar='INPUT',
                   help='.npz (u, y, fs), text table (.csv, .tsv, .txt, .dat: t,u,y or u,y, or '
                        '--columns), MATLAB .mat (variables u, y, fs or t, or --columns; v4 to '
                        'v7.3), .mcap or rosbag2 directory, or a folder of these')
    p.add_argument('--out', required=True, metavar='DIR', help='output directory')
    p.add_argument('--validate', nargs='+', metavar='VAL',
                   help='validation recordings: the INPUTs then estimate whole and these only '
                        'score and select (worst case over them); without it each INPUT is '
                        'split (--split)')
    p.add_argument('--init-samples', type=int, metavar='N',
                   help="measured samples at the start of each recording that set a model's "
                        'state (hysteresis memory, creep, sensor offset) before its free run is '
                        'scored: for recordings that do not start at rest (default: the '
                        "preset's init_seconds; 0: from rest)")
    from piezo_narx_ros.ident.state.estimate import PASTS
    p.add_argument('--past', dest='init_past', choices=PASTS,
                   help="how the recordings' unlogged pasts ended, for their state windows "
                        "(--init-samples, the envelope preset's 0.5 s) and the fit's estimated "
                        'record starts; fade-out: a move ended by fading its amplitude out, as '
                        'evaluate --past (default: any)')
    p.add_argument('--resample', type=float, metavar='HZ',
                   help='fit a model at this slower rate: every record is low-pass filtered and '
                        'resampled to it first (anti-aliased)')
    p.add_argument('--per-record', action='store_true',
                   help='fit each recording on its own: DIR/NAME/ per recording and '
                        'DIR/summary.csv')
    p.add_argument('--executor', choices=('local', 'ray'), default='local',
                   help='where the candidate fits run: local (default) = --jobs processes; '
                        'ray = Ray tasks on a local Ray of --jobs CPUs or on --ray-address')
    p.add_argument('--ray-address', metavar='ADDR',
                   help='running Ray cluster: HOST:PORT of its head node (ray start --head '
                        'prints it), or auto on a node of the cluster; needs --executor ray')
    p.add_argument('--force', action='store_true',
                   help='overwrite the model, candidates and report already in DIR')
    p.add_argument('--config', metavar='YAML', help='settings file (see config/fit.yaml)')
    p.add_argument('--preset', choices=PRESET_NAMES,
                   help='search (default): a structure search over the families, their '
                        'structures, seeds and start policies, selected on the validation '
                        "records (docs/search.md); paper: the paper's NARX lag grid and ARX "
                        'baseline, selected by the correlation tests; envelope: the '
                        'hysteresis-operator NARX over a fixed grid, selected on the worst case')
    from piezo_narx_ros.ident.selection.search import SEARCH_FAMILIES, SearchOptions
    search = p.add_argument_group('structure search (--preset search)')
    search.add_argument('--trials', type=int, metavar='N',
                        help="trials of the study, its first batch the presets' structures "
                             f'(default {SearchOptions.trials})')
    search.add_argument('--budget-s', type=float, metavar='S',
                        help='wall-time budget: no batch of trials starts that would end after '
                             f'it (default {SearchOptions.budget_s:g} s; 0: none)')
    search.add_argument('--batch', type=int, metavar='B',
                        help='trials asked at once; with --seed and --trials it fixes the '
                             'selected model for any number of workers '
                             f'(default {SearchOptions.batch})')
    search.add_argument('--tolerance', type=float, metavar='FRACTION',
                        help='the fewest parameters win within this relative error of the best '
                             f'(default {SearchOptions.tolerance:g})')
    search.add_argument('--families', metavar='LIST',
                        help=f'families searched, comma-separated (default '
                             f'{",".join(SEARCH_FAMILIES)})')
    search.add_argument('--resume', action='store_true',
                        help='continue the interrupted search stored in --out (same inputs and '
                             'options)')
    p.add_argument('--ny', metavar='RANGE', help='NARX output lags, e.g. 1-4 or 2 or 1,3 '
                                                 '(default 1-4)')
    p.add_argument('--nu', metavar='RANGE', help='NARX input lags (default 1-4)')
    p.add_argument('--hidden', type=int, metavar='H', help='sigmoid units (default 10)')
    p.add_argument('--arx-na', metavar='RANGE', help='ARX output orders (default 1-10)')
    p.add_argument('--arx-nb', metavar='RANGE', help='ARX input orders (default 1-10)')
    p.add_argument('--no-arx', action='store_true', help='skip the ARX baseline')
    p.add_argument('--fs', type=float, metavar='HZ', help='sample rate for inputs without one')
    p.add_argument('--seed', type=int, help='first network seed (default 0)')
    p.add_argument('--n-seeds', type=int, metavar='N',
                   help='networks per structure, seeds seed..seed+N-1 (paper 1, envelope 4)')
    p.add_argument('--split', type=float, metavar='FRACTION',
                   help='fraction of each input that estimates; the rest validates (default 0.5)')
    p.add_argument('--jobs', type=int, help='worker processes (default 2)')
    p.add_argument('--max-lag', type=int, metavar='L', help='correlation test lags (default 20)')
    p.add_argument('--max-outside', type=float, metavar='FRACTION', dest='max_outside_fraction',
                   help='fraction of tested lags allowed outside the 95%% band, none beyond '
                        'the 99.9%% band (default 0.05, the chance rate; 0: strict)')
    p.add_argument('--residuals', choices=('prediction', 'simulation'),
                   help='residuals whose correlation tests select the model '
                        '(default simulation)')
    p.add_argument('--noise-model', choices=('ar', 'none'),
                   help='whiten the residuals with an AR noise model fitted on the estimation '
                        'half before the tests (default ar; none: raw residuals)')
    p.add_argument('--noise-order', type=int, metavar='P',
                   help='largest AR order of the noise model, chosen by BIC (default 20)')
    p.add_argument('--command-topic', help='bag topic of the voltage commands '
                                           '(default piezo/voltage_command)')
    p.add_argument('--deflection-topic', help='bag topic of the deflection '
                                              '(default piezo/deflection)')
    p.add_argument('--no-report', action='store_true', help='skip the figures')
    p.add_argument('--quiet', action='store_true', help='no progress bar or summary')
    from piezo_narx_ros.cli.reading import add_reading_options
    add_reading_options(p)
    return p


def parse_range(text, name: str) -> tuple:
    """'1-4' -> (1, 2, 3, 4); '3' -> (3,); '1,3' -> (1, 3); a list of ints passes through."""
    from piezo_narx_ros.errors import ConfigError
    if isinstance(text, (list, tuple)):
        items = list(text)
    elif isinstance(text, int) and not isinstance(text, bool):
        items = [text]
    else:
        items = []
        try:
            for part in str(text).split(','):
                part = part.strip()
                if '-' in part[1:]:
                    lo, hi = part.split('-', 1)
                    lo, hi = int(lo), int(hi)
                    if hi < lo:
                        raise ValueError
                    items += list(range(lo, hi + 1))
                else:
                    items.append(int(part))
        except ValueError:
            raise ConfigError(f'--{name.replace("_", "-")}: not a lag range: {text!r} '
                              f'(use e.g. 1-4, 2 or 1,3)') from None
    if not all(isinstance(i, int) and not isinstance(i, bool) for i in items):
        raise ConfigError(f'{name}: lag orders must be integers, got {text!r}')
    return tuple(sorted(set(items)))


def preset_settings(preset: str) -> dict:
    """
    Built-in settings of a preset.

    ExperimentConfig's defaults, the preset's changes (PRESETS), and the command line's own keys
    (CLI_DEFAULTS).
    """
    from dataclasses import fields

    from piezo_narx_ros.errors import ConfigError
    from piezo_narx_ros.ident.selection.experiment import PRESETS, ExperimentConfig
    if preset not in PRESET_NAMES:
        raise ConfigError(f'preset must be one of {", ".join(PRESET_NAMES)}, got {preset!r}')
    base = ExperimentConfig()
    out = {f.name: getattr(base, f.name) for f in fields(ExperimentConfig)
           if f.name in CONFIG_KEYS}
    out.update(CLI_DEFAULTS)
    # The search has no grid; the experiment's settings it reads (split, tests, past) are the
    # paper's, and its window the estimator's 0.5 s.
    out.update(PRESETS.get(preset, {'init_seconds': 0.5}))
    out['preset'] = preset
    return out


def load_settings(args) -> dict:
    """Merge the settings: preset < --config file < command-line options."""
    from piezo_narx_ros.errors import ConfigError
    doc = {}
    if args.config:
        from piezo_narx_ros.settings import read_yaml_mapping
        doc = read_yaml_mapping(args.config, 'settings', known=CONFIG_KEYS)
    preset = getattr(args, 'preset', None) or doc.get('preset') or 'search'
    settings = preset_settings(preset)
    settings.update(doc)
    settings['preset'] = preset
    for key in ('ny', 'nu', 'hidden', 'seed', 'n_seeds', 'split', 'arx_na', 'arx_nb', 'max_lag',
                'max_outside_fraction', 'residuals', 'noise_model', 'noise_order', 'jobs',
                'command_topic', 'deflection_topic', 'init_past'):
        value = getattr(args, key, None)
        if value is not None:
            settings[key] = value
    if args.no_arx:
        settings['arx'] = False
    for key in ('training', 'final_training', 'hnarx'):
        if not isinstance(settings[key], dict):
            raise ConfigError(f'{key}: must be a mapping of training options')
    grid = settings['hnarx_grid']
    if not isinstance(grid, (list, tuple)) or not all(isinstance(g, dict) for g in grid):
        raise ConfigError('hnarx_grid: must be a list of mappings of HysteresisNARX options')
    return settings


def experiment_config(settings: dict, progress: bool):
    """Build the ExperimentConfig from merged settings (ConfigError on bad values)."""
    from piezo_narx_ros.errors import ConfigError
    from piezo_narx_ros.ident.selection.experiment import ExperimentConfig
    try:
        cfg = ExperimentConfig(
            ny=parse_range(settings['ny'], 'ny'), nu=parse_range(settings['nu'], 'nu'),
            hidden=int(settings['hidden']), seed=int(settings['seed']),
            n_seeds=int(settings['n_seeds']), family=str(settings['family']),
            hnarx=dict(settings['hnarx']), hnarx_grid=tuple(settings['hnarx_grid']),
            narx_beside=str(settings['narx_beside']),
            without_increments=str(settings['without_increments']),
            small_networks=str(settings['small_networks']),
            small_hidden=int(settings['small_hidden']),
            selection=str(settings['selection']),
            arx_na=parse_range(settings['arx_na'], 'arx_na') if settings['arx'] else (),
            arx_nb=parse_range(settings['arx_nb'], 'arx_nb') if settings['arx'] else (),
            split=float(settings['split']), max_lag=int(settings['max_lag']),
            max_outside_fraction=float(settings['max_outside_fraction']),
            residuals=str(settings['residuals']), noise_model=str(settings['noise_model']),
            noise_order=int(settings['noise_order']), jobs=int(settings['jobs']),
            progress=None if progress else False, training=dict(settings['training']),
            final_training=dict(settings['final_training']),
            init_seconds=float(settings['init_seconds']),
            init_past=str(settings['init_past']),
            ensemble=int(settings['ensemble']),
            ensemble_margin=float(settings['ensemble_margin']))
    except (TypeError, ValueError) as exc:
        raise ConfigError(f'invalid setting: {exc}') from None
    cfg.validate()
    return cfg


@contextlib.contextmanager
def one_line_warnings():
    """Show warnings (e.g. bag gaps from the reader) as one stderr line each while inside."""
    import sys
    import warnings
    with warnings.catch_warnings():
        warnings.showwarning = lambda message, *args, **kwargs: print(
            f'piezo-narx: warning: {message}', file=sys.stderr)
        yield


def run(args) -> int:
    """Load the inputs, run the experiment, write model, candidates and report; exit code 0."""
    with one_line_warnings():
        return _run(args)


def _run(args) -> int:
    from pathlib import Path

    from piezo_narx_ros.errors import ConfigError
    from piezo_narx_ros.ident.data.loaders import expand_inputs
    from piezo_narx_ros.ident.selection.executor import make_executor

    settings = load_settings(args)
    config = experiment_config(settings, progress=not args.quiet)
    if args.fs is not None and not args.fs > 0:
        raise ConfigError(f'--fs must be a positive number of Hz, got {args.fs}')
    executor = make_executor(args.executor, config.jobs, args.ray_address)
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise ConfigError(f'--out {out}: exists and is not a directory')
    inputs = expand_inputs(args.inputs)
    if settings['preset'] == 'search':
        return _run_search(args, settings, config, inputs, executor, out)
    if args.resume:
        raise ConfigError('--resume continues a structure search (--preset search)')
    if args.per_record:
        if args.validate:
            raise ConfigError('--validate serves one model; it cannot be combined with '
                              '--per-record')
        return _run_fleet(args, settings, config, inputs, executor, out)
    if (out / 'model.json').exists() and not args.force:
        raise ConfigError(f'--out {out} already holds a model ({out / "model.json"}); choose '
                          'another directory or pass --force to overwrite it')
    records = _resampled(_load(args, settings, config, inputs, whole=bool(args.validate)), args)
    validation = (_load_validation(args, settings, records) if args.validate
                  else None)
    config = _with_init_samples(config, args.init_samples, records[0].fs)
    from piezo_narx_ros.ident.selection.experiment import run_experiment
    with executor:
        result = run_experiment(records, config, executor, validation)
    _warn_about_estimation(records, config)
    model_path, paths = _write_fit(out, result, records, config, settings, not args.no_report,
                                   validation)
    if not args.quiet:
        _print_fit(result, config, executor, model_path, out, paths)
    return 0


def _load(args, settings, config, inputs, whole=False):
    """
    Load the records of `inputs`, warning on identifiability (errors on the first bad one).

    whole: the records estimate whole (--validate), so the split is not checked.
    """
    import warnings

    from piezo_narx_ros.cli.reading import reading_options
    from piezo_narx_ros.ident.data.loaders import load_records
    from piezo_narx_ros.ident.data.records import check_identifiable
    records = load_records(inputs, fs=args.fs, command_topic=settings['command_topic'],
                           deflection_topic=settings['deflection_topic'],
                           **reading_options(args))
    if not whole:
        for record in records:
            for line in check_identifiable(record, config.split):
                warnings.warn(line)
    return records


def _load_validation(args, settings, records):
    """
    Load the --validate records: the estimation rate, none of them an estimation record.

    With --resample they are resampled as the estimation records were, before the rates are
    compared (records given at the rig's rate validate a model fitted at the slower one).

    Warns in words where the estimation data cover less than the validation data (coverage),
    and where a validation record's output sits at its sensor's full scale (saturation).
    """
    import warnings

    from piezo_narx_ros.cli.reading import reading_options
    from piezo_narx_ros.errors import ConfigError, DataError
    from piezo_narx_ros.ident.data.coverage import coverage_warnings
    from piezo_narx_ros.ident.data.loaders import expand_inputs, load_records
    from piezo_narx_ros.ident.data.saturation import saturation_warnings
    val_paths = expand_inputs(args.validate)
    est_paths = {p.resolve() for p in expand_inputs(args.inputs)}
    shared = [str(p) for p in val_paths if p.resolve() in est_paths]
    if shared:
        raise ConfigError(f'--validate {shared[0]} is also an estimation input: a record cannot '
                          'validate the model it estimates')
    validation = load_records(val_paths, fs=args.fs, command_topic=settings['command_topic'],
                              deflection_topic=settings['deflection_topic'],
                              **reading_options(args))
    validation = _resampled(validation, args)
    fs = records[0].fs
    for r in validation:
        if abs(r.fs - fs) > 1e-6 * fs:
            raise DataError(f'{r.source}: sampled at {r.fs:g} Hz but the estimation records at '
                            f'{fs:g} Hz')
    for line in coverage_warnings(records, validation) + saturation_warnings(validation):
        warnings.warn(line)
    return validation


def _warn_about_estimation(records, config, name: str = '') -> None:
    """
    Warn where the estimation input itself limits the model (after the fit, beside its report).

    The paper's networks fitted on an input that never reverses in its range; an input that
    reaches both ends of its range late (coverage.LATE_SWEEP); an output at its sensor's full
    scale (saturation). `name` prefixes each line (fleet).
    """
    import warnings

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


def _resampled(records, args):
    """Return the records at --resample HZ (anti-aliased), or as they are."""
    if args.resample is None:
        return records
    from piezo_narx_ros.ident.data.resample import resample_record
    return [resample_record(r, args.resample) for r in records]


def _with_init_samples(config, init_samples, fs):
    """--init-samples N (at the records' rate fs, Hz) overrides the preset's init_seconds."""
    from dataclasses import replace

    from piezo_narx_ros.errors import ConfigError
    if init_samples is None:
        return config
    if init_samples < 0:
        raise ConfigError(f'--init-samples must be >= 0, got {init_samples}')
    return replace(config, init_seconds=init_samples / fs)


def _write_fit(out, result, records, config, settings, report: bool, validation=None):
    """
    DIR/model.json (+ .npz), DIR/candidates.json and, if `report`, DIR/report/.

    validation: the --validate records (else the split halves of `records` are reported).
    Returns (model path, report paths).
    """
    from piezo_narx_ros.control.gain_check import data_line
    from piezo_narx_ros.ident.selection.experiment import split_records
    from piezo_narx_ros.ident.model_io import save_model
    from piezo_narx_ros.ident.validation.report import write_json, write_report
    out.mkdir(parents=True, exist_ok=True)
    best = result.best
    data_info = {'sources': result.sources, 'fs': result.fs,
                 'split': None if validation else config.split,
                 'validation_sources': result.validation_sources,
                 'init_seconds': config.init_seconds, 'preset': settings['preset'],
                 'n_estimation': result.n_estimation, 'n_validation': result.n_validation,
                 # The data's own least-squares line: what the model's static gain is checked
                 # against before controller_node's linear mode uses it (control.gain_check).
                 'line': data_line([r.u for r in records], [r.y for r in records])}
    model_path = save_model(best.model, out / 'model.json', data=data_info,
                            metrics={**best.scores, 'selected_by': config.residuals,
                                     'noise_model': config.noise_model},
                            tests={**best.tests, 'validated': result.validated})
    write_json(result.to_dict(), out / 'candidates.json')
    paths = {}
    if report:
        from piezo_narx_ros.ident.selection.experiment import with_state_window
        scored = (with_state_window(validation, config) if validation else
                  split_records(with_state_window(records, config), config.split)[1])
        paths = write_report(result, scored, out / 'report')
    return model_path, paths


def _failed_line(failed) -> str:
    names = ', '.join(c.spec.label for c in failed[:5]) + (', ...' if len(failed) > 5 else '')
    return (f'warning: {len(failed)} candidate(s) could not be fitted ({names}); '
            f'{failed[0].spec.label}: {failed[0].error}')


def _print_fit(result, config, executor, model_path, out, paths) -> None:
    from piezo_narx_ros.ident.validation.noise_model import describe as describe_noise
    best = result.best
    val = best.scores['validation']
    r2_sim = val['simulation']['r2']
    print(f'selected {best.spec.label} ({best.n_params} parameters) of '
          f'{len(result.candidates)} candidates in {result.wall_seconds:.1f} s '
          f'({executor.describe()})')
    held = (getattr(best.model, 'training_info_', None) or {}).get('creep_fixed_s')
    if held:    # hysteresis_narx, creep='excited' (docs/real.md)
        print('creep held at 0 for the ' + ', '.join(f'{t:g} s' for t in held)
              + ' filter(s): the estimation input hardly moves them (hnarx: {creep: free} '
                'fits them)')
    print(f'validation R²: prediction {val["prediction"]["r2"]:.6f}, simulation '
          f'{"diverged" if r2_sim is None else f"{r2_sim:.6f}"}')
    per = val['simulation'].get('per_output') or []
    if per:   # several outputs: each one's free run
        print('  per output: ' + ', '.join(
            f'{o["name"]} R² {o["r2"]:.6f} RMSE {1e9 * o["rmse"]:.1f} nm' for o in per))
    for rec in val.get('records', []):
        sim = rec['simulation']
        text = ('diverged' if sim['r2'] is None else
                f'R² {sim["r2"]:.6f}, RMSE {1e9 * sim["rmse"]:.1f} nm')
        print(f'  {rec["source"]}: simulation {text}')
    chosen = best.tests[config.residuals]
    how = describe_noise(chosen.get('noise_model'))
    print(f'correlation tests ({config.residuals} residuals, {how}): ' + ', '.join(
        f'{k} {"pass" if v["passed"] else "fail"}'
        for k, v in chosen.get('tests', {}).items()))
    failed = [c for c in result.candidates if c.error is not None]
    if failed:
        print(_failed_line(failed))
    n_pass = sum(c.validated for c in result.candidates)
    print(f'{n_pass} of {len(result.candidates)} candidates pass all five tests')
    if not result.validated:
        print('warning: no candidate passed all correlation tests; selected by free-run R² '
              '(the worse of estimation and validation; not validated)')
    print(f'model: {model_path}')
    print(f'candidates: {out / "candidates.json"}')
    if paths:
        print(f'report: {out / "report"}')


def search_options(args, settings, config, fs: float):
    """Return the SearchOptions of a `fit --preset search` (ConfigError on bad values)."""
    from piezo_narx_ros.errors import ConfigError
    from piezo_narx_ros.ident.selection.search import SearchOptions
    budget = SearchOptions.budget_s if args.budget_s is None else (args.budget_s or None)
    families = (tuple(f.strip() for f in args.families.split(',')) if args.families
                else None)
    given = {'trials': args.trials, 'batch': args.batch, 'tolerance': args.tolerance}
    options = SearchOptions(
        budget_s=budget, seed=int(settings['seed']), families=families,
        init_seconds=float(settings['init_seconds']), init_samples=args.init_samples,
        past=str(settings['init_past']), split=config.split, max_lag=config.max_lag,
        max_outside_fraction=config.max_outside_fraction, noise_model=config.noise_model,
        noise_order=config.noise_order, progress=None if not args.quiet else False,
        **{k: v for k, v in given.items() if v is not None})
    try:
        options.validate()
    except ConfigError as exc:
        raise ConfigError(f'--{str(exc).replace("_", "-")}') from None
    return options


def _run_search(args, settings, config, inputs, executor, out) -> int:
    """--preset search: load, warn, search, write the selected model and the report."""
    from piezo_narx_ros.control.gain_check import data_line
    from piezo_narx_ros.errors import ConfigError
    from piezo_narx_ros.ident.selection.experiment import split_records
    from piezo_narx_ros.ident.selection.search import SEARCH_FAMILIES, run_search
    from piezo_narx_ros.ident.selection.search_report import family_lines, write_search
    if args.per_record:
        raise ConfigError('--per-record is not available with --preset search; fit each '
                          'recording with its own --out, or use --preset envelope')
    records = _resampled(_load(args, settings, config, inputs, whole=bool(args.validate)), args)
    validation = _load_validation(args, settings, records) if args.validate else None
    options = search_options(args, settings, config, records[0].fs)
    est, val = (records, validation) if validation else split_records(records, config.split)
    if not args.quiet:
        print(f'searching {options.trials} trials over '
              f'{", ".join(options.families or SEARCH_FAMILIES)} on '
              f'{executor.describe()}; study: {out / "study.journal"}')
    import signal
    import sys

    def stop(signum, frame):      # SIGTERM as Ctrl-C: the workers are stopped, the study kept
        raise KeyboardInterrupt
    previous = signal.signal(signal.SIGTERM, stop)
    try:
        with executor:
            result = run_search(est, val, options, executor, out, resume=args.resume,
                                force=args.force)
    except KeyboardInterrupt:
        print(f'piezo-narx: the search is stored in {out}: continue it with the same command '
              'and --resume', file=sys.stderr)
        raise
    finally:
        signal.signal(signal.SIGTERM, previous)
    _warn_about_estimation(records, config)
    info = {'split': None if validation else config.split,
            'line': data_line([r.u for r in records], [r.y for r in records])}
    model_path, paths = write_search(out, result, est, val, not args.no_report, info)
    if not args.quiet:
        best = result.best
        for note in result.notes:
            print(f'note: {note}')
        if result.taken_over:
            print(f'resumed: {result.taken_over} trial(s) taken over from {out}')
        if result.stopped == 'budget':
            print(f'stopped by the budget ({options.budget_s:g} s) after {len(result.trials)} '
                  'trials')
        print(f'selected {best.spec.label} ({best.n_params} parameters, start '
              f'{best.scores["start"]["policy"]!r} from {result.window} samples) of '
              f'{len(result.trials)} trials in {result.wall_seconds:.1f} s')
        print('why: ' + result.why)
        print('\n'.join(['best per family (worst case over the validation records):']
                        + family_lines(result)))
        print(f'model: {model_path}')
        if paths:
            print(f'report: {out / "report"} (pareto.png); study: optuna-dashboard '
                  f'{out / "study.journal"}')
    return 0


# Columns of DIR/summary.csv (--per-record): one row per recording. SI units.
SUMMARY_COLUMNS = ('recording', 'status', 'selected', 'n_params', 'validated',
                   'r2_validation_simulation', 'r2_worst_case', 'rmse_validation_simulation_m',
                   'samples', 'fs_hz', 'failed_candidates', 'source', 'error')


def recording_names(paths) -> list[str]:
    """
    Output folder name per input path: unique, and one plain name inside --out.

    The stem, with anything but letters, digits, '.', '-' and '_' made '_' and leading dots
    dropped (a stem '..' would have named the parent of --out); repeats get -2, -3, ..., never
    a name another input's own stem takes (a/run, run-2, b/run: run, run-2, run-3). Compared
    without case, for file systems that ignore it.
    """
    import re
    from pathlib import Path
    stems = [re.sub(r'[^\w.-]', '_', Path(path).stem).lstrip('.') or 'recording'
             for path in paths]
    reserved = {s.casefold() for s in stems}
    names, used = [], set()
    for stem in stems:
        name, k = stem, 1
        while name.casefold() in used or (k > 1 and name.casefold() in reserved):
            k += 1
            name = f'{stem}-{k}'
        used.add(name.casefold())
        names.append(name)
    return names


def _run_fleet(args, settings, config, inputs, executor, out) -> int:
    """
    --per-record: one experiment per recording, all on one executor.

    DIR/NAME/ each and DIR/summary.csv. Recordings that cannot be loaded or fitted are rows with
    their error; the others complete. Exit 0 when every recording was fitted, else a one-line error
    (exit 2).
    """
    from piezo_narx_ros.errors import ConfigError, DataError, PiezoNarxError
    from piezo_narx_ros.ident.selection.experiment import run_experiments
    names = recording_names(inputs)
    taken = [out / 'summary.csv'] + [out / n / 'model.json' for n in names]
    if any(p.exists() for p in taken) and not args.force:
        first = next(p for p in taken if p.exists())
        raise ConfigError(f'--out {out} already holds a fleet fit ({first}); choose another '
                          'directory or pass --force to overwrite it')
    loaded, rows = {}, {}
    for path, name in zip(inputs, names):
        try:
            loaded[name] = _load(args, settings, config, [path])
        except PiezoNarxError as exc:
            rows[name] = {'recording': name, 'status': 'failed', 'source': str(path),
                          'error': str(exc)}
    if not args.quiet:
        print(f'fitting {len(loaded)} recording(s), each on its own, on {executor.describe()}')
    with executor:
        results = run_experiments(list(loaded.values()), config, executor)
    for (name, records), result in zip(loaded.items(), results):
        rows[name] = _fleet_row(name, records[0], result)
        if not isinstance(result, PiezoNarxError):
            _warn_about_estimation(records, config, name)
            _write_fit(out / name, result, records, config, settings, not args.no_report)
    table = [rows[n] for n in names]
    out.mkdir(parents=True, exist_ok=True)
    _write_summary(table, out / 'summary.csv')
    if not args.quiet:
        _print_summary(table, out / 'summary.csv')
    failed = [r for r in table if r['status'] != 'ok']
    if failed:
        raise DataError(f'{len(failed)} of {len(table)} recordings could not be fitted (see '
                        f'{out / "summary.csv"}); {failed[0]["recording"]}: {failed[0]["error"]}')
    return 0


def _fleet_row(name, record, result) -> dict:
    from piezo_narx_ros.errors import PiezoNarxError
    row = {'recording': name, 'source': record.source, 'samples': len(record),
           'fs_hz': record.fs}
    if isinstance(result, PiezoNarxError):
        return {**row, 'status': 'failed', 'error': str(result)}
    best = result.best
    sim = best.scores['validation']['simulation']
    return {**row, 'status': 'ok', 'selected': best.spec.label, 'n_params': best.n_params,
            'validated': result.validated, 'r2_validation_simulation': sim['r2'],
            'r2_worst_case': best.free_run_r2(), 'rmse_validation_simulation_m': sim['rmse'],
            'failed_candidates': sum(c.error is not None for c in result.candidates)}


def _write_summary(table, path) -> None:
    import csv
    with open(path, 'w', newline='') as f:
        writer = csv.DictWriter(f, SUMMARY_COLUMNS, restval='')
        writer.writeheader()
        for row in table:
            writer.writerow({k: ('' if v is None else v) for k, v in row.items()})


def _print_summary(table, path) -> None:
    def num(value, fmt):
        return '-' if value is None or value == '' else format(value, fmt)
    width = max(len('recording'), *(len(r['recording']) for r in table))
    print(f'{"recording":<{width}}  {"selected":<28} {"R² val sim":>10} {"R² worst":>10} '
          f'{"RMSE nm":>8}  validated')
    for r in table:
        if r['status'] != 'ok':
            print(f'{r["recording"]:<{width}}  failed: {r["error"]}')
            continue
        rmse = r['rmse_validation_simulation_m']
        print(f'{r["recording"]:<{width}}  {r["selected"]:<28} '
              f'{num(r["r2_validation_simulation"], ".6f"):>10} '
              f'{num(r["r2_worst_case"], ".6f"):>10} '
              f'{num(None if rmse is None else 1e9 * rmse, ".1f"):>8}  '
              f'{"yes" if r["validated"] else "no"}')
    print(f'summary: {path}')
