"""
Is the free-run estimate trustworthy on every move a user commands? Presets side by side.

For each plant (the project's Bouc-Wen cantilever, config/plant.yaml, and the structurally
different Preisach variant, config/plant_preisach.yaml) and each seed s:

* identification record: 25 s of the identification protocol at 2 kHz (`generate('protocol')`,
  signal seed s), answered by the plant with sensor-noise seed s;
* `run_experiment` with each preset (`paper`, `envelope`; network seeds start at s), on that one
  record (50/50 split), as `piezo-narx fit --preset NAME` does, or the structure search
  (`search`, the default of `fit`: `run_search` with sampler seed s, its default trials and
  budget, the second half validating); the fit's wall time is recorded;
* the selected model's free run (`simulate(u, y[:n0])`) on the battery of the envelope issue: the
  plant starting at rest, 10 s each, noise seeds 1000*s + i: a fresh multisine +-100 V (phases
  seeded by s); sines at 0.1, 0.5 and 2 Hz with +-100 V and +-50 V; a 0.5 Hz +-100 V triangle; an
  APRBS (seeded by s); steps (0, 1, 0.5, -1, -0.5, 0, 1, -1) x 100 V held 1.25 s; a 0.1-50 Hz
  chirp.

Prints, per plant and preset: per-signal RMSE (um) median and worst over seeds, R² median and
worst, the number of runaways (free-run R² < 0.5) and the fit times; `--reference` adds today's
demo setup (paper preset identified on a 25 s multisine) for comparison. `--json FILE` writes
every number. Results: docs/envelope.md.

Run: python bench/bench_envelope.py [--seeds 0 1 2 3 4] [--plants default preisach]
     [--presets paper envelope search] [--committee K] [--reference] [--jobs 2] [--json out.json]
     [--hnarx '{"monotone": "no"}']
"""
import argparse
import json
import statistics
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

from bench_excitation import score   # {name: (R², RMSE nm)} of the free run from y[:n0]
from headline import headline
from piezo_narx_ros.ident.selection.experiment import PRESETS, ExperimentConfig, run_experiment
from piezo_narx_ros.plant import PiezoCantilever, generate, load_plant_params
from piezo_narx_ros.record import Record

FS = 2000.0
REPO = Path(__file__).resolve().parents[1]
PLANTS = {'default': REPO / 'config' / 'plant.yaml',
          'preisach': REPO / 'config' / 'plant_preisach.yaml'}
TEST_SECONDS = 10.0
# name -> (kind, amplitude V, options); 'seeded' kinds take the run seed for their random parts.
BATTERY = {
    'multisine': ('multisine', 100.0, {'seeded': True}),
    'sin 0.1 Hz 100 V': ('sine', 100.0, {'freq': 0.1}),
    'sin 0.5 Hz 100 V': ('sine', 100.0, {'freq': 0.5}),
    'sin 2 Hz 100 V': ('sine', 100.0, {'freq': 2.0}),
    'sin 0.1 Hz 50 V': ('sine', 50.0, {'freq': 0.1}),
    'sin 0.5 Hz 50 V': ('sine', 50.0, {'freq': 0.5}),
    'sin 2 Hz 50 V': ('sine', 50.0, {'freq': 2.0}),
    'tri 0.5 Hz 100 V': ('triangle', 100.0, {'freq': 0.5}),
    'aprbs': ('aprbs', 100.0, {'seeded': True}),
    'steps': ('steps', 100.0, {'levels': (0.0, 1.0, 0.5, -1.0, -0.5, 0.0, 1.0, -1.0)}),
    'chirp 0.1-50 Hz': ('chirp', 100.0, {'f0': 0.1, 'f1': 50.0}),
}
SLOW = ('sin 0.1 Hz 100 V', 'sin 0.5 Hz 100 V', 'sin 2 Hz 100 V', 'tri 0.5 Hz 100 V')
RUNAWAY_R2 = 0.5


