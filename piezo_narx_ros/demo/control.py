"""
`piezo-narx demo --control`: sensorless position control end to end, real nodes over DDS.

    1 record    command_node (identification protocol, 25 s at 2 kHz) -> simulator_node ->
                recorder_node                                          (skipped with --model)
    2 fit       `piezo-narx fit` on that bag with --preset envelope    (skipped with --model)
    3 control   for each mode (linear, inverse, inverse_feedback): command_node in position mode
                (a +-30 um sine at 1 Hz) -> controller_node -> simulator_node, whose deflection
                goes back to the controller; recorder_node records the three streams
    4 analysis  per mode: RMS of measured deflection - reference, reference -> command latency
                and lost samples from the bags; figures; summary.json

The analysis half (bags -> numbers and figures) is ROS-free and tested on synthetic bags.
"""
from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from piezo_narx_ros.demo.analysis import percentiles_us
from piezo_narx_ros.errors import ConfigError, DataError

STREAMS = {'reference': ('position_reference', 'position'),
           'command': ('voltage_command', 'effort'),
           'deflection': ('deflection', 'position')}


# ------------------------------------------------------------------------------------ analysis
@dataclass
class ControlRun:
    """
    One mode's live run paired by stamp ((n,) arrays in stamp order).

    t_s since the first reference, r (m), u (V), y measured (m), the recorder's receive times of
    the reference and the command (ns, one clock), and the samples lost per stream.
    """

    stamps_ns: np.ndarray
    t_s: np.ndarray
    r: np.ndarray
    u: np.ndarray
    y: np.ndarray
    log_reference_ns: np.ndarray
    log_command_ns: np.ndarray
    lost: dict
    fs: float


def load_control_run(bag, namespace: str = 'piezo', expected: int | None = None) -> ControlRun:
    """
    Return the three streams of a control run, paired by stamp.

    expected: references the command node published (None: the distinct stamps seen); lost =
    expected - distinct stamps received, per stream. DataError when a stream is empty or fewer than
    2 samples pair up.
    """
    from piezo_narx_ros.bag.reader import read_joint_series
    prefix = f'{namespace.strip("/")}/' if namespace.strip('/') else ''
    fields = {prefix + topic: field for topic, field in STREAMS.values()}
    series = read_joint_series(bag, fields)
    got = {}
    for name, (topic, _) in STREAMS.items():
        s = series[prefix + topic]
        if s.values.size == 0:
            raise DataError(f'{bag}: no samples on /{prefix}{topic}')
        order = np.argsort(s.stamps_ns, kind='stable')
        st = s.stamps_ns[order]
        keep = np.r_[True, st[1:] != st[:-1]]
        got[name] = (st[keep], s.values[order][keep], s.log_ns[order][keep])
    seen = np.unique(np.concatenate([v[0] for v in got.values()]))
    n = int(expected) if expected is not None else seen.size
    lost = {name: n - v[0].size for name, v in got.items()}
    common = np.intersect1d(np.intersect1d(got['reference'][0], got['command'][0]),
                            got['deflection'][0])
    if common.size < 2:
        raise DataError(f'{bag}: fewer than 2 samples have a reference, a command and a '
                        'deflection')
    idx = {k: np.searchsorted(v[0], common) for k, v in got.items()}
    rs = got['reference'][0]
    fs = 1e9 / float(np.median(np.diff(rs))) if rs.size > 1 else float('nan')
    return ControlRun(common, (common - rs[0]) * 1e-9, got['reference'][1][idx['reference']],
                      got['command'][1][idx['command']], got['deflection'][1][idx['deflection']],
                      got['reference'][2][idx['reference']], got['command'][2][idx['command']],
                      {k: int(v) for k, v in lost.items()}, fs)


def control_figures(run: ControlRun, skip_s: float = 1.0) -> dict:
    """
    JSON-ready figures of one run.

    Tracking RMS and peak of y - r (nm, after skip_s s), latency reference -> command (command
    minus reference receive time at the recorder, µs), lateness (command receive time minus its
    stamp, µs), lost samples, command range (V).
    """
    sel = run.t_s >= skip_s
    if np.count_nonzero(sel) < 2:
        raise DataError(f'too few samples after {skip_s:g} s to score ({run.t_s.size})')
    e = run.y[sel] - run.r[sel]
    return {'n_paired': int(run.t_s.size), 'n_scored': int(np.count_nonzero(sel)),
            'skipped_s': skip_s,
            'tracking_rmse_nm': float(np.sqrt(np.mean(e * e)) * 1e9),
            'tracking_max_abs_error_nm': float(np.max(np.abs(e)) * 1e9),
            'reference_span_um': float(np.ptp(run.r) * 1e6),
            'command_range_V': [float(run.u.min()), float(run.u.max())],
            'latency_us': percentiles_us(run.log_command_ns - run.log_reference_ns),
            'lateness_us': percentiles_us(run.log_command_ns - run.stamps_ns),
            'lost': dict(run.lost), 'fs': run.fs}


