"""
Selection by the networks' agreement on moves nobody recorded: measured, not in a preset.

For each envelope fit, every network candidate runs from rest on three probes over the
estimation input's span (a 0.1-10 Hz multisine, a 0.5 Hz triangle, the battery's steps, 10 s
each at 90 % of the span). Its disagreement is the RMS distance of its free run from the median
of the family's other networks, averaged over the probes. The rule: among the family's networks
whose worst validation error (1 - R²) is within K times the best candidate's, the one that
disagrees least. Prints, per cell, the test error of the selection on main and of the rule for
each K, then the sums.

Cells: `--keep` directories of bench_real.py (est_*, val_* and test *_rig.npz records; the fit
reruns in process, as `fit EST --validate VAL --preset envelope`; test records scored as
bench_real: state from 0.5 s, 2 s over a fade-out, 0.1 s on the wideband), or `--battery`
(bench_envelope.py's protocol fits and battery, both plants). Results: docs/real.md, "Four more
tries, none kept".

Run: python bench/bench_committee.py CELL_DIR [CELL_DIR ...] [--k 2 3 5] [--json out.json]
     python bench/bench_committee.py --battery [--seeds 0 1 2 3 4] [--k 3]
"""
import argparse
import json
import math
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_envelope import BATTERY, FS, PLANTS, battery, preset_config  # noqa: E402
from bench_excitation import score  # noqa: E402

from piezo_narx_ros.ident.state import estimate  # noqa: E402
from piezo_narx_ros.ident.data.loaders import load_record  # noqa: E402
from piezo_narx_ros.ident.selection.experiment import (PRESETS, ExperimentConfig,  # noqa: E402
                                                       run_experiment)
from piezo_narx_ros.plant import PiezoCantilever, generate, load_plant_params  # noqa: E402
from piezo_narx_ros.record import Record  # noqa: E402

STEPS = BATTERY['steps'][2]['levels']   # the battery's steps, as fractions of the span


def probes(lo, hi, fs):
    """Return the three probe commands (V) over 90 % of [lo, hi] V at fs Hz, 10 s each."""
    centre, amp = 0.5 * (lo + hi), 0.45 * (hi - lo)
    return [generate('multisine', fs, 10.0, amp, offset=centre, seed=11, f_max=10.0),
            generate('triangle', fs, 10.0, amp, offset=centre, freq=0.5),
            generate('steps', fs, 10.0, amp, offset=centre, levels=STEPS)]


def is_network(candidate) -> bool:
    """Return True for the envelope family's networks (the committee), not ARX or NARX."""
    return candidate.spec.label.startswith('HNARX')


def disagreements(result, commands) -> dict:
    """{candidate index: mean RMS distance (m) from the other networks' median} over commands."""
    sims = {}
    for i, c in enumerate(result.candidates):
        if c.model is not None and c.error is None and is_network(c):
            with np.errstate(all='ignore'):
                sims[i] = [np.asarray(c.model.simulate(u)).reshape(-1) for u in commands]
    out = {}
    for i, runs in sims.items():
        dist = []
        for k, run in enumerate(runs):
            median = np.median([sims[j][k] for j in sims if j != i], axis=0)
            dist.append(math.sqrt(float(np.mean((run - median) ** 2))))
        out[i] = float(np.mean(dist))
    return out


def pick(result, disagreement: dict, k: float) -> int:
    """Return the rule's candidate index (the selection on main where none is eligible)."""
    best = 1.0 - max(c.free_run_r2() for c in result.candidates)
    eligible = [i for i in disagreement
                if 1.0 - result.candidates[i].free_run_r2() <= k * best]
    return min(eligible, key=disagreement.get) if eligible else result.selected


def window_record(path, cell_name):
    """Return a kept test record's (u V, y m, state window samples), as bench_real scores it."""
    with np.load(path, allow_pickle=False) as z:
        meta = json.loads(str(z['meta']))
        u, y, fs = z['u'].reshape(-1), z['y'].reshape(-1), float(z['fs'])
    seconds = 2.0 if meta.get('preamble') else (0.1 if 'wideband' in cell_name else 0.5)
    return u, y, int(round(seconds * fs))


