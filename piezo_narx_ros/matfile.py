"""
One reader for MATLAB .mat files (v4, v5/v6, v7): records that real rigs log.

dSPACE, Simulink Real-Time and Speedgoat write .mat. `read_mat` returns the numeric variables
with MATLAB's shapes (a vector is 1xN or Nx1); a 1x1 struct is flattened into dotted names
(rec.u, rec.y, rec.meta.fs). Everything else is skipped and remembered with what it is (text,
cell arrays, struct arrays, sparse or complex matrices, MATLAB objects such as a timeseries,
function handles), so that asking for it by name says why it cannot be read and how to save it.

scipy.io.loadmat parses the MAT format itself: it never unpickles or runs anything from the file
(objects and function handles come back as inert bytes, and are skipped here). v7.3 files are
HDF5, which scipy does not read; the error says how to save the file instead.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from piezo_narx_ros.errors import DataError

# A listing in an error message names at most this many variables (Simulink logs hold hundreds).
_LISTED = 40


def _shape(arr) -> str:
    """Write a shape as MATLAB's `whos` does: 1000x1."""
    return 'x'.join(str(n) for n in (np.shape(arr) or (1, 1)))


def _text(value) -> str:
    """Return bytes or a str array element as str (the class names of MATLAB objects)."""
    value = np.asarray(value).reshape(-1)[0] if np.ndim(value) else value
    return value.decode('latin-1') if isinstance(value, bytes) else str(value)


class MatContents(dict):
    """
    {dotted name: numeric array} of a .mat file, with what was skipped and why.

    `skipped` maps a name to (what it is, how to save it readably); `find`, `get` and `matrix`
    raise `error` with one line that names the file and lists its variables.
    """

    def __init__(self, source: str, error=DataError):
        super().__init__()
        self.source = source
        self.error = error
        self.skipped: dict[str, tuple[str, str]] = {}
        self._order: list[str] = []     # every name in the order of the file, for listings

    def listing(self) -> str:
        """Every variable with its shape, on one line: 'u 1000x1, fs 1x1, ts (MATLAB object)'."""
        items = [f'{k} {_shape(self[k])}' if k in self else f'{k} ({self.skipped[k][0]})'
                 for k in dict.fromkeys(self._order)]
        if not items:
            return 'no numeric variables'
        more = len(items) - _LISTED
        return ', '.join(items[:_LISTED]) + (f' and {more} more' if more > 0 else '')

    def find(self, name: str, what: str | None = None):
        """
        Return (the file's spelling, array) of variable `name`, matched case-insensitively.

        None when absent. Raises when two variables match (u and U), or when `name` is (or lies
        inside) a variable that was skipped, saying what it is; `what` says who asks
        (e.g. '--columns u=rec.u'), for the message.
        """
        key = str(name).strip().lower()
        hits = [k for k in self if k.lower() == key]
        if len(hits) > 1:
            raise self.error(f'{self.source}: variables {" and ".join(hits)} differ only in case '
                             '(names are matched case-insensitively); rename one, or save only '
                             'the one to read')
        if hits:
            return hits[0], self[hits[0]]
        for k, (kind, fix) in self.skipped.items():
            if key == k.lower() or key.startswith(k.lower() + '.'):
                raise self.error(f'{self.source}: {what or "variable " + str(name)}: {k} is '
                                 f'{kind}, which cannot be read; {fix}')
        return None

    def get(self, name: str, what: str | None = None):
        """Return (the file's spelling, array) of variable `name`, as `find`; raise when absent."""
        hit = self.find(name, what)
        if hit is None:
            asked = f'{what}: ' if what else ''
            raise self.error(f'{self.source}: {asked}no variable {name!r} (has {self.listing()})')
        return hit

    def matrix(self, what: str) -> tuple[str, np.ndarray]:
        """
        Return (name, array) of the one numeric N x k array of the file (N, k both above 1).

        Column numbers (`--columns u=2`) pick its columns. Raises when there is none or several,
        or when it has more columns than rows (signals stored in rows).
        """
        found = [(k, v) for k, v in self.items() if v.ndim == 2 and min(v.shape) > 1]
        if len(found) != 1:
            has = ('no matrix' if not found else
                   f'{len(found)} matrices ({", ".join(k for k, _ in found)})')
            raise self.error(f'{self.source}: {what}: column numbers pick columns of the one '
                             f'matrix of a file, but it has {has}; name the variables instead, '
                             f'e.g. --columns u=NAME,y=NAME (has {self.listing()})')
        name, arr = found[0]
        if arr.shape[1] > arr.shape[0]:
            raise self.error(f'{self.source}: {what}: {name} is {_shape(arr)}, more columns than '
                             f"rows (signals in rows?); save its transpose ({name}.') so that "
                             'each column is one signal')
        return name, arr

    def _skip(self, name: str, what: str, fix: str) -> None:
        self.skipped[name] = (what, fix)
        self._order.append(name)

    def _add(self, name: str, value) -> None:
        """Add variable `name`, flattening a 1x1 struct into dotted names and skipping the rest."""
        from scipy.io.matlab import MatlabFunction, MatlabObject, MatlabOpaque
        from scipy.sparse import issparse
        if isinstance(value, (MatlabOpaque, MatlabObject)):
            cls = _object_class(value)
            self._skip(name, f'a MATLAB {cls + " " if cls else ""}object',
                       'save its Data and Time as plain arrays (e.g. u = ts.Data; t = ts.Time; '
                       "save(file, 'u', 't', ..., '-v7'))")
        elif isinstance(value, MatlabFunction):
            self._skip(name, 'a function handle', 'save the values it computes as arrays')
        elif issparse(value):
            self._skip(name, 'a sparse matrix', f'save full({name}) instead')
        elif not isinstance(value, np.ndarray):
            self._skip(name, f'a {type(value).__name__}', 'save it as a numeric array')
        elif value.dtype.names is not None:      # a struct: a record array of fields
            if value.size != 1:
                self._skip(name, f'a {_shape(value)} struct array',
                           'only 1x1 structs are read; save the element you want as its own '
                           'variable')
                return
            element = value.reshape(-1)[0]
            for field in value.dtype.names:
                self._add(f'{name}.{field}', element[field])
        elif value.dtype.kind == 'O':
            empty = all(v is None for v in value.reshape(-1))
            self._skip(name, 'an empty struct' if empty else f'a {_shape(value)} cell array',
                       'save numeric arrays (e.g. cell2mat)')
        elif value.dtype.kind in 'US':
            self._skip(name, 'text', 'save numbers')
        elif value.dtype.kind == 'c':
            self._skip(name, 'complex', 'save real(...) and imag(...) as separate arrays')
        elif value.dtype.kind == 'b':
            self._skip(name, 'logical', f'save double({name}) instead')
        elif value.dtype.kind in 'iuf':
            self[name] = value
            self._order.append(name)
        else:
            self._skip(name, f'of type {value.dtype}', 'save it as double')


