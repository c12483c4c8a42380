"""Several axes in records and files: channel order and names survive every reader (issue 20)."""
import numpy as np
import pytest

from piezo_narx_ros.errors import BagError, DataError
from piezo_narx_ros.ident.data.loaders import load_record, load_records
from piezo_narx_ros.record import Record

FS = 1000.0


def _signals(n=400, n_in=3, n_out=2, seed=0):
    rng = np.random.default_rng(seed)
    u = rng.uniform(-5, 5, (n, n_in))
    y = 1e-6 * rng.standard_normal((n, n_out))
    return u, y


def test_record_is_two_dimensional_with_names_and_keeps_them_through_splits():
    u, y = _signals()
    rec = Record(u=u, y=y, fs=FS, source='r', inputs=('a', 'b', 'c'), outputs=('p', 'q'))
    assert rec.u.shape == (400, 3) and rec.y.shape == (400, 2) and (rec.n_in, rec.n_out) == (3, 2)
    est, val = rec.split(0.5)
    assert est.inputs == val.inputs == ('a', 'b', 'c') and val.outputs == ('p', 'q')
    assert np.array_equal(val.u_before, u[:200]) and np.array_equal(val.y, y[200:])
    one = Record(u=u[:, 0], y=y[:, 0], fs=FS, source='one')
    assert one.u.shape == (400, 1) and one.inputs == ('u',) and one.outputs == ('y',)
    assert Record(u=u, y=y, fs=FS, source='d').inputs == ('u1', 'u2', 'u3')
    with pytest.raises(DataError, match='^r: 2 input name'):
        Record(u=u, y=y, fs=FS, source='r', inputs=('a', 'b'))


def test_npz_keeps_channel_order_and_names(tmp_path):
    u, y = _signals()
    np.savez(tmp_path / 'r.npz', u=u, y=y, fs=FS, inputs=np.array(['z', 'a', 'm']),
             outputs=np.array(['y_b', 'y_a']))
    rec = load_record(tmp_path / 'r.npz')
    assert rec.inputs == ('z', 'a', 'm') and rec.outputs == ('y_b', 'y_a')
    assert np.array_equal(rec.u, u) and np.array_equal(rec.y, y)
    np.savez(tmp_path / 'plain.npz', u=u, y=y, fs=FS)
    assert load_record(tmp_path / 'plain.npz').outputs == ('y1', 'y2')


def test_csv_header_splits_inputs_and_outputs(tmp_path):
    u, y = _signals(n_in=2, n_out=2)
    t = np.arange(400) / FS
    # Columns shuffled: the header names, not their positions, say which channel is which.
    table = np.column_stack([t, y[:, 1], u[:, 0], y[:, 0], u[:, 1]])
    np.savetxt(tmp_path / 'r.csv', table, delimiter=',', fmt='%.17g', header='t,y2,u1,y1,u2',
               comments='')
    rec = load_record(tmp_path / 'r.csv')
    assert rec.inputs == ('u1', 'u2') and rec.outputs == ('y1', 'y2')
    assert np.array_equal(rec.u, u) and np.array_equal(rec.y, y) and rec.fs == pytest.approx(FS)
    np.savetxt(tmp_path / 'n.csv', table, delimiter=',', fmt='%.17g',
               header='t,dy,vx,dx,vy', comments='')
    rec = load_record(tmp_path / 'n.csv', inputs=['vx', 'vy'], outputs=['dx', 'dy'])
    assert rec.inputs == ('vx', 'vy') and np.array_equal(rec.y, y)
    with pytest.raises(DataError, match="--inputs: no column named 'vz'"):
        load_record(tmp_path / 'n.csv', inputs=['vz'], outputs=['dx'])


def test_records_with_different_names_are_refused_naming_the_first_difference(tmp_path):
    u, y = _signals()
    np.savez(tmp_path / 'a.npz', u=u, y=y, fs=FS, inputs=np.array(['a', 'b', 'c']))
    np.savez(tmp_path / 'b.npz', u=u[::-1], y=y, fs=FS, inputs=np.array(['a', 'c', 'b']))
    with pytest.raises(DataError) as err:
        load_records([tmp_path / 'a.npz', tmp_path / 'b.npz'])
    assert "(channel 2: 'c' vs 'b')" in str(err.value) and '\n' not in str(err.value)


@pytest.mark.parametrize('u, y, match', [
    (np.zeros((200, 2, 2)), np.zeros(200), r'u must be \(N,\) or \(N, channels\)'),
    (np.zeros((200, 2)), np.zeros((150, 2)), 'u has 200 samples but y has 150'),
    (np.full((200, 2), np.nan), np.zeros(200), 'u contains NaN or inf'),
])
def test_bad_shapes_get_one_line(tmp_path, u, y, match):
    np.savez(tmp_path / 'r.npz', u=u, y=y, fs=FS)
    with pytest.raises(DataError, match=match) as err:
        load_record(tmp_path / 'r.npz')
    assert '\n' not in str(err.value)


