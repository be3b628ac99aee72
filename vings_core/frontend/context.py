"""What the stages of the front end share: the configuration, the BA grid of the working camera,
the flow estimators and the flow measurements made with them, the counters and the event log.

The BA grid is every ``STRIDE``-th pixel of the working resolution (``h x w = P`` points, ``uv``
in working-resolution pixels). Poses are ``T_cw`` (world-to-camera) ``(4, 4)`` float64 tensors;
inverse depths are per grid point, in 1/(map units).
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Optional

import cv2
import numpy as np
import torch

from ..types import CameraModel
from .config import FrontendConfig
from .flow import (DISFlow, FlowEstimator, GridFlow, compose_flow, dense_from_grid, flow_around, grid_flow,
                   invert_flow, make_flow_estimator, texture_weight)
from .projective import Intrinsics, grid_points, normalized_rays, project_edges
from .seed import SeedFeatures, SparseMatches, match_features
from ..profiling import profiled

DT = torch.float64
STRIDE = 8


@dataclass
class StampedPose:
    """A frame's pose: ``stamp`` (ns) and ``T_cw`` (world-to-camera, ``(4, 4)`` float64)."""

    stamp: int
    T_cw: torch.Tensor


@dataclass
class FlowChain:
    """Dense flow ``(H, W, 2)`` (working-resolution px) from the image of frame ``stamp`` (a
    keyframe, or the reference frame while waiting) to the last frame tracked against it, and that
    frame's grey image: chained with the next frame-to-frame flow it predicts the flow ``stamp`` ->
    next frame (:meth:`FrontendContext.chained_flow`)."""

    stamp: int
    flow: np.ndarray
    gray: np.ndarray


@dataclass
class FlowPair:
    """Flow between two images both ways: ``fwd``/``bwd`` reduced to the BA grid (``bwd`` is
    ``None`` when only the forward one was asked for), ``f01``/``f10`` dense ``(H, W, 2)``."""

    fwd: GridFlow
    bwd: Optional[GridFlow]
    f01: np.ndarray
    f10: np.ndarray


