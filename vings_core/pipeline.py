"""The offline SLAM runner: a :class:`~vings_core.io.Source` through the front end and the mapper.

``SlamRunner(source, ...).run()`` is what ``vings run`` calls; the ROS nodes call the same stage
classes (:class:`~vings_core.frontend.Frontend`, :class:`~vings_core.mapping.Mapper`), so offline
and ROS results agree.

Two modes:

* **concurrent** (default, as in the paper): the mapper trains in its own (niced) thread on a
  :class:`~vings_core.keyframe_queue.KeyframeQueue`, bounded in memory and spilling to disk, so
  tracking never waits for it (unless ``run.max_mapper_lag`` asks for it). Poses move between the
  stages through the pose exchange (:mod:`vings_core.exchange`) between frames.
* **sync** (``RunConfig.sync``): after each keyframe the mapper trains to completion before the next
  frame: deterministic, for tests and benchmarks.

With ``gt_poses`` the front end is bypassed: keyframes are taken from ground-truth camera poses and
ground-truth depth (sources that have both), for mapping benchmarks.
"""
from __future__ import annotations

import logging
import math
import threading
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable, Optional, Protocol

import numpy as np
import torch

from .config import load_section
from .errors import InputError, VingsError
from .eval.image import psnr, ssim
from .eval.output import CHECKPOINT_FILE, RUN_RENDER_PREFIX, RunOutput, metrics_template, peak_rss_mb  # noqa: F401
from .eval.traj import evaluate_trajectory
from .eraser.mask_io import encode_mask_png
from .exchange import ExchangeConfig, IncrementBatch, PoseFollower, PoseKeeper
from .geometry import rotation_angle_deg
from .io.base import Source, SourceOptions
from .keyframe_queue import KeyframeQueue
from .profiling import PROFILE, timed, timed_iter
from .stages import MAPPER_SOURCE
from .stages import map_keyframe, retrain_after_loop
from .types import POSED_STATES, Frame, Keyframe, TrackState, Trajectory
from .util import nice_current_thread

log = logging.getLogger("vings.run")

@dataclass
class RunConfig:
    """Runner settings (params section ``run``).

    ``width``/``height``: working resolution; 0 = automatic (half the native size when the native
    width exceeds 640 px, e.g. EuRoC 752x480 -> 376x240, KITTI 1226x370 -> 613x185; else native).
    ``gt_kf_*``: keyframe selection in ``gt_poses`` mode (translation m, rotation deg, max frame gap);
    ``gt_inv_depth_var``: the inverse-depth variance (1/m^2) given to ground-truth depth (0 = exact;
    a positive value masks far pixels as uncertain and down-weights their depth loss).
    ``eval_keyframes``/``eval_novel``: at most this many keyframes / non-keyframe frames are rendered
    for PSNR (evenly spaced). ``save_renders``: keyframe renders saved under renders/.
    ``checkpoint_every``: keyframes between map checkpoints (0 = only at the end).
    ``report``: write ``report.html`` and ``bev.png`` at the end (docs/report.md; the report's data,
    ``timeline.jsonl``, ``run.json``, ``views/``, are written either way).
    ``queue_memory_keyframes``: without ``sync``, keyframes waiting for the mapper thread that are
    held in memory; later ones spill to disk (:class:`~vings_core.keyframe_queue.KeyframeQueue`),
    so memory stays bounded and tracking never waits. ``queue_spill_dir``: their folder (empty: a
    ``.queue`` folder in the output folder, removed at the end).
    ``mapper_nice``: niceness added to the mapper thread alone (0-19), so that on a small machine
    tracking gets the CPU first and stays real time.
    ``max_mapper_lag``: when > 0, tracking waits while that many keyframes are queued (the mapper's
    refinements then reach the front end sooner, at the cost of real time); 0 (default) = never.
    The pose exchange between the stages has its own section, ``exchange``
    (:class:`~vings_core.exchange.ExchangeConfig`).
    """

    RENAMED = {"pose_writeback": "exchange.mapper", "writeback_confidence": "exchange.confidence"}

    width: int = 0
    height: int = 0
    sync: bool = False
    gt_poses: bool = False
    gt_kf_trans_m: float = 0.25
    gt_kf_rot_deg: float = 10.0
    gt_kf_max_gap: int = 10
    gt_inv_depth_var: float = 0.0
    eval_keyframes: int = 40
    eval_novel: int = 40
    save_renders: int = 6
    checkpoint_every: int = 20
    report: bool = True
    max_mapper_lag: int = 0
    mapper_nice: int = 10
    queue_memory_keyframes: int = 8
    queue_spill_dir: str = ""

    def validate(self) -> None:
        if self.width < 0 or self.height < 0:
            raise ValueError("width/height must be >= 0")
        if self.eval_keyframes < 0 or self.eval_novel < 0 or self.save_renders < 0:
            raise ValueError("eval_keyframes, eval_novel and save_renders must be >= 0")
        if self.gt_kf_max_gap < 1:
            raise ValueError(f"gt_kf_max_gap must be >= 1 frame, got {self.gt_kf_max_gap}")
        if self.max_mapper_lag < 0:
            raise ValueError(f"max_mapper_lag must be >= 0, got {self.max_mapper_lag}")
        if not 0 <= self.mapper_nice <= 19:
            raise ValueError(f"mapper_nice must be in 0..19, got {self.mapper_nice}")
        if self.queue_memory_keyframes < 1:
            raise ValueError(f"queue_memory_keyframes must be >= 1, got {self.queue_memory_keyframes}")
        for name in ("gt_kf_trans_m", "gt_kf_rot_deg", "gt_inv_depth_var"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"{name} must be a finite number >= 0, got {v}")
        if self.checkpoint_every < 0:
            raise ValueError(f"checkpoint_every must be >= 0 (0 = only at the end), got {self.checkpoint_every}")


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


