"""Rigid-body math shared by all stages (pure functions, torch batched and numpy).

Conventions:
* ``T_ab`` (4x4) maps points in frame ``b`` to frame ``a``.
* se(3) tangent vectors are ordered ``xi = [rho, phi]``: translation part (m) first, rotation (rad)
  second, as in Sophus/lietorch. (GTSAM's Pose3 orders ``[phi, rho]``; convert explicitly.)
* ``se3_exp(xi)`` gives the 4x4 matrix ``exp(xi^)``; pose updates are left-multiplied:
  ``T <- se3_exp(xi) @ T`` unless a function says otherwise.
* Quaternions are ``(x, y, z, w)`` (TUM/ROS order) unless the name says ``wxyz``.
"""
from __future__ import annotations

import numpy as np
import torch


# --------------------------------------------------------------------------------------- torch


def skew(v: torch.Tensor) -> torch.Tensor:
    """``(..., 3) -> (..., 3, 3)`` cross-product matrix ``[v]_x``."""
    z = torch.zeros_like(v[..., 0])
    x, y, w = v[..., 0], v[..., 1], v[..., 2]
    return torch.stack([torch.stack([z, -w, y], -1),
                        torch.stack([w, z, -x], -1),
                        torch.stack([-y, x, z], -1)], -2)


def so3_coeffs(theta2: torch.Tensor):
    """A = sin(t)/t, B = (1-cos t)/t^2, C = (t - sin t)/t^3 of ``theta2 = t^2``, accurate in float32
    and float64 and with finite gradients everywhere (0 included). B uses the half-angle form
    ``(1 - cos t) / t^2 = (sin(t/2) / (t/2))^2 / 2`` (no cancellation); C its series below t = 1e-2,
    where ``t - sin t`` cancels (float32: a 2x error near t = 1e-4)."""
    small = theta2 < 1e-8
    # sqrt of a safe argument: keeps autograd finite at theta = 0 (the Taylor branch is used there)
    ts = torch.sqrt(torch.where(small, torch.ones_like(theta2), theta2))
    A = torch.where(small, 1 - theta2 / 6, torch.sin(ts) / ts)
    h = ts / 2
    B = torch.where(small, 0.5 - theta2 / 24, 0.5 * (torch.sin(h) / h) ** 2)
    c_series = theta2 < 1e-4
    C = torch.where(c_series, 1.0 / 6 - theta2 / 120 + theta2 * theta2 / 5040,
                    (ts - torch.sin(ts)) / ts**3)
    return A, B, C


def so3_exp(phi: torch.Tensor) -> torch.Tensor:
    """Rodrigues: ``(..., 3)`` axis-angle (rad) -> ``(..., 3, 3)`` rotation."""
    A, B, _ = so3_coeffs((phi * phi).sum(-1))
    K = skew(phi)
    eye = torch.eye(3, dtype=phi.dtype, device=phi.device).expand(K.shape)
    return eye + A[..., None, None] * K + B[..., None, None] * (K @ K)


def so3_log(R: torch.Tensor) -> torch.Tensor:
    """``(..., 3, 3)`` rotation -> ``(..., 3)`` axis-angle, accurate near 0 and near pi."""
    q = rotmat_to_quat(R)  # xyzw, w >= 0
    v, w = q[..., :3], q[..., 3]
    n = torch.linalg.norm(v, dim=-1)
    small = n < 1e-8
    ns = torch.where(small, torch.ones_like(n), n)
    ang = 2 * torch.atan2(n, w)
    scale = torch.where(small, 2.0 / w.clamp_min(1e-12) * (1 - n**2 / (3 * w.clamp_min(1e-12) ** 2)),
                        ang / ns)
    return v * scale[..., None]


def so3_left_jacobian(phi: torch.Tensor) -> torch.Tensor:
    """Left Jacobian ``J_l(phi)`` of SO(3), ``(..., 3) -> (..., 3, 3)``."""
    _, B, C = so3_coeffs((phi * phi).sum(-1))
    K = skew(phi)
    eye = torch.eye(3, dtype=phi.dtype, device=phi.device).expand(K.shape)
    return eye + B[..., None, None] * K + C[..., None, None] * (K @ K)


def se3_exp(xi: torch.Tensor) -> torch.Tensor:
    """``(..., 6)`` tangent ``[rho, phi]`` -> ``(..., 4, 4)`` rigid transform."""
    rho, phi = xi[..., :3], xi[..., 3:]
    R = so3_exp(phi)
    t = (so3_left_jacobian(phi) @ rho[..., None])[..., 0]
    T = torch.zeros(xi.shape[:-1] + (4, 4), dtype=xi.dtype, device=xi.device)
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1
    return T