def battery(params, seed):
    """{name: (u V, y measured m)}, plant at rest, noise seeds 1000*seed + i."""
    out = {}
    for i, (name, (kind, amp, opt)) in enumerate(BATTERY.items()):
        opt = dict(opt)
        signal_seed = 7919 * (seed + 1) if opt.pop('seeded', False) else 0
        u = generate(kind, FS, TEST_SECONDS, amp, seed=signal_seed, **opt)
        out[name] = (u, PiezoCantilever(params, FS, seed=1000 * seed + i).run(u).y)
    return out


def preset_config(preset, seed, jobs, hnarx=None):
    """Return the ExperimentConfig of a preset, HysteresisNARX options `hnarx` over its own."""
    settings = dict(PRESETS[preset])
    if hnarx:
        settings['hnarx'] = {**settings.get('hnarx', {}), **hnarx}
    return replace(ExperimentConfig(), **settings, seed=seed, jobs=jobs, progress=False)


def search(record, seed, jobs, committee=None, overrides=None):
    """
    Run the structure search on one record as `fit` does: (selected model, its label).

    overrides: SearchOptions fields over the defaults (e.g. {'tolerance': 0.0}).
    """
    from piezo_narx_ros.ident.selection.executor import make_executor
    from piezo_narx_ros.ident.selection.experiment import split_records
    from piezo_narx_ros.ident.selection.search import SearchOptions, run_search
    est, val = split_records([record], SearchOptions.split)
    with tempfile.TemporaryDirectory() as out, make_executor('local', jobs) as executor:
        options = SearchOptions(seed=seed, progress=False,
                                **({'committee': committee} if committee else {}),
                                **(overrides or {}))
        result = run_search(est, val, options, executor, out)
    return result.best.model, result.best.spec.label


def identify(params, seed, preset, jobs, signal='protocol', hnarx=None, committee=None,
             search_options=None):
    """
    Identify one preset on one 25 s record: (selected model, fit wall time s, label).

    preset: a PRESETS name or 'search'; hnarx: HysteresisNARX options over the preset's (e.g.
    {'monotone': 'no'}; not with 'search'); committee: the search's (None: its default);
    search_options: other SearchOptions fields over the search's defaults.
    """
    u = generate(signal, FS, 25.0, 100.0, seed=seed)
    y = PiezoCantilever(params, FS, seed=seed).run(u).y
    record = Record(u=u, y=y, fs=FS, source=f'{signal} seed {seed}')
    t0 = time.perf_counter()
    if preset == 'search':
        model, label = search(record, seed, jobs, committee, search_options)
        return model, time.perf_counter() - t0, label
    result = run_experiment([record], preset_config(preset, seed, jobs, hnarx))
    return result.best.model, time.perf_counter() - t0, result.best.spec.label


def summarise(runs):
    """Per-signal medians and worst cases over seeds of [{name: (R², RMSE nm)}]; RMSE in m."""
    rows = {}
    for name in BATTERY:
        r2 = [r[name][0] for r in runs]
        rmse = [1e-9 * r[name][1] for r in runs]
        rows[name] = {'r2_median': statistics.median(r2), 'r2_worst': min(r2),
                      'rmse_median': statistics.median(rmse), 'rmse_worst': max(rmse),
                      'runaways': sum(v < RUNAWAY_R2 for v in r2)}
    return rows


