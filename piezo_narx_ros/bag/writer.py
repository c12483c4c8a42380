"""
Write rosbag2 bags (MCAP storage, metadata version 9) with `rosbags`.

A bag written here is a directory `NAME/` holding `NAME.mcap` (profile `ros2`, `ros2msg` schemas,
`cdr` messages, channel metadata `offered_qos_profiles` and `topic_type_hash`, a `rosbag2`
metadata record) and `metadata.yaml` (version 9, `ros_distro` of the recording), the layout of
`ros2 bag record -s mcap` (rosbag2_storage_mcap). docs/bags.md says which readers were checked.

Message definitions come from the `rosbags` built-in type store of the ROS 2 Kilted distribution:
only types it knows can be recorded (every std/sensor/diagnostic message is there).
"""
from __future__ import annotations

import os
import time
from functools import lru_cache
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

from piezo_narx_ros.errors import BagError

JOINT_STATE = 'sensor_msgs/msg/JointState'
# A batch of samples (DESIGN.md "High-rate streams"), on `<topic>_batch` topics.
JOINT_TRAJECTORY = 'trajectory_msgs/msg/JointTrajectory'
BATCH_SUFFIX = '_batch'
COMMAND_TOPIC = 'piezo/voltage_command'
DEFLECTION_TOPIC = 'piezo/deflection'
ESTIMATE_TOPIC = 'piezo/deflection_estimate'


@lru_cache(maxsize=1)
def typestore():
    """
    Return the built-in type store of rosbags (ROS 2 Kilted).

    Never extended with types from a bag, because registering a definition generates and executes
    Python code.
    """
    from rosbags.typesys import Stores, get_typestore
    return get_typestore(Stores.ROS2_KILTED)


def absolute_topic(name: str) -> str:
    """
    Return the absolute topic name (rosbag2 stores absolute names).

    'piezo/deflection' or '/piezo/deflection' -> '/piezo/deflection'. Raises BagError on an empty
    name.
    """
    stripped = str(name).strip().strip('/')
    if not stripped:
        raise BagError(f'empty topic name {name!r}')
    return '/' + stripped


def check_type(msgtype: str, topic: str = '') -> None:
    """
    Raise BagError unless `msgtype` is a built-in ROS 2 Kilted type.

    The only ones a bag here can carry: their definitions are embedded, never taken from elsewhere.
    """
    if msgtype not in typestore().fielddefs:
        where = f' for topic {topic}' if topic else ''
        raise BagError(f'unknown message type {msgtype!r}{where} '
                       '(only ROS 2 Kilted built-in types can be recorded)')


def ros_distro() -> str:
    """
    Return the distribution written in a bag's metadata.

    $ROS_DISTRO as rosbag2 does, else 'kilted', the distribution of the rclpy wheels and of the
    message definitions this writer embeds.
    """
    return os.environ.get('ROS_DISTRO', '').strip() or 'kilted'


def offered_qos(reliable: bool = True, depth: int = 100):
    """
    Return the rosbags `Qos` the project's publishers offer.

    Keep-last `depth`, reliable or best effort, volatile; stored per topic so `ros2 bag play`
    republishes with the same QoS.
    """
    from rosbags.interfaces import (Qos, QosDurability, QosHistory, QosLiveliness,
                                    QosReliability, QosTime)
    zero = QosTime(0, 0)  # 0 = rmw default (infinite) for deadline, lifespan and lease
    return Qos(QosHistory.KEEP_LAST, int(depth),
               QosReliability.RELIABLE if reliable else QosReliability.BEST_EFFORT,
               QosDurability.VOLATILE, zero, zero, QosLiveliness.AUTOMATIC, zero, False)


def lock_recording(mcap_path: Path):
    """
    Return an open handle holding an exclusive flock on `mcap_path`.

    Released when closed or when the process dies; None where flock is unavailable. Raises BagError
    when another process holds it: the file is being recorded (or repaired) right now.
    """
    try:
        import fcntl
    except ImportError:   # not POSIX: no live-recording protection
        return None
    handle = open(mcap_path, 'rb')
    try:
        fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        handle.close()
        raise BagError(f'{mcap_path} is being recorded right now (another process holds its '
                       'lock); stop the recorder first') from None
    return handle


def is_being_recorded(mcap_path: Path) -> bool:
    """Return True while a BagWriter (in any process) has `mcap_path` open for recording."""
    try:
        handle = lock_recording(mcap_path)
    except BagError:
        return True
    except OSError:
        return False
    if handle is not None:
        handle.close()
    return False


