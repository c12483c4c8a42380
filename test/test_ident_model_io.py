"""Model files: exact round trip, provenance, one-line ModelFileError for every malformed case."""
import json
import subprocess
import sys
import zipfile

import numpy as np
import pytest

from piezo_narx_ros.errors import ModelFileError
from piezo_narx_ros.ident.arx.model import ARXModel
from piezo_narx_ros.ident.model_io import FORMAT_VERSION, load_model, save_model
from piezo_narx_ros.ident.narx.model import NARXNetwork


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
    resign(saved)                   # with the checksum of the damaged file, np.load must catch it
    with pytest.raises(ModelFileError, match='not a readable .npz'):
        load_model(saved)


def resign(saved):
    """Record the weights file's present SHA-256 in the model file (as if saved so)."""
    import hashlib
    digest = hashlib.sha256(saved.with_suffix('.npz').read_bytes()).hexdigest()
    edit_json(saved, _set('weights.sha256', digest))


def test_a_model_file_without_its_checksum_is_refused(saved):
    """Issue 45: removing the sha256 key switched the check off."""
    doc = json.loads(saved.read_text())
    del doc['weights']['sha256']
    saved.write_text(json.dumps(doc))
    with pytest.raises(ModelFileError, match='weights.sha256 is missing, so its weights cannot '
                       'be verified'):
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
    resign(saved)                   # the same file loads with its own checksum
    assert np.array_equal(load_model(saved).W1, content['W1'])


def rewrite_weights(saved, **arrays):
    w = saved.with_suffix('.npz')
    with np.load(w) as npz:
        content = {k: npz[k] for k in npz.files}
    content.update(arrays)
    for k in [k for k, v in arrays.items() if v is None]:
        del content[k]
    np.savez(w, **content)
    resign(saved)


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
    resign(saved)
    with pytest.raises(ModelFileError, match='not an .npz file'):
        load_model(saved)
    assert not zipfile.is_zipfile(saved.with_suffix('.npz'))


# ------------------------------------------------- every kind's document, and the envelope family

def _random_hnarx(seed=11, rng=3):
    from test_ident_hysteresis import random_model
    m = random_model(seed=rng, scale=0.5)
    m.seed = seed
    m.input_range, m.output_range = (-90.0, 110.0), (-1e-5, 2e-5)
    m.training_info_ = {'iterations': 7}
    return m


@pytest.fixture
def saved_hnarx(tmp_path):
    return save_model(_random_hnarx(seed=11), tmp_path / 'h.json', data={'source': 'protocol'},
                      metrics={'r2': 0.999}, tests={'passed': False})


def test_each_kinds_document_holds_what_its_loader_and_readers_need(tmp_path, saved_hnarx):
    arx = ARXModel(2, 1).set_coefficients([-1.2, 0.4], [0.1, 0.2], 1e-7)
    arx.fs = 750.0
    doc = json.loads(save_model(arx, tmp_path / 'nested' / 'dir' / 'a.json').read_text())
    assert doc['structure'] == {'kind': 'arx', 'na': 2, 'nb': 1, 'nu': 1, 'ny': 2,
                                'fit_intercept': True, 'n_params': 5}
    assert (doc['normalisation'], doc['training']) == (None, {'method': 'least squares'})
    assert doc['weights']['arrays'] == {'a': [2], 'b': [2], 'c': [1]}
    narx = json.loads(save_model(make_narx(), tmp_path / 'n.json', tests={'phi_ee': True})
                      .read_text())
    assert narx['normalisation'] == {'u_mean': 0.5, 'u_std': 12.3, 'y_mean': 1e-6,
                                     'y_std': 3.3e-6}
    assert narx['training'] == {'seed': 9, 'options': make_narx().training_options,
                                'info': {'fit_seconds': 1.5, 'selected_stage': 'simulation'}}
    assert narx['tests'] == {'phi_ee': True}
    m = _random_hnarx(seed=11)
    h = json.loads(saved_hnarx.read_text())
    assert h['format_version'] == 2
    assert h['structure'] == {'kind': 'hysteresis_narx', 'hidden': 4, 'n_plays': 5,
                              'n_duhem': 2, 'n_lags': 2, 'na': 2, 'nb': 2,
                              'creep_taus': [0.01, 0.5], 'activation': 'logistic',
                              'nu': m.nu, 'ny': m.ny, 'n_params': m.n_params}
    assert h['normalisation'] == {'u_scale': 100.0, 'y_scale': 1e-5}
    assert h['training'] == {'seed': 11, 'options': json.loads(json.dumps(m.params_dict())),
                             'info': {'iterations': 7},
                             'method': 'output-error Levenberg-Marquardt'}
    assert (h['data'], h['metrics'], h['tests']) == ({'source': 'protocol'}, {'r2': 0.999},
                                                     {'passed': False})
    with np.load(saved_hnarx.with_suffix('.npz')) as z:
        assert h['weights']['arrays'] == {k: list(z[k].shape) for k in z.files}
        assert z['W1'].shape == (4, m.n_inputs) and z['duhem'].shape == (2, 6)
        assert z['radii'].shape == (5,)


