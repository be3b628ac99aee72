"""The motion cue: what the re-render cue cannot see (a region the map does not cover yet).

Dense optical flow between the keyframe and the previous one (OpenCV DIS, both directions; a
pixel's flow is reliable when the two agree within ``fb_check_px``) against the flow the camera's
own motion induces. Where the map covers the pixel, its rendered depth gives the induced flow and
the residual is the full 2-D difference; elsewhere (no depth that a moving object did not distort:
the BA's own depth is pulled by the object) the residual is the distance of the measured match from
its epipolar line, which needs no depth (motion along the epipolar line is invisible there). A
pixel moves when its distance from the epipolar line exceeds ``motion_px``, or (with the map's
depth) its distance along the line from where the depth puts it exceeds ``motion_px + motion_rel *
|translational induced flow|`` (an error of the map's depth moves the prediction along the line,
in proportion to the translational flow).

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
    """Per pixel of the current keyframe (``(H, W)`` each): ``residual`` (px: the full 2-D
    residual with depth, the epipolar distance without), ``threshold`` (px: the residual at which the
    pixel counts as moving),
    ``reliable`` (forward-backward consistent flow), ``moving`` (reliable and residual above
    threshold), ``with_depth`` (the residual used the map's depth; else the epipolar distance),
    ``informative`` (the flow could show an object's motion there, whatever its direction: the map's
    depth is known and the camera's translation moves the pixel by at least 3 ``motion_px``; a
    proposal is shown static only by such pixels)."""

    residual: np.ndarray
    ratio: np.ndarray
    reliable: np.ndarray
    moving: np.ndarray
    with_depth: np.ndarray
    informative: Optional[np.ndarray] = None


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
                    motion_rel: float, fb_check_px: float, refine: bool = True,
                    normal: Optional[np.ndarray] = None, grazing_cos_min: float = 1.0,
                    median_k: float = 0.0) -> MotionResidual:
    """Residual flow of every pixel of keyframe ``cur`` against keyframe ``prev`` (images ``(H, W)``
    or ``(H, W, 3)``). ``depth``: the map's rendered z-depth at ``cur`` (m, 0 where the map does
    not cover the pixel), or None. ``refine``: the keyframes' relative pose is first refined on
    the flow itself (:func:`refine_relative_pose`), so an error of the front end's poses is not
    taken for motion. ``normal``: the map's rendered unit normals at ``cur`` (camera frame, 0 where
    empty): a surface seen at a grazing angle has an uncertain rendered depth (a surfel's depth
    error grows as 1 / cos of the angle between its normal and the ray), so the tolerance along
    the epipolar line is divided by ``max(|cos|, grazing_cos_min)`` (1 = off). ``median_k``: a
    pixel moves only when its residual ratio also exceeds ``median_k`` times the median ratio of
    the keyframe's reliable pixels (the level a remaining pose or flow error gives every pixel;
    0 = off)."""
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
    K = np.array([[camera.fx, 0, camera.cx], [0, camera.fy, camera.cy], [0, 0, 1.0]])
    if refine:
        T_pc = refine_relative_pose(T_pc, K, u, v, xp, yp, reliable, depth, motion_px)
    R, t = T_pc[:3, :3], T_pc[:3, 3]
    fx, fy, cx, cy = float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])
    rx = (u - cx) / fx                                  # normalised rays (z = 1), float32
    ry = (v - cy) / fy
    # epipolar line of each pixel in the previous keyframe: l = F x, F = K^-T [t]x R K^-1; its
    # distance from the measured match needs no depth
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    Ki = np.linalg.inv(K)
    F = Ki.T @ tx @ R @ Ki
    F = (F / max(float(np.linalg.norm(F)), 1e-300)).astype(np.float32)     # the distance is scale-free
    l0 = F[0, 0] * u + F[0, 1] * v + F[0, 2]
    l1 = F[1, 0] * u + F[1, 1] * v + F[1, 2]
    l2 = F[2, 0] * u + F[2, 1] * v + F[2, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        epi = np.abs(l0 * xp + l1 * yp + l2) / np.maximum(np.hypot(l0, l1), 1e-12)
    Rf = R.astype(np.float32)

    def project(X, Y, Z):
        with np.errstate(divide="ignore", invalid="ignore"):
            return fx * X / Z + cx, fy * Y / Z + cy
    # the rotation-only part: where the pixel would be at infinite depth
    zi = Rf[2, 0] * rx + Rf[2, 1] * ry + Rf[2, 2]
    inf_x, inf_y = project(Rf[0, 0] * rx + Rf[0, 1] * ry + Rf[0, 2], Rf[1, 0] * rx + Rf[1, 1] * ry + Rf[1, 2], zi)
    residual = epi
    ratio = epi / motion_px
    with_depth = np.zeros((H, W), bool)
    informative = np.zeros((H, W), bool)
    trans_med = None
    if depth is not None:
        d = np.asarray(depth, np.float32)
        Z = d * zi + np.float32(t[2])
        qx = d * (Rf[0, 0] * rx + Rf[0, 1] * ry + Rf[0, 2]) + np.float32(t[0])
        qy = d * (Rf[1, 0] * rx + Rf[1, 1] * ry + Rf[1, 2]) + np.float32(t[1])
        px_x, px_y = project(qx, qy, Z)
        with_depth = np.isfinite(d) & (d > 0) & (Z > 1e-6)
        # a wrong depth moves the predicted point along the epipolar line only: the residual across
        # the line is held to motion_px, the one along it gets motion_rel of the translational flow
        full = np.hypot(px_x - xp, px_y - yp)
        along = np.sqrt(np.maximum(full ** 2 - epi ** 2, 0.0))
        trans = np.hypot(px_x - inf_x, px_y - inf_y)
        thr_along = motion_px + motion_rel * np.where(np.isfinite(trans), trans, 0.0)
        if normal is not None and grazing_cos_min < 1.0:
            n = np.asarray(normal, np.float32)
            ray_n = np.sqrt(rx * rx + ry * ry + 1.0)
            cos = np.abs(n[..., 0] * rx + n[..., 1] * ry + n[..., 2]) / ray_n
            has_n = np.linalg.norm(n, axis=-1) > 0.5
            thr_along = thr_along / np.where(has_n, np.maximum(cos, grazing_cos_min), 1.0)
        residual = np.where(with_depth, full, residual)
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = np.where(with_depth, np.maximum(ratio, along / thr_along), ratio)
        informative = with_depth & (trans >= 3.0 * motion_px)
        if with_depth.any():
            trans_med = float(np.median(trans[with_depth & np.isfinite(trans)])) if np.isfinite(trans[with_depth]).any() else None
    # (almost) no translation: the epipolar line is undefined; where the map gives no depth the
    # residual is then taken against the rotation alone (exact at zero translation)
    if float(np.linalg.norm(t)) == 0.0 or (trans_med is not None and trans_med < motion_px):
        rot = np.hypot(inf_x - xp, inf_y - yp)
        allow = motion_px + (2.0 * trans_med if trans_med is not None else 0.0)
        residual = np.where(with_depth, residual, rot)
        ratio = np.where(with_depth, ratio, rot / allow)
    residual = np.where(np.isfinite(residual), residual, 0.0)
    ratio = np.where(np.isfinite(ratio), ratio, 0.0)
    level = 1.0
    if median_k > 0 and reliable.any():
        level = max(1.0, median_k * float(np.median(ratio[reliable])))
    moving = reliable & (ratio > level)
    return MotionResidual(residual.astype(np.float32), ratio.astype(np.float32), reliable, moving, with_depth,
                          informative)


def refine_relative_pose(T_pc: np.ndarray, K: np.ndarray, u: np.ndarray, v: np.ndarray, xp: np.ndarray,
                         yp: np.ndarray, reliable: np.ndarray, depth: Optional[np.ndarray], px_thr: float,
                         stride: int = 4, min_points: int = 60) -> np.ndarray:
    """The relative pose ``T_pc`` (current camera -> previous) refined on the measured flow
    (``(u, v)`` in the current keyframe at ``(xp, yp)`` in the previous one, where ``reliable``),
    robustly, so that the static majority explains it: PnP RANSAC from the prior on the map's depth
    where it covers enough pixels; else the essential matrix by RANSAC (the translation's length is
    kept from the prior: only its direction is observable). The prior is returned when neither
    finds a consistent majority. Pixels sampled every ``stride``."""
    import cv2

    sl = (slice(stride // 2, None, stride), slice(stride // 2, None, stride))
    ok = reliable[sl]
    cur = np.stack([u[sl][ok], v[sl][ok]], -1).astype(np.float64)
    prv = np.stack([xp[sl][ok], yp[sl][ok]], -1).astype(np.float64)
    if len(cur) < min_points:
        return T_pc
    if depth is not None:
        d = np.asarray(depth, np.float64)[sl][ok]
        has = np.isfinite(d) & (d > 0)
        if has.sum() >= min_points:
            rays = (cur[has] - K[:2, 2]) / np.array([K[0, 0], K[1, 1]])
            X = np.concatenate([rays, np.ones((len(rays), 1))], 1) * d[has, None]
            rvec0, _ = cv2.Rodrigues(T_pc[:3, :3])
            tvec0 = T_pc[:3, 3].reshape(3, 1).copy()
            good, rvec, tvec, inl = cv2.solvePnPRansac(X, prv[has], K, None, rvec0.copy(), tvec0, True, 100,
                                                        float(px_thr), 0.999, flags=cv2.SOLVEPNP_ITERATIVE)
            if good and inl is not None and len(inl) >= 0.5 * has.sum():
                T = np.eye(4)
                T[:3, :3] = cv2.Rodrigues(rvec)[0]
                T[:3, 3] = tvec.ravel()
                return T
    if float(np.median(np.linalg.norm(prv - cur, axis=1))) < px_thr:
        return T_pc             # (almost) no motion: the essential matrix is degenerate
    E, mask = cv2.findEssentialMat(cur, prv, K, cv2.RANSAC, 0.999, float(px_thr))
    if E is None or E.shape != (3, 3) or mask is None or mask.sum() < 0.5 * len(cur):
        return T_pc
    n, R, t, _ = cv2.recoverPose(E, cur, prv, K, mask=mask.copy())
    if n < 0.5 * mask.sum():
        return T_pc
    scale = float(np.linalg.norm(T_pc[:3, 3]))
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t.ravel() * (scale if scale > 0 else 1.0)
    return T


def motion_fractions(labels: np.ndarray, res: MotionResidual) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per proposal (``(n,)`` each): size (px), fraction of its pixels with reliable flow, fraction
    of those that move."""
    n = int(labels.max()) + 1
    lab = labels.ravel()
    size = np.bincount(lab, minlength=n).astype(np.float64)
    rel = np.bincount(lab, weights=res.reliable.ravel().astype(np.float64), minlength=n)
    mov = np.bincount(lab, weights=res.moving.ravel().astype(np.float64), minlength=n)
    return size, rel / np.maximum(size, 1), mov / np.maximum(rel, 1)


