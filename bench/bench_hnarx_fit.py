"""
Wall time of one hysteresis-operator NARX fit (HysteresisNARX.fit), this tree against another.

The records are the identification protocol at 10 kHz from the project's simulator, 2 s (20,000
samples) and 10 s (100,000 samples), 16-bit sensor over 200 um, made as
`piezo-narx simulate --signal protocol --seconds S --fs 10000 --seed 1 --sensor-bits 16
--sensor-span 200e-6` makes them. Each is fitted with HysteresisNARX(hidden=10, seed=1) and
its default options, single-threaded BLAS (as the fit's workers run).

--against TREE runs the same fits with another checkout of the package (its directory first on
PYTHONPATH), e.g. main's version in a temporary worktree:
    git worktree add --detach /tmp/before main
    python bench/bench_hnarx_fit.py --against /tmp/before
Every fit runs in its own process, after a small warm-up fit there (numba's compiled kernels
load from its cache, or compile, before the clock starts); the trees' runs are interleaved so
that a load from other processes hits both. Printed per record size and tree: the median and
the range of the fit's wall time and CPU time over --repeats, the iterations, the training MSE
and whether the trees fitted the same parameter bits.

Run: python bench/bench_hnarx_fit.py [--against TREE] [--repeats 3] [--seconds 2 10]
Figures are only meaningful on a quiet machine; the CPU times are less sensitive to load.
"""
import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
FS = 10000.0

# One fit in a fresh interpreter: argv = record, options (JSON), where to save theta.
WORKER = r"""
import json, sys, time
import numpy as np
try:
    from piezo_narx_ros.ident.hysteresis.model import HysteresisNARX
except ImportError:   # a checkout from before ident/ was grouped by concern
    from piezo_narx_ros.ident.hysteresis import HysteresisNARX
z = np.load(sys.argv[1])
u, y, fs = z['u'], z['y'], float(z['fs'])
options = json.loads(sys.argv[2])
HysteresisNARX(**{**options, 'hidden': 2, 'n_plays': 3, 'max_iter': 2}).fit(u[:3000], y[:3000],
                                                                           fs=fs)
m = HysteresisNARX(seed=1, **options)
t0, c0 = time.perf_counter(), time.process_time()
m.fit(u, y, fs=fs)
wall, cpu = time.perf_counter() - t0, time.process_time() - c0
np.save(sys.argv[3], m.theta_)
info = m.training_info_
print(json.dumps({'wall': wall, 'cpu': cpu, 'iterations': info['iterations'],
                  'train_mse': info['train_mse'], 'stop': info['stop']}))
"""


def make_record(seconds, out):
    """Write the protocol record of `seconds` at 10 kHz (the simulate CLI) to out."""
    subprocess.run([sys.executable, '-m', 'piezo_narx_ros.cli.main', 'simulate', '--signal',
                    'protocol', '--seconds', str(seconds), '--fs', str(FS), '--seed', '1',
                    '--sensor-bits', '16', '--sensor-span', '200e-6', '--out', str(out)],
                   check=True, stdout=subprocess.DEVNULL, cwd=REPO)


def fit_once(tree, record, options, theta_out):
    """Run one fit with the package of `tree` in a fresh process; returns the worker's dict."""
    env = dict(os.environ, OPENBLAS_NUM_THREADS='1', OMP_NUM_THREADS='1', MKL_NUM_THREADS='1',
               PYTHONPATH=os.pathsep.join([str(tree)] + [p for p in [os.environ.get(
                   'PYTHONPATH')] if p]))
    done = subprocess.run([sys.executable, '-c', WORKER, str(record), json.dumps(options),
                           str(theta_out)], env=env, capture_output=True, text=True,
                          cwd=tempfile.gettempdir())
    if done.returncode:
        sys.exit(f'the fit with {tree} failed:\n{done.stderr}')
    return json.loads(done.stdout.strip().splitlines()[-1])


def main(argv=None):
    """Fit each record --repeats times with each tree and print the times."""
    import numpy as np
    p = argparse.ArgumentParser(description=__doc__.split('\n')[1])
    p.add_argument('--against', type=Path, help='another checkout of the repository')
    p.add_argument('--repeats', type=int, default=3)
    p.add_argument('--seconds', type=float, nargs='+', default=[2.0, 10.0])
    p.add_argument('--options', default='{}', help='HysteresisNARX options, JSON')
    args = p.parse_args(argv)
    options = json.loads(args.options)
    options.setdefault('hidden', 10)
    trees = {'this': REPO}
    if args.against is not None:
        if not (args.against / 'piezo_narx_ros' / 'ident').is_dir():
            sys.exit(f'--against {args.against}: no piezo_narx_ros package there')
        trees['against'] = args.against.resolve()
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        for seconds in args.seconds:
            record = tmp / f'protocol_{seconds:g}s.npz'
            make_record(seconds, record)
            runs = {name: [] for name in trees}
            for rep in range(args.repeats):
                for name, tree in trees.items():
                    runs[name].append(fit_once(tree, record, options, tmp / f'{name}.npy'))
            same = len(trees) > 1 and np.array_equal(np.load(tmp / 'this.npy'),
                                                     np.load(tmp / 'against.npy'))
            n = int(round(seconds * FS))
            print(f'{n} samples ({seconds:g} s at {FS:g} Hz), {args.repeats} runs each')
            for name, rs in runs.items():
                wall = [r['wall'] for r in rs]
                cpu = [r['cpu'] for r in rs]
                print(f'  {name:8s} {str(trees[name]):30s} wall median '
                      f'{statistics.median(wall):6.2f} s ({min(wall):.2f}-{max(wall):.2f}), '
                      f'cpu median '
                      f'{statistics.median(cpu):6.2f} s, {rs[-1]["iterations"]} iterations, '
                      f'train MSE {rs[-1]["train_mse"]:.6e}')
            if len(trees) > 1:
                ratio = (statistics.median(r['wall'] for r in runs['against'])
                         / statistics.median(r['wall'] for r in runs['this']))
                print(f'  speed-up (wall medians) {ratio:.2f}x; same parameter bits: {same}')


if __name__ == '__main__':
    main()