def _bag(path, cmd_names, defl_names, n=300, cmd_at=None, defl_at=None):
    """Write a bag of n samples; cmd_at / defl_at: {sample: names} of messages naming others."""
    from piezo_narx_ros.bag.writer import JOINT_STATE, BagWriter, joint_state_cdr
    rng = np.random.default_rng(3)
    u = rng.uniform(-5, 5, (n, len(cmd_names)))
    t0, p = 1_700_000_000_000_000_000, 1_000_000
    gains = {name: 1e-7 * (i + 1) for i, name in enumerate(sorted(set(cmd_names)))}
    with BagWriter(path) as bag:
        c = bag.add_topic('piezo/voltage_command', JOINT_STATE)
        d = bag.add_topic('piezo/deflection', JOINT_STATE)
        for k in range(n):
            t = t0 + k * p
            by_name = dict(zip(cmd_names, u[k]))
            names = (cmd_at or {}).get(k, cmd_names)
            bag.write(c, t, joint_state_cdr(t, names, effort=tuple(by_name[m] for m in names)))
            names = (defl_at or {}).get(k, defl_names)
            pos = tuple(gains.get(nm, 1e-7) * by_name.get(nm, 1.0) for nm in names)
            bag.write(d, t + 1000, joint_state_cdr(t, names, position=pos))
    return u, gains


def test_bag_axes_are_paired_by_name_in_the_command_order(tmp_path):
    u, gains = _bag(tmp_path / 'b', ('x', 'y', 'z'), ('z', 'x', 'y'))
    rec = load_record(tmp_path / 'b')
    assert rec.inputs == rec.outputs == ('x', 'y', 'z') and rec.fs == pytest.approx(FS)
    assert np.array_equal(rec.u, u)
    assert np.allclose(rec.y, u * np.array([gains[a] for a in 'xyz']), rtol=1e-12, atol=0)
    one = load_record(tmp_path / 'b', axis='y')
    assert one.u.shape == (300, 1) and np.array_equal(one.u[:, 0], u[:, 1])


def test_bag_with_several_command_axes_but_one_deflection_axis_is_refused(tmp_path):
    _bag(tmp_path / 'b', ('x', 'y'), ('x',))
    with pytest.raises(BagError, match='carries the axes x, y but .*deflection names x'):
        load_record(tmp_path / 'b')


def test_bag_axes_are_taken_over_the_whole_bag_not_from_its_first_message(tmp_path):
    """An early message missing an axis is counted and reported, not fatal (issue 20)."""
    from piezo_narx_ros.bag.reader import read_uy_report
    # The first two commands name x only (a publisher that came up before y's), one later
    # deflection names y only, and one command names them in the other order.
    u, gains = _bag(tmp_path / 'b', ('x', 'y'), ('x', 'y'), n=200,
                    cmd_at={0: ('x',), 1: ('x',), 50: ('y', 'x')}, defl_at={120: ('y',)})
    rec, report = read_uy_report(tmp_path / 'b')
    assert rec.inputs == rec.outputs == ('x', 'y')
    keep = np.setdiff1d(np.arange(200), [0, 1, 120])
    assert np.array_equal(rec.u, u[keep])
    assert np.allclose(rec.y, u[keep] * np.array([gains['x'], gains['y']]), rtol=1e-12, atol=0)
    assert report.command.malformed == 2 and report.command.missing_axes == {'y': 2}
    assert report.deflection.malformed == 1 and report.deflection.missing_axes == {'x': 1}
    lines = report.issues()
    assert any('command: 2 message(s)' in ln and 'axis missing: y in 2' in ln for ln in lines)
    assert any('deflection: 1 message(s)' in ln and 'x in 1' in ln for ln in lines)


def test_bag_whose_messages_each_name_one_of_two_axes_is_refused_not_mixed(tmp_path):
    """Messages naming x or y alone never fill one series with both axes' values."""
    names = {k: (('x',) if k % 2 else ('y',)) for k in range(240)}
    _bag(tmp_path / 'b', ('x', 'y'), ('x', 'y'), n=240, cmd_at=names, defl_at=names)
    with pytest.raises(BagError, match=r'no command samples .*240 message\(s\) without effort '
                       r'of axis y \(120\), x \(120\)'):
        load_record(tmp_path / 'b')
    one = load_record(tmp_path / 'b', axis='x')      # one axis is still readable by name
    assert one.n_in == 1 and one.u.shape == (120, 1)


def test_fit_reads_a_named_table_with_inputs_and_outputs_options(tmp_path):
    """--inputs/--outputs pick the channels of a table whose header does not say u1/y1."""
    from piezo_narx_ros.cli.main import build_parser
    from piezo_narx_ros.cli.reading import reading_options
    args = build_parser().parse_args(['evaluate', 'm.json', 'a.csv', '--inputs', 'vx, vy',
                                      '--outputs', 'dx,dy'])
    assert args.inputs == ['a.csv']           # the positional INPUTs are not overwritten
    opts = reading_options(args)
    assert opts['inputs'] == ['vx', 'vy'] and opts['outputs'] == ['dx', 'dy']
    u, y = _signals(n_in=2, n_out=2)
    np.savetxt(tmp_path / 'a.csv', np.column_stack([u, y]), delimiter=',', fmt='%.17g',
               header='vx,vy,dx,dy', comments='')
    rec = load_records([tmp_path / 'a.csv'], fs=FS, **{k: opts[k] for k in ('inputs', 'outputs')})
    assert rec[0].outputs == ('dx', 'dy') and np.array_equal(rec[0].y, y)
