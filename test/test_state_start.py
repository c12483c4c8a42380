"""Start policies (ident/state/start.py): offline, in model files, evaluate, the estimator."""
import json

import numpy as np
import pytest

from piezo_narx_ros.cli.main import main
from piezo_narx_ros.errors import DataError, ModelFileError
from piezo_narx_ros.estimator.free_run import FreeRunEstimator
from piezo_narx_ros.ident.arx.model import ARXModel
from piezo_narx_ros.ident.model_io import load_model, save_model, weights_sha256
from piezo_narx_ros.ident.state.start import check_window, policy_simulate, window_state
from piezo_narx_ros.plant.piezo import PiezoCantilever
from piezo_narx_ros.plant.signals import generate
from piezo_narx_ros.record import Record

FS = 2000.0
P = 500_000   # ns per sample at 2 kHz


@pytest.fixture(scope='module')
def records():
    out = []
    for seed in (1, 2):
        u = generate('multisine', FS, 1.0, 80.0, seed=seed, f_max=40.0)
        out.append(Record(u=u, y=PiezoCantilever(fs=FS, seed=seed).run(u).y, fs=FS,
                          source=f'r{seed}'))
    return [out[0]], [out[1]]


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


def _with_error(model, rmse_m):
    """Give the model its own free-run error (m) in its metrics, as `fit` leaves it."""
    model.metadata = {'metrics': {'validation': {'simulation': {'rmse': rmse_m}}}}
    return model


def test_a_lagged_run_on_track_through_the_window_keeps_the_papers_start(records):
    r = records[1][0]
    m = ARXModel(na=4, nb=3).fit(r.u[:, 0], r.y[:, 0], fs=FS)
    u, y, n = r.u[:, 0], r.y[:, 0], 300
    paper = m.simulate(u, y[:m.n0])
    scale = float(np.sqrt(np.mean((y[m.n0:] - paper[m.n0:]) ** 2)))
    _with_error(m, scale)
    np.testing.assert_array_equal(policy_simulate(m, u, y, n, 'state')[n:], paper[n:])
    # The same window opening with a 20-um glitch: the run from it misses the window, and the
    # start is taken at the window's end.
    bad = y.copy()
    bad[:m.n0] += 20e-6
    end = m.simulate(u[n - m.n0:], y[n - m.n0:n])
    np.testing.assert_array_equal(policy_simulate(m, u, bad, n, 'state')[n:], end[m.n0:])
    # A model that carries no error of its own cannot judge the run: the window's end.
    m.metadata = {}
    np.testing.assert_array_equal(policy_simulate(m, u, y, n, 'state')[n:], end[m.n0:])


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


def _saved(tmp_path, records, policy, window, name):
    r = records[0][0]
    m = ARXModel(na=4, nb=3).fit(r.u[:, 0], r.y[:, 0], fs=FS)
    return save_model(m, tmp_path / f'{name}.json',
                      start={'policy': policy, 'window_samples': window})


def test_evaluate_follows_the_stored_start_policy(tmp_path, records, capsys):
    data = tmp_path / 'v.npz'
    r = records[1][0]
    np.savez(data, u=r.u[:, 0], y=r.y[:, 0] + 4e-6, fs=FS)     # a sensor zero that moved
    scores = {}
    for policy in ('rest', 'offset', 'state'):
        path = _saved(tmp_path, records, policy, 300, policy)
        with pytest.raises(SystemExit) as done:
            main(['evaluate', str(path), str(data), '--json'])
        assert done.value.code == 0
        doc = json.loads(capsys.readouterr().out)
        assert doc['start_policy'] == policy and doc['init_samples'] == 300
        assert doc['n'] == len(r) - 300
        scores[policy] = doc['simulation']['rmse']
        with pytest.raises(SystemExit) as done:    # N says what is available, not the policy
            main(['evaluate', str(path), str(data), '--json', '--init-samples', '500'])
        assert json.loads(capsys.readouterr().out)['n'] == len(r) - 500
    # The moved zero: the offset start takes it; the lags decay from it to the model's rest.
    assert scores['offset'] < 0.5 * scores['rest']
    assert len(set(scores.values())) == 3
    with pytest.raises(SystemExit) as done:
        main(['evaluate', str(tmp_path / 'state.json'), str(data), '--init-samples', '3'])
    assert done.value.code == 2
    err = capsys.readouterr().err
    assert err.count('\n') == 1 and "'state' needs at least 10 measured samples" in err
    from_rest = set()
    for policy in ('rest', 'offset', 'state'):     # nothing measured: from rest, as the help says
        with pytest.raises(SystemExit) as done:
            main(['evaluate', str(tmp_path / f'{policy}.json'), str(data), '--json',
                  '--init-samples', '0'])
        assert done.value.code == 0
        doc = json.loads(capsys.readouterr().out)
        assert doc['n'] == len(r)
        from_rest.add(doc['simulation']['rmse'])
    assert len(from_rest) == 1


