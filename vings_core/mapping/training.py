"""The training step: one render of a window (or history) keyframe, its losses, the backward pass
and a sparse Adam step on the unstable Gaussians it reaches, with the score manager's hooks.

Losses (paper): ``lambda_rgb L_rgb + lambda_depth L_d (+ lambda_normal L_n + lambda_acc L_acc)``
(:mod:`.losses`). Keyframes are drawn from the local window in shuffled rounds; with probability
``history_ratio`` an older keyframe within ``tau`` of the newest one is trained on instead
(against forgetting). Learning rates are per Adam step, one per parameter column.
"""
from __future__ import annotations

import math
from typing import Optional

import numpy as np
import torch

from ..geometry import pose_inverse
from ..types import Keyframe
from .gaussians import PARAM_FIELDS, GaussianMap
from .history import expand_keyframe, scale_keyframe_depth
from .init import empty_mask, usable_depth_mask
from .losses import (accumulation_loss, depth_loss, depth_weight, l1_map, normal_loss, normals_from_depth,
                     rgb_loss, ssim_target_stats)
from .optim import sparse_adam_step_fast
from .score_manager import ScoreManager
from .state import MapState
from ..profiling import timed


def coarse_keyframe(kf: Keyframe, factor: int = 2) -> Keyframe:
    """``kf`` at ``1/factor`` of its resolution (sizes cropped to a multiple of ``factor``): RGB
    averaged over each ``factor x factor`` block; depth averaged over blocks whose pixels are all
    valid (0 elsewhere, so depth edges are dropped, not blurred); inverse-depth variance the block's
    largest; a block is dynamic when any of its pixels is; intrinsics scaled for OpenCV pixel centres (``c' = (c + 0.5) / f - 0.5``)."""
    from ..types import CameraModel
    f = int(factor)
    cam = kf.camera
    H, W = cam.height // f, cam.width // f

    def blocks(t: torch.Tensor) -> torch.Tensor:       # (H*f, W*f, ...) -> (H, W, f*f, ...)
        t = t[:H * f, :W * f]
        t = t.reshape(H, f, W, f, *t.shape[2:]).transpose(1, 2)
        return t.reshape(H, W, f * f, *t.shape[4:])
    valid = blocks(kf.valid & (kf.depth > 0)).all(2)
    depth = torch.where(valid, blocks(kf.depth).mean(2), torch.zeros((), dtype=kf.depth.dtype))
    c = CameraModel(W, H, cam.fx / f, cam.fy / f, (cam.cx + 0.5) / f - 0.5, (cam.cy + 0.5) / f - 0.5)
    dyn = None if kf.dynamic is None else blocks(kf.dynamic).any(2)
    return Keyframe(stamp_ns=kf.stamp_ns, image=blocks(kf.image).mean(2).contiguous(), T_wc=kf.T_wc,
                    depth=depth.contiguous(), inv_depth_var=blocks(kf.inv_depth_var).amax(2).contiguous(),
                    valid=valid, camera=c, index=kf.index, dynamic=dyn)


