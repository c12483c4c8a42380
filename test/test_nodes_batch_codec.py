"""nodes/wire/trajectory.py: JointTrajectory CDR bytes against rclpy's and rosbags' serialisers."""
import dataclasses

import numpy as np
import pytest
from rclpy.serialization import deserialize_message, serialize_message
from trajectory_msgs.msg import JointTrajectory

from piezo_narx_ros.errors import DataError
from piezo_narx_ros.nodes.wire import (decode_joint_trajectory, encode_joint_trajectory,
                                       make_joint_trajectory)

TRAJECTORY = 'trajectory_msgs/msg/JointTrajectory'
T0 = 1_795_241_581_999_999_990          # 10 ns before a whole second: offsets cross it


def _stamps(n, period_ns=50_000, t0=T0):
    return [t0 + k * period_ns for k in range(n)]


def _case(n, n_axes, fields, seed=0):
    rng = np.random.default_rng(seed)
    pos = rng.normal(size=(n, n_axes)) * 1e-6 if 'position' in fields else None
    eff = rng.uniform(-200, 200, size=(n, n_axes)) if 'effort' in fields else None
    return pos, eff


SHAPES = [(n, a, f) for n in (1, 2, 3, 20) for a in (1, 2, 3)
          for f in (('effort',), ('position',), ('position', 'effort'), ())]


@pytest.mark.parametrize('n, n_axes, fields', SHAPES)
def test_encode_is_what_rclpy_reads_and_decode_reads_what_rclpy_writes(n, n_axes, fields):
    names = ['x', 'yy', 'zzz'][:n_axes]
    pos, eff = _case(n, n_axes, fields)
    stamps = _stamps(n)
    msg = make_joint_trajectory(stamps, names, pos, eff)
    assert deserialize_message(encode_joint_trajectory(stamps, names, pos, eff),
                               JointTrajectory) == msg
    for raw in (serialize_message(msg), encode_joint_trajectory(stamps, names, pos, eff)):
        b = decode_joint_trajectory(raw)
        assert b.t_ns.dtype == np.int64 and b.t_ns.tolist() == stamps   # every stamp exact
        assert b.names == names and len(b) == n
        assert np.array_equal(b.position, pos if pos is not None else np.empty((n, 0)))
        assert np.array_equal(b.effort, eff if eff is not None else np.empty((n, 0)))


@pytest.mark.parametrize('stamps', [
    [T0, T0 + 1, T0 + 999_999_999, T0 + 1_000_000_000, T0 + 3_700_000_000_123],   # irregular
    [T0, T0 - 7, T0 - 1_000_000_001, T0 + 5],        # out of order: negative offsets
    [-1_500_000_000, -1_499_999_999, 2],             # before 1970
    [T0] * 3,                                        # repeated stamps
])
def test_stamps_round_trip_exactly_whatever_their_spacing(stamps):
    eff = np.arange(len(stamps), dtype=float)[:, None]
    raw = encode_joint_trajectory(stamps, ['x'], effort=eff)
    assert decode_joint_trajectory(raw).t_ns.tolist() == stamps
    msg = deserialize_message(raw, JointTrajectory)
    t0 = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
    assert t0 == stamps[0]                                         # header.stamp = t_first
    assert [t0 + p.time_from_start.sec * 10**9 + p.time_from_start.nanosec
            for p in msg.points] == stamps
    assert all(0 <= p.time_from_start.nanosec < 10**9 for p in msg.points)


@pytest.mark.parametrize('stamps', [
    [T0, T0 - 7, T0 - 1_000_000_001, T0 + 5],        # negative offsets
    [-1_500_000_000, -1_499_999_999, 2],
    [T0, T0 + 2**31 * 10**9 + 3, T0 + 1],            # an offset beyond int32 seconds: wraps
])
@pytest.mark.parametrize('n_axes, fields', [(1, ('effort',)), (1, ('position',)),
                                            (3, ('position', 'effort')), (0, ())])
