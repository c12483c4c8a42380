"""
Scaling of the candidate search: local worker processes against Ray on the same 2 CPUs.

The same search on 1 and 2 local worker processes and on a local Ray of the same 2 CPUs, side by
side, with the per-task overhead and the data shipping of each executor, and an estimate of the
wall time with N workers built from those figures.

The search is the paper preset (16 NARX networks + 100 ARX, final fit of the winner; 116
candidate tasks) on 50,000 piezo samples (25,000 estimate, 25,000 validate). Per repeat, in
this order: local jobs=1 (in this process), local jobs=2 (spawned pool), then a fresh local Ray
(2 CPUs): its start, a first search (its workers start cold, like the pool's), a second search
on the same instance (warm workers, as on a running cluster reached with --ray-address).
Target: Ray's overhead on the 2 cores <= 15 % of the local (jobs=2) wall time.

Per-task overhead: a no-op task that takes the records (operator.is_), 2 vs 2 + K tasks, so a
pool's start-up cancels out. Data shipping: the bytes of the records, the pickling the pool's
initializer pays per worker, ray.put (once per search) and what a task pays to receive them.

Estimate: the task durations of the jobs=1 run (each task alone on a core) are scheduled in
submission order on N workers, each task taking the earliest free one (what the pool and Ray
do), plus the measured per-task overhead, the executor's start and the final fit (one task,
after the grid). Checked against the measured 1 and 2 worker walls.

Run: python bench/bench_scale.py [--samples 50000] [--repeats 3] [--tasks 1000]
Figures are only meaningful on a quiet machine; the runs are interleaved so load hits all.
"""
import argparse
import operator
import os
import pickle
import statistics
import sys
import time

# Before numpy loads, as `piezo-narx` does: the jobs=1 run and the final fit run in this process,
# and a threaded BLAS here gives other bits than the single-threaded workers (measured: 6 of the
# 100 ARX fits differed at na, nb >= 8).
for _name, _value in {'OPENBLAS_NUM_THREADS': '1', 'OMP_NUM_THREADS': '1',
                      'MKL_NUM_THREADS': '1'}.items():
    os.environ.setdefault(_name, _value)

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from bench_simulate import piezo_data  # noqa: E402
from headline import headline  # noqa: E402

from piezo_narx_ros.record import Record  # noqa: E402
from piezo_narx_ros.ident.selection.executor import LocalExecutor, RayExecutor  # noqa: E402
from piezo_narx_ros.ident.selection.experiment import (ExperimentConfig,  # noqa: E402
                                                       run_experiment, split_records)
from piezo_narx_ros.ident.model_io import weights_sha256  # noqa: E402

FS = 2000.0
WORKERS = (1, 2, 4, 8, 16, 32, 64, 128)


class Stamped:
    """Wraps an executor: the time each task's result reached the driver (s since map)."""

    def __init__(self, executor):
        self.executor = executor
        self.maps = []

    def map(self, fn, tasks, data, done=None):  # noqa: A003 - Executor.map
        stamps, t0 = [], time.perf_counter()

        def seen(i, result):
            stamps.append((time.perf_counter() - t0, i))
            if done is not None:
                done(i, result)
        results = self.executor.map(fn, tasks, data, seen)
        self.maps.append({'tasks': len(tasks), 'wall': time.perf_counter() - t0,
                          'stamps': stamps})
        return results

    def describe(self):
        return self.executor.describe()


def search(record, executor):
    """(wall s, ExperimentResult, Stamped) of the paper search on `executor`."""
    stamped = Stamped(executor)
    t0 = time.perf_counter()
    result = run_experiment([record], ExperimentConfig(progress=False), executor=stamped)
    return time.perf_counter() - t0, result, stamped


def task_seconds(stamped) -> list:
    """Per-task seconds of an in-process (jobs=1) map: gaps between consecutive results."""
    stamps = sorted(stamped.maps[0]['stamps'])
    times, last = [], 0.0
    for t, _ in stamps:
        times.append(t - last)
        last = t
    return times


