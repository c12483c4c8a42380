"""
Wall time of the paper's full lag grid.

16 NARX networks (ny, nu in 1..4, H = 10) + 100 ARX (na, nb in 1..10), each scored in prediction
and simulation on estimation and validation data with the five correlation tests, on 50,000
piezo-like samples (25,000 + 25,000). Target <= 20 s on 2 cores.

Run: python bench/bench_grid.py [--samples 50000] [--jobs 2] [--repeats 1] [--compare-serial]
Data: bench_simulate.piezo_data (the project plant when importable, else its stand-in).
Figures are only meaningful on a quiet machine.
"""
import argparse
import os
import resource
import statistics
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from bench_simulate import piezo_data  # noqa: E402
from headline import headline  # noqa: E402

from piezo_narx_ros.record import Record  # noqa: E402
from piezo_narx_ros.ident.selection.experiment import (ExperimentConfig,  # noqa: E402
                                                       run_experiment)

FS = 2000.0


def _cpu_seconds():
    """User + system CPU time of this process and its finished children, s."""
    own = resource.getrusage(resource.RUSAGE_SELF)
    kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


def run_grid(record, jobs):
    """(wall seconds, CPU seconds, ExperimentResult) of the default grid on `jobs` workers."""
    c0, t0 = _cpu_seconds(), time.perf_counter()
    result = run_experiment([record], ExperimentConfig(jobs=jobs, progress=False))
    return time.perf_counter() - t0, _cpu_seconds() - c0, result


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    ap.add_argument('--samples', type=int, default=50000)
    ap.add_argument('--jobs', type=int, default=2)
    ap.add_argument('--repeats', type=int, default=1)
    ap.add_argument('--compare-serial', action='store_true',
                    help='also time jobs=1, interleaved with the parallel runs')
    args = ap.parse_args(argv)

    u, y, _, source = piezo_data(args.samples)
    record = Record(u=u, y=y, fs=FS, source=source)
    print(f'data: {args.samples} samples at {FS:g} Hz from {source}')
    print(f'machine: {os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.2f}')

    walls, cpus, serial = [], [], []
    result = None
    for _ in range(args.repeats):
        wall, cpu, result = run_grid(record, args.jobs)
        walls.append(wall)
        cpus.append(cpu)
        if args.compare_serial:
            serial.append(run_grid(record, 1)[0])
    narx = [c for c in result.candidates if c.spec.kind == 'narx']
    arx = [c for c in result.candidates if c.spec.kind == 'arx']
    best = result.best
    print(f'candidates: {len(narx)} NARX + {len(arx)} ARX')
    print(f'grid wall time, jobs={args.jobs}: median {statistics.median(walls):.2f} s over '
          f'{len(walls)} run(s) (target <= 20 s)')
    headline(f'paper grid (16 NARX + 100 ARX + final fit), {args.samples:,} samples, '
             f'{args.jobs} workers', f'{statistics.median(walls):.2f} s wall (median of '
             f'{len(walls)})', '<= 20 s', 'identification.md')
    # CPU time is what a busy machine cannot inflate much: wall on an idle 2-core box ~ CPU / 2.
    print(f'CPU time (parent + workers): median {statistics.median(cpus):.2f} s, i.e. '
          f'{statistics.median(cpus) / args.jobs:.2f} s per worker if the cores were free')
    if serial:
        print(f'grid wall time, jobs=1: median {statistics.median(serial):.2f} s; '
              f'speed-up {statistics.median(serial) / statistics.median(walls):.2f}x')
    print(f'sum of NARX fit times {sum(c.fit_seconds for c in narx):.2f} s '
          f'(median {statistics.median(c.fit_seconds for c in narx):.2f} s per network); '
          f'sum of ARX fit times {sum(c.fit_seconds for c in arx):.2f} s')
    sims = sorted(((c.r2(), c.spec.label) for c in narx), reverse=True)
    print(f'best NARX validation simulation R2: {sims[0][0]:.6f} ({sims[0][1]}); '
          f'best ARX: {max(c.r2() for c in arx):.6f}')
    print(f'selected: {best.spec.label}, validation simulation R2 {best.r2():.6f}, '
          f'validated={result.validated} ({sum(c.validated for c in result.candidates)} '
          f'candidates pass the correlation tests)')


if __name__ == '__main__':
    main()
