"""The re-render cue (the paper's "Dynamic Object Eraser"): how badly the map re-renders each pixel
of a keyframe, and which proposals that makes dynamic.

Per pixel (working resolution) ``L_re = L_SSIM * L_1 * Sigma`` with ``L_1`` the mean absolute RGB
error of the render, ``L_SSIM = (1 - SSIM) / 2`` in [0, 1] and ``Sigma`` the front end's
inverse-depth variance relative to its median over the covered pixels, clipped to
``[1/sigma_clip, sigma_clip]`` (so the threshold does not depend on the scene's scale; uncertain
pixels weigh more). Only pixels the map covers (render alpha > ``min_alpha``) count. A proposal is
dynamic when more than ``gamma`` of its covered pixels exceed the keyframe's ``percentile``-th
percentile of ``L_re`` and its mean ``L_re`` exceeds ``loss_threshold``.

:func:`rerender_loss` and :func:`dynamic_proposals` are the vectorised versions;
:func:`dynamic_proposals_reference` is the slow per-proposal loop they are tested against.
"""
from __future__ import annotations

from typing import Optional

import numpy as np

from .config import EraserConfig, LossTerms


def relative_sigma(inv_depth_var: np.ndarray, covered: np.ndarray, clip: float) -> np.ndarray:
    """``inv_depth_var`` over its median on the ``covered`` finite pixels, clipped to
    ``[1/clip, clip]``; unknown (non-finite) variance counts as ``clip`` (most uncertain)."""
    v = np.asarray(inv_depth_var, dtype=np.float64)
    ok = np.isfinite(v) & (v >= 0)
    pos = ok & (v > 0)
    ref = v[pos & covered] if np.any(pos & covered) else v[pos]
    med = float(np.median(ref)) if ref.size else 1.0
    rel = np.where(ok, v / max(med, 1e-30), clip)
    return np.clip(rel, 1.0 / clip, clip).astype(np.float32)


def ssim_map_cv(a: np.ndarray, b: np.ndarray, size: int = 11, sigma: float = 1.5) -> np.ndarray:
    """SSIM map ``(H, W)`` of two RGB images ``(H, W, 3)`` in [0, 1] (channel mean), with OpenCV's
    separable Gaussian blur (the same window and constants as
    :func:`~vings_core.mapping.losses.ssim_map`, which it is tested against; borders are
    reflected instead of zero-padded)."""
    import cv2
    C1, C2 = 0.01 ** 2, 0.03 ** 2
    x = np.ascontiguousarray(a, dtype=np.float32)
    y = np.ascontiguousarray(b, dtype=np.float32)

    def blur(z):
        return cv2.GaussianBlur(z, (size, size), sigma, borderType=cv2.BORDER_REFLECT)
    mx, my = blur(x), blur(y)
    sxx = blur(x * x) - mx * mx
    syy = blur(y * y) - my * my
    sxy = blur(x * y) - mx * my
    s = ((2 * mx * my + C1) * (2 * sxy + C2)) / ((mx * mx + my * my + C1) * (sxx + syy + C2))
    return s.mean(-1) if s.ndim == 3 else s


def rerender_maps(render: np.ndarray, image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(L_1, L_SSIM)`` maps ``(H, W)`` float32 of ``render`` against ``image`` (both ``(H, W, 3)``
    RGB in [0, 1]): the factors every :class:`LossTerms` variant is a product of."""
    r = np.ascontiguousarray(render, dtype=np.float32)
    g = np.ascontiguousarray(image, dtype=np.float32)
    return np.abs(r - g).mean(-1), np.clip((1.0 - ssim_map_cv(r, g)) * 0.5, 0.0, 1.0)


def rerender_loss(render: np.ndarray, image: np.ndarray, inv_depth_var: Optional[np.ndarray],
                  covered: np.ndarray, terms: LossTerms, sigma_clip: float = 10.0,
                  maps: Optional[tuple[np.ndarray, np.ndarray]] = None) -> np.ndarray:
    """Per-pixel re-render loss ``(H, W)`` float32 of ``render`` against ``image`` (both
    ``(H, W, 3)`` RGB in [0, 1]); 0 outside ``covered``. ``terms``: which product (module docstring);
    ``inv_depth_var`` may be None only for terms without Sigma. ``maps``: :func:`rerender_maps` of
    the same pair when the caller already has them (several variants of one keyframe)."""
    l1, l_ssim = rerender_maps(render, image) if maps is None else maps
    out = l1
    if terms in (LossTerms.SSIM_L1, LossTerms.SSIM_L1_SIGMA):
        out = out * l_ssim
    if terms == LossTerms.SSIM_L1_SIGMA:
        if inv_depth_var is None:
            raise ValueError("the Sigma term needs the keyframe's inverse-depth variance")
        out = out * relative_sigma(inv_depth_var, covered, sigma_clip)
    return np.where(covered, out, 0.0).astype(np.float32)


def dynamic_proposals(labels: np.ndarray, loss: np.ndarray, covered: np.ndarray,
                      cfg: EraserConfig) -> tuple[np.ndarray, dict]:
    """Which proposals (``labels`` ``(H, W)`` int ``0..n-1``) the re-render cue makes dynamic:
    ``(n,)`` bool, and the keyframe's figures (``percentile`` value, proposals ``judged``)."""
    n = int(labels.max()) + 1
    lab = labels.ravel()
    cov = covered.ravel()
    size = np.bincount(lab, minlength=n)
    if not cov.any():
        return np.zeros(n, bool), {"percentile": None, "judged": 0}
    p = float(np.percentile(loss.ravel()[cov], cfg.percentile))
    n_cov = np.bincount(lab, weights=cov.astype(np.float64), minlength=n)
    above = np.bincount(lab, weights=(cov & (loss.ravel() > p)).astype(np.float64), minlength=n)
    total = np.bincount(lab, weights=np.where(cov, loss.ravel(), 0.0).astype(np.float64), minlength=n)
    judged = (size >= cfg.min_proposal_px) & (n_cov >= cfg.min_covered_fraction * np.maximum(size, 1)) & (n_cov > 0)
    safe = np.maximum(n_cov, 1)
    dyn = judged & (above / safe > cfg.gamma) & (total / safe > cfg.loss_threshold)
    return dyn, {"percentile": p, "judged": int(judged.sum())}


def dynamic_proposals_reference(labels: np.ndarray, loss: np.ndarray, covered: np.ndarray,
                                cfg: EraserConfig) -> np.ndarray:
    """Slow reference of :func:`dynamic_proposals` (a loop over proposals)."""
    n = int(labels.max()) + 1
    out = np.zeros(n, bool)
    if not covered.any():
        return out
    p = np.percentile(loss[covered], cfg.percentile)
    for k in range(n):
        m = labels == k
        c = m & covered
        if m.sum() < cfg.min_proposal_px or c.sum() == 0 or c.sum() < cfg.min_covered_fraction * m.sum():
            continue
        vals = loss[c]
        out[k] = (np.mean(vals > p) > cfg.gamma) and (vals.mean() > cfg.loss_threshold)
    return out
