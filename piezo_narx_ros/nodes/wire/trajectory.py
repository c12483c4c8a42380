"""The batch message, trajectory_msgs/JointTrajectory: one point per sample, as CDR bytes."""
from __future__ import annotations

import struct
import sys
from dataclasses import dataclass
from functools import lru_cache
from typing import Sequence

import numpy as np

from piezo_narx_ros.errors import DataError
from piezo_narx_ros.nodes.wire.cdr import (_SHAPES_PER_LENGTH, _STAMP, _U32, _header_names,
                                           _put_doubles, _read_doubles, _read_header_names,
                                           ns_to_stamp)


# -------------------------------------------------------------- JointTrajectory as CDR bytes
# A batch of samples (DESIGN.md "High-rate streams") is one trajectory_msgs/msg/JointTrajectory:
# header.stamp = t of the first sample, joint_names = axes, one point per sample with
# time_from_start = t_k - t_first (builtin_interfaces/Duration: int32 sec, uint32 nanosec in
# [0, 1e9), so the offset and every stamp are exact integers of ns), positions = m, effort = V.
# CDR after the shared prefix (header, string sequence): sequence<JointTrajectoryPoint>, each
# point positions, velocities, accelerations, effort (sequence<float64>) and time_from_start.
# The nodes use it on raw=True subscriptions for the same reason as the JointState codec.
_DURATION = struct.Struct('<iI')


@dataclass
class SampleBatch:
    """
    One parsed batch: stamps (n,) int64 ns, axis names, positions (n, a) m and efforts (n, a) V.

    An array a message does not fill has a = 0 columns (e.g. the positions of a command batch).
    Decoded arrays may be read-only views of the message bytes: copy before writing to them.
    """

    t_ns: np.ndarray
    names: list[str]
    position: np.ndarray
    effort: np.ndarray

    def __len__(self) -> int:
        return int(self.t_ns.shape[0])

    def column(self, field: str, axis: str) -> np.ndarray:
        """Return the `field` ('position' or 'effort') of `axis`, (n,); DataError when absent."""
        values = self.position if field == 'position' else self.effort
        if not self.names:
            i = 0  # an unnamed single-axis batch
        else:
            try:
                i = self.names.index(axis)
            except ValueError:
                raise DataError(f'axis {axis!r} not in message (names: {self.names})') from None
        if i >= values.shape[1]:
            raise DataError(f'batch has no {field} for axis {axis!r}')
        return values[:, i]

    def columns(self, field: str, axes: Sequence[str]) -> np.ndarray:
        """Return the `field` of `axes` as (n, len(axes)), mapped by name; DataError if absent."""
        if len(axes) == 1:
            return self.column(field, axes[0])[:, None]
        values = self.position if field == 'position' else self.effort
        try:
            idx = [self.names.index(a) for a in axes]
        except ValueError:
            missing = [a for a in axes if a not in self.names]
            raise DataError(f'axis {missing[0]!r} not in message (names: {self.names})') from None
        if max(idx) >= values.shape[1]:
            raise DataError(f'batch has no {field} for every axis of {list(axes)}')
        return values[:, idx]


def _check_width(rows: list, names: list[str], field: str) -> int:
    """Columns of one field over every point: all equal, and 0 or len(names) when named."""
    width = len(rows[0]) if rows else 0
    for k, row in enumerate(rows):
        if len(row) != width:
            raise DataError(f'batch point {k} has {len(row)} {field} value(s), point 0 has '
                            f'{width}')
    if width and names and width != len(names):
        raise DataError(f'batch points have {width} {field} value(s) for {len(names)} joint '
                        f'name(s)')
    return width


@dataclass(frozen=True)
class _PointLayout:
    """Byte offsets of the fields inside a JointTrajectoryPoint of fixed shape, and its size."""

    size: int
    n_pos: int      # offset of the positions count, its values at `pos`, ...
    pos: int
    n_vel: int
    n_acc: int
    n_eff: int
    eff: int
    sec: int
    nsec: int


