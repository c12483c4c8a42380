"""nodes/ plumbing: QoS, validated parameters, JointState/CDR codec, diagnostics (in-process)."""
import time

import numpy as np
import pytest
import rclpy
from rclpy.parameter import Parameter
from rclpy.qos import ReliabilityPolicy

from piezo_narx_ros.errors import ConfigError, DataError
from piezo_narx_ros.nodes.wire import (decode_joint_state, encode_joint_state, make_joint_state,
                                       parse_joint_state)
from piezo_narx_ros.nodes.diagnostics import DIAG_WARN, Diagnostics, diagnostic_values, status_node
from piezo_narx_ros.nodes.params import ParamSpec
from piezo_narx_ros.nodes.qos import sample_qos
from piezo_narx_ros.nodes.runtime import PiezoNode, make_executor


@pytest.fixture
def ctx():
    context = rclpy.Context()
    rclpy.init(context=context)
    yield context
    rclpy.try_shutdown(context=context)


SPECS = [
    ParamSpec('fs', 2000.0, 'sample rate, Hz', low=1.0, high=1e5),
    ParamSpec('depth', 100, 'queue depth', low=1, high=10000),
    ParamSpec('kind', 'sine', 'signal', choices=('sine', 'prbs')),
    ParamSpec('axis', 'x', 'axis name', check=(lambda v: bool(v.strip()), 'must not be empty')),
    ParamSpec('gain', 1.0, 'fixed gain', low=0.0, high=10.0, read_only=True),
]


class _Node(PiezoNode):
    NODE_NAME = 'common_test'
    PARAMS = SPECS


def _make(ctx, **overrides):
    return _Node(context=ctx, parameter_overrides=[Parameter(k, value=v)
                                                   for k, v in overrides.items()])


def test_sample_qos_is_reliable_keep_last_10000():
    q = sample_qos()
    assert q.reliability == ReliabilityPolicy.RELIABLE and q.depth == 10000
    assert sample_qos(depth=5).depth == 5
    with pytest.raises(ConfigError):
        sample_qos(depth=0)


def test_parameters_declared_with_descriptor_and_int_accepted_for_float(ctx):
    from rcl_interfaces.msg import ParameterType
    node = _make(ctx, fs=500, gain=2)
    try:
        assert node.params == {'fs': 500.0, 'depth': 100, 'kind': 'sine', 'axis': 'x',
                               'gain': 2.0}
        assert isinstance(node.params['fs'], float)
        # `-p fs:=500` is stored as the double 500.0, not as an integer (what `ros2 param get`
        # and every parameter client see)
        stored = node.get_parameter('fs')
        assert stored.type_ == Parameter.Type.DOUBLE and stored.value == 500.0
        assert node.get_parameter('gain').type_ == Parameter.Type.DOUBLE
        d = node.describe_parameter('fs')
        assert d.description == 'sample rate, Hz' and d.type == ParameterType.PARAMETER_DOUBLE
        assert not d.dynamic_typing
        assert d.floating_point_range[0].from_value == 1.0
        assert node.describe_parameter('depth').integer_range[0].to_value == 10000
        # read-only parameters carry their range too
        g = node.describe_parameter('gain')
        assert g.read_only and g.type == ParameterType.PARAMETER_DOUBLE
        assert (g.floating_point_range[0].from_value, g.floating_point_range[0].to_value) == \
            (0.0, 10.0)
        assert node.get_namespace() == '/piezo'
    finally:
        node.destroy_node()


@pytest.mark.parametrize('overrides, fragment', [
    ({'fs': -3.0}, 'fs must be >= 1.0'),
    ({'fs': 'abc'}, 'fs must be a number'),
    ({'depth': 0}, 'depth must be >= 1'),
    ({'kind': 'square'}, "kind must be one of ['sine', 'prbs']"),
    ({'axis': ' '}, 'axis must not be empty'),
    ({'kind': 3}, 'parameter kind'),
    ({'gain': 11.0}, 'gain must be <= 10.0'),
])
def test_bad_start_values_refused_with_one_line_reason(ctx, overrides, fragment):
    with pytest.raises(ConfigError) as info:
        _make(ctx, **overrides)
    msg = str(info.value)
    assert fragment in msg and '\n' not in msg


