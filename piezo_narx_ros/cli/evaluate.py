"""
`piezo-narx evaluate MODEL INPUT...`: score a saved model on recorded data.

Runs the model in one-step prediction and in free-run simulation (initialised from the first n0
measured outputs of each input) over every sample of the inputs, and applies the five correlation
tests to the residuals of `--residuals` (default simulation) after the noise model: by default
the AR noise model that `piezo-narx fit` stored in the model file (fitted on its estimation data,
so a fixed filter here); a model file without one gets an AR noise model fitted on the evaluated
residuals themselves, and the JSON says so. Prints a short summary, or with --json one JSON object:

    {"model": ..., "inputs": [...], "n": ..., "prediction": {"r2", "rmse", "nrmse", "fit_percent"},
     "simulation": {...}, "tests": {name: true|false}, "tests_passed": bool | null (no test),
     "tests_residuals": "simulation",
     "tests_noise_model": {"kind", "order", "coef", "source"} | null,
     "tests_raw": {name: true|false}, "tests_detail": {...},
     "past": "any" | "fade-out" (--past),
     "state_windows": [{"source", "window_samples", "memory_spread_m", "determined",
                        "window_input_v"}] (one axis, with --init-samples N > 0),
     "simulation_from_rest": {"r2", "rmse", ...} | null (with --init-samples N > 0: the same
                             scored samples, the model started at rest),
     "warnings": [...]}

Never imports torch.
"""


def add_parser(subparsers):
    """Register the `evaluate` subcommand (argparse only)."""
    p = subparsers.add_parser(
        'evaluate', help='score a saved model on recorded data (R², RMSE, correlation tests)',
        description='Score a model file on inputs in prediction and free-run simulation.')
    p.add_argument('model', metavar='MODEL', help='model .json written by piezo-narx fit')
    p.add_argument('inputs', nargs='+', metavar='INPUT',
                   help='.npz, text table (.csv, .tsv, .txt, .dat), MATLAB .mat (v4-v7.3), '
                        '.mcap or rosbag2 directory')
    p.add_argument('--json', action='store_true', help='print one JSON object')
    p.add_argument('--init-samples', type=int, metavar='N',
                   help='the first N measured samples are available to start the free run; '
                        "the model file's start policy (fit --preset search) decides how they "
                        "are used, else they set the model's state (hysteresis memory, creep, "
                        'output dynamics, sensor offset); scores on the samples after them; 0: '
                        "free run from rest (default: the model file's window, else the first "
                        "n0 measured outputs, the paper's convention)")
    from piezo_narx_ros.ident.state.estimate import PASTS
    p.add_argument('--past', choices=PASTS, default=PASTS[0],
                   help='with --init-samples: how the unlogged past before the record ended. '
                        'any (default): histories of up to two turning points, the zero the '
                        'model was fitted with breaking ties on a hold; fade-out: a move ended '
                        'by fading its amplitude out (the memory demagnetised about the first '
                        'command), kept unless the window rejects it')
    p.add_argument('--resample', type=float, metavar='HZ',
                   help='resample the inputs to this slower rate first (anti-aliased), for a '
                        'model fitted with fit --resample')
    p.add_argument('--save-output', metavar='FILE.npz',
                   help='write the free-run output as y_sim beside u and y (and the first '
                        'scored sample as scored_from); an existing file only with --force')
    p.add_argument('--force', action='store_true', help='overwrite --save-output if it exists')
    p.add_argument('--fs', type=float, metavar='HZ', help='sample rate for inputs without one')
    p.add_argument('--max-lag', type=int, default=20, metavar='L',
                   help='correlation test lags (default 20)')
    p.add_argument('--max-outside', type=float, default=0.05, metavar='FRACTION',
                   dest='max_outside_fraction',
                   help='fraction of tested lags allowed outside the 95%% band, none beyond the '
                        '99.9%% band (default 0.05, the chance rate; 0: strict)')
    p.add_argument('--residuals', choices=('prediction', 'simulation'), default='simulation',
                   help='residuals whose verdicts fill "tests" (default simulation)')
    p.add_argument('--noise-model', choices=('stored', 'ar', 'none'), default='stored',
                   help='whitening before the tests: the AR noise model stored in the model file '
                        '(default; fitted here when the file has none), ar: fit one on these '
                        'residuals, none: raw residuals')
    p.add_argument('--noise-order', type=int, default=20, metavar='P',
                   help='largest AR order when a noise model is fitted here (default 20)')
    p.add_argument('--command-topic', default='piezo/voltage_command')
    p.add_argument('--deflection-topic', default='piezo/deflection')
    from piezo_narx_ros.cli.reading import add_reading_options
    add_reading_options(p)
    return p


