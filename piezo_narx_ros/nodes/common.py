"""
Plumbing shared by every node: QoS, validated parameters, /diagnostics, JointState, main().

Nodes stay thin: they declare parameters through `declare_parameters` (one `ParamSpec` each), build
their QoS with `sample_qos`, convert messages with `make_joint_state` / `parse_joint_state`, report
health through `Diagnostics`, and start from `run_node`.

Stamps are carried as integer nanoseconds (`int`) inside the nodes, so that t_k = t0 + k/fs is
exact and never accumulates float error over long runs.
"""
from __future__ import annotations

import copy
import math
import signal
import struct
import sys
from dataclasses import dataclass
from typing import Any, Callable, Iterable, Sequence

import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor,
                                ParameterType, SetParametersResult)
from rclpy.exceptions import ParameterException
from rclpy.node import Node
from rclpy.duration import Duration, Infinite
from rclpy.event_handler import PublisherEventCallbacks, SubscriptionEventCallbacks
from rclpy.parameter import Parameter
from rclpy.qos import (DurabilityPolicy, HistoryPolicy, QoSCompatibility, QoSProfile,
                       ReliabilityPolicy, qos_check_compatible)
from rclpy.qos_overriding_options import QoSOverridingOptions
from sensor_msgs.msg import JointState

from piezo_narx_ros.errors import ConfigError, DataError, PiezoNarxError

# Topic names (relative; the default namespace `piezo` is given at start-up, see DESIGN.md).
TOPIC_COMMAND = 'voltage_command'
TOPIC_DEFLECTION = 'deflection'
TOPIC_ESTIMATE = 'deflection_estimate'
TOPIC_REFERENCE = 'position_reference'
TOPIC_DIAGNOSTICS = '/diagnostics'
DEFAULT_NAMESPACE = 'piezo'

# Exit codes of a node process.
EXIT_OK = 0
EXIT_FAILURE = 1       # unexpected exception
EXIT_CONFIG = 2        # refused to start: bad parameter, missing model file, ...

# Signals that stop a node cleanly (SIGHUP: its terminal was closed).
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)

DIAG_OK = DiagnosticStatus.OK
DIAG_WARN = DiagnosticStatus.WARN
DIAG_ERROR = DiagnosticStatus.ERROR


# --------------------------------------------------------------------------------------------- QoS
# Keep-last depth of the per-sample streams: 5 s at 2 kHz, so a stalled subscriber loses nothing
# (memory is used only while it is behind). With 1000, a CPU-starved estimator lost commands.
SAMPLE_DEPTH = 10000


def sample_qos(depth: int = SAMPLE_DEPTH) -> QoSProfile:
    """
    Return the QoS of the per-sample streams.

    Reliable, keep-last `depth`, volatile (identification must lose nothing). Users change it with
    the standard QoS overrides (see `qos_overriding`), not with per-node parameters.
    """
    if depth < 1:
        raise ConfigError(f'qos depth must be >= 1, got {depth}')
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=int(depth),
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.VOLATILE,
    )


def qos_overriding() -> QoSOverridingOptions:
    """
    Return rclpy's standard QoS overrides (history, depth, reliability) for one endpoint.

    One publisher or subscription: read-only parameters
    `qos_overrides./TOPIC.publisher.reliability` etc., set with `-p` or a params file like any
    parameter (docs/nodes.md).
    """
    return QoSOverridingOptions.with_default_policies()


def _unset_infinite(profile: QoSProfile) -> QoSProfile:
    """
    Copy `profile` with infinite deadline, lifespan and liveliness lease written as unset (0).

    The graph reports a peer's unset durations as Infinite while our own profiles hold 0; both mean
    'none', but rmw's compatibility check reads Infinite-against-0 as 'Subscription has a deadline,
    but publisher does not'.
    """
    out = copy.copy(profile)
    for name in ('deadline', 'lifespan', 'liveliness_lease_duration'):
        if getattr(out, name) == Infinite:
            setattr(out, name, Duration())
    return out


