"""
Where the candidate fits of a search run: a local process pool or a Ray cluster.

An executor maps a task function over tasks that share data::

    results = executor.map(fn, tasks, data, done)

`tasks` is a list of (key, payload) pairs; each task runs `fn(payload, data[key])` in a worker
and the results come back in task order. `data` (the records) is shipped to the workers once,
not once per task: the local pool hands it to each worker process at start, Ray puts each entry
in the object store once and passes the reference. A task that raises, or whose worker dies
(after the executor's retries), gives a `TaskFailure` in its slot and the others complete.
Ctrl-C (KeyboardInterrupt) cancels the work not yet done and is re-raised.

The task function is the same on every executor, so a search gives the same numbers on all of
them: each worker runs one BLAS/OpenMP thread (`SINGLE_THREAD_ENV`, set before numpy loads) and
the task function asks `in_worker()` to pin torch to one thread as well. Tasks run in the calling
process (LocalExecutor with jobs = 1 or a single task, e.g. the final fit) use that process's BLAS
threads: for the same bits there, set OPENBLAS_NUM_THREADS=1 before numpy loads, as `piezo-narx`
does (measured without it: 6 of the paper grid's 100 ARX fits differed in the last bits).

`LocalExecutor(jobs)` is the default: `jobs` spawned processes (in this process for jobs = 1 or
a single task). `RayExecutor(address, num_cpus)` runs each task as a Ray task; without an
address it starts a local Ray instance of `num_cpus` CPUs (no dashboard, a small object store)
and stops it on `close()`. Ray is imported only by RayExecutor.
"""
from __future__ import annotations

import concurrent.futures as cf
import contextlib
import logging
import multiprocessing as mp
import os
import signal
import threading
from dataclasses import dataclass

from piezo_narx_ros.errors import ConfigError

EXECUTORS = ('local', 'ray')

# A worker is one of `jobs` processes on as many cores: threaded BLAS/torch inside it would only
# oversubscribe them. The variables must be set before the child imports numpy, hence at spawn.
SINGLE_THREAD_ENV = {'OMP_NUM_THREADS': '1', 'OPENBLAS_NUM_THREADS': '1', 'MKL_NUM_THREADS': '1'}

# Per worker process: the shared data (local pool) and whether this process is a pool/Ray worker.
_WORKER: dict = {}


@dataclass(frozen=True)
class TaskFailure:
    """The slot of a task that raised or whose worker died; `message` is one line."""

    message: str


def in_worker() -> bool:
    """Return True inside a worker process of an executor (not in the process that called map)."""
    return bool(_WORKER.get('worker'))


def describe(exc: BaseException) -> str:
    """One line for an exception: its type and its message, whitespace collapsed."""
    text = ' '.join(str(exc).split())
    return f'{type(exc).__name__}: {text}' if text else type(exc).__name__


@contextlib.contextmanager
def environment(values: dict):
    """Set environment variables while inside (child processes started then inherit them)."""
    saved = {k: os.environ.get(k) for k in values}
    os.environ.update(values)
    try:
        yield
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


class Executor:
    """Interface of the executors (see the module docstring); a context manager that closes."""

    name = 'executor'

    # `map` shadows a builtin as concurrent.futures.Executor.map does: the name users of an
    # executor expect.
    def map(self, fn, tasks: list, data: dict, done=None) -> list:  # noqa: A003
        """
        [fn(payload, data[key]) or TaskFailure for (key, payload) in tasks].

        `done(index, result)` is called in this process as each task finishes.
        """
        raise NotImplementedError

    def describe(self) -> str:
        """Where the tasks run, for messages."""
        return self.name

    def close(self) -> None:
        """Release the workers (idempotent)."""

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def _init_worker(data: dict, started) -> None:
    _WORKER.update(data=data, started=started, worker=True)


def _call(fn, index, key, payload):
    _WORKER['started'][index] = 1   # which task a worker was running when it died
    return fn(payload, _WORKER['data'][key])


