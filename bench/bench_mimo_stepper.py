"""
Per-sample cost of the Stepper with several axes (issue 20's target: p99 <= 10 µs for 3 x 3).

Run: python bench/bench_mimo_stepper.py [--steps 20000] [--hidden 10] [--lags 4]

Times Stepper.step one call at a time (time.perf_counter_ns around each call, as the estimator's
loop runs it) for the paper's network and ARX, 1 x 1 (float in and out) beside 3 x 3 ((3,) arrays
in and out), in the same run so their ratio holds on a busy machine. The weights are random (the
cost does not depend on their values); the 3 x 3 network has the regressor of nu = ny = --lags
over 3 inputs and 3 outputs. Prints p50 / p99 / p99.9 in µs and the load average.
"""
import argparse
import os
import time

import numpy as np

from piezo_narx_ros.ident.arx.model import ARXModel
from piezo_narx_ros.ident.narx.model import NARXNetwork


def narx(n_in, n_out, lags, hidden, rng):
    """Return a NARXNetwork with random weights (n_in inputs, n_out outputs)."""
    m = NARXNetwork(lags, lags, hidden)
    d = n_in * (lags + 1) + n_out * lags
    W1, b1 = 0.3 * rng.standard_normal((hidden, d)), 0.1 * rng.standard_normal(hidden)
    if n_in == n_out == 1:
        return m.set_weights(W1, b1, rng.standard_normal(hidden) * 0.1, 0.0,
                             [0.0, 50.0, 0.0, 1e-6])
    return m.set_weights(W1, b1, 0.1 * rng.standard_normal((n_out, hidden)), np.zeros(n_out),
                         (np.zeros(n_in), np.full(n_in, 50.0), np.zeros(n_out),
                          np.full(n_out, 1e-6)))


def arx(n_in, n_out, lags, rng):
    """Return a stable ARXModel with random input coefficients."""
    m = ARXModel(lags, lags)
    if n_in == n_out == 1:
        return m.set_coefficients(np.r_[-0.5, np.zeros(lags - 1)], rng.standard_normal(lags + 1))
    a = np.zeros((n_out, n_out, lags))
    a[np.arange(n_out), np.arange(n_out), 0] = -0.5
    return m.set_coefficients(a, 1e-7 * rng.standard_normal((n_out, n_in, lags + 1)),
                              np.zeros(n_out))


def time_steps(stepper, inputs) -> np.ndarray:
    """Return the time of each step call, ns."""
    out = np.empty(len(inputs), dtype=np.int64)
    clock = time.perf_counter_ns
    step = stepper.step
    for k, u in enumerate(inputs):
        t0 = clock()
        step(u)
        out[k] = clock() - t0
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    p.add_argument('--steps', type=int, default=20000)
    p.add_argument('--hidden', type=int, default=10)
    p.add_argument('--lags', type=int, default=4)
    args = p.parse_args()
    rng = np.random.default_rng(0)
    cases = {'NARX 1x1': narx(1, 1, args.lags, args.hidden, rng),
             'NARX 3x3': narx(3, 3, args.lags, args.hidden, rng),
             'ARX 1x1': arx(1, 1, args.lags, rng),
             'ARX 3x3': arx(3, 3, args.lags, rng)}
    print(f'{args.steps} steps each, lags {args.lags}, H {args.hidden}; load '
          f'{os.getloadavg()[0]:.2f} on {os.cpu_count()} cores')
    print(f'{"":<10}{"p50 µs":>9}{"p99 µs":>9}{"p99.9 µs":>10}')
    for name, model in cases.items():
        n_in = model.n_in
        u = 50.0 * rng.standard_normal((args.steps, n_in))
        inputs = [float(v) for v in u[:, 0]] if n_in == 1 else list(u)
        stepper = model.stepper()
        time_steps(stepper, inputs[:2000])            # compile and warm the caches
        t = time_steps(stepper, inputs) / 1e3
        print(f'{name:<10}{np.percentile(t, 50):9.2f}{np.percentile(t, 99):9.2f}'
              f'{np.percentile(t, 99.9):10.2f}')


if __name__ == '__main__':
    main()
