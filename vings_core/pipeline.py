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
import math
import queue
import threading
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable, Optional

import numpy as np
import torch

from .config import load_section
from .errors import InputError, VingsError
from .eval.image import psnr, ssim
from .eval.output import CHECKPOINT_FILE, RUN_RENDER_PREFIX, RunOutput, metrics_template, peak_rss_mb  # noqa: F401
from .eval.traj import evaluate_trajectory
from .geometry import np_pose_compose, np_pose_inverse, np_se3_log, rotation_angle_deg
from .io.base import Source, SourceOptions
from .types import Frame, Keyframe, Trajectory

log = logging.getLogger("vings.run")

WRITEBACK_POLICIES = ("none", "all", "consistent")


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
    ``max_mapper_lag``: without ``sync``, keyframes that may wait for the mapper thread; tracking
    waits when that many are queued, so memory stays bounded and the mapper's refinements reach
    the front end during the run (0 = no bound).
    ``pose_writeback``: what the front end does with the mapper's pose refinements (see
    :class:`FrontendPoseLink`): ``none`` (never applied; the mapper is told to undo them),
    ``all`` (every correction applied), ``consistent`` (applied only when the front end's own
    visual evidence agrees: the corrections of keyframes in its BA window must pass a chi-square
    test on the Schur-reduced pose information, at ``writeback_confidence``; corrections of
    keyframes outside the window are not applied). The ROS graph reads the same fields (section
    ``run``), so `vings run` and the nodes exchange poses the same way.
    """

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
    max_mapper_lag: int = 8
    pose_writeback: str = "consistent"
    writeback_confidence: float = 0.99

    def validate(self) -> None:
        if self.width < 0 or self.height < 0:
            raise ValueError("width/height must be >= 0")
        if self.pose_writeback not in WRITEBACK_POLICIES:
            raise ValueError(f"pose_writeback must be one of {WRITEBACK_POLICIES}, got {self.pose_writeback!r}")
        if not 0 < self.writeback_confidence < 1:
            raise ValueError(f"writeback_confidence must be in (0, 1), got {self.writeback_confidence}")
        if self.eval_keyframes < 0 or self.eval_novel < 0 or self.save_renders < 0:
            raise ValueError("eval_keyframes, eval_novel and save_renders must be >= 0")
        if self.gt_kf_max_gap < 1:
            raise ValueError(f"gt_kf_max_gap must be >= 1 frame, got {self.gt_kf_max_gap}")
        if self.max_mapper_lag < 0:
            raise ValueError(f"max_mapper_lag must be >= 0, got {self.max_mapper_lag}")
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


# ------------------------------------------------------------------------------ pose exchange
#
# The front end and the mapper both hold every keyframe pose and both change them: the front end's
# window BA moves keyframes after it emitted them, the mapper's pose refinement moves them too. The
# two sides exchange *increments*, never overwrite each other with absolute poses: an absolute pose
# is stale by the time it arrives (the other side moved the keyframe meanwhile) and overwriting
# with it silently undoes that move. (That was the bug behind `vings run --sync` ATE 0.0247 m vs
# 0.0011 m for the graph: after every mapped keyframe the front end's newest window-BA poses were
# replaced by the mapper's older ones.) Each side remembers, per keyframe, the last pose it
# exchanged with the other side, so an increment is never applied twice and never echoed back.
# Messages cross when both sides run at once (the graph, `vings run` without --sync): the front end
# may send a pose before it has seen a correction the mapper already sent. So corrections travel in
# numbered batches and every front-end update says which batch it saw last (`ack`); the mapper
# reads the update against its picture of the front end *as of that batch*, with the corrections
# still in flight left out (otherwise the update would undo them, and the two sides would disagree
# for good once the front end accepted them). In ROS the batch number is the corrections Path's
# header stamp, and the ack the stamp of the front end's keyframe-pose Path.
# `vings run` calls these classes directly; the nodes call the same classes across topics.


class PoseCorrections(dict):
    """``{stamp_ns: C}`` world-frame increments from one mapper refinement, numbered ``batch``
    (increasing; 0 = unnumbered)."""

    def __init__(self, items=(), batch: int = 0) -> None:
        super().__init__(items)
        self.batch = int(batch)


class PoseUpdates(dict):
    """``{stamp_ns: T_wc}`` front-end keyframe poses, with ``ack``: the last correction batch the
    front end had processed (accepted or rejected) when it sent them (None = unknown: every batch)."""

    def __init__(self, items=(), ack: Optional[int] = None) -> None:
        super().__init__(items)
        self.ack = ack


def pose_correction(T_new: np.ndarray, T_old: np.ndarray) -> np.ndarray:
    """World-frame left increment ``C`` with ``T_new = C @ T_old`` (4x4, T_wc convention)."""
    return np.asarray(T_new, np.float64) @ np_pose_inverse(np.asarray(T_old, np.float64))


def _differs(A: np.ndarray, B: np.ndarray, tol: float = 1e-7) -> bool:
    return bool(np.abs(np.asarray(A) - np.asarray(B)).max() > tol)


class MapperPoseLink:
    """Mapper side of the pose exchange.

    ``fe[s]``: the front end's pose of keyframe ``s`` as the mapper last learned it (packet pose,
    then every update), advanced by the corrections the mapper sent. A front-end update ``P`` that
    saw correction batches up to ``ack`` is applied as the increment ``P base^-1`` to the mapper's
    pose, where ``base`` is ``fe[s]`` without the corrections of later batches (still in flight);
    so the mapper's refinement is kept, and a correction the front end rejected is undone.
    :meth:`refine` returns the mapper's refinement as increments for the front end."""

    def __init__(self) -> None:
        self.fe: dict[int, np.ndarray] = {}
        #: updates for keyframes not added yet (the graph: still in the mapper's queue)
        self.pending: dict[int, np.ndarray] = {}
        #: corrections sent and not yet acknowledged: stamp -> [(batch, C), ...] oldest first
        self.in_flight: dict[int, list[tuple[int, np.ndarray]]] = {}
        self.batch = 0

    def resumed(self, poses: dict[int, np.ndarray]) -> None:
        """After loading a checkpoint: take the stored poses as the last exchanged ones."""
        self.fe.update({int(s): np.array(T, np.float64) for s, T in poses.items()})

    def keyframe_added(self, kf: Keyframe) -> None:
        self.fe[int(kf.stamp_ns)] = kf.T_wc.detach().cpu().numpy().astype(np.float64).copy()

    def apply_frontend_poses(self, mapper, poses: dict[int, np.ndarray]) -> int:
        """Front-end keyframe poses (absolute ``T_wc``; a :class:`PoseUpdates` carries the batch
        ``ack``, a plain dict counts as having seen every batch) -> increments on the mapper's
        poses. Unknown stamps are ignored. Returns how many keyframes moved."""
        ack = getattr(poses, "ack", None)
        ack = self.batch if ack is None else int(ack)
        have = mapper.keyframe_poses()
        new = {}
        for s, P in poses.items():
            s = int(s)
            if s not in have or s not in self.fe:
                if s not in have:
                    self.pending[s] = np.asarray(P, np.float64).copy()
                    while len(self.pending) > 1000:
                        self.pending.pop(min(self.pending))
                continue
            # corrections the front end had not seen yet when it sent P are not part of P; it will
            # hold F P once it accepts them (F their product), and fe[s] already includes them: so
            # the front end's own move is F P fe[s]^-1 (with no correction in flight: P fe[s]^-1)
            ahead = np.asarray(P, np.float64).copy()
            for b, C in self.in_flight.get(s, []):
                if b > ack:
                    ahead = np_pose_compose(C, ahead)
            old, self.fe[s] = self.fe[s], ahead
            if _differs(ahead, old, 1e-12):
                new[s] = np_pose_compose(pose_correction(ahead, old), have[s])
        self._acknowledged(ack)
        if new:
            mapper.set_keyframe_poses(new)
        return len(new)

    def _acknowledged(self, ack: int) -> None:
        for s in list(self.in_flight):
            left = [(b, C) for b, C in self.in_flight[s] if b > ack]
            if left:
                self.in_flight[s] = left
            else:
                del self.in_flight[s]

    def refine(self, mapper, batch: Optional[int] = None) -> PoseCorrections:
        """Run the mapper's pose refinement; returns ``{stamp: C}`` world-frame increments of the
        keyframes it moved (``T_new = C T_old``), to be offered to the front end, numbered ``batch``
        (default: the next number; always raised above the previous batch)."""
        base = mapper.keyframe_poses()
        refined = mapper.refine_poses()
        out = PoseCorrections()
        for s, T in refined.items():
            if s in base and _differs(T, base[s], 1e-12):
                out[int(s)] = pose_correction(T, base[s])
        if out:
            self.batch = max(self.batch + 1, int(batch or 0))
            out.batch = self.batch
            for s, C in out.items():
                if s in self.fe:
                    self.fe[s] = np_pose_compose(C, self.fe[s])
                    self.in_flight.setdefault(s, []).append((self.batch, C))
        return out


