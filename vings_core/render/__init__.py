"""Differentiable 2D Gaussian Splatting (2DGS) rasterizer for the CPU (numba), with the
VINGS-Mono sample-based backward pass, a pure-torch reference and an optional gsplat route.

Public API (see docs/rasterizer.md)::

    out = rasterize_2dgs(means, quats, scales, opacities, colors, T_cw, camera,
                         sh_degree=None, pose_delta=None, background=None,
                         sample_ratio=1.0, loss_map=None, near=0.01, far=1e3)
    out.color, out.depth, out.normal, out.alpha, out.distortion      # (H, W[, 3])
    out.radii, out.pixels_touched, out.contribution, out.error       # (N,)
    scores = gaussian_scores(means, quats, scales, opacities, colors, T_cw, camera, loss_map)
"""
from .rasterize import RenderOutput, gaussian_scores, rasterize_2dgs
from .reference import render_reference
from .sh import eval_sh, num_sh_bases, rgb_to_sh0, sh_to_color

__all__ = ["RenderOutput", "rasterize_2dgs", "gaussian_scores", "render_reference", "eval_sh",
           "sh_to_color", "rgb_to_sh0", "num_sh_bases", "select_sample_pixels"]


def select_sample_pixels(score, ratio: float):
    """``(H, W)`` bool mask of the pixels the sampled backward keeps: per 16x16 tile the
    ``ceil(ratio * n)`` highest-``score`` pixels (ties: lower row-major index first; NaN scores
    last); ``ratio`` in (0, 1]."""
    import numpy as np
    import torch

    from ..errors import InputError
    from .kernels import select_pixels
    from .rasterize import _as_numpy
    try:
        r = float(ratio)
    except (TypeError, ValueError):
        raise InputError(f"select_sample_pixels: ratio must be a number, got {ratio!r}") from None
    if not (0.0 < r <= 1.0):
        raise InputError(f"select_sample_pixels: ratio must be in (0, 1], got {ratio}")
    s = _as_numpy(score, np.float64, "select_sample_pixels: score")
    if s.ndim != 2:
        raise InputError(f"select_sample_pixels: score must be (H, W), got shape {s.shape}")
    sel = np.ones(s.shape, np.uint8)
    if ratio < 1.0:
        select_pixels(s, float(ratio), sel)
    return torch.from_numpy(sel.astype(bool))
