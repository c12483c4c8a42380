"""
Input/output records for identification: load (u, y, fs) from NPZ, tables, .mat or rosbag2 MCAP.

Every problem raises `DataError` (or `BagError` for bags) with a one-line message that names the
file and the problem, so `piezo-narx fit` can print it as is. Text tables (.csv with commas or
semicolons, .tsv/.txt/.dat with tabs or spaces) share one reader and one set of column rules
(`read_table`, `pick_columns`) with command_node's playback (`read_signal`); a time column gives
the rate through `time_clock`, which warns about gaps and jitter as the bag reader does. Units
other than V, m and s are stated by the user (`data.units.Units`), never guessed. MATLAB files
(`load_mat`, read by `matfile.read_mat`) follow the .npz rules with variables for keys.
"""
from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from piezo_narx_ros.errors import BagError, ConfigError, DataError
from piezo_narx_ros.ident.data.records import (TIME_RATE_RTOL, _fs_value, _make, _names_key,
                                               _vector, checked, time_clock)
from piezo_narx_ros.ident.data.units import SI, Units, check_consistent
from piezo_narx_ros.matfile import read_mat
from piezo_narx_ros.npzfile import read_npz
from piezo_narx_ros.record import Record, check_same_channels

__all__ = ['load_npz', 'load_csv', 'load_mat', 'load_bag', 'load_record', 'load_records',
           'read_table', 'parse_columns', 'pick_columns', 'read_signal']


def load_npz(path, fs: float | None = None, units: Units = SI) -> Record:
    """
    Record from an .npz with keys u, y and fs or t (optional y_true, inputs, outputs).

    u (N,) or (N, n_in) V, y (N,) or (N, n_out) m; inputs / outputs: arrays of channel names
    (default ('u',), ('y',) for one channel, u1.. / y1.. for several).

    `fs` fills a missing rate; a file whose t column and fs disagree is refused, and one with t
    but no fs takes its rate from t (`time_clock`, whose gap and jitter warnings apply).
    """
    path = Path(path)
    source = str(path)
    data = read_npz(path)
    missing = [k for k in ('u', 'y') if k not in data]
    if missing:
        raise DataError(f'{source}: missing key(s) {", ".join(missing)} '
                        f'(has {", ".join(sorted(data)) or "none"}; need u, y, fs)')
    file_fs = _fs_value(data['fs'], source) if 'fs' in data else None
    t = data.get('t')
    if t is not None:
        t = _vector('t', t, source) * units.t_factor
    return _make(data['u'], data['y'], _file_rate(file_fs, t, fs, source, units), source, t,
                 data.get('y_true'), units, _names_key(data, 'inputs', source),
                 _names_key(data, 'outputs', source))


def _file_rate(file_fs, t, fs, source: str, units: Units, kind: str = 'key') -> float:
    """
    Return the rate (Hz) of a file from its fs (Hz), its t (s) and --fs: given ones must agree.

    A file's fs and --fs must agree, and so must a t and the other given one; t alone gives the
    rate through `time_clock` (gap and jitter warnings). kind: what the file's fs and t are
    called in messages ('key' in an .npz, 'variable' in a .mat).
    """
    if file_fs is not None and fs is not None and not np.isclose(file_fs, fs, rtol=1e-9):
        raise DataError(f'{source}: file says fs = {file_fs} Hz but --fs = {fs} Hz')
    if t is not None:
        t_fs = time_clock(t, source, 't', stated='t' in units.stated).fs
        given = file_fs if file_fs is not None else fs
        if given is not None and not np.isclose(t_fs, given, rtol=TIME_RATE_RTOL):
            said = f'its fs {kind}' if file_fs is not None else '--fs'
            raise DataError(f'{source}: its t {"column" if kind == "key" else kind} steps at '
                            f'{t_fs:.6g} Hz but {said} says {given:g} Hz; correct the file (or '
                            '--t-unit if t is not in s)')
        file_fs = given if given is not None else t_fs
    if file_fs is None and fs is None:
        raise DataError(f'{source}: no fs {kind} and no t; pass the sample rate with --fs')
    return file_fs if file_fs is not None else fs


