"""The structure search (ident/selection/search.py)."""
import json

import numpy as np
import pytest

from piezo_narx_ros.errors import ConfigError, DataError
from piezo_narx_ros.ident.model_io import weights_sha256
from piezo_narx_ros.ident.selection.executor import Executor, LocalExecutor
from piezo_narx_ros.ident.selection.search import (SEARCH_FAMILIES, SPACE, SearchOptions,
                                                   SpaceContext, increment_free, pareto_front,
                                                   run_search, seed_design, space,
                                                   spec_from_params, trial_task)
from piezo_narx_ros.ident.state.start import START_POLICIES
from piezo_narx_ros.plant.piezo import PiezoCantilever
from piezo_narx_ros.plant.signals import generate
from piezo_narx_ros.record import Record

FS = 2000.0


def _record(kind, seconds, seed, offset=0.0, name='r'):
    u = generate(kind, FS, seconds, 80.0, seed=seed,
                 **({'f_max': 40.0} if kind == 'multisine' else {}))
    y = PiezoCantilever(fs=FS, seed=seed).run(u).y
    return Record(u=u, y=y + offset, fs=FS, source=f'{name}{seed}')


@pytest.fixture(scope='module')
def records():
    return [_record('protocol', 2.0, 1, name='est')], [_record('multisine', 1.0, 2, name='val')]


def _options(**kw):
    base = {'trials': 2, 'batch': 2, 'budget_s': None, 'families': ('arx', 'hysteresis_narx'),
            'init_samples': 200, 'progress': False}
    return SearchOptions(**{**base, **kw})


def search_picks(result):
    """Return what must not depend on the executor: the trials, the pick, its weights' bits."""
    return (result.numbers[result.selected], weights_sha256(result.best.model),
            [t.spec for t in result.trials], [t.scores.get('start') for t in result.trials])


# ------------------------------------------------------------------ space and selection
def test_space_seed_design_and_specs_agree():
    for context in (SpaceContext(1, 1), SpaceContext(3, 3), SpaceContext(2, 1)):
        design = seed_design(context)
        assert design and {p['family'] for p in design} == set(SEARCH_FAMILIES)
        for params in design:
            spec, _ = spec_from_params(params)
            assert spec.kind == params['family']
            spec.build({})
    for name, dist in SPACE['hysteresis_narx'].items():
        assert dist[0] in ('int', 'cat'), name
    # Several estimation records of one axis: the hysteresis family also chooses its zeros, and
    # the seed design keeps the presets' per-record zeros.
    several = SpaceContext(1, 1, 3)
    assert 'hnarx_offsets' in space(several)['hysteresis_narx']
    assert 'hnarx_offsets' not in space(SpaceContext(1, 1, 1))['hysteresis_narx']
    for params in seed_design(several, ('hysteresis_narx',)):
        assert params['hnarx_offsets'] == 'per_record'
        assert dict(spec_from_params(params)[0].options)['record_offsets'] == 'yes'
    shared = {**seed_design(several, ('hysteresis_narx',))[0], 'hnarx_offsets': 'shared'}
    assert dict(spec_from_params(shared)[0].options)['record_offsets'] == 'no'


def test_networks_without_increments_only_on_a_slow_input():
    fast = [_record('multisine', 1.0, 3)]
    slow = [Record(u=80.0 * np.sin(2 * np.pi * 0.5 * np.arange(4000) / FS), y=np.zeros(4000),
                   fs=FS, source='slow')]
    free, note = increment_free(fast)
    assert not free and 'drive increments only' in note and 'moves fast' in note
    assert increment_free(slow) == (True, '')
    two_axes = Record(u=np.column_stack([fast[0].u, fast[0].u]),
                      y=np.column_stack([fast[0].y, fast[0].y]), fs=FS, source='xy')
    assert increment_free([two_axes])[0]     # several axes: not measured, left in
    kept, dropped = SpaceContext(), SpaceContext(without_increments=False)
    assert 0 in space(kept)['hysteresis_narx']['hnarx_lags'][1]
    lags = space(dropped)['hysteresis_narx']['hnarx_lags'][1]
    assert 0 not in lags and set(lags) == set(SPACE['hysteresis_narx']['hnarx_lags'][1]) - {0}
    assert any(p.get('hnarx_lags') == 0 for p in seed_design(kept))
    design = seed_design(dropped)
    assert design and all(p.get('hnarx_lags') != 0 for p in design)
    assert len(design) == len(seed_design(kept)) - 1


