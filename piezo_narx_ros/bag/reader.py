"""
Read rosbag2 bags (MCAP or sqlite3 storage, a bag directory or a lone .mcap/.db3 file).

Reading never executes code from the bag: messages are decoded only with the `rosbags` built-in
type store (ROS 2 Kilted definitions shipped with the library), never with definitions taken from
the bag, because turning a bag's definition into a decoder generates and runs Python code.
"""
from __future__ import annotations

import struct
import sys
import warnings
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import numpy as np

from piezo_narx_ros.axis_names import repeated
from piezo_narx_ros.bag.pairing import (StreamCheck, clean_stream, pair_by_stamp,
                                        sample_clock)
from piezo_narx_ros.bag.writer import (BATCH_SUFFIX, COMMAND_TOPIC, DEFLECTION_TOPIC,
                                       JOINT_STATE, JOINT_TRAJECTORY, absolute_topic,
                                       is_being_recorded, typestore)
from piezo_narx_ros.errors import BagError
from piezo_narx_ros.record import Record

_FILE_SUFFIXES = ('.mcap', '.db3')


class BagWarning(UserWarning):
    """A non-fatal problem in a bag's data (gap, duplicate, reordering, irregular rate)."""


# ------------------------------------------------------------------------------------ opening
def _storage_file(directory: Path) -> Path | None:
    files = sorted(p for p in directory.iterdir() if p.suffix in _FILE_SUFFIXES)
    return files[0] if len(files) == 1 else None


@contextmanager
def open_bag(path: str | Path):
    """
    Open a bag for reading with rosbags' `Reader`.

    A directory with metadata.yaml, or one .mcap/.db3 file; a directory whose metadata.yaml is
    missing is read through its single storage file. Every failure is a one-line BagError naming
    the bag.
    """
    from rosbags.rosbag2 import Reader, ReaderError
    path = Path(path)
    if not path.exists():
        raise BagError(f'bag not found: {path}')
    target = path
    if path.is_dir() and not (path / 'metadata.yaml').is_file():
        target = _storage_file(path)
        if target is None:
            raise BagError(f'{path} is not a rosbag2 bag: no metadata.yaml and not exactly one '
                           '.mcap/.db3 file in it')
    elif path.is_file() and path.suffix not in _FILE_SUFFIXES:
        raise BagError(f'{path}: not a bag (expected a bag directory, .mcap or .db3 file)')
    hint = ''
    mcaps = [target] if target.suffix == '.mcap' else sorted(target.glob('*.mcap')) \
        if target.is_dir() else []
    if any(is_being_recorded(m) for m in mcaps):
        hint = ' (it is being recorded right now: read it once the recorder has stopped)'
    elif mcaps:
        hint = (f' (interrupted recording or unreadable metadata.yaml? try: piezo-narx bag repair '
                f'{path})')
    try:
        reader = Reader(target)
        reader.open()
    except (ReaderError, OSError, ValueError, KeyError, TypeError, struct.error,
            EOFError) as exc:
        raise BagError(f'cannot read bag {path}: {_one_line(exc)}{hint}') from None
    try:
        yield reader
    finally:
        reader.close()


def _one_line(exc: BaseException) -> str:
    text = ' '.join(str(exc).split()) or type(exc).__name__
    return text.rstrip('.')


def _messages(reader, connections, path) -> Iterator[tuple[object, int, bytes]]:
    """Iterate rosbags' messages with storage errors turned into one-line BagErrors."""
    from rosbags.rosbag2 import ReaderError
    try:
        yield from reader.messages(connections=connections)
    except (ReaderError, OSError, ValueError, KeyError, struct.error, EOFError) as exc:
        raise BagError(f'bag {path} is damaged while reading messages: {_one_line(exc)} '
                       f'(try: piezo-narx bag repair {path})') from None


