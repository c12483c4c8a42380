"""
Live pipeline benchmark: command -> simulator -> estimator over DDS, one process per node.

For each rate (default 2, 5 and 10 kHz) the three nodes run for --seconds (default 60) and a probe
node in this process records every voltage_command, deflection and deflection_estimate. Printed:

- latency command -> estimate: probe receive time of the estimate minus probe receive time of the
  command with the same stamp (one clock, one process), p50 / p99 / max;
- lateness stamp -> estimate: probe wall-clock receive time minus the sample's stamp t0 + k/fs
  (adds the command node's timer lateness), p50 / p99 / max;
- lost samples per topic (expected n minus distinct stamps received);
- CPU per node process (user + system time over the streaming interval, % of one core);
- the command node's catch-up figures (late ticks, largest batch) from /diagnostics;
- per-sample estimator compute (FreeRunEstimator.on_command, this process, no DDS) p50 / p99.

With `--batch N` (N > 1) every node runs with batch:=N: the streams are the `<topic>_batch`
JointTrajectory topics, N samples per message (DESIGN.md "High-rate streams"); the probe reads
every sample's stamp out of the batches, so latency, lateness and loss stay per sample.

With `--floor` each run is followed by the same streams between bare stand-ins of the three
nodes (floor_nodes.py: same names, topics, QoS, executor, spin loop, batch and message sizes and
codec, computing nothing), and their CPU and latency are printed beside the nodes':
`floor CPU (% of one core): simulator_node A, estimator_node B, command_node C`, and each node's
CPU over its floor's (CPU time per sample, the same samples streamed). The machine's load moves
both alike within one run; `--repeat N` runs N such pairs and prints their medians.

Targets (issue 43; ratios from one run): 20 kHz batch 20: zero loss, each node <= 1.15 x its
floor's CPU + 2 points; 10 kHz batch 10: p99 <= 3 ms; 2 kHz batch 1: p99 <= 1 ms with --rt and
<= 1.5 x the floor's p99 without, each node <= 1.15 x its floor's CPU; estimator compute p99
<= 5 us.

    python bench/bench_live.py                       # 60 s at 2, 5, 10 kHz
    python bench/bench_live.py --seconds 10 --rates 2000
    python bench/bench_live.py --publish-period 0.001   # batch the command timer at 1 kHz
    python bench/bench_live.py --rates 20000 --batch 20
    python bench/bench_live.py --rates 20000 --batch 20 --seconds 20 --floor --repeat 3
"""
from __future__ import annotations

import argparse
import math
import os
import signal
import struct
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from headline import headline

NODES = 'piezo_narx_ros.nodes'
FLOOR_NODES = Path(__file__).resolve().parent / 'floor_nodes.py'


