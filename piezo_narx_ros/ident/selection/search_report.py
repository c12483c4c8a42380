"""
What a structure search leaves in its output folder.

    DIR/model.json (+ .npz)   the selected model, with its start policy (`start`) and why it was
                              picked (metrics.search)
    DIR/candidates.json       every trial: parameters, scores under each start policy, tests
    DIR/study.journal         the Optuna study (optuna-dashboard DIR/study.journal opens it)
    DIR/trials/               each trial's scores and model, written as it ends (resume)
    DIR/report/pareto.png     worst-case validation error against parameters, per family, the
                              Pareto front and the pick
    DIR/report/search.json    per family its best trial; the front; the selection
    DIR/report/...            the selected model's figures and metrics.json (ident/report.py)
"""
from __future__ import annotations

from dataclasses import replace
from pathlib import Path

from piezo_narx_ros.ident.selection.experiment import ExperimentConfig, ExperimentResult
from piezo_narx_ros.ident.selection.search import SEARCH_FAMILIES, SearchResult, trial_error
from piezo_narx_ros.ident.validation.report import _pyplot, _save, write_json, write_report

FAMILY_NAMES = {'arx': 'ARX', 'narx': "paper's NARX", 'hysteresis_narx': 'hysteresis NARX'}
_MARKERS = {'arx': 's', 'narx': '^', 'hysteresis_narx': 'o'}


def as_experiment(result: SearchResult) -> ExperimentResult:
    """Return the search as an ExperimentResult, for the experiment's report."""
    config = ExperimentConfig(init_seconds=result.window / result.fs if result.fs else 0.0,
                              selection='worst_case', init_past=result.options.past,
                              max_lag=result.options.max_lag,
                              max_outside_fraction=result.options.max_outside_fraction,
                              noise_model=result.options.noise_model,
                              noise_order=result.options.noise_order)
    return ExperimentResult(config=config, candidates=result.trials, selected=result.selected,
                            validated=result.best.validated, sources=result.sources,
                            fs=result.fs, n_estimation=result.n_estimation,
                            n_validation=result.n_validation, wall_seconds=result.wall_seconds,
                            validation_sources=result.validation_sources)


def start_block(result: SearchResult) -> dict:
    """Return the model file's start: the selected trial's policy and its window."""
    return {'policy': result.best.scores['start']['policy'], 'window_samples': result.window}


def plot_pareto(result: SearchResult):
    """Worst-case validation error against parameters, per family; the front and the pick."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for family in SEARCH_FAMILIES:
        pts = [(t.n_params, trial_error(t)) for t in result.trials
               if t.spec.kind == family and t.error is None and trial_error(t) < 1e6]
        if pts:
            x, y = zip(*pts)
            ax.scatter(x, y, marker=_MARKERS[family], alpha=0.6, label=FAMILY_NAMES[family])
    front = sorted((result.trials[i].n_params, trial_error(result.trials[i]))
                   for i in result.front)
    if front:
        ax.step(*zip(*front), where='post', color='k', lw=1, label='Pareto front')
    best = result.best
    ax.scatter([best.n_params], [trial_error(best)], s=160, facecolors='none',
               edgecolors='r', lw=2,
               label=f'selected: mean of {len(result.members)} trials' if result.members
               else f'selected: {best.spec.label}')
    ax.set_xscale('log')
    ax.set_yscale('log')
    ax.set_xlabel('parameters')
    ax.set_ylabel('worst-case validation error  sqrt(1 - R²)')
    ax.set_title(f'structure search: {len(result.trials)} trials, start from '
                 f'{result.window} measured samples')
    ax.grid(True, which='both', alpha=0.3)
    ax.legend(fontsize=7, loc='best')
    fig.tight_layout()
    return fig


def write_search(out, result: SearchResult, records: list, validation: list,
                 report: bool = True, data_info: dict | None = None) -> tuple[Path, dict]:
    """
    Write DIR/model.json, DIR/candidates.json and (report) DIR/report/; return (model, paths).

    records, validation: the estimation and validation records the search ran on (the report
    draws the selected model's free runs on the validation records under its start policy).
    data_info: the model file's `data` block (the fit's provenance) besides what the search adds.
    """
    from piezo_narx_ros.ident.model_io import save_model
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    best = result.best
    start = start_block(result)
    info = dict(data_info or {})
    info.update(sources=result.sources, fs=result.fs,
                validation_sources=result.validation_sources, preset='search',
                init_seconds=result.window / result.fs if result.fs else 0.0,
                n_estimation=result.n_estimation, n_validation=result.n_validation)
    metrics = {**best.scores, 'selected_by': 'search',
               'noise_model': result.options.noise_model,
               'search': {'why': result.why, 'trial': result.numbers[result.selected],
                          'committee': [result.numbers[i] for i in result.members],
                          'trials': len(result.trials), 'tolerance': result.options.tolerance}}
    model_path = save_model(best.model, out / 'model.json', data=info, metrics=metrics,
                            tests={**best.tests, 'validated': best.validated}, start=start)
    summary = result.to_dict()
    write_json(summary, out / 'candidates.json')
    paths = {}
    if report:
        scored = [replace(r, state_window=result.window, state_policy=start['policy'],
                          state_past=result.options.past, u_before=None, y_before=None)
                  for r in validation]
        paths = write_report(as_experiment(result), scored, out / 'report')
        plt = _pyplot()
        try:
            paths['pareto'] = _save(plot_pareto(result), out / 'report' / 'pareto.png')
        finally:
            plt.close('all')
        paths['search'] = write_json(summary['search'] | {'selection': summary['selection']},
                                     out / 'report' / 'search.json')
    return model_path, paths


def family_lines(result: SearchResult) -> list[str]:
    """One printed line per family: its best trial, worst-case R², start policy, parameters."""
    lines = []
    for row in result.family_table():
        name = FAMILY_NAMES[row['family']]
        if 'best' not in row:
            lines.append(f'  {name:<16} {row["trials"]} trial(s), none fitted')
            continue
        r2 = row['r2_worst']
        lines.append(f'  {name:<16} {row["trials"]:>3} trial(s)  best {row["best"]}: worst-case '
                     f'R² {"diverged" if r2 is None else f"{r2:.6f}"} ({row["policy"]} start, '
                     f'{row["n_params"]} parameters)')
    return lines
