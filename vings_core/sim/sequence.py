"""Write a synthetic sequence as an EuRoC/ASL folder (plus a ROS 2 MCAP).

Layout of ``out_dir`` (EuRoC conventions; stamps are int nanoseconds)::

    mav0/cam0/data/<ns>.png                 RGB PNG
    mav0/cam0/data.csv                      #timestamp [ns],filename
    mav0/cam0/sensor.yaml                   pinhole intrinsics, radial-tangential zeros, T_BS = T_bc
    mav0/imu0/data.csv                      t, w_RS_S xyz [rad s^-1], a_RS_S xyz [m s^-2] (200 Hz)
    mav0/imu0/sensor.yaml                   noise densities / random walks, rate_hz
    mav0/state_groundtruth_estimate0/data.csv   body pose p, q(wxyz), v, b_w, b_a (IMU rate)
    mav0/depth0/data/<ns>.npy               float32 z-depth (m), 0 = sky
    mav0/mask0/data/<ns>.png                uint8, 255 = moving object
    sim.json                                summary
    <scene>.mcap (+ <scene>.calib.yaml)     ROS 2 MCAP written by vings_core.io.write_mcap

Everything is written under a temporary sibling folder and renamed onto ``out_dir`` at the end.
"""
from __future__ import annotations

import json
import logging
import os
import shutil
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np

from ..errors import ConfigError, VingsError
from ..geometry import np_rotmat_to_quat
from ..types import CameraModel
from ..util import atomic_write_json
from . import render_view
from .imu import ImuData, ImuNoise, simulate_imu
from .scene import (SCENES, STREET_LENGTH_DEFAULT, STREET_MAX_LENGTH_M, Scene, check_retrace, check_route,
                    default_camera, make_scene)
from .trajectory import ROUTE_MIN_DURATION_S, MotionSample, SlowStartMotion, TimeScaledMotion

log = logging.getLogger("vings.sim")

T0_NS = 1_700_000_000_000_000_000   # first stamp (ns), EuRoC-like magnitude
IMU_RATE_HZ = 200.0
ROOM_FRAMES_DEFAULT = 300
SUMMARY_NAME = "sim.json"


def _plan(scene_name: str, frames: Optional[int], fps: float, loop: bool,
          length_m: Optional[float], speed_factor: float = 1.0, retrace: Optional[float] = None,
          route: Optional[str] = None) -> tuple[Optional[int], Optional[float]]:
    """Validate options; returns (frames or None = derive from the route, street length)."""
    if scene_name not in SCENES:
        raise ConfigError(f"unknown scene {scene_name!r}; expected one of {SCENES}")
    if not (np.isfinite(fps) and 1.0 <= fps <= 200.0):
        raise ConfigError(f"fps must be in [1, 200], got {fps}")
    if abs(IMU_RATE_HZ / fps - round(IMU_RATE_HZ / fps)) > 1e-9:
        raise ConfigError(f"fps must divide the IMU rate {IMU_RATE_HZ:g} Hz (e.g. 10, 20, 25, 40), "
                          f"got {fps}")
    if frames is not None and int(frames) < 2:
        raise ConfigError(f"frames must be >= 2, got {frames}")
    if scene_name == "room":
        if loop:
            raise ConfigError("--loop applies to the street scene only")
        if length_m is not None:
            raise ConfigError("--length-m applies to the street scene only")
        if retrace is not None:
            raise ConfigError("--retrace applies to the street scene only (with --loop)")
        check_route(route)
        return int(frames or ROOM_FRAMES_DEFAULT), None
    if route is not None:
        raise ConfigError("--route applies to the room scene only (the street's route is open, or "
                          "closed with --loop)")
    check_retrace(retrace, loop)
    if length_m is None and frames is not None and not loop:
        # long enough for the requested frames at the fastest cruise speed
        length_m = max(50.0, (int(frames) - 1) / fps * 12.0 * speed_factor + 10.0)
        if length_m > STREET_MAX_LENGTH_M:
            most = int((STREET_MAX_LENGTH_M - 10.0) / (12.0 * speed_factor) * fps) + 1
            raise ConfigError(f"--frames {frames} at {fps:g} fps needs a street of {length_m / 1000:.1f} km; "
                              f"the street scene is at most {STREET_MAX_LENGTH_M / 1000:g} km "
                              f"(at most {most} frames at {fps:g} fps)")
    return (int(frames) if frames is not None else None), length_m