class FrontendPoseLink:
    """Front-end side of the pose exchange, with the write-back policy (``RunConfig.pose_writeback``).

    ``sent[s]``: the pose of keyframe ``s`` the mapper holds as far as the front end knows (the
    packet pose, every update sent, advanced by every correction received). :meth:`outgoing` returns
    the keyframes whose front-end pose differs from it (window BA moved them, or a correction was
    rejected: sending the front-end pose then makes the mapper undo it)."""

    def __init__(self, cfg: Optional[RunConfig] = None) -> None:
        self.cfg = cfg or RunConfig()
        self.sent: dict[int, np.ndarray] = {}
        self.ack = 0            # last correction batch processed (echoed with every update)
        self.stats = dict(corrections=0, applied=0, rejected=0, tests=0, tests_failed=0, last_q=None,
                          last_q_limit=None)
        self._version = 0       # the front end's kf_pose_version at the last outgoing()
        self._recheck: set[int] = set()   # keyframes with a correction since (maybe rejected)

    def keyframe_sent(self, kf: Keyframe) -> None:
        self.sent[int(kf.stamp_ns)] = kf.T_wc.detach().cpu().numpy().astype(np.float64).copy()
        # compared at the next outgoing() whatever the write log says: a pose written after the
        # packet was made, but before this call, would otherwise never be sent
        self._recheck.add(int(kf.stamp_ns))

    def outgoing(self, frontend) -> PoseUpdates:
        """Keyframe poses to send to the mapper (absolute ``T_wc``), with the batch ``ack``. Only
        keyframes the front end wrote since the last call, or that got a correction, are compared
        (``frontend.keyframes_moved_since``): the cost does not grow with the history."""
        stamps = set(frontend.keyframes_moved_since(self._version)) | self._recheck
        self._version = frontend.kf_pose_version
        self._recheck = set()
        moved = PoseUpdates(ack=self.ack)
        for s in sorted(stamps):
            old = self.sent.get(int(s))
            if old is None:
                continue
            P = frontend.pose(s)
            if _differs(P, old):
                moved[int(s)] = P.copy()
                self.sent[int(s)] = P.copy()
        return moved

    def apply_corrections(self, frontend, corrections: dict[int, np.ndarray]) -> dict[int, np.ndarray]:
        """Apply the mapper's increments the policy accepts; returns the applied ``{stamp: C}``."""
        batch = getattr(corrections, "batch", 0)
        self.ack = max(self.ack, int(batch))
        corrections = {int(s): np.asarray(C, np.float64) for s, C in corrections.items() if int(s) in self.sent}
        if not corrections:
            return {}
        for s, C in corrections.items():
            self.sent[s] = np_pose_compose(C, self.sent[s])          # what the mapper now holds
        self._recheck.update(corrections)     # a rejected one is undone by the next outgoing()
        self.stats["corrections"] += len(corrections)
        accepted = self._accept(frontend, corrections)
        if accepted:
            frontend.set_poses({s: np_pose_compose(C, frontend.pose(s)) for s, C in accepted.items()})
        self.stats["applied"] += len(accepted)
        self.stats["rejected"] += len(corrections) - len(accepted)
        return accepted

    def _accept(self, frontend, corrections: dict[int, np.ndarray]) -> dict[int, np.ndarray]:
        policy = self.cfg.pose_writeback
        if policy == "all":
            return dict(corrections)
        if policy == "none":
            return {}
        ok, q, limit = correction_consistency(frontend, corrections, self.cfg.writeback_confidence)
        if q is not None:
            self.stats["tests"] += 1
            self.stats["tests_failed"] += int(not ok)
            self.stats["last_q"], self.stats["last_q_limit"] = q, limit
        return ok


