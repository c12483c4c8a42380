"""
Fault suite, recorded data: issue 19 items 6, 7, 8, 9 and 13, and the cheap low ones.

Units that are not volts and metres, time columns in other units, quantised, jittered or epoch
stamps, gaps, an NPZ whose t and fs disagree, bag axes paired by name, `bag export --out` over a
file, European CSVs, a units row, empty cells, identical records and a real micromanipulator
record in a plain whitespace table. Each test fails on the code before issue 19.
"""
import json
import warnings

import numpy as np
import pytest

from conftest import SHARED
from piezo_narx_ros.cli.main import main
from piezo_narx_ros.errors import BagError, ConfigError, DataError
from piezo_narx_ros.ident.data.loaders import load_record, load_records, parse_columns
from piezo_narx_ros.ident.data.records import time_clock
from piezo_narx_ros.ident.data.units import Units, check_consistent, model_unit_problem

FS = 2000.0
YAN9A = SHARED / 'data' / 'piezo_yan9a' / 'Model_Vi_Do.dat'


def piezo(n=2000, seed=0):
    """Return u (V) and a smooth y (m) of a plausible rig, +-100 V and +-40 um."""
    rng = np.random.default_rng(seed)
    u = np.convolve(rng.uniform(-100, 100, n + 50), np.ones(50) / 50, mode='valid')[:n]
    u = 100 * u / np.max(np.abs(u))
    return u, 4e-7 * u + 1e-8 * rng.standard_normal(n)


def cli(argv, capsys):
    with pytest.raises(SystemExit) as exc:
        main(argv)
    out = capsys.readouterr()
    return exc.value.code, out.out, out.err


def one_line(err):
    return err.count('\n') == 1 and err.startswith('piezo-narx: error: ')


# ----------------------------------------------------------------------------- item 6: units
@pytest.mark.parametrize('scale, unit, peak', [(1e6, 'um', '40'), (1e9, 'nm', '4.0')])
def test_y_in_um_or_nm_is_refused_with_the_option_and_read_with_it(tmp_path, scale, unit, peak):
    """Before: fitted with exit 0 into a model whose output range said +-40 m."""
    u, y = piezo()
    np.savez(tmp_path / 'r.npz', u=u, y=y * scale, fs=FS)
    with pytest.raises(DataError, match=f'y reaches {peak}.*pass --y-unit um'):
        load_record(tmp_path / 'r.npz')
    rec = load_record(tmp_path / 'r.npz', units=Units.from_options(y_unit=unit))
    assert np.allclose(rec.y[:, 0], y, rtol=1e-12, atol=0)


def test_raw_counts_need_a_scale_and_mv_needs_its_unit(tmp_path):
    u, y = piezo()
    counts = np.round(y / 3.05e-9)                      # int16 counts of a 3.05 nm/count sensor
    np.savez(tmp_path / 'c.npz', u=u, y=counts.astype(np.int16), fs=FS)
    with pytest.raises(DataError, match='--y-scale METRES_PER_COUNT'):
        load_record(tmp_path / 'c.npz')
    rec = load_record(tmp_path / 'c.npz', units=Units.from_options(y_scale=3.05e-9))
    assert np.max(np.abs(rec.y[:, 0] - y)) < 3.05e-9
    np.savez(tmp_path / 'mv.npz', u=u * 1e3, y=y, fs=FS)
    with pytest.raises(DataError, match='--u-unit mV'):
        load_record(tmp_path / 'mv.npz')
    assert np.allclose(load_record(tmp_path / 'mv.npz', units=Units.from_options('mV')).u[:, 0], u)
    with pytest.raises(ConfigError, match='--y-unit or --y-scale, not both'):
        Units.from_options(y_unit='um', y_scale=1e-9)


