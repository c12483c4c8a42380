"""
One reader for MATLAB .mat files (v4, v5/v6, v7, v7.3): records that real rigs log.

dSPACE, Simulink Real-Time and Speedgoat write .mat. `read_mat` returns the numeric variables
with MATLAB's shapes (a vector is 1xN or Nx1); a 1x1 struct is flattened into dotted names
(rec.u, rec.y, rec.meta.fs). Everything else is skipped and remembered with what it is (text,
cell arrays, struct arrays, sparse or complex matrices, MATLAB objects such as a timeseries,
function handles), so that asking for it by name says why it cannot be read and how to save it.

scipy.io.loadmat parses v4-v7 itself: it never unpickles or runs anything from the file (objects
and function handles come back as inert bytes, and are skipped here). v7.3 files are HDF5, read
through h5py into the same contents: only numeric datasets are read, by their MATLAB_class
attribute; cells, struct arrays and objects are described, never dereferenced, and nothing from
the file is executed or followed outside it (links and datasets kept in other files are skipped).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from piezo_narx_ros.errors import DataError, PiezoNarxError

# A listing in an error message names at most this many variables (Simulink logs hold hundreds).
_LISTED = 40

# How to save what is skipped, the same for a v7 and a v7.3 file.
_OBJECT_FIX = ('save its Data and Time as plain arrays (e.g. u = ts.Data; t = ts.Time; '
               "save(file, 'u', 't', ..., '-v7'))")
_STRUCT_ARRAY_FIX = 'only 1x1 structs are read; save the element you want as its own variable'
_CELL_FIX = 'save numeric arrays (e.g. cell2mat)'
_FUNCTION_FIX = 'save the values it computes as arrays'


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
            self._skip(name, f'a MATLAB {cls + " " if cls else ""}object', _OBJECT_FIX)
        elif isinstance(value, MatlabFunction):
            self._skip(name, 'a function handle', _FUNCTION_FIX)
        elif issparse(value):
            self._skip(name, 'a sparse matrix', f'save full({name}) instead')
        elif not isinstance(value, np.ndarray):
            self._skip(name, f'a {type(value).__name__}', 'save it as a numeric array')
        elif value.dtype.names is not None:      # a struct: a record array of fields
            if value.size != 1:
                self._skip(name, f'a {_shape(value)} struct array', _STRUCT_ARRAY_FIX)
                return
            element = value.reshape(-1)[0]
            for field in value.dtype.names:
                self._add(f'{name}.{field}', element[field])
        elif value.dtype.kind == 'O':
            empty = all(v is None for v in value.reshape(-1))
            self._skip(name, 'an empty struct' if empty else f'a {_shape(value)} cell array',
                       _CELL_FIX)
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
    {name: numeric array} of the .mat file `path` (MATLAB v4, v5/v6, v7 or v7.3), as `MatContents`.

    1x1 structs become dotted names (rec.u); everything not numeric is skipped and described.
    v7.3 (HDF5) files are read through h5py into the same contents. Raises `error` (a
    PiezoNarxError subclass) with one line naming the file when it cannot be read, is not a MAT
    file, or is a damaged v7.3 file. Never executes anything from the file.
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
        except NotImplementedError:    # the header says v7.3: HDF5 follows, which scipy leaves
            raw = None
        except Exception as exc:   # scipy's parser raises a dozen types on crafted bytes
            text = ' '.join(str(exc).split()) or type(exc).__name__
            raise error(f'{path}: not a readable MATLAB .mat file ({text})') from None
    if raw is None:
        return _read_v73(path, error)
    out = MatContents(source, error)
    for key, value in raw.items():
        if key.startswith('__'):      # __header__, __version__, __globals__, object workspace
            continue
        out._add(_object_name(key, value), value)
    return out


# ------------------------------------------------------------------------- v7.3 (HDF5) files
# MATLAB classes read as numbers, with the dtype an empty one gets (its data are its dims).
_NUMERIC = {'double': np.float64, 'single': np.float32, 'int8': np.int8, 'uint8': np.uint8,
            'int16': np.int16, 'uint16': np.uint16, 'int32': np.int32, 'uint32': np.uint32,
            'int64': np.int64, 'uint64': np.uint64}
# MATLAB compresses with deflate, which packs at most ~1032 bytes into one: a dataset declaring
# more than this many times what the file stores for it is corrupt or crafted (it would make
# HDF5 allocate the declared size, e.g. terabytes, before noticing).
_MAX_RATIO = 1100
_SMALL = 1 << 16          # bytes any dataset may declare whatever it stores (fill values)
_RESAVE = "save it from MATLAB again (save(file, ..., '-v7.3') or '-v7')"


def _read_v73(path: Path, error) -> MatContents:
    """Read the MATLAB v7.3 (HDF5) file `path` into MatContents, as `read_mat` reads v4-v7."""
    try:
        import h5py
    except ImportError:
        raise error(f'{path}: a MATLAB v7.3 (HDF5) file, which needs h5py to be read (pip install '
                    "h5py); or save it with save(file, ..., '-v7'), or export .npz or .csv"
                    ) from None
    out = MatContents(str(path), error)
    seen: dict = {}        # HDF5 object id: its array (a dataset) or first name (a struct)
    # locking=False: reading needs no lock, and HDF5's fails on some network file systems; h5py
    # refuses the option with an HDF5 older than 1.10.7 (1.11-1.12.0 too).
    version = h5py.version.hdf5_version_tuple
    lock = {'locking': False} if version >= (1, 12, 1) or (1, 10, 7) <= version < (1, 11) else {}
    try:
        with h5py.File(path, 'r', **lock) as f:
            for key in f:
                # #refs# holds cell and struct-array elements, #subsystem# objects' data: neither
                # is a variable, and MATLAB names cannot start with #.
                if not key.startswith('#'):
                    _add_h5(out, key, f, key, seen, h5py)
    except PiezoNarxError:
        raise
    except Exception as exc:   # libhdf5 reports damage as OSError, h5py some as others
        text = ' '.join(str(exc).split()) or type(exc).__name__
        raise error(f'{path}: not a readable MATLAB v7.3 (HDF5) file ({text})') from None
    return out


def _dims(ds) -> tuple[int, ...]:
    """
    Return the MATLAB dimensions of HDF5 dataset `ds`.

    MATLAB is column-major, so a 1000x1 vector is stored with shape (1, 1000); an empty array
    (attribute MATLAB_empty) stores its dimensions as its data.
    """
    if ds.attrs.get('MATLAB_empty', 0):
        dims = tuple(int(n) for n in np.asarray(ds[()]).reshape(-1)) if ds.size <= 32 else ()
        # Anything but a list of sizes with a 0 in it is no empty array: say 0x0.
        return dims if len(dims) >= 2 and 0 in dims and min(dims) >= 0 else (0, 0)
    return ds.shape[::-1] + (1,) * (2 - len(ds.shape))


def _add_h5(out: MatContents, name: str, parent, key: str, seen: dict, h5py) -> None:
    """Add member `key` of HDF5 group `parent` as variable `name`, as `MatContents._add` does."""
    if not isinstance(parent.get(key, getlink=True), h5py.HardLink):
        # Soft and external links could reach other files; MATLAB writes none.
        out._skip(name, 'a link to other HDF5 data', _RESAVE)
        return
    obj = parent[key]
    attrs = obj.attrs
    cls = _text(attrs['MATLAB_class']) if 'MATLAB_class' in attrs else ''
    group = isinstance(obj, h5py.Group)
    if 'MATLAB_sparse' in attrs:
        out._skip(name, 'a sparse matrix', f'save full({name}) instead')
    elif cls == 'struct':
        _add_h5_struct(out, name, obj, seen, h5py)
    elif cls == 'function_handle':
        out._skip(name, 'a function handle', _FUNCTION_FIX)
    elif not cls or (group and (cls in _NUMERIC or cls in ('logical', 'char', 'cell'))):
        kind = 'group' if group else 'dataset'
        what = f'of MATLAB class {cls}' if cls else 'without a MATLAB class'
        out._skip(name, f'an HDF5 {kind} {what}, which MATLAB does not write', _RESAVE)
    elif cls in _NUMERIC:
        _add_h5_numeric(out, name, obj, cls, seen, h5py)
    elif cls == 'logical':
        out._skip(name, 'logical', f'save double({name}) instead')
    elif cls == 'char':
        out._skip(name, 'text', 'save numbers')
    elif cls == 'cell':
        out._skip(name, f'a {"x".join(map(str, _dims(obj)))} cell array', _CELL_FIX)
    else:                  # timeseries, string, table, ...: their data sit in #subsystem#
        out._skip(name, f'a MATLAB {cls} object', _OBJECT_FIX)


def _add_h5_struct(out: MatContents, name: str, obj, seen: dict, h5py) -> None:
    """Add a struct: the fields of a 1x1 one as dotted names; struct arrays are skipped."""
    if isinstance(obj, h5py.Dataset) or obj.attrs.get('MATLAB_empty', 0) or not len(obj):
        # An empty struct array stores its dimensions as a dataset; struct() has no fields.
        out._skip(name, 'an empty struct', _CELL_FIX)
        return
    if obj.id in seen:
        # A struct reached twice: a loop would never end, and shared ones multiply the names
        # (2**depth); MATLAB writes neither.
        raise out.error(f'{out.source}: {name} is the struct {seen[obj.id]} again (a shared or '
                        'circular HDF5 link, which MATLAB does not write; corrupt or crafted)')
    seen[obj.id] = name
    fields = list(obj)
    for key in fields:
        member = obj.get(key, getlink=True)
        ds = obj[key] if isinstance(member, h5py.HardLink) else None
        # A struct array keeps, per field, one reference per element; a cell field of a 1x1
        # struct holds references too, but says MATLAB_class cell.
        if (isinstance(ds, h5py.Dataset) and 'MATLAB_class' not in ds.attrs
                and h5py.check_dtype(ref=ds.dtype) is not None):
            out._skip(name, f'a {"x".join(map(str, _dims(ds)))} struct array',
                      _STRUCT_ARRAY_FIX)
            return
    for key in _field_order(obj, fields):
        _add_h5(out, f'{name}.{key}', obj, key, seen, h5py)


def _field_order(group, fields: list[str]) -> list[str]:
    """
    Return `fields` in MATLAB's order, from the group's MATLAB_fields attribute.

    HDF5 lists members by name; MATLAB_fields keeps the order of the struct (one array of
    single characters per field). Fields it does not name follow in HDF5's order.
    """
    try:
        listed = [b''.join(np.asarray(f).reshape(-1).tolist()).decode('latin-1')
                  for f in group.attrs.get('MATLAB_fields', ())]
    except (AttributeError, TypeError, ValueError):
        listed = []
    present = set(fields)
    first = [f for f in dict.fromkeys(listed) if f in present]
    return first + [f for f in fields if f not in set(first)]


def _add_h5_numeric(out: MatContents, name: str, ds, cls: str, seen: dict, h5py) -> None:
    """
    Add a numeric dataset as an array of MATLAB's shape (the transpose of HDF5's).

    Numeric variables are read whole here, as scipy does for v7 files, because MatContents is
    a plain dict downstream; text, cells, struct arrays and objects are never read.
    """
    dtype = ds.dtype
    if dtype.names is not None:
        if {'real', 'imag'} <= set(dtype.names):
            out._skip(name, 'complex', 'save real(...) and imag(...) as separate arrays')
        else:
            out._skip(name, f'of type {dtype}', 'save it as double')
        return
    if dtype.kind not in 'iuf':
        out._skip(name, f'of type {dtype}', 'save it as double')
        return
    dims = _dims(ds)
    if ds.id in seen:      # one dataset under several names: read (and held) once
        arr = seen[ds.id]
    elif ds.attrs.get('MATLAB_empty', 0):
        arr = np.zeros(dims, _NUMERIC[cls])
    else:
        plist = ds.id.get_create_plist()
        if plist.get_layout() == h5py.h5d.VIRTUAL or plist.get_external_count():
            # Data kept in other files (a virtual or external dataset): MATLAB writes none,
            # and reading it would read whatever file those name.
            out._skip(name, 'data kept in other files', _RESAVE)
            return
        need, stored = ds.size * dtype.itemsize, ds.id.get_storage_size()
        if need > _MAX_RATIO * stored + _SMALL:
            raise out.error(f'{out.source}: {name} declares {"x".join(map(str, dims))} values '
                            f'({need:.3g} bytes) but the file stores {stored} bytes for it '
                            '(corrupt or crafted)')
        arr = np.asarray(ds[()]).T.reshape(dims)
        if not arr.dtype.isnative:
            arr = arr.astype(arr.dtype.newbyteorder('='))
        seen[ds.id] = arr
    out[name] = arr
    out._order.append(name)
