"""
MATLAB .mat records (dSPACE, Simulink Real-Time, Speedgoat logs): read everywhere .npz is.

Files are written with scipy.io.savemat, which writes 1-D arrays as 1xN rows, as MATLAB stores
a row vector. v7.3 files are written with h5py as MATLAB lays them out (`savemat73`; no MATLAB
here). Each test compares with the .npz or v7 file of the same data or checks a one-line refusal.
"""
import io
import json
import struct
import sys
import warnings

import h5py
import numpy as np
import pytest
from scipy.io import savemat
from scipy.sparse import csc_matrix

from piezo_narx_ros.cli.main import main
from piezo_narx_ros.errors import ConfigError, DataError
from piezo_narx_ros.ident.data.loaders import (expand_inputs, load_record, load_records,
                                               parse_columns, read_signal)
from piezo_narx_ros.ident.data.units import Units
from piezo_narx_ros.matfile import read_mat

FS = 2000.0
N = 600


def piezo(n=N, seed=0, channels=None):
    """Return u (V, +-100) and y (m, about +-40 um) of a plausible rig; (n, k) for `channels`."""
    rng = np.random.default_rng(seed)
    shape = (n + 20,) if channels is None else (n + 20, channels)
    u = rng.uniform(-100, 100, shape)
    u = np.cumsum(u, axis=0)[20:] - np.cumsum(u, axis=0)[:-20]        # a moving sum: smooth
    u = 100 * u / np.max(np.abs(u))
    return u, 4e-7 * u + 1e-9 * rng.standard_normal(u.shape)


def one_line(exc) -> str:
    text = str(exc.value)
    assert '\n' not in text
    return text


def same(a, b):
    """Assert that two records hold the same samples, rate and channel names."""
    assert np.array_equal(a.u, b.u) and np.array_equal(a.y, b.y) and a.fs == b.fs
    assert (a.inputs, a.outputs) == (b.inputs, b.outputs)


def v5_opaque(name: str, cls: str) -> bytes:
    """
    Return a MAT v5 data element holding a MATLAB object, as MATLAB writes a timeseries.

    savemat cannot write one: an mxOPAQUE_CLASS matrix (class 17) holds the variable name, the
    type system (MCOS), the class name and an object id array.
    """
    def element(mtype, data):
        return struct.pack('<II', mtype, len(data)) + data + b'\0' * (-len(data) % 8)
    ids = (element(6, struct.pack('<II', 13, 0)) + element(5, struct.pack('<ii', 6, 1))
           + element(1, b'') + element(6, struct.pack('<6I', 0xDD000000, 2, 1, 1, 1, 1)))
    return element(14, element(6, struct.pack('<II', 17, 0)) + element(1, name.encode())
                   + element(1, b'MCOS') + element(1, cls.encode()) + element(14, ids))


# MATLAB's 128-byte text header of a v7.3 file: text, subsystem offset, version 0x0200, 'IM'.
MAT73_HEADER = (b'MATLAB 7.3 MAT-file, Platform: GLNXA64, Created on: Mon Jan  5 10:00:00 2026 '
                b'HDF5 schema 1.00 .').ljust(116) + b'\0' * 8 + struct.pack('<H', 0x0200) + b'IM'


class Obj(str):
    """A MATLAB object of this class name (a timeseries), for `savemat73`."""


class Cell(list):
    """A 1xn MATLAB cell array of these values, for `savemat73`."""


class StructArray(dict):
    """A 1xn MATLAB struct array: {field: [value of each element]}, for `savemat73`."""


def savemat73(path, variables):
    """
    Write `variables` as MATLAB v7.3 writes them: HDF5 behind a 512-byte user block.

    Numbers are stored transposed (MATLAB is column-major) with a MATLAB_class attribute; a 1-D
    array is a 1xN row, as savemat writes it.
    """
    with h5py.File(path, 'w', userblock_size=512) as f:
        for name, value in variables.items():
            _h5_put(f, name, value)
    with open(path, 'r+b') as f:          # HDF5 leaves the user block to the application
        f.write(MAT73_HEADER)


def _mark(obj, cls, **attrs):
    obj.attrs['MATLAB_class'] = np.bytes_(cls)
    for key, value in attrs.items():
        obj.attrs[key] = value
    return obj


