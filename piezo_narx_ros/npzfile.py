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


def read_npz(path, keys=None, error=DataError) -> dict[str, np.ndarray]:
    """
    {key: array} of the .npz file `path` (only `keys` when given; absent keys are left out).

    Raises `error` (a PiezoNarxError subclass) with one line naming the file when it is not a
    zip archive, is damaged, holds Python objects, or an array header declares more data than the
    file stores.
    """
    path = Path(path)
    try:
        with path.open('rb') as f:
            magic = f.read(4)
    except OSError as exc:
        raise error(f'{path}: cannot read ({exc.strerror or exc})') from None
    if magic not in _ZIP_MAGIC:
        raise error(f'{path}: not an .npz file (not a zip archive)')
    out: dict[str, np.ndarray] = {}
    try:
        with zipfile.ZipFile(path) as z:
            members = {i.filename[:-4]: i for i in z.infolist() if i.filename.endswith('.npy')}
            for key, info in members.items():
                if keys is not None and key not in keys:
                    continue
                with z.open(info) as member:
                    shape, dtype = _header(member)
                    if dtype.hasobject:
                        raise error(f'{path}: array {key!r} holds Python objects (pickled data); '
                                    'refused')
                    need = int(np.prod(shape, dtype=object)) * dtype.itemsize
                    if need > info.file_size:
                        raise error(f'{path}: array {key!r} declares shape {shape} '
                                    f'({need:.3g} bytes) but the file stores {info.file_size} '
                                    'bytes for it (corrupt or crafted)')
                with z.open(info) as member:   # read_array starts from the magic again
                    out[key] = np.lib.format.read_array(member, allow_pickle=False)
    except (zipfile.BadZipFile, zlib.error, ValueError, EOFError, OSError,
            NotImplementedError) as exc:
        text = ' '.join(str(exc).split()) or type(exc).__name__
        raise error(f'{path}: not a readable .npz file ({text})') from None
    return out
