"""
The two-axis targets of issue 20 on the coupled cantilever of config/plant_2axis.yaml.

1. Free run of both axes: one 2 x 2 model identified (`--preset`) on one 25 s record of the
   identification protocol on each axis (seeds s and s + 1), coupling on; then its free run from
   rest on the envelope battery (bench_envelope.BATTERY, 10 s each, both axes moving at once: y
   gets the same kind of move shifted by a third of the record). RMSE per axis against the
   docs/envelope.md targets: slow full-range moves <= 1 um median / 2 um worst, steps, APRBS,
   +-50 V sines and chirp <= 2 um, fresh multisine R² >= 0.9999.
2. Sensorless control of both axes: AxesController 'inverse' (the model inverted, coupling
   compensated) against 'linear' (each axis's own static line, coupling ignored) on sine
   references of both axes (x 1 Hz +-15 um, y 0.7 Hz +-10 um), the coupled plant measured; target
   inverse RMS <= 1/10 of the linear one on each axis.

    python bench/bench_axes.py --preset paper --seeds 0
"""
from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_envelope import BATTERY, SLOW, TEST_SECONDS  # noqa: E402

from piezo_narx_ros.control.axes import AxesController  # noqa: E402
from piezo_narx_ros.ident.experiment import PRESETS, ExperimentConfig, run_experiment  # noqa
from piezo_narx_ros.plant.axes import make_axis_plants  # noqa: E402
from piezo_narx_ros.plant.signals import generate  # noqa: E402
from piezo_narx_ros.record import Record  # noqa: E402
from piezo_narx_ros.share import config_path  # noqa: E402

FS = 2000.0
STAGE = config_path('plant_2axis.yaml')


def stage(seed: int):
    """Return the coupled two-axis cantilever at rest, sensor noise seed `seed`."""
    return make_axis_plants([], STAGE, fs=FS, seed=seed)


def identify(seed: int, preset: str, jobs: int):
    """One 2 x 2 model on 25 s of the protocol on each axis: (model, fit s, label)."""
    u = np.column_stack([generate('protocol', FS, 25.0, 100.0, seed=seed + i) for i in (0, 1)])
    y, _ = stage(seed).run(u)
    cfg = replace(ExperimentConfig(), **PRESETS[preset], seed=seed, jobs=jobs, progress=False)
    t0 = time.perf_counter()
    rec = Record(u=u, y=y, fs=FS, source=f'protocol seed {seed}', inputs=('x', 'y'),
                 outputs=('x', 'y'))
    result = run_experiment([rec], cfg)
    return result.best.model, time.perf_counter() - t0, result.best.spec.label


def free_run_battery(model, seed: int) -> dict:
    """{move: (R² per axis, RMSE per axis m)}: free run from rest against the stage's output."""
    out = {}
    for i, (name, (kind, amp, opt)) in enumerate(BATTERY.items()):
        opt = dict(opt)
        sig_seed = 7919 * (seed + 1) if opt.pop('seeded', False) else 0
        x = generate(kind, FS, TEST_SECONDS, amp, seed=sig_seed, **opt)
        u = np.column_stack([x, np.roll(x, x.size // 3)])
        y, _ = stage(1000 * seed + i).run(u)
        y_hat = np.asarray(model.simulate(u)).reshape(y.shape)
        err = y_hat - y
        rmse = np.sqrt(np.mean(err ** 2, axis=0))
        r2 = 1.0 - np.sum(err ** 2, axis=0) / np.sum((y - y.mean(axis=0)) ** 2, axis=0)
        out[name] = (r2, rmse)
    return out


def control(model, seed: int, seconds: float = 6.0) -> dict:
    """{mode: RMS tracking error per axis, m} after the first second, the stage measured."""
    n = int(seconds * FS)
    t = np.arange(n) / FS
    ref = np.column_stack([15e-6 * np.sin(2 * np.pi * 1.0 * t),
                           10e-6 * np.sin(2 * np.pi * 0.7 * t + 1.0)])
    out = {}
    for mode in ('linear', 'inverse'):
        ctl = AxesController(model, mode=mode)
        u = np.array([ctl.on_reference(10**15 + k * 500_000, ref[k])[0][1] for k in range(n)])
        y, _ = stage(seed + 77).run(u)
        e = y[int(FS):] - ref[int(FS):]
        out[mode] = np.sqrt(np.mean(e ** 2, axis=0))
        out[f'{mode}_unreachable'] = ctl.stats.unreachable
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.strip().split('\n\n')[0])
    ap.add_argument('--preset', default='paper', choices=sorted(PRESETS))
    ap.add_argument('--seeds', type=int, nargs='+', default=[0])
    ap.add_argument('--jobs', type=int, default=2)
    args = ap.parse_args(argv)
    for seed in args.seeds:
        model, fit_s, label = identify(seed, args.preset, args.jobs)
        print(f'seed {seed}: {label} ({type(model).__name__}, {model.n_in} x {model.n_out}), '
              f'fit {fit_s:.1f} s')
        runs = free_run_battery(model, seed)
        print('  free run from rest          R² x / y           RMSE x / y (um)')
        for name, (r2, rmse) in runs.items():
            mark = ' (slow)' if name in SLOW else ''
            print(f'  {name:24s} {r2[0]:9.6f} {r2[1]:9.6f}   {rmse[0] * 1e6:8.3f} '
                  f'{rmse[1] * 1e6:8.3f}{mark}')
        c = control(model, seed)
        ratio = c['inverse'] / c['linear']
        print(f'  control RMS x / y (um): linear {c["linear"][0] * 1e6:.3f} / '
              f'{c["linear"][1] * 1e6:.3f}, inverse {c["inverse"][0] * 1e6:.3f} / '
              f'{c["inverse"][1] * 1e6:.3f} (ratio {ratio[0]:.3f} / {ratio[1]:.3f}; target '
              f'<= 0.1; unreachable {c["inverse_unreachable"]})')
    return 0


if __name__ == '__main__':
    sys.exit(main())