def test_records_in_different_units_are_not_fitted_together(tmp_path):
    u, y = piezo()
    np.savez(tmp_path / 'm.npz', u=u, y=y, fs=FS)
    np.savez(tmp_path / 'um.npz', u=u[::-1], y=y[::-1] * 1e6, fs=FS)
    with pytest.raises(DataError, match='y spans .* records in different units'):
        load_records([tmp_path / 'm.npz', tmp_path / 'um.npz'],
                     units=Units.from_options(y_unit='m'))       # stated, so each one passes
    check_consistent(load_records([tmp_path / 'm.npz']))


def test_fit_cli_refuses_um_with_one_line(tmp_path, capsys):
    u, y = piezo()
    np.savez(tmp_path / 'r.npz', u=u, y=y * 1e6, fs=FS)
    code, _, err = cli(['fit', '--preset', 'paper',
                        str(tmp_path / 'r.npz'), '--out', str(tmp_path / 'o')], capsys)
    assert code == 2 and one_line(err) and '--y-unit um' in err
    assert not (tmp_path / 'o').exists()


def test_a_model_fitted_on_um_says_so_on_diagnostics():
    from piezo_narx_ros.counters import WARN
    from piezo_narx_ros.estimator.free_run import FreeRunEstimator
    from piezo_narx_ros.estimator.health import EstimatorHealth
    from piezo_narx_ros.estimator.toy import toy_narx
    model = toy_narx()
    assert model_unit_problem(model) is None
    model.output_range = (-40.0, 40.0)                  # what a fit on um data saved
    level, message, _ = EstimatorHealth(FreeRunEstimator(model)).tick()
    assert level == WARN and 'not a piezo deflection in metres' in message


@pytest.mark.skipif(not YAN9A.is_file(), reason=f'{YAN9A} not found')
def test_the_micromanipulator_record_loads_as_a_user_would():
    """A plain tab-separated .dat, no header, no time column, y in um (../shared/data)."""
    with pytest.raises(DataError, match='7 columns without a header; choose them with --columns'):
        load_record(YAN9A, fs=200.0)
    rec = load_record(YAN9A, fs=200.0, columns=parse_columns('u=1,y=5'),
                      units=Units.from_options(y_unit='um'))
    assert len(rec) == 8027 and rec.fs == 200.0
    assert 0.0 <= rec.u.min() and rec.u.max() <= 3.61
    assert -1.24e-4 < rec.y.min() < rec.y.max() < -7.3e-5         # -123..-74 um, in metres
    with pytest.raises(DataError, match='y reaches 123.*--y-unit um'):
        load_record(YAN9A, fs=200.0, columns=parse_columns('u=1,y=5'))


def test_columns_option_rules(tmp_path):
    assert parse_columns('u=1, y=volts,t=3') == {'u': 1, 'y': 'volts', 't': 3}
    for bad, msg in (('u=0', 'numbered from 1'), ('v=1', 'ROLE=COLUMN'), ('u=1,u=2', 'twice')):
        with pytest.raises(ConfigError, match=msg):
            parse_columns(bad)
    u, y = piezo()
    np.savetxt(tmp_path / 'w.txt', np.column_stack([u, np.zeros_like(u), y]), fmt='%.17g')
    with pytest.raises(DataError, match='--columns u=9: the file has 3 column'):
        load_record(tmp_path / 'w.txt', fs=FS, columns={'u': 9, 'y': 3})
    rec = load_record(tmp_path / 'w.txt', fs=FS, columns={'u': 1, 'y': 3})
    assert np.array_equal(rec.u[:, 0], u) and np.array_equal(rec.y[:, 0], y)


# ----------------------------------------------------------------------- item 7: time columns
def _csv(path, t, u, y, fmt='%.17g'):
    np.savetxt(path, np.column_stack([t, u, y]), delimiter=',', header='t,u,y', comments='',
               fmt=fmt)
    return path


def test_microsecond_stamps_are_refused_with_the_unit_option(tmp_path):
    """Before: a 0.002 Hz model."""
    u, y = piezo()
    p = _csv(tmp_path / 'us.csv', np.arange(u.size) * 500.0, u, y)
    with pytest.raises(DataError, match='0.002 Hz if it is in seconds.*--t-unit'):
        load_record(p)
    assert load_record(p, units=Units.from_options(t_unit='us')).fs == pytest.approx(FS)


