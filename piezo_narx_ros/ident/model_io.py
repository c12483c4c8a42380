"""
Model files: a JSON document plus its weights in an .npz beside it (same stem).

Loading never executes code from the files (json + np.load(allow_pickle=False)) and never imports
torch. The JSON records the structure, activation, normalisation, sample rate, units, the input and
output ranges seen in training, the training settings, and (when given) the data the model was
fitted on, its metrics and test results. The .npz holds every weight array, so a save/load round
trip is bit-exact; the JSON also stores the .npz's SHA-256 so a changed or truncated weights file
is caught.
"""
import hashlib
import json
import math
import os
from pathlib import Path

import numpy as np

from ..errors import ConfigError, DataError, ModelFileError
from ..npzfile import read_npz
from .arx import ARXModel
from .base import check_parameters
from .hysteresis import HysteresisNARX
from .narx import NARXNetwork

FORMAT = 'piezo_narx_ros/model'
#: Newest format this reader understands. Version 2 added the hysteresis_narx kind; NARX and ARX
#: files are still written as version 1 so that older readers keep loading them.
FORMAT_VERSION = 2
_MODEL_TYPES = (NARXNetwork, ARXModel, HysteresisNARX)
# Weight arrays of a HysteresisNARX, in the order of its parameter vector.
_HNARX_PARTS = ('W1', 'b1', 'w2', 'c', 'duhem', 'drive', 'g', 'a', 'b', 'y_off')
UNITS = {'input': 'V', 'output': 'm', 'time': 's', 'fs': 'Hz'}


def _jsonable(x):
    """Convert numpy scalars/arrays and tuples inside dicts/lists to plain JSON types."""
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return _jsonable(x.tolist())
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def _weights_of(model):
    if isinstance(model, HysteresisNARX):
        from .hysteresis_kernels import layout
        lay, _ = layout(model.hidden, model.n_inputs, model.n_duhem, len(model.creep_taus),
                        model.na, model.nb)
        out = {k: model.theta_[lo:hi] for k, (lo, hi) in lay.items()}
        out['W1'] = out['W1'].reshape(model.hidden, model.n_inputs)
        out['duhem'] = out['duhem'].reshape(model.n_duhem, 6)
        out['radii'] = model.radii_
        return out
    if isinstance(model, NARXNetwork):
        return {'W1': model.W1, 'b1': model.b1, 'w2': model.w2, 'b2': np.array([model.b2]),
                'normalisation': model.normalisation}
    return {'a': model.a, 'b': model.b, 'c': np.array([model.c])}


def weights_sha256(model) -> str:
    """
    SHA-256 (hex) of a fitted model's weights.

    Every array save_model writes, by name, with its dtype and shape, so two fits compare bit for
    bit.
    """
    h = hashlib.sha256()
    for name, value in sorted(_weights_of(model).items()):
        arr = np.ascontiguousarray(value)
        h.update(f'{name}:{arr.dtype.str}:{arr.shape};'.encode())
        h.update(arr.tobytes())
    return h.hexdigest()


def _structure_of(model):
    if isinstance(model, HysteresisNARX):
        return {'kind': model.kind, 'hidden': model.hidden, 'n_plays': model.n_plays,
                'n_duhem': model.n_duhem, 'n_lags': model.n_lags, 'na': model.na,
                'nb': model.nb, 'creep_taus': list(model.creep_taus),
                'activation': model.activation, 'nu': model.nu, 'ny': model.ny,
                'n_params': model.n_params}
    if isinstance(model, NARXNetwork):
        return {'kind': 'narx', 'nu': model.nu, 'ny': model.ny, 'hidden': model.hidden,
                'activation': model.activation, 'output': 'linear', 'n_params': model.n_params}
    return {'kind': 'arx', 'na': model.na, 'nb': model.nb, 'nu': model.nu, 'ny': model.ny,
            'fit_intercept': model.fit_intercept, 'n_params': model.n_params}


