"""
Speed of the identification core: fit time, free-run throughput, Stepper.step latency, grid time.

Both families: the paper's NARX network and the hysteresis-operator NARX of --preset envelope
(fitted on 25,000 samples of the identification protocol).

Run: python bench/bench_simulate.py [--quick]
Prints medians; the figures are only meaningful on a quiet machine (the fit uses one core).

Data: the project's piezo plant (piezo_narx_ros.plant) when it is importable, otherwise a small
stand-in with the same ingredients (Bouc-Wen hysteresis, creep, lightly damped 765 Hz mode), both
driven by a multisine at 2 kHz; 25,000 estimation + 25,000 validation samples.
"""
import argparse
import os
import statistics
import sys
import time

import numpy as np
from scipy import signal

from headline import headline

from piezo_narx_ros.ident.arx.model import ARXModel
from piezo_narx_ros.ident.validation.metrics import r2
from piezo_narx_ros.ident.narx.model import NARXNetwork

FS = 2000.0


def multisine(n, fs, f_lo, f_hi, n_lines, seed):
    rng = np.random.default_rng(seed)
    t = np.arange(n) / fs
    f = np.linspace(f_lo, f_hi, n_lines)
    x = np.sin(2 * np.pi * f[None, :] * t[:, None] + rng.uniform(0, 2 * np.pi, n_lines)).sum(1)
    return x / np.abs(x).max()


def stand_in_plant(u, fs=FS):
    """Bouc-Wen (Rakotondrabe form) + creep + 765 Hz mode, noiseless; u in V, returns y in m."""
    d_p, A, B, gamma = 5.2e-7, 0.35, 0.008, 0.004
    du = np.diff(u, prepend=0.0)
    h = np.empty(u.size)
    hk = 0.0
    for k in range(u.size):
        hk += A * d_p * du[k] - B * abs(du[k]) * hk - gamma * du[k] * abs(hk)
        h[k] = hk
    w = d_p * u - h
    z = w.copy()
    for gain, tau in ((0.008, 0.1), (0.008, 1.0), (0.008, 10.0)):
        a = np.exp(-1.0 / (fs * tau))
        z += gain * signal.lfilter([1 - a], [1, -a], w)
    wn, zeta = 2 * np.pi * 765.0, 0.02
    bd, ad, _ = signal.cont2discrete(([wn ** 2], [1, 2 * zeta * wn, wn ** 2]), 1 / fs,
                                     method='zoh')
    return signal.lfilter(np.squeeze(bd), ad, z)


def piezo_data(n=50000, seed=0):
    """(u V, y m measured, y_true m, description)."""
    u_cmd = 100.0 * multisine(n, FS, 1.0, 100.0, 50, seed)
    try:
        from piezo_narx_ros.plant import load_plant_params, PiezoCantilever  # noqa: F401
        run = PiezoCantilever(load_plant_params(), fs=FS, seed=seed).run(u_cmd)
        return run.u_applied, run.y, run.y_true, 'piezo_narx_ros.plant (config/plant.yaml)'
    except Exception as exc:  # plant not landed yet, or its API differs: use the stand-in
        y = stand_in_plant(u_cmd)
        noisy = y + 1e-7 * np.random.default_rng(seed + 1).standard_normal(n)
        return u_cmd, noisy, y, ('stand-in plant (noise 1e-7 m; project plant unavailable: '
                                 f'{type(exc).__name__})')


def step_latency(model, u, n_calls, name='paper network'):
    """Print p50/p99/max of model.stepper().step(), µs, over n_calls calls."""
    step = model.stepper().step
    for x in u[:1000]:
        step(x)
    samples = np.empty(n_calls)
    clock = time.perf_counter_ns
    vals = np.resize(u, n_calls).tolist()
    for i in range(n_calls):
        t0 = clock()
        step(vals[i])
        samples[i] = clock() - t0
    p50, p99 = np.percentile(samples, [50, 99]) / 1e3
    print(f'{n_calls} calls: p50 {p50:.2f} us, p99 {p99:.2f} us, max {samples.max() / 1e3:.1f} us')
    headline(f'Stepper.step() p50 / p99, {name}', f'{p50:.2f} / {p99:.2f} µs', 'p99 <= 10 µs')


def hnarx_section(reps, n_calls, u_long):
    """Fit time, simulate() throughput and Stepper latency of the hysteresis-operator NARX."""
    from piezo_narx_ros.ident.hysteresis.model import HysteresisNARX
    from piezo_narx_ros.plant import PiezoCantilever, generate
    u = generate('protocol', FS, 25.0, 100.0, seed=0)
    y = PiezoCantilever(fs=FS, seed=0).run(u).y
    HysteresisNARX(hidden=2, n_plays=2, max_iter=1).fit(u[:2000], y[:2000], fs=FS)   # JIT
    times = []
    for seed in range(min(reps, 3)):
        t0 = time.perf_counter()
        m = HysteresisNARX(seed=seed).fit(u[:25000], y[:25000], fs=FS)
        times.append(time.perf_counter() - t0)
        val = r2(y[25000:], m.simulate(u)[25000:])
        print(f'seed {seed}: fit {times[-1]:.2f} s ({m.training_info_["iterations"]} LM '
              f'iterations, {m.n_params} parameters); free-run R2 on the second half of the '
              f'protocol {val:.6f}')
    print(f'median fit time {statistics.median(times):.2f} s')
    headline('HysteresisNARX default fit, 25,000 samples, one core (median of seeds)',
             f'{statistics.median(times):.2f} s', '', 'envelope.md')
    m.simulate(u_long[:100])
    t_sim = median_time(lambda: m.simulate(u_long), reps)
    print(f'simulate(): {u_long.size} samples in {t_sim * 1e3:.1f} ms -> '
          f'{u_long.size / t_sim / 1e6:.2f} M samples/s')
    headline('free-run simulate(), HysteresisNARX default', f'{u_long.size / t_sim / 1e6:.2f} M '
             'samples/s', '>= 1 M/s')
    print('Stepper.step():', end=' ')
    step_latency(m, u, n_calls, 'HysteresisNARX default')