class QosWatch:
    """
    Incompatible QoS between a node's sample streams and their peers, for /diagnostics.

    Endpoints registered with `add` get rclpy's incompatible-QoS event callback, which logs the
    moment it happens, and are checked against the ROS graph at every diagnostics tick
    (`problems`), so the warning lasts as long as the incompatible peer exists rather than one
    tick: a best-effort publisher leaves a reliable subscriber with nothing, and only the graph
    says so while it lasts.
    """

    def __init__(self, node: Node):
        self._node = node
        self._endpoints: list[tuple[str, Any]] = []   # ('publisher' | 'subscription', entity)
        self.events = 0

    def callbacks(self, kind: str, topic: str):
        """Return the event callbacks to pass to create_publisher / create_subscription."""
        def on_incompatible(status) -> None:
            self.events += 1
            policy = getattr(status.last_policy_kind, 'name', str(status.last_policy_kind))
            self._node.get_logger().warning(
                f'incompatible QoS on {self._node.resolve_topic_name(topic)} ({kind}, policy '
                f'{policy.replace("RMW_QOS_POLICY_", "").lower()}): no messages flow between '
                'this node and that peer; set the qos_overrides parameters of one side')
        if kind == 'publisher':
            return PublisherEventCallbacks(incompatible_qos=on_incompatible)
        return SubscriptionEventCallbacks(incompatible_qos=on_incompatible)

    def add(self, kind: str, entity) -> None:
        """Watch a publisher or subscription (kind 'publisher' or 'subscription')."""
        self._endpoints.append((kind, entity))

    def remove(self, entity) -> None:
        """Stop watching an endpoint (before it is destroyed)."""
        self._endpoints = [(k, e) for k, e in self._endpoints if e is not entity]

    def problems(self) -> list[str]:
        """One line per (own endpoint, peer) pair whose QoS cannot match, from the graph now."""
        node, out = self._node, []
        me = (node.get_namespace(), node.get_name())
        for kind, ent in self._endpoints:
            topic = ent.topic_name
            if kind == 'subscription':
                peers = node.get_publishers_info_by_topic(topic)
            else:
                peers = node.get_subscriptions_info_by_topic(topic)
            for info in peers:
                if (info.node_namespace, info.node_name) == me:
                    continue
                mine, theirs = _unset_infinite(ent.qos_profile), _unset_infinite(info.qos_profile)
                pub, sub = (theirs, mine) if kind == 'subscription' else (mine, theirs)
                compat, reason = qos_check_compatible(pub, sub)
                if compat == QoSCompatibility.ERROR:
                    peer = f'{info.node_namespace.rstrip("/")}/{info.node_name}'
                    out.append(f'{topic}: {peer} cannot match this {kind} ({reason.strip()})')
        return out


