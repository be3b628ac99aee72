"""Optional route to gsplat's CUDA ``rasterization_2dgs`` when CUDA and gsplat are importable.

Kept small and honest: it maps our arguments onto gsplat's and gsplat's outputs back onto
:class:`RenderOutput`. Differences from the numba path (documented in docs/rasterizer.md): gsplat's
depth channel accumulates the *centre* depth and its distortion is its L1 variant; the backward is
always full (no pixel sampling); score-manager scores are not computed (``contribution`` and
``error`` are ``None``-like zeros, ``pixels_touched`` zeros).
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
                     near: float = 0.01, far: float = 1e3):
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
    zeros = torch.zeros(N, dtype=dt, device=dev)
    return RenderOutput(
        color=colors_out[0, ..., :3], depth=colors_out[0, ..., 3], normal=normals_c,
        alpha=alphas[0, ..., 0], distortion=distort[0, ..., 0], radii=radii,
        pixels_touched=torch.zeros(N, dtype=torch.int32, device=dev), contribution=zeros,
        error=None, means2d=meta["means2d"].reshape(N, 2).detach(),
        n_contrib=torch.zeros(camera.height, camera.width, dtype=torch.int32, device=dev),
        stats={"backend": "gsplat"})
