"""
The estimator node's callbacks against its floor stand-in's, in one process, fed CDR bytes.

Builds estimator_node as bench_live.py starts it for its toy model (NARX 4/4/10 at fs,
`init:=rest`, `batch`) and bench/floor_nodes.py's FloorEstimator, both real rclpy nodes with
discovery off and their publishers replaced by a stub (no DDS traffic), then feeds both the same
CDR bytes, as a raw subscription hands them over (checked with
rclpy.serialization.deserialize_message): per pair one command batch (effort = V) and one
deflection batch of the same stamps (position = m, effort = V), `batch` samples at fs. Times per
message pair, p50 / p99 / mean, in microseconds:

- hot: the pairs back to back;
- cold: a buffer touched (one byte a cache line) before each message, as the other processes of a
  node woken 1000 times a second evict its caches: `--evict-mib` sizes, one mode each (4 MiB:
  this host's L2 caches; 32 MiB: also much of L3).

The once-a-second work (the estimator's diagnostics status(), which hands the held deflection
batches over; the floor's held.take()) runs every fs / batch pairs, timed apart. The two nodes
alternate in blocks of `--block` pairs so that a change of the machine's load moves both alike.
`--against FILE` adds the node running another free_run.py's FreeRunEstimator, in turn with the
others (an A/B of the estimator's logic in one process). `--profile` adds cProfile's top entries
for the estimator's hot pairs. Prints figures; checks only that the stream stayed clean (nothing
withheld or refused).

    python bench/bench_callbacks.py [--pairs 3000] [--fs 20000] [--batch 20] [--profile]
"""
from __future__ import annotations

import argparse
import cProfile
import importlib.util
import os
import pstats
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
# One process, nothing to discover: the nodes' participants see no one (no DDS traffic).
os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'OFF'
os.environ.setdefault('ROS_DOMAIN_ID', str(100 + os.getpid() % 100))

T0_NS = 1_764_000_000_000_000_000    # a wall-clock stamp of 2025, ns


class StubPublisher:
    """Takes what a node publishes (bytes) instead of DDS; keeps the topic name for status()."""

    def __init__(self, real):
        self.topic_name = real.topic_name
        self.count = 0
        self.last = None

    def publish(self, msg) -> None:
        self.count += 1
        self.last = msg


def messages(model, fs: float, batch: int, pairs: int):
    """
    Return [(command batch CDR, deflection batch CDR)] of `pairs` consecutive batches.

    The bytes command_node and simulator_node publish (nodes.wire.encode_joint_trajectory), which
    a raw subscription hands over as sent. Not rclpy.serialization.serialize_message's: in these
    wheels its buffer carries uninitialised padding and 320 trailing bytes per 20-point batch, so
    each message would look like a new shape to the decoder. Each is checked against rclpy's
    deserialize_message (same stamps and values).
    """
    from rclpy.serialization import deserialize_message
    from trajectory_msgs.msg import JointTrajectory
    from piezo_narx_ros.nodes.wire import encode_joint_trajectory
    from piezo_narx_ros.plant.signals import generate
    n = pairs * batch
    u = generate('multisine', fs, n / fs + 1.0, 100.0, seed=0)[:n]
    y = model.simulate(u)
    t = T0_NS + np.arange(n, dtype=np.int64) * int(round(1e9 / fs))
    out = []
    for k in range(pairs):
        s = slice(k * batch, (k + 1) * batch)
        out.append((encode_joint_trajectory(t[s], ['x'], effort=u[s, None]),
                    encode_joint_trajectory(t[s], ['x'], position=y[s, None],
                                            effort=u[s, None])))
    for k in (0, pairs - 1):
        for raw, field, values in ((out[k][0], 'effort', u), (out[k][1], 'positions', y)):
            msg = deserialize_message(raw, JointTrajectory)
            s = slice(k * batch, (k + 1) * batch)
            got = [getattr(p, field)[0] for p in msg.points]
            stamps = [msg.header.stamp.sec * 10 ** 9 + msg.header.stamp.nanosec
                      + p.time_from_start.sec * 10 ** 9 + p.time_from_start.nanosec
                      for p in msg.points]
            if got != values[s].tolist() or stamps != t[s].tolist():
                raise RuntimeError(f'batch {k} ({field}) does not deserialise to its samples')
    return out


