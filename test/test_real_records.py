"""
Records of real rigs (issue 18): validation records, measured starts, coverage, the monotone prior.

`fit EST --validate VAL`, `evaluate --init-samples N`, the warnings on what the estimation data
do not cover, the estimator's measured start and its "is the state determined yet" report.
"""
import json
import subprocess
import sys
from dataclasses import replace

import numpy as np
import pytest

from piezo_narx_ros.errors import ConfigError
from piezo_narx_ros.estimator.free_run import FreeRunEstimator
from piezo_narx_ros.estimator.health import EstimatorHealth
from piezo_narx_ros.ident.hysteresis import kernels as hk
from piezo_narx_ros.ident.arx.model import ARXModel
from piezo_narx_ros.ident.data.coverage import (coverage_warnings, inner_reversals, LATE_SWEEP,
                                                late_sweep_warnings, unswept_share)
from piezo_narx_ros.ident.selection.experiment import ExperimentConfig, run_experiment
from piezo_narx_ros.ident.hysteresis.model import HysteresisNARX
from piezo_narx_ros.plant import PiezoCantilever, generate
from piezo_narx_ros.record import Record

FS = 2000.0
P = 500_000


def record(u, seed=0, offset=0.0, before=None, name='r'):
    """Return a plant Record (m); `before`: input the plant saw first, not recorded."""
    pre = np.zeros(0) if before is None else before
    y = PiezoCantilever(fs=FS, seed=seed).run(np.r_[pre, u]).y[pre.size:] + offset
    return Record(u=u, y=y, fs=FS, source=name)


def piezo_narx(*args):
    return subprocess.run([sys.executable, '-m', 'piezo_narx_ros.cli.main', *args],
                          capture_output=True, text=True, timeout=300)


def fit_small(*args):
    """Run `piezo-narx fit ARGS` with one small network and one ARX(2, 2), quietly."""
    return piezo_narx('fit', '--preset', 'paper',
                      *args, '--ny', '1', '--nu', '0', '--hidden', '2', '--arx-na', '2',
                      '--arx-nb', '2', '--no-report', '--quiet')


@pytest.fixture(scope='module')
def hnarx():
    """Return a small HysteresisNARX fitted on 8 s of the identification protocol."""
    r = record(generate('protocol', FS, 8.0, 100.0, seed=3), seed=3)
    return HysteresisNARX(hidden=6, n_plays=8, max_iter=25, seed=0).fit(r.u, r.y, fs=FS)


def test_validation_records_never_reach_a_fit():
    est = [record(generate('multisine', FS, 2.0, 80.0, seed=s), seed=s, name=f'e{s}')
           for s in (1, 2)]
    val = [record(generate('sine', FS, 2.0, 90.0, freq=1.0), seed=5, name='v')]
    cfg = ExperimentConfig(narx=False, arx_na=(2,), arx_nb=(2,), noise_model='none', jobs=1)
    result = run_experiment(est, cfg, validation=val)
    alone = ARXModel(2, 2).fit([r.u for r in est], [r.y for r in est], fs=FS)
    model = result.best.model
    assert np.array_equal(model.a, alone.a) and np.array_equal(model.b, alone.b)
    assert result.validation_sources == ['v'] and result.n_estimation == 8000
    assert result.n_validation == 4000
    # The validation scores are the validation record's: its free run, not the estimation's.
    sim = model.simulate(val[0].u[:, 0], val[0].y[:model.n0, 0])[model.n0:]
    e = val[0].y[model.n0:, 0] - sim
    assert result.best.scores['validation']['simulation']['rmse'] == pytest.approx(
        float(np.sqrt(np.mean(e * e))), rel=1e-12)


