"""Dense depth from the 1/8-resolution BA estimate: joint bilateral upsampling guided by the image,
and the validity mask (uncertainty, excessive depth, textureless far regions such as sky).

All functions are vectorised over pixels (numpy); :func:`upsample_reference` is the slow, obvious
per-pixel version the tests compare against.
"""
from __future__ import annotations

from functools import lru_cache
from typing import NamedTuple

import cv2
import numpy as np

class DenseDepth(NamedTuple):
    inv_depth: np.ndarray     #: (H, W) float32 inverse depth (1/m), 0 where unknown
    inv_var: np.ndarray       #: (H, W) float32 inverse-depth variance (1/m^2)
    depth: np.ndarray         #: (H, W) float32 z-depth (m), 0 where invalid
    valid: np.ndarray         #: (H, W) bool


def block_mean(img: np.ndarray, h: int, w: int, s: int) -> np.ndarray:
    a = img[: h * s, : w * s].astype(np.float32)
    return a.reshape(h, s, w, s).mean(axis=(1, 3))


def interpolation_variance_lr(inv_lr: np.ndarray, known: np.ndarray | None = None) -> np.ndarray:
    """Per grid cell, the squared largest inverse-depth difference to its 4-neighbours: how far a
    value interpolated between this cell and its neighbours can be off when the surface is not
    smooth between grid points (depth edges, thin structures). Neighbours outside ``known``
    (cells without an estimate) are left out. ``(h, w) -> (h, w)``."""
    inv = inv_lr.astype(np.float32)
    if known is not None:
        inv = np.where(known, inv, np.nan)
    pad = np.pad(inv, 1, mode="edge")
    c = pad[1:-1, 1:-1]
    diff = np.abs(np.stack([pad[1:-1, :-2], pad[1:-1, 2:], pad[:-2, 1:-1], pad[2:, 1:-1]]) - c)
    dmax = np.max(np.where(np.isnan(diff), 0.0, diff), axis=0)
    return dmax * dmax


def upsample_bilinear(a_lr: np.ndarray, H: int, W: int, s: int) -> np.ndarray:
    """Bilinear upsampling of a grid field (cell ``k`` at pixel ``s k + (s - 1) / 2``) to
    ``(H, W)``; pixels beyond the last whole block repeat the border."""
    h, w = a_lr.shape
    up = cv2.resize(a_lr.astype(np.float32), (w * s, h * s), interpolation=cv2.INTER_LINEAR)
    out = np.empty((H, W), np.float32)
    out[: h * s, : w * s] = up
    out[: h * s, w * s:] = up[:, -1:]
    out[h * s:] = out[h * s - 1: h * s]
    return out


@lru_cache(maxsize=8)
def _neighbour_layout(H: int, W: int, h: int, w: int, s: int, sigma_s: float):
    """Flat indices ``(16, H, W)`` of the 4x4 grid cells around every pixel and their spatial
    Gaussian weights (depend only on the image/grid sizes: cached)."""
    off = (s - 1) / 2.0
    gy = (np.arange(H, dtype=np.float32) - off) / s
    gx = (np.arange(W, dtype=np.float32) - off) / s
    by = np.floor(gy).astype(np.int64)
    bx = np.floor(gx).astype(np.int64)
    oy = np.array([-1, 0, 1, 2])
    ny = np.clip(by[None, :] + oy[:, None], 0, h - 1)                         # (4,H)
    nx = np.clip(bx[None, :] + oy[:, None], 0, w - 1)                         # (4,W)
    wy = np.exp(-((gy[None, :] - ny) ** 2) / (2 * sigma_s ** 2)).astype(np.float32)
    wx = np.exp(-((gx[None, :] - nx) ** 2) / (2 * sigma_s ** 2)).astype(np.float32)
    idx = (ny[:, None, :, None] * w + nx[None, :, None, :]).reshape(16, H, W).astype(np.int32)
    ws = (wy[:, None, :, None] * wx[None, :, None, :]).reshape(16, H, W)
    return idx, ws


