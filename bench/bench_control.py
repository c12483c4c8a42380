"""
Sensorless position control (issue 9).

How well does the plant's true deflection follow a position reference, for each controller mode and
a sensor-only PI?

For each plant (the Bouc-Wen cantilever, config/plant.yaml, and the structurally different
Preisach variant, config/plant_preisach.yaml) the model is the best the package identifies, as a
user would make it:

    piezo-narx simulate --signal protocol --seconds 25 [--plant-config P] --out p.npz
    piezo-narx fit p.npz --preset envelope --out DIR

with --seed s for each seed s (kept in --models, reused when present; --model-default /
--model-preisach take one model of your own for every seed instead). Then, for every task and
seed, a PositionController with that seed's model drives a fresh PiezoCantilever (sensor-noise
seed = seed) sample by sample (control.closed_loop.run_loop, no DDS) from rest:

  sin 0.1 / 1 / 10 Hz   +-30 um sines, 2 periods (at least 2 s); scored on the second half
  tri 0.5 Hz            +-30 um triangle, 4 s; scored on the last 2 s
  steps                 6 levels uniform in +-30 um (seeded), each held 1 s; scored on all
  random                white noise low-passed at 10 Hz (4th-order Butterworth, seeded), scaled
                        to a 30 um peak, 10 s; scored after the first second

Modes: linear (u = (r - offset)/gain, the model's static line), inverse (the model inverted
sample by sample: no sensor), inverse_feedback (inverse + PI on the measured deflection, the
controller's default gains) and pi, a sensor-only PI (no model but its static gain) whose gains
are the best of a grid on the 10 Hz sine with seed 0 (printed). --variants adds the inverse's
alternatives (exact output target; quasi-static target without the advance compensation).
Score: RMSE of y_true - r.

Printed: per plant, the median RMSE over seeds (nm) per task and mode, the ratios the issue asks
for (inverse/linear at 0.1, 1, 10 Hz; inverse_feedback/pi at 10 Hz), the controller's compute per
sample in inverse mode (on_reference: stamp gate + inversion + model step; p50 / p99 over every
inverse run) and the unreachable/limited counts. --out DIR writes results.json and the figures of
docs/control.md (reference vs deflection, error vs time, deflection vs reference).

--live S runs the loop over DDS instead (2 kHz, one process per node, S seconds): lost samples,
reference -> voltage_command latency at an in-process probe (bench_live's), CPU per node, and
bench_live's estimator pipeline right after it, for a side-by-side figure under the same load.
--rt PRIO runs the controller (then the estimator) under SCHED_FIFO.

Run: python bench/bench_control.py [--seeds 0 1 2] [--plants default preisach] [--out DIR]
     python bench/bench_control.py --live 60 [--model-default M] [--live-mode inverse] [--rt 20]
"""
from __future__ import annotations

import argparse
import itertools
import json
import statistics
import time
from pathlib import Path

import numpy as np

from headline import headline

from piezo_narx_ros.control.closed_loop import run_loop
from piezo_narx_ros.control.controller import PositionController
from piezo_narx_ros.ident.model_io import load_model
from piezo_narx_ros.plant import PiezoCantilever, generate, load_plant_params

FS = 2000.0
AMP = 30e-6
REPO = Path(__file__).resolve().parents[1]
PLANTS = {'default': REPO / 'config' / 'plant.yaml',
          'preisach': REPO / 'config' / 'plant_preisach.yaml'}
MODES = ('linear', 'inverse', 'inverse_feedback', 'pi')
# --variants: the inverse's design choices side by side (docs/control.md): the exact one-step
# inverse of the model output, and the quasi-static target without the advance compensation.
VARIANTS = {'inverse output': {'mode': 'inverse', 'target': 'output'},
            'inverse qs no-adv': {'mode': 'inverse', 'target': 'quasi_static', 'advance': 0.0}}
TASKS = ('sin 0.1 Hz', 'sin 1 Hz', 'sin 10 Hz', 'tri 0.5 Hz', 'steps', 'random')
PI_GRID = {'kp': (0.0, 0.01, 0.02, 0.05), 'ki': (25.0, 50.0, 100.0, 150.0, 200.0, 250.0, 300.0)}
SLEW = 1e5   # V/s: the simulated amplifier's own limit


