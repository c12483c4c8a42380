"""
Benchmark the bag recorder.

Messages lost at 2 kHz (and higher) on three topics, CPU of the recorder process, and offline
writer/reader throughput.

    python bench/bench_recorder.py --seconds 5 --rates 2000 5000
    python bench/bench_recorder.py --seconds 60 --rates 20000 --batch 20

Live part: recorder_node runs in its own process (isolated DDS domain, localhost only); this
process publishes JointState samples on voltage_command, deflection and deflection_estimate at
each rate for `seconds`, then SIGINTs the recorder and counts what is in the bag ('lost' = sent
- recorded, 'gaps' = samples missing in the header stamps). 'CPU %' is the recorder's user+system
time while the samples stream (/proc) per wall second, in % of one core; 'CPU % all' is over the
recorder's whole life (start-up, drain and close included, os.wait4). With `--batch N` the
samples go out N per message as the nodes' batched streams (JointTrajectory on `<topic>_batch`,
recorder_node batch:=N); 'sent', 'recorded' and 'lost' still count samples. Offline part:
BagWriter and read_uy on the same message count, median of `--repeats` runs.
"""
from __future__ import annotations

import argparse
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from headline import headline


os.environ.setdefault('ROS_DOMAIN_ID', str(101 + os.getpid() % 100))
os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'

TOPICS = ('voltage_command', 'deflection', 'deflection_estimate')
T0 = 1_700_000_000_000_000_000


