"""
Reading a model file's JSON document and weight arrays: the typed getters every family uses.

model_io reads the format envelope (format, version, units, ranges, sha256) with them, and each
family reads its own blocks (structure, normalisation, training, weight arrays) with them, so a
malformed field gives the same one-line ModelFileError whichever part reads it.
"""
import math

import numpy as np

from ..errors import ModelFileError


def get(doc, dotted, name, types):
    """
    Return the value at a dotted key of the JSON document, type-checked.

    name: the file, for the message; types: accepted Python types (bool only when listed).
    """
    cur = doc
    for part in dotted.split('.'):
        if not isinstance(cur, dict) or part not in cur:
            raise ModelFileError(f'{name}: missing key {dotted!r}')
        cur = cur[part]
    if not isinstance(cur, types) or isinstance(cur, bool) and bool not in types:
        raise ModelFileError(f'{name}: key {dotted!r} has the wrong type ({type(cur).__name__})')
    return cur


def get_int(doc, dotted, name, minimum):
    """Return the integer at a dotted key, at least `minimum`."""
    v = get(doc, dotted, name, (int,))
    if v < minimum:
        raise ModelFileError(f'{name}: key {dotted!r} must be >= {minimum}, got {v}')
    return v


def training_block(doc):
    """Return the document's 'training' object, or {} when it is missing or not an object."""
    training = doc.get('training')
    return training if isinstance(training, dict) else {}


def weight_array(arrays, key, shape, wpath):
    """Return the float64 array `key` of the weights file `wpath`, of `shape`, all finite."""
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


def range_of(doc, key, name):
    """(min, max) at doc[key]: finite numbers, min <= max; None when absent or null."""
    v = doc.get(key)
    if v is None:
        return None
    if (not isinstance(v, list) or len(v) != 2
            or not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in v)
            or not all(math.isfinite(x) for x in v) or v[0] > v[1]):
        raise ModelFileError(f'{name}: key {key!r} must be [min, max] (finite, min <= max) or '
                             f'null, got {v!r}')
    return (float(v[0]), float(v[1]))


def channel_counts(doc, name):
    """(n_in, n_out) of a model file: structure.n_in / n_out, 1 each when absent (one axis)."""
    structure = doc.get('structure') if isinstance(doc.get('structure'), dict) else {}
    n_in = get_int(doc, 'structure.n_in', name, 1) if 'n_in' in structure else 1
    n_out = get_int(doc, 'structure.n_out', name, 1) if 'n_out' in structure else 1
    return n_in, n_out
