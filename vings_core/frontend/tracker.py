"""The stateful visual front end (:class:`Frontend`): the tracking state machine over its stages.

Life cycle of a map segment::

    waiting --(enough parallax: essential matrix + 2-view BA)--> tracking
    tracking --(too few confident pixels / divergence)--> lost
    lost --(a frame tracks again against the window)--> tracking          (relocalised)
    lost --(relocalize_frames failures in a row)--> waiting               (new map segment)

The stages, one module each: :mod:`.initialise` (reference frame, two-view initialisation),
:mod:`.tracking` (per-frame motion-only tracking against a keyframe), :mod:`.window` (keyframe
window, window BA, uncertainty, emission), :mod:`.pose_buffer` (every processed frame's pose), all
sharing a :class:`~.context.FrontendContext` (configuration, camera grid, flow, counters).

Every processed frame gets a pose in the pose buffer. A non-keyframe's pose is stored relative to
its reference keyframe, so it follows later corrections of that keyframe (window BA, or
:meth:`Frontend.set_poses` from the mapper / loop closure).
"""
from __future__ import annotations

import collections
import logging
import time
from contextlib import contextmanager
from typing import TYPE_CHECKING, Optional

import numpy as np
import torch

from ..errors import ConfigError, InputError
from ..geometry import check_rigid_pose, check_sim3, sim3_apply_to_pose
from ..types import CameraModel, Frame, ImuSample, Keyframe, PoseEstimate, Trajectory, TrackState
from . import ba as BA
from .config import FrontendConfig
from .context import STRIDE, FrontendContext
from .flow import FlowEstimator
from .graph import CovisibilityGraph
from .initialise import Initialiser
from .pose_buffer import PoseBuffer
from .tracking import MotionTracker, Track, tangent_covariance
from .window import KeyframeWindow, WindowKeyframe
from ..profiling import profiled
from ..vio.config import ViState

if TYPE_CHECKING:                       # pragma: no cover
    from ..vio.fusion import ViFusion

log = logging.getLogger("vings.frontend")
#: every tracking state, in life-cycle order (the default filter of :meth:`Frontend.trajectory`)
STATES = tuple(TrackState)


@contextmanager
def _torch_threads(n: int):
    """Run with ``n`` torch threads (restored afterwards). The front end's tensors are small
    (~10^5 elements): with 2 cores shared by other processes, OpenMP's thread barriers cost far
    more than the parallelism gains (measured ~9x slower with 2 threads under load)."""
    if n <= 0:
        yield
        return
    old = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(old)


