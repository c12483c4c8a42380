"""Write rosbag2 bags (MCAP storage, metadata version 9) with `rosbags`.

A bag written here is a directory `NAME/` holding `NAME.mcap` (profile `ros2`, `ros2msg` schemas,
`cdr` messages, offered QoS in the channel metadata) and `metadata.yaml`, which is what
`ros2 bag record -s mcap` produces, so `ros2 bag info/play`, Foxglove and PlotJuggler open it.

Message definitions come from the `rosbags` built-in type store of the ROS 2 Kilted distribution:
only types it knows can be recorded (every std/sensor/diagnostic message is there).
"""
from __future__ import annotations

import time
from functools import lru_cache
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

from piezo_narx_ros.errors import BagError

JOINT_STATE = 'sensor_msgs/msg/JointState'
COMMAND_TOPIC = 'piezo/voltage_command'
DEFLECTION_TOPIC = 'piezo/deflection'
ESTIMATE_TOPIC = 'piezo/deflection_estimate'


@lru_cache(maxsize=1)
def typestore():
    """The built-in `rosbags` type store (ROS 2 Kilted); never extended with types from a bag,
    because registering a definition generates and executes Python code."""
    from rosbags.typesys import Stores, get_typestore
    return get_typestore(Stores.ROS2_KILTED)


def absolute_topic(name: str) -> str:
    """'piezo/deflection' or '/piezo/deflection' -> '/piezo/deflection' (rosbag2 stores absolute
    names). Raises BagError on an empty name."""
    stripped = str(name).strip().strip('/')
    if not stripped:
        raise BagError(f'empty topic name {name!r}')
    return '/' + stripped


def offered_qos(reliable: bool = True, depth: int = 100):
    """One rosbags `Qos` (keep-last `depth`, reliable or best effort, volatile) as offered by the
    project's publishers; stored per topic so `ros2 bag play` republishes with the same QoS."""
    from rosbags.interfaces import (Qos, QosDurability, QosHistory, QosLiveliness,
                                    QosReliability, QosTime)
    zero = QosTime(0, 0)  # 0 = rmw default (infinite) for deadline, lifespan and lease
    return Qos(QosHistory.KEEP_LAST, int(depth),
               QosReliability.RELIABLE if reliable else QosReliability.BEST_EFFORT,
               QosDurability.VOLATILE, zero, zero, QosLiveliness.AUTOMATIC, zero, False)


class BagWriter:
    """rosbag2 bag writer (MCAP, version 9) taking already-serialized CDR messages.

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
        self._connections: dict[str, object] = {}
        self._last_flush = time.monotonic()
        self.closed = False

    # ------------------------------------------------------------------------------------ topics
    @property
    def topics(self) -> dict[str, str]:
        """{absolute topic name: message type} of the topics added so far."""
        return {name: conn.msgtype for name, conn in self._connections.items()}

    def add_topic(self, topic: str, msgtype: str, reliable: bool = True, depth: int = 100) -> str:
        """Register `topic` of ROS 2 type `msgtype` (e.g. 'sensor_msgs/msg/JointState') with its
        offered QoS; returns the absolute topic name. Raises BagError for an unknown type or a
        topic already added with another type."""
        name = absolute_topic(topic)
        if name in self._connections:
            if self._connections[name].msgtype != msgtype:
                raise BagError(f'topic {name} already recorded as '
                               f'{self._connections[name].msgtype}, not {msgtype}')
            return name
        store = typestore()
        if msgtype not in store.fielddefs:
            raise BagError(f'unknown message type {msgtype!r} for topic {name} '
                           '(only ROS 2 Kilted built-in types can be recorded)')
        self._connections[name] = self._writer.add_connection(
            name, msgtype, typestore=store, offered_qos_profiles=[offered_qos(reliable, depth)])
        return name

    # ---------------------------------------------------------------------------------- messages
    def write(self, topic: str, log_time_ns: int, data: bytes) -> None:
        """Append one serialized (CDR) message of an added topic; `log_time_ns` is its receive
        time in ns since the epoch (rosbag2's message timestamp)."""
        conn = self._connections.get(topic)
        if conn is None:
            conn = self._connections.get(absolute_topic(topic))
            if conn is None:
                raise BagError(f'topic {topic} was not added to bag {self.path}')
        self._writer.write(conn, int(log_time_ns), data)
        if time.monotonic() - self._last_flush >= self.chunk_period_s:
            self.flush()

    def flush(self) -> None:
        """Cut the pending messages into a complete MCAP chunk and hand it to the OS, so that it
        survives the process being killed."""
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
        self._writer.close()

    def __enter__(self) -> 'BagWriter':
        return self

    def __exit__(self, exc_type, exc, tb) -> bool:
        self.close()  # even after an error: what was written stays readable
        return False


# ----------------------------------------------------------------------------- JointState helpers
def joint_state_cdr(stamp_ns: int, names: Sequence[str] = ('x',),
                    position: Iterable[float] = (), effort: Iterable[float] = (),
                    velocity: Iterable[float] = ()) -> bytes:
    """CDR bytes of one sensor_msgs/JointState: header.stamp = `stamp_ns` (ns since the epoch),
    positions in m, efforts in V (the project's units)."""
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


def write_uy_bag(path: str | Path, u: np.ndarray, y: np.ndarray, fs: float,
                 t0_ns: int = 1_700_000_000_000_000_000, axis: str = 'x',
                 command_topic: str = COMMAND_TOPIC, deflection_topic: str = DEFLECTION_TOPIC,
                 latency_ns: int = 0) -> Path:
    """Write a bag like a recording of the command and simulator nodes: sample k is stamped
    t_k = t0_ns + round(k * 1e9 / fs) on both topics; u (N,) volts goes to the command's effort,
    y (N,) metres to the deflection's position (its effort repeats u). Receive times are t_k plus
    `latency_ns`. Returns the bag path."""
    u = np.asarray(u, dtype=np.float64).ravel()
    y = np.asarray(y, dtype=np.float64).ravel()
    if u.shape != y.shape:
        raise BagError(f'u and y differ in length: {u.size} vs {y.size}')
    if not fs > 0:
        raise BagError(f'fs must be > 0 Hz, got {fs}')
    stamps = t0_ns + np.round(np.arange(u.size) * (1e9 / fs)).astype(np.int64)
    with BagWriter(path) as bag:
        cmd = bag.add_topic(command_topic, JOINT_STATE)
        dfl = bag.add_topic(deflection_topic, JOINT_STATE)
        for t_k, u_k, y_k in zip(stamps.tolist(), u.tolist(), y.tolist()):
            bag.write(cmd, t_k + latency_ns, joint_state_cdr(t_k, (axis,), effort=(u_k,)))
            bag.write(dfl, t_k + 2 * latency_ns,
                      joint_state_cdr(t_k, (axis,), position=(y_k,), effort=(u_k,)))
    return Path(path)