def build_scene(scene_name: str, seed: int = 0, dynamic: bool = False, loop: bool = False,
                length_m: Optional[float] = None, fps: float = 20.0, slow_start_s: float = 0.0,
                speed_factor: float = 1.0, retrace: Optional[float] = None, route: Optional[str] = None,
                route_duration_s: Optional[float] = None) -> Scene:
    """The scene :func:`generate` renders. For closed street routes the motion is time-scaled
    (by < 0.1 %) so one lap lasts a whole number of camera periods: the frame at the end of the lap
    is then exactly at the start pose (with ``retrace``, every frame of the second pass is exactly
    at the pose of the frame one lap earlier; ``scene.revisit`` gives the passes' times).
    ``speed_factor``: the motion is played that many times faster (speeds and turn rates x factor,
    accelerations x factor^2). ``route`` (room): ``'return'`` and ``'oneway'`` walks end at
    ``route_duration_s`` s on the sequence clock (default: the last of 300 frames at ``fps``),
    after a slow start and at any speed factor (the sway plays faster, the walk does not)."""
    kw: dict = {"dynamic": dynamic}
    if retrace is not None:
        kw["retrace"] = retrace             # the room does not take it: make_scene says so
    if scene_name == "street":
        kw.update(loop=loop, length_m=length_m)
        if route is not None:
            kw["route"] = route             # nor the street a route
    elif check_route(route) != "handheld":
        T = (ROOM_FRAMES_DEFAULT - 1) / fps if route_duration_s is None else float(route_duration_s)
        walk_s = speed_factor * (T - 0.5 * slow_start_s)       # the walk's own clock
        if not walk_s >= ROUTE_MIN_DURATION_S - 1e-9:
            need = int(np.ceil((ROUTE_MIN_DURATION_S / speed_factor + 0.5 * slow_start_s) * fps - 1e-9)) + 1
            raise ConfigError(f"--route {route} needs at least {ROUTE_MIN_DURATION_S:g} s of walk: at "
                              f"least {need} frames at {fps:g} fps here, got {T:g} s")
        kw.update(route=route, route_duration_s=walk_s)
    scene = make_scene(scene_name, seed=seed, **kw)
    if speed_factor != 1.0:
        scene.motion = TimeScaledMotion(scene.motion, speed_factor)
    if scene_name == "street" and loop:
        P = getattr(scene.motion, "period", None) or scene.motion.duration     # one lap (s)
        P2 = np.ceil(P * fps - 1e-9) / fps
        scene.motion = TimeScaledMotion(scene.motion, P / P2)
    lap = getattr(scene.motion, "period", None)            # set with a retrace only
    lap_end, end = lap, scene.motion.duration
    if slow_start_s > 0:        # from rest (a handheld camera picked up, a car pulling away)
        scene.motion = SlowStartMotion(scene.motion, slow_start_s)
        if lap is not None:
            lap_end, end = scene.motion.time_of(lap), scene.motion.duration
    if lap is not None:
        scene.revisit = {"first_pass_start_s": 0.0, "first_pass_end_s": float(lap_end),
                         "retrace_start_s": float(lap_end), "retrace_end_s": float(end),
                         "lap_s": float(lap), "retrace_fraction": float(scene.info["retrace"]),
                         "loop_length_m": float(scene.info["loop_length_m"])}
    return scene