def test_coverage_warnings_say_what_the_estimation_lacks():
    narrow = [record(generate('sine', FS, 2.0, 40.0, freq=1.0), name='narrow')]
    wide = [record(generate('sine', FS, 2.0, 90.0, freq=1.0), name='wide')]
    fast = [record(generate('sine', FS, 2.0, 40.0, freq=20.0), name='fast')]
    (line,) = coverage_warnings(narrow, wide)
    assert '[-90' in line and 'only over [-40' in line and 'extrapolates' in line
    (line,) = coverage_warnings(narrow, fast)
    assert 'reaches 20' in line and 'only 1' in line      # Welch bins of 0.5 Hz
    (line,) = coverage_warnings(fast, narrow)
    assert 'as slowly as 0.5 Hz' in line and 'only down to 19.5 Hz' in line
    assert coverage_warnings(wide, narrow) == []


def test_minor_loops_are_counted_and_noise_is_no_reversal():
    sine = generate('sine', FS, 5.0, 100.0, freq=1.0)
    noisy = sine + np.random.default_rng(0).normal(0.0, 1.0, sine.size)
    assert inner_reversals([sine]) == 0 and inner_reversals([noisy]) == 0
    fading = sine * np.linspace(1.0, 0.2, sine.size)
    assert inner_reversals([fading]) >= 6
    # A growing amplitude turns beyond its last turn each time: one loop, growing, no minor loop
    # (the network's memory of loops inside it is then unconstrained by the data).
    growing = generate('growing_sine', FS, 10.0, 100.0, freq=2.0, hold=1.0)
    assert inner_reversals([growing]) == 0
    assert inner_reversals([generate('protocol', FS, 10.0, 100.0, seed=1)]) > 100


def test_unswept_share_counts_the_samples_before_both_ends_of_each_record():
    # Held at 0, then the top, then the bottom: both ends reached at sample k + 1.
    k, n = 300, 1000
    step = np.r_[np.zeros(k), 10.0, -10.0, np.zeros(n - k - 2)]
    assert unswept_share([step]) == pytest.approx((k + 1) / n)
    # Each record against its own range, weighted by its samples; two channels: the later one.
    early = np.r_[10.0, -10.0, np.zeros(n - 2)]
    assert unswept_share([step, early]) == pytest.approx((k + 2) / (2 * n))
    assert unswept_share([np.column_stack([early, step])]) == pytest.approx((k + 1) / n)
    assert unswept_share([np.zeros(50)]) == 0.0
    # A sine of growing amplitude reaches its ends late; a full-range sine and the protocol early.
    growing = generate('growing_sine', FS, 10.0, 100.0, freq=2.0, hold=1.0)
    assert unswept_share([growing]) > 0.5 > LATE_SWEEP
    assert unswept_share([generate('sine', FS, 5.0, 100.0, freq=1.0)]) < LATE_SWEEP
    assert unswept_share([generate('protocol', FS, 10.0, 100.0, seed=1)]) < 0.05
    (line,) = late_sweep_warnings([growing])
    assert 'only after 6' in line and 'one full-range cycle' in line
    assert late_sweep_warnings([generate('multisine', FS, 10.0, 100.0, seed=1)]) == []


def test_fit_warns_when_the_estimation_input_reaches_its_ends_late(tmp_path):
    # One fit: the warning's wiring (which inputs warn is the test above).
    r = record(generate('growing_sine', FS, 3.0, 100.0, freq=2.0, hold=0.5), seed=4)
    np.savez(tmp_path / 'growing.npz', u=r.u, y=r.y, fs=FS)
    out = fit_small(str(tmp_path / 'growing.npz'), '--out', str(tmp_path / 'o'))
    assert out.returncode == 0, out.stderr
    late = [line for line in out.stderr.splitlines() if 'both ends of its range' in line]
    assert len(late) == 1 and late[0].startswith('piezo-narx: warning: '), out.stderr


def test_fit_per_record_warns_for_the_recording_it_concerns(tmp_path):
    fleet = tmp_path / 'fleet'
    fleet.mkdir()
    for name, kind, extra in (('growing', 'growing_sine', {'freq': 2.0, 'hold': 0.5}),
                              ('protocol', 'protocol', {'seed': 1})):
        r = record(generate(kind, FS, 3.0, 100.0, **extra), seed=4)
        np.savez(fleet / f'{name}.npz', u=r.u, y=r.y, fs=FS)
    out = fit_small(str(fleet), '--per-record', '--out', str(tmp_path / 'o'))
    assert out.returncode == 0, out.stderr
    late = [line for line in out.stderr.splitlines() if 'both ends of its range' in line]
    assert len(late) == 1 and late[0].startswith('piezo-narx: warning: growing: '), out.stderr