def cpu_seconds(pid: int) -> float:
    """User + system CPU time of a running process, s (from /proc)."""
    fields = Path(f'/proc/{pid}/stat').read_text().rsplit(')', 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK')


def live_run(rate: float, seconds: float, workdir: Path, batch: int = 1) -> dict:
    """One recorder process, three topics at `rate` Hz for `seconds` s, `batch` per message."""
    import rclpy
    from rclpy.node import Node
    from rclpy.serialization import serialize_message

    from piezo_narx_ros.bag.reader import bag_info
    from piezo_narx_ros.nodes.wire.batching import batch_topic, sample_type
    from piezo_narx_ros.nodes.wire import encode_joint_trajectory, make_joint_state
    from piezo_narx_ros.nodes.qos import sample_qos

    ns = f'/bench{int(rate)}'
    bag = workdir / f'rec_{int(rate)}'
    proc = subprocess.Popen([sys.executable, '-m', 'piezo_narx_ros.nodes.recorder_node',
                             '--ros-args', '-r', f'__ns:={ns}', '-p', f'output:={bag}',
                             '-p', f'batch:={batch}'],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    started = time.monotonic()
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    node = Node('bench_pub', namespace=ns, context=ctx)
    pubs = [node.create_publisher(sample_type(batch), batch_topic(t, batch),
                                  sample_qos(depth=1000)) for t in TOPICS]
    end = time.monotonic() + 30
    while any(p.get_subscription_count() < 1 for p in pubs) and time.monotonic() < end:
        time.sleep(0.02)
    n = int(rate * seconds)
    period = int(round(1e9 / rate))
    # Pre-serialized payloads keep this publisher cheap, so the recorder is what is measured.
    if batch > 1:
        k = np.arange(n)
        payloads = [encode_joint_trajectory(T0 + k[i:i + batch] * period, ['x'],
                                            k[i:i + batch, None] * 1e-9,
                                            k[i:i + batch, None] * 1e-3)
                    for i in range(0, n, batch)]
    else:
        payloads = [serialize_message(make_joint_state(T0 + k * period, ['x'], effort=[k * 1e-3],
                                                       position=[k * 1e-9])) for k in range(n)]
    cpu0, t_pub = cpu_seconds(proc.pid), time.monotonic()
    for i, payload in enumerate(payloads):
        for p in pubs:
            p.publish(payload)
        ahead = t_pub + (i + 1) * batch / rate - time.monotonic()
        if ahead > 0.002:
            time.sleep(ahead)
    pub_wall = time.monotonic() - t_pub
    cpu_streaming = (cpu_seconds(proc.pid) - cpu0) / pub_wall
    time.sleep(1.0)  # let the reliable streams drain
    proc.send_signal(signal.SIGINT)
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.monotonic() - started
    proc.returncode = os.waitstatus_to_exitcode(status)
    node.destroy_node()
    rclpy.try_shutdown(context=ctx)
    info = bag_info(bag)
    counts = {t.name: t.samples for t in info.topics}
    gaps = sum(t.missing for t in info.topics)
    return {'rate': rate, 'batch': batch, 'sent_per_topic': n, 'pub_rate': n / pub_wall,
            'recorded': counts, 'lost': 3 * n - sum(counts.values()), 'missing_in_stamps': gaps,
            'cpu_total': (usage.ru_utime + usage.ru_stime) / wall, 'cpu': cpu_streaming,
            'exit': proc.returncode,
            'bag_mb': sum(f.stat().st_size for f in bag.iterdir()) / 1e6}


def offline(n_samples: int, repeats: int, workdir: Path) -> dict:
    """Measure BagWriter throughput (2 topics, pre-serialized) and read_uy throughput, medians."""
    from piezo_narx_ros.bag.reader import read_uy
    from piezo_narx_ros.bag.writer import JOINT_STATE, BagWriter, joint_state_cdr

    cmd = [joint_state_cdr(T0 + k * 500_000, effort=(k * 1e-3,)) for k in range(n_samples)]
    dfl = [joint_state_cdr(T0 + k * 500_000, position=(k * 1e-9,), effort=(k * 1e-3,))
           for k in range(n_samples)]
    w_times, r_times = [], []
    for i in range(repeats):
        path = workdir / f'off_{i}'
        t = time.perf_counter()
        with BagWriter(path) as bag:
            a = bag.add_topic('piezo/voltage_command', JOINT_STATE)
            b = bag.add_topic('piezo/deflection', JOINT_STATE)
            for k in range(n_samples):
                bag.write(a, T0 + k * 500_000, cmd[k])
                bag.write(b, T0 + k * 500_000 + 1, dfl[k])
        w_times.append(time.perf_counter() - t)
        t = time.perf_counter()
        rec = read_uy(path)
        r_times.append(time.perf_counter() - t)
        assert len(rec.u) == n_samples
    msgs = 2 * n_samples
    return {'messages': msgs, 'write_s': statistics.median(w_times),
            'read_s': statistics.median(r_times),
            'write_rate': msgs / statistics.median(w_times),
            'read_rate': msgs / statistics.median(r_times)}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.strip().split('\n')[0])
    parser.add_argument('--seconds', type=float, default=5.0)
    parser.add_argument('--rates', type=float, nargs='+', default=[2000.0, 5000.0])
    parser.add_argument('--offline-samples', type=int, default=60000)
    parser.add_argument('--repeats', type=int, default=3)
    parser.add_argument('--batch', type=int, default=1,
                        help='samples per message (N > 1: JointTrajectory on <topic>_batch)')
    args = parser.parse_args(argv)
    print(f'cores: {os.cpu_count()}  load average: {os.getloadavg()[0]:.2f}')
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        print(f'\nlive: recorder_node process, 3 topics, {args.seconds:g} s per rate, batch '
              f'{args.batch}')
        print(f'{"rate Hz":>8} {"pub Hz":>8} {"sent":>7} {"recorded":>9} {"lost":>5} '
              f'{"gaps":>5} {"CPU %":>6} {"CPU % all":>9} {"MB":>6} exit')
        for rate in args.rates:
            r = live_run(rate, args.seconds, tmp, args.batch)
            print(f'{r["rate"]:>8.0f} {r["pub_rate"]:>8.0f} {3 * r["sent_per_topic"]:>7} '
                  f'{sum(r["recorded"].values()):>9} {r["lost"]:>5} {r["missing_in_stamps"]:>5} '
                  f'{100 * r["cpu"]:>6.1f} {100 * r["cpu_total"]:>9.1f} {r["bag_mb"]:>6.2f} '
                  f'{r["exit"]}')
            headline(f'recorder_node, 3 topics at {r["rate"]:.0f} Hz, batch {args.batch}, '
                     f'{args.seconds:g} s', f'{r["lost"]} lost of {3 * r["sent_per_topic"]:,}, '
                     f'{100 * r["cpu"]:.0f} % of a core', '0 lost', 'nodes.md')
        o = offline(args.offline_samples, args.repeats, tmp)
        print(f'\noffline ({o["messages"]} JointState messages, median of {args.repeats}):')
        print(f'  BagWriter: {o["write_s"]:.3f} s = {o["write_rate"]:,.0f} msg/s')
        print(f'  read_uy:   {o["read_s"]:.3f} s = {o["read_rate"]:,.0f} msg/s')
    return 0


if __name__ == '__main__':
    sys.exit(main())