def test_quantised_stamps_give_the_true_rate_and_fs_agrees(tmp_path):
    """3 kHz printed to 0.1 ms: before 3333 Hz from the median step, and --fs 3000 refused."""
    u, y = piezo(3000)
    p = _csv(tmp_path / 'q.csv', np.round(np.arange(u.size) / 3000.0, 4), u, y)
    with warnings.catch_warnings():
        warnings.simplefilter('error')                  # quantisation is not jitter
        rec = load_record(p)
        assert rec.fs == pytest.approx(3000.0, rel=1e-4)
        assert load_record(p, fs=3000.0).fs == 3000.0


def test_jittered_stamps_warn_like_a_bag(tmp_path):
    u, y = piezo()
    rng = np.random.default_rng(2)
    t = np.cumsum(rng.uniform(0.6, 1.4, u.size)) / FS              # +-40 % per step
    with pytest.warns(UserWarning, match='irregular sample rate'):
        rec = load_record(_csv(tmp_path / 'j.csv', t, u, y))
    assert rec.fs == pytest.approx(FS, rel=0.02)


def test_epoch_second_stamps_give_the_model_rate(tmp_path, capsys):
    """Before: 2000.14 Hz, and `evaluate` then refused the data of a 2 kHz model."""
    u, y = piezo()
    p = _csv(tmp_path / 'e.csv', 1.7e9 + np.arange(u.size) / FS, u, y)
    assert load_record(p).fs == pytest.approx(FS, rel=1e-6)


def test_npz_t_and_fs_must_agree_and_t_alone_gives_the_rate(tmp_path):
    u, y = piezo()
    np.savez(tmp_path / 'bad.npz', u=u, y=y, fs=FS, t=np.arange(u.size) / 2500.0)
    with pytest.raises(DataError, match='t column steps at 2500 Hz but its fs key says 2000'):
        load_record(tmp_path / 'bad.npz')
    np.savez(tmp_path / 't.npz', u=u, y=y, t=np.arange(u.size) / FS)   # low: no fs key
    assert load_record(tmp_path / 't.npz').fs == pytest.approx(FS)


# ------------------------------------------------------------------------------- item 8: gaps
@pytest.mark.parametrize('kind', ['csv', 'npz'])
def test_a_gap_in_a_time_column_is_said(tmp_path, kind):
    """Before: a 0.5 s gap was joined without a word (a bag with it warns)."""
    u, y = piezo(3000)
    t = np.arange(u.size) / FS
    t[1500:] += 0.5
    p = tmp_path / f'g.{kind}'
    if kind == 'csv':
        _csv(p, t, u, y)
    else:
        np.savez(p, u=u, y=y, t=t, fs=FS)
    with pytest.warns(UserWarning, match=r'1 gap\(s\), 1000 missing sample\(s\).*t=0.7495'):
        rec = load_record(p)
    assert rec.fs == pytest.approx(FS)
    clock = time_clock(t, 'x', warn=False)
    assert clock.gaps == [(pytest.approx(0.7495), 1000)]


def test_fit_prints_the_gap_warning(tmp_path, capsys):
    from piezo_narx_ros.cli.fit_output import one_line_warnings
    u, y = piezo(3000)
    t = np.arange(u.size) / FS
    t[1500:] += 0.5
    with one_line_warnings():
        load_records([_csv(tmp_path / 'g.csv', t, u, y)])
    assert 'piezo-narx: warning: ' in capsys.readouterr().err