def cpu_seconds(pid: int) -> float:
    """User + system CPU time of a process, s (from /proc)."""
    with open(f'/proc/{pid}/stat') as f:
        fields = f.read().rsplit(')', 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK')


def estimator_compute(model, n: int = 20000) -> tuple[float, float]:
    """Per-sample time of FreeRunEstimator.on_command, (p50, p99) in us."""
    from piezo_narx_ros.estimator.free_run import FreeRunEstimator
    est = FreeRunEstimator(model, init='rest')
    rng = np.random.default_rng(0)
    u = list(rng.uniform(-100, 100, (n, est.n_in))) if getattr(est, 'vector', False) else \
        rng.uniform(-100, 100, n).tolist()
    period = int(1e9 / est.fs)
    dt = np.empty(n)
    clock = time.perf_counter_ns
    for k in range(n):
        t = clock()
        est.on_command(k * period, u[k])
        dt[k] = clock() - t
    return tuple(np.percentile(dt[n // 10:], [50, 99]) / 1e3)


class Probe:
    """
    Subscribe to the three sample streams and /diagnostics of one namespace.

    Or to `topics`; wall-clock receive times are kept for `wall_topic`. node_priority > 0 (the
    measured node under SCHED_FIFO at it, see `realtime`): this thread and the DDS threads the
    probe starts run under SCHED_FIFO 10 below it, until close().
    """

    def __init__(self, ns: str, topics=('voltage_command', 'deflection', 'deflection_estimate'),
                 wall_topic: str = 'deflection_estimate', node_priority: int = 0,
                 batch: int = 1):
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.experimental import EventsExecutor
        from rclpy.node import Node

        from piezo_narx_ros.nodes.wire.batching import batch_topic, sample_type
        from piezo_narx_ros.nodes.wire import decode_joint_trajectory
        from piezo_narx_ros.nodes.diagnostics import diagnostic_values
        from piezo_narx_ros.nodes.qos import sample_qos
        self.realtime = node_priority > 0
        if self.realtime:   # before the context: its DDS threads inherit the policy
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(max(1, node_priority - 10)))
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = Node('bench_probe', namespace=ns, context=self.context)
        self.recv = {t: {} for t in topics}
        self.wall = {}
        self.diag = {}
        mono, wall = time.monotonic_ns, time.time_ns

        stamp = struct.Struct('<iI')

        def make_cb(store, with_wall):
            # raw=True and only the stamp read from the CDR bytes: the probe must not be the
            # bottleneck it measures (rclpy's message conversion costs ~20 us per message).
            def cb(raw):
                sec, nsec = stamp.unpack_from(raw, 4)
                t = sec * 1_000_000_000 + nsec
                store[t] = mono()
                if with_wall:
                    self.wall[t] = wall()

            def cb_batch(raw):   # every sample of a batch arrives at once
                now, w = mono(), wall()
                for t in decode_joint_trajectory(raw).t_ns.tolist():
                    store[t] = now
                    if with_wall:
                        self.wall[t] = w
            if batch > 1:
                return cb_batch
            return cb

        def on_diag(arr):
            for st in arr.status:
                self.diag[st.name] = diagnostic_values(st)

        qos = sample_qos(depth=100000)
        self.subs = {t: self.node.create_subscription(sample_type(batch), batch_topic(t, batch),
                                                      make_cb(store, t == wall_topic), qos,
                                                      raw=True)
                     for t, store in self.recv.items()}
        self.node.create_subscription(DiagnosticArray, '/diagnostics', on_diag, 100)
        self.executor = EventsExecutor(context=self.context)
        self.executor.add_node(self.node)

    def spin_until(self, predicate, timeout: float) -> bool:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            self.executor.spin_once(timeout_sec=0.01)
            if predicate():
                return True
        return False

    def close(self):
        import rclpy
        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)
        if self.realtime:
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))


def start(module: str, ns: str, *params: str, prefix: tuple = (),
          floor: bool = False) -> subprocess.Popen:
    """
    Start a node process (`prefix`: a command it runs under, e.g. ('chrt', '-f', '20')).

    floor: the node's bare stand-in from floor_nodes.py instead (module 'simulator_node' ->
    role 'simulator'), which takes fs, batch, axes and the command's stream parameters.
    """
    entry = [str(FLOOR_NODES), module.replace('_node', '')] if floor else \
        ['-m', f'{NODES}.{module}']
    args = [*prefix, sys.executable, *entry, '--ros-args', '-r', f'__ns:={ns}']
    for p in params:
        args += ['-p', p]
    return subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)


def not_up(what: str, procs: dict) -> RuntimeError:
    """Build the error for nodes that did not come up: who exited, with what, its last line."""
    dead = [f'{name} exited {p.returncode}: '
            f'{(p.stderr.read().strip().splitlines() or ["(no output)"])[-1]}'
            for name, p in procs.items() if p.poll() is not None]
    tail = ': ' + ' | '.join(dead) if dead else ' within the timeout (all still running)'
    return RuntimeError(f'{what} did not come up{tail}')


def stop(procs) -> list[int]:
    for p in procs:
        if p.poll() is None:
            p.send_signal(signal.SIGINT)
    codes = []
    for p in procs:
        try:
            codes.append(p.wait(10))
        except subprocess.TimeoutExpired:
            p.kill()
            codes.append(p.wait())
    return codes


def pct(a) -> str:
    if len(a) == 0:
        return 'n/a'
    p50, p99, mx = np.percentile(a, [50, 99, 100])
    return f'{p50:8.0f} {p99:8.0f} {mx:8.0f}'


def realtime(priority: int) -> tuple:
    """
    Return the command prefix that starts a node under SCHED_FIFO at `priority` (() for 0).

    The node measured runs above the probe (Probe(node_priority=...)), the probe above the rest
    (normal scheduling): measured here, every node under SCHED_FIFO starves the others and loses
    samples. Needs CAP_SYS_NICE.
    """
    return ('chrt', '-f', str(priority)) if priority > 0 else ()


def axes_model(axes: list, fs: float, seconds: float = 4.0):
    """
    Identify an ARX 4/4 of len(axes) inputs and outputs, named `axes`, at fs on the simulator.

    One cantilever per axis (independent), each driven by its own multisine: a model of the right
    shape and size for the live bench, not a model to judge.
    """
    from piezo_narx_ros.ident.arx.model import ARXModel
    from piezo_narx_ros.plant.axes import make_axis_plants
    from piezo_narx_ros.plant.signals import generate
    u = np.column_stack([generate('multisine', fs, seconds, 100.0, seed=i)
                         for i in range(len(axes))])
    y, _ = make_axis_plants(axes, fs=fs).run(u)
    model = ARXModel(na=4, nb=4).fit(u, y, fs=fs)
    model.inputs = model.outputs = tuple(axes)
    return model