def test_runtime_set_is_validated(ctx):
    node = _make(ctx)
    try:
        res = node.set_parameters([Parameter('kind', value='nope')])[0]
        assert not res.successful and 'kind must be one of' in res.reason
        res = node.set_parameters([Parameter('fs', value=float('nan'))])[0]
        assert not res.successful
        assert node.set_parameters([Parameter('kind', value='prbs')])[0].successful
        assert not node.set_parameters([Parameter('gain', value=2.0)])[0].successful
        assert node.describe_parameter('gain').read_only
    finally:
        node.destroy_node()


def test_joint_state_round_trip_keeps_exact_nanoseconds():
    t_ns = 1_700_000_000 * 10**9 + 123_456_789
    msg = make_joint_state(t_ns, ['x', 'y'], position=[1e-6, 2e-6], effort=[10.0, -5.0])
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (1_700_000_000, 123_456_789)
    s = parse_joint_state(msg)
    assert s.t_ns == t_ns
    assert s.value('position', 'y') == 2e-6 and s.value('effort', 'x') == 10.0
    with pytest.raises(DataError, match="axis 'z'"):
        s.value('effort', 'z')
    unnamed = parse_joint_state(make_joint_state(5, [], effort=[3.0]))
    assert unnamed.value('effort', 'x') == 3.0
    with pytest.raises(DataError, match='no position'):
        unnamed.value('position', 'x')


def test_diagnostics_status_carries_node_name_level_and_values(ctx):
    node = _make(ctx)
    try:
        state = {'n': 3}
        diag = Diagnostics(node, lambda: (DIAG_WARN, 'late',
                                          {'count': state['n'], 'rms': 1.5e-7}),
                           task='sample stream', hardware_id='udp://10.0.0.2:50000')
        arr = diag.build()
        assert len(arr.status) == 1
        st = arr.status[0]
        # diagnostic_updater's naming: fully qualified node name without the slash, ': ', task
        assert st.name == 'piezo/common_test: sample stream' and st.level == DIAG_WARN
        assert st.hardware_id == 'udp://10.0.0.2:50000'
        assert status_node(st.name) == '/piezo/common_test'
        assert diagnostic_values(st) == {'count': '3', 'rms': '1.5e-07'}
        state['n'] = 4
        assert diagnostic_values(diag.build().status[0])['count'] == '4'
    finally:
        node.destroy_node()


def test_make_executor_rejects_unknown_kind():
    with pytest.raises(ConfigError, match='executor'):
        make_executor('threads')


@pytest.mark.parametrize('names, position, velocity, effort, frame', [
    (['x'], [1e-6], [], [10.0], ''),
    (['x', 'yy', 'zzz'], [1.0, -2.0, 3.5], [0.1], [4.0, 5.0, 6.0], 'abc'),
    ([], [], [], [3.0], 'frame_with_odd_length'),
    (['axis_0'], [], [], [], ''),
])
def test_cdr_decode_reads_what_rclpy_serialises(names, position, velocity, effort, frame):
    from rclpy.serialization import serialize_message
    msg = make_joint_state(1_795_241_581_123_456_789, names, position, effort)
    msg.velocity = velocity
    msg.header.frame_id = frame
    s = decode_joint_state(serialize_message(msg))
    assert (s.t_ns, s.names, s.position, s.effort) == (1_795_241_581_123_456_789, names,
                                                       position, effort)


