"""The offline SLAM runner: a :class:`~vings_core.io.Source` through the front end and the mapper.

``SlamRunner(source, ...).run()`` is what ``vings run`` calls; the ROS nodes call the same stage
classes (:class:`~vings_core.frontend.Frontend`, :class:`~vings_core.mapping.Mapper`), so offline
and ROS results agree.

Two modes:

* **concurrent** (default, as in the paper): the mapper trains in its own thread on a keyframe queue;
  tracking never waits for it. Refined keyframe poses flow back to the front end's pose buffer
  between frames.
* **sync** (``RunConfig.sync``): after each keyframe the mapper trains to completion before the next
  frame: deterministic, for tests and benchmarks.

With ``gt_poses`` the front end is bypassed: keyframes are taken from ground-truth camera poses and
ground-truth depth (sources that have both), for mapping benchmarks.
"""
from __future__ import annotations

import logging
import queue
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Optional

import numpy as np
import torch

from .config import load_section
from .errors import InputError, VingsError
from .eval.image import psnr, ssim
from .eval.output import RunOutput, metrics_template, peak_rss_mb
from .eval.traj import evaluate_trajectory
from .geometry import rotation_angle_deg
from .io.base import Source
from .types import Frame, Keyframe, Trajectory

log = logging.getLogger("vings.run")

CHECKPOINT_FILE = "checkpoint.pt"


@dataclass
class RunConfig:
    """Runner settings (params section ``run``).

    ``width``/``height``: working resolution; 0 = automatic (half the native size when the native
    width exceeds 640 px, e.g. EuRoC 752x480 -> 376x240, KITTI 1226x370 -> 613x185; else native).
    ``gt_kf_*``: keyframe selection in ``gt_poses`` mode (translation m, rotation deg, max frame gap).
    ``eval_keyframes``/``eval_novel``: at most this many keyframes / non-keyframe frames are rendered
    for PSNR (evenly spaced). ``save_renders``: keyframe renders saved under renders/.
    ``checkpoint_every``: keyframes between map checkpoints (0 = only at the end).
    """

    width: int = 0
    height: int = 0
    sync: bool = False
    gt_poses: bool = False
    gt_kf_trans_m: float = 0.25
    gt_kf_rot_deg: float = 10.0
    gt_kf_max_gap: int = 10
    gt_inv_depth_var: float = 1.0e-4
    eval_keyframes: int = 40
    eval_novel: int = 40
    save_renders: int = 6
    checkpoint_every: int = 20

    def validate(self) -> None:
        if self.width < 0 or self.height < 0:
            raise ValueError("width/height must be >= 0")
        if self.eval_keyframes < 0 or self.eval_novel < 0 or self.save_renders < 0:
            raise ValueError("eval_keyframes, eval_novel and save_renders must be >= 0")


def auto_working_size(native_w: int, native_h: int, width: int = 0, height: int = 0) -> tuple[int, int]:
    """Working resolution from the run config (0 = automatic, see :class:`RunConfig`)."""
    if width and height:
        return width, height
    if width:
        return width, max(8, round(native_h * width / native_w))
    if height:
        return max(8, round(native_w * height / native_h)), height
    if native_w > 640:
        return native_w // 2, native_h // 2
    return native_w, native_h


def _even_subset(items: list, n: int) -> list:
    if n <= 0 or not items:
        return []
    if len(items) <= n:
        return list(items)
    idx = np.unique(np.linspace(0, len(items) - 1, n).round().astype(int))
    return [items[i] for i in idx]


