"""
The envelope family on the Fine Steering Mirror (3 x 3 real piezo actuators), measured.

Run: python bench/bench_fsm_envelope.py [--data ../shared/data/fsm] [--fit 1-4] [--score 5-6]
         [--order 28] [--half] [--steps 20000]

Fits HysteresisNARX on realizations --fit of every level (whole records, or with --half their
first period only, as `piezo-narx fit`'s 50/50 split gives the family), scores realizations
--score the benchmark's way (RMSE in µm after the first 100 samples, averaged over outputs and
records, per level) with the state set two ways (bench_fsm.py's `window` and `periodic`), and
times the fitted model's Stepper (p50 / p99 per step, µs) beside a one-axis envelope model's in
the same run. Prints the fit time and the load average. docs/mimo.md has the figures.
"""
import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_fsm import DEFAULT_DATA, LEVELS, PUBLISHED, load, parse_list, scores  # noqa: E402

from piezo_narx_ros.ident.hysteresis.model import HysteresisNARX  # noqa: E402


def step_times(stepper, inputs) -> np.ndarray:
    """Return the time of each step call, µs."""
    out = np.empty(len(inputs))
    clock = time.perf_counter_ns
    step = stepper.step
    for k, u in enumerate(inputs):
        t0 = clock()
        step(u)
        out[k] = (clock() - t0) * 1e-3
    return out


def main() -> None:
    """Fit, score and time (see the module docstring)."""
    p = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    p.add_argument('--data', type=Path, default=DEFAULT_DATA)
    p.add_argument('--fit', default='1-4')
    p.add_argument('--score', default='5-6')
    p.add_argument('--order', type=int, default=28)
    p.add_argument('--half', action='store_true')
    p.add_argument('--steps', type=int, default=20000)
    args = p.parse_args()
    fit_r, score_r = parse_list(args.fit), parse_list(args.score)
    train = [r for lv in LEVELS for r in load(args.data, lv, fit_r)]
    if args.half:
        train = [r.split(0.5)[0] for r in train]
    print(f'FSM envelope: fit on {fit_r}{" (first periods)" if args.half else ""}, scored on '
          f'{score_r}; order {args.order}; load {os.getloadavg()[0]:.1f} on '
          f'{os.cpu_count()} cores', flush=True)
    t0 = time.perf_counter()
    model = HysteresisNARX(mimo_order=args.order).fit([r.u for r in train],
                                                      [r.y for r in train], fs=train[0].fs)
    fit_s = time.perf_counter() - t0
    info = model.training_info_
    print(f'fit {fit_s:.1f} s (denominators {info["denominator_seconds"]:.1f} s), '
          f'{model.n_params} parameters, largest pole {info["max_pole"]:.4f}, '
          f'{len(info["local_centres"])} output model(s) at amplitudes '
          f'{", ".join(f"{c:.3f}" for c in info["local_centres"])}', flush=True)
    got = scores(model, {lv: load(args.data, lv, score_r) for lv in LEVELS})
    print('RMSE µm           100 mV   200 mV   300 mV')
    for how, per in got.items():
        if not per:
            continue
        print(f'{"envelope, " + how:<17}' + ''.join(
            f'{per[lv]:8.4f} ' if per.get(lv) is not None else '  diverged' for lv in LEVELS))
    for name, vals in PUBLISHED.items():
        print(f'{name[:17]:<17}' + ''.join(f'{v:8.4f} ' for v in vals))
    # Stepper: 3 x 3 beside a one-axis envelope model fitted on one column, same run.
    rng = np.random.default_rng(0)
    u3 = 0.3 * rng.standard_normal((args.steps, 3))
    one = HysteresisNARX(max_iter=2).fit(train[0].u[:4000, 0], train[0].y[:4000, 0],
                                         fs=train[0].fs)
    for label, stepper, inputs in (('3 x 3 envelope', model.stepper(), u3),
                                   ('1 x 1 envelope', one.stepper(), u3[:, 0].tolist())):
        step_times(stepper, inputs[:2000])          # compile and warm the caches
        t = step_times(stepper, inputs)
        print(f'Stepper {label}: p50 {np.percentile(t, 50):.2f} µs, p99 '
              f'{np.percentile(t, 99):.2f} µs, p99.9 {np.percentile(t, 99.9):.2f} µs')
    print(f'load {os.getloadavg()[0]:.1f}')


if __name__ == '__main__':
    main()