class Trainer:
    """Training of the map in ``st`` (:class:`MapState`); ``scores``: the score manager strategy
    whose hooks each step calls. Owns the shuffled round of window keyframes (``queue``) and the
    cached per-keyframe loss inputs."""

    def __init__(self, st: MapState, scores: ScoreManager) -> None:
        self.st = st
        self.scores = scores
        self.queue: list[int] = []                  # shuffled round of window stamps
        self._aux: dict[int, dict[int, dict]] = {}      # stamp -> image width -> cached masks / weights
        self._coarse: dict[int, tuple[torch.Tensor, Keyframe]] = {}    # coarse copies of window keyframes

    def new_round(self) -> None:
        """Start a new shuffled round (the window changed)."""
        self.queue = []

    def forget(self, stamp: int) -> None:
        """Drop what is cached for keyframe ``stamp`` (it left the window)."""
        self._aux.pop(stamp, None)
        self._coarse.pop(stamp, None)

    def coarse_of(self, kf: Keyframe) -> Keyframe:
        """The coarse copy of window keyframe ``kf`` (cached while its depth is the same tensor)."""
        c = self._coarse.get(kf.stamp_ns)
        if c is None or c[0] is not kf.depth:
            c = (kf.depth, coarse_keyframe(kf, self.st.cfg.coarse_factor))
            self._coarse[kf.stamp_ns] = c
        return c[1]

    def next_keyframe(self, queue: list[int]) -> Keyframe:
        """The next window keyframe of the shuffled round ``queue`` (refilled from the mapper's
        random generator when empty)."""
        st = self.st
        if not queue:
            perm = torch.randperm(len(st.window), generator=st.rng).tolist()
            queue.extend(st.window[i].stamp_ns for i in perm)
        return st.window_keyframe(queue.pop(0))

    def keyframe_aux(self, kf: Keyframe) -> dict:
        """Per-keyframe constant loss inputs, cached while the keyframe is in the window (one set
        per resolution: full and coarse)."""
        history = self.st.history
        a = self._aux.get(kf.stamp_ns, {}).get(kf.camera.width) if kf.stamp_ns not in history else None
        if a is None or a["T"] is not kf.depth or a["D"] is not kf.dynamic:
            cfg = self.st.cfg
            a = {"T": kf.depth, "D": kf.dynamic,
                 "static": None if kf.dynamic is None else ~kf.dynamic,
                 # SSIM windows (11 x 11) that stay clear of the dynamic pixels
                 "ssim_static": None if kf.dynamic is None else
                 -torch.nn.functional.max_pool2d(-(~kf.dynamic).float()[None, None], 11, 1, 5)[0, 0] > 0.5,
                 "usable": usable_depth_mask(kf, cfg.max_depth, cfg.max_depth_rel_std),
                 "w_depth": depth_weight(kf.depth, kf.inv_depth_var, cfg.depth_rel_std0),
                 "masked": empty_mask(kf, cfg.max_depth),
                 "ssim_stats": ssim_target_stats(kf.image) if cfg.lambda_ssim > 0 else None}
            if kf.stamp_ns not in history:
                self._aux.setdefault(kf.stamp_ns, {})[kf.camera.width] = a
        return a

    def losses(self, out, kf: Keyframe, it_terms: dict, with_normal: bool = True, with_acc: bool = True,
               expected_depth: bool = False) -> torch.Tensor:
        """Training loss of one render. ``expected_depth`` (pose refinement): the depth term compares
        the expected depth ``D_hat / alpha`` where ``alpha > 0.5`` instead of the accumulated depth
        ``D_hat``: the accumulated depth is short of the surface wherever alpha < 1, which for the
        map means "fill this pixel" but would pull a camera along its axis. ``it_terms`` receives
        the terms' values and the per-pixel L1 map (``l1_map``). The keyframe's dynamic pixels
        (``kf.dynamic``) are left out of every term and have 0 in ``l1_map``."""
        cfg = self.st.cfg
        img = kf.image
        aux = self.keyframe_aux(kf)
        l1 = l1_map(out.color, img)
        static = aux["static"]      # None: no dynamic mask; else the pixels every loss may use
        it_terms["l1_map"] = l1.detach() if static is None else torch.where(static, l1.detach(), 0.0)
        l_rgb = rgb_loss(out.color, img, cfg.lambda_ssim, mask=static, target_stats=aux["ssim_stats"], l1=l1,
                         ssim_mask=aux["ssim_static"])
        if expected_depth:
            a = out.alpha
            l_d = depth_loss(out.depth / a.clamp_min(1e-6), kf.depth, aux["w_depth"],
                             aux["usable"] & (a.detach() > 0.5))
        else:
            l_d = depth_loss(out.depth, kf.depth, aux["w_depth"], aux["usable"])
        total = cfg.lambda_rgb * l_rgb + cfg.lambda_depth * l_d
        l_n = torch.zeros(())
        l_a = torch.zeros(())
        if with_normal and cfg.lambda_normal > 0 and self.st.render_count >= cfg.normal_loss_warmup:
            a = out.alpha
            exp_d = out.depth / a.clamp_min(1e-6)
            n_d, ok = normals_from_depth(exp_d, kf.camera)
            ok = ok & (a.detach() > 0.5)
            if static is not None:
                ok = ok & static
            l_n = normal_loss(out.normal, n_d, torch.ones_like(a), ok)
            total = total + cfg.lambda_normal * l_n
        if with_acc and cfg.lambda_acc > 0:
            l_a = accumulation_loss(out.alpha, aux["masked"])
            total = total + cfg.lambda_acc * l_a
        it_terms.update(loss=float(total.detach()), rgb=float(l_rgb.detach()), depth=float(l_d.detach()),
                        normal=float(l_n.detach()), acc=float(l_a.detach()))
        return total

    def history_keyframe(self) -> Optional[Keyframe]:
        """With probability ``history_ratio``, an older keyframe (not in the window) whose camera is
        within ``tau`` of the newest keyframe, uniformly; else None."""
        st = self.st
        cfg = st.cfg
        if cfg.history_ratio <= 0 or not st.history:
            return None
        if float(torch.rand((), generator=st.rng)) >= cfg.history_ratio:
            return None
        cand = self.history_near()
        if not cand:
            return None
        return self.history_at(cand[int(torch.randint(len(cand), (), generator=st.rng))])

    def history_near(self) -> list[int]:
        """Stamps of the history keyframes whose camera is within ``tau`` of the newest keyframe."""
        st = self.st
        if not st.history or not st.window:
            return []
        cur = st.poses[st.window[-1].stamp_ns][:3, 3]
        stamps = st.history.stamps()
        pos = np.stack([st.poses[s][:3, 3] for s in stamps])
        return [stamps[int(i)] for i in np.flatnonzero(np.linalg.norm(pos - cur, axis=1) < st.cfg.tau)]

    def history_at(self, s: int) -> Optional[Keyframe]:
        """History keyframe ``s`` expanded at its current pose (None: its spill file was lost)."""
        st = self.st
        rec = st.history.get(s)     # None: its spill file was lost (reported); skip this turn
        if rec is None:
            return None
        kf = expand_keyframe(rec, s, st.poses[s], st.camera)
        k = st.depth_scale.get(s)
        if k is not None:           # similarity increments since it left the window
            scale_keyframe_depth(kf, k)
        return kf

    def step(self, given: Optional[Keyframe] = None) -> dict:
        """One training iteration; returns its loss terms and the render's PSNR (dB). ``given``: a
        keyframe to train on instead of the sampled one (taken like a history keyframe: the window
        scores are left alone)."""
        st = self.st
        cfg = st.cfg
        gm = st.gm
        hist = given if given is not None else self.history_keyframe()
        kf = hist if hist is not None else self.next_keyframe(self.queue)
        # a coarse iteration (cfg.coarse_fraction of the window's): the keyframe at 1/coarse_factor
        # resolution; like a history keyframe it leaves the scores and loss maps alone
        coarse = hist is None and cfg.coarse_fraction > 0 and \
            float(torch.rand((), generator=st.rng)) < cfg.coarse_fraction
        if coarse:
            kf = self.coarse_of(kf)
        scored = hist is None and not coarse
        T_cw = pose_inverse(kf.T_wc)
        leaves = {p: getattr(gm, p).detach().requires_grad_(True) for p in PARAM_FIELDS}
        stale = st.loss_maps.get(kf.stamp_ns) if scored else None
        with timed("mapping", "render"):
            out = st.rasterize(gm, T_cw, kf.camera, sample_ratio=cfg.sample_ratio, loss_map=stale, **leaves)
        terms: dict = {}
        with timed("mapping", "loss"):
            loss = self.losses(out, kf, terms)
        l1 = terms.pop("l1_map")
        if cfg.sample_ratio < 1.0:
            # per tile, the pixels with the highest colour error L_rgb(u) (the paper's per-pixel
            # loss, also the error score's map); ranking by every term's share costs PSNR
            # (docs/mapping.md, sampled backward)
            out.set_sample_map(l1)
        with timed("mapping", "backward"):
            loss.backward()
        terms["psnr"] = -10 * math.log10(max(float((out.color.detach().clamp(0, 1) - kf.image).pow(2).mean()), 1e-12))
        with torch.no_grad():
            if scored:
                # score bookkeeping (window keyframes only; error w.r.t. the last loss map)
                st.loss_maps[kf.stamp_ns] = l1.to(torch.float32)
                with timed("mapping", "scores"):
                    self.scores.step_post_backward(gm, kf.stamp_ns, out)
            with timed("mapping", "optimiser step"):
                self._adam_step(gm, leaves, out)
            st.render_count += 1
            with timed("mapping", "scores"):
                st.gm = self.scores.after_train_step(st.gm, st.render_count, st.loss_maps)
        return terms

    def _adam_step(self, gm: GaussianMap, leaves: dict[str, torch.Tensor], out) -> None:
        """Sparse Adam on the unstable Gaussians the render reached (``radii > 0``); non-finite
        gradient entries are zeroed (and counted) so a degenerate splat cannot poison the map."""
        cfg = self.st.cfg
        rows = ((out.radii > 0).to(self.st.device) & ~gm.stable).nonzero()[:, 0]
        if not rows.numel():
            return
        gm.adam_step[rows] += 1
        lrs = self.lr_columns()
        betas = (cfg.adam_betas[0], cfg.adam_betas[1])
        for p in PARAM_FIELDS:
            g = leaves[p].grad
            if g is None:
                continue
            bad = ~torch.isfinite(g)
            if bool(bad.any()):
                self.st.counters["nonfinite_grads"] += int(bad.reshape(len(g), -1).any(1).sum())
                g = torch.where(bad, torch.zeros((), dtype=g.dtype), g)
            sparse_adam_step_fast(getattr(gm, p), g, getattr(gm, f"m_{p}"), getattr(gm, f"v_{p}"),
                                  gm.adam_step, rows, lrs[p], betas, cfg.adam_eps)

    def lr_columns(self) -> dict[str, np.ndarray]:
        """Learning rate per column of each parameter viewed as (N, D) (per Adam step; means in m,
        log-scales in log units, opacities in logits; higher SH bands at a twentieth of the DC)."""
        cfg = self.st.cfg
        lr_means = cfg.lr_means * (cfg.lr_means_outdoor_factor if cfg.outdoor else 1.0)
        k = (cfg.sh_degree + 1) ** 2
        lr_sh = np.full((k, 3), cfg.lr_sh / 20.0)
        lr_sh[0] = cfg.lr_sh
        return dict(means=np.full(3, lr_means), quats=np.full(4, cfg.lr_quats), log_scales=np.full(2, cfg.lr_scales),
                    opacity_logits=np.full(1, cfg.lr_opacity), sh=lr_sh.reshape(-1))
