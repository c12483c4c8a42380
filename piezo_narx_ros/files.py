"""
Files the tools write: never over one the user did not ask to replace, nor through a planted name.

`refuse_overwrite` is the one rule for every output named on the command line: an existing file
is replaced only with --force. `write_atomic` writes through a temporary file that is created
fresh and exclusively (O_EXCL, a random name) in the target's directory and then renamed over the
target: a reader never sees half a file, and a symlink planted at a fixed temporary name (issue
45: model.json.tmp, pnr_model.h.tmp) can neither be followed nor redirect the write.
"""
from __future__ import annotations

import os
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

from piezo_narx_ros.errors import ConfigError


def refuse_overwrite(path, force: bool, option: str) -> None:
    """Raise ConfigError (one line) when `path` exists (a dangling symlink too) and not force."""
    path = Path(path)
    if (path.exists() or path.is_symlink()) and not force:
        raise ConfigError(f'{option} {path} exists; choose another name or pass --force to '
                          'overwrite it')


@contextmanager
def write_atomic(path, mode: str = 'wb', encoding: str | None = None) -> Iterator:
    """
    Open a fresh temporary file beside `path` for writing; on success rename it to `path`.

    On an exception the temporary file is removed and `path` is left as it was. The file gets
    the permissions a plain open() would give (0666 less the umask), not mkstemp's 0600.
    """
    path = Path(path)
    fd, tmp = _fresh_temp(path)
    try:
        with os.fdopen(fd, mode, encoding=encoding) as fh:
            yield fh
        os.replace(tmp, path)
    except BaseException:
        _discard([tmp])
        raise


def write_text_atomic(path, text: str) -> None:
    """Write `text` (UTF-8) to `path` through write_atomic."""
    with write_atomic(path, 'w', encoding='utf-8') as fh:
        fh.write(text)


def write_files_atomic(contents: dict) -> None:
    """
    Write {path: text (UTF-8) or bytes}: every temporary file first, then every rename.

    Files that belong together (a C header and its source, a model file and its weights) are
    never half written; the window in which one is new and the other old is a few renames.
    """
    temps = []
    try:
        for path, content in contents.items():
            fd, tmp = _fresh_temp(Path(path))
            temps.append(tmp)
            binary = isinstance(content, (bytes, bytearray))
            with os.fdopen(fd, 'wb' if binary else 'w',
                           encoding=None if binary else 'utf-8') as fh:
                fh.write(content)
        for tmp, path in zip(temps, contents):
            os.replace(tmp, path)
    except BaseException:
        _discard(temps)
        raise


def _fresh_temp(path: Path) -> tuple[int, str]:
    """Create a new file (O_EXCL, random name) beside `path`, with open()'s permissions."""
    fd, tmp = tempfile.mkstemp(prefix=f'.{path.name}.', suffix='.tmp', dir=path.parent)
    os.fchmod(fd, 0o666 & ~_umask())
    return fd, tmp


def _discard(temps) -> None:
    for tmp in temps:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass


def write_npz(path, **arrays) -> None:
    """np.savez `arrays` to `path` (its name kept as given) through write_atomic."""
    import numpy as np
    with write_atomic(path) as fh:
        np.savez(fh, **arrays)


def _umask() -> int:
    """Return the process umask, read without changing it where the OS says it (racy else)."""
    try:
        with open('/proc/self/status') as fh:
            for line in fh:
                if line.startswith('Umask:'):
                    return int(line.split()[1], 8)
    except OSError:
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask
