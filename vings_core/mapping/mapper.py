"""Stateful online 2DGS mapper (paper section "2D Gaussian Map").

Typical use (see docs/mapping.md)::

    m = Mapper(MapperConfig())
    for kf in keyframes:            # vings_core.types.Keyframe, T_wc camera-to-world
        m.add_keyframe(kf)          # render, delete conflicting, add in low-accumulation regions
        m.train()                   # iters_per_keyframe iterations on the local window
        poses = m.refine_poses()    # single-to-multi pose refinement -> {stamp_ns: T_wc}
    out = m.render(T_wc, camera)    # numpy color / depth / normal / alpha
    m.save_ply("map.ply"); m.save_checkpoint("map.ckpt.npz")

:class:`Mapper` is a facade over parts with one job each, sharing one :class:`~.state.MapState`:
map growth (:mod:`.growth`), training (:mod:`.training`) with the score manager strategy
(:mod:`.score_manager`), pose refinement (:mod:`.refine`), storage tiers (:mod:`.storage`) and
checkpoints (:mod:`.checkpoint`).

Frames: ``T_wc`` 4x4 float64 camera-to-world; Gaussians in the world frame (m). Nothing here loops
over Gaussians or pixels in Python.
"""
from __future__ import annotations

import bisect
import itertools
import os
import time
from dataclasses import replace
from typing import Iterator, Optional

import numpy as np
import torch

from ..errors import ConfigError, InputError
from ..geometry import check_rigid_pose, check_sim3, sim3_apply_to_pose, sim3_scale
from ..types import CameraModel, Keyframe
from . import checkpoint as ckpt
from .config import MapperConfig, RefineMode
from .gaussians import GaussianMap, sh_dc_to_rgb
from .growth import check_keyframe, densify
from .history import compact_keyframe, scale_keyframe_depth
from .refine import PoseRefiner
from .score_manager import ScoreManager
from .state import MapState
from .storage import active_split, owner_distances
from .training import Trainer


def _shared(name: str, doc: str, settable: bool = True) -> property:
    """A Mapper attribute that is the shared state's ``name``."""
    set_ = (lambda self, v: setattr(self.state, name, v)) if settable else None
    return property(lambda self: getattr(self.state, name), set_, doc=doc)


