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
* ``rates``: the room (seed 0) with the IMU thinned to 100 Hz and to 50 Hz, 5 % of the readings
  dropped at random and one 0.2 s gap at 4 s: initialised or not, scale error, SE(3) ATE.

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


def _sim(name: str, frames: int, seed: int) -> Path:
    from vings_core.sim import generate
    d = WORK / f"{name}_{frames}_s{seed}"
    if not (d / "sim.json").exists():
        generate(name, d, frames=frames, seed=seed, width=376, height=240, mcap=False)
    return d


def run_frontend(path: Path, use_imu: bool, imu_filter=None) -> dict:
    """The front end over a recording (IMU readings merged in time order), with or without the
    fusion; trajectory figures against the truth."""
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
        vio, why = ViFusion.for_source(ViConfig(), cal, True)
        if vio is None:
            raise RuntimeError(why)
    fe = Frontend(FrontendConfig(), cal.camera, vio=vio)
    imu_keep = imu_filter(src.imu_samples()) if imu_filter else None
    t0 = time.perf_counter()
    for item in src.stream():
        if isinstance(item, Frame):
            fe.process(item)
            fe.pop_keyframes()
        elif vio is not None and (imu_keep is None or item.stamp_ns in imu_keep):
            fe.add_imu(item)
    fe.finish()
    wall = time.perf_counter() - t0
    gt = src.gt_camera_trajectory()
    est = fe.trajectory(states=("tracking",))
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
    if vio is not None:
        at = vio.initialised_at_ns
        out.update(init_s=None if at is None else (at - f0) * 1e-9,
                   gravity_err_deg_median=float(np.median(ang)), gravity_err_deg_max=float(np.max(ang)),
                   fusion_ms_per_keyframe=1e3 * vio.t_fusion / max(st["keyframes"], 1),
                   alignments_refused=vio.alignments_refused, vi_events=vio.events[:4])
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


def _thin(rate_hz: float, drop: float, gap=(4.0, 4.2), seed: int = 0):
    def f(samples):
        rng = np.random.default_rng(seed)
        st = np.array([s.stamp_ns for s in samples], np.int64)
        t = (st - st[0]) * 1e-9
        step = max(int(round(200.0 / rate_hz)), 1)
        keep = (np.arange(len(st)) % step == 0) & (rng.random(len(st)) >= drop)
        keep &= ~((t >= gap[0]) & (t < gap[1]))
        return set(st[keep].tolist())
    return f


def exp_rates(a) -> dict:
    d = _sim("room", a.room_frames, 0)
    out = {}
    for hz in (100.0, 50.0):
        r = run_frontend(d, True, _thin(hz, 0.05))
        out[f"{int(hz)}hz"] = {k: r.get(k) for k in ("vi_state", "init_s", "scale_error", "ate_se3_m",
                                                      "ate_se3_pct", "gravity_err_deg_median", "vi_events")}
        log(f"room IMU {hz:g} Hz, 5% dropped, 0.2 s gap: {out[f'{int(hz)}hz']}")
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--exp", default="sim,rates")
    ap.add_argument("--seeds", type=lambda s: [int(x) for x in s.split(",")], default=[0, 1, 2])
    ap.add_argument("--room-frames", type=int, default=300)
    ap.add_argument("--street-frames", type=int, default=900, help="20 Hz frames (900: about 400 m)")
    a = ap.parse_args(argv)
    table = {"sim": lambda: exp_sim(a), "rates": lambda: exp_rates(a)}
    return run_selected(ap, a, table, log)


if __name__ == "__main__":
    raise SystemExit(main())
