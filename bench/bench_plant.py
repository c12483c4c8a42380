"""
Speed of the simulated cantilever: real-time factor of run() and cost of one step() call.

    python bench/bench_plant.py [--seconds 25] [--repeats 7]

Prints medians over repeats (the numba kernel is compiled/loaded from cache before timing). The
target is >= 100x real time for run() at 2 kHz on one core.
"""
import argparse
import os
import time

os.environ.setdefault('NUMBA_NUM_THREADS', '1')

import numpy as np  # noqa: E402

from piezo_narx_ros.plant import PiezoCantilever, generate, load_plant_params  # noqa: E402
from headline import headline  # noqa: E402


def main():
    ap = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    ap.add_argument('--seconds', type=float, default=25.0, help='simulated duration per run, s')
    ap.add_argument('--fs', type=float, default=2000.0, help='sample rate, Hz')
    ap.add_argument('--repeats', type=int, default=7)
    ap.add_argument('--steps', type=int, default=20000, help='step() calls per repeat')
    args = ap.parse_args()

    params = load_plant_params()
    u = generate('multisine', args.fs, args.seconds, 100.0, seed=0)
    plant = PiezoCantilever(params, args.fs, seed=0)
    plant.run(u[:10])
    plant.step(0.0)  # compile / load both call paths before timing

    run_s = []
    for _ in range(args.repeats):
        plant.reset()
        t0 = time.perf_counter()
        plant.run(u)
        run_s.append(time.perf_counter() - t0)
    step_s = []
    for _ in range(args.repeats):
        plant.reset()
        t0 = time.perf_counter()
        for v in u[:args.steps]:
            plant.step(v)
        step_s.append((time.perf_counter() - t0) / args.steps)

    run_med = float(np.median(run_s))
    step_med = float(np.median(step_s))
    period = 1.0 / args.fs
    print(f'plant: {params.substeps} sub-steps/sample, '
          f'{len(params.creep_gains) + 3} linear states')
    print(f'run():  {u.size} samples ({args.seconds:g} s at {args.fs:g} Hz) in '
          f'{1e3 * run_med:.1f} ms (median of {args.repeats}, min {1e3 * min(run_s):.1f} ms) -> '
          f'{args.seconds / run_med:.0f}x real time, {1e9 * run_med / u.size:.0f} ns/sample')
    print(f'step(): {1e6 * step_med:.2f} us/call (median of {args.repeats} x {args.steps}) -> '
          f'{period / step_med:.0f}x real time; run() is '
          f'{step_med / (run_med / u.size):.0f}x faster per sample')
    headline(f'plant run() / step() at {args.fs:g} Hz', f'{args.seconds / run_med:.0f}x / '
             f'{period / step_med:.0f}x real time', '>= 100x')


if __name__ == '__main__':
    main()
