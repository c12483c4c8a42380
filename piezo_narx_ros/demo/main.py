"""`piezo-narx demo` flow: the five phases, the summary JSON and the printed table."""
from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from piezo_narx_ros.demo.runner import (Demo, PhaseFailed, install_signal_handlers,
                                        restore_signal_handlers, stream_counts)
from piezo_narx_ros.errors import ConfigError

TOPICS_UY = {'piezo/voltage_command': 'effort', 'piezo/deflection': 'position'}


def _say(text: str = '') -> None:
    print(text, flush=True)


PHASES = 5


def _header(n: int, title: str) -> None:
    _say(f'\n== {n}/{PHASES} {title}')


def run_demo(settings: dict, out: Path) -> int:
    """
    All five phases into `out`; returns 0.

    PhaseFailed / Interrupted propagate after every child has been stopped.
    """
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ConfigError(f'--out {out}: exists and is not a directory')
    if any((out / name).exists() for name in ('record', 'fit', 'live', 'live_slow',
                                              'summary.json')):
        raise ConfigError(f'--out {out}: holds an earlier demo; choose a new folder')
    s = settings
    t_all = time.monotonic()
    demo = Demo(s, out, say=_say)
    old = install_signal_handlers(demo)
    try:
        _say(f'piezo-narx demo -> {out} (node logs: {out / "demo.log"})')
        with demo:
            _header(1, f'record: {s["kind"]} {s["seconds"]:g} s at {s["fs"]:g} Hz, '
                       f'seed {s["seed"]} (command -> simulator -> recorder)')
            t0 = time.monotonic()
            rec = demo.stream('record', out / 'record', s['seconds'], s['seed'])
            demo.times.add('record', t0)
            rec_counts = stream_counts(out / 'record', TOPICS_UY)
            rec_lost = {t.rsplit('/', 1)[1]: rec['published'] - c for t, c in rec_counts.items()}
            if min(rec_counts.values()) == 0:
                raise PhaseFailed('record: no samples recorded')

            _header(2, 'fit: piezo-narx fit on the recording (preset '
                       f'{s["fit"].get("preset", "paper")})')
            t0 = time.monotonic()
            model_doc = demo.fit(out / 'record', out / 'fit')
            demo.times.add('fit', t0)
            cands = json.loads((out / 'fit' / 'candidates.json').read_text())
            sel = cands['selection']
            val = model_doc['metrics']['validation']
            verdict = 'validated' if sel['validated'] else 'NOT validated'
            _say(f'  selected {sel["label"]} ({verdict} by the correlation tests) of '
                 f'{len(cands["candidates"])} candidates; offline validation R²: '
                 f'prediction {val["prediction"]["r2"]:.6f}, simulation '
                 f'{_fmt(val["simulation"]["r2"], ".6f")}')

            model_path = out / 'fit' / 'model.json'
            _header(3, f'live: estimator_node with {sel["label"]}, fresh {s["validation_kind"]}'
                       f' {s["validation_seconds"]:g} s, seed {s["validation_seed"]}')
            t0 = time.monotonic()
            live = demo.stream('live', out / 'live', s['validation_seconds'],
                               s['validation_seed'], model=model_path, kind=s['validation_kind'])
            demo.times.add('live', t0)
            est_diag = demo.probe.status(demo.fq('estimator_node'))

            _header(4, f'live, slow full-range move: {s["slow_kind"]} {s["slow_freq"]:g} Hz '
                       f'+-{s["amplitude"]:g} V, {s["slow_seconds"]:g} s')
            t0 = time.monotonic()
            slow = demo.stream('live_slow', out / 'live_slow', s['slow_seconds'],
                               s['validation_seed'] + 1, model=model_path, kind=s['slow_kind'],
                               extra_command={'freq': float(s['slow_freq'])})
            demo.times.add('live_slow', t0)
            slow_diag = demo.probe.status(demo.fq('estimator_node'))

        _header(5, 'analysis')
        t0 = time.monotonic()
        summary = analyse(out, live, model_doc, est_diag)
        slow_summary = analyse(out, slow, model_doc, slow_diag, phase='live_slow',
                               fig_dir=out / 'figures' / 'slow')
        summary['live_slow'] = slow_summary['live']
        summary['figures_slow'] = slow_summary['figures']
        demo.times.add('analysis', t0)
    finally:
        restore_signal_handlers(old)
    demo.times.seconds['total'] = round(time.monotonic() - t_all, 3)
    summary = {
        'settings': s,
        'wall_seconds': demo.times.seconds,
        'record': {'bag': str(out / 'record'), 'published': rec['published'],
                   'expected': rec['expected'], 'lost': rec_lost},
        'fit': {'dir': str(out / 'fit'), 'model': str(out / 'fit' / 'model.json'),
                'report': str(out / 'fit' / 'report'), 'selected': sel['label'],
                'validated': sel['validated'], 'candidates': len(cands['candidates']),
                'offline_validation': val},
        **summary,
    }
    from piezo_narx_ros.ident.validation.report import write_json
    write_json(summary, out / 'summary.json')
    print_table(summary)
    _say(f'\nreport: {out}  (summary.json, figures/, fit/report/)')
    return 0


