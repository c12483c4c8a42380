"""What `piezo-narx fit` prints: the selected model, the search's pick, a fleet's table."""
import contextlib


@contextlib.contextmanager
def one_line_warnings():
    """Show warnings (e.g. bag gaps from the reader) as one stderr line each while inside."""
    import sys
    import warnings
    with warnings.catch_warnings():
        warnings.showwarning = lambda message, *args, **kwargs: print(
            f'piezo-narx: warning: {message}', file=sys.stderr)
        yield


def failed_line(failed) -> str:
    """One line naming the candidates that could not be fitted and the first one's error."""
    names = ', '.join(c.spec.label for c in failed[:5]) + (', ...' if len(failed) > 5 else '')
    return (f'warning: {len(failed)} candidate(s) could not be fitted ({names}); '
            f'{failed[0].spec.label}: {failed[0].error}')


def print_fit(outcome, executor) -> None:
    """Print the selected candidate, its scores and tests, and the files written."""
    from piezo_narx_ros.ident.validation.noise_model import describe as describe_noise
    result, config, model_path = outcome.result, outcome.config, outcome.model_path
    out, paths = model_path.parent, outcome.paths
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
        print(failed_line(failed))
    n_pass = sum(c.validated for c in result.candidates)
    print(f'{n_pass} of {len(result.candidates)} candidates pass all five tests')
    if not result.validated:
        print('warning: no candidate passed all correlation tests; selected by free-run R² '
              '(the worse of estimation and validation; not validated)')
    print(f'model: {model_path}')
    print(f'candidates: {out / "candidates.json"}')
    if paths:
        print(f'report: {out / "report"}')


def print_search(outcome) -> None:
    """Print the search's notes, its pick and why, each family's best, and the files."""
    result, options, out = outcome.result, outcome.options, outcome.model_path.parent
    model_path, paths = outcome.model_path, outcome.paths
    from piezo_narx_ros.ident.selection.search_report import family_lines
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


def print_summary(table, path) -> None:
    """Print a fleet's table, one recording a line."""
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
