"""Flow targets for dense BA: a :class:`FlowEstimator` interface, the classical default (OpenCV
DIS) and an optional TorchScript plug-in, plus the reduction of dense flow to the 1/8 BA grid with
per-block confidence weights.

The flow estimator stands in for the learned update operator of DROID-SLAM / VINGS-Mono: run
around the flow induced by the current poses and depths (``init``), its output minus the induced
flow is the residual revision ``r_ij``; its confidence replaces the learned weights ``w_ij``.
"""
from __future__ import annotations

from abc import ABC, abstractmethod
from pathlib import Path
from typing import NamedTuple, Optional

import cv2
import numpy as np

from ..errors import ConfigError, InputError
from .config import FrontendConfig

_DIS_PRESETS = {"ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST,
                "fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
                "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM}


class FlowEstimator(ABC):
    """Dense optical flow between two grey images of the working resolution.

    ``flow(img0, img1, init)``: ``img0, img1`` uint8 ``(H, W)``; ``init`` optional float32
    ``(H, W, 2)`` initial flow (pixels, ``img0 -> img1``; estimators may ignore it). Returns float32
    ``(H, W, 2)``: for each pixel ``x`` of ``img0`` the displacement to its match ``x + f`` in ``img1``.
    """

    name: str = "flow"

    @abstractmethod
    def flow(self, img0: np.ndarray, img1: np.ndarray, init: Optional[np.ndarray] = None) -> np.ndarray:
        ...


class DISFlow(FlowEstimator):
    """OpenCV Dense Inverse Search (Kroeger et al. 2016) with variational refinement; uses ``init``
    as the coarse-level initialisation. No weights, deterministic."""

    name = "dis"

    def __init__(self, preset: str = "medium", finest_scale: Optional[int] = None):
        if preset not in _DIS_PRESETS:
            raise ConfigError(f"frontend.dis_preset: unknown preset {preset!r}; "
                              f"known: {', '.join(_DIS_PRESETS)}")
        self._dis = cv2.DISOpticalFlow_create(_DIS_PRESETS[preset])
        if finest_scale is not None:
            self._dis.setFinestScale(int(finest_scale))

    def flow(self, img0: np.ndarray, img1: np.ndarray, init: Optional[np.ndarray] = None) -> np.ndarray:
        a = np.ascontiguousarray(img0, dtype=np.uint8)
        b = np.ascontiguousarray(img1, dtype=np.uint8)
        if init is None:
            return self._dis.calc(a, b, None)
        return self._dis.calc(a, b, np.ascontiguousarray(init, dtype=np.float32).copy())


class TorchScriptFlow(FlowEstimator):
    """A learned flow network (e.g. RAFT) exported with TorchScript, loaded from a local file.

    Contract of the scripted module: ``forward(img0, img1) -> flow`` with ``img0, img1`` float32
    ``(1, 3, H, W)`` in ``[0, 255]`` and ``flow`` ``(1, 2, H, W)`` (or a list/tuple whose last
    element is that). ``init`` is ignored. Nothing is ever downloaded: a missing file is a
    :class:`ConfigError`.
    """

    name = "torchscript"

    def __init__(self, path: str):
        import torch
        p = Path(path)
        if not p.is_file():
            raise ConfigError(f"frontend.flow_weights_path: {p} not found (learned flow models are "
                              f"loaded from a local TorchScript file only)")
        try:
            self._model = torch.jit.load(str(p), map_location="cpu").eval()
        except Exception as e:  # torch raises several types for bad archives
            raise ConfigError(f"frontend.flow_weights_path: {p} is not a TorchScript model: {e}") from None
        self._torch = torch

    def flow(self, img0: np.ndarray, img1: np.ndarray, init: Optional[np.ndarray] = None) -> np.ndarray:
        torch = self._torch

        def prep(img):
            t = torch.from_numpy(np.asarray(img, dtype=np.float32))
            return t[None, None].expand(1, 3, *t.shape).contiguous()

        with torch.no_grad():
            out = self._model(prep(img0), prep(img1))
        if isinstance(out, (list, tuple)):
            out = out[-1]
        H, W = img0.shape[:2]
        if tuple(out.shape) != (1, 2, H, W):
            raise InputError(f"frontend.flow_weights_path: model returned shape {tuple(out.shape)}, "
                             f"expected (1, 2, {H}, {W})")
        return out[0].permute(1, 2, 0).numpy().astype(np.float32)


def _grid(H: int, W: int):
    ys, xs = np.mgrid[0:H, 0:W].astype(np.float32)
    return xs, ys


def compose_flow(base: np.ndarray, residual: np.ndarray) -> np.ndarray:
    """``f(x) = r(x) + base(x + r(x))``: the flow ``i -> j`` when ``residual`` was measured from
    ``i`` to ``j`` warped by ``base`` (``W(y) = I_j(y + base(y))``)."""
    H, W = base.shape[:2]
    xs, ys = _grid(H, W)
    b = cv2.remap(base, xs + residual[..., 0], ys + residual[..., 1], cv2.INTER_LINEAR,
                  borderMode=cv2.BORDER_REPLICATE)
    return (residual + b).astype(np.float32)


def invert_flow(f: np.ndarray, iters: int = 3) -> np.ndarray:
    """Approximate inverse ``g`` of a smooth flow (``g(y) = -f(y + g(y))``, fixed point)."""
    H, W = f.shape[:2]
    xs, ys = _grid(H, W)
    g = -f
    for _ in range(iters):
        g = -cv2.remap(f, xs + g[..., 0], ys + g[..., 1], cv2.INTER_LINEAR,
                       borderMode=cv2.BORDER_REPLICATE)
    return g


def flow_around(est: FlowEstimator, img_i: np.ndarray, img_j: np.ndarray,
                base: Optional[np.ndarray]) -> np.ndarray:
    """Flow ``i -> j`` refined around a prior flow ``base`` (e.g. induced by the current poses and
    depths): ``I_j`` is warped by ``base`` so the estimator only measures the residual revision
    ``r_ij`` (small, robust to large displacements and perspective distortion), then the two are
    composed. ``base=None``: plain estimation."""
    if base is None:
        return est.flow(img_i, img_j, None)
    H, W = img_i.shape[:2]
    xs, ys = _grid(H, W)
    warped = cv2.remap(img_j, xs + base[..., 0], ys + base[..., 1], cv2.INTER_LINEAR,
                       borderMode=cv2.BORDER_REPLICATE)
    return compose_flow(base, est.flow(img_i, warped, None))


def make_flow_estimator(cfg: FrontendConfig) -> FlowEstimator:
    if cfg.flow_method == "dis":
        return DISFlow(cfg.dis_preset, cfg.dis_finest_scale)
    if cfg.flow_method == "torchscript":
        return TorchScriptFlow(cfg.flow_weights_path)
    raise ConfigError(f"frontend.flow_method: unknown method {cfg.flow_method!r}")


# ------------------------------------------------------------------------ grid reduction


class GridFlow(NamedTuple):
    """Flow targets on the BA grid of image ``i`` towards image ``j`` (row-major, ``P = h*w``)."""

    target: np.ndarray   #: (P, 2) float64 matched position in j (working-resolution px)
    weight: np.ndarray   #: (P,) float64 confidence in [0, 1]
    mean_flow: float     #: confidence-weighted mean flow magnitude (working-resolution px)
    conf_frac: float     #: confident mass: mean weight over the grid (1 = every pixel fully trusted)


def _blocks(a: np.ndarray, h: int, w: int, s: int) -> np.ndarray:
    """``(H, W, ...)`` -> block sums ``(h, w, ...)`` over ``s x s`` blocks (top-left crop)."""
    a = a[: h * s, : w * s]
    return a.reshape(h, s, w, s, *a.shape[2:]).sum(axis=(1, 3))


def texture_weight(img: np.ndarray, h: int, w: int, s: int, tau: float) -> np.ndarray:
    """Per-block texture confidence from the structure tensor's smaller eigenvalue (grey^2/px^2):
    ``lam_min / (lam_min + tau)``. Flat blocks (sky, walls) give ~0."""
    g = img.astype(np.float32)
    gx = cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3) / 8.0
    gy = cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3) / 8.0
    n = float(s * s)
    sxx = _blocks(gx * gx, h, w, s) / n
    syy = _blocks(gy * gy, h, w, s) / n
    sxy = _blocks(gx * gy, h, w, s) / n
    lmin = 0.5 * (sxx + syy) - np.sqrt(0.25 * (sxx - syy) ** 2 + sxy ** 2)
    lmin = np.maximum(lmin, 0.0)
    return (lmin / (lmin + tau)).astype(np.float64)


