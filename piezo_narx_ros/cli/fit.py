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
from piezo_narx_ros.ident.pipeline.settings import CONFIG_KEYS, OVERRIDE_KEYS, PRESET_NAMES

__all__ = ('CONFIG_KEYS', 'PRESET_NAMES', 'add_parser', 'run')


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
                        help='the fewest parameters win within this relative error of the best, '
                             'and a start that reads the measured window wins over rest within '
                             f'it (default {SearchOptions.tolerance:g})')
    search.add_argument('--committee', type=int, metavar='K',
                        help='the model is the mean of the pick and the K - 1 next best trials '
                             'of its family where it scores within --tolerance of the pick '
                             '(one-axis networks; K steps a sample live; 1: the pick alone; '
                             f'default {SearchOptions.committee})')
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


def job_from_args(args):
    """Return the FitJob of parsed `fit` options (ConfigError on a bad setting)."""
    from piezo_narx_ros.cli.reading import reading_options
    from piezo_narx_ros.ident.pipeline.fit import FitJob
    from piezo_narx_ros.ident.pipeline.settings import merge_settings
    settings = merge_settings(getattr(args, 'preset', None), args.config,
                              {k: getattr(args, k, None) for k in OVERRIDE_KEYS}, args.no_arx)
    return FitJob(inputs=args.inputs, out=args.out, settings=settings, validate=args.validate,
                  fs=args.fs, resample=args.resample, init_samples=args.init_samples,
                  reading=reading_options(args), report=not args.no_report, force=args.force,
                  progress=not args.quiet)


def run(args) -> int:
    """Fit as the options say (ident.pipeline), print the outcome; exit code 0."""
    from piezo_narx_ros.cli.fit_output import one_line_warnings
    with one_line_warnings():
        return _run(args)


def _run(args) -> int:
    from piezo_narx_ros.cli import fit_output
    from piezo_narx_ros.errors import ConfigError
    from piezo_narx_ros.ident.pipeline import fit as pipeline
    from piezo_narx_ros.ident.pipeline.fleet import fit_fleet
    from piezo_narx_ros.ident.selection.executor import make_executor
    job = job_from_args(args)
    executor = make_executor(args.executor, job.config.jobs, args.ray_address)
    if job.preset == 'search':
        if args.per_record:
            raise ConfigError('--per-record is not available with --preset search; fit each '
                              'recording with its own --out, or use --preset envelope')
        return _run_search(args, job, executor)
    if args.resume:
        raise ConfigError('--resume continues a structure search (--preset search)')
    if args.per_record:
        def announce(n):
            if not args.quiet:
                print(f'fitting {n} recording(s), each on its own, on {executor.describe()}')
        outcome = fit_fleet(job, executor, announce)
        if not args.quiet:
            fit_output.print_summary(outcome.table, outcome.summary_path)
        outcome.check()
        return 0
    outcome = pipeline.fit_experiment(job, executor)
    if not args.quiet:
        fit_output.print_fit(outcome, executor)
    return 0


def _run_search(args, job, executor) -> int:
    """--preset search; SIGTERM stops it as Ctrl-C does, the study kept for --resume."""
    import signal
    import sys

    from piezo_narx_ros.cli.fit_output import print_search
    from piezo_narx_ros.ident.pipeline.fit import fit_search
    from piezo_narx_ros.ident.selection.search import SEARCH_FAMILIES

    def announce(options):
        if not args.quiet:
            print(f'searching {options.trials} trials over '
                  f'{", ".join(options.families or SEARCH_FAMILIES)} on '
                  f'{executor.describe()}; study: {job.out / "study.journal"}')

    def stop(signum, frame):      # the workers are stopped, the study kept
        raise KeyboardInterrupt
    previous = signal.signal(signal.SIGTERM, stop)
    try:
        outcome = fit_search(job, executor, resume=args.resume, announce=announce,
                             trials=args.trials, budget_s=args.budget_s, batch=args.batch,
                             tolerance=args.tolerance, committee=args.committee,
                             families=args.families)
    except KeyboardInterrupt:
        print(f'piezo-narx: the search is stored in {job.out}: continue it with the same '
              'command and --resume', file=sys.stderr)
        raise
    finally:
        signal.signal(signal.SIGTERM, previous)
    if not args.quiet:
        print_search(outcome)
    return 0
