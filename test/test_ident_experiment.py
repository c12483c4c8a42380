"""Lag-grid experiment: selection rule, ARX order recovery, parallel = serial, report folder."""
import json
from dataclasses import replace

import numpy as np
import pytest
from scipy import stats
from scipy.signal import lfilter

from piezo_narx_ros.errors import ConfigError, DataError
from piezo_narx_ros.record import Record
from piezo_narx_ros.ident.selection.experiment import (CandidateResult, CandidateSpec,
                                                       ExperimentConfig, run_experiment, select,
                                                       split_records)
from piezo_narx_ros.ident.validation.report import write_report

# Few iterations: these tests check the plumbing, not the optimiser.
FAST_TRAINING = {'restarts': 1, 'restart_iter': 2, 'max_iter': 5, 'refine_iter': 2,
                 'n_segments': 5, 'onestep_samples': 1000}


def arx_record(n=4000, seed=0, noise=0.05):
    """ARX(na=2, nb=1) system with white equation noise: the right model's residuals are white."""
    rng = np.random.default_rng(seed)
    u = rng.uniform(-1, 1, n)
    e = noise * rng.standard_normal(n)
    y = np.zeros(n)
    for k in range(2, n):
        y[k] = 1.2 * y[k - 1] - 0.5 * y[k - 2] + u[k - 1] + e[k]
    return Record(u=u, y=y * 1e-6, fs=1000.0, source=f'arx-{seed}')


def _cand(kind, nu, ny, n_params, r2, validated, error=None, r2_est=1.0):
    c = CandidateResult(spec=CandidateSpec(kind, nu=nu, ny=ny), n_params=n_params,
                        validated=validated, error=error)
    if error is None:
        c.scores = {'validation': {'simulation': {'r2': r2}},
                    'estimation': {'simulation': {'r2': r2_est}}}
    return c


def test_selection_prefers_fewest_parameters_among_passing():
    cands = [_cand('narx', 2, 2, 71, 0.9999, True), _cand('arx', 3, 3, 8, 0.99, True),
             _cand('arx', 1, 1, 4, 0.999, False), _cand('arx', 2, 3, 7, 0.98, True)]
    assert select(cands) == (3, True)


def test_selection_ties_go_to_best_validation_simulation_r2():
    cands = [_cand('arx', 2, 3, 7, 0.95, True), _cand('arx', 3, 2, 7, 0.97, True),
             _cand('arx', 3, 3, 8, 0.999, True)]
    assert select(cands) == (1, True)


def test_selection_without_passing_model_takes_best_r2_not_validated():
    cands = [_cand('arx', 1, 1, 4, 0.9, False), _cand('narx', 1, 1, 51, None, False),
             _cand('narx', 2, 2, 71, 0.99, False), _cand('arx', 2, 2, 6, 0.0, False, 'bad')]
    assert select(cands) == (2, False)


def test_selection_rejects_a_network_unstable_on_the_estimation_start():
    # Best on validation, but its free run falls into a limit cycle at the record's start.
    cands = [_cand('narx', 3, 4, 81, 0.99993, False, r2_est=-119.0),
             _cand('narx', 2, 4, 71, 0.99990, False, r2_est=0.99995),
             _cand('arx', 4, 4, 10, 0.995, False)]
    assert select(cands) == (1, False)
    passing = [_cand('arx', 3, 2, 7, 0.999, True, r2_est=0.5),
               _cand('arx', 2, 3, 7, 0.998, True)]
    assert select(passing) == (1, True)   # tie on size broken by the worse half


def test_selection_when_nothing_fitted_raises():
    with pytest.raises(DataError, match='no candidate'):
        select([_cand('arx', 1, 1, 4, 0.0, False, 'degenerate data')])


def arx_records(n_seeds, n=3000, noise=0.05, seed=0):
    """arx_record's system for many seeds at once (one lfilter call along axis 1)."""
    rng = np.random.default_rng(seed)
    u = rng.uniform(-1, 1, (n_seeds, n))
    e = noise * rng.standard_normal((n_seeds, n))
    drive = np.pad(u, ((0, 0), (1, 0)))[:, :-1] + e
    y = lfilter([1.0], [1.0, -1.2, 0.5], drive, axis=1)
    return [Record(u=u[s], y=y[s] * 1e-6, fs=1000.0, source=f'arx-{s}') for s in range(n_seeds)]


