"""Poses: ``geometry_msgs/Pose(Stamped)``, ``nav_msgs/Odometry`` and ``nav_msgs/Path``.

Poses are 4x4 float64 ``T_wc`` (camera-to-world): the camera optical frame's pose in the world frame
``map``. Quaternions are ``(x, y, z, w)``, as in vings_core.geometry.

Covariance: :class:`PoseEstimate.covariance` is over the *left* perturbation ``T = Exp(xi) T_hat``,
``xi = [rho (m), phi (rad)]``. ROS wants ``(x, y, z, rot X, rot Y, rot Z)`` of the pose in the header
frame with fixed-axis rotations, i.e. ``dt = rho - [t]x phi``, ``dtheta = phi``:
``C_ros = A C_xi A^T`` with ``A = [[I, -[t]x], [0, I]]`` (and back with ``A^-1 = [[I, [t]x], [0, I]]``).
An unknown covariance is written as ``covariance[0] = -1`` (the sensor_msgs convention), which reads
back as ``None``. The twist is not estimated and is written the same way (zero, ``[0] = -1``).
"""
from __future__ import annotations

from typing import Optional

import numpy as np
from geometry_msgs.msg import Point, Pose, PoseStamped, Quaternion
from nav_msgs.msg import Odometry, Path

from vings_core.errors import InputError
from vings_core.geometry import check_rigid_pose, np_quat_to_rotmat, np_rotmat_to_quat
from vings_core.types import PoseEstimate, Trajectory

from .stamps import header_ns, make_header
from .topics import CAMERA_FRAME, WORLD_FRAME


def _skew(t: np.ndarray) -> np.ndarray:
    x, y, z = t
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def tangent_cov_to_ros(cov: np.ndarray, T_wc: np.ndarray) -> np.ndarray:
    """6x6 left-tangent ``[rho, phi]`` covariance -> ROS ``(x, y, z, rx, ry, rz)`` covariance."""
    A = np.eye(6)
    A[:3, 3:] = -_skew(np.asarray(T_wc, dtype=np.float64)[:3, 3])
    return A @ np.asarray(cov, dtype=np.float64).reshape(6, 6) @ A.T


def ros_cov_to_tangent(cov: np.ndarray, T_wc: np.ndarray) -> np.ndarray:
    """Inverse of :func:`tangent_cov_to_ros`."""
    A = np.eye(6)
    A[:3, 3:] = _skew(np.asarray(T_wc, dtype=np.float64)[:3, 3])
    return A @ np.asarray(cov, dtype=np.float64).reshape(6, 6) @ A.T


def _check_pose(T: np.ndarray, where: str) -> np.ndarray:
    """``T`` as a float64 4x4 rigid transform (to 1e-4): a scaled matrix or a reflection has no
    quaternion, it would be published as another rotation. InputError naming ``where`` otherwise."""
    if np.shape(T) != (4, 4):
        raise InputError(f"{where}: pose must be a finite 4x4 matrix, got shape {np.shape(T)}")
    return check_rigid_pose(T, where, tol=1e-4, error=InputError)


def matrix_to_pose(T: np.ndarray, where: str = "pose") -> Pose:
    """4x4 rigid transform -> ``geometry_msgs/Pose``."""
    T = _check_pose(T, where)
    q = np_rotmat_to_quat(T[:3, :3])
    return Pose(position=Point(x=float(T[0, 3]), y=float(T[1, 3]), z=float(T[2, 3])),
                orientation=Quaternion(x=float(q[0]), y=float(q[1]), z=float(q[2]),
                                       w=float(q[3])))


def _quat_array(qs: np.ndarray, where: str) -> np.ndarray:
    n = np.linalg.norm(qs, axis=-1)
    bad = ~np.isfinite(n) | (np.abs(n - 1.0) > 1e-3)
    if np.any(bad):
        i = int(np.argmax(bad))
        raise InputError(f"{where}: orientation quaternion {qs[i].tolist()} is not a unit "
                         f"quaternion (norm {n[i]:.6g})")
    return qs / n[..., None]


def pose_to_matrix(pose: Pose, where: str = "pose") -> np.ndarray:
    """``geometry_msgs/Pose`` -> 4x4 float64. The quaternion must have unit norm (+-1e-3)."""
    o, p = pose.orientation, pose.position
    q = _quat_array(np.array([[o.x, o.y, o.z, o.w]], dtype=np.float64), f"{where}.orientation")
    t = np.array([p.x, p.y, p.z], dtype=np.float64)
    if not np.all(np.isfinite(t)):
        raise InputError(f"{where}.position: not finite: {t.tolist()}")
    T = np.eye(4)
    T[:3, :3] = np_quat_to_rotmat(q[0])
    T[:3, 3] = t
    return T


def matrix_to_pose_stamped(T: np.ndarray, stamp_ns: int, frame_id: str = WORLD_FRAME,
                           where: str = "pose") -> PoseStamped:
    return PoseStamped(header=make_header(stamp_ns, frame_id, where),
                       pose=matrix_to_pose(T, where))


def pose_stamped_to_matrix(msg: PoseStamped, where: str = "pose") -> tuple[int, np.ndarray]:
    """PoseStamped -> ``(stamp_ns, T 4x4)``."""
    return header_ns(msg.header, f"{where}.header"), pose_to_matrix(msg.pose, f"{where}.pose")


# ----------------------------------------------------------------------------------- odometry