def _h5_refs(group, name, values, cls=None):
    """Store `values` in #refs# and a 1xn dataset of references to them, as cells are."""
    refs = group.file.require_group('#refs#')
    ds = group.create_dataset(name, shape=(len(values), 1), dtype=h5py.ref_dtype)
    for i, value in enumerate(values):
        key = str(len(refs))
        _h5_put(refs, key, value)
        ds[i, 0] = refs[key].ref
    return _mark(ds, cls) if cls else ds


def _h5_put(group, name, value):
    """Store one variable (or struct field) `name` in HDF5 `group` as MATLAB v7.3 does."""
    if isinstance(value, StructArray):
        sub = _mark(group.create_group(name), 'struct')
        for field, values in value.items():
            _h5_refs(sub, field, values)            # no MATLAB_class: the struct's elements
    elif isinstance(value, dict):
        sub = _mark(group.create_group(name), 'struct')
        fields = np.empty(len(value), dtype=object)
        for i, field in enumerate(value):
            fields[i] = np.frombuffer(field.encode(), 'S1')
        sub.attrs.create('MATLAB_fields', fields, dtype=h5py.vlen_dtype(np.dtype('S1')))
        for field, item in value.items():
            _h5_put(sub, field, item)
    elif isinstance(value, Obj):       # MCOS: an id array; the object's data sit in #subsystem#
        group.file.require_group('#subsystem#').require_dataset('MCOS', (1, 1), np.uint32)
        _mark(group.create_dataset(name, data=np.array([[0xDD000000], [2], [1], [1], [1], [1]],
                                                       np.uint32).T),
              str(value), MATLAB_object_decode=np.int32(3))
    elif isinstance(value, str):
        codes = np.frombuffer(value.encode('utf-16-le'), '<u2')[:, None]
        _mark(group.create_dataset(name, data=codes), 'char', MATLAB_int_decode=np.int32(2))
    elif isinstance(value, Cell):
        _h5_refs(group, name, list(value), 'cell')
    elif isinstance(value, csc_matrix):
        sub = _mark(group.create_group(name), 'double', MATLAB_sparse=np.uint64(value.shape[0]))
        sub['data'], sub['ir'] = value.data, value.indices.astype(np.uint64)
        sub['jc'] = value.indptr.astype(np.uint64)
    else:
        arr = np.asarray(value)
        arr = arr if arr.ndim >= 2 else arr.reshape(1, -1)        # 1-D: a 1xN row
        cls = ('logical' if arr.dtype == bool else 'double' if arr.dtype.kind == 'c'
               else {'float64': 'double', 'float32': 'single'}.get(arr.dtype.name,
                                                                   arr.dtype.name))
        if arr.size == 0:                 # an empty array stores its dimensions instead
            _mark(group.create_dataset(name, data=np.array(arr.shape, np.uint64)), cls,
                  MATLAB_empty=np.uint8(1))
            return
        if arr.dtype.kind == 'c':         # complex: a compound of real and imag
            parts = np.empty(arr.shape, [('real', '<f8'), ('imag', '<f8')])
            parts['real'], parts['imag'] = arr.real, arr.imag
            arr = parts
        _mark(group.create_dataset(name, data=(arr.astype(np.uint8) if cls == 'logical'
                                               else arr).T), cls)


def test_default_names_read_as_the_npz_of_the_same_data(tmp_path):
    u, y = piezo()
    np.savez(tmp_path / 'r.npz', u=u, y=y, fs=FS)
    savemat(tmp_path / 'r.mat', {'u': u, 'y': y, 'fs': FS})
    mat, npz = load_record(tmp_path / 'r.mat'), load_record(tmp_path / 'r.npz')
    same(mat, npz)
    assert mat.u.shape == (N, 1) and mat.source == str(tmp_path / 'r.mat')
    # MATLAB stores vectors as rows or columns, and Fs, U, Y in its own spelling.
    savemat(tmp_path / 'c.mat', {'U': u[None, :], 'Y': y[:, None], 'Fs': np.array([[FS]])})
    assert read_mat(tmp_path / 'c.mat')['U'].shape == (1, N)
    same(load_record(tmp_path / 'c.mat'), npz)
    with pytest.raises(DataError, match=r'file says fs = 2000.0 Hz but --fs = 1000.0 Hz'):
        load_record(tmp_path / 'c.mat', fs=1000.0)