class _GtKeyframer:
    """Keyframes from ground-truth poses and depth (``gt_poses`` mode)."""

    def __init__(self, source: Source, cfg: RunConfig) -> None:
        gt = source.gt_camera_trajectory()
        if gt is None or len(gt) < 2:
            raise InputError(f"{source.path}: --gt-poses needs ground-truth poses, the source has none")
        self.gt, self.cfg, self.source = gt, cfg, source
        self.last: Optional[tuple[int, np.ndarray]] = None
        self.count = 0
        self.gap = 0

    def pose(self, stamp: int) -> np.ndarray:
        from .eval.traj import interpolate_poses
        return interpolate_poses(self.gt, np.array([stamp], np.int64))[0]

    def process(self, frame: Frame) -> tuple[np.ndarray, Optional[Keyframe]]:
        T = self.pose(frame.stamp_ns)
        self.gap += 1
        new = self.last is None
        if not new:
            d = np.linalg.norm(T[:3, 3] - self.last[1][:3, 3])
            ang = float(rotation_angle_deg(self.last[1][:3, :3].T @ T[:3, :3]))
            new = d > self.cfg.gt_kf_trans_m or ang > self.cfg.gt_kf_rot_deg or self.gap >= self.cfg.gt_kf_max_gap
        if not new:
            return T, None
        depth = self.source.gt_depth(frame.stamp_ns)
        if depth is None:
            raise InputError(f"{self.source.path}: --gt-poses needs ground-truth depth for every "
                             f"keyframe; none for frame {frame.stamp_ns}")
        self.last, self.gap = (frame.stamp_ns, T), 0
        depth_t = torch.from_numpy(np.ascontiguousarray(depth, np.float32))
        valid = depth_t > 0
        kf = Keyframe(stamp_ns=frame.stamp_ns,
                      image=torch.from_numpy(frame.rgb().astype(np.float32) / 255.0),
                      T_wc=torch.from_numpy(T), depth=depth_t,
                      inv_depth_var=torch.full_like(depth_t, self.cfg.gt_inv_depth_var),
                      valid=valid, camera=frame.camera, index=self.count)
        self.count += 1
        return T, kf


