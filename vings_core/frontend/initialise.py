"""Initialisation of a map segment: a reference frame, flow from it to each new frame, and once the
parallax suffices the essential matrix and a two-view BA give the first two keyframes; the frames
that waited are re-posed against them.

Poses are ``T_cw`` (world-to-camera). A segment's world frame is its anchor: the identity for the
first segment, the last good pose for a segment started after tracking was lost. The scale is median
depth 1 (first segment) or the previous segment's median depth.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Optional

import cv2
import numpy as np
import torch

from ..geometry import pose_inverse
from ..types import Frame, PoseEstimate, TrackState
from . import ba as BA
from .context import DT, STRIDE, FlowChain, FlowPair, FrontendContext, StampedPose
from .flow import GridFlow, dense_from_grid
from .pose_buffer import PoseBuffer
from .seed import interpolate_displacements
from .window import KeyframeWindow, WindowKeyframe

log = logging.getLogger("vings.frontend")
MAX_PENDING = 400          # waiting frames re-posed at initialisation (most recent)
MAX_ORPHANS = 100          # frames of replaced references kept for back-filling (most recent)


def rotation_only_residual(p0: np.ndarray, p1: np.ndarray, K: np.ndarray) -> float:
    """Median pixel distance left between matched pixels ``p0 -> p1`` (``(N, 2)``) after the best
    pure-rotation model ``p1 ~ K R K^-1 p0`` (``R`` by Kabsch on the unit bearing vectors): ~0 when
    the camera only rotated (no baseline: depth is unobservable), the parallax otherwise."""
    Ki = np.linalg.inv(K)
    b0 = np.c_[p0, np.ones(len(p0))] @ Ki.T
    b1 = np.c_[p1, np.ones(len(p1))] @ Ki.T
    b0 /= np.linalg.norm(b0, axis=1, keepdims=True)
    b1 /= np.linalg.norm(b1, axis=1, keepdims=True)
    U, _, Vt = np.linalg.svd(b1.T @ b0)
    R = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    q = np.c_[p0, np.ones(len(p0))] @ (K @ R @ Ki).T
    return float(np.median(np.linalg.norm(p1 - q[:, :2] / q[:, 2:3], axis=1)))


def triangulation_angles_deg(p0: np.ndarray, p1: np.ndarray, K: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Angle (deg) between the two viewing rays of each match ``p0 -> p1`` (``(N, 2)`` pixels)
    once the relative rotation ``R`` (``x1 = R x0 + t``) is removed: the triangulation angle of
    the point, independent of the baseline's direction (near the focus of expansion of a forward
    motion it is small, at the image border large; the median flow alone misses that)."""
    Ki = np.linalg.inv(K)
    b0 = np.c_[p0, np.ones(len(p0))] @ Ki.T
    b1 = np.c_[p1, np.ones(len(p1))] @ Ki.T @ R        # rows: R^T b1, in the reference frame
    b0 /= np.linalg.norm(b0, axis=1, keepdims=True)
    b1 /= np.linalg.norm(b1, axis=1, keepdims=True)
    return np.degrees(np.arccos(np.clip((b0 * b1).sum(1), -1.0, 1.0)))


@dataclass
class PendingFrame:
    """A frame that waited for initialisation: its stamp, the grid flow reference -> frame and its
    grey image (kept to back-fill it should its reference be replaced)."""

    stamp: int
    flow: GridFlow
    gray: Optional[np.ndarray] = None


@dataclass
class Reference:
    """The reference frame of an initialisation: its image, grid texture weight ``tex``, the frames
    measured against it since (``pending``, oldest first) and the flow chain to the latest of them."""

    stamp: int
    gray: np.ndarray
    rgb: np.ndarray
    tex: np.ndarray
    pending: list[PendingFrame] = field(default_factory=list)
    chain: Optional[FlowChain] = None


@dataclass
class SegmentStart:
    """Where the current map segment starts: its number ``index`` (0 for the first), the anchor
    ``T_cw`` (world-to-camera, 4x4 float64) of its first keyframe, and the median depth its
    initialisation is scaled to (``None``: 1)."""

    index: int = 0
    T_cw: np.ndarray = field(default_factory=lambda: np.eye(4))
    depth: Optional[float] = None


@dataclass
class RelativePose:
    """Reference -> current frame from the essential matrix: ``R``, unit ``t`` (``T_10``), the
    inlier fraction, the median rotation-compensated parallax of the inliers (working px) and the
    fraction of inliers whose triangulation angle reaches ``init_min_angle_deg``."""

    R: np.ndarray
    t: np.ndarray
    inlier_frac: float
    parallax_px: float
    wide_frac: float = 0.0