@pytest.mark.parametrize('save', ['v7', 'v7.3'])
def test_struct_fields_by_dotted_columns_with_the_struct_rate(tmp_path, save):
    u, y = piezo()
    write = {'v7': savemat, 'v7.3': savemat73}[save]
    write(tmp_path / 's.mat', {'log': {'rig': {'U': u, 'y': y, 'Fs': 1000.0}, 'note': 'run 3'},
                               'fs': 5.0})
    with pytest.raises(DataError) as err:
        load_record(tmp_path / 's.mat')
    assert 'missing variable(s) u, y' in one_line(err)
    assert 'log.rig.U 1x600, log.rig.y 1x600, log.rig.Fs 1x1, log.note (text)' in str(err.value)
    rec = load_record(tmp_path / 's.mat', columns=parse_columns('u=log.rig.u,y=LOG.rig.Y'))
    # The rate is the struct's own (1000 Hz), not the top-level fs of 5 Hz.
    assert rec.fs == 1000.0 and np.array_equal(rec.u[:, 0], u) and np.array_equal(rec.y[:, 0], y)
    with pytest.raises(DataError, match='--columns y=log.note: log.note is text, which cannot'):
        load_record(tmp_path / 's.mat', columns=parse_columns('u=log.rig.u,y=log.note'))


def test_a_struct_array_and_a_matlab_object_are_skipped_and_explained(tmp_path):
    u, y = piezo()
    runs = np.empty((1, 2), dtype=[('u', 'O'), ('y', 'O')])
    runs[0, 0], runs[0, 1] = (u, y), (u, y)
    buf = io.BytesIO()
    savemat(buf, {'u': u, 'fs': FS, 'runs': runs})
    (tmp_path / 'o.mat').write_bytes(buf.getvalue() + v5_opaque('ts', 'timeseries'))
    contents = read_mat(tmp_path / 'o.mat')
    assert set(contents) == {'u', 'fs'}
    assert contents.listing() == ('u 1x600, fs 1x1, runs (a 1x2 struct array), '
                                  'ts (a MATLAB timeseries object)')
    with pytest.raises(DataError) as err:
        load_record(tmp_path / 'o.mat', columns=parse_columns('u=u,y=ts'))
    assert 'ts is a MATLAB timeseries object' in one_line(err)
    assert 'save its Data and Time as plain arrays' in str(err.value)
    with pytest.raises(DataError, match=r'runs is a 1x2 struct array.*only 1x1 structs'):
        load_record(tmp_path / 'o.mat', columns=parse_columns('u=u,y=runs.y'))


def test_one_matrix_by_column_numbers(tmp_path):
    u, y = piezo()
    t = 10.0 + np.arange(N) / FS
    # A row (gain) and a vector (y_lp) are no second matrix.
    savemat(tmp_path / 'm.mat', {'data': np.column_stack([t, u, y, 2 * y]), 'fs': FS,
                                 'gain': np.ones((1, 4)), 'y_lp': y / 2})
    rec = load_record(tmp_path / 'm.mat', columns=parse_columns('t=1,u=2,y=3,y_true=4'))
    assert np.array_equal(rec.u[:, 0], u) and np.array_equal(rec.y_true[:, 0], 2 * y)
    assert np.array_equal(rec.t, t) and rec.fs == FS
    with pytest.raises(DataError, match=r'--columns y=7: data has 4 column\(s\)'):
        load_record(tmp_path / 'm.mat', columns=parse_columns('u=2,y=7'))
    # Names and numbers mix; without t the rate comes from the fs variable.
    rec = load_record(tmp_path / 'm.mat', columns=parse_columns('u=2,y=Y_LP'))
    assert np.array_equal(rec.y[:, 0], y / 2) and rec.fs == FS and rec.t is None
    savemat(tmp_path / 'rows.mat', {'data': np.vstack([u, y])})
    with pytest.raises(DataError, match=r"data is 2x600, more columns than rows.*data\.'"):
        load_record(tmp_path / 'rows.mat', columns=parse_columns('u=1,y=2'), fs=FS)


@pytest.mark.parametrize('variables, has', [
    ({'u': np.zeros((N, 1)), 'y': np.zeros((1, N)), 'fs': FS}, 'no matrix'),
    ({'a': np.zeros((N, 2)), 'b': np.zeros((N, 3)), 'fs': FS}, '2 matrices (a, b)'),
])
def test_column_numbers_without_one_matrix_say_to_name_variables(tmp_path, variables, has):
    savemat(tmp_path / 'x.mat', variables)
    with pytest.raises(DataError) as err:
        load_record(tmp_path / 'x.mat', columns=parse_columns('u=1,y=2'))
    text = one_line(err)
    assert f'but it has {has}; name the variables instead' in text
    assert ', '.join(f'{k} {"x".join(map(str, np.atleast_2d(v).shape))}'
                     for k, v in variables.items()) in text