# ------------------------------------------------------------------------------------- parameters
@dataclass(frozen=True)
class ParamSpec:
    """
    One node parameter: default (its type fixes the parameter type), description and limits.

    `low`/`high` are inclusive bounds for numbers (published in the descriptor so that tools show
    them), `choices` a closed set for strings, `check` an extra predicate with its reason, e.g.
    `(lambda v: v > 0, 'must be > 0')`.
    """

    name: str
    default: Any
    description: str
    low: float | None = None
    high: float | None = None
    choices: tuple | None = None
    read_only: bool = False
    check: tuple[Callable[[Any], bool], str] | None = None

    @property
    def is_float(self) -> bool:
        return isinstance(self.default, float)

    def descriptor(self, final: bool = True) -> ParameterDescriptor:
        """
        Return the ParameterDescriptor carrying the description, the range and the read-only flag.

        `final=False` is the descriptor used to declare the parameter: writable, no range, and
        dynamically typed for floats, so that `-p fs:=500` (an integer) reaches our own check and
        its one-line message. `declare_parameters` then applies the final descriptor, which fixes
        the type (a float parameter holds 500.0), the range and the read-only flag.
        """
        d = ParameterDescriptor(name=self.name, description=self.description,
                                read_only=self.read_only and final,
                                dynamic_typing=self.is_float and not final)
        if self.is_float and final:
            d.type = ParameterType.PARAMETER_DOUBLE
        notes = []
        if self.choices is not None:
            notes.append('one of: ' + ', '.join(map(str, self.choices)))
        numeric = isinstance(self.default, (int, float)) and not isinstance(self.default, bool)
        if numeric and self.low is not None and self.high is not None and final:
            if self.is_float:
                d.floating_point_range = [FloatingPointRange(
                    from_value=float(self.low), to_value=float(self.high), step=0.0)]
            else:
                d.integer_range = [IntegerRange(from_value=int(self.low), to_value=int(self.high),
                                                step=0)]
        if self.low is not None:
            notes.append(f'>= {self.low}')
        if self.high is not None:
            notes.append(f'<= {self.high}')
        if self.check is not None:
            notes.append(self.check[1])
        d.additional_constraints = '; '.join(notes)
        return d

    def validate(self, value: Any) -> str | None:
        """Reason why `value` is refused, or None when it is acceptable."""
        if value is None:
            return (f'{self.name} has no value (`[]` has no type in ROS 2; give at least one '
                    f'element, default {self.default!r})')
        if self.is_float and (isinstance(value, bool) or not isinstance(value, (int, float))):
            return f'{self.name} must be a number, got {value!r}'
        if isinstance(value, float) and not math.isfinite(value):
            return f'{self.name} must be finite, got {value}'
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            if self.low is not None and value < self.low:
                return f'{self.name} must be >= {self.low}, got {value}'
            if self.high is not None and value > self.high:
                return f'{self.name} must be <= {self.high}, got {value}'
        if self.choices is not None and value not in self.choices:
            return f'{self.name} must be one of {list(self.choices)}, got {value!r}'
        if self.check is not None:
            try:
                ok = self.check[0](value)
            except (TypeError, ValueError, AttributeError):   # e.g. len() of a number
                ok = False
            if not ok:
                return f'{self.name} {self.check[1]}, got {value!r}'
        return None


def declare_parameters(node: Node, specs: Iterable[ParamSpec]) -> dict[str, Any]:
    """
    Declare every spec on `node` and validate the start-up values and later changes.

    Later `set_parameters` calls are validated too. Returns {name: value}. Raises ConfigError (one
    line) on a bad value.
    """
    specs = list(specs)
    by_name = {s.name: s for s in specs}
    values: dict[str, Any] = {}
    for spec in specs:
        try:
            # Declared loosely first (see ParamSpec.descriptor), so a bad value gets our message.
            param = node.declare_parameter(spec.name, spec.default, spec.descriptor(final=False))
        except ParameterException as exc:  # wrong type
            raise ConfigError(f'parameter {spec.name}: {_one_line(exc)}') from None
        value = param.value
        reason = spec.validate(value)
        if reason:
            raise ConfigError(f'parameter {reason}')
        if spec.is_float:
            value = float(value)
        final = spec.descriptor(final=True)
        if not spec.is_float:
            final.type = node.describe_parameter(spec.name).type  # set_descriptor insists on it
        # The stored value becomes the checked one (500 -> 500.0 for a float), then the range and
        # read-only flag apply: `ros2 param describe` shows the bounds of read-only ones too.
        node.set_descriptor(spec.name, final,
                            Parameter(spec.name, value=value).get_parameter_value())
        values[spec.name] = value

    def on_set(params) -> SetParametersResult:
        for p in params:
            spec = by_name.get(p.name)
            if spec is None:
                continue
            reason = spec.validate(p.value)
            if reason:
                return SetParametersResult(successful=False, reason=reason)
        return SetParametersResult(successful=True)

    node.add_on_set_parameters_callback(on_set)
    return values


def _one_line(exc: BaseException) -> str:
    return ' '.join(str(exc).split())


