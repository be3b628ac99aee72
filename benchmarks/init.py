#!/usr/bin/env python3
"""Initialisation of the visual front end: how soon a run starting anywhere gives live odometry.

Experiments (``--exp``, comma list):

* ``start_anywhere``: ``kitti06_snippet`` and ``kitti07_160`` (default working size 613x185) cut into
  clips of ``--clip`` frames starting at every ``--every``-th frame; a fresh front end runs each
  clip. Per clip: the first frame (0-based, within the clip) whose own ``process`` call returned a
  tracking pose ("live", not back-filled), the frames posed at the end (back-filled included) and
  the clip's ATE Sim(3). Summary: the fraction of clips live by the clip's ``--live-by``-th frame
  (4th: index 3), the distribution of frames to initialise, the fraction of frames posed.
* ``lowrate``: every 3rd and 5th image of ``kitti07_160``, of the synthetic room (and every 10th:
  2 Hz) and street (300 frames at 20 Hz, 376x240): images to live odometry, images posed, ATE.
* ``onset``: the synthetic room and street starting from rest (``vings sim --slow-start 2``):
  seconds from the onset of motion to live odometry, frames posed, ATE.
* ``lost``: the synthetic room and street with the lens covered for 1 s (``--blind 3:4``):
  segments, seconds from the lens clearing to live odometry in the new segment, frames posed.
* ``static``: ``euroc_v101_micro`` (camera still) at 376x240: the front end must never initialise.
* ``rotation``: the synthetic room turned in place about the camera centre (no translation):
  never initialise.

The last stdout line is one JSON object (``benchmarks/_harness.py``).
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

SHARED = HERE.parent.parent / "shared" / "data"


def log(*a) -> None:
    print("[bench init]", *a, file=sys.stderr, flush=True)


def run_clip(frames, camera, cfg, gt) -> dict:
    """A fresh front end over ``frames``; live and final states, ATE against ``gt`` (or None)."""
    from vings_core.eval.traj import associate, ate
    from vings_core.frontend import Frontend
    from vings_core.types import TrackState
    fe = Frontend(cfg, camera)
    live = None
    t0 = time.perf_counter()
    for k, f in enumerate(frames):
        ests = fe.process(f)
        fe.pop_keyframes()
        own = [e for e in ests if e.stamp_ns == f.stamp_ns]
        if live is None and own and own[-1].state == TrackState.TRACKING:
            live = k
    fe.finish()
    wall = time.perf_counter() - t0
    states = fe.frame_states()
    posed = sum(1 for s in states.values() if s in (TrackState.TRACKING, TrackState.LOST))
    res = {"live_at": live, "posed": posed, "frames": len(frames), "wall_s": round(wall, 2),
           "reason": fe.status()["reason"]}
    if gt is not None and posed >= 3:
        est = fe.trajectory(states=("tracking", "lost"))
        e, g = associate(est, gt, max_dt_ns=5_000_000)
        if len(e) >= 3:
            res["ate_sim3_m"] = ate(e, g, mode="sim3")["rmse_m"]
    return res


def _load(path: Path, width: int, height: int):
    from vings_core.io import open_source
    from vings_core.io.base import SourceOptions
    src = open_source(path, SourceOptions(width=width, height=height))
    return src, list(src.frames())


def exp_start_anywhere(a, cfg) -> dict:
    out: dict = {"clips": {}}
    live_by, n_clips, frames_to_init, posed, total = 0, 0, [], 0, 0
    for name in ("kitti06_snippet", "kitti07_160"):
        p = SHARED / name
        if not p.is_dir():
            out["clips"][name] = {"skipped": f"{p} not found"}
            continue
        src, frames = _load(p, 613, 185)
        gt = src.gt_camera_trajectory()
        res = []
        for s in range(0, len(frames) - a.clip + 1, a.every):
            r = run_clip(frames[s:s + a.clip], src.calibration.camera, cfg, gt)
            r["start"] = s
            res.append(r)
            log(f"{name} clip at {s}: live at {r['live_at']}, posed {r['posed']}/{r['frames']}, "
                f"ATE {r.get('ate_sim3_m')}")
            n_clips += 1
            live_by += int(r["live_at"] is not None and r["live_at"] <= a.live_by - 1)
            frames_to_init.append(r["live_at"] if r["live_at"] is not None else a.clip)
            posed += r["posed"]
            total += r["frames"]
        out["clips"][name] = res
    if n_clips:
        f = np.asarray(frames_to_init)
        out.update(clips=out["clips"], n_clips=n_clips, live_by_frac=live_by / n_clips,
                   live_by_frame=a.live_by, posed_frac=posed / max(total, 1),
                   frames_to_live={"median": float(np.median(f)), "p90": float(np.percentile(f, 90)),
                                   "max": int(f.max()), "histogram": np.bincount(f).tolist()})
    return out


def exp_lowrate(a, cfg) -> dict:
    """Every k-th image of ``kitti07_160`` (k = 3, 5), of the synthetic room (3, 5, 10: 2 Hz) and
    street (3, 5): images to live odometry, images posed, ATE Sim(3) against the same run at the
    full rate."""
    import frontend as fb
    work = Path(os.environ.get("TMPDIR", "/tmp")) / "vings_bench_frontend"
    out = {}
    for name, steps in (("kitti07", (1, 3, 5)), ("room", (1, 3, 5, 10)), ("street", (1, 3, 5))):
        src = fb._source(name, work, a.lowrate_frames)
        if src is None:
            out[name] = {"skipped": "data not found"}
            continue
        frames = list(src.frames())
        gt = src.gt_camera_trajectory()
        res = {}
        for k in steps:
            r = run_clip(frames[::k], src.calibration.camera, cfg, gt)
            res[f"every_{k}"] = {key: r.get(key) for key in ("frames", "live_at", "posed", "ate_sim3_m", "reason")}
            log(f"{name} every {k}: {res[f'every_{k}']}")
        out[name] = res
    return out


def exp_onset(a, cfg) -> dict:
    """The synthetic room (120 frames) and street (160 frames), 376x240 at 20 Hz, starting from
    rest (``vings sim --slow-start 2``), and the highway-speed street (60 frames at 10 Hz,
    ``--speed-factor 2.5``: 21-29 m/s, from rest over 1 s): the onset of motion is the first frame whose camera moved
    ``onset_m`` from where it started (room 2 cm, street 20 cm); reported: seconds from the onset to
    the first live pose, frames posed, ATE Sim(3)."""
    from vings_core.io import SourceOptions, open_source
    from vings_core.sim import generate
    work = Path(os.environ.get("TMPDIR", "/tmp")) / "vings_bench_init"
    out = {}
    cases = (("room", "room", 120, 0.02, 20.0, 1.0, 2.0), ("street", "street", 160, 0.2, 20.0, 1.0, 2.0),
             ("highway", "street", 60, 0.2, 10.0, 2.5, 1.0))
    for key, name, frames, onset_m, fps, speed, ramp in cases:
        d = work / f"{key}_slow{frames}"
        if not (d / "sim.json").exists():
            generate(name, d, frames=frames, width=376, height=240, mcap=False, slow_start_s=ramp,
                     fps=fps, speed_factor=speed)
        src = open_source(d, SourceOptions(width=376, height=240))
        fr = list(src.frames())
        gt = src.gt_camera_trajectory()
        pos = gt.poses[:, :3, 3]
        moved = np.linalg.norm(pos - pos[0], axis=1)
        onset_stamp = int(gt.stamps_ns[int(np.argmax(moved >= onset_m))])
        r = run_clip(fr, src.calibration.camera, cfg, gt)
        live_stamp = fr[r["live_at"]].stamp_ns if r["live_at"] is not None else None
        out[key] = {"frames": r["frames"], "posed": r["posed"], "ate_sim3_m": r.get("ate_sim3_m"),
                    "path_m": float(np.linalg.norm(np.diff(pos, axis=0), axis=1).sum()),
                    "onset_s": (onset_stamp - fr[0].stamp_ns) / 1e9,
                    "live_s": None if live_stamp is None else (live_stamp - fr[0].stamp_ns) / 1e9,
                    "live_after_onset_s": None if live_stamp is None else (live_stamp - onset_stamp) / 1e9}
        log(f"{key} slow start: {out[key]}")
    return out


def exp_lost(a, cfg) -> dict:
    """The synthetic room and street (160 frames, 376x240, 20 Hz) with the lens covered for 1 s
    (``vings sim --blind 3:4``), visual only: map segments, seconds from the lens clearing to the
    first live pose of the new segment, share of the seeing frames posed in some segment."""
    from vings_core.frontend import Frontend
    from vings_core.io import SourceOptions, open_source
    from vings_core.sim import generate
    from vings_core.types import TrackState
    work = Path(os.environ.get("TMPDIR", "/tmp")) / "vings_bench_init"
    out = {}
    for name in ("room", "street"):
        d = work / f"{name}_blind160"
        if not (d / "sim.json").exists():
            generate(name, d, frames=160, width=376, height=240, mcap=False, blind=(3.0, 4.0))
        src = open_source(d, SourceOptions(width=376, height=240))
        fr = list(src.frames())
        t0 = fr[0].stamp_ns
        blind = {f.stamp_ns for f in fr if 3.0 <= (f.stamp_ns - t0) / 1e9 < 4.0}
        clear = min(f.stamp_ns for f in fr if (f.stamp_ns - t0) / 1e9 >= 4.0)
        fe = Frontend(cfg, src.calibration.camera)
        live_after = None
        for f in fr:
            ests = fe.process(f)
            fe.pop_keyframes()
            own = [e for e in ests if e.stamp_ns == f.stamp_ns]
            if (live_after is None and f.stamp_ns >= clear and own and own[-1].state == TrackState.TRACKING
                    and fe.status()["segment"] > 0):
                live_after = (f.stamp_ns - clear) / 1e9
        fe.finish()
        states = fe.frame_states()
        seeing = [s for s in states if s not in blind]
        posed = sum(1 for s in seeing if states[s] == TrackState.TRACKING)
        out[name] = {"frames": len(fr), "blind_frames": len(blind), "segments": len(fe.segments()),
                     "new_segment_live_after_clear_s": live_after,
                     "seeing_frames_posed_frac": posed / max(len(seeing), 1)}
        log(f"{name} covered lens: {out[name]}")
    return out


def exp_static(a, cfg) -> dict:
    p = SHARED / "euroc_v101_micro"
    if not p.is_dir():
        return {"skipped": f"{p} not found"}
    src, frames = _load(p, 376, 240)
    r = run_clip(frames, src.calibration.camera, cfg, None)
    return {"frames": r["frames"], "initialised": r["live_at"] is not None, "posed": r["posed"],
            "reason": r["reason"]}


def exp_rotation(a, cfg) -> dict:
    from vings_core import sim
    from vings_core.geometry import np_pose, np_so3_exp
    from vings_core.types import Frame
    scene = sim.make_scene("room", seed=0)
    camera = sim.default_camera(376, 240)
    T0 = scene.T_wc(np.array([0.0]))[0]
    frames = []
    for k in range(40):        # yaw 1 degree per frame about the camera centre
        T = T0 @ np_pose(np_so3_exp(np.array([0.0, np.deg2rad(1.0) * k, 0.0])), np.zeros(3))
        rgb = sim.render_view(scene, camera, T)[0]
        frames.append(Frame(1_000_000_000 + k * 50_000_000, rgb, camera))
    r = run_clip(frames, camera, cfg, None)
    return {"frames": r["frames"], "initialised": r["live_at"] is not None, "posed": r["posed"],
            "reason": r["reason"]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--exp", default="start_anywhere,lowrate,onset,lost,static,rotation")
    ap.add_argument("--clip", type=int, default=30, help="frames per clip")
    ap.add_argument("--every", type=int, default=5, help="a clip starts at every n-th frame")
    ap.add_argument("--live-by", type=int, default=4, help="live odometry by this frame of the clip (1-based)")
    ap.add_argument("--lowrate-frames", type=int, default=300, help="synthetic frames of the low-rate test")
    ap.add_argument("--params", default=None, help="params file with a 'frontend' section")
    ap.add_argument("--set", action="append", default=[], help="frontend override, e.g. --set window=6")
    a = ap.parse_args(argv)
    from vings_core.config import load_section
    from vings_core.frontend import FrontendConfig
    import yaml
    overrides = {k: yaml.safe_load(v) for k, v in (s.split("=", 1) for s in a.set)}
    cfg = load_section(FrontendConfig, "frontend", a.params, overrides)
    table = {"start_anywhere": lambda: exp_start_anywhere(a, cfg), "static": lambda: exp_static(a, cfg),
             "lowrate": lambda: exp_lowrate(a, cfg), "onset": lambda: exp_onset(a, cfg),
             "lost": lambda: exp_lost(a, cfg),
             "rotation": lambda: exp_rotation(a, cfg)}
    return run_selected(ap, a, table, log)


if __name__ == "__main__":
    raise SystemExit(main())