def load_csv(path, fs: float | None = None, columns: dict | None = None,
             units: Units = SI, inputs=None, outputs=None) -> Record:
    """
    Record from a delimited text table: .csv, or .tsv/.txt/.dat (tabs or spaces).

    A header row naming the columns is allowed (t, u, y, y_true, any order); without one the
    columns are t,u,y (3 columns) or u,y (2 columns), or chosen with `columns` ({'u': 1, 'y': 5,
    't': ...}: 1-based numbers or header names, as `--columns u=1,y=5`). fs comes from the t
    column (`time_clock`) or `fs`; both given must agree.

    Several axes: a header `t, u1, u2, ..., y1, y2, ...` (inputs named u<k>, outputs y<k>), or
    any header names with `inputs` / `outputs` (lists of column names, `--inputs a,b --outputs
    c,d`); the channels keep the header's names, in the order given.
    """
    path = Path(path)
    source = str(path)
    names, table = read_table(path)
    several = _channel_columns(names, inputs, outputs, source)
    if several is not None:
        iu, iy = several
        t = None
        if names is not None and 't' in names:
            t = _vector('t', table[:, names.index('t')], source) * units.t_factor
        fs = _csv_rate(t, fs, source, units)
        return _make(table[:, iu], table[:, iy], fs, source, t, None, units,
                     [names[i] for i in iu], [names[i] for i in iy])
    cols = pick_columns(names, table.shape[1], columns, source)
    if 'u' not in cols or 'y' not in cols:
        missing = [k for k in ('u', 'y') if k not in cols]
        raise DataError(f'{source}: missing column(s) {", ".join(missing)} '
                        f'(header has {", ".join(names or [])}; need t,u,y or u,y, or choose '
                        'them with --columns u=N,y=M)')
    t = table[:, cols['t']] if 't' in cols else None
    if t is not None:
        t = _vector('t', t, source) * units.t_factor
    fs = _csv_rate(t, fs, source, units)
    return _make(table[:, cols['u']], table[:, cols['y']], fs, source, t,
                 table[:, cols['y_true']] if 'y_true' in cols else None, units)


def _csv_rate(t, fs, source: str, units: Units) -> float:
    """Return the rate (Hz) of a table: from its t column (s) and/or --fs, which must agree."""
    if t is not None:
        csv_fs = time_clock(t, source, 't', stated='t' in units.stated).fs
        if fs is not None and not np.isclose(csv_fs, fs, rtol=TIME_RATE_RTOL):
            raise DataError(f'{source}: time stamps give fs = {csv_fs:.6g} Hz but --fs = {fs} '
                            'Hz; if t is not in seconds pass --t-unit, or leave the t column '
                            'out with --columns')
        fs = fs if fs is not None else csv_fs
    if fs is None:
        raise DataError(f'{source}: no t column; pass the sample rate with --fs')
    return fs


def _numbered(names, prefix: str) -> list[int]:
    """Return the indices of the header names prefix1, prefix2, ... in the order of the numbers."""
    found = [(int(n[len(prefix):]), i) for i, n in enumerate(names)
             if n.startswith(prefix) and n[len(prefix):].isdigit()]
    return [i for _, i in sorted(found)]


def _channel_columns(names, inputs, outputs, source: str):
    """
    (input column indices, output column indices) of a several-axes table, or None.

    Given names (`inputs` / `outputs`) pick header columns; else a header of u1.. and y1..
    columns (and no plain u / y column) is a several-axes table.
    """
    if inputs is not None or outputs is not None:
        if inputs is None or outputs is None:
            raise DataError(f'{source}: give both --inputs and --outputs (column names)')
        if names is None:
            raise DataError(f'{source}: --inputs/--outputs name header columns, but the file '
                            'has no header row')
        picked = []
        for what, wanted in (('--inputs', inputs), ('--outputs', outputs)):
            idx = []
            for col in wanted:
                key = str(col).strip().lower()
                if key not in names:
                    raise DataError(f'{source}: {what}: no column named {key!r} (header: '
                                    f'{", ".join(names)})')
                idx.append(names.index(key))
            picked.append(idx)
        if set(picked[0]) & set(picked[1]) or len(set(picked[0])) != len(picked[0]) \
                or len(set(picked[1])) != len(picked[1]):
            raise DataError(f'{source}: a column is named twice in --inputs/--outputs')
        return picked[0], picked[1]
    if names is None or 'u' in names or 'y' in names:
        return None
    iu, iy = _numbered(names, 'u'), _numbered(names, 'y')
    if not iu and not iy:
        return None
    if not iu or not iy:
        raise DataError(f'{source}: the header names {"inputs u1.." if iu else "outputs y1.."} '
                        f'but no {"outputs y1.." if iu else "inputs u1.."} (header: '
                        f'{", ".join(names)}); name the columns u1.., y1.. or pass --inputs and '
                        '--outputs')
    return iu, iy


