"""
CubeSpec Fine Steering Mirror benchmark (3 x 3 real piezo actuators), scored the benchmark's way.

Fit on a split of the training realizations and score on the others, beside the published
baselines.

Run: python bench/bench_fsm.py [--data ../shared/data/fsm] [--fit 1-4] [--score 5-6]
         [--family arx --orders 2,10,20,28,30] [--family narx --lags 4 --hidden 10]
         [--family preset:NAME] [--per-level] [--json out.json]

Data: ../shared/data/fsm/train_{100,200,300}mV_r{1..6}.npz, u (16384, 3) V, y (16384, 3) m at
6400 Hz, two periods of 8192 samples in periodic steady state (NOT at rest). The benchmark's test
sets are held out by design; this bench fits on realizations --fit of every level and scores on
realizations --score (never fitted on).

Score (the benchmark's rule for a test record): the model may use the input and the first 100
measured output samples to set its state; the figure is the RMSE (µm) of the free-run output over
the remaining samples, averaged over outputs and records, per amplitude level. Three ways to set
the state, each reported:
  * window:   the first 100 measured samples set the state (model.estimate_state, as
              `piezo-narx evaluate --init-samples 100`); the input before sample 0 is unknown
              and taken as held at u(0);
  * periodic: the input is periodic (steady state), so the model free-runs from rest through one
              extra copy of the record's input first and is scored on the second copy after
              sample 100 (no measured output used);
  * history:  lagged models (ARX, the network) only: the free run starts from the first n0
              measured outputs (n0 <= 100, the paper's convention), scored after sample 100.
Published baselines on the test sets (data README): BLA per level 0.114 / 0.216 / 0.228, BLA all
levels 0.252 / 0.179 / 0.658, nonlinear LFR 0.0866 / 0.131 / 0.169 µm.

Families: `arx` (MIMO ARX, na = nb = each of --orders), `narx` (the paper's network, one MLP with
3 outputs over all lagged channels), `preset:NAME` (piezo-narx fit's experiment with that preset
on the fit records, split in halves to select; the selected model is scored). Add a family with
`register_family(name, builder)`.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from piezo_narx_ros.ident.data.loaders import load_record
from piezo_narx_ros.ident.selection.scoring import free_run
from piezo_narx_ros.record import as_columns, channels_arg

REPO = Path(__file__).resolve().parents[1]
DEFAULT_DATA = Path(os.environ.get('PIEZO_NARX_SHARED', REPO.parent / 'shared')) / 'data' / 'fsm'
LEVELS = (100, 200, 300)                # mV
INIT = 100                              # samples that may set the state (the benchmark's rule)
UM = 1e6
DIVERGED_UM = 1e3                       # a free-run RMSE beyond 1 mm is an unstable model
PUBLISHED = {                           # µm on the test sets, per level (data README)
    'BLA (28th order) per level, own level': (0.114, 0.216, 0.228),
    'BLA all levels': (0.252, 0.179, 0.658),
    'nonlinear LFR all levels': (0.0866, 0.131, 0.169),
}


def parse_list(text: str) -> list[int]:
    """'1-4' or '1,3,5' -> [1, 2, 3, 4] / [1, 3, 5]."""
    out = []
    for part in str(text).split(','):
        lo, _, hi = part.partition('-')
        out += list(range(int(lo), int(hi) + 1)) if hi else [int(lo)]
    return out


def load(data: Path, level: int, realizations) -> list:
    """Load the records train_<level>mV_r<i>.npz (u (N, 3) V, y (N, 3) m, names u1.., y1..)."""
    return [load_record(data / f'train_{level}mV_r{i}.npz') for i in realizations]


HOWS = ('periodic', 'window', 'history')


def free_runs(model, record) -> dict:
    """{how: (N, 3)} free runs of a model on one record (m), for each way in HOWS."""
    windowed = replace(record, state_window=INIT)
    _, sim_window = free_run(model, windowed)
    u = channels_arg(record.u)
    with np.errstate(all='ignore'):
        twice = as_columns(model.simulate(np.concatenate([u, u])))
        out = {'periodic': twice[len(record):], 'window': sim_window}
        if not getattr(model, 'state_from_input', False) and model.n0 <= INIT:
            # Lagged models: the first n0 measured outputs are their whole state.
            out['history'] = as_columns(model.simulate(u, channels_arg(record.y)[:model.n0]))
    return out


def scores(model, by_level: dict) -> dict:
    """{how: {level: µm}}: RMSE after INIT per output and record, averaged over both."""
    out = {how: {} for how in HOWS}
    for level, records in by_level.items():
        per = {how: [] for how in HOWS}
        for rec in records:
            for how, sim in free_runs(model, rec).items():
                e = (sim - rec.y)[INIT:]
                with np.errstate(all='ignore'):
                    per[how] += list(np.sqrt(np.mean(e * e, axis=0)) * UM)
        for how, values in per.items():
            if not values:
                continue
            with np.errstate(all='ignore'):
                v = float(np.mean(values))
            # An unstable free run (grows past a millimetre) is reported as diverged.
            out[how][level] = v if np.isfinite(v) and v < DIVERGED_UM else None
    return out


# ------------------------------------------------------------------------------ families
FAMILIES = {}


def register_family(name: str, builder) -> None:
    """
    Add a family: builder(args) -> list of (label, fit) with fit(records) -> fitted model.

    Each fit gets the fit records of one level (--per-level) or of all levels.
    """
    FAMILIES[name] = builder


def _arx(args):
    from piezo_narx_ros.ident.arx.model import ARXModel

    def fitter(order):
        def fit(records):
            return ARXModel(na=order, nb=order).fit([channels_arg(r.u) for r in records],
                                                    [channels_arg(r.y) for r in records],
                                                    fs=records[0].fs)
        return fit
    return [(f'MIMO ARX(na={o}, nb={o})', fitter(o)) for o in parse_list(args.orders)]


def _narx(args):
    from piezo_narx_ros.ident.narx.model import NARXNetwork
    options = json.loads(args.training) if args.training else {}

    def fit(records):
        return NARXNetwork(nu=args.lags, ny=args.lags, hidden=args.hidden, seed=args.seed,
                           **options).fit([channels_arg(r.u) for r in records],
                                          [channels_arg(r.y) for r in records],
                                          fs=records[0].fs)
    return [(f'NARX network (nu=ny={args.lags}, H={args.hidden})', fit)]


def _preset(name):
    def build(args):
        from piezo_narx_ros.ident.selection.experiment import (PRESETS, ExperimentConfig,
                                                               run_experiment)

        def fit(records):
            settings = {**PRESETS[name], 'jobs': args.jobs, 'progress': False}
            result = run_experiment(records, ExperimentConfig(**settings))
            fit.label = result.best.spec.label
            return result.best.model
        return [(f'preset {name}', fit)]
    return build


register_family('arx', _arx)
register_family('narx', _narx)


def family_builders(names, args):
    """Return the (label, fit) pairs of the families named (preset:NAME allowed)."""
    out = []
    for name in names:
        if name.startswith('preset:'):
            out += _preset(name.split(':', 1)[1])(args)
        elif name in FAMILIES:
            out += FAMILIES[name](args)
        else:
            raise SystemExit(f'bench_fsm: unknown family {name!r} (known: '
                             f'{", ".join(FAMILIES)}, preset:NAME)')
    return out


# ------------------------------------------------------------------------------ main
def row(label: str, values: dict | tuple) -> str:
    """Return one table line: label and the three levels' µm."""
    vals = [values.get(lv) if isinstance(values, dict) else values[i]
            for i, lv in enumerate(LEVELS)]
    text = ''.join(f'{"diverged" if v is None else f"{v:.4f}":>10}' for v in vals)
    return f'{label:<52}{text}'


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    p.add_argument('--data', type=Path, default=DEFAULT_DATA)
    p.add_argument('--fit', default='1-4', help='realizations that fit (default 1-4)')
    p.add_argument('--score', default='5-6', help='realizations that score (default 5-6)')
    p.add_argument('--family', action='append',
                   help='arx, narx or preset:NAME (repeatable; default arx)')
    p.add_argument('--orders', default='2,10,20,28,30', help='ARX orders na = nb')
    p.add_argument('--lags', type=int, default=4, help='NARX nu = ny')
    p.add_argument('--hidden', type=int, default=10)
    p.add_argument('--seed', type=int, default=0)
    p.add_argument('--training', help='NARX training options as JSON')
    p.add_argument('--jobs', type=int, default=1)
    p.add_argument('--per-level', action='store_true',
                   help='also fit one model per level, scored on its own level (as the BLA)')
    p.add_argument('--json', type=Path, help='write every figure to this file')
    args = p.parse_args(argv)
    if not args.data.is_dir():
        print(f'bench_fsm: no FSM data at {args.data} (give --data)', file=sys.stderr)
        return 2
    fit_ids, score_ids = parse_list(args.fit), parse_list(args.score)
    if set(fit_ids) & set(score_ids):
        raise SystemExit('bench_fsm: --fit and --score realizations overlap')
    fit_sets = {lv: load(args.data, lv, fit_ids) for lv in LEVELS}
    score_sets = {lv: load(args.data, lv, score_ids) for lv in LEVELS}
    every = [r for lv in LEVELS for r in fit_sets[lv]]
    print(f'FSM: fit on realizations {fit_ids}, scored on {score_ids} of every level; '
          f'load {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores')
    results = []
    for label, fit in family_builders(args.family or ['arx'], args):
        t0 = time.perf_counter()
        model = fit(every)
        seconds = time.perf_counter() - t0
        label = getattr(fit, 'label', None) or label
        s = scores(model, score_sets)
        results.append({'label': label + ', all levels', 'fit_seconds': seconds, **s,
                        'n_params': int(model.n_params)})
        print(f'{label}, all levels: fitted in {seconds:.1f} s ({model.n_params} parameters)',
              flush=True)
        if args.per_level:
            own = {how: {} for how in HOWS}
            for lv in LEVELS:
                m = fit(fit_sets[lv])
                s = scores(m, {lv: score_sets[lv]})
                for how in own:
                    own[how][lv] = s[how].get(lv)
            results.append({'label': label + ', per level', **own})
    print(f'\nfree-run RMSE after the first {INIT} samples, µm, mean over 3 outputs and the '
          'scored records')
    print(f'{"model [how the state is set]":<52}' + ''.join(f'{f"{lv} mV":>10}' for lv in LEVELS))
    for res in results:
        for how in HOWS:
            if res[how]:
                print(row(f'{res["label"]} [{how}]', res[how]))
    print('published, on the test sets:')
    for label, values in PUBLISHED.items():
        print(row('  ' + label, values))
    if args.json:
        args.json.write_text(json.dumps({'fit': fit_ids, 'score': score_ids, 'init': INIT,
                                         'results': results, 'published': PUBLISHED},
                                        indent=1) + '\n')
    return 0


if __name__ == '__main__':
    sys.exit(main())
