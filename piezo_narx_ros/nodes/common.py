"""Plumbing shared by every node: QoS, validated parameters, /diagnostics, JointState, main().

Nodes stay thin: they declare parameters through `declare_parameters` (one `ParamSpec` each), build
their QoS with `sample_qos`, convert messages with `make_joint_state` / `parse_joint_state`, report
health through `Diagnostics`, and start from `run_node`.

Stamps are carried as integer nanoseconds (`int`) inside the nodes, so that t_k = t0 + k/fs is exact
and never accumulates float error over long runs.
"""
from __future__ import annotations

import math
import struct
import sys
from dataclasses import dataclass
from typing import Any, Callable, Iterable, Sequence

import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor,
                                SetParametersResult)
from rclpy.exceptions import ParameterException
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState

from piezo_narx_ros.errors import ConfigError, DataError, PiezoNarxError

# Topic names (relative; the default namespace `piezo` is given at start-up, see DESIGN.md).
TOPIC_COMMAND = 'voltage_command'
TOPIC_DEFLECTION = 'deflection'
TOPIC_ESTIMATE = 'deflection_estimate'
TOPIC_DIAGNOSTICS = '/diagnostics'
DEFAULT_NAMESPACE = 'piezo'

# Exit codes of a node process.
EXIT_OK = 0
EXIT_FAILURE = 1       # unexpected exception
EXIT_CONFIG = 2        # refused to start: bad parameter, missing model file, ...

DIAG_OK = DiagnosticStatus.OK
DIAG_WARN = DiagnosticStatus.WARN
DIAG_ERROR = DiagnosticStatus.ERROR


# --------------------------------------------------------------------------------------------- QoS
def sample_qos(best_effort: bool = False, depth: int = 100) -> QoSProfile:
    """QoS of the per-sample streams: reliable keep-last(depth) by default (identification must lose
    nothing); best effort when asked (a live display that prefers fresh data to complete data)."""
    if depth < 1:
        raise ConfigError(f'qos depth must be >= 1, got {depth}')
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=int(depth),
        reliability=ReliabilityPolicy.BEST_EFFORT if best_effort else ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.VOLATILE,
    )