def _object_class(value) -> str:
    """Return the MATLAB class name of an object variable ('' when scipy does not say)."""
    try:
        if getattr(value, 'classname', None):          # old-style objects (MatlabObject)
            return str(value.classname)
        names = value.dtype.names or ()
        # MatlabOpaque (classdef objects such as timeseries): type system, then class name;
        # scipy 1.17 calls the fields s0..s2, later versions _Class.
        field = '_Class' if '_Class' in names else 's2' if 's2' in names else None
        return _text(value.reshape(-1)[0][field]) if field else ''
    except (AttributeError, IndexError, KeyError, TypeError, ValueError):
        return ''


def _object_name(key: str, value) -> str:
    """Return the variable name of an object: scipy before 1.18 names every one 'None'."""
    from scipy.io.matlab import MatlabOpaque
    if key != 'None' or not isinstance(value, MatlabOpaque) or 's0' not in (value.dtype.names
                                                                            or ()):
        return key
    try:
        return _text(value.reshape(-1)[0]['s0']) or key
    except (IndexError, KeyError, TypeError, ValueError):
        return key


def read_mat(path, error=DataError) -> MatContents:
    """
    {name: numeric array} of the .mat file `path` (MATLAB v4, v5/v6 or v7), as `MatContents`.

    1x1 structs become dotted names (rec.u); everything not numeric is skipped and described.
    Raises `error` (a PiezoNarxError subclass) with one line naming the file when it cannot be
    read, is not a MAT file, or is a v7.3 (HDF5) file. Never executes anything from the file.
    """
    from scipy.io import loadmat
    path = Path(path)
    source = str(path)
    try:
        handle = path.open('rb')
    except OSError as exc:
        raise error(f'{path}: cannot read ({exc.strerror or exc})') from None
    with handle:
        try:
            # squeeze_me=False keeps MATLAB's shapes for the listings; struct_as_record gives
            # structs as record arrays, flattened by their dtype's field names.
            raw = loadmat(handle, squeeze_me=False, struct_as_record=True)
        except NotImplementedError:
            raise error(f'{path}: a MATLAB v7.3 (HDF5) file, which cannot be read; save it with '
                        "save(file, ..., '-v7'), or export .npz or .csv") from None
        except Exception as exc:   # scipy's parser raises a dozen types on crafted bytes
            text = ' '.join(str(exc).split()) or type(exc).__name__
            raise error(f'{path}: not a readable MATLAB .mat file ({text})') from None
    out = MatContents(source, error)
    for key, value in raw.items():
        if key.startswith('__'):      # __header__, __version__, __globals__, object workspace
            continue
        out._add(_object_name(key, value), value)
    return out
