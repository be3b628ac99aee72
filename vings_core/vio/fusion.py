"""Visual-inertial fusion of the front end: IMU buffer, state machine, alignment to the metric
gravity-aligned frame, and the window smoother alternating with the dense BA.

Life cycle (:class:`ViState`)::

    initialising --(alignment accepted)--> visual-inertial
    visual-inertial --(new map segment / IMU gap)--> initialising
    visual-only: fusion off, no IMU, or no known T_bc (never leaves it)

While initialising, the front end runs visual-only (arbitrary scale). At each new keyframe, once the
segment has ``init_min_keyframes`` keyframes spanning ``init_min_span_s`` and the IMU excitation
passes (:func:`.align.excitation`), the keyframes are aligned (:func:`.align.align`); an accepted
alignment moves every pose of the segment (and, through the pose exchange, the map) by the
similarity ``C`` into the metric frame whose z axis is opposite to gravity (REP-103 ``map``).
From then on, after every window BA the smoother (:class:`.smoother.WindowSmoother`) takes the
BA's pose system as a factor, adds the new keyframe with its IMU factor, optimises, and writes the
window's poses back for the next BA; keyframes leaving the window are marginalised with the visual
information of their edges.
"""
from __future__ import annotations

import logging
import threading
import time
from dataclasses import replace
from typing import TYPE_CHECKING, Optional

import numpy as np

from ..errors import ConfigError
from ..eval.align import umeyama
from ..geometry import sim3, sim3_apply_to_pose, sim3_compose, sim3_scale
from ..mapping.history import scale_keyframe_depth
from ..types import Calibration, ImuSample, Keyframe
from .align import Alignment, align, excitation
from .config import ViConfig, ViState
from .preint import (ImuArrays, ImuNoiseConfig, centred, gtsam_params, gtsam_preintegrate, hat, predict,
                     preintegrate)
from .smoother import NavEstimate, WindowSmoother
from .standstill import StillTest, attitude_from_gravity, imu_still, units_problem
from .time_offset import TdEstimate, estimate_td

if TYPE_CHECKING:                      # pragma: no cover
    from ..frontend.tracker import Frontend

log = logging.getLogger("vings.vio")

MAX_EVENTS = 200
#: kinds of :meth:`ImuBuffer.covers` refusals
BEFORE, NOT_YET, GAP = "no IMU before", "IMU not there yet", "IMU gap"