def correction_consistency(frontend, corrections: dict[int, np.ndarray],
                           confidence: float = 0.99) -> tuple[dict[int, np.ndarray], Optional[float], Optional[float]]:
    """Which mapper corrections the front end's visual evidence allows.

    The corrections of keyframes in the front end's BA window form a joint perturbation ``x`` of the
    window poses (left tangent of ``T_cw``); its cost under the Schur-reduced pose information ``H``
    of the last window BA (``frontend.pose_system``, 1/px^2 units: flow residuals over their
    sigma) is ``q = x^T H x``, chi-square with ``rank(H_xx)`` (at most ``6 n``) degrees of freedom
    if the correction were within the front end's noise. ``x`` is the deviation of the corrected
    poses from the BA's linearisation point, not just this correction: corrections accepted since
    the last BA count too, so a series of small ones cannot walk away from the visual evidence.
    They are accepted together iff ``q <= chi2.ppf(confidence, dof)``.
    Keyframes outside the window are never accepted (no evidence to check them against).
    Returns ``(accepted, q, limit)``; ``q``/``limit`` are None when no keyframe was in the window."""
    from scipy.stats import chi2

    ps = getattr(frontend, "pose_system", None)
    if ps is None:
        return {}, None, None
    idx = {int(s): i for i, s in enumerate(ps.stamps_ns)}
    inwin = {s: C for s, C in corrections.items() if s in idx}
    if not inwin:
        return {}, None, None
    H = ps.H.detach().cpu().numpy().astype(np.float64)
    T_lin = ps.T_cw.detach().cpu().numpy().astype(np.float64)
    x = np.zeros(H.shape[0])
    rows = []
    for s, C in inwin.items():
        i = idx[s]
        T_wc_new = np_pose_compose(C, frontend.pose(s))
        # T_cw_new = exp(xi) T_cw_lin  ->  xi = log(T_cw_new T_cw_lin^-1)
        x[6 * i:6 * i + 6] = np_se3_log(np_pose_inverse(T_wc_new) @ np_pose_inverse(T_lin[i]))
        rows.extend(range(6 * i, 6 * i + 6))
    q = float(x @ H @ x)
    ev = np.linalg.eigvalsh(H[np.ix_(rows, rows)])
    dof = int((ev > 1e-9 * max(float(ev.max()), 1e-300)).sum())
    if dof == 0:            # the window's BA constrains none of these poses: nothing to check against
        return {}, None, None
    limit = float(chi2.ppf(confidence, dof))
    return (dict(inwin) if q <= limit else {}), q, limit