# Calibration of the pipeline (default rule, free-run residuals whitened by the AR noise model
# fitted on the estimation half), measured over 1000 seeds other than the test's, N = 3000: the
# true ARX(2, 1) passes all five tests in 12.6 % of records. Below the 15 % that five independent
# chance rates give: its coefficients are estimated on the other half, and that error leaves a
# little of the input in the validation residual (φuε passes 56 %, not 66 %; docs/testing.md).
TRUE_ORDERS_VALIDATED = 0.126


def test_arx_grid_over_seeds_rejects_missing_orders_and_validates_the_true_ones_by_chance():
    n_seeds = 100
    true = CandidateSpec('arx', nu=1, ny=2)
    cfg = ExperimentConfig(narx=False, arx_na=(1, 2), arx_nb=(0, 1), jobs=1)
    true_validated = under_validated = noise_model_found = 0
    for rec in arx_records(n_seeds, seed=7):
        result = run_experiment([rec], cfg)
        by_spec = {c.spec: c for c in result.candidates}
        under = [c for c in result.candidates if c.spec != true]
        under_validated += sum(c.validated for c in under)
        # Under-modelled structures are never the answer; the true one is, when it passes.
        assert result.best.spec == true, result.best.spec
        assert result.validated == by_spec[true].validated
        nm = by_spec[true].tests['simulation']['noise_model']
        noise_model_found += (nm['order'] == 2
                              and np.allclose(nm['coef'], [1.2, -0.5], atol=0.05))
        true_validated += by_spec[true].validated
    # Leaving out y(k-2) or u(k-1) leaves dynamics in the residuals: rejected (never, measured).
    assert under_validated <= 0.05 * 3 * n_seeds
    # The free run of the equation-error system is coloured by 1/A(q): the AR noise model
    # fitted on the estimation half is A(q) itself (97 of 100 seeds measured).
    assert noise_model_found >= 0.9 * n_seeds
    low, high = stats.binom.interval(0.999, n_seeds, TRUE_ORDERS_VALIDATED)
    assert low <= true_validated <= high, true_validated


def test_arx_grid_writes_a_report_of_what_it_found(tmp_path):
    rec = arx_record()
    cfg = ExperimentConfig(narx=False, arx_na=(1, 2, 3), arx_nb=(0, 1, 2), jobs=1)
    result = run_experiment([rec], cfg)
    assert len(result.candidates) == 9
    assert result.n_estimation == result.n_validation == 2000
    by_label = {c.spec.label: c for c in result.candidates}
    # Under-modelled structures leave dynamics in the residuals and fail.
    assert not by_label['ARX(na=1, nb=1)'].validated
    assert not by_label['ARX(na=2, nb=0)'].validated
    best = result.best
    for data in ('estimation', 'validation'):
        for mode in ('prediction', 'simulation'):
            assert set(best.scores[data][mode]) == {'r2', 'rmse', 'nrmse', 'fit_percent'}
    assert best.scores['validation']['simulation']['r2'] > 0.99
    assert set(best.tests) == {'prediction', 'simulation', 'raw', 'noise_model', 'residuals'}
    assert best.tests['residuals'] == 'simulation' and best.tests['noise_model'] == 'ar'
    assert set(best.tests['raw']) == {'prediction', 'simulation'}
    # The raw free-run residuals keep the 1/A(q) colouring (0 of 1000 seeds pass φεε).
    assert not best.tests['raw']['simulation']['tests']['phi_ee']['passed']

    _, val = split_records([rec], cfg.split)
    paths = write_report(result, val, tmp_path / 'report')
    doc = json.loads(paths['metrics'].read_text())
    assert len(doc['candidates']) == 9
    assert doc['selection']['label'] == best.spec.label
    assert doc['selection']['validated'] == result.validated
    assert set(doc['selected_correlation']['prediction']['tests']) == {
        'phi_ee', 'phi_ue', 'phi_u2e', 'phi_u2e2', 'phi_e_eu'}
    for key in ('r2_grid_arx', 'correlation', 'simulation', 'hysteresis'):
        assert paths[key].read_bytes()[:8] == b'\x89PNG\r\n\x1a\n'
    assert 'r2_grid_narx' not in paths


