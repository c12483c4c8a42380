"""
Per-axis choice among the chain candidates that `bench_axes.py --keep DIR` kept (docs/mimo.md).

The experiment selects one 2 x 2 chain model on the worst case over both axes, so x's worst case
picks y's chain too. Here each axis takes the chain of the candidate whose own axis has the best
worst-case free-run R² (the blocks of CandidateResult.free_run_r2, that output only), the
coupling is refitted on the estimation half for the mixed chains (`refine_coupling`), and the
mix is scored as a candidate and run on bench_axes.py's battery beside the selected model. Two
pools: every chain candidate ('any') and those of the selected candidate's structure ('same':
only the network seed differs, so that both chains take the same input history). No fit.

    python bench/bench_axes.py --no-control --seconds 50 --keep /tmp/keep50
    python bench/bench_axes_peraxis.py /tmp/keep50 --seconds 50
"""
import argparse
import copy
import pickle
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_axes as B  # noqa: E402

from piezo_narx_ros.command.stream import make_signal  # noqa: E402
from piezo_narx_ros.ident.experiment import (CandidateResult, CandidateSpec,  # noqa: E402
                                             score_candidate, split_records, with_state_window)
from piezo_narx_ros.ident.hysteresis_chains import (HysteresisChains,  # noqa: E402
                                                    check_coupling, refine_coupling)
from piezo_narx_ros.record import Record  # noqa: E402


def axis_worst(c, i):
    """Return output i's worst-case free-run R² (CandidateResult.free_run_r2's blocks)."""
    sc = c.scores
    val = sc.get('validation', {})
    blocks = [sc.get('estimation', {}).get('simulation', {}), val.get('simulation', {})]
    blocks += [r['simulation'] for r in val.get('records', [])]
    out = [-np.inf if b['per_output'][i]['r2'] is None else b['per_output'][i]['r2']
           for b in blocks if b.get('per_output')]
    return min(out) if out else -np.inf


def mix(pool, est, val, cfg):
    """Return (model, scored CandidateResult, picks): each axis's best chain of `pool`, mixed."""
    picks = [max(pool, key=lambda c: axis_worst(c, i)) for i in range(len(B.AXES))]
    model = copy.deepcopy(picks[0].model)
    model.chains_ = [copy.deepcopy(p.model.chains_[i]) for i, p in enumerate(picks)]
    model.coupling_ = check_coupling(refine_coupling(model.chains_, [r.u for r in est],
                                                     [r.y for r in est], B.FS))
    spec = CandidateSpec('hysteresis_narx', nu=model.nu, ny=model.ny,
                         options=(('per_axis', tuple(p.spec.label for p in picks)),))
    return model, score_candidate(CandidateResult(spec=spec), model, est, val, cfg), picks


def ms(run):
    """Return the multisine's RMSE (nm) and R² per axis of a battery run, as text."""
    rmse, r2 = run['multisine'][1], run['multisine'][0]
    return (f'multisine {rmse[0] * 1e9:.0f} / {rmse[1] * 1e9:.0f} nm, R² {r2[0]:.6f} / '
            f'{r2[1]:.6f}')


def main(argv=None):
    """Compare the selected model and the per-axis mixes on every kept seed."""
    ap = argparse.ArgumentParser(description=__doc__.strip().split('\n\n')[0])
    ap.add_argument('keep', help="bench_axes.py --keep's folder")
    ap.add_argument('--seconds', type=float, default=25.0,
                    help='the identification record length the models were fitted on, s')
    ap.add_argument('--seeds', type=int, nargs='+', default=[0, 1, 2, 3, 4])
    args = ap.parse_args(argv)
    runs = {'selected': [], 'any': [], 'same': []}
    for seed in args.seeds:
        with open(Path(args.keep) / f'seed{seed}.pkl', 'rb') as fh:
            res = pickle.load(fh)
        cfg = res.config
        u = make_signal('protocol', B.FS, args.seconds, 100.0, seed=seed, n_axes=len(B.AXES))
        y, _ = B.stage(seed).run(u)
        rec = Record(u=u, y=y, fs=B.FS, source=f'protocol seed {seed}', inputs=B.AXES,
                     outputs=B.AXES)
        est, val = split_records(with_state_window([rec], cfg), cfg.split)
        chains = [c for c in res.candidates
                  if c.error is None and isinstance(c.model, HysteresisChains)]
        print(f'seed {seed}: selected {res.best.spec.label}, worst {res.best.free_run_r2():.7f}')
        for c in chains:
            print(f'    {c.spec.label:48s} worst {c.free_run_r2():.7f}, per axis '
                  f'{axis_worst(c, 0):.7f} / {axis_worst(c, 1):.7f}; '
                  f'{ms(B.free_run_battery(c.model, seed))}', flush=True)
        runs['selected'].append(B.free_run_battery(res.best.model, seed))
        print(f'  selected: {ms(runs["selected"][-1])}')
        same = [c for c in chains if (c.spec.hidden, c.spec.options)
                == (res.best.spec.hidden, res.best.spec.options)]
        for name, pool in (('any', chains), ('same', same)):
            model, scored, picks = mix(pool, est, val, cfg)
            runs[name].append(B.free_run_battery(model, seed))
            print(f'  per axis ({name}): x from {picks[0].spec.label}, y from '
                  f'{picks[1].spec.label}; M {np.round(model.coupling_, 4).tolist()}; worst '
                  f'{scored.free_run_r2():.7f} (per axis {axis_worst(scored, 0):.7f} / '
                  f'{axis_worst(scored, 1):.7f}); {ms(runs[name][-1])}', flush=True)
    for name, rs in runs.items():
        print(f'\n== {name}')
        B.print_free_run(B.summarise(rs), len(rs))
    return 0


if __name__ == '__main__':
    sys.exit(main())
