"""`piezo-narx fit` and `piezo-narx evaluate` end to end on small synthetic data, and bad input."""
import json
import subprocess
import sys

import numpy as np
import pytest
import yaml

from conftest import REPO
from piezo_narx_ros.cli.main import main

FAST_TRAINING = {'restarts': 1, 'restart_iter': 2, 'max_iter': 8, 'refine_iter': 3,
                 'n_segments': 5, 'onestep_samples': 1000}


def piezo_like(n=3000, fs=2000.0, seed=0, noise=2e-9):
    """(u V, y m): Bouc-Wen-type hysteresis into a lightly damped 2nd-order mode."""
    rng = np.random.default_rng(seed)
    steps = rng.uniform(0, 100, n // 40 + 2)
    u = np.interp(np.arange(n), np.arange(steps.size) * 40, steps)
    du = np.diff(u, prepend=u[0])
    h = np.zeros(n)
    for k in range(1, n):
        h[k] = h[k - 1] + 0.4 * du[k] - 0.02 * abs(du[k]) * h[k - 1] - 0.01 * du[k] * abs(h[k - 1])
    x = 1e-7 * (u - h)
    y = np.zeros(n)
    for k in range(2, n):
        y[k] = 1.6 * y[k - 1] - 0.7 * y[k - 2] + 0.1 * x[k - 1]
    return u, y + noise * rng.standard_normal(n)


def cli(argv, capsys):
    """Run piezo-narx in-process: (exit code, stdout, stderr)."""
    with pytest.raises(SystemExit) as exc:
        main(argv)
    out = capsys.readouterr()
    return exc.value.code, out.out, out.err


@pytest.fixture(scope='module')
def data_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp('data')
    u, y = piezo_like()
    np.savez(d / 'rec.npz', u=u, y=y, fs=2000.0)
    t = np.arange(u.size) / 2000.0
    np.savetxt(d / 'rec.csv', np.column_stack([t, u, y]), delimiter=',', header='t,u,y',
               comments='')
    np.savetxt(d / 'noheader.csv', np.column_stack([u, y]), delimiter=',')
    (d / 'fast.yaml').write_text(yaml.safe_dump({'training': FAST_TRAINING, 'final_training': {}}))
    return d


@pytest.fixture(scope='module')
def fitted(data_dir, tmp_path_factory):
    """One fit shared by the end-to-end checks: one network + a 2x2 ARX grid, serial."""
    out = tmp_path_factory.mktemp('fit')
    with pytest.raises(SystemExit) as exc:
        main(['fit', '--preset', 'paper',
              str(data_dir / 'rec.npz'), '--ny', '2', '--nu', '2', '--hidden', '4',
              '--arx-na', '1-2', '--arx-nb', '1-2', '--jobs', '1', '--quiet', '--out', str(out),
              '--config', str(data_dir / 'fast.yaml')])
    assert exc.value.code == 0
    return out


def test_fit_writes_model_candidates_and_report(fitted, data_dir):
    cands = json.loads((fitted / 'candidates.json').read_text())
    assert [c['label'] for c in cands['candidates']] == [
        'NARX(ny=2, nu=2, H=4)', 'ARX(na=1, nb=1)', 'ARX(na=1, nb=2)', 'ARX(na=2, nb=1)',
        'ARX(na=2, nb=2)']
    assert cands['config']['max_outside_fraction'] == 0.05
    assert (cands['config']['residuals'], cands['config']['noise_model']) == ('simulation', 'ar')
    assert cands['config']['training'] == FAST_TRAINING
    sel = cands['candidates'][cands['selection']['index']]
    for c in cands['candidates']:
        assert c['error'] is None
        assert set(c['scores']) == {'estimation', 'validation'}
        assert c['scores']['validation']['prediction']['r2'] > 0.99
    doc = json.loads((fitted / 'model.json').read_text())
    assert doc['structure']['kind'] == sel['kind']
    assert doc['fs'] == 2000.0
    assert doc['data']['n_estimation'] == 1500
    # The data's least-squares line, the reference the linear mode's gain is checked against.
    rec = np.load(data_dir / 'rec.npz')
    gain, offset = np.polyfit(rec['u'], rec['y'], 1)
    line = doc['data']['line']
    assert line['gain_m_per_v'] == pytest.approx(gain, rel=1e-9)
    assert line['offset_m'] == pytest.approx(offset, rel=1e-9, abs=1e-15)
    assert doc['metrics']['validation']['simulation']['r2'] == pytest.approx(
        sel['scores']['validation']['simulation']['r2'])
    assert (fitted / 'model.npz').is_file()
    # The verdicts record which residuals and which noise model they used, and the raw ones.
    tests = doc['tests']
    assert tests['residuals'] == 'simulation' and tests['noise_model'] == 'ar'
    assert tests['simulation']['noise_model']['kind'] == 'ar'
    assert len(tests['simulation']['noise_model']['coef']) == \
        tests['simulation']['noise_model']['order']
    assert set(tests['raw']) == {'prediction', 'simulation'}
    assert doc['metrics']['noise_model'] == 'ar'
    for name in ('metrics.json', 'fig6_narx_r2_grid.png', 'fig6_arx_r2_grid.png',
                 'fig7_correlation.png', 'fig8_simulation.png', 'fig9_hysteresis.png'):
        assert (fitted / 'report' / name).stat().st_size > 1000, name


def test_evaluate_json_matches_model_and_data(fitted, data_dir, capsys):
    code, out, err = cli(['evaluate', str(fitted / 'model.json'), str(data_dir / 'rec.npz'),
                          '--json'], capsys)
    assert code == 0, err
    result = json.loads(out)
    assert out.count('\n') == 1
    for mode in ('simulation', 'prediction'):
        assert 0.9 < result[mode]['r2'] <= 1.0
        assert 0 < result[mode]['rmse'] < 1e-6          # metres
    assert set(result['tests']) == {'phi_ee', 'phi_ue', 'phi_u2e', 'phi_u2e2', 'phi_e_eu'}
    assert all(isinstance(v, bool) for v in result['tests'].values())
    structure = json.loads((fitted / 'model.json').read_text())['structure']
    assert result['n'] == 3000 - max(structure['nu'], structure['ny'])   # scored from k = n0
    assert result['tests_residuals'] == 'simulation'
    stored = json.loads((fitted / 'model.json').read_text())['tests']['simulation']['noise_model']
    assert result['tests_noise_model']['coef'] == stored['coef']      # the fixed, stored filter
    assert result['tests_noise_model']['source'].startswith('model file')
    assert set(result['tests_raw']) == set(result['tests'])
    detail = result['tests_detail']
    assert result['tests'] == {k: v['passed']
                               for k, v in detail['simulation']['tests'].items()}

    code, out, _ = cli(['evaluate', str(fitted / 'model.json'), str(data_dir / 'rec.npz'),
                        '--json', '--noise-model', 'none'], capsys)
    raw = json.loads(out)
    assert code == 0 and raw['tests_noise_model'] is None
    assert raw['tests'] == raw['tests_raw'] == result['tests_raw']

    code, out, _ = cli(['evaluate', str(fitted / 'model.json'), str(data_dir / 'rec.npz')],
                       capsys)
    assert code == 0 and 'simulation: R²' in out and 'correlation tests' in out


def test_csv_and_npz_inputs_give_the_same_fit(data_dir, tmp_path, capsys):
    args = ['--no-arx', '--ny', '1', '--nu', '1', '--hidden', '3', '--jobs', '1', '--quiet',
            '--no-report', '--config', str(data_dir / 'fast.yaml')]
    assert cli(['fit', '--preset', 'paper',
                str(data_dir / 'rec.npz'), '--out', str(tmp_path / 'a')] + args,
               capsys)[0] == 0
    assert cli(['fit', '--preset', 'paper',
                str(data_dir / 'noheader.csv'), '--fs', '2000', '--out',
                str(tmp_path / 'b')] + args, capsys)[0] == 0
    a = json.loads((tmp_path / 'a' / 'candidates.json').read_text())['candidates'][0]
    b = json.loads((tmp_path / 'b' / 'candidates.json').read_text())['candidates'][0]
    assert a['scores'] == b['scores']
    assert not (tmp_path / 'a' / 'report').exists()


def test_fit_from_bag(data_dir, tmp_path, capsys):
    from piezo_narx_ros.bag.writer import write_uy_bag
    u, y = piezo_like(2000, seed=4)
    bag = write_uy_bag(tmp_path / 'bag', u, y, 2000.0)
    code, out, err = cli(['fit', '--preset', 'paper',
                          str(bag), '--no-arx', '--ny', '1', '--nu', '1', '--hidden', '2',
                          '--jobs', '1', '--no-report', '--config', str(data_dir / 'fast.yaml'),
                          '--out', str(tmp_path / 'out')], capsys)
    assert code == 0, err
    assert 'selected NARX(ny=1, nu=1, H=2)' in out
    doc = json.loads((tmp_path / 'out' / 'model.json').read_text())
    assert doc['fs'] == pytest.approx(2000.0)
    assert doc['data']['sources'] == [str(bag)]


def test_evaluate_does_not_import_torch(fitted, data_dir):
    code = ('import sys\nfrom piezo_narx_ros.cli.main import main\n'
            'try:\n    main(sys.argv[1:])\nexcept SystemExit as e:\n    assert e.code == 0\n'
            'print("torch" in sys.modules)')
    proc = subprocess.run([sys.executable, '-c', code, 'evaluate', str(fitted / 'model.json'),
                           str(data_dir / 'rec.csv'), '--json'], capture_output=True, text=True,
                          cwd=REPO, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip().splitlines()[-1] == 'False'


def _write_bad(d, name):
    u, y = piezo_like(400)
    if name == 'wrong_columns.csv':
        np.savetxt(d / name, np.column_stack([u, y]), delimiter=',', header='volts,metres',
                   comments='')
    elif name == 'missing_key.npz':
        np.savez(d / name, u=u, fs=2000.0)
    elif name == 'nan.npz':
        u[17] = np.nan
        np.savez(d / name, u=u, y=y, fs=2000.0)
    elif name == 'short.npz':
        np.savez(d / name, u=u[:50], y=y[:50], fs=2000.0)
    elif name == 'short_for_lags.npz':
        np.savez(d / name, u=u[:150], y=y[:150], fs=2000.0)
    elif name == 'length.npz':
        np.savez(d / name, u=u, y=y[:-1], fs=2000.0)
    elif name == 'no_fs.csv':
        np.savetxt(d / name, np.column_stack([u, y]), delimiter=',', header='u,y', comments='')
    elif name == 'data.xlsx':
        (d / name).write_text('1 2\n')
    elif name == 'other_fs.npz':
        np.savez(d / name, u=u, y=y, fs=1000.0)
    return d / name


@pytest.mark.parametrize('inputs, extra, message', [
    (['absent.npz'], [], 'no such file'),
    (['wrong_columns.csv'], [], 'missing column(s) u, y'),
    (['missing_key.npz'], [], 'missing key(s) y'),
    (['nan.npz'], [], 'u contains NaN or inf (first at sample 17)'),
    (['short.npz'], [], 'only 50 samples'),
    (['short_for_lags.npz'], [], 'too few'),
    (['length.npz'], [], 'u has 400 samples but y has 399'),
    (['no_fs.csv'], [], 'pass the sample rate with --fs'),
    (['data.xlsx'], [], 'unknown input type'),
    (['rec.npz', 'other_fs.npz'], [], 'sample rates differ'),
    (['rec.npz'], ['--fs', '1000'], 'file says fs = 2000.0 Hz but --fs = 1000.0 Hz'),
    (['rec.npz'], ['--ny', '4-1'], 'not a lag range'),
    (['rec.npz'], ['--hidden', '0'], 'hidden'),
    (['rec.npz'], ['--max-outside', '1.5'], 'max_outside_fraction'),
    (['rec.npz'], ['--noise-order', '-2'], 'noise_order'),
])
def test_fit_bad_input_one_line_exit_2(data_dir, tmp_path, capsys, inputs, extra, message):
    paths = [str(data_dir / 'rec.npz') if i == 'rec.npz' else
             str(tmp_path / i) if i == 'absent.npz' else str(_write_bad(tmp_path, i))
             for i in inputs]
    code, out, err = cli(['fit', '--preset', 'paper',
                          *paths, '--out', str(tmp_path / 'out'), '--no-arx', '--ny', '1',
                          '--nu', '1', '--jobs', '1', *extra], capsys)
    assert code == 2
    assert err.count('\n') == 1 and err.startswith('piezo-narx: error: ')
    assert message in err
    assert not (tmp_path / 'out' / 'model.json').exists()


def test_fit_bad_config_file(data_dir, tmp_path, capsys):
    (tmp_path / 'bad.yaml').write_text('hiden: 10\n')
    code, _, err = cli(['fit', '--preset', 'paper',
                        str(data_dir / 'rec.npz'), '--out', str(tmp_path / 'o'),
                        '--config', str(tmp_path / 'bad.yaml')], capsys)
    assert code == 2 and 'unknown setting(s) hiden' in err and err.count('\n') == 1


def test_default_config_file_matches_built_in_defaults(tmp_path):
    from piezo_narx_ros.ident.pipeline.settings import experiment_config, merge_settings
    # config/fit.yaml spells out the paper preset (the search, the default, has no grid).
    built_in = merge_settings('paper')
    assert merge_settings()['preset'] == 'search'
    from_file = merge_settings(config_file=str(REPO / 'config' / 'fit.yaml'))
    # The file spells ranges as text ('1-4'); what matters is the experiment they configure.
    assert experiment_config(from_file, False) == experiment_config(built_in, False)
    assert set(from_file) == set(built_in)
    cfg = experiment_config(built_in, progress=False)
    assert len(cfg.specs()) == 16 + 100 and cfg.hidden == 10
    assert (cfg.max_outside_fraction, cfg.residuals, cfg.noise_model, cfg.noise_order) == (
        0.05, 'simulation', 'ar', 20)


@pytest.mark.parametrize('case, message', [
    ('missing_model', 'model.json'),
    ('fs_mismatch', 'sampled at 1000 Hz but the model was fitted at 2000 Hz'),
    ('short', 'too few'),
    ('bad_noise_model', 'tests.simulation.noise_model is malformed'),
])
def test_evaluate_bad_input_one_line_exit_2(fitted, data_dir, tmp_path, capsys, case, message):
    model = str(fitted / 'model.json')
    data = str(data_dir / 'rec.npz')
    if case == 'missing_model':
        model = str(tmp_path / 'model.json')
    elif case == 'fs_mismatch':
        data = str(_write_bad(tmp_path, 'other_fs.npz'))
    elif case == 'bad_noise_model':
        import shutil
        doc = json.loads((fitted / 'model.json').read_text())
        doc['tests']['simulation']['noise_model']['coef'] = ['print(1)']
        (tmp_path / 'model.json').write_text(json.dumps(doc))
        shutil.copy(fitted / 'model.npz', tmp_path / 'model.npz')
        model = str(tmp_path / 'model.json')
    else:
        u, y = piezo_like(120)
        np.savez(tmp_path / 's.npz', u=u, y=y, fs=2000.0)
        data = str(tmp_path / 's.npz')
    extra = ['--max-lag', '40'] if case == 'short' else []
    code, _, err = cli(['evaluate', model, data, '--json', *extra], capsys)
    assert code == 2 and err.count('\n') == 1 and message in err, err


def test_warnings_print_as_one_line(capsys):
    import warnings

    from piezo_narx_ros.cli.fit_output import one_line_warnings
    with one_line_warnings():
        warnings.warn('bag.mcap: 3 samples missing on /piezo/deflection', UserWarning)
    err = capsys.readouterr().err
    assert err == 'piezo-narx: warning: bag.mcap: 3 samples missing on /piezo/deflection\n'


def test_fit_envelope_preset_from_two_records(tmp_path, capsys):
    from piezo_narx_ros.plant import PiezoCantilever, generate
    for i in (0, 1):
        u = generate('protocol', 2000.0, 3.0, 100.0, seed=i, cycles=2)
        np.savez(tmp_path / f'p{i}.npz', u=u, y=PiezoCantilever(seed=i).run(u).y, fs=2000.0)
    (tmp_path / 'small.yaml').write_text(yaml.safe_dump(
        {'hidden': 3, 'n_seeds': 2, 'hnarx': {'n_plays': 4, 'max_iter': 3}, 'arx_na': '2',
         'arx_nb': '2'}))
    code, out, err = cli(['fit', str(tmp_path / 'p0.npz'), str(tmp_path / 'p1.npz'),
                          '--preset', 'envelope', '--config', str(tmp_path / 'small.yaml'),
                          '--jobs', '1', '--no-report', '--out', str(tmp_path / 'o')], capsys)
    assert code == 0, err
    doc = json.loads((tmp_path / 'o' / 'model.json').read_text())
    assert doc['data']['preset'] == 'envelope' and len(doc['data']['sources']) == 2
    assert doc['structure']['kind'] in ('hysteresis_narx', 'arx')
    # Each record's validation score is shown and stored.
    assert out.count('[validation]: simulation') == 2
    assert len(doc['metrics']['validation']['records']) == 2
    cands = json.loads((tmp_path / 'o' / 'candidates.json').read_text())
    assert [c['seed'] for c in cands['candidates'][:2]] == [0, 1]
    assert cands['config']['selection'] == 'worst_case'
    code, _, err = cli(['fit', str(tmp_path / 'p0.npz'), '--preset', 'nope', '--out',
                        str(tmp_path / 'x')], capsys)
    assert code == 2 and 'nope' in err


def test_fit_says_which_creep_filters_a_sine_leaves_at_zero(tmp_path, capsys):
    from piezo_narx_ros.plant import PiezoCantilever, generate
    u = generate('sine', 2000.0, 6.0, 100.0, freq=1.0)
    np.savez(tmp_path / 's.npz', u=u, y=PiezoCantilever(seed=0).run(u).y, fs=2000.0)
    (tmp_path / 'small.yaml').write_text(yaml.safe_dump(
        {'hidden': 3, 'n_seeds': 1, 'hnarx': {'n_plays': 4, 'max_iter': 3}, 'hnarx_grid': [],
         'without_increments': 'no', 'arx_na': [], 'arx_nb': []}))
    code, out, err = cli(['fit', str(tmp_path / 's.npz'), '--preset', 'envelope', '--config',
                          str(tmp_path / 'small.yaml'), '--jobs', '1', '--no-report', '--out',
                          str(tmp_path / 'o')], capsys)
    assert code == 0, err
    # A 1 Hz sine around its start moves neither the 30 s nor the 100 s creep filter by 1 %.
    assert 'creep held at 0 for the 30 s, 100 s filter(s)' in out
    doc = json.loads((tmp_path / 'o' / 'model.json').read_text())
    assert doc['training']['info']['creep_fixed_s'] == [30.0, 100.0]
