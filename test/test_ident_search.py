"""The structure search (ident/search.py) and the start policies (ident/start.py)."""
import json

import numpy as np
import pytest

from piezo_narx_ros.errors import ConfigError, DataError, ModelFileError
from piezo_narx_ros.ident.arx.model import ARXModel
from piezo_narx_ros.ident.model_io import load_model, save_model, weights_sha256
from piezo_narx_ros.ident.selection.executor import Executor, LocalExecutor
from piezo_narx_ros.ident.selection.search import (SEARCH_FAMILIES, SPACE, SearchOptions,
                                                   SpaceContext, pareto_front, run_search,
                                                   seed_design, spec_from_params, trial_task)
from piezo_narx_ros.ident.state.start import (START_POLICIES, check_window, policy_simulate,
                                              window_state)
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


# ------------------------------------------------------------------ start policies
def test_state_policy_of_a_lagged_model_is_the_paper_start_at_the_window_end(records):
    est, val = records
    r = val[0]
    m = ARXModel(na=4, nb=3).fit(r.u[:, 0], r.y[:, 0], fs=FS)
    u, y, n = r.u[:, 0], r.y[:, 0], 300
    sim = policy_simulate(m, u, y, n, 'state')
    paper = m.simulate(u[n - m.n0:], y[n - m.n0:n])
    np.testing.assert_array_equal(sim[n:], paper[m.n0:])
    rest = policy_simulate(m, u, y, n, 'rest')
    np.testing.assert_array_equal(rest, m.simulate(u))


def test_offset_policy_recovers_a_moved_sensor_zero(records):
    r = records[1][0]
    m = ARXModel(na=4, nb=3).fit(r.u[:, 0], r.y[:, 0], fs=FS)
    u, y = r.u[:, 0], r.y[:, 0]
    shift = 3e-6
    state = window_state(m, u[:400], m.simulate(u)[:400] + shift, 'offset')
    assert state.offset == pytest.approx(shift, rel=1e-9)
    moved = policy_simulate(m, u, m.simulate(u) + shift, 400, 'offset')
    np.testing.assert_allclose(moved, m.simulate(u) + shift, rtol=0, atol=1e-15)
    assert not np.allclose(policy_simulate(m, u, y, 400, 'rest'), moved)


def test_a_window_too_short_for_a_policy_is_refused_in_one_line(records):
    m = ARXModel(na=8, nb=3).fit(records[1][0].u[:, 0], records[1][0].y[:, 0], fs=FS)
    with pytest.raises(DataError, match="'state' needs at least 10 measured samples, got 5"):
        check_window(m, 'state', 5, 1000, 'rec.npz')
    with pytest.raises(DataError, match='too short for a window of 990'):
        check_window(m, 'offset', 990, 991, 'rec.npz')
    check_window(m, 'rest', 0, 10, 'rec.npz')


def test_start_policy_round_trips_through_the_model_file(tmp_path, records):
    r = records[1][0]
    m = ARXModel(na=2, nb=2).fit(r.u[:, 0], r.y[:, 0], fs=FS)
    path = save_model(m, tmp_path / 'm.json', start={'policy': 'offset', 'window_samples': 1000})
    loaded = load_model(path)
    assert loaded.metadata['start'] == {'policy': 'offset', 'window_samples': 1000,
                                        'window_s': 0.5}
    doc = json.loads(path.read_text())
    doc['start']['policy'] = 'magic'
    path.write_text(json.dumps(doc))
    with pytest.raises(ModelFileError, match='start must be'):
        load_model(path)
    with pytest.raises(ModelFileError, match='window_samples'):
        save_model(m, tmp_path / 'n.json', start={'policy': 'state', 'window_samples': -3})


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


def test_every_policy_is_scored_and_the_best_kept(records):
    est, val = records
    options = _options()
    options.validate()
    res = trial_task(({'family': 'arx', 'arx_na': 3, 'arx_nb': 3}, options, 200), (est, val))
    start = res.scores['start']
    assert set(start['policies']) == set(START_POLICIES)
    errors = {p: v['error'] for p, v in start['policies'].items()}
    assert start['error'] == min(errors.values())
    assert errors[start['policy']] == start['error']