def test_defaults_are_chance_rate_rule_on_whitened_simulation_residuals():
    cfg = ExperimentConfig()
    assert (cfg.max_outside_fraction, cfg.residuals, cfg.noise_model) == (0.05, 'simulation', 'ar')


def test_without_noise_model_tests_are_the_raw_verdicts():
    rec = arx_record()
    result = run_experiment([rec], ExperimentConfig(narx=False, arx_na=(2,), arx_nb=(1,), jobs=1,
                                                    noise_model='none'))
    tests = result.best.tests
    assert tests['simulation'] == tests['raw']['simulation']
    assert 'noise_model' not in tests['simulation']
    # The free run of an equation-error system is coloured by 1/A(q); its one-step residual
    # is the white equation noise.
    assert not tests['simulation']['tests']['phi_ee']['passed']
    assert tests['simulation']['tests']['phi_ee']['n_outside'] >= 5
    assert tests['prediction']['tests']['phi_ee']['n_outside'] <= 2


def test_strict_rule_validates_no_more_than_tolerant_rule():
    grid = {'narx': False, 'arx_na': (2, 3), 'arx_nb': (1,), 'jobs': 1}
    strict_total = tolerant_total = 0
    for rec in arx_records(8, seed=3):
        strict = run_experiment([rec], ExperimentConfig(max_outside_fraction=0.0, **grid))
        tolerant = run_experiment([rec], ExperimentConfig(max_outside_fraction=0.1, **grid))
        s = [c.validated for c in strict.candidates]
        t = [c.validated for c in tolerant.candidates]
        assert all(tv or not sv for sv, tv in zip(s, t))     # strict pass implies tolerant pass
        strict_total, tolerant_total = strict_total + sum(s), tolerant_total + sum(t)
        # Scores do not depend on the test rule.
        assert [c.scores for c in strict.candidates] == [c.scores for c in tolerant.candidates]
    # Correct and over-parameterised models: the 0.1 rule passes about 60 % of them, the strict
    # rule (every one of 160 lags inside the band) almost none.
    assert tolerant_total >= 6 and strict_total < tolerant_total


def test_parallel_run_equals_serial_run():
    recs = [arx_record(3000, seed=1), arx_record(3000, seed=2)]
    base = {'ny': (1,), 'nu': (1,), 'hidden': 2, 'arx_na': (1, 2), 'arx_nb': (1,),
            'training': FAST_TRAINING}
    serial = run_experiment(recs, ExperimentConfig(jobs=1, **base))
    parallel = run_experiment(recs, ExperimentConfig(jobs=2, **base))
    assert [c.spec for c in serial.candidates] == [c.spec for c in parallel.candidates]
    assert serial.candidates[0].spec.kind == 'narx'
    for a, b in zip(serial.candidates, parallel.candidates):
        assert a.error is None and b.error is None
        assert a.scores == b.scores
        assert a.tests == b.tests
    assert serial.selected == parallel.selected
    assert serial.n_estimation == 3000   # two estimation halves concatenated


def test_too_short_record_raises():
    with pytest.raises(DataError, match='too few'):
        run_experiment([arx_record(150)], ExperimentConfig(narx=False, jobs=1))


@pytest.mark.parametrize('kwargs, match', [
    ({'ny': (0,)}, 'ny'), ({'hidden': 0}, 'hidden'), ({'residuals': 'both'}, 'residuals'),
    ({'jobs': 0}, 'jobs'), ({'split': 0.99}, 'split'), ({'max_outside_fraction': 1.5}, 'max_'),
    ({'narx': False, 'arx_na': ()}, 'nothing to fit'), ({'noise_model': 'ma'}, 'noise_model'),
    ({'noise_order': -1}, 'noise_order'),
    ({'training': {'epochs': 5}}, 'unknown training option'),
    ({'final_training': {'epochs': 5}}, 'final_training'),
])
def test_bad_config_raises(kwargs, match):
    with pytest.raises(ConfigError, match=match):
        ExperimentConfig(**kwargs).validate()