def stored_noise_models(model) -> dict:
    """
    {residual kind: ARNoiseModel} read from the model file's test record (may be empty).

    Only numbers are read (coefficients as a float list); anything malformed is a ModelFileError.
    """
    from piezo_narx_ros.errors import DataError, ModelFileError
    from piezo_narx_ros.ident.validation.noise_model import noise_models_from_doc

    tests = (getattr(model, 'metadata', None) or {}).get('tests') or {}
    if not isinstance(tests, dict):
        raise ModelFileError(f'{getattr(model, "source", "model")}: tests must be a mapping')
    out = {}
    for mode in ('prediction', 'simulation'):
        doc = tests.get(mode, {}).get('noise_model') if isinstance(tests.get(mode), dict) else None
        if doc is None:
            continue
        try:
            out[mode] = noise_models_from_doc(doc)
        except DataError:
            raise ModelFileError(f'{getattr(model, "source", "model")}: tests.{mode}.noise_model '
                                 f'is malformed') from None
    return out


def range_warnings(model, records, margin: float = 0.1) -> list[str]:
    """
    Warn, one line per record, when the input leaves the model's trained input range.

    When it leaves the range (V) by more than `margin` times its span: the scores then measure
    extrapolation, not the model. Several inputs: each channel against its own range.
    """
    from piezo_narx_ros.ident.base import channel_ranges
    if getattr(model, 'input_range', None) is None:
        return []
    ranges, _ = channel_ranges(model)
    out = []
    for r in records:
        u = r.u.reshape(len(r), -1)
        for i, (lo, hi) in enumerate(ranges):
            if i >= u.shape[1]:
                break
            pad = margin * (hi - lo)
            u_lo, u_hi = float(u[:, i].min()), float(u[:, i].max())
            if u_lo < lo - pad or u_hi > hi + pad:
                what = 'input' if len(ranges) == 1 else f'input {model.inputs[i]}'
                out.append(f'{r.source}: {what} spans [{u_lo:.4g}, {u_hi:.4g}] V, outside the '
                           f'[{lo:.4g}, {hi:.4g}] V the model was trained on: its scores measure '
                           'extrapolation')
                break
    return out


def memory_windows(model, records, init_samples) -> tuple[list[dict], list[str]]:
    """
    Whether each record's state window determines the model's memory; (per record, warnings).

    The two extreme pasts the model admits (from above and from below: estimator.memory) are run
    through the window's inputs: where they still differ after it, the window has not set the
    hysteresis memory (a hold gives the level, not the memory), the state estimate has guessed
    the rest, and the score after the window carries that guess. One axis only: nothing for
    several, for a free run from rest, without --init-samples or for a family without brackets.
    """
    import numpy as np

    from piezo_narx_ros.estimator.memory import memory_bracket
    if not init_samples or model.n_in != 1 or model.n_out != 1:
        return [], []
    out, notes = [], []
    for r in records:
        u = np.asarray(r.u, dtype=np.float64).reshape(len(r))[:int(init_samples)]
        bracket = memory_bracket(model, float(u[0]))
        if bracket is None:                             # a family without brackets
            return [], []
        for x in u:
            bracket.step(float(x))
        entry = {'source': r.source, 'window_samples': int(u.size),
                 'memory_spread_m': 0.0 if bracket.determined else float(bracket.spread),
                 'determined': bool(bracket.determined),
                 'window_input_v': [float(u.min()), float(u.max())]}
        out.append(entry)
        if not bracket.determined:
            notes.append(f"{r.source}: the first {u.size} samples do not set the model's memory "
                         f'(the input moved over [{u.min():.4g}, {u.max():.4g}] V there): pasts '
                         f'from above and from below still differ by '
                         f'{bracket.spread * 1e6:.3g} um after them, so the score after them '
                         "carries the state estimate's guess"
                         + (' (if the last move before the record faded out, say so with '
                            '--past fade-out)' if r.state_past == 'any' else '')
                         + '; on a hold it cannot tell memory from a sensor zero that moved: '
                         'open records with a fade-out (simulate and command_node preamble) '
                         'and set the state over it (docs/real.md)')
    return out, notes