def record_error(model, u, y, n) -> float:
    """RMSE (m) of a free run after its state is set from the first n samples of u, y."""
    with np.errstate(all='ignore'):
        sim = np.asarray(model.simulate(u, state=estimate.estimate_state(model, u[:n], y[:n])))
    return math.sqrt(float(np.mean((y[n:] - sim.reshape(-1)[n:]) ** 2)))


def kept_cell(cell: Path, ks, jobs):
    """Return (selection on main, {K: rule}): summed test RMSE (m) of a bench_real cell."""
    est = [load_record(p) for p in sorted(cell.glob('est_*_rig.npz'))]
    val = [load_record(p) for p in sorted(cell.glob('val_*_rig.npz'))]
    cfg = replace(ExperimentConfig(), **PRESETS['envelope'], jobs=jobs, progress=False)
    result = run_experiment(est, cfg, validation=val)
    lo = min(float(np.min(r.u)) for r in est)
    hi = max(float(np.max(r.u)) for r in est)
    dis = disagreements(result, probes(lo, hi, est[0].fs))
    tests = [window_record(p, cell.name) for p in sorted(cell.glob('*_rig.npz'))
             if not p.name.startswith(('est_', 'val_'))]
    totals = {}   # candidate index -> summed RMSE (several K often pick the same network)

    def total(i):
        if i not in totals:
            totals[i] = sum(record_error(result.candidates[i].model, *t) for t in tests)
        return totals[i]
    return total(result.selected), {k: total(pick(result, dis, k)) for k in ks}


def battery_cell(plant, seed, ks, jobs):
    """Return the same for a protocol fit of bench_envelope.py: battery RMSE (m) per move."""
    params = load_plant_params(PLANTS[plant])
    u = generate('protocol', FS, 25.0, 100.0, seed=seed)
    y = PiezoCantilever(params, FS, seed=seed).run(u).y
    result = run_experiment([Record(u=u, y=y, fs=FS, source=f'protocol seed {seed}')],
                            preset_config('envelope', seed, jobs))
    dis = disagreements(result, probes(float(u.min()), float(u.max()), FS))
    moves = battery(params, seed)

    def per_move(i):
        return {name: 1e-9 * v[1] for name, v in score(result.candidates[i].model, moves).items()}
    return per_move(result.selected), {k: per_move(pick(result, dis, k)) for k in ks}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    ap.add_argument('cells', nargs='*', type=Path, help='bench_real.py --keep cell directories')
    ap.add_argument('--battery', action='store_true')
    ap.add_argument('--seeds', type=int, nargs='+', default=[0, 1, 2, 3, 4])
    ap.add_argument('--k', type=float, nargs='+', default=[2.0, 3.0, 5.0])
    ap.add_argument('--jobs', type=int, default=2)
    ap.add_argument('--json', help='write every figure to this file')
    args = ap.parse_args(argv)
    if not args.cells and not args.battery:
        ap.error('give bench_real --keep cell directories, or --battery')
    out = {}
    for cell in args.cells:
        main_sum, rule = kept_cell(cell, args.k, args.jobs)
        out[cell.name] = {'main': main_sum, 'rule': rule}
        print(f'{cell.name:24s} main {1e6 * main_sum:8.3f} um  '
              + '  '.join(f'K {k:g}: {1e6 * v:8.3f}' for k, v in rule.items()), flush=True)
    if args.cells:
        print('sum' + ' ' * 22 + f'main {1e6 * sum(v["main"] for v in out.values()):8.3f} um  '
              + '  '.join(f'K {k:g}: {1e6 * sum(v["rule"][k] for v in out.values()):8.3f}'
                          for k in args.k))
    if args.battery:
        for plant in PLANTS:
            runs = [battery_cell(plant, s, args.k, args.jobs) for s in args.seeds]
            out[f'battery {plant}'] = runs
            for label, per in [('main', [r[0] for r in runs])] + [
                    (f'K {k:g}', [r[1][k] for r in runs]) for k in args.k]:
                med = sum(float(np.median([p[n] for p in per])) for n in per[0])
                worst = sum(max(p[n] for p in per) for n in per[0])
                print(f'battery {plant:9s} {label:6s} medians summed {1e6 * med:.3f} um, '
                      f'worst summed {1e6 * worst:.3f} um', flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1))


if __name__ == '__main__':
    main()