def run_rate(fs: float, seconds: float, model_path: Path, publish_period: float,
             executor: str, rt: int = 0, batch: int = 1, axes=('x',),
             amplitude: float = 100.0, floor: bool = False) -> dict:
    """
    Run command -> simulator -> estimator for `seconds` at `fs` Hz and observe it.

    rt > 0: the estimator under SCHED_FIFO at that priority, the probe 10 below (`realtime`).
    floor: the same streams between the nodes' bare stand-ins (floor_nodes.py), on a namespace
    of their own.
    """
    ns = f'/{"floor" if floor else "bench"}{int(fs)}'
    n = int(round(seconds * fs))
    os.environ['PIEZO_NARX_EXECUTOR'] = executor
    probe = Probe(ns, node_priority=rt, batch=batch)
    names = '[' + ','.join(f"'{a}'" for a in axes) + ']'
    common = (f'fs:={fs}', f'batch:={batch}', f'axes:={names}')
    if floor:
        procs = {'simulator': start('simulator_node', ns, *common, floor=True),
                 'estimator': start('estimator_node', ns, *common, prefix=realtime(rt),
                                    floor=True)}
    else:
        procs = {'simulator': start('simulator_node', ns, *common),
                 'estimator': start('estimator_node', ns, f'model:={model_path}', f'fs:={fs}',
                                    'init:=rest', f'batch:={batch}', prefix=realtime(rt))}
    result = {'fs': fs, 'n': n}
    try:
        ok = probe.spin_until(lambda: all(probe.subs[t].get_publisher_count() >= 1 for t in
                                          ('deflection', 'deflection_estimate')), 60.0)
        if not ok:
            raise not_up('simulator/estimator', procs)
        probe.spin_until(lambda: False, 0.5)
        if floor:
            procs['command'] = start('command_node', ns, *common, f'seconds:={seconds}',
                                     'wait_for_subscribers:=3', f'amplitude:={amplitude}',
                                     floor=True)
        else:
            procs['command'] = start('command_node', ns, f'fs:={fs}', 'loop:=false',
                                     f'seconds:={seconds}', 'wait_for_subscribers:=3',
                                     f'publish_period:={publish_period}', 'kind:=multisine',
                                     f'amplitude:={amplitude}', f'batch:={batch}',
                                     f'axes:={names}')
        cmd = probe.recv['voltage_command']
        probe.spin_until(lambda: len(cmd) > 0, 60.0)
        cpu0 = {k: cpu_seconds(p.pid) for k, p in procs.items()}
        t0 = time.monotonic()
        est = probe.recv['deflection_estimate']
        probe.spin_until(lambda: all(len(v) >= n for v in probe.recv.values()), seconds + 10.0)
        wall = time.monotonic() - t0
        cpu1 = {k: cpu_seconds(p.pid) for k, p in procs.items()}
        probe.spin_until(lambda: False, 1.2)   # one more /diagnostics round
        result['cpu'] = {k: 100.0 * (cpu1[k] - cpu0[k]) / wall for k in procs}
        # CPU time per sample streamed: less sensitive to how busy the machine is than % of a
        # core over the wall-clock interval (a starved node is slower, not cheaper).
        result['cpu_us_per_sample'] = {k: 1e6 * (cpu1[k] - cpu0[k]) / n for k in procs}
        result['lost'] = {t: n - len(v) for t, v in probe.recv.items()}
        lat = [est[t] - cmd[t] for t in est if t in cmd]
        result['latency_us'] = np.array(lat) / 1e3
        result['lateness_us'] = np.array([probe.wall[t] - t for t in est]) / 1e3
        result['diag'] = {k.rsplit('/', 1)[-1]: v for k, v in probe.diag.items()
                          if k.startswith(ns)}
    finally:
        result['codes'] = stop(procs.values())
        probe.close()
        result['errors'] = {k: p.stderr.read().strip().splitlines()[-3:]
                            for k, p in procs.items() if p.returncode}
    return result


ORDER = ('simulator', 'estimator', 'command')