def test_compiled_batches_are_the_bytes_and_values_of_the_numpy_paths(stamps, n_axes, fields):
    """codec_kernels (a stream's second batch on) against the numpy views and the general path."""
    from piezo_narx_ros.nodes.wire import trajectory as codec
    names = ['x', 'y', 'z'][:n_axes]
    pos, eff = _case(len(stamps), n_axes, fields, seed=3)
    codec._ENCODED.clear()
    codec._SHAPES.clear()
    general = encode_joint_trajectory(stamps, names, pos, eff)    # remembers the template
    (template,) = codec._ENCODED.values()
    assert template[1] is not None                     # little-endian host: compiled
    compiled = encode_joint_trajectory(stamps, names, pos, eff)
    codec._ENCODED[next(iter(codec._ENCODED))] = (template[0], None, *template[2:])
    assert compiled == general == encode_joint_trajectory(stamps, names, pos, eff)
    first = decode_joint_trajectory(general)           # the general path; remembers the shape
    (shape,) = codec._SHAPES[len(general)]
    assert shape.meta is not None
    again = decode_joint_trajectory(general)           # compiled
    codec._SHAPES[len(general)] = [dataclasses.replace(shape, meta=None)]
    views = decode_joint_trajectory(general)           # numpy views
    for b in (again, views):
        assert b.t_ns.tolist() == first.t_ns.tolist()
        assert np.array_equal(b.position, first.position)
        assert np.array_equal(b.effort, first.effort)
        assert b.names == first.names
    msg = deserialize_message(compiled, JointTrajectory)
    t0 = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
    assert [t0 + p.time_from_start.sec * 10**9 + p.time_from_start.nanosec
            for p in msg.points] == again.t_ns.tolist()
    if max(stamps) - min(stamps) < 2**31 * 10**9:
        assert again.t_ns.tolist() == stamps


@pytest.mark.parametrize('little_endian', [False, True])
@pytest.mark.parametrize('names, velocities', [(['x', 'abc'], []), ([], [0.5]), (['a'], [])])
def test_decode_reads_both_byte_orders_and_foreign_fields_as_rosbags_writes_them(
        little_endian, names, velocities):
    """Big-endian peers, a frame_id, velocities/accelerations: the general path reads them."""
    from piezo_narx_ros.bag.writer import typestore
    store = typestore()
    types = store.types
    n_axes = max(1, len(names))
    stamps = _stamps(4, 100_000)
    points = [types['trajectory_msgs/msg/JointTrajectoryPoint'](
        positions=np.full(n_axes, 1e-6 * k), velocities=np.array(velocities * n_axes),
        accelerations=np.array([]), effort=np.full(n_axes, 3.0 * k),
        time_from_start=types['builtin_interfaces/msg/Duration'](sec=0, nanosec=100_000 * k))
        for k in range(4)]
    sec, nsec = divmod(stamps[0], 10**9)
    msg = types[TRAJECTORY](
        header=types['std_msgs/msg/Header'](
            stamp=types['builtin_interfaces/msg/Time'](sec=sec, nanosec=nsec), frame_id='odd'),
        joint_names=names, points=points)
    raw = bytes(store.serialize_cdr(msg, TRAJECTORY, little_endian=little_endian))
    b = decode_joint_trajectory(raw)
    assert b.t_ns.tolist() == stamps and b.names == names
    assert np.array_equal(b.effort[:, 0], [0.0, 3.0, 6.0, 9.0])
    assert np.array_equal(b.position[:, -1], [0.0, 1e-6, 2e-6, 3e-6])


def test_rosbags_reads_the_encoder_bytes():
    """The bag reader decodes with rosbags' definitions: the node bytes must read the same."""
    from piezo_narx_ros.bag.reader import decode_cdr
    stamps = _stamps(5)
    pos, eff = _case(5, 2, ('position', 'effort'))
    msg = decode_cdr(encode_joint_trajectory(stamps, ['x', 'y'], pos, eff), TRAJECTORY)
    t0 = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
    assert [t0 + p.time_from_start.sec * 10**9 + p.time_from_start.nanosec
            for p in msg.points] == stamps
    assert np.array_equal([p.effort for p in msg.points], eff)
    assert np.array_equal([p.positions for p in msg.points], pos)