def test_a_record_without_minor_loops_gets_a_network_rising_with_every_play():
    r = record(generate('sine', FS, 6.0, 100.0, freq=1.0), seed=2)
    m = HysteresisNARX(hidden=4, n_plays=6, max_iter=8, seed=1).fit(r.u, r.y, fs=FS)
    assert m.training_info_['monotone'] is True and m.training_info_['inner_reversals'] == 0
    lay, _ = hk.layout(m.hidden, m.n_inputs, m.n_duhem, len(m.creep_taus), m.na, m.nb)
    part = {k: m.theta_[lo:hi] for k, (lo, hi) in lay.items()}
    W1 = part['W1'].reshape(m.hidden, m.n_inputs)
    assert np.all(W1[:, :m.n_plays] >= 0) and np.all(part['w2'] >= 0)
    assert np.all(part['c'][:m.n_plays] >= 0)
    # A falling actuator (sensor mounted the other way): the same, with the sign flipped.
    down = HysteresisNARX(hidden=4, n_plays=6, max_iter=8, seed=1).fit(r.u, -r.y, fs=FS)
    np.testing.assert_allclose(down.simulate(r.u), -m.simulate(r.u), rtol=1e-9, atol=1e-15)


def test_evaluate_init_samples_scores_after_the_window_and_saves_the_run(tmp_path, hnarx):
    from piezo_narx_ros.ident.model_io import save_model
    model = save_model(hnarx, tmp_path / 'm.json')
    hist = generate('aprbs', FS, 2.0, 80.0, seed=9)
    rec = record(generate('sine', FS, 3.0, 70.0, freq=1.0) + 20.0, seed=4, offset=2e-6,
                 before=hist)
    np.savez(tmp_path / 'r.npz', u=rec.u, y=rec.y, fs=FS)

    def score(*extra):
        out = piezo_narx('evaluate', str(model), str(tmp_path / 'r.npz'), '--json', *extra)
        assert out.returncode == 0, out.stderr
        return json.loads(out.stdout)
    rest, measured = score('--init-samples', '0'), score('--init-samples', '1000',
                                                         '--save-output', str(tmp_path / 'o.npz'))
    assert rest['n'] == 6000 and measured['n'] == 5000 and measured['init_samples'] == 1000
    assert measured['simulation']['rmse'] < 0.2 * rest['simulation']['rmse']
    saved = np.load(tmp_path / 'o.npz')
    assert saved['y_sim'].shape == (len(rec),) and int(saved['scored_from']) == 1000
    e = (saved['y'] - saved['y_sim'])[1000:]
    assert float(np.sqrt(np.mean(e * e))) == pytest.approx(measured['simulation']['rmse'],
                                                           rel=1e-9)
    # Beside it, the same samples from rest (this record started 2 um off and mid-history).
    from_rest = measured['simulation_from_rest']
    e = (rec.y[:, 0] - hnarx.simulate(rec.u[:, 0]))[1000:]
    assert from_rest['rmse'] == pytest.approx(float(np.sqrt(np.mean(e * e))), rel=1e-9)
    assert measured['simulation']['rmse'] < 0.2 * from_rest['rmse']
    assert rest['simulation_from_rest'] is None


