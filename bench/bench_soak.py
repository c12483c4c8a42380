"""Soak benchmark: command -> simulator -> estimator -> recorder at 2 kHz for 10 minutes, with
faults injected on a schedule, one process per node over DDS (isolated domain).

Faults (at 20, 35, 50 and 70 % of the run):
  sigstop    the simulator is stopped with SIGSTOP for 200 ms, then continued;
  burst      a second writer publishes 50 bad commands on voltage_command within ~50 ms: NaN
             values and outlier stamps (+0.5 s, +1 h, -0.25 s, random, duplicates of past ones);
  estimator  the estimator is stopped (SIGTERM) and a new one started (init auto: from the
             measurement);
  recorder   the recorder is killed (SIGKILL) and a new recorder started on a new bag; the
             killed bag is repaired with `repair_bag` after the run (not during it, so that the
             repair's CPU does not perturb the streams measured).
A probe in this process records the stamp and wall-clock arrival of every voltage_command,
deflection and deflection_estimate, and every /diagnostics status.

Printed:
- samples lost per stream, outside the injected windows (target 0) and inside them. A stream's
  window is the part of the run a fault could touch: every stream for sigstop and burst, the
  estimate for the estimator restart, the bag for the recorder kill; expected samples are the
  command node's grid t0 + k/fs from its first to its last stamp;
- recovery after each fault: when every stream's lateness (arrival - stamp) is back under the
  quiet-period threshold for 200 consecutive samples, counted from the end of the injection
  (for the restarts, from the kill: it includes the new process's start-up), and when the
  estimator's /diagnostics level is OK again;
- RSS of every node process after a 60 s warm-up and at its end, and the growth (target < 5 %),
  plus CPU per node;
- the estimator's counters (stamp outliers, restarts, rejected) and the repair report.

    python bench/bench_soak.py                 # 10 minutes at 2 kHz (the issue's run)
    python bench/bench_soak.py --minutes 2     # a shorter check of the same schedule
"""
from __future__ import annotations

import argparse
import array
import math
import os
import signal
import struct
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_live import cpu_seconds, start, stop  # noqa: E402 - this folder's shared helpers

NS = 1_000_000_000
TOPICS = ('voltage_command', 'deflection', 'deflection_estimate')
SCHEDULE = (('sigstop', 0.20), ('burst', 0.35), ('estimator', 0.50), ('recorder', 0.70))
WARMUP_S = 60.0


def rss_kib(pid: int) -> int | None:
    """Resident set size of a live process, KiB (None once it has exited)."""
    try:
        with open(f'/proc/{pid}/status') as f:
            for line in f:
                if line.startswith('VmRSS:'):
                    return int(line.split()[1])
    except FileNotFoundError:
        return None
    return None


class Probe:
    """Stamps and wall-clock arrivals of the three streams, /diagnostics, spun in a thread."""

    def __init__(self, ns: str):
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.experimental import EventsExecutor
        from rclpy.node import Node
        from sensor_msgs.msg import JointState

        from piezo_narx_ros.nodes.common import diagnostic_values, sample_qos
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = Node('soak_probe', namespace=ns, context=self.context)
        self.stamps = {t: array.array('q') for t in TOPICS}
        self.arrivals = {t: array.array('q') for t in TOPICS}
        self.diag: list[tuple[int, str, int, str, dict]] = []   # (wall ns, name, level, msg, kv)
        head = struct.Struct('<iI')
        wall = time.time_ns

        def make_cb(topic):
            stamps, arrivals = self.stamps[topic], self.arrivals[topic]

            def cb(raw):   # only the stamp: the probe must stay cheap
                sec, nsec = head.unpack_from(raw, 4)
                stamps.append(sec * NS + nsec)
                arrivals.append(wall())
            return cb

        def on_diag(arr):
            now = wall()
            for st in arr.status:
                self.diag.append((now, st.name, st.level[0] if isinstance(st.level, bytes)
                                  else int(st.level), st.message, diagnostic_values(st)))

        self.subs = {t: self.node.create_subscription(JointState, t, make_cb(t),
                                                      sample_qos(100000), raw=True)
                     for t in TOPICS}
        self.node.create_subscription(DiagnosticArray, '/diagnostics', on_diag, 1000)
        self.executor = EventsExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._run = True
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()

    def _spin(self):
        while self._run and self.context.ok():
            self.executor.spin_once(timeout_sec=0.05)

    def wait_for(self, predicate, timeout: float) -> bool:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if predicate():
                return True
            time.sleep(0.05)
        return False

    def close(self):
        import rclpy
        self._run = False
        self.thread.join(5)
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)