def test_boucwen_benchmark_arx_baseline(boucwen_dir):
    # Public hysteresis benchmark (u in N, y in m, 750 Hz): a linear ARX captures most of the
    # response in free run but leaves the hysteresis, which the tests must see.
    from piezo_narx_ros.ident.data.loaders import load_records
    records = load_records([boucwen_dir / 'train.npz'])
    assert records[0].fs == 750.0 and len(records[0]) == 40960
    cfg = ExperimentConfig(narx=False, arx_na=(2, 4), arx_nb=(2, 4), jobs=1)
    result = run_experiment(records, cfg)
    best = result.best
    assert 0.8 < best.r2() < 0.99          # linear model, hysteretic system
    assert not result.validated
    assert not best.tests['prediction']['passed']
    assert not best.tests['simulation']['passed']


def nonlinear_record(n=4000, seed=0):
    """Return a NARX system with a saturating nonlinearity that no ARX model can represent."""
    rng = np.random.default_rng(seed)
    u = rng.uniform(-1, 1, n)
    y = np.zeros(n)
    for k in range(1, n):
        y[k] = 0.6 * y[k - 1] + np.tanh(2.0 * u[k]) + 0.1 * u[k - 1] ** 2
    return Record(u=u, y=y * 1e-6, fs=1000.0, source=f'nl-{seed}')


def test_selected_network_is_trained_again_and_kept_only_if_no_worse():
    recs = [nonlinear_record()]
    base = {'ny': (1,), 'nu': (1,), 'hidden': 4, 'arx_na': (1,), 'arx_nb': (1,), 'jobs': 1,
            'training': FAST_TRAINING}
    screened = run_experiment(recs, ExperimentConfig(final_training={}, **base))
    assert screened.best.spec.kind == 'narx' and screened.best.final_fit is None
    final = run_experiment(recs, ExperimentConfig(
        final_training={'max_iter': 40, 'refine_iter': 20}, **base))
    info = final.best.final_fit
    assert info['options'] == {'max_iter': 40, 'refine_iter': 20}
    # The screening fit is the same deterministic fit as in the run without a final stage.
    assert info['screening']['r2_validation_simulation'] == pytest.approx(screened.best.r2())
    # Longer training of the winner improves its free run here (0.99987 -> 0.99999 measured).
    assert info['kept'] and final.best.r2() > screened.best.r2()
    assert final.best.r2() == pytest.approx(info['final']['r2_validation_simulation'])
    doc = json.loads(json.dumps(final.to_dict()))
    assert doc['candidates'][final.selected]['final_fit'] == info


def test_free_run_start_up_transient_is_not_taken_for_noise():
    """
    The true model of an output-error system.

    Its free-run residual is the white sensor noise plus a start-up transient (the lags start from
    noisy measurements). The noise model must see white residuals, not fit the transient.
    """
    from piezo_narx_ros.ident.arx.model import ARXModel
    from piezo_narx_ros.ident.selection.scoring import fit_noise_models
    rng = np.random.default_rng(3)
    n, a, b = 6000, [-1.6, 0.8], [0.0, 0.5, 0.3]
    true = ARXModel(2, 2, fit_intercept=False).set_coefficients(a, b)
    u = rng.uniform(-1, 1, n)
    y_clean = true.simulate(u)
    # A large initial deflection makes the transient from the noisy first samples visible.
    y = y_clean + 0.02 * rng.standard_normal(n)
    y[:2] += 3.0
    noise = fit_noise_models(true, [Record(u=u, y=y, fs=1000.0, source='oe')])
    assert noise['simulation'].order == 0


# ---------------------------------------------------------------------------- several records
def test_arx_regressors_never_cross_records():
    # Two noise-free records of one ARX system, each starting from its own rest. Fitted as a
    # list, every row comes from one record and the coefficients are exact; joined into one
    # array, the rows straddling the junction (record 1's end as the past of record 2's start)
    # are wrong equations and pull the estimate off.
    from piezo_narx_ros.ident.arx.model import ARXModel
    r1, r2 = arx_record(3000, seed=1, noise=0.0), arx_record(3000, seed=2, noise=0.0)
    m = ARXModel(na=2, nb=1, fit_intercept=False).fit([r1.u, r2.u], [r1.y, r2.y])
    np.testing.assert_allclose(m.a, [-1.2, 0.5], rtol=0, atol=1e-10)
    np.testing.assert_allclose(m.b, [0.0, 1e-6], rtol=0, atol=1e-16)
    joined = ARXModel(na=2, nb=1, fit_intercept=False).fit(np.r_[r1.u, r2.u], np.r_[r1.y, r2.y])
    assert np.max(np.abs(joined.a - [-1.2, 0.5])) > 1e-6