def stored_start(model, init_samples=None) -> tuple[str | None, int | None]:
    """
    Return (start policy, measured samples) for a model: the model file's `start`, if any.

    init_samples (given by the user) says how many measured samples are available; the stored
    policy decides how they are used. A model file without a start: (None, init_samples).
    """
    from piezo_narx_ros.ident.state.start import model_start
    start = model_start(model)
    if not start:
        return None, init_samples
    n = start['window_samples'] if init_samples is None else int(init_samples)
    return start['policy'], n


def evaluate(model, records, max_lag=20, max_outside_fraction=0.05, residuals='simulation',
             noise_model='stored', noise_order=20, init_samples=None, policy=None):
    """
    JSON-ready dict of scores and verdicts of a fitted model on records.

    init_samples: None scores every sample after the first n0 (free run from the first n0
    measured outputs); 0 a free run from rest, every sample; N the samples after the first N,
    whose measurement set the model's state (ModelState), or as `policy` says (ident.state.start:
    'rest', 'offset', 'state'; the model file's start policy).
    """
    import math
    import warnings
    from dataclasses import replace

    import numpy as np

    from piezo_narx_ros.errors import ConfigError, DataError
    from piezo_narx_ros.ident.selection.scoring import (evaluate_model, fit_noise_models,
                                                        from_rest_scores, scored_from)
    from piezo_narx_ros.ident.data.records import check_scorable
    from piezo_narx_ros.ident.data.saturation import saturation_warnings

    if init_samples == 0:
        policy = None   # nothing measured: a free run from rest, whatever start the model stores
    if init_samples is not None:
        from piezo_narx_ros.ident.state.estimate import MIN_WINDOW
        need = max(MIN_WINDOW, int(model.n0))
        if init_samples < 0:
            raise ConfigError(f'--init-samples must be >= 0, got {init_samples}')
        if policy is None and 0 < init_samples < need:
            raise ConfigError(f'--init-samples {init_samples} is too few to set the state: this '
                              f'model needs at least {need} measured samples (n0 = {model.n0}; '
                              f'a state is estimated from {MIN_WINDOW} or more); 0 runs from '
                              'rest')
        records = [replace(r, state_window=int(init_samples), state_policy=policy)
                   for r in records]
    if policy is not None:
        from piezo_narx_ros.ident.state.start import check_window
        for r in records:
            check_window(model, policy, int(init_samples), len(r), r.source)
    for r in records:
        if (r.n_in, r.n_out) != (model.n_in, model.n_out):
            raise DataError(f'{r.source}: {r.n_in} input(s) and {r.n_out} output(s), but the '
                            f'model has {model.n_in} and {model.n_out}')
        if model.n_in > 1 or model.n_out > 1:
            for what in ('inputs', 'outputs'):
                if getattr(r, what) != tuple(getattr(model, what)):
                    raise DataError(f'{r.source}: {what} {", ".join(getattr(r, what))} differ '
                                    f'from the model\'s {", ".join(getattr(model, what))}')

    if max_lag < 1:
        raise ConfigError(f'--max-lag must be >= 1, got {max_lag}')
    if not 0.0 <= max_outside_fraction < 1.0:
        raise ConfigError(f'--max-outside must be in [0, 1), got {max_outside_fraction}')
    for r in records:
        if model.fs is not None and abs(r.fs - model.fs) > 1e-6 * model.fs:
            raise DataError(f'{r.source}: sampled at {r.fs:g} Hz but the model was fitted at '
                            f'{model.fs:g} Hz')
        check_scorable(r, scored_from(model, r))     # R² against a flat output: undefined
        # Whole records are scored here (no split), so half the usual length suffices.
        if len(r) < scored_from(model, r) + 4 * max_lag:
            raise DataError(f'{r.source}: {len(r)} samples are too few for the model '
                            f'(n0 = {model.n0}'
                            + (f', {init_samples} samples to set its state'
                               if init_samples else '')
                            + f') and {max_lag} test lags')
    if noise_model not in ('stored', 'ar', 'none'):
        raise ConfigError(f'--noise-model must be stored, ar or none, got {noise_model!r}')
    if not 0 <= noise_order <= 200:
        raise ConfigError(f'--noise-order must be in [0, 200], got {noise_order}')
    noise, source = None, None
    if noise_model == 'stored':
        noise = stored_noise_models(model)
        source = 'model file (fitted on its estimation data)'
    if noise_model == 'ar' or (noise_model == 'stored' and residuals not in noise):
        # In-sample: slightly favourable to the model, hence said in the output.
        noise = fit_noise_models(model, records, noise_order, max_lag)
        source = 'fitted on the evaluated residuals'
    notes = range_warnings(model, records) + saturation_warnings(records)
    windows, memory = memory_windows(model, records, init_samples)
    notes += memory
    for line in notes:
        warnings.warn(line)
    with np.errstate(all='ignore'):   # overflow far outside the range: reported below instead
        scores = evaluate_model(model, records, max_lag, max_outside_fraction,
                                noise_models=noise)
    r2 = scores['prediction']['r2']
    if r2 is None or not math.isfinite(r2):
        raise DataError("the model's one-step predictions are not finite on "
                        f'{", ".join(r.source for r in records)}: no score can be computed'
                        + (' (input far outside the trained range)' if notes else ''))
    tests = scores.pop('tests')
    chosen = tests[residuals]
    nm = chosen.get('noise_model')
    return {
        'model': getattr(model, 'source', None),
        'structure': repr(model),
        'inputs': [r.source for r in records],
        'n': int(sum(len(r) - scored_from(model, r) for r in records)),
        'init_samples': init_samples,
        'start_policy': policy,
        'prediction': _with_per_output(scores['prediction'], model),
        'simulation': _with_per_output(scores['simulation'], model),
        'tests': {k: v['passed'] for k, v in chosen.get('tests', {}).items()},
        # null, not false, when no test could run (the free run diverged): nothing failed.
        'tests_passed': bool(chosen['passed']) if chosen.get('tests') else None,
        'tests_residuals': residuals,
        'tests_noise_model': (None if nm is None else
                              {'per_output': nm, 'source': source} if isinstance(nm, list)
                              else {**nm, 'source': source}),
        'tests_raw': {k: v['passed'] for k, v in tests['raw'][residuals].get('tests', {}).items()},
        'tests_detail': tests,
        'state_windows': windows,
        # With a state window: the same samples from rest, to choose the estimator's `init`.
        'simulation_from_rest': (_with_per_output(from_rest_scores(model, records), model)
                                 if init_samples else None),
        'warnings': notes,
    }