def analyse(out: Path, live: dict, model_doc: dict, est_diag, phase: str = 'live',
            fig_dir: Path | None = None) -> dict:
    """Live figures, offline-equality check and PNGs of one live recording (OUT/phase)."""
    from piezo_narx_ros.demo.analysis import (live_figures, load_live_run, offline_difference,
                                              write_figures)
    from piezo_narx_ros.ident.model_io import load_model
    model = load_model(out / 'fit' / 'model.json')
    run = load_live_run(out / phase, expected=live['published'])
    diag = dict(est_diag[1]) if est_diag else {}
    # Initialised from measurement, the first init_samples estimates are the window the state
    # was fitted to: not scored.
    measured = diag.get('init') == 'measurement'
    skip = int(diag.get('init_samples', model.n0)) if measured else 0
    in_range = getattr(model, 'input_range', None)
    if in_range is not None:       # (lo, hi) V, or ((lo...), (hi...)) for several inputs
        in_range = tuple(np.asarray(v, dtype=np.float64) if np.ndim(v) else float(v)
                         for v in in_range)
    figures = live_figures(run, skip, in_range)
    diff = offline_difference(run, model, skip if measured else 0)
    paths = write_figures(run, skip, fig_dir or out / 'figures', in_range)
    return {'live': {'bag': str(out / phase), 'published': live['published'],
                     'estimator_init': diag.get('init'), 'estimator_diagnostics': diag,
                     **figures,
                     'live_vs_offline_simulate_max_nm': None if diff is None else diff * 1e9,
                     'latency_source': 'recorder_node receive times: estimate minus command '
                                       'of the same stamp (one process, one clock)',
                     'lateness_source': 'recorder receive time of the estimate minus the '
                                        'sample stamp t0 + k/fs (adds the command timer '
                                        'lateness)'},
            'figures': {k: str(v) for k, v in paths.items()}}


def _fmt(v, spec: str) -> str:
    return 'n/a' if v is None else format(v, spec)


def _range(r) -> str:
    if r is None:
        return 'n/a'
    if np.ndim(r[0]):      # several axes: per axis
        return ', '.join(f'[{lo:.1f}, {hi:.1f}]' for lo, hi in zip(*r)) + ' V'
    return f'[{r[0]:.1f}, {r[1]:.1f}] V'


def print_table(summary: dict) -> None:
    """Print the final summary table on stdout."""
    live, w = summary['live'], summary['wall_seconds']
    lat, late = live['latency_us'], live['lateness_us']
    init = live.get('init_latency_us', {'n': 0, 'max': None})
    rows = [
        ('selected model', f'{summary["fit"]["selected"]} '
                           f'({"validated" if summary["fit"]["validated"] else "not validated"})'),
        ('offline validation R² (sim)',
         _fmt(summary['fit']['offline_validation']['simulation']['r2'], '.6f')),
        ('live free-run R²', f'{live["r2"]:.6f}  ({live["n_scored"]} samples)'),
        ('  slow full-range sine', f'R² {summary["live_slow"]["r2"]:.6f}, RMSE '
                                   f'{summary["live_slow"]["rmse_nm"]:.1f} nm  '
                                   f'({summary["live_slow"]["n_scored"]} samples)'),
        ('  inside training input range',
         f'R² {_fmt(live.get("r2_inside_input_range"), ".6f")}, RMSE '
         f'{_fmt(live.get("rmse_nm_inside_input_range"), ".1f")} nm '
         f'({live.get("outside_input_range", "n/a")} samples outside '
         f'{_range(live.get("input_range_V"))})'),
        ('live RMSE', f'{live["rmse_nm"]:.1f} nm  (max |error| {live["max_abs_error_nm"]:.0f} nm,'
                      f' span {live["y_span_um"]:.1f} µm)'),
        ('live vs offline simulate', f'{_fmt(live["live_vs_offline_simulate_max_nm"], ".2e")} nm'
                                     ' max'),
        ('latency cmd->estimate', f'p50 {_fmt(lat["p50"], ".0f")} µs, p99 '
                                  f'{_fmt(lat["p99"], ".0f")} µs, '
                                  f'max {_fmt(lat["max"], ".0f")} µs'),
        ('lateness stamp->estimate', f'p50 {_fmt(late["p50"], ".0f")} µs, p99 '
                                     f'{_fmt(late["p99"], ".0f")} µs'),
        ('  waiting for the state', f'{init["n"]} samples, max {_fmt(init["max"], ".0f")} µs '
                                    '(the measured window and the state estimate)'),
        ('lost samples (record)', ', '.join(f'{k} {v}' for k, v in
                                            summary['record']['lost'].items())),
        ('lost samples (live)', ', '.join(f'{k} {v}' for k, v in live['lost'].items())),
        ('lost samples (live slow)', ', '.join(f'{k} {v}' for k, v in
                                               summary['live_slow']['lost'].items())),
        ('wall time', ', '.join(f'{k} {v:.1f} s' for k, v in w.items())),
    ]
    width = max(len(r[0]) for r in rows)
    _say('\n== summary')
    for name, value in rows:
        _say(f'  {name:<{width}}  {value}')