def save_model(model, path, data=None, metrics=None, tests=None):
    """
    Write ``path`` (.json) and its weights ``path`` with suffix .npz.

    data : provenance of the estimation data (e.g. {'source': ..., 'samples': ...});
    metrics, tests : results to record (JSON-serialisable dicts). None keeps what the model carries
    in ``model.metadata`` (set by load_model). Returns the JSON path.
    """
    path = Path(path)
    if path.suffix != '.json':
        raise ModelFileError(f'model file name must end in .json: {path}')
    if not isinstance(model, _MODEL_TYPES):
        raise ModelFileError(f'cannot save a {type(model).__name__}: not a NARXNetwork, '
                             f'ARXModel or HysteresisNARX')
    if not model._is_fitted():
        raise ModelFileError(f'cannot save {model!r} to {path}: it has no weights (fit it first)')
    meta = dict(getattr(model, 'metadata', None) or {})
    for key, val in (('data', data), ('metrics', metrics), ('tests', tests)):
        if val is not None:
            meta[key] = val
    wpath = path.with_suffix('.npz')
    path.parent.mkdir(parents=True, exist_ok=True)
    # Write to temporary names and rename, so a reader never sees half a file.
    tmp_w = wpath.with_name(wpath.name + '.tmp')
    with open(tmp_w, 'wb') as fh:
        np.savez(fh, **_weights_of(model))
    digest = hashlib.sha256(tmp_w.read_bytes()).hexdigest()
    hnarx = isinstance(model, HysteresisNARX)
    if isinstance(model, NARXNetwork):
        normalisation = dict(zip(('u_mean', 'u_std', 'y_mean', 'y_std'),
                                 model.normalisation.tolist()))
    elif hnarx:
        normalisation = {'u_scale': model.u_scale_, 'y_scale': model.y_scale_}
    else:
        normalisation = None
    if isinstance(model, NARXNetwork):
        training = {'seed': model.seed, 'options': model.training_options,
                    'info': model.training_info_}
    elif hnarx:
        training = {'seed': model.seed, 'options': model.params_dict(),
                    'info': model.training_info_, 'method': 'output-error Levenberg-Marquardt'}
    else:
        training = {'method': 'least squares'}
    doc = {
        'format': FORMAT,
        'format_version': 2 if hnarx else 1,
        'structure': _structure_of(model),
        'normalisation': normalisation,
        'fs': model.fs,
        'units': UNITS,
        'input_range': model.input_range,
        'output_range': model.output_range,
        'weights': {'file': wpath.name, 'sha256': digest,
                    'arrays': {k: list(np.shape(v)) for k, v in _weights_of(model).items()}},
        'training': training,
        'data': meta.get('data'),
        'metrics': meta.get('metrics'),
        'tests': meta.get('tests'),
    }
    tmp_j = path.with_name(path.name + '.tmp')
    tmp_j.write_text(json.dumps(_jsonable(doc), indent=2, allow_nan=False) + '\n')
    os.replace(tmp_w, wpath)
    os.replace(tmp_j, path)
    return path


def _get(doc, dotted, name, types):
    """Value at a dotted key of the JSON document, type-checked."""
    cur = doc
    for part in dotted.split('.'):
        if not isinstance(cur, dict) or part not in cur:
            raise ModelFileError(f'{name}: missing key {dotted!r}')
        cur = cur[part]
    if not isinstance(cur, types) or isinstance(cur, bool) and bool not in types:
        raise ModelFileError(f'{name}: key {dotted!r} has the wrong type ({type(cur).__name__})')
    return cur


def _get_int(doc, dotted, name, minimum):
    v = _get(doc, dotted, name, (int,))
    if v < minimum:
        raise ModelFileError(f'{name}: key {dotted!r} must be >= {minimum}, got {v}')
    return v


def _range(doc, key, name):
    v = doc.get(key)
    if v is None:
        return None
    if (not isinstance(v, list) or len(v) != 2
            or not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in v)
            or not all(math.isfinite(x) for x in v) or v[0] > v[1]):
        raise ModelFileError(f'{name}: key {key!r} must be [min, max] (finite, min <= max) or '
                             f'null, got {v!r}')
    return (float(v[0]), float(v[1]))


def _refuse_constant(token):
    # save_model writes finite numbers only (allow_nan=False); NaN or Infinity in a model file
    # would pass every range and rate check silently.
    raise ValueError(f'{token} is not allowed in a model file (finite numbers only)')