class Mapper:
    """Online 2D Gaussian map trained from keyframes.

    ``config``: :class:`MapperConfig` (None = defaults). ``device``: torch device of the active set
    ('cpu'; the rasterizer routes CUDA tensors to gsplat when installed).
    """

    gm = _shared("gm", "The active Gaussians (:class:`GaussianMap`): rendered and optimised.")
    passive = _shared("passive", "The passive store (:class:`~.storage.PassiveStore`).")
    window = _shared("window", "The local window's keyframes, oldest first.")
    camera = _shared("camera", "The keyframes' camera model (None before the first keyframe).")
    render_count = _shared("render_count", "Training renders so far (the score manager's clock).")
    kf_count = _shared("kf_count", "Keyframes added so far.")
    rng = _shared("rng", "The random generator of every draw the mapper makes.")
    counters = _shared("counters", "Event counters (added, deleted, pruned, tier moves, ...).", settable=False)

    def __init__(self, config: Optional[MapperConfig] = None, device: str = "cpu"):
        self.cfg = config if config is not None else MapperConfig()
        self.cfg.validate()
        self.device = torch.device(device)
        if self.device.type != "cpu":
            # the renderer has a CUDA route (gsplat), but the mapper's sparse optimiser, SSIM and
            # sampled backward are CPU (numba) kernels
            raise ConfigError(f"Mapper(device={device!r}): the mapper runs on the CPU only (its optimiser, "
                              "loss and sampled-backward kernels are numba); render a saved map on the GPU "
                              "with vings_core.render.rasterize_2dgs instead")
        self.state = MapState.create(self.cfg, self.device)
        self.scores = ScoreManager(self.cfg, self.state.counters)
        self.trainer = Trainer(self.state, self.scores)
        self.refiner = PoseRefiner(self.state, self.trainer)
        self.timings = dict(add_s=0.0, train_s=0.0, refine_s=0.0)

    # ================================================================== public API
    @property
    def num_gaussians(self) -> int:
        """Active + passive Gaussians."""
        return len(self.gm) + self.passive.num_gaussians

    @property
    def num_active(self) -> int:
        return len(self.gm)

    @property
    def num_passive(self) -> int:
        return self.passive.num_gaussians

    def keyframe_poses(self) -> dict[int, np.ndarray]:
        """``{stamp_ns: T_wc}`` of every keyframe added (copies, float64 4x4)."""
        return {s: self.state.poses[s].copy() for s in self.state.order}

    def set_keyframe_poses(self, poses: dict[int, np.ndarray], move_gaussians: bool = True) -> None:
        """Replace keyframe poses (loop closure, front-end updates).

        With ``move_gaussians`` each keyframe's Gaussians (ID(g) = that keyframe) follow it rigidly:
        ``mu' = T_new T_old^-1 mu`` (paper, loop correction); passive ones when they come back.
        Unknown stamps raise :class:`InputError`.
        """
        known = self.state.poses
        unknown = [s for s in poses if int(s) not in known]
        if unknown:
            raise InputError(f"set_keyframe_poses: unknown keyframe stamps {unknown[:5]}")
        # every pose checked before any is applied: a bad one leaves the map as it was
        checked = {s: check_rigid_pose(T, f"set_keyframe_poses[{s}]", tol=1e-2, project=True) for s, T in poses.items()}
        changes = {int(s): (known[int(s)], T) for s, T in checked.items() if not np.array_equal(T, known[int(s)])}
        self._commit_poses(changes, move_gaussians)

    def apply_increments(self, increments: dict[int, np.ndarray]) -> int:
        """Apply world-frame similarity increments ``{stamp_ns: C}`` (4x4 ``[[s R, t], [0, 1]]``
        float64, acting on world points as ``x -> s R x + t``) to keyframes: the pose becomes
        :func:`~vings_core.geometry.sim3_apply_to_pose` ``(C, T_old)`` (camera centre mapped by
        ``C``, orientation rotated by ``R``) and the keyframe's Gaussians (ID(g) = it; passive ones
        when they come back) follow ``C``: means mapped, rotations and view-dependent colour turned
        by ``R``, scales multiplied by ``s``. A rigid ``C`` does what :meth:`set_keyframe_poses`
        does with ``C T_old``. Unknown stamps are ignored; every increment is checked before any is
        applied (:class:`InputError`). Returns the number of keyframes moved."""
        known = self.state.poses
        checked = {int(s): _check_similarity(C, f"apply_increments[{s}]") for s, C in increments.items()
                   if int(s) in known}
        changes, scales = {}, {}
        for s, (C, k) in checked.items():
            if not np.array_equal(C, np.eye(4)):
                changes[s] = (known[s], sim3_apply_to_pose(C, known[s]))
                scales[s] = k
        self._commit_poses(changes, move_gaussians=True, scales=scales)
        return len(changes)

    def add_keyframe(self, kf: Keyframe) -> dict:
        """Insert a keyframe: tier update (every ``delta_k``), with its dynamic mask (``kf.dynamic``)
        erase what moving objects left (:meth:`set_dynamic_mask`), render it, delete conflicting
        Gaussians, add Gaussians from its depth in low-accumulation regions (never in dynamic
        pixels). Returns counts."""
        t0 = time.perf_counter()
        st, cfg = self.state, self.cfg
        check_keyframe(kf, st.poses, st.camera)
        if st.camera is None:
            st.camera = kf.camera          # only once the first keyframe is known to be good
        T_ok = torch.from_numpy(check_rigid_pose(kf.T_wc, f"keyframe {kf.stamp_ns} T_wc", tol=1e-2, project=True))
        kf = replace(kf, T_wc=T_ok, image=kf.image.to(torch.float32)[..., :3].contiguous(),
                     depth=kf.depth.to(torch.float32), inv_depth_var=kf.inv_depth_var.to(torch.float32),
                     valid=kf.valid.to(torch.bool))
        s = int(kf.stamp_ns)
        st.poses[s] = kf.T_wc.numpy().copy()
        bisect.insort(st.order, s)      # stamp order; a late (re-sent) keyframe in its place
        st.window.append(kf)
        left = None
        if len(st.window) > cfg.window_size:
            old = st.window.pop(0)
            if cfg.history_ratio > 0:
                st.history.put(old.stamp_ns, compact_keyframe(old))
            st.loss_maps.pop(old.stamp_ns, None)
            self.trainer.forget(old.stamp_ns)
            left = old.stamp_ns
        self.scores.keyframe_added(st.gm, s, left)
        self.trainer.new_round()
        self.refiner.new_round()
        st.kf_count += 1
        info = {"stamp_ns": s}
        if st.kf_count % cfg.delta_k == 0:
            info.update(self.update_tiers(st.poses[s]))
        if kf.dynamic is not None:
            info["erased_dynamic"] = self._erase_dynamic(kf)
        info.update(densify(st, kf))
        if len(st.gm) > cfg.max_active:
            info.update(self.update_tiers(st.poses[s]))
        self.timings["add_s"] += time.perf_counter() - t0
        return info

    def set_dynamic_mask(self, stamp: int, mask) -> int:
        """Keyframe ``stamp``'s dynamic mask (``(H, W)`` bool, True = moving object) arriving after
        the keyframe was added: the keyframe (in the window or the history) keeps its dynamic
        pixels out of training from now on, and the Gaussians inside the mask whose ID(g) keyframe
        is among the ``erase_owner_keyframes`` latest ones are erased (what the object left before
        it was caught, this keyframe's own included). Returns the number erased; a stamp the mapper
        does not know is ignored (0)."""
        st = self.state
        s = int(stamp)
        m = torch.as_tensor(np.asarray(mask)).to(torch.bool)
        for i, kf in enumerate(st.window):
            if kf.stamp_ns == s:
                if tuple(m.shape) != tuple(kf.valid.shape):
                    raise ValueError(f"dynamic mask of keyframe {s} has shape {tuple(m.shape)}, expected "
                                     f"{tuple(kf.valid.shape)}")
                st.window[i] = kf = replace(kf, dynamic=m)
                self.trainer.forget(s)
                if s in st.loss_maps:       # the error map that drives sampling and scores
                    st.loss_maps[s] = torch.where(m, torch.zeros((), dtype=st.loss_maps[s].dtype), st.loss_maps[s])
                return self._erase_dynamic(kf, include_own=True)
        if s in st.history:
            rec = st.history.get(s)
            if rec is not None:
                if tuple(rec["valid"].shape) != tuple(m.shape):
                    raise ValueError(f"dynamic mask of keyframe {s} has shape {tuple(m.shape)}, expected "
                                     f"{tuple(rec['valid'].shape)}")
                st.history.put(s, {**rec, "dynamic": m.clone()})
        return 0

    def _erase_dynamic(self, kf: Keyframe, include_own: bool = False) -> int:
        """Remove the active Gaussians whose centre projects into ``kf.dynamic``, no deeper than
        the keyframe's depth there (``delete_depth_rel`` margin; any depth where it has none), and
        whose ID(g) keyframe is among the ``erase_owner_keyframes`` latest before ``kf`` (and ``kf``
        itself with ``include_own``)."""
        st, n_own = self.state, int(self.cfg.erase_owner_keyframes)
        if kf.dynamic is None or not bool(kf.dynamic.any()) or not len(st.gm) or n_own == 0:
            return 0
        s = int(kf.stamp_ns)
        before = [o for o in st.order if o < s][-n_own:]
        owners = torch.tensor(before + ([s] if include_own else []), dtype=st.gm.kf_id.dtype)
        recent = torch.isin(st.gm.kf_id, owners)
        if not bool(recent.any()):
            return 0
        T_cw = torch.from_numpy(np.linalg.inv(kf.T_wc.numpy()))
        cam = kf.camera
        p = st.gm.means.to(torch.float64) @ T_cw[:3, :3].T + T_cw[:3, 3]
        z = p[:, 2]
        u = torch.round(cam.fx * p[:, 0] / z.clamp_min(1e-9) + cam.cx).long()
        v = torch.round(cam.fy * p[:, 1] / z.clamp_min(1e-9) + cam.cy).long()
        inside = (z > 1e-6) & (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
        hit = torch.zeros_like(inside)
        hit[inside] = kf.dynamic[v[inside], u[inside]]
        # only what lies at or in front of the object's observed surface: the static map behind it
        # (hidden now) stays; where the keyframe has no depth, what projects into the mask goes
        D = torch.zeros_like(z)
        D[inside] = kf.depth[v[inside], u[inside]].to(D.dtype)
        front = (D <= 0) | (z < D * (1 + self.cfg.delete_depth_rel))
        kill = hit & recent & front
        n = int(kill.sum())
        if n:
            st.gm = st.gm.remove(kill)
            st.counters["erased_dynamic"] += n
        return n

    def train(self, iters: Optional[int] = None) -> dict:
        """Run ``iters`` (default ``iters_per_keyframe``) training iterations on the local window.

        Returns stats: iterations, mean loss terms, PSNR of the last renders, Gaussian counts."""
        iters = self.cfg.iters_per_keyframe if iters is None else int(iters)
        t0 = time.perf_counter()
        acc = dict(loss=0.0, rgb=0.0, depth=0.0, normal=0.0, acc=0.0, psnr=0.0)
        done = 0
        for _ in range(iters):
            if not self.window or len(self.gm) == 0:
                break
            terms = self.trainer.step()
            done += 1
            for k in acc:
                acc[k] += terms[k]
        dt = time.perf_counter() - t0
        self.timings["train_s"] += dt
        out = {k: v / max(1, done) for k, v in acc.items()}
        out.update(iterations=done, time_s=dt, num_active=len(self.gm), num_passive=self.passive.num_gaussians,
                   num_stable=int(self.gm.stable.sum()), **self.counters)
        return out

    def retrain_region(self, iters: int, max_s: float, prune: bool = True) -> dict:
        """After a loop correction: ``iters`` training iterations cycling over the window keyframes
        and the history keyframes within ``tau`` of the newest one (the revisited region, where the
        corrected first visit and the new pass overlap); then (``prune``) remove the active
        Gaussians that lie in front of at least one of the trained views and contribute to none of
        them (their contribution score ``sum alpha T`` over the views is below
        ``loop_prune_contribution``): surfaces left doubled by the drift. The whole takes at most
        about ``max_s`` seconds (training stops at 3/4 of it, the prune's renders at the bound; the
        views rendered by then decide). Returns counts."""
        t0 = time.perf_counter()
        st = self.state
        stamps = [kf.stamp_ns for kf in st.window] + self.trainer.history_near()
        out = dict(retrain_iters=0, retrain_views=len(stamps), loop_pruned=0)
        if not stamps or len(self.gm) == 0:
            return out
        order = [stamps[int(i)] for i in torch.randperm(len(stamps), generator=st.rng)]
        win = {kf.stamp_ns: kf for kf in st.window}
        views: dict[int, Keyframe] = {}
        train_s = 0.75 * max_s if prune else max_s     # the prune's renders take the rest
        for it in range(int(iters)):
            if time.perf_counter() - t0 > train_s or len(self.gm) == 0:
                break
            s = order[it % len(order)]
            if s not in views:
                kf = win.get(s) or self.trainer.history_at(s)
                if kf is None:
                    continue
                views[s] = kf
            self.trainer.step(views[s])
            out["retrain_iters"] += 1
        if prune and views and len(self.gm):
            with torch.no_grad():
                seen = torch.zeros(len(self.gm), dtype=torch.bool)
                used = torch.zeros(len(self.gm), dtype=torch.float32)
                for kf in views.values():
                    if time.perf_counter() - t0 > max_s:       # the views rendered so far decide
                        break
                    T_cw = torch.linalg.inv(kf.T_wc.to(torch.float64))
                    r = self.state.rasterize(self.gm, T_cw, kf.camera, sample_ratio=1.0)
                    used += r.contribution.to(torch.float32)
                    seen |= _in_view(self.gm.means, T_cw, kf.camera)
                drop = seen & (used < self.cfg.loop_prune_contribution)
                n = int(drop.sum())
                if n:
                    st.gm = self.gm.remove(drop)
                    self.counters["pruned"] += n
                out["loop_pruned"] = n
        self.timings["train_s"] += time.perf_counter() - t0
        out["retrain_s"] = round(time.perf_counter() - t0, 3)
        return out

    def refine_poses(self, iters: Optional[int] = None,
                     mode: Optional[RefineMode | str] = None) -> dict[int, np.ndarray]:
        """Single-to-multi pose refinement; returns the refined ``{stamp_ns: T_wc}`` of all keyframes.

        Each iteration renders one window keyframe. ``mode`` (a :class:`RefineMode` or its value;
        default ``config.refine_mode``): ``multi``: the loss reaches the pose of every keyframe
        owning visible Gaussians (through ID(g)); a pose change of keyframe k moves its Gaussians
        rigidly with it, so the rendered keyframe's own Gaussians move with its camera. ``single``:
        only the rendered camera moves, the map is fixed (the MonoGS/SplaTAM baseline). ``none``:
        nothing. Updated poses replace the stored ones (and the window keyframes' ``T_wc``)."""
        want = self.cfg.refine_mode if mode is None else mode
        try:
            mode = RefineMode(want)
        except ValueError:
            raise InputError(f"refine_poses: mode must be none|single|multi, got {want!r}") from None
        iters = self.cfg.refine_iters if iters is None else int(iters)
        if mode == RefineMode.NONE or iters <= 0 or not self.window or len(self.gm) == 0:
            return self.keyframe_poses()
        t0 = time.perf_counter()
        changes = self.refiner.run(mode, iters)
        # single: only the cameras move, the owners' Gaussians (active and passive) stay
        self._commit_poses(changes, move_gaussians=(mode == RefineMode.MULTI))
        self.timings["refine_s"] += time.perf_counter() - t0
        return self.keyframe_poses()

    @torch.no_grad()
    def render(self, T_wc: np.ndarray, camera: CameraModel, include_passive: bool = True,
               owners_before: Optional[int] = None) -> dict:
        """Render the map from camera-to-world ``T_wc`` with ``camera``.

        Uses the active set plus (``include_passive``) the passive Gaussians whose ID(g) keyframe is
        within ``tau`` of the camera (read, not moved); with ``owners_before`` (a stamp, ns) only the
        Gaussians whose ID(g) keyframe is older than it (the map as an earlier visit left it, for
        loop verification). Returns numpy arrays: ``color`` (H, W, 3)
        float32 in [0, 1]; ``depth`` (H, W) expected z-depth (m, 0 where empty); ``normal`` (H, W, 3)
        unit normals in the camera frame (0 where empty); ``alpha`` (H, W) accumulated opacity.
        """
        T_wc = check_rigid_pose(T_wc, "render T_wc", tol=1e-2, project=True)
        gm = self.gm
        if include_passive and self.passive.num_gaussians:
            extra = self._peek_passive(T_wc[:3, 3], self.cfg.tau)
            if extra is not None:
                gm = GaussianMap.concat([gm, extra.to(self.device)])
        if owners_before is not None:
            gm = gm.index(torch.nonzero(gm.kf_id < int(owners_before)).flatten())
        out = self.state.rasterize(gm, torch.from_numpy(np.linalg.inv(T_wc)), camera, sample_ratio=1.0)
        a = out.alpha
        nrm = out.normal / torch.linalg.norm(out.normal, dim=-1, keepdim=True).clamp_min(1e-12)
        return {"color": out.color.clamp(0, 1).numpy().astype(np.float32),
                "depth": torch.where(a > 1e-4, out.depth / a.clamp_min(1e-10), torch.zeros_like(a)).numpy()
                .astype(np.float32),
                "normal": torch.where(a[..., None] > 1e-4, nrm, torch.zeros_like(nrm)).numpy().astype(np.float32),
                "alpha": a.numpy().astype(np.float32)}

    def all_gaussians(self) -> GaussianMap:
        """Active and passive Gaussians in one map (passive ones moved by pending pose changes)."""
        extra = self.passive.all(self.state.poses)
        return self.gm if extra is None else GaussianMap.concat([self.gm, extra.to(self.device)])

    def point_sample(self, max_points: int) -> tuple[np.ndarray, np.ndarray]:
        """Up to ``max_points`` Gaussians spread evenly over the whole map (active, then passive ones
        moved by pending pose changes, in :meth:`all_gaussians` order): centres ``(M, 3)`` float32
        (world, m) and DC colours ``(M, 3)`` RGB in [0, 1]. The passive store is read one chunk
        at a time, so a preview of a long run's map does not gather it in memory."""
        n = self.num_gaussians
        if n == 0 or max_points <= 0:
            return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32)
        want = np.linspace(0, n - 1, min(n, int(max_points))).round().astype(np.int64)
        xyz, rgb, off = [], [], 0
        for part in self._map_parts():
            sel = want[(want >= off) & (want < off + len(part))] - off
            off += len(part)
            if len(sel):
                idx = torch.from_numpy(sel)
                xyz.append(part.means.detach()[idx].cpu().numpy().astype(np.float32))
                rgb.append(sh_dc_to_rgb(part.sh.detach()[idx, 0, :]).clamp(0, 1).cpu().numpy().astype(np.float32))
        if not xyz:
            return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32)
        return np.concatenate(xyz), np.concatenate(rgb)

    def save_ply(self, path: str | os.PathLike) -> None:
        """Write every Gaussian (active + passive) as a viewer-compatible ``map.ply``."""
        from .ply import write_ply
        # chunk by chunk: the passive store (spilled to disk in a long run) is not gathered in memory
        write_ply(path, self._map_parts, sh_degree=self.cfg.sh_degree)

    def update_tiers(self, T_wc_now: np.ndarray) -> dict:
        """Storage tiers: Gaussians whose ID(g) keyframe is within ``tau`` of the camera are active
        (nearest first, at most ``max_active``), the others go to the passive store."""
        st = self.state
        pos = np.asarray(T_wc_now, dtype=np.float64)[:3, 3]
        stamps, positions = st.pose_table()
        near = lambda owners: (np.linalg.norm(  # noqa: E731
            positions[np.searchsorted(stamps, owners).clip(0, len(stamps) - 1)] - pos, axis=1) < self.cfg.tau) \
            | ~np.isin(owners, stamps)
        back = st.passive.take(near, st.poses) if st.passive.num_gaussians else None
        n_back = 0 if back is None else len(back)
        if back is not None:
            self.scores.gaussians_returned(back, st.render_count)
            st.gm = GaussianMap.concat([st.gm, back.to(self.device)])
        dist = owner_distances(st.gm.kf_id, stamps, positions, pos)
        keep = active_split(dist, self.cfg.tau, self.cfg.max_active).to(self.device)
        n_out = int((~keep).sum())
        if n_out:
            st.passive.put(st.gm.index(~keep), st.poses)
            st.gm = st.gm.index(keep)
        st.counters["to_passive"] += n_out
        st.counters["from_passive"] += n_back
        st.counters["tier_updates"] += 1
        return {"tier_in": n_back, "tier_out": n_out}

    def close(self) -> None:
        """Remove the passive store's and the history's spill files (private folders)."""
        self.passive.close()
        self.state.history.close()

    def save_checkpoint(self, path: str | os.PathLike) -> None:
        """Lossless checkpoint (``.npz``, :mod:`.checkpoint`): all Gaussians (parameters, two scales,
        ID(g), scores, status, optimiser state; passive ones included), keyframe poses, the window
        and history keyframes, counters, RNG state and config. :meth:`load_checkpoint` restores it
        bit-exactly. Written atomically."""
        ckpt.save_checkpoint(self, path)

    @staticmethod
    def load_checkpoint(path: str | os.PathLike, config: Optional[MapperConfig] = None,
                        device: str = "cpu") -> "Mapper":
        """Restore a mapper saved by :meth:`save_checkpoint` (any earlier checkpoint version too).
        ``config`` overrides the stored one (None = the stored config); it must keep the stored
        ``window_size`` and ``sh_degree``. A missing, damaged, foreign or newer file raises
        :class:`InputError` naming it."""
        return ckpt.load_checkpoint(path, config, device, Mapper)

    # ================================================================== internals
    def _commit_poses(self, changes: dict[int, tuple[np.ndarray, np.ndarray]], move_gaussians: bool,
                      scales: Optional[dict[int, float]] = None) -> None:
        """Keyframe pose changes ``{stamp: (T_old, T_new)}`` (``T_wc``) into the stored poses and the
        window keyframes. ``move_gaussians``: each keyframe's active Gaussians follow it by
        ``T_new Z T_old^-1`` (``Z = diag(s, s, s, 1)``, ``s`` its entry in ``scales``, default 1:
        rigidly); passive ones on their return; else no Gaussian moves (a move still pending for
        passive ones stays)."""
        if not changes:
            return
        st = self.state
        for s, (_, T) in changes.items():
            st.poses[s] = T
        for kf in st.window:
            if kf.stamp_ns in changes:
                kf.T_wc = torch.from_numpy(st.poses[kf.stamp_ns].copy())
        if move_gaussians:
            scaled = {s: k for s, k in (scales or {}).items() if s in changes and k != 1.0}
            self._move_active_by_owner({s: _owner_motion(old, new, scaled.get(s, 1.0))
                                        for s, (old, new) in changes.items()}, scaled)
            if scaled:
                st.passive.rescale(scaled)
                self._rescale_depths(scaled)
        else:
            st.passive.resnapshot(changes)

    def _rescale_depths(self, scales: dict[int, float]) -> None:
        """Keyframe depth maps follow a similarity of scale ``s``: depth times ``s``, inverse-depth
        variance over ``s^2``; window keyframes now (new tensors, so cached loss inputs are rebuilt),
        history keyframes when they are read (:attr:`MapState.depth_scale`)."""
        st = self.state
        for kf in st.window:
            k = scales.get(kf.stamp_ns)
            if k is not None:
                scale_keyframe_depth(kf, k)
        for s, k in scales.items():
            if s in st.history:
                st.depth_scale[s] = st.depth_scale.get(s, 1.0) * k

    def _move_active_by_owner(self, deltas: dict[int, np.ndarray], scales: dict[int, float]) -> None:
        """Move each active Gaussian by its owner's world-frame motion in ``deltas`` (a similarity
        with scale ``scales[owner]`` where given, else rigid)."""
        owners = np.array(sorted(deltas), dtype=np.int64)
        kid = self.gm.kf_id.cpu().numpy()
        i = np.searchsorted(owners, kid).clip(0, len(owners) - 1)
        rows = owners[i] == kid
        if not rows.any():
            return
        D = np.stack([deltas[int(s)] for s in owners])
        moves, sel = torch.from_numpy(D[i[rows]]), torch.from_numpy(rows).to(self.device)
        if scales:
            k = np.array([scales.get(int(s), 1.0) for s in owners])
            self.gm.apply_similarity(moves, sel, torch.from_numpy(k[i[rows]]))
        else:
            self.gm.apply_rigid(moves, sel)

    def _peek_passive(self, center: np.ndarray, radius: float) -> Optional[GaussianMap]:
        """Copies of the passive Gaussians whose owner keyframe lies within ``radius`` of
        ``center`` (world, m), moved by pending pose changes; the store unchanged."""
        stamps, positions = self.state.pose_table()

        def want(owners: np.ndarray) -> np.ndarray:
            i = np.searchsorted(stamps, owners).clip(0, max(len(stamps) - 1, 0))
            return np.linalg.norm(positions[i] - center, axis=1) < radius
        return self.passive.take(want, self.state.poses, remove=False)

    def _map_parts(self) -> Iterator[GaussianMap]:
        """The active map, then the passive store one chunk at a time (moved by pending pose
        changes): :meth:`all_gaussians` without gathering it."""
        return itertools.chain((self.gm,), self.passive.iter_moved(self.state.poses))


