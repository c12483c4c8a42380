"""
The CDR pieces every sample message shares: stamps, the header and name sequence, float64 runs.

Stamps are carried as integer nanoseconds (`int`) inside the nodes, so that t_k = t0 + k/fs is
exact and never accumulates float error over long runs.
"""
from __future__ import annotations

import struct
from typing import Sequence

from piezo_narx_ros.axis_names import repeated
from piezo_narx_ros.errors import DataError


def ns_to_stamp(t_ns: int) -> tuple[int, int]:
    """Integer nanoseconds -> (sec, nanosec) of builtin_interfaces/Time."""
    sec, nsec = divmod(int(t_ns), 1_000_000_000)
    return sec, nsec


def stamp_to_ns(stamp) -> int:
    """builtin_interfaces/Time -> integer nanoseconds."""
    return stamp.sec * 1_000_000_000 + stamp.nanosec


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
# Shapes remembered per buffer length: a stream's messages share one; a few per length, so
# that streams of different shapes that happen to be as long stay fast.
_SHAPES_PER_LENGTH = 4


def _read_header_names(buf: bytes):
    """
    Read the common prefix of JointState and JointTrajectory CDR: header, then a string sequence.

    Returns (struct byte-order character, payload memoryview, stamp ns, names, offset after the
    names). The frame_id is skipped.
    """
    e = '<' if buf[1] == 1 else '>'
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
    # Read only when a message's shape is new: a stream's usual message takes the fast path.
    check_message_names(names)
    return e, data, sec * 1_000_000_000 + nsec, names, off


def check_message_names(names) -> None:
    """Raise DataError when a message names one axis twice (its values cannot be told apart)."""
    dup = repeated(names)
    if dup is not None:
        raise DataError(f'message names axis {dup!r} twice (names: {list(names)}): each axis '
                        'may appear once')


def _read_doubles(e: str, data, off: int) -> tuple[tuple, int]:
    """Read one sequence<float64> at `off` (before alignment); returns (values, next offset)."""
    off = (off + 3) & ~3
    (count,) = struct.unpack_from(e + 'I', data, off)
    off += 4
    if not count:
        return (), off
    off = (off + 7) & ~7
    return struct.unpack_from(f'{e}{count}d', data, off), off + 8 * count


def _read_doubles_at(e: str, data, off: int) -> tuple[tuple, int, int]:
    """_read_doubles, also returning where the values start (after count and alignment)."""
    values, end = _read_doubles(e, data, off)
    return values, end, end - 8 * len(values)


def _header_names(t_ns: int, names: Sequence[str]) -> bytearray:
    """CDR of the common prefix: encapsulation (little endian), header (empty frame_id), names."""
    sec, nsec = divmod(int(t_ns), 1_000_000_000)
    out = bytearray(b'\x00\x01\x00\x00')
    out += _STAMP.pack(sec, nsec)
    out += b'\x01\x00\x00\x00\x00\x00\x00\x00'      # frame_id '' (length 1: the NUL) + pad
    out += _U32.pack(len(names))
    for name in names:
        raw = name.encode() + b'\x00'
        out += b'\x00' * (-(len(out) - 4) % 4)
        out += _U32.pack(len(raw)) + raw
    return out


def _put_doubles(out: bytearray, values: Sequence[float]) -> None:
    """Append one sequence<float64>, aligned from the byte after the encapsulation header."""
    out += b'\x00' * (-(len(out) - 4) % 4)
    out += _U32.pack(len(values))
    if len(values):
        out += b'\x00' * (-(len(out) - 4) % 8)
        out += struct.pack(f'<{len(values)}d', *values)
