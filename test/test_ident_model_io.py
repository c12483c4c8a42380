"""Model files: exact round trip, provenance, one-line ModelFileError for every malformed case."""
import json
import subprocess
import sys
import zipfile

import numpy as np
import pytest

from piezo_narx_ros.errors import ModelFileError
from piezo_narx_ros.ident.arx import ARXModel
from piezo_narx_ros.ident.model_io import FORMAT_VERSION, load_model, save_model
from piezo_narx_ros.ident.narx import NARXNetwork


def make_narx():
    rng = np.random.default_rng(0)
    m = NARXNetwork(3, 2, 5, seed=9).set_weights(rng.normal(size=(5, 6)), rng.normal(size=5),
                                                 rng.normal(size=5), 0.123456789012345,
                                                 (0.5, 12.3, 1e-6, 3.3e-6))
    m.fs, m.input_range, m.output_range = 2000.0, (-100.0, 100.0), (-2e-5, 3e-5)
    m.training_info_ = {'fit_seconds': 1.5, 'selected_stage': 'simulation'}
    return m


@pytest.fixture
def saved(tmp_path):
    path = save_model(make_narx(), tmp_path / 'model.json',
                      data={'source': 'bags/sine.mcap', 'samples': 25000},
                      metrics={'r2_simulate': 0.99991}, tests={'phi_ee': True})
    return path


def test_narx_round_trip_is_exact(saved):
    m = make_narx()
    assert saved.with_suffix('.npz').is_file()
    back = load_model(saved)
    assert isinstance(back, NARXNetwork)
    for name in ('W1', 'b1', 'w2', 'normalisation'):
        assert np.array_equal(getattr(m, name), getattr(back, name))
    assert back.b2 == m.b2
    assert (back.nu, back.ny, back.hidden, back.fs) == (3, 2, 5, 2000.0)
    assert back.input_range == (-100.0, 100.0) and back.output_range == (-2e-5, 3e-5)
    assert back.metadata['data'] == {'source': 'bags/sine.mcap', 'samples': 25000}
    assert back.metadata['metrics'] == {'r2_simulate': 0.99991}
    assert back.training_info_['selected_stage'] == 'simulation'
    u = np.sin(np.arange(500) * 0.05) * 50
    assert np.array_equal(back.simulate(u), m.simulate(u))
    doc = json.loads(saved.read_text())
    assert doc['format_version'] == 1   # NARX/ARX stay at version 1 for older readers
    assert doc['structure'] == {'kind': 'narx', 'nu': 3, 'ny': 2, 'hidden': 5,
                                'activation': 'logistic', 'output': 'linear', 'n_params': 41}
    assert doc['units']['input'] == 'V' and doc['units']['output'] == 'm'


def test_arx_round_trip_is_exact(tmp_path):
    m = ARXModel(2, 3).set_coefficients([-1.2, 0.4], [0.1, 0.2, 0.3, 0.4], 1e-7)
    m.fs = 750.0
    back = load_model(save_model(m, tmp_path / 'arx.json'))
    assert isinstance(back, ARXModel)
    assert np.array_equal(back.a, m.a) and np.array_equal(back.b, m.b) and back.c == m.c
    assert (back.na, back.nb, back.fs, back.fit_intercept) == (2, 3, 750.0, True)
    # resaving a loaded model keeps the metadata it carries
    back.metadata['data'] = {'source': 'x.npz'}
    again = load_model(save_model(back, tmp_path / 'again.json'))
    assert again.metadata['data'] == {'source': 'x.npz'}


def test_loading_does_not_import_torch(saved):
    code = ('import sys\nfrom piezo_narx_ros.ident.model_io import load_model\n'
            f'm = load_model({str(saved)!r})\nm.simulate([0.0] * 10)\n'
            "print('torch' in sys.modules)")
    out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == 'False'


def test_save_rejects_bad_requests(tmp_path):
    with pytest.raises(ModelFileError, match='must end in .json'):
        save_model(make_narx(), tmp_path / 'model.txt')
    with pytest.raises(ModelFileError, match='no weights'):
        save_model(NARXNetwork(), tmp_path / 'm.json')


def edit_json(path, change):
    doc = json.loads(path.read_text())
    change(doc)
    path.write_text(json.dumps(doc))


def _del(dotted):
    def change(doc):
        *head, last = dotted.split('.')
        for part in head:
            doc = doc[part]
        del doc[last]
    return change


def _set(dotted, value):
    def change(doc):
        *head, last = dotted.split('.')
        for part in head:
            doc = doc[part]
        doc[last] = value
    return change