@dataclass
class TwoView:
    """The scaled two-view BA: poses ``T_cw`` of the reference and the current frame, and their grid
    inverse depths ``d`` ``(2, P)``."""

    T0: torch.Tensor
    T1: torch.Tensor
    d: torch.Tensor


@dataclass
class Initialised:
    """A new segment's first window: the estimates of the reference, of the frames that waited and
    of the current frame (in time order), the last two tracked poses for the motion model, and the
    flow chain from the newest keyframe."""

    estimates: list[PoseEstimate]
    prev: StampedPose
    last: StampedPose
    chain: FlowChain


class Initialiser:
    """Waits for parallax against a reference frame and builds the first window of a segment."""

    def __init__(self, ctx: FrontendContext, buffer: PoseBuffer, window: KeyframeWindow):
        self.ctx = ctx
        self.buffer = buffer
        self.window = window
        self.ref: Optional[Reference] = None
        self.segment = SegmentStart()
        # frames of references that lost overlap (stamp, grey; oldest first): posed at initialisation
        # by flow from the first keyframe, back to the oldest one that still overlaps it
        self.orphans: list[tuple[int, np.ndarray]] = []
        self.unposed_why: Optional[str] = None      # why frames before initialisation kept no pose

    def next_segment(self, T_cw: Optional[np.ndarray], depth: Optional[float]) -> None:
        """Start over for a new segment anchored at ``T_cw`` (``None``: the current anchor) with
        median depth ``depth``."""
        self.segment = SegmentStart(self.segment.index + 1,
                                    T_cw if T_cw is not None else self.segment.T_cw, depth)
        self.ref = None
        self.orphans = []

    def new_reference(self, frame: Frame, gray: np.ndarray, why: str) -> None:
        old = self.ref
        if old is not None:         # its frames wait for a pose from the next initialisation
            self.orphans.append((old.stamp, old.gray))
            self.orphans.extend((p.stamp, p.gray) for p in old.pending
                                if p.gray is not None and p.stamp != frame.stamp_ns)
            del self.orphans[:-MAX_ORPHANS]
        self.ref = Reference(frame.stamp_ns, gray, frame.rgb(), self.ctx.texture(gray))
        self.ctx.reason = why

    def step(self, frame: Frame, gray: np.ndarray) -> Optional[Initialised]:
        """Measure ``frame`` against the reference and initialise when possible; ``None`` while
        waiting (``ctx.reason`` says why)."""
        ctx, cfg = self.ctx, self.ctx.cfg
        stamp = frame.stamp_ns
        if self.ref is None:
            self.new_reference(frame, gray, "waiting for motion: first frame of a map segment")
            return None
        ref = self.ref
        base = ctx.chained_flow(ref.chain, gray) if ref.chain is not None else None
        tex1 = ctx.texture(gray)
        pair = ctx.flow_pair(ref.gray, gray, init01=base, tex0=ref.tex, tex1=tex1)
        gf = pair.fwd
        if gf.conf_frac < cfg.min_confident_frac and float(tex1.mean()) < cfg.min_confident_frac:
            # a black, saturated or blank frame is not a new start: keep the reference (and the
            # flow chain, which must not run through this frame)
            why = f"has almost no texture (black, saturated or blank image); kept reference frame {ref.stamp}"
            if not ctx.reason.endswith(why):       # one event per run of such frames
                ctx.events.append(f"waiting: frame {stamp} {why}")
            ctx.reason = f"waiting: frame {stamp} {why}"
            return None
        if gf.conf_frac < cfg.min_confident_frac:
            # the motion may be beyond the dense flow's reach: seed it from sparse matches
            seeded = self._seeded_pair(ref, gray, tex1)
            if seeded is not None and seeded.fwd.conf_frac > gf.conf_frac:
                pair, gf = seeded, seeded.fwd
        ref.chain = FlowChain(ref.stamp, pair.f01, gray)
        mean_lr = gf.mean_flow / STRIDE
        ctx.max_mean_flow_lr = max(ctx.max_mean_flow_lr, mean_lr)
        if mean_lr >= cfg.still_flow_lr_px:
            ctx.motion_detected = True
        ref.pending.append(PendingFrame(stamp, gf, gray))
        if len(ref.pending) > MAX_ORPHANS:     # grey images only for the frames a back-fill may reach
            ref.pending[-MAX_ORPHANS - 1].gray = None
        if len(ref.pending) > MAX_PENDING:     # long still periods: keep memory bounded (older
            ref.pending.pop(0)                 # waiting frames keep their 'waiting' pose)
        if gf.conf_frac < cfg.min_confident_frac:
            self.new_reference(frame, gray, f"waiting: lost overlap with the reference frame "
                               f"(mean confidence {gf.conf_frac:.2f}); restarted "
                               f"initialisation from frame {stamp}")
        elif mean_lr < cfg.still_flow_lr_px:
            ctx.reason = (f"waiting for motion: mean flow {mean_lr:.2f} px at 1/8 resolution; "
                          f"no motion detected (camera still)")
        else:
            return self._try_initialise(frame, gray, pair)
        return None

    def _seeded_pair(self, ref: Reference, gray: np.ndarray, tex1: np.ndarray) -> Optional[FlowPair]:
        """Flow reference <-> frame refined around a prior interpolated from sparse feature matches
        that fit a fundamental matrix (no depth exists yet); ``None`` when seeding is off or too
        few matches agree."""
        ctx, cfg = self.ctx, self.ctx.cfg
        m = ctx.seed_matches(ref.gray, gray)
        if m is None:
            return None
        disp = interpolate_displacements(m, ctx.uv_np, ransac_px=cfg.seed_ransac_px,
                                         min_inliers=cfg.seed_min_inliers)
        if disp is None:
            return None
        ctx.stats["seeded"] += 1
        base = dense_from_grid(disp, ctx.h, ctx.w, ctx.H, ctx.W, STRIDE)
        return ctx.flow_pair(ref.gray, gray, init01=base, tex0=ref.tex, tex1=tex1)

    def _try_initialise(self, frame: Frame, gray: np.ndarray, pair: FlowPair) -> Optional[Initialised]:
        rel = self._relative_pose(pair.fwd)
        if rel is None:
            return None
        two = self._two_view(rel, pair)
        if two is None:
            return None
        ref, seg = self.ref, self.segment
        kf0 = WindowKeyframe(ref.stamp, self.window.new_index(), ref.gray, ref.rgb, ref.tex,
                             two.T0.clone(), two.d[0].clone(), segment=seg.index)
        kf1 = WindowKeyframe(frame.stamp_ns, self.window.new_index(), gray, frame.rgb(),
                             self.ctx.texture(gray), two.T1, two.d[1].clone(), segment=seg.index)
        self.window.start(kf0, kf1, pair.fwd, pair.bwd)
        out = self._backfill_orphans(kf0) + self._repose_pending(kf0, kf1)
        pending = ref.pending[:-1]
        prev = (StampedPose(kf0.stamp, kf0.T_cw.clone()) if not pending else
                StampedPose(pending[-1].stamp, torch.from_numpy(self.buffer.T_cw(pending[-1].stamp))))
        last = StampedPose(kf1.stamp, kf1.T_cw.clone())
        chain = FlowChain(kf1.stamp, np.zeros((self.ctx.H, self.ctx.W, 2), np.float32), gray)
        self.ref = None
        self.ctx.reason = (f"initialised segment {seg.index} from frames {kf0.stamp} and "
                           f"{kf1.stamp}: {100 * rel.inlier_frac:.0f}% essential-matrix inliers, "
                           f"parallax {rel.parallax_px:.1f} px, {100 * rel.wide_frac:.0f}% of the "
                           f"inliers under a wide triangulation angle")
        self.ctx.events.append(self.ctx.reason)
        log.info(self.ctx.reason)
        self.ctx.stats["keyframes"] += 2
        self.window.after_change(r_ne=None)
        return Initialised(out, prev, last, chain)

    def _relative_pose(self, gf: GridFlow) -> Optional[RelativePose]:
        """Essential matrix of the confident grid flow reference -> frame; ``None`` (with the reason)
        when it is not reliable or the motion has too little parallax."""
        ctx, cfg = self.ctx, self.ctx.cfg
        sel = gf.weight > max(cfg.min_weight, 0.2)
        if sel.sum() < 30:
            ctx.reason = f"waiting: only {int(sel.sum())} confident correspondences to initialise"
            return None
        p0 = ctx.uv_np[sel]
        p1 = gf.target[sel]
        E, mask = cv2.findEssentialMat(p0, p1, ctx.Kmat, cv2.RANSAC, 0.999, cfg.init_ransac_px)
        if E is None or E.shape[0] < 3:
            ctx.reason = "waiting: essential matrix estimation failed"
            return None
        E = E[:3]
        n_inl, R, t, mask2 = cv2.recoverPose(E, p0, p1, ctx.Kmat, mask=mask.copy())
        inl = mask2.ravel() > 0
        frac = n_inl / len(p0)
        # rotation-compensated parallax of the inliers (infinite homography K R K^-1)
        Hinf = ctx.Kmat @ R @ np.linalg.inv(ctx.Kmat)
        p0h = np.c_[p0, np.ones(len(p0))] @ Hinf.T
        p0r = p0h[:, :2] / p0h[:, 2:3]
        par = float(np.median(np.linalg.norm(p1 - p0r, axis=1)[inl])) if inl.any() else 0.0
        if frac < cfg.init_min_inlier_frac:
            ctx.reason = (f"waiting: essential matrix has only {100 * frac:.0f}% inliers "
                          f"(need {100 * cfg.init_min_inlier_frac:.0f}%)")
            return None
        # under pure rotation E is degenerate and recoverPose's R can be off by degrees, which
        # leaves fake "parallax": refuse when a rotation alone explains the matches to noise level
        rot_res = rotation_only_residual(p0[inl], p1[inl], ctx.Kmat) if inl.any() else 0.0
        if rot_res < 2.0 * cfg.init_ransac_px:
            ctx.reason = (f"waiting for parallax: a pure rotation explains the motion (median "
                          f"residual {rot_res:.2f} px); depth needs the camera to translate")
            return None
        # enough parallax: the median flow (sideways motion), or enough inliers seen under a wide
        # triangulation angle (forward motion: most pixels lie near the focus of expansion)
        ang = triangulation_angles_deg(p0[inl], p1[inl], ctx.Kmat, R) if inl.any() else np.zeros(0)
        wide = float((ang >= cfg.init_min_angle_deg).mean()) if len(ang) else 0.0
        wide_ok = cfg.init_min_wide_frac > 0 and wide >= cfg.init_min_wide_frac
        if par < cfg.init_min_parallax_lr_px * STRIDE and not wide_ok:
            ctx.reason = (f"waiting for parallax: median rotation-compensated flow "
                          f"{par / STRIDE:.2f} px at 1/8 resolution (need "
                          f"{cfg.init_min_parallax_lr_px:.2f}) and {100 * wide:.0f}% of the inliers "
                          f"triangulated under {cfg.init_min_angle_deg:g} deg or more (need "
                          f"{100 * cfg.init_min_wide_frac:.0f}%)")
            return None
        return RelativePose(R, t, frac, par, wide)

    def _two_view(self, rel: RelativePose, pair: FlowPair) -> Optional[TwoView]:
        """Two-view BA of the reference and the current frame (world: the segment's anchor), scaled
        to the segment's median depth; ``None`` (with the reason) when it diverges."""
        ctx, cfg = self.ctx, self.ctx.cfg
        gf, gb = pair.fwd, pair.bwd
        T0 = torch.from_numpy(self.segment.T_cw.copy())
        T10 = torch.eye(4, dtype=DT)
        T10[:3, :3] = torch.from_numpy(rel.R)
        T10[:3, 3] = torch.from_numpy(rel.t.ravel())
        T = torch.stack([T0, T10 @ T0])
        ii = torch.tensor([0, 1])
        jj = torch.tensor([1, 0])
        tg = torch.from_numpy(np.stack([gf.target, gb.target]))
        wt = torch.from_numpy(np.stack([gf.weight, gb.weight])) * ctx.info_scale
        t_ba = time.perf_counter()
        # depths: exhaustive 1-D search (baseline 1) from 0.3 to 1000 baselines, then Gauss-Newton
        cands = 1.0 / torch.logspace(np.log10(0.3), 3.0, 48, dtype=DT)
        d = BA.triangulate_grid(T, ii, jj, ctx.rays, tg, wt, ctx.K, cands, cfg.robust_loss,
                                cfg.robust_delta_px)
        r = BA.bundle_adjust(T, d, ii, jj, ctx.rays, tg, wt, ctx.K, n_fixed=2, iters=8,
                             loss=cfg.robust_loss, delta=cfg.robust_delta_px, d_bounds=(1e-4, 10.0))
        r = BA.bundle_adjust(r.T_cw, r.d, ii, jj, ctx.rays, tg, wt, ctx.K, n_fixed=1,
                             iters=cfg.init_ba_iters, loss=cfg.robust_loss, delta=cfg.robust_delta_px,
                             d_bounds=ctx.d_bounds(r.d))
        ctx.stats["t_ba"] += time.perf_counter() - t_ba
        if not (torch.isfinite(r.T_cw).all() and torch.isfinite(r.d).all()):
            ctx.reason = "waiting: two-view BA diverged"
            return None
        # scale: median depth 1 (first segment) or the previous segment's median depth
        med_d = float(r.d[0][wt[0] > 0].median()) if (wt[0] > 0).any() else float(r.d[0].median())
        target_depth = self.segment.depth if self.segment.depth else 1.0
        s = target_depth * med_d       # depth_new = depth_old * s
        T_rel = r.T_cw[1] @ pose_inverse(r.T_cw[0])
        T_rel[:3, 3] *= s
        T1 = T_rel @ r.T_cw[0]
        return TwoView(r.T_cw[0], T1, r.d / s)

    def _backfill_orphans(self, kf0: WindowKeyframe) -> list[PoseEstimate]:
        """Estimates of the frames whose reference lost overlap before this initialisation (in time
        order): flow from the first keyframe to each, newest first, each seeded with the previous
        one's flow, and a motion-only BA against the keyframe's depths; from the first frame that
        no longer overlaps the keyframe on, the older ones keep no pose (``unposed_why``)."""
        ctx, cfg = self.ctx, self.ctx.cfg
        out: list[PoseEstimate] = []
        prior = None
        T_start = kf0.T_cw          # each BA starts from the newer neighbour's pose
        for k in range(len(self.orphans) - 1, -1, -1):
            stamp, gray = self.orphans[k]
            pair = ctx.flow_pair(kf0.gray, gray, init01=prior, tex0=kf0.tex, both=False)
            gf = pair.fwd
            mo = None
            if gf.conf_frac >= cfg.min_confident_frac:
                mo = BA.motion_only(kf0.T_cw[None], kf0.d[None], ctx.rays, torch.from_numpy(gf.target)[None],
                                    torch.from_numpy(gf.weight)[None] * ctx.info_scale, ctx.K, T_start,
                                    iters=cfg.track_iters, loss=cfg.robust_loss, delta=cfg.robust_delta_px)
            # the tracking checks: enough confident flow, a finite pose that the flow agrees with
            if mo is None or not (bool(torch.isfinite(mo.T_cw).all()) and mo.rms_px <= cfg.max_track_rms_px
                                  and mo.inlier_frac >= 0.3):
                self.unposed_why = (f"{k + 1} frame(s) up to frame {stamp} share too little of the "
                                    f"image with the first keyframe {kf0.stamp} (mean confidence "
                                    f"{gf.conf_frac:.2f}) to be posed")
                ctx.events.append(f"back-fill: {self.unposed_why}")
                break
            prior = pair.f01
            T_start = mo.T_cw
            out.append(self.buffer.record(stamp, kf0.stamp, mo.T_cw.numpy(), TrackState.TRACKING))
        if out:
            ctx.events.append(f"back-filled {len(out)} frame(s) before the reference frame {kf0.stamp}")
        self.orphans = []
        return out[::-1]

    def _repose_pending(self, kf0: WindowKeyframe, kf1: WindowKeyframe) -> list[PoseEstimate]:
        """Estimates of the new keyframes and of the frames that waited (motion-only against the
        reference keyframe with their stored flow), in time order."""
        ctx, cfg = self.ctx, self.ctx.cfg
        out = []
        for p in self.ref.pending[:-1]:
            mo = BA.motion_only(kf0.T_cw[None], kf0.d[None], ctx.rays,
                                torch.from_numpy(p.flow.target)[None],
                                torch.from_numpy(p.flow.weight)[None] * ctx.info_scale, ctx.K,
                                kf0.T_cw, iters=cfg.track_iters, loss=cfg.robust_loss,
                                delta=cfg.robust_delta_px)
            out.append(self.buffer.record(p.stamp, kf0.stamp, mo.T_cw.numpy(), TrackState.TRACKING))
        out.insert(0, self.buffer.record(kf0.stamp, kf0.stamp, kf0.T_cw.numpy(), TrackState.TRACKING, True))
        out.append(self.buffer.record(kf1.stamp, kf1.stamp, kf1.T_cw.numpy(), TrackState.TRACKING, True))
        return out
