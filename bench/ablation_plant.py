"""Which element of the simulated plant keeps NARX 4/4/10 from passing Billings' tests?

One PlantParams field (or a small named group) is changed at a time from config/plant.yaml; for
each variant the paper's experiment is rerun on 25 s of the default identification multisine
(2 kHz, 100 V peak, fit on the first half, free run on the second) with the project's own tools
and defaults: NARXNetwork(4, 4, 10) and ARXModel(4, 4), an AR noise model fitted on the
estimation half (experiment.fit_noise_models) and the five tests on the whitened free-run
residuals of the validation half under the chance-rate rule (experiment.residual_correlations).

Printed per fit: free-run error against the noise-free sensor output (nm RMS, and its RMS in the
lowest / highest quartile of |u|), std of the whitened validation residuals (nm), free-run R²
against the measurement, max |φ| / band of the five tests (x = test fails) and the verdict.

    python bench/ablation_plant.py                       # every variant, record seed 0, seeds 0 1
    python bench/ablation_plant.py --variants default amp_off --record-seeds 0 1 2
    python bench/ablation_plant.py --variants default --arx-all   # also ARX 1..10 x 1..10

Serial, one torch thread (the trainer's default); about 2-4 s per network fit.
"""
from __future__ import annotations

import argparse
import sys
import time

import numpy as np

from piezo_narx_ros.ident.arx import ARXModel
from piezo_narx_ros.ident.correlation import TEST_NAMES
from piezo_narx_ros.ident.data import Record
from piezo_narx_ros.ident.experiment import (evaluate_model, fit_noise_models, outputs_by_record,
                                             residual_correlations)
from piezo_narx_ros.ident.narx import NARXNetwork
from piezo_narx_ros.plant import PiezoCantilever, generate, load_plant_params

FS = 2000.0          # Hz
SECONDS = 25.0       # s, the paper's record length
AMPLITUDE = 100.0    # V peak, the default identification record
OFF_HZ = 1.0e6       # Hz: a first-order lag this fast is "off" at 2 kHz (tau = 0.16 us)

#: name -> PlantParams changes. One element at a time, then a few combinations.
VARIANTS = {
    'default': {},
    'noise_free': {'noise_std': 0.0, 'quantisation': 0.0},
    'quant_off': {'quantisation': 0.0},
    'amp_10k': {'amp_bandwidth': 1.0e4},
    'amp_30k': {'amp_bandwidth': 3.0e4},
    'amp_off': {'amp_bandwidth': OFF_HZ},
    'amp_1k': {'amp_bandwidth': 1.0e3},
    'sensor_20k': {'sensor_bandwidth': 2.0e4},
    'sensor_off': {'sensor_bandwidth': OFF_HZ},
    'sensor_2k': {'sensor_bandwidth': 2.0e3},
    'creep_off': {'creep_gains': (0.0, 0.0, 0.0, 0.0)},
    'slew_off': {'slew_rate': float('inf')},
    'substeps_4': {'substeps': 4},
    'substeps_64': {'substeps': 64},
    'damping_0.05': {'mode_damping': 0.05},
    'damping_0.1': {'mode_damping': 0.1},
    'damping_0.01': {'mode_damping': 0.01},
    'mode_400': {'mode_frequency': 400.0},
    'mode_20k': {'mode_frequency': 2.0e4},   # quasi-static beam (no mode below Nyquist)
    'loop_A0.15': {'A': 0.15},              # narrower loop
    'loop_A0': {'A': 0.0},                  # no hysteresis: a linear plant (control)
    'bw_Bx2': {'B': 0.022, 'gamma': 0.008},  # loop saturates at half the voltage
    'bw_Bx0.5': {'B': 0.0055, 'gamma': 0.002},
    'electronics_off': {'amp_bandwidth': OFF_HZ, 'sensor_bandwidth': OFF_HZ,
                        'slew_rate': float('inf'), 'quantisation': 0.0},
    'linear_static': {'A': 0.0, 'mode_frequency': 2.0e4},
}


def make_records(params, record_seed: int) -> tuple[Record, Record]:
    """(estimation, validation) halves of the default 25 s multisine record on `params`.

    y_true is the noise-free sensor output (same command, no noise, no quantisation): the output
    a perfect model of the measured signal would give.
    """
    u = generate('multisine', FS, SECONDS, AMPLITUDE, seed=record_seed)
    y = PiezoCantilever(params, FS, seed=record_seed).run(u).y
    clean = PiezoCantilever(params.replace(noise_std=0.0, quantisation=0.0), FS,
                            seed=record_seed).run(u).y
    return Record(u=u, y=y, fs=FS, source='plant', y_true=clean).split(0.5)


