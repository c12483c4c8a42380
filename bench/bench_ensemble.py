"""
Issue 18.4 / 20: the mean of the best candidates' free runs against the selected model.

The experiment (ident/selection/experiment.py) fits several candidates (network seeds x
increments, ARX) and selects one by the worst case of its free-run R² over the validation
records and outputs.
Here, after the same experiment, the candidates that fitted are ranked by that worst case and
these models are compared on the same moves:

  single   the selected model (the product today);
  top-K    EnsembleModel (ident/ensemble/model.py) of the K best candidates, K = 2, 3, 5;
  seeds    the selected structure over every network seed the grid fitted (the same options).

For each, its own validation worst case (what the experiment would see: `score_candidate` on the
same validation halves) and its free run on a battery:

  axes      bench_axes.py's two-axis stage (the coupled cantilever; its identification record and
            battery; seeds s), both axes;
  envelope  bench_envelope.py's one-axis battery, both plants;
  yan9a     the real micromanipulator (fit on Model_Vi_Do, as `fit --preset envelope`; free run
            of Test_Vi_Do_Di with the state set from its first 200 samples, as bench_real.py).

Run: python bench/bench_ensemble.py --setting axes|envelope|yan9a [--seeds 0 1 2 3 4]
     [--plants default preisach] [--jobs 2] [--json out.json]
"""
import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_axes  # noqa: E402
import bench_envelope  # noqa: E402
from bench_excitation import score  # noqa: E402

from piezo_narx_ros.ident.validation import metrics  # noqa: E402
from piezo_narx_ros.ident.ensemble.model import EnsembleModel  # noqa: E402
from piezo_narx_ros.ident.selection.experiment import (CandidateResult,  # noqa: E402
                                                       run_experiment, score_candidate,
                                                       split_records, with_state_window)
from piezo_narx_ros.ident.selection.scoring import free_run  # noqa: E402
from piezo_narx_ros.plant import load_plant_params  # noqa: E402
from piezo_narx_ros.record import Record  # noqa: E402

KS = (2, 3, 5)


def variants(result):
    """{name: (model, labels)}: the selected model, the top-K ensembles, the seeds ensemble."""
    ok = sorted((c for c in result.candidates if c.error is None and c.model is not None),
                key=lambda c: -c.free_run_r2())
    best = result.best
    out = {'single': (best.model, [best.spec.label])}
    for k in KS:
        if len(ok) >= k:
            out[f'top-{k}'] = (EnsembleModel([c.model for c in ok[:k]]),
                               [c.spec.label for c in ok[:k]])
    same = [c for c in ok if (c.spec.kind, c.spec.hidden, c.spec.options, c.spec.nu,
                              c.spec.ny) == (best.spec.kind, best.spec.hidden,
                                             best.spec.options, best.spec.nu, best.spec.ny)]
    if len(same) > 1:
        out['seeds'] = (EnsembleModel([c.model for c in same]), [c.spec.label for c in same])
    return out


def validation_worst(model, result, records, config):
    """Return the experiment's worst-case free-run R² of `model` on the same records."""
    est, val = split_records(with_state_window(records, config), config.split)
    res = CandidateResult(spec=result.best.spec)
    score_candidate(res, model, est, val, config)
    return res.free_run_r2()


def run_axes(seed, jobs):
    """{variant: {'val': R², 'moves': {move: (R² per axis, RMSE per axis m)}, 'labels'}}."""
    u = bench_axes.make_signal('protocol', bench_axes.FS, 25.0, 100.0, seed=seed,
                               n_axes=len(bench_axes.AXES))
    y, _ = bench_axes.stage(seed).run(u)
    cfg = bench_envelope.preset_config('envelope', seed, jobs)
    rec = Record(u=u, y=y, fs=bench_axes.FS, source=f'protocol seed {seed}',
                 inputs=bench_axes.AXES, outputs=bench_axes.AXES)
    t0 = time.perf_counter()
    result = run_experiment([rec], cfg)
    fit_s = time.perf_counter() - t0
    out = {}
    for name, (model, labels) in variants(result).items():
        moves = bench_axes.free_run_battery(model, seed)
        out[name] = {'val': validation_worst(model, result, [rec], cfg), 'labels': labels,
                     'moves': {k: (list(v[0]), list(v[1])) for k, v in moves.items()}}
    return out, fit_s