def _sensor_yaml_cam(camera, T_bc: np.ndarray, fps: float) -> str:
    d = ", ".join(f"{v:.12g}" for v in T_bc.reshape(-1))
    return ("%YAML:1.0\n"
            "# General sensor definitions.\n"
            "sensor_type: camera\n"
            "comment: VINGS simulator cam0 (ideal pinhole, ray-cast)\n\n"
            "# Sensor extrinsics wrt. the body-frame.\n"
            "T_BS:\n  cols: 4\n  rows: 4\n"
            f"  data: [{d}]\n\n"
            "# Camera specific definitions.\n"
            f"rate_hz: {fps:g}\n"
            f"resolution: [{camera.width}, {camera.height}]\n"
            "camera_model: pinhole\n"
            f"intrinsics: [{camera.fx:.12g}, {camera.fy:.12g}, {camera.cx:.12g}, {camera.cy:.12g}]"
            " #fu, fv, cu, cv\n"
            "distortion_model: radial-tangential\n"
            "distortion_coefficients: [0.0, 0.0, 0.0, 0.0]\n")


_IDENTITY_T_BS = ("T_BS:\n  cols: 4\n  rows: 4\n"
                  "  data: [1.0, 0.0, 0.0, 0.0,\n         0.0, 1.0, 0.0, 0.0,\n"
                  "         0.0, 0.0, 1.0, 0.0,\n         0.0, 0.0, 0.0, 1.0]\n")


def _sensor_yaml_imu(noise: ImuNoise) -> str:
    return ("%YAML:1.0\n"
            "sensor_type: imu\n"
            "comment: VINGS simulator IMU (EuRoC ADIS16448-like noise)\n\n"
            "# Sensor extrinsics wrt. the body-frame.\n" + _IDENTITY_T_BS +
            f"rate_hz: {IMU_RATE_HZ:g}\n\n"
            "# inertial sensor noise model parameters (static)\n"
            f"gyroscope_noise_density: {noise.gyro_noise_density:.6e}     # [ rad / s / sqrt(Hz) ]\n"
            f"gyroscope_random_walk: {noise.gyro_random_walk:.6e}       # [ rad / s^2 / sqrt(Hz) ]\n"
            f"accelerometer_noise_density: {noise.accel_noise_density:.6e}  # [ m / s^2 / sqrt(Hz) ]\n"
            f"accelerometer_random_walk: {noise.accel_random_walk:.6e}    # [ m / s^3 / sqrt(Hz) ]\n")


def _sensor_yaml_gt() -> str:
    return ("%YAML:1.0\n"
            "sensor_type: visual-inertial\n"
            "comment: exact ground truth of the simulated body (IMU) frame\n\n" + _IDENTITY_T_BS)


def _write_csv(path: Path, header: str, stamps: np.ndarray, values: Optional[np.ndarray] = None,
               names: Optional[list[str]] = None) -> None:
    lines = [header]
    if names is not None:
        lines += [f"{int(s)},{n}" for s, n in zip(stamps, names)]
    else:
        for s, row in zip(stamps, values):
            lines.append(f"{int(s)}," + ",".join(f"{v:.17g}" for v in row))
    path.write_text("\n".join(lines) + "\n")


def _is_sim_entry(name: str) -> bool:
    """Names the simulator writes into its output folder."""
    return name in ("mav0", SUMMARY_NAME) or name.endswith((".mcap", ".calib.yaml"))


def _check_out_dir(out: Path) -> None:
    """``out`` may be absent, empty, or an earlier simulator output holding nothing else: it is
    replaced whole, so anything else in it (a run's outputs, notes) would be deleted."""
    if out.exists():
        if not out.is_dir():
            raise ConfigError(f"{out}: output path exists and is not a folder")
        entries = [p.name for p in out.iterdir()]
        if entries and SUMMARY_NAME not in entries:
            raise ConfigError(f"{out}: folder exists, is not empty and is not a simulator output "
                              f"(no {SUMMARY_NAME}); choose another --out or remove it")
        extra = sorted(e for e in entries if not _is_sim_entry(e))
        if extra:
            raise ConfigError(f"{out}: this simulator output also holds {', '.join(extra[:5])}"
                              f"{' ...' if len(extra) > 5 else ''}, which replacing it would delete; "
                              f"move them or choose another --out")