class ImuBuffer:
    """IMU readings in time order, read on the camera clock (``stamp - td_ns``; ``td_ns`` may be
    changed, e.g. by the online offset estimate) with centred holds (:func:`.preint.centred`);
    refuses non-finite, duplicate and out-of-order readings and counts them (``refused``).
    Thread-safe: a node adds readings from its IMU callback while the front end reads them."""

    def __init__(self, td_ns: int = 0, keep_s: float = 60.0):
        self._lock = threading.Lock()
        self._td_ns = int(td_ns)
        self.keep_ns = int(keep_s * 1e9)
        self._t: list[int] = []
        self._g: list[np.ndarray] = []
        self._a: list[np.ndarray] = []
        self.refused = {"out_of_order": 0, "duplicate": 0, "non_finite": 0}
        self.count = 0
        self._cache: Optional[ImuArrays] = None

    def __getstate__(self) -> dict:
        """Pickled without its lock (a front-end checkpoint)."""
        with self._lock:
            d = dict(self.__dict__)
        del d["_lock"]
        return d

    def __setstate__(self, d: dict) -> None:
        self.__dict__.update(d)
        self._lock = threading.Lock()

    @property
    def td_ns(self) -> int:
        """Camera-IMU offset in use (ns): ``t_imu = t_cam + td``."""
        return self._td_ns

    @td_ns.setter
    def td_ns(self, td: int) -> None:
        with self._lock:
            self._td_ns = int(td)
            self._cache = None

    def add(self, s: ImuSample) -> bool:
        t = int(s.stamp_ns)
        g, a = np.asarray(s.gyro, np.float64), np.asarray(s.accel, np.float64)
        with self._lock:
            if not (g.shape == (3,) and a.shape == (3,) and np.isfinite(g).all() and np.isfinite(a).all()):
                self.refused["non_finite"] += 1
                return False
            if self._t and t <= self._t[-1]:
                self.refused["duplicate" if t == self._t[-1] else "out_of_order"] += 1
                return False
            self._t.append(t)
            self._g.append(g)
            self._a.append(a)
            self.count += 1
            self._cache = None
            if self._t[-1] - self._t[0] > 2 * self.keep_ns:          # bounded memory
                cut = int(np.searchsorted(np.asarray(self._t), self._t[-1] - self.keep_ns))
                del self._t[:cut], self._g[:cut], self._a[:cut]
        return True

    def arrays(self) -> ImuArrays:
        with self._lock:
            if self._cache is None:
                self._cache = centred(ImuArrays(np.asarray(self._t, np.int64) - self._td_ns,
                                                np.asarray(self._g).reshape(-1, 3),
                                                np.asarray(self._a).reshape(-1, 3)))
            return self._cache

    def covers(self, t0_ns: int, t1_ns: int, max_gap_s: float) -> Optional[str]:
        """Why ``[t0_ns, t1_ns]`` cannot be pre-integrated (``None`` when it can): no reading at or
        before ``t0`` (:data:`BEFORE`), none near ``t1`` yet (:data:`NOT_YET`: wait for them), or a
        gap longer than ``max_gap_s`` (:data:`GAP`). The reason starts with its kind."""
        st = self.arrays().stamps_ns
        if not len(st):
            return f"{NOT_YET}: no IMU readings yet"
        if st[0] > t0_ns:
            return f"{BEFORE}: no IMU reading before {t0_ns} ns"
        if st[-1] < t1_ns - int(max_gap_s * 1e9):
            return f"{NOT_YET}: IMU readings end at {int(st[-1])} ns, before {t1_ns} ns"
        i0 = int(np.searchsorted(st, t0_ns, side="right")) - 1
        i1 = int(np.searchsorted(st, t1_ns, side="left"))
        seg = np.concatenate([[t0_ns], st[i0 + 1:i1], [min(t1_ns, int(st[-1])) if i1 >= len(st) else t1_ns]])
        gap = float(np.diff(seg).max(initial=0)) * 1e-9
        if gap > max_gap_s:
            return f"{GAP}: IMU gap of {gap:.3f} s (> max_imu_gap_s {max_gap_s:g})"
        return None


def scale_keyframe(kf: Keyframe, C: np.ndarray) -> Keyframe:
    """``kf`` moved by the similarity ``C`` (``x -> s R x + t``): pose by
    :func:`~vings_core.geometry.sim3_apply_to_pose`, depth times ``s``, inverse-depth variance
    divided by ``s^2``."""
    import torch
    T = sim3_apply_to_pose(C, kf.T_wc.detach().cpu().numpy().astype(np.float64))
    out = replace(kf, T_wc=torch.from_numpy(T))
    scale_keyframe_depth(out, float(np.cbrt(np.linalg.det(C[:3, :3]))))
    return out


def _gtsam_system(ps, weight: float) -> tuple:
    """A :class:`~vings_core.frontend.ba.PoseSystem` as the smoother takes it: ``(G, g, stamps,
    T_wc_lin)`` in GTSAM's ordering, the information times ``weight``."""
    G, g = ps.to_gtsam_ordering()
    return (weight * G.numpy(), weight * g.numpy(), list(ps.stamps_ns),
            [np.linalg.inv(T) for T in ps.T_cw.numpy()])