def run_envelope(plant, seed, jobs):
    """As run_axes on one plant of bench_envelope.py (one axis: lists of one)."""
    params = load_plant_params(bench_envelope.PLANTS[plant])
    u = bench_envelope.generate('protocol', bench_envelope.FS, 25.0, 100.0, seed=seed)
    y = bench_envelope.PiezoCantilever(params, bench_envelope.FS, seed=seed).run(u).y
    cfg = bench_envelope.preset_config('envelope', seed, jobs)
    rec = Record(u=u, y=y, fs=bench_envelope.FS, source=f'protocol seed {seed}')
    t0 = time.perf_counter()
    result = run_experiment([rec], cfg)
    fit_s = time.perf_counter() - t0
    tests = bench_envelope.battery(params, seed)
    out = {}
    for name, (model, labels) in variants(result).items():
        moves = score(model, tests)
        out[name] = {'val': validation_worst(model, result, [rec], cfg), 'labels': labels,
                     'moves': {k: ([r2], [rmse_nm * 1e-9]) for k, (r2, rmse_nm) in moves.items()}}
    return out, fit_s


def read_yan9a(path):
    table = np.loadtxt(path, ndmin=2)
    # Column 1: actuator input, V; column 5: sensor, um (README of the data set).
    return Record(u=table[:, 0], y=table[:, 4] * 1e-6, fs=200.0, source=str(path))


def run_yan9a(seed, jobs, data):
    """Fit on Model_Vi_Do (split as `fit` does), free run of Test_Vi_Do_Di from 200 samples."""
    est = read_yan9a(Path(data) / 'piezo_yan9a' / 'Model_Vi_Do.dat')
    test = read_yan9a(Path(data) / 'piezo_yan9a' / 'Test_Vi_Do_Di.dat')
    cfg = bench_envelope.preset_config('envelope', seed, jobs)
    t0 = time.perf_counter()
    result = run_experiment([est], cfg)
    fit_s = time.perf_counter() - t0
    test = Record(u=test.u, y=test.y, fs=test.fs, source=test.source, state_window=200)
    out = {}
    for name, (model, labels) in variants(result).items():
        _, sim = free_run(model, test)
        y = test.y[200:]
        sim = sim[200:]
        r2 = metrics.r2(y[:, 0], sim[:, 0]) if np.all(np.isfinite(sim)) else -np.inf
        rmse = metrics.rmse(y[:, 0], sim[:, 0]) if np.all(np.isfinite(sim)) else np.inf
        out[name] = {'val': validation_worst(model, result, [est], cfg), 'labels': labels,
                     'moves': {'Test_Vi_Do_Di': ([r2], [rmse])}}
    return out, fit_s


def stepper_costs(steps=20000):
    """
    Stepper.step p50 / p99 (us) of preset-size envelope models, single beside ensembles of K.

    Members: HysteresisNARX (hidden 10, 12 plays, the preset's size) fitted briefly (the cost
    does not depend on the fit), one axis; and HysteresisChains (the same per axis), two axes.
    Timed one call at a time, as estimator_node's loop runs it, all in one run.
    """
    from bench_mimo_stepper import time_steps
    from piezo_narx_ros.ident.hysteresis.model import HysteresisNARX
    from piezo_narx_ros.ident.hysteresis.chains import HysteresisChains
    u1 = bench_envelope.generate('protocol', 2000.0, 3.0, 100.0, seed=0)
    y1 = bench_envelope.PiezoCantilever(load_plant_params(bench_envelope.PLANTS['default']),
                                        2000.0, seed=0).run(u1).y
    u2 = bench_axes.make_signal('protocol', 2000.0, 3.0, 100.0, seed=0, n_axes=2)
    y2, _ = bench_axes.stage(0).run(u2)
    one = [HysteresisNARX(hidden=10, seed=s, max_iter=3).fit(u1, y1, fs=2000.0)
           for s in range(5)]
    two = [HysteresisChains(hidden=10, seed=s, max_iter=3).fit(u2, y2, fs=2000.0)
           for s in range(3)]
    rng = np.random.default_rng(0)
    x1 = list(rng.uniform(-50, 50, steps))
    x2 = list(rng.uniform(-50, 50, (steps, 2)))
    rows = []
    for label, models, x in (('1 x 1', one, x1), ('2 x 2 chains', two, x2)):
        for k in [1] + [k for k in KS if k <= len(models)]:
            model = models[0] if k == 1 else EnsembleModel(models[:k])
            t = time_steps(model.stepper(), x) / 1e3
            rows.append((label, k, float(np.percentile(t, 50)), float(np.percentile(t, 99))))
            print(f'  {label:13s} K={k}: Stepper.step p50 {rows[-1][2]:6.1f} us, p99 '
                  f'{rows[-1][3]:6.1f} us', flush=True)
    print(f'  load average {os.getloadavg()}')
    return rows