def find_topic(reader, topic: str, msgtype: str | None = None, path='bag') -> list:
    """
    Return the connections of `topic` (with or without leading '/').

    BagError naming the available topics when it is absent, or when its type is not `msgtype`.
    """
    name = absolute_topic(topic)
    conns = [c for c in reader.connections if absolute_topic(c.topic) == name]
    if not conns:
        have = ', '.join(sorted({absolute_topic(c.topic) for c in reader.connections})) or 'none'
        raise BagError(f'topic {name} not in bag {path} (topics: {have})')
    if msgtype is not None:
        wrong = sorted({c.msgtype for c in conns if c.msgtype != msgtype})
        if wrong:
            raise BagError(f'topic {name} in bag {path} has type {wrong[0]}, expected {msgtype}')
        expected_hash = typestore().hash_rihs01(msgtype)
        for c in conns:
            # Bags from before ROS 2 Iron carry no hash; a different one is a foreign definition.
            if c.digest and c.digest.startswith('RIHS01_') and c.digest != expected_hash:
                raise BagError(f'topic {name} in bag {path}: {msgtype} definition differs from '
                               f'the standard one (type hash {c.digest[:19]}...)')
    return conns


SAMPLE_TYPES = (JOINT_STATE, JOINT_TRAJECTORY)


def find_sample_topic(reader, topic: str, path='bag') -> tuple[list, str]:
    """
    Return (connections, type) of a sample stream: `topic`, or its batched twin `<topic>_batch`.

    A batched recording (DESIGN.md "High-rate streams") reads like a one-sample one: asked for
    /piezo/deflection, a bag holding only /piezo/deflection_batch gives that. BagError when
    neither is there, or when the type is neither JointState nor JointTrajectory.
    """
    name = absolute_topic(topic)
    have = {absolute_topic(c.topic) for c in reader.connections}
    if name not in have and name + BATCH_SUFFIX in have:
        name += BATCH_SUFFIX
    conns = find_topic(reader, name, None, path)
    types = sorted({c.msgtype for c in conns})
    if len(types) != 1 or types[0] not in SAMPLE_TYPES:
        raise BagError(f'topic {name} in bag {path} has type {types[0]}, expected '
                       f'{JOINT_STATE} (or {JOINT_TRAJECTORY} for batches)')
    return find_topic(reader, name, types[0], path), types[0]


def joint_samples(msg, msgtype: str, field: str) -> list[tuple[int, object]]:
    """
    Return [(stamp ns, array of `field`)] of one decoded sample message.

    One pair for a JointState, one per point for a JointTrajectory (stamp = header.stamp +
    time_from_start, exact).

    field: 'position', 'velocity' or 'effort' (the JointState names; a point's are plural).
    """
    st = msg.header.stamp
    t0 = st.sec * 1_000_000_000 + st.nanosec
    if msgtype == JOINT_STATE:
        return [(t0, getattr(msg, field))]
    name = {'position': 'positions', 'velocity': 'velocities'}.get(field, field)
    return [(t0 + p.time_from_start.sec * 1_000_000_000 + p.time_from_start.nanosec,
             getattr(p, name)) for p in msg.points]


def decode_cdr(raw: bytes, typename: str):
    """
    Decode CDR bytes of a built-in type with the rosbags type store.

    Trailing bytes after a complete message are tolerated: rclpy's serialize_message with this
    rmw returns buffers 8 bytes longer than the message, and a bag of republished bytes keeps
    them, while rosbags refuses more than 3 bytes of end padding.
    """
    from rosbags.serde import SerdeError
    store = typestore()
    try:
        return store.deserialize_cdr(raw, typename)
    except SerdeError as exc:
        if 'size mismatch' not in str(exc) or len(raw) < 4:
            raise
    msgdef = store.get_msgdef(typename)
    func = msgdef.deserialize_cdr_le if raw[1] == 1 else msgdef.deserialize_cdr_be
    return func(memoryview(raw)[4:], 0, msgdef.cls, store)[0]