def makespan(durations, workers: int, overhead: float) -> float:
    """Wall of tasks run in order, each on the earliest free of `workers`, each + overhead."""
    free = [0.0] * workers
    for d in durations:
        i = min(range(workers), key=free.__getitem__)
        free[i] += d + overhead
    return max(free)


def per_task_overhead(executor, data, k: int) -> tuple:
    """(seconds per no-op task, wall of 2 tasks) for an executor; the no-op takes the records."""
    base = [(0, i) for i in range(2)]
    t0 = time.perf_counter()
    executor.map(operator.is_, base, data)
    t_two = time.perf_counter() - t0
    t0 = time.perf_counter()
    executor.map(operator.is_, base + [(0, i) for i in range(k)], data)
    t_many = time.perf_counter() - t0
    return max(0.0, (t_many - t_two) / k), t_two


def shipping(data) -> dict:
    """Bytes of the records and what it costs to move them (pickle = the pool's initializer)."""
    t0 = time.perf_counter()
    blob = pickle.dumps(data, protocol=pickle.HIGHEST_PROTOCOL)
    t_pickle = time.perf_counter() - t0
    t0 = time.perf_counter()
    pickle.loads(blob)
    return {'bytes': len(blob), 'pickle_s': t_pickle, 'unpickle_s': time.perf_counter() - t0}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    ap.add_argument('--samples', type=int, default=50000)
    ap.add_argument('--repeats', type=int, default=3)
    ap.add_argument('--tasks', type=int, default=1000, help='no-op tasks for the overhead')
    args = ap.parse_args(argv)

    u, y, _, source = piezo_data(args.samples)
    record = Record(u=u, y=y, fs=FS, source=source)
    print(f'data: {args.samples} samples at {FS:g} Hz from {source}')
    print(f'machine: {os.cpu_count()} CPUs, load average at start '
          f'{os.getloadavg()[0]:.2f} (other work on the box inflates every figure alike)')

    walls = {'local jobs=1': [], 'local jobs=2': [], 'ray start': [], 'ray cold': [],
             'ray warm': [], 'ray put': []}
    durations, final_seconds, weights, result = [], [], {}, None
    for rep in range(args.repeats):
        wall, result, stamped = search(record, LocalExecutor(1))
        walls['local jobs=1'].append(wall)
        durations.append(task_seconds(stamped))
        final_seconds.append(stamped.maps[1]['wall'] if len(stamped.maps) > 1 else 0.0)
        weights[f'{rep} jobs=1'] = result
        wall, result, _ = search(record, LocalExecutor(2))
        walls['local jobs=2'].append(wall)
        weights[f'{rep} jobs=2'] = result
        ray = RayExecutor(num_cpus=2)
        try:
            t0 = time.perf_counter()
            ray.open()
            walls['ray start'].append(time.perf_counter() - t0)
            for kind in ('ray cold', 'ray warm'):
                wall, result, _ = search(record, ray)
                walls[kind].append(wall)
                weights[f'{rep} {kind}'] = result
            data = {0: split_records([record])}
            t0 = time.perf_counter()
            ray.open().put(data[0])
            walls['ray put'].append(time.perf_counter() - t0)
            if rep == 0:
                ray_task, _ = per_task_overhead(ray, data, args.tasks)
        finally:
            ray.close()
        print(f'repeat {rep + 1} (load average {os.getloadavg()[0]:.2f}): '
              + ', '.join(f'{k} {v[-1]:.3f} s' for k, v in walls.items()), flush=True)
    # Per task, the median over repeats: one busy moment on a shared box does not make the
    # estimate.
    durations = [statistics.median(d) for d in zip(*durations)]

    data = {0: split_records([record])}
    pool_task, pool_start = per_task_overhead(LocalExecutor(2), data, args.tasks)
    ship = shipping(data)
    med = {k: statistics.median(v) for k, v in walls.items()}
    n_tasks = len(durations)
    kinds = [c.spec.kind for c in result.candidates]
    digests = {run: [weights_sha256(c.model) for c in res.candidates]
               for run, res in weights.items()}
    first = next(iter(digests))
    for run, d in digests.items():
        differ = [c.spec.label for c, a, b in zip(result.candidates, digests[first], d) if a != b]
        if differ:
            print(f'weights differ between {first!r} and {run!r}: {", ".join(differ)}')
    print(f'\nsearch: {kinds.count("narx")} NARX + {kinds.count("arx")} ARX = {n_tasks} '
          f'candidate tasks + the final fit; selected {result.best.spec.label}; every '
          f"candidate's weights SHA-256 equal in all {len(digests)} runs: "
          f'{len({tuple(d) for d in digests.values()}) == 1}')
    print(f'medians over {args.repeats} repeat(s), wall time of run_experiment:')
    print(f'  local, 1 worker (this process):     {med["local jobs=1"]:7.2f} s')
    print(f'  local, 2 worker processes:          {med["local jobs=2"]:7.2f} s   '
          f'speed-up {med["local jobs=1"] / med["local jobs=2"]:.2f}x')
    for kind, what in (('ray cold', 'first search, cold workers'),
                       ('ray warm', 'second search, warm workers')):
        over = (med[kind] - med['local jobs=2']) / med['local jobs=2']
        print(f'  Ray, 2 CPUs, {what}: {med[kind]:7.2f} s   overhead vs local 2 workers '
              f'{100 * over:+.1f} % (target <= 15 %)')
        headline(f'paper grid on Ray (2 local CPUs) against the process pool, {what}',
                 f'{100 * over:+.1f} %', '<= 15 %', 'scaling.md')
    over = (med['ray cold'] + med['ray start'] - med['local jobs=2']) / med['local jobs=2']
    print(f'  local Ray start (ray.init, not in the walls above): {med["ray start"]:.2f} s; '
          f'start + cold search = {med["ray start"] + med["ray cold"]:.2f} s, '
          f'{100 * over:+.1f} % over local')
    print('per-task overhead (no-op task taking the records, '
          f'{args.tasks} tasks on 2 workers):')
    print(f'  local pool: {1e3 * pool_task:.3f} ms per task; pool start with data: '
          f'{pool_start:.2f} s')
    print(f'  Ray:        {1e3 * ray_task:.3f} ms per task')
    print(f'data shipping: records {ship["bytes"] / 1e6:.2f} MB pickled; pool initializer '
          f'pickles them once per worker ({1e3 * ship["pickle_s"]:.1f} ms pickle, '
          f'{1e3 * ship["unpickle_s"]:.1f} ms unpickle); Ray: ray.put once per search '
          f'{1e3 * med["ray put"]:.1f} ms, tasks read them zero-copy from the object store '
          '(inside the per-task figure above)')

    grid = sum(durations)
    final = statistics.median(final_seconds)
    print(f'estimate from the jobs=1 task times (sum {grid:.2f} s over {n_tasks} tasks, longest '
          f'{max(durations):.2f} s) + final fit {final:.2f} s:')
    print(f'  {"N":>4} {"pool est. s":>12} {"Ray est. s":>11}  (pool: + its {pool_start:.1f} s '
          f'start; Ray: instance running)')
    for n in WORKERS:
        pool = (0.0 if n == 1 else pool_start) + makespan(durations, n, pool_task) + final
        ray_est = makespan(durations, n, ray_task) + final
        print(f'  {n:>4} {pool:>12.2f} {ray_est:>11.2f}')
    print(f'  measured: N=1 {med["local jobs=1"]:.2f} s, N=2 pool {med["local jobs=2"]:.2f} s, '
          f'N=2 Ray warm {med["ray warm"]:.2f} s. Floor: the longest task + the final fit = '
          f'{max(durations) + final:.2f} s, whatever N.')
    # What Ray adds to this search on 2 workers, from the per-task figures alone (independent
    # of the load on the box): its per-task cost over the pool's on every task, and the put.
    extra = (ray_task - pool_task) * n_tasks / 2 + med['ray put']
    print(f"Ray's own cost in this search from the per-task figures: {1e3 * extra:+.0f} ms on "
          f'2 workers = {100 * extra / med["local jobs=2"]:+.2f} % of the local wall (plus '
          f'{med["ray start"]:.1f} s to start a local instance, which the pool does not pay; '
          f'the pool pays its own {pool_start:.1f} s start on every search)')


if __name__ == '__main__':
    main()
