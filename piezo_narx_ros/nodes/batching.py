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

from piezo_narx_ros.nodes.codec import (SampleBatch, decode_joint_trajectories,
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
    limit: batches held before `push` says it is time to take them.
    """

    def __init__(self, limit: int):
        if limit < 1:
            raise ValueError(f'limit must be >= 1, got {limit}')
        self.limit = int(limit)
        self._raw: list[bytes] = []

    def __len__(self) -> int:
        return len(self._raw)

    def push(self, raw: bytes) -> bool:
        """Hold one serialized batch; True once `limit` are held (take them now)."""
        self._raw.append(raw)
        return len(self._raw) >= self.limit

    def take(self) -> list:
        """Decode and release the held batches: [(messages, SampleBatch or DataError)]."""
        raw, self._raw = self._raw, []
        return decode_joint_trajectories(raw) if raw else []