def map_keyframe(mapper, link: MapperPoseLink, kf: Keyframe, refine: bool = True, chunk: int = 0,
                 stop: Optional[Callable[[], bool]] = None) -> tuple[dict, dict[int, np.ndarray]]:
    """One mapping step, the same in `vings run` and ``mapper_node``: add the keyframe, train
    ``iters_per_keyframe`` iterations (in chunks of ``chunk`` when > 0, ending early once ``stop()``
    is true: prompt shutdown), then (``refine``) the pose refinement. Returns the last training
    stats and the refinement as increments ``{stamp: C}`` for the front end."""
    mapper.add_keyframe(kf)
    link.keyframe_added(kf)
    later = link.pending.pop(int(kf.stamp_ns), None)
    if later is not None:   # the front end moved it while it waited in the queue
        link.apply_frontend_poses(mapper, {int(kf.stamp_ns): later})
    iters = int(mapper.cfg.iters_per_keyframe)
    step = iters if chunk <= 0 else int(chunk)
    stats: dict = {}
    done = 0
    while done < iters:
        if stop is not None and stop():
            break
        n = min(step, iters - done)
        stats = mapper.train(n)
        done += n
    stats["iterations_total"] = done
    corrections = (link.refine(mapper, batch=int(kf.stamp_ns)) if refine and not (stop is not None and stop())
                   else PoseCorrections())
    return stats, corrections


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
        self._pending_corrections: list[dict[int, np.ndarray]] = []
        self._lock = threading.Lock()
        self._queue: "queue.Queue[Optional[tuple[str, object]]]" = queue.Queue()
        # slots of the bounded mapper queue (mapper thread only, see max_mapper_lag)
        self._kf_queued = (threading.Semaphore(self.cfg.max_mapper_lag)
                           if self.cfg.max_mapper_lag and not self.cfg.sync else None)
        self._lag_warned = False
        self.fe_link = FrontendPoseLink(self.cfg)     # pose exchange, as between the nodes
        self.map_link = MapperPoseLink()
        self.out.prepare()      # after the configuration is known to be valid, before any work

    # --------------------------------------------------------------------------- mapping side

    def _map_keyframe(self, kf: Keyframe) -> None:
        _, corrections = map_keyframe(self.mapper, self.map_link, kf, refine=self.frontend is not None,
                                      chunk=10, stop=lambda: self._abort)
        if corrections:
            with self._lock:
                self._pending_corrections.append(corrections)
        n = len(self.mapper.keyframe_poses())
        if self.cfg.checkpoint_every and n % self.cfg.checkpoint_every == 0 and not self._abort:
            # the previous run's checkpoint.pt stays until this run completes
            self.mapper.save_checkpoint(self.out.partial_checkpoint_path)
            self._partial_ckpt = True

    def _handle(self, kind: str, item: object) -> None:
        if kind == "kf":
            try:
                self._map_keyframe(item)
            finally:
                if self._kf_queued is not None:
                    self._kf_queued.release()
        else:  # "poses": front-end BA moved keyframes the mapper already holds
            self.map_link.apply_frontend_poses(self.mapper, item)

    def _mapper_loop(self) -> None:
        try:
            while True:
                msg = self._queue.get()
                if msg is None:
                    return
                if not self._abort:     # a failed or interrupted run writes nothing: skip the rest
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
        self.fe_link.keyframe_sent(kf)
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
        self._queue.put((kind, item))

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
        """Mapper refinements -> front end (through the write-back policy), before a frame."""
        if self.frontend is None:
            return
        with self._lock:
            pending, self._pending_corrections = self._pending_corrections, []
        for corr in pending:
            self.fe_link.apply_corrections(self.frontend, corr)

    def _send_moves(self, worker: Optional[threading.Thread]) -> None:
        """Front-end keyframe poses that changed since last exchanged -> mapper, after a frame
        and before its new keyframes (so the mapper refines from the front end's latest poses)."""
        if self.frontend is None:
            return
        moved = self.fe_link.outgoing(self.frontend)
        if moved:
            self._dispatch("poses", moved, worker)

    # --------------------------------------------------------------------------------- run

    def run(self) -> dict:
        """Process the whole source; returns the metrics dict (also written to metrics.json)."""
        t0 = time.perf_counter()
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
            for frame in self.source.frames():
                n_frames += 1
                self._raise_mapper_error()
                self._take_corrections()
                if self.gt_kf is not None:
                    T, kf = self.gt_kf.process(frame)
                    if T is not None:
                        self._gt_poses[frame.stamp_ns] = T
                    kfs = [kf] if kf is not None else []
                    state = "tracking" if T is not None else "no ground truth"
                else:
                    ests = self.frontend.process(frame)
                    kfs = self.frontend.pop_keyframes()
                    state = ests[-1].state if ests else self.frontend.state
                if frame.stamp_ns in keep_novel:
                    self._frame_images[frame.stamp_ns] = frame.rgb().copy()
                self._send_moves(worker)
                for kf in kfs:
                    self._submit(kf, worker)
                bar.update(1)
                bar.set_postfix_str(f"{state} kf={len(self._kf_stamps)}", refresh=False)
                if self.on_frame is not None:
                    self.on_frame({"stamp_ns": frame.stamp_ns, "state": state,
                                   "keyframes": len(self._kf_stamps)})
            if self.frontend is not None:
                self._take_corrections()
                kfs = self.frontend.finish()
                self._send_moves(worker)
                for kf in kfs:
                    self._submit(kf, worker)
            bar.close()
            if worker is not None and self._queue.qsize():
                n_kf = sum(1 for m in list(self._queue.queue) if m is not None and m[0] == "kf")
                log.info("tracking done; the mapper is finishing %d queued keyframe(s) (Ctrl-C stops it; "
                         "the trajectory is kept)", n_kf)
            self._stop_worker(worker)
            self._raise_mapper_error()
            self._take_corrections()
            self._send_moves(None)
            # everything slow (evaluation renders) happens before any output file is replaced
            final = self._evaluate(n_frames)
        except BaseException as e:
            self._abort = True      # Ctrl-C or an input error: do not map the queued keyframes first
            bar.close()
            self._stop_worker_after_failure(worker)
            if self._mapper_err is not None and self._mapper_err not in (e, e.__cause__):
                log.warning("the mapper had stopped too: %s", self._mapper_err)
            self._save_partial()
            raise
        return self._write_final(final, t0)

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

    def trajectory(self) -> Trajectory:
        """Every tracked frame's cam0 ``T_wc``."""
        if self.frontend is None:
            return Trajectory.from_poses(self._gt_poses)
        return self.frontend.trajectory(states=("tracking",))

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
            st = self.fe_link.stats
            log.info("pose write-back (%s): %d mapper corrections, %d applied, %d rejected",
                     self.cfg.pose_writeback, st["corrections"], st["applied"], st["rejected"])
        m.update(frames=n_frames, frames_tracked=len(traj), keyframes=len(kf_traj),
                 num_gaussians=int(self.mapper.num_gaussians))
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
        images, renders = self._image_metrics(kf_traj, traj)
        m.update(images)
        return {"traj": traj, "kf_traj": kf_traj, "metrics": m, "renders": renders}

    def _write_final(self, final: dict, t0: float) -> dict:
        """Replace the previous run's files by this run's, ``metrics.json`` last. Everything is
        first written to a staging folder (the slow part: a failure or Ctrl-C there leaves the
        previous run's outputs as they were, and this run's partial trajectory), then moved in
        place by renames."""
        out = self.out
        try:
            out.write_trajectory(final["traj"], staged=True)
            out.write_keyframes(final["kf_traj"], staged=True)
            self.mapper.save_ply(out.staging_path(out.map_path))
            self.mapper.save_checkpoint(out.staging_path(out.checkpoint_path))
            for name, rgb in final["renders"].items():
                out.save_render(name, rgb, staged=True)
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

    def _image_metrics(self, kf_traj: Trajectory, traj: Trajectory) -> tuple[dict, dict]:
        """PSNR/SSIM figures and the keyframe renders to save (``{file name: RGB}``)."""
        kf_poses = dict(zip(kf_traj.stamps_ns.tolist(), kf_traj.poses))
        psnrs, ssims, renders = [], [], {}
        eval_kfs = _even_subset([s for s in self._kf_stamps if s in kf_poses and s in self._kf_images],
                                self.cfg.eval_keyframes)
        save = set(_even_subset(eval_kfs, self.cfg.save_renders))
        for s in eval_kfs:
            out = self.mapper.render(kf_poses[s], self.camera)
            ref = self._kf_images[s][1].astype(np.float32) / 255.0
            psnrs.append(psnr(out["color"], ref))
            ssims.append(ssim(out["color"], ref))
            if s in save:
                renders[f"{RUN_RENDER_PREFIX}{s}.png"] = out["color"]
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