# ------------------------------------------------------------------- item 9: bag axes by name
def _two_axis_bag(path, swap=True, n=400):
    from piezo_narx_ros.bag.writer import JOINT_STATE, BagWriter, joint_state_cdr
    rng = np.random.default_rng(0)
    ux, uy = rng.uniform(-50, 50, n), rng.uniform(-50, 50, n)
    t0, p = 1_700_000_000_000_000_000, 500_000
    with BagWriter(path) as bag:
        c = bag.add_topic('piezo/voltage_command', JOINT_STATE)
        d = bag.add_topic('piezo/deflection', JOINT_STATE)
        for k in range(n):
            t = t0 + k * p
            bag.write(c, t, joint_state_cdr(t, ('x', 'y'), effort=(ux[k], uy[k])))
            yx, yy = 4e-7 * ux[k], -3e-7 * uy[k]
            names, pos = ((('y', 'x'), (yy, yx)) if swap else (('x', 'y'), (yx, yy)))
            bag.write(d, t + 1000, joint_state_cdr(t, names, position=pos))
    return ux, uy


def test_bag_axes_pair_by_name_never_by_position(tmp_path):
    """Command names [x, y], deflection names [y, x]: before, x's volts with y's position."""
    from piezo_narx_ros.bag.reader import read_uy
    ux, uy = _two_axis_bag(tmp_path / 'b')
    both = read_uy(tmp_path / 'b')     # every axis: inputs x, y and outputs x, y, by name
    assert both.inputs == ('x', 'y') and both.outputs == ('x', 'y')
    assert np.array_equal(both.u, np.column_stack([ux, uy]))
    assert np.allclose(both.y, np.column_stack([4e-7 * ux, -3e-7 * uy]), rtol=1e-12, atol=0)
    rx = read_uy(tmp_path / 'b', axis='x')
    assert np.array_equal(rx.u[:, 0], ux) and np.allclose(rx.y[:, 0], 4e-7 * ux)
    ry = read_uy(tmp_path / 'b', axis='y')
    assert np.array_equal(ry.u[:, 0], uy) and np.allclose(ry.y[:, 0], -3e-7 * uy)
    with pytest.raises(BagError, match="has no axis 'z' \\(its axes: x, y\\)"):
        read_uy(tmp_path / 'b', axis='z')


def test_bag_info_shows_joint_names_and_fit_takes_axis(tmp_path, capsys):
    _two_axis_bag(tmp_path / 'b')
    code, out, _ = cli(['bag', 'info', str(tmp_path / 'b')], capsys)
    assert code == 0 and 'x,y' in out and 'y,x' in out
    code, out, err = cli(['bag', 'export', str(tmp_path / 'b'), '--axis', 'y', '--out',
                          str(tmp_path / 'e.npz')], capsys)
    assert code == 0, err
    with np.load(tmp_path / 'e.npz') as d:
        assert np.allclose(d['y'], -3e-7 * d['u'])


def test_single_axes_of_different_names_do_not_pair(tmp_path):
    from piezo_narx_ros.bag.reader import read_uy
    from piezo_narx_ros.bag.writer import JOINT_STATE, BagWriter, joint_state_cdr
    with BagWriter(tmp_path / 'b') as bag:
        c = bag.add_topic('piezo/voltage_command', JOINT_STATE)
        d = bag.add_topic('piezo/deflection', JOINT_STATE)
        for k in range(10):
            t = 1_700_000_000_000_000_000 + k * 500_000
            bag.write(c, t, joint_state_cdr(t, ('x',), effort=(1.0,)))
            bag.write(d, t, joint_state_cdr(t, ('y',), position=(1e-6,)))
    with pytest.raises(BagError, match="axis 'x' but .* is axis 'y': they do not pair by name"):
        read_uy(tmp_path / 'b')


# ------------------------------------------------------------------ item 13: export overwrite
def test_bag_export_does_not_overwrite_without_force(tmp_path, capsys):
    from piezo_narx_ros.bag.writer import write_uy_bag
    u, y = piezo()
    bag = write_uy_bag(tmp_path / 'b', u, y, FS)
    out = tmp_path / 'e.npz'
    out.write_bytes(b'keep me')
    code, _, err = cli(['bag', 'export', str(bag), '--out', str(out)], capsys)
    assert code == 2 and one_line(err) and 'pass --force' in err
    assert out.read_bytes() == b'keep me'
    code, _, err = cli(['bag', 'export', str(bag), '--out', str(out), '--force'], capsys)
    assert code == 0 and np.load(out)['u'].size == u.size
    # The same class: simulate --out over a file.
    out.write_bytes(b'keep me')
    code, _, err = cli(['simulate', '--seconds', '0.1', '--out', str(out)], capsys)
    assert code == 2 and one_line(err) and 'pass --force' in err
    assert out.read_bytes() == b'keep me'
    code, _, err = cli(['simulate', '--seconds', '0.1', '--out', str(out), '--force'], capsys)
    assert code == 0 and np.load(out)['u'].size == 200