# ------------------------------------------------------------------------------- JointState data
@dataclass
class JointSeries:
    """
    One sample topic's values in arrival order (JointState, or JointTrajectory batches).

    Header stamps (ns, per sample: a batch's points each have theirs), receive times (ns, of the
    message that carried the sample), the chosen field of the chosen axis, how many samples
    lacked it, and the joint names the messages carried (first seen first).
    """

    topic: str
    stamps_ns: np.ndarray      # (n,) int64
    log_ns: np.ndarray         # (n,) int64, rosbag2 receive timestamps
    values: np.ndarray         # (n,) float64, SI (m for position, V for effort); (n, k) for k axes
    malformed: int = 0
    names: list = field(default_factory=list)   # joint names seen on the topic
    axis: str | int | None = None                # the axis read: its name, or an index
    channels: tuple = ()       # several axes read (axis None, messages naming several joints)
    missing: dict = field(default_factory=dict)  # several axes: {axis: samples without it}


def _axis_index(names, axis, n_values: int):
    """
    Index into a message's arrays for `axis`, or None when the message lacks it.

    By name whenever the message names its joints (never by position then); an index only for
    messages without names; axis None: the message's only joint.
    """
    if names:
        if axis is None:
            return 0 if len(names) == 1 else None
        key = str(axis)
        return names.index(key) if key in names else None
    if axis is None:
        return 0 if n_values >= 1 else None
    if isinstance(axis, int) or str(axis).isdigit():
        i = int(axis)
        return i if i < n_values else None
    return None


def _channel_indices(names, channels):
    """Return the indices of `channels` in a message's joint names (-1 where one is missing)."""
    return [names.index(c) if c in names else -1 for c in channels]


def topic_channels(keys) -> tuple:
    """
    Return the axes of a topic from the distinct joint-name tuples its messages carried.

    Every name seen on the topic is an axis (a message naming only some of them does not decide
    for the others); in the order of the first message that names them all, else first seen
    first. Fewer than two names: () (the one-axis case, read by `axis`).
    """
    union = tuple(dict.fromkeys(n for key in keys for n in key))
    if len(union) < 2:
        return ()
    full = [key for key in keys if set(key) == set(union)]
    return tuple(full[0]) if full else union


def read_joint_series(path: str | Path, fields: dict[str, str], axis: str | int | None = None
                      ) -> dict[str, JointSeries]:
    """
    Read JointState topics of a bag in one pass.

    fields: {topic: 'position' | 'effort'}; axis: the joint name to read (matched by name in each
    message), an index for messages without names, or None for a bag with one axis. Returns
    {topic (as given): JointSeries}. Samples lacking the axis are counted in `malformed`. A topic
    recorded batched (`<topic>_batch`, JointTrajectory) gives the same samples and stamps.

    With axis None and messages naming several joints, every joint is read: the topic's channels
    are every name its messages carried over the whole bag (`topic_channels`), each message's
    values are found by name (never by position), and a sample lacking one of them is counted
    (`malformed`, and per axis in `missing`), not fatal; values are then (n, channels).
    """
    with open_bag(path) as reader:
        by_conn, kinds = {}, {}
        for topic, fld in fields.items():
            if fld not in ('position', 'effort', 'velocity'):
                raise BagError(f'unknown JointState field {fld!r}')
            conns, kinds[topic] = find_sample_topic(reader, topic, path)
            for c in conns:
                by_conn[c.id] = topic
        # Per topic: stamps, receive times, the sample's joint-name tuple (an id into `seen`),
        # and its whole value array; which names are axes is decided once the bag is read.
        acc = {t: ([], [], [], []) for t in fields}
        seen = {t: {} for t in fields}          # names tuple -> id (first seen first)
        conns = [c for c in reader.connections if c.id in by_conn]
        for conn, log_ns, raw in _messages(reader, conns, path):
            topic = by_conn[conn.id]
            kind = kinds[topic]
            try:
                msg = decode_cdr(raw, kind)
            except Exception as exc:  # noqa: BLE001 - any decode failure is a damaged message
                raise BagError(f'bag {path}: cannot decode a {kind} message on '
                               f'{absolute_topic(conn.topic)} at log time {log_ns} ns: '
                               f'{_one_line(exc)}') from None
            names = tuple(msg.name if kind == JOINT_STATE else msg.joint_names)
            key = seen[topic].setdefault(names, len(seen[topic]))
            stamps, logs, keys, values = acc[topic]
            for t_ns, arr in joint_samples(msg, kind, fields[topic]):
                stamps.append(t_ns)
                logs.append(log_ns)
                keys.append(key)
                values.append(arr)
    for topic, keys in seen.items():
        for names in keys:
            dup = repeated(names)
            if dup is not None:
                raise BagError(f'bag {path}: {absolute_topic(topic)} carries messages naming '
                               f'axis {dup!r} twice ({", ".join(names)}): their values cannot '
                               'be told apart')
    return {t: _series(t, acc[t], list(seen[t]), axis) for t in fields}