def write_control_figures(runs: dict, out_dir, skip_s: float = 1.0) -> dict[str, Path]:
    """
    Save control_tracking.png and control_latency.png; returns {name: path}.

    Tracking: reference and deflection over two periods, error vs time, deflection vs reference,
    every mode.
    """
    from piezo_narx_ros.demo.analysis import _pyplot
    plt = _pyplot()
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = {}
    try:
        fig, ax = plt.subplots(1, 3, figsize=(16, 4.6), constrained_layout=True)
        first = next(iter(runs.values()))
        t0 = skip_s
        for i, (mode, run) in enumerate(runs.items()):
            sel = (run.t_s >= t0) & (run.t_s <= t0 + 2.0)
            if i == 0:
                ax[0].plot(run.t_s[sel], run.r[sel] * 1e6, 'k', lw=1.6, label='reference')
            ax[0].plot(run.t_s[sel], run.y[sel] * 1e6, lw=0.9, label=mode)
            late = run.t_s >= skip_s
            ax[1].plot(run.t_s[late], (run.y[late] - run.r[late]) * 1e6, lw=0.5, label=mode)
            ax[2].plot(run.r[late] * 1e6, run.y[late] * 1e6, lw=0.6, label=mode)
        ax[0].set(xlabel='t [s]', ylabel='deflection [µm]', title='live: deflection vs reference')
        ax[1].set(xlabel='t [s]', ylabel='deflection - reference [µm]', title='tracking error')
        ax[2].set(xlabel='reference [µm]', ylabel='deflection [µm]',
                  title='deflection vs reference')
        for a in ax:
            a.grid(alpha=0.3)
            a.legend(fontsize=8, loc='upper right')
        paths['tracking'] = out_dir / 'control_tracking.png'
        fig.savefig(paths['tracking'], dpi=100)
        plt.close(fig)
        fig, a = plt.subplots(figsize=(8, 4), constrained_layout=True)
        for mode, run in runs.items():
            d = (run.log_command_ns - run.log_reference_ns) / 1e3
            d = d[d > 0]
            if d.size:
                a.hist(d, bins=np.logspace(0, np.log10(d.max() * 1.01 + 1), 60), alpha=0.5,
                       label=f'{mode}: p99 {np.percentile(d, 99):.0f} µs')
        a.set_xscale('log')
        a.set(xlabel='reference -> voltage_command latency at the recorder [µs]',
              ylabel='samples', title=f'{first.fs:g} Hz, one process per node')
        a.legend()
        paths['latency'] = out_dir / 'control_latency.png'
        fig.savefig(paths['latency'], dpi=100)
    finally:
        plt.close('all')
    return paths


