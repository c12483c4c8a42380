"""
Soak benchmark.

Command -> simulator -> estimator -> recorder at 2 kHz for 10 minutes, with faults injected on a
schedule, one process per node over DDS (isolated domain).

Faults (at 20, 35, 50 and 70 % of the run):
  sigstop    the simulator is stopped with SIGSTOP for 200 ms, then continued;
  burst      a second writer publishes 50 bad commands on voltage_command within ~50 ms: NaN
             values and outlier stamps (+0.5 s, +1 h, -0.25 s, random, duplicates of past ones);
  estimator  the estimator is stopped (SIGTERM) and a new one started (init auto: from the
             measurement);
  recorder   the recorder is killed (SIGKILL) and a new recorder started on a new bag; the
             killed bag is repaired with `repair_bag` after the run (not during it, so that the
             repair's CPU does not perturb the streams measured).
The recorder is the observer: every sample's stamp and arrival time (the bag's receive time) come
from its bags, so the run carries no extra subscriber on the 2 kHz streams; a probe in this
process only listens to /diagnostics (and reads one command stamp for the burst).

Printed:
- samples lost per stream, outside the injected windows (target 0) and inside them. A stream's
  window is the part of the run a fault could touch (from 0.5 s before the injection to 0.5 s
  after it ends): every stream for sigstop and burst, the estimate for the estimator restart
  (until the new estimator's first estimate: the first stamped after the old process exited),
  every stream for the recorder kill (until the new recorder's first message of that stream).
  Expected samples are the command node's grid t0 + k/fs from its first to its last recorded
  stamp;
- recovery after each fault: when every stream's lateness (arrival - stamp) is back under the
  quiet-period threshold for 200 consecutive samples, counted from the end of the injection
  (for the restarts, from the kill: it includes the new process's start-up), and when the
  estimator's /diagnostics level is OK again;
- RSS of every node process after a 60 s warm-up and at its end, and the growth (target < 5 %),
  plus CPU per node;
- each estimator's and the simulator's counters (stamp outliers, restarts, rejected, gaps) and
  the repair report.

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
    """/diagnostics of every node (wall ns, name, level, message, values), spun in a thread."""

    def __init__(self, ns: str):
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.experimental import EventsExecutor
        from rclpy.node import Node

        from piezo_narx_ros.nodes.diagnostics import diagnostic_values
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = Node('soak_probe', namespace=ns, context=self.context)
        self.diag: list[tuple[int, str, int, str, dict]] = []

        def on_diag(arr):
            now = time.time_ns()
            for st in arr.status:
                level = st.level[0] if isinstance(st.level, bytes) else int(st.level)
                self.diag.append((now, st.name, level, st.message, diagnostic_values(st)))

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

    def status(self, role: str, after_ns: int = 0) -> dict | None:
        """Values of the latest status of `role` (e.g. 'estimator') received after after_ns."""
        for t, name, _, _, kv in reversed(self.diag):
            if t <= after_ns:
                return None
            if role in name:
                return kv
        return None

    def one_command_stamp(self, timeout: float = 10.0) -> int:
        """Return the stamp of one voltage_command (a temporary raw subscription)."""
        from sensor_msgs.msg import JointState

        from piezo_narx_ros.nodes.qos import sample_qos
        got = []
        head = struct.Struct('<iI')

        def cb(raw):
            sec, nsec = head.unpack_from(raw, 4)
            got.append(sec * NS + nsec)
        sub = self.node.create_subscription(JointState, 'voltage_command', cb, sample_qos(100),
                                            raw=True)
        self.wait_for(lambda: got, timeout)
        self.node.destroy_subscription(sub)
        if not got:
            raise RuntimeError('no voltage_command seen')
        return got[-1]

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
        self.load: list[float] = []                     # 1-min load average every 5 s

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
        self.load.append(os.getloadavg()[0])
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

        from piezo_narx_ros.nodes.wire import encode_joint_state
        from piezo_narx_ros.nodes.qos import sample_qos
        last = probe.one_command_stamp()
        pub = probe.node.create_publisher(JointState, 'voltage_command', sample_qos(1000))
        probe.wait_for(lambda: pub.get_subscription_count() >= 3, 10.0)
        rng = np.random.default_rng(1)
        t0 = time.time_ns()
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
        # Everything stamped from here on can only be the new process's: the old one is gone.
        self.events['estimator'] = {'start': t0, 'end': None, 'streams': ('deflection_estimate',),
                                    'code': old.returncode, 'exited': time.time_ns(),
                                    'last_status': probe.status('estimator')}
        self.start_estimator()
        # Back when the new estimator reports estimates (the exact first one: from the bag).
        probe.wait_for(lambda: int((probe.status('estimator', t0) or {}).get('estimates', 0)) > 0,
                       60.0)

    def fault_recorder(self) -> None:
        old = self.procs[self.live['recorder']]
        t0 = time.time_ns()
        self.retire('recorder')
        old.kill()
        old.wait(10)
        self.start_recorder()
        self.events['recorder'] = {'start': t0, 'end': None, 'streams': TOPICS,
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
        if not probe.wait_for(lambda: all(probe.status(r) is not None for r in
                                          ('simulator', 'estimator', 'recorder')), 90.0):
            raise RuntimeError('simulator/estimator/recorder did not come up')
        time.sleep(2.0)   # recorder and estimator <-> simulator matching
        self.spawn('command', f'fs:={self.fs}', 'kind:=multisine', 'amplitude:=100.0',
                   'seconds:=25.0', 'loop:=true', 'wait_for_subscribers:=3')
        if not probe.wait_for(lambda: int((probe.status('command') or {}).get('published', 0))
                              > 0, 60.0):
            raise RuntimeError('command node did not start streaming')
        t_start = time.monotonic()
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
        # Stop the commands first and let the pipeline drain, so that a backlog still in flight
        # at the end is not counted as lost.
        command = self.procs[self.live['command']]
        self.retire('command')
        stop([command])
        t_drain = time.monotonic()
        last, since = -1, time.monotonic()
        while time.monotonic() - t_drain < 120.0 and time.monotonic() - since < 3.0:
            received = int((probe.status('recorder') or {}).get('received', 0))
            if received != last:
                last, since = received, time.monotonic()
            time.sleep(0.2)
        self.drain_s = since - t_drain
        for role in list(self.live):
            self.retire(role)
        self.codes = dict(zip(self.procs, stop([self.procs[n] for n in self.procs])))
        time.sleep(0.5)
        self.repair_killed_bag()
        return probe


# ------------------------------------------------------------------------------------ analysis
def read_bags(bags) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """
    Read the header stamps and receive times of every stream over all bags.

    {topic without namespace: (header stamps ns, receive times ns)}, sorted by receive time; one
    pass per bag, only the stamp decoded.
    """
    from piezo_narx_ros.bag.reader import iter_raw
    head = struct.Struct('<iI')
    out = {t: (array.array('q'), array.array('q')) for t in TOPICS}
    for bag in bags:
        for topic, _, log_ns, raw in iter_raw(bag):
            sec, nsec = head.unpack_from(raw, 4)
            stamps, logs = out[topic.rsplit('/', 1)[-1]]
            stamps.append(sec * NS + nsec)
            logs.append(log_ns)
    return {t: (np.frombuffer(s, np.int64), np.frombuffer(a, np.int64))
            for t, (s, a) in out.items()}


def on_grid(stamps: np.ndarray, t0: int, period: int) -> np.ndarray:
    """Mask of the stamps on the command grid t0 + k * period, k >= 0."""
    d = stamps - t0
    return (d % period == 0) & (d >= 0)


def recovery_ms(data, start_ns: int, thr_ns: float, t0: int, period: int,
                run: int = 200) -> float:
    """
    Return the time (ms) from start_ns until every stream is on time again, nan if never.

    On time: the stream's samples stamped after start_ns arrive within thr_ns of their stamp for
    `run` consecutive samples.
    """
    worst = 0.0
    for stamps, logs in data.values():
        sel = on_grid(stamps, t0, period) & (stamps >= start_ns)
        s, late = stamps[sel], logs[sel] - stamps[sel]
        order = np.argsort(s, kind='stable')
        s, late = s[order], late[order]
        hits = np.convolve((late <= thr_ns).astype(int), np.ones(run, int), 'valid')
        first = np.flatnonzero(hits == run)
        if first.size == 0:
            return math.nan
        worst = max(worst, (s[first[0]] + late[first[0]] - start_ns) / 1e6)
    return worst


def window_end(event: dict, topic: str) -> int:
    """End of a fault's window for one stream, ns: a restart's is per stream (analyse)."""
    end = event['end']
    return end[topic] if isinstance(end, dict) else end


def counters(kv: dict | None, keys) -> str:
    return ', '.join(f'{k} {(kv or {}).get(k)}' for k in keys)


ESTIMATOR_KEYS = ('commands', 'estimates', 'stamp_outliers', 'stream_restarts',
                  'rejected_nonfinite', 'rejected_range', 'refused_messages', 'gaps', 'filled',
                  'out_of_range', 'init')


def analyse(soak: Soak, probe: Probe) -> None:
    period, ev, margin = soak.period, soak.events, NS // 2
    data = read_bags(soak.bags)
    cmd, cmd_log = data['voltage_command']
    # The command node's own samples: the burst's outlier stamps (+0.5 s, +1 h) can be on the
    # grid too, but arrive far from their stamp.
    own = cmd[np.abs(cmd_log - cmd) < 30 * NS]
    t0 = int(own.min())
    k_own = (own[on_grid(own, t0, period)] - t0) // period
    k_all = np.arange(0, int(k_own.max()) + 1)
    end_ns = t0 + int(k_all[-1]) * period
    # Each restart's window ends at the first sample of the process that replaces the faulty
    # one, per stream: not at the old process's last words after its SIGTERM.
    if 'estimator' in ev:
        # The new estimator's first estimate: stamped after the old process exited (whatever
        # the old one published between SIGTERM and its exit carries earlier stamps).
        s, logs = data['deflection_estimate']
        later = logs[s >= ev['estimator']['exited']]
        ev['estimator']['end'] = {'deflection_estimate': int(later.min()) if later.size
                                  else end_ns}
    if 'recorder' in ev:
        fresh = read_bags(soak.bags[-1:])      # the new recorder's own bag
        ev['recorder']['end'] = {t: int(fresh[t][1].min()) if fresh[t][1].size else end_ns
                                 for t in TOPICS}
    load = np.array(soak.load)
    print(f'\n1-minute load average during the run (every 5 s): min {load.min():.2f}, median '
          f'{np.median(load):.2f}, max {load.max():.2f} ({os.cpu_count()} cores)')
    print(f'stream: {k_all.size} command samples at {soak.fs:g} Hz over '
          f'{k_all.size / soak.fs:.1f} s; the pipeline drained {soak.drain_s:.1f} s after the '
          'command node stopped')

    first_fault = min(e['start'] for e in ev.values())
    quiet = []
    for s, logs in data.values():
        # the grid's samples only: a burst's random stamp may fall in this period too
        sel = on_grid(s, t0, period) & (s > t0 + 10 * NS) & (s < first_fault - NS) & \
            (logs - s < 30 * NS)
        quiet.append(logs[sel] - s[sel])
    quiet = np.concatenate(quiet)
    p50, p99, pmax = np.percentile(quiet, [50, 99, 100])
    thr = max(3 * p99, 5e6)
    print(f'quiet-period lateness (receive - stamp, all streams, before the first fault): '
          f'p50 {p50 / 1e6:.2f} ms, p99 {p99 / 1e6:.2f} ms, max {pmax / 1e6:.1f} ms; recovered '
          f'= lateness <= {thr / 1e6:.1f} ms for 200 consecutive samples of every stream')

    print('\nsamples lost (expected: the command grid from its first to its last stamp)')
    print(f'{"stream":<22} {"expected":>9} {"lost outside windows":>21} {"lost inside":>12}')
    for topic, (stamps, _) in data.items():
        k = np.unique((stamps[on_grid(stamps, t0, period)] - t0) // period)
        missing = np.setdiff1d(k_all, k)
        windows = [(e['start'] - margin, window_end(e, topic) + margin) for e in ev.values()
                   if topic in e['streams']]
        t_missing = t0 + missing * period
        inside = np.zeros(missing.size, bool)
        for a, b in windows:
            inside |= (t_missing >= a) & (t_missing <= b)
        print(f'{topic:<22} {k_all.size:>9} {int((~inside).sum()):>21} {int(inside.sum()):>12}')

    print('\nrecovery after each fault')
    diag = [(t, lvl, msg) for t, name, lvl, msg, _ in probe.diag if 'estimator' in name]
    for e in ev.values():       # from here on one end per fault: its last stream's
        e['end'] = max(e['end'].values()) if isinstance(e['end'], dict) else e['end']
    for name, e in ev.items():
        restart = name in ('estimator', 'recorder')
        rec = recovery_ms(data, e['start'] if restart else e['end'], thr, t0, period)
        ok_at = next((t for t, lvl, _ in diag if t > e['end'] and lvl == 0), None)
        warn = next((msg for t, lvl, msg in diag if e['start'] <= t and lvl and
                     (ok_at is None or t <= ok_at)), None)
        text = (f'{name:<10} streams caught up {rec:7.0f} ms after '
                f'{"the kill" if restart else "the injection"}; estimator /diagnostics ' +
                (f'OK again {(ok_at - e["end"]) / 1e9:.1f} s after' if ok_at else 'not OK again'))
        if warn:
            text += f' (WARN meanwhile: {warn})'
        if name == 'estimator':
            text += (f'; the new estimator\'s first estimate {(e["end"] - e["start"]) / 1e6:.0f} '
                     f'ms after SIGTERM (old one exited {e["code"]})')
        if name == 'recorder':
            text += (f'; the new recorder\'s first message {(e["end"] - e["start"]) / 1e6:.0f} ms'
                     f' after SIGKILL; repair {e["repair_s"]:.2f} s, {e["repaired"]} messages '
                     f'recovered, {e["dropped_bytes"]} bytes dropped')
        print(text)

    print(f'\nRSS per node process ({WARMUP_S:.0f} s after its start -> its end) and CPU')
    print(f'{"process":<14} {"RSS start MiB":>13} {"end MiB":>8} {"growth %":>9} {"CPU %":>6}'
          f' {"exit":>5}')
    for name, samples in soak.rss.items():
        wall, cpu = soak.cpu[name]
        t_first = samples[0][0] if samples else 0.0
        base = [kib for t, kib in samples if t >= t_first + WARMUP_S]
        if len(base) >= 2:
            growth = 100.0 * (base[-1] - base[0]) / base[0]
            cols = f'{base[0] / 1024:>13.1f} {base[-1] / 1024:>8.1f} {growth:>9.2f}'
        else:
            cols = f'{"(ran < 60 s)":>13} {"":>8} {"":>9}'
        print(f'{name:<14} {cols} {100 * cpu / wall:>6.0f} {soak.codes.get(name)!s:>5}')
    busy = sum(cpu for wall, cpu in soak.cpu.values()) / (soak.args.minutes * 60.0)
    print(f'the nodes together: {100 * busy:.0f} % of one core on average')

    if 'estimator' in ev:
        print('\nestimator#1 before its restart: '
              + counters(ev['estimator']['last_status'], ESTIMATOR_KEYS))
    print('estimator at the end: ' + counters(probe.status('estimator'), ESTIMATOR_KEYS))
    print('simulator at the end: ' + counters(probe.status('simulator'), (
        'answered', 'rejected', 'stamp_outliers', 'stream_restarts', 'gaps', 'filled')))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.strip().split('\n\n')[0])
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