def reference(task: str, seed: int) -> tuple[np.ndarray, int]:
    """Return a task's reference, (N,) m, and its first scored sample."""
    rng = np.random.default_rng(seed)
    if task.startswith('sin'):
        f = float(task.split()[1])
        n = int(round(max(2.0 / f, 2.0) * FS))
        return AMP * np.sin(2 * np.pi * f * np.arange(n) / FS), n // 2
    if task.startswith('tri'):
        r = generate('triangle', FS, 4.0, AMP / 1e-6, freq=0.5) * 1e-6
        return r, r.size // 2
    if task == 'steps':
        return np.repeat(rng.uniform(-AMP, AMP, 6), int(FS)), 0
    if task == 'random':
        from scipy.signal import butter, sosfilt
        n = int(10 * FS)
        x = sosfilt(butter(4, 10.0, fs=FS, output='sos'), rng.normal(size=n + 2000))[2000:]
        return AMP * x / np.max(np.abs(x)), int(FS)
    raise ValueError(task)


def identify(plant: str, folder: Path, seed: int = 0) -> Path:
    """
    Return the envelope model of `plant` identified from the protocol record with `seed`.

    The seed sets the signal and the sensor noise; the model is fitted with the piezo-narx commands
    when not there yet.
    """
    import subprocess
    import sys
    model = folder / 'model.json'
    if model.is_file():
        return model
    folder.mkdir(parents=True, exist_ok=True)
    data = folder / 'protocol.npz'
    print(f'identifying the {plant} plant (seed {seed}): simulate --signal protocol + fit '
          f'--preset envelope (a few minutes) -> {folder}', flush=True)
    t0 = time.monotonic()
    cli = [sys.executable, '-m', 'piezo_narx_ros.cli.main']
    for args in (['simulate', '--signal', 'protocol', '--seconds', '25', '--seed', str(seed),
                  '--plant-config', str(PLANTS[plant]), '--out', str(data), '--force'],
                 ['fit', str(data), '--preset', 'envelope', '--out', str(folder),
                  '--no-report']):
        if subprocess.run(cli + args).returncode:
            raise SystemExit(f'piezo-narx {args[0]} failed for the {plant} plant')
    print(f'  identified in {time.monotonic() - t0:.0f} s', flush=True)
    return model


def controller(model, mode: str, pi: dict | None = None) -> PositionController:
    """
    Return the controller of a mode.

    'pi': the sensor-only baseline with the given gains; a VARIANTS name: that inverse.
    """
    if mode == 'pi':
        return PositionController(model, mode='feedback', slew_rate=SLEW, **pi)
    if mode in VARIANTS:
        return PositionController(model, slew_rate=SLEW, **VARIANTS[mode])
    return PositionController(model, mode=mode, slew_rate=SLEW)


def run(model, params, task: str, mode: str, seed: int, pi: dict | None = None):
    """One closed-loop run from rest; returns (LoopRun, first scored sample, controller)."""
    ref, start = reference(task, seed)
    ctl = controller(model, mode, pi)
    return run_loop(ctl, PiezoCantilever(params, fs=FS, seed=seed), ref), start, ctl


def tune_pi(model, params) -> tuple[dict, float]:
    """Tune the sensor-only PI on the 10 Hz sine (seed 0): its best gains and RMSE there (m)."""
    best, best_rmse = None, np.inf
    for kp, ki in itertools.product(PI_GRID['kp'], PI_GRID['ki']):
        loop, start, _ = run(model, params, 'sin 10 Hz', 'pi', 0, {'kp': kp, 'ki': ki})
        rmse = loop.rmse(start)
        if np.isfinite(rmse) and rmse < best_rmse:
            best, best_rmse = {'kp': kp, 'ki': ki}, rmse
    return best, best_rmse