@pytest.mark.parametrize('names, position, effort', [
    (['x'], [1e-6], [10.0]), (['x', 'long_name'], [1.5], [2.0, -3.0]), ([], [], [7.0]),
    (['ab', 'c'], [], []),
])
def test_cdr_encode_is_read_back_by_rclpy(names, position, effort):
    from rclpy.serialization import deserialize_message
    from sensor_msgs.msg import JointState
    msg = deserialize_message(encode_joint_state(123_000_000_007, names, position, effort),
                              JointState)
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (123, 7)
    assert (list(msg.name), list(msg.position), list(msg.effort)) == (names, position, effort)
    assert msg.header.frame_id == '' and list(msg.velocity) == []


@pytest.mark.parametrize('names, position, velocity, effort, frame', [
    (['x'], [1e-6], [], [10.0], ''),
    (['x', 'yy', 'zzz'], [1.0, -2.0, 3.5], [0.1], [4.0, 5.0, 6.0], 'abc'),
    ([], [], [], [3.0], 'frame_with_odd_length'),
])
@pytest.mark.parametrize('little_endian', [False, True])
def test_cdr_decode_reads_both_byte_orders_as_rosbags_writes_them(
        names, position, velocity, effort, frame, little_endian):
    """
    DDS peers may send big-endian CDR (encapsulation 0x0000).

    Rclpy here only writes little endian, so rosbags' serialiser is the reference for both orders.
    """
    from rosbags.typesys import Stores, get_typestore
    store = get_typestore(Stores.ROS2_KILTED)
    JointState = store.types['sensor_msgs/msg/JointState']
    Header, Time = store.types['std_msgs/msg/Header'], store.types['builtin_interfaces/msg/Time']
    msg = JointState(header=Header(stamp=Time(sec=1_795_241_581, nanosec=123_456_789),
                                   frame_id=frame),
                     name=names, position=np.array(position, dtype=np.float64),
                     velocity=np.array(velocity, dtype=np.float64),
                     effort=np.array(effort, dtype=np.float64))
    raw = bytes(store.serialize_cdr(msg, 'sensor_msgs/msg/JointState',
                                    little_endian=little_endian))
    assert raw[1] == int(little_endian)          # the encapsulation says which order follows
    s = decode_joint_state(raw)
    assert (s.t_ns, s.names, s.position, s.effort) == (1_795_241_581_123_456_789, names,
                                                       position, effort)


@pytest.mark.parametrize('t_ns, names, position, effort', [
    (1_795_241_581_123_456_789, ['', 'a', 'ab', 'abc'], [1.0], [2.0, 3.0]),   # every padding
    (7, ['abcd', 'e'], [1.0, 2.0], []),
    (-1_500_000_000, ['x'], [], [4.0]),                                       # before 1970
    (3, ['ab'], [], [5.0]),                          # the array count after an odd string end
])
def test_cdr_encode_is_byte_for_byte_what_rosbags_serialises(t_ns, names, position, effort):
    # Padding between the strings and before the doubles as the CDR rules place it (rosbags'
    # serialiser is the reference), and the stamp's sign read back.
    from rosbags.typesys import Stores, get_typestore
    store = get_typestore(Stores.ROS2_KILTED)
    JointState = store.types['sensor_msgs/msg/JointState']
    Header, Time = store.types['std_msgs/msg/Header'], store.types['builtin_interfaces/msg/Time']
    sec, nsec = divmod(t_ns, 10**9)
    msg = JointState(header=Header(stamp=Time(sec=sec, nanosec=nsec), frame_id=''), name=names,
                     position=np.array(position, dtype=np.float64),
                     velocity=np.array([], dtype=np.float64),
                     effort=np.array(effort, dtype=np.float64))
    ref = bytes(store.serialize_cdr(msg, 'sensor_msgs/msg/JointState', little_endian=True))
    raw = encode_joint_state(t_ns, names, position, effort)
    assert raw == ref
    s = decode_joint_state(raw)
    assert (s.t_ns, s.names, s.position, s.effort) == (t_ns, names, position, effort)


@pytest.mark.parametrize('offset', [12, 20, 24])   # frame_id length, name count, name length
def test_cdr_decode_refuses_a_length_field_beyond_any_buffer(offset):
    raw = bytearray(encode_joint_state(5, ['x'], [1.0], [2.0]))
    raw[offset:offset + 4] = b'\xff\xff\xff\xff'
    with pytest.raises(DataError, match='malformed JointState'):
        decode_joint_state(bytes(raw))