def _with_per_output(block: dict, model) -> dict:
    """Return the scores with per_output ({name, r2, rmse, ...} per output) always present."""
    if block.get('per_output') is not None or block.get('r2') is None:
        return block
    return {**block, 'per_output': [{'name': model.outputs[0], 'r2': block['r2'],
                                     'rmse': block['rmse'], 'nrmse': block['nrmse'],
                                     'fit_percent': block['fit_percent']}]}


def check_save_output(path, records, force: bool = False) -> None:
    """Raise ConfigError (one line) for a --save-output that cannot or must not be written."""
    from pathlib import Path

    from piezo_narx_ros.errors import ConfigError
    from piezo_narx_ros.files import refuse_overwrite
    path = Path(path)
    if path.suffix != '.npz':
        raise ConfigError(f'--save-output must name an .npz file, got {path}')
    if len(records) != 1:
        raise ConfigError(f"--save-output writes one record's free run; {len(records)} inputs "
                          'were given')
    if not path.parent.is_dir():
        raise ConfigError(f'--save-output directory {path.parent} does not exist')
    refuse_overwrite(path, force, '--save-output')


def save_output(model, records, init_samples, path, policy=None, force: bool = False) -> None:
    """
    Write the free run of the (first) record to an .npz: u (V), y, y_sim (m), scored_from.

    The same free run as the scores (state from the first init_samples samples, or as
    `evaluate` says for None and 0). An existing file only with `force`; written to a fresh
    temporary file and renamed (files.write_atomic).
    """
    from dataclasses import replace

    import numpy as np

    from piezo_narx_ros.files import write_npz
    from piezo_narx_ros.ident.selection.scoring import free_run, scored_from
    check_save_output(path, records, force)
    rec = records[0]
    if init_samples is not None:
        rec = replace(rec, state_window=int(init_samples), state_policy=policy)
    from piezo_narx_ros.record import channels_arg
    _, sim = free_run(model, rec)
    # One axis: (N,) arrays as before several axes; several: (N, channels) with their names.
    names = {} if rec.n_in == 1 and rec.n_out == 1 else {
        'inputs': np.array(rec.inputs), 'outputs': np.array(rec.outputs)}
    write_npz(path, u=channels_arg(rec.u), y=channels_arg(rec.y), y_sim=channels_arg(sim),
              fs=rec.fs, scored_from=scored_from(model, rec), **names)


