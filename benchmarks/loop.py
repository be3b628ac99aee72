#!/usr/bin/env python3
"""Loop closure (``vings_core.loop``) on the simulator's revisiting routes and on sequences without
a revisit. Every run is ``vings run --sync`` in-process (``SlamRunner``), the same run with the loop
closer on and with ``--no-loop``.

Experiments (``--exp``, comma list):

Runs are concurrent (the mapper in its thread, as ``vings run``) unless ``--sync``.

* ``revisit``: ``room --route return`` (ends where it started) and ``street --loop --retrace F``
  (the loop driven, then its first ``F`` again), each visual-only (``--no-imu``) and
  visual-inertial. Per run: loops accepted (and whether one joins the revisit to the first pass),
  end-to-start drift (position error of the first revisiting keyframe after aligning the
  trajectory's first 10 % to the truth: Sim(3) visual-only, SE(3) visual-inertial), ATE over the
  whole trajectory (Sim(3) / SE(3)), the drop of both against ``--no-loop``; the map: PSNR of the
  first revisiting keyframes rendered from their final poses with only the Gaussians of keyframes
  before the revisit, against the same for the first visit's keyframes; Gaussians whose centres
  lie in the first pass's frusta at the start of the revisit and at the end (growth); loop
  detection time per keyframe and correction time.
* ``nofalse``: sequences without a revisit (``street`` open route with repeated facades,
  ``kitti06_snippet``, ``kitti07_160``, ``room --route oneway``): loops accepted (0 expected),
  candidates checked and rejected, and the rejections counted by reason.
* ``long``: ``street --loop --length-m 1000 --retrace 0.2 --fps 10`` visual-only with the loop
  closer: the accepted loops' candidate sources (``retrieval`` when the drift exceeded the radius),
  their distance at detection, and the drift figures.
* ``rejoin``: ``room --route return`` with the lens covered (``--blind``) for ``--blind-s`` seconds
  in the middle, visual-only: tracking is lost and a new map segment starts, anchored at a guess.
  With the loop closer told of the segment (the default) and with it not told: segments, loops
  accepted and whether one crosses the segment start, and ATE Sim(3) of every keyframe of every
  segment under one alignment (one world frame) against ATE of each segment aligned on its own.
* ``cost``: the correction of a map of >= 100 k Gaussians (some passive): the pose exchange's
  increments applied by the mapper and the retrain with its prune, timed.

The last stdout line is one JSON object keyed by experiment (``benchmarks/_harness.py``).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from _harness import run_selected  # noqa: E402

WORK = Path(os.environ.get("TMPDIR", "/tmp")) / "vings_bench_loop"
DATA = HERE.parent.parent / "shared" / "data"


def log(*a) -> None:
    print("[bench loop]", *a, file=sys.stderr, flush=True)


def _sim(scene: str, tag: str, **kw) -> Path:
    from vings_core.sim import generate
    d = WORK / f"{scene}_{tag}"
    if not (d / "sim.json").exists():
        t = time.perf_counter()
        generate(scene, d, width=376, height=240, mcap=False, **kw)
        log(f"simulated {d.name} in {time.perf_counter() - t:.0f} s")
    return d


SYNC = False


def _run(path: Path, tag: str, use_imu: bool, use_loop: bool, probe=None) -> tuple[dict, object]:
    """``vings run`` of ``path`` (``--sync`` with the benchmark's ``--sync``); returns metrics.json
    and the runner. ``probe(runner, kf)``: called in the mapper's thread after every mapped
    keyframe (and its loop check)."""
    from vings_core.config import load_section
    from vings_core.loop import LoopConfig
    from vings_core.pipeline import RunConfig, SlamRunner, open_working_source
    from vings_core.io.base import SourceOptions
    from vings_core.vio.config import ViConfig

    class Runner(SlamRunner):
        def _close_loops(self, kf):
            super()._close_loops(kf)
            if probe is not None:
                probe(self, kf)

    cfg = RunConfig(sync=SYNC)
    vio_cfg = load_section(ViConfig, "vio", None)
    vio_cfg.enabled = use_imu
    loop_cfg = load_section(LoopConfig, "loop", None)
    loop_cfg.enabled = use_loop
    src = open_working_source(path, SourceOptions(), cfg.width, cfg.height)
    out = WORK / "runs" / f"{path.name}_{tag}_{'vi' if use_imu else 'vo'}_{'loop' if use_loop else 'noloop'}"
    runner = Runner(src, out, run_cfg=cfg, progress=False, vio_cfg=vio_cfg, loop_cfg=loop_cfg)
    t = time.perf_counter()
    m = runner.run()
    log(f"{out.name}: {time.perf_counter() - t:.0f} s, loops {m.get('loops_accepted')}, ATE sim3 "
        f"{m.get('ate_sim3_m')}, se3 {m.get('ate_se3_m')}")
    return m, runner


def _gt(path: Path):
    from vings_core.io import SourceOptions, open_source
    return open_source(path, SourceOptions()).gt_camera_trajectory()


def _first_revisit(path: Path, gt) -> int:
    """Index (in the truth's frames) of the first frame back at the start: the simulator's
    ``revisit.first_revisit_frame`` when it retraced, else the first frame in the second half of
    the run within 5 % of the route's extent of the first frame's position, facing within 30 deg
    of it."""
    info = json.loads((path / "sim.json").read_text())
    rv = info.get("revisit")
    if rv and rv.get("first_revisit_frame") is not None:
        return int(rv["first_revisit_frame"])
    P = gt.positions
    ext = float(np.linalg.norm(P.max(0) - P.min(0)))
    R0 = gt.poses[0][:3, :3]
    for k in range(len(P) // 2, len(P)):
        ang = np.degrees(np.arccos(np.clip((np.trace(R0.T @ gt.poses[k][:3, :3]) - 1) / 2, -1, 1)))
        if np.linalg.norm(P[k] - P[0]) < 0.05 * ext and ang < 30:
            return k
    return len(P) - 1


def _drift(traj, gt, k_revisit_stamp: int, metric: bool) -> float:
    """Position error at the frame ``k_revisit_stamp`` after aligning the trajectory's first 10 %
    to the truth (SE(3) when ``metric``, else Sim(3))."""
    from vings_core.eval.align import umeyama
    from vings_core.eval.traj import associate
    e, g = associate(traj, gt, max_dt_ns=5_000_000)
    n = max(3, len(e) // 10)
    s, R, t = umeyama(e.positions[:n], g.positions[:n], with_scale=not metric)
    i = int(np.argmin(np.abs(e.stamps_ns - k_revisit_stamp)))
    p = s * R @ e.positions[i] + t
    return float(np.linalg.norm(p - g.positions[i]))


def _frusta_count(means: np.ndarray, poses: list, cam, max_depth: float) -> int:
    """Gaussian centres inside at least one of the frusta (depth in (0, max_depth])."""
    inside = np.zeros(len(means), bool)
    for T in poses:
        Tcw = np.linalg.inv(T)
        p = means @ Tcw[:3, :3].T + Tcw[:3, 3]
        z = p[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = cam.fx * p[:, 0] / z + cam.cx
            v = cam.fy * p[:, 1] / z + cam.cy
        inside |= (z > 0) & (z <= max_depth) & (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
    return int(inside.sum())


class _RevisitProbe:
    """Counts the Gaussians in the first pass's frusta when the run reaches the first revisit."""

    def __init__(self, revisit_stamp: int, first_pass_end_stamp: int) -> None:
        self.revisit_stamp = revisit_stamp
        self.first_pass_end = first_pass_end_stamp
        self.at_revisit = None

    def region(self, runner) -> tuple[list, float]:
        kp = runner.mapper.keyframe_poses()          # the mapper's thread: its own copy of the poses
        poses = [kp[s] for s in sorted(kp) if s <= self.first_pass_end]
        d = np.median([np.linalg.norm(P[:3, 3] - Q[:3, 3]) for P, Q in zip(poses[:-1], poses[1:])]) if len(poses) > 1 else 1.0
        return poses, 20.0 * float(d)

    def __call__(self, runner, kf) -> None:
        if self.at_revisit is None and int(kf.stamp_ns) >= self.revisit_stamp:
            means = runner.mapper.all_gaussians().means.numpy().astype(np.float64)
            poses, dmax = self.region(runner)
            self.at_revisit = _frusta_count(means, poses, runner.camera, dmax)


def _map_figures(runner, path: Path, revisit_stamp: int, n: int = 3) -> dict:
    """PSNR of the first ``n`` revisiting keyframes and of the first ``n`` keyframes (the first
    visit), each rendered from its final pose with the Gaussians of keyframes before the revisit."""
    from vings_core.eval.image import psnr
    from vings_core.io.base import SourceOptions
    from vings_core.pipeline import open_working_source
    kf = runner.keyframe_trajectory()
    stamps = [int(s) for s in kf.stamps_ns]
    poses = dict(zip(stamps, kf.poses))
    first = stamps[:n]
    rev = [s for s in stamps if s >= revisit_stamp][:n]
    if not rev:
        return {"psnr_revisit_db": None, "psnr_first_visit_db": None}
    want = set(first) | set(rev)
    src = open_working_source(path, SourceOptions(), runner.cfg.width, runner.cfg.height)
    images = {}
    for fr in src.frames():
        if fr.stamp_ns in want:
            a = np.asarray(fr.image)
            a = a.astype(np.float32) / 255.0 if a.dtype == np.uint8 else a.astype(np.float32)
            images[fr.stamp_ns] = np.repeat(a[..., None], 3, -1) if a.ndim == 2 else a[..., :3]
    bound = rev[0]

    def score(ss):
        vals = []
        for s in ss:
            if s in images:
                r = runner.mapper.render(poses[s], runner.camera, owners_before=bound)
                import torch
                vals.append(float(psnr(torch.from_numpy(r["color"]), torch.from_numpy(images[s]))))
        return round(float(np.mean(vals)), 3) if vals else None
    return {"psnr_revisit_db": score(rev), "psnr_first_visit_db": score(first)}


def _revisit_run(path: Path, tag: str, use_imu: bool, use_loop: bool) -> dict:
    gt = _gt(path)
    k = _first_revisit(path, gt)
    rev_stamp = int(gt.stamps_ns[k])
    info = json.loads((path / "sim.json").read_text())
    rv = info.get("revisit") or {}
    t_end = rv.get("retrace_end_s")
    f0 = int(gt.stamps_ns[0])
    first_pass_end = f0 + int(1e9 * (t_end - rv["retrace_start_s"])) if t_end else rev_stamp
    probe = _RevisitProbe(rev_stamp, min(first_pass_end, rev_stamp))
    m, runner = _run(path, tag, use_imu, use_loop, probe)
    traj = runner.trajectory()
    metric = bool(m.get("scale_observable"))
    out = {"loops_accepted": m["loops_accepted"], "candidates_rejected": m["loop_candidates_rejected"],
           "ate_sim3_m": m["ate_sim3_m"], "ate_se3_m": m["ate_se3_m"],
           "ate_m": m["ate_se3_m"] if metric else m["ate_sim3_m"], "metric": metric,
           "drift_m": _drift(traj, gt, rev_stamp, metric), "keyframes": m["keyframes"],
           "frames": m["frames"], "wall_s": m["wall_s"], "psnr_keyframes_db": m["psnr_keyframes_db"],
           "loop_detect_ms_mean": m.get("loop_detect_ms_mean"), "num_gaussians": m["num_gaussians"]}
    if runner.loop is not None:
        acc = [r for r in runner.loop.records if r["verdict"] == "accepted"]
        out["loops"] = [{k: r[k] for k in ("older", "newer", "sources", "matches", "inliers", "render_l1", "scale")}
                        | {"correct_s": r["correction"]["seconds"], "newer_shift": r["correction"]["newer_shift"]}
                        for r in acc]
        out["revisit_detected"] = any(r["newer"] >= rev_stamp - int(5e9) and r["older"] < first_pass_end
                                      for r in acc)
        out["loop_detect_ms_max"] = runner.loop.summary()["loop_detect_ms_max"]
        out["retrains"] = runner.retrains
    poses, dmax = probe.region(runner)
    means = runner.mapper.all_gaussians().means.numpy().astype(np.float64)
    end = _frusta_count(means, poses, runner.camera, dmax)
    out.update(region_gaussians_at_revisit=probe.at_revisit, region_gaussians_end=end,
               region_growth=None if not probe.at_revisit else round(end / probe.at_revisit - 1.0, 4))
    out.update(_map_figures(runner, path, rev_stamp))
    return out


VARIANTS = ("loop", "noloop")


def _pair(path: Path, tag: str, use_imu: bool) -> dict:
    on = _revisit_run(path, tag, use_imu, True) if "loop" in VARIANTS else None
    off = _revisit_run(path, tag, use_imu, False) if "noloop" in VARIANTS else None
    res = {"loop": on, "no_loop": off}
    if on is None or off is None:
        return res
    if off["drift_m"] and on["drift_m"] is not None:
        res["drift_drop"] = round(1.0 - on["drift_m"] / off["drift_m"], 4)
    if off["ate_m"] and on["ate_m"] is not None:
        res["ate_drop"] = round(1.0 - on["ate_m"] / off["ate_m"], 4)
    if on.get("psnr_revisit_db") is not None and on.get("psnr_first_visit_db") is not None:
        res["psnr_revisit_minus_first_db"] = round(on["psnr_revisit_db"] - on["psnr_first_visit_db"], 3)
    return res


def exp_revisit(a) -> dict:
    out = {}
    for seed in a.seeds:
        if "room" in a.scenes:
            p = _sim("room", f"return_{a.room_frames}_s{seed}", frames=a.room_frames, seed=seed, route="return")
            for imu in a.modes:
                out[f"room_s{seed}_{'vi' if imu else 'vo'}"] = _pair(p, "", imu)
        if "street" in a.scenes:
            p = _sim("street", f"retrace_{a.street_length:g}_{a.retrace:g}_s{seed}", seed=seed, loop=True,
                     length_m=a.street_length, retrace=a.retrace, fps=a.street_fps)
            for imu in a.modes:
                out[f"street_s{seed}_{'vi' if imu else 'vo'}"] = _pair(p, "", imu)
    return out


def _nofalse_run(path: Path, use_imu: bool) -> dict:
    m, runner = _run(path, "", use_imu, True)
    recs = runner.loop.records if runner.loop is not None else []
    reasons = Counter()
    for r in recs:
        t = r["reason"]
        key = ("matches" if "matches (need" in t else "matches with depth" if "with depth" in t else
               "pnp" if t.startswith("PnP") else "scale" if ("relative scale" in t or t.startswith("scale")) else
               "coverage" if "covers" in t else "render L1" if "above" in t else
               "spacing" if "after the last loop" in t else
               "nested" if "nested" in t else "no map" if "no map" in t else
               "accepted" if r["verdict"] == "accepted" else "other")
        reasons[key] += 1
    return {"loops_accepted": m["loops_accepted"], "candidates_checked": len(recs),
            "candidates_rejected": m["loop_candidates_rejected"], "rejected_by": dict(reasons),
            "keyframes": m["keyframes"], "frames": m["frames"], "loop_detect_ms_mean": m.get("loop_detect_ms_mean"),
            "accepted": [{k: r[k] for k in ("older", "newer", "matches", "inliers", "render_l1", "distance")}
                         for r in recs if r["verdict"] == "accepted"]}


def exp_nofalse(a) -> dict:
    out = {}
    p = _sim("room", f"oneway_{a.room_frames}_s0", frames=a.room_frames, seed=0, route="oneway")
    out["room_oneway_vo"] = _nofalse_run(p, False)
    p = _sim("street", f"open_{a.open_length:g}_s0", seed=0, length_m=a.open_length, fps=a.street_fps)
    out["street_open_vo"] = _nofalse_run(p, False)
    for name in ("kitti06_snippet", "kitti07_160"):
        d = DATA / name
        if d.exists():
            out[name] = _nofalse_run(d, False)
        else:
            out[name] = {"skipped": f"{d} not found"}
    return out


def exp_long(a) -> dict:
    """The long loop with the loop closer on (the ``--no-loop`` run of ``revisit`` is its
    reference for the drift figures): whether the loop joining the revisit came from retrieval and
    how far the drift had carried the keyframe from its candidate."""
    p = _sim("street", "long_1000_0.2_s0", seed=0, loop=True, length_m=1000.0, retrace=0.2, fps=10.0)
    r = _revisit_run(p, "", False, True)
    from vings_core.loop import LoopConfig
    r["radius"] = float(LoopConfig().radius)
    return {"street_long_vo": r}


def exp_cost(a) -> dict:
    """A mapper with >= 100 k Gaussians (a share passive), a loop-sized similarity for every
    keyframe (growing along the keyframes), applied through ``apply_increments``, then the retrain
    and prune of ``retrain_region`` (the loop section's iterations and time bound)."""
    import torch
    from vings_core.geometry import np_se3_exp, sim3
    from vings_core.loop import LoopConfig
    from vings_core.mapping import GaussianMap, Mapper, MapperConfig
    from vings_core.types import CameraModel, Keyframe
    cam = CameraModel(width=376, height=240, fx=300.0, fy=300.0, cx=187.5, cy=119.5)
    m = Mapper(MapperConfig(iters_per_keyframe=0, window_size=8, max_active=a.cost_gaussians))
    g = torch.Generator().manual_seed(0)
    n_kf = 40
    for i in range(n_kf):
        T = np.eye(4)
        T[0, 3] = 0.5 * i
        u = torch.rand(cam.height, cam.width, 3, generator=g)
        d = torch.full((cam.height, cam.width), 4.0)
        m.add_keyframe(Keyframe(stamp_ns=1000 * (i + 1), image=u, T_wc=torch.from_numpy(T), depth=d,
                                inv_depth_var=torch.full_like(d, 1e-3), valid=d > 0, camera=cam))
    k = 1
    need = a.cost_gaussians - m.num_gaussians
    if need > 0:   # more Gaussians, half of them passive
        owners = torch.tensor([1000 * (i + 1) for i in range(n_kf)])
        extra = GaussianMap.create(torch.randn(need, 3, generator=g) * 3 + torch.tensor([10.0, 0, 4]),
                                   torch.randn(need, 4, generator=g), torch.randn(need, 2, generator=g) - 4,
                                   torch.randn(need, generator=g), torch.rand(need, k, 3, generator=g),
                                   owners[torch.randint(n_kf, (need,), generator=g)], window=8)
        half = need // 2
        m.state.gm = GaussianMap.concat([m.gm, extra.index(torch.arange(half))])
        m.passive.put(extra.index(torch.arange(half, need)), m.state.poses)
    n_total, n_passive = m.num_gaussians, m.num_passive
    incs = {1000 * (i + 1): sim3(np_se3_exp(np.array([0, 0, 0, 0, 0, 0.002 * i]))[:3, :3],
                                 np.array([0.01 * i, -0.02 * i, 0.0]), 1.0 + 0.001 * i) for i in range(n_kf)}
    t = time.perf_counter()
    m.apply_increments(incs)
    all_moved = m.all_gaussians()         # passive ones come back moved: the full correction
    t_apply = time.perf_counter() - t
    lc = LoopConfig()
    t = time.perf_counter()
    re = m.retrain_region(lc.retrain_iters, lc.retrain_max_s, lc.prune_after)
    t_re = time.perf_counter() - t
    return {"gaussians": n_total, "passive": n_passive, "moved_checked": len(all_moved), "apply_s": round(t_apply, 3),
            "retrain_s": round(t_re, 3), "total_s": round(t_apply + t_re, 3), **re}


def exp_rejoin(a) -> dict:
    from vings_core.eval.traj import evaluate_trajectory
    from vings_core.loop import LoopCloser
    out = {}
    for seed in a.seeds:
        dur = a.room_frames / 20.0
        b0 = round(0.45 * dur, 2)
        p = _sim("room", f"return_{a.room_frames}_blind{a.blind_s:g}_s{seed}", frames=a.room_frames, seed=seed,
                 route="return", blind=(b0, b0 + a.blind_s))
        gt = _gt(p)
        for told in (True, False):
            orig = LoopCloser.segment_started
            if not told:
                LoopCloser.segment_started = lambda self, stamp_ns: None      # the closer never hears of it
            try:
                m, runner = _run(p, "told" if told else "untold", False, True)
            finally:
                LoopCloser.segment_started = orig
            fe = runner.frontend
            starts = {k: v for k, v in fe.segment_starts().items() if k > 0}
            kft = fe.keyframe_trajectory()
            rec = {"segments": len(fe.segments()), "segment_starts": sorted(starts.values()),
                   "loops_accepted": m.get("loops_accepted"), "keyframes": len(kft)}
            loops = [r for r in runner.loop.records if r["verdict"] == "accepted"] if runner.loop else []
            rec["loops_across_a_start"] = sum(1 for r in loops if any(r["older"] < s0 <= r["newer"]
                                                                     for s0 in starts.values()))
            rec["kf_ate_sim3_all_m"] = evaluate_trajectory(kft, gt)["ate_sim3_m"] if len(kft) >= 3 else None
            per = []
            for seg in fe.segments():
                t = fe.trajectory(states=("tracking",), segments={seg["index"]})
                if len(t) >= 3:
                    per.append(round(evaluate_trajectory(t, gt)["ate_sim3_m"], 4))
            rec["ate_sim3_per_segment_m"] = per
            out[f"room_s{seed}_{'told' if told else 'not_told'}"] = rec
            log(f"rejoin seed {seed} told={told}: {json.dumps(rec)}")
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--exp", default="revisit,nofalse,long,cost")
    ap.add_argument("--seeds", type=lambda s: [int(x) for x in s.split(",")], default=[0])
    ap.add_argument("--scenes", default="room,street", help="revisit: room,street")
    ap.add_argument("--modes", type=lambda s: [x == "vi" for x in s.split(",")], default=[False, True],
                    help="revisit: vo,vi")
    ap.add_argument("--room-frames", type=int, default=300)
    ap.add_argument("--street-length", type=float, default=500.0, help="street loop length asked for (m)")
    ap.add_argument("--retrace", type=float, default=0.3)
    ap.add_argument("--street-fps", type=float, default=10.0)
    ap.add_argument("--open-length", type=float, default=400.0)
    ap.add_argument("--cost-gaussians", type=int, default=120_000)
    ap.add_argument("--blind-s", type=float, default=0.6, help="rejoin: seconds the lens is covered")
    ap.add_argument("--sync", action="store_true", help="runs with --sync (deterministic, slower)")
    ap.add_argument("--variants", default="loop,noloop", help="revisit: loop,noloop (the runs of each pair)")
    a = ap.parse_args(argv)
    global SYNC, VARIANTS
    SYNC = a.sync
    VARIANTS = tuple(a.variants.split(","))
    table = {"revisit": lambda: exp_revisit(a), "nofalse": lambda: exp_nofalse(a), "long": lambda: exp_long(a),
             "cost": lambda: exp_cost(a), "rejoin": lambda: exp_rejoin(a)}
    return run_selected(ap, a, table, log)


if __name__ == "__main__":
    raise SystemExit(main())