def test_evaluate_past_fade_out_needs_a_window_and_is_reported(tmp_path, hnarx):
    from piezo_narx_ros.ident.model_io import save_model
    model = save_model(hnarx, tmp_path / 'm.json')
    t = np.arange(int(3.0 * FS)) / FS
    fade = 20.0 + 60.0 * (1.0 - t / t[-1]) * np.sin(2 * np.pi * 2.0 * t)
    u = np.r_[np.full(1000, 20.0), 20.0 + 70.0 * np.sin(2 * np.pi * t[:4000])]
    rec = record(u, seed=4, offset=1e-6, before=np.r_[fade, np.full(1000, 20.0)])
    np.savez(tmp_path / 'r.npz', u=rec.u, y=rec.y, fs=FS)
    bad = piezo_narx('evaluate', str(model), str(tmp_path / 'r.npz'), '--past', 'fade-out')
    assert bad.returncode != 0 and '--init-samples' in bad.stderr.strip().splitlines()[-1]

    def score(past):
        out = piezo_narx('evaluate', str(model), str(tmp_path / 'r.npz'), '--json',
                         '--init-samples', '1000', '--past', past)
        assert out.returncode == 0, out.stderr
        return json.loads(out.stdout)
    told, default = score('fade-out'), score('any')
    assert (told['past'], default['past']) == ('fade-out', 'any')
    # The hold leaves the memory open: the warning says so, and (by default) how to say more.
    assert any('--past fade-out' in w for w in default['warnings'])
    assert not any('--past fade-out' in w for w in told['warnings'])
    assert told['simulation']['rmse'] < default['simulation']['rmse']


def test_fit_past_reaches_every_scored_state_window():
    from piezo_narx_ros.errors import ConfigError
    from piezo_narx_ros.ident.pipeline.settings import experiment_config, merge_settings
    from piezo_narx_ros.ident.selection.experiment import with_state_window
    cfg = experiment_config(merge_settings('envelope', overrides={'init_past': 'fade-out'}),
                            progress=False)
    assert (cfg.init_past, cfg.init_seconds) == ('fade-out', 0.5)
    recs = with_state_window([record(np.zeros(2000))], cfg)
    assert (recs[0].state_window, recs[0].state_past) == (1000, 'fade-out')
    with pytest.raises(ConfigError, match='init_past must be one of any, fade-out'):
        replace(cfg, init_past='ramp').validate()


def test_evaluate_says_when_the_state_window_leaves_the_memory_open(hnarx):
    """
    A window that holds the input sets the level, not the hysteresis memory: evaluate says so.

    A window that sweeps the trained range wipes the memory: no warning, `determined`.
    """
    from piezo_narx_ros.cli.evaluate import memory_windows
    t = np.arange(4000) / FS
    held = record(np.r_[np.full(1000, 20.0), 20.0 + 70.0 * np.sin(2 * np.pi * t[:3000])],
                  name='held')
    swept = record(100.0 * np.sin(2 * np.pi * 2.0 * t), name='swept')
    windows, notes = memory_windows(hnarx, [held, swept], 1000)
    assert [w['determined'] for w in windows] == [False, True]
    assert windows[0]['memory_spread_m'] > 0.1e-6 and windows[1]['memory_spread_m'] == 0.0
    assert windows[0]['window_input_v'] == [20.0, 20.0]
    assert len(notes) == 1
    assert notes[0].startswith("held: the first 1000 samples do not set the model's memory")
    assert 'fade-out' in notes[0] and 'preamble' in notes[0]     # what to do about it
    assert memory_windows(hnarx, [held], 0) == ([], [])     # from rest: nothing to say


def test_fit_validate_cli_refuses_an_estimation_record_as_validation(tmp_path):
    r = record(generate('multisine', FS, 2.0, 80.0, seed=1), seed=1)
    np.savez(tmp_path / 'a.npz', u=r.u, y=r.y, fs=FS)
    out = piezo_narx('fit', '--preset', 'paper',
                     str(tmp_path / 'a.npz'), '--validate', str(tmp_path / 'a.npz'),
                     '--out', str(tmp_path / 'o'), '--no-report', '--quiet')
    assert out.returncode == 2
    assert out.stderr.count('\n') == 1 and 'cannot validate the model it estimates' in out.stderr