def test_several_axes_by_inputs_outputs_and_by_matrices(tmp_path):
    u, y = piezo(channels=2)
    savemat(tmp_path / 'n.mat', {'Vx': u[:, 0], 'vy': u[:, 1][:, None], 'dx': y[:, 0],
                                 'DY': y[:, 1], 't': np.arange(N) / FS})
    rec = load_record(tmp_path / 'n.mat', inputs=['vy', 'vx'], outputs=['dx', 'dy'])
    assert rec.inputs == ('vy', 'vx') and rec.outputs == ('dx', 'dy')
    assert np.array_equal(rec.u, u[:, ::-1]) and np.array_equal(rec.y, y)
    assert rec.fs == pytest.approx(FS)
    with pytest.raises(DataError) as err:
        load_record(tmp_path / 'n.mat', inputs=['vx', 'vz'], outputs=['dx'])
    assert "--inputs vz: no variable 'vz' (has Vx 1x600, vy 600x1" in one_line(err)
    with pytest.raises(DataError, match='named twice'):
        load_record(tmp_path / 'n.mat', inputs=['vx'], outputs=['VX'])
    # (N, k) u and y are k channels, named u1.. and y1.. as in an .npz.
    savemat(tmp_path / 'k.mat', {'u': u, 'y': y, 'fs': FS})
    np.savez(tmp_path / 'k.npz', u=u, y=y, fs=FS)
    rec = load_record(tmp_path / 'k.mat')
    assert rec.inputs == ('u1', 'u2') and rec.outputs == ('y1', 'y2')
    same(rec, load_record(tmp_path / 'k.npz'))


def test_units_apply_as_for_the_other_readers(tmp_path):
    u, y = piezo()
    savemat(tmp_path / 'um.mat', {'u': u * 1e3, 'y': y * 1e6, 't': np.arange(N) * 1e3 / FS})
    with pytest.raises(DataError, match='--y-unit um'):
        load_record(tmp_path / 'um.mat', units=Units.from_options('mV', t_unit='ms'))
    rec = load_record(tmp_path / 'um.mat', units=Units.from_options('mV', 'um', 'ms'))
    assert np.allclose(rec.u[:, 0], u, rtol=1e-12) and np.allclose(rec.y[:, 0], y, rtol=1e-12)
    assert rec.fs == pytest.approx(FS) and rec.t[-1] == pytest.approx((N - 1) / FS)


def test_t_gives_the_rate_and_a_disagreeing_fs_is_refused(tmp_path):
    u, y = piezo()
    t = np.arange(N) / FS
    savemat(tmp_path / 't.mat', {'u': u, 'y': y, 'T': t[:, None]})
    rec = load_record(tmp_path / 't.mat')
    assert rec.fs == pytest.approx(FS) and np.array_equal(rec.t, t)
    savemat(tmp_path / 'tf.mat', {'u': u, 'y': y, 't': t, 'fs': 1000.0})
    with pytest.raises(DataError) as err:
        load_record(tmp_path / 'tf.mat')
    assert 'its t variable steps at 2000 Hz but its fs variable says 1000 Hz' in one_line(err)
    savemat(tmp_path / 'none.mat', {'u': u, 'y': y})
    with pytest.raises(DataError, match='no fs variable and no t; pass the sample rate'):
        load_record(tmp_path / 'none.mat')
    assert load_record(tmp_path / 'none.mat', fs=500.0).fs == 500.0
    savemat(tmp_path / 'fsv.mat', {'u': u, 'y': y, 'fs': [FS, FS]})
    with pytest.raises(DataError, match='fs must be one number'):
        load_record(tmp_path / 'fsv.mat')


