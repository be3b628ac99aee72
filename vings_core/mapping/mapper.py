"""Stateful online 2DGS mapper (paper section "2D Gaussian Map").

Typical use (see docs/mapping.md)::

    m = Mapper(MapperConfig())
    for kf in keyframes:            # vings_core.types.Keyframe, T_wc camera-to-world
        m.add_keyframe(kf)          # render, delete conflicting, add in low-accumulation regions
        m.train()                   # iters_per_keyframe iterations on the local window
        poses = m.refine_poses()    # single-to-multi pose refinement -> {stamp_ns: T_wc}
    out = m.render(T_wc, camera)    # numpy color / depth / normal / alpha
    m.save_ply("map.ply"); m.save_checkpoint("map.ckpt.npz")

Frames: ``T_wc`` 4x4 float64 camera-to-world; Gaussians in the world frame (m). Nothing here loops
over Gaussians or pixels in Python.
"""
from __future__ import annotations

import io
import itertools
import json
import math
import os
import time
import zipfile
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Optional

import numpy as np
import torch

from ..config import config_from_dict
from ..errors import ConfigError, InputError
from ..geometry import np_project_rotation, pose_inverse, rotmat_to_quat, se3_exp
from ..render import rasterize_2dgs
from ..render.sh import rotate_sh
from ..types import CameraModel, Keyframe
from ..util import NPZ_READ_ERRORS, atomic_write, log
from . import pose_gn as GN
from . import scores as S
from .config import MapperConfig
from .gaussians import ALL_FIELDS, PARAM_FIELDS, GaussianMap, quat_multiply, sh_dc_to_rgb
from .history import FIELDS as HISTORY_FIELDS, HistoryStore, compact_keyframe, expand_keyframe
from .init import depth_normals, empty_mask, fill_depth, gaussians_from_pixels, num_to_add, sample_pixels, usable_depth_mask
from .losses import (accumulation_loss, depth_loss, depth_weight, l1_map, normal_loss, normals_from_depth,
                     rgb_loss, ssim_target_stats)
from .optim import sparse_adam_step_fast
from .storage import PassiveStore, active_split, owner_distances

CHECKPOINT_VERSION = 1