def test_several_records_are_scored_each_and_the_worst_selects():
    recs = [arx_record(3000, seed=s) for s in (3, 4)]
    recs[1] = Record(u=recs[1].u, y=recs[1].y * 3, fs=1000.0, source='scaled')   # harder one
    cfg = ExperimentConfig(narx=False, arx_na=(1, 2), arx_nb=(1,), jobs=1, progress=False,
                           selection='worst_case')
    res = run_experiment(recs, cfg)
    for c in res.candidates:
        per = c.scores['validation']['records']
        assert [r['source'] for r in per] == ['arx-3[validation]', 'scaled[validation]']
        assert c.free_run_r2() == pytest.approx(min(
            [c.r2('estimation'), c.r2('validation')] + [r['simulation']['r2'] for r in per]))
    best = res.best
    assert best.free_run_r2() == max(c.free_run_r2() for c in res.candidates)
    assert 'worst case' in res.to_dict()['selection']['rule']


def test_stateful_model_is_scored_from_its_recording_start():
    from piezo_narx_ros.ident.selection.scoring import free_run
    from piezo_narx_ros.ident.hysteresis.model import HysteresisNARX
    from piezo_narx_ros.plant import PiezoCantilever, generate
    u = generate('protocol', 2000.0, 4.0, 100.0, seed=1, cycles=1)
    y = PiezoCantilever(fs=2000.0, seed=1).run(u).y
    rec = Record(u=u, y=y, fs=2000.0, source='p')
    est, val = rec.split(0.5)
    assert np.array_equal(val.u_before, est.u)
    m = HysteresisNARX(hidden=3, n_plays=4, max_iter=3).fit(est.u, est.y, fs=2000.0)
    _, sim = free_run(m, val)
    # free_run gives (N, n_out) columns; the one-axis model's own output is (N,).
    assert np.array_equal(sim[:, 0], m.simulate(u, y[:m.n0])[len(est):])
    # The paper's networks keep the paper's protocol: from the validation half's own outputs.
    from piezo_narx_ros.ident.arx.model import ARXModel
    a = ARXModel(2, 2).fit(est.u, est.y)
    assert np.array_equal(free_run(a, val)[1], a.simulate(val.u, val.y[:a.n0]))   # (N, 1) each


def test_envelope_preset_fits_hysteresis_networks_over_seeds(tmp_path):
    from dataclasses import replace

    from piezo_narx_ros.ident.selection.experiment import PRESETS
    from piezo_narx_ros.ident.hysteresis.model import HysteresisNARX
    from piezo_narx_ros.plant import PiezoCantilever, generate
    u = generate('protocol', 2000.0, 4.0, 100.0, seed=2)
    rec = Record(u=u, y=PiezoCantilever(fs=2000.0, seed=2).run(u).y, fs=2000.0, source='p')
    cfg = replace(ExperimentConfig(), **{**PRESETS['envelope'], 'n_seeds': 2, 'hidden': 3,
                                         'hnarx': {'n_plays': 4, 'max_iter': 4}},
                  jobs=1, progress=False)
    specs = cfg.specs()
    n_net = 2 * len(cfg.hnarx_structures())
    assert [s.kind for s in specs[:n_net]] == ['hysteresis_narx'] * n_net
    # Then the paper's NARX grid beside them (narx_beside 'auto', first seed), then 9 ARX.
    assert [s.seed for s in specs[:2]] == [0, 1] and len(specs) == n_net + 16 + 9
    assert [s.kind for s in specs[n_net:n_net + 16]] == ['narx'] * 16
    assert {s.seed for s in specs if s.kind == 'narx'} == {0}
    res = run_experiment([rec], cfg)
    assert isinstance(res.best.model, HysteresisNARX) or res.best.spec.kind == 'arx'
    assert res.best.free_run_r2() == max(c.free_run_r2() for c in res.candidates)
    paths = write_report(res, split_records([rec])[1], tmp_path)
    assert paths['simulation'].is_file()
    with pytest.raises(ConfigError, match='hnarx'):
        replace(cfg, hnarx={'hidden': 4}).validate()
    with pytest.raises(ConfigError, match='n_plays'):
        replace(cfg, hnarx={'n_plays': 0}).validate()