def _series(topic, acc, keys, axis) -> JointSeries:
    """Map one topic's samples to its axis (or channels) by name; count the ones lacking it."""
    stamps, logs, key_of, arrays = acc
    chans = topic_channels(keys) if axis is None else ()
    # Per name tuple: the channel indices, or the axis's index (checked against each array).
    index = [_channel_indices(names, chans) if chans else _axis_index(names, axis, sys.maxsize)
             for names in keys]
    missing = dict.fromkeys(chans, 0)
    keep, values = [], []
    for n, (key, arr) in enumerate(zip(key_of, arrays)):
        names, i = keys[key], index[key]
        if chans:
            if len(arr) != len(names):
                continue
            lacking = [c for c, j in zip(chans, i) if j < 0]
            for c in lacking:
                missing[c] += 1
            if lacking:
                continue
            values.append([float(arr[j]) for j in i])
        else:
            if i is None or i >= len(arr):
                continue
            values.append(float(arr[i]))
        keep.append(n)
    keep = np.asarray(keep, dtype=np.int64)
    names = list(dict.fromkeys(nm for key in keys for nm in key))
    k = len(chans)
    return JointSeries(absolute_topic(topic),
                       np.asarray(stamps, dtype=np.int64).reshape(-1)[keep],
                       np.asarray(logs, dtype=np.int64).reshape(-1)[keep],
                       np.asarray(values, dtype=np.float64).reshape((-1, k) if k else (-1,)),
                       len(key_of) - keep.size, names, axis, chans,
                       {c: m for c, m in missing.items() if m})


def _check_axes(path, series, axis) -> None:
    """Raise BagError when the topics cannot be paired by joint name (never by position)."""
    named = [s for s in series if s.names]
    if axis is None:
        multi = [s for s in series if s.channels]
        if multi:
            for s in series:
                if not s.channels:
                    raise BagError(f'bag {path}: {multi[0].topic} carries the axes '
                                   f'{", ".join(multi[0].channels)} but {s.topic} names '
                                   f'{", ".join(s.names) or "no axis"}: several axes pair by '
                                   'name on both topics; choose one with --axis NAME')
            return
        if len(named) == 2 and named[0].names != named[1].names:
            raise BagError(f'bag {path}: {named[0].topic} is axis {named[0].names[0]!r} but '
                           f'{named[1].topic} is axis {named[1].names[0]!r}: they do not pair '
                           'by name; choose one with --axis NAME')
    elif not str(axis).isdigit():
        for s in series:
            if s.values.size == 0 and s.names:
                raise BagError(f'bag {path}: {s.topic} has no axis {axis!r} (its axes: '
                               f'{", ".join(s.names)})')


