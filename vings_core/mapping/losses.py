"""Mapping losses (paper eq. "loss"): L = l_rgb L_rgb + l_depth L_d + l_norm L_n + l_acc L_acc.

Images are (H, W, 3) float in [0, 1]; depth (H, W) metric z-depth (m, 0 = invalid); normals
(H, W, 3) unit vectors in the camera frame; alpha (H, W) accumulated opacity.
"""
from __future__ import annotations

import functools
import math

import numpy as np
import torch
import torch.nn.functional as F
from numba import njit, prange

from ..types import CameraModel


def _gauss_window(size: int = 11, sigma: float = 1.5, dtype=torch.float32) -> torch.Tensor:
    x = torch.arange(size, dtype=dtype) - (size - 1) / 2
    g = torch.exp(-(x ** 2) / (2 * sigma ** 2))
    g = g / g.sum()
    return g


def _ssim_from_moments(mu_x, mu_y, xx, yy, xy) -> torch.Tensor:
    """SSIM per channel and pixel from the blurred moments ``E[x], E[y], E[x^2], E[y^2], E[xy]``."""
    sxx = xx - mu_x ** 2
    syy = yy - mu_y ** 2
    sxy = xy - mu_x * mu_y
    C1, C2 = 0.01 ** 2, 0.03 ** 2
    return ((2 * mu_x * mu_y + C1) * (2 * sxy + C2)) / ((mu_x ** 2 + mu_y ** 2 + C1) * (sxx + syy + C2))


def ssim_map(a: torch.Tensor, b: torch.Tensor, size: int = 11, sigma: float = 1.5) -> torch.Tensor:
    """Differentiable SSIM map (H, W) of (H, W, C) images in [0, 1] (Gaussian window, as 3DGS).

    The window is separable (two 1-D convolutions) with zero padding like 3DGS's ``ssim``.
    """
    C = a.shape[-1]
    x = a.permute(2, 0, 1)[None]
    y = b.permute(2, 0, 1)[None]
    g = _gauss_window(size, sigma, a.dtype).to(a.device)
    p = size // 2
    stacked = torch.cat([x, y, x * x, y * y, x * y], 1)
    gh5 = g.reshape(1, 1, 1, size).expand(5 * C, 1, 1, size)
    gv5 = g.reshape(1, 1, size, 1).expand(5 * C, 1, size, 1)
    f = F.conv2d(F.conv2d(stacked, gh5, padding=(0, p), groups=5 * C), gv5, padding=(p, 0), groups=5 * C)
    return _ssim_from_moments(*f.split(C, 1))[0].mean(0)


@njit(parallel=True, cache=True)
def _sep_blur_kernel(x, g, out):  # pragma: no cover - compiled
    """Separable zero-padded blur of (C, H, W) float32 ``x`` with the 1-D window ``g`` into ``out``.

    Each row is copied into a zero-padded buffer and the vertical pass reads a zero-padded
    intermediate, so both inner loops run over whole rows without bounds tests (the compiler
    vectorises them; 4x faster than clipping the range per tap). Same sums in the same order."""
    C, H, W = x.shape
    r = g.shape[0] // 2
    K = 2 * r + 1
    tmp = np.empty((C, H + 2 * r, W), x.dtype)     # horizontal pass, r zero rows above and below
    for c in range(C):
        for i in range(r):
            for j in range(W):
                tmp[c, i, j] = 0.0
                tmp[c, H + r + i, j] = 0.0
    for idx in prange(C * H):
        c = idx // H
        i = idx % H
        pad = np.zeros(W + 2 * r, x.dtype)
        xr = x[c, i]
        for j in range(W):
            pad[j + r] = xr[j]
        tr = tmp[c, i + r]
        for j in range(W):
            tr[j] = 0.0
        for k in range(K):
            gk = g[k]
            for j in range(W):
                tr[j] += gk * pad[j + k]
    for idx in prange(C * H):
        c = idx // H
        i = idx % H
        orow = out[c, i]
        for j in range(W):
            orow[j] = 0.0
        for k in range(K):
            gk = g[k]
            trow = tmp[c, i + k]
            for j in range(W):
                orow[j] += gk * trow[j]