def test_paper_networks_beside_the_envelope_family_only_where_minor_loops_shape_them():
    """narx_beside 'auto': the NARX grid only on one-axis data closing >= 20 minor loops."""
    from piezo_narx_ros.ident.selection.grid import beside
    from piezo_narx_ros.plant import generate
    cfg = ExperimentConfig(family='hysteresis_narx', hidden=3, narx_beside='auto',
                           arx_na=(2,), arx_nb=(2,))
    cfg.validate()
    specs = cfg.specs()
    assert [s.kind for s in specs] == ['hysteresis_narx'] + ['narx'] * 16 + ['arx']

    def rec(u):
        return Record(u=u, y=np.zeros_like(u), fs=2000.0, source='r')
    loops = rec(generate('multisine', 2000.0, 4.0, 100.0, seed=1))
    one_loop = rec(generate('growing_sine', 2000.0, 4.0, 100.0, freq=1.0, hold=0.5))
    assert beside(specs, cfg, [loops]) == specs
    assert [s.kind for s in beside(specs, cfg, [one_loop])] == ['hysteresis_narx', 'arx']
    axes = Record(u=np.c_[loops.u, loops.u], y=np.c_[loops.u, loops.u], fs=2000.0, source='a',
                  inputs=('u1', 'u2'), outputs=('y1', 'y2'))
    assert 'narx' not in [s.kind for s in beside(specs, cfg, [axes])]
    assert beside(specs, replace(cfg, narx_beside='yes'), [one_loop]) == specs
    assert 'narx' not in [s.kind for s in replace(cfg, narx_beside='no').specs()]
    with pytest.raises(ConfigError, match='narx_beside'):
        replace(cfg, narx_beside='maybe').validate()
    # The paper's training options are checked when its networks are fitted beside.
    with pytest.raises(ConfigError, match='training'):
        replace(cfg, training={'no_such_option': 1}).validate()


def test_increment_free_structure_only_where_the_estimation_input_moves_slowly():
    """without_increments 'auto': every seed also without increments on slow one-axis inputs."""
    from piezo_narx_ros.ident.data.coverage import SLOW_STEP, step_share
    from piezo_narx_ros.ident.selection.grid import increments
    from piezo_narx_ros.plant import generate
    cfg = ExperimentConfig(family='hysteresis_narx', hidden=3, n_seeds=2,
                           without_increments='auto', hnarx_grid=({}, {'n_lags': 6}),
                           arx_na=(2,), arx_nb=(2,))
    cfg.validate()
    specs = cfg.specs()
    assert [dict(s.options).get('n_lags') for s in specs if s.kind == 'hysteresis_narx'] == \
        [None, None, 6, 6, 0, 0]

    def rec(u, fs=2000.0):
        return Record(u=u, y=np.zeros_like(u), fs=fs, source='r')
    # A 1 Hz growing sine at 2 kHz steps 0.16 % of its range; at 10 kHz 0.03 %.
    slow = rec(generate('growing_sine', 2000.0, 4.0, 100.0, freq=1.0, hold=0.5))
    slow10k = rec(generate('growing_sine', 10000.0, 2.0, 100.0, freq=1.0, hold=0.5), 10000.0)
    # The protocol and APRBS jump (a piecewise-constant input is as fast as its jumps).
    fast = [rec(generate('protocol', 2000.0, 4.0, 100.0, seed=1)),
            rec(generate('aprbs', 2000.0, 4.0, 100.0, seed=1))]
    assert step_share([slow]) < SLOW_STEP and step_share([slow10k]) < step_share([slow])
    assert all(step_share([r]) > 2 * SLOW_STEP for r in fast)
    assert increments(specs, cfg, [slow]) == specs
    for r in fast:
        assert [s for s in increments(specs, cfg, [r]) if s.kind == 'hysteresis_narx'] == \
            specs[:4]
    # A slow record with a fast one: the fit's inputs move fast where it matters.
    assert len(increments(specs, cfg, [slow, fast[0]])) == len(specs) - 2
    axes = Record(u=np.c_[slow.u, slow.u], y=np.c_[slow.u, slow.u], fs=2000.0, source='a',
                  inputs=('u1', 'u2'), outputs=('y1', 'y2'))
    assert len(increments(specs, cfg, [axes])) == len(specs) - 2
    assert increments(specs, replace(cfg, without_increments='yes'), fast) == specs
    assert len(replace(cfg, without_increments='no').specs()) == len(specs) - 2
    # Not added twice when the grid has a structure without increments already.
    own = replace(cfg, hnarx_grid=({}, {'n_lags': 0}))
    assert own.increment_free() is None and len(own.specs()) == len(specs) - 2
    assert len(increments(own.specs(), own, fast)) == len(own.specs())
    with pytest.raises(ConfigError, match='without_increments'):
        replace(cfg, without_increments='maybe').validate()


