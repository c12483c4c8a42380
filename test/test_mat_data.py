"""
MATLAB .mat records (dSPACE, Simulink Real-Time, Speedgoat logs): read everywhere .npz is.

Files are written with scipy.io.savemat, which writes 1-D arrays as 1xN rows, as MATLAB stores
a row vector. Each test compares with the .npz of the same data or checks a one-line refusal.
"""
import io
import json
import struct
import warnings

import numpy as np
import pytest
from scipy.io import savemat

from piezo_narx_ros.cli.main import main
from piezo_narx_ros.errors import ConfigError, DataError
from piezo_narx_ros.ident.data import (expand_inputs, load_record, load_records, parse_columns,
                                       read_signal)
from piezo_narx_ros.ident.units import Units
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


def test_struct_fields_by_dotted_columns_with_the_struct_rate(tmp_path):
    u, y = piezo()
    savemat(tmp_path / 's.mat', {'log': {'rig': {'U': u, 'y': y, 'Fs': 1000.0},
                                         'note': 'run 3'}, 'fs': 5.0})
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


def test_v73_and_non_mat_files_get_one_line(tmp_path):
    # A v7.3 file is HDF5 behind MATLAB's 128-byte header, whose version field says 0x0200.
    text = b'MATLAB 7.3 MAT-file, Platform: GLNXA64, HDF5 schema 1.00 .'
    header = text.ljust(116, b' ') + b'\0' * 8 + struct.pack('<H', 0x0200) + b'IM'
    (tmp_path / 'h.mat').write_bytes(header + b'\0' * 384 + b'\x89HDF\r\n\x1a\n' + b'\0' * 64)
    with pytest.raises(DataError) as err:
        load_record(tmp_path / 'h.mat')
    assert one_line(err) == (f"{tmp_path / 'h.mat'}: a MATLAB v7.3 (HDF5) file, which cannot "
                             "be read; save it with save(file, ..., '-v7'), or export .npz or "
                             '.csv')
    for name, data in (('text.mat', b'time,u,y\n' * 40), ('empty.mat', b''),
                       ('cut.mat', header[:60])):
        (tmp_path / name).write_bytes(data)
        with pytest.raises(DataError) as err:
            load_record(tmp_path / name)
        assert one_line(err).startswith(f'{tmp_path / name}: not a readable MATLAB .mat file (')
    with pytest.raises(ConfigError, match='not a readable MATLAB'):
        read_mat(tmp_path / 'text.mat', error=ConfigError)


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
    from piezo_narx_ros.ident.arx import ARXModel
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