class Mapper:
    """Online 2D Gaussian map trained from keyframes.

    ``config``: :class:`MapperConfig` (None = defaults). ``device``: torch device of the active set
    ('cpu'; the rasterizer routes CUDA tensors to gsplat when installed).
    """

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
        self.gm = GaussianMap.empty(self.cfg.sh_degree, self.cfg.window_size, self.device)
        self._slots: list[int] = [-1] * self.cfg.window_size   # window keyframe stamp per score slot
        self.passive = PassiveStore(int(self.cfg.passive_memory_mb * 2**20), self.cfg.spill_dir or None)
        self.window: list[Keyframe] = []
        self._poses: dict[int, np.ndarray] = {}
        self._order: list[int] = []                 # keyframe stamps in insertion order
        self.camera: Optional[CameraModel] = None
        self.render_count = 0                        # training renders so far (score clock)
        self.kf_count = 0
        self.rng = torch.Generator().manual_seed(int(self.cfg.seed))
        self._queue: list[int] = []                  # shuffled round of window stamps (training)
        self._rqueue: list[int] = []                 # same, for pose refinement
        self._loss_maps: dict[int, torch.Tensor] = {}  # last per-pixel L1 map of window keyframes
        self._aux: dict[int, dict] = {}               # cached per-keyframe masks / weights
        self._pose_adam: dict[int, tuple] = {}        # stamp -> (m (6,), v (6,), steps) of pose refinement
        self._pose_v = np.zeros(7)                    # shared second moment of pose gradients (6,) + its steps
        self._pose_gn_steps: dict[int, int] = {}      # stamp -> Gauss-Newton steps taken (refine_gn_decay)
        # keyframes that left the window, compact, spilled to disk beyond history_memory_mb
        self._history = HistoryStore(int(self.cfg.history_memory_mb * 2**20), self.cfg.spill_dir or None)
        self.counters = dict(added=0, deleted=0, pruned=0, nonfinite_grads=0, to_stable=0, to_unstable=0, to_passive=0,
                             from_passive=0, tier_updates=0)
        self.timings = dict(add_s=0.0, train_s=0.0, refine_s=0.0)
        self._bg = torch.tensor(self.cfg.background, dtype=torch.float32)

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
        return {s: self._poses[s].copy() for s in self._order}

    def set_keyframe_poses(self, poses: dict[int, np.ndarray], move_gaussians: bool = True) -> None:
        """Replace keyframe poses (loop closure, front-end updates).

        With ``move_gaussians`` each keyframe's Gaussians (ID(g) = that keyframe) follow it rigidly:
        ``mu' = T_new T_old^-1 mu`` (paper, loop correction); passive ones when they come back.
        Unknown stamps raise :class:`InputError`.
        """
        unknown = [s for s in poses if int(s) not in self._poses]
        if unknown:
            raise InputError(f"set_keyframe_poses: unknown keyframe stamps {unknown[:5]}")
        # every pose checked before any is applied: a bad one leaves the map as it was
        checked = {s: _check_pose(T, f"set_keyframe_poses[{s}]") for s, T in poses.items()}
        changes = {int(s): (self._poses[int(s)], T.copy()) for s, T in checked.items()
                   if not np.array_equal(T, self._poses[int(s)])}
        self._commit_poses(changes, move_gaussians)

    def _commit_poses(self, changes: dict[int, tuple[np.ndarray, np.ndarray]], move_gaussians: bool) -> None:
        """Keyframe pose changes ``{stamp: (T_old, T_new)}`` (``T_wc``) into the stored poses and the
        window keyframes. ``move_gaussians``: each keyframe's active Gaussians follow it rigidly
        (``T_new T_old^-1``; passive ones on their return); else no Gaussian moves (a move still
        pending for passive ones stays)."""
        if not changes:
            return
        for s, (_, T) in changes.items():
            self._poses[s] = T
        for kf in self.window:
            if kf.stamp_ns in changes:
                kf.T_wc = torch.from_numpy(self._poses[kf.stamp_ns].copy())
        if move_gaussians:
            self._move_active_by_owner({s: new @ np.linalg.inv(old) for s, (old, new) in changes.items()})
        else:
            self.passive.resnapshot(changes)

    def add_keyframe(self, kf: Keyframe) -> dict:
        """Insert a keyframe: tier update (every ``delta_k``), render it, delete conflicting Gaussians,
        add Gaussians from its depth in low-accumulation regions. Returns counts."""
        t0 = time.perf_counter()
        self._check_keyframe(kf)
        T_ok = torch.from_numpy(_check_pose(kf.T_wc.numpy(), f"keyframe {kf.stamp_ns} T_wc"))
        kf = replace(kf, T_wc=T_ok, image=kf.image.to(torch.float32)[..., :3].contiguous(),
                     depth=kf.depth.to(torch.float32), inv_depth_var=kf.inv_depth_var.to(torch.float32),
                     valid=kf.valid.to(torch.bool))
        s = int(kf.stamp_ns)
        self._poses[s] = kf.T_wc.numpy().copy()
        self._order.append(s)
        self.window.append(kf)
        if len(self.window) > self.cfg.window_size:
            old = self.window.pop(0)
            if self.cfg.history_ratio > 0:
                self._history.put(old.stamp_ns, compact_keyframe(old))
            self._loss_maps.pop(old.stamp_ns, None)
            self._aux.pop(old.stamp_ns, None)
            slot = self._slots.index(old.stamp_ns)
            S.clear_slot(self.gm.win_c, self.gm.win_e, slot)    # window turnover: its scores go
            self._slots[slot] = -1
        self._slots[self._slots.index(-1)] = s
        self._queue = []
        self._rqueue = []
        self.kf_count += 1
        info = {"stamp_ns": s}
        if self.kf_count % self.cfg.delta_k == 0:
            info.update(self.update_tiers(self._poses[s]))
        info.update(self._densify(kf))
        if len(self.gm) > self.cfg.max_active:
            info.update(self.update_tiers(self._poses[s]))
        self.timings["add_s"] += time.perf_counter() - t0
        return info

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
            terms = self._train_step()
            done += 1
            for k in acc:
                acc[k] += terms[k]
        dt = time.perf_counter() - t0
        self.timings["train_s"] += dt
        out = {k: v / max(1, done) for k, v in acc.items()}
        out.update(iterations=done, time_s=dt, num_active=len(self.gm), num_passive=self.passive.num_gaussians,
                   num_stable=int(self.gm.stable.sum()), **self.counters)
        return out

    def refine_poses(self, iters: Optional[int] = None, mode: Optional[str] = None) -> dict[int, np.ndarray]:
        """Single-to-multi pose refinement; returns the refined ``{stamp_ns: T_wc}`` of all keyframes.

        Each iteration renders one window keyframe. ``mode`` (default ``config.refine_mode``):
        ``"multi"``: the loss reaches the pose of every keyframe owning visible Gaussians (through
        ID(g)); a pose change of keyframe k moves its Gaussians rigidly with it, so the rendered
        keyframe's own Gaussians move with its camera. ``"single"``: only the rendered camera moves,
        the map is fixed (the MonoGS/SplaTAM baseline). ``"none"``: nothing. Updated poses replace the
        stored ones (and the window keyframes' ``T_wc``)."""
        mode = self.cfg.refine_mode if mode is None else mode
        if mode not in ("none", "single", "multi"):
            raise InputError(f"refine_poses: mode must be none|single|multi, got {mode!r}")
        iters = self.cfg.refine_iters if iters is None else int(iters)
        if mode == "none" or iters <= 0 or not self.window or len(self.gm) == 0:
            return self.keyframe_poses()
        t0 = time.perf_counter()
        self._refine(mode, iters)
        self.timings["refine_s"] += time.perf_counter() - t0
        return self.keyframe_poses()

    @torch.no_grad()
    def render(self, T_wc: np.ndarray, camera: CameraModel, include_passive: bool = True) -> dict:
        """Render the map from camera-to-world ``T_wc`` with ``camera``.

        Uses the active set plus (``include_passive``) the passive Gaussians whose ID(g) keyframe is
        within ``tau`` of the camera (read, not moved). Returns numpy arrays: ``color`` (H, W, 3)
        float32 in [0, 1]; ``depth`` (H, W) expected z-depth (m, 0 where empty); ``normal`` (H, W, 3)
        unit normals in the camera frame (0 where empty); ``alpha`` (H, W) accumulated opacity.
        """
        T_wc = _check_pose(T_wc, "render T_wc")
        gm = self.gm
        if include_passive and self.passive.num_gaussians:
            extra = self._peek_passive(T_wc[:3, 3], self.cfg.tau)
            if extra is not None:
                gm = GaussianMap.concat([gm, extra.to(self.device)])
        out = self._rasterize(gm, torch.from_numpy(np.linalg.inv(T_wc)), camera, sample_ratio=1.0)
        a = out.alpha
        nrm = out.normal / torch.linalg.norm(out.normal, dim=-1, keepdim=True).clamp_min(1e-12)
        return {"color": out.color.clamp(0, 1).numpy().astype(np.float32),
                "depth": torch.where(a > 1e-4, out.depth / a.clamp_min(1e-10), torch.zeros_like(a)).numpy()
                .astype(np.float32),
                "normal": torch.where(a[..., None] > 1e-4, nrm, torch.zeros_like(nrm)).numpy().astype(np.float32),
                "alpha": a.numpy().astype(np.float32)}

    def all_gaussians(self) -> GaussianMap:
        """Active and passive Gaussians in one map (passive ones moved by pending pose changes)."""
        extra = self.passive.all(self._poses)
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

    def _map_parts(self):
        """The active map, then the passive store one chunk at a time (moved by pending pose
        changes): :meth:`all_gaussians` without gathering it."""
        return itertools.chain((self.gm,), self.passive.iter_moved(self._poses))

    def update_tiers(self, T_wc_now: np.ndarray) -> dict:
        """Storage tiers: Gaussians whose ID(g) keyframe is within ``tau`` of the camera are active
        (nearest first, at most ``max_active``), the others go to the passive store."""
        pos = np.asarray(T_wc_now, dtype=np.float64)[:3, 3]
        stamps, positions = self._pose_table()
        near = lambda owners: (np.linalg.norm(  # noqa: E731
            positions[np.searchsorted(stamps, owners).clip(0, len(stamps) - 1)] - pos, axis=1) < self.cfg.tau) \
            | ~np.isin(owners, stamps)
        back = self.passive.take(near, self._poses) if self.passive.num_gaussians else None
        n_back = 0 if back is None else len(back)
        if back is not None:
            # their window scores refer to keyframes that have left the window: scoring restarts
            S.reset_scores(back.win_c, back.win_e, back.score_since, None, self.render_count)
            self.gm = GaussianMap.concat([self.gm, back.to(self.device)])
        dist = owner_distances(self.gm.kf_id, stamps, positions, pos)
        keep = active_split(dist, self.cfg.tau, self.cfg.max_active).to(self.device)
        n_out = int((~keep).sum())
        if n_out:
            self.passive.put(self.gm.index(~keep), self._poses)
            self.gm = self.gm.index(keep)
        self.counters["to_passive"] += n_out
        self.counters["from_passive"] += n_back
        self.counters["tier_updates"] += 1
        return {"tier_in": n_back, "tier_out": n_out}

    def close(self) -> None:
        """Remove the passive store's and the history's spill files (private folders)."""
        self.passive.close()
        self._history.close()

    # ---------------------------------------------------------------- checkpoint
    def save_checkpoint(self, path: str | os.PathLike) -> None:
        """Lossless checkpoint (``.npz``): all Gaussians (parameters, two scales, ID(g), scores, status,
        optimiser state; passive ones included), keyframe poses, the window keyframes, counters, RNG
        state and config. :meth:`load_checkpoint` restores it bit-exactly. Written atomically."""
        d: dict[str, np.ndarray] = {}
        for k, v in self.gm.to_numpy().items():
            d[f"active/{k}"] = v
        d["kf/stamps"] = np.array(self._order, dtype=np.int64)
        d["kf/T_wc"] = np.stack([self._poses[s] for s in self._order]) if self._order else np.zeros((0, 4, 4))
        for i, kf in enumerate(self.window):
            d[f"win{i}/stamp"] = np.array(kf.stamp_ns, dtype=np.int64)
            d[f"win{i}/index"] = np.array(kf.index, dtype=np.int64)
            for k in ("image", "T_wc", "depth", "inv_depth_var", "valid"):
                d[f"win{i}/{k}"] = getattr(kf, k).cpu().numpy()
            d[f"win{i}/loss_map"] = (self._loss_maps[kf.stamp_ns].numpy() if kf.stamp_ns in self._loss_maps
                                     else np.zeros((0, 0), np.float32))
        meta = {"version": CHECKPOINT_VERSION, "config": asdict(self.cfg), "render_count": self.render_count,
                "kf_count": self.kf_count, "queue": self._queue, "rqueue": self._rqueue, "slots": self._slots,
                "window": len(self.window), "counters": self.counters,
                "camera": self.camera.to_dict() if self.camera is not None else None}
        d["meta"] = np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8)
        d["rng_state"] = self.rng.get_state().numpy()
        pa = sorted(self._pose_adam)
        d["pose_adam/stamps"] = np.array(pa, dtype=np.int64)
        d["pose_adam/m"] = np.stack([self._pose_adam[s][0] for s in pa]) if pa else np.zeros((0, 6))
        d["pose_adam/v"] = np.stack([self._pose_adam[s][1] for s in pa]) if pa else np.zeros((0, 6))
        d["pose_adam/steps"] = np.array([self._pose_adam[s][2] for s in pa], dtype=np.int64)
        d["pose_adam/v_shared"] = self._pose_v.copy()
        gs = sorted(self._pose_gn_steps)
        d["pose_gn/stamps"] = np.array(gs, dtype=np.int64)
        d["pose_gn/steps"] = np.array([self._pose_gn_steps[s] for s in gs], dtype=np.int64)

        def _w(tmp: str) -> None:
            # an .npz (uncompressed zip of .npy) written entry by entry: the history keyframes go in
            # one at a time (``hist/<stamp>/<field>``), so a long run's spilled history is not
            # gathered in memory to be saved
            with zipfile.ZipFile(tmp, "w", zipfile.ZIP_STORED, allowZip64=True) as zf:
                for k, a in d.items():
                    _write_npy(zf, k, a)
                # passive Gaussians chunk by chunk as stored (a spilled chunk is read only while it
                # is written), with the owner poses they were stored under: a pose change still
                # pending for them is applied once, on return, exactly as without the checkpoint
                count = 0
                for fields, owners, owner_T in self.passive.stored_chunks():
                    for k in ALL_FIELDS:
                        _write_npy(zf, f"pchunk/{count}/{k}", fields[k])
                    _write_npy(zf, f"pchunk/{count}/owners", owners)
                    _write_npy(zf, f"pchunk/{count}/owner_T", owner_T)
                    count += 1
                _write_npy(zf, "pchunk/count", np.array(count, dtype=np.int64))
                saved, index = [], []
                for s, rec in self._history.items():
                    for k in HISTORY_FIELDS:
                        _write_npy(zf, f"hist/{s}/{k}", rec[k].numpy())
                    saved.append(s)
                    index.append(rec["index"])
                _write_npy(zf, "hist/stamps", np.array(saved, dtype=np.int64))
                _write_npy(zf, "hist/index", np.array(index, dtype=np.int64))
        atomic_write(path, _w)

    @staticmethod
    def load_checkpoint(path: str | os.PathLike, config: Optional[MapperConfig] = None,
                        device: str = "cpu") -> "Mapper":
        """Restore a mapper saved by :meth:`save_checkpoint`. ``config`` overrides the stored one
        (None = the stored config); it must keep the stored ``window_size`` and ``sh_degree``. A
        missing, damaged or foreign file raises :class:`InputError` naming it."""
        path = Path(path)
        if not path.is_file():
            raise InputError(f"{path}: map checkpoint not found")
        try:
            z = np.load(path, allow_pickle=False)
        except NPZ_READ_ERRORS as e:
            raise InputError(f"{path}: not a VINGS map checkpoint ({type(e).__name__}: {e})") from None
        if not isinstance(z, np.lib.npyio.NpzFile):
            raise InputError(f"{path}: not a VINGS map checkpoint (a single .npy array, not an .npz)")
        with z:
            return Mapper._from_npz(_Entries(z, path), path, config, device)

    @staticmethod
    def _from_npz(z: "_Entries", path: Path, config: Optional[MapperConfig], device: str) -> "Mapper":
        """The body of :meth:`load_checkpoint`: ``z`` reads entries lazily, each read turning a
        missing or damaged entry into an InputError naming the file (other errors are bugs)."""
        try:
            meta = json.loads(bytes(z["meta"]).decode())
        except (ValueError, UnicodeDecodeError) as e:
            raise InputError(f"{path}: not a VINGS map checkpoint (meta: {e})") from None
        if not isinstance(meta, dict) or meta.get("version") != CHECKPOINT_VERSION:
            v = meta.get("version") if isinstance(meta, dict) else None
            raise InputError(f"{path}: checkpoint version {v} not supported")
        lacking = [k for k in _META_KEYS if k not in meta]
        if lacking:
            raise InputError(f"{path}: not a VINGS map checkpoint, or damaged (meta lacks {', '.join(lacking)})")
        cfg = config if config is not None else config_from_dict(MapperConfig, meta["config"], f"{path}: config")
        m = Mapper(cfg, device)
        m.gm = GaussianMap.from_numpy({k: z[f"active/{k}"] for k in ALL_FIELDS}, device)

        def _check_sh(gm: GaussianMap) -> GaussianMap:
            if gm.sh.shape[1] != (cfg.sh_degree + 1) ** 2:
                raise InputError(f"{path}: checkpoint holds SH of degree {math.isqrt(gm.sh.shape[1]) - 1}, "
                                 f"the config {cfg.sh_degree}; load it with the same sh_degree")
            return gm
        _check_sh(m.gm)
        stamps = z["kf/stamps"]
        Ts = z["kf/T_wc"]
        m._order = [int(s) for s in stamps]
        m._poses = {int(s): np.array(T) for s, T in zip(stamps, Ts)}
        m.camera = CameraModel.from_dict(meta["camera"]) if meta["camera"] else None
        for i in range(int(meta["window"])):
            p = f"win{i}/"
            kf = Keyframe(stamp_ns=int(z[p + "stamp"]), image=torch.from_numpy(z[p + "image"]),
                          T_wc=torch.from_numpy(z[p + "T_wc"]), depth=torch.from_numpy(z[p + "depth"]),
                          inv_depth_var=torch.from_numpy(z[p + "inv_depth_var"]),
                          valid=torch.from_numpy(z[p + "valid"]), camera=m.camera, index=int(z[p + "index"]))
            m.window.append(kf)
            lm = z[p + "loss_map"]
            if lm.size:
                m._loss_maps[kf.stamp_ns] = torch.from_numpy(lm)
        m.rng.set_state(torch.from_numpy(z["rng_state"]))
        stacked = {k: z[f"hist/{k}"] for k in HISTORY_FIELDS} if "hist/image" in z.files else None  # older layout
        for j, (s_, ix) in enumerate(zip(z["hist/stamps"].tolist(), z["hist/index"].tolist())):
            rec = {k: torch.from_numpy(np.array(stacked[k][j]) if stacked is not None else z[f"hist/{s_}/{k}"])
                   for k in HISTORY_FIELDS}
            m._history.put(int(s_), {**rec, "index": int(ix)})
        if "pose_adam/v_shared" in z:
            m._pose_v = np.array(z["pose_adam/v_shared"], dtype=np.float64)
        m._pose_adam = {int(s): (np.array(a), np.array(b), int(c)) for s, a, b, c in
                        zip(z["pose_adam/stamps"], z["pose_adam/m"], z["pose_adam/v"], z["pose_adam/steps"])}
        if "pose_gn/stamps" in z:      # older checkpoints: no Gauss-Newton step counts
            m._pose_gn_steps = {int(s): int(c) for s, c in zip(z["pose_gn/stamps"], z["pose_gn/steps"])}
        if "pchunk/count" in z:        # one chunk at a time (it spills as it goes, like the saved store)
            for k in range(int(z["pchunk/count"])):
                p = f"pchunk/{k}/"
                gm = _check_sh(GaussianMap.from_numpy({f: z[p + f] for f in ALL_FIELDS}))
                m.passive.put(gm, {int(s): T for s, T in zip(z[p + "owners"], z[p + "owner_T"])})
        else:                          # older layouts: the passive store in stacked arrays
            pas = _check_sh(GaussianMap.from_numpy({k: z[f"passive/{k}"] for k in ALL_FIELDS}))
            if "passive_chunks/chunk" in z and len(pas):
                m.passive.restore({**{k: z[f"passive/{k}"] for k in ALL_FIELDS},
                                   **{k: z[f"passive_chunks/{k}"] for k in ("chunk", "owner_chunk", "owners",
                                                                           "owner_T")}})
            elif len(pas):             # oldest: passive Gaussians saved moved to the current poses
                m.passive.put(pas, m._poses)
        m.render_count = int(meta["render_count"])
        m.kf_count = int(meta["kf_count"])
        m._queue = [int(s) for s in meta["queue"]]
        m._rqueue = [int(s) for s in meta["rqueue"]]
        if len(meta["slots"]) != cfg.window_size or m.gm.win_c.shape[1] != cfg.window_size:
            raise InputError(f"{path}: checkpoint has a window of {len(meta['slots'])} keyframes, the config "
                             f"{cfg.window_size}; load it with the same window_size")
        m._slots = [int(s) for s in meta["slots"]]
        m.counters.update(meta["counters"])
        return m

    # ================================================================== internals
    def _check_keyframe(self, kf: Keyframe) -> None:
        if not isinstance(kf, Keyframe):
            raise InputError(f"add_keyframe: expected a Keyframe, got {type(kf).__name__}")
        if int(kf.stamp_ns) in self._poses:
            raise InputError(f"add_keyframe: keyframe {kf.stamp_ns} was already added")
        if self._order and int(kf.stamp_ns) < self._order[-1]:
            raise InputError(f"add_keyframe: keyframe {kf.stamp_ns} is older than the last one "
                             f"({self._order[-1]}); keyframes must arrive in time order")
        what = f"add_keyframe {kf.stamp_ns}"
        if kf.camera.is_distorted:
            raise InputError(f"{what}: camera has lens distortion; undistort first")
        if self.camera is not None and kf.camera != self.camera:
            c, f = kf.camera, self.camera
            raise InputError(f"{what}: camera model differs from the first keyframe's ({c.width}x{c.height} "
                             f"fx {c.fx:g} fy {c.fy:g} cx {c.cx:g} cy {c.cy:g} vs {f.width}x{f.height} "
                             f"fx {f.fx:g} fy {f.fy:g} cx {f.cx:g} cy {f.cy:g})")
        img = kf.image
        if img.ndim != 3 or img.shape[2] < 3:
            raise InputError(f"{what}: image must be (H, W, 3), got {tuple(img.shape)}")
        if not img.dtype.is_floating_point:
            raise InputError(f"{what}: image must be float RGB in [0, 1], got dtype {img.dtype} "
                             f"(8-bit images: divide by 255)")
        if not bool(torch.isfinite(img).all()):
            raise InputError(f"{what}: image has non-finite values")
        lo, hi = float(img.min()), float(img.max())
        if lo < -1e-3 or hi > 1.0 + 1e-3:
            raise InputError(f"{what}: image values must lie in [0, 1], got [{lo:g}, {hi:g}]")
        H, W = kf.camera.height, kf.camera.width
        for name in ("depth", "inv_depth_var", "valid"):
            t = getattr(kf, name)
            if tuple(t.shape) != (H, W):
                raise InputError(f"{what}: {name} must have shape ({H}, {W}), got {tuple(t.shape)}")
        _check_pose(kf.T_wc.numpy(), f"keyframe {kf.stamp_ns} T_wc")
        if not bool(torch.isfinite(kf.depth).all()):
            raise InputError(f"{what}: depth has non-finite values (use 0 for invalid)")
        var = kf.inv_depth_var
        if bool(torch.isnan(var).any()) or bool((var < 0).any()):
            raise InputError(f"{what}: inv_depth_var has NaN or negative values (use inf for unknown)")
        if self.camera is None:
            self.camera = kf.camera          # only once the first keyframe is known to be good

    def _pose_table(self) -> tuple[np.ndarray, np.ndarray]:
        stamps = np.array(sorted(self._poses), dtype=np.int64)
        pos = np.stack([self._poses[int(s)][:3, 3] for s in stamps]) if len(stamps) else np.zeros((0, 3))
        return stamps, pos

    def _peek_passive(self, center: np.ndarray, radius: float) -> Optional[GaussianMap]:
        stamps, positions = self._pose_table()

        def want(owners: np.ndarray) -> np.ndarray:
            i = np.searchsorted(stamps, owners).clip(0, max(len(stamps) - 1, 0))
            return np.linalg.norm(positions[i] - center, axis=1) < radius
        return self.passive.take(want, self._poses, remove=False)

    def _activated(self, gm: GaussianMap, means=None, quats=None, log_scales=None, opacity_logits=None, sh=None):
        means = gm.means if means is None else means
        quats = gm.quats if quats is None else quats
        scales = torch.exp(gm.log_scales if log_scales is None else log_scales)
        opac = torch.sigmoid(gm.opacity_logits if opacity_logits is None else opacity_logits)
        sh = gm.sh if sh is None else sh
        return means, quats, scales, opac, sh

    def _rasterize(self, gm: GaussianMap, T_cw: torch.Tensor, camera: CameraModel, sample_ratio: float = 1.0,
                   loss_map: Optional[torch.Tensor] = None, **override):
        means, quats, scales, opac, sh = self._activated(gm, **override)
        if self.cfg.sh_degree == 0:
            colors = (sh[:, 0] * 0.28209479177387814 + 0.5).clamp_min(0.0)
            return rasterize_2dgs(means, quats, scales, opac, colors, T_cw, camera, background=self._bg,
                                  sample_ratio=sample_ratio, loss_map=loss_map)
        return rasterize_2dgs(means, quats, scales, opac, sh, T_cw, camera, sh_degree=self.cfg.sh_degree,
                              background=self._bg, sample_ratio=sample_ratio, loss_map=loss_map)

    # ---------------------------------------------------------------- densification
    @torch.no_grad()
    def _densify(self, kf: Keyframe) -> dict:
        cfg = self.cfg
        cam = kf.camera
        T_wc = kf.T_wc
        T_cw = pose_inverse(T_wc)
        usable = usable_depth_mask(kf, cfg.max_depth, cfg.max_depth_rel_std)
        if not bool(usable.any()):
            log.warning("keyframe %d: no pixel has usable depth (missing, or too uncertain: e.g. too "
                        "little parallax yet); no Gaussians from it", int(kf.stamp_ns))
        depth = kf.depth
        # pixels that may seed Gaussians: usable depth, and (fill_unknown_depth) pixels whose depth is
        # unknown (dropped as uncertain, not known empty) at depth interpolated from the usable ones
        seed, seed_depth = usable, depth
        if cfg.fill_unknown_depth and bool(usable.any()):
            unknown = ~usable & ~empty_mask(kf, cfg.max_depth)
            if bool(unknown.any()):
                seed = usable | unknown
                seed_depth = fill_depth(depth, usable)
        n_del = 0
        self._last_delete = {}
        if len(self.gm):
            out = self._rasterize(self.gm, T_cw, cam)
            l1 = l1_map(out.color, kf.image)
            self._loss_maps[kf.stamp_ns] = l1.to(torch.float32)
            exp_d = out.depth / out.alpha.clamp_min(1e-10)
            dmask = self._conflicts(out, l1, exp_d, kf, usable, T_cw)
            n_del = int(dmask.sum())
            if n_del:
                self.gm = self.gm.remove(dmask)
                out = self._rasterize(self.gm, T_cw, cam)
            alpha = out.alpha
            exp_d = out.depth / alpha.clamp_min(1e-10)
            # low accumulation, or the observed surface lies clearly in front of what is rendered
            behind = usable & (alpha > cfg.add_alpha_threshold) & (exp_d > depth * (1 + cfg.delete_depth_rel))
            low = seed & ((alpha < cfg.add_alpha_threshold) | behind)
        else:
            low = seed
        n_add = num_to_add(low, cfg.points_per_keyframe)
        if n_add > 0:
            rc = sample_pixels(low, n_add, self.rng)
            src = kf if seed_depth is depth else replace(kf, depth=seed_depth)
            new = gaussians_from_pixels(src, rc, cfg.sh_degree, cfg.init_opacity, cfg.init_scale_factor,
                                        cfg.min_scale_px, cfg.max_scale_px, score_since=self.render_count,
                                        normals_cam=depth_normals(seed_depth, cam), window=cfg.window_size)
            self.gm = GaussianMap.concat([self.gm, new.to(self.device)])
            n_add = len(rc)                  # at most one per low pixel
        self.counters["added"] += n_add
        self.counters["deleted"] += n_del
        return {"added": n_add, "deleted": n_del, "low_fraction": float(low.float().mean()),
                "delete_rules": dict(getattr(self, "_last_delete", {}))}

    def _conflicts(self, out, l1: torch.Tensor, exp_d: torch.Tensor, kf: Keyframe, usable: torch.Tensor,
                   T_cw: torch.Tensor) -> torch.Tensor:
        """Gaussians to delete for a new keyframe (vectorised over Gaussians).

        Each centre is projected into the keyframe. Inside the frustum a Gaussian is removed when
        (a) it floats in front of the observed surface: its depth ``z < D_min (1 - delete_depth_rel)``,
        ``D_min`` the nearest observed depth in the 5x5 neighbourhood of its pixel (so splats on an
        object's silhouette are not taken for floaters), while the render there is in front of the
        observed surface by the same margin; or (b) it lies on the observed surface
        (``|z - D| < delete_depth_rel D``) and the RGB error stays above ``delete_rgb`` over the whole
        3x3 neighbourhood (a persistent error, not a one-pixel misalignment at an edge); or (c) it is
        seen (contribution > 0) with a projected radius above ``delete_max_radius_frac`` x diagonal.
        """
        cfg = self.cfg
        cam = kf.camera
        H, W = cam.height, cam.width
        R = T_cw[:3, :3].to(torch.float32)
        t = T_cw[:3, 3].to(torch.float32)
        pc = self.gm.means @ R.T + t
        finite = self.gm.finite_rows()
        pc = torch.where(finite[:, None], pc, torch.zeros((), dtype=pc.dtype))
        z = pc[:, 2]
        front = z > 1e-3
        u = torch.round(pc[:, 0] / z.clamp_min(1e-6) * cam.fx + cam.cx)
        v = torch.round(pc[:, 1] / z.clamp_min(1e-6) * cam.fy + cam.cy)
        inside = front & (u >= 0) & (u <= W - 1) & (v >= 0) & (v <= H - 1)
        ui = u.clamp(0, W - 1).long()
        vi = v.clamp(0, H - 1).long()
        D = kf.depth
        Dinf = torch.where(usable, D, torch.full_like(D, float("inf")))
        Dmin = -torch.nn.functional.max_pool2d(-Dinf[None, None], 5, stride=1, padding=2)[0, 0]
        l1min = -torch.nn.functional.max_pool2d(-l1[None, None], 3, stride=1, padding=1)[0, 0]
        ok = inside & usable[vi, ui]
        rel = cfg.delete_depth_rel
        Dg = D[vi, ui]
        render_in_front = exp_d[vi, ui] < Dg * (1 - rel)
        floater = ok & (z < Dmin[vi, ui] * (1 - rel)) & render_in_front
        on_surface = ok & ((z - Dg).abs() < rel * Dg) & (l1min[vi, ui] > cfg.delete_rgb)
        # only splats whose centre projects into the image and that are actually seen: Gaussians beside
        # or behind the camera plane have huge clipped screen boxes but are not in this view
        too_big = inside & (out.contribution.to(self.device) > 0) & \
            (out.radii.to(self.device) > cfg.delete_max_radius_frac * math.hypot(W, H))
        self._last_delete = {"floater": int(floater.sum()), "wrong_colour": int(on_surface.sum()),
                             "too_big": int(too_big.sum())}
        self._last_delete["non_finite"] = int((~finite).sum())
        return floater | on_surface | too_big | ~finite

    # ---------------------------------------------------------------- training
    def _next_kf(self, queue: list[int]) -> Keyframe:
        if not queue:
            perm = torch.randperm(len(self.window), generator=self.rng).tolist()
            queue.extend(self.window[i].stamp_ns for i in perm)
        s = queue.pop(0)
        for kf in self.window:
            if kf.stamp_ns == s:
                return kf
        raise RuntimeError("window keyframe vanished")  # pragma: no cover

    def _kf_aux(self, kf: Keyframe) -> dict:
        """Per-keyframe constant loss inputs, cached while the keyframe is in the window."""
        a = self._aux.get(kf.stamp_ns) if kf.stamp_ns not in self._history else None
        if a is None or a["T"] is not kf.depth:
            cfg = self.cfg
            a = {"T": kf.depth, "usable": usable_depth_mask(kf, cfg.max_depth, cfg.max_depth_rel_std),
                 "w_depth": depth_weight(kf.depth, kf.inv_depth_var, cfg.depth_rel_std0),
                 "masked": empty_mask(kf, cfg.max_depth),
                 "ssim_stats": ssim_target_stats(kf.image) if cfg.lambda_ssim > 0 else None}
            if kf.stamp_ns not in self._history:
                self._aux[kf.stamp_ns] = a
        return a

    def _losses(self, out, kf: Keyframe, it_terms: dict, with_normal: bool = True, with_acc: bool = True,
                expected_depth: bool = False):
        """Training loss of one render. ``expected_depth`` (pose refinement): the depth term compares
        the expected depth ``D_hat / alpha`` where ``alpha > 0.5`` instead of the accumulated depth
        ``D_hat``: the accumulated depth is short of the surface wherever alpha < 1, which for the
        map means "fill this pixel" but would pull a camera along its axis."""
        cfg = self.cfg
        img = kf.image
        aux = self._kf_aux(kf)
        l1 = l1_map(out.color, img)
        it_terms["l1_map"] = l1.detach()
        l_rgb = rgb_loss(out.color, img, cfg.lambda_ssim, target_stats=aux["ssim_stats"], l1=l1)
        if expected_depth:
            a = out.alpha
            l_d = depth_loss(out.depth / a.clamp_min(1e-6), kf.depth, aux["w_depth"],
                             aux["usable"] & (a.detach() > 0.5))
        else:
            l_d = depth_loss(out.depth, kf.depth, aux["w_depth"], aux["usable"])
        total = cfg.lambda_rgb * l_rgb + cfg.lambda_depth * l_d
        l_n = torch.zeros(())
        l_a = torch.zeros(())
        if with_normal and cfg.lambda_normal > 0 and self.render_count >= cfg.normal_loss_warmup:
            a = out.alpha
            exp_d = out.depth / a.clamp_min(1e-6)
            n_d, ok = normals_from_depth(exp_d, kf.camera)
            ok = ok & (a.detach() > 0.5)
            l_n = normal_loss(out.normal, n_d, torch.ones_like(a), ok)
            total = total + cfg.lambda_normal * l_n
        if with_acc and cfg.lambda_acc > 0:
            l_a = accumulation_loss(out.alpha, aux["masked"])
            total = total + cfg.lambda_acc * l_a
        it_terms.update(loss=float(total.detach()), rgb=float(l_rgb.detach()), depth=float(l_d.detach()),
                        normal=float(l_n.detach()), acc=float(l_a.detach()))
        return total

    def _history_keyframe(self) -> Optional[Keyframe]:
        """With probability ``history_ratio``, an older keyframe (not in the window) whose camera is
        within ``tau`` of the newest keyframe, uniformly; else None."""
        cfg = self.cfg
        if cfg.history_ratio <= 0 or not self._history:
            return None
        if float(torch.rand((), generator=self.rng)) >= cfg.history_ratio:
            return None
        cur = self._poses[self.window[-1].stamp_ns][:3, 3]
        stamps = self._history.stamps()
        pos = np.stack([self._poses[s][:3, 3] for s in stamps])
        cand = np.flatnonzero(np.linalg.norm(pos - cur, axis=1) < cfg.tau)
        if not len(cand):
            return None
        s = stamps[int(cand[int(torch.randint(len(cand), (), generator=self.rng))])]
        rec = self._history.get(s)     # None: its spill file was lost (reported); skip this turn
        return None if rec is None else expand_keyframe(rec, s, self._poses[s], self.camera)

    def _train_step(self) -> dict:
        cfg = self.cfg
        gm = self.gm
        hist = self._history_keyframe()
        kf = hist if hist is not None else self._next_kf(self._queue)
        T_cw = pose_inverse(kf.T_wc)
        leaves = {p: getattr(gm, p).detach().requires_grad_(True) for p in PARAM_FIELDS}
        stale = None if hist is not None else self._loss_maps.get(kf.stamp_ns)
        out = self._rasterize(gm, T_cw, kf.camera, sample_ratio=cfg.sample_ratio, loss_map=stale, **leaves)
        terms: dict = {}
        loss = self._losses(out, kf, terms)
        l1 = terms.pop("l1_map")
        if cfg.sample_ratio < 1.0:
            # per tile, the pixels with the highest colour error L_rgb(u) (the paper's per-pixel
            # loss, also the error score's map); ranking by every term's share was measured worse
            out.set_sample_map(l1)
        loss.backward()
        terms["psnr"] = -10 * math.log10(max(float((out.color.detach().clamp(0, 1) - kf.image).pow(2).mean()), 1e-12))
        with torch.no_grad():
            if hist is None:
                # score manager bookkeeping (window keyframes only; error w.r.t. the last loss map)
                self._loss_maps[kf.stamp_ns] = l1.to(torch.float32)
                err = out.error if out.error is not None else torch.zeros(len(gm))
                S.record_render(gm.win_c, gm.win_e, gm.kf_id, gm.id_score, self._slots.index(kf.stamp_ns),
                                out.contribution.to(torch.float32), err.to(torch.float32), kf.stamp_ns)
            rows = ((out.radii > 0).to(self.device) & ~gm.stable).nonzero()[:, 0]
            if rows.numel():
                gm.adam_step[rows] += 1
                lrs = self._lr_cols()
                betas = (cfg.adam_betas[0], cfg.adam_betas[1])
                for p in PARAM_FIELDS:
                    g = leaves[p].grad
                    if g is None:
                        continue
                    bad = ~torch.isfinite(g)
                    if bool(bad.any()):          # never let a degenerate splat poison the map
                        self.counters["nonfinite_grads"] += int(bad.reshape(len(g), -1).any(1).sum())
                        g = torch.where(bad, torch.zeros((), dtype=g.dtype), g)
                    sparse_adam_step_fast(getattr(gm, p), g, getattr(gm, f"m_{p}"), getattr(gm, f"v_{p}"),
                                          gm.adam_step, rows, lrs[p], betas, cfg.adam_eps)
            self.render_count += 1
            if cfg.score_manager:
                self._score_control()
        return terms

    def _lr_cols(self) -> dict[str, np.ndarray]:
        """Learning rate per column of each parameter viewed as (N, D)."""
        cfg = self.cfg
        lr_means = cfg.lr_means * (cfg.lr_means_outdoor_factor if cfg.outdoor else 1.0)
        k = (cfg.sh_degree + 1) ** 2
        lr_sh = np.full((k, 3), cfg.lr_sh / 20.0)
        lr_sh[0] = cfg.lr_sh
        return dict(means=np.full(3, lr_means), quats=np.full(4, cfg.lr_quats), log_scales=np.full(2, cfg.lr_scales),
                    opacity_logits=np.full(1, cfg.lr_opacity), sh=lr_sh.reshape(-1))

    @torch.no_grad()
    def _score_control(self) -> None:
        """Algorithm 1: status control every ``delta_status`` and storage control every
        ``delta_storage`` training iterations (status first when both are due)."""
        cfg = self.cfg
        j = self.render_count
        gm = self.gm
        status_now = j % cfg.delta_status == 0
        storage_now = j % cfg.delta_storage == 0
        if not (status_now or storage_now):
            return
        s_c, s_e = S.window_scores(gm.win_c, gm.win_e)
        judged = S.scored_long_enough(gm.score_since, j, cfg.min_score_age)
        if status_now:
            to_stable, to_unstable = S.status_control(gm.stable, s_c, s_e, judged, cfg.sc_status, cfg.se_status)
            gm.stable[to_stable] = True
            gm.stable[to_unstable] = False
            S.reset_scores(gm.win_c, gm.win_e, gm.score_since, to_unstable, j)
            self.counters["to_stable"] += int(to_stable.sum())
            self.counters["to_unstable"] += int(to_unstable.sum())
            s_c, s_e = S.window_scores(gm.win_c, gm.win_e)
            judged = S.scored_long_enough(gm.score_since, j, cfg.min_score_age)
        if storage_now:
            owned = None
            if cfg.prune_window_owned_only:
                win = torch.tensor([x for x in self._slots if x != -1], dtype=gm.kf_id.dtype, device=gm.kf_id.device)
                owned = torch.isin(gm.kf_id, win)
            s_store = S.per_view_contribution(gm.win_c, cfg.sc_view_floor) if cfg.sc_storage_per_view else s_c
            spared = None
            if cfg.prune_spare_high_error and self._loss_maps:
                # the window keyframes' mean L1 error (their latest training renders)
                ref = float(np.mean([float(lm.mean()) for lm in self._loss_maps.values()]))
                spared = S.error_density(gm.win_c, gm.win_e) > ref
            prune = S.storage_control(gm.stable, s_store, judged, cfg.sc_storage, cfg.sc_status, owned, spared)
            n = int(prune.sum())
            if n:
                self.gm = gm.remove(prune)
                self.counters["pruned"] += n

    # ---------------------------------------------------------------- pose refinement
    def _move_active_by_owner(self, deltas: dict[int, np.ndarray]) -> None:
        owners = np.array(sorted(deltas), dtype=np.int64)
        kid = self.gm.kf_id.cpu().numpy()
        i = np.searchsorted(owners, kid).clip(0, len(owners) - 1)
        rows = owners[i] == kid
        if not rows.any():
            return
        D = np.stack([deltas[int(s)] for s in owners])
        self.gm.apply_rigid(torch.from_numpy(D[i[rows]]), torch.from_numpy(rows).to(self.device))

    def _depth_scale(self) -> float:
        """Median over the window keyframes of their median valid depth (scene units): the length
        scale of pose-refinement translation steps (1.0 when no keyframe has depth)."""
        meds = []
        for kf in self.window:
            d = kf.depth[kf.valid & (kf.depth > 0)]
            if d.numel():
                meds.append(float(d.median()))
        return float(np.median(meds)) if meds else 1.0

    def _refine(self, mode: str, iters: int) -> None:
        cfg = self.cfg
        gm = self.gm
        ok = gm.finite_rows()
        if not bool(ok.all()):
            # a non-finite Gaussian (deleted at the next keyframe) would make its owner's whole
            # gradient NaN (0 x NaN through the rigid motion) and silently freeze that pose
            log.debug("pose refinement: %d non-finite Gaussians left out", int((~ok).sum()))
            gm = gm.index(ok)
        first = self._order[0] if (cfg.refine_fix_first and self._order) else None
        if mode == "multi":
            owners = torch.unique(gm.kf_id).cpu()
            win = torch.tensor([kf.stamp_ns for kf in self.window], dtype=torch.int64)
            owners = torch.sort(torch.cat([owners, win[~torch.isin(win, owners)]])).values
            inv = torch.searchsorted(owners, gm.kf_id.cpu())
        else:
            owners = torch.tensor(sorted(kf.stamp_ns for kf in self.window), dtype=torch.int64)
            inv = None
        U = len(owners)
        T_own = torch.from_numpy(np.stack([self._poses.get(int(o), np.eye(4)) for o in owners.tolist()])) \
            if U else torch.zeros(0, 4, 4, dtype=torch.float64)
        fixed = (owners == first) if first is not None else torch.zeros(U, dtype=torch.bool)
        ctx = _RefineCtx(gm=gm, mode=mode, owners=owners, inv=inv, T_own=T_own, T_own_inv=pose_inverse(T_own),
                         fixed=fixed)
        solve = self._refine_gn if cfg.refine_solver == "gn" else self._refine_adam
        xi = solve(ctx, iters)
        # commit: T_k <- T_k exp(xi_k) (camera-frame delta); in multi mode the owners' Gaussians move with them
        moved = (xi.abs().sum(1) > 0).nonzero()[:, 0]
        if moved.numel() == 0:
            return
        D = se3_exp(xi[moved]).numpy()
        changes = {}
        for j, i in enumerate(moved.tolist()):
            s = int(owners[i])
            changes[s] = (self._poses[s], self._poses[s] @ D[j])
        # single: only the cameras move, the owners' Gaussians (active and passive) stay
        self._commit_poses(changes, move_gaussians=(mode == "multi"))

    def _refine_render(self, ctx: "_RefineCtx", xi: torch.Tensor, r: int, kf: Keyframe):
        """Render keyframe ``r`` (index into ``ctx.owners``) with the deltas ``xi`` applied: its camera
        ``T_r exp(xi_r)``; in multi mode every owner's Gaussians moved by ``T_k exp(xi_k) T_k^-1``.
        Differentiable in ``xi``. Returns the render and, in multi mode, ``(means, quats, T_cw)`` it used."""
        D = se3_exp(xi)                                   # (U, 4, 4) camera-frame deltas
        T_cw = pose_inverse(ctx.T_own[r] @ D[r])
        if ctx.mode != "multi":
            return self._rasterize(ctx.gm, T_cw.to(torch.float32), kf.camera, sample_ratio=1.0), None
        gm, inv = ctx.gm, ctx.inv
        Wd = ctx.T_own @ D @ ctx.T_own_inv                 # world-frame motion of each owner's Gaussians
        # index_select, not Wd[inv]: the backward of advanced indexing (index_put_ with
        # accumulate) sums in a thread-dependent order on the CPU, index_select's does not
        Dg = torch.index_select(Wd.to(torch.float32), 0, inv)
        means = (Dg[:, :3, :3] @ gm.means[:, :, None])[:, :, 0] + Dg[:, :3, 3]
        qd = torch.index_select(rotmat_to_quat(Wd[:, :3, :3]).to(torch.float32), 0, inv)
        quats = quat_multiply(qd, gm.quats)
        sh = rotate_sh(gm.sh, Wd[:, :3, :3], inv)        # view-dependent colour turns along
        out = self._rasterize(gm, T_cw.to(torch.float32), kf.camera, sample_ratio=1.0,
                              means=means, quats=quats, sh=sh)
        return out, (means, quats, T_cw)

    def _refine_visible(self, ctx: "_RefineCtx", out, r: int) -> torch.Tensor:
        """``(U,)`` bool: the poses this render may update. A pose is updated only when the render
        shows enough of what constrains it (refine_min_pixels, in pixel weights sum alpha T): in
        single mode the rendered keyframe needs that much map in view; in multi mode another keyframe
        needs that much contribution from its own Gaussians (one seen through a few pixels at the
        edge of the view does not step on their noise), and the rendered keyframe that much from
        OTHER keyframes' Gaussians: its own move with its camera, so they cannot constrain it."""
        cfg = self.cfg
        U = len(ctx.owners)
        contrib = out.contribution.detach().to(torch.float64)
        vis = torch.zeros(U, dtype=torch.bool)
        if ctx.mode == "multi":
            per_owner = torch.zeros(U, dtype=torch.float64).index_add_(0, ctx.inv, contrib)
            vis = per_owner >= cfg.refine_min_pixels
            vis[r] = float(contrib.sum() - per_owner[r]) >= cfg.refine_min_pixels
        else:
            vis[r] = float(contrib.sum()) >= cfg.refine_min_pixels
        return vis & ~ctx.fixed

    def _refine_adam(self, ctx: "_RefineCtx", iters: int) -> torch.Tensor:
        """First-order refinement: autograd gradients of the training loss, Adam steps."""
        cfg = self.cfg
        owners = ctx.owners
        U = len(owners)
        xi = torch.zeros(U, 6, dtype=torch.float64)
        # Adam state per keyframe persists across calls (like a per-keyframe pose optimiser)
        st = [self._pose_adam.get(int(o)) for o in owners.tolist()]
        m = torch.stack([torch.from_numpy(a[0]) if a is not None else torch.zeros(6, dtype=torch.float64) for a in st]) \
            if U else torch.zeros(0, 6, dtype=torch.float64)
        v = torch.stack([torch.from_numpy(a[1]) if a is not None else torch.zeros(6, dtype=torch.float64) for a in st]) \
            if U else torch.zeros(0, 6, dtype=torch.float64)
        steps = torch.tensor([int(a[2]) if a is not None else 0 for a in st], dtype=torch.int64)
        lr_t = cfg.refine_lr_trans_rel * self._depth_scale()
        lr = torch.tensor([lr_t] * 3 + [cfg.refine_lr_rot] * 3, dtype=torch.float64)
        b1, b2, eps = 0.9, 0.999, 1e-12
        vs = self._pose_v
        for _ in range(iters):
            kf = self._next_kf(self._rqueue)
            r = int(torch.searchsorted(owners, torch.tensor(kf.stamp_ns)))
            x = xi.clone().requires_grad_(True)
            out, _ = self._refine_render(ctx, x, r, kf)
            terms: dict = {}
            loss = self._losses(out, kf, terms, with_normal=False, with_acc=False, expected_depth=True)
            terms.pop("l1_map", None)
            loss.backward()
            g = x.grad.detach().clone()
            upd = self._refine_visible(ctx, out, r) & torch.isfinite(g).all(1)
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
            self._pose_adam[int(owners[i])] = (m[i].numpy().copy(), v[i].numpy().copy(), int(steps[i]))
        return xi

    @torch.no_grad()
    def _owner_shares(self, ctx: "_RefineCtx", moved, kf: Keyframe, vis_idx: list[int]) -> torch.Tensor:
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
    def _refine_gn(self, ctx: "_RefineCtx", iters: int) -> torch.Tensor:
        """Second-order refinement (:mod:`.pose_gn`): the normal equations of ``refine_gn_batch``
        renders (window keyframes in turn; 0: as many as the window holds) are summed and solved
        jointly for every pose they constrain, one damped Gauss-Newton step per batch. Steps scale
        with the residual, so a far pose travels in a few steps and a converged one stays put (no
        random walk on gradient noise); the joint solve lets each pose be fixed by the renders
        that observe it best (one render alone leaves poorly observed directions free)."""
        cfg = self.cfg
        owners = ctx.owners
        U = len(owners)
        xi = torch.zeros(U, 6, dtype=torch.float64)
        max_t = cfg.refine_gn_max_trans_rel * self._depth_scale()
        batch = cfg.refine_gn_batch or len(self.window)
        # the system spans the window keyframes only (the only ones rendered, so the only ones that
        # can step, below); ``pos`` maps an owner index to its place there (-1: not in the window)
        in_window = torch.isin(owners, torch.tensor([kf.stamp_ns for kf in self.window], dtype=torch.int64))
        win_idx = in_window.nonzero()[:, 0]
        n = len(win_idx)
        pos = torch.full((U,), -1, dtype=torch.int64)
        pos[win_idx] = torch.arange(n)
        H_all = torch.zeros(6 * n, 6 * n, dtype=torch.float64)
        b_all = torch.zeros(6 * n, dtype=torch.float64)
        free = torch.zeros(n, dtype=torch.bool)
        rendered = torch.zeros(n, dtype=torch.bool)
        for it in range(iters):
            kf = self._next_kf(self._rqueue)
            r = int(torch.searchsorted(owners, torch.tensor(kf.stamp_ns)))
            rendered[pos[r]] = True
            terms = None
            out, moved = self._refine_render(ctx, xi, r, kf)
            upd = self._refine_visible(ctx, out, r)
            if upd.any():
                aux = self._kf_aux(kf)
                terms = GN.pixel_terms(out.color, out.depth / out.alpha.clamp_min(1e-6), out.alpha, kf.image,
                                       kf.depth, aux["w_depth"], aux["usable"], kf.camera,
                                       sigma_rgb=cfg.refine_gn_sigma_rgb, sigma_depth_rel=cfg.depth_rel_std0,
                                       huber=cfg.refine_gn_huber, blur_px=cfg.refine_gn_blur_px,
                                       stride=cfg.refine_gn_stride)
            if terms is not None and terms.pix.numel() >= 6:
                T_cur = ctx.T_own @ se3_exp(xi)
                if ctx.mode == "multi":
                    # the others' content enters as held (moves by -xi_r), without share renders
                    idx = sorted(set((upd & in_window).nonzero()[:, 0].tolist()) | {r})
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
                loc = pos[idx]
                cols = (loc[:, None] * 6 + torch.arange(6)).reshape(-1)
                H_all[cols[:, None], cols[None]] += H
                b_all[cols] += b
                free[loc[upd[idx]]] = True
            if (it + 1) % batch == 0 or it == iters - 1:
                # only poses whose own camera was rendered in the batch step (so keyframes that
                # left the window keep theirs): a keyframe seen only through its Gaussians in
                # others' views has a weakly observed rotation (turning about its camera centre ~
                # shifting a distant patch), which the step would take freely, and a joint solve
                # would split each new keyframe's error between it and the old owners it sees
                free &= rendered
                if free.any():
                    step = GN.damped_step(H_all, b_all, free, cfg.refine_gn_damping, max_t, cfg.refine_gn_max_rot)
                    if cfg.refine_gn_decay:
                        step = step * self._gn_step_scale(owners[win_idx], free)[:, None]
                    xi[win_idx] += step
                H_all.zero_()
                b_all.zero_()
                free[:] = False
                rendered[:] = False
        return xi

    def _gn_step_scale(self, stamps: torch.Tensor, free: torch.Tensor) -> torch.Tensor:
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
            t = self._pose_gn_steps.get(s, 0) + 1
            self._pose_gn_steps[s] = t
            f[i] = 1.0 / t
        return f


