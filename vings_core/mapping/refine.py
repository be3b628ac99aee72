"""Single-to-multi pose refinement (paper): keyframe poses corrected against the map by rendering
window keyframes, with a first-order (Adam on autograd gradients) or a second-order (damped
Gauss-Newton, :mod:`.pose_gn`) solver.

Each refinement call solves for camera-frame deltas ``xi_k`` (se(3): translation first, m, then
rotation, rad) of the keyframes that may move: ``T_k <- T_k exp(xi_k)`` (``T_k`` = ``T_wc``). In
``multi`` mode a delta also moves keyframe k's Gaussians (ID(g) = k) by ``T_k exp(xi_k) T_k^-1``
(world frame); in ``single`` mode only the rendered camera moves.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np
import torch

from ..geometry import pose_inverse, rotmat_to_quat, se3_exp
from ..render import rasterize_2dgs
from ..render.sh import rotate_sh
from ..types import Keyframe
from ..util import log
from . import pose_gn as GN
from .config import RefineMode, RefineSolver
from .gaussians import GaussianMap, quat_multiply
from .state import MapState
from .training import Trainer
from ..profiling import profiled


@dataclass
class RefineCtx:
    """One refinement call's fixed inputs: the Gaussians used, the keyframes whose poses may
    move (``owners``, sorted stamps), each Gaussian's owner index (multi mode), their poses ``T_wc``
    at the call's start and which are held (gauge)."""

    gm: GaussianMap
    mode: RefineMode
    owners: torch.Tensor
    inv: Optional[torch.Tensor]
    T_own: torch.Tensor
    T_own_inv: torch.Tensor
    fixed: torch.Tensor