def with_rule(run, margin=0.0):
    """Add 'rule-K': top-K where its validation beats the single's by `margin`, else single."""
    for k in KS:
        top = run.get(f'top-{k}')
        if top is not None:
            run[f'rule-{k}'] = top if top['val'] > run['single']['val'] + margin else run['single']
    return run


def summary(runs, slow, moves):
    """Print per variant: validation worst case median, per move RMSE median / worst per axis."""
    runs = [with_rule(dict(r)) for r in runs]
    names = [n for n in runs[0] if all(n in r for r in runs)]
    for name in names:
        val = [r[name]['val'] for r in runs]
        print(f'  {name:7s} validation worst-case R² median {statistics.median(val):.6f} '
              f'(worst {min(val):.6f}); beats single on '
              f'{sum(r[name]["val"] > r["single"]["val"] for r in runs)}/{len(runs)}')
        for move in moves:
            rmse = np.array([r[name]['moves'][move][1] for r in runs]) * 1e9   # (seeds, axes)
            r2 = np.array([r[name]['moves'][move][0] for r in runs])
            cells = ' | '.join(f'{np.median(rmse[:, a]):7.1f} {rmse[:, a].max():7.1f} '
                               f'{np.median(r2[:, a]):.6f}' for a in range(rmse.shape[1]))
            print(f'      {move:18s} {cells}{" (slow)" if move in slow else ""}')


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    ap.add_argument('--setting', choices=('axes', 'envelope', 'yan9a', 'stepper'), required=True)
    ap.add_argument('--seeds', type=int, nargs='+', default=[0, 1, 2, 3, 4])
    ap.add_argument('--plants', nargs='+', default=['default', 'preisach'])
    ap.add_argument('--jobs', type=int, default=2)
    ap.add_argument('--data', default=str(Path(__file__).resolve().parents[3] / 'shared' /
                                          'data'))
    ap.add_argument('--json')
    args = ap.parse_args(argv)
    if args.setting == 'stepper':
        stepper_costs()
        return 0
    groups = ([(None, args.setting)] if args.setting != 'envelope'
              else [(p, f'envelope {p}') for p in args.plants])
    report = {}
    for plant, title in groups:
        runs = []
        for seed in args.seeds:
            if args.setting == 'axes':
                out, fit_s = run_axes(seed, args.jobs)
            elif args.setting == 'envelope':
                out, fit_s = run_envelope(plant, seed, args.jobs)
            else:
                out, fit_s = run_yan9a(seed, args.jobs, args.data)
            runs.append(out)
            cells = ', '.join(f'{n} val {v["val"]:.6f} ms/first '
                              f'{np.array(next(iter(v["moves"].values()))[1]) * 1e9}'
                              for n, v in out.items())
            print(f'[{title}] seed {seed}: fit {fit_s:.0f} s; {cells}', flush=True)
            print(f'    members top-5: {out.get("top-5", out["single"])["labels"]}', flush=True)
        moves = list(runs[0]['single']['moves'])
        print(f'\n== {title}, seeds {args.seeds}: RMSE nm median / worst, R² median per axis')
        summary(runs, bench_envelope.SLOW, moves)
        report[title] = runs
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=1, default=float) + '\n')
    return 0


if __name__ == '__main__':
    sys.exit(main())