def _read_json(path):
    name = str(path)
    if not path.is_file():
        raise ModelFileError(f'model file not found: {name}')
    try:
        doc = json.loads(path.read_text(encoding='utf-8'), parse_constant=_refuse_constant)
    except ValueError as exc:
        if not isinstance(exc, json.JSONDecodeError):   # from _refuse_constant
            raise ModelFileError(f'{name}: {exc}') from None
        raise ModelFileError(f'{name}: not valid JSON ({exc.msg} at line {exc.lineno} column '
                             f'{exc.colno})') from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ModelFileError(f'{name}: cannot read ({exc})') from None
    if not isinstance(doc, dict):
        raise ModelFileError(f'{name}: top level must be a JSON object')
    if doc.get('format') != FORMAT:
        raise ModelFileError(f'{name}: not a piezo_narx_ros model '
                             f'(format is {doc.get("format")!r}, expected {FORMAT!r})')
    version = _get(doc, 'format_version', name, (int,))
    if version > FORMAT_VERSION:
        raise ModelFileError(f'{name}: format_version {version} is newer than this reader '
                             f'supports ({FORMAT_VERSION}); upgrade piezo_narx_ros')
    if version < 1:
        raise ModelFileError(f'{name}: invalid format_version {version}')
    return doc


def _read_weights(path, doc):
    name = str(path)
    wname = _get(doc, 'weights.file', name, (str,))
    if not wname or Path(wname).name != wname:
        raise ModelFileError(f'{name}: weights.file must be a plain file name, got {wname!r}')
    wpath = path.parent / wname
    if not wpath.is_file():
        raise ModelFileError(f'weights file not found: {wpath} (named by {name})')
    raw = wpath.read_bytes()
    digest = doc['weights'].get('sha256')
    if digest is not None and hashlib.sha256(raw).hexdigest() != digest:
        raise ModelFileError(f'{wpath}: contents do not match the SHA-256 recorded in {name} '
                             f'(changed or truncated)')
    return wpath, read_npz(wpath, error=ModelFileError)


def _array(arrays, key, shape, wpath):
    if key not in arrays:
        raise ModelFileError(f'{wpath}: missing weight array {key!r}')
    a = arrays[key]
    if a.dtype != np.float64:
        raise ModelFileError(f'{wpath}: weight array {key!r} has dtype {a.dtype}, '
                             'expected float64')
    if a.shape != tuple(shape):
        raise ModelFileError(f'{wpath}: weight array {key!r} has shape {a.shape}, '
                             f'expected {tuple(shape)}')
    if not np.all(np.isfinite(a)):
        raise ModelFileError(f'{wpath}: weight array {key!r} contains NaN or infinite values')
    return a


def _load_hnarx(doc, name, arrays, wpath, fs):
    """Return a HysteresisNARX from its JSON document and weight arrays (see save_model)."""
    struct = _get(doc, 'structure', name, (dict,))
    keys = ('hidden', 'n_plays', 'n_duhem', 'n_lags', 'na', 'nb', 'creep_taus')
    missing = [k for k in keys if k not in struct]
    if missing:
        raise ModelFileError(f'{name}: missing key {"structure." + missing[0]!r}')
    try:
        values = check_parameters(HysteresisNARX, {k: struct[k] for k in keys})
    except ConfigError as exc:
        raise ModelFileError(f'{name}: structure.{exc}') from None
    act = _get(doc, 'structure.activation', name, (str,))
    if act != HysteresisNARX.activation:
        raise ModelFileError(f'{name}: unsupported activation {act!r} (only logistic)')
    if fs is None or not math.isfinite(fs):
        raise ModelFileError(f'{name}: a hysteresis_narx model needs a finite fs (its creep '
                             f'time constants are in seconds), got {fs!r}')
    u_scale = _get(doc, 'normalisation.u_scale', name, (int, float))
    y_scale = _get(doc, 'normalisation.y_scale', name, (int, float))
    if not (math.isfinite(u_scale) and math.isfinite(y_scale) and u_scale > 0 and y_scale > 0):
        raise ModelFileError(f'{name}: normalisation u_scale and y_scale must be finite and > 0')
    training = doc.get('training') if isinstance(doc.get('training'), dict) else {}
    seed = training.get('seed', 0)
    model = HysteresisNARX(**values, seed=seed if isinstance(seed, int) and seed >= 0 else 0)
    from .hysteresis_kernels import layout
    lay, _ = layout(model.hidden, model.n_inputs, model.n_duhem, len(model.creep_taus),
                    model.na, model.nb)
    shapes = {k: (hi - lo,) for k, (lo, hi) in lay.items()}
    shapes['W1'] = (model.hidden, model.n_inputs)
    shapes['duhem'] = (model.n_duhem, 6)
    theta = np.concatenate([_array(arrays, k, shapes[k], wpath).ravel() for k in _HNARX_PARTS])
    radii = _array(arrays, 'radii', (model.n_plays,), wpath)
    model.set_theta(theta, u_scale, y_scale, radii, fs)
    if np.any(np.abs(model.output_poles) >= 1.0):
        raise ModelFileError(f'{wpath}: the output dynamics are unstable (a root of A(q) has '
                             f'modulus {np.max(np.abs(model.output_poles)):.4f} >= 1)')
    model.training_info_ = training.get('info') or {}
    return model