class BagWriter:
    """
    rosbag2 bag writer (MCAP, version 9) taking already-serialized CDR messages.

    Use as a context manager, or call `close()`: metadata.yaml and the MCAP summary are written on
    close. Pending messages are cut into an MCAP chunk and handed to the OS at least every
    `chunk_period_s` seconds, so a process killed with SIGKILL loses at most that much; its bag is
    made readable again by `piezo_narx_ros.bag.repair.repair_bag`.
    """

    def __init__(self, path: str | Path, chunk_period_s: float = 0.5,
                 custom_data: dict[str, str] | None = None):
        from rosbags.rosbag2 import StoragePlugin, Writer, WriterError
        self.path = Path(path)
        if self.path.exists():
            raise BagError(f'{self.path} already exists; choose a new bag path')
        if not chunk_period_s > 0:
            raise BagError(f'chunk_period_s must be > 0, got {chunk_period_s}')
        self.chunk_period_s = float(chunk_period_s)
        self._writer = Writer(self.path, version=9, storage_plugin=StoragePlugin.MCAP)
        for key, value in (custom_data or {}).items():
            self._writer.set_custom_data(str(key), str(value))
        try:
            self._writer.open()
        except (WriterError, OSError) as exc:
            raise BagError(f'cannot create bag {self.path}: {exc}') from None
        _write_type_hash_in_channels(self._writer.storage)
        # Held until close(): `bag repair` refuses a bag whose lock is taken (a live recording);
        # the OS drops it when the process dies, even by SIGKILL.
        self._lock = lock_recording(next(self.path.glob('*.mcap')))
        self._connections: dict[str, object] = {}
        self._last_flush = time.monotonic()
        self.closed = False

    # ------------------------------------------------------------------------------------ topics
    @property
    def topics(self) -> dict[str, str]:
        """{absolute topic name: message type} of the topics added so far."""
        return {name: conn.msgtype for name, conn in self._connections.items()}

    def add_topic(self, topic: str, msgtype: str, reliable: bool = True, depth: int = 100,
                  offered: list | None = None) -> str:
        """
        Register `topic` of ROS 2 type `msgtype` (e.g. 'sensor_msgs/msg/JointState').

        Returns the absolute topic name. `offered`: the QoS profiles its publishers offer (rosbags
        `Qos`, see `qos_from_rclpy`), as `ros2 bag record` stores them; None: one
        reliable/best-effort keep-last `depth` profile. Raises BagError for an unknown type or a
        topic already added with another type.
        """
        name = absolute_topic(topic)
        if name in self._connections:
            if self._connections[name].msgtype != msgtype:
                raise BagError(f'topic {name} already recorded as '
                               f'{self._connections[name].msgtype}, not {msgtype}')
            return name
        check_type(msgtype, name)
        store = typestore()
        self._connections[name] = self._writer.add_connection(
            name, msgtype, typestore=store,
            offered_qos_profiles=[offered_qos(reliable, depth)] if offered is None else offered)
        return name

    # ---------------------------------------------------------------------------------- messages
    def write(self, topic: str, log_time_ns: int, data: bytes) -> None:
        """
        Append one serialized (CDR) message of an added topic.

        `log_time_ns` is its receive time in ns since the epoch (rosbag2's message timestamp).
        """
        conn = self._connections.get(topic)
        if conn is None:
            conn = self._connections.get(absolute_topic(topic))
            if conn is None:
                raise BagError(f'topic {topic} was not added to bag {self.path}')
        self._writer.write(conn, int(log_time_ns), data)
        if time.monotonic() - self._last_flush >= self.chunk_period_s:
            self.flush()

    def flush(self) -> None:
        """
        Cut the pending messages into a complete MCAP chunk and hand it to the OS.

        So that it survives the process being killed.
        """
        self._last_flush = time.monotonic()
        storage = self._writer.storage
        # rosbags writes a chunk only when it exceeds 1 MiB; closing it early is what bounds the
        # loss on SIGKILL. Both calls exist in rosbags' MCAP storage (0.11).
        close_chunk = getattr(storage, 'close_chunk', None)
        if close_chunk is not None and storage.chunk.bio.tell():
            close_chunk()
        bio = getattr(storage, 'bio', None)
        if bio is not None:
            bio.flush()

    @property
    def message_count(self) -> int:
        """Messages written so far (all topics)."""
        return int(sum(self._writer.counts.values()))

    def close(self) -> None:
        """Write the MCAP summary and metadata.yaml; idempotent."""
        if self.closed:
            return
        self.closed = True
        # rosbags writes `ros_distro: rosbags` in both copies of the metadata (the MCAP's rosbag2
        # record and metadata.yaml); rosbag2 writes the distribution there.
        storage, distro = self._writer.storage, ros_distro()
        close_storage = storage.close

        def close_with_distro(version, metadata: str):
            return close_storage(version, _set_distro(metadata, distro))

        storage.close = close_with_distro
        try:
            self._writer.close()
            meta = self._writer.metapath
            meta.write_text(_set_distro(meta.read_text(), distro))
        finally:
            if self._lock is not None:
                self._lock.close()   # releases the flock

    def __enter__(self) -> 'BagWriter':
        return self

    def __exit__(self, exc_type, exc, tb) -> bool:
        self.close()  # even after an error: what was written stays readable
        return False