def judge(model, est: Record, val: Record) -> dict:
    """Scores, whitened free-run test values and model error of a fitted model (SI units)."""
    noise = fit_noise_models(model, [est])
    out = evaluate_model(model, [val], noise_models=noise)
    parts = outputs_by_record(model, [val])
    corr = residual_correlations(parts, 'simulation', 20, 0.05, noise['simulation'])
    n0 = model.n0
    sim = parts[0]['simulation']
    err = val.y_true[n0:] - sim
    au = np.abs(val.u[n0:])
    lo, hi = np.quantile(au, [0.25, 0.75])
    ratio = {}
    for name in TEST_NAMES:
        t = corr.tests[name]
        tested = t.lags != 0
        ratio[name] = (float(np.max(np.abs(t.values[tested]))) / corr.band, t.passed)
    nm = noise['simulation']
    innov = nm.whiten(val.y[n0:] - sim) if nm is not None and nm.order else val.y[n0:] - sim
    return {'r2': out['simulation']['r2'], 'err': float(np.sqrt(np.mean(err ** 2))),
            'err_lo': float(np.sqrt(np.mean(err[au <= lo] ** 2))),
            'err_hi': float(np.sqrt(np.mean(err[au >= hi] ** 2))),
            'innov': float(np.std(innov)), 'order': 0 if nm is None else nm.order,
            'tests': ratio, 'passed': bool(out['tests']['simulation']['passed'])}


def row(variant, rseed, label, res, seconds) -> str:
    tests = ' '.join(f'{v:5.1f}{" " if ok else "x"}' for v, ok in res['tests'].values())
    return (f'{variant:16s} {rseed:2d} {label:12s} {res["err"] * 1e9:7.1f} '
            f'{res["err_lo"] * 1e9:6.1f} {res["err_hi"] * 1e9:6.1f} {res["innov"] * 1e9:6.1f} '
            f'{res["r2"]:.6f}  {tests}  {"PASS" if res["passed"] else "fail"} {seconds:5.1f}s')


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--variants', nargs='+', default=list(VARIANTS),
                    help=f'variants to run (default all): {", ".join(VARIANTS)}')
    ap.add_argument('--record-seeds', nargs='+', type=int, default=[0])
    ap.add_argument('--train-seeds', nargs='+', type=int, default=[0, 1])
    ap.add_argument('--hidden', type=int, default=10)
    ap.add_argument('--lags', type=int, default=4, help='NARX nu = ny')
    ap.add_argument('--no-arx', action='store_true', help='skip ARX 4/4')
    ap.add_argument('--arx-all', action='store_true',
                    help='also ARX 1..10 x 1..10: print how many pass and the smallest max φu²\'ε²')
    ap.add_argument('--set', nargs='*', default=[], metavar='FIELD=VALUE',
                    help='extra PlantParams changes applied to every variant (floats)')
    args = ap.parse_args(argv)
    unknown = [v for v in args.variants if v not in VARIANTS]
    if unknown:
        print(f'ablation_plant: unknown variant {unknown[0]!r}', file=sys.stderr)
        return 2
    extra = {}
    for item in args.set:
        key, _, value = item.partition('=')
        extra[key] = int(value) if key == 'substeps' else float(value)
    base = load_plant_params()
    print('max |phi|/band over lags 1..20 of the whitened free-run residuals; x = test fails')
    print(f'{"variant":16s} rs {"model":12s} {"err nm":>7s} {"|u|lo":>6s} {"|u|hi":>6s} '
          f'{"innov":>6s} {"R2 sim":8s}  {"ee":>5s}  {"ue":>5s}  {"u2e":>5s}  {"u2e2":>5s}  '
          f'{"e(eu)":>5s}')
    for variant in args.variants:
        params = base.replace(**{**VARIANTS[variant], **extra})
        for rseed in args.record_seeds:
            est, val = make_records(params, rseed)
            for tseed in args.train_seeds:
                t0 = time.perf_counter()
                model = NARXNetwork(args.lags, args.lags, args.hidden, seed=tseed)
                model.fit(est.u, est.y, fs=FS)
                label = f'NARX{args.lags}/{args.hidden} s{tseed}'
                print(row(variant, rseed, label, judge(model, est, val),
                          time.perf_counter() - t0), flush=True)
            if not args.no_arx:
                t0 = time.perf_counter()
                arx = ARXModel(4, 4).fit(est.u, est.y, fs=FS)
                print(row(variant, rseed, 'ARX 4/4', judge(arx, est, val),
                          time.perf_counter() - t0), flush=True)
            if args.arx_all:
                passed, worst = 0, np.inf
                for na in range(1, 11):
                    for nb in range(1, 11):
                        res = judge(ARXModel(na, nb).fit(est.u, est.y, fs=FS), est, val)
                        passed += res['passed']
                        worst = min(worst, res['tests']['phi_u2e2'][0])
                print(f'{variant:16s} {rseed:2d} ARX 1..10 x 1..10: {passed}/100 pass, '
                      f'smallest max phi_u2e2/band {worst:.1f}', flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())
