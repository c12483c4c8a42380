"""
Model files: a JSON document plus its weights in an .npz beside it (same stem).

Loading never executes code from the files (json + np.load(allow_pickle=False)) and never imports
torch. The JSON records the structure, activation, normalisation, sample rate, units, the input and
output ranges seen in training, the training settings, and (when given) the data the model was
fitted on, its metrics and test results. The .npz holds every weight array, so a save/load round
trip is bit-exact; the JSON also stores the .npz's SHA-256 so a changed or truncated weights file
is caught.

This module owns that envelope (format, version, units, ranges, checksum, atomic write, safe
read); each family owns its blocks (structure, normalisation, training, weight arrays and
reading them back: `file_document`, `file_weights`, `from_file_document`) and is found by the
document's structure.kind in the registry (ident.families).
"""
import hashlib
import io
import json
import math
from pathlib import Path

import numpy as np

from ..errors import DataError, ModelFileError
from ..files import write_files_atomic
from ..npzfile import read_npz
from . import families
from . import document
from .document import get as _get

FORMAT = 'piezo_narx_ros/model'
#: Newest format this reader understands. Version 2 added the hysteresis_narx kind, version 3
#: several axes (top-level `inputs` / `outputs` names, structure.n_in / n_out); a file is written
#: with its family's `file_format_version` (NARX and ARX: 1), raised to 3 only for a model with
#: several inputs or outputs, so that older readers keep loading what they know.
FORMAT_VERSION = 3
#: The first format version with several axes.
MULTI_AXIS_VERSION = 3
UNITS = {'input': 'V', 'output': 'm', 'time': 's', 'fs': 'Hz'}
# What a model file may make a reader hold, whatever it declares: far above any model fitted here
# (the largest, an ensemble of envelope models, is well under 1 MB), far below a machine's memory.
MAX_JSON_BYTES = 16 * 2**20
MAX_WEIGHT_BYTES = 256 * 2**20
# Integers in a model file are counts, lags and seeds: more digits than this is not one of them.
MAX_INT_DIGITS = 30


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


def weights_sha256(model) -> str:
    """
    SHA-256 (hex) of a fitted model's weights.

    Every array save_model writes, by name, with its dtype and shape, so two fits compare bit for
    bit.
    """
    h = hashlib.sha256()
    for name, value in sorted(model.file_weights().items()):
        arr = np.ascontiguousarray(value)
        h.update(f'{name}:{arr.dtype.str}:{arr.shape};'.encode())
        h.update(arr.tobytes())
    return h.hexdigest()


def save_model(model, path, data=None, metrics=None, tests=None, start=None):
    """
    Write ``path`` (.json) and its weights ``path`` with suffix .npz.

    data : provenance of the estimation data (e.g. {'source': ..., 'samples': ...});
    metrics, tests : results to record (JSON-serialisable dicts); start : the start policy the
    model's users follow by default, {'policy': 'rest' | 'offset' | 'state', 'window_samples': N}
    (ident/state/start.py; `check_start`). None keeps what the model carries in
    ``model.metadata`` (set by load_model). Returns the JSON path.
    """
    path = Path(path)
    if path.suffix != '.json':
        raise ModelFileError(f'model file name must end in .json: {path}')
    cls = families.family(getattr(model, 'kind', None))
    if cls is None or not isinstance(model, cls):
        known = ', '.join(c.__name__ for c in families.registered_families().values())
        raise ModelFileError(f'cannot save a {type(model).__name__}: not a model of a known '
                             f'family ({known})')
    if not model._is_fitted():
        raise ModelFileError(f'cannot save {model!r} to {path}: it has no weights (fit it first)')
    meta = dict(getattr(model, 'metadata', None) or {})
    for key, val in (('data', data), ('metrics', metrics), ('tests', tests), ('start', start)):
        if val is not None:
            meta[key] = val
    if meta.get('start') is not None:
        meta['start'] = check_start(meta['start'], str(path), model.fs)
    wpath = path.with_suffix('.npz')
    path.parent.mkdir(parents=True, exist_ok=True)
    weights = model.file_weights()
    buf = io.BytesIO()
    np.savez(buf, **weights)
    raw = buf.getvalue()
    digest = hashlib.sha256(raw).hexdigest()
    blocks = model.file_document()
    multi = is_multi_axis(model)
    structure = dict(blocks['structure'])
    if multi:
        structure.update(n_in=int(model.n_in), n_out=int(model.n_out))
    doc = {
        'format': FORMAT,
        'format_version': (max(model.file_format_version, MULTI_AXIS_VERSION) if multi
                           else model.file_format_version),
        **({'inputs': list(model.inputs), 'outputs': list(model.outputs)} if multi else {}),
        'structure': structure,
        'normalisation': blocks['normalisation'],
        'fs': model.fs,
        'units': UNITS,
        'input_range': model.input_range,
        'output_range': model.output_range,
        'weights': {'file': wpath.name, 'sha256': digest,
                    'arrays': {k: list(np.shape(v)) for k, v in weights.items()}},
        'training': blocks['training'],
        'data': meta.get('data'),
        'metrics': meta.get('metrics'),
        'tests': meta.get('tests'),
        **({'start': meta['start']} if meta.get('start') is not None else {}),
    }
    # Fresh temporary files renamed over the targets (files.write_files_atomic): a reader never
    # sees half a file, and a name planted beside them (model.json.tmp) is never followed.
    write_files_atomic({wpath: raw,
                        path: json.dumps(_jsonable(doc), indent=2, allow_nan=False) + '\n'})
    return path