# ---------------------------------------------------------------------------- MATLAB files
MAT_SUFFIX = '.mat'


def load_mat(path, fs: float | None = None, columns: dict | None = None,
             units: Units = SI, inputs=None, outputs=None) -> Record:
    """
    Record from a MATLAB .mat file (v4, v5/v6, v7, or v7.3 through h5py).

    Variables as the keys of an .npz, matched case-insensitively (Fs, U, Y): u, y and fs or t
    (optional y_true); u (N,) or (N, n_in) V, y (N,) or (N, n_out) m, t s, fs Hz, a vector 1xN
    or Nx1 alike. 1x1 structs are read as dotted names (`matfile.read_mat`). `columns` (as
    `--columns u=rec.u,y=rec.y[,t=..,y_true=..]`) names the variables instead, or with 1-based
    numbers picks columns of the file's one matrix (data = [t u y]: `--columns t=1,u=2,y=3`).
    Several axes: `inputs` / `outputs` name one vector variable per channel, stacked in the order
    given and named as given. The rate, as for .npz (given ones must agree): the fs variable (Hz)
    and, by default or when named, the t variable (s) of u's struct when it has either, else the
    top-level ones; `fs` fills a missing rate.
    """
    path = Path(path)
    source = str(path)
    mat = read_mat(path)
    y_true = t = None
    if inputs is not None or outputs is not None:
        if not inputs or not outputs:
            raise DataError(f'{source}: give both --inputs and --outputs (variable names)')
        picked = [[mat.get(n, f'{opt} {n}') for n in wanted]
                  for opt, wanted in (('--inputs', inputs), ('--outputs', outputs))]
        found = [k for group in picked for k, _ in group]
        if len(set(found)) != len(found):
            raise DataError(f'{source}: a variable is named twice in --inputs/--outputs')
        u, y = (_stack(group, source) for group in picked)
        fs_hit, t = _clock(mat, found[0])
        inputs, outputs = list(inputs), list(outputs)
    else:
        if columns:
            chosen = {role: _mat_pick(mat, col, f'--columns {role}={col}')
                      for role, col in columns.items()}
            need = 'choose them with --columns u=NAME,y=NAME'
        else:
            chosen = {role: hit for role in COLUMN_ROLES if (hit := mat.find(role)) is not None}
            need = 'need u, y and fs or t, or choose them with --columns u=NAME,y=NAME'
        missing = [k for k in ('u', 'y') if k not in chosen]
        if missing:
            raise DataError(f'{source}: missing variable(s) {", ".join(missing)} (has '
                            f'{mat.listing()}; {need})')
        u, y = chosen['u'][1], chosen['y'][1]
        # A t is read when found by default or named in --columns, as a table's t column.
        fs_hit, _ = _clock(mat, chosen['u'][0])
        t = chosen.get('t')
        y_true = chosen['y_true'][1] if 'y_true' in chosen else None
    if t is not None:
        t = _vector(t[0], t[1], source) * units.t_factor
    file_fs = _mat_fs(fs_hit, source)
    return _make(u, y, _file_rate(file_fs, t, fs, source, units, 'variable'), source, t, y_true,
                 units, inputs, outputs)


def _stack(group, source: str) -> np.ndarray:
    """Return the vector variables [(name, array)] of --inputs or --outputs as (N, k) channels."""
    cols = [_vector(name, arr, source) for name, arr in group]
    for (name, _), col in zip(group, cols):
        if col.size != cols[0].size:
            raise DataError(f'{source}: {name} has {col.size} samples but {group[0][0]} '
                            f'{cols[0].size}')
    return np.column_stack(cols)