def test_hnarx_round_trip_is_exact(saved_hnarx):
    from piezo_narx_ros.ident.hysteresis.model import HysteresisNARX
    m = _random_hnarx(seed=11)
    back = load_model(saved_hnarx)
    assert isinstance(back, HysteresisNARX)
    assert np.array_equal(back.theta_, m.theta_) and np.array_equal(back.radii_, m.radii_)
    assert (back.u_scale_, back.y_scale_, back.fs, back.seed) == (100.0, 1e-5, 2000.0, 11)
    assert back.params_dict() == m.params_dict()
    assert back.training_info_ == {'iterations': 7}
    assert back.output_range == (-1e-5, 2e-5) and back.metadata['tests'] == {'passed': False}
    u = 80.0 * np.sin(np.arange(2000) * 0.01)
    assert np.array_equal(back.simulate(u), m.simulate(u))


@pytest.mark.parametrize('change, match', [
    *[(_del(f'structure.{k}'), f"missing key 'structure.{k}'")
      for k in ('hidden', 'n_plays', 'n_duhem', 'n_lags', 'na', 'nb', 'creep_taus')],
    (_set('structure.n_plays', 0), 'structure.*n_plays'),
    (_set('structure.activation', 'tanh'), "unsupported activation 'tanh'"),
    (_del('structure.activation'), "missing key 'structure.activation'"),
    (_set('fs', None), 'needs a finite fs'),
    (_set('normalisation.u_scale', 0.0), 'u_scale and y_scale must be finite and > 0'),
    (_set('normalisation.y_scale', -1e-5), 'u_scale and y_scale must be finite and > 0'),
    (_set('normalisation.y_scale', 'big'), "'normalisation.y_scale' has the wrong type"),
    (_del('normalisation.u_scale'), "missing key 'normalisation.u_scale'"),
])
def test_malformed_hnarx_documents(saved_hnarx, change, match):
    edit_json(saved_hnarx, change)
    with pytest.raises(ModelFileError, match=match) as exc:
        load_model(saved_hnarx)
    assert 'h.json' in str(exc.value) and '\n' not in str(exc.value)


@pytest.mark.parametrize('key', ['W1', 'b1', 'w2', 'c', 'duhem', 'drive', 'g', 'a', 'b', 'y_off',
                                 'radii'])
def test_every_hnarx_weight_array_is_checked(saved_hnarx, key):
    with np.load(saved_hnarx.with_suffix('.npz')) as z:
        shape = z[key].shape
    rewrite_weights(saved_hnarx, **{key: None})
    with pytest.raises(ModelFileError, match=f"missing weight array '{key}'"):
        load_model(saved_hnarx)
    rewrite_weights(saved_hnarx, **{key: np.zeros(shape[:-1] + (shape[-1] + 1,))})
    with pytest.raises(ModelFileError, match=f"'{key}' has shape"):
        load_model(saved_hnarx)


def test_hnarx_seed_training_info_and_stability_when_loading(saved_hnarx):
    edit_json(saved_hnarx, _set('training', {'seed': -3}))     # no info, a bad seed: defaults
    back = load_model(saved_hnarx)
    assert back.seed == 0 and back.training_info_ == {}
    edit_json(saved_hnarx, _set('training', None))
    assert load_model(saved_hnarx).seed == 0
    for a in ([-2.5, 1.6], [-1.0, 0.0]):       # poles outside, and one on, the unit circle
        rewrite_weights(saved_hnarx, a=np.array(a))
        with pytest.raises(ModelFileError, match='h.npz: the output dynamics are unstable'):
            load_model(saved_hnarx)


