"""
Fault suite, command line.

What a hostile new user feeds `piezo-narx` ends in one line and a non-zero exit, or in a clear
warning, never in a traceback or a silently wrong result.

Covers issue 10 items 11-15: non-UTF-8 YAML, absurd lengths, crafted .npz headers, data that
cannot identify anything, inputs far outside a model's range, NaN in model files, BOM and
header-only CSV, random bytes, and `fit --out` over an existing model.
"""
import json
import re
import subprocess
import sys
import zipfile

import numpy as np
import pytest

from conftest import REPO
from piezo_narx_ros.cli.main import main

LATIN1 = 'ny: 2  # r\xe9glage\n'.encode('latin-1')   # not UTF-8


def cli(argv, capsys):
    """Run piezo-narx in-process: (exit code, stdout, stderr)."""
    with pytest.raises(SystemExit) as exc:
        main(argv)
    out = capsys.readouterr()
    return exc.value.code, out.out, out.err


def one_error_line(err: str) -> bool:
    return err.count('\n') == 1 and err.startswith('piezo-narx: error: ')


def record(n=2000, fs=2000.0, seed=0):
    """(u V, y m) of a simple first-order lag: enough to be identifiable."""
    rng = np.random.default_rng(seed)
    u = np.repeat(rng.uniform(-100, 100, n // 20 + 1), 20)[:n]
    y = np.zeros(n)
    for k in range(1, n):
        y[k] = 0.9 * y[k - 1] + 1e-8 * u[k]
    return u, y + 1e-9 * rng.standard_normal(n)


@pytest.fixture
def good_npz(tmp_path):
    u, y = record()
    path = tmp_path / 'good.npz'
    np.savez(path, u=u, y=y, fs=2000.0)
    return path


# ------------------------------------------------------------------- files that are not UTF-8
@pytest.mark.parametrize('argv', [
    ['fit', '--preset', 'paper', '{good}', '--out', '{tmp}/o', '--config', '{bad}'],
    ['bringup', '{bad}'],
    ['demo', '--config', '{bad}', '--out', '{tmp}/d'],
    ['simulate', '--seconds', '1', '--plant-config', '{bad}', '--out', '{tmp}/s.npz'],
])
def test_non_utf8_yaml_is_one_line(tmp_path, good_npz, capsys, argv):
    bad = tmp_path / 'bad.yaml'
    bad.write_bytes(LATIN1)
    argv = [a.format(good=good_npz, tmp=tmp_path, bad=bad) for a in argv]
    code, _, err = cli(argv, capsys)
    assert code == 2 and one_error_line(err) and 'UTF-8' in err, err


# ------------------------------------------------------------------------- absurd sizes
@pytest.mark.parametrize('extra', [['--seconds', '1e7'], ['--fs', '1e9'],
                                   ['--seconds', '1e300', '--fs', '1e300']])
def test_simulate_absurd_length_is_refused_before_allocating(tmp_path, capsys, extra):
    code, _, err = cli(['simulate', *extra, '--out', str(tmp_path / 's.npz')], capsys)
    assert code == 2 and one_error_line(err) and 'samples' in err, err
    assert not (tmp_path / 's.npz').exists()


def crafted_npz(path, declared=10**12, names=('u', 'y')):
    """Return an .npz whose 'u' header declares `declared` float64 values but stores 80 bytes."""
    import io
    head = io.BytesIO()
    np.lib.format.write_array_header_1_0(
        head, {'descr': '<f8', 'fortran_order': False, 'shape': (declared,)})
    with zipfile.ZipFile(path, 'w') as z:
        for name in names:       # the header includes the magic
            z.writestr(f'{name}.npy', head.getvalue() + b'\x00' * 80)
        buf = io.BytesIO()
        np.save(buf, np.float64(2000.0))
        z.writestr('fs.npy', buf.getvalue())
    return path


def test_npz_header_declaring_1e12_values_is_refused(tmp_path, capsys):
    path = crafted_npz(tmp_path / 'huge.npz')
    code, _, err = cli(['fit', '--preset', 'paper',
                        str(path), '--out', str(tmp_path / 'o')], capsys)
    assert code == 2 and one_error_line(err) and 'declares shape (1000000000000,)' in err, err


def test_crafted_npz_refused_by_every_reader(tmp_path):
    from piezo_narx_ros.errors import ConfigError, ModelFileError
    from piezo_narx_ros.ident.model_io import load_model, save_model
    from piezo_narx_ros.estimator.toy import toy_narx
    from piezo_narx_ros.plant.signals import generate
    crafted = crafted_npz(tmp_path / 'c.npz')
    with pytest.raises(ConfigError, match='declares shape'):
        generate('playback', 2000.0, None, None, path=str(crafted))
    # Model weights: the JSON's SHA-256 and declared shape are updated so that only the header
    # check can stop it.
    model = save_model(toy_narx(), tmp_path / 'm.json')
    import hashlib
    weights = crafted_npz(tmp_path / 'm.npz', names=('W1',))
    doc = json.loads(model.read_text())
    doc['weights'].update(sha256=hashlib.sha256(weights.read_bytes()).hexdigest(),
                          arrays={'W1': [10**12]})
    model.write_text(json.dumps(doc))
    with pytest.raises(ModelFileError, match='declares shape'):
        load_model(model)


def test_random_bytes_npz_is_not_called_pickled(tmp_path, capsys):
    path = tmp_path / 'r.npz'
    path.write_bytes(np.random.default_rng(0).bytes(1000))
    code, _, err = cli(['fit', '--preset', 'paper',
                        str(path), '--out', str(tmp_path / 'o')], capsys)
    assert code == 2 and one_error_line(err) and 'not an .npz file' in err, err
    assert 'pickle' not in err


def test_object_arrays_are_refused_without_unpickling(tmp_path):
    from piezo_narx_ros.errors import DataError
    from piezo_narx_ros.npzfile import read_npz
    path = tmp_path / 'o.npz'
    np.savez(path, u=np.array([{'a': 1}], dtype=object))
    with pytest.raises(DataError, match='Python objects'):
        read_npz(path)


# ------------------------------------------------------------------------------------ CSV
def test_utf8_bom_csv_reads_its_t_column(tmp_path):
    from piezo_narx_ros.ident.data.loaders import load_record
    u, y = record()
    t = np.arange(u.size) / 2000.0
    rows = zip(t.tolist(), u.tolist(), y.tolist())
    body = 't,u,y\n' + '\n'.join(f'{a!r},{b!r},{c!r}' for a, b, c in rows)
    path = tmp_path / 'bom.csv'
    path.write_bytes(b'\xef\xbb\xbf' + body.encode())
    rec = load_record(path)
    assert rec.fs == pytest.approx(2000.0) and np.array_equal(rec.u[:, 0], u)


def test_header_only_csv_says_so(tmp_path, capsys):
    path = tmp_path / 'h.csv'
    path.write_text('t,u,y\n')
    code, _, err = cli(['fit', '--preset', 'paper',
                        str(path), '--out', str(tmp_path / 'o')], capsys)
    assert code == 2 and one_error_line(err) and 'only a header row' in err, err


# ------------------------------------------------------------------ data that identifies nothing
def test_near_constant_output_is_refused(tmp_path, capsys):
    u, _ = record()
    y = np.full(u.size, 1e-6) * (1 + 1e-16 * np.random.default_rng(1).standard_normal(u.size))
    np.savez(tmp_path / 'flat.npz', u=u, y=y, fs=2000.0)
    code, _, err = cli(['fit', '--preset', 'paper',
                        str(tmp_path / 'flat.npz'), '--out', str(tmp_path / 'o')], capsys)
    assert code == 2 and one_error_line(err) and 'output is constant' in err, err
    assert not (tmp_path / 'o').exists()


def test_idle_estimation_half_is_refused_with_the_fix(tmp_path, capsys):
    u, y = record(4000)
    u[:2400] = 0.0                      # rig idle for the first 1.2 s, then moving
    np.savez(tmp_path / 'idle.npz', u=u, y=y, fs=2000.0)
    code, _, err = cli(['fit', '--preset', 'paper',
                        str(tmp_path / 'idle.npz'), '--out', str(tmp_path / 'o')], capsys)
    assert code == 2 and one_error_line(err), err
    assert 'input is constant over the estimation part' in err and '--split' in err


def test_weak_estimation_half_warns():
    from piezo_narx_ros.ident.data.records import check_identifiable
    from piezo_narx_ros.record import Record
    u, y = record(4000)
    u[:2000] *= 0.01
    warns = check_identifiable(Record(u, y, 2000.0, 'weak.npz'), 0.5)
    assert len(warns) == 1 and 'moves little' in warns[0] and '--split' in warns[0]
    assert check_identifiable(Record(*record(4000), 2000.0, 'ok.npz'), 0.5) == []


# ------------------------------------------------------------------ fit --out over a model
def test_fit_refuses_to_overwrite_a_model_without_force(tmp_path, good_npz, capsys):
    out = tmp_path / 'o'
    out.mkdir()
    (out / 'model.json').write_text('{"keep": true}')
    code, _, err = cli(['fit', '--preset', 'paper', str(good_npz), '--out', str(out)], capsys)
    assert code == 2 and one_error_line(err) and '--force' in err, err
    assert (out / 'model.json').read_text() == '{"keep": true}'


# ---------------------------------------------------------------------------- model files
@pytest.fixture
def toy_model(tmp_path):
    from piezo_narx_ros.estimator.toy import toy_narx
    from piezo_narx_ros.ident.model_io import save_model
    return save_model(toy_narx(fs=2000.0), tmp_path / 'toy.json')


@pytest.mark.parametrize('key, value, message', [
    ('fs', 'NaN', 'NaN is not allowed'),
    ('output_range', '[NaN, NaN]', 'NaN is not allowed'),
    ('input_range', '[-Infinity, 1.0]', '-Infinity is not allowed'),
    ('output_range', '[1.0, -1.0]', 'output_range.*min <= max'),
])
def test_model_file_with_nan_or_inverted_range_is_refused(toy_model, key, value, message):
    from piezo_narx_ros.errors import ModelFileError
    from piezo_narx_ros.ident.model_io import load_model
    doc = json.loads(toy_model.read_text())
    doc[key] = '@@'
    toy_model.write_text(json.dumps(doc).replace('"@@"', value))
    with pytest.raises(ModelFileError, match=message):
        load_model(toy_model)


def test_evaluate_warns_on_inputs_outside_the_trained_range(toy_model, tmp_path, capsys):
    from piezo_narx_ros.ident.model_io import load_model
    model = load_model(toy_model)
    u = np.random.default_rng(0).uniform(-100, 100, 2000)
    np.savez(tmp_path / 'far.npz', u=u * 1e296, y=model.simulate(u), fs=2000.0)
    code, _, err = cli(['evaluate', str(toy_model), str(tmp_path / 'far.npz')], capsys)
    assert code == 2 and 'u reaches 9.996e+297' in err and '--u-unit' in err   # issue 19
    # Said to be volts: scored, with the range warning.
    code, out, err = cli(['evaluate', str(toy_model), str(tmp_path / 'far.npz'), '--json',
                          '--u-unit', 'V'], capsys)
    assert code == 0 and 'outside the [-150, 150] V the model was trained on' in err, err
    assert json.loads(out)['warnings'] and 'RuntimeWarning' not in err


def test_evaluate_refuses_non_finite_scores(tmp_path, capsys):
    from piezo_narx_ros.ident.arx.model import ARXModel
    from piezo_narx_ros.ident.model_io import save_model
    u, y = record()
    model = ARXModel(2, 2).fit(u, y)
    model.fs = 2000.0
    save_model(model, tmp_path / 'arx.json')
    np.savez(tmp_path / 'huge.npz', u=u * 1e300, y=y, fs=2000.0)
    code, _, err = cli(['evaluate', str(tmp_path / 'arx.json'), str(tmp_path / 'huge.npz'),
                        '--u-unit', 'V'], capsys)
    assert code == 2 and 'not finite' in err and err.count('piezo-narx: error:') == 1, err
    assert 'Traceback' not in err


def test_unexpected_exception_is_one_line(monkeypatch, capsys):
    import piezo_narx_ros.cli.bag as bag_cli
    monkeypatch.delenv('PIEZO_NARX_DEBUG', raising=False)
    monkeypatch.setattr(bag_cli, '_info', lambda args: 1 / 0)
    code, _, err = cli(['bag', 'info', 'x'], capsys)
    assert code == 1 and one_error_line(err) and 'ZeroDivisionError' in err


def test_no_traceback_in_a_real_process(tmp_path):
    """The console script itself (not only main()) ends bad input in one line."""
    bad = tmp_path / 'bad.yaml'
    bad.write_bytes(LATIN1)
    proc = subprocess.run([sys.executable, '-m', 'piezo_narx_ros.cli.main', 'bringup', str(bad)],
                          capture_output=True, text=True, cwd=REPO, timeout=60)
    assert proc.returncode == 2 and proc.stderr.count('\n') == 1, proc.stderr
    assert 'Traceback' not in proc.stderr


# ------------------------------------------------------------------- argument errors (issue 13)
@pytest.mark.parametrize('argv, message', [
    (['evaluate', '{model}', '{good}', '--max-lag', '0'], '--max-lag must be >= 1, got 0'),
    (['evaluate', '{model}', '{good}', '--max-outside', '1'],
     r'--max-outside must be in \[0, 1\), got 1.0'),
    (['evaluate', '{model}', '{good}', '--noise-order', '500'],
     r'--noise-order must be in \[0, 200\], got 500'),
    (['fit', '--preset', 'paper',
      '{good}', '--out', '{tmp}/o', '--ny', '1.5'], "--ny: not a lag range: '1.5'"),
    (['fit', '--preset', 'paper', '{good}', '--out', '{tmp}/o', '--config', '{cfg}'],
     r'ny: lag orders must be integers, got \[1, 2.5\]'),
    (['fit', '--preset', 'paper', '{good}', '--out', '{tmp}/o', '--fs', '-1'],
     '--fs must be a positive number of Hz, got -1.0'),
    (['fit', '--preset', 'paper',
      '{good}', '--out', '{good}'], 'good.npz: exists and is not a directory'),
    (['simulate', '--seconds', '1', '--out', '{tmp}/missing/s.npz'],
     '--out directory .*missing does not exist'),
    (['simulate', '--seconds', '1', '--seed', '-3', '--out', '{tmp}/s.npz'],
     '--seed must be a non-negative integer, got -3'),
    (['bag', 'export', '{bag}', '--out', '{tmp}/x.txt'], '--out must end in .npz or .csv'),
    (['bringup', 'sim.launch.yaml', '-p', 'nobody.fs=1'],
     '--param names node.s. not in .*sim.launch.yaml: nobody'),
    (['bringup', 'rig.launch.yaml', '-p', 'fake_rig.seed=1'],
     '--param fake_rig.seed: fake_rig takes no parameters'),
])
def test_argument_errors_are_one_line_naming_the_option(tmp_path, good_npz, toy_model, capsys,
                                                        argv, message):
    from piezo_narx_ros.bag.writer import write_uy_bag
    u, y = record()
    write_uy_bag(tmp_path / 'bag', u, y, 2000.0)
    (tmp_path / 'c.yaml').write_text('ny: [1, 2.5]\n')
    argv = [a.format(good=good_npz, tmp=tmp_path, model=toy_model, bag=tmp_path / 'bag',
                     cfg=tmp_path / 'c.yaml') for a in argv]
    code, out, err = cli(argv, capsys)
    assert code == 2 and one_error_line(err), err
    assert re.search(message, err), err
    assert not (tmp_path / 'o').exists() and not (tmp_path / 's.npz').exists()
