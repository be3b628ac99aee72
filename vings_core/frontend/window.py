"""The keyframe window: keyframes with their grid inverse depths, the covisibility graph of flow
edges between them, the window bundle adjustment, depth uncertainty, the Schur-reduced pose system,
window sliding and the emission of finished keyframes (dense depth) to the mapper.

Poses are ``T_cw`` (world-to-camera) ``(4, 4)`` float64 tensors; each keyframe pose written here is
also written to the pose buffer. Emitted :class:`~vings_core.types.Keyframe` objects carry ``T_wc``.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Optional

import cv2
import numpy as np
import torch

from ..geometry import orthonormalize_pose, pose_inverse
from ..types import Frame, Keyframe
from . import ba as BA
from .context import DT, STRIDE, FrontendContext
from .depth import dense_depth
from .flow import GridFlow
from .graph import CovisibilityGraph, Edge, select_edges
from .pose_buffer import PoseBuffer
from .projective import project_edges
from .uncertainty import window_inv_depth_var


@dataclass
class WindowKeyframe:
    """A keyframe in the window: its image (``gray``, ``rgb``), grid texture weight ``tex``
    ``(h, w)``, pose ``T_cw`` ``(4, 4)``, grid inverse depth ``d`` ``(P,)`` and its marginal
    variance ``var`` ``(P,)`` (``None`` before the first uncertainty pass); ``index`` is the running
    keyframe number, ``segment`` the map segment it belongs to. ``dynamic``: the eraser's mask
    ``(H, W)`` bool (True = moving object) once it arrived, and ``static`` ``(P,)`` float64 its grid
    points' weight (0 on the mask, 1 elsewhere); None without a mask."""

    stamp: int
    index: int
    gray: np.ndarray
    rgb: np.ndarray
    tex: np.ndarray
    T_cw: torch.Tensor
    d: torch.Tensor
    var: Optional[torch.Tensor] = None
    segment: int = 0
    emitted: bool = False
    dynamic: Optional[np.ndarray] = None
    static: Optional[np.ndarray] = None


@dataclass
class _WindowBackup:
    """Poses, inverse depths and edges of the window before a keyframe is added (to undo it)."""

    poses: list[torch.Tensor]
    depths: list[torch.Tensor]
    edges: dict


