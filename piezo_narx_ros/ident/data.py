"""
Input/output records for identification: load (u, y, fs) from NPZ, CSV or rosbag2 MCAP.

Every problem raises `DataError` (or `BagError` for bags) with a one-line message that names the
file and the problem, so `piezo-narx fit` can print it as is.
"""
from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from piezo_narx_ros.errors import BagError, DataError
from piezo_narx_ros.npzfile import read_npz
from piezo_narx_ros.record import Record

__all__ = ['Record', 'MIN_SAMPLES', 'load_npz', 'load_csv', 'load_bag', 'load_record',
           'load_records', 'check_length']

# Fewest samples a record may have: below this neither a 50/50 split nor the correlation tests
# (20 lags) mean anything. `check_length` applies the stricter bound for given lags.
MIN_SAMPLES = 100


def _vector(name: str, value, source: str) -> np.ndarray:
    arr = np.asarray(value)
    if arr.dtype.kind not in 'fiu':
        raise DataError(f'{source}: {name} is not numeric (dtype {arr.dtype})')
    arr = arr.astype(np.float64)
    if arr.ndim == 2 and 1 in arr.shape:   # a column or row vector saved as 2-D
        arr = arr.reshape(-1)
    if arr.ndim != 1:
        raise DataError(f'{source}: {name} must be 1-D, got shape {arr.shape}')
    if not np.all(np.isfinite(arr)):
        bad = int(np.flatnonzero(~np.isfinite(arr))[0])
        raise DataError(f'{source}: {name} contains NaN or inf (first at sample {bad})')
    return arr


def _fs_value(fs, source: str) -> float:
    try:
        fs = float(np.asarray(fs).reshape(-1)[0]) if np.ndim(fs) else float(fs)
    except (TypeError, ValueError, IndexError):
        raise DataError(f'{source}: sample rate fs is not a number: {fs!r}') from None
    if not np.isfinite(fs) or fs <= 0:
        raise DataError(f'{source}: sample rate fs must be a positive number of Hz, got {fs}')
    return fs


def _make(u, y, fs, source, t=None, y_true=None) -> Record:
    u = _vector('u', u, source)
    y = _vector('y', y, source)
    if u.size != y.size:
        raise DataError(f'{source}: u has {u.size} samples but y has {y.size}')
    if t is not None:
        t = _vector('t', t, source)
        if t.size != u.size:
            raise DataError(f'{source}: t has {t.size} samples but u has {u.size}')
    if y_true is not None:
        y_true = _vector('y_true', y_true, source)
        if y_true.size != u.size:
            raise DataError(f'{source}: y_true has {y_true.size} samples but u has {u.size}')
    if u.size < MIN_SAMPLES:
        raise DataError(f'{source}: only {u.size} samples, need at least {MIN_SAMPLES}')
    return Record(u=u, y=y, fs=_fs_value(fs, source), source=source, t=t, y_true=y_true)


def load_npz(path, fs: float | None = None) -> Record:
    """Record from an .npz with keys u, y, fs (optional t, y_true); `fs` fills a missing fs key."""
    path = Path(path)
    source = str(path)
    data = read_npz(path)
    missing = [k for k in ('u', 'y') if k not in data]
    if missing:
        raise DataError(f'{source}: missing key(s) {", ".join(missing)} '
                        f'(has {", ".join(sorted(data)) or "none"}; need u, y, fs)')
    if 'fs' not in data and fs is None:
        raise DataError(f'{source}: no fs key; pass the sample rate with --fs')
    file_fs = _fs_value(data['fs'], source) if 'fs' in data else None
    if file_fs is not None and fs is not None and not np.isclose(file_fs, fs, rtol=1e-9):
        raise DataError(f'{source}: file says fs = {file_fs} Hz but --fs = {fs} Hz')
    return _make(data['u'], data['y'], file_fs if file_fs is not None else fs, source,
                 data.get('t'), data.get('y_true'))


