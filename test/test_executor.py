"""
Executors of the candidate search.

The Ray executor gives the local pool's results bit for bit, failures are reported per candidate
while the rest completes, and Ctrl-C leaves no Ray process.

One local Ray instance (2 CPUs, no dashboard, small object store) serves the module and is shut
down at its end; the CLI tests run in-process and reuse it (RayExecutor leaves a connection it did
not make open).
"""
import csv
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from piezo_narx_ros.cli.main import main
from piezo_narx_ros.errors import ConfigError
from piezo_narx_ros.record import Record
from piezo_narx_ros.ident.selection.executor import (LocalExecutor, RayExecutor, TaskFailure,
                                                     make_executor)
from piezo_narx_ros.ident.selection.experiment import ExperimentConfig, fit_task, run_experiment
from piezo_narx_ros.ident.model_io import save_model, weights_sha256

# Few iterations: these tests check where and how fits run, not the optimiser.
FAST_TRAINING = {'restarts': 1, 'restart_iter': 2, 'max_iter': 5, 'refine_iter': 3,
                 'n_segments': 5, 'onestep_samples': 1000}
PAPER_LIKE = {'ny': (1, 2), 'nu': (1, 2), 'hidden': 3, 'arx_na': (1, 2), 'arx_nb': (1, 2),
              'training': FAST_TRAINING, 'final_training': {'max_iter': 8, 'refine_iter': 4},
              'progress': False}
ENVELOPE_LIKE = {'family': 'hysteresis_narx', 'hidden': 3, 'n_seeds': 2,
                 'hnarx': {'n_plays': 4, 'max_iter': 3}, 'arx_na': (2,), 'arx_nb': (2,),
                 'selection': 'worst_case', 'final_training': {}, 'progress': False}


def hysteretic_record(n=3000, seed=0, fs=1000.0):
    """Return a backlash-like hysteresis into a first-order lag, with sensor noise (u V, y m)."""
    rng = np.random.default_rng(seed)
    u = np.convolve(rng.uniform(-1, 1, n + 20), np.ones(20) / 20, mode='valid')[:n]
    play, y = np.zeros(n), np.zeros(n)
    for k in range(1, n):
        play[k] = min(max(play[k - 1], u[k] - 0.2), u[k] + 0.2)
        y[k] = 0.8 * y[k - 1] + 0.2 * play[k]
    return Record(u=u, y=1e-6 * (y + 1e-3 * rng.standard_normal(n)), fs=fs,
                  source=f'hyst-{seed}')


def without_times(doc):
    """Return a result's to_dict() without wall/fit seconds (the only fields that may differ)."""
    if isinstance(doc, dict):
        return {k: without_times(v) for k, v in doc.items()
                if k not in ('wall_seconds', 'fit_seconds')}
    if isinstance(doc, list):
        return [without_times(v) for v in doc]
    return doc


@pytest.fixture(scope='module')
def ray_executor():
    from ray import cloudpickle
    # Ray workers cannot import this test module: ship its task functions by value.
    cloudpickle.register_pickle_by_value(sys.modules[__name__])
    executor = RayExecutor(num_cpus=2)
    executor.open()
    yield executor
    executor.close()


@pytest.mark.parametrize('settings', [PAPER_LIKE, ENVELOPE_LIKE], ids=['paper', 'envelope'])
def test_ray_search_equals_local_bit_for_bit(ray_executor, settings):
    records = [hysteretic_record(seed=1), hysteretic_record(seed=2)]
    config = ExperimentConfig(jobs=2, **settings)
    local = run_experiment(records, config)
    ray = run_experiment(records, config, executor=ray_executor)
    assert [c.error for c in ray.candidates] == [None] * len(ray.candidates)
    assert [weights_sha256(c.model) for c in ray.candidates] == \
        [weights_sha256(c.model) for c in local.candidates]
    # Same selection, scores, test verdicts and final-fit decision: the whole report but times.
    assert without_times(ray.to_dict()) == without_times(local.to_dict())
    if settings is PAPER_LIKE:
        assert ray.best.spec.kind == 'narx' and ray.best.final_fit is not None


def boom(payload, data):
    """Task function: raises for payload 'bad', else the payload's length."""
    if payload == 'bad':
        raise RuntimeError('candidate exploded')
    return len(payload)


def die_once(payload, data):
    """Task function: the worker dies the first time ('once', marker file) or every time."""
    mode, marker = payload
    if mode == 'always' or (mode == 'once' and not os.path.exists(marker)):
        Path(marker).touch()
        os._exit(3)
    return mode