class KeyframeWindow:
    """Sliding window of :class:`WindowKeyframe` with their flow graph and window BA.

    ``keyframes`` (oldest first), ``graph``, ``pose_system`` (the Schur-reduced pose system of the
    latest window BA, :class:`~vings_core.frontend.ba.PoseSystem`), ``emitted`` (keyframes emitted
    and not popped yet). With ``keep_lowres_depth``, ``lowres_depth`` maps an emitted keyframe's
    stamp to its grid ``(inverse depth, marginal variance)`` ``(h, w)`` arrays (benchmarks; ~90 kB per
    keyframe at 752x480).
    """

    def __init__(self, ctx: FrontendContext, buffer: PoseBuffer):
        self.ctx = ctx
        self.buffer = buffer
        self.keyframes: list[WindowKeyframe] = []
        self.graph = CovisibilityGraph()
        self.pose_system: Optional[BA.PoseSystem] = None
        self.emitted: list[Keyframe] = []
        self.keep_lowres_depth = False
        self.lowres_depth: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        #: with ``export_incident``, the pose system of the edges incident to each keyframe that
        #: leaves the window (over the window as it was), in ``leaving`` until taken
        self.export_incident = False
        self.leaving: list[tuple[int, BA.PoseSystem]] = []
        self._count = 0

    def new_index(self) -> int:
        """The next running keyframe number."""
        self._count += 1
        return self._count - 1

    # ------------------------------------------------------------------------------ changes

    def start(self, kf0: WindowKeyframe, kf1: WindowKeyframe, f01: GridFlow, f10: GridFlow) -> None:
        """A new window of two keyframes joined by the grid flows ``f01`` (kf0 -> kf1) and ``f10``."""
        self.keyframes = [kf0, kf1]
        self.graph.clear()
        self.graph.add(Edge(kf0.stamp, kf1.stamp, f01.target, f01.weight))
        self.graph.add(Edge(kf1.stamp, kf0.stamp, f10.target, f10.weight))
        self.buffer.set_keyframe_pose(kf0.stamp, kf0.T_cw.numpy().copy())
        self.buffer.set_keyframe_pose(kf1.stamp, kf1.T_cw.numpy().copy())

    def add(self, frame: Frame, gray: np.ndarray, tex: np.ndarray, T_cw: torch.Tensor, gf: GridFlow,
            gb: GridFlow, segment: int) -> Optional[WindowKeyframe]:
        """Make ``frame`` (pose ``T_cw``; ``gf``/``gb``: grid flows newest keyframe <-> frame) a
        keyframe: connect it, run the window BA, slide and emit. ``None`` (window unchanged) when the
        BA diverges."""
        cfg, ctx = self.ctx.cfg, self.ctx
        last = self.keyframes[-1]
        new = WindowKeyframe(frame.stamp_ns, self.new_index(), gray, frame.rgb(), tex, T_cw.clone(),
                             self.propagate_depth(last, T_cw), segment=segment)
        backup = _WindowBackup([k.T_cw.clone() for k in self.keyframes],
                               [k.d.clone() for k in self.keyframes], dict(self.graph.edges))
        self.keyframes.append(new)
        n = len(self.keyframes) - 1
        self.graph.add(Edge(last.stamp, new.stamp, gf.target, gf.weight))
        self.graph.add(Edge(new.stamp, last.stamp, gb.target, gb.weight))
        # the new keyframe's depth from its edge to the last keyframe (poses held: independent 1-D
        # problems), so the flow its other edges are refined around is induced by a real depth map
        t = time.perf_counter()
        r0 = BA.bundle_adjust(torch.stack([last.T_cw, new.T_cw]), torch.stack([last.d, new.d]),
                              torch.tensor([1]), torch.tensor([0]), ctx.rays,
                              torch.from_numpy(gb.target)[None],
                              torch.from_numpy(gb.weight)[None] * ctx.info_scale, ctx.K,
                              n_fixed=2, iters=3, loss=cfg.robust_loss, delta=cfg.robust_delta_px,
                              d_bounds=ctx.d_bounds(last.d))
        ctx.stats["t_ba"] += time.perf_counter() - t
        if torch.isfinite(r0.d[1]).all():
            new.d = r0.d[1].clone()
        if cfg.refine_flow:
            # the tracking flow came from a chained prior; re-measure the pair around the flow
            # induced by the poses and the new depth (the residual revision r_ij)
            self.connect(last, new)
        T_all = torch.stack([k.T_cw for k in self.keyframes])
        d_all = torch.stack([k.d for k in self.keyframes])
        others = select_edges(T_all, d_all, n, ctx.rays, ctx.uv, ctx.K, ctx.W, ctx.H,
                              cfg.temporal_radius, cfg.proximity_flow_lr_px * STRIDE,
                              cfg.max_edges_per_keyframe)
        for m in others:
            o = self.keyframes[m]
            if o is last:
                continue
            self.connect(o, new)
        res = self.bundle_adjust(cfg.ba_iters)
        if res is None:
            self._undo(backup, new)
            return None
        ctx.stats["keyframes"] += 1
        self.after_change(res.ne, res.fixed)
        ctx.reason = (f"tracking: keyframe {new.index} added ({len(self.keyframes)} in window, "
                      f"{len(self.graph)} edges)")
        return new

    def _undo(self, backup: _WindowBackup, new: WindowKeyframe) -> None:
        """Divergence: drop keyframe ``new``, restore the window (tracking goes on against it)."""
        for k, T, d in zip(self.keyframes[:-1], backup.poses, backup.depths):
            k.T_cw, k.d = T, d
        self.keyframes.pop()
        self.graph.edges = backup.edges
        self.ctx.events.append(f"keyframe {new.stamp} rejected: window BA diverged")

    def propagate_depth(self, kf: WindowKeyframe, T_new: torch.Tensor) -> torch.Tensor:
        """Initial inverse depth of a new keyframe at ``T_new``: ``kf``'s grid splatted into the new
        view (nearest surface wins), holes filled with the median."""
        ctx = self.ctx
        T = torch.stack([kf.T_cw, T_new])
        ii, jj = torch.tensor([0]), torch.tensor([1])
        q_uv, valid = project_edges(T, kf.d[None].expand(2, -1), ii, jj, ctx.rays, ctx.K)
        Tji = T_new @ pose_inverse(kf.T_cw)
        q = (Tji[:3, :3] @ ctx.rays.T).T + Tji[:3, 3] * kf.d[:, None]
        dn = kf.d / q[:, 2].clamp_min(1e-9)           # inverse depth in the new camera
        uv = q_uv[0]
        cx = torch.floor(uv[:, 0] / STRIDE).long()
        cy = torch.floor(uv[:, 1] / STRIDE).long()
        ok = valid[0] & (cx >= 0) & (cx < ctx.w) & (cy >= 0) & (cy < ctx.h) & (q[:, 2] > 0)
        out = torch.full((ctx.P,), -1.0, dtype=DT)
        if ok.any():
            out.scatter_reduce_(0, (cy * ctx.w + cx)[ok], dn[ok], reduce="amax")
        fill = float(dn[ok].median()) if ok.any() else float(kf.d.median())
        return torch.where(out > 0, out, torch.full_like(out, fill))

    def connect(self, o: WindowKeyframe, new: WindowKeyframe) -> None:
        """Flow edges ``o <-> new`` initialised by the flow the current estimate induces."""
        ctx = self.ctx
        init_on = ctx.induced_init(o.T_cw, ctx.filled_depth(o.d, o.var), new.T_cw)
        init_no = ctx.induced_init(new.T_cw, ctx.filled_depth(new.d, new.var), o.T_cw)
        pair = ctx.flow_pair(o.gray, new.gray, init_on, init_no, o.tex, new.tex)
        self.graph.add(Edge(o.stamp, new.stamp, pair.fwd.target, pair.fwd.weight))
        self.graph.add(Edge(new.stamp, o.stamp, pair.bwd.target, pair.bwd.weight))

    def edge_tensors(self, stamps: list[int]):
        """The graph's edges among ``stamps`` (:meth:`CovisibilityGraph.tensors`) with the dynamic
        masks applied: weight 0 for a grid point of keyframe ``i`` on its mask, and for one whose
        flow target lands on keyframe ``j``'s mask (the object hides the point there)."""
        ii, jj, tg, wt = self.graph.tensors(stamps)
        by = {k.stamp: k for k in self.keyframes if k.dynamic is not None}
        if not by or not len(ii):
            return ii, jj, tg, wt
        wt = wt.clone()
        H, W = self.ctx.H, self.ctx.W
        for e, (i, j) in enumerate(zip(ii.tolist(), jj.tolist())):     # a loop over edges, not pixels
            ki, kj = by.get(stamps[i]), by.get(stamps[j])
            if ki is not None:
                wt[e] *= torch.from_numpy(ki.static)
            if kj is not None:
                t = tg[e].numpy()
                ok = np.isfinite(t).all(-1)
                u = np.clip(np.round(np.where(ok, t[:, 0], 0)), 0, W - 1).astype(np.int64)
                v = np.clip(np.round(np.where(ok, t[:, 1], 0)), 0, H - 1).astype(np.int64)
                wt[e] *= torch.from_numpy((~(kj.dynamic[v, u] & ok)).astype(np.float64))
        return ii, jj, tg, wt

    def set_dynamic(self, stamp: int, mask: np.ndarray) -> bool:
        """Keyframe ``stamp``'s dynamic mask (``(H, W)`` bool): its grid points whose block touches the
        mask get weight 0 in every later window BA and tracking step, and so do observations of
        other keyframes' points landing on it (grown by half a block). False when the keyframe is
        no longer in the window."""
        for k in self.keyframes:
            if k.stamp == int(stamp):
                m = np.asarray(mask, dtype=bool)
                if m.shape != (self.ctx.H, self.ctx.W):
                    raise ValueError(f"dynamic mask of keyframe {stamp} has shape {m.shape}, expected "
                                     f"{(self.ctx.H, self.ctx.W)}")
                # a grid point's flow is its STRIDE x STRIDE block's: masked when any pixel of the
                # block is; flow targets are checked against the mask grown by half a block
                h, w, S = self.ctx.h, self.ctx.w, STRIDE
                blk = np.zeros((h, w), bool)
                hh, ww = min(h, self.ctx.H // S), min(w, self.ctx.W // S)
                blk[:hh, :ww] = m[:hh * S, :ww * S].reshape(hh, S, ww, S).any((1, 3))
                k.static = (~blk.reshape(-1)).astype(np.float64)
                k.dynamic = cv2.dilate(m.astype(np.uint8), np.ones((S + 1, S + 1), np.uint8)).astype(bool)
                return True
        return False

    def bundle_adjust(self, iters: int) -> Optional[BA.BAResult]:
        """Window BA (``iters`` LM iterations); the refined poses and depths are written to the
        window and the pose buffer. ``None`` (nothing written) when the BA diverges."""
        cfg, ctx = self.ctx.cfg, self.ctx
        stamps = [k.stamp for k in self.keyframes]
        ii, jj, tg, wt = self.edge_tensors(stamps)
        T = torch.stack([k.T_cw for k in self.keyframes])
        d = torch.stack([k.d for k in self.keyframes])
        t = time.perf_counter()
        # gauge: the oldest poses, with a baseline among them where the window has one
        # (BA.gauge_mask); the depth variances use the same gauge (after_change)
        fixed = BA.gauge_mask(T, min(cfg.fixed_poses, len(self.keyframes) - 1))
        res = BA.bundle_adjust(T, d, ii, jj, ctx.rays, tg, wt * ctx.info_scale, ctx.K,
                               n_fixed=0, fixed_mask=fixed, iters=iters, loss=cfg.robust_loss,
                               delta=cfg.robust_delta_px, lam=cfg.lm_lambda,
                               d_bounds=ctx.d_bounds(d))
        ctx.stats["t_ba"] += time.perf_counter() - t
        if not (torch.isfinite(res.T_cw).all() and torch.isfinite(res.d).all()
                and res.cost <= res.cost0 * 1.0001):       # also refuses a NaN cost
            return None
        for k, Tk, dk in zip(self.keyframes, orthonormalize_pose(res.T_cw), res.d):
            k.T_cw = Tk.clone()
            k.d = dk.clone()
            self.buffer.set_keyframe_pose(k.stamp, Tk.numpy().copy())
        return res

    def after_change(self, r_ne: Optional[BA.NormalEquations],
                     fixed: Optional[torch.Tensor] = None) -> None:
        """Uncertainty, pose-system export, window sliding and emission after a BA (``r_ne``: its
        normal equations, assembled here if ``None``; ``fixed``: its gauge, reused for the depth
        variances)."""
        cfg, ctx = self.ctx.cfg, self.ctx
        stamps = [k.stamp for k in self.keyframes]
        if r_ne is None:
            ii, jj, tg, wt = self.edge_tensors(stamps)
            T = torch.stack([k.T_cw for k in self.keyframes])
            d = torch.stack([k.d for k in self.keyframes])
            r_ne = BA.assemble(T, d, ii, jj, ctx.rays, tg, wt * ctx.info_scale, ctx.K,
                               cfg.robust_loss, cfg.robust_delta_px)
        T = torch.stack([k.T_cw for k in self.keyframes])
        self.pose_system = BA.reduced_pose_system(r_ne, T, stamps)
        # the monocular gauge (incl. scale) is fixed by the window BA's fixed poses (the oldest
        # ones, with a baseline among them: BA.gauge_mask), also for the 2-view initialisation
        # whose BA left the second pose free (scale held by damping): at least two fixed poses
        n_gauge = max(2, cfg.fixed_poses)
        if fixed is None or fixed.shape[0] != len(self.keyframes) or int(fixed.sum()) < min(
                n_gauge, len(self.keyframes)):
            fixed = BA.gauge_mask(T, n_gauge)
        free = torch.nonzero(~fixed)[:, 0]
        var = window_inv_depth_var(r_ne, free)
        for k, v in zip(self.keyframes, var):
            k.var = v.clone()
        self._slide_and_emit()

    def _slide_and_emit(self) -> None:
        """Drop the oldest keyframes beyond ``window`` (emitting them) and emit every keyframe with
        ``emit_delay`` newer ones."""
        cfg = self.ctx.cfg
        while len(self.keyframes) > cfg.window:
            if self.export_incident:
                sysm = self.incident_system(0)
                if sysm is not None:
                    self.leaving.append((self.keyframes[0].stamp, sysm))
            old = self.keyframes.pop(0)
            if not old.emitted:
                self.emit(old)
            self.graph.remove_keyframe(old.stamp)
        n = len(self.keyframes)
        for pos, kf in enumerate(self.keyframes):
            if not kf.emitted and n - 1 - pos >= cfg.emit_delay and pos < n - 1:
                self.emit(kf)

    def incident_system(self, pos: int) -> Optional[BA.PoseSystem]:
        """Schur-reduced pose system (depths eliminated) of the edges that start or end at the
        window keyframe at position ``pos``, over every window pose, linearised at the current
        estimate; ``None`` without such edges. This is the visual information a keyframe takes with
        it when it leaves the window (kept as a prior by a smoother)."""
        cfg, ctx = self.ctx.cfg, self.ctx
        stamps = [k.stamp for k in self.keyframes]
        ii, jj, tg, wt = self.edge_tensors(stamps)
        m = (ii == pos) | (jj == pos)
        if not bool(m.any()):
            return None
        T = torch.stack([k.T_cw for k in self.keyframes])
        d = torch.stack([k.d for k in self.keyframes])
        ne = BA.assemble(T, d, ii[m], jj[m], ctx.rays, tg[m], wt[m] * ctx.info_scale, ctx.K,
                         cfg.robust_loss, cfg.robust_delta_px)
        return BA.reduced_pose_system(ne, T, stamps)

    def take_poses(self, kf_T_cw: dict[int, np.ndarray]) -> None:
        """New ``T_cw`` for keyframes (those in the window take them for the next BA); inverse
        depths (and variances) are divided by the median change of the window's baselines, so a
        Sim(3) correction keeps the depths consistent with the poses."""
        old_T = {kf.stamp: kf.T_cw.clone() for kf in self.keyframes}
        for kf in self.keyframes:
            if kf.stamp in kf_T_cw:
                kf.T_cw = torch.from_numpy(kf_T_cw[kf.stamp].copy())
        if len(self.keyframes) < 2:
            return
        ratios = []
        for a, b in zip(self.keyframes[:-1], self.keyframes[1:]):
            t_old = (old_T[b.stamp] @ pose_inverse(old_T[a.stamp]))[:3, 3].norm()
            t_new = (b.T_cw @ pose_inverse(a.T_cw))[:3, 3].norm()
            if t_old > 1e-9:
                ratios.append(float(t_new / t_old))
        if ratios:
            r = float(np.median(ratios))
            if abs(r - 1.0) > 1e-3 and r > 0:
                for kf in self.keyframes:
                    kf.d = kf.d / r
                    if kf.var is not None:
                        kf.var = kf.var / (r * r)     # var(d / r) = var(d) / r^2

    def close_segment(self) -> Optional[float]:
        """Emit every keyframe not emitted yet and empty the window; returns the median over the
        keyframes of their median depth (``None`` without a positive depth), the scale a new
        segment continues with."""
        self.emit_all()
        meds = [float((1.0 / kf.d[kf.d > 0]).median()) for kf in self.keyframes if (kf.d > 0).any()]
        depth = float(np.median(meds)) if meds else None
        self.keyframes = []
        self.graph.clear()
        self.pose_system = None
        return depth

    # ----------------------------------------------------------------------------- emission

    def emit_all(self) -> None:
        """Emit every keyframe of the window not emitted yet."""
        for kf in self.keyframes:
            if not kf.emitted:
                self.emit(kf)

    def pop_emitted(self) -> list[Keyframe]:
        """Keyframes emitted since the last call."""
        out, self.emitted = self.emitted, []
        return out

    def emit(self, kf: WindowKeyframe) -> None:
        """Dense depth of ``kf`` (upsampled from the grid, guided by its image) -> a
        :class:`~vings_core.types.Keyframe` (``T_wc``) in :attr:`emitted`."""
        t = time.perf_counter()
        cfg, ctx = self.ctx.cfg, self.ctx
        h, w = ctx.h, ctx.w
        var = kf.var if kf.var is not None else torch.full((ctx.P,), float("inf"), dtype=DT)
        dd = dense_depth(kf.d.reshape(h, w).numpy(), var.reshape(h, w).numpy(),
                         kf.gray, STRIDE, cfg.upsample_sigma_spatial, cfg.upsample_sigma_range,
                         cfg.upsample_spread_var, cfg.max_rel_depth_std, cfg.max_depth_factor,
                         cfg.far_factor, cfg.textureless_grad)
        kf.emitted = True
        if self.keep_lowres_depth:
            self.lowres_depth[kf.stamp] = (kf.d.reshape(h, w).numpy().copy(),
                                           var.reshape(h, w).numpy().copy())
        img = torch.from_numpy(kf.rgb.astype(np.float32) / 255.0)
        self.emitted.append(Keyframe(
            stamp_ns=kf.stamp, image=img, T_wc=torch.from_numpy(np.linalg.inv(kf.T_cw.numpy())),
            depth=torch.from_numpy(dd.depth),
            inv_depth_var=torch.from_numpy(np.minimum(dd.inv_var, 1e10).astype(np.float32)),
            valid=torch.from_numpy(dd.valid), camera=ctx.camera, index=kf.index))
        ctx.stats["t_emit"] += time.perf_counter() - t