def sep_blur(x: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    """(C, H, W) float32 CPU -> same-size blur with the symmetric 1-D window ``g`` along both axes,
    zero padding (what :func:`ssim_map`'s two convolutions compute). Differentiable: the operator is
    self-adjoint (symmetric window, zero padding), so the backward pass is the same blur."""
    return _SepBlur.apply(x, g)


def _blur_numpy(x: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    x = x.detach().contiguous()
    out = torch.empty_like(x)
    _sep_blur_kernel(x.numpy(), g.numpy(), out.numpy())
    return out


class _SepBlur(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, g):  # noqa: D401
        ctx.g = g
        return _blur_numpy(x, g)

    @staticmethod
    def backward(ctx, grad):
        return _blur_numpy(grad, ctx.g), None   # self-adjoint: the backward is the same blur


@functools.lru_cache(maxsize=8)
def _window(size: int, sigma: float) -> torch.Tensor:
    return _gauss_window(size, sigma, torch.float32).contiguous()


def ssim_target_stats(b: torch.Tensor, size: int = 11, sigma: float = 1.5) -> tuple[torch.Tensor, torch.Tensor]:
    """Blurred mean and second moment ``(mu_y, E[y^2])``, (C, H, W) each, of a target image
    (H, W, C): constant per keyframe, so :func:`ssim_map_fast` can reuse them."""
    y = b.to(torch.float32).permute(2, 0, 1)
    f = sep_blur(torch.cat([y, y * y], 0).contiguous(), _window(size, sigma))
    C = y.shape[0]
    return f[:C], f[C:]


def ssim_map_fast(a: torch.Tensor, b: torch.Tensor, target_stats: tuple | None = None, size: int = 11,
                  sigma: float = 1.5) -> torch.Tensor:
    """Same SSIM map as :func:`ssim_map` (float32, CPU) with a compiled separable blur, and only the
    three prediction-dependent moments blurred per call when the target's moments are given
    (``target_stats = ssim_target_stats(b)``)."""
    if a.device.type != "cpu" or a.dtype != torch.float32:
        return ssim_map(a, b, size, sigma)
    C = a.shape[-1]
    x = a.permute(2, 0, 1)
    y = b.to(torch.float32).permute(2, 0, 1)
    mu_y, yy = target_stats if target_stats is not None else ssim_target_stats(b, size, sigma)
    f = sep_blur(torch.cat([x, x * x, x * y], 0).contiguous(), _window(size, sigma))
    return _ssim_from_moments(f[:C], mu_y, f[C:2 * C], yy, f[2 * C:]).mean(0)


def ssim_reference(a: torch.Tensor, b: torch.Tensor, size: int = 11, sigma: float = 1.5) -> torch.Tensor:
    """Slow reference SSIM map with an explicit 2-D window (for tests)."""
    C = a.shape[-1]
    g = _gauss_window(size, sigma, a.dtype)
    w2 = (g[:, None] * g[None, :]).expand(C, 1, size, size)
    x = a.permute(2, 0, 1)[None]
    y = b.permute(2, 0, 1)[None]
    p = size // 2
    mu_x = F.conv2d(x, w2, padding=p, groups=C)
    mu_y = F.conv2d(y, w2, padding=p, groups=C)
    sxx = F.conv2d(x * x, w2, padding=p, groups=C) - mu_x ** 2
    syy = F.conv2d(y * y, w2, padding=p, groups=C) - mu_y ** 2
    sxy = F.conv2d(x * y, w2, padding=p, groups=C) - mu_x * mu_y
    C1, C2 = 0.01 ** 2, 0.03 ** 2
    s = ((2 * mu_x * mu_y + C1) * (2 * sxy + C2)) / ((mu_x ** 2 + mu_y ** 2 + C1) * (sxx + syy + C2))
    return s[0].mean(0)


def l1_map(pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    """(H, W) mean absolute RGB error per pixel (the per-pixel L_rgb(u) of the score manager)."""
    return (pred - gt).abs().mean(-1)


def rgb_loss(pred: torch.Tensor, gt: torch.Tensor, lambda_ssim: float = 0.2,
             mask: torch.Tensor | None = None, target_stats: tuple | None = None,
             l1: torch.Tensor | None = None, ssim_mask: torch.Tensor | None = None) -> torch.Tensor:
    """``(1 - l) L1 + l (1 - SSIM)`` averaged over pixels (or over ``mask``). ``target_stats``:
    cached :func:`ssim_target_stats` of ``gt``; ``l1``: the (differentiable) :func:`l1_map` if the
    caller already has it. ``ssim_mask``: the SSIM term is averaged over these pixels instead (each
    term over its own mask): pixels whose SSIM window reaches outside ``mask`` are left out, so
    nothing outside ``mask`` (e.g. a moving object) enters the loss."""
    l1 = l1_map(pred, gt) if l1 is None else l1
    if ssim_mask is not None and mask is not None:
        m = mask.to(l1.dtype)
        out = (1 - lambda_ssim) * (l1 * m).sum() / m.sum().clamp_min(1)
        if lambda_ssim > 0:
            ms = ssim_mask.to(l1.dtype)
            out = out + lambda_ssim * ((1 - ssim_map_fast(pred, gt, target_stats)) * ms).sum() / ms.sum().clamp_min(1)
        return out
    term = (1 - lambda_ssim) * l1
    if lambda_ssim > 0:
        term = term + lambda_ssim * (1 - ssim_map_fast(pred, gt, target_stats))
    if mask is None:
        return term.mean()
    m = mask.to(term.dtype)
    return (term * m).sum() / m.sum().clamp_min(1)


def depth_weight(depth: torch.Tensor, inv_depth_var: torch.Tensor, rel_std0: float) -> torch.Tensor:
    """Inverse-uncertainty weight in (0, 1]: ``1 / (1 + (sigma_d / d / rel_std0)^2)``.

    ``sigma_d / d = sqrt(var(1/d)) * d`` (first-order propagation of the inverse-depth variance).
    """
    rel = torch.sqrt(inv_depth_var.clamp_min(0)) * depth
    w = 1.0 / (1.0 + (rel / rel_std0) ** 2)
    # infinite variance: weight 0 (inf * 0 depth would give NaN and poison the whole loss)
    return torch.where(torch.isfinite(w), w, torch.zeros((), dtype=w.dtype))


def depth_loss(pred: torch.Tensor, gt: torch.Tensor, weight: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """Uncertainty-weighted relative L1 ``mean_valid w |D_hat - D| / D`` (scale-free: indoors and outdoors)."""
    m = valid & (gt > 0) & torch.isfinite(gt)
    n = m.sum().clamp_min(1)
    # computed under the mask: a masked pixel's inf or NaN must not make the sum NaN (NaN * 0 = NaN)
    r = torch.where(m, (pred - gt).abs() / torch.where(m, gt, torch.ones_like(gt)).clamp_min(1e-6),
                    torch.zeros_like(pred))
    return (r * torch.where(m, weight, torch.zeros_like(weight))).sum() / n


def normals_from_depth(depth: torch.Tensor, camera: CameraModel) -> tuple[torch.Tensor, torch.Tensor]:
    """Differentiable camera-frame normals of a depth map (central differences), facing the camera.

    Returns ``(normals (H, W, 3), valid (H, W) bool)``; border pixels and pixels with a zero
    neighbour are invalid.
    """
    H, W = depth.shape
    v, u = torch.meshgrid(torch.arange(H, dtype=depth.dtype, device=depth.device),
                          torch.arange(W, dtype=depth.dtype, device=depth.device), indexing="ij")
    P = torch.stack([(u - camera.cx) / camera.fx * depth, (v - camera.cy) / camera.fy * depth, depth], -1)
    du = torch.zeros_like(P)
    dv = torch.zeros_like(P)
    du[:, 1:-1] = P[:, 2:] - P[:, :-2]
    dv[1:-1] = P[2:] - P[:-2]
    n = torch.cross(du, dv, dim=-1)
    # sqrt of the clamped squared norm: finite gradients where n = 0 (empty pixels, depth 0);
    # linalg.norm's backward is 0/0 = NaN there even under a zero mask, and the NaN reached the
    # rasterizer's backward through dL/d(depth)
    n = n / torch.sqrt((n * n).sum(-1, keepdim=True).clamp_min(1e-24))
    n = torch.where(((n * P).sum(-1, keepdim=True) > 0), -n, n)
    ok = torch.zeros_like(depth, dtype=torch.bool)
    d = depth.detach()
    ok[1:-1, 1:-1] = (d[1:-1, 1:-1] > 0) & (d[1:-1, 2:] > 0) & (d[1:-1, :-2] > 0) & (d[2:, 1:-1] > 0) & \
        (d[:-2, 1:-1] > 0)
    return n, ok


def normal_loss(n_render: torch.Tensor, n_depth: torch.Tensor, weight: torch.Tensor,
                valid: torch.Tensor) -> torch.Tensor:
    """2DGS normal consistency: ``mean_valid w (1 - n_render . n_depth)``."""
    m = valid.to(n_render.dtype)
    e = 1 - (n_render * n_depth).sum(-1)
    return (e * weight * m).sum() / m.sum().clamp_min(1)


def accumulation_loss(alpha: torch.Tensor, masked: torch.Tensor) -> torch.Tensor:
    """Pixels known to be empty (``init.empty_mask``: sky, beyond max depth) must stay transparent:
    ``mean_masked alpha``."""
    if not bool(masked.any()):
        return alpha.sum() * 0
    return alpha[masked].mean()


def psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    mse = float(((a - b) ** 2).mean())
    return float("inf") if mse <= 0 else -10 * math.log10(mse)