@lru_cache(maxsize=64)
def _point_layout(phase: int, n_pos: int, n_eff: int,
                  repeat: bool = True) -> _PointLayout | None:
    """
    Return the layout of a point starting at `phase` (its offset mod 8 after the encapsulation).

    Points with `n_pos` positions, empty velocities and accelerations, `n_eff` efforts. None
    unless the next point starts at the same phase (or `repeat` is False): then every later point
    has this same layout (its size a multiple of 8), so a run of them is a strided array per field.
    """
    off, where = phase, {}

    def put(name: str, size: int, count: int = 1) -> None:
        nonlocal off
        if count:            # an empty sequence has no payload to align
            off += -off % size
        where[name] = off - phase
        off += size * count

    put('n_pos', 4)
    put('pos', 8, n_pos)
    for name in ('n_vel', 'n_acc', 'n_eff'):
        put(name, 4)
    put('eff', 8, n_eff)
    put('sec', 4)
    put('nsec', 4)
    if repeat and off % 8 != phase:
        return None
    return _PointLayout(size=off - phase, **where)


def _field(buf, layout: _PointLayout, name: str, start: int, count: int, code: str,
           width: int = 0) -> np.ndarray:
    """Strided view of one field over `count` points from byte `start`: (count,) or (count, w)."""
    shape, strides = ((count, width), (layout.size, 8)) if width else ((count,), (layout.size,))
    return np.ndarray(shape, code, buf, start + getattr(layout, name), strides)


