"""
Batched sample streams (DESIGN.md "High-rate streams"): the `batch` parameter and its topics.

batch = 1 is the one-JointState-per-sample contract on `<topic>`; batch > 1 switches a node's
sample streams to `<topic>_batch`, trajectory_msgs/msg/JointTrajectory, one point per sample
(nodes.codec). A node feeds a received batch to its ROS-free logic sample by sample, the same
calls as for single samples, so every check of that logic applies to batches too, and answers
with one batch of the stamps it answered.
"""
from __future__ import annotations

from sensor_msgs.msg import JointState

from collections import deque

from piezo_narx_ros.nodes.wire import (SampleBatch, batch_points, decode_joint_trajectories,
                                       decode_joint_trajectory)
from piezo_narx_ros.nodes.params import ParamSpec

BATCH_SUFFIX = '_batch'
MAX_BATCH = 1000

BATCH_PARAM = ParamSpec(
    'batch', 1, 'samples per message: 1 = one sensor_msgs/JointState per sample on <topic>; '
    'N > 1 = trajectory_msgs/JointTrajectory batches on <topic>_batch (rates of 5-20 kHz)',
    low=1, high=MAX_BATCH, read_only=True)


def batch_topic(topic: str, batch: int) -> str:
    """Return the topic a stream uses at `batch` samples per message ('deflection_batch')."""
    return topic + BATCH_SUFFIX if batch > 1 else topic


def sample_type(batch: int):
    """Return the message type of a sample stream at `batch` samples per message."""
    if batch > 1:
        from trajectory_msgs.msg import JointTrajectory
        return JointTrajectory
    return JointState


def batch_values(raw: bytes, field: str, axis: str) -> list[tuple[int, float]]:
    """
    Decode a batch and return [(stamp ns, `field` of `axis`)] per sample, in message order.

    field: 'position' (m) or 'effort' (V). Raises DataError for a malformed batch, points of the
    wrong size or a missing axis (the whole message is refused, as a bad JointState is).
    """
    b: SampleBatch = decode_joint_trajectory(raw)
    return list(zip(b.t_ns.tolist(), b.column(field, axis).tolist()))


class HeldBatches:
    """
    Serialized batches held back, to be decoded together (codec.decode_joint_trajectories).

    The estimator's measurement stream at 20 kHz: each batch only feeds the running error once the
    free run is steady, and decoding and pairing 50 of them at once costs about what one did
    (FreeRunEstimator.steady says when holding them back is allowed).
    limit: batches held before `push` says it is time to take them. keep: instead, hold only the
    batches that carry the newest `keep` samples and drop older ones unread (the running error
    is over its last `window` pairs: older measurements would only be pushed out of it); a batch
    of a shape not seen before is never dropped unread: `push` says to take it at once.
    """

    def __init__(self, limit: int, keep: int | None = None):
        if limit < 1 or (keep is not None and keep < 1):
            raise ValueError(f'limit and keep must be >= 1, got {limit} and {keep}')
        self.limit = int(limit)
        self.keep = None if keep is None else int(keep)
        self._raw: deque = deque()
        self._points: deque = deque()   # keep: samples of each held batch
        self._held = 0                  # keep: samples held
        self.dropped = 0                # batches dropped unread

    def __len__(self) -> int:
        return len(self._raw)

    def push(self, raw: bytes) -> bool:
        """Hold one serialized batch; True when the held ones must be taken now."""
        self._raw.append(raw)
        if self.keep is None:
            return len(self._raw) >= self.limit
        n = batch_points(raw)
        if n is None:
            return True
        self._points.append(n)
        self._held += n
        points = self._points
        while self._held - points[0] >= self.keep:    # the rest still hold `keep` samples
            self._held -= points.popleft()
            self._raw.popleft()
            self.dropped += 1
        return False

    def take(self) -> list:
        """Decode and release the held batches: [(messages, SampleBatch or DataError)]."""
        raw, self._raw = list(self._raw), deque()
        self._points.clear()
        self._held = 0
        return decode_joint_trajectories(raw) if raw else []