def _neighbour_weights(guide: np.ndarray, guide_lr: np.ndarray, conf_lr: np.ndarray, s: int,
                       sigma_s: float, sigma_r: float):
    """Flat indices ``(16, H, W)`` of the 4x4 low-res neighbours of every pixel and their weights
    (spatial x range x confidence)."""
    H, W = guide.shape
    h, w = guide_lr.shape
    idx, ws = _neighbour_layout(H, W, h, w, s, float(sigma_s))
    gr = guide_lr.astype(np.float32).ravel().take(idx)
    diff = guide[None] - gr
    wr = np.exp(diff * diff * np.float32(-1.0 / (2 * sigma_r ** 2)))
    return idx, ws * wr * conf_lr.astype(np.float32).ravel().take(idx)


def joint_bilateral_upsample(inv_lr: np.ndarray, var_lr: np.ndarray, guide: np.ndarray, stride: int,
                             sigma_s: float = 0.8, sigma_r: float = 12.0,
                             spread_var: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Upsample inverse depth ``(h, w)`` and its variance to the guide's ``(H, W)``.

    Each pixel takes a weighted mean over its 4x4 nearest grid cells (grid cell ``k`` sits at pixel
    ``stride * k + (stride - 1) / 2``) with weights spatial Gaussian (``sigma_s`` in grid cells) x
    range Gaussian on the difference between the pixel's grey level and the cell's mean grey level
    (``sigma_r``) x confidence ``1 / (1 + var / median(var))``. The variance is the same weighted
    mean of the cells' (BA marginal) variances plus, with ``spread_var``, the uncertainty of the
    interpolation itself: the bilinearly upsampled :func:`interpolation_variance_lr`, large across
    depth edges. Cells without a usable estimate (infinite variance: nothing observed them, or no
    positive inverse depth) take no part, and a pixel with such a cell among the (up to) four of its
    bilinear support has no direct observation: its variance is ``inf`` whatever the fraction of
    unobserved cells in the frame.
    """
    g = guide.astype(np.float32)
    h, w = inv_lr.shape
    glr = block_mean(g, h, w, stride)
    v = np.where(np.isfinite(var_lr), var_lr, np.inf)
    finite = np.isfinite(v) & (inv_lr > 0)
    vref = float(np.median(v[finite])) if finite.any() else 1.0
    conf = np.where(finite, 1.0 / (1.0 + v / max(vref, 1e-30)), 0.0)
    idx, wt = _neighbour_weights(g, glr, conf, stride, sigma_s, sigma_r)
    sw = wt.sum(0)
    ok = sw > 1e-20
    sws = np.where(ok, sw, 1.0)
    inv = (wt * inv_lr.astype(np.float32).ravel().take(idx)).sum(0) / sws
    vv = np.where(finite, v, 0.0).astype(np.float32).ravel().take(idx)
    var = (wt * vv).sum(0) / sws
    if spread_var:
        var = var + upsample_bilinear(interpolation_variance_lr(inv_lr, finite), *g.shape, stride)
    ok &= _observed_support(finite, *g.shape, stride)
    inv = np.where(ok, inv, 0.0)
    var = np.where(ok, var, np.inf)
    return inv.astype(np.float32), var.astype(np.float32)


def _observed_support(finite_lr: np.ndarray, H: int, W: int, stride: int) -> np.ndarray:
    """``(H, W)``: every grid cell of the pixel's bilinear support has an estimate."""
    return upsample_bilinear((~finite_lr).astype(np.float32), H, W, stride) <= 0.0


def upsample_reference(inv_lr, var_lr, guide, stride, sigma_s=0.8, sigma_r=12.0, spread_var=True):
    """Per-pixel loop version of :func:`joint_bilateral_upsample` (tests only: slow)."""
    g = guide.astype(np.float32)
    h, w = inv_lr.shape
    H, W = g.shape
    glr = block_mean(g, h, w, stride)
    v = np.where(np.isfinite(var_lr), var_lr, np.inf)
    finite = np.isfinite(v) & (inv_lr > 0)
    vref = float(np.median(v[finite]))
    inv_out = np.zeros((H, W), np.float64)
    var_out = np.zeros((H, W), np.float64)
    off = (stride - 1) / 2.0
    for y in range(H):
        for x in range(W):
            cy, cx = (y - off) / stride, (x - off) / stride
            by, bx = int(np.floor(cy)), int(np.floor(cx))
            num = den = vnum = 0.0
            vals, wts = [], []
            for oy in (-1, 0, 1, 2):
                for ox in (-1, 0, 1, 2):
                    yy = min(max(by + oy, 0), h - 1)
                    xx = min(max(bx + ox, 0), w - 1)
                    c = 1.0 / (1.0 + v[yy, xx] / vref) if finite[yy, xx] else 0.0
                    wgt = (np.exp(-((cy - yy) ** 2 + (cx - xx) ** 2) / (2 * sigma_s ** 2))
                           * np.exp(-((g[y, x] - glr[yy, xx]) ** 2) / (2 * sigma_r ** 2)) * c)
                    num += wgt * inv_lr[yy, xx]
                    den += wgt
                    vnum += wgt * (v[yy, xx] if finite[yy, xx] else 0.0)
                    vals.append(inv_lr[yy, xx])
                    wts.append(wgt)
            m = num / den
            inv_out[y, x] = m
            var_out[y, x] = vnum / den
    if spread_var:
        var_out += upsample_bilinear(interpolation_variance_lr(inv_lr, finite), H, W, stride)
    for y in range(H):
        for x in range(W):
            # the cells of the pixel's bilinear support (rows/columns beyond the last whole block
            # repeat the border): one without an estimate leaves the pixel unknown
            cy = (min(y, h * stride - 1) - off) / stride
            cx = (min(x, w * stride - 1) - off) / stride
            y0, x0 = int(np.floor(cy)), int(np.floor(cx))
            rows = {min(max(y0, 0), h - 1)} | ({min(max(y0 + 1, 0), h - 1)} if cy > y0 else set())
            cols = {min(max(x0, 0), w - 1)} | ({min(max(x0 + 1, 0), w - 1)} if cx > x0 else set())
            if not all(finite[r, c] for r in rows for c in cols):
                inv_out[y, x] = 0.0
                var_out[y, x] = np.inf
    return inv_out.astype(np.float32), var_out.astype(np.float32)


def validity_mask(inv: np.ndarray, inv_var: np.ndarray, guide: np.ndarray, median_depth: float,
                  max_rel_std: float, max_depth_factor: float, far_factor: float,
                  textureless_grad: float) -> np.ndarray:
    """Pixels whose depth is usable for mapping:

    * positive, finite inverse depth,
    * relative inverse-depth std ``sqrt(var) / inv`` below ``max_rel_std`` (drops uncertain pixels,
      which include depth edges through the interpolation spread),
    * depth below ``max_depth_factor`` x the keyframe's median depth (excessive depth),
    * not (textureless and beyond ``far_factor`` x median depth): flat far regions such as sky,
      where the flow carries no depth information. "Textureless": mean gradient magnitude in a 9x9
      window below ``textureless_grad`` grey levels / px.
    """
    ok = np.isfinite(inv) & (inv > 0) & np.isfinite(inv_var)
    rel = np.sqrt(np.maximum(inv_var, 0)) / np.maximum(inv, 1e-12)
    ok &= rel < max_rel_std
    depth = np.where(inv > 0, 1.0 / np.maximum(inv, 1e-12), np.inf)
    ok &= depth < max_depth_factor * median_depth
    g = guide.astype(np.float32)
    gx = cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3) / 8.0
    gy = cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3) / 8.0
    gm = cv2.blur(np.sqrt(gx * gx + gy * gy), (9, 9))
    ok &= ~((gm < textureless_grad) & (depth > far_factor * median_depth))
    return ok


def dense_depth(inv_lr: np.ndarray, var_lr: np.ndarray, guide: np.ndarray, stride: int,
                sigma_s: float, sigma_r: float, spread_var: bool, max_rel_std: float,
                max_depth_factor: float, far_factor: float, textureless_grad: float) -> DenseDepth:
    """Upsample and mask a keyframe's BA depth. ``guide`` is the grey image (working resolution)."""
    inv, var = joint_bilateral_upsample(inv_lr, var_lr, guide, stride, sigma_s, sigma_r, spread_var)
    good_lr = (inv_lr > 0) & np.isfinite(var_lr)
    med = float(np.median(1.0 / inv_lr[good_lr])) if good_lr.any() else 1.0
    valid = validity_mask(inv, var, guide, med, max_rel_std, max_depth_factor, far_factor,
                          textureless_grad)
    depth = np.where(valid, 1.0 / np.maximum(inv, 1e-12), 0.0).astype(np.float32)
    return DenseDepth(inv, var, depth, valid)