class Soak:
    """Starts the nodes, injects the faults, samples RSS/CPU, then analyses."""

    def __init__(self, args, work: Path, model: Path):
        self.args, self.work, self.model = args, work, model
        self.ns = f'/soak{os.getpid() % 1000}'
        self.fs = 2000.0
        self.period = int(round(NS / self.fs))
        self.procs: dict[str, subprocess.Popen] = {}   # 'estimator#2' etc.: every instance
        self.live: dict[str, str] = {}                  # role -> instance name
        self.rss: dict[str, list[tuple[float, int]]] = {}
        self.cpu: dict[str, tuple[float, float]] = {}
        self.events: dict[str, dict] = {}
        self.bags: list[Path] = []

    # -------------------------------------------------------------------------- processes
    def spawn(self, role: str, *params: str) -> None:
        n = sum(1 for k in self.procs if k.split('#')[0] == role) + 1
        name = f'{role}#{n}'
        module = {'command': 'command_node', 'simulator': 'simulator_node',
                  'estimator': 'estimator_node', 'recorder': 'recorder_node'}[role]
        self.procs[name] = start(module, self.ns, *params)
        self.live[role] = name
        self.cpu[name] = (time.monotonic(), cpu_seconds(self.procs[name].pid))
        self.rss[name] = []

    def retire(self, role: str) -> None:
        name = self.live.pop(role)
        proc = self.procs[name]
        t0, c0 = self.cpu[name]
        self.cpu[name] = (time.monotonic() - t0, cpu_seconds(proc.pid) - c0)

    def start_estimator(self) -> None:
        self.spawn('estimator', f'model:={self.model}', f'fs:={self.fs}')

    def start_recorder(self) -> None:
        bag = self.work / f'bag{len(self.bags) + 1}'
        self.bags.append(bag)
        self.spawn('recorder', f'output:={bag}', 'chunk_period_s:=0.5')

    def sample_rss(self, t: float) -> None:
        for role, name in self.live.items():
            kib = rss_kib(self.procs[name].pid)
            if kib is not None:
                self.rss[name].append((t, kib))

    # ------------------------------------------------------------------------------ faults
    def fault_sigstop(self) -> None:
        pid = self.procs[self.live['simulator']].pid
        t0 = time.time_ns()
        os.kill(pid, signal.SIGSTOP)
        time.sleep(0.2)
        os.kill(pid, signal.SIGCONT)
        self.events['sigstop'] = {'start': t0, 'end': time.time_ns(), 'streams': TOPICS}

    def fault_burst(self, probe: Probe) -> None:
        from sensor_msgs.msg import JointState

        from piezo_narx_ros.nodes.common import encode_joint_state, sample_qos
        pub = probe.node.create_publisher(JointState, 'voltage_command', sample_qos(1000))
        probe.wait_for(lambda: pub.get_subscription_count() >= 3, 10.0)
        rng = np.random.default_rng(1)
        t0 = time.time_ns()
        last = probe.stamps['voltage_command'][-1]
        offsets = [NS // 2, 3600 * NS, -NS // 4]
        for i in range(50):
            if i % 2:       # NaN value, random (odd: off-grid) stamp within +-1 h
                t, u = (last + int(rng.integers(-3600 * NS, 3600 * NS))) | 1, math.nan
            elif i % 10 == 0:   # a duplicate of a stamp already sent
                t, u = last - self.period * int(rng.integers(1, 100)), 50.0
            else:
                t, u = last + offsets[i % 3] + int(rng.integers(0, 10)) * self.period, 50.0
            pub.publish(encode_joint_state(t, ['x'], effort=(u,)))
            time.sleep(0.001)
        t1 = time.time_ns()
        time.sleep(0.5)
        probe.node.destroy_publisher(pub)
        self.events['burst'] = {'start': t0, 'end': t1, 'streams': TOPICS}

    def fault_estimator(self, probe: Probe) -> None:
        old = self.procs[self.live['estimator']]
        t0 = time.time_ns()
        self.retire('estimator')
        old.send_signal(signal.SIGTERM)
        old.wait(20)
        self.start_estimator()
        n = len(probe.stamps['deflection_estimate'])
        probe.wait_for(lambda: len(probe.stamps['deflection_estimate']) > n, 60.0)
        first = probe.arrivals['deflection_estimate'][n] if len(
            probe.arrivals['deflection_estimate']) > n else time.time_ns()
        self.events['estimator'] = {'start': t0, 'end': first, 'streams': ('deflection_estimate',),
                                    'code': old.returncode}

    def fault_recorder(self) -> None:
        old = self.procs[self.live['recorder']]
        t0 = time.time_ns()
        self.retire('recorder')
        old.kill()
        old.wait(10)
        self.start_recorder()
        self.events['recorder'] = {'start': t0, 'end': None, 'streams': ('bag',),
                                   'killed_bag': self.bags[-2]}

    def repair_killed_bag(self) -> None:
        from piezo_narx_ros.bag.repair import repair_bag
        e = self.events.get('recorder')
        if e is None:
            return
        r0 = time.monotonic()
        report = repair_bag(e['killed_bag'])
        e.update(repair_s=time.monotonic() - r0, repaired=report.messages,
                 dropped_bytes=report.dropped_bytes, intact=report.intact)

    # --------------------------------------------------------------------------------- run
    def run(self) -> Probe:
        seconds = self.args.minutes * 60.0
        probe = Probe(self.ns)
        self.spawn('simulator', f'fs:={self.fs}')
        self.start_estimator()
        self.start_recorder()
        if not probe.wait_for(lambda: all(probe.subs[t].get_publisher_count() >= 1
                                          for t in TOPICS[1:]), 90.0):
            raise RuntimeError('simulator/estimator did not come up')
        time.sleep(2.0)   # recorder and estimator <-> simulator matching
        self.spawn('command', f'fs:={self.fs}', 'kind:=multisine', 'amplitude:=100.0',
                   'seconds:=25.0', 'loop:=true', 'wait_for_subscribers:=4')
        if not probe.wait_for(lambda: len(probe.stamps['voltage_command']) > 0, 60.0):
            raise RuntimeError('command node did not start streaming')
        t_start = time.monotonic()
        self.stream_start_ns = probe.stamps['voltage_command'][0]
        due = [(frac * seconds, name) for name, frac in SCHEDULE]
        next_rss = 0.0
        while (elapsed := time.monotonic() - t_start) < seconds:
            if elapsed >= next_rss:
                self.sample_rss(elapsed)
                next_rss += 5.0
            if due and elapsed >= due[0][0]:
                _, name = due.pop(0)
                print(f'  t={elapsed:6.1f} s: fault {name}', flush=True)
                {'sigstop': self.fault_sigstop, 'burst': lambda: self.fault_burst(probe),
                 'estimator': lambda: self.fault_estimator(probe),
                 'recorder': self.fault_recorder}[name]()
            for name in list(self.live.values()):
                if self.procs[name].poll() is not None:
                    raise RuntimeError(f'{name} exited with {self.procs[name].returncode}: '
                                       + self.procs[name].stderr.read()[-500:])
            time.sleep(0.05)
        self.sample_rss(time.monotonic() - t_start)
        for role in list(self.live):
            self.retire(role)
        self.codes = dict(zip(self.procs, stop([self.procs[n] for n in self.procs])))
        time.sleep(0.5)
        self.repair_killed_bag()
        return probe


# ------------------------------------------------------------------------------------ analysis
def grid(stamps: np.ndarray, t0: int, period: int) -> np.ndarray:
    """Sample indices k of the stamps on the command grid t0 + k * period (others dropped)."""
    d = stamps - t0
    on = (d % period == 0) & (d >= 0)
    return np.unique(d[on] // period)


def in_windows(k: np.ndarray, t0: int, period: int, windows) -> np.ndarray:
    t = t0 + k * period
    mask = np.zeros(k.size, bool)
    for a, b in windows:
        mask |= (t >= a) & (t <= b)
    return mask


def recovery_ms(probe: Probe, start_ns: int, thr_ns: float, t0: int, period: int,
                run: int = 200) -> float:
    """ms from start_ns until every stream's samples stamped after it arrive within thr_ns of
    their stamp for `run` consecutive samples (nan if never)."""
    worst = 0.0
    for topic in TOPICS:
        s = np.frombuffer(probe.stamps[topic], np.int64)
        a = np.frombuffer(probe.arrivals[topic], np.int64)
        on = ((s - t0) % period == 0) & (s >= start_ns)
        s, late = s[on], (a[on] - s[on])
        order = np.argsort(s, kind='stable')
        s, late = s[order], late[order]
        ok = late <= thr_ns
        # first index i with ok[i:i+run] all true
        c = np.convolve(ok.astype(int), np.ones(run, int), 'valid')
        hit = np.flatnonzero(c == run)
        if hit.size == 0:
            return math.nan
        worst = max(worst, (s[hit[0]] + late[hit[0]] - start_ns) / 1e6)
    return worst


def bag_stamps(bags) -> dict[str, np.ndarray]:
    """{topic name without namespace: header stamps (ns)} over all bags, in one pass each."""
    from piezo_narx_ros.bag.reader import iter_raw
    head = struct.Struct('<iI')
    out = {t: array.array('q') for t in TOPICS}
    for bag in bags:
        for topic, _, _, raw in iter_raw(bag):
            sec, nsec = head.unpack_from(raw, 4)
            out[topic.rsplit('/', 1)[-1]].append(sec * NS + nsec)
    return {t: np.frombuffer(a, np.int64) for t, a in out.items()}


def analyse(soak: Soak, probe: Probe) -> None:
    period = soak.period
    cmd = np.frombuffer(probe.stamps['voltage_command'], np.int64)
    arrived = np.frombuffer(probe.arrivals['voltage_command'], np.int64)
    t0 = soak.stream_start_ns
    # The command node's own samples: the burst's outlier stamps (+0.5 s, +1 h) are on the
    # grid too, but arrive far from their stamp.
    k_cmd = grid(cmd[np.abs(arrived - cmd) < 30 * NS], t0, period)
    k_all = np.arange(k_cmd.min(), k_cmd.max() + 1)
    end_ns = t0 + int(k_all[-1]) * period
    margin = NS // 2
    ev = soak.events
    in_bags = bag_stamps(soak.bags)
    if 'recorder' in ev and ev['recorder']['end'] is None:
        first = bag_stamps(soak.bags[-1:])['voltage_command']
        ev['recorder']['end'] = int(first.min()) if first.size else end_ns
    print(f'\nstream: {k_all.size} command samples at {soak.fs:g} Hz over '
          f'{k_all.size / soak.fs:.1f} s')

    # Lateness threshold from the quiet part before the first fault.
    first_fault = min(e['start'] for e in ev.values())
    quiet = []
    for topic in TOPICS:
        s = np.frombuffer(probe.stamps[topic], np.int64)
        a = np.frombuffer(probe.arrivals[topic], np.int64)
        sel = (s > t0 + 10 * NS) & (s < first_fault - NS)
        quiet.append(a[sel] - s[sel])
    quiet = np.concatenate(quiet)
    p50, p99 = np.percentile(quiet, [50, 99])
    thr = max(3 * p99, 5e6)
    print(f'quiet-period lateness (arrival - stamp, all streams): p50 {p50 / 1e6:.2f} ms, '
          f'p99 {p99 / 1e6:.2f} ms; recovered = {run_ms(thr)} for 200 samples')

    print('\nsamples lost (expected: the command grid from its first to its last stamp)')
    print(f'{"stream":<22} {"expected":>9} {"lost outside windows":>21} {"lost inside":>12}')
    streams = {t: grid(np.frombuffer(probe.stamps[t], np.int64), t0, period) for t in TOPICS}
    for topic in TOPICS:
        streams[f'bag {topic}'] = grid(in_bags[topic], t0, period)
    for name, k in streams.items():
        missing = np.setdiff1d(k_all, k)
        key = 'bag' if name.startswith('bag') else name
        windows = [(e['start'] - margin, (e['end'] or end_ns) + margin) for e in ev.values()
                   if key in e['streams'] or (key != 'bag' and e['streams'] == TOPICS)]
        inside = in_windows(missing, t0, period, windows)
        print(f'{name:<22} {k_all.size:>9} {int((~inside).sum()):>21} {int(inside.sum()):>12}')

    print('\nrecovery after each fault')
    diag = [(t, lvl, msg) for t, name, lvl, msg, _ in probe.diag if 'estimator' in name]
    for name, e in ev.items():
        ref = e['start'] if name in ('estimator', 'recorder') else e['end']
        rec = recovery_ms(probe, ref, thr, t0, period)
        ok_at = next((t for t, lvl, _ in diag if t > e['end'] and lvl == 0), None)
        warn = [msg for t, lvl, msg in diag if e['start'] <= t <= (ok_at or end_ns) and lvl]
        extra = ''
        if name == 'estimator':
            extra = (f'; new estimator\'s first estimate {(e["end"] - e["start"]) / 1e6:.0f} ms '
                     f'after SIGTERM (old one exited {e["code"]})')
        if name == 'recorder':
            extra = (f'; new recorder\'s first message {(e["end"] - e["start"]) / 1e6:.0f} ms '
                     f'after SIGKILL; repair {e["repair_s"]:.2f} s, {e["repaired"]} messages '
                     f'recovered, {e["dropped_bytes"]} bytes dropped')
        diag_text = (f'estimator /diagnostics OK again {(ok_at - e["end"]) / 1e9:.1f} s after'
                     if ok_at else 'estimator /diagnostics not OK again')
        print(f'{name:<10} streams caught up {rec:8.0f} ms after '
              f'{"the kill" if ref == e["start"] else "the injection"}; {diag_text}'
              f'{" (WARN: " + warn[0] + ")" if warn else ""}{extra}')

    print(f'\nRSS per node process (after {WARMUP_S:.0f} s warm-up -> end) and CPU')
    print(f'{"process":<14} {"RSS start MiB":>13} {"end MiB":>8} {"growth %":>9} {"CPU %":>6}'
          f' {"exit":>5}')
    for name, samples in soak.rss.items():
        t_first = samples[0][0] if samples else 0.0
        base = [kib for t, kib in samples if t >= t_first + WARMUP_S]
        wall, cpu = soak.cpu[name]
        if len(base) >= 2:
            growth = 100.0 * (base[-1] - base[0]) / base[0]
            print(f'{name:<14} {base[0] / 1024:>13.1f} {base[-1] / 1024:>8.1f} {growth:>9.2f} '
                  f'{100 * cpu / wall:>6.0f} {soak.codes.get(name)!s:>5}')
        else:
            print(f'{name:<14} {"(ran < warm-up)":>13} {"":>8} {"":>9} {100 * cpu / wall:>6.0f}'
                  f' {soak.codes.get(name)!s:>5}')

    last = {}
    for t, name, lvl, msg, kv in probe.diag:
        last[name] = kv
    for name, kv in last.items():
        if 'estimator' in name:
            print(f'\n{name}: ' + ', '.join(f'{k} {kv.get(k)}' for k in (
                'commands', 'estimates', 'stamp_outliers', 'stream_restarts',
                'rejected_nonfinite', 'gaps', 'filled', 'out_of_range', 'init')))
        if 'simulator' in name:
            print(f'{name}: ' + ', '.join(f'{k} {kv.get(k)}' for k in (
                'answered', 'rejected', 'stamp_outliers', 'stream_restarts', 'gaps')))


def run_ms(thr: float) -> str:
    return f'lateness <= {thr / 1e6:.1f} ms'


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--minutes', type=float, default=10.0, help='run length (default 10)')
    ap.add_argument('--model', default=None,
                    help='model file (default bags/model.json, else a toy NARX)')
    ap.add_argument('--keep', metavar='DIR', help='keep the bags in DIR (default: a temp dir)')
    args = ap.parse_args(argv)
    if args.minutes < 1.0:
        ap.error('--minutes must be >= 1 (the warm-up alone is 1 minute)')
    os.environ.setdefault('ROS_DOMAIN_ID', str(1 + os.getpid() % 100))
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    tmp = tempfile.TemporaryDirectory(prefix='soak-')
    work = Path(args.keep) if args.keep else Path(tmp.name)
    work.mkdir(parents=True, exist_ok=True)
    repo_model = Path(__file__).resolve().parents[1] / 'bags' / 'model.json'
    model = Path(args.model) if args.model else repo_model
    if not model.is_file():
        from piezo_narx_ros.estimator.toy import toy_narx
        from piezo_narx_ros.ident.model_io import save_model
        model = save_model(toy_narx(nu=4, ny=4, hidden=10, fs=2000.0), work / 'toy.json')
    load0 = os.getloadavg()
    print(f'soak: {args.minutes:g} min at 2 kHz, model {model}, {os.cpu_count()} CPUs, load '
          f'average {load0[0]:.2f} / {load0[1]:.2f} / {load0[2]:.2f} at start', flush=True)
    soak = Soak(args, work, model)
    probe = None
    try:
        probe = soak.run()
        analyse(soak, probe)
    finally:
        live = [p for p in soak.procs.values() if p.poll() is None]
        for p in live:
            try:
                os.kill(p.pid, signal.SIGCONT)
            except ProcessLookupError:
                pass
        stop(live)
        if probe is not None:
            probe.close()
        load1 = os.getloadavg()
        print(f'\nload average at end {load1[0]:.2f} / {load1[1]:.2f} / {load1[2]:.2f}')
        if not args.keep:
            tmp.cleanup()
    return 0


if __name__ == '__main__':
    sys.exit(main())
