"""Pose-exchange batches (:class:`vings_core.exchange.IncrementBatch`) <-> ``nav_msgs/Path``.

Each stage that writes keyframe poses publishes its batches on ``/vings/exchange/<source>``
(:func:`exchange_topic`): the front end (the keeper) on ``/vings/exchange/frontend``, the mapper on
``/vings/exchange/mapper``, a loop closer on ``/vings/exchange/loop_closer``. The source is the
topic's last name.

==============================================  ==========================================================
field                                           content
==============================================  ==========================================================
``header.stamp``                                the batch's sequence number, as a time in ns (> 0)
``header.frame_id``                             the world frame (``map``)
``poses[i]``, ``header.frame_id`` = world frame  the increment ``C = [[s R, t], [0, 1]]`` of the keyframe
                                                whose image stamp is ``header.stamp``: ``position`` = ``t``,
                                                ``orientation`` = the quaternion of ``R`` (xyzw, w >= 0)
                                                multiplied by ``s``: its norm is the scale (1 for a rigid
                                                increment)
``poses[i]``, ``header.frame_id`` = ``ack:<src>``  acknowledgement: ``header.stamp`` is the last batch of
                                                ``<src>`` processed when this batch was written (identity pose)
==============================================  ==========================================================

A keyframe's new pose is ``vings_core.geometry.sim3_apply_to_pose(C, T_wc_old)``; its content moves
as ``x -> s R x + t``.
"""
from __future__ import annotations

import numpy as np
from geometry_msgs.msg import Point, Pose, PoseStamped, Quaternion
from nav_msgs.msg import Path

from vings_core.errors import InputError
from vings_core.exchange import IncrementBatch
from vings_core.geometry import np_quat_to_rotmat, np_rotmat_to_quat, sim3, sim3_scale

from .stamps import header_ns, make_header
from .topics import EXCHANGE_TOPIC_PREFIX, WORLD_FRAME

ACK_PREFIX = "ack:"


def exchange_topic(source: str) -> str:
    """The topic a stage's batches travel on."""
    return EXCHANGE_TOPIC_PREFIX + source


def batch_to_path(batch: IncrementBatch, frame_id: str = WORLD_FRAME) -> Path:
    """Batch -> ``nav_msgs/Path`` (table in the module docstring)."""
    where = exchange_topic(batch.source)
    msg = Path(header=make_header(batch.seq, frame_id, where))
    for s, C in sorted(batch.increments.items()):
        sc = sim3_scale(C)
        q = np_rotmat_to_quat(C[:3, :3] / sc)
        q = (q if q[3] >= 0 else -q) * sc
        t = C[:3, 3]
        msg.poses.append(PoseStamped(
            header=make_header(int(s), frame_id, where),
            pose=Pose(position=Point(x=float(t[0]), y=float(t[1]), z=float(t[2])),
                      orientation=Quaternion(x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])))))
    for src, seq in sorted(batch.acks.items()):
        msg.poses.append(PoseStamped(header=make_header(int(seq), ACK_PREFIX + src, where)))
    return msg


def path_to_batch(msg: Path, source: str, where: str = "") -> IncrementBatch:
    """``nav_msgs/Path`` from ``/vings/exchange/<source>`` -> batch; a malformed message raises
    :class:`InputError` naming the topic and field."""
    where = where or exchange_topic(source)
    seq = header_ns(msg.header, f"{where}.header")
    incs, acks = {}, {}
    for i, p in enumerate(msg.poses):
        at = f"{where}.poses[{i}]"
        stamp = header_ns(p.header, f"{at}.header")
        if p.header.frame_id.startswith(ACK_PREFIX):
            acks[p.header.frame_id[len(ACK_PREFIX):]] = stamp
            continue
        o, t = p.pose.orientation, p.pose.position
        q = np.array([o.x, o.y, o.z, o.w], np.float64)
        xyz = np.array([t.x, t.y, t.z], np.float64)
        sc = float(np.linalg.norm(q))
        if not (np.isfinite(q).all() and np.isfinite(xyz).all()) or not sc > 1e-9:
            raise InputError(f"{at}.pose: increment not finite, or a zero quaternion (its norm is the scale)")
        incs[stamp] = sim3(np_quat_to_rotmat(q / sc), xyz, sc)
    return IncrementBatch(source, seq, incs, acks).check(where)