@pytest.mark.parametrize('change, match', [
    (_set('format_version', FORMAT_VERSION + 1), 'newer than this reader'),
    (_set('format_version', 0), 'invalid format_version 0'),
    (_set('format_version', '1'), "'format_version' has the wrong type"),
    (_del('format_version'), "missing key 'format_version'"),
    (_set('format', 'something/else'), 'not a piezo_narx_ros model'),
    (_del('structure'), "missing key 'structure.kind'"),
    (_del('structure.hidden'), "missing key 'structure.hidden'"),
    (_set('structure.hidden', 6), "'W1' has shape \\(5, 6\\), expected \\(6, 6\\)"),
    (_set('structure.nu', -1), "'structure.nu' must be >= 0"),
    (_set('structure.kind', 'lstm'), "unknown model kind 'lstm'"),
    (_set('structure.activation', 'relu'), "unsupported activation 'relu'"),
    (_set('fs', -5), 'fs must be a positive number'),
    (_set('units', {'input': 'mV', 'output': 'm'}), 'units must be input V'),
    (_set('input_range', [1]), "'input_range' must be \\[min, max\\]"),
    (_set('weights.file', '../elsewhere.npz'), 'plain file name'),
    (_set('weights.file', 'gone.npz'), 'weights file not found: .*gone.npz'),
])
def test_malformed_json_fields(saved, change, match):
    edit_json(saved, change)
    with pytest.raises(ModelFileError, match=match) as exc:
        load_model(saved)
    assert str(saved.name) in str(exc.value) or 'gone.npz' in str(exc.value) \
        or 'model.npz' in str(exc.value)
    assert '\n' not in str(exc.value)


def test_missing_or_invalid_json(tmp_path, saved):
    with pytest.raises(ModelFileError, match='model file not found: .*nothing.json'):
        load_model(tmp_path / 'nothing.json')
    saved.write_text('{"format": "piezo_narx_ros/model", ')
    with pytest.raises(ModelFileError, match='model.json: not valid JSON'):
        load_model(saved)
    saved.write_text('[1, 2]')
    with pytest.raises(ModelFileError, match='top level must be a JSON object'):
        load_model(saved)


def test_missing_weights_file(saved):
    saved.with_suffix('.npz').unlink()
    with pytest.raises(ModelFileError, match='weights file not found: .*model.npz'):
        load_model(saved)


def test_truncated_weights_file(saved):
    w = saved.with_suffix('.npz')
    w.write_bytes(w.read_bytes()[:200])
    with pytest.raises(ModelFileError, match='do not match the SHA-256'):
        load_model(saved)
    edit_json(saved, _set('weights.sha256', None))  # without the checksum np.load must catch it
    with pytest.raises(ModelFileError, match='not a readable .npz'):
        load_model(saved)


def test_tampered_well_formed_weights_with_the_old_hash_are_refused(saved):
    # A valid .npz with the right arrays, shapes and dtypes, but other numbers: only the SHA-256
    # recorded in the JSON can tell (a truncated file numpy refuses anyway).
    w = saved.with_suffix('.npz')
    with np.load(w) as npz:
        content = {k: npz[k] for k in npz.files}
    content['W1'] = content['W1'] * 1.001
    np.savez(w, **content)
    with pytest.raises(ModelFileError, match='do not match the SHA-256') as exc:
        load_model(saved)
    assert 'model.npz' in str(exc.value) and '\n' not in str(exc.value)
    edit_json(saved, _set('weights.sha256', None))   # the same file loads once the hash is gone
    assert np.array_equal(load_model(saved).W1, content['W1'])


def rewrite_weights(saved, **arrays):
    w = saved.with_suffix('.npz')
    with np.load(w) as npz:
        content = {k: npz[k] for k in npz.files}
    content.update(arrays)
    for k in [k for k, v in arrays.items() if v is None]:
        del content[k]
    np.savez(w, **content)
    edit_json(saved, _set('weights.sha256', None))


@pytest.mark.parametrize('arrays, match', [
    ({'b1': np.zeros(4)}, "'b1' has shape \\(4,\\), expected \\(5,\\)"),
    ({'w2': None}, "missing weight array 'w2'"),
    ({'W1': np.full((5, 6), np.nan)}, "'W1' contains NaN"),
    ({'b1': np.zeros(5, dtype=np.float32)}, "'b1' has dtype float32"),
    ({'normalisation': np.array([0.0, -1.0, 0.0, 1.0])}, 'normalisation must be'),
    ({'b1': np.array([{'x': 1}] * 5, dtype=object)}, 'Python objects'),
])
def test_bad_weight_arrays(saved, arrays, match):
    rewrite_weights(saved, **arrays)
    with pytest.raises(ModelFileError, match=match) as exc:
        load_model(saved)
    assert 'model.npz' in str(exc.value) and '\n' not in str(exc.value)


def test_weights_file_that_is_not_a_zip(saved):
    saved.with_suffix('.npz').write_text('not a zip archive')
    edit_json(saved, _set('weights.sha256', None))
    with pytest.raises(ModelFileError, match='not an .npz file'):
        load_model(saved)
    assert not zipfile.is_zipfile(saved.with_suffix('.npz'))