def test_small_networks_only_where_the_estimation_input_closes_few_minor_loops():
    """small_networks 'auto': every structure and seed also small, on one-axis loop-poor inputs."""
    from piezo_narx_ros.ident.selection.grid import small
    from piezo_narx_ros.plant import generate
    cfg = ExperimentConfig(family='hysteresis_narx', hidden=6, n_seeds=2, small_networks='auto',
                           small_hidden=2, hnarx_grid=({}, {'n_lags': 0}), arx_na=(2,),
                           arx_nb=(2,))
    cfg.validate()
    specs = cfg.specs()
    nets = [(dict(s.options).get('n_lags'), s.hidden, s.seed) for s in specs
            if s.kind == 'hysteresis_narx']
    assert nets == [(None, 6, 0), (None, 6, 1), (None, 2, 0), (None, 2, 1),
                    (0, 6, 0), (0, 6, 1), (0, 2, 0), (0, 2, 1)]
    assert len({s.label for s in specs}) == len(specs)   # the report tells them apart

    def rec(u):
        return Record(u=u, y=np.zeros_like(u), fs=2000.0, source='r')
    one_loop = rec(generate('growing_sine', 2000.0, 4.0, 100.0, freq=1.0, hold=0.5))
    loops = rec(generate('multisine', 2000.0, 4.0, 100.0, seed=1))
    assert small(specs, cfg, [one_loop]) == specs
    kept = small(specs, cfg, [loops])
    assert [s.hidden for s in kept if s.kind == 'hysteresis_narx'] == [6] * 4
    assert [s.kind for s in kept][-1] == 'arx'
    axes = Record(u=np.c_[one_loop.u, one_loop.u], y=np.c_[one_loop.u, one_loop.u],
                  fs=2000.0, source='a', inputs=('u1', 'u2'), outputs=('y1', 'y2'))
    assert len(small(specs, cfg, [axes])) == len(kept)
    assert small(specs, replace(cfg, small_networks='yes'), [loops]) == specs
    assert len(replace(cfg, small_networks='no').specs()) == len(kept)
    # Nothing to add when the small size is the size.
    assert replace(cfg, small_hidden=6).specs() == kept
    for bad in ({'small_networks': 'maybe'}, {'small_hidden': 0}, {'small_hidden': 2.5}):
        with pytest.raises(ConfigError, match=next(iter(bad))):
            replace(cfg, **bad).validate()


def test_small_networks_on_a_growing_sine_are_fitted_and_selected_among():
    from dataclasses import replace

    from piezo_narx_ros.ident.selection.experiment import PRESETS
    from piezo_narx_ros.plant import PiezoCantilever, generate

    def rec(freq, seed):
        u = generate('growing_sine', 2000.0, 3.0, 100.0, freq=freq, hold=0.2)
        return Record(u=u, y=PiezoCantilever(fs=2000.0, seed=seed).run(u).y, fs=2000.0,
                      source=f'{freq} Hz')
    cfg = replace(ExperimentConfig(), **{**PRESETS['envelope'], 'n_seeds': 1, 'hidden': 4,
                                         'small_networks': 'auto', 'small_hidden': 2,
                                         'hnarx': {'n_plays': 4, 'max_iter': 3}},
                  jobs=1, progress=False)
    res = run_experiment([rec(1.0, 1)], cfg, validation=[rec(5.0, 2)])
    nets = [c for c in res.candidates if c.spec.kind == 'hysteresis_narx']
    # Every structure (two of the grid, one without increments on this slow input) twice.
    assert sorted(c.spec.hidden for c in nets) == [2, 2, 2, 4, 4, 4]
    assert all(c.error is None and np.isfinite(c.free_run_r2()) for c in nets)
    assert res.best.free_run_r2() == max(c.free_run_r2() for c in res.candidates)