def bench_plant(plant: str, model_paths: dict, seeds, figures: Path | None,
                modes=MODES) -> dict:
    """model_paths: {seed: model file} (one model per seed, or the same for all)."""
    params = load_plant_params(PLANTS[plant])
    models = {s: load_model(p) for s, p in model_paths.items()}
    pi, pi_rmse = tune_pi(models[seeds[0]], params)
    names = sorted({str(p) for p in model_paths.values()})
    print(f'\n== {plant} plant, model(s) {", ".join(names)}; sensor-only PI tuned on sin 10 '
          f'Hz seed {seeds[0]}: kp {pi["kp"]:g}, ki {pi["ki"]:g}/s ({pi_rmse * 1e9:.0f} nm)',
          flush=True)
    rmse = {t: {m: [] for m in modes} for t in TASKS}
    limited = dict.fromkeys(modes, 0)
    compute = []
    examples = {}
    for task, mode, seed in itertools.product(TASKS, modes, seeds):
        loop, start, ctl = run(models[seed], params, task, mode, seed, pi)
        rmse[task][mode].append(loop.rmse(start))
        limited[mode] += ctl.stats.unreachable
        if mode == 'inverse':
            compute.append(loop.compute_ns[10:])
        if seed == seeds[0]:
            examples[(task, mode)] = loop
    med = {t: {m: statistics.median(v) for m, v in d.items()} for t, d in rmse.items()}
    ct = np.concatenate(compute) / 1e3
    out = {'models': {str(k): str(v) for k, v in model_paths.items()}, 'pi_gains': pi,
           'seeds': list(seeds),
           'rmse_nm_median': {t: {m: v * 1e9 for m, v in d.items()} for t, d in med.items()},
           'rmse_nm_all': {t: {m: [x * 1e9 for x in v] for m, v in d.items()}
                           for t, d in rmse.items()},
           'ratios': {'inverse/linear sin 0.1 Hz': med['sin 0.1 Hz']['inverse'] /
                      med['sin 0.1 Hz']['linear'],
                      'inverse/linear sin 1 Hz': med['sin 1 Hz']['inverse'] /
                      med['sin 1 Hz']['linear'],
                      'inverse/linear sin 10 Hz': med['sin 10 Hz']['inverse'] /
                      med['sin 10 Hz']['linear'],
                      'inverse_feedback/pi sin 10 Hz': med['sin 10 Hz']['inverse_feedback'] /
                      med['sin 10 Hz']['pi']},
           'compute_us': {'p50': float(np.percentile(ct, 50)),
                          'p99': float(np.percentile(ct, 99)), 'max': float(ct.max()),
                          'samples': int(ct.size)},
           'unreachable_samples': limited}
    width = max(len(t) for t in TASKS)
    print(f'median RMSE of y_true - r over seeds {list(seeds)}, nm')
    print(f'  {"task":<{width}}' + ''.join(f'{m:>18}' for m in modes))
    for t in TASKS:
        print(f'  {t:<{width}}' + ''.join(f'{med[t][m] * 1e9:18.1f}' for m in modes))
    for name, value in out['ratios'].items():
        print(f'  {name:<32} {value:.4f}')
    c = out['compute_us']
    print(f'  compute per sample (inverse): p50 {c["p50"]:.1f} us, p99 {c["p99"]:.1f} us, '
          f'max {c["max"]:.0f} us over {c["samples"]} samples')
    print(f'  samples with an unreachable target: {limited}', flush=True)
    r = out['ratios']
    headline(f'sensorless control, {plant} plant, seeds {list(seeds)}: inverse / linear RMSE '
             'at 0.1, 1, 10 Hz; inverse_feedback / PI at 10 Hz',
             ', '.join(f'{v:.3f}' for v in r.values()), '<= 0.1, 0.1, 1/3', 'control.md')
    if figures is not None:
        out['figures'] = write_figures(examples, plant, figures)
    return out


