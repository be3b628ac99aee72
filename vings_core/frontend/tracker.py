"""The stateful visual front end: initialisation, per-frame tracking, keyframes, window BA, pose
buffer, failure handling and keyframe emission.

Life cycle of a map segment::

    waiting --(enough parallax: essential matrix + 2-view BA)--> tracking
    tracking --(too few confident pixels / divergence)--> lost
    lost --(a frame tracks again against the window)--> tracking          (relocalised)
    lost --(relocalize_frames failures in a row)--> waiting               (new map segment)

Every processed frame gets a pose in the pose buffer. A non-keyframe's pose is stored relative to
its reference keyframe, so it follows later corrections of that keyframe (window BA, or
:meth:`Frontend.set_poses` from the mapper / loop closure).
"""
from __future__ import annotations

import logging
import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Optional

import cv2
import numpy as np
import torch

from ..errors import ConfigError, InputError
from ..geometry import pose_inverse, se3_exp, se3_log
from ..types import CameraModel, Frame, Keyframe, PoseEstimate, Trajectory
from . import ba as BA
from .config import FrontendConfig
from .depth import dense_depth
from .flow import (DISFlow, FlowEstimator, GridFlow, compose_flow, dense_from_grid, flow_around, grid_flow,
                   invert_flow, make_flow_estimator, texture_weight)
from .graph import CovisibilityGraph, Edge, select_edges
from .projective import Intrinsics, adjoint, grid_points, normalized_rays, project_edges
from .uncertainty import window_inv_depth_var

log = logging.getLogger("vings.frontend")
DT = torch.float64
STRIDE = 8


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


def orthonormalize(T: torch.Tensor) -> torch.Tensor:
    """Project the rotation block of ``(..., 4, 4)`` poses onto SO(3) (SVD)."""
    U, _, Vh = torch.linalg.svd(T[..., :3, :3])
    R = U @ Vh
    det = torch.linalg.det(R)
    flip = torch.tensor([1.0, 1.0, -1.0], dtype=T.dtype, device=T.device)
    U = torch.where(det[..., None, None] < 0, U * flip, U)
    out = T.clone()
    out[..., :3, :3] = U @ Vh
    out[..., 3, :] = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=T.dtype, device=T.device)
    return out
STATES = ("waiting", "tracking", "lost")
MAX_PENDING = 400          # waiting frames re-posed at initialisation (most recent)
#: longest extrapolation of the constant-velocity prior, in units of the last frame interval
MAX_VELOCITY_RATIO = 8.0


@dataclass
class _KF:
    stamp: int
    index: int
    gray: np.ndarray
    rgb: np.ndarray
    tex: np.ndarray              # (h, w) texture weight of the BA grid
    T_cw: torch.Tensor           # (4,4)
    d: torch.Tensor              # (P,) inverse depth
    var: Optional[torch.Tensor] = None   # (P,) marginal inverse-depth variance
    segment: int = 0
    emitted: bool = False


@dataclass
class _PoseRecord:
    ref: Optional[int]           # reference keyframe stamp (None: absolute)
    T_rel: np.ndarray            # T_c_kf (frame from keyframe) if ref else T_cw
    state: str
    is_keyframe: bool = False
    covariance: Optional[np.ndarray] = None


@dataclass
class _Ref:
    stamp: int
    gray: np.ndarray
    rgb: np.ndarray
    tex: np.ndarray
    pending: list = field(default_factory=list)   # (stamp, GridFlow) of frames since the reference
    chain: Optional[tuple] = None                 # (dense flow ref -> last frame, last grey)