@dataclass
class _RefineCtx:
    """One refine_poses() call's fixed inputs: the Gaussians used, the keyframes whose poses may
    move (``owners``, sorted stamps), each Gaussian's owner index (multi mode), their poses ``T_wc``
    at the call's start and which are held (gauge)."""

    gm: GaussianMap
    mode: str
    owners: torch.Tensor
    inv: Optional[torch.Tensor]
    T_own: torch.Tensor
    T_own_inv: torch.Tensor
    fixed: torch.Tensor


_META_KEYS = ("config", "camera", "window", "render_count", "kf_count", "queue", "rqueue", "slots",
              "counters")


class _Entries:
    """An open checkpoint's entries: a missing or damaged one is an InputError naming the file
    (``np.load`` reads them lazily, so damage shows where an entry is first read)."""

    def __init__(self, z, path: Path) -> None:
        self.z, self.path = z, path
        self.files = z.files

    def __contains__(self, name: str) -> bool:
        return name in self.z.files

    def __getitem__(self, name: str) -> np.ndarray:
        try:
            return self.z[name]
        except KeyError:
            raise InputError(f"{self.path}: not a VINGS map checkpoint, or damaged (lacks {name})") from None
        except NPZ_READ_ERRORS as e:
            raise InputError(f"{self.path}: not a VINGS map checkpoint, or damaged ({name}: "
                             f"{type(e).__name__}: {e})") from None


def _write_npy(zf: "zipfile.ZipFile", name: str, a) -> None:
    """One ``name.npy`` entry of an ``.npz`` (what ``np.savez`` writes, and ``np.load`` reads)."""
    with zf.open(name + ".npy", "w", force_zip64=True) as f:
        np.lib.format.write_array(f, np.asanyarray(a), allow_pickle=False)


def _check_pose(T, what: str) -> np.ndarray:
    T = np.asarray(T.detach().cpu().numpy() if torch.is_tensor(T) else T, dtype=np.float64)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise InputError(f"{what}: expected a finite 4x4 pose, got shape {T.shape}")
    R = T[:3, :3]
    dev = max(float(np.abs(R @ R.T - np.eye(3)).max()), abs(float(np.linalg.det(R)) - 1))
    if dev > 1e-2 or not np.allclose(T[3], [0, 0, 0, 1]):
        raise InputError(f"{what}: not a rigid pose (rotation block deviates from orthonormal by {dev:.2g})")
    if dev > 1e-9:
        # round-off of composed increments (e.g. many pose corrections): project onto SO(3)
        T = T.copy()
        T[:3, :3] = np_project_rotation(R)
    return T