class Frontend:
    """Monocular dense-BA visual front end.

    ``Frontend(config, camera)``: ``camera`` is the undistorted working-resolution model the
    frames come in. Feed frames in time order with :meth:`process`; collect keyframes with
    :meth:`pop_keyframes`; read the pose of any processed frame with :meth:`pose` or
    :meth:`trajectory`. ``state`` is a :class:`~vings_core.types.TrackState` (``'waiting'``,
    ``'tracking'`` or ``'lost'``) and ``reason`` says why in words. ``pose_system`` is the
    Schur-reduced pose system of the latest window BA (:class:`~vings_core.frontend.ba.PoseSystem`)
    for fusion with other factors.
    """

    def __init__(self, config: Optional[FrontendConfig], camera: CameraModel,
                 flow: Optional[FlowEstimator] = None, vio: Optional["ViFusion"] = None):
        """``flow``: the flow estimator to use (default: made from ``config``; a node builds it at
        start so a bad ``flow_weights_path`` is reported before the camera is known). ``vio``: the
        visual-inertial fusion (:class:`~vings_core.vio.fusion.ViFusion`; ``None``: visual-only);
        feed its IMU readings with :meth:`add_imu`, in time order with the frames."""
        self.cfg = config or FrontendConfig()
        self.cfg.validate()
        if camera.is_distorted:
            raise ConfigError("frontend: the camera model still has lens distortion; the front end "
                              "needs undistorted frames (SourceOptions.undistort=True)")
        if camera.width < 4 * STRIDE or camera.height < 4 * STRIDE:
            raise ConfigError(f"frontend: working resolution {camera.width}x{camera.height} is too "
                              f"small (need at least {4 * STRIDE} px per side)")
        self.ctx = FrontendContext(self.cfg, camera, flow)
        self.buffer = PoseBuffer()
        self.win = KeyframeWindow(self.ctx, self.buffer)
        self.init = Initialiser(self.ctx, self.buffer, self.win)
        self.motion = MotionTracker(self.ctx)
        self.vio = vio
        self.win.export_incident = vio is not None
        self.state = TrackState.WAITING
        self._fails = 0                                # lost frames in a row
        self._last_stamp: Optional[int] = None
        self._last_visual: Optional[int] = None         # the last frame posed by the images
        self._still_anchored = False                    # the segment is anchored at a standstill
        # the camera grid (read-only) and the shared counters, as attributes of the front end
        ctx = self.ctx
        self.camera, self.W, self.H, self.K, self.Kmat = ctx.camera, ctx.W, ctx.H, ctx.K, ctx.Kmat
        self.h, self.w, self.uv, self.P = ctx.h, ctx.w, ctx.uv, ctx.P
        self.uv_np, self.rays = ctx.uv_np, ctx.rays
        self.chain_est, self.info_scale = ctx.chain_est, ctx.info_scale
        self.stats: dict = ctx.stats
        self.events: list[str] = ctx.events
        # dynamic masks from the eraser (any thread) -> applied before the next frame
        self._masks: collections.deque = collections.deque()

    # ------------------------------------------------------------------- shared state views

    @property
    def reason(self) -> str:
        """Why the front end is in its state, in words."""
        return self.ctx.reason

    @reason.setter
    def reason(self, text: str) -> None:
        self.ctx.reason = text

    @property
    def flow_est(self) -> FlowEstimator:
        """The dense flow estimator (assignable)."""
        return self.ctx.flow_est

    @flow_est.setter
    def flow_est(self, est: FlowEstimator) -> None:
        self.ctx.flow_est = est

    @property
    def motion_detected(self) -> bool:
        """Whether the camera moved (flow above ``still_flow_lr_px``) while waiting."""
        return self.ctx.motion_detected

    @property
    def max_mean_flow_lr(self) -> float:
        """Largest mean flow (px at 1/8 resolution) to the reference or keyframe so far."""
        return self.ctx.max_mean_flow_lr

    @property
    def window(self) -> list[WindowKeyframe]:
        """The keyframes of the window, oldest first (assignable)."""
        return self.win.keyframes

    @window.setter
    def window(self, keyframes: list[WindowKeyframe]) -> None:
        self.win.keyframes = keyframes

    @property
    def graph(self) -> CovisibilityGraph:
        return self.win.graph

    @property
    def pose_system(self) -> Optional[BA.PoseSystem]:
        return self.win.pose_system

    @property
    def keep_lowres_depth(self) -> bool:
        """Keep emitted keyframes' grid depths in :attr:`lowres_depth` (benchmarks)."""
        return self.win.keep_lowres_depth

    @keep_lowres_depth.setter
    def keep_lowres_depth(self, keep: bool) -> None:
        self.win.keep_lowres_depth = keep

    @property
    def lowres_depth(self) -> dict[int, tuple[np.ndarray, np.ndarray]]:
        """stamp -> (inverse depth, marginal variance) ``(h, w)`` grids of emitted keyframes."""
        return self.win.lowres_depth

    @property
    def last_stamp_ns(self) -> Optional[int]:
        """Stamp of the last frame processed (``None`` before the first)."""
        return self._last_stamp

    @property
    def kf_pose_version(self) -> int:
        """Counts keyframe-pose writes (see :meth:`keyframes_moved_since`)."""
        return self.buffer.version

    # ------------------------------------------------------------------------------- public

    @profiled("tracking", "frame (total)")
    def process(self, frame: Frame) -> list[PoseEstimate]:
        """Track one frame. Returns its :class:`PoseEstimate`, preceded (at initialisation) by
        revised estimates of the frames that waited for it."""
        t0 = time.perf_counter()
        self._check_frame(frame)
        self._apply_dynamic_masks()
        gray = frame.gray()
        self.stats["frames"] += 1
        if self.vio is not None:
            self.vio.frame_mode = None
        with _torch_threads(self.cfg.num_threads):
            if self.state == TrackState.WAITING:
                out = self._step_waiting(frame, gray)
            else:
                out = self._step_tracking(frame, gray)
        if out and out[-1].state == TrackState.TRACKING:
            self._last_visual = frame.stamp_ns
        self._last_stamp = frame.stamp_ns
        self.stats["t_total"] += time.perf_counter() - t0
        return out

    def post_dynamic_mask(self, stamp_ns: int, mask: np.ndarray) -> None:
        """The eraser's mask of keyframe ``stamp_ns`` (``(H, W)`` bool, True = moving object), from
        any thread; the front end never waits for it. Applied before the next frame: the
        keyframe's grid points on the mask (and flow targets landing on it) get weight 0 in the
        dense BA and tracking while the keyframe is in the window; a mask for a keyframe that has
        left the window is counted (``stats["dynamic_masks_late"]``) and dropped."""
        self._masks.append((int(stamp_ns), np.asarray(mask, dtype=bool)))

    def _apply_dynamic_masks(self) -> None:
        while self._masks:
            s, m = self._masks.popleft()
            applied = self.win.set_dynamic(s, m)
            self.stats["dynamic_masks" if applied else "dynamic_masks_late"] += 1

    def add_imu(self, sample: ImuSample) -> bool:
        """One IMU reading (body frame, REP-145 units) for the fusion; ``False`` when refused
        (non-finite, duplicate or out of order; counted) or when no fusion runs."""
        return self.vio.add_imu(sample) if self.vio is not None else False

    def take_similarities(self) -> dict[int, np.ndarray]:
        """Keyframes the front end moved by a similarity of its own (the metric alignment of the
        visual-inertial initialisation) since the last call: ``stamp -> C`` (4x4), for the pose
        exchange so the followers scale their content with it."""
        return self.vio.take_similarities() if self.vio is not None else {}

    def pop_keyframes(self) -> list[Keyframe]:
        """Keyframes emitted since the last call (a keyframe is emitted once ``emit_delay`` newer
        keyframes refined its depth, or at :meth:`finish`)."""
        return self.win.pop_emitted()

    def finish(self) -> list[Keyframe]:
        """Emit every keyframe still waiting in the window (end of the stream) and return all
        keyframes not popped yet."""
        self.win.emit_all()
        return self.pop_keyframes()

    def pose(self, stamp_ns: int) -> np.ndarray:
        """Current best ``T_wc`` of a processed frame (4x4 float64)."""
        return self.buffer.pose(stamp_ns)

    def trajectory(self, states: tuple[str, ...] = STATES, max_poses: Optional[int] = None,
                   segments: Optional[set[int]] = None) -> Trajectory:
        """Every processed frame's current ``T_wc`` (cam0-to-world), optionally only those whose
        latest state is in ``states`` and whose map segment is in ``segments``; ``max_poses``: at
        most that many, evenly spread over them (first and last kept), so a periodic display of a
        long run does not cost O(history) poses."""
        return self.buffer.trajectory(states, max_poses, segments)

    def segment_starts(self) -> dict[int, int]:
        """Map segment -> its earliest frame's stamp (every keyframe of a segment is at or after
        it; those of the segment before are before it)."""
        return dict(self.buffer.segment_first)

    def segments(self) -> list[dict]:
        """The map segments with tracked frames (a new one starts when tracking is lost for
        ``relocalize_frames`` frames; each has its own world frame and scale): ``index``,
        ``first_stamp_ns``, ``last_stamp_ns``, ``frames``, ``keyframes``."""
        return self.buffer.segments()

    def keyframes_moved_since(self, version: int) -> list[int]:
        """Keyframes whose pose was written (window BA, :meth:`set_poses`, a new keyframe) after
        ``kf_pose_version`` had the value ``version``; cost proportional to their number, not to
        the history (a consumer polls this every frame)."""
        return self.buffer.moved_since(version)

    def keyframe_trajectory(self) -> Trajectory:
        """``T_wc`` of every keyframe made so far, in stamp order."""
        return self.buffer.keyframe_trajectory()

    def frame_states(self) -> dict[int, TrackState]:
        """Latest state of every processed frame, in processing order."""
        return self.buffer.frame_states()

    def set_poses(self, poses_wc: dict[int, np.ndarray]) -> None:
        """Overwrite poses in the buffer (``stamp_ns -> T_wc``), e.g. after pose refinement or loop
        closure. Keyframes in the window take the new pose for the next BA (inverse depths are
        rescaled by the median change of the window's baselines, so a Sim(3) correction keeps the
        depths consistent); non-keyframes keep the given pose relative to their reference keyframe.
        Unknown stamps or poses that are not rigid raise :class:`InputError` before anything
        changes."""
        checked = {}
        for s, T in poses_wc.items():
            if int(s) not in self.buffer:
                raise InputError(f"frontend.set_poses: stamp {s} was never processed by the front end")
            what = f"frontend.set_poses: pose for stamp {s}"
            if np.shape(T) != (4, 4):
                raise InputError(f"{what}: expected a 4x4 pose, got shape {np.shape(T)}")
            checked[int(s)] = check_rigid_pose(T, what, tol=1e-6, error=InputError)
        self.win.take_poses(self.buffer.write_poses(checked))
        self.motion.refresh(self.buffer)

    def apply_increments(self, increments: dict[int, np.ndarray]) -> None:
        """Move processed frames by world-frame similarity increments ``stamp_ns -> C`` (4x4
        ``[[s R, t], [0, 1]]``, acting on world points as ``x -> s R x + t``): a frame's new pose is
        ``sim3_apply_to_pose(C, T_wc)`` (for a rigid ``C``: ``C @ T_wc``), written as by
        :meth:`set_poses` (window inverse depths follow the median change of the window's baselines:
        ``1/s`` for a uniform scale ``s``). Unknown stamps or increments that are not similarities
        raise :class:`InputError` before anything changes."""
        checked = {}
        for s, C in increments.items():
            if int(s) not in self.buffer:
                raise InputError(f"frontend.apply_increments: stamp {s} was never processed by the "
                                 f"front end")
            checked[int(s)] = check_sim3(C, f"frontend.apply_increments: increment for stamp {s}",
                                         tol=1e-6, error=InputError)
        self.set_poses({s: sim3_apply_to_pose(C, self.pose(s)) for s, C in checked.items()})

    def apply_jump(self, increments: dict[int, np.ndarray]) -> None:
        """A correction of the past (a loop closure): :meth:`apply_increments`, and every frame and
        keyframe newer than the newest stamp in ``increments`` moves by that stamp's increment
        (keyframes still in the window and not emitted, frames tracked since). With the IMU fused,
        the smoother's states move with their keyframes and its prior is re-anchored
        (:meth:`~vings_core.vio.fusion.ViFusion.world_moved`). The window's pose system is
        re-linearised at the moved poses. Subscribers see the jump in the next frame's pose."""
        if not increments:
            return
        newest = max(int(s) for s in increments)
        C = np.asarray(increments[newest], np.float64)
        moved = {int(s): np.asarray(v, np.float64) for s, v in increments.items()}
        for s in self.buffer.stamps_after(newest):
            moved.setdefault(s, C)
        self.apply_increments(moved)
        if self.vio is not None:
            self.vio.world_moved(moved)
        if len(self.win.keyframes) >= 2:
            self.win.after_change(None)
        self.stats["jumps"] += 1

    def restarted(self, resume: bool, gap_s: float) -> None:
        """This front end was restored from its checkpoint (:mod:`.checkpoint`) and the first new
        frame comes ``gap_s`` seconds after the last one it holds. ``resume``: go on tracking (a
        short gap). Otherwise the next frames are relocalised against the window's keyframes from
        the last tracked pose (state ``lost``, no velocity prior): one that passes the tracking
        checks continues the same world frame; after ``relocalize_frames`` failures a new map
        segment starts, as after any loss. The outcome is in the events and in
        ``stats["relocalisations"]`` / ``stats["segments"]``."""
        what = f"restarted from the checkpoint, {gap_s:.2f} s after its last frame"
        if resume or self.state != TrackState.TRACKING:
            self.events.append(what + (": tracking goes on" if self.state == TrackState.TRACKING else ""))
            return
        self.motion.chain = None            # the flow chain of the frame before the gap is stale
        self.motion.prev = None             # predict the last pose, not a velocity over the gap
        self.state = TrackState.LOST
        self._fails = 0
        self.reason = what + ": relocalising against the window's keyframes"
        self.events.append(self.reason)

    def status(self) -> dict:
        """State, reason and counters (plain data, for logs and diagnostics)."""
        vi = self.vio.status() if self.vio is not None else {"vi_state": "visual-only"}
        return {**vi, "state": self.state, "reason": self.reason, "segment": self.init.segment.index,
                "segment_first_stamp_ns": self.buffer.segment_first.get(self.init.segment.index, 0),
                "keyframes_in_window": len(self.window), "edges": len(self.graph),
                "motion_detected": self.motion_detected,
                "max_mean_flow_lr_px": self.max_mean_flow_lr, **self.stats}

    def unposed(self) -> tuple[int, Optional[str]]:
        """Processed frames without a tracked pose (waiting for an initialisation that never came
        or could not reach back to them; lost) and, when there are any, why (one line)."""
        states = self.buffer.frame_states()
        waiting = sum(1 for s in states.values() if s == TrackState.WAITING)
        lost = sum(1 for s in states.values() if s == TrackState.LOST)
        if not waiting and not lost:
            return 0, None
        why = []
        if waiting and self.state == TrackState.WAITING:
            why.append(f"{waiting} frame(s) waiting for initialisation at the end: {self.reason}")
        elif waiting:
            why.append(f"{waiting} frame(s) before an initialisation: "
                       f"{self.init.unposed_why or 'they did not overlap the first keyframe'}")
        if lost:
            why.append(f"{lost} frame(s) lost (tracking failed; see the events)")
        return waiting + lost, "; ".join(why)

    # ---------------------------------------------------------------------------- helpers

    def _check_frame(self, frame: Frame) -> None:
        if isinstance(frame.stamp_ns, (bool, np.bool_)) or not isinstance(frame.stamp_ns, (int, np.integer)):
            raise InputError(f"frame stamp {frame.stamp_ns!r}: stamps are integer nanoseconds "
                             f"(got {type(frame.stamp_ns).__name__})")
        img = np.asarray(frame.image)
        if img.ndim not in (2, 3) or img.shape[0] != self.H or img.shape[1] != self.W:
            raise InputError(f"frame {frame.stamp_ns}: image shape {img.shape} does not match the "
                             f"front end's working resolution {self.W}x{self.H}")
        if img.ndim == 3 and img.shape[2] not in (1, 3):
            raise InputError(f"frame {frame.stamp_ns}: image has {img.shape[2]} channels, expected "
                             f"1 (grey) or 3 (RGB)")
        if frame.camera is not None and frame.camera != self.camera:
            raise InputError(f"frame {frame.stamp_ns}: camera {frame.camera} differs from the "
                             f"front end's {self.camera}")
        if img.dtype != np.uint8:
            raise InputError(f"frame {frame.stamp_ns}: image dtype {img.dtype}, expected uint8")
        if self._last_stamp is not None and frame.stamp_ns <= self._last_stamp:
            raise InputError(f"frame {frame.stamp_ns}: stamps must increase (previous "
                             f"{self._last_stamp})")

    # ---------------------------------------------------------------------- state machine

    def _step_waiting(self, frame: Frame, gray: np.ndarray) -> list[PoseEstimate]:
        done = self.init.step(frame, gray)
        if done is None:
            still = self._standstill_before_init(frame.stamp_ns)
            if still is not None:
                return still
            return [self.buffer.record(frame.stamp_ns, None, self.init.segment.T_cw.copy(),
                                       TrackState.WAITING)]
        self.motion.start(done.prev, done.last, done.chain)
        self.state = TrackState.TRACKING
        return done.estimates

    def _standstill_before_init(self, stamp: int) -> Optional[list[PoseEstimate]]:
        """Before the first visual initialisation, while neither the images (no flow above
        ``still_flow_lr_px`` since the first frame) nor the IMU (:meth:`ViFusion.standstill`) show
        motion, frames are posed at zero velocity: the body at the origin with roll and pitch from
        the accelerometer (yaw 0, world z up), frame state ``INERTIAL``. The first such frame also
        poses the frames that waited before it and anchors the segment there, so a later visual
        initialisation continues in this gravity-aligned frame (at its own scale until the metric
        alignment). ``None`` when not at a standstill."""
        vio = self.vio
        if vio is None or self.ctx.motion_detected or self.init.segment.index != 0:
            return None
        R_wb = vio.standstill(stamp)
        if R_wb is None:
            return None
        vio.frame_mode = ViState.STANDSTILL
        out = []
        if not self._still_anchored:
            self._still_anchored = True
            T_wb = np.eye(4)
            T_wb[:3, :3] = R_wb
            self.init.segment.T_cw = np.linalg.inv(T_wb @ vio.T_bc)
            waiting = [s for s, st in self.buffer.frame_states().items() if st == TrackState.WAITING]
            out = [self.buffer.record(s, None, self.init.segment.T_cw.copy(), TrackState.INERTIAL)
                   for s in waiting]
            self.events.append(f"standstill from frame {waiting[0] if waiting else stamp}: posed at zero "
                               f"velocity, roll and pitch from the accelerometer")
        self.reason = "waiting for motion: standstill (IMU and images still), posed at zero velocity"
        out.append(self.buffer.record(stamp, None, self.init.segment.T_cw.copy(), TrackState.INERTIAL))
        return out

    def _step_tracking(self, frame: Frame, gray: np.ndarray) -> list[PoseEstimate]:
        stamp = frame.stamp_ns
        tex = self.ctx.texture(gray)
        imu = (self.vio.propagate(stamp, self._last_visual)
               if self.vio is not None and self.state == TrackState.LOST and self._last_visual else None)
        if imu is not None:
            # re-acquisition after a vision outage: from the IMU-propagated pose
            T_pred = torch.from_numpy(np.linalg.inv(imu[0]))
            track = self.motion.track_against(self.window[-1], gray, T_pred, tex, use_chain=False)
        else:
            T_pred = self.motion.predict(stamp, self.window[-1].T_cw)
            track = self.motion.track_against(self.window[-1], gray, T_pred, tex)
        why = self.motion.check(track.fwd, track.motion)
        if why is not None or not track.motion.rms_px <= self.cfg.seed_above_rms_px:
            # failed or doubtful: the motion may be beyond the dense flow's reach; seed it from
            # sparse matches and keep whichever passing result fits its flow better
            seeded = self.motion.track_seeded(self.window[-1], gray, tex)
            if (seeded is not None and self.motion.check(seeded.fwd, seeded.motion) is None
                    and (why is not None or seeded.motion.rms_px < track.motion.rms_px)):
                track, why = seeded, None
        if why is None and imu is not None:
            why = self._imu_disagrees(track, imu)
        if why is not None and self.state == TrackState.LOST:
            found = self._relocalise(gray, tex)
            if found is not None and (imu is None or self._imu_disagrees(found, imu) is None):
                track, why = found, None
        if why is not None:
            return [self._fail(stamp, why, imu)]
        if self.state == TrackState.LOST:
            self.stats["relocalisations"] += 1
            self.events.append(f"relocalised at frame {stamp} against keyframe {track.kf.stamp} after "
                               f"{self._fails} lost frames"
                               + (" (IMU-propagated)" if imu is not None else ""))
            self.reason = self.events[-1]
        self.state = TrackState.TRACKING
        self._fails = 0
        T_cw = self.motion.accept(stamp, gray, track)
        mean_lr = self.ctx.induced_mean_flow(track.kf.T_cw, track.kf.d, T_cw) / STRIDE
        self.ctx.max_mean_flow_lr = max(self.ctx.max_mean_flow_lr, mean_lr)
        cov = tangent_covariance(T_cw, track.motion.H)
        if track.kf is self.window[-1]:
            overlap_loss = self.motion.overlap_lost(track)
            if mean_lr > self.cfg.keyframe_flow_lr_px or overlap_loss:
                est = self._add_keyframe(frame, gray, tex, T_cw, track)
                if est is not None:
                    return [est]
        if not self.reason.startswith("relocalised"):
            self.reason = f"tracking: mean flow to keyframe {mean_lr:.2f} px at 1/8 resolution"
        T = T_cw.numpy()
        prev = self.motion.prev
        if (self.vio is not None and prev is not None and prev.stamp == self._last_stamp
                and mean_lr < self.cfg.still_flow_lr_px
                and self.vio.standstill(stamp) is not None):
            # standstill (IMU and images still): zero velocity, the previous frame's pose
            self.vio.frame_mode = ViState.STANDSTILL
            T = self.buffer.T_cw(self._last_stamp)
        return [self.buffer.record(stamp, track.kf.stamp, T, TrackState.TRACKING, cov=cov)]

    def _imu_disagrees(self, track: Track, imu: tuple[np.ndarray, np.ndarray]) -> Optional[str]:
        """Why a re-acquisition after a vision outage is refused: its position is further from the
        IMU-propagated one than ``vio.reacquire_sigmas`` times the propagation's position standard
        deviation (plus ``vio.reacquire_floor_m``); ``None`` when it agrees."""
        T_wc, cov = imu
        p_vis = np.linalg.inv(track.motion.T_cw.numpy())[:3, 3]
        sigma = float(np.sqrt(max(np.trace(cov[:3, :3]), 0.0)))
        c = self.vio.cfg
        gate = c.reacquire_sigmas * sigma + c.reacquire_floor_m
        dist = float(np.linalg.norm(p_vis - T_wc[:3, 3]))
        if dist > gate:
            return f"re-acquired pose {dist:.2f} m from the IMU-propagated one (gate {gate:.2f} m)"
        return None

    def _relocalise(self, gray: np.ndarray, tex: np.ndarray) -> Optional[Track]:
        """Lost: track against the rest of the window, newest first, from the last good pose.
        Returns the first track that passes the checks (``None`` if none does)."""
        for other in reversed(self.window[:-1]):
            track = self.motion.track_against(other, gray, self.motion.last.T_cw.clone(), tex)
            if self.motion.check(track.fwd, track.motion) is None:
                return track
            track = self.motion.track_seeded(other, gray, tex)
            if track is not None and self.motion.check(track.fwd, track.motion) is None:
                return track
        return None

    def _add_keyframe(self, frame: Frame, gray: np.ndarray, tex: np.ndarray, T_cw: torch.Tensor,
                      track: Track) -> Optional[PoseEstimate]:
        """Make the tracked frame a keyframe; ``None`` when the window BA refused it."""
        if track.bwd is None:
            self.motion.complete_pair(track, gray, tex)
        new = self.win.add(frame, gray, tex, T_cw, track.fwd, track.bwd, self.init.segment.index)
        if new is None:
            return None
        # the frame's pose is the BA pose of its keyframe
        self.motion.keyframe_added(new, gray)
        est = self.buffer.record(new.stamp, new.stamp, new.T_cw.numpy(), TrackState.TRACKING, True)
        if self.vio is not None:
            # the smoother (or the metric alignment) may move the window, this keyframe included
            self.vio.after_keyframe(self)
            est.T_wc = self.buffer.pose(new.stamp)
        return est

    def _fail(self, stamp: int, why: str,
              imu: Optional[tuple[np.ndarray, np.ndarray]] = None) -> PoseEstimate:
        """Record a frame visual tracking failed on: posed by the IMU (``imu``, the propagation
        :meth:`_step_tracking` made when already lost; made here on the first failure) while
        :meth:`ViFusion.propagate` can, else at the last good pose; a new segment after
        ``relocalize_frames`` such frames."""
        first = self.state != TrackState.LOST
        if imu is None and first and self.vio is not None and self._last_visual is not None:
            imu = self.vio.propagate(stamp, self._last_visual)
        self._fails += 1
        self.stats["lost_frames"] += 1
        self.state = TrackState.LOST
        if imu is not None:
            # a vision outage while visual-inertial: the IMU carries the pose (same world frame)
            T_wc, cov = imu
            self.vio.frame_mode = ViState.IMU_ONLY
            self.stats["imu_only_frames"] += 1
            if self._fails == 1:
                self.events.append(f"vision outage at frame {stamp} ({why}): IMU-only propagation")
                log.warning(self.events[-1])
            self.reason = (f"IMU-only: vision outage for {(stamp - self._last_visual) * 1e-9:.2f} s "
                           f"(at most {self.vio.cfg.outage_max_s:g} s): {why}")
            return self.buffer.record(stamp, self.window[-1].stamp, np.linalg.inv(T_wc), TrackState.INERTIAL,
                                      cov=cov)
        self.reason = f"tracking lost at frame {stamp}: {why}"
        self.events.append(self.reason)
        log.warning(self.reason)
        last = self.motion.last
        T_last = last.T_cw.numpy() if last is not None else self.window[-1].T_cw.numpy()
        est = self.buffer.record(stamp, self.window[-1].stamp, T_last.copy(), TrackState.LOST)
        if self._fails >= self.cfg.relocalize_frames:
            self._start_new_segment(why)
        return est

    def new_segment(self, why: str) -> None:
        """Start a new map segment now (as after ``relocalize_frames`` lost frames): e.g. a
        relocalisation that a render of the map contradicts."""
        self._start_new_segment(why)

    def _start_new_segment(self, why: str) -> None:
        """Give up on the current window: emit its keyframes and re-initialise from the next frame,
        anchored at the last good pose and keeping the scale (median depth)."""
        depth = self.win.close_segment()
        last = self.motion.last
        self.init.next_segment(last.T_cw.numpy().copy() if last is not None else None, depth)
        self.buffer.segment = self.init.segment.index
        self.stats["segments"] += 1
        self.motion.reset()
        if self.vio is not None:
            self.vio.reset(f"new map segment {self.init.segment.index}")
        self._fails = 0
        self.state = TrackState.WAITING
        self.reason = (f"re-initialising a new map segment ({self.init.segment.index}) after "
                       f"{self.cfg.relocalize_frames} lost frames: {why}")
        self.events.append(self.reason)
        log.warning(self.reason)
