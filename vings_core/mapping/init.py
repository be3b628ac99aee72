"""New Gaussians from a keyframe's depth: masking, sampling, back-projection, 2DGS-style attributes.

All functions are vectorised over pixels. Frames: camera optical frame (x right, y down, z forward),
``T_wc`` camera-to-world, depth = metric z-depth (m).
"""
from __future__ import annotations

import math

import numpy as np
import torch
from scipy.spatial import cKDTree

from ..geometry import rotmat_to_quat
from ..types import CameraModel, Keyframe
from .gaussians import GaussianMap, rgb_to_sh_dc


def pixel_rays(camera: CameraModel, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """(H, W, 3) rays ``K^-1 [u, v, 1]`` (z = 1) through pixel centres (pixel (0,0) centre at 0,0)."""
    v, u = torch.meshgrid(torch.arange(camera.height, dtype=dtype), torch.arange(camera.width, dtype=dtype),
                          indexing="ij")
    return torch.stack([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, torch.ones_like(u)], -1)


def depth_to_points(depth: torch.Tensor, camera: CameraModel) -> torch.Tensor:
    """(H, W) z-depth (m) -> (H, W, 3) points in the camera frame."""
    return pixel_rays(camera, depth.dtype) * depth[..., None]


def depth_normals(depth: torch.Tensor, camera: CameraModel, max_rel_jump: float = 0.05) -> torch.Tensor:
    """(H, W, 3) unit camera-frame normals from central differences of the back-projected depth.

    Normals face the camera (``n . p < 0``). Where a neighbour is invalid or the depth jumps by more
    than ``max_rel_jump`` (relative), the normal falls back to the reversed viewing ray.
    """
    P = depth_to_points(depth, camera)
    d = depth
    Pp = torch.nn.functional.pad(P.permute(2, 0, 1)[None], (1, 1, 1, 1), mode="replicate")[0].permute(1, 2, 0)
    dp = torch.nn.functional.pad(d[None, None], (1, 1, 1, 1), mode="replicate")[0, 0]
    du = Pp[1:-1, 2:] - Pp[1:-1, :-2]
    dv = Pp[2:, 1:-1] - Pp[:-2, 1:-1]
    n = torch.cross(du, dv, dim=-1)
    norm = torch.linalg.norm(n, dim=-1, keepdim=True)
    neigh = torch.stack([dp[1:-1, 2:], dp[1:-1, :-2], dp[2:, 1:-1], dp[:-2, 1:-1]], -1)
    ok = (d > 0) & (neigh > 0).all(-1) & ((neigh - d[..., None]).abs() <= max_rel_jump * d[..., None]).all(-1)
    ok = ok & (norm[..., 0] > 0)
    ray = P / torch.linalg.norm(P, dim=-1, keepdim=True).clamp_min(1e-12)
    n = torch.where(ok[..., None], n / norm.clamp_min(1e-30), -ray)
    flip = (n * P).sum(-1, keepdim=True) > 0
    n = torch.where(flip, -n, n)
    return n


def frame_from_normals(n: torch.Tensor) -> torch.Tensor:
    """(M, 3) unit normals -> (M, 3, 3) right-handed rotations with columns (t1, t2, n)."""
    a = torch.zeros_like(n)
    use_y = n[:, 0].abs() > 0.9
    a[:, 0] = (~use_y).to(n.dtype)
    a[:, 1] = use_y.to(n.dtype)
    t1 = a - (a * n).sum(-1, keepdim=True) * n
    t1 = t1 / torch.linalg.norm(t1, dim=-1, keepdim=True)
    t2 = torch.cross(n, t1, dim=-1)
    return torch.stack([t1, t2, n], -1)


def usable_depth_mask(kf: Keyframe, max_depth: float, max_rel_std: float) -> torch.Tensor:
    """(H, W) bool: pixels whose depth may seed Gaussians.

    Masks invalid pixels, depth <= 0 or > ``max_depth`` (m, "excessive depth") and pixels whose
    relative depth standard deviation ``sigma_d / d = sqrt(inv_depth_var) * d`` exceeds
    ``max_rel_std`` (high uncertainty; ``inv_depth_var`` is the variance of inverse depth, 1/m^2),
    and the keyframe's dynamic pixels (:func:`static_mask`).
    """
    d = kf.depth.to(torch.float32)
    rel_std = torch.sqrt(kf.inv_depth_var.to(torch.float32).clamp_min(0)) * d
    return kf.valid.to(torch.bool) & (d > 0) & (d <= max_depth) & (rel_std <= max_rel_std) & static_mask(kf)


def static_mask(kf: Keyframe) -> torch.Tensor:
    """(H, W) bool: pixels not marked dynamic by the eraser (all of them without a mask)."""
    if kf.dynamic is None:
        return torch.ones(kf.depth.shape[:2], dtype=torch.bool)
    return ~kf.dynamic.to(torch.bool)


def empty_mask(kf: Keyframe, max_depth: float) -> torch.Tensor:
    """(H, W) bool: pixels the depth source declares *empty* (sky, beyond ``max_depth``), where the
    accumulation loss keeps the map transparent.

    A pixel is empty when its depth exceeds ``max_depth`` (valid or not: "excessive depth" is
    masked out, and seeding such a pixel at a nearer interpolated depth would put Gaussians where
    there is no surface), or when it is not valid and has no surface (depth <= 0) with an
    inverse-depth standard deviation below ``1 / max_depth`` (1/m): the inverse depth is then known
    to be ~0, i.e. any surface lies beyond ``max_depth`` at 1 sigma (ground-truth / rendered depth
    of the sky: variance 0). Pixels without depth because the
    estimate is *uncertain* (front-end depth dropped for high variance) are unknown, not empty:
    forcing them transparent would punch black holes into surfaces other keyframes see well.
    Dynamic pixels are never empty.
    """
    d = kf.depth.to(torch.float32)
    std = torch.sqrt(kf.inv_depth_var.to(torch.float32).clamp_min(0))
    # a dynamic pixel is neither: the object hides whatever lies behind it
    return ((d > max_depth) | ((~kf.valid.to(torch.bool)) & (d <= 0) & (std < 1.0 / max_depth))) & static_mask(kf)


def fill_depth(depth: torch.Tensor, known: torch.Tensor) -> torch.Tensor:
    """Fill the pixels outside ``known`` by push-pull interpolation of the known depths.

    Push: a pyramid of 2x2 averages of ``(depth * known, known)`` until no level has holes; pull:
    from the coarsest level down, each hole takes the bilinear upsampling of the coarser filled
    level. Known pixels keep their depth exactly; holes get a smooth blend of the surrounding known
    depths (a wall without texture, whose depth the front end dropped, gets the depth of its
    outline). Returns (H, W); all zeros when nothing is known. Vectorised (no pixel loops).
    """
    F = torch.nn.functional
    w = known.to(torch.float32)
    if not bool(w.any()):
        return torch.zeros_like(depth, dtype=torch.float32)
    d = torch.where(known, depth.to(torch.float32), torch.zeros((), dtype=torch.float32))
    levels = [(d[None, None], w[None, None])]
    while bool((levels[-1][1] <= 0).any()) and min(levels[-1][1].shape[-2:]) > 1:
        dl, wl = levels[-1]
        levels.append((F.avg_pool2d(dl, 2, ceil_mode=True), F.avg_pool2d(wl, 2, ceil_mode=True)))
    dl, wl = levels[-1]
    filled = torch.where(wl > 0, dl / wl.clamp_min(1e-12), (dl.sum() / wl.sum()).expand_as(dl))
    for dl, wl in reversed(levels[:-1]):
        up = F.interpolate(filled, size=dl.shape[-2:], mode="bilinear", align_corners=False)
        filled = torch.where(wl > 0, dl / wl.clamp_min(1e-12), up)
    out = filled[0, 0]
    return torch.where(known, depth.to(torch.float32), out)


def sample_pixels(mask: torch.Tensor, n: int, generator: torch.Generator | None = None) -> torch.Tensor:
    """Up to ``n`` distinct (row, col) indices drawn uniformly from the True pixels of ``mask``."""
    idx = mask.reshape(-1).nonzero()[:, 0]
    if idx.numel() > n:
        idx = idx[torch.randperm(idx.numel(), generator=generator)[:n]]
    W = mask.shape[1]
    return torch.stack([idx // W, idx % W], -1)


def knn_spacing(points: np.ndarray, k: int = 3) -> np.ndarray:
    """Root mean squared distance to the ``k`` nearest other points (2DGS initial scale)."""
    if len(points) <= 1:
        return np.full(len(points), np.nan)
    kk = min(k, len(points) - 1)
    d, _ = cKDTree(points).query(points, k=kk + 1)
    return np.sqrt((d[:, 1:] ** 2).mean(1))


def gaussians_from_pixels(kf: Keyframe, rc: torch.Tensor, sh_degree: int, init_opacity: float,
                          scale_factor: float, min_scale_px: float, max_scale_px: float,
                          score_since: int = 0, normals_cam: torch.Tensor | None = None,
                          window: int = 8) -> GaussianMap:
    """Back-project pixels ``rc`` (M, 2) (row, col) of keyframe ``kf`` into new Gaussians.

    Centres: ``T_wc @ (d K^-1 [u v 1])``; colours: the pixel RGB as the DC SH band; surfel normal: the
    depth normal (facing the camera); sigma: ``scale_factor`` x RMS distance to the 3 nearest new
    centres, clamped to ``[min_scale_px, max_scale_px]`` pixel footprints ``d / f``; opacity
    ``init_opacity``; ID(g) = the keyframe's stamp.
    """
    cam = kf.camera
    depth = kf.depth.to(torch.float32)
    if normals_cam is None:
        normals_cam = depth_normals(depth, cam)
    r, c = rc[:, 0], rc[:, 1]
    d = depth[r, c]
    x = (c.to(torch.float32) - cam.cx) / cam.fx * d
    y = (r.to(torch.float32) - cam.cy) / cam.fy * d
    p_c = torch.stack([x, y, d], -1).to(torch.float64)
    T = kf.T_wc.to(torch.float64)
    p_w = p_c @ T[:3, :3].T + T[:3, 3]
    R_c = frame_from_normals(normals_cam[r, c].to(torch.float64))
    q = rotmat_to_quat(T[:3, :3].expand(len(rc), 3, 3) @ R_c)
    foot = d.to(torch.float64) / math.sqrt(cam.fx * cam.fy)  # m per pixel at the point
    sp = torch.from_numpy(knn_spacing(p_w.numpy()))
    sp = torch.where(torch.isfinite(sp), sp, foot * max_scale_px)
    sigma = torch.minimum(torch.maximum(sp * scale_factor, foot * min_scale_px), foot * max_scale_px)
    log_s = torch.log(sigma)[:, None].expand(-1, 2)
    rgb = kf.image.to(torch.float32)[r, c, :3]
    K = (sh_degree + 1) ** 2
    sh = torch.zeros(len(rc), K, 3, dtype=torch.float32)
    sh[:, 0] = rgb_to_sh_dc(rgb)
    op = torch.full((len(rc),), math.log(init_opacity / (1 - init_opacity)), dtype=torch.float32)
    return GaussianMap.create(p_w.to(torch.float32), q.to(torch.float32), log_s.to(torch.float32), op, sh,
                              int(kf.stamp_ns), score_since=score_since, window=window)


def num_to_add(low_mask: torch.Tensor, points_per_keyframe: int) -> int:
    """Number of Gaussians for a low-accumulation mask: ``k * (low pixels / all pixels)``."""
    return int(round(points_per_keyframe * float(low_mask.sum()) / low_mask.numel()))
