"""
The wire: the sample messages as objects and as CDR bytes, apart from the node plumbing.

JointState carries one sample (`joint_state`), JointTrajectory a batch (`trajectory`, its points
read and written by the compiled `kernels`); `cdr` holds what both share and `batching` the
topics and the held batches of a batch stream. Stamps are integer nanoseconds inside the nodes,
so that t_k = t0 + k/fs is exact over long runs.
"""
from piezo_narx_ros.nodes.wire.cdr import check_message_names, ns_to_stamp, stamp_to_ns
from piezo_narx_ros.nodes.wire.joint_state import (Sample, decode_joint_state,
                                                   encode_joint_state, make_joint_state,
                                                   parse_joint_state)
from piezo_narx_ros.nodes.wire.trajectory import (SampleBatch, batch_points,
                                                  decode_joint_trajectories,
                                                  decode_joint_trajectory,
                                                  encode_joint_trajectory, make_joint_trajectory,
                                                  warm_up)

__all__ = ('Sample', 'SampleBatch', 'batch_points', 'check_message_names',
           'decode_joint_state', 'decode_joint_trajectories', 'decode_joint_trajectory',
           'encode_joint_state', 'encode_joint_trajectory', 'make_joint_state',
           'make_joint_trajectory', 'ns_to_stamp', 'parse_joint_state', 'stamp_to_ns', 'warm_up')