# ---------------------------------------------------------------------------------- JointState
def ns_to_stamp(t_ns: int) -> tuple[int, int]:
    """Integer nanoseconds -> (sec, nanosec) of builtin_interfaces/Time."""
    sec, nsec = divmod(int(t_ns), 1_000_000_000)
    return sec, nsec


def stamp_to_ns(stamp) -> int:
    """builtin_interfaces/Time -> integer nanoseconds."""
    return stamp.sec * 1_000_000_000 + stamp.nanosec


def make_joint_state(t_ns: int, names: Sequence[str], position: Sequence[float] | None = None,
                     effort: Sequence[float] | None = None) -> JointState:
    """Build the JointState of one sample: stamp t_ns (ns), names, position (m), effort (V)."""
    msg = JointState()
    msg.header.stamp.sec, msg.header.stamp.nanosec = ns_to_stamp(t_ns)
    msg.name = list(names)
    if position is not None:
        msg.position = [float(v) for v in position]
    if effort is not None:
        msg.effort = [float(v) for v in effort]
    return msg


@dataclass
class Sample:
    """One parsed JointState: stamp (ns), axis names, positions (m) and efforts (V)."""

    t_ns: int
    names: list[str]
    position: list[float]
    effort: list[float]

    def value(self, field: str, axis: str) -> float:
        """Return the `field` ('position' or 'effort') of `axis`; raises DataError when absent."""
        seq = self.position if field == 'position' else self.effort
        if not self.names:
            i = 0  # an unnamed single-axis message
        else:
            try:
                i = self.names.index(axis)
            except ValueError:
                raise DataError(f'axis {axis!r} not in message (names: {self.names})') from None
        if i >= len(seq):
            raise DataError(f'message has no {field} for axis {axis!r}')
        return float(seq[i])


def parse_joint_state(msg: JointState) -> Sample:
    """Convert a JointState to a Sample (no validation of values; see Sample.value)."""
    return Sample(stamp_to_ns(msg.header.stamp), list(msg.name), list(msg.position),
                  list(msg.effort))


# ------------------------------------------------------------------- JointState as CDR bytes
# rclpy turns every received JointState into a Python object (about 20 us here) and back on
# publish (about 6 us). The sample streams carry one stamp and one or two numbers, so the nodes
# subscribe with raw=True and read/write the CDR bytes directly (about 2 us each way). The layout
# is the OMG CDR of sensor_msgs/msg/JointState: 4-byte encapsulation header, then header.stamp
# (int32 sec, uint32 nanosec), header.frame_id (string), name (sequence<string>), position,
# velocity, effort (sequence<float64>); primitives aligned to their size from the byte after the
# encapsulation header. Test: test_nodes_common.py checks both directions against rclpy's own.
_U32 = struct.Struct('<I')
_STAMP = struct.Struct('<iI')


def decode_joint_state(buf: bytes) -> Sample:
    """
    Decode a serialized JointState (CDR, as from a raw=True subscription) to a Sample.

    Raises DataError on a truncated or malformed buffer.
    """
    try:
        little = buf[1] == 1
        e = '<' if little else '>'
        data = memoryview(buf)[4:]
        sec, nsec = struct.unpack_from(e + 'iI', data, 0)
        (n,) = struct.unpack_from(e + 'I', data, 8)
        off = 12 + n
        off = (off + 3) & ~3
        (count,) = struct.unpack_from(e + 'I', data, off)
        off += 4
        names = []
        for _ in range(count):
            off = (off + 3) & ~3
            (n,) = struct.unpack_from(e + 'I', data, off)
            names.append(bytes(data[off + 4:off + 3 + n]).decode())
            off += 4 + n
        arrays = []
        for _ in range(3):
            off = (off + 3) & ~3
            (count,) = struct.unpack_from(e + 'I', data, off)
            off += 4
            if count:
                off = (off + 7) & ~7
                arrays.append(list(struct.unpack_from(f'{e}{count}d', data, off)))
                off += 8 * count
            else:
                arrays.append([])
    except (struct.error, IndexError, UnicodeDecodeError) as exc:
        raise DataError(f'malformed JointState ({len(buf)} bytes): {exc}') from None
    return Sample(sec * 1_000_000_000 + nsec, names, arrays[0], arrays[2])