def report(fs: float, seconds: float, r: dict, f: dict | None) -> None:
    """Print one rate's run `r` and, beside it, the floor's run `f` (None: no floor)."""
    print(f'\n--- {fs:g} Hz, {seconds:g} s, {r["n"]} samples '
          f'(exit codes {r["codes"]}{"; floor " + str(f["codes"]) if f else ""}; '
          f'load average now {os.getloadavg()[0]:.1f}) ---')
    for what, run in (('', r), ('floor ', f)):
        for k, lines in (run or {}).get('errors', {}).items():
            print(f'{what}{k} failed: ' + ' | '.join(lines))
    print('                                 p50      p99      max  (us)')
    print(f'latency command -> estimate  {pct(r["latency_us"])}')
    if f:
        print(f'floor latency                {pct(f["latency_us"])}')
    print(f'lateness stamp -> estimate   {pct(r["lateness_us"])}')
    print('lost samples: ' + ', '.join(f'{t} {v}' for t, v in r['lost'].items()))
    if f:
        print('floor lost samples: ' + ', '.join(f'{t} {v}' for t, v in f['lost'].items()))
    print('CPU (% of one core): ' + ', '.join(f'{k} {r["cpu"][k]:.0f}' for k in ORDER))
    if f:
        print('floor CPU (% of one core): ' + ', '.join(
            f'{k}_node {f["cpu"][k]:.0f}' for k in ORDER))
        print('CPU / floor: ' + ', '.join(f'{k} {ratio(r, f, k):.2f}' for k in ORDER)
              + '; within 1.15 x floor + 2 points: ' + ', '.join(
                  f'{k} {"yes" if r["cpu"][k] <= 1.15 * f["cpu"][k] + 2 else "no"}'
                  for k in ORDER))
    print('CPU per sample (us): ' + ', '.join(f'{k} {r["cpu_us_per_sample"][k]:.2f}'
                                              for k in ORDER))
    lat = np.percentile(r['latency_us'], [50, 99]) if len(r['latency_us']) else (math.nan,) * 2
    cpu = ' / '.join(f'{r["cpu"][k]:.0f}' for k in ORDER)
    floor = ('; CPU / floor ' + ' / '.join(f'{ratio(r, f, k):.2f}' for k in ORDER)) if f else ''
    headline(f'command -> simulator -> estimator over DDS, {fs:g} Hz, {seconds:g} s',
             f'{sum(r["lost"].values())} lost; latency p50 / p99 {lat[0] / 1e3:.2f} / '
             f'{lat[1] / 1e3:.2f} ms; CPU sim / est / cmd {cpu} %{floor}', '0 lost', 'nodes.md')
    d = r['diag']
    if 'command_node' in d:
        c = d['command_node']
        print(f"command node: late ticks {c.get('late_ticks')}, largest batch "
              f"{c.get('max_batch')}")
    if 'estimator_node' in d:
        e = d['estimator_node']
        print(f"estimator: gaps {e.get('gaps')}, filled {e.get('filled')}, "
              f"rejected {e.get('rejected_nonfinite')}/{e.get('rejected_range')}")
    if 'simulator_node' in d:
        print(f"simulator: gaps {d['simulator_node'].get('gaps')}")


def ratio(r: dict, f: dict, node: str) -> float:
    """Return a node's CPU over its floor's: CPU time per sample (the same samples streamed)."""
    floor = f['cpu_us_per_sample'][node]
    return r['cpu_us_per_sample'][node] / floor if floor > 0 else math.nan