def test_missing_and_ambiguous_variables_name_what_the_file_has(tmp_path):
    u, y = piezo()
    savemat(tmp_path / 'm.mat', {'u': u, 'Fs': FS, 'note': 'rig 2'})
    with pytest.raises(DataError) as err:
        load_record(tmp_path / 'm.mat')
    assert one_line(err) == (f'{tmp_path / "m.mat"}: missing variable(s) y (has u 1x600, Fs 1x1, '
                             'note (text); need u, y and fs or t, or choose them with --columns '
                             'u=NAME,y=NAME)')
    savemat(tmp_path / 'd.mat', {'u': u, 'y': y, 'Y': y, 'fs': FS})
    with pytest.raises(DataError) as err:
        load_record(tmp_path / 'd.mat')
    assert 'variables y and Y differ only in case' in one_line(err)


def test_v73_reads_as_the_npz_of_the_same_data_rows_or_columns(tmp_path):
    u, y = piezo()
    np.savez(tmp_path / 'r.npz', u=u, y=y, fs=FS)
    npz = load_record(tmp_path / 'r.npz')
    savemat73(tmp_path / 'r.mat', {'u': u, 'y': y, 'fs': FS})
    assert (tmp_path / 'r.mat').read_bytes().startswith(b'MATLAB 7.3 MAT-file')
    assert read_mat(tmp_path / 'r.mat')['u'].shape == (1, N)
    same(load_record(tmp_path / 'r.mat'), npz)
    savemat73(tmp_path / 'c.mat', {'U': u[:, None], 'Y': y[None, :], 'Fs': np.array([[FS]])})
    contents = read_mat(tmp_path / 'c.mat')
    assert contents['U'].shape == (N, 1) and contents['Y'].shape == (1, N)
    same(load_record(tmp_path / 'c.mat'), npz)
    rec = read_signal(tmp_path / 'c.mat')
    assert np.array_equal(rec.u, u) and rec.fs == FS


def test_v73_and_v7_of_the_same_data_give_identical_contents(tmp_path):
    u, y = piezo()
    runs = np.empty((1, 2), dtype=[('u', 'O'), ('y', 'O')])
    runs[0, 0], runs[0, 1] = (u, y), (u, y)
    # Names in HDF5's (alphabetical) order, which is the order a v7.3 file lists them in; the
    # struct's fields keep MATLAB's order (MATLAB_fields), not HDF5's.
    both = {'cells': None, 'col': u[:, None], 'count': np.round(y / 3e-9).astype(np.int16),
            'cplx': u + 1j * y, 'empty': np.zeros((0, 5)), 'fs': FS, 'gain': np.float32([2, 3]),
            'note': 'run 3', 'rec': {'y': y, 'u': u, 'meta': {'fs': 1000.0, 'who': 'rig 2'}},
            'runs': None, 'sp': csc_matrix(np.eye(3))}
    v7 = dict(both, cells=np.array([[u, 'a']], dtype=object), runs=runs)
    buf = io.BytesIO()
    savemat(buf, v7)
    (tmp_path / 'v7.mat').write_bytes(buf.getvalue() + v5_opaque('ts', 'timeseries'))
    savemat73(tmp_path / 'v73.mat', dict(both, cells=Cell([u, 'a']),
                                         runs=StructArray(u=[u, u], y=[y, y]),
                                         ts=Obj('timeseries')))
    a, b = read_mat(tmp_path / 'v7.mat'), read_mat(tmp_path / 'v73.mat')
    assert list(a) == list(b) == ['col', 'count', 'empty', 'fs', 'gain', 'rec.y', 'rec.u',
                                  'rec.meta.fs']
    for name in a:
        assert a[name].shape == b[name].shape and a[name].dtype == b[name].dtype, name
        assert np.array_equal(a[name], b[name]), name
    assert a.skipped == b.skipped and a.listing() == b.listing()
    assert b.listing() == ('cells (a 1x2 cell array), col 600x1, count 1x600, cplx (complex), '
                           'empty 0x5, fs 1x1, gain 1x2, note (text), rec.y 1x600, rec.u 1x600, '
                           'rec.meta.fs 1x1, rec.meta.who (text), runs (a 1x2 struct array), '
                           'sp (a sparse matrix), ts (a MATLAB timeseries object)')


