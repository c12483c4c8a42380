"""
The state set from a short measured window, over many random pasts (ident/state/, issue 18).

bench_real.py scores each model on a few test records; this bench asks the state estimator
alone, on many: for each model fitted by bench_real (`--keep DIR`), K test records of its own
plant, each after its own random 20 s history and 1 s hold, half of them with the sensor zero
moved (uniform in +-2.5 um, as a session of another day) and half with the estimation session's
zero; the test signal cycles through what a rig records after a past nobody logged: a hold then
a growing 3 Hz sine, a 0.5 Hz triangle, a 0.1-10 Hz multisine, held levels, the protocol. Each
record's first `--window` seconds set the state (`model.estimate_state`), the rest is scored.
`--pasts`: `random` (the default) ends each past with a ramp from above or below; `fade` ends it
with a fade-out about the record's first command (how the real micromanipulator's test record
ends each segment before its hold); `both` alternates them every len(SIGNALS) records.
`--state-past fade-out` tells the estimate that each past faded out (ident/state/ step 5).


    ratio = RMSE(free run from the estimated state) / RMSE(the same model from rest, on the
            same command applied to the plant at rest, the better of the two sensor zeros)

the ratio bench_real prints (issue 18's target: <= 2). Also the start from rest without any
measurement (`rest`) and the model run through the record's own past with the zero told
(`true`): what a perfect state estimate of this model would give. No fitting: seconds per
model, so rules of the estimator can be compared on the same pasts.

    python bench/bench_real.py --scenarios session growing --seeds 0 1 --presets envelope \
        --keep /tmp/real
    python bench/bench_state.py /tmp/real [--trials 10] [--window 0.5] [--pasts both] \
        [--json out.json]
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np

from piezo_narx_ros.ident.model_io import load_model
from piezo_narx_ros.ident.state.estimate import PASTS
from piezo_narx_ros.plant import PiezoCantilever, generate, load_plant_params, random_history
from piezo_narx_ros.share import config_path

PLANTS = {'bouc_wen': 'plant.yaml', 'preisach': 'plant_preisach.yaml'}
SPREAD = 2.5e-6          # a moved sensor zero: uniform in +-SPREAD (m)
TEST_SECONDS = 10.0
# name -> (generate kind, options); each after the record's own past
SIGNALS = {
    'hold, growing 3 Hz': ('growing_sine', {'freq': 3.0, 'hold': 1.0}),
    'triangle 0.5 Hz': ('triangle', {'freq': 0.5}),
    'multisine 0.1-10 Hz': ('multisine', {'f_max': 10.0}),
    'held levels': ('holds', {'hold': 1.5, 'ramp': 0.05}),
    'protocol': ('protocol', {}),
}


def rmse(e) -> float:
    """Root mean square of e (same unit)."""
    return float(np.sqrt(np.mean(np.square(e))))


def cells(root: Path):
    """(name, plant, model path, estimation session's zero m) of each kept bench_real cell."""
    for cell in sorted(p for p in root.iterdir() if p.is_dir()):
        path = cell / 'fit_envelope' / 'model.json'
        plant = next((k for k in PLANTS if f'_{k}_' in cell.name), None)
        est = sorted(cell.glob('est_*_rig.npz'))
        if not path.exists() or plant is None or not est:
            continue
        with np.load(est[0], allow_pickle=False) as z:
            zero = json.loads(str(z['meta']))['sensor']['offset_m']
        yield cell.name, plant, path, zero


def fade_history(fs, amplitude, seed, end, hold=1.0) -> np.ndarray:
    """
    Return a random past (V) ended by a fade-out about `end` V, then `hold` s there.

    20 s of random ramps (random_history), then 3-8 s of a 0.5-5 Hz sine about `end` whose
    amplitude (30-100 % of `amplitude`, clipped to +-amplitude) falls linearly to 0.
    """
    base = random_history(fs, 20.0, amplitude, seed=seed, end=end, hold=0.0)
    rng = np.random.default_rng(seed + 99)
    freq, seconds = rng.uniform(0.5, 5.0), rng.uniform(3.0, 8.0)
    top = rng.uniform(0.3, 1.0) * amplitude
    t = np.arange(int(seconds * fs)) / fs
    fade = np.clip(end + top * (1.0 - t / seconds) * np.sin(2 * np.pi * freq * t),
                   -amplitude, amplitude)
    return np.concatenate([base, fade, np.full(int(round(hold * fs)), end)])


def trial(model, plant_name, fs, zero, k, window_s, spread=SPREAD, pasts='random',
          state_past='any'):
    """
    One test record after a random past; returns {'signal', 'moved', 'past', 'init', ...}.

    spread: the moved sensor zero is uniform in +-spread (m) on every other record; pasts:
    'random', 'fade' or 'both' (see the module docstring); state_past: what the estimate is
    told about how the past ended (estimate_state's past).
    """
    name = list(SIGNALS)[k % len(SIGNALS)]
    kind, options = SIGNALS[name]
    rng = np.random.default_rng(1000 + k)
    moved = bool(k % 2)
    offset = zero + (rng.uniform(-spread, spread) if moved else 0.0)
    params = load_plant_params(config_path(PLANTS[plant_name]))
    u = generate(kind, fs, TEST_SECONDS, 100.0, seed=500 + k, **options)
    kind_of_past = pasts if pasts != 'both' else ('fade' if (k // len(SIGNALS)) % 2 else
                                                  'random')
    if kind_of_past == 'fade':
        past = fade_history(fs, 100.0, seed=700 + k, end=float(u[0]))
    else:
        past = random_history(fs, 20.0, 100.0, seed=700 + k, end=float(u[0]), hold=1.0)
    y = PiezoCantilever(params, fs=fs, seed=300 + k, sensor_offset=offset).run(
        u, history=past).y
    n = int(round(window_s * fs))
    refs = [rmse(PiezoCantilever(params, fs=fs, seed=300 + k, sensor_offset=z).run(u).y[n:]
                 - model.simulate(u)[n:]) for z in (0.0, zero)]
    ref = min(refs)
    t0 = time.perf_counter()
    state = model.estimate_state(u[:n], y[:n], past=state_past)
    seconds = time.perf_counter() - t0
    init = rmse(y[n:] - model.simulate(u, state=state)[n:])
    rest = rmse(y[n:] - model.simulate(u)[n:])
    true = rmse(y[n:] - model.simulate(np.r_[past, u])[past.size:][n:] - (offset - zero))
    return {'signal': name, 'moved': moved, 'past': kind_of_past, 'ref_m': ref, 'init': init / ref,
            'rest': rest / ref, 'true': true / ref, 'estimate_s': seconds,
            'offset_err_m': float(state.offset) - (offset - zero)}


def summarise(rows, key):
    """'median / worst (share > 2x)' of rows[key]."""
    v = [r[key] for r in rows]
    over = sum(x > 2.0 for x in v)
    return f'{statistics.median(v):5.2f} / {max(v):5.2f} ({over}/{len(v)} > 2x)'


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.strip().split('\n\n')[0])
    ap.add_argument('root', type=Path, help='a bench_real.py --keep directory')
    ap.add_argument('--trials', type=int, default=10, help='test records per model')
    ap.add_argument('--window', type=float, default=0.5, help='measured window, s')
    ap.add_argument('--spread', type=float, default=SPREAD * 1e6,
                    help='a moved sensor zero is uniform in +-SPREAD um (default %(default)s)')
    ap.add_argument('--pasts', choices=('random', 'fade', 'both'), default='random',
                    help='how each past ends: a ramp from above or below, a fade-out, or both '
                         '(default %(default)s)')
    ap.add_argument('--state-past', choices=PASTS, default='any',
                    help='what the state estimate is told about how each past ended '
                         '(default %(default)s)')
    ap.add_argument('--json', type=Path, help='write every trial as JSON')
    args = ap.parse_args(argv)
    rows = []
    t0 = time.perf_counter()
    for name, plant, path, zero in cells(args.root):
        model = load_model(path)
        got = [trial(model, plant, model.fs, zero, k, args.window,
                     args.spread * 1e-6, args.pasts, args.state_past)
               for k in range(args.trials)]
        for r in got:
            r['cell'] = name
        rows += got
        took = statistics.median(r['estimate_s'] for r in got)
        print(f'{name:26s} init {summarise(got, "init")}  rest {summarise(got, "rest")}  '
              f'true {summarise(got, "true")}  estimate {took:.2f} s', flush=True)
    if not rows:
        print(f'no bench_real cells with an envelope model under {args.root}', file=sys.stderr)
        return 2
    print('\nby signal (ratio to the start from rest on the plant at rest: median / worst)')
    for sig in SIGNALS:
        sub = [r for r in rows if r['signal'] == sig]
        if sub:
            print(f'  {sig:22s} init {summarise(sub, "init")}  rest {summarise(sub, "rest")}  '
                  f'true {summarise(sub, "true")}')
    for kind in sorted({r['past'] for r in rows}):
        sub = [r for r in rows if r['past'] == kind]
        print(f'  {"past: " + kind:22s} init {summarise(sub, "init")}  '
              f'rest {summarise(sub, "rest")}  true {summarise(sub, "true")}')
    for moved in (False, True):
        sub = [r for r in rows if r['moved'] == moved]
        print(f'  {"zero moved" if moved else "same zero":22s} init {summarise(sub, "init")}  '
              f'rest {summarise(sub, "rest")}  true {summarise(sub, "true")}')
    mean = statistics.mean(r['init'] for r in rows)
    print(f'  {"all":22s} init {summarise(rows, "init")}  rest {summarise(rows, "rest")}  '
          f'true {summarise(rows, "true")}   mean init {mean:.2f}, sum of RMSE '
          f'{1e6 * sum(r["init"] * r["ref_m"] for r in rows):.2f} um')
    print(f'wall {time.perf_counter() - t0:.0f} s')
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == '__main__':
    sys.exit(main())