def test_ray_structure_search_equals_local_bit_for_bit(ray_executor, tmp_path):
    """The structure search (fit --preset search) on Ray selects the local pool's model."""
    from piezo_narx_ros.ident.selection.search import SearchOptions, run_search
    rec = hysteretic_record(n=3000, seed=5)
    est, val = [rec.segment(0, 2000)], [rec.segment(2000, 3000)]
    picks = []
    local = LocalExecutor(jobs=2)
    for name, executor in (('local', local), ('ray', ray_executor)):
        options = SearchOptions(trials=2, batch=2, budget_s=None, init_samples=100,
                                families=('arx', 'hysteresis_narx'), progress=False)
        res = run_search(est, val, options, executor, tmp_path / name)
        picks.append((res.numbers[res.selected], weights_sha256(res.best.model),
                      [t.spec for t in res.trials],
                      [t.scores['start']['error'] for t in res.trials]))
    local.close()
    assert picks[0] == picks[1]


def _executors(ray_executor):
    return [LocalExecutor(jobs=2), ray_executor]


def worker_pid(payload, data):
    """Return the worker process's pid (after a pause, so that both workers take tasks)."""
    time.sleep(0.2)
    return os.getpid()


def test_the_local_pool_is_kept_between_calls_with_the_same_data():
    data, other = {0: 'records'}, {0: 'other records'}
    tasks = [(0, i) for i in range(4)]
    with LocalExecutor(jobs=2) as ex:
        first = set(ex.map(worker_pid, tasks, data))
        again = set(ex.map(worker_pid, tasks, data))
        assert len(first) == 2 and again == first          # the same two workers
        fresh = set(ex.map(worker_pid, tasks, other))
        assert not fresh & first                           # other data: other workers
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline and any(_alive(p) for p in fresh | first):
        time.sleep(0.1)
    assert not [p for p in fresh | first if _alive(p)], 'the pool outlived close()'


def test_a_task_that_raises_fills_its_slot_and_the_rest_complete(ray_executor):
    tasks = [(0, 'ok'), (0, 'bad'), (0, 'fine')]
    for executor in (LocalExecutor(jobs=1), *_executors(ray_executor)):
        seen = []
        results = executor.map(boom, tasks, {0: None}, lambda i, r: seen.append(i))
        if executor is not ray_executor:
            executor.close()
        assert results[0] == 2 and results[2] == 4, executor.name
        assert isinstance(results[1], TaskFailure)
        assert results[1].message == 'RuntimeError: candidate exploded'
        assert sorted(seen) == [0, 1, 2]


def test_a_dead_worker_is_retried_then_reported(ray_executor, tmp_path):
    for executor in _executors(ray_executor):
        d = tmp_path / executor.name
        d.mkdir()
        tasks = [(0, ('once', str(d / 'a'))), (0, ('always', str(d / 'b'))),
                 (0, ('fine', str(d / 'c')))]
        results = executor.map(die_once, tasks, {0: None})
        if executor is not ray_executor:
            executor.close()
        assert results[0] == 'once' and results[2] == 'fine', executor.name   # retried
        assert isinstance(results[1], TaskFailure), executor.name
        assert 'died' in results[1].message or 'Crashed' in results[1].message


def test_failed_candidate_is_named_and_the_search_completes(ray_executor):
    record = hysteretic_record(seed=3)
    config = ExperimentConfig(narx=False, arx_na=(1, 2), arx_nb=(1, 2), progress=False)

    class Faulty(RayExecutor):
        """The Ray executor with ARX(na=2, nb=1)'s worker killed on every attempt."""

        def map(self, fn, tasks, data, done=None):  # noqa: A003 - Executor.map
            def task(payload, shared):
                if payload[0].label == 'ARX(na=2, nb=1)':
                    os._exit(1)
                return fn(payload, shared)
            return ray_executor.map(task, tasks, data, done)

    result = run_experiment([record], config, executor=Faulty())
    failed = [c for c in result.candidates if c.error is not None]
    assert [c.spec.label for c in failed] == ['ARX(na=2, nb=1)']
    assert 'WorkerCrashedError' in failed[0].error
    assert result.best.error is None and len(result.candidates) == 4


def _cli(argv, capsys):
    with pytest.raises(SystemExit) as exc:
        main(argv)
    out = capsys.readouterr()
    return exc.value.code, out.out, out.err


def _write_npz(path, record):
    np.savez(path, u=record.u, y=record.y, fs=record.fs)


FLEET_ARGS = ['--ny', '1-2', '--nu', '1', '--hidden', '3', '--arx-na', '1-2', '--arx-nb', '1',
              '--no-report', '--quiet']