def read_uy_report(path: str | Path, command_topic: str = COMMAND_TOPIC,
                   deflection_topic: str = DEFLECTION_TOPIC, axis: str | int | None = None):
    """Like `read_uy`, but returns (Record, PairingReport) and issues no warning."""
    if absolute_topic(command_topic) == absolute_topic(deflection_topic):
        raise BagError('command and deflection topics must differ')
    series = read_joint_series(path, {command_topic: 'effort', deflection_topic: 'position'},
                               axis)
    su, sy = series[command_topic], series[deflection_topic]
    _check_axes(path, (su, sy), axis)
    for s, kind, fld in ((su, 'command', 'effort'), (sy, 'deflection', 'position')):
        if s.values.size == 0:
            which = f'axis {axis!r}' if axis is not None else 'its axis'
            if s.missing:
                which = 'axis ' + ', '.join(f'{a} ({m})' for a, m in s.missing.items())
            extra = f' ({s.malformed} message(s) without {fld} of {which})' if s.malformed \
                else ''
            raise BagError(f'bag {path}: no {kind} samples on {s.topic}{extra}')
    if su.channels and set(sy.channels) == set(su.channels) and sy.channels != su.channels:
        # The same axes on both topics: outputs in the command's order (axis k in, axis k out).
        order = [sy.channels.index(c) for c in su.channels]
        sy.values, sy.channels = sy.values[:, order], su.channels
    t_ns, u, y, report = pair_by_stamp(su.stamps_ns, su.values, sy.stamps_ns, sy.values)
    for check, s in ((report.command, su), (report.deflection, sy)):
        check.malformed, check.missing_axes = s.malformed, dict(s.missing)
    for name, arr in (('command', u), ('deflection', y)):
        if not np.all(np.isfinite(arr)):
            raise BagError(f'bag {path}: {np.count_nonzero(~np.isfinite(arr))} non-finite '
                           f'{name} value(s)')
    record = Record(u=u, y=y, fs=report.fs, source=str(path),
                    t=(t_ns - t_ns[0]).astype(np.float64) * 1e-9, y_true=None,
                    inputs=su.channels or None, outputs=sy.channels or None)
    return record, report


def read_uy(path: str | Path, command_topic: str = COMMAND_TOPIC,
            deflection_topic: str = DEFLECTION_TOPIC, axis: str | int | None = None):
    """
    Identification record (u in V, y in m) from a bag, samples paired by header.stamp.

    u is the effort of joint `axis` on the command topic, y its position on the deflection topic,
    each found by name in every message (None: the bag's one axis, or every axis when the
    messages name several: each command joint an input, each deflection joint an output, named
    as in the bag; an index only for messages without names); topic names may have a leading
    '/'. fs (Hz) is inferred from the stamps;
    `Record.t` is seconds since the first paired sample. Non-fatal findings (gaps, duplicates,
    reordering, irregular rate) are issued as `BagWarning`s; a missing/mistyped topic or an
    unreadable bag raises BagError.
    """
    record, report = read_uy_report(path, command_topic, deflection_topic, axis)
    for line in report.issues():
        warnings.warn(f'{path}: {line}', BagWarning, stacklevel=2)
    return record


# ------------------------------------------------------------------------------------- summary
@dataclass
class TopicInfo:
    """
    One topic of a bag.

    Stamp figures come from header.stamp for JointState topics (from every point's stamp for
    JointTrajectory batches, so a batched stream shows its sample rate) and from the receive time
    otherwise.
    """

    name: str
    msgtype: str
    count: int
    samples: int = 0          # samples (= count, or the points of every batch) with a stamp
    first_ns: int = 0
    last_ns: int = 0
    rate_hz: float = 0.0
    gaps: int = 0
    missing: int = 0
    jitter: float = 0.0
    check: StreamCheck | None = None
    names: list = field(default_factory=list)   # JointState joint names seen (first seen first)

    @property
    def duration_s(self) -> float:
        """Span from the first to the last stamp, s."""
        return (self.last_ns - self.first_ns) * 1e-9