def _report(results, index, result, done):
    results[index] = result
    if done is not None:
        done(index, result)


class LocalExecutor(Executor):
    """
    `jobs` spawned worker processes on this machine.

    A worker that dies breaks the pool: the tasks it had not started run again without a mark;
    the ones running then (which one killed it is unknown) are suspects, run again one at a time
    so a death is pinned on its task, and reported as failures after `retries` more deaths.
    The pool stays open between `map` calls with the same `data` (a search's batches): spawning
    and importing two workers cost about 2 s a batch, a fifth of a 32-trial search on 8,000
    samples. `close` (or leaving the `with` block) stops it.
    """

    name = 'local'
    #: Task slots of a kept pool's "started" flags (a call with more tasks gets a pool of its own).
    SLOTS = 1024

    def __init__(self, jobs: int = 2, retries: int = 1):
        if int(jobs) != jobs or jobs < 1:
            raise ConfigError(f'jobs must be an integer >= 1, got {jobs}')
        self.jobs = int(jobs)
        self.retries = int(retries)
        self._kept = None    # (pool, data, started) while a pool is kept open for `data`

    def close(self) -> None:
        """Stop the kept pool's workers (idempotent)."""
        kept, self._kept = self._kept, None
        if kept is not None:
            kept[0].shutdown(wait=True, cancel_futures=True)

    def _drop(self, pool, wait: bool = False) -> None:
        """Stop `pool` (broken or interrupted) and forget it if it is the kept one."""
        if self._kept is not None and self._kept[0] is pool:
            self._kept = None
        pool.shutdown(wait=wait, cancel_futures=True)

    def _pool(self, data, n_tasks: int, jobs: int):
        """Return (pool, started, kept): the kept pool for the same data, else a new one."""
        keep = jobs == self.jobs and n_tasks <= self.SLOTS
        if keep:
            kept = self._kept
            if kept is not None and kept[1] is data:
                for i in range(n_tasks):
                    kept[2][i] = 0
                return kept[0], kept[2], True
            self.close()
        ctx = mp.get_context('spawn')   # not fork: a parent holding torch/OpenMP threads can hang
        started = ctx.Array('b', self.SLOTS if keep else n_tasks, lock=False)
        pool = cf.ProcessPoolExecutor(max_workers=jobs if keep else min(jobs, n_tasks),
                                      mp_context=ctx, initializer=_init_worker,
                                      initargs=(data, started))
        if keep:
            self._kept = (pool, data, started)
        return pool, started, keep

    def describe(self) -> str:
        """'N local worker process(es)'."""
        return f'{self.jobs} local worker process{"es" if self.jobs > 1 else ""}'

    def map(self, fn, tasks, data, done=None):  # noqa: A003 - Executor.map
        """See Executor.map; in this process when jobs = 1 or there is one task."""
        results = [None] * len(tasks)
        if self.jobs == 1 or len(tasks) == 1:
            for i, (key, payload) in enumerate(tasks):
                try:
                    result = fn(payload, data[key])
                except Exception as exc:  # noqa: BLE001 - reported in the task's slot
                    result = TaskFailure(describe(exc))
                _report(results, i, result, done)
            return results
        deaths = [0] * len(tasks)
        todo = list(range(len(tasks)))
        while todo:
            fresh = [i for i in todo if not deaths[i]]
            jobs = self.jobs if fresh else 1
            redo = self._round(fn, tasks, data, fresh or todo[:1], jobs, deaths, results, done)
            todo = sorted(set(todo) - set(fresh or todo[:1]) | set(redo))
        return results

    def _round(self, fn, tasks, data, indices, jobs, deaths, results, done) -> list:
        """Run `indices` on a pool of `jobs` (kept or fresh); returns the indices to run again."""
        pool, started, kept = self._pool(data, len(tasks), jobs)
        broken = []
        try:
            with environment(SINGLE_THREAD_ENV):   # the workers spawn at their first task
                futures = {pool.submit(_call, fn, i, *tasks[i]): i for i in indices}
            for fut in cf.as_completed(futures):
                i = futures[fut]
                try:
                    _report(results, i, fut.result(), done)
                except cf.process.BrokenProcessPool:
                    broken.append(i)
                except Exception as exc:  # noqa: BLE001 - raised by the task itself
                    _report(results, i, TaskFailure(describe(exc)), done)
        except BaseException:
            self._drop(pool)
            raise
        if broken or not kept:
            self._drop(pool, wait=True)
        # A pool that broke before any task started (workers cannot start) marks them all, so
        # the retries end this too.
        suspects = [i for i in broken if started[i]] or broken
        redo = []
        for i in broken:
            deaths[i] += i in suspects
            if deaths[i] > self.retries:
                _report(results, i, TaskFailure(
                    f'its worker process died {deaths[i]} times (killed, out of memory or a '
                    'crash in compiled code)'), done)
            else:
                redo.append(i)
        return redo