def test_estimator_says_when_its_state_is_determined(hnarx):
    """From rest the unknown past is bracketed: WARN with its bound until a full sweep fixes it."""
    est = FreeRunEstimator(hnarx, init='rest')
    health = EstimatorHealth(est)
    u = np.r_[30.0 + 20.0 * np.sin(2 * np.pi * np.arange(2000) / FS),       # inside the range
              100.0 * np.sin(2 * np.pi * 0.5 * np.arange(4000) / FS + 0.5)]   # a full sweep
    for k in range(2000):
        est.on_command(k * P, float(u[k]))
    level, message, values = health.tick()
    assert est.stats.state == 'undetermined' and values['state_spread_m'] > 1e-7
    assert level == 1 and 'state undetermined' in message
    for k in range(2000, u.size):
        est.on_command(k * P, float(u[k]))
    level, message, values = health.tick()
    assert est.stats.state == 'determined' and level == 0, message


def test_estimator_starts_from_the_measured_state_of_a_plant_not_at_rest(hnarx):
    hist = generate('aprbs', FS, 2.0, 80.0, seed=2)
    rec = record(generate('sine', FS, 3.0, 70.0, freq=1.0) + 20.0, seed=6, offset=-3e-6,
                 before=hist)
    est = FreeRunEstimator(hnarx, init='measurement', init_window=0.5)
    out = []
    u, y = rec.u[:, 0], rec.y[:, 0]
    for k in range(len(rec)):
        out += est.on_command(k * P, float(u[k]))
        out += est.on_measurement(k * P, float(y[k]))
    y_hat = np.array([y for _, y in out])
    assert len(out) == len(rec) and est.stats.state == 'estimated'
    ref = hnarx.simulate(u, state=hnarx.estimate_state(u[:1000], y[:1000]))
    assert np.max(np.abs(y_hat - ref)) <= 1e-12
    err = np.sqrt(np.mean((y_hat - y)[1000:] ** 2))
    rest = np.sqrt(np.mean((hnarx.simulate(u) - y)[1000:] ** 2))
    assert err < 0.2 * rest, (err, rest)


def test_resample_is_anti_aliased_and_only_slower():
    from piezo_narx_ros.errors import DataError
    from piezo_narx_ros.ident.data.resample import resample_record
    t = np.arange(20000) / 10000.0
    slow, fast = np.sin(2 * np.pi * 5.0 * t), 0.5 * np.sin(2 * np.pi * 1700.0 * t)
    rec = Record(u=slow + fast, y=2.0 * slow + fast, fs=10000.0, source='r',
                 t=100.0 + t)
    down = resample_record(rec, 2000.0)
    t2 = np.arange(4000) / 2000.0
    assert down.fs == 2000.0 and down.u.size == 4000
    # 1700 Hz is above the new Nyquist (1000 Hz): filtered out, not folded to 300 Hz.
    np.testing.assert_allclose(down.u[50:-50, 0], np.sin(2 * np.pi * 5.0 * t2)[50:-50], atol=5e-3)
    np.testing.assert_allclose(down.t, 100.0 + t2)
    for bad in (10000.0, 20000.0, -1.0):
        with pytest.raises(DataError):
            resample_record(rec, bad)
    # Issue 45: 1999 Hz from 2000 Hz was "resampled" by the nearest ratio, 1/1: a 2000 Hz fit.
    at2k = resample_record(rec, 2000.0)
    with pytest.raises(DataError, match='--resample 1999 Hz cannot be made from the record.s '
                       '2000 Hz .* the nearest slower rate it can make is 1998 Hz'):
        resample_record(at2k, 1999.0)
    assert resample_record(at2k, 1998.0).fs == 1998.0