def median_time(f, repeats):
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        f()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    ap.add_argument('--quick', action='store_true', help='fewer repeats, no grid')
    args = ap.parse_args(argv)
    reps = 3 if args.quick else 5
    u, y, y_true, source = piezo_data()
    half = u.size // 2
    ue, ye, uv, yv, ytv = u[:half], y[:half], u[half:], y[half:], y_true[half:]
    print(f'data: {source}; {half} estimation + {u.size - half} validation samples at '
          f'{FS:.0f} Hz; cpu count {os.cpu_count()}')

    NARXNetwork(4, 4, 10, restarts=1, max_iter=2, refine_iter=2).fit(ue[:3000], ye[:3000])  # JIT
    print('\n# NARX fit, nu=ny=4, H=10, default options, one core (torch threads=1)')
    fits = []
    for seed in range(reps):
        t0 = time.perf_counter()
        m = NARXNetwork(4, 4, 10, seed=seed).fit(ue, ye, fs=FS)
        dt = time.perf_counter() - t0
        ys = m.simulate(uv, yv[:4])
        fits.append((dt, r2(yv[4:], ys[4:]), r2(ytv[4:], ys[4:]), m))
        i = m.training_info_
        print(f'seed {seed}: fit {dt:.2f} s (stage 1 {i["stage1_seconds"]:.2f} s, stage 2 '
              f'{i.get("stage2_seconds", 0):.2f} s, kept {i["selected_stage"]}); '
              f'free-run validation '
              f'R2 {fits[-1][1]:.6f} vs measured y, {fits[-1][2]:.6f} vs y_true')
    print(f'median fit time {statistics.median(f[0] for f in fits):.2f} s; median free-run R2 '
          f'{statistics.median(f[1] for f in fits):.6f} (measured), '
          f"{statistics.median(f[2] for f in fits):.6f} (y_true: the plant's tip deflection "
          f'before sensor filter and noise)')
    headline('NARX(4,4,10) fit, 25,000 samples, one core (median of seeds)',
             f'{statistics.median(f[0] for f in fits):.2f} s')
    headline('NARX(4,4,10) free-run validation R² (plant data, median of seeds)',
             f'{statistics.median(f[1] for f in fits):.6f}', '>= 0.9999', 'identification.md')
    model = fits[0][3]

    print('\n# free-run simulate() throughput, H=10, nu=ny=4 (median of repeats)')
    u_long = np.tile(uv, 40)                                   # 1,000,000 samples
    model.simulate(u_long[:100])
    t_sim = median_time(lambda: model.simulate(u_long), reps)
    print(f'{u_long.size} samples in {t_sim * 1e3:.1f} ms -> '
          f'{u_long.size / t_sim / 1e6:.2f} M samples/s')
    arx = ARXModel(4, 4).fit(ue, ye)
    t_arx = median_time(lambda: arx.simulate(u_long), reps)
    print(f'ARX(4,4): {u_long.size / t_arx / 1e6:.2f} M samples/s')
    headline('free-run simulate(), NARX 10 units / ARX(4,4)',
             f'{u_long.size / t_sim / 1e6:.2f} / {u_long.size / t_arx / 1e6:.2f} M samples/s',
             '>= 1 M/s')

    print('\n# Stepper.step() per call, including Python call overhead')
    n_calls = 20000 if args.quick else 100000
    step_latency(model, uv, n_calls)

    print('\n# HysteresisNARX (--preset envelope family), default structure, one core')
    hnarx_section(reps, n_calls, u_long)

    if not args.quick:
        print('\n# identification grid: 16 NARX (nu, ny in 1..4, H=10) + 100 ARX '
              '(na, nb in 1..10), 25,000 estimation samples, sequential on one core')
        t0 = time.perf_counter()
        for nu in range(1, 5):
            for ny in range(1, 5):
                NARXNetwork(nu, ny, 10, seed=0).fit(ue, ye)
        t_narx = time.perf_counter() - t0
        t0 = time.perf_counter()
        for na in range(1, 11):
            for nb in range(1, 11):
                ARXModel(na, nb).fit(ue, ye)
        t_arx = time.perf_counter() - t0
        headline('paper grid, 16 NARX + 100 ARX, 25,000 samples, one core',
                 f'{t_narx + t_arx:.1f} s')
        print(f'16 NARX {t_narx:.1f} s + 100 ARX {t_arx:.1f} s = {t_narx + t_arx:.1f} s '
              f'on one core '
              f'(about {(t_narx + t_arx) / 2:.1f} s split over 2 cores)')
    return 0


if __name__ == '__main__':
    sys.exit(main())