def test_every_start_is_scored_and_the_state_kept_unless_a_lagged_offset_never_loses(
        monkeypatch):
    from piezo_narx_ros.ident.selection import search
    errors = {'rest': 0.0050, 'offset': 0.0101, 'state': 0.0110}
    short = {}

    def policy_error(model, records, n, policy, past):
        e = short.get((policy, n), errors[policy])
        return {'r2_worst': 1 - e ** 2, 'error': e, 'records': []}

    monkeypatch.setattr(search, '_policy_error', policy_error)
    monkeypatch.setattr(search, 'check_window', lambda *a: None)
    monkeypatch.setattr(search, 'lagged', lambda model: False)
    rec = Record(u=np.zeros(400), y=np.zeros(400), fs=FS, source='v')
    got = search.start_scores(None, [rec], 100)
    # The hysteresis family: rest and offset score better here, and are reported; state is kept.
    assert got['policy'] == 'state' and got['error'] == errors['state']
    assert got['policies']['rest']['error'] == errors['rest']
    assert got['policies']['offset']['error'] == errors['offset']
    # A lagged family: offset, no worse with every window, is kept; rest never.
    monkeypatch.setattr(search, 'lagged', lambda model: True)
    monkeypatch.setattr(search, 'check_windows', lambda model, n: (50, 100))
    assert search.start_scores(None, [rec], 100)['policy'] == 'offset'
    short[('offset', 50)] = 0.0200      # worse than the measured lags with a shorter window
    assert search.start_scores(None, [rec], 100)['policy'] == 'state'


def test_pareto_front_keeps_the_undominated_points():
    points = [(0.1, 10), (0.05, 100), (0.2, 5), (0.1, 20), (0.05, 100), (0.3, 200)]
    assert pareto_front(points) == [0, 1, 2]


def test_options_are_checked_against_their_table():
    with pytest.raises(ConfigError, match='trials must be an integer'):
        SearchOptions(trials=0).validate()
    with pytest.raises(ConfigError, match='families must be distinct'):
        SearchOptions(families=('arx', 'lstm')).validate()


# ------------------------------------------------------------------ the study
def test_no_validation_sample_reaches_a_fit(records):
    est, val = records
    other = [Record(u=val[0].u, y=val[0].y[::-1].copy(), fs=FS, source='scrambled')]
    options = _options()
    options.validate()
    for params in ({'family': 'arx', 'arx_na': 3, 'arx_nb': 2},
                   seed_design(SpaceContext(), ('hysteresis_narx',))[2]):
        a = trial_task((params, options, 200), (est, val))
        b = trial_task((params, options, 200), (est, other))
        assert a.error is None and b.error is None
        assert weights_sha256(a.model) == weights_sha256(b.model)
        assert a.scores['start'] != b.scores['start']


def test_the_same_model_for_one_and_two_workers(tmp_path, records):
    est, val = records
    picks = []
    for jobs in (1, 2):
        with LocalExecutor(jobs) as ex:
            res = run_search(est, val, _options(), ex, tmp_path / f'j{jobs}')
        picks.append(search_picks(res))
    assert picks[0] == picks[1]
    assert [s.kind for s in picks[0][2]] == ['hysteresis_narx'] * 2


class _Interrupting(Executor):
    """An executor whose run is interrupted (Ctrl-C) after `after` finished tasks."""

    def __init__(self, after):
        self.after, self.count = after, 0

    def map(self, fn, tasks, data, done=None):  # noqa: A003 - Executor.map
        out = []
        for i, (key, payload) in enumerate(tasks):
            if self.count == self.after:
                raise KeyboardInterrupt
            out.append(fn(payload, data[key]))
            self.count += 1
            if done:
                done(i, out[-1])
        return out


def test_resume_after_an_interruption_ends_on_the_same_model(tmp_path, records):
    est, val = records
    options = _options(families=('arx',), trials=7, batch=3)
    with LocalExecutor(1) as ex:
        whole = run_search(est, val, options, ex, tmp_path / 'whole')
    with pytest.raises(KeyboardInterrupt):     # in the second batch, one of its trials done
        run_search(est, val, options, _Interrupting(4), tmp_path / 'cut')
    with pytest.raises(ConfigError, match='continue it with --resume'):
        run_search(est, val, options, LocalExecutor(1), tmp_path / 'cut')
    with LocalExecutor(1) as ex:
        resumed = run_search(est, val, options, ex, tmp_path / 'cut', resume=True)
    assert resumed.taken_over == 4
    assert search_picks(resumed) == search_picks(whole)
    assert len(resumed.trials) == 7
    with pytest.raises(ConfigError, match='other records or settings'):
        run_search(est, [Record(u=val[0].u, y=val[0].y * 2, fs=FS, source='v')], options,
                   LocalExecutor(1), tmp_path / 'cut', resume=True)