def test_cdr_decode_refuses_truncated_bytes():
    from rclpy.serialization import serialize_message
    raw = serialize_message(make_joint_state(5, ['x'], effort=[1.0]))
    with pytest.raises(DataError, match='malformed JointState'):
        decode_joint_state(raw[:30])


def test_remembered_joint_states_give_the_bytes_and_values_of_the_general_path():
    """The encoder's templates and the decoder's remembered shapes change no byte or value."""
    from rclpy.serialization import serialize_message

    from piezo_narx_ros.nodes.wire import joint_state as codec
    rng = np.random.default_rng(4)
    cases = [(['x'], 1, 0), (['x'], 0, 1), (['x'], 1, 1), (['x', 'yy', 'zzz'], 3, 3),
             (['ab', 'c'], 0, 0), ([], 0, 1)]
    for names, n_pos, n_eff in cases:
        codec._STATE_ENCODED.clear()
        codec._STATE_SHAPES.clear()
        for t_ns in (1_795_241_581_123_456_789, -1_500_000_001, 7):
            pos, eff = rng.normal(size=n_pos).tolist(), rng.normal(size=n_eff).tolist()
            fast = encode_joint_state(t_ns, names, pos, eff)     # a template after the first
            kept = dict(codec._STATE_ENCODED)
            codec._STATE_ENCODED.clear()
            assert fast == encode_joint_state(t_ns, names, pos, eff)
            codec._STATE_ENCODED.update(kept)
            for _ in range(2):                                  # general, then remembered
                s = decode_joint_state(fast)
                assert (s.t_ns, s.names, s.position, s.effort) == (t_ns, names, pos, eff)
            assert codec._STATE_SHAPES[len(fast)]
    # As long as a remembered message, other names or counts inside: read the general way.
    codec._STATE_SHAPES.clear()
    first = serialize_message(make_joint_state(5, ['ab'], [1.0, 2.0], []))
    other = serialize_message(make_joint_state(6, ['cd'], [3.0, 4.0], []))
    moved = serialize_message(make_joint_state(7, ['ab'], [5.0], [6.0]))
    assert len(first) == len(other) == len(moved)
    for raw, want in ((first, (['ab'], [1.0, 2.0], [])), (first, (['ab'], [1.0, 2.0], [])),
                      (other, (['cd'], [3.0, 4.0], [])), (moved, (['ab'], [5.0], [6.0]))):
        s = decode_joint_state(raw)
        assert (s.names, s.position, s.effort) == want
    # A remembered shape's names are the caller's own list.
    decode_joint_state(first).names.append('z')
    assert decode_joint_state(first).names == ['ab']


class _Backlog:
    """An executor and a draining node: each spin takes one of `n` queued messages."""

    def __init__(self, n):
        self.n, self.taken, self.spins = n, 0, 0

    def spin_once(self, timeout_sec):
        self.spins += 1
        if self.taken < self.n:
            self.taken += 1
        else:
            time.sleep(timeout_sec)                     # nothing ready: waits as rclpy does

    def drain_count(self):
        return self.taken


def test_a_stop_signal_drains_what_was_delivered_then_stops():
    from piezo_narx_ros.nodes import runtime
    queued = _Backlog(500)
    runtime._drain(queued, queued)
    assert queued.taken == 500                          # nothing delivered is left behind
    assert queued.spins <= 500 + 20                     # and it stops once the queue is quiet
    # A stream that never ends (a publisher still running) is cut at DRAIN_S.
    endless = _Backlog(10 ** 9)
    start = time.monotonic()
    runtime._drain(endless, endless)
    assert runtime.DRAIN_S <= time.monotonic() - start < runtime.DRAIN_S + 1.0
    assert PiezoNode.drain_count(None) is None          # other nodes stop at once