def _clock(mat, name: str):
    """
    Return the hits (name, array) or None of the fs and t variables that go with variable `name`.

    Those of the struct holding `name` when it has either (a log of several rigs keeps one rate
    per struct), else those at the top level.
    """
    prefix = name.rpartition('.')[0]
    for scope in ([prefix + '.'] if prefix else []) + ['']:
        fs_hit, t_hit = mat.find(scope + 'fs'), mat.find(scope + 't')
        if fs_hit is not None or t_hit is not None:
            break
    return fs_hit, t_hit


def _mat_fs(hit, source: str) -> float | None:
    """Return the rate (Hz) of an fs variable hit (name, array), None for None."""
    if hit is None:
        return None
    if hit[1].size != 1:
        raise DataError(f'{source}: {hit[0]} must be one number (the sample rate in Hz), got '
                        f'{"x".join(map(str, hit[1].shape))} values')
    return _fs_value(hit[1], source)


def _mat_pick(mat, col, what: str):
    """Return (name, array) of a --columns entry: a variable name, or a column of the matrix."""
    if isinstance(col, int):
        name, arr = mat.matrix(what)
        if not 1 <= col <= arr.shape[1]:
            raise DataError(f'{mat.source}: {what}: {name} has {arr.shape[1]} column(s) '
                            '(numbered from 1)')
        return name, arr[:, col - 1]
    return mat.get(col, what)


# ------------------------------------------------------------------------------ text tables
TABLE_SUFFIXES = ('.csv', '.tsv', '.txt', '.dat')
COLUMN_ROLES = ('t', 'u', 'y', 'y_true')


def _split_row(line: str, sep: str | None) -> list[str]:
    return [c.strip() for c in (line.split(sep) if sep else line.split())]


def read_table(path) -> tuple[list[str] | None, np.ndarray]:
    """
    Numbers from a delimited text file: (header names or None, table (N, k) float64).

    Columns are separated by ',' (CSV), ';' (then ',' is the decimal mark, as spreadsheets in
    many locales write it), or tabs/spaces (.dat/.txt/.tsv from instruments and MATLAB). Blank
    lines and lines starting with '#' are skipped. Every problem names its row (1-based line of
    the file): a units row after the header, an empty cell, a trailing separator, text.
    """
    path = Path(path)
    source = str(path)
    try:
        # utf-8-sig: spreadsheets start CSV files with a byte-order mark, which is not part of
        # the first column's name.
        text = path.read_text(encoding='utf-8-sig')
    except UnicodeDecodeError:
        raise DataError(f'{source}: not a text file (not UTF-8)') from None
    except OSError as exc:
        raise DataError(f'{source}: cannot read ({exc.strerror or exc})') from None
    lines = [(i + 1, ln) for i, ln in enumerate(text.splitlines())
             if ln.strip() and not ln.lstrip().startswith('#')]
    if not lines:
        raise DataError(f'{source}: empty file')
    first = lines[0][1]
    sep = ';' if ';' in first else ',' if ',' in first else '\t' if '\t' in first else None
    decimal_comma = sep == ';'
    head = _split_row(first, sep)
    has_header = not all(_is_number(c, decimal_comma) for c in head if c)
    names = [c.lower() for c in head] if has_header else None
    body = lines[1:] if has_header else lines
    if not body:
        raise DataError(f'{source}: only a header row ({", ".join(head)}), no data rows')
    width = len(head)
    try:   # the fast path: every row well formed
        rows = [_split_row(ln, sep) for _, ln in body]
        if decimal_comma:
            rows = [[c.replace(',', '.') for c in r] for r in rows]
        if any(len(r) != width for r in rows) or any('' in r for r in rows):
            raise ValueError
        table = np.array(rows, dtype=np.float64)
    except ValueError:
        _raise_bad_row(source, body, sep, width, decimal_comma, has_header)
    return names, table.reshape(len(body), width)


def _is_number(text: str, decimal_comma: bool = False) -> bool:
    try:
        float(text.replace(',', '.') if decimal_comma else text)
        return True
    except ValueError:
        return False