class ViFusion:
    """Visual-inertial fusion for one :class:`~vings_core.frontend.Frontend` (see module docs).

    ``state``, ``reason`` (in words), ``events`` (state changes), ``initialised_at_ns`` (stamp of
    the first accepted alignment), ``alignment`` (the last attempt), ``scale_applied`` (product of
    the accepted alignments' scales)."""

    def __init__(self, cfg: Optional[ViConfig], calib: Calibration):
        self.cfg = cfg or ViConfig()
        self.cfg.validate()
        self.T_bc = np.asarray(calib.T_bc, np.float64)
        c = self.cfg
        infl = c.noise_inflation
        self.noise = ImuNoiseConfig(
            gyro_noise_density=infl * (c.gyro_noise_density or calib.gyro_noise_density),
            gyro_random_walk=c.gyro_random_walk or calib.gyro_random_walk,
            accel_noise_density=infl * (c.accel_noise_density or calib.accel_noise_density),
            accel_random_walk=c.accel_random_walk or calib.accel_random_walk,
            gravity=float(calib.gravity))
        self.params = gtsam_params(self.noise)
        self.imu = ImuBuffer(int(round(c.td_s * 1e9)))
        self.smoother: Optional[WindowSmoother] = None
        self.state = ViState.INITIALISING
        self.reason = "initialising: waiting for keyframes and IMU excitation"
        self.events: list[str] = []
        self.initialised_at_ns: Optional[int] = None
        self.alignment: Optional[Alignment] = None
        self.alignments_refused = 0
        self.scale_applied = 1.0
        self.similarities: dict[int, np.ndarray] = {}    # for the pose exchange (taken by the owner)
        self._tried_at: Optional[int] = None
        self._marginals: Optional[tuple[np.ndarray, np.ndarray]] = None   # newest state's v, bias
        self.t_fusion = 0.0
        self.frame_mode: Optional[ViState] = None       # STANDSTILL / IMU_ONLY for the latest frame
        self.still: Optional[StillTest] = None          # the latest standstill test that passed
        self.units_error: Optional[str] = None          # the IMU's units are wrong (fusion refused)
        self.td_estimate: Optional[TdEstimate] = None   # the latest online offset estimate
        self.td_estimates = 0                           # accepted estimates
        self._kf_since_td = 0

    @staticmethod
    def for_source(cfg: Optional[ViConfig], calib: Calibration, has_imu: bool) -> tuple[Optional["ViFusion"], str]:
        """The fusion a source allows, and why not when ``None``: fusion off, no IMU, or no known
        camera-IMU extrinsic (never a silent identity)."""
        cfg = cfg or ViConfig()
        if not cfg.enabled:
            return None, "visual-only: IMU fusion switched off"
        if not has_imu:
            return None, "visual-only: the source has no IMU"
        if not calib.T_bc_known:
            return None, ("visual-only: the IMU has no known camera-IMU extrinsic T_bc (give a "
                          "calibration file); not fused")
        if calib.camera is None:
            raise ConfigError("vio: no camera")
        return ViFusion(cfg, calib), "initialising"

    def _event(self, text: str) -> None:
        """Record a state change or refusal; the newest ``MAX_EVENTS`` are kept (a long drive
        without acceleration refuses an alignment at every keyframe)."""
        self.events.append(text)
        del self.events[:-MAX_EVENTS]

    @property
    def td_s(self) -> float:
        """Camera-IMU time offset in use (s): ``t_imu = t_cam + td``."""
        return self.imu.td_ns * 1e-9

    # --------------------------------------------------------------------------- inputs

    def add_imu(self, s: ImuSample) -> bool:
        return self.imu.add(s) if self.units_error is None else False

    def _refuse_units(self, why: str) -> None:
        """The IMU's units are wrong: no fusion from now on (an ERROR, never a silent misuse)."""
        self.units_error = why
        self.smoother = None
        self.state = ViState.VISUAL_ONLY
        self.reason = f"visual-only: IMU refused: {why}"
        self._event(self.reason)
        log.error("vio: %s", self.reason)

    # ------------------------------------------------------------------ standstill, outage

    def standstill(self, stamp_ns: int) -> Optional[np.ndarray]:
        """``R_wb`` (roll and pitch from the accelerometer, yaw 0) when the IMU is still at
        ``stamp_ns`` (:func:`.standstill.imu_still`), else ``None``. The first still window also
        checks the accelerometer's units: a stream in g or with gravity removed is refused
        (:attr:`units_error`, fusion off)."""
        if self.units_error is not None:
            return None
        c = self.cfg
        test = imu_still(self.imu.arrays(), stamp_ns, c.zupt_window_s, c.zupt_block_s, c.zupt_gyro_tol,
                         c.zupt_acc_tol)
        if test is None or not test.still:
            return None
        why = units_problem(float(np.linalg.norm(test.acc_mean)), self.noise.gravity)
        if why is not None:
            self._refuse_units(why)
            return None
        self.still = test
        return attitude_from_gravity(test.acc_mean)

    def propagate(self, stamp_ns: int, since_visual_ns: int) -> Optional[tuple[np.ndarray, np.ndarray]]:
        """IMU-only pose at ``stamp_ns`` through a vision outage: ``(T_wc, cov)`` with ``cov`` the
        6x6 left-tangent ``[rho, phi]`` covariance of ``T_wc``; ``None`` unless visual-inertial,
        with IMU readings up to ``stamp_ns``, and the outage (since the last visually tracked frame
        ``since_visual_ns``) at most ``outage_max_s``. The newest smoother state is propagated with
        its biases. The covariance grows from that state's marginals: position
        ``P_v dt^2 + P_ba dt^4 / 4 + s_a^2 dt^3 / 3``, rotation ``P_bg dt^2 + s_g^2 dt``."""
        if self.state != ViState.VISUAL_INERTIAL or self.smoother is None or not self.smoother.states:
            return None
        if (stamp_ns - since_visual_ns) * 1e-9 > self.cfg.outage_max_s:
            return None
        est = self.smoother.latest()
        if stamp_ns <= est.stamp_ns or self.imu.covers(est.stamp_ns, stamp_ns, self.cfg.max_imu_gap_s) is not None:
            return None
        pre = preintegrate(self.imu.arrays(), est.stamp_ns, stamp_ns, est.bg, est.ba)
        R, p, _ = predict(pre, est.T_wb[:3, :3], est.T_wb[:3, 3], est.v,
                          np.array([0.0, 0.0, -self.noise.gravity]))
        T_wb = np.eye(4)
        T_wb[:3, :3], T_wb[:3, 3] = R, p
        T_wc = T_wb @ self.T_bc
        dt = pre.dt
        Pv, Pb = self._marginals if self._marginals is not None else (np.eye(3) * 0.01, np.eye(6) * 1e-4)
        n = self.noise
        Pp = Pv * dt ** 2 + Pb[:3, :3] * dt ** 4 / 4 + np.eye(3) * n.accel_noise_density ** 2 * dt ** 3 / 3
        Pr = Pb[3:, 3:] * dt ** 2 + np.eye(3) * n.gyro_noise_density ** 2 * dt
        # world-frame (dp, dtheta) -> left tangent of T_wc: rho = dp + [p]x dtheta, phi = dtheta
        A = np.eye(6)
        A[:3, 3:] = hat(T_wc[:3, 3])
        cov = A @ np.block([[Pp, np.zeros((3, 3))], [np.zeros((3, 3)), Pr]]) @ A.T
        return T_wc, cov

    # ------------------------------------------------------------------------ time offset

    def _update_td(self, fe: "Frontend") -> None:
        """Estimate the camera-IMU offset from the segment's newest tracked frames (``td_window_s``)
        and apply an accepted correction; the IMU buffer reads on the new clock from then on."""
        c = self.cfg
        seg, R_bc = fe.init.segment.index, self.T_bc[:3, :3]
        bg = self.smoother.latest().bg if self.smoother is not None and self.smoother.states else None
        kw = dict(max_abs_s=c.td_max_abs_s, max_std_s=c.td_max_std_s)
        # every tracked frame of the newest td_window_s; while initialising their rotations are the
        # images' alone, once visual-inertial the smoother has pulled them part of the way towards
        # the offset in use (see the gain below)
        traj = fe.buffer.trajectory(("tracking",), None, {seg})
        stamps = np.asarray(traj.stamps_ns, np.int64)
        keep = stamps >= (stamps[-1] if len(stamps) else 0) - int(c.td_window_s * 1e9)
        R_wb = traj.poses[keep, :3, :3] @ R_bc.T
        e = estimate_td(self.imu.arrays(), stamps[keep], R_wb, bg, pair_s=c.td_pair_s, **kw)
        self.td_estimate = e
        if not e.ok:
            log.debug("vio: time offset not estimated: %s", e.why)
            return
        # the first estimate is taken whole; later ones move the offset half way, a fixed-point
        # iteration whose fixed point is where the rotations agree (once visual-inertial, the
        # smoother pulls the rotations towards the offset in use, so a correction is seen only in
        # part and is applied again at the next estimate), damped against the estimates' noise
        gain = 1.0 if self.td_estimates == 0 else 0.5
        self.td_estimates += 1
        td = self.td_s + gain * e.delta_s
        if self.td_estimates == 1:
            self._event(f"time offset estimated: td {1e3 * td:.2f} ms (correction {1e3 * e.delta_s:+.2f} ms, "
                        f"std {1e3 * e.std_s:.2f} ms over {e.pairs} frame pairs)")
            log.info("vio: %s", self.events[-1])
        self.imu.td_ns = int(round(td * 1e9))

    def reset(self, why: str) -> None:
        """Back to initialising (a new map segment, an IMU gap): the smoother is dropped."""
        if self.state == ViState.VISUAL_INERTIAL:
            self._event(f"visual-inertial -> initialising: {why}")
            log.warning("vio: %s", self.events[-1])
        self.smoother = None
        self.state = ViState.INITIALISING
        self.reason = f"initialising: {why}"

    # ------------------------------------------------------------------------- keyframes

    def after_keyframe(self, fe: "Frontend") -> None:
        """Called by the front end after each accepted window BA of a new keyframe."""
        t = time.perf_counter()
        try:
            if self.cfg.estimate_td and self.state != ViState.VISUAL_ONLY:
                self._kf_since_td += 1
                # while initialising the frames' rotations are the images' alone: every keyframe
                if self.state == ViState.INITIALISING or self._kf_since_td >= self.cfg.td_every_keyframes:
                    self._kf_since_td = 0
                    self._update_td(fe)
            if self.state == ViState.INITIALISING:
                self._try_initialise(fe)
            elif self.state == ViState.VISUAL_INERTIAL:
                self._smooth(fe)
        finally:
            self.t_fusion += time.perf_counter() - t

    def _preints(self, stamps: list[int]) -> Optional[list]:
        for a, b in zip(stamps[:-1], stamps[1:]):
            why = self.imu.covers(a, b, self.cfg.max_imu_gap_s)
            if why is not None:
                self.reason = f"initialising: {why}"
                return None
        arr = self.imu.arrays()
        return [preintegrate(arr, a, b) for a, b in zip(stamps[:-1], stamps[1:])]

    def _try_initialise(self, fe: "Frontend") -> None:
        c = self.cfg
        kfs = fe.buffer.keyframes_of_segment(fe.init.segment.index)
        st = self.imu.arrays().stamps_ns
        if len(st):       # keyframes before the first reading (on the camera clock) cannot take part
            kfs = [s for s in kfs if s >= st[0]]
        kfs = kfs[-c.init_max_keyframes:]
        if len(kfs) < c.init_min_keyframes or (kfs[-1] - kfs[0]) * 1e-9 < c.init_min_span_s:
            self.reason = (f"initialising: {len(kfs)} keyframe(s) over {(kfs[-1] - kfs[0]) * 1e-9 if kfs else 0:.2f} s "
                           f"(need {c.init_min_keyframes} over {c.init_min_span_s:g} s)")
            return
        pres = self._preints(kfs)
        if pres is None:
            return
        exc = excitation(pres)
        if exc < c.init_min_excitation:
            self.reason = (f"initialising: IMU excitation {exc:.3f} m/s^2 below "
                           f"{c.init_min_excitation:g} (motion too smooth for scale and gravity)")
            return
        T_wc = [fe.pose(s) for s in kfs]
        al = align(T_wc, self.T_bc, pres, gravity=self.noise.gravity, g_tol=c.align_g_tol,
                   max_residual=c.align_max_residual, max_scale_std=c.align_max_scale_std)
        log.debug("vio: alignment over %d keyframes: %s (scale %.4g, relative std %.4f, residual %.3g)",
                  len(kfs), al.why, al.scale, al.scale_std, al.residual_rms)
        self.alignment = al
        if not al.ok:
            self.alignments_refused += 1
            self.reason = f"initialising: alignment refused ({al.why})"
            if self._tried_at is None or kfs[-1] != self._tried_at:
                self._event(f"alignment at keyframe {kfs[-1]} refused: {al.why}")
            self._tried_at = kfs[-1]
            return
        self._apply_alignment(fe, al, kfs)

    def _apply_alignment(self, fe: "Frontend", al: Alignment, kfs: list[int]) -> None:
        C = al.C
        seg = fe.init.segment.index
        stamps = fe.buffer.stamps_of_segment(seg)
        fe.apply_increments({s: C for s in stamps})
        # keyframes emitted by this same window BA and not handed on yet: their packets were made
        # in the visual frame; they leave in the metric one (pose, depth and its variance)
        fe.win.emitted = [scale_keyframe(kf, C) for kf in fe.win.emitted]
        for s in fe.buffer.keyframes_of_segment(seg):
            self.similarities[s] = C
        fe.win.after_change(None)              # the window's pose system at the metric poses
        self.scale_applied *= al.scale
        R = C[:3, :3] / al.scale
        vel = {s: R @ v for s, v in zip(kfs, al.velocities)}
        if not self._start_smoother(fe, vel, al.bg):
            self.smoother = None          # the poses are metric now; the next alignment starts it
            self._event(f"alignment at keyframe {kfs[-1]} applied, smoother not started: {self.reason}")
            return
        self.state = ViState.VISUAL_INERTIAL
        if self.initialised_at_ns is None:
            self.initialised_at_ns = int(kfs[-1])
        self.reason = (f"visual-inertial since keyframe {kfs[-1]}: scale {al.scale:.4g}, gyro bias "
                       f"{np.round(al.bg, 4).tolist()} rad/s, scale std {100 * al.scale_std:.2f} %, alignment "
                       f"residual {al.residual_rms:.3g}")
        self._event(f"initialised: {self.reason}")
        log.info("vio: %s", self.events[-1])

    def _body(self, fe: "Frontend", s: int) -> np.ndarray:
        return fe.pose(s) @ np.linalg.inv(self.T_bc)

    def _start_smoother(self, fe: "Frontend", vel: dict[int, np.ndarray], bg: np.ndarray) -> bool:
        """The smoother over the window's keyframes from the first one with IMU readings before it;
        ``False`` (and no smoother) when the IMU does not cover them."""
        c = self.cfg
        st = self.imu.arrays().stamps_ns
        win = [k.stamp for k in fe.window if len(st) and k.stamp >= st[0]]
        if len(win) < 2:
            self.reason = "initialising: the IMU does not cover the window's keyframes"
            return False
        sm = WindowSmoother(self.params, self.T_bc)
        first = win[0]
        sm.start(NavEstimate(first, self._body(fe, first), vel.get(first, np.zeros(3)), np.zeros(3), bg),
                 [c.prior_rot_sigma] * 3 + [c.prior_pos_sigma] * 3, c.prior_vel_sigma,
                 c.prior_acc_bias_sigma, c.prior_gyro_bias_sigma)
        self.smoother = sm
        for s in win[1:]:
            if not self._add_state(fe, s, vel.get(s)):
                return self.smoother is not None     # a gap resets; readings not there yet wait
        self._visual_and_optimise(fe)
        return True

    def _add_state(self, fe: "Frontend", s: int, v: Optional[np.ndarray] = None) -> bool:
        sm = self.smoother
        prev = sm.window_stamps()[-1]
        why = self.imu.covers(prev, s, self.cfg.max_imu_gap_s)
        if why is not None:
            if not why.startswith(NOT_YET):      # a gap: the IMU chain is broken
                self.reset(why)
            return False                         # not there yet: the next keyframe adds both
        est = sm.latest()
        import gtsam
        pim = gtsam_preintegrate(self.imu.arrays(), prev, s, self.params,
                                 gtsam.imuBias.ConstantBias(est.ba, est.bg))
        k = sm.add(s, pim, self._body(fe, s))
        if v is not None:
            sm.values.update(gtsam.symbol("v", k), np.asarray(v, np.float64))
        return True

    def _visual_and_optimise(self, fe: "Frontend") -> None:
        c, sm = self.cfg, self.smoother
        if fe.pose_system is not None:
            sm.set_visual(*_gtsam_system(fe.pose_system, c.visual_weight))
        sm.optimize(c.smoother_iters)
        self._marginals = sm.velocity_bias_covariance(sm.window_stamps()[-1])
        win = {k.stamp for k in fe.window}
        self._write_back(fe, {s: sm.estimate(s).T_wb @ self.T_bc for s in sm.window_stamps() if s in win})
        # keyframes that left the window take their visual information into the prior
        leaving = dict(fe.win.leaving)
        fe.win.leaving.clear()
        while sm.window_stamps() and sm.window_stamps()[0] not in win:
            old = sm.window_stamps()[0]
            inc = leaving.get(old)
            sm.marginalize_oldest(None if inc is None else _gtsam_system(inc, c.visual_weight))

    def _write_back(self, fe: "Frontend", new: dict[int, np.ndarray]) -> None:
        """Move the window's keyframes to the smoother's poses ``new`` (``T_wc``). The smoother
        also corrects the window's scale (by 1-2 % in the first keyframes after the alignment);
        as rigid moves that correction would reach the map as keyframes moving apart while their
        Gaussians keep their size and distance to them. So the scale ``s`` of the similarity that
        best maps the window's old camera centres onto the new ones (Umeyama) travels with every
        keyframe's move: ``C_k = [s R_k, p_new - s R_k p_old]`` with ``R_k = R_new R_old^T``, which
        takes the keyframe exactly to its new pose and scales its content about it by ``s``;
        the moves go to the pose exchange as similarities (:meth:`take_similarities`)."""
        stamps = sorted(new)
        old = {t: fe.pose(t) for t in stamps}
        P_old = np.array([old[t][:3, 3] for t in stamps])
        P_new = np.array([new[t][:3, 3] for t in stamps])
        if len(stamps) < 3 or np.linalg.norm(P_old - P_old.mean(0), axis=1).max() < 1e-9:
            fe.set_poses(new)
            return
        sc = umeyama(P_old, P_new, with_scale=True)[0]
        incs = {}
        for t in stamps:
            R = new[t][:3, :3] @ old[t][:3, :3].T
            incs[t] = sim3(R, new[t][:3, 3] - sc * R @ old[t][:3, 3], sc)
        fe.apply_increments(incs)
        for t, C in incs.items():
            self.similarities[t] = sim3_compose(C, self.similarities[t]) if t in self.similarities else C

    def _smooth(self, fe: "Frontend") -> None:
        sm = self.smoother
        known = set(sm.window_stamps())
        for k in fe.window:
            if k.stamp not in known and k.stamp > sm.window_stamps()[-1]:
                if not self._add_state(fe, k.stamp):
                    return
        self._visual_and_optimise(fe)

    def world_moved(self, increments: dict[int, np.ndarray]) -> None:
        """Frames moved by a correction of the past (``Frontend.apply_jump``, ``{stamp: C}``):
        the smoother's states move with their keyframes (:meth:`WindowSmoother.move`). A
        correction that changes the scale of a metric state cannot be right for the IMU: the
        fusion starts over (a new alignment)."""
        sm = self.smoother
        if sm is None or not sm.states:
            return
        mine = {s: C for s, C in increments.items() if s in set(sm.window_stamps())}
        if not mine:
            return
        if any(abs(sim3_scale(C) - 1.0) > 1e-6 for C in mine.values()):
            self.reset("a loop correction changed the scale of the metric window")
            self._event(self.reason)
            return
        sm.move(mine)
        self._event(f"smoother moved by a correction of the past ({len(mine)} state(s))")

    # ---------------------------------------------------------------------------- output

    def take_similarities(self) -> dict[int, np.ndarray]:
        """Similarities the fusion applied to keyframes since the last call (for the pose exchange,
        so the followers scale their content too)."""
        out, self.similarities = self.similarities, {}
        return out

    def twist(self, stamp_ns: int, T_wc: np.ndarray) -> Optional[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """Velocity (m/s), angular rate (rad/s) and their 6x6 covariance (``[v, w]``) of the camera
        at ``stamp_ns`` (pose ``T_wc``), in the camera frame, when visual-inertial: the newest
        keyframe state propagated with the IMU to ``stamp_ns`` (its velocity and the
        bias-corrected gyro of the last reading, plus the lever arm ``w x p_bc``). The covariance
        is the smoother's marginal of that state's velocity and gyro bias (plus the gyro's white
        noise at the IMU rate), rotated into the camera frame; the propagation's own growth is not
        added. ``None`` when not visual-inertial or without IMU readings up to the stamp."""
        if self.smoother is None or not self.smoother.states:
            return None
        est = self.smoother.latest()
        if stamp_ns < est.stamp_ns or self.imu.covers(est.stamp_ns, stamp_ns, self.cfg.max_imu_gap_s) is not None:
            return None
        arr = self.imu.arrays()
        v_w = est.v
        if stamp_ns > est.stamp_ns:
            pre = preintegrate(arr, est.stamp_ns, stamp_ns, est.bg, est.ba)
            _, _, v_w = predict(pre, est.T_wb[:3, :3], est.T_wb[:3, 3], est.v,
                                np.array([0.0, 0.0, -self.noise.gravity]))
        k = int(np.searchsorted(arr.stamps_ns, stamp_ns, side="right")) - 1
        w_b = arr.gyro[max(k, 0)] - est.bg
        R_bc, p_bc = self.T_bc[:3, :3], self.T_bc[:3, 3]
        R_cw = np.asarray(T_wc, np.float64)[:3, :3].T
        # camera velocity = body velocity + w x (lever arm), all in the world, then into the camera
        R_wb = np.asarray(T_wc, np.float64)[:3, :3] @ R_bc.T
        v_c = R_cw @ (v_w + R_wb @ np.cross(w_b, p_bc))
        cov = np.zeros((6, 6))
        if self._marginals is not None:
            Pv, Pb = self._marginals
            rate = 1.0 / max(float(np.median(np.diff(arr.stamps_ns[-20:]))) * 1e-9, 1e-4) if len(arr.stamps_ns) > 2 else 200.0
            Pw = Pb[3:, 3:] + np.eye(3) * self.noise.gyro_noise_density ** 2 * rate
            cov[:3, :3] = R_cw @ Pv @ R_cw.T
            cov[3:, 3:] = R_bc.T @ Pw @ R_bc
        return v_c, R_bc.T @ w_b, cov

    def status(self) -> dict:
        out = {"vi_state": self.state.value, "vi_reason": self.reason,
               "vi_initialised_at_ns": self.initialised_at_ns,
               "vi_scale_applied": self.scale_applied, "imu_samples": self.imu.count,
               "imu_refused": dict(self.imu.refused), "alignments_refused": self.alignments_refused,
               "td_s": self.td_s, "td_estimates": self.td_estimates,
               "t_fusion_s": round(self.t_fusion, 3)}
        if self.frame_mode is not None and self.state != ViState.VISUAL_ONLY:
            out["vi_state"] = self.frame_mode.value
        if self.units_error is not None:
            out["vi_error"] = self.units_error
        if self.still is not None:
            out["still_acc_mean"] = self.still.acc_mean.tolist()
        if self.smoother is not None and self.smoother.states:
            e = self.smoother.latest()
            out.update(acc_bias=e.ba.tolist(), gyro_bias=e.bg.tolist(), velocity=e.v.tolist())
        if self.alignment is not None and self.alignment.ok:
            out["gravity_visual_world"] = self.alignment.g_w.tolist()
        return out