def estimator(fs: float, batch: int, model_path: Path, namespace: str, against=None):
    """
    Return estimator_node as bench_live starts it, its publisher stubbed.

    against: a free_run.py whose FreeRunEstimator the node runs instead of the package's.
    """
    from rclpy.parameter import Parameter
    from piezo_narx_ros.nodes import estimator_node
    own = estimator_node.FreeRunEstimator
    if against is not None:
        spec = importlib.util.spec_from_file_location('free_run_against', against)
        module = importlib.util.module_from_spec(spec)
        sys.modules[spec.name] = module      # dataclasses look their module up there
        spec.loader.exec_module(module)
        estimator_node.FreeRunEstimator = module.FreeRunEstimator
    try:
        node = estimator_node.EstimatorNode(parameter_overrides=[
            Parameter('model', value=str(model_path)), Parameter('fs', value=float(fs)),
            Parameter('init', value='rest'), Parameter('batch', value=batch)],
            namespace=namespace)
    finally:
        estimator_node.FreeRunEstimator = own
    node.pub = StubPublisher(node.pub)
    # Live, the command stream has one writer and deflection one publisher: the node asks DDS.
    node.sub_cmd.get_publisher_count = lambda: 1
    node.sub_meas.get_publisher_count = lambda: 1
    return node


def floor_estimator(fs: float, batch: int):
    """Return bench/floor_nodes.py's FloorEstimator, its publisher stubbed."""
    from rclpy.parameter import Parameter
    from floor_nodes import FloorEstimator
    floor = FloorEstimator(parameter_overrides=[
        Parameter('fs', value=float(fs)), Parameter('batch', value=batch)],
        namespace='/floor_cb')
    floor.pub = StubPublisher(floor.pub)
    return floor


class Runner:
    """Feeds one node its pairs in order and records the time of each pair and each tick, ns."""

    def __init__(self, name, on_cmd, on_meas, tick, msgs, tick_every: int):
        self.name, self.on_cmd, self.on_meas, self.tick = name, on_cmd, on_meas, tick
        self.msgs, self.tick_every = msgs, tick_every
        self.k = 0
        self.pairs: dict = {'warm-up': []}
        self.ticks: dict = {'warm-up': []}

    def run(self, n: int, evict=None, mode: str = 'warm-up') -> None:
        """Feed the next n pairs; evict: called before each message (cold), or None (hot)."""
        clock = time.perf_counter_ns
        on_cmd, on_meas, msgs = self.on_cmd, self.on_meas, self.msgs
        pairs, ticks = self.pairs[mode], self.ticks[mode]
        for _ in range(n):
            cmd, meas = msgs[self.k]     # never again from the start: a new stream
            self.k += 1
            if evict is not None:
                evict()
            a = clock()
            on_cmd(cmd)
            b = clock()
            if evict is not None:
                evict()
            c = clock()
            on_meas(meas)
            d = clock()
            pairs.append(b - a + d - c)
            if self.k % self.tick_every == 0:
                if evict is not None:
                    evict()
                a = clock()
                self.tick()
                ticks.append(clock() - a)


def evictor(mib: float):
    """Return a function that touches one byte of each 64-byte line of a `mib` MiB buffer."""
    buf = np.zeros(int(mib * 2 ** 20), dtype=np.uint8)
    lines = buf[::64]

    def evict() -> None:
        np.add(lines, 1, out=lines)
    return evict