class SlamRunner:
    """Runs front end + mapper over a source and writes the output contract to ``out_dir``."""

    def __init__(self, source: Source, out_dir: str | Path, params_file: Optional[str] = None,
                 run_cfg: Optional[RunConfig] = None, progress: bool = True,
                 on_frame: Optional[Callable[[dict], None]] = None) -> None:
        from .frontend import Frontend, FrontendConfig
        from .mapping import Mapper, MapperConfig

        self.source = source
        self.cfg = run_cfg or load_section(RunConfig, "run", params_file)
        self.out = RunOutput(out_dir)
        self.progress = progress
        self.on_frame = on_frame
        cam = source.calibration.camera
        if cam is None:
            raise InputError(f"{source.path}: the recording has no camera images; SLAM needs an image stream")
        self.camera = cam
        self.mapper = Mapper(load_section(MapperConfig, "mapping", params_file))
        self.frontend = None if self.cfg.gt_poses else Frontend(
            load_section(FrontendConfig, "frontend", params_file), cam)
        self.gt_kf = _GtKeyframer(source, self.cfg) if self.cfg.gt_poses else None
        # evaluation material kept while running
        self._kf_images: dict[int, np.ndarray] = {}
        self._frame_images: dict[int, np.ndarray] = {}
        self._gt_poses: dict[int, np.ndarray] = {}
        self._kf_stamps: list[int] = []
        self._mapper_err: Optional[BaseException] = None
        self._pending_refined: dict[int, np.ndarray] = {}
        self._lock = threading.Lock()
        self._queue: "queue.Queue[Optional[tuple[str, object]]]" = queue.Queue()
        self._sent_kf_poses: dict[int, np.ndarray] = {}   # front-end keyframe poses given to the mapper

    # --------------------------------------------------------------------------- mapping side

    def _map_keyframe(self, kf: Keyframe) -> None:
        self.mapper.add_keyframe(kf)
        self.mapper.train()
        if self.frontend is not None:
            refined = self.mapper.refine_poses()
            if refined:
                with self._lock:
                    self._pending_refined.update(refined)
        n = len(self._kf_stamps)
        if self.cfg.checkpoint_every and n % self.cfg.checkpoint_every == 0:
            self.mapper.save_checkpoint(self.out.out_dir / CHECKPOINT_FILE)

    def _handle(self, kind: str, item: object) -> None:
        if kind == "kf":
            self._map_keyframe(item)
        else:  # "poses": front-end BA moved keyframes the mapper already holds
            self.mapper.set_keyframe_poses(item)

    def _mapper_loop(self) -> None:
        try:
            while True:
                msg = self._queue.get()
                if msg is None:
                    return
                self._handle(*msg)
        except BaseException as e:  # surfaced in the main thread
            self._mapper_err = e
            log.exception("mapper thread failed")

    def _submit(self, kf: Keyframe, worker: Optional[threading.Thread]) -> None:
        self._kf_stamps.append(kf.stamp_ns)
        self._kf_images[kf.stamp_ns] = (kf.image.numpy() * 255).round().astype(np.uint8)
        self._sent_kf_poses[kf.stamp_ns] = kf.T_wc.numpy().copy()
        self._dispatch("kf", kf, worker)

    def _dispatch(self, kind: str, item: object, worker: Optional[threading.Thread]) -> None:
        if worker is None:
            self._handle(kind, item)
        else:
            self._queue.put((kind, item))

    def _sync_poses(self, worker: Optional[threading.Thread]) -> None:
        """Refined keyframe poses -> front end; front-end BA updates of mapped keyframes -> mapper."""
        if self.frontend is None:
            return
        with self._lock:
            refined, self._pending_refined = self._pending_refined, {}
        if refined:
            self.frontend.set_poses(refined)
            self._sent_kf_poses.update({int(s): np.asarray(T) for s, T in refined.items()})
        moved = {}
        for s, T in zip(*self._frontend_kf_poses()):
            old = self._sent_kf_poses.get(s)
            if old is not None and np.abs(old - T).max() > 1e-7:
                moved[s] = T
        if moved:
            self._sent_kf_poses.update(moved)
            self._dispatch("poses", moved, worker)

    def _frontend_kf_poses(self) -> tuple[list[int], np.ndarray]:
        traj = self.frontend.keyframe_trajectory()
        return traj.stamps_ns.tolist(), traj.poses

    # --------------------------------------------------------------------------------- run

    def run(self) -> dict:
        """Process the whole source; returns the metrics dict (also written to metrics.json)."""
        t0 = time.perf_counter()
        stamps = self.source.frame_stamps()
        n_total = len(stamps)
        if n_total == 0:
            raise InputError(f"{self.source.path}: no camera frames to process")
        keep_novel = set(_even_subset(list(stamps), max(self.cfg.eval_novel * 2, 1)))
        worker = None
        if not self.cfg.sync:
            worker = threading.Thread(target=self._mapper_loop, name="vings-mapper", daemon=True)
            worker.start()
        bar = _progress(n_total, self.progress)
        n_frames = 0
        try:
            for frame in self.source.frames():
                n_frames += 1
                if self._mapper_err is not None:
                    raise VingsError(f"mapper failed: {self._mapper_err}")
                self._sync_poses(worker)
                if self.gt_kf is not None:
                    T, kf = self.gt_kf.process(frame)
                    self._gt_poses[frame.stamp_ns] = T
                    kfs = [kf] if kf is not None else []
                    state = "tracking"
                else:
                    ests = self.frontend.process(frame)
                    kfs = self.frontend.pop_keyframes()
                    state = ests[-1].state if ests else self.frontend.state
                if frame.stamp_ns in keep_novel:
                    self._frame_images[frame.stamp_ns] = frame.rgb().copy()
                for kf in kfs:
                    self._submit(kf, worker)
                bar.update(1)
                bar.set_postfix_str(f"{state} kf={len(self._kf_stamps)}", refresh=False)
                if self.on_frame is not None:
                    self.on_frame({"stamp_ns": frame.stamp_ns, "state": state,
                                   "keyframes": len(self._kf_stamps)})
            if self.frontend is not None:
                for kf in self.frontend.finish():
                    self._submit(kf, worker)
                self._sync_poses(worker)
        finally:
            if worker is not None:
                self._queue.put(None)
                worker.join()
            bar.close()
        if self._mapper_err is not None:
            raise VingsError(f"mapper failed: {self._mapper_err}")
        self._sync_poses(None)
        wall = time.perf_counter() - t0
        return self._finish(n_frames, wall)

    # ------------------------------------------------------------------------------ outputs

    def trajectory(self) -> Trajectory:
        """Every tracked frame's cam0 ``T_wc``."""
        if self.frontend is None:
            st = sorted(self._gt_poses)
            return Trajectory(np.array(st, np.int64), np.stack([self._gt_poses[s] for s in st]))
        return self.frontend.trajectory(states=("tracking",))

    def keyframe_trajectory(self) -> Trajectory:
        poses = self.mapper.keyframe_poses()
        st = sorted(poses)
        return Trajectory(np.array(st, np.int64),
                          np.stack([poses[s] for s in st]) if st else np.zeros((0, 4, 4)))

    def _finish(self, n_frames: int, wall: float) -> dict:
        traj = self.trajectory()
        kf_traj = self.keyframe_trajectory()
        self.out.write_trajectory(traj)
        self.out.write_keyframes(kf_traj)
        self.mapper.save_ply(self.out.map_path)
        self.mapper.save_checkpoint(self.out.out_dir / CHECKPOINT_FILE)
        m = metrics_template()
        m.update(frames=n_frames, frames_tracked=len(traj), keyframes=len(kf_traj), wall_s=wall,
                 fps=n_frames / wall if wall > 0 else None, num_gaussians=int(self.mapper.num_gaussians))
        gt = self.source.gt_camera_trajectory()
        if gt is not None and len(traj) >= 3:
            try:
                ev = evaluate_trajectory(traj, gt)
                m.update({k: ev.get(k) for k in ("ate_sim3_m", "ate_se3_m", "sim3_scale", "rpe")})
            except InputError as e:
                log.warning("trajectory evaluation skipped: %s", e)
        m.update(self._image_metrics(kf_traj, traj))
        m["peak_rss_mb"] = peak_rss_mb()
        return self.out.write_metrics(m)

    def _image_metrics(self, kf_traj: Trajectory, traj: Trajectory) -> dict:
        kf_poses = dict(zip(kf_traj.stamps_ns.tolist(), kf_traj.poses))
        psnrs, ssims = [], []
        eval_kfs = _even_subset([s for s in self._kf_stamps if s in kf_poses], self.cfg.eval_keyframes)
        save = set(_even_subset(eval_kfs, self.cfg.save_renders))
        for s in eval_kfs:
            out = self.mapper.render(kf_poses[s], self.camera)
            ref = self._kf_images[s].astype(np.float32) / 255.0
            psnrs.append(psnr(out["color"], ref))
            ssims.append(ssim(out["color"], ref))
            if s in save:
                self.out.save_render(f"kf_{s}.png", out["color"])
        frame_poses = dict(zip(traj.stamps_ns.tolist(), traj.poses))
        kf_set = set(self._kf_stamps)
        novel = _even_subset([s for s in sorted(self._frame_images) if s in frame_poses and s not in kf_set],
                             self.cfg.eval_novel)
        npsnr = []
        for s in novel:
            out = self.mapper.render(frame_poses[s], self.camera)
            npsnr.append(psnr(out["color"], self._frame_images[s].astype(np.float32) / 255.0))
        fin = lambda v: [x for x in v if np.isfinite(x)]  # noqa: E731
        return {"psnr_keyframes_db": float(np.mean(fin(psnrs))) if fin(psnrs) else None,
                "ssim_keyframes": float(np.mean(ssims)) if ssims else None,
                "psnr_novel_db": float(np.mean(fin(npsnr))) if fin(npsnr) else None}


def _progress(total: int, enabled: bool):
    from tqdm import tqdm
    return tqdm(total=total, unit="frame", disable=not enabled, dynamic_ncols=True, leave=True)