def load_csv(path, fs: float | None = None) -> Record:
    """
    Record from a CSV with columns t,u,y (fs from the stamps) or u,y (fs required).

    A header row naming the columns is allowed (any order; optional y_true column); without one
    the columns are taken as t,u,y (3 columns) or u,y (2 columns).
    """
    path = Path(path)
    source = str(path)
    try:
        # utf-8-sig: spreadsheets start CSV files with a byte-order mark, which is not part of
        # the first column's name.
        with open(path, newline='', encoding='utf-8-sig') as f:
            rows = [r for r in csv.reader(f) if r and any(c.strip() for c in r)]
    except UnicodeDecodeError:
        raise DataError(f'{source}: not a text CSV file') from None
    if not rows:
        raise DataError(f'{source}: empty CSV file')
    header = [c.strip().lower() for c in rows[0]]
    try:
        [float(c) for c in rows[0]]
        has_header = False
    except ValueError:
        has_header = True
    if has_header:
        names, body = header, rows[1:]
        if not body:
            raise DataError(f'{source}: only a header row ({", ".join(names)}), no data rows')
        missing = [k for k in ('u', 'y') if k not in names]
        if missing:
            raise DataError(f'{source}: missing column(s) {", ".join(missing)} '
                            f'(header has {", ".join(names)}; need t,u,y or u,y)')
    else:
        body = rows
        if len(header) == 3:
            names = ['t', 'u', 'y']
        elif len(header) == 2:
            names = ['u', 'y']
        else:
            raise DataError(f'{source}: {len(header)} columns without a header; need t,u,y or u,y')
    try:
        table = np.array([[float(c) for c in r] for r in body], dtype=np.float64)
    except ValueError as exc:
        raise DataError(f'{source}: non-numeric value in CSV ({exc})') from None
    if table.ndim != 2 or table.shape[1] != len(names):
        raise DataError(f'{source}: rows do not all have {len(names)} columns')
    cols = {name: table[:, i] for i, name in enumerate(names)}
    t = cols.get('t')
    if t is not None:
        t = _vector('t', t, source)
        dt = np.diff(t)
        if np.any(dt <= 0):
            raise DataError(f'{source}: time column t is not strictly increasing')
        csv_fs = 1.0 / float(np.median(dt))
        if fs is not None and not np.isclose(csv_fs, fs, rtol=1e-3):
            raise DataError(f'{source}: time stamps give fs = {csv_fs:.6g} Hz but --fs = {fs} Hz')
        fs = fs if fs is not None else csv_fs
    if fs is None:
        raise DataError(f'{source}: no t column; pass the sample rate with --fs')
    return _make(cols['u'], cols['y'], fs, source, t, cols.get('y_true'))


def load_bag(path, command_topic: str, deflection_topic: str) -> Record:
    """Record from a rosbag2 directory or .mcap file, through piezo_narx_ros.bag.reader.read_uy."""
    try:
        from piezo_narx_ros.bag.reader import read_uy
    except ImportError:
        raise BagError('bag support not available '
                       '(piezo_narx_ros.bag.reader is missing)') from None
    record = read_uy(path, command_topic, deflection_topic)
    # Re-validate through the same checks as files so every source obeys one contract.
    return _make(record.u, record.y, record.fs, record.source or str(path), record.t,
                 record.y_true)


def _is_bag(path: Path) -> bool:
    return path.suffix == '.mcap' or (path.is_dir() and (
        (path / 'metadata.yaml').is_file() or any(path.glob('*.mcap'))))


def load_record(path, fs: float | None = None, command_topic: str = 'piezo/voltage_command',
                deflection_topic: str = 'piezo/deflection') -> Record:
    """One Record from an .npz, .csv, .mcap file or rosbag2 directory (dispatch on the path)."""
    path = Path(path)
    if not path.exists():
        raise DataError(f'{path}: no such file or directory')
    if _is_bag(path):
        return load_bag(path, command_topic, deflection_topic)
    if path.is_dir():
        raise DataError(f'{path}: a directory but not a rosbag2 bag (no metadata.yaml or .mcap)')
    suffix = path.suffix.lower()
    if suffix == '.npz':
        return load_npz(path, fs)
    if suffix == '.csv':
        return load_csv(path, fs)
    raise DataError(f'{path}: unknown input type {suffix or "(no suffix)"}; '
                    f'use .npz, .csv, .mcap or a rosbag2 directory')