def se3_log(T: torch.Tensor) -> torch.Tensor:
    """``(..., 4, 4)`` rigid transform -> ``(..., 6)`` tangent ``[rho, phi]``."""
    phi = so3_log(T[..., :3, :3])
    J = so3_left_jacobian(phi)
    rho = torch.linalg.solve(J, T[..., :3, 3:4])[..., 0]
    return torch.cat([rho, phi], -1)


def pose_inverse(T: torch.Tensor) -> torch.Tensor:
    """Inverse of ``(..., 4, 4)`` rigid transforms."""
    R, t = T[..., :3, :3], T[..., :3, 3:4]
    Ti = torch.zeros_like(T)
    Rt = R.transpose(-1, -2)
    Ti[..., :3, :3] = Rt
    Ti[..., :3, 3:4] = -Rt @ t
    Ti[..., 3, 3] = 1
    return Ti


def project_rotation(R: torch.Tensor) -> torch.Tensor:
    """Nearest rotations (Frobenius) of ``(..., 3, 3)`` near-rotation matrices: SVD
    ``U S V^T -> U diag(1, 1, det(U V^T)) V^T`` (the last column of ``U`` flipped where
    ``U V^T`` is a reflection). Same dtype and device as ``R``."""
    U, _, Vh = torch.linalg.svd(R)
    det = torch.linalg.det(U @ Vh)
    flip = torch.tensor([1.0, 1.0, -1.0], dtype=R.dtype, device=R.device)
    U = torch.where(det[..., None, None] < 0, U * flip, U)
    return U @ Vh


def orthonormalize_pose(T: torch.Tensor) -> torch.Tensor:
    """``(..., 4, 4)`` transforms with the rotation block projected onto SO(3)
    (:func:`project_rotation`) and the last row set to ``0 0 0 1`` (a new tensor; the translation
    is kept)."""
    out = T.clone()
    out[..., :3, :3] = project_rotation(T[..., :3, :3])
    out[..., 3, :] = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=T.dtype, device=T.device)
    return out


def transform_points(T: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    """Apply ``(4, 4)`` (or broadcastable ``(..., 4, 4)``) ``T`` to points ``(..., 3)``."""
    return (p[..., None, :] @ T[..., :3, :3].transpose(-1, -2))[..., 0, :] + T[..., :3, 3]


def rotmat_to_quat(R: torch.Tensor) -> torch.Tensor:
    """``(..., 3, 3)`` -> unit quaternion ``(..., 4)`` in ``(x, y, z, w)`` order with ``w >= 0``."""
    m00, m11, m22 = R[..., 0, 0], R[..., 1, 1], R[..., 2, 2]
    tr = m00 + m11 + m22
    cands = torch.stack([
        torch.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0],
                     R[..., 1, 0] - R[..., 0, 1], 1 + tr], -1),
        torch.stack([1 + m00 - m11 - m22, R[..., 0, 1] + R[..., 1, 0],
                     R[..., 0, 2] + R[..., 2, 0], R[..., 2, 1] - R[..., 1, 2]], -1),
        torch.stack([R[..., 0, 1] + R[..., 1, 0], 1 - m00 + m11 - m22,
                     R[..., 1, 2] + R[..., 2, 1], R[..., 0, 2] - R[..., 2, 0]], -1),
        torch.stack([R[..., 0, 2] + R[..., 2, 0], R[..., 1, 2] + R[..., 2, 1],
                     1 - m00 - m11 + m22, R[..., 1, 0] - R[..., 0, 1]], -1),
    ], -2)  # (..., 4, 4): each row proportional to q, pick the best-conditioned
    diag = torch.stack([1 + tr, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], -1)
    idx = diag.argmax(-1)
    q = torch.gather(cands, -2, idx[..., None, None].expand(idx.shape + (1, 4)))[..., 0, :]
    q = q / torch.linalg.norm(q, dim=-1, keepdim=True)
    return torch.where(q[..., 3:4] < 0, -q, q)


def quat_to_rotmat(q: torch.Tensor) -> torch.Tensor:
    """Quaternion ``(..., 4)`` ``(x, y, z, w)`` (normalised here) -> ``(..., 3, 3)``."""
    q = q / torch.linalg.norm(q, dim=-1, keepdim=True)
    x, y, z, w = q.unbind(-1)
    return torch.stack([
        torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
        torch.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
        torch.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
    ], -2)


# --------------------------------------------------------------------------------------- numpy


