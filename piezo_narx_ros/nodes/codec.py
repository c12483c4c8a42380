"""
The sample messages: JointState objects (make/parse) and their CDR bytes (encode/decode).

Stamps are carried as integer nanoseconds (`int`) inside the nodes, so that t_k = t0 + k/fs is
exact and never accumulates float error over long runs.
"""
from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import Sequence

from sensor_msgs.msg import JointState

from piezo_narx_ros.errors import DataError


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