def moving_proposals(labels: np.ndarray, res: MotionResidual, min_px: int, fraction: float,
                     min_reliable: float) -> np.ndarray:
    """Which proposals move: ``(n,)`` bool. A proposal of at least ``min_px`` pixels moves when at
    least ``min_reliable`` of its pixels have reliable flow and more than ``fraction`` of those move."""
    size, rel, mov = motion_fractions(labels, res)
    return (size >= min_px) & (rel >= min_reliable) & (rel > 0) & (mov > fraction)


def static_proposals(labels: np.ndarray, res: MotionResidual, min_reliable: float, fraction: float) -> np.ndarray:
    """Proposals the flow shows static: ``(n,)`` bool, at least ``min_reliable`` of their pixels
    with reliable *and informative* flow (:class:`MotionResidual`: where any motion would show) and
    at most ``fraction`` of those moving. An object moving along its epipolar line where the
    camera's translation hardly moves the pixels (a car ahead, near the focus of expansion) is not
    shown static."""
    if res.informative is None:
        return np.zeros(int(labels.max()) + 1, bool)
    view = MotionResidual(res.residual, res.ratio, res.reliable & res.informative, res.moving & res.informative,
                          res.with_depth, res.informative)
    _, rel, mov = motion_fractions(labels, view)
    return (rel >= min_reliable) & (rel > 0) & (mov <= fraction)


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