def print_table(title, rows, fit_times, labels):
    print(f'\n== {title}: fit {statistics.median(fit_times):.1f} s median '
          f'(max {max(fit_times):.1f} s); selected: {", ".join(labels)}')
    print(f'   {"signal":<18}{"RMSE um median":>16}{"worst":>10}{"R² median":>14}{"worst":>12}'
          f'{"runaways":>10}')
    for name, r in rows.items():
        print(f'   {name:<18}{1e6 * r["rmse_median"]:16.3f}{1e6 * r["rmse_worst"]:10.3f}'
              f'{r["r2_median"]:14.6f}{r["r2_worst"]:12.6f}{r["runaways"]:10d}')
    total = sum(r['runaways'] for r in rows.values())
    slow = max(rows[n]['rmse_worst'] for n in SLOW)
    slow_med = max(rows[n]['rmse_median'] for n in SLOW)
    rest = max(r['rmse_worst'] for n, r in rows.items() if n not in SLOW and n != 'multisine')
    print(f'   runaways {total} of {len(rows) * len(fit_times)} runs; slow full-range moves: '
          f'median <= {1e6 * slow_med:.3f} um, worst {1e6 * slow:.3f} um; other moves worst '
          f'{1e6 * rest:.3f} um; fresh multisine R² median {rows["multisine"]["r2_median"]:.6f}'
          f' (worst {rows["multisine"]["r2_worst"]:.6f})', flush=True)
    headline(f'envelope battery, {title}: runaways; slow full-range RMSE median / worst; other '
             'moves worst; fresh multisine R² worst',
             f'{total} of {len(rows) * len(fit_times)}; {1e6 * slow_med:.3f} / {1e6 * slow:.3f} '
             f'µm; {1e6 * rest:.3f} µm; {rows["multisine"]["r2_worst"]:.6f}',
             '0; <= 1 / 2 µm; <= 2 µm', 'envelope.md')


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    ap.add_argument('--seeds', type=int, nargs='+', default=[0, 1, 2, 3, 4])
    ap.add_argument('--plants', nargs='+', choices=tuple(PLANTS), default=list(PLANTS))
    ap.add_argument('--presets', nargs='+', choices=(*PRESETS, 'search'),
                    default=list(PRESETS))
    ap.add_argument('--reference', action='store_true',
                    help="also today's demo setup: paper preset identified on a multisine")
    ap.add_argument('--jobs', type=int, default=2)
    ap.add_argument('--json', help='write every figure to this file')
    ap.add_argument('--hnarx', type=json.loads, default={}, metavar='JSON',
                    help='HysteresisNARX options over the preset\'s, e.g. \'{"monotone": "no"}\'')
    ap.add_argument('--committee', type=int, default=None, metavar='K',
                    help="the search's committee size (default: SearchOptions')")
    ap.add_argument('--search-options', type=json.loads, default={}, metavar='JSON',
                    help='SearchOptions fields over the defaults, e.g. \'{"tolerance": 0}\'')
    args = ap.parse_args(argv)
    setups = [(p, 'protocol') for p in args.presets]
    if args.reference:
        setups.append(('paper', 'multisine'))
    print(f'identification: 25 s at 2 kHz per seed, seeds {args.seeds}; battery of '
          f'{len(BATTERY)} signals x {TEST_SECONDS:g} s from rest; runaway: free-run R² < '
          f'{RUNAWAY_R2}', flush=True)
    report = {}
    t_start = time.perf_counter()
    for plant in args.plants:
        params = load_plant_params(PLANTS[plant])
        for preset, signal in setups:
            runs, times, labels = [], [], []
            for seed in args.seeds:
                model, seconds, label = identify(params, seed, preset, args.jobs, signal,
                                                 args.hnarx, args.committee,
                                                 args.search_options)
                runs.append(score(model, battery(params, seed)))
                times.append(seconds)
                labels.append(label)
            rows = summarise(runs)
            title = f'{plant} plant, --preset {preset} on the {signal}'
            print_table(title, rows, times, labels)
            per_seed = [{k: list(v) for k, v in r.items()} for r in runs]
            report[title] = {'rows': rows, 'fit_seconds': times, 'selected': labels,
                             'per_seed_r2_rmse_nm': per_seed}
    print(f'\nbench wall time {time.perf_counter() - t_start:.0f} s')
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=1, default=float) + '\n')
    return 0


if __name__ == '__main__':
    sys.exit(main())