class PoseRefiner:
    """Pose refinement of the keyframes in ``st`` (:class:`MapState`); renders and losses through
    ``trainer``. Owns its solvers' state across calls: the per-keyframe Adam moments and shared
    second moment, the Gauss-Newton step counts, and its own shuffled round of window keyframes."""

    def __init__(self, st: MapState, trainer: Trainer) -> None:
        self.st = st
        self.trainer = trainer
        self.queue: list[int] = []                    # shuffled round of window stamps
        self.adam: dict[int, tuple] = {}              # stamp -> (m (6,), v (6,), steps) of Adam refinement
        self.adam_v = np.zeros(7)                     # shared second moment of pose gradients (6,) + its steps
        self.gn_steps: dict[int, int] = {}            # stamp -> Gauss-Newton steps taken (refine_gn_decay)

    def new_round(self) -> None:
        """Start a new shuffled round (the window changed)."""
        self.queue = []

    @profiled("mapping", "pose refinement")
    def run(self, mode: RefineMode, iters: int) -> dict[int, tuple[np.ndarray, np.ndarray]]:
        """``iters`` refinement renders in ``mode`` (single or multi); returns the pose changes
        ``{stamp: (T_old, T_new)}`` (``T_wc``) for the caller to commit, moving the Gaussians in
        multi mode."""
        ctx = self._context(mode)
        solve = self._gn if self.st.cfg.refine_solver == RefineSolver.GN else self._adam
        xi = solve(ctx, iters)
        # T_k <- T_k exp(xi_k) (camera-frame delta)
        moved = (xi.abs().sum(1) > 0).nonzero()[:, 0]
        if moved.numel() == 0:
            return {}
        D = se3_exp(xi[moved]).numpy()
        poses = self.st.poses
        changes = {}
        for j, i in enumerate(moved.tolist()):
            s = int(ctx.owners[i])
            changes[s] = (poses[s], poses[s] @ D[j])
        return changes

    def _context(self, mode: RefineMode) -> RefineCtx:
        st = self.st
        gm = st.gm
        ok = gm.finite_rows()
        if not bool(ok.all()):
            # a non-finite Gaussian (deleted at the next keyframe) would make its owner's whole
            # gradient NaN (0 x NaN through the rigid motion) and silently freeze that pose
            log.debug("pose refinement: %d non-finite Gaussians left out", int((~ok).sum()))
            gm = gm.index(ok)
        first = st.order[0] if (st.cfg.refine_fix_first and st.order) else None
        if mode == RefineMode.MULTI:
            owners = torch.unique(gm.kf_id).cpu()
            win = torch.tensor([kf.stamp_ns for kf in st.window], dtype=torch.int64)
            owners = torch.sort(torch.cat([owners, win[~torch.isin(win, owners)]])).values
            inv = torch.searchsorted(owners, gm.kf_id.cpu())
        else:
            owners = torch.tensor(sorted(kf.stamp_ns for kf in st.window), dtype=torch.int64)
            inv = None
        U = len(owners)
        T_own = torch.from_numpy(np.stack([st.poses.get(int(o), np.eye(4)) for o in owners.tolist()])) \
            if U else torch.zeros(0, 4, 4, dtype=torch.float64)
        fixed = (owners == first) if first is not None else torch.zeros(U, dtype=torch.bool)
        return RefineCtx(gm=gm, mode=mode, owners=owners, inv=inv, T_own=T_own, T_own_inv=pose_inverse(T_own),
                         fixed=fixed)

    def depth_scale(self) -> float:
        """Median over the window keyframes of their median valid depth (scene units): the length
        scale of pose-refinement translation steps (1.0 when no keyframe has depth)."""
        meds = []
        for kf in self.st.window:
            d = kf.depth[kf.valid & (kf.depth > 0)]
            if d.numel():
                meds.append(float(d.median()))
        return float(np.median(meds)) if meds else 1.0

    def _render(self, ctx: RefineCtx, xi: torch.Tensor, r: int, kf: Keyframe):
        """Render keyframe ``r`` (index into ``ctx.owners``) with the deltas ``xi`` applied: its camera
        ``T_r exp(xi_r)``; in multi mode every owner's Gaussians moved by ``T_k exp(xi_k) T_k^-1``.
        Differentiable in ``xi``. Returns the render and, in multi mode, ``(means, quats, T_cw)`` it used."""
        D = se3_exp(xi)                                   # (U, 4, 4) camera-frame deltas
        T_cw = pose_inverse(ctx.T_own[r] @ D[r])
        if ctx.mode != RefineMode.MULTI:
            return self.st.rasterize(ctx.gm, T_cw.to(torch.float32), kf.camera, sample_ratio=1.0), None
        gm, inv = ctx.gm, ctx.inv
        Wd = ctx.T_own @ D @ ctx.T_own_inv                 # world-frame motion of each owner's Gaussians
        # index_select, not Wd[inv]: the backward of advanced indexing (index_put_ with
        # accumulate) sums in a thread-dependent order on the CPU, index_select's does not
        Dg = torch.index_select(Wd.to(torch.float32), 0, inv)
        means = (Dg[:, :3, :3] @ gm.means[:, :, None])[:, :, 0] + Dg[:, :3, 3]
        qd = torch.index_select(rotmat_to_quat(Wd[:, :3, :3]).to(torch.float32), 0, inv)
        quats = quat_multiply(qd, gm.quats)
        sh = rotate_sh(gm.sh, Wd[:, :3, :3], inv)        # view-dependent colour turns along
        out = self.st.rasterize(gm, T_cw.to(torch.float32), kf.camera, sample_ratio=1.0,
                                means=means, quats=quats, sh=sh)
        return out, (means, quats, T_cw)

    def _visible(self, ctx: RefineCtx, out, r: int) -> torch.Tensor:
        """``(U,)`` bool: the poses this render may update. A pose is updated only when the render
        shows enough of what constrains it (refine_min_pixels, in pixel weights sum alpha T): in
        single mode the rendered keyframe needs that much map in view; in multi mode another keyframe
        needs that much contribution from its own Gaussians (one seen through a few pixels at the
        edge of the view does not step on their noise), and the rendered keyframe that much from
        OTHER keyframes' Gaussians: its own move with its camera, so they cannot constrain it."""
        min_px = self.st.cfg.refine_min_pixels
        U = len(ctx.owners)
        contrib = out.contribution.detach().to(torch.float64)
        vis = torch.zeros(U, dtype=torch.bool)
        if ctx.mode == RefineMode.MULTI:
            per_owner = torch.zeros(U, dtype=torch.float64).index_add_(0, ctx.inv, contrib)
            vis = per_owner >= min_px
            vis[r] = float(contrib.sum() - per_owner[r]) >= min_px
        else:
            vis[r] = float(contrib.sum()) >= min_px
        return vis & ~ctx.fixed

    def _adam(self, ctx: RefineCtx, iters: int) -> torch.Tensor:
        """First-order refinement: autograd gradients of the training loss, Adam steps. Returns
        the deltas ``xi`` ``(U, 6)``."""
        cfg = self.st.cfg
        owners = ctx.owners
        U = len(owners)
        xi = torch.zeros(U, 6, dtype=torch.float64)
        # Adam state per keyframe persists across calls (like a per-keyframe pose optimiser)
        saved = [self.adam.get(int(o)) for o in owners.tolist()]
        zero = torch.zeros(6, dtype=torch.float64)
        m = torch.stack([torch.from_numpy(a[0]) if a is not None else zero for a in saved]) \
            if U else torch.zeros(0, 6, dtype=torch.float64)
        v = torch.stack([torch.from_numpy(a[1]) if a is not None else zero for a in saved]) \
            if U else torch.zeros(0, 6, dtype=torch.float64)
        steps = torch.tensor([int(a[2]) if a is not None else 0 for a in saved], dtype=torch.int64)
        lr_t = cfg.refine_lr_trans_rel * self.depth_scale()
        lr = torch.tensor([lr_t] * 3 + [cfg.refine_lr_rot] * 3, dtype=torch.float64)
        b1, b2, eps = 0.9, 0.999, 1e-12
        vs = self.adam_v
        for _ in range(iters):
            kf = self.trainer.next_keyframe(self.queue)
            r = int(torch.searchsorted(owners, torch.tensor(kf.stamp_ns)))
            x = xi.clone().requires_grad_(True)
            out, _ = self._render(ctx, x, r, kf)
            terms: dict = {}
            loss = self.trainer.losses(out, kf, terms, with_normal=False, with_acc=False, expected_depth=True)
            terms.pop("l1_map", None)
            loss.backward()
            g = x.grad.detach().clone()
            upd = self._visible(ctx, out, r) & torch.isfinite(g).all(1)
            if not upd.any():
                continue
            steps[upd] += 1
            m[upd] = b1 * m[upd] + (1 - b1) * g[upd]
            v[upd] = b2 * v[upd] + (1 - b2) * g[upd] ** 2
            t = steps[upd].to(torch.float64)[:, None]
            # second moment shared by all keyframes (per se(3) component): a keyframe whose gradient
            # is small compared with the others' (a direction the render hardly observes, e.g. a
            # keyframe that sees mostly its own Gaussians) takes a proportionally small step; a
            # per-keyframe normalisation would blow its gradient noise up to full-size steps
            vs[:6] = b2 * vs[:6] + (1 - b2) * (g[upd] ** 2).mean(0).numpy()
            vs[6] += 1
            v_hat = torch.as_tensor(vs[:6] / (1 - b2 ** vs[6]))[None]
            # step size lr / sqrt(t) over the keyframe's lifetime of refinement steps (stochastic
            # approximation schedule): Adam's steps are ~lr whatever the gradient size, so with a
            # constant rate a converged pose random-walks on the gradient noise (~lr sqrt(N) after N
            # steps); with the decay the walk stays ~lr sqrt(ln N) while sum lr/sqrt(t) still allows
            # centimetre corrections
            rate = lr / t.sqrt() if cfg.refine_lr_decay else lr
            xi[upd] -= rate * (m[upd] / (1 - b1 ** t)) / (v_hat.sqrt() + eps)
        for i in (steps > 0).nonzero()[:, 0].tolist():
            self.adam[int(owners[i])] = (m[i].numpy().copy(), v[i].numpy().copy(), int(steps[i]))
        return xi

    @torch.no_grad()
    def _owner_shares(self, ctx: RefineCtx, moved, kf: Keyframe, vis_idx: list[int]) -> torch.Tensor:
        """``(H, W, V)`` each listed owner's share ``sum_{g in k} alpha T`` of the render of ``kf``
        (renders of indicator colours, three owners per render)."""
        gm = ctx.gm
        means, quats, T_cw = moved
        scales = torch.exp(gm.log_scales)
        opac = torch.sigmoid(gm.opacity_logits)
        shares = []
        for j in range(0, len(vis_idx), 3):
            colors = torch.zeros(len(gm), 3, dtype=gm.means.dtype)
            for c, k in enumerate(vis_idx[j:j + 3]):
                colors[:, c] = (ctx.inv == k).to(colors.dtype)
            o = rasterize_2dgs(means, quats, scales, opac, colors, T_cw.to(torch.float32), kf.camera,
                               background=torch.zeros(3))
            shares.append(o.color[..., :len(vis_idx[j:j + 3])])
        return torch.cat(shares, -1).to(torch.float64)

    @torch.no_grad()
    def _gn(self, ctx: RefineCtx, iters: int) -> torch.Tensor:
        """Second-order refinement (:mod:`.pose_gn`): the normal equations of ``refine_gn_batch``
        renders (window keyframes in turn; 0: as many as the window holds) are summed and solved
        jointly for every pose they constrain, one damped Gauss-Newton step per batch. Steps scale
        with the residual, so a far pose travels in a few steps and a converged one stays put (no
        random walk on gradient noise); the joint solve lets each pose be fixed by the renders
        that observe it best (one render alone leaves poorly observed directions free). Returns
        the deltas ``xi`` ``(U, 6)``."""
        cfg = self.st.cfg
        owners = ctx.owners
        xi = torch.zeros(len(owners), 6, dtype=torch.float64)
        max_t = cfg.refine_gn_max_trans_rel * self.depth_scale()
        batch = cfg.refine_gn_batch or len(self.st.window)
        eq = _GNSystem.over_window(owners, self.st.window)
        for it in range(iters):
            kf = self.trainer.next_keyframe(self.queue)
            r = int(torch.searchsorted(owners, torch.tensor(kf.stamp_ns)))
            eq.rendered[eq.pos[r]] = True
            self._gn_accumulate(ctx, eq, xi, r, kf)
            if (it + 1) % batch == 0 or it == iters - 1:
                # only poses whose own camera was rendered in the batch step (so keyframes that
                # left the window keep theirs): a keyframe seen only through its Gaussians in
                # others' views has a weakly observed rotation (turning about its camera centre ~
                # shifting a distant patch), which the step would take freely, and a joint solve
                # would split each new keyframe's error between it and the old owners it sees
                eq.free &= eq.rendered
                if eq.free.any():
                    step = GN.damped_step(eq.H, eq.b, eq.free, cfg.refine_gn_damping, max_t, cfg.refine_gn_max_rot)
                    if cfg.refine_gn_decay:
                        step = step * self.gn_step_scale(owners[eq.win_idx], eq.free)[:, None]
                    xi[eq.win_idx] += step
                eq.reset()
        return xi

    def _gn_accumulate(self, ctx: RefineCtx, eq: "_GNSystem", xi: torch.Tensor, r: int, kf: Keyframe) -> None:
        """Render keyframe ``r`` at the deltas ``xi`` and add its normal equations to ``eq``."""
        cfg = self.st.cfg
        terms = None
        out, moved = self._render(ctx, xi, r, kf)
        upd = self._visible(ctx, out, r)
        if upd.any():
            aux = self.trainer.keyframe_aux(kf)
            terms = GN.pixel_terms(out.color, out.depth / out.alpha.clamp_min(1e-6), out.alpha, kf.image,
                                   kf.depth, aux["w_depth"], aux["usable"], kf.camera,
                                   sigma_rgb=cfg.refine_gn_sigma_rgb, sigma_depth_rel=cfg.depth_rel_std0,
                                   huber=cfg.refine_gn_huber, blur_px=cfg.refine_gn_blur_px,
                                   stride=cfg.refine_gn_stride)
        if terms is None or terms.pix.numel() < 6:
            return
        T_cur = ctx.T_own @ se3_exp(xi)
        if ctx.mode == RefineMode.MULTI:
            # the others' content enters as held (moves by -xi_r), without share renders
            idx = sorted(set((upd & eq.in_window).nonzero()[:, 0].tolist()) | {r})
            w = self._owner_shares(ctx, moved, kf, idx)                   # (H, W, V)
            w = (w / out.alpha.to(torch.float64).clamp_min(1e-6)[..., None]).reshape(-1, len(idx))
            coeff = w[terms.pix]
            jr = idx.index(r)
            # content of r moves with its camera; all else (other owners, held ones) by -xi_r
            coeff[:, jr] = coeff[:, jr] - 1.0
            adj = GN.se3_adjoint(pose_inverse(T_cur[r])[None] @ T_cur[idx])
        else:
            idx = [r]
            coeff = -torch.ones(terms.pix.numel(), 1, dtype=torch.float64)
            adj = torch.eye(6, dtype=torch.float64)[None]
        H, b = GN.owner_system(terms, coeff, adj)
        loc = eq.pos[idx]
        cols = (loc[:, None] * 6 + torch.arange(6)).reshape(-1)
        eq.H[cols[:, None], cols[None]] += H
        eq.b[cols] += b
        eq.free[loc[upd[idx]]] = True

    def gn_step_scale(self, stamps: torch.Tensor, free: torch.Tensor) -> torch.Tensor:
        """``(n,)`` factors ``1/t`` of the free keyframes' steps (``t``: that keyframe's Gauss-Newton
        steps so far, this one included; held ones 0), counting this step. Each step goes to the
        minimum of the current map's cost, which moves as training follows the poses (noise of ~1 mm
        here even from exact poses and depth); full steps would random-walk on it. With ``1/t``
        (stochastic approximation: the factors sum to infinity, their squares do not) a keyframe's
        pose converges to the average of the minima its steps saw; its ~10 decayed steps sum to ~2.9
        full ones, which stops a 2 cm error short (measured, docs/mapping.md), hence off by default."""
        f = torch.zeros(len(stamps), dtype=torch.float64)
        for i in free.nonzero()[:, 0].tolist():
            s = int(stamps[i])
            t = self.gn_steps.get(s, 0) + 1
            self.gn_steps[s] = t
            f[i] = 1.0 / t
        return f