def _raise_bad_row(source, body, sep, width, decimal_comma, has_header):
    """Find the first malformed row and say what is wrong with it (DataError)."""
    for row, line in body:
        cells = _split_row(line, sep)
        if cells and cells[-1] == '' and len(cells) == width + 1:
            raise DataError(f'{source}: row {row} ends with a separator (an empty column after '
                            'the last one)')
        if len(cells) != width:
            raise DataError(f'{source}: row {row} has {len(cells)} column(s), the first row '
                            f'{width}')
        for j, cell in enumerate(cells):
            if cell == '':
                raise DataError(f'{source}: row {row}, column {j + 1} is empty')
            if not _is_number(cell, decimal_comma):
                what = ('a units row after the header? Remove it and give units with --u-unit '
                        '/ --y-unit' if has_header and row == body[0][0]
                        and not any(_is_number(c, decimal_comma) for c in cells)
                        else 'not a number')
                raise DataError(f'{source}: row {row}, column {j + 1}: {cell!r} is {what}'
                                if what == 'not a number' else
                                f'{source}: row {row} is text ({", ".join(cells)}): {what}')
    raise DataError(f'{source}: the rows are not a table of numbers')


def parse_columns(text: str | None) -> dict | None:
    """
    Parse `--columns u=1,y=5[,t=2]` into {'u': 1, 'y': 5, ...} (numbers 1-based, or names).

    ConfigError for a role other than t, u, y, y_true, a repeated role, or a number below 1.
    """
    if text is None or not str(text).strip():
        return None
    out = {}
    for part in str(text).split(','):
        role, eq, col = part.partition('=')
        role, col = role.strip().lower(), col.strip()
        if not eq or role not in COLUMN_ROLES or not col:
            raise ConfigError(f'--columns: {part.strip()!r} is not ROLE=COLUMN with ROLE one of '
                              f'{", ".join(COLUMN_ROLES)} (e.g. --columns u=1,y=5)')
        if role in out:
            raise ConfigError(f'--columns: {role} given twice')
        if col.isdigit():
            if int(col) < 1:
                raise ConfigError('--columns: columns are numbered from 1')
            out[role] = int(col)
        else:
            out[role] = col.lower()
    return out


def pick_columns(names: list[str] | None, width: int, columns: dict | None,
                 source: str) -> dict[str, int]:
    """
    {role: 0-based column index} of a table: the roles of `columns`, or the header's, or by count.

    Without a header and without `columns`, 3 columns are t,u,y, 2 are u,y and 1 is u; other
    counts must be chosen. The same rules serve `fit` and command_node's playback.
    """
    if columns:
        out = {}
        for role, col in columns.items():
            if isinstance(col, int):
                if not 1 <= col <= width:
                    raise DataError(f'{source}: --columns {role}={col}: the file has {width} '
                                    'column(s) (numbered from 1)')
                out[role] = col - 1
            elif names is None or col not in names:
                raise DataError(f'{source}: --columns {role}={col}: no column named {col!r} '
                                f'(' + (f'header: {", ".join(names)}' if names else 'no header: '
                                        'give its number') + ')')
            else:
                out[role] = names.index(col)
        return out
    if names is not None:
        return {role: names.index(role) for role in COLUMN_ROLES if role in names}
    by_count = {3: ('t', 'u', 'y'), 2: ('u', 'y'), 1: ('u',)}
    if width not in by_count:
        raise DataError(f'{source}: {width} columns without a header; choose them with '
                        '--columns, e.g. --columns u=1,y=5 (1-based; t=N for a time column)')
    return {role: i for i, role in enumerate(by_count[width])}


def load_bag(path, command_topic: str, deflection_topic: str, axis: str | int | None = None,
             units: Units = SI) -> Record:
    """
    Record from a rosbag2 directory or .mcap file, through piezo_narx_ros.bag.reader.read_uy.

    axis: the joint name whose command and deflection are paired (by name in each message, never
    by position); None: the one axis the bag has.
    """
    try:
        from piezo_narx_ros.bag.reader import read_uy
    except ImportError:
        raise BagError('bag support not available '
                       '(piezo_narx_ros.bag.reader is missing)') from None
    record = read_uy(path, command_topic, deflection_topic, axis)
    record.source = record.source or str(path)
    # Re-validate through the same checks as files so every source obeys one contract.
    return checked(record, units)


def _is_bag(path: Path) -> bool:
    return path.suffix == '.mcap' or (path.is_dir() and (
        (path / 'metadata.yaml').is_file() or any(path.glob('*.mcap'))))