def gain_offset(src: np.ndarray, dst: np.ndarray, mask: np.ndarray, min_px: int = 20) -> tuple[float, float]:
    """Robust global brightness model ``dst ~ a src + b`` between two aligned grey images (grey
    levels), from the samples of ``mask`` that are unclipped in both: ``a`` the ratio of the
    interquartile ranges (clamped to 0.5..2), ``b`` the median residual. ``(1, 0)`` when fewer than
    ``min_px`` samples qualify. Give it block means, not pixels: a bilinear warp blurs ``src``,
    which shrinks its pixel spread (a biased ``a`` of ~1.04 on a scene of constant exposure), while
    block means are unchanged by the blur."""
    m = mask & (src > 3) & (src < 252) & (dst > 3) & (dst < 252)
    if int(m.sum()) < min_px:
        return 1.0, 0.0
    s, d = src[m], dst[m]
    qs = np.percentile(s, (25.0, 75.0))
    qd = np.percentile(d, (25.0, 75.0))
    a = float(np.clip((qd[1] - qd[0]) / max(qs[1] - qs[0], 1.0), 0.5, 2.0))
    return a, float(np.median(d - a * s))


def grid_flow(flow_ij: np.ndarray, flow_ji: Optional[np.ndarray], img_i: np.ndarray,
              img_j: np.ndarray, grid_uv: np.ndarray, stride: int, cfg: FrontendConfig,
              tex_i: Optional[np.ndarray] = None) -> GridFlow:
    """Reduce dense flow ``i -> j`` to the BA grid with confidence weights.

    Per pixel: forward-backward consistency ``|f_ij(x) + f_ji(x + f_ij(x))|`` (if ``flow_ji`` is
    given), photometric error ``|a I_j(x + f) + b - I_i(x)|`` (global gain/offset ``a, b`` from
    :func:`gain_offset`: exposure changes) and in-bounds test, each mapped to
    ``1 / (1 + (e / sigma)^2)``. Per ``stride`` block: the confidence-weighted mean flow (assigned to
    the block centre), times the block's mean confidence, texture weight, the block NCC between
    ``I_i`` and the flow-warped ``I_j`` (mapped linearly from ``ncc_min..1`` to ``0..1``) and a
    penalty on the flow spread inside the block (depth edges).
    """
    H, W = img_i.shape[:2]
    h, w = H // stride, W // stride
    # a non-finite flow (a learned plug-in's overflow) is no measurement: confidence 0 there, and
    # a finite stand-in so that no NaN reaches the block means or the BA targets
    fin = np.isfinite(flow_ij).all(-1)
    if not fin.all():
        flow_ij = np.where(fin[..., None], flow_ij, 0.0).astype(np.float32)
    ys, xs = np.mgrid[0:H, 0:W].astype(np.float32)
    mx = xs + flow_ij[..., 0]
    my = ys + flow_ij[..., 1]
    inb = (mx >= 0) & (mx <= W - 1) & (my >= 0) & (my <= H - 1)
    c = (inb & fin).astype(np.float32)
    if flow_ji is not None:
        back = cv2.remap(flow_ji, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        e2 = ((flow_ij + back) ** 2).sum(-1)
        e2 = np.where(np.isfinite(e2), e2, np.inf)      # no valid backward flow: inconsistent
        c = c / (1.0 + e2 / cfg.fb_sigma_px ** 2)
    warped = cv2.remap(img_j.astype(np.float32), mx, my, cv2.INTER_LINEAR,
                       borderMode=cv2.BORDER_REPLICATE)
    gi = img_i.astype(np.float32)
    n = float(stride * stride)
    mi = _blocks(gi, h, w, stride) / n
    mw = _blocks(warped, h, w, stride) / n
    # a global brightness change between the images (auto exposure, lights) is not a matching
    # error: compare after the gain/offset that maps I_j onto I_i, fitted on the block means of
    # fully in-bounds blocks (the block NCC below is invariant to it anyway)
    a, b = gain_offset(mw, mi, _blocks(inb.astype(np.float32), h, w, stride) >= n - 0.5)
    ph = a * warped + b - gi
    c = c / (1.0 + (ph * ph) / cfg.photo_sigma ** 2)
    # block zero-mean NCC between I_i and the warped I_j: rejects flows that are consistent both
    # ways but wrong (self-similar fine texture matched at the wrong place)
    vi = np.maximum(_blocks(gi * gi, h, w, stride) / n - mi * mi, 0)
    vw = np.maximum(_blocks(warped * warped, h, w, stride) / n - mw * mw, 0)
    cov = _blocks(gi * warped, h, w, stride) / n - mi * mw
    ncc = cov / np.sqrt(vi * vw + 1e-6)
    c_ncc = np.clip((ncc - cfg.ncc_min) / (1.0 - cfg.ncc_min), 0.0, 1.0)
    sc = _blocks(c, h, w, stride)
    scf = _blocks(c[..., None] * flow_ij, h, w, stride)
    scf2 = _blocks(c * (flow_ij ** 2).sum(-1), h, w, stride)
    denom = np.maximum(sc, 1e-6)
    mean_f = scf / denom[..., None]
    spread = np.maximum(scf2 / denom - (mean_f ** 2).sum(-1), 0.0)
    if tex_i is None:
        tex_i = texture_weight(img_i, h, w, stride, cfg.texture_tau)
    wgt = (sc / n) * tex_i * c_ncc / (1.0 + spread / cfg.block_spread_sigma_px ** 2)
    wgt = np.where(sc > 1e-3, wgt, 0.0).reshape(-1).astype(np.float64)
    mf = mean_f.reshape(-1, 2).astype(np.float64)
    target = grid_uv + mf
    conf = wgt > cfg.min_weight
    mag = np.linalg.norm(mf, axis=1)
    mean_flow = float((wgt * mag).sum() / wgt.sum()) if wgt.sum() > 0 else 0.0
    wgt = np.where(conf, wgt, 0.0)
    return GridFlow(target, wgt, mean_flow, float(wgt.mean()))


def dense_from_grid(grid_disp: np.ndarray, h: int, w: int, H: int, W: int, stride: int) -> np.ndarray:
    """Upsample a ``(h*w, 2)`` grid displacement (block centres) to a dense ``(H, W, 2)`` float32
    field (bilinear, edges replicated) - the DIS initialisation from induced flow."""
    g = grid_disp.reshape(h, w, 2).astype(np.float32)
    up = cv2.resize(g, (w * stride, h * stride), interpolation=cv2.INTER_LINEAR)
    out = np.empty((H, W, 2), np.float32)
    out[: h * stride, : w * stride] = up
    if W > w * stride:
        out[: h * stride, w * stride:] = up[:, -1:]
    if H > h * stride:
        out[h * stride:] = out[h * stride - 1: h * stride]
    return out