@pytest.mark.parametrize('policy', ['rest', 'offset', 'state'])
def test_the_estimator_follows_the_stored_start_policy(tmp_path, records, policy):
    model = load_model(_saved(tmp_path, records, policy, 40, policy))
    r = records[1][0]
    u, y = r.u[:, 0], r.y[:, 0] + 4e-6
    est = FreeRunEstimator(model, init='auto', init_window=None)
    est.start(measurement_available=True)
    assert est.start_policy == policy and est.init_samples == 40
    out = []
    for k in range(len(u)):
        out += est.on_command(k * P, float(u[k]))
        out += est.on_measurement(k * P, float(y[k]))
    assert est.stats.init == ('rest' if policy == 'rest' else 'measurement')
    live = np.array([v for _, v in out])
    offline = policy_simulate(model, u, y, 40, policy)
    np.testing.assert_allclose(live[40:], offline[40:], rtol=0, atol=1e-12)


def _controlled(model, ref, shift, measure=True):
    """Drive a PositionController on `model` whose plant is the model + a sensor offset."""
    from piezo_narx_ros.control.controller import PositionController
    ctl = PositionController(model, mode='inverse', u_min=-100.0, u_max=100.0)
    plant = model.stepper()
    u, y, y_model = [], [], []
    for k, r in enumerate(ref):
        (t, uk), = ctl.on_reference(k * P, float(r))
        u.append(uk)
        y.append(plant.step(uk) + shift)
        if measure:
            ctl.on_measurement(t, y[-1])
        y_model.append(ctl.y_model)
    return ctl, np.array(u), np.array(y), np.array(y_model)


@pytest.mark.parametrize('policy', ['rest', 'offset', 'state'])
def test_the_controller_follows_the_stored_start_policy(tmp_path, records, policy):
    r = records[0][0]
    # One input lag: an inverse with no zeros to go unstable (na=4, nb=3 has one outside).
    model = load_model(save_model(ARXModel(na=2, nb=1).fit(r.u[:, 0], r.y[:, 0], fs=FS),
                                  tmp_path / 'c.json',
                                  start={'policy': policy, 'window_samples': 40}))
    lo, hi = model.output_range
    ref = 0.5 * (lo + hi) + 0.3 * (hi - lo) * np.sin(2 * np.pi * 2.0 * np.arange(2000) / FS)
    shift = 0.05 * (hi - lo)         # the sensor's zero moved since the fit
    ctl, u, y, y_model = _controlled(model, ref, shift)
    assert ctl.stats.unreachable == 0
    assert (ctl.start_policy, ctl.start_window) == (policy, 0 if policy == 'rest' else 40)
    assert ctl.stats.start == ('rest' if policy == 'rest' else 'measurement')
    # From the window's last sample on, the controller's model is the offline free run of
    # what it sent under that policy.
    offline = policy_simulate(model, u, y, 40, policy)
    np.testing.assert_allclose(y_model[39:], offline[39:], rtol=0, atol=1e-12)
    # Only the offset policy sees the sensor's zero: the deflection then follows the reference.
    # The measured lags of 'state' carry the shift into the model only until it decays.
    miss = np.sqrt(np.mean((y - ref)[200:] ** 2))
    assert (miss < 1e-3 * shift) if policy == 'offset' else (miss > 0.9 * shift)


def test_a_controller_without_deflections_stays_from_rest_and_says_so(tmp_path, records):
    from piezo_narx_ros.control.controller import PositionController
    from piezo_narx_ros.control.start import START_PATIENCE
    from piezo_narx_ros.errors import ConfigError
    model = load_model(_saved(tmp_path, records, 'offset', 40, 'off'))
    ref = np.full(START_PATIENCE * 40 + 5, 30e-6)
    ctl, _, _, _ = _controlled(model, ref, 4e-6, measure=False)
    assert ctl.stats.start == 'rest (no measurement)'
    assert PositionController(model, mode='inverse', start_policy='rest').stats.start == 'rest'
    waiting = PositionController(model, mode='inverse')
    assert waiting.stats.start == 'waiting'
    waiting.request_reset()         # the actuator is at rest: nothing left to wait for
    assert waiting.stats.start == 'rest' and not waiting._start.waiting
    with pytest.raises(ConfigError, match='start_window must be at least'):
        PositionController(model, mode='inverse', start_window=3)


def test_a_committee_is_controlled_through_its_first_member_and_its_start(tmp_path, records):
    from piezo_narx_ros.control.controller import PositionController
    from piezo_narx_ros.ident.ensemble.model import EnsembleModel
    r = records[0][0]
    lead, other = (ARXModel(na=2, nb=1).fit(r.u[:n, 0], r.y[:n, 0], fs=FS)
                   for n in (2000, 1500))
    committee = load_model(save_model(EnsembleModel([lead, other]), tmp_path / 'e.json',
                                      start={'policy': 'offset', 'window_samples': 40}))
    ctl = PositionController(committee, mode='inverse', u_min=-100.0, u_max=100.0)
    assert ctl.model.kind == 'arx' and 'committee of 2' in ctl.model_note
    assert weights_sha256(ctl.model) == weights_sha256(lead)
    assert (ctl.start_policy, ctl.start_window) == ('offset', 40)
    lo, hi = lead.output_range
    ref = 0.5 * (lo + hi) + 0.3 * (hi - lo) * np.sin(2 * np.pi * 2.0 * np.arange(800) / FS)
    plant = lead.stepper()
    for k, rk in enumerate(ref):
        (t, uk), = ctl.on_reference(k * P, float(rk))
        ctl.on_measurement(t, plant.step(uk) + 2e-6)
    assert ctl.stats.start == 'measurement' and ctl.inverse.offset == pytest.approx(2e-6)