@dataclass
class _GNSystem:
    """The joint normal equations of one Gauss-Newton batch over the window keyframes (the only
    ones rendered, so the only ones that can step): ``H`` ``(6n, 6n)``, ``b`` ``(6n,)``, which of
    the ``n`` poses a render constrains (``free``) and which were rendered; ``pos`` maps an owner
    index to its place among them (-1: not in the window), ``win_idx`` the reverse."""

    in_window: torch.Tensor
    win_idx: torch.Tensor
    pos: torch.Tensor
    H: torch.Tensor
    b: torch.Tensor
    free: torch.Tensor
    rendered: torch.Tensor

    @staticmethod
    def over_window(owners: torch.Tensor, window: list[Keyframe]) -> "_GNSystem":
        in_window = torch.isin(owners, torch.tensor([kf.stamp_ns for kf in window], dtype=torch.int64))
        win_idx = in_window.nonzero()[:, 0]
        n = len(win_idx)
        pos = torch.full((len(owners),), -1, dtype=torch.int64)
        pos[win_idx] = torch.arange(n)
        return _GNSystem(in_window=in_window, win_idx=win_idx, pos=pos,
                         H=torch.zeros(6 * n, 6 * n, dtype=torch.float64), b=torch.zeros(6 * n, dtype=torch.float64),
                         free=torch.zeros(n, dtype=torch.bool), rendered=torch.zeros(n, dtype=torch.bool))

    def reset(self) -> None:
        """Start the next batch."""
        self.H.zero_()
        self.b.zero_()
        self.free[:] = False
        self.rendered[:] = False