def generate(scene_name: str, out_dir, frames: Optional[int] = None, width: int = 376,
             height: int = 240, seed: int = 0, dynamic: bool = False, loop: bool = False,
             length_m: Optional[float] = None, mcap: bool = True, fps: float = 20.0,
             noise: bool = True, progress: bool = False,
             blind: Optional[tuple[float, float]] = None, slow_start_s: float = 0.0,
             speed_factor: float = 1.0, imu: Optional["ImuStreamOptions"] = None,
             retrace: Optional[float] = None, route: Optional[str] = None) -> Path:
    """Render scene ``scene_name`` and write it as an EuRoC/ASL folder at ``out_dir`` (and, if
    ``mcap``, ``<out_dir>/<scene>.mcap`` via :func:`vings_core.io.write_mcap`). Returns ``out_dir``.

    ``frames``: number of camera frames (room default 300; street default: the whole route,
    ``length_m`` m, default 400, or the whole loop). ``fps``: camera rate (must divide 200 Hz).
    ``noise=False`` writes the exact IMU (no noise, zero biases). ``seed`` fixes scene, motion and
    noise. ``blind``: ``(start, end)`` seconds after the first frame during which the lens is
    covered: those images are black with sensor noise (depth, masks, ground truth and IMU as
    usual). ``slow_start_s``: the motion starts from rest and reaches its own speed after that
    many seconds (:class:`~vings_core.sim.trajectory.SlowStartMotion`; closed loops do not close
    then). ``speed_factor``: the scene's motion played that many times faster (street at 2.5: cruise
    21-29 m/s, highway speed; turn rates scale with the factor, accelerations with its square).
    ``imu``: how the IMU stream is recorded (:class:`ImuStreamOptions`: rate, camera-IMU time
    offset, dropped readings, gaps); the ground truth stays at 200 Hz on the true clock.
    ``retrace`` (street, with ``loop``): after closing the loop, drive that fraction (0, 1] of it
    again over the same lanes (default frames: the whole drive). ``route`` (room): ``'handheld'``
    (default: wanders around), ``'return'`` (a lap of the room that ends at the first frame's
    pose at the last frame) or ``'oneway'`` (turns round at one end of the room and walks to the
    other, never re-seeing its first views); see :func:`~vings_core.sim.trajectory.route_handheld`.
    The summary (see :func:`summarize`) is saved as ``<out_dir>/sim.json``.
    """
    if not (np.isfinite(slow_start_s) and slow_start_s >= 0):
        raise ConfigError(f"slow start must be >= 0 s, got {slow_start_s}")
    if not (np.isfinite(speed_factor) and 0.1 <= speed_factor <= 10.0):
        raise ConfigError(f"speed factor must be in [0.1, 10], got {speed_factor}")
    stream = imu or ImuStreamOptions()
    stream.validate()
    if blind is not None:
        b0, b1 = (float(v) for v in blind)
        if not (np.isfinite(b0) and np.isfinite(b1) and 0 <= b0 < b1):
            raise ConfigError(f"blind interval must be 0 <= start < end seconds, got {blind}")
    wall0 = time.time()
    out = Path(out_dir).expanduser().absolute()
    frames_req, length_m = _plan(scene_name, frames, fps, loop, length_m, speed_factor, retrace, route)
    camera = default_camera(int(width), int(height))
    _check_out_dir(out)
    route_s = (frames_req - 1) / fps if scene_name == "room" and route not in (None, "handheld") else None
    scene = build_scene(scene_name, seed=seed, dynamic=dynamic, loop=loop, length_m=length_m, fps=fps,
                        slow_start_s=slow_start_s, speed_factor=speed_factor, retrace=retrace,
                        route=route, route_duration_s=route_s)

    notes: list[str] = []
    n_frames = _frame_count(scene, frames_req, fps, loop, notes)
    frame_ns, imu_ns = _sample_stamps(n_frames, fps)
    t_frames = frame_ns * 1e-9
    t_imu = imu_ns * 1e-9

    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x1A2B]))
    noise_cfg = ImuNoise()
    imu_data = simulate_imu(scene.motion, t_imu, noise_cfg if noise else None, rng if noise else None)
    gt = scene.motion.sample(t_imu)
    T_wc = scene.T_wc(t_frames)

    tmp = _fresh_tmp_dir(out)
    try:
        dirs = _make_mav0(tmp / "mav0")
        stamps = T0_NS + frame_ns
        stats = _render_all(scene, camera, T_wc, t_frames, stamps, dirs, progress, blind)
        if stream != ImuStreamOptions():
            notes.append(f"IMU recorded at {stream.rate_hz:g} Hz, time offset td {1e3 * stream.td_s:g} ms "
                         f"(t_imu = t_cam + td), {100 * stream.drop:g} % of readings dropped, gaps "
                         f"{list(stream.gaps)} s")
        if blind is not None:
            notes.append(f"lens covered from {blind[0]:g} s to {blind[1]:g} s: "
                         f"{stats['blind_frames']} black frames")
        _write_camera_files(dirs, stamps, camera, scene.T_bc, fps)
        _write_imu_files(dirs, T0_NS + imu_ns, imu_data, gt, noise_cfg, stream, rng)

        summary = summarize(scene, camera, gt, t_frames, fps, seed, noise, stats, notes)
        mcap_path = None
        if mcap:
            mcap_path, why = _write_mcap(tmp, scene_name)
            if why:
                notes.append(why)
        summary["notes"] = list(notes)      # with the MCAP step's note, if any
        summary["mcap"] = str(out / mcap_path.name) if mcap_path else None
        summary["out_dir"] = str(out)
        summary["wall_s"] = round(time.time() - wall0, 3)
        atomic_write_json(tmp / SUMMARY_NAME, summary)
        _swap_in(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    log.info("sim: wrote %d frames of %s to %s in %.1f s", n_frames, scene_name, out,
             time.time() - wall0)
    return out


def _frame_count(scene: Scene, frames_req: Optional[int], fps: float, loop: bool, notes: list[str]) -> int:
    """Camera frames to render: ``frames_req``, or (None) every frame of the motion's duration at
    ``fps`` Hz. More than the route lasts is an error; a loop cut short adds a note to ``notes``."""
    D = scene.motion.duration
    if frames_req is None:
        return int(np.floor(D * fps + 1e-6)) + 1
    n_frames = frames_req
    if D is not None and (n_frames - 1) / fps > D + 1e-9:
        max_frames = int(np.floor(D * fps + 1e-6)) + 1
        raise ConfigError(f"{n_frames} frames at {fps:g} Hz last {(n_frames - 1) / fps:.1f} s but "
                          f"the {scene.info.get('route_length_m', 0):.0f} m route lasts {D:.1f} s "
                          f"(at most {max_frames} frames); raise --length-m or lower --frames")
    if loop and (n_frames - 1) / fps < D - 1e-9:
        lap = scene.revisit["first_pass_end_s"] if scene.revisit else D
        what = "the loop is not closed" if (n_frames - 1) / fps < lap - 1e-9 else "the retrace is cut short"
        notes.append(f"only {n_frames} of {int(np.floor(D * fps + 1e-6)) + 1} frames: {what}")
    return n_frames


def _sample_stamps(n_frames: int, fps: float) -> tuple[np.ndarray, np.ndarray]:
    """Stamps (ns from the first frame, int64) of ``n_frames`` frames at ``fps`` Hz and of the IMU
    samples (at :data:`IMU_RATE_HZ`) up to the last frame."""
    period_ns = int(round(1e9 / fps))
    imu_step_ns = int(round(1e9 / IMU_RATE_HZ))
    frame_ns = np.arange(n_frames, dtype=np.int64) * period_ns
    n_imu = int(frame_ns[-1] // imu_step_ns) + 1
    return frame_ns, np.arange(n_imu, dtype=np.int64) * imu_step_ns


def _fresh_tmp_dir(out: Path) -> Path:
    """An empty temporary sibling folder of ``out`` (``.<name>.tmp-<pid>``) to build the output in."""
    tmp = out.parent / f".{out.name}.tmp-{os.getpid()}"
    try:
        if tmp.exists():
            shutil.rmtree(tmp)
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp.mkdir()
    except OSError as e:
        raise ConfigError(f"{out}: cannot write the simulator output there ({e.strerror or e})") from None
    return tmp


def _make_mav0(mav0: Path) -> dict[str, Path]:
    """The sensor folders of ``mav0`` (``cam0``, ``depth0``, ``mask0`` with their ``data/``;
    ``imu0``, ``state_groundtruth_estimate0``), created, by name."""
    dirs = {k: mav0 / k for k in ("cam0", "imu0", "state_groundtruth_estimate0", "depth0", "mask0")}
    for k in ("cam0", "depth0", "mask0"):
        (dirs[k] / "data").mkdir(parents=True)
    for k in ("imu0", "state_groundtruth_estimate0"):
        dirs[k].mkdir(parents=True)
    return dirs


_FILE_LIST_HEADER = "#timestamp [ns],filename"


def _write_camera_files(dirs: dict[str, Path], stamps: np.ndarray, camera: CameraModel,
                        T_bc: np.ndarray, fps: float) -> None:
    """The file lists of ``cam0``, ``depth0`` and ``mask0`` (frame ``stamps``, ns) and
    ``cam0/sensor.yaml`` (intrinsics in px, ``T_BS = T_bc``, ``fps`` Hz)."""
    names = [f"{s}.png" for s in stamps]
    _write_csv(dirs["cam0"] / "data.csv", _FILE_LIST_HEADER, stamps, names=names)
    _write_csv(dirs["depth0"] / "data.csv", _FILE_LIST_HEADER, stamps, names=[f"{s}.npy" for s in stamps])
    _write_csv(dirs["mask0"] / "data.csv", _FILE_LIST_HEADER, stamps, names=names)
    (dirs["cam0"] / "sensor.yaml").write_text(_sensor_yaml_cam(camera, T_bc, fps))


@dataclass
class ImuStreamOptions:
    """How the simulated IMU is recorded: ``rate_hz`` (divides 200), ``td_s`` (camera-IMU time
    offset: the reading taken at true time ``t`` is stamped ``t + td_s``, so ``t_imu = t_cam + td``),
    ``drop`` (fraction of readings dropped at random), ``gaps`` (``(start, end)`` seconds after the
    first frame without readings)."""

    rate_hz: float = IMU_RATE_HZ
    td_s: float = 0.0
    drop: float = 0.0
    gaps: tuple = ()

    def validate(self) -> None:
        step = IMU_RATE_HZ / self.rate_hz if self.rate_hz > 0 else 0.0
        if not (self.rate_hz > 0 and abs(step - round(step)) < 1e-9):
            raise ConfigError(f"IMU rate must divide {IMU_RATE_HZ:g} Hz, got {self.rate_hz}")
        if not (np.isfinite(self.td_s) and abs(self.td_s) <= 0.5):
            raise ConfigError(f"IMU time offset must be within +-0.5 s, got {self.td_s}")
        if not 0.0 <= self.drop < 0.5:
            raise ConfigError(f"IMU drop fraction must be in [0, 0.5), got {self.drop}")
        for g in self.gaps:
            if len(g) != 2 or not 0 <= g[0] < g[1]:
                raise ConfigError(f"IMU gap must be 0 <= start < end seconds, got {g}")

    def keep(self, t_s: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Which readings at true times ``t_s`` (s from the first frame) are recorded."""
        step = int(round(IMU_RATE_HZ / self.rate_hz))
        keep = (np.arange(len(t_s)) % step) == 0
        if self.drop > 0:
            keep &= rng.random(len(t_s)) >= self.drop
        for g0, g1 in self.gaps:
            keep &= ~((t_s >= g0) & (t_s < g1))
        return keep


def _write_imu_files(dirs: dict[str, Path], istamps: np.ndarray, imu: ImuData, gt: MotionSample,
                     noise_cfg: ImuNoise, stream: ImuStreamOptions, rng: np.random.Generator) -> None:
    """``imu0`` (samples: gyro rad/s, accel m/s^2, body frame; noise of ``noise_cfg``; recorded as
    ``stream`` says) and ``state_groundtruth_estimate0`` (body position m and quaternion wxyz with
    w >= 0 in the world, velocity m/s, IMU biases, every 200 Hz sample on the true clock), at the
    IMU stamps ``istamps`` (ns)."""
    keep = stream.keep((istamps - istamps[0]) * 1e-9, rng)
    _write_csv(dirs["imu0"] / "data.csv",
               "#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],"
               "a_RS_S_x [m s^-2],a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]",
               istamps[keep] + int(round(stream.td_s * 1e9)), np.hstack([imu.gyro, imu.accel])[keep])
    (dirs["imu0"] / "sensor.yaml").write_text(_sensor_yaml_imu(noise_cfg))
    q_xyzw = np_rotmat_to_quat(gt.R)
    q_wxyz = np.hstack([q_xyzw[:, 3:], q_xyzw[:, :3]])
    q_wxyz *= np.where(q_wxyz[:, :1] < 0, -1.0, 1.0)
    _write_csv(dirs["state_groundtruth_estimate0"] / "data.csv",
               "#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], "
               "q_RS_y [], q_RS_z [], v_RS_R_x [m s^-1], v_RS_R_y [m s^-1], v_RS_R_z [m s^-1], "
               "b_w_RS_S_x [rad s^-1], b_w_RS_S_y [rad s^-1], b_w_RS_S_z [rad s^-1], "
               "b_a_RS_S_x [m s^-2], b_a_RS_S_y [m s^-2], b_a_RS_S_z [m s^-2]",
               istamps, np.hstack([gt.p, q_wxyz, gt.v, imu.bias_gyro, imu.bias_accel]))
    (dirs["state_groundtruth_estimate0"] / "sensor.yaml").write_text(_sensor_yaml_gt())


def _render_all(scene: Scene, camera, T_wc: np.ndarray, t_frames: np.ndarray, stamps: np.ndarray,
                dirs: dict, progress: bool, blind: Optional[tuple[float, float]] = None) -> dict:
    """Render every frame; PNG/NPY encoding overlaps with rendering on a worker thread. Frames in
    the ``blind`` interval (s after the first frame) get a black image with sensor noise."""
    import cv2
    dark = np.random.default_rng(7)
    n_blind = 0

    n = len(t_frames)
    dyn_px = np.zeros(n)
    dmin, dmax = np.inf, 0.0
    sky_frac = np.zeros(n)
    render_s = 0.0

    def save(i: int, rgb: np.ndarray, depth: np.ndarray, mask: np.ndarray) -> None:
        s = int(stamps[i])
        if not cv2.imwrite(str(dirs["cam0"] / "data" / f"{s}.png"), rgb[..., ::-1]):
            raise VingsError(f"could not write {dirs['cam0'] / 'data' / f'{s}.png'}")
        np.save(dirs["depth0"] / "data" / f"{s}.npy", depth)
        cv2.imwrite(str(dirs["mask0"] / "data" / f"{s}.png"), mask.astype(np.uint8) * 255)

    it = range(n)
    if progress:
        from tqdm import tqdm
        it = tqdm(it, desc=f"sim {scene.name}", unit="frame")
    pending = []
    with ThreadPoolExecutor(max_workers=1) as pool:
        for i in it:
            t0 = time.perf_counter()
            rgb, depth, mask = render_view(scene, camera, T_wc[i], float(t_frames[i]))
            if blind is not None and blind[0] <= t_frames[i] - t_frames[0] < blind[1]:
                rgb = dark.integers(0, 4, rgb.shape, dtype=np.uint8)     # covered lens
                n_blind += 1
            render_s += time.perf_counter() - t0
            valid = depth > 0
            if valid.any():
                dmin = min(dmin, float(depth[valid].min()))
                dmax = max(dmax, float(depth[valid].max()))
            sky_frac[i] = 1.0 - valid.mean()
            dyn_px[i] = mask.mean()
            pending.append(pool.submit(save, i, rgb, depth, mask))
            if len(pending) > 8:
                pending.pop(0).result()
        for f in pending:
            f.result()
    return {"render_ms_per_frame": round(1e3 * render_s / n, 2),
            "depth_range_m": [round(dmin, 4) if np.isfinite(dmin) else None, round(dmax, 4)],
            "sky_fraction": round(float(sky_frac.mean()), 4),
            "dynamic_pixel_fraction": round(float(dyn_px.mean()), 5),
            "frames_with_dynamic": int((dyn_px > 0).sum()), "blind_frames": n_blind}


def summarize(scene: Scene, camera, gt, t_frames: np.ndarray, fps: float, seed: int, noise: bool,
              stats: dict, notes: list) -> dict:
    """The ``sim.json`` summary of a generated sequence."""
    steps = np.linalg.norm(np.diff(gt.p, axis=0), axis=1)
    speed = np.linalg.norm(gt.v, axis=1)
    T_wb_first = scene.T_wb(t_frames[:1])[0]
    T_wb_last = scene.T_wb(t_frames[-1:])[0]
    if scene.name == "room":
        route = scene.info.get("route", "handheld")
    else:
        route = "loop" if scene.info.get("loop") else "open"
    return {
        "scene": scene.name, "seed": int(seed), "frames": int(len(t_frames)), "fps": float(fps),
        "duration_s": round(float(t_frames[-1]), 6), "imu_samples": int(len(gt.t)),
        "imu_rate_hz": IMU_RATE_HZ, "path_length_m": round(float(steps.sum()), 3),
        "mean_speed_mps": round(float(speed.mean()), 3), "max_speed_mps": round(float(speed.max()), 3),
        "loop": bool(scene.info.get("loop", False)), "route": route,
        "retrace": scene.info.get("retrace"), "revisit": _revisit_summary(scene, t_frames, fps),
        "start_end_distance_m": float(np.linalg.norm(T_wb_last[:3, 3] - T_wb_first[:3, 3])),
        "dynamic": bool(scene.movers), "moving_objects": len(scene.movers),
        "imu_noise": bool(noise), "resolution": [camera.width, camera.height],
        "intrinsics": [camera.fx, camera.fy, camera.cx, camera.cy],
        "T_bc": scene.T_bc.tolist(), "first_stamp_ns": T0_NS,
        "scene_info": scene.info, **stats, "notes": list(notes),
    }


def _revisit_summary(scene: Scene, t_frames: np.ndarray, fps: float) -> Optional[dict]:
    """``scene.revisit`` (times in s on the sequence clock) with its frames: ``first_revisit_frame``
    (the first frame at or after the end of the first pass; at the first frame's pose when it
    falls on the end of the lap, as it always does without a slow start),
    ``lap_frames`` (frame ``i + lap_frames`` retraces frame ``i``; exactly at its pose, after a
    slow-start ramp), ``retrace_frames`` (frames after the end of the first pass) and
    ``retrace_end_s`` cut to the last frame. None when the route has no second pass."""
    if scene.revisit is None:
        return None
    r = {k: (round(v, 6) if isinstance(v, float) else v) for k, v in scene.revisit.items()}
    t_end = float(t_frames[-1])
    after = np.nonzero(t_frames >= scene.revisit["first_pass_end_s"] - 1e-6)[0]
    r["retrace_end_s"] = round(min(scene.revisit["retrace_end_s"], t_end), 6) if len(after) else None
    r["first_revisit_frame"] = int(after[0]) if len(after) else None
    r["retrace_frames"] = int(np.count_nonzero(t_frames > scene.revisit["first_pass_end_s"] + 1e-6))
    r["lap_frames"] = int(round(scene.revisit["lap_s"] * fps))
    return r


def _write_mcap(tmp: Path, scene_name: str) -> tuple[Optional[Path], Optional[str]]:
    """``<tmp>/<scene>.mcap`` via the I/O layer, or (None, reason) if it is not available."""
    try:
        from ..io import open_source, write_mcap
    except ImportError as e:                       # the I/O layer is optional for the generator
        msg = f"MCAP skipped: vings_core.io.write_mcap is not available ({e})"
        log.warning(msg)
        return None, msg
    path = tmp / f"{scene_name}.mcap"
    write_mcap(path, open_source(tmp))
    return path, None


def _swap_in(tmp: Path, out: Path) -> None:
    """Rename ``tmp`` onto ``out``; a previous simulator output there is replaced."""
    old = None
    if out.exists():
        _check_out_dir(out)
        old = out.parent / f".{out.name}.old-{os.getpid()}"
        os.replace(out, old)
    os.replace(tmp, out)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def load_summary(out_dir) -> dict:
    """The ``sim.json`` of a generated folder."""
    return json.loads((Path(out_dir) / SUMMARY_NAME).read_text())