# ------------------------------------------------------------------------------------- parameters
@dataclass(frozen=True)
class ParamSpec:
    """One node parameter: default (its type fixes the parameter type), description and limits.

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

    def descriptor(self, with_ranges: bool = True) -> ParameterDescriptor:
        """ParameterDescriptor carrying the description, the range and the read-only flag.

        Float parameters use dynamic typing so that `-p fs:=500` (an integer) is accepted; their
        type is then checked by `validate`."""
        d = ParameterDescriptor(name=self.name, description=self.description,
                                read_only=self.read_only, dynamic_typing=self.is_float)
        notes = []
        if self.choices is not None:
            notes.append('one of: ' + ', '.join(map(str, self.choices)))
        numeric = isinstance(self.default, (int, float)) and not isinstance(self.default, bool)
        if numeric and self.low is not None and self.high is not None and with_ranges:
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
        if self.check is not None and not self.check[0](value):
            return f'{self.name} {self.check[1]}, got {value!r}'
        return None


def declare_parameters(node: Node, specs: Iterable[ParamSpec]) -> dict[str, Any]:
    """Declare every spec on `node`, validate the start-up values, and keep validating later
    `set_parameters` calls. Returns {name: value}. Raises ConfigError (one line) on a bad value."""
    specs = list(specs)
    by_name = {s.name: s for s in specs}
    values: dict[str, Any] = {}
    for spec in specs:
        try:
            # Ranges are attached after our own check, so a bad value is refused with our message.
            param = node.declare_parameter(spec.name, spec.default, spec.descriptor(False))
        except ParameterException as exc:  # wrong type
            raise ConfigError(f'parameter {spec.name}: {_one_line(exc)}') from None
        value = param.value
        reason = spec.validate(value)
        if reason:
            raise ConfigError(f'parameter {reason}')
        if spec.is_float:
            value = float(value)
        if not spec.read_only:
            # A read-only parameter refuses set_descriptor; it keeps its bounds in the text of
            # additional_constraints, and nothing can change it after this check anyway.
            full = spec.descriptor(True)
            full.type = node.describe_parameter(spec.name).type  # set_descriptor insists on it
            node.set_descriptor(spec.name, full)
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
    """JointState for one sample: stamp t_ns (ns), axis names, position (m) and/or effort (V)."""
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
        """The `field` ('position' or 'effort') of `axis`; raises DataError when absent."""
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
    """JointState -> Sample (no validation of values; see Sample.value)."""
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
    """Serialized JointState (CDR, as from a raw=True subscription) -> Sample. Raises DataError
    on a truncated or malformed buffer."""
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
    """JointState CDR bytes (little endian, empty frame_id and velocity) for Publisher.publish."""
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
    """Publishes one DiagnosticStatus for `node` on /diagnostics every `period` s.

    `provider()` returns (level, message, {key: value}); level is DIAG_OK/WARN/ERROR. The provider
    is read only at publication time, so the nodes' hot paths just bump counters.
    """

    def __init__(self, node: Node, provider: Callable[[], tuple[bytes, str, dict]],
                 period: float = 1.0, hardware_id: str = 'piezo'):
        self._node = node
        self._provider = provider
        self._hardware_id = hardware_id
        self._pub = node.create_publisher(DiagnosticArray, TOPIC_DIAGNOSTICS, 10)
        self._timer = node.create_timer(period, self.publish)

    def build(self) -> DiagnosticArray:
        """The DiagnosticArray that would be published now."""
        level, message, values = self._provider()
        status = DiagnosticStatus(level=level, name=self._node.get_fully_qualified_name(),
                                  message=message, hardware_id=self._hardware_id,
                                  values=[KeyValue(key=str(k), value=_fmt(v))
                                          for k, v in values.items()])
        arr = DiagnosticArray(status=[status])
        arr.header.stamp = self._node.get_clock().now().to_msg()
        return arr

    def publish(self) -> None:
        """Publish one status now (also called by the timer)."""
        self._pub.publish(self.build())


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return f'{v:.6g}'
    return str(v)


def diagnostic_values(status: DiagnosticStatus) -> dict[str, str]:
    """{key: value} of one DiagnosticStatus (for tests and tools)."""
    return {kv.key: kv.value for kv in status.values}


# ---------------------------------------------------------------------------------------- main
def make_executor(kind: str = 'events'):
    """'events' -> rclpy.experimental.EventsExecutor (C++ event loop; pub->sub latency ~14 us here
    against ~92 us with the single-threaded executor), 'single' -> SingleThreadedExecutor."""
    if kind == 'events':
        from rclpy.experimental import EventsExecutor
        return EventsExecutor()
    if kind == 'single':
        from rclpy.executors import SingleThreadedExecutor
        return SingleThreadedExecutor()
    raise ConfigError(f"executor must be 'events' or 'single', got {kind!r}")


def run_node(node_cls: Callable[..., Node], args: list[str] | None = None,
             executor: str | None = None) -> int:
    """Main of a node process: init, construct, spin, clean shutdown. Returns the exit code.

    SIGINT/SIGTERM stop the spin and exit 0; a node that refuses to start (ConfigError or any
    PiezoNarxError from its constructor) prints one line `NAME: error: reason` and exits 2; any
    other exception exits 1. The executor is EventsExecutor unless PIEZO_NARX_EXECUTOR=single or
    `executor` says otherwise.
    """
    import os
    import signal
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
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    code = EXIT_OK
    node = None
    ex = None
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    try:
        node = node_cls()
        ex = make_executor(kind)
        ex.add_node(node)
        while not stop.is_set() and rclpy.ok():
            ex.spin_once(timeout_sec=0.1)
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


def main_for(node_cls) -> Callable[[list[str] | None], None]:
    """`main` for a console script: exits the process with run_node's code."""
    def main(args: list[str] | None = None) -> None:
        sys.exit(run_node(node_cls, args))
    return main


class PiezoNode(Node):
    """Node base: default namespace `piezo` (a `__ns:=` remap still wins), `close()` hook called
    once on shutdown, and start-up parameters declared from `PARAMS` (a list of ParamSpec)."""

    NODE_NAME = 'piezo_node'
    PARAMS: Sequence[ParamSpec] = ()

    def __init__(self, **kwargs):
        kwargs.setdefault('namespace', DEFAULT_NAMESPACE)
        super().__init__(self.NODE_NAME, **kwargs)
        self.params = declare_parameters(self, self.PARAMS)

    def close(self) -> None:
        """Release resources (files, sockets); called once by run_node before destroy_node."""
