"""Batched bags (JointTrajectory on <topic>_batch) read exactly like one-sample bags; no DDS."""
import json
import warnings

import numpy as np
import pytest
import yaml

from piezo_narx_ros.bag.reader import BagWarning, bag_info, read_joint_series, read_uy_report
from piezo_narx_ros.bag.writer import (JOINT_STATE, JOINT_TRAJECTORY, BagWriter,
                                       joint_trajectory_cdr, write_uy_bag)
from piezo_narx_ros.cli.main import main

FS = 20000.0
T0 = 1_700_000_000_999_990_000


def _uy(n=3001, seed=0):
    rng = np.random.default_rng(seed)
    u = rng.uniform(-100, 100, n)
    return u, 1e-7 * np.convolve(u, [0.5, 0.3, 0.2])[:n] + 1e-9 * rng.standard_normal(n)


@pytest.mark.parametrize('batch', [2, 7, 20])
def test_a_batched_bag_reads_as_the_same_record_as_the_one_sample_bag(tmp_path, batch):
    u, y = _uy()
    one = write_uy_bag(tmp_path / 'one', u, y, FS, t0_ns=T0)
    many = write_uy_bag(tmp_path / 'many', u, y, FS, t0_ns=T0, batch=batch)
    assert {t.name for t in bag_info(many).topics} == {'/piezo/voltage_command_batch',
                                                       '/piezo/deflection_batch'}
    a, rep_a = read_uy_report(one)
    b, rep_b = read_uy_report(many)                  # default topics find the batched twins
    for field in ('u', 'y', 't'):
        assert np.array_equal(getattr(a, field), getattr(b, field))
    assert a.fs == b.fs == FS and rep_a.t0_ns == rep_b.t0_ns == T0
    assert rep_b.issues() == [] and rep_b.paired == u.size
    c, _ = read_uy_report(many, 'piezo/voltage_command_batch', '/piezo/deflection_batch')
    assert np.array_equal(c.y, a.y)                   # named explicitly, too


def test_every_stamp_of_a_batch_is_read_exactly(tmp_path):
    """Irregular stamps, across whole seconds and out of order: each point keeps its own."""
    stamps = [T0, T0 + 1, T0 + 9_999, T0 + 10_000, T0 + 1_000_000_007, T0 - 3]
    with BagWriter(tmp_path / 'b') as bag:
        topic = bag.add_topic('/piezo/voltage_command_batch', JOINT_TRAJECTORY)
        bag.write(topic, T0, joint_trajectory_cdr(stamps[:4], effort=np.arange(4.0)[:, None]))
        bag.write(topic, T0 + 1, joint_trajectory_cdr(stamps[4:], effort=[[4.0], [5.0]]))
    s = read_joint_series(tmp_path / 'b', {'piezo/voltage_command': 'effort'})
    got = s['piezo/voltage_command']
    assert got.stamps_ns.tolist() == stamps and got.values.tolist() == [0, 1, 2, 3, 4, 5]
    assert got.log_ns.tolist() == [T0] * 4 + [T0 + 1] * 2
    info = bag_info(tmp_path / 'b').topics[0]
    assert (info.count, info.samples, info.check.reordered) == (2, 6, 1)


def test_bad_points_gaps_and_nans_are_reported_as_for_one_sample_bags(tmp_path):
    """A point without the axis is dropped and counted; a gap is a gap; a NaN is refused."""
    u, y = _uy(200)
    keep = np.r_[0:50, 55:200]                 # 5 samples missing on both streams
    stamps = T0 + keep * 50_000
    with BagWriter(tmp_path / 'g') as bag:
        cmd = bag.add_topic('/piezo/voltage_command_batch', JOINT_TRAJECTORY)
        dfl = bag.add_topic('/piezo/deflection_batch', JOINT_TRAJECTORY)
        for k in range(0, keep.size, 10):
            t = stamps[k:k + 10]
            bag.write(cmd, int(t[-1]), joint_trajectory_cdr(t, effort=u[keep[k:k + 10], None]))
            pos = [[v] for v in y[keep[k:k + 10]]]
            if k == 100:
                pos[3] = []                   # one point without a position
            bag.write(dfl, int(t[-1]), joint_trajectory_cdr(t, position=pos))
    rec, report = read_uy_report(tmp_path / 'g')
    # The dropped point is one more missing sample of the paired record, as a dropped message is.
    assert report.deflection.malformed == 1 and report.missing_samples == 5 + 1
    assert any('1 message(s) without the expected value' in line for line in report.issues())
    assert rec.u.size == keep.size - 1
    with pytest.warns(BagWarning, match='gap'):
        from piezo_narx_ros.bag.reader import read_uy
        read_uy(tmp_path / 'g')
    y2 = y.copy()
    y2[7] = np.nan
    nan_bag = write_uy_bag(tmp_path / 'nan', u, y2, FS, batch=10)
    with pytest.raises(Exception, match='1 non-finite deflection'):
        read_uy_report(nan_bag)


