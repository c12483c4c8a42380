"""
UDP datagrams between driver_node and a real-time rig target (docs/driver.md, byte by byte).

Version 1 carries one sample per datagram; version 2 (for 5-20 kHz rigs) carries several, each
with its own stamp. Both start with the same 24-byte header.

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

Version 2 (version byte 2) adds 8 bytes after the header, then one record per sample:

    24     2    uint16   n_samples  samples that follow (1..MAX_SAMPLES)
    26     2    uint16   reserved   0
    28     4    uint32   reserved   0
    32     ...  per sample: int64 stamp_ns, then the version-1 payload of that sample

header.stamp_ns is the first sample's stamp; seq numbers the datagram (a reply echoes it).
"""
from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from functools import lru_cache

from piezo_narx_ros.errors import DataError

MAGIC = b'PZRG'
VERSION = 1
VERSION_BATCH = 2
VERSIONS = (VERSION, VERSION_BATCH)
KIND_COMMAND = 1
KIND_REPLY = 2
MAX_AXES = 16
SEQ_MODULO = 1 << 32

FLAG_RAMP = 0x1          # command: the driver's watchdog is ramping the output to 0 V
FLAG_PING = 0x2          # command: do not apply; reply with the current measurement and output
FLAG_TARGET_FAULT = 0x1  # reply: the target reports a fault (amplifier, sensor, its own limits)

HEADER = struct.Struct('<4sBBHIIq')
HEADER_SIZE = HEADER.size  # 24 bytes
BATCH_HEADER = struct.Struct('<HHI')
BATCH_HEADER_SIZE = HEADER_SIZE + BATCH_HEADER.size   # 32 bytes
# Largest sample count of a version-2 datagram: a 16-axis reply (264 bytes per sample) then
# stays below the 65507-byte UDP payload limit.
MAX_SAMPLES = 240
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
        why = ' (a version-2 datagram: unpack it with unpack_*_batch)' \
            if version == VERSION_BATCH else ''
        raise DatagramError(f'protocol version {version} not supported (expected {VERSION})'
                            + why)
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


# ------------------------------------------------------------------------------- version 2
@dataclass(frozen=True)
class CommandBatch:
    """Driver -> target, version 2: volts per axis for each sample, each with its stamp."""

    seq: int
    stamps_ns: tuple[int, ...]
    volts: tuple[tuple[float, ...], ...]      # per sample, per axis
    flags: int = 0


@dataclass(frozen=True)
class ReplyBatch:
    """Target -> driver, version 2: measured m and applied V per axis for each sample."""

    seq: int
    stamps_ns: tuple[int, ...]
    position_m: tuple[tuple[float, ...], ...]
    applied_volts: tuple[tuple[float, ...], ...]
    flags: int = 0


def datagram_version(data: bytes) -> int | None:
    """Return the version byte of a datagram with the right magic, else None."""
    if len(data) < HEADER_SIZE or data[:4] != MAGIC:
        return None
    return data[4]


@lru_cache(maxsize=256)
def _samples_struct(n_samples: int, per_sample: int) -> struct.Struct:
    return struct.Struct('<' + ('q' + 'd' * per_sample) * n_samples)


def _pack_batch(kind: int, seq: int, flags: int, stamps, rows, n_axes: int) -> bytes:
    n = len(stamps)
    if not 1 <= n <= MAX_SAMPLES:
        raise DatagramError(f'{n} samples; a version-2 datagram carries 1..{MAX_SAMPLES}')
    _check_fields(seq, int(stamps[0]), flags, n_axes)
    flat = []
    for stamp, row in zip(stamps, rows):
        if not -(1 << 63) <= stamp < (1 << 63):
            raise DatagramError(f'stamp {stamp} ns outside int64')
        flat.append(int(stamp))
        flat += row
    return HEADER.pack(MAGIC, VERSION_BATCH, kind, n_axes, seq, flags, int(stamps[0])) + \
        BATCH_HEADER.pack(n, 0, 0) + _samples_struct(n, len(rows[0])).pack(*flat)


def pack_command_batch(cmd: CommandBatch) -> bytes:
    """Encode a version-2 command; DatagramError for bad fields, sizes or non-finite volts."""
    n_axes = len(cmd.volts[0]) if cmd.volts else 0
    if len(cmd.volts) != len(cmd.stamps_ns):
        raise DatagramError(f'{len(cmd.stamps_ns)} stamps but {len(cmd.volts)} samples of volts')
    for row in cmd.volts:
        if len(row) != n_axes:
            raise DatagramError(f'samples of {len(row)} and {n_axes} axes in one datagram')
        _check_finite(row, 'volts')
    return _pack_batch(KIND_COMMAND, cmd.seq, cmd.flags, cmd.stamps_ns,
                       [list(r) for r in cmd.volts], n_axes)