def write_figures(examples: dict, plant: str, folder: Path) -> list[str]:
    """Plot reference vs deflection, error vs time, deflection vs reference (docs/control.md)."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    colours = {'linear': 'tab:red', 'inverse': 'tab:blue', 'inverse_feedback': 'tab:green',
               'pi': 'tab:orange'}
    styles = {'inverse_feedback': '--'}
    for task in ('sin 1 Hz', 'sin 10 Hz', 'steps'):
        fig, axes = plt.subplots(1, 4, figsize=(18, 4.2))
        some = examples[(task, 'linear')]
        t = np.arange(some.r.size) / FS
        axes[0].plot(t, some.r * 1e6, 'k', lw=1.5, label='reference')
        for mode in MODES:
            loop = examples[(task, mode)]
            kw = {'color': colours[mode], 'lw': 0.8, 'ls': styles.get(mode, '-'), 'label': mode}
            axes[0].plot(t, loop.y_true * 1e6, **kw)
            axes[1].plot(t, (loop.y_true - loop.r) * 1e6, **kw)
            if mode.startswith('inverse'):
                axes[2].plot(t, (loop.y_true - loop.r) * 1e9, **kw)
            axes[3].plot(loop.r * 1e6, loop.y_true * 1e6, **kw)
        axes[0].set(xlabel='t (s)', ylabel='deflection (µm)', title=f'{plant}: {task}')
        axes[1].set(xlabel='t (s)', ylabel='y_true - reference (µm)', title='tracking error')
        axes[1].set_ylim(*np.percentile((some.y_true - some.r) * 1e6, [0.5, 99.5]) * 1.3)
        inv = examples[(task, 'inverse')]
        axes[2].set_ylim(*np.percentile((inv.y_true - inv.r) * 1e9, [1, 99]) * 2.0)
        axes[2].set(xlabel='t (s)', ylabel='y_true - reference (nm)',
                    title='tracking error, model-based modes')
        axes[3].set(xlabel='reference (µm)', ylabel='deflection (µm)',
                    title='deflection vs reference')
        for ax in axes:
            ax.grid(alpha=0.3)
        axes[0].legend(fontsize=8)
        axes[2].legend(fontsize=8)
        fig.tight_layout()
        path = folder / f'control_{plant}_{task.replace(" ", "_").replace(".", "p")}.png'
        fig.savefig(path, dpi=80)
        plt.close(fig)
        paths.append(str(path))
    return paths


def live(model_path: Path, seconds: float, mode: str = 'inverse', rt: int = 0) -> dict:
    """
    Run the control loop over DDS, then the estimator pipeline, side by side.

    command_node (position, 1 Hz +-30 um sine) -> controller_node -> simulator_node over DDS for
    `seconds` at 2 kHz, one process each, observed by bench_live's probe in this process (raw
    stamps, one clock); then bench_live's estimator pipeline for the same time, so the two are
    measured side by side under the same machine load. rt > 0: the controller (then the
    estimator) under SCHED_FIFO at that priority, the probe 10 below (bench_live.Probe).
    """
    import os
    import sys
    sys.path.insert(0, str(Path(__file__).parent))
    from bench_live import Probe, cpu_seconds, not_up, realtime, run_rate, start, stop
    os.environ.setdefault('ROS_DOMAIN_ID', str(1 + os.getpid() % 100))
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    ns, n = '/benchctl', int(round(seconds * FS))
    probe = Probe(ns, ('position_reference', 'voltage_command', 'deflection'),
                  wall_topic='voltage_command', node_priority=rt)
    load0 = os.getloadavg()[0]
    procs = {'simulator': start('simulator_node', ns, f'fs:={FS}'),
             'controller': start('controller_node', ns, f'model:={model_path}', f'mode:={mode}',
                                 'wait_for_subscribers:=2',
                                 f'use_deflection:={str(mode == "inverse_feedback").lower()}',
                                 prefix=realtime(rt))}
    out = {'mode': mode, 'n': n, 'rt': rt}
    try:
        if not probe.spin_until(lambda: probe.subs['voltage_command'].get_publisher_count() >= 1
                                and probe.subs['deflection'].get_publisher_count() >= 1, 60.0):
            raise not_up('simulator/controller', procs)
        procs['command'] = start('command_node', ns, 'output:=position', 'kind:=sine',
                                 'freq:=1.0', f'amplitude:={AMP}', f'fs:={FS}', 'loop:=false',
                                 f'seconds:={seconds}', 'wait_for_subscribers:=2')
        ref = probe.recv['position_reference']
        probe.spin_until(lambda: len(ref) > 0, 60.0)
        cpu0 = {k: cpu_seconds(p.pid) for k, p in procs.items()}
        t0 = time.monotonic()
        probe.spin_until(lambda: all(len(v) >= n for v in probe.recv.values()), seconds + 10.0)
        wall = time.monotonic() - t0
        cpu1 = {k: cpu_seconds(p.pid) for k, p in procs.items()}
        probe.spin_until(lambda: False, 1.2)
        cmd = probe.recv['voltage_command']
        out['cpu'] = {k: 100.0 * (cpu1[k] - cpu0[k]) / wall for k in procs}
        out['lost'] = {t: n - len(v) for t, v in probe.recv.items()}
        out['latency_us'] = np.array([cmd[t] - ref[t] for t in cmd if t in ref]) / 1e3
        out['lateness_us'] = np.array([probe.wall[t] - t for t in cmd]) / 1e3
        out['controller'] = next((v for k, v in probe.diag.items()
                                  if k.startswith(ns.strip('/') + '/controller_node')), {})
    finally:
        out['codes'] = stop(procs.values())
        probe.close()
    out['load'] = (load0, os.getloadavg()[0])
    est = run_rate(FS, seconds, model_path, 0.0, 'events', rt)
    out['estimator'] = {'latency_us': est['latency_us'], 'lost': est['lost'],
                        'cpu': est['cpu'], 'codes': est['codes']}
    out['load_after_estimator'] = os.getloadavg()[0]
    return out


def print_live(r: dict) -> None:
    from bench_live import pct
    sched = f'controller SCHED_FIFO {r["rt"]}' if r['rt'] else 'normal scheduling'
    print(f'\n== live over DDS, {r["mode"]}, {sched}, {r["n"]} references at {FS:g} Hz '
          f'(exit codes {r["codes"]}; load average {r["load"][0]:.1f} -> {r["load"][1]:.1f}, then '
          f'{r["load_after_estimator"]:.1f} after the estimator pipeline)')
    print('                                          p50      p99      max  (us)')
    print(f'  reference -> voltage_command        {pct(r["latency_us"])}')
    print(f'  lateness stamp -> voltage_command   {pct(r["lateness_us"])}')
    print(f'  same time: command -> estimate      {pct(r["estimator"]["latency_us"])}  '
          '(bench_live, estimator pipeline)')
    print('  lost: ' + ', '.join(f'{t} {v}' for t, v in r['lost'].items()) + '; estimator '
          'pipeline: ' + ', '.join(f'{t} {v}' for t, v in r['estimator']['lost'].items()))
    print('  CPU % of a core: ' + ', '.join(f'{k} {v:.0f}' for k, v in r['cpu'].items()) +
          '; estimator pipeline: ' + ', '.join(f'{k} {v:.0f}'
                                               for k, v in r['estimator']['cpu'].items()))
    c = r['controller']
    print(f"  controller: references {c.get('references')}, commands {c.get('commands')}, "
          f"gaps {c.get('gaps')}, unreachable {c.get('unreachable')}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.strip().split('\n\n')[0])
    ap.add_argument('--seeds', type=int, nargs='+', default=[0, 1, 2])
    ap.add_argument('--plants', nargs='+', choices=tuple(PLANTS), default=list(PLANTS))
    ap.add_argument('--models', type=Path, default=REPO / 'reports' / 'control-models',
                    help='folder of the fitted models (one subfolder per plant)')
    ap.add_argument('--model-default', type=Path, help='one model for the default plant, every '
                    'seed (default: one identified per seed)')
    ap.add_argument('--model-preisach', type=Path, help='the same for the Preisach plant')
    ap.add_argument('--out', type=Path, help='write results.json and figures here')
    ap.add_argument('--live', type=float, metavar='S', help='instead: the loop over DDS for S '
                    's (2 kHz) and, right after, the estimator pipeline of bench_live for '
                    'comparison; the model is --model-default or the seed-0 default model')
    ap.add_argument('--live-mode', default='inverse', choices=('linear', 'inverse',
                                                               'inverse_feedback'))
    ap.add_argument('--rt', type=int, default=0, metavar='PRIO', help='--live: the controller '
                    '(then the estimator) under SCHED_FIFO at PRIO, the probe at PRIO-10 (needs '
                    'CAP_SYS_NICE; 0: normal scheduling)')
    ap.add_argument('--variants', action='store_true', help='also the inverse with the exact '
                    'output target and without the advance compensation')
    args = ap.parse_args()
    if args.live:
        model = args.model_default or identify('default', args.models / 'default-seed0', 0)
        print_live(live(model, args.live, args.live_mode, args.rt))
        return
    results = {}
    t0 = time.monotonic()
    for plant in args.plants:
        given = getattr(args, f'model_{plant}')
        models = {s: given or identify(plant, args.models / f'{plant}-seed{s}', s)
                  for s in args.seeds}
        results[plant] = bench_plant(plant, models, args.seeds,
                                     args.out / 'figures' if args.out else None,
                                     MODES + (tuple(VARIANTS) if args.variants else ()))
    print(f'\nwall time {time.monotonic() - t0:.0f} s')
    if args.out:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / 'results.json').write_text(json.dumps(results, indent=1))
        print(f'wrote {args.out / "results.json"}')


if __name__ == '__main__':
    main()