def _set_distro(metadata_yaml: str, distro: str) -> str:
    import re
    return re.sub(r'^(\s*ros_distro:) rosbags$', lambda m: f'{m.group(1)} {distro}',
                  metadata_yaml, count=1, flags=re.M)


def _write_type_hash_in_channels(storage) -> None:
    """
    Make this rosbags MCAP storage write `topic_type_hash` in each channel's metadata.

    The RIHS01 hash of the type, next to `offered_qos_profiles`, as rosbag2_storage_mcap does;
    rosbags 0.11 writes only the QoS. Same record layout as rosbags' own add_connection (pinned
    version; the bag tests read both keys back).
    """
    from io import BytesIO

    from rosbags.rosbag2 import storage_mcap as mcap_storage

    def add_connection(connection, offered_qos_profiles: str) -> None:
        meta = BytesIO()
        for key, value in (('offered_qos_profiles', offered_qos_profiles),
                           ('topic_type_hash', connection.digest)):
            mcap_storage.write_string(meta, key)
            mcap_storage.write_string(meta, value)
        channel = mcap_storage.Channel(connection.id, connection.msgtype, connection.topic,
                                       connection.ext.serialization_format, meta.getvalue())
        storage.channels.append(channel)
        storage.channel_stats[connection.id] = 0
        mcap_storage.write_channel(storage.chunk.bio, channel, storage.schemas)

    storage.add_connection = add_connection


def qos_from_rclpy(profile):
    """
    Convert an rclpy QoSProfile to a rosbags `Qos` for `BagWriter.add_topic(offered=...)`.

    The profile is e.g. a publisher's, from Node.get_publishers_info_by_topic. Durations are kept
    as the middleware reports them (sec, nsec; infinite ones as its largest value, like rosbag2).
    """
    from rosbags.interfaces import (Qos, QosDurability, QosHistory, QosLiveliness,
                                    QosReliability, QosTime)

    def duration(d) -> QosTime:
        sec, nsec = divmod(int(d.nanoseconds), 1_000_000_000)
        return QosTime(sec, nsec)

    return Qos(QosHistory(int(profile.history)), int(profile.depth),
               QosReliability(int(profile.reliability)), QosDurability(int(profile.durability)),
               duration(profile.deadline), duration(profile.lifespan),
               QosLiveliness(int(profile.liveliness)),
               duration(profile.liveliness_lease_duration),
               bool(profile.avoid_ros_namespace_conventions))


# ----------------------------------------------------------------------------- JointState helpers
def joint_state_cdr(stamp_ns: int, names: Sequence[str] = ('x',),
                    position: Iterable[float] = (), effort: Iterable[float] = (),
                    velocity: Iterable[float] = ()) -> bytes:
    """
    CDR bytes of one sensor_msgs/JointState.

    Header.stamp = `stamp_ns` (ns since the epoch), positions in m, efforts in V (the project's
    units).
    """
    store = typestore()
    types = store.types
    sec, nsec = divmod(int(stamp_ns), 1_000_000_000)
    msg = types[JOINT_STATE](
        header=types['std_msgs/msg/Header'](
            stamp=types['builtin_interfaces/msg/Time'](sec=sec, nanosec=nsec), frame_id=''),
        name=list(names),
        position=np.asarray(list(position), dtype=np.float64),
        velocity=np.asarray(list(velocity), dtype=np.float64),
        effort=np.asarray(list(effort), dtype=np.float64))
    return bytes(store.serialize_cdr(msg, JOINT_STATE))