def pack_reply_batch(reply: ReplyBatch) -> bytes:
    """Encode a version-2 reply; per sample the axes' (m, V) pairs interleave as in version 1."""
    n = len(reply.stamps_ns)
    if len(reply.position_m) != n or len(reply.applied_volts) != n:
        raise DatagramError(f'{n} stamps but {len(reply.position_m)} positions and '
                            f'{len(reply.applied_volts)} applied volts samples')
    n_axes = len(reply.position_m[0]) if n else 0
    rows = []
    for pos, app in zip(reply.position_m, reply.applied_volts):
        if len(pos) != n_axes or len(app) != n_axes:
            raise DatagramError(f'samples of {len(pos)}/{len(app)} and {n_axes} axes in one '
                                'datagram')
        _check_finite(pos, 'position')
        _check_finite(app, 'applied volts')
        rows.append([v for pair in zip(pos, app) for v in pair])
    return _pack_batch(KIND_REPLY, reply.seq, reply.flags, reply.stamps_ns, rows, n_axes)


def _unpack_batch(data: bytes, kind: int, per_axis: int, expected_axes: int | None):
    if len(data) < BATCH_HEADER_SIZE:
        raise DatagramError(f'datagram of {len(data)} bytes is shorter than the '
                            f'{BATCH_HEADER_SIZE}-byte version-2 header')
    magic, version, got_kind, n_axes, seq, flags, stamp_ns = HEADER.unpack_from(data)
    if magic != MAGIC:
        raise DatagramError(f'bad magic {magic!r} (expected {MAGIC!r})')
    if version != VERSION_BATCH:
        raise DatagramError(f'protocol version {version} where {VERSION_BATCH} was expected')
    if got_kind != kind:
        raise DatagramError(f'datagram kind {got_kind} where kind {kind} was expected')
    if not 1 <= n_axes <= MAX_AXES:
        raise DatagramError(f'{n_axes} axes; a datagram carries 1..{MAX_AXES}')
    if expected_axes is not None and n_axes != expected_axes:
        raise DatagramError(f'{n_axes} axes where {expected_axes} were expected')
    n, _, _ = BATCH_HEADER.unpack_from(data, HEADER_SIZE)
    if not 1 <= n <= MAX_SAMPLES:
        raise DatagramError(f'{n} samples; a version-2 datagram carries 1..{MAX_SAMPLES}')
    per_sample = per_axis * n_axes
    size = BATCH_HEADER_SIZE + n * 8 * (1 + per_sample)
    if len(data) != size:
        raise DatagramError(f'datagram of {len(data)} bytes; {n} samples of {n_axes} axes need '
                            f'exactly {size}')
    flat = _samples_struct(n, per_sample).unpack_from(data, BATCH_HEADER_SIZE)
    stride = 1 + per_sample
    stamps = flat[0::stride]
    if stamps[0] != stamp_ns:
        raise DatagramError(f'header stamp {stamp_ns} differs from the first sample stamp '
                            f'{stamps[0]}')
    rows = [flat[k * stride + 1:(k + 1) * stride] for k in range(n)]
    for row in rows:
        _check_finite(row, 'volts' if kind == KIND_COMMAND else 'reply')
    return seq, flags, stamps, rows


def unpack_command_batch(data: bytes, n_axes: int | None = None) -> CommandBatch:
    """Decode and validate a version-2 command (n_axes: required axis count, None = any)."""
    seq, flags, stamps, rows = _unpack_batch(data, KIND_COMMAND, 1, n_axes)
    return CommandBatch(seq=seq, stamps_ns=stamps, volts=tuple(rows), flags=flags)


def unpack_reply_batch(data: bytes, n_axes: int | None = None) -> ReplyBatch:
    """Decode and validate a version-2 reply (n_axes: required axis count, None = any)."""
    seq, flags, stamps, rows = _unpack_batch(data, KIND_REPLY, 2, n_axes)
    return ReplyBatch(seq=seq, stamps_ns=stamps, position_m=tuple(r[0::2] for r in rows),
                      applied_volts=tuple(r[1::2] for r in rows), flags=flags)