def _points_with(sizes):
    msg = make_joint_trajectory(_stamps(len(sizes)), ['x', 'y'],
                                effort=np.zeros((len(sizes), 2)))
    for point, size in zip(msg.points, sizes):
        point.effort = [1.0] * size
    return serialize_message(msg)


@pytest.mark.parametrize('sizes, match', [
    ([2, 2, 1, 2], 'point 2 has 1 effort value'),
    ([2, 3, 3, 3], 'point 1 has 3 effort value'),
    ([1, 1, 1], '1 effort value.* for 2 joint name'),
    ([3], '3 effort value.* for 2 joint name'),
])
def test_points_whose_arrays_do_not_match_are_refused_with_one_line(sizes, match):
    with pytest.raises(DataError, match=match):
        decode_joint_trajectory(_points_with(sizes))


def test_truncated_or_absurd_batches_are_refused():
    raw = encode_joint_trajectory(_stamps(20), ['x'], effort=np.ones((20, 1)))
    for cut in (30, len(raw) // 2, len(raw) - 1):
        with pytest.raises(DataError, match='malformed JointTrajectory'):
            decode_joint_trajectory(raw[:cut])
    bad = bytearray(raw)
    bad[32:36] = b'\xff\xff\xff\x7f'       # the point count (after header and 'x')
    with pytest.raises(DataError, match='malformed JointTrajectory'):
        decode_joint_trajectory(bytes(bad))


def test_an_empty_batch_decodes_to_empty_arrays():
    b = decode_joint_trajectory(encode_joint_trajectory([], ['x']))
    assert len(b) == 0 and b.effort.shape == (0, 0)


def test_column_names_the_missing_axis_or_field():
    b = decode_joint_trajectory(encode_joint_trajectory(_stamps(3), ['x', 'y'],
                                                        effort=np.ones((3, 2))))
    assert b.column('effort', 'y').tolist() == [1.0, 1.0, 1.0]
    with pytest.raises(DataError, match="axis 'z' not in message"):
        b.column('effort', 'z')
    with pytest.raises(DataError, match='no position'):
        b.column('position', 'x')


def test_remembered_shapes_give_the_bytes_and_values_of_the_general_path():
    """The encoder's templates and the decoder's remembered shapes change no byte or value."""
    from piezo_narx_ros.nodes.wire import trajectory as codec
    rng = np.random.default_rng(5)
    for names in (['x'], ['x', 'y'], ['x', 'y', 'z'], []):
        for n_pos, n_eff in ((1, 0), (0, 1), (1, 1), (len(names), len(names))):
            if names and {n_pos, n_eff} - {0, len(names)}:
                continue
            for n in (1, 2, 20):
                codec._ENCODED.clear()
                for _ in range(3):
                    t = 10**15 + rng.integers(1, 10**9, n).cumsum()
                    pos = rng.normal(size=(n, n_pos)) if n_pos else None
                    eff = rng.normal(size=(n, n_eff)) if n_eff else None
                    fast = encode_joint_trajectory(t, names, pos, eff)   # template after once
                    kept = dict(codec._ENCODED)
                    codec._ENCODED.clear()
                    assert fast == encode_joint_trajectory(t, names, pos, eff)
                    codec._ENCODED.update(kept)
                    b = decode_joint_trajectory(fast)       # remembered after the first
                    assert b.t_ns.tolist() == t.tolist()
                    assert np.array_equal(b.position, pos if n_pos else np.empty((n, 0)))
                    assert np.array_equal(b.effort, eff if n_eff else np.empty((n, 0)))
    # Same length and names, other counts inside: the remembered shape must not read it.
    from trajectory_msgs.msg import JointTrajectoryPoint

    def batch(rows):
        msg = JointTrajectory()
        msg.joint_names = ['x']
        for i, r in enumerate(rows):
            point = JointTrajectoryPoint()
            point.positions = r
            point.time_from_start.nanosec = i
            msg.points.append(point)
        return serialize_message(msg)
    good, bad = batch([[1.0], [2.0], [3.0]]), batch([[1.0, 2.0], [], [3.0]])
    assert len(good) == len(bad)
    assert decode_joint_trajectory(good).position[:, 0].tolist() == [1.0, 2.0, 3.0]
    with pytest.raises(DataError, match='point 1 has 0 positions'):
        decode_joint_trajectory(bad)


def test_command_and_deflection_batches_both_take_the_remembered_shape(monkeypatch):
    """The estimator takes both streams; a deflection batch's point 0 has a layout of its own."""
    from piezo_narx_ros.nodes.wire import trajectory as codec
    t = _stamps(20)
    cmd = encode_joint_trajectory(t, ['x'], effort=np.arange(20.0)[:, None])
    meas = encode_joint_trajectory(t, ['x'], position=-np.arange(20.0)[:, None])
    codec._SHAPES.clear()
    decode_joint_trajectory(cmd)
    decode_joint_trajectory(meas)

    def general_path(*_):
        raise AssertionError('a remembered shape was read the general way')
    monkeypatch.setattr(codec, '_read_header_names', general_path)
    for _ in range(2):
        assert decode_joint_trajectory(cmd).effort[:, 0].tolist() == list(range(20))
        assert decode_joint_trajectory(meas).position[:, 0].tolist() == [-k for k in range(20)]


def test_batches_decoded_together_equal_each_decoded_alone():
    """decode_joint_trajectories: runs of one shape in one view, anything else alone, in order."""
    from trajectory_msgs.msg import JointTrajectoryPoint

    from piezo_narx_ros.nodes.wire import trajectory as codec
    from piezo_narx_ros.nodes.wire import decode_joint_trajectories
    rng = np.random.default_rng(11)
    codec._SHAPES.clear()

    def batch(k, names, field, n=20):
        t = _stamps(n, t0=T0 + k * n * 50_000)
        values = {field: rng.normal(size=(n, len(names)))}
        return encode_joint_trajectory(t, names, **values)

    def odd_counts():      # as long as a one-axis position batch of 3, other counts inside
        msg = JointTrajectory()
        msg.joint_names = ['x']
        for i, r in enumerate([[1.0, 2.0], [], [3.0]]):
            point = JointTrajectoryPoint()
            point.positions = r
            point.time_from_start.nanosec = i
            msg.points.append(point)
        return serialize_message(msg)
    msgs = ([batch(k, ['x'], 'position') for k in range(6)]            # a run (point 0 apart)
            + [batch(6, ['x', 'y'], 'effort'), b'\x00\x01\x00\x00\x01']  # another shape, junk
            + [batch(k, ['x', 'y'], 'effort') for k in range(7, 10)]
            + [batch(10, ['x'], 'position', n=3), odd_counts(), batch(11, ['x'], 'position', n=3)]
            + [batch(k, ['x'], 'position') for k in range(12, 14)])
    for m in msgs:          # every well-formed shape seen once before, as in a running stream
        try:
            decode_joint_trajectory(m)
        except DataError:
            pass
    got = decode_joint_trajectories(msgs)
    assert sum(k for k, _ in got) == len(msgs)
    assert [k for k, _ in got][:1] == [6]           # the first run was read together
    i = 0
    for k, part in got:
        alone = []
        for m in msgs[i:i + k]:
            try:
                alone.append(decode_joint_trajectory(m))
            except DataError as exc:
                alone.append(exc)
        i += k
        if isinstance(part, DataError):
            assert k == 1 and isinstance(alone[0], DataError) and str(part) == str(alone[0])
            continue
        assert all(isinstance(a, codec.SampleBatch) and a.names == part.names for a in alone)
        assert part.t_ns.tolist() == [s for a in alone for s in a.t_ns.tolist()]
        assert np.array_equal(part.position, np.concatenate([a.position for a in alone]))
        assert np.array_equal(part.effort, np.concatenate([a.effort for a in alone]))
    refused = [str(p) for _, p in got if isinstance(p, DataError)]
    assert len(refused) == 2 and any('point 1 has 0 positions' in r for r in refused)
    assert decode_joint_trajectories([]) == []
