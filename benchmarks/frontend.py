"""Front-end benchmark: trajectory accuracy, keyframe depth accuracy, uncertainty quality and speed.

Sequences (each skipped with a reason when its data are missing):

* ``room``, ``street``: synthetic (vings_core.sim.generate, 376x240, 300 frames), generated into
  ``--workdir`` on first use; depth truth available.
* ``kitti06``, ``kitti07``: ../shared/data/kitti06_snippet, kitti07_160 at half resolution.
* ``euroc_static``: ../shared/data/euroc_v101_micro (the MAV sits still): must not initialise.

Metrics per sequence: ``ate_sim3_m`` (RMSE after Sim(3) alignment of every frame's pose),
``path_m`` (ground-truth path length of the evaluated frames), ``ate_pct_path``, ``fps`` (frames /
wall time spent in ``Frontend.process``, on this machine), ``fps_cpu`` (frames / CPU time of this
process in ``process``: less sensitive to other load on a shared machine), ``keyframes``, and with
depth truth:
``depth_rel_err`` (median |s d - d_gt| / d_gt over valid pixels of all emitted keyframes, ``s`` the
per-keyframe median scale), ``depth_rel_err_traj_scale`` (same with the trajectory's Sim(3) scale),
``depth_valid_frac`` (valid pixels / all pixels), ``unc_spearman`` (Spearman correlation over valid
pixels between the delivered inverse-depth std and |inverse-depth error|) and
``unc_spearman_ba_only`` (same with the BA marginal variance alone, without the upsampling spread).

The last line printed is one JSON object keyed by sequence name.
Usage: ``python benchmarks/frontend.py [--seqs room,street,kitti06,kitti07,euroc_static]``
"""
from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _harness import run_experiments  # noqa: E402
from vings_core.frontend import Frontend, FrontendConfig  # noqa: E402
from vings_core.types import Trajectory  # noqa: E402

SHARED = Path(os.environ.get("VINGS_SHARED_DATA", REPO.parent / "shared" / "data"))
ALL = ("room", "street", "kitti06", "kitti07", "euroc_static")


def _source(name: str, workdir: Path, frames: int):
    from vings_core.io import SourceOptions, open_source
    if name in ("room", "street"):
        out = workdir / f"{name}_{frames}"
        if not (out / "mav0").is_dir():
            from vings_core.sim import generate
            generate(name, out, frames=frames, width=376, height=240, mcap=False)
        return open_source(out, SourceOptions(width=376, height=240))
    if name == "kitti06":
        p = SHARED / "kitti06_snippet"
        return open_source(p, SourceOptions(width=613, height=185)) if p.is_dir() else None
    if name == "kitti07":
        p = SHARED / "kitti07_160"
        return open_source(p, SourceOptions(width=613, height=185)) if p.is_dir() else None
    if name == "euroc_static":
        p = SHARED / "euroc_v101_micro"
        return open_source(p, SourceOptions(width=376, height=240)) if p.is_dir() else None
    raise SystemExit(f"unknown sequence {name!r}; known: {', '.join(ALL)}")


def _depth_metrics(src, kfs, sim3_scale: float, fe: Frontend) -> dict:
    from scipy.stats import spearmanr
    from vings_core.frontend.depth import joint_bilateral_upsample
    cfg = fe.cfg
    rel_all, rel_traj, std_all, std_ba, err_all = [], [], [], [], []
    n_valid = n_pix = 0
    for kf in kfs:
        gt = src.gt_depth(kf.stamp_ns)
        if gt is None:
            continue
        gt = np.asarray(gt, np.float64)
        depth = kf.depth.numpy().astype(np.float64)
        valid = kf.valid.numpy() & (gt > 0) & (depth > 0)
        n_pix += gt.size
        n_valid += int(valid.sum())
        if valid.sum() < 10:
            continue
        s = float(np.median(gt[valid] / depth[valid]))
        rel_all.append(np.abs(s * depth[valid] - gt[valid]) / gt[valid])
        rel_traj.append(np.abs(sim3_scale * depth[valid] - gt[valid]) / gt[valid])
        inv_err = np.abs(1.0 / (s * depth[valid]) - 1.0 / gt[valid])
        std = np.sqrt(kf.inv_depth_var.numpy().astype(np.float64)[valid]) / s
        std_all.append(std)
        err_all.append(inv_err)
        lr = fe.lowres_depth.get(kf.stamp_ns)
        if lr is not None:
            gray = (kf.image.numpy() @ np.array([0.299, 0.587, 0.114], np.float32)) * 255.0
            _, ba = joint_bilateral_upsample(lr[0], lr[1], gray, 8, cfg.upsample_sigma_spatial,
                                             cfg.upsample_sigma_range, spread_var=False)
            std_ba.append(np.sqrt(ba[valid].astype(np.float64)) / s)
    if not rel_all:
        return {}
    out = {"depth_rel_err": float(np.median(np.concatenate(rel_all))),
           "depth_rel_err_traj_scale": float(np.median(np.concatenate(rel_traj))),
           "depth_valid_frac": n_valid / max(n_pix, 1),
           "unc_spearman": float(spearmanr(np.concatenate(std_all), np.concatenate(err_all))[0]),
           "depth_keyframes": len(rel_all)}
    if std_ba:
        out["unc_spearman_ba_only"] = float(spearmanr(np.concatenate(std_ba),
                                                      np.concatenate(err_all))[0])
    return out


