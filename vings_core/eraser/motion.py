"""The motion cue: what the re-render cue cannot see (a region the map does not cover yet).

Dense optical flow between the keyframe and the previous one (OpenCV DIS, both directions; a
pixel's flow is reliable when the two agree within ``fb_check_px``) against the flow the camera's
own motion induces. Where the map covers the pixel, its rendered depth gives the induced flow and
the residual is the full 2-D difference; elsewhere (no depth that a moving object did not distort:
the BA's own depth is pulled by the object) the residual is the distance of the measured match from
its epipolar line, which needs no depth (motion along the epipolar line is invisible there). A
pixel moves when its residual exceeds ``motion_px + motion_rel * |induced flow|``.

Frames: ``T_wc`` camera-to-world (4x4); pixels of the working resolution; depth in metres (the
map's units).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import cv2
import numpy as np

from ..types import CameraModel


@dataclass
class MotionResidual:
    """Per pixel of the current keyframe (``(H, W)`` each): ``residual`` (px), ``threshold`` (px),
    ``reliable`` (forward-backward consistent flow), ``moving`` (reliable and residual above
    threshold), ``with_depth`` (the residual used the map's depth; else the epipolar distance)."""

    residual: np.ndarray
    threshold: np.ndarray
    reliable: np.ndarray
    moving: np.ndarray
    with_depth: np.ndarray


def _gray8(image: np.ndarray) -> np.ndarray:
    if image.ndim == 3:
        image = cv2.cvtColor(np.ascontiguousarray(image, dtype=np.float32), cv2.COLOR_RGB2GRAY)
    if image.dtype != np.uint8:
        image = np.clip(image * 255.0 + 0.5, 0, 255).astype(np.uint8)
    return np.ascontiguousarray(image)


_DIS = None


def dense_flow(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """DIS optical flow ``(H, W, 2)`` float32 from image ``a`` to ``b`` (gray or RGB, uint8 or
    float in [0, 1]): pixel ``x`` of ``a`` is at ``x + flow[x]`` in ``b``."""
    global _DIS
    if _DIS is None:
        _DIS = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    return _DIS.calc(_gray8(a), _gray8(b), None)


def sample_flow(flow: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """``flow (H, W, 2)`` bilinearly sampled at pixel positions ``x, y`` (``(H, W)`` float32)."""
    return cv2.remap(flow, x.astype(np.float32), y.astype(np.float32), cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_CONSTANT, borderValue=(np.nan, np.nan))


def motion_residual(cur: np.ndarray, prev: np.ndarray, T_wc_cur: np.ndarray, T_wc_prev: np.ndarray,
                    camera: CameraModel, depth: Optional[np.ndarray], motion_px: float,
                    motion_rel: float, fb_check_px: float) -> MotionResidual:
    """Residual flow of every pixel of keyframe ``cur`` against keyframe ``prev`` (images ``(H, W)``
    or ``(H, W, 3)``). ``depth``: the map's rendered z-depth at ``cur`` (m, 0 where the map does
    not cover the pixel), or None."""
    H, W = camera.height, camera.width
    back = dense_flow(cur, prev)                       # cur -> prev
    fwd = dense_flow(prev, cur)                        # prev -> cur
    u, v = np.meshgrid(np.arange(W, dtype=np.float32), np.arange(H, dtype=np.float32))
    xp = u + back[..., 0]
    yp = v + back[..., 1]
    ret = sample_flow(fwd, xp, yp)                     # flow back to cur from where the pixel went
    fb = np.hypot(back[..., 0] + ret[..., 0], back[..., 1] + ret[..., 1])
    inside = (xp >= 0) & (xp <= W - 1) & (yp >= 0) & (yp <= H - 1)
    reliable = inside & np.isfinite(fb) & (fb < fb_check_px)

    T_pc = np.linalg.inv(np.asarray(T_wc_prev, np.float64)) @ np.asarray(T_wc_cur, np.float64)
    R, t = T_pc[:3, :3], T_pc[:3, 3]
    K = np.array([[camera.fx, 0, camera.cx], [0, camera.fy, camera.cy], [0, 0, 1.0]])
    Ki = np.linalg.inv(K)
    pix = np.stack([u, v, np.ones_like(u)], -1).astype(np.float64)      # (H, W, 3)
    rays = pix @ Ki.T
    # epipolar distance of the measured match (no depth needed): l = F x, F = K^-T [t]x R K^-1
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    F = Ki.T @ tx @ R @ Ki
    lines = pix @ F.T
    x2 = np.stack([xp, yp, np.ones_like(xp)], -1).astype(np.float64)
    epi = np.abs((lines * x2).sum(-1)) / np.maximum(np.hypot(lines[..., 0], lines[..., 1]), 1e-12)
    # rotation-only part: the flow the camera induces at infinite depth
    q_inf = rays @ R.T @ K.T
    with np.errstate(divide="ignore", invalid="ignore"):
        inf_xy = q_inf[..., :2] / q_inf[..., 2:3]
    rot_flow = np.hypot(inf_xy[..., 0] - u, inf_xy[..., 1] - v)
    residual = epi
    induced = rot_flow
    with_depth = np.zeros((H, W), bool)
    if depth is not None:
        d = np.asarray(depth, np.float64)
        with_depth = np.isfinite(d) & (d > 0)
        X = rays * d[..., None]
        q = (X @ R.T + t) @ K.T
        with np.errstate(divide="ignore", invalid="ignore"):
            px = q[..., :2] / q[..., 2:3]
        ok = with_depth & (q[..., 2] > 1e-6)
        full = np.hypot(px[..., 0] - xp, px[..., 1] - yp)
        residual = np.where(ok, full, residual)
        induced = np.where(ok, np.hypot(px[..., 0] - u, px[..., 1] - v), induced)
        with_depth = ok
    residual = np.where(np.isfinite(residual), residual, 0.0)
    threshold = motion_px + motion_rel * np.where(np.isfinite(induced), induced, 0.0)
    moving = reliable & (residual > threshold)
    return MotionResidual(residual.astype(np.float32), threshold.astype(np.float32), reliable, moving,
                          with_depth)


def moving_proposals(labels: np.ndarray, res: MotionResidual, min_px: int, fraction: float,
                     min_reliable: float) -> np.ndarray:
    """Which proposals move: ``(n,)`` bool. A proposal of at least ``min_px`` pixels moves when at
    least ``min_reliable`` of its pixels have reliable flow and more than ``fraction`` of those move."""
    n = int(labels.max()) + 1
    lab = labels.ravel()
    size = np.bincount(lab, minlength=n)
    rel = np.bincount(lab, weights=res.reliable.ravel().astype(np.float64), minlength=n)
    mov = np.bincount(lab, weights=res.moving.ravel().astype(np.float64), minlength=n)
    return (size >= min_px) & (rel >= min_reliable * np.maximum(size, 1)) & (rel > 0) & \
        (mov > fraction * np.maximum(rel, 1))


def moving_proposals_reference(labels: np.ndarray, res: MotionResidual, min_px: int, fraction: float,
                               min_reliable: float) -> np.ndarray:
    """Slow reference of :func:`moving_proposals`."""
    n = int(labels.max()) + 1
    out = np.zeros(n, bool)
    for k in range(n):
        m = labels == k
        r = m & res.reliable
        if m.sum() < min_px or r.sum() == 0 or r.sum() < min_reliable * m.sum():
            continue
        out[k] = (m & res.moving).sum() > fraction * r.sum()
    return out