def test_a_constant_validation_record_is_refused(tmp_path, records):
    est, val = records
    flat = [Record(u=val[0].u, y=np.zeros_like(val[0].y), fs=FS, source='flat.npz')]
    with pytest.raises(DataError, match='flat.npz: the output is constant'):
        run_search(est, flat, _options(), LocalExecutor(1), tmp_path / 'f')


def test_every_policy_is_scored_and_the_best_eligible_one_kept(records):
    est, val = records
    options = _options()
    options.validate()
    res = trial_task(({'family': 'arx', 'arx_na': 3, 'arx_nb': 3}, options, 200), (est, val))
    start = res.scores['start']
    assert set(start['policies']) == set(START_POLICIES)
    pol = start['policies']
    assert set(pol['rest']['windows']) == {'25', '50', '100', '200'}
    # A lagged model leaves its measured lags only for a policy no worse with any window.
    eligible = [p for p in pol if p == 'state' or all(
        pol[p]['windows'][w] <= pol['state']['windows'][w] for w in pol[p]['windows'])]
    assert start['policy'] in eligible
    eligible = [p for p in eligible if p != 'rest']      # scored and reported, never kept
    assert start['policy'] in eligible
    assert start['error'] == min(pol[p]['error'] for p in eligible)


def test_the_papers_network_is_searched_only_where_the_input_closes_minor_loops(records):
    from piezo_narx_ros.ident.selection.search import resolve_families
    sine = _record('sine', 2.0, 3)
    families, notes = resolve_families([sine], None)
    assert 'narx' not in families and "the paper's NARX is left out" in notes[0]
    assert resolve_families(records[0], None) == (SEARCH_FAMILIES, [])
    assert resolve_families([sine], ('narx',)) == (('narx',), [])


def test_fit_searches_by_default_and_resumes_from_the_command_line(tmp_path, records, capsys):
    from piezo_narx_ros.cli.main import main
    paths = []
    for name, rec in (('est', records[0][0]), ('val', records[1][0])):
        paths.append(tmp_path / f'{name}.npz')
        np.savez(paths[-1], u=rec.u[:, 0], y=rec.y[:, 0], fs=FS)

    def fit(out, *extra):
        with pytest.raises(SystemExit) as done:
            main(['fit', str(paths[0]), '--validate', str(paths[1]), '--out', str(out),
                  '--families', 'arx', '--batch', '3', '--init-samples', '200', '--jobs', '1',
                  *extra])
        captured = capsys.readouterr()
        return done.value.code, captured.out, captured.err

    code, out, err = fit(tmp_path / 'a', '--trials', '3')
    assert code == 0, err
    assert 'selected ARX(' in out and 'why: ' in out and 'optuna-dashboard' in out
    doc = json.loads((tmp_path / 'a' / 'model.json').read_text())
    assert doc['start']['window_samples'] == 200 and doc['data']['preset'] == 'search'
    assert (tmp_path / 'a' / 'report' / 'pareto.png').stat().st_size > 10_000
    assert len(json.loads((tmp_path / 'a' / 'candidates.json').read_text())['candidates']) == 3
    code, _, err = fit(tmp_path / 'a', '--trials', '3')
    assert code == 2 and err.count('\n') == 1 and 'continue it with --resume' in err
    code, out, err = fit(tmp_path / 'a', '--trials', '6', '--resume', '--no-report')
    assert code == 0 and 'resumed: 3 trial(s) taken over' in out, err
    code, _, err = fit(tmp_path / 'b', '--trials', '6', '--no-report')
    assert code == 0, err
    from piezo_narx_ros.ident.model_io import load_model
    assert weights_sha256(load_model(tmp_path / 'a' / 'model.json')) == \
        weights_sha256(load_model(tmp_path / 'b' / 'model.json'))
    code, _, err = fit(tmp_path / 'c', '--trials', '0')
    assert code == 2 and 'trials must be an integer in [1' in err