def np_pose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """4x4 float64 transform from rotation (3, 3) and translation (3,)."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t).reshape(3)
    return T


def np_project_rotation(R: np.ndarray) -> np.ndarray:
    """Nearest rotations (Frobenius) of ``(..., 3, 3)`` near-rotation matrices:
    SVD ``U S V^T -> U diag(1, 1, det(U V^T)) V^T`` (float64; :func:`project_rotation`)."""
    return project_rotation(torch.from_numpy(np.array(R, np.float64))).numpy()


def np_pose_compose(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """``A @ B`` for 4x4 rigid transforms with the rotation block projected back onto SO(3) (SVD),
    so chains of increments do not drift away from orthonormality (float64)."""
    T = np.asarray(A, np.float64) @ np.asarray(B, np.float64)
    T[:3, :3] = np_project_rotation(T[:3, :3])
    T[3] = (0.0, 0.0, 0.0, 1.0)
    return T


def np_pose_inverse(T: np.ndarray) -> np.ndarray:
    """Inverse of (..., 4, 4) rigid transforms (numpy)."""
    return pose_inverse(torch.as_tensor(np.asarray(T, dtype=np.float64))).numpy()


def np_quat_to_rotmat(q_xyzw: np.ndarray) -> np.ndarray:
    return quat_to_rotmat(torch.as_tensor(np.asarray(q_xyzw, dtype=np.float64))).numpy()


def np_rotmat_to_quat(R: np.ndarray) -> np.ndarray:
    return rotmat_to_quat(torch.as_tensor(np.asarray(R, dtype=np.float64))).numpy()


def np_so3_exp(phi: np.ndarray) -> np.ndarray:
    return so3_exp(torch.as_tensor(np.asarray(phi, dtype=np.float64))).numpy()


def np_so3_log(R: np.ndarray) -> np.ndarray:
    return so3_log(torch.as_tensor(np.asarray(R, dtype=np.float64))).numpy()


def np_se3_exp(xi: np.ndarray) -> np.ndarray:
    return se3_exp(torch.as_tensor(np.asarray(xi, dtype=np.float64))).numpy()


def np_se3_log(T: np.ndarray) -> np.ndarray:
    return se3_log(torch.as_tensor(np.asarray(T, dtype=np.float64))).numpy()


def rotation_angle_deg(R: np.ndarray) -> np.ndarray:
    """Rotation angle (degrees) of (..., 3, 3) rotations: ``atan2(|vee(R - R^T)| / 2, (tr R - 1) / 2)``,
    accurate for tiny angles too (``arccos`` of the trace loses everything below ~1e-7 rad)."""
    R = np.asarray(R, dtype=np.float64)
    c = (np.trace(R, axis1=-2, axis2=-1) - 1) / 2
    v = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1)
    return np.degrees(np.arctan2(np.linalg.norm(v, axis=-1) / 2, c))


# ------------------------------------------------------------------------- rigid checks, Sim(3)


def rigid_deviation(T: np.ndarray) -> np.ndarray:
    """How far ``(..., 4, 4)`` transforms are from rigid: ``max(|R^T R - I|, |det R - 1|)`` per
    transform (``inf`` where the last row is not ``0 0 0 1`` or an entry is not finite)."""
    T = np.asarray(T, np.float64)
    R = T[..., :3, :3]
    eye = np.eye(3)
    dev = np.maximum(np.abs(np.swapaxes(R, -1, -2) @ R - eye).max(axis=(-2, -1)),
                     np.abs(np.linalg.det(R) - 1.0))
    bad_row = np.abs(T[..., 3, :] - (0.0, 0.0, 0.0, 1.0)).max(axis=-1) > 1e-9
    finite = np.isfinite(T).all(axis=(-2, -1))
    return np.where(bad_row | ~finite, np.inf, dev)


def check_rigid_pose(T, what: str, tol: float = 1e-6, error: type = None, project: bool = False) -> np.ndarray:
    """Check that ``T`` (a ``(4, 4)`` or ``(N, 4, 4)`` array or tensor) holds finite rigid transforms
    and return it as a float64 array (a copy). ``tol`` bounds :func:`rigid_deviation`; ``error`` is
    the exception class raised, with a one-line message starting with ``what`` (default
    :class:`~vings_core.errors.InputError`). ``project``: rotation blocks that deviate by more than
    1e-9 (round-off of composed increments) are projected back onto SO(3)."""
    if error is None:
        from .errors import InputError as error
    if torch.is_tensor(T):
        T = T.detach().cpu().numpy()
    T = np.array(T, dtype=np.float64)
    if T.ndim < 2 or T.shape[-2:] != (4, 4):
        raise error(f"{what}: expected a 4x4 pose, got shape {T.shape}")
    if not np.isfinite(T).all():
        raise error(f"{what}: pose has non-finite entries")
    dev = rigid_deviation(T)
    worst = float(np.max(dev)) if dev.size else 0.0
    if worst > tol:
        which = "" if T.ndim == 2 else f" (pose {int(np.argmax(dev))} of {len(T)})"
        raise error(f"{what}: not a rigid pose{which}: rotation block not orthonormal with det 1, or last "
                    f"row not 0 0 0 1 (deviation {worst:.2g} > {tol:.2g})")
    if project and worst > 1e-9:
        T[..., :3, :3] = np_project_rotation(T[..., :3, :3])
    return T


def sim3(R: np.ndarray, t: np.ndarray, s: float = 1.0) -> np.ndarray:
    """4x4 similarity ``[[s R, t], [0, 1]]`` acting on points as ``x -> s R x + t`` (float64)."""
    C = np.eye(4)
    C[:3, :3] = float(s) * np.asarray(R, np.float64)
    C[:3, 3] = np.asarray(t, np.float64).reshape(3)
    return C


def sim3_scale(C: np.ndarray) -> float:
    """The scale ``s`` of a 4x4 similarity ``[[s R, t], [0, 1]]`` (1 for a rigid transform)."""
    return float(np.cbrt(np.linalg.det(np.asarray(C, np.float64)[:3, :3])))


def sim3_inverse(C: np.ndarray) -> np.ndarray:
    """Inverse of a 4x4 similarity: ``[[R^T / s, -R^T t / s], [0, 1]]``."""
    C = np.asarray(C, np.float64)
    s = sim3_scale(C)
    Rt = C[:3, :3].T / s
    return sim3(Rt, -(Rt @ C[:3, 3]) / s, 1.0 / s)


def sim3_compose(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """``A B`` for 4x4 similarities (apply ``B`` first), with the rotation re-projected onto SO(3)."""
    if is_rigid_scale(A) and is_rigid_scale(B):
        return np_pose_compose(A, B)
    C = np.asarray(A, np.float64) @ np.asarray(B, np.float64)
    s = sim3_scale(C)
    return sim3(np_project_rotation(C[:3, :3] / s), C[:3, 3], s)


def is_rigid_scale(C: np.ndarray, tol: float = 1e-12) -> bool:
    """Whether the similarity ``C`` has scale 1 (to ``tol``): a rigid transform."""
    return abs(sim3_scale(C) - 1.0) <= tol


def sim3_apply_to_pose(C: np.ndarray, T_wc: np.ndarray) -> np.ndarray:
    """The camera pose ``T_wc`` after the world moves by the similarity ``C`` (``x -> s R x + t``):
    the camera centre is mapped as a point, its orientation rotated by ``R`` (a camera pose stays
    rigid). For a rigid ``C`` this is ``C @ T_wc``. Successive applications compose:
    ``apply(B, apply(A, T)) == apply(B A, T)`` (:func:`sim3_compose`); a rigid ``C`` is applied as
    :func:`np_pose_compose` ``(C, T_wc)``."""
    C = np.asarray(C, np.float64)
    T = np.asarray(T_wc, np.float64)
    if is_rigid_scale(C):
        return np_pose_compose(C, T)
    s = sim3_scale(C)
    R = C[:3, :3] / s
    return np_pose(np_project_rotation(R @ T[:3, :3]), s * (R @ T[:3, 3]) + C[:3, 3])


def pose_increment(T_new: np.ndarray, T_old: np.ndarray) -> np.ndarray:
    """World-frame rigid increment ``C`` with ``T_new = C T_old`` (4x4 ``T_wc``, float64)."""
    return np.asarray(T_new, np.float64) @ np_pose_inverse(np.asarray(T_old, np.float64))


def check_sim3(C: np.ndarray | torch.Tensor, what: str, tol: float = 1e-6,
               error: type[Exception] | None = None) -> np.ndarray:
    """Check that ``C`` is a finite 4x4 similarity ``[[s R, t], [0, 1]]`` (``s > 0``, ``R`` a rotation
    to ``tol`` as in :func:`check_rigid_pose`) and return it as a float64 array (a copy); ``error``
    (default :class:`~vings_core.errors.InputError`) is raised with a message starting with ``what``."""
    if error is None:
        from .errors import InputError as error
    if torch.is_tensor(C):
        C = C.detach().cpu().numpy()
    C = np.array(C, dtype=np.float64)
    if C.shape != (4, 4):
        raise error(f"{what}: expected a finite 4x4 similarity, got shape {C.shape}")
    if not np.isfinite(C).all():
        raise error(f"{what}: expected a finite 4x4 similarity, it has non-finite entries")
    s = sim3_scale(C)
    if not s > 0:
        raise error(f"{what}: not a similarity with a positive scale (the linear block has determinant "
                    f"{s ** 3:.3g})")
    T = C.copy()
    T[:3, :3] /= s
    dev = float(rigid_deviation(T))
    if dev > tol:
        raise error(f"{what}: not a similarity [[s R, t], [0, 1]]: the linear block over its scale "
                    f"{s:.6g} is not a rotation, or the last row is not 0 0 0 1 (deviation {dev:.2g} > "
                    f"{tol:.2g})")
    return C
