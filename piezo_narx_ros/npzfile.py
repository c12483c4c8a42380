"""
One reader for .npz files (data records, model weights, playback signals).

`np.load(allow_pickle=False)` alone is not enough for files from strangers: random bytes are
reported as "pickled data, load it unsafely", and a member whose header declares 10^12 values
makes numpy allocate terabytes before it notices the data is not there. `read_npz` checks the zip
structure and every array header against the bytes actually stored before reading anything, and
never unpickles.
"""
from __future__ import annotations

import zipfile
import zlib
from pathlib import Path

import numpy as np

from piezo_narx_ros.errors import DataError

_ZIP_MAGIC = (b'PK\x03\x04', b'PK\x05\x06')   # a local file header, or an empty archive


def _header(member) -> tuple[tuple[int, ...], np.dtype]:
    """(shape, dtype) from an open .npy member, without reading its data."""
    version = np.lib.format.read_magic(member)
    if version == (1, 0):
        shape, _, dtype = np.lib.format.read_array_header_1_0(member)
    else:
        shape, _, dtype = np.lib.format.read_array_header_2_0(member)
    return shape, dtype


def read_npz(path, keys=None, error=DataError, shapes=None,
             max_bytes=None) -> dict[str, np.ndarray]:
    """
    {key: array} of the .npz file `path` (only `keys` when given; absent keys are left out).

    shapes: {key: shape} the caller expects (a model file's declared weights): only those are
    read, each must be there with exactly that shape, and no other member is decompressed.
    max_bytes: the most the arrays read may hold together, checked from their headers before
    any data is read. Raises `error` (a PiezoNarxError subclass) with one line naming the file
    when it is not a zip archive, is damaged, holds Python objects, an array header declares
    more data than the file stores, or shapes / max_bytes are not met.
    """
    if shapes is not None:
        keys = tuple(shapes)
    path = Path(path)
    try:
        with path.open('rb') as f:
            magic = f.read(4)
    except OSError as exc:
        raise error(f'{path}: cannot read ({exc.strerror or exc})') from None
    if magic not in _ZIP_MAGIC:
        raise error(f'{path}: not an .npz file (not a zip archive)')
    out: dict[str, np.ndarray] = {}
    total = 0
    try:
        with zipfile.ZipFile(path) as z:
            members = {i.filename[:-4]: i for i in z.infolist() if i.filename.endswith('.npy')}
            for key in shapes or ():
                if key not in members:
                    raise error(f'{path}: missing weight array {key!r}')
            for key, info in members.items():
                if keys is not None and key not in keys:
                    continue
                with z.open(info) as member:
                    shape, dtype = _header(member)
                    if dtype.hasobject:
                        raise error(f'{path}: array {key!r} holds Python objects (pickled data); '
                                    'refused')
                    if shapes is not None and tuple(shape) != shapes[key]:
                        raise error(f'{path}: weight array {key!r} has shape {tuple(shape)}, '
                                    f'expected {shapes[key]} (the shape its model file declares)')
                    need = int(np.prod(shape, dtype=object)) * dtype.itemsize
                    if need > info.file_size:
                        raise error(f'{path}: array {key!r} declares shape {shape} '
                                    f'({need:.3g} bytes) but the file stores {info.file_size} '
                                    'bytes for it (corrupt or crafted)')
                    total += need
                    if max_bytes is not None and total > max_bytes:
                        raise error(f'{path}: its arrays declare more than {max_bytes} bytes '
                                    '(the most this file may hold); refused before reading')
                with z.open(info) as member:   # read_array starts from the magic again
                    out[key] = np.lib.format.read_array(member, allow_pickle=False)
    except (zipfile.BadZipFile, zlib.error, ValueError, EOFError, OSError,
            NotImplementedError) as exc:
        text = ' '.join(str(exc).split()) or type(exc).__name__
        raise error(f'{path}: not a readable .npz file ({text})') from None
    return out