def check_start(start, name: str, fs=None) -> dict:
    """
    Return a model file's start block checked: {'policy', 'window_samples', 'window_s'}.

    policy: one of ident.state.start.START_POLICIES; window_samples: the measured samples it was
    chosen with (an integer >= 0); window_s their duration at the model's rate fs (Hz, when
    known). ModelFileError naming the file otherwise.
    """
    from .state.start import START_POLICIES
    if not isinstance(start, dict) or start.get('policy') not in START_POLICIES:
        raise ModelFileError(f'{name}: start must be {{"policy": one of '
                             f'{", ".join(START_POLICIES)}, "window_samples": N}}, got '
                             f'{str(start)[:80]!r}')
    n = start.get('window_samples')
    if isinstance(n, bool) or not isinstance(n, int) or not 0 <= n <= 10 ** 9:
        raise ModelFileError(f'{name}: start.window_samples must be an integer >= 0, got '
                             f'{str(n)[:40]!r}')
    out = {'policy': start['policy'], 'window_samples': n}
    if fs:
        out['window_s'] = n / float(fs)
    return out


def is_multi_axis(model) -> bool:
    """Return True when the model has several inputs or outputs (a format-3 model file)."""
    return int(getattr(model, 'n_in', 1)) > 1 or int(getattr(model, 'n_out', 1)) > 1


def _channel_names(doc, name):
    """Return the (inputs, outputs) names of a model file; ('u',), ('y',) for a one-axis file."""
    if 'inputs' not in doc and 'outputs' not in doc:
        return ('u',), ('y',)
    out = []
    for key in ('inputs', 'outputs'):
        v = doc.get(key)
        if (not isinstance(v, list) or not v or not all(isinstance(x, str) and x for x in v)
                or len(set(v)) != len(v)):
            raise ModelFileError(f'{name}: {key!r} must be a list of distinct channel names, '
                                 f'got {v!r}')
        out.append(tuple(v))
    return out[0], out[1]


def _channel_range(doc, key, name, n):
    """Return a model file's range: [min, max] for one channel, [[min...], [max...]] for n."""
    v = doc.get(key)
    if n == 1 or v is None:
        return document.range_of(doc, key, name)
    ok = (isinstance(v, list) and len(v) == 2
          and all(isinstance(side, list) and len(side) == n for side in v)
          and all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)
                  for side in v for x in side)
          and all(lo <= hi for lo, hi in zip(*v)))
    if not ok:
        raise ModelFileError(f'{name}: key {key!r} must be [[min per channel], [max per '
                             f'channel]] for {n} channels (finite, min <= max), got {v!r}')
    return (tuple(float(x) for x in v[0]), tuple(float(x) for x in v[1]))


class _Refused(ValueError):
    """A value the model file format does not allow (raised while parsing)."""


def _refuse_constant(token):
    # save_model writes finite numbers only (allow_nan=False); NaN or Infinity in a model file
    # would pass every range and rate check silently.
    raise _Refused(f'{token} is not allowed in a model file (finite numbers only)')


def _parse_int(text: str) -> int:
    digits = len(text.lstrip('-'))
    if digits > MAX_INT_DIGITS:
        raise _Refused(f'an integer of {digits} digits is not allowed in a model file (at most '
                       f'{MAX_INT_DIGITS})')
    return int(text)


def _parse_float(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):
        raise _Refused(f'the number {text[:20]}{"..." if len(text) > 20 else ""} does not fit '
                       'a double (finite numbers only)')
    return value


