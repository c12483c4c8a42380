"""
UDP datagrams between driver_node and a real-time rig target (docs/driver.md, byte by byte).

Every datagram is little-endian and starts with the same 24-byte header, so a target written in C
can read it with one packed struct (or memcpy per field):

    offset size type     field
    0      4    char[4]  magic     b'PZRG'
    4      1    uint8    version   1
    5      1    uint8    kind      1 = command (driver -> target), 2 = reply (target -> driver)
    6      2    uint16   n_axes    number of axes that follow (1..MAX_AXES)
    8      4    uint32   seq       command sequence number; a reply echoes the command's
    12     4    uint32   flags     command: bit 0 ramp, bit 1 ping; reply: bit 0 target fault
    16     8    int64    stamp_ns  sample stamp t_k in ns (command); a reply echoes it

Command payload: n_axes x float64 volts to output.
Reply payload:   n_axes x (float64 measured metres, float64 volts actually applied).

The header is 8-byte aligned so the float64 payload is naturally aligned too.
"""
from __future__ import annotations

import math
import struct
from dataclasses import dataclass

from piezo_narx_ros.errors import DataError

MAGIC = b'PZRG'
VERSION = 1
KIND_COMMAND = 1
KIND_REPLY = 2
MAX_AXES = 16
SEQ_MODULO = 1 << 32

FLAG_RAMP = 0x1          # command: the driver's watchdog is ramping the output to 0 V
FLAG_PING = 0x2          # command: do not apply; reply with the current measurement and output
FLAG_TARGET_FAULT = 0x1  # reply: the target reports a fault (amplifier, sensor, its own limits)

HEADER = struct.Struct('<4sBBHIIq')
HEADER_SIZE = HEADER.size  # 24 bytes
_F64 = 8


class DatagramError(DataError):
    """A datagram that is no valid command or reply (bad magic, version, kind, size or value)."""


@dataclass(frozen=True)
class Command:
    """Driver -> target: volts to output on each axis for the sample stamped stamp_ns."""

    seq: int
    stamp_ns: int
    volts: tuple[float, ...]
    flags: int = 0


@dataclass(frozen=True)
class Reply:
    """Target -> driver: measured deflection (m) and applied volts (V) per axis for command seq."""

    seq: int
    stamp_ns: int
    position_m: tuple[float, ...]
    applied_volts: tuple[float, ...]
    flags: int = 0


def command_size(n_axes: int) -> int:
    """Size in bytes of a command datagram for n_axes axes."""
    return HEADER_SIZE + _F64 * n_axes


def reply_size(n_axes: int) -> int:
    """Size in bytes of a reply datagram for n_axes axes."""
    return HEADER_SIZE + 2 * _F64 * n_axes


def _check_fields(seq: int, stamp_ns: int, flags: int, n_axes: int) -> None:
    if not 0 <= seq < SEQ_MODULO:
        raise DatagramError(f'sequence number {seq} outside uint32')
    if not -(1 << 63) <= stamp_ns < (1 << 63):
        raise DatagramError(f'stamp {stamp_ns} ns outside int64')
    if not 0 <= flags < (1 << 32):
        raise DatagramError(f'flags {flags} outside uint32')
    if not 1 <= n_axes <= MAX_AXES:
        raise DatagramError(f'{n_axes} axes; a datagram carries 1..{MAX_AXES}')


def _check_finite(values, what: str) -> None:
    for v in values:
        if not math.isfinite(v):
            raise DatagramError(f'{what} value {v} is not finite')


def pack_command(cmd: Command) -> bytes:
    """Encode a command datagram; DatagramError for out-of-range fields or non-finite volts."""
    n = len(cmd.volts)
    _check_fields(cmd.seq, cmd.stamp_ns, cmd.flags, n)
    _check_finite(cmd.volts, 'volts')
    return HEADER.pack(MAGIC, VERSION, KIND_COMMAND, n, cmd.seq, cmd.flags, cmd.stamp_ns) + \
        struct.pack(f'<{n}d', *cmd.volts)


def pack_reply(reply: Reply) -> bytes:
    """Encode a reply datagram; position and applied volts interleave per axis (m, V, m, V...)."""
    n = len(reply.position_m)
    if len(reply.applied_volts) != n:
        raise DatagramError(f'{n} positions but {len(reply.applied_volts)} applied volts')
    _check_fields(reply.seq, reply.stamp_ns, reply.flags, n)
    _check_finite(reply.position_m, 'position')
    _check_finite(reply.applied_volts, 'applied volts')
    payload = [v for pair in zip(reply.position_m, reply.applied_volts) for v in pair]
    return HEADER.pack(MAGIC, VERSION, KIND_REPLY, n, reply.seq, reply.flags, reply.stamp_ns) + \
        struct.pack(f'<{2 * n}d', *payload)


def _unpack_header(data: bytes, kind: int, per_axis: int, expected_axes: int | None):
    if len(data) < HEADER_SIZE:
        raise DatagramError(f'datagram of {len(data)} bytes is shorter than the '
                            f'{HEADER_SIZE}-byte header')
    magic, version, got_kind, n, seq, flags, stamp_ns = HEADER.unpack_from(data)
    if magic != MAGIC:
        raise DatagramError(f'bad magic {magic!r} (expected {MAGIC!r})')
    if version != VERSION:
        raise DatagramError(f'protocol version {version} not supported (expected {VERSION})')
    if got_kind != kind:
        raise DatagramError(f'datagram kind {got_kind} where kind {kind} was expected')
    if not 1 <= n <= MAX_AXES:
        raise DatagramError(f'{n} axes; a datagram carries 1..{MAX_AXES}')
    if expected_axes is not None and n != expected_axes:
        raise DatagramError(f'{n} axes where {expected_axes} were expected')
    size = HEADER_SIZE + per_axis * _F64 * n
    if len(data) != size:
        raise DatagramError(f'datagram of {len(data)} bytes; {n} axes need exactly {size}')
    values = struct.unpack_from(f'<{per_axis * n}d', data, HEADER_SIZE)
    return n, seq, flags, stamp_ns, values


def unpack_command(data: bytes, n_axes: int | None = None) -> Command:
    """Decode and validate a command datagram (n_axes: required axis count, None = any)."""
    _, seq, flags, stamp_ns, values = _unpack_header(data, KIND_COMMAND, 1, n_axes)
    _check_finite(values, 'volts')
    return Command(seq=seq, stamp_ns=stamp_ns, volts=values, flags=flags)


def unpack_reply(data: bytes, n_axes: int | None = None) -> Reply:
    """Decode and validate a reply datagram (n_axes: required axis count, None = any)."""
    _, seq, flags, stamp_ns, values = _unpack_header(data, KIND_REPLY, 2, n_axes)
    _check_finite(values, 'reply')
    return Reply(seq=seq, stamp_ns=stamp_ns, position_m=values[0::2], applied_volts=values[1::2],
                 flags=flags)