def test_fleet_per_record_local_and_ray(ray_executor, tmp_path, capsys):
    fleet = tmp_path / 'fleet'
    fleet.mkdir()
    for seed in (4, 5):
        _write_npz(fleet / f'rig{seed}.npz', hysteretic_record(seed=seed))
    idle = hysteretic_record(seed=6)
    _write_npz(fleet / 'idle.npz', Record(u=np.zeros(3000), y=idle.y, fs=idle.fs, source='idle'))
    save_model(run_experiment([hysteretic_record(seed=7)], ExperimentConfig(
        narx=False, arx_na=(1,), arx_nb=(1,), jobs=1)).best.model, fleet / 'model.json')
    (tmp_path / 'fast.yaml').write_text(json.dumps({'training': FAST_TRAINING,
                                                    'final_training': {'refine_iter': 4}}))
    common = [str(fleet), '--per-record', '--config', str(tmp_path / 'fast.yaml'), *FLEET_ARGS]
    outs = {}
    for name, extra in (('local', ['--jobs', '2']), ('ray', ['--executor', 'ray'])):
        outs[name] = tmp_path / name
        code, out, err = _cli(['fit', '--preset', 'paper',
                               *common, '--out', str(outs[name]), *extra], capsys)
        # The idle recording fails alone, named in one line; the others are fitted.
        assert code == 2 and err.count('\n') == 1, err
        assert '1 of 3 recordings could not be fitted' in err and 'idle:' in err
    for name in ('rig4', 'rig5'):
        models = [weights_sha256(_load(outs[k] / name / 'model.json')) for k in outs]
        assert models[0] == models[1]
        cands = [without_times(json.loads((outs[k] / name / 'candidates.json').read_text()))
                 for k in outs]
        assert cands[0] == cands[1]
        assert cands[0]['data']['sources'] == [str(fleet / f'{name}.npz')]
    tables = []
    for k in outs:
        with open(outs[k] / 'summary.csv', newline='') as f:
            tables.append(list(csv.DictReader(f)))
    assert [(r['recording'], r['status']) for r in tables[0]] == [
        ('idle', 'failed'), ('rig4', 'ok'), ('rig5', 'ok')]
    assert 'constant' in tables[0][0]['error']
    same = ('recording', 'status', 'selected', 'n_params', 'validated',
            'r2_validation_simulation', 'r2_worst_case', 'rmse_validation_simulation_m')
    assert [{c: r[c] for c in same} for r in tables[0]] == \
        [{c: r[c] for c in same} for r in tables[1]]
    assert not (outs['local'] / 'model').exists()     # the model.json/.npz pair was skipped

    # Each recording's fit is the fit of that recording alone.
    alone = tmp_path / 'alone'
    code, _, _ = _cli(['fit', '--preset', 'paper',
                       str(fleet / 'rig5.npz'), '--config', str(tmp_path / 'fast.yaml'),
                       *FLEET_ARGS, '--jobs', '1', '--out', str(alone)], capsys)
    assert code == 0
    assert weights_sha256(_load(alone / 'model.json')) == \
        weights_sha256(_load(outs['local'] / 'rig5' / 'model.json'))


def _load(path):
    from piezo_narx_ros.ident.model_io import load_model
    return load_model(path)


def test_executor_options_are_checked(capsys, tmp_path):
    with pytest.raises(ConfigError, match='--ray-address needs --executor ray'):
        make_executor('local', 2, 'auto')
    with pytest.raises(ConfigError, match='executor must be one of local, ray'):
        make_executor('dask', 2)
    with pytest.raises(ConfigError, match='jobs must be an integer'):
        LocalExecutor(0)
    _write_npz(tmp_path / 'r.npz', hysteretic_record())
    code, _, err = _cli(['fit', '--preset', 'paper',
                         str(tmp_path / 'r.npz'), '--out', str(tmp_path / 'o'),
                         '--ray-address', 'auto', *FLEET_ARGS], capsys)
    assert code == 2 and err == 'piezo-narx: error: --ray-address needs --executor ray\n'


def test_fit_task_is_what_every_executor_runs():
    # The Ray and pool paths call the one task function; its payload is (spec, config).
    config = ExperimentConfig(narx=False, arx_na=(2,), arx_nb=(1,), jobs=1)
    record = hysteretic_record(seed=8)
    from piezo_narx_ros.ident.selection.experiment import split_records
    direct = fit_task((config.specs()[0], config), split_records([record]))
    assert direct.error is None
    assert direct.scores == run_experiment([record], config).best.scores