def test_fit_and_evaluate_at_a_resampled_rate(tmp_path):
    r = record(generate('multisine', FS, 3.0, 80.0, seed=1), seed=1)
    np.savez(tmp_path / 'a.npz', u=r.u, y=r.y, fs=FS)
    out = fit_small(str(tmp_path / 'a.npz'), '--resample', '1000', '--out', str(tmp_path / 'o'))
    assert out.returncode == 0, out.stderr
    doc = json.loads((tmp_path / 'o' / 'model.json').read_text())
    assert doc['fs'] == 1000.0
    good = piezo_narx('evaluate', str(tmp_path / 'o' / 'model.json'), str(tmp_path / 'a.npz'),
                      '--resample', '1000', '--json')
    assert good.returncode == 0, good.stderr
    assert json.loads(good.stdout)['n'] > 1400
    bad = piezo_narx('evaluate', str(tmp_path / 'o' / 'model.json'), str(tmp_path / 'a.npz'))
    assert bad.returncode == 2 and '2000 Hz' in bad.stderr and '1000 Hz' in bad.stderr
    # Validation records at the rig's rate are resampled like the estimation records (they were
    # compared with the resampled rate first, and every --resample --validate fit was refused).
    v = record(generate('multisine', FS, 3.0, 80.0, seed=2), seed=2)
    np.savez(tmp_path / 'v.npz', u=v.u, y=v.y, fs=FS)
    out = fit_small(str(tmp_path / 'a.npz'), '--validate', str(tmp_path / 'v.npz'),
                    '--resample', '1000', '--out', str(tmp_path / 'ov'))
    assert out.returncode == 0, out.stderr
    assert json.loads((tmp_path / 'ov' / 'model.json').read_text())['fs'] == 1000.0


def test_records_of_sessions_with_different_sensor_zeros_fit_together():
    a = record(generate('protocol', FS, 6.0, 100.0, seed=1), seed=1)
    b = record(generate('protocol', FS, 6.0, 100.0, seed=2), seed=2)

    def fit(offset):
        m = HysteresisNARX(hidden=6, n_plays=8, max_iter=20, seed=0)
        return m.fit([a.u, b.u], [a.y, b.y + offset], fs=FS)
    same, moved = fit(0.0), fit(4e-6)
    # The second session's sensor zero moved by 4 um: found, and the model is as if it had not.
    got = moved.training_info_['record_offsets_m'][1] - same.training_info_['record_offsets_m'][1]
    assert got == pytest.approx(4e-6, abs=0.05e-6)
    for u in (a.u, b.u):
        assert np.max(np.abs(moved.simulate(u) - same.simulate(u))) < 0.05e-6


def test_records_of_one_session_can_share_one_sensor_zero(tmp_path):
    from piezo_narx_ros.ident.model_io import save_model
    a = record(generate('protocol', FS, 3.0, 100.0, seed=1), seed=1)
    b = record(generate('protocol', FS, 3.0, 100.0, seed=2), seed=2)

    def fit(offsets):
        m = HysteresisNARX(hidden=4, n_plays=6, max_iter=8, seed=0, record_offsets=offsets)
        return m.fit([a.u, b.u], [a.y, b.y + 4e-6], fs=FS)
    own, shared, auto = fit('yes'), fit('no'), fit('auto')
    assert len(own.training_info_['record_offsets_m']) == 2
    assert shared.training_info_['record_offsets_m'] == []
    assert auto.training_info_['record_offsets_m'] == own.training_info_['record_offsets_m']
    # A fit told so says it in its file's training options; the default leaves them as they were.
    doc = json.loads(save_model(shared, tmp_path / 's.json').read_text())
    assert doc['training']['options']['record_offsets'] == 'no'
    assert 'record_offsets' not in auto.params_dict()
    with pytest.raises(ConfigError, match='record_offsets'):
        HysteresisNARX(record_offsets='maybe')


def test_selection_judges_state_windows_with_the_candidates_own_error(hnarx, monkeypatch):
    """
    Selection scores a validation record's state window as evaluate judges the saved model's.

    With the model's own free-run error as the window's floor (ident.state, step 4): during
    selection that is its error on the estimation records, the only one known then.
    """
    import copy

    from piezo_narx_ros.ident.state import estimate
    from piezo_narx_ros.ident.selection.experiment import (CandidateResult, CandidateSpec,
                                                           score_candidate)
    floors = []

    def spy(model):
        floors.append(real(model))
        return floors[-1]
    real = estimate.error_scale
    monkeypatch.setattr(estimate, 'error_scale', spy)
    est = [record(generate('multisine', FS, 2.0, 80.0, seed=1), seed=1, name='e')]
    u = generate('multisine', FS, 2.0, 80.0, seed=2)
    val = [replace(record(u, seed=2, offset=1e-6, before=30.0 * np.ones(500), name='v'),
                   state_window=1000)]
    model = copy.deepcopy(hnarx)
    res = score_candidate(CandidateResult(spec=CandidateSpec('hysteresis_narx', 1, 1)), model,
                          est, val, ExperimentConfig(family='hysteresis_narx'))
    rmse = res.scores['estimation']['simulation']['rmse']
    assert rmse > 0 and floors and all(f == rmse for f in floors)
    assert np.isfinite(res.scores['validation']['simulation']['r2'])