# ------------------------------------------------------------------------------- the DDS runs
def _control_phase(demo, mode: str, bag: Path, model: Path, c: dict) -> dict:
    """
    Run command (position) -> controller -> simulator, recorder on the three streams.

    Until the reference has been answered and recorded; returns {'published', 'expected',
    'received', 'controller': its last /diagnostics values, 'codes'}.
    """
    s = demo.s
    seconds, seed = float(c['seconds']), int(c['seed'])
    topics = [t for t, _ in STREAMS.values()]
    listeners = [
        {'executable': 'simulator_node', 'parameters': {'fs': float(s['fs']), 'seed': seed,
                                                        'plant_params': str(c['plant_params'])}},
        {'executable': 'controller_node', 'parameters': {
            'model': str(model), 'mode': mode, 'fs': float(s['fs']),
            # The bag has the deflection; only the PI needs it live (saves CPU on 2 cores).
            'use_deflection': mode == 'inverse_feedback',
            'wait_for_subscribers': 2}},      # the simulator and the recorder
        {'executable': 'recorder_node', 'parameters': {'output': str(bag), 'topics': topics}}]
    command = {'executable': 'command_node', 'parameters': {
        'output': 'position', 'fs': float(s['fs']), 'kind': c['kind'], 'freq': float(c['freq']),
        'amplitude': float(c['amplitude']), 'seconds': seconds, 'seed': seed, 'loop': False,
        'wait_for_subscribers': 2}}           # the controller (itself waiting) and the recorder
    from piezo_narx_ros.cli.bringup import load_launch
    specs = load_launch(demo._launch_yaml(f'control_{mode}', listeners + [command]))
    names = [n['executable'] for n in listeners]
    demo.wait(0.3)
    demo.probe.latest.clear()
    demo.start_group([sp for sp in specs if sp.name != 'command_node'])
    demo._wait_up(mode, names)
    demo.start_group([sp for sp in specs if sp.name == 'command_node'])
    result = _wait_answered(demo, mode, seconds)
    result['controller'] = dict((demo.probe.status(demo.fq('controller_node')) or ('', {}))[1])
    result['codes'] = demo.stop_all()
    if result['codes'].get('recorder_node') not in (0, None):
        from piezo_narx_ros.demo.runner import PhaseFailed
        raise PhaseFailed(f'{mode}: recorder_node exited with code '
                          f'{result["codes"]["recorder_node"]} while closing {bag}')
    return result


def _wait_answered(demo, phase: str, seconds: float) -> dict:
    """
    Wait until the command node has finished and every reference was answered and recorded.

    Or until nothing new reached the recorder for settle_s.
    """
    from piezo_narx_ros.demo.runner import PhaseFailed
    s = demo.s
    fs, n_total = s['fs'], int(round(seconds * s['fs']))
    cmd, ctl, sim, rec = (demo.fq(n) for n in ('command_node', 'controller_node',
                                               'simulator_node', 'recorder_node'))
    limit = s['startup_timeout_s'] + 3 * seconds + 30
    deadline = time.monotonic() + limit
    last_line = last_change = time.monotonic()
    last_received = -1
    while True:
        demo.check_alive(phase)
        now = time.monotonic()
        published = demo.probe.value(cmd, 'published')
        received = demo.probe.value(rec, 'received')
        if now > deadline:
            raise PhaseFailed(f'{phase}: reference not answered within {limit:.0f} s '
                              f'({published} references sent, {received} messages recorded)')
        if received != last_received:
            last_received, last_change = received, now
        st = demo.probe.status(cmd)
        finished = (st is not None and st[0] == 'finished') or published >= n_total
        if now - last_line >= 3.0:
            last_line = now
            demo.say(f'  {phase}: {published / fs:5.1f} of {seconds:g} s sent, '
                     f'{received} messages recorded')
        if finished:
            done = (demo.probe.value(ctl, 'commands') >= published and
                    demo.probe.value(sim, 'answered') >= published and
                    received >= 3 * published)
            if done or now - last_change > s['settle_s']:
                demo.wait(1.2)   # one more diagnostics tick: the controller's final counters
                return {'published': published, 'expected': n_total,
                        'received': demo.probe.value(rec, 'received')}
        demo.wait(0.1)