def summary(fs: float, runs: list) -> None:
    """Print the medians over repeated (run, floor run) pairs of one rate."""
    def med(values):
        return float(np.median(values))
    print(f'\n=== {fs:g} Hz: medians of {len(runs)} runs ===')
    print('CPU (% of one core): ' + ', '.join(
        f'{k} {med([r["cpu"][k] for r, _ in runs]):.1f}' for k in ORDER))
    lat = [np.percentile(r['latency_us'], [50, 99]) for r, _ in runs if len(r['latency_us'])]
    if lat:
        print(f'latency p50 / p99 (us): {med([a[0] for a in lat]):.0f} / '
              f'{med([a[1] for a in lat]):.0f}')
    print('lost (largest): ' + ', '.join(f'{t} {max(r["lost"][t] for r, _ in runs)}'
                                         for t in runs[0][0]['lost']))
    if runs[0][1] is None:
        return
    print('floor CPU (% of one core): ' + ', '.join(
        f'{k}_node {med([f["cpu"][k] for _, f in runs]):.1f}' for k in ORDER))
    lat = [np.percentile(f['latency_us'], [50, 99]) for _, f in runs if len(f['latency_us'])]
    if lat:
        print(f'floor latency p50 / p99 (us): {med([a[0] for a in lat]):.0f} / '
              f'{med([a[1] for a in lat]):.0f}')
    print("CPU / floor (median of the runs' ratios): " + ', '.join(
        f'{k} {med([ratio(r, f, k) for r, f in runs]):.2f}' for k in ORDER))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.strip().split('\n\n')[0])
    ap.add_argument('--seconds', type=float, default=60.0, help='stream length per rate, s')
    ap.add_argument('--rates', default='2000,5000,10000', help='comma-separated rates, Hz')
    ap.add_argument('--model', default=None, help='model file (default: a toy NARX 4/4/10)')
    ap.add_argument('--publish-period', type=float, default=0.0,
                    help='command node timer period, s (0: one tick per sample)')
    ap.add_argument('--executor', choices=('events', 'single'), default='events',
                    help='executor of the node processes')
    ap.add_argument('--batch', type=int, default=1, metavar='N',
                    help='samples per message on every stream (1: one JointState per sample; '
                    'N > 1: JointTrajectory batches on the <topic>_batch topics)')
    ap.add_argument('--rt', type=int, default=0, metavar='PRIO',
                    help='run the estimator under SCHED_FIFO at PRIO and the probe at PRIO-10 '
                    '(needs CAP_SYS_NICE; 0: normal scheduling)')
    ap.add_argument('--axes', type=int, default=1, metavar='N',
                    help='axes per sample (N > 1: N independent cantilevers and an N x N ARX '
                    'model named x, y, z, a4...; every message carries every axis)')
    ap.add_argument('--floor', action='store_true',
                    help='after each run, the same streams between bare stand-ins of the nodes '
                    "(floor_nodes.py): their CPU and latency printed beside the nodes'")
    ap.add_argument('--repeat', type=int, default=1, metavar='N',
                    help='runs per rate (each followed by its floor run), then their medians')
    args = ap.parse_args(argv)
    axes = ['x', 'y', 'z'][:args.axes] + [f'a{i + 1}' for i in range(3, args.axes)]
    os.environ.setdefault('ROS_DOMAIN_ID', str(1 + os.getpid() % 100))
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')

    from piezo_narx_ros.ident.base import channel_ranges
    from piezo_narx_ros.ident.model_io import load_model, save_model
    tmp = tempfile.TemporaryDirectory()
    amplitude = 100.0
    if args.model:
        model_path = Path(args.model)
        model = load_model(model_path)
        if model.n_in > 1:   # the streams carry the model's own axis names, in its order
            axes = list(model.inputs)
        # Commands inside the range the model was fitted on (the FSM's are millivolts).
        rng = channel_ranges(model)[0]
        amplitude = float(np.max(np.abs(rng))) if rng is not None else amplitude
    elif len(axes) > 1:
        model = axes_model(axes, float(args.rates.split(',')[0]))
        model_path = save_model(model, Path(tmp.name) / 'axes.json')
    else:
        from piezo_narx_ros.estimator.toy import toy_narx
        model = toy_narx(nu=4, ny=4, hidden=10)
        model_path = save_model(model, Path(tmp.name) / 'toy.json')
    p50, p99 = estimator_compute(model)
    print(f'model: {type(model).__name__} nu={model.nu} ny={model.ny} '
          f'{getattr(model, "hidden", "")} hidden, axes {axes}; executor {args.executor}; '
          f'publish_period {args.publish_period or "1/fs"}; batch {args.batch}; '
          f'{os.cpu_count()} CPUs, '
          f'load average {os.getloadavg()[0]:.1f}')
    print(f'estimator compute per sample (FreeRunEstimator.on_command): p50 {p50:.2f} us, '
          f'p99 {p99:.2f} us (target p99 <= 5 us)')
    for fs in [float(r) for r in args.rates.split(',')]:
        if not args.model:   # a model runs only at its own rate: the toy model made for this one
            if len(axes) > 1:
                model = axes_model(axes, fs)
            else:
                model.fs = fs
            model_path = save_model(model, Path(tmp.name) / f'toy{fs:g}.json')
        runs = []
        for _ in range(args.repeat):
            r = run_rate(fs, args.seconds, model_path, args.publish_period, args.executor,
                         args.rt, args.batch, axes, amplitude)
            f = run_rate(fs, args.seconds, model_path, args.publish_period, args.executor,
                         args.rt, args.batch, axes, amplitude, floor=True) if args.floor else None
            report(fs, args.seconds, r, f)
            runs.append((r, f))
        if args.repeat > 1:
            summary(fs, runs)
    tmp.cleanup()
    return 0


if __name__ == '__main__':
    sys.exit(main())
