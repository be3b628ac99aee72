"""Optional route to gsplat's CUDA ``rasterization_2dgs`` when CUDA and gsplat are importable.

Kept small and honest: it maps our arguments onto gsplat's and gsplat's outputs back onto
:class:`RenderOutput`. Differences from the numba path (documented in docs/rasterizer.md): gsplat's
depth channel accumulates the *centre* depth and its distortion is its L1 variant; the backward is
always full (no pixel sampling). The per-Gaussian scores are computed on the GPU too: ``contribution``
``sum_u alpha T`` and ``error`` ``sum_u L(u) alpha T`` as the colour gradients of a second,
two-channel render (colour 1 everywhere; upstream 1 and ``L(u)``: ``dC/dc_i = alpha_i T_i``), and
``pixels_touched`` / ``n_contrib`` by counting gsplat's (Gaussian, pixel) intersections.
"""
from __future__ import annotations

from typing import Optional

import torch

from ..types import CameraModel


def gsplat_available() -> bool:
    """True when CUDA is usable and ``gsplat.rasterization_2dgs`` imports."""
    if not torch.cuda.is_available():
        return False
    try:
        from gsplat import rasterization_2dgs  # noqa: F401
    except Exception:
        return False
    return True


def rasterize_gsplat(means, quats, scales, opacities, colors, T_cw: torch.Tensor,
                     camera: CameraModel, *, sh_degree: Optional[int] = None,
                     pose_delta: Optional[torch.Tensor] = None, background=None,
                     near: float = 0.01, far: float = 1e3, loss_map=None):
    from gsplat import rasterization_2dgs

    from .rasterize import RenderOutput
    dev, dt = means.device, means.dtype
    T = T_cw.to(device=dev, dtype=torch.float64)
    if pose_delta is not None:
        from .rasterize import apply_pose_delta
        T = apply_pose_delta(pose_delta.to(dev), T)
    T = T.to(dt)
    Ks = torch.tensor(camera.K, dtype=dt, device=dev)[None]
    # gsplat's pixel centres are at j + 0.5: shift the principal point by half a pixel.
    Ks[0, 0, 2] += 0.5
    Ks[0, 1, 2] += 0.5
    wxyz = torch.cat([quats[:, 3:4], quats[:, :3]], 1)
    sc3 = torch.cat([scales, torch.zeros_like(scales[:, :1])], 1)
    bg = None if background is None else torch.as_tensor(background, device=dev, dtype=dt)[None]
    # gsplat 1.5 wants post-activation colours per camera ([C, N, 3]); SH stays [N, K, 3]
    cols = colors[None] if sh_degree is None else colors
    colors_out, alphas, normals, _surf, distort, _median, meta = rasterization_2dgs(
        means, wxyz, sc3, opacities, cols, T[None], Ks, camera.width, camera.height,
        near_plane=near, far_plane=far, sh_degree=sh_degree, backgrounds=bg,
        render_mode="RGB+D", distloss=True)
    # gsplat returns world-frame normals; ours are camera-frame.
    normals_c = normals[0] @ T[:3, :3].T
    N = means.shape[0]
    radii = meta["radii"].reshape(N, -1).max(-1).values.to(torch.int32)
    H, W = camera.height, camera.width
    L = None if loss_map is None else loss_map.to(device=dev, dtype=dt)    # checked by the caller
    with torch.no_grad():
        contribution, error = _scores(rasterization_2dgs, means, wxyz, sc3, opacities, T, Ks, camera,
                                      near, far, L)
        touched, n_contrib = _counts(meta, N, H, W)
    return RenderOutput(
        color=colors_out[0, ..., :3], depth=colors_out[0, ..., 3], normal=normals_c,
        alpha=alphas[0, ..., 0], distortion=distort[0, ..., 0], radii=radii,
        pixels_touched=touched, contribution=contribution, error=error,
        means2d=meta["means2d"].reshape(N, 2).detach(), n_contrib=n_contrib,
        stats={"backend": "gsplat"})


def _scores(rasterization_2dgs, means, wxyz, sc3, opacities, T, Ks, camera, near, far, L):
    """``(contribution (N,), error (N,) or None)`` from the colour gradient of a two-channel render."""
    N = means.shape[0]
    with torch.enable_grad():
        ones = torch.ones(1, N, 2, dtype=means.dtype, device=means.device, requires_grad=True)
        img = rasterization_2dgs(means.detach(), wxyz.detach(), sc3.detach(), opacities.detach(), ones,
                                 T.detach()[None], Ks, camera.width, camera.height, near_plane=near,
                                 far_plane=far, render_mode="RGB")[0][0]
        total = img[..., 0].sum() + (img[..., 1] * L).sum() if L is not None else img[..., 0].sum()
        (g,) = torch.autograd.grad(total, ones, allow_unused=True)
    if g is None:   # nothing visible
        g = torch.zeros_like(ones)
    return g[0, :, 0].detach(), (g[0, :, 1].detach() if L is not None else None)


def _counts(meta: dict, N: int, H: int, W: int):
    """``(pixels_touched (N,), n_contrib (H, W))`` int32 from gsplat's per-pixel intersection list
    (alpha >= 1/255 and before the transmittance stop, as composited)."""
    from gsplat.cuda._wrapper import rasterize_to_indices_in_range_2dgs
    dev = meta["means2d"].device
    res = rasterize_to_indices_in_range_2dgs(
        0, 2**30, torch.ones(1, H, W, device=dev, dtype=meta["means2d"].dtype),
        meta["means2d"].detach(), meta["ray_transforms"].detach(), meta["opacities"].detach(),
        W, H, meta["tile_size"], meta["isect_offsets"], meta["flatten_ids"])
    gids, pids = res[0].long(), res[1].long()
    touched = torch.bincount(gids, minlength=N)[:N].to(torch.int32)
    n_contrib = torch.bincount(pids, minlength=H * W)[: H * W].reshape(H, W).to(torch.int32)
    return touched, n_contrib
