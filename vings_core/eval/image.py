"""Image quality: PSNR (optionally masked) and SSIM (Gaussian window 11, sigma 1.5), vectorised torch.

Inputs are ``(H, W)`` or ``(H, W, C)`` images (numpy or torch) with values in [0, 1] (float), or
``uint8`` in [0, 255] (divided by 255 here). SSIM follows Wang et al. 2004 exactly as
``skimage.metrics.structural_similarity(a, b, gaussian_weights=True, sigma=1.5,
use_sample_covariance=False, data_range=1.0, channel_axis=-1)`` does: statistics with an 11-tap
Gaussian (sigma 1.5, truncated at 3.5 sigma), ``K1 = 0.01``, ``K2 = 0.03``, averaged over the pixels
at least 5 px from the border (the window fits) and over channels.
"""
from __future__ import annotations

from typing import Optional, Union

import numpy as np
import torch
import torch.nn.functional as F

from ..errors import InputError

ArrayLike = Union[np.ndarray, torch.Tensor]

SSIM_WIN = 11
SSIM_SIGMA = 1.5
SSIM_K1 = 0.01
SSIM_K2 = 0.03


def to_float_image(img: ArrayLike, name: str = "image") -> torch.Tensor:
    """``(H, W)`` / ``(H, W, C)`` numpy or torch -> float64 torch ``(H, W, C)`` in [0, 1]-units.

    ``uint8`` input is divided by 255; float input is taken as is (expected in [0, 1])."""
    t = img.detach() if isinstance(img, torch.Tensor) else torch.from_numpy(np.ascontiguousarray(img))
    if t.dtype == torch.uint8:
        t = t.to(torch.float64) / 255.0
    elif t.dtype == torch.bool or not (t.is_floating_point()):
        raise InputError(f"{name}: expected a float image in [0, 1] or uint8, got dtype {t.dtype}")
    else:
        t = t.to(torch.float64)
    if t.ndim == 2:
        t = t[..., None]
    if t.ndim != 3:
        raise InputError(f"{name}: expected shape (H, W) or (H, W, C), got {tuple(t.shape)}")
    return t.cpu()


def _pair(a: ArrayLike, b: ArrayLike) -> tuple[torch.Tensor, torch.Tensor]:
    ta, tb = to_float_image(a, "first image"), to_float_image(b, "second image")
    if ta.shape != tb.shape:
        raise InputError(f"images differ in shape: {tuple(ta.shape)} vs {tuple(tb.shape)}")
    return ta, tb


def _metric_pair(a: ArrayLike, b: ArrayLike, data_range: Optional[float]) -> tuple[torch.Tensor, torch.Tensor, float]:
    """Both images in [0, 1]-units and the peak value in those units.

    ``data_range`` is the peak of the inputs as given: None = 1 for float images (uint8 ones are
    divided by 255 first); 255 with uint8 input is the same thing (the skimage habit). A float
    image outside ``[0, data_range]`` (e.g. 0..255 floats without ``/ 255``) or with NaN is refused
    rather than measured: it would give a meaningless PSNR."""
    is8 = any(getattr(x, "dtype", None) in (np.uint8, torch.uint8) for x in (a, b))
    rng = 1.0 if data_range is None else float(data_range)
    if not (np.isfinite(rng) and rng > 0):
        raise InputError(f"data_range must be a positive number, got {data_range}")
    if is8 and rng not in (1.0, 255.0):
        raise InputError(f"data_range {data_range} with uint8 images: uint8 images are compared in "
                         f"[0, 1] units (255 -> 1); leave data_range out")
    if is8:
        rng = 1.0
    ta, tb = _pair(a, b)
    for name, t in (("first image", ta), ("second image", tb)):
        if not bool(torch.isfinite(t).all()):
            raise InputError(f"{name}: {int((~torch.isfinite(t)).sum())} non-finite values")
        lo, hi = float(t.min()), float(t.max())
        if lo < -1e-6 * rng or hi > rng * (1 + 1e-6):
            raise InputError(f"{name}: values in [{lo:.4g}, {hi:.4g}] outside [0, {rng:g}]"
                             + (" (0..255 floats? divide by 255)" if hi > 1.5 * rng else "")
                             + "; give data_range for another scale")
    return ta, tb, rng