def test_hnarx_grid_fits_every_structure_with_every_seed():
    """Each structure of hnarx_grid is its options over hnarx, fitted with every seed."""
    cfg = ExperimentConfig(family='hysteresis_narx', n_seeds=2, hidden=3, arx_na=(), arx_nb=(),
                           hnarx={'n_plays': 4}, hnarx_grid=({}, {'n_lags': 6, 'na': 4}))
    cfg.validate()
    specs = cfg.specs()
    assert [(dict(s.options).get('n_lags', 3), s.seed) for s in specs] == \
        [(3, 0), (3, 1), (6, 0), (6, 1)]
    assert all(dict(s.options)['n_plays'] == 4 for s in specs)
    assert [s.nu for s in specs] == [3, 3, 6, 6] and [s.ny for s in specs] == [3, 3, 4, 4]
    assert 'lags=6' in specs[2].label and 'lags' not in specs[0].label
    with pytest.raises(ConfigError, match='n_lags'):
        ExperimentConfig(family='hysteresis_narx', hnarx_grid=({'n_lags': -1},)).validate()
    with pytest.raises(ConfigError, match='hnarx_grid'):
        ExperimentConfig(family='hysteresis_narx', hnarx_grid=({'seed': 1},)).validate()
    with pytest.raises(ConfigError, match='hnarx_grid'):
        ExperimentConfig(family='hysteresis_narx', hnarx_grid=(6,)).validate()


def test_several_axes_fit_the_envelope_family_once_not_once_per_seed_and_structure():
    """The several-axes envelope fit uses neither seed nor drive increments: one candidate."""
    from dataclasses import replace

    from piezo_narx_ros.ident.selection.experiment import PRESETS
    from piezo_narx_ros.ident.selection.grid import auto_grid, distinct_specs
    cfg = replace(ExperimentConfig(), **PRESETS['envelope'])
    # 3 seeds x 2 structures; the third (without increments) and the paper's 16 networks
    # beside are dropped on several axes.
    specs = auto_grid(cfg.specs(), cfg, [Record(u=np.zeros((50, 3)), y=np.zeros((50, 3)),
                                                fs=1e3, source='c', inputs=('u1', 'u2', 'u3'),
                                                outputs=('y1', 'y2', 'y3'))])
    n_net = sum(s.kind == 'hysteresis_narx' for s in specs)
    assert n_net == 6 and len(cfg.specs()) == len(specs) + 3 + 16
    one = Record(u=np.zeros((50, 1)), y=np.zeros((50, 1)), fs=1e3, source='a')
    three = Record(u=np.zeros((50, 3)), y=np.zeros((50, 3)), fs=1e3, source='b',
                   inputs=('u1', 'u2', 'u3'), outputs=('y1', 'y2', 'y3'))
    assert distinct_specs(specs, [one]) == specs
    kept = distinct_specs(specs, [three])
    common = [s for s in kept
              if s.kind == 'hysteresis_narx' and 'structure' not in dict(s.options)]
    assert common == [specs[0]]                 # the common-denominator structure: fitted once
    # One chain per axis (ident/hysteresis/chains.py) uses seeds and increments: each kept.
    assert len(kept) == 1 + n_net + (len(specs) - n_net)
    assert [s.kind for s in kept].count('arx') == [s.kind for s in specs].count('arx')


def test_init_past_reaches_every_network_candidate_and_not_through_hnarx():
    """init_past 'fade-out' builds every HysteresisNARX told so; 'past' inside hnarx is refused."""
    from piezo_narx_ros.ident.selection.experiment import PRESETS
    cfg = replace(ExperimentConfig(), **{**PRESETS['envelope'], 'n_seeds': 1}, jobs=1)
    told = replace(cfg, init_past='fade-out')
    nets = [s for s in told.specs() if s.kind == 'hysteresis_narx']
    assert nets and all(dict(s.options)['past'] == 'fade-out' for s in nets)
    assert all(s.build().past == 'fade-out' for s in nets)
    assert all('past' not in dict(s.options) for s in cfg.specs())
    with pytest.raises(ConfigError, match='init_past'):
        replace(cfg, hnarx={'past': 'fade-out'}).validate()