def _descendants(pid: int) -> set:
    """Every live process below pid (from /proc)."""
    children = {}
    for stat in Path('/proc').glob('[0-9]*/stat'):
        try:
            fields = stat.read_text().rsplit(')', 1)[1].split()
        except OSError:
            continue
        children.setdefault(int(fields[1]), []).append(int(stat.parent.name))
    found, todo = set(), [pid]
    while todo:
        for child in children.get(todo.pop(), []):
            found.add(child)
            todo.append(child)
    return found


def _alive(pid: int) -> bool:
    try:
        state = Path(f'/proc/{pid}/stat').read_text().rsplit(')', 1)[1].split()[0]
    except OSError:
        return False
    return state != 'Z'


def _cmdline(pid: int) -> str:
    try:
        return Path(f'/proc/{pid}/cmdline').read_bytes().replace(b'\0', b' ').decode()
    except OSError:
        return ''


def _terminal_sigint():
    """
    Give the child SIGINT as a terminal does.

    A suite started in the background (nohup, `&` in a script) runs with SIGINT ignored, and an
    ignored SIGINT is inherited and respected (tested below).
    """
    signal.signal(signal.SIGINT, signal.SIG_DFL)


@pytest.mark.parametrize('whom, when', [('group', 'ray::_ray_call'), ('driver', 'ray::_ray_call'),
                                        ('driver', 'gcs_server')])
def test_ctrl_c_stops_the_local_ray_cleanly(tmp_path, whom, when):
    """
    Ctrl-C in a terminal signals the whole process group.

    A signal to the driver alone takes the path a remote cluster sees (cancel the tasks,
    disconnect). Either while tasks run, or while the local Ray is still starting (`gcs_server` up,
    the rest coming).
    """
    _write_npz(tmp_path / 'r.npz', hysteretic_record(n=6000, seed=9))
    proc = subprocess.Popen(
        [sys.executable, '-m', 'piezo_narx_ros.cli.main', 'fit', '--preset', 'paper',
         str(tmp_path / 'r.npz'),
         '--executor', 'ray', '--jobs', '2', '--ny', '1-4', '--nu', '1-4', '--no-report',
         '--out', str(tmp_path / 'out')],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
        preexec_fn=_terminal_sigint)
    family = set()
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and proc.poll() is None:
            family |= _descendants(proc.pid)
            if any(when in _cmdline(p) for p in family):
                break
            time.sleep(0.05)
        assert proc.poll() is None, 'the fit ended before the interrupt'
        assert any(when in _cmdline(p) for p in family), f'no {when} process came up'
        (os.killpg if whom == 'group' else os.kill)(proc.pid, signal.SIGINT)
        out, err = proc.communicate(timeout=60)
    finally:
        family |= _descendants(proc.pid)
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert proc.returncode == 130, err
    assert err.strip().splitlines()[-1] == 'piezo-narx: interrupted'
    assert not (tmp_path / 'out' / 'model.json').exists()
    deadline = time.monotonic() + 20
    while time.monotonic() < deadline and any(_alive(p) for p in family):
        time.sleep(0.5)
    left = [(p, _cmdline(p)[:60]) for p in family if _alive(p)]
    for pid, _ in left:     # do not leave them to the next test, but fail
        os.kill(pid, signal.SIGKILL)
    assert not left, f'Ray processes left behind: {left}'


def _stop_group(proc, grace=15.0):
    """SIGTERM to a process group this test started, SIGKILL after `grace` seconds."""
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGTERM)
        try:
            proc.wait(timeout=grace)
        except subprocess.TimeoutExpired:
            pass
    with_pids = list(_descendants(proc.pid))
    try:
        os.killpg(proc.pid, signal.SIGKILL)
    except ProcessLookupError:
        pass
    proc.wait()
    return with_pids