def run_sequence(name: str, workdir: Path, frames: int, cfg: FrontendConfig) -> dict:
    from vings_core.eval.traj import associate, ate
    src = _source(name, workdir, frames)
    if src is None:
        return {"skipped": f"data not found under {SHARED}"}
    fe = Frontend(cfg, src.calibration.camera)
    fe.keep_lowres_depth = True           # the depth-calibration figures read the BA-grid depths
    kfs = []
    t_proc = c_proc = 0.0
    n = 0
    for frame in src.frames():
        t, c = time.perf_counter(), time.process_time()
        fe.process(frame)
        t_proc += time.perf_counter() - t
        c_proc += time.process_time() - c
        kfs.extend(fe.pop_keyframes())
        n += 1
    t, c = time.perf_counter(), time.process_time()
    kfs.extend(fe.finish())
    t_proc += time.perf_counter() - t
    c_proc += time.process_time() - c
    st = fe.status()
    res = {"frames": n, "fps": n / t_proc if t_proc > 0 else None,
           "fps_cpu": n / c_proc if c_proc > 0 else None, "keyframes": st["keyframes"],
           "state": st["state"], "reason": st["reason"], "segments": st["segments"],
           "lost_frames": st["lost_frames"], "relocalisations": st["relocalisations"],
           "motion_detected": st["motion_detected"],
           "time_s": {k[2:]: round(v, 2) for k, v in st.items() if k.startswith("t_")}}
    states = fe.frame_states()
    res["tracked_frames"] = sum(1 for s in states.values() if s == "tracking")
    gt = src.gt_camera_trajectory()
    est = fe.trajectory(states=("tracking", "lost"))
    if name == "euroc_static":
        res["initialised"] = res["tracked_frames"] > 0
        return res
    if gt is None or len(est) < 3:
        res["error"] = "too few tracked frames to evaluate" if gt is not None else "no ground truth"
        return res
    e, g = associate(est, gt, max_dt_ns=5_000_000)
    a = ate(e, g, mode="sim3")
    gpath = Trajectory(g.stamps_ns, g.poses).path_length()
    res.update({"ate_sim3_m": a["rmse_m"], "path_m": gpath,
                "ate_pct_path": 100.0 * a["rmse_m"] / max(gpath, 1e-9),
                "evaluated_frames": len(e), "sim3_scale": a["scale"]})
    res.update(_depth_metrics(src, kfs, a["scale"], fe))
    return res


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seqs", default=",".join(ALL))
    ap.add_argument("--frames", type=int, default=300, help="synthetic sequence length")
    ap.add_argument("--workdir", type=Path, default=Path(os.environ.get("TMPDIR", "/tmp")) / "vings_bench_frontend")
    ap.add_argument("--params", default=None, help="params YAML with a 'frontend' section")
    ap.add_argument("--set", action="append", default=[], help="override, e.g. --set ba_iters=4")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    from vings_core.config import load_section
    import yaml
    overrides = {k: yaml.safe_load(v) for k, v in (s.split("=", 1) for s in args.set)}
    cfg = load_section(FrontendConfig, "frontend", args.params, overrides)
    out: dict = {}

    def one(name: str) -> dict:
        t = time.perf_counter()
        r = run_sequence(name, args.workdir, args.frames, cfg)
        r["wall_s"] = round(time.perf_counter() - t, 1)
        print(f"{name}: " + json.dumps({k: (round(v, 4) if isinstance(v, float) else v)
                                         for k, v in r.items()}), flush=True)
        return r
    # a sequence that fails leaves {"error": ...} in its place; the JSON is the last line anyway
    return run_experiments([(n, lambda n=n: one(n)) for n in args.seqs.split(",")], out)


if __name__ == "__main__":
    raise SystemExit(main())