@dataclass
class BagInfo:
    """What `bag_info` reports about a bag."""

    path: str
    storage: str
    message_count: int
    start_ns: int
    end_ns: int
    topics: list[TopicInfo] = field(default_factory=list)

    @property
    def duration_s(self) -> float:
        """Receive-time span of the whole bag, s."""
        return max(0, self.end_ns - self.start_ns) * 1e-9


def bag_info(path: str | Path) -> BagInfo:
    """
    Summarise a bag: topics, counts, duration, per-topic rate, gaps and stamp order.

    Reads every message; JointState and JointTrajectory topics are decoded for their stamps.
    """
    store = typestore()
    path = Path(path)
    with open_bag(path) as reader:
        # Receive times of every message (the count) and header stamps while they decode; a
        # topic with an undecodable message falls back to receive times, and loses no count.
        logs: dict[int, list[int]] = {c.id: [] for c in reader.connections}
        headers: dict[int, list[int]] = {c.id: [] for c in reader.connections}
        joints: dict[int, dict] = {c.id: {} for c in reader.connections}
        decodable = {c.id for c in reader.connections
                     if c.msgtype in SAMPLE_TYPES and not (
                         c.digest and c.digest.startswith('RIHS01_')
                         and c.digest != store.hash_rihs01(c.msgtype))}
        for conn, log_ns, raw in _messages(reader, reader.connections, path):
            logs[conn.id].append(log_ns)
            if conn.id in decodable:
                try:
                    msg = decode_cdr(raw, conn.msgtype)
                    samples = joint_samples(msg, conn.msgtype, 'position')
                    headers[conn.id] += [t for t, _ in samples]
                    joints[conn.id].update(dict.fromkeys(
                        msg.name if conn.msgtype == JOINT_STATE else msg.joint_names))
                except Exception:  # noqa: BLE001 - fall back to receive times for this topic
                    decodable.discard(conn.id)
        stamps = {cid: headers[cid] if cid in decodable else logs[cid] for cid in logs}
        subs = getattr(reader.storage, 'storages', None) or [reader.storage]
        storage = 'sqlite3' if any('Sqlite3' in type(s).__name__ for s in subs) else 'mcap'
        topics = []
        for conn in reader.connections:
            s, _, check = clean_stream(np.asarray(stamps[conn.id], np.int64),
                                       np.zeros(len(stamps[conn.id])))
            info = TopicInfo(absolute_topic(conn.topic), conn.msgtype, len(logs[conn.id]),
                             len(stamps[conn.id]),
                             check=check if conn.id in decodable else None,
                             names=list(joints[conn.id]))
            if s.size:
                info.first_ns, info.last_ns = int(s[0]), int(s[-1])
            if s.size >= 2:
                info.rate_hz, gaps, info.jitter = sample_clock(s)
                info.gaps, info.missing = len(gaps), int(sum(n for _, n in gaps))
            topics.append(info)
        count = sum(t.count for t in topics)
        start = reader.start_time if count else 0
        end = reader.end_time if count else 0
    return BagInfo(str(path), storage, count, start, end, topics)


def iter_raw(path: str | Path, topics: list[str] | None = None
             ) -> Iterator[tuple[str, str, int, bytes]]:
    """
    Iterate the raw messages of a bag in receive-time order.

    (absolute topic, type, receive time ns, CDR bytes) of every message, optionally only of
    `topics` (BagError when one is absent). Nothing is decoded.
    """
    with open_bag(path) as reader:
        conns = reader.connections
        if topics:
            conns = [c for t in topics for c in find_topic(reader, t, None, path)]
        for conn, log_ns, raw in _messages(reader, conns, path):
            yield absolute_topic(conn.topic), conn.msgtype, int(log_ns), bytes(raw)
