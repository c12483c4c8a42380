"""
This project's NARX fitter against SysIdentPy's NARXNN on the same piezo-like data.

Both fit a 4/4-lag network with one hidden layer of 10 sigmoid units on 25,000 estimation samples
and are judged in free run (simulation) on the next 25,000 samples, initialised from the first
4 measured outputs. Prints fit time, free-run validation R² and the speed ratio.
Targets: this project >= 10x faster, R² >= 0.9999.

SysIdentPy settings are its defaults (Adam, lr 0.01, batch 100, 200 epochs, MSE) except that the
data are standardised with the estimation mean/std before it sees them: it does not scale inputs
itself, and with y ~ 1e-5 m next to u ~ 100 V its training does not move. Its lags follow its own
convention (x(k-1)..x(k-4), y(k-1)..y(k-4), Polynomial degree 1 = the raw regressors); ours are
u(k)..u(k-4), y(k-1)..y(k-4). Both use one torch thread.

Run: pip install -r bench/requirements.txt; python bench/bench_sysidentpy.py [--samples 50000]
[--epochs 200] [--repeats 1]. Data: bench_simulate.piezo_data (project plant when importable).
"""
import argparse
import os
import statistics
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from bench_simulate import piezo_data  # noqa: E402
from headline import headline  # noqa: E402

from piezo_narx_ros.ident.validation import metrics  # noqa: E402
from piezo_narx_ros.ident.narx.model import NARXNetwork  # noqa: E402

LAGS, HIDDEN = 4, 10


def fit_ours(u_est, y_est, u_val, y_val, seed):
    """(fit s, free-run validation R², one-step validation R²) of this project's NARXNetwork."""
    t0 = time.perf_counter()
    model = NARXNetwork(nu=LAGS, ny=LAGS, hidden=HIDDEN, seed=seed).fit(u_est, y_est)
    fit_s = time.perf_counter() - t0
    sim = model.simulate(u_val, y_val[:model.n0])
    pred = model.predict(u_val, y_val)
    return (fit_s, metrics.r2(y_val, sim, start=model.n0),
            metrics.r2(y_val, pred, start=model.n0))


def fit_sysidentpy(u_est, y_est, u_val, y_val, seed, epochs):
    """
    (fit s, free-run validation R², one-step validation R², free-run s) of SysIdentPy's NARXNN.

    The one-step R² shows whether its training worked at all; its free run was checked against a
    hand-written loop over its network (identical), so a poor free run is its training's result.
    """
    import torch
    from sysidentpy.basis_function import Polynomial
    from sysidentpy.neural_network import NARXNN
    from torch import nn

    n_regressors = 2 * LAGS

    class Net(nn.Module):

        def __init__(self):
            super().__init__()
            self.hidden = nn.Linear(n_regressors, HIDDEN)
            self.out = nn.Linear(HIDDEN, 1)

        def forward(self, xb):
            return self.out(torch.sigmoid(self.hidden(xb)))

    um, us, ym, ys = u_est.mean(), u_est.std(), y_est.mean(), y_est.std()
    model = NARXNN(ylag=LAGS, xlag=LAGS, basis_function=Polynomial(degree=1),
                   model_type='NARMAX', epochs=epochs, random_state=seed, net=Net())
    t0 = time.perf_counter()
    model.fit(X=((u_est - um) / us).reshape(-1, 1), y=((y_est - ym) / ys).reshape(-1, 1))
    fit_s = time.perf_counter() - t0
    x_val = ((u_val - um) / us).reshape(-1, 1)
    y_val_n = ((y_val - ym) / ys).reshape(-1, 1)
    t1 = time.perf_counter()
    sim_n = model.predict(X=x_val, y=y_val_n[:LAGS]).ravel()
    sim_s = time.perf_counter() - t1
    pred_n = model.predict(X=x_val, y=y_val_n, steps_ahead=1).ravel()
    sim = sim_n.astype(np.float64) * ys + ym
    pred = pred_n.astype(np.float64) * ys + ym
    return (fit_s, metrics.r2(y_val, sim, start=LAGS), metrics.r2(y_val, pred, start=LAGS),
            sim_s)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    ap.add_argument('--samples', type=int, default=50000)
    ap.add_argument('--epochs', type=int, default=200, help='SysIdentPy epochs (its default 200)')
    ap.add_argument('--repeats', type=int, default=1)
    ap.add_argument('--seed', type=int, default=0)
    args = ap.parse_args(argv)

    import torch
    torch.set_num_threads(1)
    try:
        import sysidentpy
    except ImportError:
        sys.exit('bench_sysidentpy: SysIdentPy is not installed; '
                 'pip install -r bench/requirements.txt')

    u, y, _, source = piezo_data(args.samples)
    half = u.size // 2
    u_est, y_est, u_val, y_val = u[:half], y[:half], u[half:], y[half:]
    print(f'data: {u.size} samples ({half} estimation + {u.size - half} validation) from {source}')
    print(f'SysIdentPy {sysidentpy.__version__}, numpy {np.__version__}, '
          f'torch {torch.__version__}; load average {os.getloadavg()[0]:.2f}')

    ours, theirs = [], []
    for r in range(args.repeats):   # interleaved, so both see the same machine load
        ours.append(fit_ours(u_est, y_est, u_val, y_val, args.seed + r))
        theirs.append(fit_sysidentpy(u_est, y_est, u_val, y_val, args.seed + r, args.epochs))
        print(f'run {r + 1}: ours fit {ours[-1][0]:.2f} s, free-run R2 {ours[-1][1]:.6f}, '
              f'one-step R2 {ours[-1][2]:.6f} | SysIdentPy fit {theirs[-1][0]:.2f} s, free-run R2 '
              f'{theirs[-1][1]:.6f}, one-step R2 {theirs[-1][2]:.6f} (its free run took '
              f'{theirs[-1][3]:.2f} s)')
    t_ours = statistics.median(o[0] for o in ours)
    t_theirs = statistics.median(t[0] for t in theirs)
    print(f'this project   : fit median {t_ours:.2f} s, free-run validation R2 median '
          f'{statistics.median(o[1] for o in ours):.6f}')
    print(f'SysIdentPy     : fit median {t_theirs:.2f} s ({args.epochs} epochs), free-run '
          f'validation R2 median {statistics.median(t[1] for t in theirs):.6f}')
    print(f'speed ratio (SysIdentPy fit / ours): {t_theirs / t_ours:.1f}x (target >= 10x)')
    headline(f'NARX(4,4,10) fit against SysIdentPy {sysidentpy.__version__} NARXNN '
             f'({args.epochs} epochs), {u.size:,} samples',
             f'ours {t_ours:.2f} s, R² {statistics.median(o[1] for o in ours):.6f}; SysIdentPy '
             f'{t_theirs:.2f} s, R² {statistics.median(t[1] for t in theirs):.6f}: '
             f'{t_theirs / t_ours:.1f}x', '>= 10x', 'identification.md')


if __name__ == '__main__':
    main()
