"""The one-sample message, sensor_msgs/JointState: objects, and CDR bytes for raw subscriptions."""
from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import Sequence

from sensor_msgs.msg import JointState

from piezo_narx_ros.errors import DataError
from piezo_narx_ros.nodes.wire.cdr import (_SHAPES_PER_LENGTH, _STAMP, _header_names,
                                           _put_doubles, _read_doubles, _read_doubles_at,
                                           _read_header_names, check_message_names, ns_to_stamp,
                                           stamp_to_ns)


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

    def values(self, field: str, axes: Sequence[str]) -> list[float]:
        """Return the `field` of each of `axes`, in that order (mapped by name); DataError."""
        return [self.value(field, a) for a in axes]


def parse_joint_state(msg: JointState) -> Sample:
    """Convert a JointState to a Sample (names checked, values not: see Sample.value)."""
    check_message_names(msg.name)
    return Sample(stamp_to_ns(msg.header.stamp), list(msg.name), list(msg.position),
                  list(msg.effort))


@dataclass(frozen=True)
class _StateShape:
    """
    What a stream's JointStates repeat: every byte but the stamp's and the values'.

    Byte ranges [0, 4) and [12, pos) (encapsulation; frame_id, names, the positions' count),
    [pos_end, eff) (the empty velocities, the efforts' count) and [eff_end, length) (usually
    nothing) as they were; the values unpacked with `pos_values` / `eff_values` at pos / eff.
    """

    encapsulation: bytes
    head: bytes
    mid: bytes
    tail: bytes
    pos: int
    pos_end: int
    eff: int
    eff_end: int
    stamp: struct.Struct
    pos_values: struct.Struct
    eff_values: struct.Struct
    names: tuple


# JointState shapes seen, per buffer length (a stream's messages share one); templates of the
# encoder per (names, positions, efforts): its bytes, where the values go and their Structs.
_STATE_SHAPES: dict = {}
_STATE_ENCODED: dict = {}


def decode_joint_state(buf: bytes) -> Sample:
    """
    Decode a serialized JointState (CDR, as from a raw=True subscription) to a Sample.

    Raises DataError on a truncated or malformed buffer. A message of a shape seen before (same
    length, and every byte but the stamp and the values the same: a stream's usual case) is read
    with three unpacks.
    """
    if isinstance(buf, bytes):
        for sh in _STATE_SHAPES.get(len(buf), ()):
            if buf[12:sh.pos] == sh.head and buf[sh.pos_end:sh.eff] == sh.mid \
                    and buf[:4] == sh.encapsulation and buf[sh.eff_end:] == sh.tail:
                sec, nsec = sh.stamp.unpack_from(buf, 4)
                return Sample(sec * 1_000_000_000 + nsec, list(sh.names),
                              list(sh.pos_values.unpack_from(buf, sh.pos)),
                              list(sh.eff_values.unpack_from(buf, sh.eff)))
    try:
        e, data, t_ns, names, off = _read_header_names(buf)
        position, off, pos = _read_doubles_at(e, data, off)
        velocity, off = _read_doubles(e, data, off)
        pos_end = off
        effort, off, eff = _read_doubles_at(e, data, off)
    except (struct.error, IndexError, UnicodeDecodeError) as exc:
        raise DataError(f'malformed JointState ({len(buf)} bytes): {exc}') from None
    if isinstance(buf, bytes) and not velocity:
        _remember_state_shape(buf, e, names, pos + 4, len(position), pos_end + 4, eff + 4,
                              len(effort), off + 4)
    return Sample(t_ns, names, list(position), list(effort))


def _remember_state_shape(buf: bytes, e: str, names, pos: int, n_pos: int, pos_end: int,
                          eff: int, n_eff: int, eff_end: int) -> None:
    """Keep the shape of a well-formed JointState (absolute byte offsets; _StateShape)."""
    if len(_STATE_SHAPES) > 64:
        _STATE_SHAPES.clear()
    shape = _StateShape(bytes(buf[:4]), bytes(buf[12:pos]), bytes(buf[pos_end:eff]),
                        bytes(buf[eff_end:]), pos, pos_end, eff, eff_end,
                        struct.Struct(e + 'iI'), struct.Struct(f'{e}{n_pos}d'),
                        struct.Struct(f'{e}{n_eff}d'), tuple(names))
    kept = [k for k in _STATE_SHAPES.get(len(buf), ()) if k != shape]
    _STATE_SHAPES[len(buf)] = [shape] + kept[:_SHAPES_PER_LENGTH - 1]


def encode_joint_state(t_ns: int, names: Sequence[str], position: Sequence[float] = (),
                       effort: Sequence[float] = ()) -> bytes:
    """
    Encode JointState CDR (little endian, empty frame_id and velocity) for Publisher.publish.

    A stream's usual message (the names and value counts of one encoded before) is written into
    that one's bytes: the stamp and values packed in place.
    """
    key = (tuple(names), len(position), len(effort))
    template = _STATE_ENCODED.get(key)
    if template is not None:
        raw, pos, pos_values, eff, eff_values = template
        out = bytearray(raw)
        _STAMP.pack_into(out, 4, *divmod(int(t_ns), 1_000_000_000))
        pos_values.pack_into(out, pos, *position)
        eff_values.pack_into(out, eff, *effort)
        return bytes(out)
    out = _header_names(t_ns, names)
    at = []
    for values in (position, (), effort):
        _put_doubles(out, values)
        at.append(len(out) - 8 * len(values))
    if len(_STATE_ENCODED) > 64:
        _STATE_ENCODED.clear()
    _STATE_ENCODED[key] = (bytes(out), at[0], struct.Struct(f'<{len(position)}d'), at[2],
                           struct.Struct(f'<{len(effort)}d'))
    return bytes(out)
