"""`piezo-narx fit`: run the identification experiment and save the selected model.

    piezo-narx fit INPUT... --out DIR [--preset paper|envelope] [--ny 1-4 --nu 1-4 --hidden 10 ...]

`--preset paper` (the default) is the paper's lag grid; `--preset envelope` fits the
hysteresis-operator NARX over several network seeds and selects on the worst case over records
(piezo_narx_ros.ident.experiment.PRESETS, docs/envelope.md). Several INPUTs are fitted together:
no regressor or state crosses from one record to the next, each is split, and the report gives
each record's scores.

Writes DIR/model.json (+ DIR/model.npz) for the selected model, DIR/candidates.json with every
candidate's metrics and test verdicts, and DIR/report/ (metrics.json and the figures).
Settings come from, in increasing precedence: the preset's built-in values (ExperimentConfig's
defaults with the preset's changes; config/fit.yaml spells out the paper preset), `--config FILE`,
then the command-line options.
"""
import argparse
import contextlib

# Keys a --config YAML file may hold (config/fit.yaml lists them all with their defaults).
CONFIG_KEYS = ('preset', 'family', 'ny', 'nu', 'hidden', 'seed', 'n_seeds', 'hnarx', 'arx_na',
               'arx_nb', 'arx', 'split', 'max_lag', 'max_outside_fraction', 'residuals',
               'noise_model', 'noise_order', 'selection', 'jobs', 'training', 'final_training',
               'command_topic', 'deflection_topic')
# Settings that belong to the command line, not to ExperimentConfig, with their defaults.
CLI_DEFAULTS = {'arx': True, 'command_topic': 'piezo/voltage_command',
                'deflection_topic': 'piezo/deflection'}
PRESET_NAMES = ('paper', 'envelope')


def add_parser(subparsers):
    """Register the `fit` subcommand (argparse only; heavy imports wait for run)."""
    p = subparsers.add_parser(
        'fit', help='identify NARX/ARX models from recorded data and select one',
        description='Fit a grid of NARX networks and ARX models on the first half of each input, '
                    'score them on the second half (R², correlation tests) and save the selected '
                    'model and a report.')
    p.add_argument('inputs', nargs='+', metavar='INPUT',
                   help='.npz (u, y, fs), .csv (t,u,y or u,y), .mcap or rosbag2 directory')
    p.add_argument('--out', required=True, metavar='DIR', help='output directory')
    p.add_argument('--force', action='store_true',
                   help='overwrite the model, candidates and report already in DIR')
    p.add_argument('--config', metavar='YAML', help='settings file (see config/fit.yaml)')
    p.add_argument('--preset', choices=PRESET_NAMES,
                   help='paper (default): the paper\'s NARX lag grid and ARX baseline, selected '
                        'by the correlation tests; envelope: the hysteresis-operator NARX, '
                        'accurate on slow, step and hold moves too, selected on the worst case')
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
    """Built-in settings of a preset: ExperimentConfig's defaults, the preset's changes
    (PRESETS), and the command line's own keys (CLI_DEFAULTS)."""
    from dataclasses import fields

    from piezo_narx_ros.errors import ConfigError
    from piezo_narx_ros.ident.experiment import PRESETS, ExperimentConfig
    if preset not in PRESETS:
        raise ConfigError(f'preset must be one of {", ".join(PRESETS)}, got {preset!r}')
    base = ExperimentConfig()
    out = {f.name: getattr(base, f.name) for f in fields(ExperimentConfig)
           if f.name in CONFIG_KEYS}
    out.update(CLI_DEFAULTS)
    out.update(PRESETS[preset])
    out['preset'] = preset
    return out


def load_settings(args) -> dict:
    """Merged settings dict: preset < --config file < command-line options."""
    from piezo_narx_ros.errors import ConfigError
    doc = {}
    if args.config:
        from piezo_narx_ros.settings import read_yaml_mapping
        doc = read_yaml_mapping(args.config, 'settings', known=CONFIG_KEYS)
    preset = getattr(args, 'preset', None) or doc.get('preset') or 'paper'
    settings = preset_settings(preset)
    settings.update(doc)
    settings['preset'] = preset
    for key in ('ny', 'nu', 'hidden', 'seed', 'n_seeds', 'split', 'arx_na', 'arx_nb', 'max_lag',
                'max_outside_fraction', 'residuals', 'noise_model', 'noise_order', 'jobs',
                'command_topic', 'deflection_topic'):
        value = getattr(args, key, None)
        if value is not None:
            settings[key] = value
    if args.no_arx:
        settings['arx'] = False
    for key in ('training', 'final_training', 'hnarx'):
        if not isinstance(settings[key], dict):
            raise ConfigError(f'{key}: must be a mapping of training options')
    return settings