def run(args) -> int:
    """Load model and inputs, print the scores; exit code 0."""
    from piezo_narx_ros.cli.fit_output import one_line_warnings
    with one_line_warnings():
        return _run(args)


def _run(args) -> int:
    import json

    from piezo_narx_ros.ident.validation.noise_model import describe as describe_noise
    from piezo_narx_ros.cli.reading import reading_options
    from piezo_narx_ros.ident.data.loaders import load_records
    from piezo_narx_ros.ident.validation.usable import load_runnable
    from piezo_narx_ros.ident.validation.report import json_safe

    model = load_runnable(args.model)
    records = load_records(args.inputs, fs=args.fs, command_topic=args.command_topic,
                           deflection_topic=args.deflection_topic, **reading_options(args))
    if args.save_output:     # before the work: a refusal costs nothing
        check_save_output(args.save_output, records, args.force)
    if args.resample is not None:
        from piezo_narx_ros.ident.data.resample import resample_record
        records = [resample_record(r, args.resample) for r in records]
    if args.past != 'any':
        if not args.init_samples:
            from piezo_narx_ros.errors import ConfigError
            raise ConfigError(f'--past {args.past} needs --init-samples N > 0: it says how the '
                              'past before the measured window ended')
        from dataclasses import replace
        records = [replace(r, state_past=args.past) for r in records]
    policy, init_samples = stored_start(model, args.init_samples)
    result = evaluate(model, records, args.max_lag, args.max_outside_fraction, args.residuals,
                      args.noise_model, args.noise_order, init_samples, policy)
    if args.save_output:
        save_output(model, records, init_samples, args.save_output, policy, args.force)
    result['past'] = args.past
    if args.json:
        print(json.dumps(json_safe(result)))
        return 0

    def fmt(v, spec):
        return 'diverged' if v is None else format(v, spec)

    print(f'{result["structure"]} on {", ".join(result["inputs"])} ({result["n"]} samples)')
    if policy is not None:
        print(f'start: {policy!r} from the first {init_samples} measured samples (the model '
              "file's start policy)")
    for mode in ('prediction', 'simulation'):
        s = result[mode]
        print(f'{mode:>10}: R² {fmt(s["r2"], ".6f")}  RMSE {fmt(s["rmse"], ".4g")} m  '
              f'NRMSE {fmt(s["nrmse"], ".4g")}  fit {fmt(s["fit_percent"], ".2f")} %')
        per = s.get('per_output') or []
        for o in per if len(per) > 1 else []:
            print(f'{o["name"]:>12}: R² {fmt(o["r2"], ".6f")}  RMSE {fmt(o["rmse"], ".4g")} m')
    rest = result['simulation_from_rest']
    if rest is not None:
        print(f'{"from rest":>10}: R² {fmt(rest["r2"], ".6f")}  RMSE {fmt(rest["rmse"], ".4g")} m'
              '  (the same samples; estimator init:=rest where this is the better one)')
    if not result['tests']:
        print(f'correlation tests: not run (the {result["tests_residuals"]} residuals are not '
              'finite: the run diverged)')
        return 0
    nm = result['tests_noise_model']
    how = describe_noise(nm.get('per_output', nm) if nm else None)
    print(f'correlation tests ({result["tests_residuals"]} residuals, {how}): '
          + ', '.join(f'{k} {"pass" if v else "fail"}' for k, v in result['tests'].items())
          + f' -> {"PASS" if result["tests_passed"] else "FAIL"}')
    return 0