def run_control_demo(settings: dict, out: Path, model: Path | None = None) -> int:
    """
    Phases 1-4 (1-2 skipped with `model`) into `out`; returns 0.

    PhaseFailed / Interrupted propagate after every child has been stopped.
    """
    from piezo_narx_ros.demo.main import _say
    from piezo_narx_ros.demo.runner import (Demo, PhaseFailed, install_signal_handlers,
                                            restore_signal_handlers)
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ConfigError(f'--out {out}: exists and is not a directory')
    if any((out / n).exists() for n in ('record', 'fit', 'control', 'summary.json')):
        raise ConfigError(f'--out {out}: holds an earlier demo; choose a new folder')
    if model is not None and not Path(model).is_file():
        raise ConfigError(f'--model {model}: no such model file')
    s = dict(settings)
    c = dict(s['control'])
    if c['seed'] is None:
        c['seed'] = s['seed'] + 1
    s['fit'] = dict(c['fit'])
    modes = list(c['modes'])
    t_all = time.monotonic()
    demo = Demo(s, out, say=_say)
    old = install_signal_handlers(demo)
    ident = None
    results = {}
    try:
        _say(f'piezo-narx demo --control -> {out} (node logs: {out / "demo.log"})')
        with demo:
            if model is None:
                _say(f'\n== 1/4 record: protocol {c["record_seconds"]:g} s at {s["fs"]:g} Hz, '
                     f'+-{s["amplitude"]:g} V (command -> simulator -> recorder)')
                t0 = time.monotonic()
                demo.stream('record', out / 'record', float(c['record_seconds']), s['seed'],
                            kind='protocol', extra_simulator={
                                'plant_params': str(c['plant_params'])})
                demo.times.add('record', t0)
                _say(f'\n== 2/4 fit: piezo-narx fit --preset {s["fit"].get("preset")}')
                t0 = time.monotonic()
                doc = demo.fit(out / 'record', out / 'fit', no_report=True)
                demo.times.add('fit', t0)
                model = out / 'fit' / 'model.json'
                sel = json.loads((out / 'fit' / 'candidates.json').read_text())['selection']
                ident = {'selected': sel['label'],
                         'offline_validation': doc['metrics']['validation']}
                _say(f'  selected {sel["label"]}')
            else:
                _say('\n== 1-2/4 identification skipped: --model given')
            for i, mode in enumerate(modes):
                _say(f'\n== 3/4 control {i + 1}/{len(modes)}: {mode}, reference {c["kind"]} '
                     f'{c["freq"]:g} Hz +-{c["amplitude"] * 1e6:g} um, {c["seconds"]:g} s')
                t0 = time.monotonic()
                results[mode] = _control_phase(demo, mode, out / 'control' / mode, model, c)
                demo.times.add(f'control {mode}', t0)
        _say('\n== 4/4 analysis')
        t0 = time.monotonic()
        runs = {m: load_control_run(out / 'control' / m, s['namespace'],
                                    results[m]['published']) for m in modes}
        figures = {m: control_figures(r) for m, r in runs.items()}
        paths = write_control_figures(runs, out / 'figures')
        demo.times.add('analysis', t0)
    finally:
        restore_signal_handlers(old)
    demo.times.seconds['total'] = round(time.monotonic() - t_all, 3)
    summary = {'settings': s, 'model': str(model), 'identification': ident,
               'wall_seconds': demo.times.seconds,
               'modes': {m: {**figures[m], 'published': results[m]['published'],
                             'controller_diagnostics': results[m]['controller'],
                             'bag': str(out / 'control' / m)} for m in modes},
               'figures': {k: str(v) for k, v in paths.items()},
               'latency_source': 'recorder_node receive times: voltage_command minus '
                                 'position_reference of the same stamp (one process, one clock)',
               'tracking_source': 'measured deflection (sensor noise included) minus reference, '
                                  'after the first second'}
    if 'linear' in figures:
        base = figures['linear']['tracking_rmse_nm']
        summary['rmse_ratio_to_linear'] = {m: f['tracking_rmse_nm'] / base
                                           for m, f in figures.items() if m != 'linear'}
    from piezo_narx_ros.ident.validation.report import write_json
    write_json(summary, out / 'summary.json')
    print_control_table(summary)
    _say(f'\nreport: {out}  (summary.json, figures/, control/<mode> bags)')
    if any(v for m in modes for v in figures[m]['lost'].values()):
        raise PhaseFailed('samples were lost (see summary.json)')
    return 0


def print_control_table(summary: dict) -> None:
    """One line per mode: tracking RMSE, latency p50/p99/max, lost samples."""
    from piezo_narx_ros.demo.main import _say
    _say('\n== summary')
    _say(f'  {"mode":<17} {"RMSE nm":>9} {"max nm":>9} {"lat p50 µs":>11} {"p99 µs":>8} '
         f'{"max µs":>8}  lost (reference, command, deflection)')
    for mode, f in summary['modes'].items():
        lat = f['latency_us']
        _say(f'  {mode:<17} {f["tracking_rmse_nm"]:9.1f} {f["tracking_max_abs_error_nm"]:9.0f} '
             f'{lat["p50"]:11.0f} {lat["p99"]:8.0f} {lat["max"]:8.0f}  '
             f'{", ".join(str(v) for v in f["lost"].values())}')
    for mode, ratio in summary.get('rmse_ratio_to_linear', {}).items():
        _say(f'  {mode} / linear RMSE: {ratio:.4f}')
    _say('  wall time: ' + ', '.join(f'{k} {v:.1f} s' for k, v in summary['wall_seconds'].items()))