def open_working_source(path, opts: SourceOptions, width: int = 0, height: int = 0) -> Source:
    """Open ``path`` at the working resolution ``vings run`` uses: the size in ``opts`` when it
    sets one, else :func:`auto_working_size` of the stored images' camera with the run config's
    ``width``/``height`` (0 = automatic)."""
    from .io import open_source
    if opts.width is None and opts.height is None:
        cam = open_source(path, opts).raw_camera
        if cam is not None:
            w, h = auto_working_size(cam.width, cam.height, width, height)
            opts = replace(opts, width=w, height=h)
    return open_source(path, opts)


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
        self.skipped = 0        # frames without a ground-truth pose (outside its span, or in a gap)

    def pose(self, stamp: int) -> Optional[np.ndarray]:
        """Ground-truth ``T_wc`` at ``stamp`` by the evaluation's association rules (interpolated
        between samples at most 2 max_dt apart, else the nearest sample within max_dt); None when
        the ground truth has no pose there (never extrapolated, never bridged over a gap)."""
        from .eval.traj import DEFAULT_MAX_DT_NS, associate_indices
        one = Trajectory(np.array([stamp], np.int64), np.eye(4)[None])
        try:
            a = associate_indices(one, self.gt, DEFAULT_MAX_DT_NS)
        except InputError:      # outside the ground truth's span
            return None
        return a["gt_poses"][0] if len(a["est_idx"]) else None

    def process(self, frame: Frame) -> tuple[Optional[np.ndarray], Optional[Keyframe]]:
        """(ground-truth pose or None, keyframe or None) for one frame."""
        T = self.pose(frame.stamp_ns)
        if T is None:
            self.skipped += 1
            if self.skipped in (1, 20) or self.skipped % 200 == 0:
                log.warning("--gt-poses: no ground-truth pose at frame %d (outside the ground truth's "
                            "span %d..%d ns, or in a gap); frame skipped (%d so far)", frame.stamp_ns,
                            int(self.gt.stamps_ns[0]), int(self.gt.stamps_ns[-1]), self.skipped)
            return None, None
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


class RunnerStage(Protocol):
    """A further pose writer in ``vings run`` (a loop closer, or a test's stage): it follows the
    keeper's batches and offers its own, through the same exchange as the nodes."""

    name: str

    def add_keyframe(self, kf: Keyframe) -> None:
        """A keyframe the front end emitted (its pose as emitted)."""

    def receive(self, batch: IncrementBatch) -> None:
        """A batch of the keeper (the front end)."""

    def poll(self) -> Optional[IncrementBatch]:
        """Its own increments since the last call, or None."""