def load_record(path, fs: float | None = None, command_topic: str = 'piezo/voltage_command',
                deflection_topic: str = 'piezo/deflection', columns: dict | None = None,
                units: Units = SI, axis: str | int | None = None, inputs=None,
                outputs=None) -> Record:
    """
    Load one Record from an .npz, a text table, a .mat, an .mcap file or a rosbag2 directory.

    Dispatch on the path; text tables are .csv, .tsv, .txt and .dat. columns: `parse_columns`
    result for text tables and .mat files; units: how to read u, y and t (ident.data.units.Units:
    --u-unit, --y-unit, --y-scale, --t-unit); axis: a bag's joint name.
    """
    path = Path(path)
    if not path.exists():
        raise DataError(f'{path}: no such file or directory')
    if _is_bag(path):
        return load_bag(path, command_topic, deflection_topic, axis, units)
    if path.is_dir():
        raise DataError(f'{path}: a directory but not a rosbag2 bag (no metadata.yaml or .mcap)')
    suffix = path.suffix.lower()
    if suffix == '.npz':
        return load_npz(path, fs, units)
    if suffix in TABLE_SUFFIXES:
        return load_csv(path, fs, columns, units, inputs, outputs)
    if suffix == MAT_SUFFIX:
        return load_mat(path, fs, columns, units, inputs, outputs)
    raise DataError(f'{path}: unknown input type {suffix or "(no suffix)"}; '
                    f'use .npz, {", ".join(TABLE_SUFFIXES)}, .mat, .mcap or a rosbag2 directory')


RECORDING_SUFFIXES = ('.npz', '.mcap', MAT_SUFFIX) + TABLE_SUFFIXES


def expand_inputs(paths) -> list[Path]:
    """
    Input paths with each folder of recordings replaced by the recordings in it, sorted by name.

    rosbag2 bags (directories or .mcap files), .npz and .mat files and text tables. A folder that
    is itself a bag stays one input; an .npz beside a .json of the same stem is a model's weights
    and is left out. DataError for a folder holding no recording.
    """
    if isinstance(paths, (str, Path)):
        paths = [paths]
    out = []
    for path in map(Path, paths):
        # One bag: metadata.yaml, or a single .mcap (a recording whose metadata was lost).
        if not path.is_dir() or (path / 'metadata.yaml').is_file() \
                or len(list(path.glob('*.mcap'))) == 1:
            out.append(path)
            continue
        found = [p for p in sorted(path.iterdir())
                 if (_is_bag(p) or (p.is_file() and p.suffix.lower() in RECORDING_SUFFIXES))
                 and not (p.suffix.lower() == '.npz' and p.with_suffix('.json').is_file())]
        if not found:
            raise DataError(f'{path}: a directory that is neither a rosbag2 bag nor a folder of '
                            'recordings (no bag, .mcap, .npz, .mat or text table in it)')
        out += found
    return out


def load_records(paths, fs: float | None = None, command_topic: str = 'piezo/voltage_command',
                 deflection_topic: str = 'piezo/deflection', columns: dict | None = None,
                 units: Units = SI, axis: str | int | None = None, inputs=None,
                 outputs=None) -> list[Record]:
    """
    Load the records from every path (options as `load_record`, the same for each).

    A folder of recordings gives each one in it (`expand_inputs`). All must share one sample
    rate (Hz), hold different samples (a bag and its own export fitted together count twice),
    have the same channel names in the same order, and be in the same units
    (`units.check_consistent`), else DataError.
    """
    records = [load_record(p, fs, command_topic, deflection_topic, columns, units, axis, inputs,
                           outputs)
               for p in expand_inputs(paths)]
    if not records:
        raise DataError('no input files given')
    first = records[0]
    for r in records[1:]:
        if not np.isclose(r.fs, first.fs, rtol=1e-6):
            raise DataError(f'sample rates differ: {first.source} has {first.fs:g} Hz, '
                            f'{r.source} has {r.fs:g} Hz')
    check_same_channels(records)
    seen = {}
    for r in records:
        key = (len(r), hashlib.sha256(r.u.tobytes() + r.y.tobytes()).hexdigest())
        if key in seen:
            raise DataError(f'{r.source} holds the same samples as {seen[key]} (a bag and its '
                            'export?): give each recording once')
        seen[key] = r.source
    check_consistent(records)
    return records