def encode_joint_state(t_ns: int, names: Sequence[str], position: Sequence[float] = (),
                       effort: Sequence[float] = ()) -> bytes:
    """Encode JointState CDR (little endian, empty frame_id and velocity) for Publisher.publish."""
    sec, nsec = divmod(int(t_ns), 1_000_000_000)
    out = bytearray(b'\x00\x01\x00\x00')
    out += _STAMP.pack(sec, nsec)
    out += b'\x01\x00\x00\x00\x00\x00\x00\x00'      # frame_id '' (length 1: the NUL) + pad
    out += _U32.pack(len(names))
    for name in names:
        raw = name.encode() + b'\x00'
        out += b'\x00' * (-(len(out) - 4) % 4)
        out += _U32.pack(len(raw)) + raw
    for values in (position, (), effort):
        out += b'\x00' * (-(len(out) - 4) % 4)
        out += _U32.pack(len(values))
        if len(values):
            out += b'\x00' * (-(len(out) - 4) % 8)
            out += struct.pack(f'<{len(values)}d', *values)
    return bytes(out)


# ---------------------------------------------------------------------------------- diagnostics
class Diagnostics:
    """
    Publishes one DiagnosticStatus for `node` on /diagnostics every `period` s.

    `provider()` returns (level, message, {key: value}); level is DIAG_OK/WARN/ERROR. The provider
    is read only at publication time, so the nodes' hot paths just bump counters.

    The status is named `NODE: TASK` as ros/diagnostics' diagnostic_updater names it (NODE is the
    fully qualified node name without its leading slash, e.g. `piezo/driver_node: rig link`), so
    aggregators and rqt_robot_monitor group it like any other node's. `hardware_id` names the
    device the status is about (the rig address for the driver); 'none' when there is none, as
    diagnostic_updater asks.
    """

    def __init__(self, node: Node, provider: Callable[[], tuple[bytes, str, dict]],
                 task: str, hardware_id: str = 'none', period: float = 1.0):
        self._node = node
        self._provider = provider
        self.name = status_name(node.get_fully_qualified_name(), task)
        self.hardware_id = hardware_id
        self._pub = node.create_publisher(DiagnosticArray, TOPIC_DIAGNOSTICS, 10)
        self._timer = node.create_timer(period, self.publish)

    def build(self) -> DiagnosticArray:
        """
        Return the DiagnosticArray that would be published now.

        The provider's status, raised to WARN while a QoS incompatibility with a peer lasts (see
        QosWatch).
        """
        level, message, values = self._provider()
        watch = getattr(self._node, 'qos_watch', None)
        problems = watch.problems() if watch is not None else []
        if problems:
            level = max(level, DIAG_WARN)
            more = f' (+{len(problems) - 1} more)' if len(problems) > 1 else ''
            message = f'incompatible QoS: {problems[0]}{more}; ' + message
            values = {**values, 'incompatible_qos': len(problems)}
        status = DiagnosticStatus(level=level, name=self.name,
                                  message=message, hardware_id=self.hardware_id,
                                  values=[KeyValue(key=str(k), value=_fmt(v))
                                          for k, v in values.items()])
        arr = DiagnosticArray(status=[status])
        arr.header.stamp = self._node.get_clock().now().to_msg()
        return arr

    def publish(self) -> None:
        """Publish one status now (also called by the timer)."""
        self._pub.publish(self.build())


def status_name(node_fqn: str, task: str) -> str:
    """
    Name a status as diagnostic_updater does.

    '/piezo/driver_node', 'rig link' -> 'piezo/driver_node: rig link'.
    """
    return f'{node_fqn.lstrip("/")}: {task}'