RECORDING_SUFFIXES = ('.npz', '.csv', '.mcap')


def expand_inputs(paths) -> list[Path]:
    """
    Input paths with each folder of recordings replaced by the recordings in it, sorted by name.

    rosbag2 bags (directories or .mcap files), .npz and .csv files. A folder that is itself a bag
    stays one input; an .npz beside a .json of the same stem is a model's weights and is left out.
    DataError for a folder holding no recording.
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
                            'recordings (no bag, .mcap, .npz or .csv in it)')
        out += found
    return out


def load_records(paths, fs: float | None = None, command_topic: str = 'piezo/voltage_command',
                 deflection_topic: str = 'piezo/deflection') -> list[Record]:
    """
    Load the records from every path.

    A folder of recordings gives each one in it (`expand_inputs`).

    All must share one sample rate (Hz), else DataError.
    """
    records = [load_record(p, fs, command_topic, deflection_topic)
               for p in expand_inputs(paths)]
    if not records:
        raise DataError('no input files given')
    first = records[0]
    for r in records[1:]:
        if not np.isclose(r.fs, first.fs, rtol=1e-6):
            raise DataError(f'sample rates differ: {first.source} has {first.fs:g} Hz, '
                            f'{r.source} has {r.fs:g} Hz')
    return records


def check_length(record: Record, n0: int, max_lag: int = 20, what: str = 'lags') -> None:
    """
    Raise DataError unless each half of `record` is long enough for the tests.

    Each half must hold n0 start-up samples (the deepest lag) plus the 4 * max_lag samples the
    correlation tests need.
    """
    need = max(MIN_SAMPLES, 2 * (n0 + 4 * max_lag))
    if len(record) < need:
        raise DataError(f'{record.source}: {len(record)} samples are too few for {what} up to '
                        f'{n0} (need at least {need})')


def _constant(x: np.ndarray) -> bool:
    """Return True when x does not vary beyond float rounding (relative spread <= 1e-9)."""
    return bool(np.ptp(x) <= 1e-9 * np.max(np.abs(x)))


def check_identifiable(record: Record, split: float = 0.5) -> list[str]:
    """
    Refuse a record from which nothing can be identified; warn about a weak one.

    The first `split` of the samples estimates, the rest validates. Raises DataError when the
    estimation input is constant (an idle rig excites nothing: any model fits it) or the output of
    either part is constant to float rounding (a flat channel gives R² 1 or NaN, not a model).
    Returns warning lines when the estimation input moves much less than the validation input.
    Every message says how to fix the record.
    """
    est, val = record.split(split)
    fix = ('trim the idle part of the record or move the split (fit --split, now '
           f'{split:g})')
    if _constant(est.u):
        raise DataError(f'{record.source}: the input is constant over the estimation part '
                        f'(first {len(est)} samples, u = {est.u[0]:.6g} V): it excites nothing, '
                        f'so no model can be identified from it; {fix}')
    for part, name in ((est, 'estimation'), (val, 'validation')):
        if len(part) and _constant(part.y):
            raise DataError(f'{record.source}: the output is constant in the {name} part '
                            f'(y = {part.y[0]:.6g} m, spread {np.ptp(part.y):.3g} m): nothing to '
                            'identify; check that y is the measured deflection')
    warnings = []
    s_est, s_val = float(np.std(est.u)), float(np.std(val.u))
    if s_est < 0.1 * s_val:
        warnings.append(f'{record.source}: the estimation part moves little (input std '
                        f'{s_est:.3g} V against {s_val:.3g} V in the validation part): the model '
                        f'will extrapolate; {fix}')
    return warnings