class Frontend:
    """Monocular dense-BA visual front end.

    ``Frontend(config, camera)``: ``camera`` is the undistorted working-resolution model the
    frames come in. Feed frames in time order with :meth:`process`; collect keyframes with
    :meth:`pop_keyframes`; read the pose of any processed frame with :meth:`pose` or
    :meth:`trajectory`. ``state`` is ``'waiting'``, ``'tracking'`` or ``'lost'`` and ``reason`` says
    why in words. ``pose_system`` is the Schur-reduced pose system of the latest window BA
    (:class:`~vings_core.frontend.ba.PoseSystem`) for fusion with other factors.
    """

    def __init__(self, config: Optional[FrontendConfig], camera: CameraModel,
                 flow: Optional[FlowEstimator] = None):
        """``flow``: the flow estimator to use (default: made from ``config``; a node builds it at
        start so a bad ``flow_weights_path`` is reported before the camera is known)."""
        self.cfg = config or FrontendConfig()
        self.cfg.validate()
        if camera.is_distorted:
            raise ConfigError("frontend: the camera model still has lens distortion; the front end "
                              "needs undistorted frames (SourceOptions.undistort=True)")
        self.camera = camera
        self.W, self.H = camera.width, camera.height
        if self.W < 4 * STRIDE or self.H < 4 * STRIDE:
            raise ConfigError(f"frontend: working resolution {self.W}x{self.H} is too small "
                              f"(need at least {4 * STRIDE} px per side)")
        self.K = Intrinsics(camera.fx, camera.fy, camera.cx, camera.cy)
        self.Kmat = camera.K
        self.h, self.w, self.uv = grid_points(self.W, self.H, STRIDE)
        self.P = self.uv.shape[0]
        self.uv_np = self.uv.numpy()
        self.rays = normalized_rays(self.uv, self.K)
        self.flow_est = flow if flow is not None else make_flow_estimator(self.cfg)
        self.chain_est = DISFlow(self.cfg.chain_preset, None)
        self.info_scale = 1.0 / self.cfg.flow_sigma_px ** 2

        self.state = "waiting"
        self.reason = "waiting for the first frame"
        self.window: list[_KF] = []
        self.graph = CovisibilityGraph()
        self.pose_system: Optional[BA.PoseSystem] = None
        self._kf_T_cw: dict[int, np.ndarray] = {}      # every keyframe ever: stamp -> T_cw
        self._buffer: dict[int, _PoseRecord] = {}
        self._order: list[int] = []
        self._emitted: list[Keyframe] = []
        self._ref: Optional[_Ref] = None
        self._kf_count = 0
        self._segment = 0
        self._anchor_T_cw = np.eye(4)                  # world-to-camera of a new segment's origin
        self._scale_depth: Optional[float] = None      # median depth to continue a segment's scale
        self._last: Optional[tuple[int, torch.Tensor]] = None   # last tracked frame (stamp, T_cw)
        self._prev: Optional[tuple[int, torch.Tensor]] = None
        # (keyframe stamp, dense flow keyframe -> last tracked frame, that frame's grey image):
        # chained with the next frame-to-frame flow it predicts the next keyframe flow
        self._chain: Optional[tuple[int, np.ndarray, np.ndarray]] = None
        self._kf_conf: Optional[tuple[int, float]] = None   # (keyframe, mean confidence after it)
        self._last_flow: Optional[tuple[int, np.ndarray]] = None
        self._last_init: Optional[np.ndarray] = None
        self._fails = 0
        self._last_stamp: Optional[int] = None
        self.max_mean_flow_lr = 0.0
        self.motion_detected = False
        self.stats = {"frames": 0, "keyframes": 0, "segments": 1, "lost_frames": 0,
                      "relocalisations": 0, "t_flow": 0.0, "t_track": 0.0, "t_ba": 0.0,
                      "t_emit": 0.0, "t_total": 0.0}
        self.events: list[str] = []
        #: stamp -> (inverse depth, marginal variance) on the BA grid (h, w) of emitted keyframes,
        #: kept only when ``keep_lowres_depth`` is set (benchmarks; ~90 kB per keyframe at 752x480)
        self.keep_lowres_depth = False
        self.lowres_depth: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        #: counts keyframe-pose writes; ``_kf_written`` maps a keyframe to the count at its last
        #: write, in write order (see :meth:`keyframes_moved_since`)
        self.kf_pose_version = 0
        self._kf_written: dict[int, int] = {}

    # ------------------------------------------------------------------------------- public

    def process(self, frame: Frame) -> list[PoseEstimate]:
        """Track one frame. Returns its :class:`PoseEstimate`, preceded (at initialisation) by
        revised estimates of the frames that waited for it."""
        t0 = time.perf_counter()
        self._check_frame(frame)
        gray = frame.gray()
        self.stats["frames"] += 1
        with _torch_threads(self.cfg.num_threads):
            if self.state == "waiting":
                out = self._step_waiting(frame, gray)
            else:
                out = self._step_tracking(frame, gray)
        self._last_stamp = frame.stamp_ns
        self.stats["t_total"] += time.perf_counter() - t0
        return out

    def pop_keyframes(self) -> list[Keyframe]:
        """Keyframes emitted since the last call (a keyframe is emitted once ``emit_delay`` newer
        keyframes refined its depth, or at :meth:`finish`)."""
        out, self._emitted = self._emitted, []
        return out

    def finish(self) -> list[Keyframe]:
        """Emit every keyframe still waiting in the window (end of the stream) and return all
        keyframes not popped yet."""
        for kf in self.window:
            if not kf.emitted:
                self._emit(kf)
        return self.pop_keyframes()

    def pose(self, stamp_ns: int) -> np.ndarray:
        """Current best ``T_wc`` of a processed frame (4x4 float64)."""
        if int(stamp_ns) not in self._buffer:
            raise InputError(f"frontend.pose: stamp {stamp_ns} was never processed by the front end")
        return np.linalg.inv(self._T_cw_of(int(stamp_ns)))

    def trajectory(self, states: tuple = STATES, max_poses: Optional[int] = None) -> Trajectory:
        """Every processed frame's current ``T_wc`` (cam0-to-world), optionally only those whose
        latest state is in ``states``; ``max_poses``: at most that many, evenly spread over them
        (first and last kept), so a periodic display of a long run does not cost O(history) poses."""
        st = [s for s in self._order if self._buffer[s].state in states]
        if max_poses is not None and len(st) > max_poses:
            idx = np.linspace(0, len(st) - 1, max(int(max_poses), 2)).round().astype(int)
            st = [st[i] for i in idx]
        poses = np.stack([self.pose(s) for s in st]) if st else np.zeros((0, 4, 4))
        return Trajectory(np.asarray(st, np.int64), poses)

    def keyframes_moved_since(self, version: int) -> list[int]:
        """Keyframes whose pose was written (window BA, :meth:`set_poses`, a new keyframe) after
        ``kf_pose_version`` had the value ``version``; cost proportional to their number, not to
        the history (a consumer polls this every frame)."""
        out = []
        for s in reversed(self._kf_written):
            if self._kf_written[s] <= version:
                break
            out.append(s)
        return out

    def keyframe_trajectory(self) -> Trajectory:
        st = sorted(self._kf_T_cw)
        poses = np.stack([self.pose(s) for s in st]) if st else np.zeros((0, 4, 4))
        return Trajectory(np.asarray(st, np.int64), poses)

    def frame_states(self) -> dict[int, str]:
        return {s: self._buffer[s].state for s in self._order}

    def set_poses(self, poses_wc: dict[int, np.ndarray]) -> None:
        """Overwrite poses in the buffer (``stamp_ns -> T_wc``), e.g. after pose refinement or loop
        closure. Keyframes in the window take the new pose for the next BA (inverse depths are
        rescaled by the median change of the window's baselines, so a Sim(3) correction keeps the
        depths consistent); non-keyframes keep the given pose relative to their reference keyframe.
        Unknown stamps raise :class:`InputError`."""
        for s, T in poses_wc.items():
            if int(s) not in self._buffer:
                raise InputError(f"frontend.set_poses: stamp {s} was never processed by the front end")
            T = np.asarray(T, np.float64)
            if T.shape != (4, 4) or not np.all(np.isfinite(T)):
                raise InputError(f"frontend.set_poses: pose for stamp {s} is not a finite 4x4 matrix")
            R = T[:3, :3]
            if (not np.allclose(T[3], (0.0, 0.0, 0.0, 1.0), atol=1e-9)
                    or not np.allclose(R.T @ R, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0):
                raise InputError(f"frontend.set_poses: pose for stamp {s} is not a rigid transform "
                                 f"(rotation block not orthonormal, or last row not 0 0 0 1)")
        win = {kf.stamp: kf for kf in self.window}
        old_T = {kf.stamp: kf.T_cw.clone() for kf in self.window}
        for s, T in poses_wc.items():
            s = int(s)
            if s in self._kf_T_cw:
                T_cw = np.linalg.inv(np.asarray(T, np.float64))
                self._set_kf_pose(s, T_cw)
                if s in win:
                    win[s].T_cw = torch.from_numpy(T_cw.copy())
        for s, T in poses_wc.items():
            s = int(s)
            rec = self._buffer[s]
            if s in self._kf_T_cw:
                continue
            T_cw = np.linalg.inv(np.asarray(T, np.float64))
            if rec.ref is not None and rec.ref in self._kf_T_cw:
                rec.T_rel = T_cw @ np.linalg.inv(self._kf_T_cw[rec.ref])
            else:
                rec.ref, rec.T_rel = None, T_cw
        # scale consistency of the window depths
        if len(self.window) >= 2:
            ratios = []
            for a, b in zip(self.window[:-1], self.window[1:]):
                t_old = (old_T[b.stamp] @ pose_inverse(old_T[a.stamp]))[:3, 3].norm()
                t_new = (b.T_cw @ pose_inverse(a.T_cw))[:3, 3].norm()
                if t_old > 1e-9:
                    ratios.append(float(t_new / t_old))
            if ratios:
                r = float(np.median(ratios))
                if abs(r - 1.0) > 1e-3 and r > 0:
                    for kf in self.window:
                        kf.d = kf.d / r
                        if kf.var is not None:
                            kf.var = kf.var / (r * r)     # var(d / r) = var(d) / r^2
        if self._last is not None:
            self._last = (self._last[0], torch.from_numpy(self._T_cw_of(self._last[0])))
        if self._prev is not None:
            self._prev = (self._prev[0], torch.from_numpy(self._T_cw_of(self._prev[0])))

    def status(self) -> dict:
        """State, reason and counters (plain data, for logs and diagnostics)."""
        return {"state": self.state, "reason": self.reason, "segment": self._segment,
                "keyframes_in_window": len(self.window), "edges": len(self.graph),
                "motion_detected": self.motion_detected,
                "max_mean_flow_lr_px": self.max_mean_flow_lr, **self.stats}

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

    def _set_kf_pose(self, stamp: int, T_cw: np.ndarray) -> None:
        self._kf_T_cw[stamp] = T_cw
        self.kf_pose_version += 1
        self._kf_written.pop(stamp, None)          # re-insert: the dict stays in write order
        self._kf_written[stamp] = self.kf_pose_version

    def _T_cw_of(self, stamp: int) -> np.ndarray:
        if stamp in self._kf_T_cw:
            return self._kf_T_cw[stamp]
        rec = self._buffer[stamp]
        if rec.ref is None:
            return rec.T_rel
        return rec.T_rel @ self._kf_T_cw[rec.ref]

    def _record(self, stamp: int, ref: Optional[int], T_cw: np.ndarray, state: str,
                is_kf: bool = False, cov: Optional[np.ndarray] = None) -> PoseEstimate:
        if ref is not None:
            T_rel = T_cw @ np.linalg.inv(self._kf_T_cw[ref])
        else:
            T_rel = T_cw
        if stamp not in self._buffer:
            self._order.append(stamp)
        self._buffer[stamp] = _PoseRecord(ref, T_rel, state, is_kf, cov)
        return PoseEstimate(stamp, np.linalg.inv(T_cw), cov, state, is_kf)

    def _flow_pair(self, g0, g1, init01=None, init10=None, tex0=None, tex1=None,
                   both: bool = True) -> tuple[GridFlow, Optional[GridFlow], np.ndarray, np.ndarray]:
        """Flow both ways (each refined around its prior flow, if any) reduced to the grid."""
        t = time.perf_counter()
        if init01 is not None and init10 is None:
            init10 = invert_flow(init01)
        f01 = flow_around(self.flow_est, g0, g1, init01)
        f10 = flow_around(self.flow_est, g1, g0, init10)
        gf01 = grid_flow(f01, f10, g0, g1, self.uv_np, STRIDE, self.cfg, tex0)
        gf10 = grid_flow(f10, f01, g1, g0, self.uv_np, STRIDE, self.cfg, tex1) if both else None
        self.stats["t_flow"] += time.perf_counter() - t
        return gf01, gf10, f01, f10

    def _tex(self, gray):
        return texture_weight(gray, self.h, self.w, STRIDE, self.cfg.texture_tau)

    def _filled_depth(self, kf: _KF) -> torch.Tensor:
        """Inverse depth for predicting flow: pixels whose depth is unknown (relative std above
        0.3, e.g. never observed) are replaced by a Gaussian-weighted average of known ones."""
        if kf.var is None:
            return kf.d
        d = kf.d.numpy().reshape(self.h, self.w)
        rel = np.sqrt(np.maximum(kf.var.numpy(), 0)).reshape(self.h, self.w) / np.maximum(d, 1e-12)
        good = (rel < 0.3) & (d > 0)
        if good.all():
            return kf.d
        if good.sum() < 10:
            return kf.d
        c = good.astype(np.float32)
        num = cv2.GaussianBlur((d * c).astype(np.float32), (0, 0), 3.0)
        den = cv2.GaussianBlur(c, (0, 0), 3.0)
        fill = np.where(den > 1e-3, num / np.maximum(den, 1e-6), float(np.median(d[good])))
        return torch.from_numpy(np.where(good, d, fill).reshape(-1).astype(np.float64))

    def _induced_init(self, T_i: torch.Tensor, d_i: torch.Tensor, T_j: torch.Tensor) -> np.ndarray:
        T = torch.stack([T_i, T_j])
        uvj, valid = project_edges(T, d_i[None].expand(2, -1), torch.tensor([0]), torch.tensor([1]),
                                   self.rays, self.K)
        disp = (uvj[0] - self.uv).numpy()
        disp[~valid[0].numpy()] = 0.0
        disp = np.clip(disp, -self.W, self.W)
        return dense_from_grid(disp, self.h, self.w, self.H, self.W, STRIDE)

    def _d_bounds(self, d: torch.Tensor) -> tuple[float, float]:
        med = float(d[d > 0].median()) if (d > 0).any() else 1.0
        return self.cfg.min_inv_depth * med, self.cfg.max_inv_depth * med

    # --------------------------------------------------------------------------- waiting

    def _new_reference(self, frame: Frame, gray: np.ndarray, why: str) -> None:
        self._ref = _Ref(frame.stamp_ns, gray, frame.rgb(), self._tex(gray))
        self.reason = why

    def _step_waiting(self, frame: Frame, gray: np.ndarray) -> list[PoseEstimate]:
        cfg = self.cfg
        stamp = frame.stamp_ns
        if self._ref is None:
            self._new_reference(frame, gray, "waiting for motion: first frame of a map segment")
            return [self._record(stamp, None, self._anchor_T_cw.copy(), "waiting")]
        ref = self._ref
        base = self._chained_base(ref.chain[0], ref.chain[1], gray) if ref.chain else None
        tex1 = self._tex(gray)
        gf, gb, f01, _ = self._flow_pair(ref.gray, gray, init01=base, tex0=ref.tex, tex1=tex1)
        if gf.conf_frac < cfg.min_confident_frac and float(tex1.mean()) < cfg.min_confident_frac:
            # a black, saturated or blank frame is not a new start: keep the reference (and the
            # flow chain, which must not run through this frame)
            why = f"has almost no texture (black, saturated or blank image); kept reference frame {ref.stamp}"
            if not self.reason.endswith(why):       # one event per run of such frames
                self.events.append(f"waiting: frame {stamp} {why}")
            self.reason = f"waiting: frame {stamp} {why}"
            return [self._record(stamp, None, self._anchor_T_cw.copy(), "waiting")]
        ref.chain = (f01, gray)
        mean_lr = gf.mean_flow / STRIDE
        self.max_mean_flow_lr = max(self.max_mean_flow_lr, mean_lr)
        if mean_lr >= cfg.still_flow_lr_px:
            self.motion_detected = True
        ref.pending.append((stamp, gf))
        if len(ref.pending) > MAX_PENDING:     # long still periods: keep memory bounded (older
            ref.pending.pop(0)                 # waiting frames keep their 'waiting' pose)
        if gf.conf_frac < cfg.min_confident_frac:
            self._new_reference(frame, gray, f"waiting: lost overlap with the reference frame "
                                f"(mean confidence {gf.conf_frac:.2f}); restarted "
                                f"initialisation from frame {stamp}")
        elif mean_lr < cfg.still_flow_lr_px:
            self.reason = (f"waiting for motion: mean flow {mean_lr:.2f} px at 1/8 resolution; "
                           f"no motion detected (camera still)")
        else:
            out = self._try_initialise(frame, gray, gf, gb)
            if out is not None:
                return out
        return [self._record(stamp, None, self._anchor_T_cw.copy(), "waiting")]

    def _try_initialise(self, frame: Frame, gray: np.ndarray, gf: GridFlow,
                        gb: GridFlow) -> Optional[list[PoseEstimate]]:
        cfg = self.cfg
        ref = self._ref
        sel = gf.weight > max(cfg.min_weight, 0.2)
        if sel.sum() < 30:
            self.reason = f"waiting: only {int(sel.sum())} confident correspondences to initialise"
            return None
        p0 = self.uv_np[sel]
        p1 = gf.target[sel]
        E, mask = cv2.findEssentialMat(p0, p1, self.Kmat, cv2.RANSAC, 0.999, cfg.init_ransac_px)
        if E is None or E.shape[0] < 3:
            self.reason = "waiting: essential matrix estimation failed"
            return None
        E = E[:3]
        n_inl, R, t, mask2 = cv2.recoverPose(E, p0, p1, self.Kmat, mask=mask.copy())
        inl = mask2.ravel() > 0
        frac = n_inl / len(p0)
        # rotation-compensated parallax of the inliers (infinite homography K R K^-1)
        Hinf = self.Kmat @ R @ np.linalg.inv(self.Kmat)
        p0h = np.c_[p0, np.ones(len(p0))] @ Hinf.T
        p0r = p0h[:, :2] / p0h[:, 2:3]
        par = float(np.median(np.linalg.norm(p1 - p0r, axis=1)[inl])) if inl.any() else 0.0
        if frac < cfg.init_min_inlier_frac:
            self.reason = (f"waiting: essential matrix has only {100 * frac:.0f}% inliers "
                           f"(need {100 * cfg.init_min_inlier_frac:.0f}%)")
            return None
        # under pure rotation E is degenerate and recoverPose's R can be off by degrees, which
        # leaves fake "parallax": refuse when a rotation alone explains the matches to noise level
        rot_res = rotation_only_residual(p0[inl], p1[inl], self.Kmat) if inl.any() else 0.0
        if rot_res < 2.0 * cfg.init_ransac_px:
            self.reason = (f"waiting for parallax: a pure rotation explains the motion (median "
                           f"residual {rot_res:.2f} px); depth needs the camera to translate")
            return None
        if par < cfg.init_min_parallax_lr_px * STRIDE:
            self.reason = (f"waiting for parallax: median rotation-compensated flow "
                           f"{par / STRIDE:.2f} px at 1/8 resolution (need "
                           f"{cfg.init_min_parallax_lr_px:.2f})")
            return None
        # two-view BA: poses [ref, cur], world = the segment's anchor
        T0 = torch.from_numpy(self._anchor_T_cw.copy())
        T10 = torch.eye(4, dtype=DT)
        T10[:3, :3] = torch.from_numpy(R)
        T10[:3, 3] = torch.from_numpy(t.ravel())
        T = torch.stack([T0, T10 @ T0])
        ii = torch.tensor([0, 1])
        jj = torch.tensor([1, 0])
        tg = torch.from_numpy(np.stack([gf.target, gb.target]))
        wt = torch.from_numpy(np.stack([gf.weight, gb.weight])) * self.info_scale
        t_ba = time.perf_counter()
        # depths: exhaustive 1-D search (baseline 1) from 0.3 to 1000 baselines, then Gauss-Newton
        cands = 1.0 / torch.logspace(np.log10(0.3), 3.0, 48, dtype=DT)
        d = BA.triangulate_grid(T, ii, jj, self.rays, tg, wt, self.K, cands, cfg.robust_loss,
                                cfg.robust_delta_px)
        r = BA.bundle_adjust(T, d, ii, jj, self.rays, tg, wt, self.K, n_fixed=2, iters=8,
                             loss=cfg.robust_loss, delta=cfg.robust_delta_px, d_bounds=(1e-4, 10.0))
        r = BA.bundle_adjust(r.T_cw, r.d, ii, jj, self.rays, tg, wt, self.K, n_fixed=1,
                             iters=cfg.init_ba_iters, loss=cfg.robust_loss, delta=cfg.robust_delta_px,
                             d_bounds=self._d_bounds(r.d))
        self.stats["t_ba"] += time.perf_counter() - t_ba
        if not (torch.isfinite(r.T_cw).all() and torch.isfinite(r.d).all()):
            self.reason = "waiting: two-view BA diverged"
            return None
        # scale: median depth 1 (first segment) or the previous segment's median depth
        med_d = float(r.d[0][wt[0] > 0].median()) if (wt[0] > 0).any() else float(r.d[0].median())
        target_depth = self._scale_depth if self._scale_depth else 1.0
        s = target_depth * med_d       # depth_new = depth_old * s
        T_rel = r.T_cw[1] @ pose_inverse(r.T_cw[0])
        T_rel[:3, 3] *= s
        T1 = T_rel @ r.T_cw[0]
        d = r.d / s
        idx0 = self._new_kf_index()
        kf0 = _KF(ref.stamp, idx0, ref.gray, ref.rgb, ref.tex, r.T_cw[0].clone(), d[0].clone(),
                  segment=self._segment)
        kf1 = _KF(frame.stamp_ns, self._new_kf_index(), gray, frame.rgb(), self._tex(gray), T1,
                  d[1].clone(), segment=self._segment)
        self.window = [kf0, kf1]
        self.graph.clear()
        self.graph.add(Edge(kf0.stamp, kf1.stamp, gf.target, gf.weight))
        self.graph.add(Edge(kf1.stamp, kf0.stamp, gb.target, gb.weight))
        self._set_kf_pose(kf0.stamp, kf0.T_cw.numpy().copy())
        self._set_kf_pose(kf1.stamp, kf1.T_cw.numpy().copy())
        out = []
        # frames that waited: motion-only against the reference keyframe with their stored flow
        for stamp, g in ref.pending[:-1]:
            mo = BA.motion_only(kf0.T_cw[None], kf0.d[None], self.rays,
                                torch.from_numpy(g.target)[None],
                                torch.from_numpy(g.weight)[None] * self.info_scale, self.K,
                                kf0.T_cw, iters=cfg.track_iters, loss=cfg.robust_loss,
                                delta=cfg.robust_delta_px)
            out.append(self._record(stamp, kf0.stamp, mo.T_cw.numpy(), "tracking"))
        out.insert(0, self._record(kf0.stamp, kf0.stamp, kf0.T_cw.numpy(), "tracking", True))
        out.append(self._record(kf1.stamp, kf1.stamp, kf1.T_cw.numpy(), "tracking", True))
        self._prev = (kf0.stamp, kf0.T_cw.clone()) if not ref.pending[:-1] else \
            (ref.pending[-2][0], torch.from_numpy(self._T_cw_of(ref.pending[-2][0])))
        self._last = (kf1.stamp, kf1.T_cw.clone())
        self._chain = (kf1.stamp, np.zeros((self.H, self.W, 2), np.float32), gray)
        self._ref = None
        self.state = "tracking"
        self.reason = (f"initialised segment {self._segment} from frames {kf0.stamp} and "
                       f"{kf1.stamp}: {100 * frac:.0f}% essential-matrix inliers, parallax "
                       f"{par:.1f} px")
        self.events.append(self.reason)
        log.info(self.reason)
        self.stats["keyframes"] += 2
        self._after_window_change(r_ne=None)
        return out

    def _new_kf_index(self) -> int:
        self._kf_count += 1
        return self._kf_count - 1

    # --------------------------------------------------------------------------- tracking

    def _predict(self, stamp_ns: int) -> torch.Tensor:
        """Constant-velocity prediction of ``T_cw`` at ``stamp_ns`` (re-orthonormalised: composing
        poses repeatedly would otherwise let rounding errors grow geometrically). The motion between
        the last two tracked frames is scaled by the time ratio, so dropped or lost frames in
        between (or uneven frame intervals) do not make the prior a few frame-steps off."""
        if self._last is None:
            return self.window[-1].T_cw.clone()
        if self._prev is None:
            return self._last[1].clone()
        delta = self._last[1] @ pose_inverse(self._prev[1])
        span = self._last[0] - self._prev[0]
        ratio = (int(stamp_ns) - self._last[0]) / span if span > 0 else 1.0
        # past a few intervals the motion model says little and its error is multiplied: hold it
        ratio = min(ratio, MAX_VELOCITY_RATIO)
        if ratio != 1.0:
            delta = se3_exp(ratio * se3_log(delta))
        return orthonormalize(delta @ self._last[1])

    def _chained_base(self, f_to_last: np.ndarray, last_gray: np.ndarray,
                      gray: np.ndarray) -> np.ndarray:
        """Prior flow reference -> current frame: the stored flow to the previous frame chained
        with a plain frame-to-frame flow (small motion, so reliable even for fast forward motion)."""
        t = time.perf_counter()
        step = self.chain_est.flow(last_gray, gray, None)
        self.stats["t_flow"] += time.perf_counter() - t
        return compose_flow(step, f_to_last)

    def _track_against(self, kf: _KF, gray: np.ndarray, T_pred: torch.Tensor, tex: np.ndarray):
        if self._chain is not None and self._chain[0] == kf.stamp:
            init = self._chained_base(self._chain[1], self._chain[2], gray)
        else:
            init = self._induced_init(kf.T_cw, self._filled_depth(kf), T_pred)
        if self.cfg.track_fb_check:
            gf, gb, f01, f10 = self._flow_pair(kf.gray, gray, init01=init, tex0=kf.tex, tex1=tex)
        else:
            # forward flow only; the backward flow (for the keyframe edges) is computed only if
            # this frame becomes a keyframe (see _complete_pair)
            t = time.perf_counter()
            f01 = flow_around(self.flow_est, kf.gray, gray, init)
            gf = grid_flow(f01, None, kf.gray, gray, self.uv_np, STRIDE, self.cfg, kf.tex)
            gb = None
            self.stats["t_flow"] += time.perf_counter() - t
        self._last_flow = (kf.stamp, f01)
        self._last_init = init
        t = time.perf_counter()
        mo = BA.motion_only(kf.T_cw[None], kf.d[None], self.rays,
                            torch.from_numpy(gf.target)[None],
                            torch.from_numpy(gf.weight)[None] * self.info_scale, self.K, T_pred,
                            iters=self.cfg.track_iters, loss=self.cfg.robust_loss,
                            delta=self.cfg.robust_delta_px,
                            d_var=None if kf.var is None else kf.var[None])
        self.stats["t_track"] += time.perf_counter() - t
        return gf, gb, mo

    def _complete_pair(self, kf: _KF, gray: np.ndarray, tex: np.ndarray) -> tuple[GridFlow, GridFlow]:
        """Forward-backward checked grid flows keyframe <-> current frame (for new graph edges)."""
        t = time.perf_counter()
        f01 = self._last_flow[1]
        f10 = flow_around(self.flow_est, gray, kf.gray,
                          None if self._last_init is None else invert_flow(self._last_init))
        gf = grid_flow(f01, f10, kf.gray, gray, self.uv_np, STRIDE, self.cfg, kf.tex)
        gb = grid_flow(f10, f01, gray, kf.gray, self.uv_np, STRIDE, self.cfg, tex)
        self.stats["t_flow"] += time.perf_counter() - t
        return gf, gb

    def _induced_mean_flow(self, kf: _KF, T_cw: torch.Tensor) -> float:
        """Mean flow (working-res px) the pose ``T_cw`` induces on ``kf``'s grid (DROID-SLAM's
        keyframe distance): all pixels in front of the camera, no confidence weighting."""
        T = torch.stack([kf.T_cw, T_cw])
        uvj, valid = project_edges(T, kf.d[None].expand(2, -1), torch.tensor([0]), torch.tensor([1]),
                                   self.rays, self.K)
        if not valid.any():
            return float("inf")
        return float(torch.linalg.norm(uvj[0] - self.uv, dim=-1)[valid[0]].mean())

    def _check_track(self, gf: GridFlow, mo: BA.MotionResult) -> Optional[str]:
        cfg = self.cfg
        if gf.conf_frac < cfg.min_confident_frac:
            return (f"too few confident pixels (mean confidence {gf.conf_frac:.2f} < "
                    f"{cfg.min_confident_frac:.2f})")
        if not bool(torch.isfinite(mo.T_cw).all()):
            return "motion-only BA diverged (non-finite pose)"
        # written so that NaN fails (NaN > x is False)
        if not mo.rms_px <= cfg.max_track_rms_px:
            return f"flow disagrees with the map (residual RMS {mo.rms_px:.1f} px)"
        if not mo.inlier_frac >= 0.3:
            return f"only {100 * mo.inlier_frac:.0f}% of confident pixels agree with the pose"
        return None

    def _step_tracking(self, frame: Frame, gray: np.ndarray) -> list[PoseEstimate]:
        stamp = frame.stamp_ns
        tex = self._tex(gray)
        T_pred = self._predict(stamp)
        kf = self.window[-1]
        gf, gb, mo = self._track_against(kf, gray, T_pred, tex)
        why = self._check_track(gf, mo)
        if why is not None and self.state == "lost":
            # relocalisation: try the rest of the window, newest first, from the last good pose
            for other in reversed(self.window[:-1]):
                g2, b2, m2 = self._track_against(other, gray, self._last[1].clone(), tex)
                if self._check_track(g2, m2) is None:
                    kf, gf, gb, mo, why = other, g2, b2, m2, None
                    break
        if why is not None:
            return [self._fail(stamp, why)]
        if self.state == "lost":
            self.stats["relocalisations"] += 1
            self.events.append(f"relocalised at frame {stamp} against keyframe {kf.stamp} after "
                               f"{self._fails} lost frames")
            self.reason = self.events[-1]
        self.state = "tracking"
        self._fails = 0
        self._chain = (self._last_flow[0], self._last_flow[1], gray)
        T_cw = orthonormalize(mo.T_cw)
        mean_lr = self._induced_mean_flow(kf, T_cw) / STRIDE
        self.max_mean_flow_lr = max(self.max_mean_flow_lr, mean_lr)
        self._prev, self._last = self._last, (stamp, T_cw.clone())
        cov = self._covariance(T_cw, mo.H)
        if kf is self.window[-1]:
            if self._kf_conf is None or self._kf_conf[0] != kf.stamp:
                self._kf_conf = (kf.stamp, gf.conf_frac)      # first frame after the keyframe
            overlap_loss = gf.conf_frac < self.cfg.keyframe_conf_ratio * self._kf_conf[1]
            if mean_lr > self.cfg.keyframe_flow_lr_px or overlap_loss:
                if gb is None:
                    gf, gb = self._complete_pair(kf, gray, tex)
                est = self._add_keyframe(frame, gray, tex, T_cw, gf, gb)
                if est is not None:
                    return [est]
        if not self.reason.startswith("relocalised"):
            self.reason = f"tracking: mean flow to keyframe {mean_lr:.2f} px at 1/8 resolution"
        return [self._record(stamp, kf.stamp, T_cw.numpy(), "tracking", cov=cov)]

    def _covariance(self, T_cw: torch.Tensor, H: torch.Tensor) -> Optional[np.ndarray]:
        """6x6 covariance of the left tangent of ``T_wc`` (relative to the fixed keyframe)."""
        try:
            S = torch.linalg.inv(H + torch.eye(6, dtype=DT) * 1e-9 * torch.diagonal(H).mean())
        except RuntimeError:
            return None
        A = adjoint(pose_inverse(T_cw))
        return (A @ S @ A.T).numpy()

    def _fail(self, stamp: int, why: str) -> PoseEstimate:
        self._fails += 1
        self.stats["lost_frames"] += 1
        self.state = "lost"
        self.reason = f"tracking lost at frame {stamp}: {why}"
        self.events.append(self.reason)
        log.warning(self.reason)
        T_last = self._last[1].numpy() if self._last is not None else self.window[-1].T_cw.numpy()
        kf = self.window[-1]
        est = self._record(stamp, kf.stamp, T_last.copy(), "lost")
        if self._fails >= self.cfg.relocalize_frames:
            self._start_new_segment(stamp, why)
        return est

    def _start_new_segment(self, stamp: int, why: str) -> None:
        """Give up on the current window: emit its keyframes and re-initialise from the next frame,
        anchored at the last good pose and keeping the scale (median depth)."""
        for kf in self.window:
            if not kf.emitted:
                self._emit(kf)
        meds = [float((1.0 / kf.d[kf.d > 0]).median()) for kf in self.window if (kf.d > 0).any()]
        self._scale_depth = float(np.median(meds)) if meds else None
        self._anchor_T_cw = (self._last[1].numpy().copy() if self._last is not None
                             else self._anchor_T_cw)
        self.window = []
        self.graph.clear()
        self.pose_system = None
        self._segment += 1
        self.stats["segments"] += 1
        self._last = self._prev = None
        self._chain = None
        self._ref = None
        self._fails = 0
        self.state = "waiting"
        self.reason = (f"re-initialising a new map segment ({self._segment}) after "
                       f"{self.cfg.relocalize_frames} lost frames: {why}")
        self.events.append(self.reason)
        log.warning(self.reason)

    # ------------------------------------------------------------------------- keyframes

    def _propagate_depth(self, kf: _KF, T_new: torch.Tensor) -> torch.Tensor:
        """Initial inverse depth of a new keyframe: the last keyframe's grid splatted into the new
        view (nearest surface wins), holes filled with the median."""
        T = torch.stack([kf.T_cw, T_new])
        ii, jj = torch.tensor([0]), torch.tensor([1])
        q_uv, valid = project_edges(T, kf.d[None].expand(2, -1), ii, jj, self.rays, self.K)
        Tji = T_new @ pose_inverse(kf.T_cw)
        q = (Tji[:3, :3] @ self.rays.T).T + Tji[:3, 3] * kf.d[:, None]
        dn = kf.d / q[:, 2].clamp_min(1e-9)           # inverse depth in the new camera
        uv = q_uv[0]
        cx = torch.floor(uv[:, 0] / STRIDE).long()
        cy = torch.floor(uv[:, 1] / STRIDE).long()
        ok = valid[0] & (cx >= 0) & (cx < self.w) & (cy >= 0) & (cy < self.h) & (q[:, 2] > 0)
        out = torch.full((self.P,), -1.0, dtype=DT)
        if ok.any():
            out.scatter_reduce_(0, (cy * self.w + cx)[ok], dn[ok], reduce="amax")
        fill = float(dn[ok].median()) if ok.any() else float(kf.d.median())
        return torch.where(out > 0, out, torch.full_like(out, fill))

    def _add_keyframe(self, frame: Frame, gray: np.ndarray, tex: np.ndarray, T_cw: torch.Tensor,
                      gf: GridFlow, gb: GridFlow) -> Optional[PoseEstimate]:
        cfg = self.cfg
        last = self.window[-1]
        new = _KF(frame.stamp_ns, self._new_kf_index(), gray, frame.rgb(), tex, T_cw.clone(),
                  self._propagate_depth(last, T_cw), segment=self._segment)
        backup = ([(k.T_cw.clone(), k.d.clone()) for k in self.window], dict(self.graph.edges))
        self.window.append(new)
        n = len(self.window) - 1
        self.graph.add(Edge(last.stamp, new.stamp, gf.target, gf.weight))
        self.graph.add(Edge(new.stamp, last.stamp, gb.target, gb.weight))
        # the new keyframe's depth from its edge to the last keyframe (poses held: independent 1-D
        # problems), so the flow its other edges are refined around is induced by a real depth map
        t = time.perf_counter()
        r0 = BA.bundle_adjust(torch.stack([last.T_cw, new.T_cw]), torch.stack([last.d, new.d]),
                              torch.tensor([1]), torch.tensor([0]), self.rays,
                              torch.from_numpy(gb.target)[None],
                              torch.from_numpy(gb.weight)[None] * self.info_scale, self.K,
                              n_fixed=2, iters=3, loss=cfg.robust_loss, delta=cfg.robust_delta_px,
                              d_bounds=self._d_bounds(last.d))
        self.stats["t_ba"] += time.perf_counter() - t
        if torch.isfinite(r0.d[1]).all():
            new.d = r0.d[1].clone()
        if cfg.refine_flow:
            # the tracking flow came from a chained prior; re-measure the pair around the flow
            # induced by the poses and the new depth (the residual revision r_ij)
            self._connect(last, new)
        T_all = torch.stack([k.T_cw for k in self.window])
        d_all = torch.stack([k.d for k in self.window])
        others = select_edges(T_all, d_all, n, self.rays, self.uv, self.K, self.W, self.H,
                              cfg.temporal_radius, cfg.proximity_flow_lr_px * STRIDE,
                              cfg.max_edges_per_keyframe)
        for m in others:
            o = self.window[m]
            if o is last:
                continue
            self._connect(o, new)
        res = self._window_ba(cfg.ba_iters)
        if res is None:
            # divergence: undo the keyframe, keep tracking against the old window
            for k, (T, d) in zip(self.window[:-1], backup[0]):
                k.T_cw, k.d = T, d
            self.window.pop()
            self.graph.edges = backup[1]
            self.events.append(f"keyframe {new.stamp} rejected: window BA diverged")
            return None
        self.stats["keyframes"] += 1
        self._chain = (new.stamp, np.zeros((self.H, self.W, 2), np.float32), gray)
        # the frame's pose is the BA pose of its keyframe
        self._last = (new.stamp, new.T_cw.clone())
        est = self._record(new.stamp, new.stamp, new.T_cw.numpy(), "tracking", True)
        self._after_window_change(res.ne, res.fixed)
        self.reason = (f"tracking: keyframe {new.index} added ({len(self.window)} in window, "
                       f"{len(self.graph)} edges)")
        return est

    def _connect(self, o: _KF, new: _KF) -> None:
        """Flow edges ``o <-> new`` initialised by the flow the current estimate induces."""
        init_on = self._induced_init(o.T_cw, self._filled_depth(o), new.T_cw)
        init_no = self._induced_init(new.T_cw, self._filled_depth(new), o.T_cw)
        g_on, g_no, _, _ = self._flow_pair(o.gray, new.gray, init_on, init_no, o.tex, new.tex)
        self.graph.add(Edge(o.stamp, new.stamp, g_on.target, g_on.weight))
        self.graph.add(Edge(new.stamp, o.stamp, g_no.target, g_no.weight))

    def _window_ba(self, iters: int) -> Optional[BA.BAResult]:
        cfg = self.cfg
        stamps = [k.stamp for k in self.window]
        ii, jj, tg, wt = self.graph.tensors(stamps)
        T = torch.stack([k.T_cw for k in self.window])
        d = torch.stack([k.d for k in self.window])
        t = time.perf_counter()
        # gauge: the oldest poses, with a baseline among them where the window has one
        # (BA.gauge_mask); the depth variances use the same gauge (_after_window_change)
        fixed = BA.gauge_mask(T, min(cfg.fixed_poses, len(self.window) - 1))
        res = BA.bundle_adjust(T, d, ii, jj, self.rays, tg, wt * self.info_scale, self.K,
                               n_fixed=0, fixed_mask=fixed, iters=iters, loss=cfg.robust_loss,
                               delta=cfg.robust_delta_px, lam=cfg.lm_lambda,
                               d_bounds=self._d_bounds(d))
        self.stats["t_ba"] += time.perf_counter() - t
        if not (torch.isfinite(res.T_cw).all() and torch.isfinite(res.d).all()
                and res.cost <= res.cost0 * 1.0001):       # also refuses a NaN cost
            return None
        for k, Tk, dk in zip(self.window, orthonormalize(res.T_cw), res.d):
            k.T_cw = Tk.clone()
            k.d = dk.clone()
            self._set_kf_pose(k.stamp, Tk.numpy().copy())
        return res

    def _after_window_change(self, r_ne: Optional[BA.NormalEquations],
                             fixed: Optional[torch.Tensor] = None) -> None:
        """Uncertainty, pose-system export, window sliding and emission after a BA (``fixed``: the
        BA's gauge, reused for the depth variances)."""
        cfg = self.cfg
        stamps = [k.stamp for k in self.window]
        if r_ne is None:
            ii, jj, tg, wt = self.graph.tensors(stamps)
            T = torch.stack([k.T_cw for k in self.window])
            d = torch.stack([k.d for k in self.window])
            r_ne = BA.assemble(T, d, ii, jj, self.rays, tg, wt * self.info_scale, self.K,
                               cfg.robust_loss, cfg.robust_delta_px)
        T = torch.stack([k.T_cw for k in self.window])
        self.pose_system = BA.reduced_pose_system(r_ne, T, stamps)
        # the monocular gauge (incl. scale) is fixed by the window BA's fixed poses (the oldest
        # ones, with a baseline among them: BA.gauge_mask), also for the 2-view initialisation
        # whose BA left the second pose free (scale held by damping): at least two fixed poses
        n_gauge = max(2, cfg.fixed_poses)
        if fixed is None or fixed.shape[0] != len(self.window) or int(fixed.sum()) < min(
                n_gauge, len(self.window)):
            fixed = BA.gauge_mask(T, n_gauge)
        free = torch.nonzero(~fixed)[:, 0]
        var = window_inv_depth_var(r_ne, free)
        for k, v in zip(self.window, var):
            k.var = v.clone()
        while len(self.window) > cfg.window:
            old = self.window.pop(0)
            if not old.emitted:
                self._emit(old)
            self.graph.remove_keyframe(old.stamp)
        for pos, kf in enumerate(self.window):
            if not kf.emitted and len(self.window) - 1 - pos >= cfg.emit_delay and pos < len(self.window) - 1:
                self._emit(kf)

    def _emit(self, kf: _KF) -> None:
        t = time.perf_counter()
        cfg = self.cfg
        var = kf.var if kf.var is not None else torch.full((self.P,), float("inf"), dtype=DT)
        dd = dense_depth(kf.d.reshape(self.h, self.w).numpy(), var.reshape(self.h, self.w).numpy(),
                         kf.gray, STRIDE, cfg.upsample_sigma_spatial, cfg.upsample_sigma_range,
                         cfg.upsample_spread_var, cfg.max_rel_depth_std, cfg.max_depth_factor,
                         cfg.far_factor, cfg.textureless_grad)
        kf.emitted = True
        if self.keep_lowres_depth:
            self.lowres_depth[kf.stamp] = (kf.d.reshape(self.h, self.w).numpy().copy(),
                                           var.reshape(self.h, self.w).numpy().copy())
        img = torch.from_numpy(kf.rgb.astype(np.float32) / 255.0)
        self._emitted.append(Keyframe(
            stamp_ns=kf.stamp, image=img, T_wc=torch.from_numpy(np.linalg.inv(kf.T_cw.numpy())),
            depth=torch.from_numpy(dd.depth),
            inv_depth_var=torch.from_numpy(np.minimum(dd.inv_var, 1e10).astype(np.float32)),
            valid=torch.from_numpy(dd.valid), camera=self.camera, index=kf.index))
        self.stats["t_emit"] += time.perf_counter() - t