def status_node(name: str) -> str:
    """Return the node of a status named by `status_name` ('/piezo/driver_node')."""
    return '/' + name.split(': ', 1)[0].lstrip('/')


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return f'{v:.6g}'
    return str(v)


def diagnostic_values(status: DiagnosticStatus) -> dict[str, str]:
    """{key: value} of one DiagnosticStatus (for tests and tools)."""
    return {kv.key: kv.value for kv in status.values}


# ---------------------------------------------------------------------------------------- main
def make_executor(kind: str = 'events'):
    """
    Return the executor of a name.

    'events' -> rclpy.experimental.EventsExecutor (C++ event loop; pub->sub latency ~14 us here
    against ~92 us with the single-threaded executor), 'single' -> SingleThreadedExecutor.
    """
    if kind == 'events':
        from rclpy.experimental import EventsExecutor
        return EventsExecutor()
    if kind == 'single':
        from rclpy.executors import SingleThreadedExecutor
        return SingleThreadedExecutor()
    raise ConfigError(f"executor must be 'events' or 'single', got {kind!r}")


def run_node(node_cls: Callable[..., Node], args: list[str] | None = None,
             executor: str | None = None) -> int:
    """
    Run a node process: init, construct, spin, clean shutdown. Returns the exit code.

    SIGINT/SIGTERM/SIGHUP stop the spin and exit 0 (SIGHUP: the terminal was closed; a recorder
    must close its bag then, not die); a node that refuses to start (ConfigError or any
    PiezoNarxError from its constructor) prints one line `NAME: error: reason` and exits 2; any
    other exception exits 1. The executor is EventsExecutor unless PIEZO_NARX_EXECUTOR=single or
    `executor` says otherwise.
    """
    import os
    import threading

    from rclpy.executors import ExternalShutdownException
    from rclpy.signals import SignalHandlerOptions

    if args is None:
        args = sys.argv
    kind = executor or os.environ.get('PIEZO_NARX_EXECUTOR', 'events')
    prog = getattr(node_cls, 'NODE_NAME', node_cls.__name__)
    stop = threading.Event()
    # Our own handlers only set a flag: the spin loop then ends between callbacks, so no callback
    # ever runs on a context that a signal has already shut down (rclpy's handlers do that, and
    # publish() in a running callback then fails). EventsExecutor.spin() also ignores shutdown.
    for sig in STOP_SIGNALS:
        signal.signal(sig, lambda *_: stop.set())
    code = EXIT_OK
    node = None
    ex = None
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    try:
        node = node_cls()
        check_overrides(node)
        ex = make_executor(kind)
        ex.add_node(node)
        paced = node.take_pacing() if isinstance(node, PiezoNode) else False
        timeout = 0.1
        while not stop.is_set() and rclpy.ok():
            ex.spin_once(timeout_sec=timeout)
            if paced and not stop.is_set():
                timeout = node.pace()
    except (KeyboardInterrupt, ExternalShutdownException):
        code = EXIT_OK
    except PiezoNarxError as exc:
        print(f'{prog}: error: {_one_line(exc)}', file=sys.stderr, flush=True)
        code = EXIT_CONFIG
    except Exception as exc:  # noqa: BLE001 - last resort: one line, non-zero
        print(f'{prog}: error: {type(exc).__name__}: {_one_line(exc)}', file=sys.stderr,
              flush=True)
        code = EXIT_FAILURE
    finally:
        if ex is not None:
            ex.shutdown()
        if node is not None:
            try:
                node.close()  # node-specific cleanup hook (see PiezoNode)
            except Exception:  # noqa: BLE001 - never mask the real exit reason
                pass
            node.destroy_node()
        rclpy.try_shutdown()
    return code


# Parameters replaced by the standard QoS overrides (issue 10): refused with the new name rather
# than silently ignored, since a user who sets them expects a QoS change.
RETIRED_QOS_PARAMETERS = ('best_effort', 'qos_depth', 'depth')