def load_model(path):
    """
    Load a model saved by save_model.

    Returns a NARXNetwork, ARXModel or HysteresisNARX ready to simulate.

    Raises ModelFileError (one line naming the file and the problem) on anything malformed.
    """
    path = Path(path)
    name = str(path)
    doc = _read_json(path)
    kind = _get(doc, 'structure.kind', name, (str,))
    if kind not in ('narx', 'arx', HysteresisNARX.kind):
        raise ModelFileError(f'{name}: unknown model kind {kind!r} (expected narx, arx or '
                             f'{HysteresisNARX.kind})')
    fs = doc.get('fs')
    if fs is not None and (not isinstance(fs, (int, float)) or isinstance(fs, bool)
                           or not math.isfinite(fs) or fs <= 0):
        raise ModelFileError(f'{name}: fs must be a positive number of Hz or null, got {fs!r}')
    units = doc.get('units')
    if units is not None and (not isinstance(units, dict) or units.get('input', 'V') != 'V'
                              or units.get('output', 'm') != 'm'):
        raise ModelFileError(f'{name}: units must be input V and output m, got {units!r}')
    in_range, out_range = _range(doc, 'input_range', name), _range(doc, 'output_range', name)
    wpath, arrays = _read_weights(path, doc)
    try:
        if kind == HysteresisNARX.kind:
            model = _load_hnarx(doc, name, arrays, wpath, fs)
        elif kind == 'narx':
            nu = _get_int(doc, 'structure.nu', name, 0)
            ny = _get_int(doc, 'structure.ny', name, 1)
            hidden = _get_int(doc, 'structure.hidden', name, 1)
            act = _get(doc, 'structure.activation', name, (str,))
            if act != NARXNetwork.activation:
                raise ModelFileError(f'{name}: unsupported activation {act!r} (only logistic)')
            training = doc.get('training') if isinstance(doc.get('training'), dict) else {}
            seed = training.get('seed', 0)
            model = NARXNetwork(nu, ny, hidden, seed=seed if isinstance(seed, int) else 0)
            d = nu + 1 + ny
            model.set_weights(_array(arrays, 'W1', (hidden, d), wpath),
                              _array(arrays, 'b1', (hidden,), wpath),
                              _array(arrays, 'w2', (hidden,), wpath),
                              _array(arrays, 'b2', (1,), wpath)[0],
                              _array(arrays, 'normalisation', (4,), wpath))
            model.training_info_ = training.get('info') or {}
        else:
            na = _get_int(doc, 'structure.na', name, 1)
            nb = _get_int(doc, 'structure.nb', name, 0)
            icpt = _get(doc, 'structure.fit_intercept', name, (bool,))
            model = ARXModel(na, nb, fit_intercept=icpt)
            model.set_coefficients(_array(arrays, 'a', (na,), wpath),
                                   _array(arrays, 'b', (nb + 1,), wpath),
                                   _array(arrays, 'c', (1,), wpath)[0])
    except DataError as exc:  # e.g. a non-positive std in the normalisation
        raise ModelFileError(f'{wpath}: {exc}') from None
    model.fs = float(fs) if fs is not None else None
    model.input_range, model.output_range = in_range, out_range
    model.metadata = {k: doc.get(k) for k in ('data', 'metrics', 'tests')}
    model.source = name
    return model