def experiment_config(settings: dict, progress: bool):
    """ExperimentConfig from merged settings (ConfigError on bad values)."""
    from piezo_narx_ros.errors import ConfigError
    from piezo_narx_ros.ident.experiment import ExperimentConfig
    try:
        cfg = ExperimentConfig(
            ny=parse_range(settings['ny'], 'ny'), nu=parse_range(settings['nu'], 'nu'),
            hidden=int(settings['hidden']), seed=int(settings['seed']),
            n_seeds=int(settings['n_seeds']), family=str(settings['family']),
            hnarx=dict(settings['hnarx']), selection=str(settings['selection']),
            arx_na=parse_range(settings['arx_na'], 'arx_na') if settings['arx'] else (),
            arx_nb=parse_range(settings['arx_nb'], 'arx_nb') if settings['arx'] else (),
            split=float(settings['split']), max_lag=int(settings['max_lag']),
            max_outside_fraction=float(settings['max_outside_fraction']),
            residuals=str(settings['residuals']), noise_model=str(settings['noise_model']),
            noise_order=int(settings['noise_order']), jobs=int(settings['jobs']),
            progress=None if progress else False, training=dict(settings['training']),
            final_training=dict(settings['final_training']))
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
    import warnings

    from piezo_narx_ros.ident.data import check_identifiable, load_records
    from piezo_narx_ros.ident.experiment import run_experiment, split_records
    from piezo_narx_ros.ident.model_io import save_model
    from piezo_narx_ros.ident.report import write_json, write_report

    settings = load_settings(args)
    config = experiment_config(settings, progress=not args.quiet)
    if args.fs is not None and not args.fs > 0:
        raise ConfigError(f'--fs must be a positive number of Hz, got {args.fs}')
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise ConfigError(f'--out {out}: exists and is not a directory')
    if (out / 'model.json').exists() and not args.force:
        raise ConfigError(f'--out {out} already holds a model ({out / "model.json"}); choose '
                          'another directory or pass --force to overwrite it')
    records = load_records(args.inputs, fs=args.fs, command_topic=settings['command_topic'],
                           deflection_topic=settings['deflection_topic'])
    for record in records:
        for line in check_identifiable(record, config.split):
            warnings.warn(line)
    result = run_experiment(records, config)
    out.mkdir(parents=True, exist_ok=True)
    best = result.best
    data_info = {'sources': result.sources, 'fs': result.fs, 'split': config.split,
                 'preset': settings['preset'],
                 'n_estimation': result.n_estimation, 'n_validation': result.n_validation}
    model_path = save_model(best.model, out / 'model.json', data=data_info,
                            metrics={**best.scores, 'selected_by': config.residuals,
                                     'noise_model': config.noise_model},
                            tests={**best.tests, 'validated': result.validated})
    write_json(result.to_dict(), out / 'candidates.json')
    paths = {}
    if not args.no_report:
        _, validation = split_records(records, config.split)
        paths = write_report(result, validation, out / 'report')
    if not args.quiet:
        val = best.scores['validation']
        r2_sim = val['simulation']['r2']
        print(f'selected {best.spec.label} ({best.n_params} parameters) of '
              f'{len(result.candidates)} candidates in {result.wall_seconds:.1f} s')
        print(f'validation R²: prediction {val["prediction"]["r2"]:.6f}, simulation '
              f'{"diverged" if r2_sim is None else f"{r2_sim:.6f}"}')
        for rec in val.get('records', []):
            sim = rec['simulation']
            text = ('diverged' if sim['r2'] is None else
                    f'R² {sim["r2"]:.6f}, RMSE {1e9 * sim["rmse"]:.1f} nm')
            print(f'  {rec["source"]}: simulation {text}')
        chosen = best.tests[config.residuals]
        noise = chosen.get('noise_model')
        how = f'AR({noise["order"]}) noise model' if noise else 'raw'
        print(f'correlation tests ({config.residuals} residuals, {how}): ' + ', '.join(
            f'{k} {"pass" if v["passed"] else "fail"}'
            for k, v in chosen.get('tests', {}).items()))
        failed = [c for c in result.candidates if c.error is not None]
        if failed:
            print(f'warning: {len(failed)} candidate(s) could not be fitted, e.g. '
                  f'{failed[0].spec.label}: {failed[0].error}')
        n_pass = sum(c.validated for c in result.candidates)
        print(f'{n_pass} of {len(result.candidates)} candidates pass all five tests')
        if not result.validated:
            print('warning: no candidate passed all correlation tests; selected by free-run R² '
                  '(the worse of estimation and validation; not validated)')
        print(f'model: {model_path}')
        print(f'candidates: {out / "candidates.json"}')
        if paths:
            print(f'report: {out / "report"}')
    return 0