def check_overrides(node: Node) -> None:
    """
    Refuse retired QoS parameters with a hint.

    Warn about other parameters that were given but that `node` does not declare (ROS 2 ignores
    them silently; a typo then looks like a setting that took effect).
    """
    given = set(getattr(node, '_parameter_overrides', {}))   # rclpy keeps no public copy
    declared = {name for name in given if node.has_parameter(name)}
    pending = node.pending_parameter_prefixes() if hasattr(
        node, 'pending_parameter_prefixes') else []
    unknown = sorted(n for n in given - declared if not any(n.startswith(p) for p in pending))
    retired = [n for n in unknown if n in RETIRED_QOS_PARAMETERS]
    if retired:
        raise ConfigError(f'parameter {retired[0]} no longer exists: QoS is set with the standard '
                          'overrides, e.g. -p qos_overrides./piezo/deflection.publisher.'
                          'reliability:=best_effort or ...depth:=20000 (docs/nodes.md)')
    if unknown:
        node.get_logger().warning(f'ignoring unknown parameter(s): {", ".join(unknown)}')


def main_for(node_cls) -> Callable[[list[str] | None], None]:
    """Return the `main` of a console script: it exits the process with run_node's code."""
    def main(args: list[str] | None = None) -> None:
        sys.exit(run_node(node_cls, args))
    return main


class PiezoNode(Node):
    """
    Node base.

    Default namespace `piezo` (a `__ns:=` remap still wins), `close()` hook called once on
    shutdown, and start-up parameters declared from `PARAMS` (a list of ParamSpec).
    """

    NODE_NAME = 'piezo_node'
    PARAMS: Sequence[ParamSpec] = ()

    def __init__(self, **kwargs):
        kwargs.setdefault('namespace', DEFAULT_NAMESPACE)
        super().__init__(self.NODE_NAME, **kwargs)
        self.qos_watch = QosWatch(self)
        self.params = declare_parameters(self, self.PARAMS)

    def sample_publisher(self, topic: str, msg_type=JointState, depth: int = SAMPLE_DEPTH,
                         qos: QoSProfile | None = None):
        """
        Create the publisher of a per-sample stream.

        `sample_qos` (or `qos`, e.g. a bag's recorded profile), the standard QoS overrides, and
        incompatible-QoS reporting (QosWatch).
        """
        pub = self.create_publisher(msg_type, topic, qos or sample_qos(depth),
                                    qos_overriding_options=qos_overriding(),
                                    event_callbacks=self.qos_watch.callbacks('publisher', topic))
        self.qos_watch.add('publisher', pub)
        return pub

    def sample_subscription(self, topic: str, callback, msg_type=JointState, raw: bool = True,
                            depth: int = SAMPLE_DEPTH):
        """
        Create the subscription to a per-sample stream (raw CDR bytes by default).

        With the same QoS handling as `sample_publisher`.
        """
        sub = self.create_subscription(
            msg_type, topic, callback, sample_qos(depth), raw=raw,
            qos_overriding_options=qos_overriding(),
            event_callbacks=self.qos_watch.callbacks('subscription', topic))
        self.qos_watch.add('subscription', sub)
        return sub

    def pending_parameter_prefixes(self) -> list[str]:
        """
        Return the prefixes of parameters declared later than construction.

        QoS overrides of subscriptions made on demand; run_node does not call them unknown.
        """
        return []

    def take_pacing(self) -> bool:
        """
        Return True to be paced by run_node's loop instead of by a timer (default False).

        Such a node does its due work in `pace()`, which run_node calls after every spin_once,
        and says there how long the loop may wait for callbacks. At 2 kHz an rclpy timer alone
        cost ~110 us of CPU and 4 context switches per tick here; paced this way, the command
        node went from 45-50 % to 38 % of a core.
        """
        return False

    def pace(self) -> float:
        """Do the work due now; return the seconds until more is due (see take_pacing)."""
        return 0.1

    def close(self) -> None:
        """Release resources (files, sockets); called once by run_node before destroy_node."""