def estimate_to_odometry(est: PoseEstimate, frame_id: str = WORLD_FRAME,
                         child_frame_id: str = CAMERA_FRAME,
                         where: str = "odometry", twist=None) -> Odometry:
    """PoseEstimate -> Odometry: pose ``T_wc`` of ``child_frame_id`` in ``frame_id``; ``twist``:
    optional ``(v, w[, cov])`` linear (m/s) and angular (rad/s) velocity in ``child_frame_id``
    (REP-105) with their 6x6 covariance (``[v, w]``, the message's order), else the twist is marked
    unknown (covariance[0] = -1)."""
    T = _check_pose(est.T_wc, f"{where}.pose")
    msg = Odometry(header=make_header(est.stamp_ns, frame_id, where),
                   child_frame_id=str(child_frame_id))
    msg.pose.pose = matrix_to_pose(T, f"{where}.pose")
    if est.covariance is None:
        c = np.zeros(36)
        c[0] = -1.0
    else:
        cov = np.asarray(est.covariance, dtype=np.float64)
        if cov.shape != (6, 6) or not np.all(np.isfinite(cov)):
            raise InputError(f"{where}: covariance must be a finite 6x6 matrix, got {cov.shape}")
        c = tangent_cov_to_ros(cov, T).reshape(-1)
    msg.pose.covariance = c
    tc = np.zeros(36)
    if twist is None:
        tc[0] = -1.0
    else:
        v, w = (np.asarray(x, np.float64).reshape(3) for x in twist[:2])
        if not (np.isfinite(v).all() and np.isfinite(w).all()):
            raise InputError(f"{where}: twist must be finite, got {v}, {w}")
        if len(twist) > 2 and twist[2] is not None:
            tcov = np.asarray(twist[2], np.float64)
            if tcov.shape != (6, 6) or not np.isfinite(tcov).all():
                raise InputError(f"{where}: twist covariance must be a finite 6x6 matrix")
            tc = tcov.reshape(-1).copy()
        msg.twist.twist.linear.x, msg.twist.twist.linear.y, msg.twist.twist.linear.z = (float(x) for x in v)
        msg.twist.twist.angular.x, msg.twist.twist.angular.y, msg.twist.twist.angular.z = (float(x) for x in w)
    msg.twist.covariance = tc
    return msg


def odometry_to_estimate(msg: Odometry, where: str = "odometry") -> PoseEstimate:
    """Odometry -> PoseEstimate (``state='tracking'``, ``is_keyframe=False``: Odometry carries
    neither; the tracking state is on /diagnostics)."""
    T = pose_to_matrix(msg.pose.pose, f"{where}.pose.pose")
    c = np.asarray(msg.pose.covariance, dtype=np.float64).reshape(6, 6)
    if c[0, 0] == -1.0:
        cov = None
    else:
        if not np.all(np.isfinite(c)):
            raise InputError(f"{where}.pose.covariance: not finite")
        cov = ros_cov_to_tangent(c, T)
    return PoseEstimate(stamp_ns=header_ns(msg.header, f"{where}.header"), T_wc=T, covariance=cov)


# --------------------------------------------------------------------------------------- paths


def trajectory_to_path(traj: Trajectory, frame_id: str = WORLD_FRAME,
                       stamp_ns: Optional[int] = None, where: str = "path") -> Path:
    """Trajectory -> Path; each pose carries its own stamp; the header stamp is ``stamp_ns`` or
    the last pose's stamp (0 for an empty path)."""
    poses = np.asarray(traj.poses, dtype=np.float64)
    if not np.all(np.isfinite(poses)):
        raise InputError(f"{where}: trajectory holds non-finite poses")
    if stamp_ns is None:
        stamp_ns = int(traj.stamps_ns[-1]) if len(traj) else 0
    msg = Path(header=make_header(stamp_ns, frame_id, where))
    if len(traj) == 0:
        return msg
    qs = np_rotmat_to_quat(poses[:, :3, :3]).tolist()
    ts = poses[:, :3, 3].tolist()
    msg.poses = [PoseStamped(header=make_header(int(s), frame_id, where),
                             pose=Pose(position=Point(x=t[0], y=t[1], z=t[2]),
                                       orientation=Quaternion(x=q[0], y=q[1], z=q[2], w=q[3])))
                 for s, t, q in zip(traj.stamps_ns.tolist(), ts, qs)]
    return msg


def path_to_trajectory(msg: Path, where: str = "path") -> Trajectory:
    """Path -> Trajectory (stamps from each PoseStamped's header)."""
    n = len(msg.poses)
    if n == 0:
        return Trajectory(np.zeros(0, dtype=np.int64), np.zeros((0, 4, 4)))
    stamps = np.array([header_ns(p.header, f"{where}.poses[{i}].header")
                       for i, p in enumerate(msg.poses)], dtype=np.int64)
    raw = np.array([(p.pose.position.x, p.pose.position.y, p.pose.position.z,
                     p.pose.orientation.x, p.pose.orientation.y, p.pose.orientation.z,
                     p.pose.orientation.w) for p in msg.poses], dtype=np.float64)
    if not np.all(np.isfinite(raw[:, :3])):
        i = int(np.argmax(~np.all(np.isfinite(raw[:, :3]), axis=1)))
        raise InputError(f"{where}.poses[{i}].pose.position: not finite")
    q = _quat_array(raw[:, 3:], f"{where}.poses[*].pose.orientation")
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = np_quat_to_rotmat(q)
    T[:, :3, 3] = raw[:, :3]
    return Trajectory(stamps, T)


__all__ = ["tangent_cov_to_ros", "ros_cov_to_tangent", "matrix_to_pose", "pose_to_matrix",
           "matrix_to_pose_stamped", "pose_stamped_to_matrix", "estimate_to_odometry",
           "odometry_to_estimate", "trajectory_to_path", "path_to_trajectory"]