def test_fit_on_a_running_cluster_by_address(tmp_path):
    """
    Check that `--ray-address` connects to a cluster started apart (`ray start --head`).

    It ships this package's code with the job, and gives the local pool's model.
    """
    import re
    record = hysteretic_record(seed=10)
    _write_npz(tmp_path / 'r.npz', record)
    (tmp_path / 'fast.yaml').write_text(json.dumps({'training': FAST_TRAINING,
                                                    'final_training': {}}))
    args = ['fit', '--preset', 'paper', str(tmp_path / 'r.npz'), '--config',
            str(tmp_path / 'fast.yaml'), *FLEET_ARGS]
    # The local pool's reference fit runs while the cluster comes up (most of that is waiting).
    local = subprocess.Popen(
        [sys.executable, '-m', 'piezo_narx_ros.cli.main', *args, '--jobs', '2',
         '--out', str(tmp_path / 'local')], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
        text=True)
    ray_cli = Path(sys.executable).with_name('ray')
    head = subprocess.Popen(
        [str(ray_cli), 'start', '--head', '--block', '--port=0', '--num-cpus=2',
         '--include-dashboard=false', '--disable-usage-stats',
         f'--object-store-memory={200 * 2 ** 20}'],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True)
    try:
        address, lines = None, []
        deadline = time.monotonic() + 90
        while address is None and time.monotonic() < deadline:
            line = head.stdout.readline()
            if not line:
                break
            lines.append(line)
            found = re.search(r"ray start --address='([^']+)'", line)
            address = found.group(1) if found else None
        assert address, 'ray start --head did not come up:\n' + ''.join(lines[-20:])
        done = subprocess.run(
            [sys.executable, '-m', 'piezo_narx_ros.cli.main', *args, '--executor', 'ray',
             '--ray-address', address, '--out', str(tmp_path / 'cluster')],
            capture_output=True, text=True, timeout=300)
        assert done.returncode == 0, done.stderr
        _, err = local.communicate(timeout=300)
        assert local.returncode == 0, err
    finally:
        if local.poll() is None:
            local.kill()
            local.wait()
        _stop_group(head)
        # `ray start` notes its address for later `ray.init()` calls; the cluster is gone.
        note = Path('/tmp/ray/ray_current_cluster')
        if address and note.is_file() and note.read_text().strip() == address:
            note.unlink()
    assert weights_sha256(_load(tmp_path / 'cluster' / 'model.json')) == \
        weights_sha256(_load(tmp_path / 'local' / 'model.json'))
    docs = [without_times(json.loads((tmp_path / d / 'candidates.json').read_text()))
            for d in ('cluster', 'local')]
    assert docs[0] == docs[1]


def test_unreachable_address_is_one_line(tmp_path):
    _write_npz(tmp_path / 'r.npz', hysteretic_record(seed=11))
    done = subprocess.run(
        [sys.executable, '-m', 'piezo_narx_ros.cli.main', 'fit', '--preset', 'paper',
         str(tmp_path / 'r.npz'),
         *FLEET_ARGS, '--executor', 'ray', '--ray-address', '127.0.0.1:9',
         '--out', str(tmp_path / 'o')], capture_output=True, text=True, timeout=300)
    assert done.returncode == 2, done.stderr
    assert done.stderr.strip().splitlines()[-1].startswith(
        'piezo-narx: error: --ray-address 127.0.0.1:9: cannot connect to a Ray cluster')


def test_without_address_a_local_ray_is_started_and_stopped(tmp_path):
    _write_npz(tmp_path / 'r.npz', hysteretic_record(seed=12))
    proc = subprocess.Popen(
        [sys.executable, '-m', 'piezo_narx_ros.cli.main', 'fit', '--preset', 'paper',
         str(tmp_path / 'r.npz'),
         '--no-arx', '--ny', '1', '--nu', '1', '--hidden', '2', '--no-report', '--executor',
         'ray', '--jobs', '2', '--out', str(tmp_path / 'o')],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    seen = {}
    try:
        while proc.poll() is None:
            for pid in _descendants(proc.pid) - set(seen):
                seen[pid] = _cmdline(pid)
            time.sleep(0.1)
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert proc.returncode == 0, err
    assert '(local Ray (2 CPUs))' in out.splitlines()[0]
    assert any('raylet' in c for c in seen.values()), 'no Ray of its own was started'
    family = set(seen)
    deadline = time.monotonic() + 20
    while time.monotonic() < deadline and any(_alive(p) for p in family):
        time.sleep(0.5)
    assert not [p for p in family if _alive(p)], 'the local Ray outlived the command'
    assert (tmp_path / 'o' / 'model.json').is_file()


def test_an_ignored_sigint_stays_ignored_by_the_ray_search():
    """A fit started with SIGINT ignored (nohup, a background job) is not stopped by one."""
    from piezo_narx_ros.ident.selection import executor
    caught = []
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        for hold in (True, False):
            with executor._record_interrupts(caught, hold):
                assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
                os.kill(os.getpid(), signal.SIGINT)
                time.sleep(0.05)
        assert caught == []
        # Python's default disposition (a terminal's): recorded and raised.
        signal.signal(signal.SIGINT, signal.default_int_handler)
        with executor._record_interrupts(caught, hold=False):
            with pytest.raises(KeyboardInterrupt):
                os.kill(os.getpid(), signal.SIGINT)
                time.sleep(1.0)
        assert caught == [True]
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    finally:
        signal.signal(signal.SIGINT, previous)