def _probe(address: str, timeout: float = 5.0) -> None:
    """
    Raise ConfigError unless something accepts TCP connections at a HOST:PORT address.

    Ray itself retries an absent cluster for minutes. 'auto' and other forms are left to Ray.
    """
    import socket
    host, _, port = address.rpartition('://')[2].rpartition(':')
    if not host or not port.isdigit():
        return
    try:
        socket.create_connection((host.strip('[]'), int(port)), timeout=timeout).close()
    except OSError as exc:
        raise ConfigError(f'--ray-address {address}: cannot connect to a Ray cluster (nothing '
                          f'answers there: {exc.strerror or exc})') from None


def _has_token() -> bool:
    """
    Tell whether a Ray authentication token is at hand.

    RAY_AUTH_TOKEN, RAY_AUTH_TOKEN_PATH or the default file ~/.ray/auth_token (where `ray start`
    and `ray get-auth-token --generate` put it).
    """
    return bool(os.environ.get('RAY_AUTH_TOKEN') or os.environ.get('RAY_AUTH_TOKEN_PATH')
                or os.path.isfile(os.path.join(os.path.expanduser('~'), '.ray', 'auth_token')))


@contextlib.contextmanager
def _record_interrupts(caught: list, hold: bool):
    """
    Inside, SIGINT is recorded in `caught` (main thread only; an ignored SIGINT stays ignored).

    hold=True: only recorded, the caller acts on it afterwards. hold=False: recorded, then raised
    as usual; Ray's compiled calls (wait, get) run their own loops, and the record lets the caller
    see a Ctrl-C even if one of them turned the KeyboardInterrupt into something else.
    """
    previous = signal.getsignal(signal.SIGINT)
    if threading.current_thread() is not threading.main_thread() or \
            previous is signal.SIG_IGN:
        yield          # ignored SIGINT (nohup, a background job) stays ignored
        return

    def handler(signum, frame):
        caught.append(True)
        if hold:
            return
        if callable(previous):
            previous(signum, frame)
        else:
            raise KeyboardInterrupt
    signal.signal(signal.SIGINT, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


_AUTH_LOGGER = 'ray._private.authentication.authentication_token_setup'


@contextlib.contextmanager
def _quiet(name: str):
    """Only errors from logger `name` while inside."""
    logger = logging.getLogger(name)
    level = logger.level
    logger.setLevel(logging.ERROR)
    try:
        yield
    finally:
        logger.setLevel(level)


def _ray_call(fn, payload, shared):
    """Body of every Ray task: mark the process as a worker, then the task function."""
    _WORKER['worker'] = True
    return fn(payload, shared)


def _data_bytes(data: dict) -> int:
    """Bytes of the numpy arrays in `data` (records: u, y, t, ...), for sizing the store."""
    import numpy as np
    total = 0
    stack = list(data.values())
    while stack:
        item = stack.pop()
        if isinstance(item, np.ndarray):
            total += item.nbytes
        elif isinstance(item, (list, tuple)):
            stack += list(item)
        elif hasattr(item, '__dict__'):
            stack += list(vars(item).values())
    return total


class RayExecutor(Executor):
    """
    Each task a Ray task (one CPU); the data put in the object store once per map.

    `address` None starts a local Ray instance with `num_cpus` CPUs (default: all), no
    dashboard and an object store sized from the data (at least `min_store` bytes), stopped on
    close(). An address ('HOST:PORT' of the head node, or 'auto' on a node of the cluster)
    connects to a running cluster as a driver: its nodes need this project's requirements; this
    package's code is shipped with the job. close() then only disconnects. (Ray Client's
    'ray://' addresses need the ray[client] extras, which requirements.txt does not install.)
    A worker that dies is retried `retries` times by Ray; a task that raises is not retried (a
    fit is deterministic). In a process already connected to Ray (ray.init done by the caller)
    the existing connection is used and left open.
    """

    name = 'ray'

    def __init__(self, address: str | None = None, num_cpus: int | None = None,
                 retries: int = 2, min_store: int = 256 * 2 ** 20):
        self.address = address or None
        self.num_cpus = None if num_cpus is None else int(num_cpus)
        self.retries = int(retries)
        self.min_store = int(min_store)
        self._owns = False
        self._ray = None
        self._data, self._refs = None, {}
        self._cpus = 0

    def describe(self) -> str:
        """Describe the executor: 'Ray cluster at ADDR (N CPUs)' or 'local Ray (N CPUs)'."""
        where = f'Ray cluster at {self.address}' if self.address else 'local Ray'
        return f'{where} ({self._cpus} CPUs)' if self._cpus else where

    def open(self, store_bytes: int = 0):  # noqa: A003 - pairs with close()
        """Connect (or start the local instance); returns the ray module."""
        if self._ray is not None:
            return self._ray
        if self.address is not None:
            _probe(self.address)
        if self.address is not None and 'RAY_AUTH_MODE' not in os.environ and _has_token():
            # A cluster started with token authentication (Ray's default since 2.59) takes
            # drivers that say so; Ray reads the mode from the environment when it loads.
            os.environ['RAY_AUTH_MODE'] = 'token'
        try:
            import ray
        except ImportError:
            raise ConfigError('--executor ray needs the ray package (pip install -r '
                              'requirements.txt)') from None
        if ray.is_initialized():
            self._ray = ray
            self._cpus = int(ray.cluster_resources().get('CPU', 0))
            return ray
        options = {'include_dashboard': False, 'log_to_driver': False,
                   'logging_level': logging.WARNING,
                   'runtime_env': {'env_vars': dict(SINGLE_THREAD_ENV)}}
        failure, interrupted = None, []
        # Ctrl-C is held until the start is over: cut half way, the start left Ray's agent
        # processes running for good (measured); after it, shutdown() stops everything.
        with _record_interrupts(interrupted, hold=True):
            try:
                self._init(ray, options, store_bytes)
            except Exception as exc:  # noqa: BLE001 - mapped to one line below
                failure = exc
        if failure is not None or interrupted:
            with contextlib.suppress(Exception):
                ray.shutdown()
            if interrupted:
                raise KeyboardInterrupt
            self._start_error(failure)
        self._owns = True
        self._ray = ray
        self._cpus = int(ray.cluster_resources().get('CPU', 0))
        return ray

    def _init(self, ray, options, store_bytes):
        if self.address is None:
            # The raylet and its workers inherit this environment: one thread each. Ray turns
            # token authentication on for a local instance and says so in a warning line at
            # every start; the CLI's user needs no such line.
            with environment(SINGLE_THREAD_ENV), _quiet(_AUTH_LOGGER):
                ray.init(address='local', num_cpus=self.num_cpus or os.cpu_count(),
                         object_store_memory=max(self.min_store, 2 * store_bytes), **options)
        else:
            # This package's code goes with the job, so the cluster runs the very code that
            # the driver runs (its nodes need the requirements installed).
            package = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
            options['runtime_env']['py_modules'] = [package]
            ray.init(address=self.address, **options)

    def _start_error(self, exc: Exception):
        """Raise a start or connection failure as one ConfigError line."""
        why = ' '.join(str(exc).split())[:200]
        if self.address is None:
            raise ConfigError(f'cannot start a local Ray instance ({type(exc).__name__}: '
                              f'{why})') from None
        hint = ('' if _has_token() else '; if the cluster uses token authentication, put its '
                'token in ~/.ray/auth_token or RAY_AUTH_TOKEN')
        raise ConfigError(f'--ray-address {self.address}: cannot connect to a Ray cluster '
                          f'({why}){hint}') from None

    def map(self, fn, tasks, data, done=None):  # noqa: A003 - Executor.map
        """See Executor.map."""
        ray = self.open(_data_bytes(data))
        if self._data is not data:
            # Put once per data set: the final fits of a search reuse the records of its grid.
            # Only the latest set is kept referenced, so a long-lived executor does not pile up.
            self._data, self._refs = data, {key: ray.put(value) for key, value in data.items()}
        refs = self._refs
        remote = ray.remote(num_cpus=1, max_retries=self.retries,
                            retry_exceptions=False)(_ray_call)
        pending = {remote.remote(fn, payload, refs[key]): i
                   for i, (key, payload) in enumerate(tasks)}
        results, interrupted = [None] * len(tasks), []
        try:
            with _record_interrupts(interrupted, hold=False):
                while pending and not interrupted:
                    ready, _ = ray.wait(list(pending), num_returns=len(pending), timeout=0.2)
                    for ref in ready:
                        _report(results, pending.pop(ref), self._get(ray, ref), done)
                if interrupted:
                    raise KeyboardInterrupt
        except BaseException:
            self._cancel(ray, pending)
            raise
        return results

    def _get(self, ray, ref):
        try:
            return ray.get(ref)
        except ray.exceptions.RayTaskError as exc:
            cause = getattr(exc, 'cause', None)
            return TaskFailure(describe(cause) if cause is not None else
                               f'the task raised in its worker: {describe(exc)}')
        except ray.exceptions.RayError as exc:
            # Worker or node died past the retries, object lost, ...: one line of Ray's reason.
            first = str(exc).strip().splitlines()[0] if str(exc).strip() else ''
            return TaskFailure(f'{type(exc).__name__} after {self.retries} retries'
                               + (f': {first[:300]}' if first else ''))

    @staticmethod
    def _cancel(ray, pending) -> None:
        """
        Stop the cluster's work on an interrupt.

        Queued tasks are dropped, running ones killed (force), so a cluster is not left computing
        for nobody.
        """
        for ref in pending:
            with contextlib.suppress(Exception):
                ray.cancel(ref, force=True)

    def close(self) -> None:
        """Stop the local instance, or disconnect from the cluster, if this executor made it."""
        self._data, self._refs = None, {}
        if self._ray is not None and self._owns:
            with contextlib.suppress(Exception):
                self._ray.shutdown()
        self._ray, self._owns = None, False


def make_executor(name: str = 'local', jobs: int = 2, address: str | None = None) -> Executor:
    """
    Executor by name.

    'local' (`jobs` processes) or 'ray' (`address`, or a local Ray instance of `jobs` CPUs).
    ConfigError for anything else.
    """
    if name == 'local':
        if address:
            raise ConfigError('--ray-address needs --executor ray')
        return LocalExecutor(jobs)
    if name == 'ray':
        return RayExecutor(address=address, num_cpus=None if address else jobs)
    raise ConfigError(f'executor must be one of {", ".join(EXECUTORS)}, got {name!r}')
