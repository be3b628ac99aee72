#!/usr/bin/env python3
"""Visual-inertial front end against visual-only on the simulator (exact ground truth, EuRoC-like
IMU noise and biases, the simulator's non-identity ``T_bc``).

Experiments (``--exp``, comma list):

* ``sim``: synthetic ``room`` (``--room-frames``, handheld) and ``street`` (``--street-frames`` at
  20 Hz, about 0.45 m per frame) for each seed of ``--seeds``, with the IMU fused and with
  ``--no-imu`` (``vio.enabled`` false). Per run: seconds from the first frame to the accepted
  alignment (``init_s``), scale error ``|s - 1|`` of the Sim(3) aligning the final trajectory to the
  truth, ATE after SE(3) alignment (m and % of the path), the gravity error (median / max over the
  frames of the angle between estimated and true gravity in the camera frame), the Sim(3) ATE of the
  same frames with and without the IMU and their ratio, fusion time per keyframe (ms) and the
  front end's frames per second with and without the IMU.
* ``rates``: the room (seed 0) with the IMU recorded at 100 Hz and at 50 Hz, 5 % of the readings
  dropped at random and one 0.2 s gap at 4 s (``vings sim --imu-rate --imu-drop --imu-gap``):
  initialised or not, scale error, SE(3) ATE.
* ``td``: the room (``--seeds``) simulated with a camera-IMU offset of 15 ms (``vings sim
  --imu-td 0.015``), configured 0: the online estimate, and the ATE with and without estimation.
* ``outage``: a 1 s vision outage (lens covered, ``vings sim --blind``) in the room (8-9 s) and the
  street (20-21 s): frames posed by the IMU alone, map segments, the position error of the last
  IMU-only frame and of the first re-acquired frame against the truth (trajectory before the
  outage aligned to the truth with SE(3)); the same with ``--no-imu``.
* ``euroc``: the real ``euroc_v101_micro`` (the MAV stands on the ground, rotors running): frames
  posed, standstill, gravity error against the ground truth, position drift, ``scale_observable``.

The last stdout line is one JSON object keyed by experiment (``benchmarks/_harness.py``).
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from _harness import run_selected  # noqa: E402

WORK = Path(os.environ.get("TMPDIR", "/tmp")) / "vings_bench_vio"


def log(*a) -> None:
    print("[bench vio]", *a, file=sys.stderr, flush=True)


def _sim(name: str, frames: int, seed: int, tag: str = "", **kw) -> Path:
    from vings_core.sim import generate
    d = WORK / f"{name}_{frames}_s{seed}{tag}"
    if not (d / "sim.json").exists():
        generate(name, d, frames=frames, seed=seed, width=376, height=240, mcap=False, **kw)
    return d


def run_frontend(path: Path, use_imu: bool, cfg=None, keep_fe: bool = False) -> dict:
    """The front end over a recording (IMU readings merged in time order), with or without the
    fusion (``cfg``: its :class:`ViConfig`); trajectory figures against the truth (``keep_fe``:
    the front end and the truth in ``_fe``, ``_gt``)."""
    from vings_core.eval.traj import associate, ate
    from vings_core.frontend import Frontend, FrontendConfig
    from vings_core.io import SourceOptions, open_source
    from vings_core.types import Frame
    from vings_core.vio.config import ViConfig
    from vings_core.vio.fusion import ViFusion
    src = open_source(path, SourceOptions(width=376, height=240))
    cal = src.calibration
    vio = None
    if use_imu:
        vio, why = ViFusion.for_source(cfg or ViConfig(), cal, True)
        if vio is None:
            raise RuntimeError(why)
    fe = Frontend(FrontendConfig(), cal.camera, vio=vio)
    t0 = time.perf_counter()
    for item in src.stream():
        if isinstance(item, Frame):
            fe.process(item)
            fe.pop_keyframes()
        elif vio is not None:
            fe.add_imu(item)
    fe.finish()
    wall = time.perf_counter() - t0
    gt = src.gt_camera_trajectory()
    est = fe.trajectory(states=("tracking", "inertial"))
    e, g = associate(est, gt, max_dt_ns=5_000_000)
    a3, a1 = ate(e, g, "sim3"), ate(e, g, "se3")
    path_m = float(np.linalg.norm(np.diff(g.positions, axis=0), axis=1).sum())
    z = np.array([0.0, 0.0, -1.0])
    ang = np.degrees(np.arccos(np.clip([(Pe[:3, :3].T @ z) @ (Pg[:3, :3].T @ z)
                                        for Pe, Pg in zip(e.poses, g.poses)], -1, 1)))
    st = fe.status()
    f0 = int(src.frame_stamps()[0])
    out = {"frames": int(len(src.frame_stamps())), "posed": int(len(est)), "path_m": round(path_m, 3),
           "ate_sim3_m": a3["rmse_m"], "ate_se3_m": a1["rmse_m"], "ate_se3_pct": 100 * a1["rmse_m"] / path_m,
           "scale_error": abs(a3["scale"] - 1.0), "fps": len(src.frame_stamps()) / wall,
           "keyframes": st["keyframes"], "vi_state": st["vi_state"]}
    if keep_fe:
        out.update(_fe=fe, _gt=gt)
    if vio is not None:
        at = vio.initialised_at_ns
        out.update(init_s=None if at is None else (at - f0) * 1e-9,
                   gravity_err_deg_median=float(np.median(ang)), gravity_err_deg_max=float(np.max(ang)),
                   fusion_ms_per_keyframe=1e3 * vio.t_fusion / max(st["keyframes"], 1),
                   alignments_refused=vio.alignments_refused, vi_events=vio.events[:4],
                   td_s=vio.td_s, td_estimates=vio.td_estimates)
    return out


def exp_sim(a) -> dict:
    out = {}
    for name, frames in (("room", a.room_frames), ("street", a.street_frames)):
        for seed in a.seeds:
            d = _sim(name, frames, seed)
            r_vi = run_frontend(d, True)
            r_vo = run_frontend(d, False)
            r_vi["ate_sim3_ratio_to_visual"] = r_vi["ate_sim3_m"] / r_vo["ate_sim3_m"]
            r_vi["fps_ratio_to_visual"] = r_vi["fps"] / r_vo["fps"]
            r_vi["visual_only"] = {k: r_vo[k] for k in ("ate_sim3_m", "scale_error", "ate_se3_pct", "fps")}
            out[f"{name}_s{seed}"] = r_vi
            log(f"{name} seed {seed}: {r_vi}")
    return out


def exp_rates(a) -> dict:
    out = {}
    for hz in (100.0, 50.0):
        stream = _stream(rate_hz=hz, drop=0.05, gaps=((4.0, 4.2),))
        d = _sim("room", a.room_frames, 0, f"_imu{int(hz)}", imu=stream)
        r = run_frontend(d, True)
        out[f"{int(hz)}hz"] = {k: r.get(k) for k in ("vi_state", "init_s", "scale_error", "ate_se3_m",
                                                      "ate_se3_pct", "gravity_err_deg_median", "vi_events")}
        log(f"room IMU {hz:g} Hz, 5% dropped, 0.2 s gap: {out[f'{int(hz)}hz']}")
    return out


def exp_td(a) -> dict:
    from vings_core.vio.config import ViConfig
    out = {}
    for seed in a.seeds:
        d = _sim("room", a.room_frames, seed, "_td15", imu=_stream(td_s=0.015))
        on = run_frontend(d, True)
        off = run_frontend(d, True, cfg=ViConfig(estimate_td=False))
        out[f"room_s{seed}"] = {"td_true_ms": 15.0, "td_estimated_ms": 1e3 * on["td_s"],
                                "td_error_ms": abs(1e3 * on["td_s"] - 15.0), "td_estimates": on["td_estimates"],
                                "ate_se3_m_estimated": on["ate_se3_m"], "ate_se3_m_fixed_0": off["ate_se3_m"],
                                "scale_error_estimated": on["scale_error"], "scale_error_fixed_0": off["scale_error"],
                                "init_s": on["init_s"]}
        log(f"td room seed {seed}: {out[f'room_s{seed}']}")
    return out


def _stream(**kw):
    from vings_core.sim.sequence import ImuStreamOptions
    return ImuStreamOptions(**kw)


def _outage_errors(r: dict, blind: tuple[float, float], with_scale: bool) -> dict:
    """Drift through the outage: the displacement from the last frame before it to the last
    IMU-only frame and to the first frame tracked again, against the truth's, with the estimate
    rotated (and, ``with_scale`` for a visual-only run, scaled) by the alignment of the 2 s before
    the outage to the truth."""
    from vings_core.eval.align import umeyama
    from vings_core.eval.traj import associate
    from vings_core.types import TrackState
    fe, gt = r.pop("_fe"), r.pop("_gt")
    states = fe.frame_states()
    st = np.array(list(states), np.int64)
    inertial = [s for s, v in states.items() if v == TrackState.INERTIAL]
    back = [int(s) for s in st if (s - st[0]) * 1e-9 >= blind[1] and states[int(s)] == TrackState.TRACKING]
    e, g = associate(fe.trajectory(states=("tracking", "inertial")), gt, max_dt_ns=5_000_000)
    te = (e.stamps_ns - st[0]) * 1e-9
    before = (te >= blind[0] - 2.0) & (te < blind[0])
    out = {"frames_imu_only": len(inertial), "segments": len(fe.segments()),
           "lost_frames": int(sum(1 for v in states.values() if v == TrackState.LOST))}
    if before.sum() < 3:
        return out
    sc, R, _ = umeyama(e.poses[before, :3, 3], g.poses[before, :3, 3], with_scale=with_scale)
    a = int(np.flatnonzero(before)[-1])
    idx = {int(s): k for k, s in enumerate(e.stamps_ns)}

    def drift(s: int) -> float:
        k = idx[s]
        d_e = sc * R @ (e.poses[k, :3, 3] - e.poses[a, :3, 3])
        return float(np.linalg.norm(d_e - (g.poses[k, :3, 3] - g.poses[a, :3, 3])))
    if inertial and inertial[-1] in idx:
        out["error_last_imu_only_m"] = drift(inertial[-1])
    if back and back[0] in idx:
        out["error_reacquired_m"] = drift(back[0])
        out["reacquired_after_s"] = (back[0] - st[0]) * 1e-9 - blind[1]
    return out


def exp_outage(a) -> dict:
    out = {}
    for name, frames, blind in (("room", a.room_frames, (8.0, 9.0)), ("street", 600, (20.0, 21.0))):
        d = _sim(name, frames, 0, "_blind", blind=blind)
        for use_imu in (True, False):
            r = run_frontend(d, use_imu, keep_fe=True)
            o = _outage_errors(r, blind, with_scale=not use_imu)
            o.update(ate_se3_m=r["ate_se3_m"], ate_sim3_m=r["ate_sim3_m"], posed=r["posed"], frames=r["frames"])
            out[f"{name}_{'imu' if use_imu else 'no_imu'}"] = o
            log(f"outage {name} {'imu' if use_imu else 'no-imu'}: {o}")
    return out


def exp_euroc(a) -> dict:
    from vings_core.eval.traj import associate
    from vings_core.frontend import Frontend, FrontendConfig
    from vings_core.io import SourceOptions, open_source
    from vings_core.types import Frame, TrackState
    from vings_core.vio.config import ViConfig
    from vings_core.vio.fusion import ViFusion
    src = open_source(a.euroc, SourceOptions(width=376, height=240))
    cal = src.calibration
    vio, why = ViFusion.for_source(ViConfig(), cal, True)
    fe = Frontend(FrontendConfig(), cal.camera, vio=vio)
    modes = []
    for item in src.stream():
        if isinstance(item, Frame):
            fe.process(item)
            fe.pop_keyframes()
            modes.append(vio.status()["vi_state"])
        else:
            fe.add_imu(item)
    fe.finish()
    est = fe.trajectory(states=("tracking", "inertial"))
    e, g = associate(est, src.gt_camera_trajectory(), max_dt_ns=5_000_000)
    z = np.array([0.0, 0.0, -1.0])
    ang = np.degrees(np.arccos(np.clip([(Pe[:3, :3].T @ z) @ (Pg[:3, :3].T @ z)
                                        for Pe, Pg in zip(e.poses, g.poses)], -1, 1)))
    p = est.poses[:, :3, 3]
    states = fe.frame_states()
    return {"frames": len(src.frame_stamps()), "posed": len(est),
            "frames_standstill": modes.count("standstill"),
            "inertial_frames": sum(1 for v in states.values() if v == TrackState.INERTIAL),
            "gravity_err_deg_median": float(np.median(ang)), "gravity_err_deg_max": float(ang.max()),
            "position_drift_m": float(np.linalg.norm(p - p[0], axis=1).max()) if len(p) else None,
            "scale_observable": vio.initialised_at_ns is not None, "vi_state": vio.status()["vi_state"],
            "events": fe.events[:3]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--exp", default="sim,rates,td,outage,euroc")
    ap.add_argument("--euroc", type=Path, default=HERE.parent.parent / "shared" / "data" / "euroc_v101_micro")
    ap.add_argument("--seeds", type=lambda s: [int(x) for x in s.split(",")], default=[0, 1, 2])
    ap.add_argument("--room-frames", type=int, default=300)
    ap.add_argument("--street-frames", type=int, default=900, help="20 Hz frames (900: about 400 m)")
    a = ap.parse_args(argv)
    table = {"sim": lambda: exp_sim(a), "rates": lambda: exp_rates(a), "td": lambda: exp_td(a),
             "outage": lambda: exp_outage(a), "euroc": lambda: exp_euroc(a)}
    return run_selected(ap, a, table, log)


if __name__ == "__main__":
    raise SystemExit(main())
