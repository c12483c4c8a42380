"""
The two-axis targets of issue 20 on the coupled cantilever of config/plant_2axis.yaml.

For each seed s (default 0..4, as bench_envelope.py):

1. Free run of both axes: one 2 x 2 model identified (`--preset`, as `piezo-narx fit` runs it:
   50/50 split, network seeds s..) on one 25 s record of the identification protocol on both
   axes, as command_node streams it (`command.stream.make_signal`, axis i seeded s + i and
   rotated by i/2 of a protocol cycle), coupling on, sensor noise seed s; then its free run from
   rest on bench_envelope.py's battery (its moves, 10 s each, its signal and noise seeds; both
   axes move at once: y gets the same kind of move shifted by a third of the record). RMSE per
   axis, median and worst over the seeds, against docs/envelope.md's targets: slow full-range
   moves <= 1 um median / 2 um worst, steps, APRBS, +-50 V sines and chirp <= 2 um worst, fresh
   multisine R² median >= 0.9999, no runaway (R² < 0.5).
2. Sensorless control of both axes: AxesController 'inverse' (the model inverted, coupling
   compensated) against 'linear' (each axis's own static line, coupling ignored) on sine
   references of both axes at once (CONTROL_TASKS), the coupled stage measured (its true
   deflection, no noise; scored after the first second); target inverse RMS <= 1/10 of the
   linear one on each axis at 0.1 and 1 Hz (docs/control.md's one-axis targets), <= 1/3 at
   10 Hz. Also the controller's compute per sample (p50 / p99, us).

    python bench/bench_axes.py --preset envelope [--seeds 0 1 2 3 4] [--json out.json]
                               [--no-control] [--hnarx '{"na": 4, "nb": 4}'] [--seconds 50]
                               [--keep DIR | --kept DIR]

--keep DIR writes each seed's selected model as a model file (DIR/seed<s>/model.json, the
JSON + .npz of `piezo-narx fit`, loaded without pickle) and its fit time and label
(DIR/seed<s>/fit.json); --kept DIR runs the battery and control on those models instead of
fitting (fit s: the kept fit's wall time).
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_envelope import BATTERY, RUNAWAY_R2, SLOW, TEST_SECONDS, preset_config  # noqa

from piezo_narx_ros.command.stream import make_signal  # noqa: E402
from piezo_narx_ros.control.axes import AxesController  # noqa: E402
from piezo_narx_ros.ident.selection.experiment import PRESETS, run_experiment  # noqa: E402
from piezo_narx_ros.ident.model_io import load_model, save_model  # noqa: E402
from piezo_narx_ros.plant.axes import AxisPlants, make_axis_plants  # noqa: E402
from piezo_narx_ros.plant.signals import generate  # noqa: E402
from piezo_narx_ros.record import Record  # noqa: E402
from piezo_narx_ros.share import config_path  # noqa: E402

FS = 2000.0
STAGE = config_path('plant_2axis.yaml')
AXES = ('x', 'y')
# name -> (seconds, [(amplitude m, frequency Hz, phase rad) per axis], ratio target)
CONTROL_TASKS = {
    'sin 0.1 Hz': (12.0, [(20e-6, 0.1, 0.0), (15e-6, 0.13, 1.0)], 0.1),
    'sin 1 Hz': (6.0, [(15e-6, 1.0, 0.0), (10e-6, 0.7, 1.0)], 0.1),
    'sin 10 Hz': (3.0, [(15e-6, 10.0, 0.0), (10e-6, 7.0, 1.0)], 1 / 3),
}


def stage(seed: int):
    """Return the coupled two-axis cantilever at rest, sensor noise seed `seed`."""
    return make_axis_plants([], STAGE, fs=FS, seed=seed)


def identify(seed: int, preset: str, jobs: int, hnarx=None, seconds: float = 25.0):
    """
    One 2 x 2 model on `seconds` of the protocol on each axis: (model, fit s, label, result).

    hnarx: HysteresisNARX options over the preset's (e.g. {'na': 4, 'nb': 4}).
    """
    u = make_signal('protocol', FS, seconds, 100.0, seed=seed, n_axes=len(AXES))
    y, _ = stage(seed).run(u)
    cfg = preset_config(preset, seed, jobs, hnarx)
    t0 = time.perf_counter()
    rec = Record(u=u, y=y, fs=FS, source=f'protocol seed {seed}', inputs=AXES, outputs=AXES)
    result = run_experiment([rec], cfg)
    return result.best.model, time.perf_counter() - t0, result.best.spec.label, result


def free_run_battery(model, seed: int) -> dict:
    """{move: (R² per axis, RMSE per axis m)}: free run from rest against the stage's output."""
    out = {}
    for i, (name, (kind, amp, opt)) in enumerate(BATTERY.items()):
        opt = dict(opt)
        sig_seed = 7919 * (seed + 1) if opt.pop('seeded', False) else 0
        x = generate(kind, FS, TEST_SECONDS, amp, seed=sig_seed, **opt)
        u = np.column_stack([x, np.roll(x, x.size // 3)])
        y, _ = stage(1000 * seed + i).run(u)
        with np.errstate(all='ignore'):
            y_hat = np.asarray(model.simulate(u)).reshape(y.shape)
        err = y_hat - y
        rmse = np.sqrt(np.mean(err ** 2, axis=0))
        r2 = 1.0 - np.sum(err ** 2, axis=0) / np.sum((y - y.mean(axis=0)) ** 2, axis=0)
        out[name] = (np.where(np.isfinite(r2), r2, -np.inf),
                     np.where(np.isfinite(rmse), rmse, np.inf))
    return out


def references(task: str) -> np.ndarray:
    """Return the task's reference (N, 2) m."""
    seconds, axes, _ = CONTROL_TASKS[task]
    t = np.arange(int(seconds * FS)) / FS
    return np.column_stack([a * np.sin(2 * np.pi * f * t + ph) for a, f, ph in axes])


def control(model, seed: int) -> dict:
    """{task: {mode: RMS error per axis m, ...}}: the true deflection after the first second."""
    out = {}
    for task in CONTROL_TASKS:
        ref = references(task)
        res = {}
        for mode in ('linear', 'inverse'):
            ctl = AxesController(model, mode=mode)
            u = np.empty_like(ref)
            times = np.empty(len(ref))
            for k in range(len(ref)):
                t0 = time.perf_counter_ns()
                u[k] = ctl.on_reference(10**15 + k * 500_000, ref[k])[0][1]
                times[k] = time.perf_counter_ns() - t0
            plant = stage(seed + 77)
            chains, _ = AxisPlants.run(plant, u)        # before the sensors' noise
            y = plant.true_deflection(chains)
            e = y[int(FS):] - ref[int(FS):]
            res[mode] = np.sqrt(np.mean(e ** 2, axis=0))
            res[f'{mode}_unreachable'] = ctl.stats.unreachable
            res[f'{mode}_us'] = (float(np.percentile(times, 50)) / 1e3,
                                 float(np.percentile(times, 99)) / 1e3)
            res[f'{mode}_status'] = ctl.status()[:2]
        out[task] = res
    return out


def summarise(runs: list[dict]) -> dict:
    """Per move and axis: RMSE median / worst, R² median / worst over seeds, runaways."""
    rows = {}
    for name in BATTERY:
        r2 = np.array([r[name][0] for r in runs])        # (seeds, axes)
        rmse = np.array([r[name][1] for r in runs])
        rows[name] = {'rmse_median': np.median(rmse, axis=0), 'rmse_worst': rmse.max(axis=0),
                      'r2_median': np.median(r2, axis=0), 'r2_worst': r2.min(axis=0),
                      'runaways': int(np.sum(r2 < RUNAWAY_R2))}
    return rows


def print_free_run(rows: dict, n_seeds: int) -> bool:
    """Print the free-run table; returns whether every target is met."""
    print(f'\n  free run from rest, {n_seeds} seed(s): RMSE um median / worst, R² median, per '
          'axis x | y')
    for name, r in rows.items():
        cells = ' | '.join(f'{r["rmse_median"][a] * 1e6:7.3f} {r["rmse_worst"][a] * 1e6:7.3f} '
                           f'{r["r2_median"][a]:9.6f}' for a in range(len(AXES)))
        print(f'  {name:18s} {cells}{" (slow)" if name in SLOW else ""}')
    slow_med = np.max([rows[n]['rmse_median'] for n in SLOW], axis=0)
    slow_worst = np.max([rows[n]['rmse_worst'] for n in SLOW], axis=0)
    rest = np.max([r['rmse_worst'] for n, r in rows.items()
                   if n not in SLOW and n != 'multisine'], axis=0)
    ms = rows['multisine']['r2_median']
    runaways = sum(r['runaways'] for r in rows.values())
    ok = bool((slow_med <= 1e-6).all() and (slow_worst <= 2e-6).all() and (rest <= 2e-6).all()
              and (ms >= 0.9999).all() and runaways == 0)
    um = (lambda a: ' / '.join(f'{v * 1e6:.3f}' for v in a))
    print('  per axis x / y: slow moves median <= ' + um(slow_med) + ' um (target 1), worst '
          + um(slow_worst)
          + ' um (2); other moves worst ' + um(rest)
          + ' um (2); multisine R² median ' + ' / '.join(f'{v:.6f}' for v in ms)
          + f' (0.9999); runaways {runaways}: ' + ('MET' if ok else 'NOT MET'))
    return ok


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.strip().split('\n\n')[0])
    ap.add_argument('--preset', default='envelope', choices=sorted(PRESETS))
    ap.add_argument('--seeds', type=int, nargs='+', default=[0, 1, 2, 3, 4])
    ap.add_argument('--jobs', type=int, default=2)
    ap.add_argument('--no-control', action='store_true', help='free run only')
    ap.add_argument('--json', help='write every figure to this file')
    ap.add_argument('--hnarx', type=json.loads, default={}, metavar='JSON',
                    help="HysteresisNARX options over the preset's, e.g. '{\"na\": 4, \"nb\": 4}'")
    ap.add_argument('--seconds', type=float, default=25.0,
                    help='length of the identification record, s (default 25)')
    ap.add_argument('--keep', metavar='DIR',
                    help="write each seed's selected model (a model file) and fit time here")
    ap.add_argument('--kept', metavar='DIR',
                    help='take the models of an earlier --keep DIR instead of fitting')
    args = ap.parse_args(argv)
    runs, report = [], {'preset': args.preset, 'seeds': {}}
    for seed in args.seeds:
        if args.kept:
            kept = Path(args.kept) / f'seed{seed}'
            model = load_model(kept / 'model.json')
            fit = json.loads((kept / 'fit.json').read_text())
            fit_s, label, result = fit['fit_seconds'], fit['label'], None
        else:
            model, fit_s, label, result = identify(seed, args.preset, args.jobs, args.hnarx,
                                                   args.seconds)
        coupling = getattr(model, 'coupling_', None)
        extra = '' if coupling is None else \
            f', coupling {np.round(coupling, 4).tolist()} (stage: [[1, 0.05], [0.12, 1]])'
        print(f'seed {seed}: {label} ({type(model).__name__}, {model.n_in} x {model.n_out}), '
              f'fit {fit_s:.1f} s{extra}', flush=True)
        for c in result.candidates if result is not None else ():
            print(f'    candidate {c.spec.label:44s} worst-case free-run R² '
                  f'{c.free_run_r2():10.6f}{"  " + c.error[:90] if c.error else ""}')
        if args.keep:
            kept = Path(args.keep) / f'seed{seed}'
            save_model(model, kept / 'model.json')
            (kept / 'fit.json').write_text(json.dumps({'fit_seconds': fit_s, 'label': label}))
        run = free_run_battery(model, seed)
        runs.append(run)
        entry = {'label': label, 'fit_seconds': fit_s,
                 'free_run': {k: {'r2': list(v[0]), 'rmse_m': list(v[1])} for k, v in run.items()}}
        if not args.no_control:
            entry['control'] = ctl = control(model, seed)
            for task, c in ctl.items():
                ratio = c['inverse'] / c['linear']
                target = CONTROL_TASKS[task][2]
                print(f'  control {task:10s} RMS x / y (um): linear {c["linear"][0] * 1e6:.3f} / '
                      f'{c["linear"][1] * 1e6:.3f}, inverse {c["inverse"][0] * 1e6:.4f} / '
                      f'{c["inverse"][1] * 1e6:.4f} (ratio {ratio[0]:.3f} / {ratio[1]:.3f}, '
                      f'target <= {target:.3g}: {"met" if (ratio <= target).all() else "NOT met"};'
                      f' unreachable {c["inverse_unreachable"]}; compute p50/p99 '
                      f'{c["inverse_us"][0]:.0f}/{c["inverse_us"][1]:.0f} us; status '
                      f'{c["inverse_status"][1][:60]!r})', flush=True)
        report['seeds'][seed] = entry
    rows = summarise(runs)
    report['free_run_met'] = print_free_run(rows, len(runs))
    report['free_run'] = rows
    if not args.no_control:
        print('\n  control, median over seeds of inverse / linear per axis x | y:')
        for task in CONTROL_TASKS:
            ratios = np.array([report['seeds'][s]['control'][task]['inverse']
                               / report['seeds'][s]['control'][task]['linear']
                               for s in args.seeds])
            lin = np.array([report['seeds'][s]['control'][task]['linear'] for s in args.seeds])
            inv = np.array([report['seeds'][s]['control'][task]['inverse'] for s in args.seeds])
            print(f'  {task:10s} linear {np.median(lin, 0)[0] * 1e6:.3f} | '
                  f'{np.median(lin, 0)[1] * 1e6:.3f} um, inverse {np.median(inv, 0)[0] * 1e9:.1f}'
                  f' | {np.median(inv, 0)[1] * 1e9:.1f} nm, ratio median '
                  f'{np.median(ratios, 0)[0]:.4f} | {np.median(ratios, 0)[1]:.4f}, worst '
                  f'{ratios.max(0)[0]:.4f} | {ratios.max(0)[1]:.4f} (target <= '
                  f'{CONTROL_TASKS[task][2]:.3g})')
        fits = [report['seeds'][s]['fit_seconds'] for s in args.seeds]
        print(f'  fit {statistics.median(fits):.0f} s median (max {max(fits):.0f} s)')
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=1, default=_plain) + '\n')
    return 0


def _plain(x):
    return x.tolist() if isinstance(x, np.ndarray) else float(x)


if __name__ == '__main__':
    sys.exit(main())