# ------------------------------------------------------------------------------ the low ones
def test_semicolon_tables_with_decimal_commas_are_read(tmp_path):
    u, y = piezo()
    rows = ['t;u;y'] + [f'{k / FS:.6f};{a:.9f};{b:.12e}'.replace('.', ',')
                        for k, (a, b) in enumerate(zip(u, y))]
    (tmp_path / 'eu.csv').write_text('\n'.join(rows) + '\n')
    rec = load_record(tmp_path / 'eu.csv')
    assert rec.fs == pytest.approx(FS) and np.allclose(rec.u[:, 0], u, atol=1e-9)


@pytest.mark.parametrize('mutate, message', [
    (lambda lines: lines.insert(1, 's,V,m'), r'row 2 is text \(s, V, m\): a units row'),
    (lambda lines: lines.__setitem__(7, '0.003,,1e-6'), 'row 8, column 2 is empty'),
    (lambda lines: lines.__setitem__(9, lines[9] + ','), 'row 10 ends with a separator'),
    (lambda lines: lines.__setitem__(5, '0.002,abc,1e-6'), "row 6, column 2: 'abc' is not a"),
])
def test_malformed_rows_are_named(tmp_path, mutate, message):
    u, y = piezo(200)
    lines = ['t,u,y'] + [f'{k / FS!r},{float(a)!r},{float(b)!r}'
                         for k, (a, b) in enumerate(zip(u, y))]
    mutate(lines)
    (tmp_path / 'bad.csv').write_text('\n'.join(lines) + '\n')
    with pytest.raises(DataError, match=message):
        load_record(tmp_path / 'bad.csv')


def test_the_same_record_twice_is_refused(tmp_path):
    """A bag and its own export fitted together used to count twice without a word."""
    from piezo_narx_ros.bag.writer import write_uy_bag
    u, y = piezo()
    bag = write_uy_bag(tmp_path / 'b', u, y, FS)
    rec = load_record(bag)
    np.savez(tmp_path / 'e.npz', u=rec.u, y=rec.y, fs=rec.fs)
    with pytest.raises(DataError, match='holds the same samples as .*give each recording once'):
        load_records([bag, tmp_path / 'e.npz'])


def test_cli_options_reach_the_loader(tmp_path, capsys):
    """`fit` and `evaluate` read a whitespace table with --columns and --y-unit."""
    from piezo_narx_ros.estimator.toy import toy_narx
    from piezo_narx_ros.ident.model_io import save_model
    u, _ = piezo()
    model = toy_narx()
    save_model(model, tmp_path / 'm.json')
    y = model.simulate(u)
    np.savetxt(tmp_path / 'r.dat', np.column_stack([u, np.zeros_like(u), y * 1e6]), fmt='%.17g',
               delimiter='\t')
    code, _, err = cli(['fit', '--preset', 'paper',
                        str(tmp_path / 'r.dat'), '--fs', '2000', '--columns', 'u=1,y=4',
                        '--out', str(tmp_path / 'o')], capsys)
    assert code == 2 and one_line(err) and '--columns y=4: the file has 3 column(s)' in err
    argv = ['evaluate', str(tmp_path / 'm.json'), str(tmp_path / 'r.dat'), '--fs', '2000',
            '--columns', 'u=1,y=3', '--json']
    code, _, err = cli(argv, capsys)
    assert code == 2 and one_line(err) and '--y-unit um' in err
    code, out, err = cli(argv + ['--y-unit', 'um'], capsys)
    assert code == 0, err
    assert json.loads(out)['simulation']['r2'] > 0.999999