def mse(a: ArrayLike, b: ArrayLike, mask: Optional[ArrayLike] = None) -> float:
    """Mean squared error over all channels (of the pixels where ``mask`` is true, if given)."""
    ta, tb = _pair(a, b)
    d2 = (ta - tb) ** 2
    if mask is None:
        return float(d2.mean())
    m = (mask.detach() if isinstance(mask, torch.Tensor)
         else torch.from_numpy(np.ascontiguousarray(mask))).cpu()
    if m.ndim == 3 and m.shape[-1] == 1:
        m = m[..., 0]
    if tuple(m.shape) != tuple(ta.shape[:2]):
        raise InputError(f"mask shape {tuple(m.shape)} does not match image {tuple(ta.shape[:2])}")
    m = m.to(torch.bool)
    if not bool(m.any()):
        raise InputError("PSNR mask selects no pixel")
    return float(d2[m].mean())


def psnr(a: ArrayLike, b: ArrayLike, mask: Optional[ArrayLike] = None,
         data_range: Optional[float] = None) -> float:
    """Peak signal-to-noise ratio in dB, ``10 log10(peak^2 / MSE)``; ``inf`` for identical
    images. ``mask`` (``(H, W)`` bool) restricts the MSE to the selected pixels. Float images in
    [0, 1] or uint8 (``data_range``: see :func:`_metric_pair`)."""
    ta, tb, rng = _metric_pair(a, b, data_range)
    e = mse(ta, tb, mask)
    if e == 0.0:
        return float("inf")
    return float(10.0 * np.log10(rng ** 2 / e))


def gaussian_kernel1d(win: int = SSIM_WIN, sigma: float = SSIM_SIGMA, dtype=torch.float64) -> torch.Tensor:
    """Normalised 1-D Gaussian of ``win`` taps (odd)."""
    x = torch.arange(win, dtype=dtype) - (win - 1) / 2
    k = torch.exp(-0.5 * (x / sigma) ** 2)
    return k / k.sum()


def ssim_map(a: torch.Tensor, b: torch.Tensor, data_range: float = 1.0,
             win: int = SSIM_WIN, sigma: float = SSIM_SIGMA) -> torch.Tensor:
    """SSIM map of batched images ``(B, C, H, W)`` (differentiable, any float dtype/device).

    Returns ``(B, C, H - win + 1, W - win + 1)``: the statistics where the window fits entirely
    ('valid' separable convolution, no padding)."""
    B, C, H, W = a.shape
    if H < win or W < win:
        raise InputError(f"SSIM needs images of at least {win}x{win} px, got {W}x{H}")
    k = gaussian_kernel1d(win, sigma, a.dtype).to(a.device)
    kx = k.view(1, 1, 1, win).expand(5 * C, 1, 1, win)
    ky = k.view(1, 1, win, 1).expand(5 * C, 1, win, 1)
    x = torch.cat([a, b, a * a, b * b, a * b], dim=1)  # (B, 5C, H, W)
    f = F.conv2d(F.conv2d(x, kx, groups=5 * C), ky, groups=5 * C)
    mu_a, mu_b, e_aa, e_bb, e_ab = f.split(C, dim=1)
    va = e_aa - mu_a * mu_a
    vb = e_bb - mu_b * mu_b
    cov = e_ab - mu_a * mu_b
    c1 = (SSIM_K1 * data_range) ** 2
    c2 = (SSIM_K2 * data_range) ** 2
    return ((2 * mu_a * mu_b + c1) * (2 * cov + c2)) / ((mu_a ** 2 + mu_b ** 2 + c1) * (va + vb + c2))


def ssim(a: ArrayLike, b: ArrayLike, data_range: Optional[float] = None) -> float:
    """Mean SSIM of two ``(H, W)`` / ``(H, W, C)`` images (Gaussian window 11, sigma 1.5),
    matching skimage's ``structural_similarity`` with ``gaussian_weights=True`` (``data_range``:
    see :func:`_metric_pair`)."""
    ta, tb, rng = _metric_pair(a, b, data_range)
    m = ssim_map(ta.permute(2, 0, 1)[None], tb.permute(2, 0, 1)[None], rng)
    return float(m.mean())
