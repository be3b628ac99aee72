"""Per-frame tracking against a keyframe: the constant-velocity prior, flow keyframe -> frame
(chained from the previous frame's), motion-only BA, the acceptance checks, the pose covariance and
the keyframe decision's overlap reference.

Poses are ``T_cw`` (world-to-camera) ``(4, 4)`` float64 tensors.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Optional

import numpy as np
import torch

from ..geometry import orthonormalize_pose, pose_inverse, se3_exp, se3_log
from . import ba as BA
from .context import DT, STRIDE, FlowChain, FrontendContext, StampedPose
from .flow import GridFlow, flow_around, grid_flow, invert_flow
from .pose_buffer import PoseBuffer
from .seed import pnp_seed
from .projective import adjoint
from .window import WindowKeyframe

#: longest extrapolation of the constant-velocity prior, in units of the last frame interval
MAX_VELOCITY_RATIO = 8.0


@dataclass
class TrackFlow:
    """Dense flow ``(H, W, 2)`` of the latest tracking attempt, keyframe ``kf_stamp`` -> frame, and
    the prior flow it was refined around."""

    kf_stamp: int
    flow: np.ndarray
    init: Optional[np.ndarray]


@dataclass
class KeyframeOverlap:
    """Mean flow confidence of the first frame tracked against keyframe ``stamp`` (the reference
    for the overlap-loss keyframe test)."""

    stamp: int
    conf_frac: float


@dataclass
class Track:
    """A frame tracked against keyframe ``kf``: grid flow keyframe -> frame (``fwd``) and back
    (``bwd``; ``None`` unless forward-backward checked), and the motion-only BA result."""

    kf: WindowKeyframe
    fwd: GridFlow
    bwd: Optional[GridFlow]
    motion: BA.MotionResult


def tangent_covariance(T_cw: torch.Tensor, H: torch.Tensor) -> Optional[np.ndarray]:
    """6x6 covariance of the left tangent ``[rho, phi]`` of ``T_wc`` from the motion-only BA's
    information ``H`` on ``T_cw`` (relative to the fixed keyframe); ``None`` if singular."""
    try:
        S = torch.linalg.inv(H + torch.eye(6, dtype=DT) * 1e-9 * torch.diagonal(H).mean())
    except RuntimeError:
        return None
    A = adjoint(pose_inverse(T_cw))
    return (A @ S @ A.T).numpy()


class MotionTracker:
    """Tracks frames against window keyframes. ``last``/``prev``: the last two tracked poses (the
    motion model); ``chain``: flow from the newest keyframe to the last tracked frame; ``flow``:
    the latest tracking attempt's dense flow."""

    def __init__(self, ctx: FrontendContext):
        self.ctx = ctx
        self.last: Optional[StampedPose] = None
        self.prev: Optional[StampedPose] = None
        self.chain: Optional[FlowChain] = None
        self.overlap: Optional[KeyframeOverlap] = None
        self.flow: Optional[TrackFlow] = None

    def start(self, prev: StampedPose, last: StampedPose, chain: FlowChain) -> None:
        """Motion model and flow chain of a freshly initialised window."""
        self.prev, self.last, self.chain = prev, last, chain

    def reset(self) -> None:
        """Forget the motion model and the flow chain (a new segment)."""
        self.last = self.prev = None
        self.chain = None

    def refresh(self, buffer: PoseBuffer) -> None:
        """Re-read the last two tracked poses from the buffer (after a pose correction)."""
        if self.last is not None:
            self.last = StampedPose(self.last.stamp, torch.from_numpy(buffer.T_cw(self.last.stamp)))
        if self.prev is not None:
            self.prev = StampedPose(self.prev.stamp, torch.from_numpy(buffer.T_cw(self.prev.stamp)))

    def predict(self, stamp_ns: int, T_kf: torch.Tensor) -> torch.Tensor:
        """Constant-velocity prediction of ``T_cw`` at ``stamp_ns`` (``T_kf``, the newest keyframe's
        pose, without a tracked frame), re-orthonormalised: composing poses repeatedly would
        otherwise let rounding errors grow geometrically. The motion between the last two tracked
        frames is scaled by the time ratio, so dropped or lost frames in between (or uneven frame
        intervals) do not make the prior a few frame-steps off."""
        if self.last is None:
            return T_kf.clone()
        if self.prev is None:
            return self.last.T_cw.clone()
        delta = self.last.T_cw @ pose_inverse(self.prev.T_cw)
        span = self.last.stamp - self.prev.stamp
        ratio = (int(stamp_ns) - self.last.stamp) / span if span > 0 else 1.0
        # past a few intervals the motion model says little and its error is multiplied: hold it
        ratio = min(ratio, MAX_VELOCITY_RATIO)
        if ratio != 1.0:
            delta = se3_exp(ratio * se3_log(delta))
        return orthonormalize_pose(delta @ self.last.T_cw)

    def track_against(self, kf: WindowKeyframe, gray: np.ndarray, T_pred: torch.Tensor,
                      tex: np.ndarray, use_chain: bool = True) -> Track:
        """Flow ``kf`` -> frame (grey image ``gray``, grid texture ``tex``) around the chained
        (``use_chain`` and the chain starts at ``kf``) or the induced prior, then motion-only BA
        from ``T_pred``."""
        ctx, cfg = self.ctx, self.ctx.cfg
        if use_chain and self.chain is not None and self.chain.stamp == kf.stamp:
            init = ctx.chained_flow(self.chain, gray)
        else:
            init = ctx.induced_init(kf.T_cw, ctx.filled_depth(kf.d, kf.var), T_pred)
        if cfg.track_fb_check:
            pair = ctx.flow_pair(kf.gray, gray, init01=init, tex0=kf.tex, tex1=tex)
            gf, gb, f01 = pair.fwd, pair.bwd, pair.f01
        else:
            # forward flow only; the backward flow (for the keyframe edges) is computed only if
            # this frame becomes a keyframe (see complete_pair)
            t = time.perf_counter()
            f01 = flow_around(ctx.flow_est, kf.gray, gray, init)
            gf = grid_flow(f01, None, kf.gray, gray, ctx.uv_np, STRIDE, cfg, kf.tex)
            gb = None
            ctx.stats["t_flow"] += time.perf_counter() - t
        self.flow = TrackFlow(kf.stamp, f01, init)
        t = time.perf_counter()
        w = gf.weight if kf.static is None else gf.weight * kf.static     # the eraser's mask: weight 0
        mo = BA.motion_only(kf.T_cw[None], kf.d[None], ctx.rays,
                            torch.from_numpy(gf.target)[None],
                            torch.from_numpy(w)[None] * ctx.info_scale, ctx.K, T_pred,
                            iters=cfg.track_iters, loss=cfg.robust_loss,
                            delta=cfg.robust_delta_px,
                            d_var=None if kf.var is None else kf.var[None])
        ctx.stats["t_track"] += time.perf_counter() - t
        return Track(kf, gf, gb, mo)

    def track_seeded(self, kf: WindowKeyframe, gray: np.ndarray, tex: np.ndarray) -> Optional[Track]:
        """Tracking for motions the dense flow cannot follow: sparse feature matches ``kf`` -> frame,
        PnP on the keyframe's known depths (:meth:`FrontendContext.known_depth`),
        then the dense flow around the flow that pose induces and motion-only BA from it. ``None``
        when seeding is off or no pose is found (the result still has to pass :meth:`check`)."""
        ctx, cfg = self.ctx, self.ctx.cfg
        m = ctx.seed_matches(kf.gray, gray)
        if m is None:
            return None
        t = time.perf_counter()
        d = kf.d.numpy().reshape(ctx.h, ctx.w)
        seed = pnp_seed(m, d, ctx.known_depth(kf.d, kf.var), ctx.Kmat, kf.T_cw.numpy(), STRIDE, cfg.seed_min_inliers,
                        cfg.seed_ransac_px)
        ctx.stats["t_seed"] += time.perf_counter() - t
        if seed is None:
            return None
        ctx.stats["seeded"] += 1
        return self.track_against(kf, gray, torch.from_numpy(seed.T_cw), tex, use_chain=False)

    def complete_pair(self, track: Track, gray: np.ndarray, tex: np.ndarray) -> None:
        """Forward-backward checked grid flows keyframe <-> frame of the latest tracking attempt
        (``track``), for new graph edges."""
        ctx, kf = self.ctx, track.kf
        t = time.perf_counter()
        f01 = self.flow.flow
        f10 = flow_around(ctx.flow_est, gray, kf.gray,
                          None if self.flow.init is None else invert_flow(self.flow.init))
        track.fwd = grid_flow(f01, f10, kf.gray, gray, ctx.uv_np, STRIDE, ctx.cfg, kf.tex)
        track.bwd = grid_flow(f10, f01, gray, kf.gray, ctx.uv_np, STRIDE, ctx.cfg, tex)
        ctx.stats["t_flow"] += time.perf_counter() - t

    def check(self, gf: GridFlow, mo: BA.MotionResult) -> Optional[str]:
        """Why the tracking result is refused, in words; ``None`` when it is accepted."""
        cfg = self.ctx.cfg
        if gf.conf_frac < cfg.min_confident_frac:
            return (f"too few confident pixels (mean confidence {gf.conf_frac:.2f} < "
                    f"{cfg.min_confident_frac:.2f})")
        if not bool(torch.isfinite(mo.T_cw).all()):
            return "motion-only BA diverged (non-finite pose)"
        # written so that NaN fails (NaN > x is False)
        if not mo.rms_px <= cfg.max_track_rms_px:
            return f"flow disagrees with the map (residual RMS {mo.rms_px:.1f} px)"
        if not mo.inlier_frac >= 0.3:
            return f"only {100 * mo.inlier_frac:.0f}% of confident pixels agree with the pose"
        return None

    def accept(self, stamp: int, gray: np.ndarray, track: Track) -> torch.Tensor:
        """Take ``track`` as frame ``stamp``'s pose: the flow chain continues from it and the motion
        model moves on. Returns the orthonormalised ``T_cw``."""
        self.chain = FlowChain(self.flow.kf_stamp, self.flow.flow, gray)
        T_cw = orthonormalize_pose(track.motion.T_cw)
        self.prev, self.last = self.last, StampedPose(stamp, T_cw.clone())
        return T_cw

    def overlap_lost(self, track: Track) -> bool:
        """Whether the flow confidence against the newest keyframe ``track.kf`` fell below
        ``keyframe_conf_ratio`` of that of the first frame tracked against it."""
        kf, gf = track.kf, track.fwd
        if self.overlap is None or self.overlap.stamp != kf.stamp:
            self.overlap = KeyframeOverlap(kf.stamp, gf.conf_frac)      # first frame after the keyframe
        return gf.conf_frac < self.ctx.cfg.keyframe_conf_ratio * self.overlap.conf_frac

    def keyframe_added(self, kf: WindowKeyframe, gray: np.ndarray) -> None:
        """The frame became keyframe ``kf`` (grey image ``gray``): its pose is the BA pose and the
        flow chain restarts from it."""
        self.chain = FlowChain(kf.stamp, np.zeros((self.ctx.H, self.ctx.W, 2), np.float32), gray)
        self.last = StampedPose(kf.stamp, kf.T_cw.clone())