def _in_view(means: torch.Tensor, T_cw: torch.Tensor, camera: CameraModel) -> torch.Tensor:
    """``(N,)`` bool: centres in front of the camera (z > 0) that project inside the image."""
    p = means.to(torch.float64) @ T_cw[:3, :3].T + T_cw[:3, 3]
    z = p[:, 2]
    u = camera.fx * p[:, 0] / z.clamp_min(1e-9) + camera.cx
    v = camera.fy * p[:, 1] / z.clamp_min(1e-9) + camera.cy
    return (z > 0) & (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)


def _owner_motion(T_old: np.ndarray, T_new: np.ndarray, scale: float) -> np.ndarray:
    """World-frame motion of a keyframe's Gaussians when its pose ``T_wc`` goes from ``T_old`` to
    ``T_new``: ``T_new T_old^-1``, with a ``scale`` about the old camera centre first
    (``T_new diag(s, s, s, 1) T_old^-1``) when it is not 1."""
    if scale == 1.0:
        return T_new @ np.linalg.inv(T_old)
    return T_new @ np.diag([scale, scale, scale, 1.0]) @ np.linalg.inv(T_old)


def _check_similarity(C, what: str) -> tuple[np.ndarray, float]:
    """``C`` as a float64 4x4 similarity ``[[s R, t], [0, 1]]`` with ``s > 0`` and its scale ``s``
    (exactly 1.0 within 1e-12 of it); :class:`InputError` naming ``what`` otherwise (the rotation
    may deviate from orthonormal by round-off, up to 1e-2, as poses may)."""
    C = check_sim3(C, what, tol=1e-2)
    s = sim3_scale(C)
    return C, (1.0 if abs(s - 1.0) <= 1e-12 else s)