def figures(ns: list) -> str:
    """p50 / p99 / mean of times in ns, as microseconds."""
    a = np.asarray(ns, dtype=np.float64) / 1e3
    return f'{np.percentile(a, 50):7.1f} {np.percentile(a, 99):7.1f} {a.mean():7.1f}'


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--pairs', type=int, default=3000, help='message pairs per node and mode')
    ap.add_argument('--fs', type=float, default=20000.0, help='sample rate, Hz')
    ap.add_argument('--batch', type=int, default=20, help='samples per message')
    ap.add_argument('--block', type=int, default=500, help='pairs per node before alternating')
    ap.add_argument('--evict-mib', default='4,32',
                    help='buffers touched (one cold mode each), MiB')
    ap.add_argument('--profile', action='store_true', help="cProfile the estimator's hot pairs")
    ap.add_argument('--modes', default='hot,cold', help='hot, cold or both')
    ap.add_argument('--against', default=None, metavar='FREE_RUN_PY',
                    help='also time the node running the FreeRunEstimator of this file, in turn '
                    'with the others (e.g. git show main:piezo_narx_ros/estimator/free_run.py)')
    args = ap.parse_args(argv)

    import rclpy
    from piezo_narx_ros.estimator.toy import toy_narx
    from piezo_narx_ros.ident.model_io import save_model

    model = toy_narx(nu=4, ny=4, hidden=10)
    model.fs = args.fs
    tick_every = max(1, int(round(args.fs / args.batch)))    # once a second of stream
    rclpy.init()
    with tempfile.TemporaryDirectory() as tmp:
        path = save_model(model, Path(tmp) / 'toy.json')
        est = estimator(args.fs, args.batch, path, '/bench_cb')
        floor = floor_estimator(args.fs, args.batch)
        n_modes = len(args.modes.split(',')) + args.evict_mib.count(',') + args.profile
        msgs = messages(model, args.fs, args.batch, tick_every + 10 + n_modes * args.pairs)
        runners = [
            Runner('estimator_node', est.on_command_batch, est.on_measurement_batch,
                   est.status, msgs, tick_every),
            Runner('floor stand-in', floor.on_batch, floor.on_measurement_batch,
                   floor.held.take, msgs, tick_every)]
        nodes = [est, floor]
        if args.against:
            other = estimator(args.fs, args.batch, path, '/bench_cb_against', args.against)
            runners.append(Runner('estimator_node, against', other.on_command_batch,
                                  other.on_measurement_batch, other.status, msgs, tick_every))
            nodes.append(other)
        for r in runners:          # warm up: numba loads, codec shapes, the first tick
            r.run(tick_every + 10)
        modes = {}
        for mode in [m for m in args.modes.split(',') if m]:
            if mode == 'cold':
                for mib in args.evict_mib.split(','):
                    modes[f'cold {float(mib):g} MiB'] = evictor(float(mib))
            else:
                modes[mode] = None
        for r in runners:
            r.pairs = {m: [] for m in modes}
            r.ticks = {m: [] for m in modes}
        for mode, evict in modes.items():
            done = 0
            while done < args.pairs:
                n = min(args.block, args.pairs - done)
                for r in runners:
                    r.run(n, evict, mode)
                done += n
        assert est.est.stats.rate_withheld == 0 and est.est.stats.refused_messages == 0, \
            'the bench stream must be a clean one'
        print(f'{args.fs:g} Hz, batch {args.batch}, {args.pairs} pairs per node and mode; load '
              f'{os.getloadavg()[0]:.2f}')
        print(f'{"per message pair (us)":<36} {"p50":>7} {"p99":>7} {"mean":>7}')
        for mode in modes:
            for r in runners:
                print(f'{r.name + ", " + mode:<36} {figures(r.pairs[mode])}')
            for r in runners[::2]:
                ratio = np.median(r.pairs[mode]) / np.median(runners[1].pairs[mode])
                label = '  p50 / floor p50, ' + r.name.split(', ')[-1]
                print(f'{label:<36} {ratio:7.2f}')
        print('once a second (us)')
        for mode in modes:
            for r in runners:
                if r.ticks[mode]:
                    print(f'{"tick " + r.name + ", " + mode:<36} {figures(r.ticks[mode])}'
                          f'  ({len(r.ticks[mode])} ticks)')
        if args.profile:
            prof = cProfile.Profile()
            prof.enable()
            runners[0].pairs['profile'], runners[0].ticks['profile'] = [], []
            runners[0].run(args.pairs, None, 'profile')
            prof.disable()
            print(f'\ncProfile, estimator_node, {args.pairs} hot pairs (tottime):')
            pstats.Stats(prof, stream=sys.stdout).sort_stats('tottime').print_stats(25)
        for node in nodes:
            node.destroy_node()
    rclpy.try_shutdown()
    return 0


if __name__ == '__main__':
    sys.exit(main())