class SlamRunner:
    """Runs front end + mapper (+ ``stages``) over a source and writes the output contract to
    ``out_dir``."""

    def __init__(self, source: Source, out_dir: str | Path, params_file: Optional[str] = None,
                 run_cfg: Optional[RunConfig] = None, progress: bool = True,
                 on_frame: Optional[Callable[[dict], None]] = None,
                 stages: tuple[RunnerStage, ...] = (), exchange_cfg: Optional[ExchangeConfig] = None,
                 vio_cfg: Optional["ViConfig"] = None, loop_cfg: Optional["LoopConfig"] = None,
                 eraser_cfg: Optional["EraserConfig"] = None, rerun_path: Optional[str] = None) -> None:
        """``vio_cfg``: the visual-inertial fusion's configuration (default: section ``vio`` of the
        params file; ``enabled=False`` is ``--no-imu``). ``loop_cfg``: the loop closer's (default:
        section ``loop``; ``enabled=False`` is ``--no-loop``); the loop closer runs in the mapper's
        thread after each mapped keyframe, its renders from the map as trained. ``eraser_cfg``: the
        dynamic eraser's (default: section ``eraser``; ``enabled=False`` is ``--no-eraser``); it
        runs in the mapper's thread on each keyframe before its Gaussians are added, and its mask
        goes to the mapper at once and to the front end for its next frame. ``rerun_path``: log the
        run for the rerun viewer to this ``.rrd`` file (:mod:`vings_core.report.rerun_log`; needs
        the optional rerun SDK)."""
        from .frontend import Frontend, FrontendConfig
        from .mapping import Mapper, MapperConfig
        from .vio.config import ViConfig
        from .vio.fusion import ViFusion

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
        self.vio, self.vio_why = None, "visual-only"
        if not self.cfg.gt_poses:
            vcfg = vio_cfg or load_section(ViConfig, "vio", params_file)
            has_imu = bool(source.calibration.has_imu or source.imu_samples())
            self.vio, self.vio_why = ViFusion.for_source(vcfg, source.calibration, has_imu)
            if self.vio is None and has_imu and vcfg.enabled:
                log.error("%s", self.vio_why)
            else:
                log.info("IMU fusion: %s", self.vio_why)
        self.frontend = None if self.cfg.gt_poses else Frontend(
            load_section(FrontendConfig, "frontend", params_file), cam, vio=self.vio)
        self.gt_kf = _GtKeyframer(source, self.cfg) if self.cfg.gt_poses else None
        # evaluation material kept while running; keyframe images: every stride-th keyframe, the
        # stride doubling whenever more than 2 x eval_keyframes are held (bounded memory on long
        # recordings, still evenly spread over the run)
        self._kf_images: dict[int, tuple[int, np.ndarray]] = {}
        self._kf_stride = 1
        self._frame_images: dict[int, np.ndarray] = {}
        self._gt_poses: dict[int, np.ndarray] = {}
        self._kf_stamps: list[int] = []
        self._mapper_err: Optional[BaseException] = None
        self._abort = False     # set when the run fails: the mapper thread drops what is queued
        self._mapper_done = threading.Event()
        self._partial_ckpt = False  # this run wrote checkpoint.partial.pt
        self._to_keeper: list[IncrementBatch] = []     # mapper batches, from the mapper thread
        self._lock = threading.Lock()
        self._queue = KeyframeQueue(self.cfg.queue_memory_keyframes,
                                    self.cfg.queue_spill_dir or self.out.out_dir / ".queue", remove_dir=True)
        # slots of the bounded mapper queue (mapper thread only, see max_mapper_lag)
        self._kf_queued = (threading.Semaphore(self.cfg.max_mapper_lag)
                           if self.cfg.max_mapper_lag and not self.cfg.sync else None)
        self._lag_warned = False
        self.light_keyframes = 0    # keyframes trained lightly to catch up (mapping.catch_up_backlog)
        # the pose exchange, as between the nodes: the front end keeps the poses, the mapper and the
        # further stages follow it
        self.xcfg = exchange_cfg or load_section(ExchangeConfig, "exchange", params_file)
        self.keeper = None if self.frontend is None else PoseKeeper(self.frontend, self.xcfg)
        self.follower = PoseFollower(MAPPER_SOURCE, self.mapper)
        self.stages = tuple(stages)
        from .loop import LoopCloser, LoopConfig
        from .vio.config import ViState
        lcfg = loop_cfg or load_section(LoopConfig, "loop", params_file)
        self.loop: Optional[LoopCloser] = None
        if lcfg.enabled and self.frontend is not None:
            self.loop = LoopCloser(lcfg, render=self._loop_render,
                                   metric=lambda: self.vio is not None and self.vio.state == ViState.VISUAL_INERTIAL)
        self._loop_ack = 0
        self.loop_error: Optional[str] = None
        self.retrains: list[dict] = []
        from .eraser import DynamicEraser, EraserConfig
        ecfg = eraser_cfg or load_section(EraserConfig, "eraser", params_file)
        self.eraser: Optional[DynamicEraser] = DynamicEraser(ecfg) if ecfg.enabled else None
        self.eraser_error: Optional[str] = None
        self.eraser_results: list[dict] = []     # per keyframe: EraserResult.summary()
        self._masks: dict[int, bytes] = {}       # stamp -> PNG (mono8), written at the end
        self._eraser_epoch = (1, 0)              # (front-end segments, loop corrections acknowledged)
        from .report.timeline import Timeline
        self.timeline: Optional[Timeline] = None     # timeline.jsonl, from run()
        self._views: list[dict] = []                 # views/ of the saved keyframe renders
        self._loop_seen = 0                          # loop records already in the timeline
        self._n_frames = 0
        self.report_s: Optional[float] = None       # time to draw report.html and bev.png
        self.rerun = None
        if rerun_path:
            from .report.rerun_log import RerunLog
            self.rerun = RerunLog(rerun_path, cam)
        self.out.prepare()      # after the configuration is known to be valid, before any work
        self._queue.discard_leftovers()     # of a killed earlier run (runs do not resume)

    # --------------------------------------------------------------------------- mapping side

    def _map_keyframe(self, kf: Keyframe) -> None:
        kf = self._erase(kf)
        stats, batch = map_keyframe(self.mapper, self.follower, kf, refine=self.frontend is not None,
                                    chunk=10, stop=lambda: self._abort, backlog=self._backlog())
        self.light_keyframes += int(stats.get("light", False))
        if batch is not None:
            with self._lock:
                self._to_keeper.append(batch)
        n = len(self.mapper.keyframe_poses())
        if self.cfg.checkpoint_every and n % self.cfg.checkpoint_every == 0 and not self._abort:
            # the previous run's checkpoint.pt stays until this run completes
            self.mapper.save_checkpoint(self.out.partial_checkpoint_path)
            self._partial_ckpt = True

    def _erase(self, kf: Keyframe) -> Keyframe:
        """The dynamic eraser on keyframe ``kf`` (mapper thread), on the map rendered at its pose
        before its Gaussians are added: the keyframe with its mask for the mapper, the mask posted
        to the front end and kept for ``masks/``. A failing eraser stops itself (logged,
        ``metrics.json`` ``eraser_error``); mapping goes on without masks."""
        if self.eraser is None or self.eraser_error is not None or self._abort:
            return kf
        # the previous keyframe is no reference for the motion cue after a new map segment or a
        # loop correction (another frame, or poses that jumped)
        epoch = (self.frontend.stats["segments"] if self.frontend is not None else 0, self._loop_ack)
        if epoch != self._eraser_epoch:
            self.eraser.reset()
            self._eraser_epoch = epoch
        try:
            with timed("eraser", "keyframe (total)"):
                with timed("eraser", "render"):
                    render = (self.mapper.render(kf.T_wc.detach().cpu().numpy(), kf.camera)
                              if self.mapper.num_gaussians else None)
                res = self.eraser.process(kf, render)
        except Exception as e:  # noqa: BLE001 - the eraser is optional: tracking and mapping go on
            log.exception("the dynamic eraser failed at keyframe %d; it is off for the rest of the run", kf.stamp_ns)
            self.eraser_error = f"failed at keyframe {kf.stamp_ns}: {type(e).__name__}: {e}"
            return kf
        self.eraser_results.append(res.summary())
        self._masks[int(kf.stamp_ns)] = encode_mask_png(res.mask)
        if not res.mask.any():
            return kf
        if self.frontend is not None:
            self.frontend.post_dynamic_mask(kf.stamp_ns, res.mask)
        return replace(kf, dynamic=torch.from_numpy(res.mask))

    def _loop_render(self, T_wc: np.ndarray, camera, older_than: Optional[int]) -> Optional[dict]:
        """The loop closer's renders (mapper thread): the map from ``T_wc``, Gaussians of keyframes
        older than ``older_than`` only."""
        if not self.mapper.num_gaussians:
            return None
        return self.mapper.render(T_wc, camera, owners_before=older_than)

    def _close_loops(self, kf: Keyframe) -> None:
        """The loop closer after the keyframe was mapped; its correction goes to the keeper. A
        failure of the loop closer stops it (logged, ``loops.json`` says why), never the mapping."""
        if self.loop is None or self._abort or self.loop_error is not None:
            return
        if self.frontend is not None:       # the front end's later map segments: rejoined by a loop
            for seg, first in self.frontend.segment_starts().items():
                if seg > 0:
                    self.loop.segment_started(first)
        try:
            with timed("loop", "keyframe (total)"):
                self.loop.add_keyframe(kf)
        except Exception as e:  # noqa: BLE001 - the loop closer is optional: tracking and mapping go on
            log.exception("the loop closer failed at keyframe %d; it is off for the rest of the run", kf.stamp_ns)
            self.loop_error = f"failed at keyframe {kf.stamp_ns}: {type(e).__name__}: {e}"
            return
        batch = self.loop.poll()
        if batch is not None:
            with self._lock:
                self._to_keeper.append(batch)

    def _backlog(self) -> int:
        """Keyframes waiting for the mapper thread (0 in sync mode)."""
        return self._queue.keyframes

    def _record_timeline(self, kf: Keyframe) -> None:
        """The timeline's line of keyframe ``kf`` (mapper thread, after its mapping and loop check)."""
        if self.timeline is None or self._abort:
            return
        loop = None
        if self.loop is not None:
            new = self.loop.records[self._loop_seen:]
            self._loop_seen = len(self.loop.records)
            loop = {"candidates": len(new), "accepted": sum(r.get("verdict") == "accepted" for r in new)}
        er = None
        if self.eraser is not None and self.eraser_results and self.eraser_results[-1].get("stamp_ns") == kf.stamp_ns:
            r = self.eraser_results[-1]
            er = {"masked_fraction": r["masked_fraction"], "time_ms": r["time_ms"], "proposals": r["proposals"],
                  "dynamic_rerender": r["dynamic_rerender"], "dynamic_motion": r["dynamic_motion"]}
        mp = self.mapper
        fe = self.frontend
        self.timeline.record(
            kf.stamp_ns, {"active": mp.num_active, "passive": mp.num_passive, "on_disk": mp.passive.num_on_disk,
                          "total": mp.num_gaussians},
            tracking=None if fe is None else str(fe.state.value),
            vi_state=None if self.vio is None else str(self.vio.status()["vi_state"]),
            mapper={"light": self.light_keyframes > self._light_seen, "backlog": self._backlog()},
            loop=loop, eraser=er)
        self._light_seen = self.light_keyframes
        if self.rerun is not None:
            T = mp.keyframe_poses().get(int(kf.stamp_ns))
            if T is not None:
                pts = mp.point_sample(self.rerun.map_points) if self.rerun.want_points() else None
                self.rerun.keyframe(kf.stamp_ns, T, mp.render(T, kf.camera) if mp.num_gaussians else None, pts)

    def _handle(self, kind: str, item: object) -> None:
        if kind == "kf":
            try:
                self._map_keyframe(item)
                self._close_loops(item)
                self._record_timeline(item)
            finally:
                if self._kf_queued is not None:
                    self._kf_queued.release()
        else:  # "poses": the keeper's batch (front-end moves, accepted and refused increments)
            self.follower.receive(item)
            if self.loop is not None and self.loop_error is None:
                self.loop.receive(item)
                lc = self.loop.cfg
                self._loop_ack, re = retrain_after_loop(self.mapper, item, self._loop_ack, lc.retrain_iters,
                                                        lc.retrain_max_s, lc.prune_after)
                if re is not None:
                    self.retrains.append(re)
                    log.info("loop correction: map retrained %d iterations over %d views in %.2f s, %d pruned",
                             re["retrain_iters"], re["retrain_views"], re.get("retrain_s", 0.0), re["loop_pruned"])

    def _mapper_loop(self) -> None:
        nice_current_thread(self.cfg.mapper_nice)
        try:
            while True:
                if self._abort:     # a failed or interrupted run writes nothing: drop the rest
                    self._queue.clear()
                msg = self._queue.get(0.2)
                if msg is None:
                    if self._queue.closed() and not len(self._queue):
                        return
                    continue
                if not self._abort:
                    self._handle(*msg)
        except VingsError as e:     # a user-facing error (disk full, bad input): one line, in the main thread
            self._mapper_err = e
            log.debug("mapper thread stopped", exc_info=True)
        except BaseException as e:  # a bug: traceback here, surfaced in the main thread
            self._mapper_err = e
            log.exception("mapper thread failed")
        finally:
            self._mapper_done.set()

    def _raise_mapper_error(self) -> None:
        e = self._mapper_err
        if e is None:
            return
        if isinstance(e, VingsError):
            raise e
        raise VingsError(f"mapper failed: {type(e).__name__}: {e}") from e

    def _stop_worker(self, worker: Optional[threading.Thread]) -> None:
        """Let the mapper thread finish what is queued (or, after ``_abort``, drop it) and wait for
        it. A Ctrl-C while waiting aborts the queue and keeps waiting: the thread must be out of
        torch before the interpreter exits (a thread killed inside it aborts the process)."""
        if worker is None:
            return
        self._queue.put(None)
        while not self._mapper_done.is_set():
            try:
                self._mapper_done.wait(0.2)
            except KeyboardInterrupt:
                if not self._abort:
                    self._abort = True
                    log.warning("interrupted: stopping the mapper (it ends its current step)")
                    raise

    def _submit(self, kf: Keyframe, worker: Optional[threading.Thread]) -> None:
        self._kf_stamps.append(kf.stamp_ns)
        self._keep_kf_image(len(self._kf_stamps) - 1, kf)
        if self.keeper is not None:
            self.keeper.keyframe_sent(kf.stamp_ns, kf.T_wc.detach().cpu().numpy().astype(np.float64))
        for st in self.stages:
            st.add_keyframe(kf)
        self._dispatch("kf", kf, worker)

    def _keep_kf_image(self, index: int, kf: Keyframe) -> None:
        cap = 2 * self.cfg.eval_keyframes
        if cap == 0 or index % self._kf_stride:
            return
        self._kf_images[kf.stamp_ns] = (index, (kf.image.numpy() * 255).round().astype(np.uint8))
        if len(self._kf_images) > cap:
            self._kf_stride *= 2
            self._kf_images = {s: v for s, v in self._kf_images.items() if v[0] % self._kf_stride == 0}

    def _dispatch(self, kind: str, item: object, worker: Optional[threading.Thread]) -> None:
        if worker is None:
            try:
                self._handle(kind, item)
            except VingsError:
                raise
            except Exception as e:  # a bug: traceback logged, one line for the user (as the thread's)
                log.exception("mapper failed")
                raise VingsError(f"mapper failed: {type(e).__name__}: {e}") from e
            return
        if kind == "kf" and self._kf_queued is not None:
            self._wait_for_mapper()
        self._queue.put(kind, item)

    def _wait_for_mapper(self) -> None:
        """Take a keyframe slot of the bounded mapper queue (``max_mapper_lag``); waits while the
        mapper thread works, and stops waiting when it failed."""
        if self._kf_queued.acquire(blocking=False):
            return
        if not self._lag_warned:
            self._lag_warned = True
            log.info("tracking waits for the mapper (%d keyframes queued, run.max_mapper_lag)",
                     self.cfg.max_mapper_lag)
        while not self._kf_queued.acquire(timeout=0.2):
            if self._mapper_done.is_set():
                self._raise_mapper_error()
                return

    def _take_corrections(self) -> None:
        """The writers' batches (mapper refinements, further stages) -> front end, through their
        write-back policies, before a frame."""
        if self.keeper is None:
            return
        with self._lock:
            pending, self._to_keeper = self._to_keeper, []
        pending += [b for b in (st.poll() for st in self.stages) if b is not None]
        for batch in pending:
            self.keeper.receive(batch)

    def _send_moves(self, worker: Optional[threading.Thread], seq_hint: int = 0) -> None:
        """The keeper's batch (front-end moves since the last one, and what it did with the writers'
        batches) -> mapper and further stages, after a frame and before its new keyframes (so the
        mapper refines from the front end's latest poses)."""
        if self.keeper is None:
            return
        batch = self.keeper.outgoing(seq_hint)
        if batch is not None:
            for st in self.stages:
                st.receive(batch)
            self._dispatch("poses", batch, worker)

    # --------------------------------------------------------------------------------- run

    def run(self) -> dict:
        """Process the whole source; returns the metrics dict (also written to metrics.json)."""
        t0 = time.perf_counter()
        from .report.timeline import Timeline
        own_profile = not PROFILE.enabled   # the timeline's step times (a timer costs ~1 us)
        if own_profile:
            PROFILE.enable()
        self.timeline, self._light_seen = Timeline(PROFILE, t0), 0
        try:
            return self._run(t0)
        finally:
            if own_profile:
                PROFILE.disable()
            if self.rerun is not None:
                self.rerun.close()

    def _run(self, t0: float) -> dict:
        stamps = self.source.frame_stamps()
        n_total = len(stamps)
        if n_total == 0:
            raise InputError(f"{self.source.path}: no camera frames to process")
        # candidates for the novel views, chosen before it is known which frames become keyframes:
        # twice as many as needed and at least eight more, so a few keyframes among them (the first
        # frame always is one) still leave eval_novel non-keyframes
        n_novel = self.cfg.eval_novel
        keep_novel = set(_even_subset(list(stamps), max(2 * n_novel, n_novel + 8) if n_novel else 0))
        worker = None
        if not self.cfg.sync:
            worker = threading.Thread(target=self._mapper_loop, name="vings-mapper", daemon=True)
            worker.start()
        bar = _progress(n_total, self.progress)
        n_frames = 0
        try:
            for frame in timed_iter(self._frames(), "io", "read frame"):
                n_frames += 1
                state = self._track_frame(frame, worker, frame.stamp_ns in keep_novel)
                bar.update(1)
                bar.set_postfix_str(f"{state} kf={len(self._kf_stamps)}", refresh=False)
                if self.on_frame is not None:
                    self.on_frame({"stamp_ns": frame.stamp_ns, "state": state,
                                   "keyframes": len(self._kf_stamps)})
            bar.close()
            bad = getattr(self.source, "bad_frames", [])
            if n_frames == 0 and bad:
                raise InputError(f"{self.source.path}: none of the {len(bad)} frames could be decoded "
                                 f"(first: {bad[0]})")
            self._finish_stages(worker)
            # everything slow (evaluation renders) happens before any output file is replaced
            with timed("evaluation", "renders and metrics"):
                final = self._evaluate(n_frames)
        except BaseException as e:
            self._abort = True      # Ctrl-C or an input error: do not map the queued keyframes first
            bar.close()
            self._stop_worker_after_failure(worker)
            if self._mapper_err is not None and self._mapper_err not in (e, e.__cause__):
                log.warning("the mapper had stopped too: %s", self._mapper_err)
            self._save_partial()
            raise
        finally:
            self._queue.close()
        with timed("io", "write outputs"):
            return self._write_final(final, t0)

    def _frames(self):
        """The source's frames; with IMU fusion, the IMU readings up to each frame go to the front
        end first (the merged stream, in time order)."""
        if self.vio is None:
            yield from self.source.frames()
            return
        for item in self.source.stream():
            if isinstance(item, Frame):
                yield item
            else:
                self.frontend.add_imu(item)

    def _track_frame(self, frame: Frame, worker: Optional[threading.Thread], keep_image: bool) -> TrackState:
        """One frame: take the writers' batches, track it (or take its ground-truth pose), send the
        keeper's batch, then its keyframes. Returns the frame's tracking state."""
        self._raise_mapper_error()
        self._take_corrections()
        ests = None
        if self.gt_kf is not None:
            T, kf = self.gt_kf.process(frame)
            if T is not None:
                self._gt_poses[frame.stamp_ns] = T
            kfs = [kf] if kf is not None else []
            state = TrackState.TRACKING if T is not None else TrackState.LOST
        else:
            ests = self.frontend.process(frame)
            kfs = self.frontend.pop_keyframes()
            state = ests[-1].state if ests else self.frontend.state
            sims = self.frontend.take_similarities()
            if sims:       # the metric alignment: the followers scale their content with it
                self.keeper.own_similarity(sims)
        if keep_image:
            self._frame_images[frame.stamp_ns] = frame.rgb().copy()
        if self.rerun is not None:
            T = None
            if self.gt_kf is not None:
                T = self._gt_poses.get(frame.stamp_ns)
            elif ests and ests[-1].state in POSED_STATES:
                T = ests[-1].T_wc
            self.rerun.frame(self._n_frames, frame.stamp_ns, T, frame.rgb())
        self._n_frames += 1
        self._send_moves(worker, frame.stamp_ns)
        for kf in kfs:
            self._submit(kf, worker)
        return state

    def _finish_stages(self, worker: Optional[threading.Thread]) -> None:
        """After the last frame: the front end's last keyframes, the mapper's queue, and a last
        exchange so every stage ends at the same poses."""
        if self.frontend is not None:
            self._take_corrections()
            kfs = self.frontend.finish()
            self._send_moves(worker)
            for kf in kfs:
                self._submit(kf, worker)
        if worker is not None and self._queue.keyframes:
            n_kf = self._queue.keyframes
            log.info("tracking done; the mapper is finishing %d queued keyframe(s) (Ctrl-C stops it; "
                     "the trajectory is kept)", n_kf)
        self._stop_worker(worker)
        self._raise_mapper_error()
        self._take_corrections()
        self._send_moves(None)

    def _stop_worker_after_failure(self, worker: Optional[threading.Thread]) -> None:
        while True:
            try:
                self._stop_worker(worker)
                return
            except KeyboardInterrupt:
                continue    # already aborting: keep waiting for the thread to leave torch

    def _save_partial(self) -> None:
        """After an interruption or failure: the trajectory so far, beside the previous run's
        complete outputs (which stay untouched); best effort, never masks the original error
        (not even a second Ctrl-C while writing)."""
        try:
            traj = self.trajectory()
            if len(traj) == 0:
                return
            a, b = self.out.write_partial(traj, self.keyframe_trajectory())
            ck = self.out.partial_checkpoint_path
            log.warning("stopped early: the trajectory so far is in %s and %s%s", a, b,
                        f" (map checkpoint as of an earlier keyframe: {ck})" if self._partial_ckpt else "")
        except BaseException as e:  # noqa: BLE001 - best effort while another error propagates
            log.warning("could not write the partial trajectory: %s", e)

    # ------------------------------------------------------------------------------ outputs

    def main_segment(self) -> Optional[int]:
        """The front end's map segment with the most tracked frames (the earliest of equals), the
        one ``trajectory.tum`` holds; None without a front end or before any tracking."""
        segs = self.frontend.segments() if self.frontend is not None else []
        if not segs:
            return None
        return max(segs, key=lambda d: (d["frames"], -d["index"]))["index"]

    def segment_joins(self) -> dict[int, int]:
        """Map segment -> the earlier segment a loop joined it to (its keyframes moved into that
        segment's world frame; :attr:`LoopCloser.joins`)."""
        if self.frontend is None or self.loop is None or not self.loop.joins:
            return {}
        starts = self.frontend.segment_starts()
        by_start = {v: k for k, v in starts.items()}
        out = {}
        for s0, older in self.loop.joins.items():
            if s0 in by_start:
                out[by_start[s0]] = max((k for k, v in starts.items() if v <= older), default=0)
        return out

    def trajectory_segments(self) -> Optional[set[int]]:
        """The segments ``trajectory.tum`` holds: the main one (:meth:`main_segment`) and every
        segment joined to it by loops, directly or through others (one world frame)."""
        main = self.main_segment()
        if main is None:
            return None
        group, joins = {main}, self.segment_joins()
        grew = True
        while grew:
            grew = False
            for a, b in joins.items():
                if (a in group) != (b in group):
                    group |= {a, b}
                    grew = True
        return group

    def trajectory(self, segment: Optional[int] = -1) -> Trajectory:
        """Tracked frames' cam0 ``T_wc``: of the main segment and those joined to it by loops
        (``segment=-1``, :meth:`trajectory_segments`), of one segment, or (``None``) of every
        segment."""
        if self.frontend is None:
            return Trajectory.from_poses(self._gt_poses)
        segs = self.trajectory_segments() if segment == -1 else (None if segment is None else {segment})
        return self.frontend.trajectory(states=POSED_STATES, segments=segs)

    def _segment_records(self, gt: Optional[Trajectory]) -> tuple[list[dict], dict[int, Trajectory]]:
        """``segments.json`` entries (the front end's segments, whether each is in
        ``trajectory.tum``, its ATE Sim(3) against ``gt`` when there are 3 frames or more) and each
        segment's trajectory by index."""
        group = self.trajectory_segments() or set()
        joins = self.segment_joins()
        out, trajs = [], {}
        for d in self.frontend.segments():
            k = d["index"]
            trajs[k] = self.trajectory(k)
            rec = dict(d, joined_to=joins.get(k), in_trajectory=k in group, ate_sim3_m=None)
            if gt is not None and d["frames"] >= 3:
                try:
                    rec["ate_sim3_m"] = evaluate_trajectory(trajs[k], gt).get("ate_sim3_m")
                except InputError as e:
                    log.warning("segment %d: trajectory evaluation skipped: %s", k, e)
            out.append(rec)
        return out, trajs

    def keyframe_trajectory(self) -> Trajectory:
        return Trajectory.from_poses(self.mapper.keyframe_poses())

    def _evaluate(self, n_frames: int) -> dict:
        """Everything the final outputs need, computed in memory (renders included), before any
        file of a previous run is replaced."""
        traj = self.trajectory()
        kf_traj = self.keyframe_trajectory()
        if len(kf_traj) == 0:
            log.warning("no keyframe was mapped (%d frames; the front end did not initialise: too "
                        "few frames or too little camera motion): the map is empty", n_frames)
        elif self.mapper.num_gaussians == 0:
            log.warning("the map is empty: none of the %d keyframes had usable depth (%d frames: "
                        "too few, or too little camera motion, for confident depth)", len(kf_traj),
                        n_frames)
        m = metrics_template()
        if self.frontend is not None:
            st = self.keeper.stats
            log.info("pose write-back (mapper: %s): %d increments received, %d applied, %d refused",
                     self.xcfg.mapper, st["corrections"], st["applied"], st["rejected"])
        if self.light_keyframes:
            log.info("%d of %d keyframes trained lightly to keep up (mapping.catch_up_backlog)",
                     self.light_keyframes, len(kf_traj))
        q = self._queue.stats()
        bad = getattr(self.source, "bad_frames", [])
        if bad:
            log.warning("%d frame(s) could not be decoded and were skipped (first: %s)", len(bad), bad[0])
        m.update(frames_bad=len(bad))
        m.update(frames=n_frames, frames_tracked=len(traj), keyframes=len(kf_traj),
                 num_gaussians=int(self.mapper.num_gaussians), keyframes_light=self.light_keyframes,
                 queue_peak_keyframes=q["queue_peak_keyframes"], queue_spilled=q["queue_spilled"])
        if self.frontend is not None:
            n_unposed, why = self.frontend.unposed()
            m.update(frames_unposed=n_unposed, frames_unposed_reason=why)
            if n_unposed:
                log.warning("%d of %d frames have no pose: %s", n_unposed, n_frames, why)
        if self.frontend is not None:
            m.update(self._vi_metrics())
        if self.eraser is not None:
            er = self.eraser_results
            m.update(masked_fraction=float(np.mean([r["masked_fraction"] for r in er])) if er else 0.0,
                     eraser_ms_mean=float(np.mean([r["time_ms"] for r in er])) if er else None,
                     eraser_error=self.eraser_error)
        if self.loop is not None:
            ls = self.loop.summary()
            m.update(loops_accepted=ls["loops_accepted"], loop_candidates_rejected=ls["loop_candidates_rejected"],
                     loop_detect_ms_mean=ls["loop_detect_ms_mean"])
        # with gt_poses the trajectory IS the ground truth: no ATE/RPE to report (null)
        gt = None
        if not self.cfg.gt_poses:
            try:
                gt = self.source.gt_camera_trajectory()
            except InputError as e:    # body ground truth without an extrinsic: no metric, say why
                log.warning("trajectory evaluation skipped: %s", e)
        if gt is not None and len(traj) < 3:
            log.warning("trajectory evaluation skipped: %d tracked frame(s), at least 3 are needed", len(traj))
        elif gt is not None:
            try:
                ev = evaluate_trajectory(traj, gt)
                m.update({k: ev.get(k) for k in ("ate_sim3_m", "ate_se3_m", "sim3_scale", "rpe")})
            except InputError as e:
                log.warning("trajectory evaluation skipped: %s", e)
        segments, seg_trajs = None, None
        if self.frontend is not None:
            segments, seg_trajs = self._segment_records(gt)
            m.update(segments=len(segments),
                     ate_segments_m=[d["ate_sim3_m"] for d in segments] if gt is not None else None)
            if len(segments) > 1:
                held = sorted(d["index"] for d in segments if d["in_trajectory"])
                log.warning("tracking was lost: %d map segments; trajectory.tum holds segment(s) %s "
                            "(%d frames; more than one: rejoined by loops), trajectory_segments/ each one",
                            len(segments), held, len(traj))
        images, renders = self._image_metrics(kf_traj, traj)
        m.update(images)
        return {"traj": traj, "kf_traj": kf_traj, "metrics": m, "renders": renders, "segments": segments,
                "segment_trajs": seg_trajs, "loops": self.loop_report(), "gt": gt}

    def loop_report(self) -> Optional[dict]:
        """``loops.json``'s content (None without a loop closer)."""
        if self.loop is None:
            return None
        return {"candidates": self.loop.records, "corrections": self.loop.corrections,
                "retrains": self.retrains, "summary": self.loop.summary(), "error": self.loop_error}

    def _vi_metrics(self) -> dict:
        """``vi_*``, ``scale_observable``, biases and the time offset for metrics.json."""
        if self.vio is None:
            return {"vi_state": "visual-only", "scale_observable": False}
        st = self.vio.status()
        t0 = int(self.source.frame_stamps()[0])
        at = self.vio.initialised_at_ns
        return {"vi_state": st["vi_state"], "scale_observable": at is not None,
                "vi_initialised_at_s": None if at is None else (at - t0) * 1e-9,
                "acc_bias": st.get("acc_bias"), "gyro_bias": st.get("gyro_bias"), "td_s": st["td_s"],
                "td_estimates": st["td_estimates"], "imu_only_frames": self.frontend.stats["imu_only_frames"],
                "vi_error": st.get("vi_error")}

    def _write_final(self, final: dict, t0: float) -> dict:
        """Replace the previous run's files by this run's, ``metrics.json`` last. Everything is
        first written to a staging folder (the slow part: a failure or Ctrl-C there leaves the
        previous run's outputs as they were, and this run's partial trajectory), then moved in
        place by renames."""
        out = self.out
        try:
            out.write_trajectory(final["traj"], staged=True)
            out.write_keyframes(final["kf_traj"], staged=True)
            if final["segments"] is not None:
                out.write_segments(final["segments"], final["segment_trajs"], staged=True)
            if final["loops"] is not None:
                out.write_loops(final["loops"], staged=True)
            self.mapper.save_ply(out.staging_path(out.map_path))
            self.mapper.save_checkpoint(out.staging_path(out.checkpoint_path))
            for name, rgb in final["renders"].items():
                out.save_render(name, rgb, staged=True)
            for stamp, png in self._masks.items():
                out.write_mask(stamp, png, staged=True)
            self._write_report_data(final)
            out.begin_final()
            out.commit_staged()     # milliseconds of renames
        except BaseException:
            out.discard_staged()
            self._save_partial()
            raise
        m = final["metrics"]
        m["peak_rss_mb"] = peak_rss_mb()
        wall = time.perf_counter() - t0     # reading to the last output before metrics.json
        m.update(wall_s=wall, fps=m["frames"] / wall if wall > 0 else None)
        out = self.out.write_metrics(m)
        self.out.remove_partials()
        return out

    def _write_report_data(self, final: dict) -> None:
        """The report's data into the staging folder (``timeline.jsonl``, ``run.json``,
        ``ground_truth.tum``, ``views/``), then, with ``run.report``, ``bev.png`` and
        ``report.html`` drawn from the staged files (docs/report.md). A failure of the drawing is
        logged and leaves the run's other outputs complete."""
        from .report import run_files
        out = self.out
        stage = out.staging_dir
        gt = final.get("gt")
        run_files.write_data(stage, timeline=self.timeline, info=run_files.run_info(self), gt=gt, views=self._views)
        if not self.cfg.report:
            return
        t0 = time.perf_counter()
        try:
            with timed("io", "report"):
                m = dict(final["metrics"], wall_s=None, fps=None, peak_rss_mb=peak_rss_mb())
                run_files.write_report(stage, m, gt, out.out_dir)
            self.report_s = time.perf_counter() - t0
        except Exception as e:  # noqa: BLE001 - the report is a view of the outputs, never their loss
            log.exception("the report could not be drawn (%s); the run's outputs are complete", e)

    def _image_metrics(self, kf_traj: Trajectory, traj: Trajectory) -> tuple[dict, dict]:
        """PSNR/SSIM figures and the keyframe renders to save (``{file name: RGB}``)."""
        kf_poses = dict(zip(kf_traj.stamps_ns.tolist(), kf_traj.poses))
        psnrs, ssims, renders = [], [], {}
        eval_kfs = _even_subset([s for s in self._kf_stamps if s in kf_poses and s in self._kf_images],
                                self.cfg.eval_keyframes)
        save = set(_even_subset(eval_kfs, self.cfg.save_renders))
        self._views = []
        for s in eval_kfs:
            out = self.mapper.render(kf_poses[s], self.camera)
            ref = self._kf_images[s][1].astype(np.float32) / 255.0
            psnrs.append(psnr(out["color"], ref))
            ssims.append(ssim(out["color"], ref))
            if s in save:
                renders[f"{RUN_RENDER_PREFIX}{s}.png"] = out["color"]
                self._views.append({"stamp_ns": int(s), "psnr_db": psnrs[-1], "ssim": ssims[-1],
                                    "input": self._kf_images[s][1], "depth": out["depth"], "normal": out["normal"]})
        frame_poses = dict(zip(traj.stamps_ns.tolist(), traj.poses))
        kf_set = set(self._kf_stamps)
        novel = _even_subset([s for s in sorted(self._frame_images) if s in frame_poses and s not in kf_set],
                             self.cfg.eval_novel)
        npsnr = []
        for s in novel:
            out = self.mapper.render(frame_poses[s], self.camera)
            npsnr.append(psnr(out["color"], self._frame_images[s].astype(np.float32) / 255.0))
        fin = lambda v: [x for x in v if np.isfinite(x)]  # noqa: E731
        return ({"psnr_keyframes_db": float(np.mean(fin(psnrs))) if fin(psnrs) else None,
                 "ssim_keyframes": float(np.mean(ssims)) if ssims else None,
                 "psnr_novel_db": float(np.mean(fin(npsnr))) if fin(npsnr) else None}, renders)


def _progress(total: int, enabled: bool):
    from tqdm import tqdm
    return tqdm(total=total, unit="frame", disable=not enabled, dynamic_ncols=True, leave=True)