def test_a_sample_topic_of_another_type_is_refused_in_one_line(tmp_path):
    from piezo_narx_ros.errors import BagError
    with BagWriter(tmp_path / 'w') as bag:
        bag.add_topic('/piezo/voltage_command_batch', 'std_msgs/msg/String')
        bag.add_topic('/piezo/deflection', JOINT_STATE)
    with pytest.raises(BagError, match='has type std_msgs/msg/String, expected '
                                       'sensor_msgs/msg/JointState'):
        read_uy_report(tmp_path / 'w')


def _cli(argv, capsys):
    with pytest.raises(SystemExit) as exc:
        main(argv)
    out = capsys.readouterr()
    return exc.value.code, out.out, out.err


def test_bag_info_and_export_of_a_batched_bag(tmp_path, capsys):
    u, y = _uy(1000)
    one = write_uy_bag(tmp_path / 'one', u, y, FS)
    many = write_uy_bag(tmp_path / 'many', u, y, FS, batch=20)
    code, out, _ = _cli(['bag', 'info', str(many)], capsys)
    assert code == 0
    line = next(s for s in out.splitlines() if s.startswith('/piezo/deflection_batch'))
    assert line.split()[1:7] == [JOINT_TRAJECTORY, '50', '1000', '20000', '0', '0']
    for bag, name in ((one, 'a.csv'), (many, 'b.csv')):
        assert _cli(['bag', 'export', str(bag), '--out', str(tmp_path / name)], capsys)[0] == 0
    assert (tmp_path / 'a.csv').read_bytes() == (tmp_path / 'b.csv').read_bytes()


def test_a_batched_bag_fits_to_the_same_model_bit_for_bit(tmp_path, capsys):
    from test_cli_fit import FAST_TRAINING, piezo_like

    from piezo_narx_ros.ident.model_io import load_model, weights_sha256
    (tmp_path / 'fast.yaml').write_text(yaml.safe_dump({'training': FAST_TRAINING,
                                                        'final_training': {}}))
    u, y = piezo_like(2000, seed=4)
    models = []
    for batch in (1, 20):
        bag = write_uy_bag(tmp_path / f'bag{batch}', u, y, 2000.0, batch=batch)
        out = tmp_path / f'fit{batch}'
        with warnings.catch_warnings():
            warnings.simplefilter('error', BagWarning)     # a clean record, both ways
            code, _, err = _cli(['fit', '--preset', 'paper',
                                 str(bag), '--ny', '1', '--nu', '1', '--hidden', '2',
                                 '--arx-na', '1-2', '--arx-nb', '1', '--jobs', '1',
                                 '--no-report', '--quiet', '--config',
                                 str(tmp_path / 'fast.yaml'), '--out', str(out)], capsys)
        assert code == 0, err
        models.append((weights_sha256(load_model(out / 'model.json')),
                       json.loads((out / 'candidates.json').read_text())['candidates']))
    assert models[0][0] == models[1][0]
    assert [c['scores'] for c in models[0][1]] == [c['scores'] for c in models[1][1]]
    code, out, err = _cli(['evaluate', str(tmp_path / 'fit1' / 'model.json'),
                           str(tmp_path / 'bag20'), '--json'], capsys)
    code1, out1, _ = _cli(['evaluate', str(tmp_path / 'fit1' / 'model.json'),
                           str(tmp_path / 'bag1'), '--json'], capsys)
    assert code == code1 == 0, err
    a, b = json.loads(out), json.loads(out1)
    assert a['simulation'] == b['simulation']