def joint_trajectory_cdr(stamps_ns: Sequence[int], names: Sequence[str] = ('x',),
                         position=None, effort=None) -> bytes:
    """
    CDR bytes of one trajectory_msgs/JointTrajectory: a batch of samples.

    header.stamp = the first stamp, one point per sample with time_from_start = t_k - t_first
    (ns, exact); position (n, a) m and effort (n, a) V, or None for empty fields.
    """
    store = typestore()
    types = store.types
    stamps = [int(t) for t in stamps_ns]
    t0 = stamps[0] if stamps else 0
    sec, nsec = divmod(t0, 1_000_000_000)
    empty = np.empty(0, dtype=np.float64)
    points = []
    for k, t in enumerate(stamps):
        d_sec, d_nsec = divmod(t - t0, 1_000_000_000)
        points.append(types['trajectory_msgs/msg/JointTrajectoryPoint'](
            positions=empty if position is None else np.asarray(position[k], np.float64).ravel(),
            velocities=empty, accelerations=empty,
            effort=empty if effort is None else np.asarray(effort[k], np.float64).ravel(),
            time_from_start=types['builtin_interfaces/msg/Duration'](sec=d_sec, nanosec=d_nsec)))
    msg = types[JOINT_TRAJECTORY](
        header=types['std_msgs/msg/Header'](
            stamp=types['builtin_interfaces/msg/Time'](sec=sec, nanosec=nsec), frame_id=''),
        joint_names=list(names), points=points)
    return bytes(store.serialize_cdr(msg, JOINT_TRAJECTORY))


def write_uy_bag(path: str | Path, u: np.ndarray, y: np.ndarray, fs: float,
                 t0_ns: int = 1_700_000_000_000_000_000, axis: str = 'x',
                 command_topic: str = COMMAND_TOPIC, deflection_topic: str = DEFLECTION_TOPIC,
                 latency_ns: int = 0, batch: int = 1) -> Path:
    """
    Write a bag like a recording of the command and simulator nodes.

    Sample k is stamped t_k = t0_ns + round(k * 1e9 / fs) on both topics; u (N,) volts goes to the
    command's effort, y (N,) metres to the deflection's position (its effort repeats u). Receive
    times are t_k plus `latency_ns`. batch > 1: the nodes' batched streams instead, JointTrajectory
    messages of `batch` samples on `<topic>_batch`, received when their last sample is due.
    Returns the bag path.
    """
    u = np.asarray(u, dtype=np.float64).ravel()
    y = np.asarray(y, dtype=np.float64).ravel()
    if u.shape != y.shape:
        raise BagError(f'u and y differ in length: {u.size} vs {y.size}')
    if not fs > 0:
        raise BagError(f'fs must be > 0 Hz, got {fs}')
    stamps = t0_ns + np.round(np.arange(u.size) * (1e9 / fs)).astype(np.int64)
    if batch > 1:
        with BagWriter(path) as bag:
            cmd = bag.add_topic(command_topic + BATCH_SUFFIX, JOINT_TRAJECTORY)
            dfl = bag.add_topic(deflection_topic + BATCH_SUFFIX, JOINT_TRAJECTORY)
            for k in range(0, u.size, batch):
                t, uk, yk = stamps[k:k + batch], u[k:k + batch, None], y[k:k + batch, None]
                last = int(t[-1])
                bag.write(cmd, last + latency_ns, joint_trajectory_cdr(t, (axis,), effort=uk))
                bag.write(dfl, last + 2 * latency_ns,
                          joint_trajectory_cdr(t, (axis,), position=yk, effort=uk))
        return Path(path)
    with BagWriter(path) as bag:
        cmd = bag.add_topic(command_topic, JOINT_STATE)
        dfl = bag.add_topic(deflection_topic, JOINT_STATE)
        for t_k, u_k, y_k in zip(stamps.tolist(), u.tolist(), y.tolist()):
            bag.write(cmd, t_k + latency_ns, joint_state_cdr(t_k, (axis,), effort=(u_k,)))
            bag.write(dfl, t_k + 2 * latency_ns,
                      joint_state_cdr(t_k, (axis,), position=(y_k,), effort=(u_k,)))
    return Path(path)