def test_sigint_then_resume_ends_on_the_uninterrupted_model(tmp_path, records):
    import os
    import signal
    import subprocess
    import sys
    import time
    paths = []
    for name, rec in (('est', records[0][0]), ('val', records[1][0])):
        paths.append(tmp_path / f'{name}.npz')
        np.savez(paths[-1], u=rec.u[:, 0], y=rec.y[:, 0], fs=FS)
    env = {**os.environ, 'PYTHONUNBUFFERED': '1'}

    def argv(out, *extra):
        return [sys.executable, '-m', 'piezo_narx_ros.cli.main', 'fit', str(paths[0]),
                '--validate', str(paths[1]), '--out', str(out), '--families', 'arx',
                '--trials', '16', '--batch', '2', '--init-samples', '200', '--jobs', '1',
                '--no-report', '--quiet', *extra]
    # SIGINT as a terminal leaves it (a suite started in the background inherits it ignored).
    proc = subprocess.Popen(argv(tmp_path / 'cut'), env=env, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    trials = tmp_path / 'cut' / 'trials'
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and len(list(trials.glob('*.model.json'))) < 3:
        time.sleep(0.05)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err
    assert 'continue it with the same command and --resume' in err
    done = subprocess.run(argv(tmp_path / 'cut', '--resume'), env=env, capture_output=True,
                          text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    whole = subprocess.run(argv(tmp_path / 'whole'), env=env, capture_output=True, text=True,
                           timeout=300)
    assert whole.returncode == 0, whole.stderr
    from piezo_narx_ros.ident.model_io import load_model
    assert weights_sha256(load_model(tmp_path / 'cut' / 'model.json')) == \
        weights_sha256(load_model(tmp_path / 'whole' / 'model.json'))
    cut = json.loads((tmp_path / 'cut' / 'candidates.json').read_text())
    # Three trial models were on disk at the interrupt; the newest trial's scores are written
    # after its model (study.save_trial), so a cut between the two fits that trial again.
    assert cut['search']['taken_over'] >= 2
    assert [c['label'] for c in cut['candidates']] == [
        c['label'] for c in json.loads((tmp_path / 'whole' / 'candidates.json').read_text())[
            'candidates']]


@pytest.mark.parametrize('signum', ['SIGINT', 'SIGTERM'])
def test_a_signal_inside_a_journal_write_comes_after_it(tmp_path, signum):
    # CI once stopped with FileNotFoundError instead of the interruption: SIGINT landed inside
    # Optuna's lock release. The write must finish, the lock go, then the signal act.
    import os
    import signal
    from piezo_narx_ros.ident.selection.study import signal_safe_journal
    sig = getattr(signal, signum)
    # Both as a terminal's Python has them (a suite started in the background inherits SIGINT
    # ignored, and an ignored signal stays ignored through the write).
    previous = {s: signal.signal(s, signal.default_int_handler)
                for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        backend = signal_safe_journal(str(tmp_path / 'j'))
        release = backend._lock.release

        def release_after_a_signal():
            os.kill(os.getpid(), sig)
            release()

        backend._lock.release = release_after_a_signal
        with pytest.raises(KeyboardInterrupt):
            backend.append_logs([{'op': 1}])
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
    assert list(backend.read_logs(0)) == [{'op': 1}]
    assert sorted(p.name for p in tmp_path.iterdir()) == ['j']


def test_an_interruption_after_any_journal_write_resumes_to_the_same_model(
        tmp_path, records, monkeypatch):
    # Ctrl-C can land between any two writes of the study (asking a batch, fitting it, telling
    # its results): a resume from each must end on the uninterrupted run's model and trials.
    from piezo_narx_ros.ident.selection import study as study_module
    real = study_module.signal_safe_journal
    writes = {'n': 0, 'stop_after': None}

    def counting(path):
        backend = real(path)
        append = backend.append_logs

        def append_logs(logs):
            append(logs)
            writes['n'] += 1
            if writes['n'] == writes['stop_after']:
                raise KeyboardInterrupt
        backend.append_logs = append_logs
        return backend
    monkeypatch.setattr(study_module, 'signal_safe_journal', counting)
    est, val = records
    options = _options(families=('arx',), trials=6, batch=3)

    def picks(result):
        return (weights_sha256(result.best.model), [t.spec for t in result.trials],
                [t.scores.get('start') for t in result.trials])
    with LocalExecutor(1) as ex:
        whole = picks(run_search(est, val, options, ex, tmp_path / 'whole'))
    total = writes['n']
    for stop in range(1, total):
        out = tmp_path / f'cut{stop}'
        writes.update(n=0, stop_after=stop)
        with pytest.raises(KeyboardInterrupt), LocalExecutor(1) as ex:
            run_search(est, val, options, ex, out)
        writes['stop_after'] = None
        with LocalExecutor(1) as ex:
            assert picks(run_search(est, val, options, ex, out, resume=True)) == whole, stop


def test_the_committee_is_the_mean_of_the_pick_and_the_next_best_of_its_family(
        tmp_path, records):
    from piezo_narx_ros.ident.model_io import load_model
    from piezo_narx_ros.ident.selection.search import trial_error
    from piezo_narx_ros.ident.selection.search_report import write_search
    est, val = records
    with LocalExecutor(2) as ex:
        # A wide tolerance: the committee is kept on any CPU (its bits may differ between them).
        wide = {'trials': 4, 'batch': 4, 'tolerance': 0.5, 'families': ('hysteresis_narx',)}
        res = run_search(est, val, _options(**wide, committee=2), ex, tmp_path / 'c')
        alone = run_search(est, val, _options(**wide, committee=1), ex, tmp_path / 'a')
        linear = run_search(est, val, _options(trials=2, batch=2, families=('arx',)), ex,
                            tmp_path / 'l')
    pick = res.trials[res.selected]
    assert pick.spec.kind == 'hysteresis_narx' and len(res.members) == 2
    assert res.members[0] == res.selected
    other = res.trials[res.members[1]]
    family = [i for i, t in enumerate(res.trials)
              if t.spec.kind == pick.spec.kind and i != res.selected]
    assert res.members[1] == min(family, key=lambda i: trial_error(res.trials[i]))
    # The committee's free run is the mean of its members', and it is scored like a trial.
    u = val[0].u[:, 0]
    np.testing.assert_allclose(res.best.model.simulate(u),
                               0.5 * (pick.model.simulate(u) + other.model.simulate(u)),
                               rtol=0, atol=1e-15)
    assert trial_error(res.best) <= 1.5 * trial_error(pick)
    assert res.best.scores['start']['policy'] in START_POLICIES
    assert 'mean of it and the 1 next best' in res.why
    assert res.to_dict()['selection']['committee'] == [res.numbers[i] for i in res.members]
    model_path, _ = write_search(tmp_path / 'out', res, est, val, report=False)
    saved = load_model(model_path)
    assert saved.kind == 'ensemble' and len(saved.members) == 2
    assert saved.metadata['start']['policy'] == res.best.scores['start']['policy']
    # One model asked for, or a family without random starts: the pick itself.
    assert alone.committee is None and alone.best is alone.trials[alone.selected]
    assert weights_sha256(alone.best.model) == weights_sha256(pick.model)
    assert linear.committee is None and linear.best.spec.kind == 'arx'


def test_the_committee_is_refused_when_it_scores_worse_than_the_pick():
    from piezo_narx_ros.ident.selection.committee import form_committee
    from piezo_narx_ros.ident.selection.experiment import CandidateResult, CandidateSpec

    class One:           # a fitted one-axis model as form_committee and an ensemble see it
        n_in = n_out = 1
        nu, ny = 0, 3
        output_2d_, fs, input_range, output_range = False, FS, None, None
        state_from_input, inputs, outputs = True, ('x',), ('x',)
    trials = [CandidateResult(CandidateSpec('hysteresis_narx', 0, 3, 4, seed=s), model=One())
              for s in range(3)]
    scored = []

    def score(model, spec):
        scored.append(len(model.members))
        return CandidateResult(spec=spec, n_params=3), 0.5
    got, members, why = form_committee(trials, [0.1, 0.3, 0.2], [0, 1, 2], 0, 2, 0.02, score)
    assert (got, members, scored) == (None, [], [2]) and 'the pick alone is the model' in why
    # Within the tolerance of the pick it is kept, its members the pick and the next best.
    kept = form_committee(trials, [0.1, 0.3, 0.2], [0, 1, 2], 0, 3, 0.02,
                          lambda m, s: (CandidateResult(spec=s, n_params=9), 0.101))
    assert kept[0] is not None and kept[1] == [0, 2, 1] and 'within 2 % of the pick' in kept[2]
    assert form_committee(trials, [0.1, 0.3, 0.2], [0, 1, 2], 0, 3, 0.02,
                          lambda m, s: (CandidateResult(spec=s, n_params=9), 0.103))[0] is None