def test_v73_text_objects_and_logicals_are_skipped_and_explained(tmp_path):
    u, y = piezo()
    savemat73(tmp_path / 'o.mat', {'fs': FS, 'note': 'rig 2', 'ok': y > 0, 'ts': Obj('timeseries'),
                                   'u': u})
    contents = read_mat(tmp_path / 'o.mat')
    # #refs# and #subsystem# (what objects and cells point into) are no variables.
    assert contents.listing() == ('fs 1x1, note (text), ok (logical), '
                                  'ts (a MATLAB timeseries object), u 1x600')

    def refused(column):
        with pytest.raises(DataError) as err:
            load_record(tmp_path / 'o.mat', columns=parse_columns(f'u=u,y={column}'))
        return one_line(err)
    assert 'ts is a MATLAB timeseries object, which cannot be read; save its Data and Time as ' \
           'plain arrays' in refused('ts')
    assert 'ok is logical, which cannot be read; save double(ok) instead' in refused('ok')
    assert 'note is text, which cannot be read; save numbers' in refused('note')


def test_v73_int16_counts_are_numbers_read_with_y_scale(tmp_path):
    u, y = piezo()
    counts = np.round(y / 3.05e-9).astype(np.int16)      # a 3.05 nm/count sensor
    savemat73(tmp_path / 'c.mat', {'u': u, 'y': counts[:, None], 'fs': FS})
    assert read_mat(tmp_path / 'c.mat')['y'].dtype == np.int16
    with pytest.raises(DataError, match='--y-scale METRES_PER_COUNT'):
        load_record(tmp_path / 'c.mat')
    rec = load_record(tmp_path / 'c.mat', units=Units.from_options(y_scale=3.05e-9))
    assert np.max(np.abs(rec.y[:, 0] - y)) < 3.05e-9 and np.array_equal(rec.u[:, 0], u)


def test_v73_without_h5py_says_how_to_read_it(tmp_path, monkeypatch):
    savemat73(tmp_path / 'r.mat', {'u': np.zeros(3)})
    monkeypatch.setitem(sys.modules, 'h5py', None)          # as if not installed
    with pytest.raises(DataError) as err:
        read_mat(tmp_path / 'r.mat')
    assert one_line(err) == (f"{tmp_path / 'r.mat'}: a MATLAB v7.3 (HDF5) file, which needs "
                             'h5py to be read (pip install h5py); or save it with save(file, '
                             "..., '-v7'), or export .npz or .csv")


def test_damaged_v73_and_non_mat_files_get_one_line(tmp_path):
    # MATLAB's v7.3 header, then a damaged HDF5 body: a bare signature, or a file cut short.
    (tmp_path / 'h.mat').write_bytes(MAT73_HEADER + b'\0' * 384 + b'\x89HDF\r\n\x1a\n'
                                     + b'\0' * 64)
    savemat73(tmp_path / 'full.mat', {'u': np.zeros(5000), 'fs': FS})
    (tmp_path / 'cut73.mat').write_bytes((tmp_path / 'full.mat').read_bytes()[:2000])
    for name in ('h.mat', 'cut73.mat'):
        with pytest.raises(DataError) as err:
            load_record(tmp_path / name)
        assert one_line(err).startswith(f'{tmp_path / name}: not a readable MATLAB v7.3 (HDF5) '
                                        'file (')
    for name, data in (('text.mat', b'time,u,y\n' * 40), ('empty.mat', b''),
                       ('cut.mat', MAT73_HEADER[:60])):
        (tmp_path / name).write_bytes(data)
        with pytest.raises(DataError) as err:
            load_record(tmp_path / name)
        assert one_line(err).startswith(f'{tmp_path / name}: not a readable MATLAB .mat file (')
    with pytest.raises(ConfigError, match='not a readable MATLAB'):
        read_mat(tmp_path / 'text.mat', error=ConfigError)


