"""
Queue + writer thread between subscription callbacks and a `BagWriter` (no ROS here).

Callbacks only append (topic, receive time, bytes) to a queue, which costs about a microsecond, so
the executor keeps up with several kHz; a background thread drains the queue into the bag in
batches. Nothing is dropped: the queue is unbounded, its high-water mark is reported instead.
"""
from __future__ import annotations

import queue
import threading
from dataclasses import dataclass
from pathlib import Path

from piezo_narx_ros.bag.writer import BagWriter
from piezo_narx_ros.errors import BagError

_STOP = object()


def _one_line(exc: BaseException) -> str:
    return ' '.join(str(exc).split())


@dataclass
class RecorderStats:
    """Counters of a BagRecorder (messages, not bytes)."""

    written: int = 0         # messages handed to the bag
    failed: int = 0          # messages refused by the bag (see error)
    queue_peak: int = 0      # largest backlog seen by the writer thread
    bytes_written: int = 0   # payload bytes written
    error: str = ''          # first writer error, if the writer thread stopped on one


class BagRecorder:
    """
    Record serialized messages to a rosbag2 MCAP bag from any thread.

    `add_topic` then `put` from callbacks; `close()` drains the queue, writes the summary and
    metadata.yaml, and returns the stats. Safe to call `close()` more than once.
    """

    def __init__(self, path: str | Path, chunk_period_s: float = 0.5,
                 custom_data: dict[str, str] | None = None, batch: int = 512):
        self.path = Path(path)
        self._bag = BagWriter(self.path, chunk_period_s=chunk_period_s, custom_data=custom_data)
        self._lock = threading.Lock()  # add_topic (executor thread) vs writes (writer thread)
        self._queue: queue.SimpleQueue = queue.SimpleQueue()
        self._batch = int(batch)
        self._chunk_period_s = float(chunk_period_s)
        self.stats = RecorderStats()
        self._closed = False
        self._thread = threading.Thread(target=self._run, name='bag-writer', daemon=True)
        self._thread.start()

    @property
    def topics(self) -> dict[str, str]:
        """{absolute topic: type} registered so far."""
        with self._lock:
            return self._bag.topics

    def add_topic(self, topic: str, msgtype: str, reliable: bool = True, depth: int = 100,
                  offered: list | None = None) -> str:
        """Register a topic (see BagWriter.add_topic); returns its absolute name."""
        with self._lock:
            return self._bag.add_topic(topic, msgtype, reliable, depth, offered)

    def put(self, topic: str, log_time_ns: int, data: bytes) -> None:
        """
        Queue one serialized message of a registered topic (absolute name).

        Received at `log_time_ns` (ns since the epoch). Cheap; safe from any thread.
        """
        self._queue.put((topic, log_time_ns, data))  # SimpleQueue.put is thread-safe

    @property
    def received(self) -> int:
        """
        Messages put so far (written + failed + still queued).

        Counted by the writer thread only, so that put() stays lock-free.
        """
        return self.stats.written + self.stats.failed + self.backlog

    @property
    def backlog(self) -> int:
        """Messages queued but not yet written."""
        return self._queue.qsize()

    def _run(self) -> None:
        q, bag, stats = self._queue, self._bag, self.stats
        while True:
            try:
                item = q.get(timeout=self._chunk_period_s)
            except queue.Empty:
                with self._lock:
                    if bag.message_count and not stats.error:
                        try:
                            bag.flush()  # idle: push the pending chunk to disk
                        except OSError as exc:
                            stats.error = _one_line(exc)
                continue
            items = [item]
            while len(items) < self._batch:
                try:
                    items.append(q.get_nowait())
                except queue.Empty:
                    break
            stats.queue_peak = max(stats.queue_peak, len(items) + q.qsize())
            stop = False
            with self._lock:
                for it in items:
                    if it is _STOP:
                        stop = True
                        continue
                    if stats.error:
                        stats.failed += 1
                        continue
                    try:
                        bag.write(*it)
                    except (BagError, OSError) as exc:   # OSError: disk full, file too large
                        stats.error = _one_line(exc)
                        stats.failed += 1
                        continue
                    stats.written += 1
                    stats.bytes_written += len(it[2])
            if stop:
                return

    def close(self, timeout: float = 30.0) -> RecorderStats:
        """Write everything queued, then the MCAP summary and metadata.yaml."""
        if self._closed:
            return self.stats
        self._closed = True
        self._queue.put(_STOP)
        self._thread.join(timeout)
        with self._lock:
            try:
                self._bag.close()
            except OSError as exc:   # what was written stays repairable (bag repair)
                self.stats.error = self.stats.error or _one_line(exc)
        return self.stats

    def __enter__(self) -> 'BagRecorder':
        return self

    def __exit__(self, *exc) -> bool:
        self.close()
        return False


AUTO_TYPE = 'auto'


def expand_types(topics: list[str], types: list[str]) -> list[str]:
    """
    Type per topic from the `types` parameter.

    One entry applies to every topic, otherwise one per topic; 'auto' (or '') means discover it
    from the ROS graph. Raises BagError on a length mismatch.
    """
    if len(types) == 1:
        types = list(types) * len(topics)
    if len(types) != len(topics):
        raise BagError(f'types must have 1 or {len(topics)} entries (one per topic), '
                       f'got {len(types)}')
    return [t.strip() or AUTO_TYPE for t in types]


def discovered_types(wanted: dict[str, str], graph: list[tuple[str, list[str]]]
                     ) -> dict[str, str]:
    """
    Resolve 'auto' entries of {absolute topic: type} from get_topic_names_and_types() output.

    Returns only the topics that now have a type (first advertised type wins).
    """
    advertised = dict(graph)
    found = {}
    for topic, kind in wanted.items():
        if kind != AUTO_TYPE:
            found[topic] = kind
        elif advertised.get(topic):
            found[topic] = advertised[topic][0]
    return found