class FrontendContext:
    """Configuration, camera grid, flow estimation, counters and the event log of one front end.

    ``stats`` holds the counters and timings (s) reported by ``Frontend.status``; ``events`` the
    state changes in words; ``reason`` says in words why the front end is in its current state.
    """

    def __init__(self, cfg: FrontendConfig, camera: CameraModel, flow: Optional[FlowEstimator] = None):
        self.cfg = cfg
        self.camera = camera
        self.W, self.H = camera.width, camera.height
        self.K = Intrinsics(camera.fx, camera.fy, camera.cx, camera.cy)
        self.Kmat = camera.K
        self.h, self.w, self.uv = grid_points(self.W, self.H, STRIDE)
        self.P = self.uv.shape[0]
        self.uv_np = self.uv.numpy()
        self.rays = normalized_rays(self.uv, self.K)
        self.flow_est = flow if flow is not None else make_flow_estimator(cfg)
        self.chain_est = DISFlow(cfg.chain_preset, None)
        self.info_scale = 1.0 / cfg.flow_sigma_px ** 2
        self.reason = "waiting for the first frame"
        self.events: list[str] = []
        self.stats = {"frames": 0, "keyframes": 0, "segments": 1, "lost_frames": 0, "imu_only_frames": 0,
                      "jumps": 0, "relocalisations": 0, "seeded": 0, "dynamic_masks": 0, "dynamic_masks_late": 0, "t_flow": 0.0, "t_track": 0.0, "t_ba": 0.0,
                      "t_emit": 0.0, "t_seed": 0.0, "t_total": 0.0}
        self.max_mean_flow_lr = 0.0
        self.motion_detected = False

    @profiled("tracking", "flow")
    def flow_pair(self, g0: np.ndarray, g1: np.ndarray, init01: Optional[np.ndarray] = None,
                  init10: Optional[np.ndarray] = None, tex0: Optional[np.ndarray] = None,
                  tex1: Optional[np.ndarray] = None, both: bool = True) -> FlowPair:
        """Flow ``g0 -> g1`` and ``g1 -> g0`` (grey images), each refined around its prior dense
        flow (if any; a missing backward prior is the inverted forward one), reduced to the grid
        (``tex0``/``tex1``: texture weights of the grid, see :meth:`texture`)."""
        t = time.perf_counter()
        if init01 is not None and init10 is None:
            init10 = invert_flow(init01)
        f01 = flow_around(self.flow_est, g0, g1, init01)
        f10 = flow_around(self.flow_est, g1, g0, init10)
        gf01 = grid_flow(f01, f10, g0, g1, self.uv_np, STRIDE, self.cfg, tex0)
        gf10 = grid_flow(f10, f01, g1, g0, self.uv_np, STRIDE, self.cfg, tex1) if both else None
        self.stats["t_flow"] += time.perf_counter() - t
        return FlowPair(gf01, gf10, f01, f10)

    def seed_matches(self, g0: np.ndarray, g1: np.ndarray) -> Optional[SparseMatches]:
        """Sparse feature matches between two grey images for seeding the dense flow
        (``seed_features``); ``None`` when seeding is off. Timed in ``stats['t_seed']``."""
        kind = SeedFeatures(self.cfg.seed_features)
        if kind == SeedFeatures.NONE:
            return None
        t = time.perf_counter()
        m = match_features(g0, g1, kind, self.cfg.seed_max_features)
        self.stats["t_seed"] += time.perf_counter() - t
        return m

    def texture(self, gray: np.ndarray) -> np.ndarray:
        """``(h, w)`` texture weight of the grid points of a grey image."""
        return texture_weight(gray, self.h, self.w, STRIDE, self.cfg.texture_tau)

    @profiled("tracking", "flow chain")
    def chained_flow(self, chain: FlowChain, gray: np.ndarray) -> np.ndarray:
        """Prior dense flow ``chain.stamp`` -> current frame: the stored flow to the previous frame
        chained with a plain frame-to-frame flow (small motion, so reliable even for fast forward
        motion)."""
        t = time.perf_counter()
        step = self.chain_est.flow(chain.gray, gray, None)
        self.stats["t_flow"] += time.perf_counter() - t
        return compose_flow(step, chain.flow)

    def filled_depth(self, d: torch.Tensor, var: Optional[torch.Tensor]) -> torch.Tensor:
        """Inverse depth ``d`` ``(P,)`` for predicting flow: grid points whose depth is unknown
        (relative std from the variance ``var`` above 0.3, e.g. never observed) are replaced by a
        Gaussian-weighted average of known ones."""
        if var is None:
            return d
        dd = d.numpy().reshape(self.h, self.w)
        good = self.known_depth(d, var)
        if good.all():
            return d
        if good.sum() < 10:
            return d
        c = good.astype(np.float32)
        num = cv2.GaussianBlur((dd * c).astype(np.float32), (0, 0), 3.0)
        den = cv2.GaussianBlur(c, (0, 0), 3.0)
        fill = np.where(den > 1e-3, num / np.maximum(den, 1e-6), float(np.median(dd[good])))
        return torch.from_numpy(np.where(good, dd, fill).reshape(-1).astype(np.float64))

    def known_depth(self, d: torch.Tensor, var: Optional[torch.Tensor]) -> np.ndarray:
        """``(h, w)`` bool: grid points whose inverse depth ``d`` is known, i.e. positive with a
        relative std (from the variance ``var``) below 0.3; every positive one without ``var``."""
        dd = d.numpy().reshape(self.h, self.w)
        if var is None:
            return dd > 0
        std = np.sqrt(np.maximum(var.numpy(), 0)).reshape(self.h, self.w)
        return (dd > 0) & (std < 0.3 * np.maximum(dd, 1e-12))

    def induced_init(self, T_i: torch.Tensor, d_i: torch.Tensor, T_j: torch.Tensor) -> np.ndarray:
        """Dense flow ``(H, W, 2)`` from camera ``i`` (pose ``T_i``, grid inverse depth ``d_i``) to
        camera ``j`` (``T_j``) induced by the geometry (0 where a point falls behind a camera)."""
        T = torch.stack([T_i, T_j])
        uvj, valid = project_edges(T, d_i[None].expand(2, -1), torch.tensor([0]), torch.tensor([1]),
                                   self.rays, self.K)
        disp = (uvj[0] - self.uv).numpy()
        disp[~valid[0].numpy()] = 0.0
        disp = np.clip(disp, -self.W, self.W)
        return dense_from_grid(disp, self.h, self.w, self.H, self.W, STRIDE)

    def induced_mean_flow(self, T_kf: torch.Tensor, d_kf: torch.Tensor, T_cw: torch.Tensor) -> float:
        """Mean flow (working-resolution px) the pose ``T_cw`` induces on the grid of a keyframe
        (pose ``T_kf``, inverse depth ``d_kf``), DROID-SLAM's keyframe distance: all grid points in
        front of the camera, no confidence weighting."""
        T = torch.stack([T_kf, T_cw])
        uvj, valid = project_edges(T, d_kf[None].expand(2, -1), torch.tensor([0]), torch.tensor([1]),
                                   self.rays, self.K)
        if not valid.any():
            return float("inf")
        return float(torch.linalg.norm(uvj[0] - self.uv, dim=-1)[valid[0]].mean())

    def d_bounds(self, d: torch.Tensor) -> tuple[float, float]:
        """Inverse-depth clamp ``(low, high)`` for a BA, relative to the median of ``d``'s positive
        entries (``min_inv_depth``, ``max_inv_depth``)."""
        med = float(d[d > 0].median()) if (d > 0).any() else 1.0
        return self.cfg.min_inv_depth * med, self.cfg.max_inv_depth * med