def _read_json(path):
    name = str(path)
    if not path.is_file():
        raise ModelFileError(f'model file not found: {name}')
    try:
        size = path.stat().st_size
        if size > MAX_JSON_BYTES:
            raise ModelFileError(f'{name}: {size} bytes is more than a model file holds (at '
                                 f'most {MAX_JSON_BYTES}); not a model file')
        doc = json.loads(path.read_text(encoding='utf-8'), parse_constant=_refuse_constant,
                         parse_int=_parse_int, parse_float=_parse_float)
    except UnicodeDecodeError:      # e.g. the .npz given instead of the .json
        raise ModelFileError(f'{name}: not a JSON model file (not UTF-8 text)') from None
    except RecursionError:
        raise ModelFileError(f'{name}: nested too deeply to be a model file') from None
    except _Refused as exc:
        raise ModelFileError(f'{name}: {exc}') from None
    except ValueError as exc:
        if not isinstance(exc, json.JSONDecodeError):   # e.g. Python's own integer limit
            raise ModelFileError(f'{name}: not a valid model file ({exc})') from None
        raise ModelFileError(f'{name}: not valid JSON ({exc.msg} at line {exc.lineno} column '
                             f'{exc.colno})') from None
    except OSError as exc:
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
    # Every model file save_model writes carries the checksum: without one the weights cannot
    # be vouched for, so a missing key is refused, not taken as "do not check".
    digest = doc['weights'].get('sha256') if isinstance(doc.get('weights'), dict) else None
    if not isinstance(digest, str):
        raise ModelFileError(f'{name}: weights.sha256 is missing, so its weights cannot be '
                             'verified (every model file fit writes has it; re-save the model)')
    shapes = _declared_shapes(doc, name)
    size = wpath.stat().st_size
    if size > MAX_WEIGHT_BYTES:
        raise ModelFileError(f'{wpath}: {size} bytes is more than the weights of a model hold '
                             f'(at most {MAX_WEIGHT_BYTES})')
    h = hashlib.sha256()
    with open(wpath, 'rb') as fh:
        for block in iter(lambda: fh.read(1 << 20), b''):
            h.update(block)
    if h.hexdigest() != digest:
        raise ModelFileError(f'{wpath}: contents do not match the SHA-256 recorded in {name} '
                             f'(changed or truncated)')
    # Only the arrays the document declares, of the shapes it declares, within the size limit:
    # an extra member that inflates to gigabytes is never decompressed.
    return wpath, read_npz(wpath, error=ModelFileError, shapes=shapes,
                           max_bytes=MAX_WEIGHT_BYTES)


def _declared_shapes(doc, name) -> dict[str, tuple[int, ...]]:
    """{array name: shape} of weights.arrays, each shape a list of non-negative integers."""
    arrays = _get(doc, 'weights.arrays', name, (dict,))
    out = {}
    for key, shape in arrays.items():
        if not (isinstance(shape, list) and len(shape) <= 8 and all(
                isinstance(n, int) and not isinstance(n, bool) and n >= 0 for n in shape)):
            raise ModelFileError(f'{name}: weights.arrays.{key} must be a shape (a list of '
                                 f'non-negative integers), got {shape!r}')
        out[key] = tuple(shape)
    return out


def load_model(path):
    """
    Load a model saved by save_model.

    Returns a model of the family registered for the file's structure.kind (NARXNetwork, ARXModel,
    HysteresisNARX, ...) ready to simulate, with its channel names (inputs, outputs: ('u',),
    ('y',) for a one-axis file). A several-axes file gives a model whose predict/simulate return
    (N, n_out) arrays; a one-axis file one returning (N,).

    Raises ModelFileError (one line naming the file and the problem) on anything malformed.
    """
    path = Path(path)
    name = str(path)
    doc = _read_json(path)
    kind = _get(doc, 'structure.kind', name, (str,))
    cls = families.family(kind)
    if cls is None:
        *head, last = families.kinds()
        known = f'{", ".join(head)} or {last}' if head else last
        raise ModelFileError(f'{name}: unknown model kind {kind!r} (expected {known})')
    fs = doc.get('fs')
    if fs is not None and (not isinstance(fs, (int, float)) or isinstance(fs, bool)
                           or not math.isfinite(fs) or fs <= 0):
        raise ModelFileError(f'{name}: fs must be a positive number of Hz or null, got {fs!r}')
    units = doc.get('units')
    if units is not None and (not isinstance(units, dict) or units.get('input', 'V') != 'V'
                              or units.get('output', 'm') != 'm'):
        raise ModelFileError(f'{name}: units must be input V and output m, got {units!r}')
    inputs, outputs = _channel_names(doc, name)
    n_in, n_out = len(inputs), len(outputs)
    if 'inputs' in doc:
        if doc['format_version'] < MULTI_AXIS_VERSION:
            raise ModelFileError(f'{name}: inputs/outputs names need format_version >= '
                                 f'{MULTI_AXIS_VERSION}, got {doc["format_version"]}')
        for key, n in (('structure.n_in', n_in), ('structure.n_out', n_out)):
            if document.get_int(doc, key, name, 1) != n:
                raise ModelFileError(f'{name}: {key} is {document.get(doc, key, name, (int,))} '
                                     f'but the file names {n} channel(s)')
    in_range = _channel_range(doc, 'input_range', name, n_in)
    out_range = _channel_range(doc, 'output_range', name, n_out)
    wpath, arrays = _read_weights(path, doc)
    try:
        model = cls.from_file_document(doc, arrays, name, wpath, fs)
    except DataError as exc:  # e.g. a non-positive std in the normalisation
        raise ModelFileError(f'{wpath}: {exc}') from None
    if (model.n_in, model.n_out) != (n_in, n_out):
        raise ModelFileError(f'{wpath}: the weights are for {model.n_in} input(s) and '
                             f'{model.n_out} output(s) but {name} names {n_in} and {n_out}')
    if 'inputs' in doc:
        model.inputs, model.outputs = inputs, outputs
        model.output_2d_ = True
    model.fs = float(fs) if fs is not None else None
    model.input_range, model.output_range = in_range, out_range
    model.metadata = {k: doc.get(k) for k in ('data', 'metrics', 'tests')}
    if doc.get('start') is not None:
        model.metadata['start'] = check_start(doc['start'], name, model.fs)
    model.source = name
    return model