def test_an_output_at_the_sensors_full_scale_is_found_where_the_input_moves_on():
    from piezo_narx_ros.ident.data.saturation import clipped_runs, saturation_warnings
    u = generate('sine', FS, 2.0, 100.0, freq=2.0)
    # A 16-bit sensor over 40 um on a sine of about 80 um peak to peak clips every crest: 4
    # cycles, 8 runs, each while the crest passes.
    clipped = PiezoCantilever(fs=FS, seed=1, sensor_bits=16, sensor_span=40e-6).run(u).y
    runs = clipped_runs(u, clipped)
    assert sorted(side for _, _, side in runs) == ['maximum'] * 4 + ['minimum'] * 4
    for start, stop, side in runs:
        assert np.all(clipped[start:stop] == (clipped.max() if side == 'maximum'
                                              else clipped.min()))
    # Over 400 um the same converter never clips: no run, noise or not.
    assert clipped_runs(u, PiezoCantilever(fs=FS, seed=1, sensor_bits=16,
                                           sensor_span=400e-6).run(u).y) == []
    # A hold at the top reads one code while the input holds: not clipping; nor is a coarse
    # sensor that stays on its top code while a crest moves by less than three codes' worth.
    ramp = np.r_[np.linspace(0.0, 100.0, 1000), np.full(1000, 100.0)]
    assert clipped_runs(ramp, np.round(ramp * 0.4e-6 / 1e-8) * 1e-8) == []
    coarse = np.round(np.sin(np.linspace(0, 6 * np.pi, 3000)) * 10.0) / 10.0
    assert clipped_runs(100.0 * np.sin(np.linspace(0, 6 * np.pi, 3000)), coarse) == []
    # Several outputs: one line for the clipped one, named.
    two = Record(u=u, y=np.column_stack([clipped, 0.5 * clipped + 1e-9 * np.arange(u.size)]),
                 fs=FS, source='two.npz', outputs=('x', 'z'))
    (line,) = saturation_warnings([two])
    assert line.startswith('two.npz: the output x sits at its maximum') and 'end of its range' \
        in line


def test_fit_and_evaluate_warn_when_the_output_sits_at_the_sensors_full_scale(tmp_path):
    u = generate('multisine', FS, 3.0, 100.0, seed=1)
    plant = PiezoCantilever(fs=FS, seed=1, sensor_bits=16, sensor_span=50e-6)
    np.savez(tmp_path / 'clipped.npz', u=u, y=plant.run(u).y, fs=FS)
    clean = record(generate('multisine', FS, 3.0, 100.0, seed=2), seed=2)
    np.savez(tmp_path / 'clean.npz', u=clean.u, y=clean.y, fs=FS)
    out = fit_small(str(tmp_path / 'clipped.npz'), '--out', str(tmp_path / 'o'))
    assert out.returncode == 0, out.stderr
    lines = [line for line in out.stderr.splitlines() if 'end of its range' in line]
    assert len(lines) == 1 and 'clipped.npz: the output sits at its ' in lines[0], out.stderr
    model = str(tmp_path / 'o' / 'model.json')
    for name, warned in (('clipped.npz', 1), ('clean.npz', 0)):
        out = piezo_narx('evaluate', model, str(tmp_path / name), '--json')
        assert out.returncode == 0, out.stderr
        assert out.stderr.count('end of its range') == warned, out.stderr