@dataclass
class RecordedSignal:
    """One input signal read from a file for playback: volts as recorded and its own rate."""

    u: np.ndarray            # (N,) V, as in the file
    fs: float | None         # Hz from the file (fs key or time column); None when it has none
    source: str
    issues: list = field(default_factory=list)   # warning lines (gaps, jitter of its t column)


def read_signal(path, column: str | int | None = None, key: str = 'u',
                error=ConfigError) -> RecordedSignal:
    """
    Read the input signal of a recording, for playback: an .npz key, a .mat variable or a column.

    .npz: key `key` (default u) with fs or t for the rate. .mat: variable `column` (a name, or a
    1-based column of the file's one matrix), else `key`, matched case-insensitively, with an fs
    or t variable beside it for the rate (as `load_mat`). Text tables: `column` (a header name
    or a 1-based number), else the column `pick_columns` calls u (header u, or the 2nd of a
    headerless t,u,y, the 1st of u,y or of a single column); its t column gives the rate. Errors
    are `error` (ConfigError for a node parameter) naming the file.
    """
    path = Path(path)
    source = str(path)
    kind = 'key'      # what the file calls its fs and t, for messages
    try:
        if path.suffix.lower() == '.npz':
            data = read_npz(path, error=error)
            if key not in data:
                raise error(f'playback file {path} has no key {key!r} (keys: {", ".join(data)})')
            u = data[key]
            fs = _fs_value(data['fs'], source) if 'fs' in data else None
            t = data.get('t')
        elif path.suffix.lower() == MAT_SUFFIX:
            mat = read_mat(path)
            by_key = column is None or column == ''
            wanted = key if by_key else column
            if isinstance(wanted, str) and wanted.strip().isdigit():
                wanted = int(wanted)
            name, u = _mat_pick(mat, wanted, f'{"key" if by_key else "column"} {wanted}')
            fs_hit, t = _clock(mat, name)
            fs, t, kind = _mat_fs(fs_hit, source), t[1] if t is not None else None, 'variable'
        elif path.suffix.lower() in TABLE_SUFFIXES:
            names, table = read_table(path)
            if isinstance(column, str) and column.strip().isdigit():
                column = int(column)
            wanted = None if column is None or column == '' else {'u': column}
            if isinstance(column, str) and wanted:
                wanted = {'u': column.strip().lower()}
            cols = pick_columns(names, table.shape[1], wanted, source)
            if 'u' not in cols:
                raise DataError(f'{source}: no column u (header: {", ".join(names or [])}); '
                                'choose one with the column parameter')
            u, t, fs = table[:, cols['u']], None, None
            if not wanted and 't' in cols:
                t = table[:, cols['t']]
            elif wanted and names and 't' in names:
                t = table[:, names.index('t')]
        else:
            raise error(f'playback file {path} must be .npz, .mat or a text table '
                        f'({", ".join(TABLE_SUFFIXES)})')
        u = np.asarray(u)
        if u.dtype.kind not in 'fiu':
            raise DataError(f'{source}: {key} is not numeric')
        u = u.astype(np.float64)
        if u.ndim == 2 and 1 in u.shape:
            u = u.reshape(-1)
        if u.ndim != 1 or u.size < 1:
            raise DataError(f'{source}: the signal must be a non-empty 1-D array, got shape '
                            f'{u.shape}')
        if not np.all(np.isfinite(u)):
            raise DataError(f'{source}: the signal has non-finite values')
        issues = []
        if t is not None:
            t = _vector('t', t, source)
            if t.size != u.size:
                raise DataError(f'{source}: t has {t.size} samples but the signal {u.size}')
            clock = time_clock(t, source, warn=False)
            issues = clock.issues(source)
            if fs is not None and not np.isclose(clock.fs, fs, rtol=TIME_RATE_RTOL):
                raise DataError(f'{source}: its t {"column" if kind == "key" else kind} steps at '
                                f'{clock.fs:.6g} Hz but its fs {kind} says {fs:g} Hz')
            fs = fs if fs is not None else clock.fs
    except DataError as exc:
        if error is DataError:
            raise
        raise error(f'playback file: {exc}') from None
    return RecordedSignal(u, fs, source, issues)