def test_weights_digest_follows_every_weight(saved_hnarx):
    from piezo_narx_ros.ident.model_io import weights_sha256
    m = make_narx()
    digest = weights_sha256(m)
    assert len(digest) == 64 and int(digest, 16) >= 0
    assert weights_sha256(make_narx()) == digest
    assert weights_sha256(load_model(save_model(m, saved_hnarx.parent / 'n.json'))) == digest
    for name in ('W1', 'b1', 'w2', 'normalisation'):
        other = make_narx()
        getattr(other, name).flat[0] = np.nextafter(getattr(other, name).flat[0], np.inf)
        assert weights_sha256(other) != digest, name
    h = load_model(saved_hnarx)
    assert weights_sha256(h) == weights_sha256(_random_hnarx())
    assert weights_sha256(h) != weights_sha256(_random_hnarx(rng=4))


@pytest.mark.parametrize('change, loads', [
    (_set('fs', 0.5), True), (_set('fs', 0), False), (_set('fs', True), False),
    (_set('fs', '2000'), False), (_set('format_version', FORMAT_VERSION), True),
    (_set('units', {'input': 'V'}), True), (_set('units', {'output': 'm'}), True),
    (_set('units', {'input': 'V', 'output': 'um'}), False), (_set('units', 'SI'), False),
    (_set('input_range', [1.0, 1.0]), True), (_set('input_range', [2.0, 1.0]), False),
    (_set('input_range', [True, 2.0]), False), (_set('output_range', [0.0, 1e400]), False),
    (_set('output_range', None), True),
])
def test_document_fields_accepted_and_refused_at_their_limits(saved, change, loads):
    edit_json(saved, change)
    if loads:
        load_model(saved)
        return
    with pytest.raises(ModelFileError, match='model.json'):
        load_model(saved)


def test_an_order_of_zero_passes_the_order_check(saved):
    # nu = 0 is a valid order (not for these weights: refused on their shape, past that check).
    edit_json(saved, _set('structure.nu', 0))
    with pytest.raises(ModelFileError, match="'W1' has shape"):
        load_model(saved)


def test_non_finite_numbers_in_a_model_file_are_refused(saved):
    saved.write_text(saved.read_text().replace('"fs": 2000.0', '"fs": NaN'))
    with pytest.raises(ModelFileError, match='NaN is not allowed in a model file'):
        load_model(saved)


def test_numpy_values_in_metadata_are_written_as_json(tmp_path):
    path = save_model(make_narx(), tmp_path / 'm.json',
                      metrics={'r2': np.float64(0.5), 'per_lag': np.array([1.0, np.nan]),
                               'n': np.int64(3), 'pair': (1, 2)})
    metrics = json.loads(path.read_text())['metrics']
    assert metrics == {'r2': 0.5, 'per_lag': [1.0, None], 'n': 3, 'pair': [1, 2]}


@pytest.mark.parametrize('change', [
    _del('structure.ny'), _set('structure.hidden', 'five'), _del('structure.activation'),
    _set('output_range', [3.0, 1.0]), _set('weights.file', 7)])
def test_narx_document_errors_name_the_file(saved, change):
    edit_json(saved, change)
    with pytest.raises(ModelFileError, match='model.json: '):
        load_model(saved)


@pytest.mark.parametrize('arrays', [{'b2': np.zeros(2)}, {'normalisation': np.zeros(3)}])
def test_narx_weight_errors_name_the_weights_file(saved, arrays):
    rewrite_weights(saved, **arrays)
    with pytest.raises(ModelFileError, match='model.npz: weight array'):
        load_model(saved)


@pytest.mark.parametrize('change, arrays', [
    (_del('structure.na'), {}), (_set('structure.nb', -1), {}),
    (_set('structure.fit_intercept', 1), {}),
    (None, {'a': np.zeros(3)}), (None, {'b': np.zeros(1)}), (None, {'c': np.zeros(2)})])
def test_arx_errors_name_the_file(tmp_path, change, arrays):
    arx = ARXModel(2, 1).set_coefficients([-1.2, 0.4], [0.1, 0.2])
    path = save_model(arx, tmp_path / 'a.json')
    if change:
        edit_json(path, change)
    if arrays:
        rewrite_weights(path, **arrays)
    with pytest.raises(ModelFileError, match='a.npz: weight array' if arrays else 'a.json: '):
        load_model(path)


@pytest.mark.parametrize('key', ['W1', 'radii'])
def test_hnarx_weight_errors_name_the_weights_file(saved_hnarx, key):
    rewrite_weights(saved_hnarx, **{key: np.zeros(1)})
    with pytest.raises(ModelFileError, match=f"h.npz: weight array '{key}'"):
        load_model(saved_hnarx)


def test_smallest_orders_scales_and_what_a_load_restores(tmp_path):
    # The smallest valid orders load (ny = hidden = na = 1, nb = 0); a NARX keeps its seed (0
    # when the file has none), a model its source path and fs (None when the file has none);
    # an ARX without intercept stays without; an hnarx input scale below 1 V is valid.
    rng = np.random.default_rng(1)
    narx = NARXNetwork(0, 1, 1, seed=5).set_weights(rng.normal(size=(1, 2)), [0.1], [0.2], 0.3,
                                                    (0, 1, 0, 1))
    path = save_model(narx, tmp_path / 'n.json')
    back = load_model(path)
    assert (back.nu, back.ny, back.hidden, back.seed, back.fs) == (0, 1, 1, 5, None)
    assert back.source == str(path)
    edit_json(path, _set('training', None))
    assert load_model(path).seed == 0
    for training in ({'options': {}}, {'seed': 'x'}, {'seed': 1.5}):   # none, or not an integer
        edit_json(path, _set('training', training))
        assert load_model(path).seed == 0
    arx = ARXModel(1, 0, fit_intercept=False).set_coefficients([-0.5], [2.0])
    back = load_model(save_model(arx, tmp_path / 'a.json'))
    assert (back.na, back.nb, back.fit_intercept) == (1, 0, False)
    h = _random_hnarx()
    h.u_scale_ = 0.5
    assert load_model(save_model(h, tmp_path / 'h.json')).u_scale_ == 0.5
    edit_json(tmp_path / 'h.json', _set('normalisation.y_scale', 0.0))
    with pytest.raises(ModelFileError, match='u_scale and y_scale must be finite and > 0'):
        load_model(tmp_path / 'h.json')


# ------------------------------------------------- the family registry

def register_toy_family(monkeypatch):
    """Register (for this test only) a family model_io has never heard of: y = k u."""
    from piezo_narx_ros.ident import base, document

    monkeypatch.setattr(base, '_FAMILIES', dict(base._FAMILIES))

    @base.register_family
    class Gain(base.DynamicModel):
        kind = 'test_gain'
        nu, ny = 0, 1
        file_format_version = 2

        def __init__(self, k=None):
            self.k = k

        def _is_fitted(self):
            return self.k is not None

        def file_document(self):
            return {'structure': {'kind': self.kind}, 'normalisation': None,
                    'training': {'method': 'none'}}

        def file_weights(self):
            return {'k': np.array([self.k])}

        @classmethod
        def from_file_document(cls, doc, arrays, name, wpath, fs):
            return cls(float(document.weight_array(arrays, 'k', (1,), wpath)[0]))

    return Gain


def test_a_new_family_registers_itself_and_model_io_saves_and_loads_it(tmp_path, monkeypatch):
    # The toy family owns its document and is found by its kind; model_io keeps the envelope
    # (checksum, ranges, units, version).
    from piezo_narx_ros.ident import base

    Gain = register_toy_family(monkeypatch)
    g = Gain(2.5e-7)
    g.fs, g.output_range = 2000.0, (-1e-5, 1e-5)
    path = save_model(g, tmp_path / 'g.json')
    back = load_model(path)
    assert isinstance(back, Gain) and back.k == 2.5e-7 and back.fs == 2000.0
    assert back.output_range == (-1e-5, 1e-5) and back.source == str(path)
    assert json.loads(path.read_text())['format_version'] == 2
    rewrite_weights(path, k=np.zeros(2))
    with pytest.raises(ModelFileError, match="g.npz: weight array 'k' has shape"):
        load_model(path)
    edit_json(path, _set('structure.kind', 'other'))
    with pytest.raises(ModelFileError, match="unknown model kind 'other' .*test_gain"):
        load_model(path)
    with pytest.raises(TypeError, match="'test_gain' is already registered"):
        base.register_family(type('Gain', (base.DynamicModel,), {'kind': 'test_gain'}))
    with pytest.raises(TypeError, match='not a DynamicModel with its own kind'):
        base.register_family(type('NoKind', (base.DynamicModel,), {}))


def test_only_models_of_a_registered_family_are_saved(tmp_path):
    class Unknown:
        kind = 'narx'     # claims a known kind without being that family

    with pytest.raises(ModelFileError, match='cannot save a Unknown: not a model of a known '
                                             'family .*NARXNetwork'):
        save_model(Unknown(), tmp_path / 'u.json')