def _read_run(buf, start: int, count: int, layout: _PointLayout, e: str, n_pos: int,
              n_eff: int):
    """
    Read `count` points of one layout from byte `start` of `buf` as arrays.

    Returns (time_from_start ns (count,), positions (count, n_pos), efforts (count, n_eff)), or
    None when a point's counts differ from the layout (the caller then reads point by point).
    """
    words = np.ndarray((count, layout.size // 4), e + 'u4', buf, start)
    counts = words[:, [layout.n_pos // 4, layout.n_vel // 4, layout.n_acc // 4,
                       layout.n_eff // 4]]
    if not (counts == (n_pos, 0, 0, n_eff)).all():
        return None
    sec = words[:, layout.sec // 4].astype(np.int64)
    sec[sec >= 1 << 31] -= 1 << 32                     # int32 seconds: negative offsets
    offsets = sec * 1_000_000_000 + words[:, layout.nsec // 4]

    def doubles(at: int, width: int) -> np.ndarray:
        if not width:
            return np.empty((count, 0))
        return np.ndarray((count, width), e + 'f8', buf, start + at, (layout.size, 8))
    return offsets, doubles(layout.pos, n_pos), doubles(layout.eff, n_eff)


def _read_point(e: str, data, off: int):
    """Read one point at `off`; returns (positions, efforts, (sec, nsec), next offset)."""
    pos, off = _read_doubles(e, data, off)
    _, off = _read_doubles(e, data, off)     # velocities
    _, off = _read_doubles(e, data, off)     # accelerations
    eff, off = _read_doubles(e, data, off)
    off = (off + 3) & ~3
    return pos, eff, struct.unpack_from(e + 'iI', data, off), off + 8


@lru_cache(maxsize=64)
def _point_dtype(e: str, layout: _PointLayout, n_pos: int, n_eff: int) -> np.dtype:
    """Structured dtype of one point of `layout` (byte order e): one view reads every point."""
    fields = {'n_pos': (e + 'u4', layout.n_pos), 'n_vae': ((e + 'u4', 3), layout.n_vel),
              'sec': (e + 'i4', layout.sec), 'nsec': (e + 'u4', layout.nsec)}
    if n_pos:
        fields['pos'] = ((e + 'f8', n_pos), layout.pos)
    if n_eff:
        fields['eff'] = ((e + 'f8', n_eff), layout.eff)
    return np.dtype({'names': list(fields), 'formats': [f for f, _ in fields.values()],
                     'offsets': [o for _, o in fields.values()], 'itemsize': layout.size})


@dataclass(frozen=True)
class _BatchShape:
    """What a stream's batches repeat: everything before the points but the stamp, and layout."""

    encapsulation: bytes   # the 4 bytes before the header (byte order)
    prefix: bytes       # header after the stamp (frame_id), names, point count
    start: int          # byte offset of the first point in the buffer
    names: tuple
    count: int
    dtype: np.dtype     # of the points from `run` on
    n_pos: int
    n_eff: int
    head: np.dtype | None   # point 0, when its layout is not the others' (_remember_shape)
    run: int            # byte offset of the strided points: start, or after point 0
    meta: np.ndarray | None = None   # the points for codec_kernels (None: numpy views)


# Batch shapes seen, per buffer length: a stream's batches share one (same names, same size).
# A few per length, so that streams of different shapes that happen to be as long stay fast.
_SHAPES: dict = {}
# Encoded batches per (names, points, positions, efforts): the template bytes of that shape, its
# codec_kernels meta (or None), then (offset, point dtype, points) of point 0 and of the run.
_ENCODED: dict = {}
# The compiled point readers and writers (nodes.codec_kernels): one call per batch instead of a
# dozen numpy calls of about a microsecond each. Imported on first use (numba's import takes
# about half a second, which a tool reading one bag need not pay); little-endian hosts only, the
# byte order the kernels read.
_KERNELS = None
_KERNEL_HOST = sys.byteorder == 'little'
_WARM = False


def _kernels():
    global _KERNELS
    if _KERNELS is None:
        from piezo_narx_ros.nodes.wire import kernels as codec_kernels
        _KERNELS = codec_kernels
    return _KERNELS


def warm_up() -> None:
    """
    Load (or compile) the batch kernels now rather than on a stream's second batch.

    Nodes with batch streams call it at start: the first use would otherwise hold the stream up
    while numba loads them (0.1-1 s; a few seconds the first time they are compiled).
    """
    global _WARM
    if _KERNEL_HOST and not _WARM:
        t = np.arange(2, dtype=np.int64)
        for _ in range(2):       # the first round remembers the shape, the second uses it
            decode_joint_trajectory(encode_joint_trajectory(t, ['x'], effort=np.zeros((2, 1))))
        _WARM = True


def _plain(a: np.ndarray) -> np.ndarray:
    """Return `a` as the kernels take it (C-contiguous, writable), copied if need be."""
    f = a.flags
    return a if f.c_contiguous and f.writeable else np.array(a, order='C')


def _decode_known_shape(buf: bytes) -> SampleBatch | None:
    """Decode a batch of a shape seen before with one structured view; None if not known."""
    for shape in _SHAPES.get(len(buf), ()):
        if buf[12:shape.start] != shape.prefix or buf[:4] != shape.encapsulation:
            continue
        if shape.meta is not None:       # little endian: one compiled call
            sec, nsec = _STAMP.unpack_from(buf, 4)
            ok, stamps, pos, eff = _kernels().read_points(
                np.frombuffer(buf, np.uint8), shape.meta, sec * 1_000_000_000 + nsec)
            if ok:
                return SampleBatch(stamps, list(shape.names), pos, eff)
            continue
        parts = [np.frombuffer(buf, shape.dtype, shape.count - (shape.head is not None),
                               shape.run)]
        if shape.head is not None:
            parts.insert(0, np.frombuffer(buf, shape.head, 1, shape.start))
        if all((p['n_pos'] == shape.n_pos).all() and (p['n_vae'] == (0, 0, shape.n_eff)).all()
               for p in parts):
            return _known_batch(buf, shape, parts)
    return None       # no shape of this length matches: the general path decides


def _known_batch(buf: bytes, shape: _BatchShape, parts: list) -> SampleBatch:
    """Return the SampleBatch of `parts`, structured views of `buf`'s points in order."""
    def field(name: str) -> np.ndarray:
        return parts[0][name] if len(parts) == 1 else np.concatenate([p[name] for p in parts])
    e = '<' if buf[1] == 1 else '>'
    sec, nsec = struct.unpack_from(e + 'iI', buf, 4)
    stamps = field('sec').astype(np.int64) * 1_000_000_000 + field('nsec')
    stamps += sec * 1_000_000_000 + nsec
    empty = np.empty((shape.count, 0))
    return SampleBatch(stamps, list(shape.names),
                       field('pos') if shape.n_pos else empty,
                       field('eff') if shape.n_eff else empty)


def _known_shape_of(buf) -> _BatchShape | None:
    """Return the remembered shape whose header (but the stamp) `buf` repeats, or None."""
    if not isinstance(buf, bytes):
        return None
    for shape in _SHAPES.get(len(buf), ()):
        if buf[12:shape.start] == shape.prefix and buf[:4] == shape.encapsulation:
            return shape
    return None


def batch_points(buf) -> int | None:
    """
    Count the points of a serialized JointTrajectory without decoding it.

    Only for a batch whose header (but the stamp) repeats a shape seen before, a stream's usual
    batch; None for any other (decode it to know).
    """
    shape = _known_shape_of(buf)
    return None if shape is None else shape.count


def _decode_run(bufs: list, shape: _BatchShape) -> SampleBatch | None:
    """
    Decode messages of one known shape as one batch of all their points, in order.

    One strided view per field over the joined bytes (m messages of L bytes): the cost of one
    message for the lot. None when a point's counts differ from the shape (decode one by one).
    """
    m, size = len(bufs), len(bufs[0])
    joined = b''.join(bufs)
    e = '<' if joined[1] == 1 else '>'
    n_run = shape.count - (shape.head is not None)
    parts = [np.ndarray((m, n_run), shape.dtype, joined, shape.run,
                        (size, shape.dtype.itemsize))]
    if shape.head is not None:
        parts.insert(0, np.ndarray((m, 1), shape.head, joined, shape.start, (size, 0)))
    if not all((p['n_pos'] == shape.n_pos).all() and (p['n_vae'] == (0, 0, shape.n_eff)).all()
               for p in parts):
        return None

    def field(name: str) -> np.ndarray:
        values = parts[0][name] if len(parts) == 1 else np.concatenate(
            [p[name] for p in parts], axis=1)
        return values.reshape((m * shape.count,) + values.shape[2:])
    sec = np.ndarray((m, 1), e + 'i4', joined, 4, (size, 4)).astype(np.int64)
    nsec = np.ndarray((m, 1), e + 'u4', joined, 8, (size, 4))
    stamps = (field('sec').astype(np.int64) * 1_000_000_000 + field('nsec')).reshape(m, -1)
    stamps += sec * 1_000_000_000 + nsec
    empty = np.empty((m * shape.count, 0))
    return SampleBatch(stamps.ravel(), list(shape.names),
                       field('pos') if shape.n_pos else empty,
                       field('eff') if shape.n_eff else empty)


def decode_joint_trajectories(bufs: Sequence[bytes]) -> list[tuple[int, SampleBatch | DataError]]:
    """
    Decode serialized JointTrajectory messages in order, consecutive ones of a shape together.

    Returns [(number of messages, SampleBatch of all their points, or the DataError of the one
    message refused)]: a run of messages of one shape seen before (a stream's usual case: same
    names, same batch size) is read with one view over all of them, about the cost of one
    decode_joint_trajectory() for the lot; any other message is decoded alone, so a malformed
    one is refused alone, exactly as decode_joint_trajectory() refuses it.
    """
    out: list = []
    i, n = 0, len(bufs)
    while i < n:
        shape = _known_shape_of(bufs[i])
        j = i + 1
        if shape is not None:
            while j < n and len(bufs[j]) == len(bufs[i]) and _known_shape_of(bufs[j]) is shape:
                j += 1
            batch = _decode_run(list(bufs[i:j]), shape) if j - i > 1 else None
            if batch is not None:
                out.append((j - i, batch))
                i = j
                continue
        for buf in bufs[i:j]:     # alone: a point of another size is refused with its message
            try:
                out.append((1, decode_joint_trajectory(buf)))
            except DataError as exc:
                out.append((1, exc))
        i = j
    return out


def decode_joint_trajectory(buf: bytes) -> SampleBatch:
    """
    Decode a serialized JointTrajectory (CDR) to a SampleBatch of every point's stamp and values.

    Stamp of point k: header.stamp + time_from_start, in exact integer ns. Raises DataError on a
    truncated or malformed buffer, or on points whose positions/effort sizes differ from each
    other or from joint_names (a bad batch is refused whole, as a bad JointState is). A batch of
    the shape of the one before it (a stream's usual case) is read with one structured view.
    """
    known = _decode_known_shape(buf) if isinstance(buf, bytes) else None
    if known is not None:
        return known
    try:
        e, data, t0, names, off = _read_header_names(buf)
        off = (off + 3) & ~3
        (count,) = struct.unpack_from(e + 'I', data, off)
        off += 4
        if count > len(data) // 20:   # a point takes at least 20 bytes: no absurd allocation
            raise DataError(f'malformed JointTrajectory ({len(buf)} bytes): {count} points '
                            'cannot fit')
        stamps, positions, efforts = [], [], []
        first = off
        for k in range(count):
            pos, eff, (sec, nsec), next_off = _read_point(e, data, off)
            if k == 0 or (k == 1 and (len(pos), len(eff)) == (len(positions[0]),
                                                              len(efforts[0]))):
                # The points from here on as arrays, when they share this point's shape: from
                # point 0 when its layout repeats, else (it starts at the other phase) point 1.
                layout = _point_layout(off % 8, len(pos), len(eff))
                if layout is not None and off + (count - k) * layout.size <= len(data):
                    run = _read_run(buf, off + 4, count - k, layout, e, len(pos), len(eff))
                    if run is not None:
                        if isinstance(buf, bytes) and len(names) in (
                                0, len(pos), len(eff)) and len(names) >= len(pos) \
                                and len(names) >= len(eff):
                            _remember_shape(buf, first + 4, off + 4, names, count, layout, e,
                                            len(pos), len(eff))
                        if k:
                            stamps = np.concatenate((stamps, run[0]))
                            positions = np.concatenate((np.reshape(positions, (1, -1)), run[1]))
                            efforts = np.concatenate((np.reshape(efforts, (1, -1)), run[2]))
                        else:
                            stamps, positions, efforts = run
                        break
            stamps.append(sec * 1_000_000_000 + nsec)
            positions.append(pos)
            efforts.append(eff)
            off = next_off
    except (struct.error, IndexError, UnicodeDecodeError) as exc:
        raise DataError(f'malformed JointTrajectory ({len(buf)} bytes): {exc}') from None
    if not isinstance(positions, np.ndarray):
        n_pos = _check_width(positions, names, 'positions')
        n_eff = _check_width(efforts, names, 'effort')
        positions = np.array(positions, dtype=np.float64).reshape(count, n_pos)
        efforts = np.array(efforts, dtype=np.float64).reshape(count, n_eff)
    else:
        _check_width(list(positions[:1]), names, 'positions')
        _check_width(list(efforts[:1]), names, 'effort')
    return SampleBatch(np.asarray(stamps, dtype=np.int64) + t0, names, positions, efforts)


def _remember_shape(buf: bytes, start: int, run: int, names, count: int, layout: _PointLayout,
                    e: str, n_pos: int, n_eff: int) -> None:
    """
    Keep the shape of a well-formed batch: points at byte `start`, one strided run from `run`.

    run > start: point 0 has a layout of its own (it starts at the other 8-byte phase: e.g. the
    positions of one axis, 36 bytes, then 32 for every later point).
    """
    if len(_SHAPES) > 64:
        _SHAPES.clear()
    own = _point_layout((start - 4) % 8, n_pos, n_eff, repeat=False) if run > start else None
    head = None if own is None else _point_dtype(e, own, n_pos, n_eff)
    meta = None
    if e == '<' and _KERNEL_HOST:
        meta = _kernels().make_meta(start, run, count, n_pos, n_eff, layout.size, own, layout)
    shape = _BatchShape(bytes(buf[:4]), bytes(buf[12:start]), start, tuple(names), count,
                        _point_dtype(e, layout, n_pos, n_eff), n_pos, n_eff, head, run, meta)
    kept = [k for k in _SHAPES.get(len(buf), ()) if k != shape]
    _SHAPES[len(buf)] = [shape] + kept[:_SHAPES_PER_LENGTH - 1]


def encode_joint_trajectory(t_ns: Sequence[int], names: Sequence[str], position=None,
                            effort=None) -> bytes:
    """
    Encode a batch as JointTrajectory CDR (little endian) for Publisher.publish.

    t_ns: (n,) stamps, ns (any order; the first is header.stamp); position (n, a) m and effort
    (n, a) V, or None for an empty field. Velocities and accelerations are empty.
    """
    stamps = np.asarray(t_ns, dtype=np.int64).ravel()
    n = stamps.shape[0]
    pos = np.empty((n, 0)) if position is None else \
        np.asarray(position, dtype=np.float64).reshape(n, -1)
    eff = np.empty((n, 0)) if effort is None else \
        np.asarray(effort, dtype=np.float64).reshape(n, -1)
    t0 = int(stamps[0]) if n else 0
    key = (tuple(names), n, pos.shape[1], eff.shape[1])
    template = _ENCODED.get(key)
    if template is not None and template[1] is not None:   # a stream's usual batch, compiled
        out = bytearray(template[0])
        _STAMP.pack_into(out, 4, *divmod(t0, 1_000_000_000))
        _kernels().write_points(np.frombuffer(out, np.uint8), template[1], _plain(stamps), t0,
                                _plain(pos), _plain(eff))
        return bytes(out)
    sec, nsec = np.divmod(stamps - t0, 1_000_000_000)
    if template is not None:      # a stream's usual batch: its bytes but the values and stamps
        out = bytearray(template[0])
        _STAMP.pack_into(out, 4, *divmod(t0, 1_000_000_000))
        k = 0
        for start, dtype, count in template[2:]:   # point 0 alone (other phase), then the run
            points = np.frombuffer(out, dtype, count, start)
            if pos.shape[1]:
                points['pos'] = pos[k:k + count]
            if eff.shape[1]:
                points['eff'] = eff[k:k + count]
            points['sec'] = sec[k:k + count]
            points['nsec'] = nsec[k:k + count]
            k += count
        return bytes(out)
    out = _header_names(t0, names)
    out += b'\x00' * (-(len(out) - 4) % 4)
    out += _U32.pack(n)
    first = len(out)       # where point 0 starts
    for k in range(n):
        layout = _point_layout((len(out) - 4) % 8, pos.shape[1], eff.shape[1])
        if layout is not None:     # every remaining point has this layout: strided arrays
            rest, start = n - k, len(out)
            out += bytes(rest * layout.size)

            def view(name, code, width=0):
                return _field(out, layout, name, start, rest, code, width)
            view('n_pos', '<u4')[:] = pos.shape[1]
            view('n_eff', '<u4')[:] = eff.shape[1]
            if pos.shape[1]:
                view('pos', '<f8', pos.shape[1])[:] = pos[k:]
            if eff.shape[1]:
                view('eff', '<f8', eff.shape[1])[:] = eff[k:]
            view('sec', '<i4')[:] = sec[k:]
            view('nsec', '<u4')[:] = nsec[k:]
            if k <= 1:     # the batch is one strided run (after point 0): keep its bytes
                if len(_ENCODED) > 64:
                    _ENCODED.clear()
                parts = [(start, _point_dtype('<', layout, pos.shape[1], eff.shape[1]), rest)]
                own = None
                if k:
                    own = _point_layout((first - 4) % 8, pos.shape[1], eff.shape[1], False)
                    parts.insert(0, (first, _point_dtype('<', own, pos.shape[1], eff.shape[1]),
                                     1))
                meta = _kernels().make_meta(first, start, n, pos.shape[1], eff.shape[1],
                                            layout.size, own, layout) if _KERNEL_HOST else None
                _ENCODED[key] = (bytes(out), meta, *parts)
            break
        _put_doubles(out, pos[k].tolist())
        out += b'\x00' * 8                            # velocities, accelerations: empty
        _put_doubles(out, eff[k].tolist())
        out += b'\x00' * (-(len(out) - 4) % 4)
        out += _DURATION.pack(int(sec[k]), int(nsec[k]))
    return bytes(out)


def make_joint_trajectory(t_ns: Sequence[int], names: Sequence[str], position=None,
                          effort=None):
    """Build the trajectory_msgs/JointTrajectory of a batch (rclpy object; see the encoder)."""
    from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint
    stamps = [int(t) for t in t_ns]
    msg = JointTrajectory()
    t0 = stamps[0] if stamps else 0
    msg.header.stamp.sec, msg.header.stamp.nanosec = ns_to_stamp(t0)
    msg.joint_names = list(names)
    for k, t in enumerate(stamps):
        point = JointTrajectoryPoint()
        if position is not None:
            point.positions = [float(v) for v in np.ravel(position[k])]
        if effort is not None:
            point.effort = [float(v) for v in np.ravel(effort[k])]
        point.time_from_start.sec, point.time_from_start.nanosec = divmod(t - t0, 1_000_000_000)
        msg.points.append(point)
    return msg
