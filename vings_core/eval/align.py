"""Least-squares similarity / rigid alignment of two point sets (Umeyama 1991), pure numpy.

Used to align an estimated trajectory onto ground truth before computing the absolute trajectory
error: ``dst ~= s * R @ src + t``.
"""
from __future__ import annotations

import numpy as np

from ..errors import InputError

#: Point sets whose RMS spread about their centroid is below this (metres, or the caller's unit)
#: are treated as "all points identical": the alignment is undefined.
MIN_SPREAD = 1e-9


def umeyama(src: np.ndarray, dst: np.ndarray, with_scale: bool) -> tuple[float, np.ndarray, np.ndarray]:
    """Find ``s, R, t`` minimising ``sum_i ||dst_i - (s R src_i + t)||^2``.

    Args:
        src: ``(N, 3)`` points to move (e.g. estimated positions).
        dst: ``(N, 3)`` target points (e.g. ground-truth positions), same order.
        with_scale: estimate the scale ``s`` (Sim(3)); otherwise ``s = 1`` (SE(3)).

    Returns:
        ``(s, R, t)``: scale (float), rotation ``(3, 3)`` with ``det = +1``, translation ``(3,)``.

    Raises:
        InputError: fewer than 3 point pairs, mismatched shapes, non-finite values, or all points
        of ``src`` (or of ``dst`` when scaling) identical, where the alignment is undefined.

    Collinear points are accepted: the rotation about the common line is then arbitrary, but the
    residual (and hence the ATE) is still the true minimum.
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    if src.ndim != 2 or src.shape[1] != 3 or src.shape != dst.shape:
        raise InputError(f"alignment needs two (N, 3) point sets of equal size, got "
                         f"{src.shape} and {dst.shape}")
    n = src.shape[0]
    if n < 3:
        raise InputError(f"alignment needs at least 3 matched poses, got {n}")
    if not (np.all(np.isfinite(src)) and np.all(np.isfinite(dst))):
        raise InputError("alignment input contains non-finite positions (NaN or inf)")
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    var_s = float((xs * xs).sum() / n)
    var_d = float((xd * xd).sum() / n)
    if np.sqrt(var_s) <= MIN_SPREAD * max(1.0, float(np.abs(mu_s).max())):
        raise InputError(f"all {n} estimated positions are identical (spread {np.sqrt(var_s):.3g}): "
                         "alignment is undefined (static sequence?)")
    if with_scale and np.sqrt(var_d) <= MIN_SPREAD * max(1.0, float(np.abs(mu_d).max())):
        raise InputError(f"all {n} ground-truth positions are identical (spread {np.sqrt(var_d):.3g}): "
                         "scale alignment is undefined (static sequence?)")
    cov = xd.T @ xs / n  # (3, 3), dst x src
    U, D, Vt = np.linalg.svd(cov)
    S = np.ones(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2] = -1.0  # reflection -> proper rotation (Kabsch)
    R = (U * S) @ Vt
    s = float((D * S).sum() / var_s) if with_scale else 1.0
    t = mu_d - s * R @ mu_s
    return s, R, t


def apply_sim3(poses: np.ndarray, s: float, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Apply ``x -> s R x + t`` to ``(N, 4, 4)`` poses ``T_wc``: rotations become ``R @ R_wc``,
    positions ``s R p + t``. The result stays a rigid transform per pose (the scale only moves
    positions)."""
    poses = np.asarray(poses, dtype=np.float64)
    out = poses.copy()
    out[:, :3, :3] = R @ poses[:, :3, :3]
    out[:, :3, 3] = s * poses[:, :3, 3] @ R.T + t
    return out