def test_crafted_v73_files_are_refused_or_skipped_without_reading_elsewhere(tmp_path):
    savemat73(tmp_path / 'x.mat', {'u': np.ones(4)})
    with h5py.File(tmp_path / 'x.mat', 'r+') as f:
        # 8 GB declared, nothing stored: refused before HDF5 allocates it.
        big = f.create_dataset('big', shape=(1, 10**9), dtype='f8', chunks=(1, 1000))
        big.attrs['MATLAB_class'] = np.bytes_('double')
        f['far'] = h5py.ExternalLink(str(tmp_path / 'other.h5'), '/u')
        f['near'] = h5py.SoftLink('/u')
    with pytest.raises(DataError) as err:
        read_mat(tmp_path / 'x.mat')
    assert one_line(err) == (f"{tmp_path / 'x.mat'}: big declares 1000000000x1 values (8e+09 "
                             'bytes) but the file stores 0 bytes for it (corrupt or crafted)')
    with h5py.File(tmp_path / 'x.mat', 'r+') as f:
        del f['big']
        f['loop'] = f.create_group('rec')
        f['rec'].attrs['MATLAB_class'] = f['loop'].attrs['MATLAB_class'] = np.bytes_('struct')
        f['rec']['self'] = f['rec']
    # A struct inside itself (or shared: the names would double with each level) is refused.
    with pytest.raises(DataError) as err:
        read_mat(tmp_path / 'x.mat')
    assert one_line(err).endswith(': loop.self is the struct loop again (a shared or circular '
                                  'HDF5 link, which MATLAB does not write; corrupt or crafted)')
    with h5py.File(tmp_path / 'x.mat', 'r+') as f:
        del f['rec']['self'], f['rec']
        f['loop']['v'] = f['u']       # one dataset under two names is read once
    contents = read_mat(tmp_path / 'x.mat')
    assert list(contents) == ['loop.v', 'u'] and contents['loop.v'] is contents['u']
    assert contents.listing() == ('far (a link to other HDF5 data), loop.v 1x4, '
                                  'near (a link to other HDF5 data), u 1x4')


def test_a_folder_of_recordings_holds_mat_files(tmp_path):
    u, y = piezo()
    savemat(tmp_path / 'b.mat', {'u': u, 'y': y, 'fs': FS})
    np.savez(tmp_path / 'a.npz', u=u[::-1], y=y[::-1], fs=FS)
    (tmp_path / 'notes.md').write_text('not a recording')
    assert expand_inputs(tmp_path) == [tmp_path / 'a.npz', tmp_path / 'b.mat']
    records = load_records([tmp_path])
    assert [r.source for r in records] == [str(tmp_path / 'a.npz'), str(tmp_path / 'b.mat')]
    only = tmp_path / 'only'
    only.mkdir()
    savemat(only / 'r.mat', {'u': u, 'y': y, 'fs': FS})
    assert expand_inputs(only) == [only / 'r.mat']


def test_read_signal_plays_a_mat_variable(tmp_path):
    u, y = piezo()
    savemat(tmp_path / 'p.mat', {'U': u, 'Fs': FS, 'drive': {'v': 2 * u, 't': np.arange(N) / 500}})
    rec = read_signal(tmp_path / 'p.mat')
    assert np.array_equal(rec.u, u) and rec.fs == FS
    rec = read_signal(tmp_path / 'p.mat', column='drive.v')        # its struct's t: 500 Hz
    assert np.array_equal(rec.u, 2 * u) and rec.fs == pytest.approx(500.0)
    with pytest.raises(ConfigError) as err:
        read_signal(tmp_path / 'p.mat', key='v')
    assert one_line(err).startswith(f'playback file: {tmp_path / "p.mat"}: key v: no variable '
                                    "'v' (has U 1x600, Fs 1x1, drive.v 1x600, drive.t 1x600)")
    savemat(tmp_path / 'm.mat', {'data': np.column_stack([u, y])})
    rec = read_signal(tmp_path / 'm.mat', column='2')
    assert np.array_equal(rec.u, y) and rec.fs is None


def test_evaluate_reads_a_mat_as_the_npz_of_the_same_data(tmp_path, capsys):
    from piezo_narx_ros.ident.arx.model import ARXModel
    from piezo_narx_ros.ident.model_io import save_model
    u, y = piezo(2000, seed=3)
    model = save_model(ARXModel(na=2, nb=2).fit(u, y, fs=FS), tmp_path / 'm.json')
    np.savez(tmp_path / 'r.npz', u=u, y=y, fs=FS)
    savemat(tmp_path / 'r.mat', {'U': u, 'Y': y, 'Fs': FS})

    def evaluate(data):
        with pytest.raises(SystemExit) as exc, warnings.catch_warnings():
            warnings.simplefilter('ignore')
            main(['evaluate', str(model), str(tmp_path / data), '--json'])
        out = capsys.readouterr()
        assert exc.value.code == 0, out.err
        return json.loads(out.out)
    npz, mat = evaluate('r.npz'), evaluate('r.mat')
    assert mat['n'] == npz['n'] == 2000 - 2 and mat['simulation']['r2'] > 0.9
    assert mat['simulation'] == npz['simulation'] and mat['prediction'] == npz['prediction']
    assert mat['tests'] == npz['tests']
