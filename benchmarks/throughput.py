#!/usr/bin/env python3
"""Throughput of the whole system on this machine: the figures of docs/performance.md.

Experiments (``--exp``, comma list; each runs in its own child process so that its peak memory
is its own, read from the child's rusage):

* ``frontend``: the front end alone (``benchmarks/frontend.py``) on the synthetic ``room`` and
  ``street`` (``--frames`` frames at 376x240) and on ``kitti07_160`` at the default working size:
  frames per second of ``Frontend.process`` and ATE Sim(3).
* ``run_room80``, ``run_room300``, ``run_kitti07``: ``vings run`` with the default parameters in
  the default concurrent mode, as a user runs it (a fresh process: start-up, tracking, mapping,
  evaluation and output writing): ``fps`` and ``wall_s`` of its ``metrics.json``, ATE, keyframe
  PSNR, keyframes trained lightly, queue peak.
* ``mapping``: the mapper alone with ground-truth poses on the 200-frame room
  (``benchmarks/mapping.py --exp room,timing``): seconds per keyframe and keyframe PSNR.
* ``ros``: the live ROS graph at 20 Hz with the keep-newest policy (``benchmarks/ros_graph.py
  --only live``): fraction of frames with odometry, publish-to-odometry latency p95.

Every experiment reports ``peak_rss_mb`` (its child process). Run it with the machine otherwise
idle. The last stdout line is one JSON object (``benchmarks/_harness.py``).
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(HERE))
from _harness import run_experiments  # noqa: E402

SHARED = ROOT.parent / "shared" / "data"
VINGS = [sys.executable, "-m", "vings_ros.cli"]


def log(*a) -> None:
    print("[bench throughput]", *a, file=sys.stderr, flush=True)


def child(cmd: list[str], timeout_s: float) -> tuple[str, float, float]:
    """Run ``cmd``; returns (its stdout, its own peak RSS in MiB from ``wait4``, wall seconds). A
    non-zero exit is an error naming the command and the last lines of its stderr."""
    import tempfile
    import threading
    t0 = time.perf_counter()
    log("$", " ".join(cmd))
    with tempfile.TemporaryFile("w+") as fo, tempfile.TemporaryFile("w+") as fe:
        p = subprocess.Popen(cmd, cwd=ROOT, stdout=fo, stderr=fe, text=True)
        killer = threading.Timer(timeout_s, p.kill)
        killer.start()
        try:
            _, status, ru = os.wait4(p.pid, 0)
        finally:
            killer.cancel()
        p.returncode = os.waitstatus_to_exitcode(status)
        fo.seek(0)
        fe.seek(0)
        out, err = fo.read(), fe.read()
    if p.returncode != 0:
        tail = " | ".join(err.strip().splitlines()[-3:])
        raise RuntimeError(f"{' '.join(cmd[:4])} exited {p.returncode}: {tail}")
    return out, ru.ru_maxrss / 1024.0, time.perf_counter() - t0


def last_json(text: str) -> dict:
    lines = [ln for ln in text.strip().splitlines() if ln.startswith("{")]
    if not lines:
        raise RuntimeError("the child printed no JSON line")
    return json.loads(lines[-1])


def exp_frontend(a) -> dict:
    out, rss, _ = child([sys.executable, str(HERE / "frontend.py"), "--seqs", "room,street,kitti07",
                         "--frames", str(a.frames)], a.timeout)
    d = last_json(out)
    res = {}
    for name in ("room", "street", "kitti07"):
        r = d.get(name) or {}
        res[name] = {k: r.get(k) for k in ("frames", "fps", "fps_cpu", "keyframes", "tracked_frames", "ate_sim3_m")}
    res["peak_rss_mb"] = rss
    return res


def _sim(scene: str, frames: int, work: Path) -> Path:
    p = work / f"{scene}{frames}"
    if not (p / "sim.json").exists():
        child(VINGS + ["sim", "--scene", scene, "--frames", str(frames), "--no-mcap", "--out", str(p)], 900)
    return p


def _run(src: Path, work: Path, tag: str, a, extra: list[str]) -> dict:
    out_dir = work / f"run_{tag}"
    cmd = VINGS + ["run", str(src), "--out", str(out_dir), "--json", "--no-progress"] + extra
    if a.params:
        cmd += ["--params", a.params]
    out, rss, wall = child(cmd, a.timeout)
    m = last_json(out)
    keep = ("frames", "frames_tracked", "keyframes", "wall_s", "fps", "ate_sim3_m", "psnr_keyframes_db",
            "psnr_novel_db", "num_gaussians", "peak_rss_mb", "keyframes_light", "queue_peak_keyframes",
            "queue_spilled")
    res = {k: m.get(k) for k in keep}
    res["process_wall_s"] = wall          # the whole command, interpreter start-up included
    res["process_fps"] = m["frames"] / wall if m.get("frames") else None
    res["child_peak_rss_mb"] = rss
    return res


def exp_run_room(a, frames: int) -> dict:
    work = Path(a.work)
    return _run(_sim("room", frames, work), work, f"room{frames}", a, [])


def exp_run_kitti07(a) -> dict:
    src = SHARED / "kitti07_160"
    if not src.is_dir():
        return {"skipped": f"{src} not found"}
    extra = ["--max-frames", str(a.kitti_frames)] if a.kitti_frames else []
    return _run(src, Path(a.work), "kitti07", a, extra)


def exp_mapping(a) -> dict:
    cmd = [sys.executable, str(HERE / "mapping.py"), "--exp", "room,timing"]
    if a.params:
        cmd += ["--params", a.params]
    out, rss, _ = child(cmd, a.timeout)
    d = last_json(out)["room"]
    return {k: d.get(k) for k in ("keyframes", "iters_per_keyframe", "time_per_kf_s", "time_per_kf_median_s",
                                  "psnr_keyframes_db", "psnr_novel_db", "num_gaussians")} | {"peak_rss_mb": rss}


def exp_ros(a) -> dict:
    out, rss, _ = child([sys.executable, str(HERE / "ros_graph.py"), "--only", "live"], a.timeout)
    d = last_json(out)
    r = d.get("live_20hz") or {}
    return {k: r.get(k) for k in ("frames", "odometry_fraction", "latency_ms_p50", "latency_ms_p95")} | \
        {"peak_rss_mb_all_processes_max": rss}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--exp", default="frontend,run_room80,run_room300,run_kitti07,mapping,ros")
    ap.add_argument("--frames", type=int, default=300, help="synthetic frames of the front-end experiment")
    ap.add_argument("--kitti-frames", type=int, default=0, help="frames of kitti07_160 (0 = all)")
    ap.add_argument("--params", default=None, help="params file for vings run and the mapper")
    ap.add_argument("--work", default=os.path.join(os.environ.get("TMPDIR", "/tmp"), "vings_bench_throughput"))
    ap.add_argument("--timeout", type=float, default=3600.0, help="seconds per child process")
    a = ap.parse_args(argv)
    Path(a.work).mkdir(parents=True, exist_ok=True)
    table = {"frontend": lambda: exp_frontend(a), "run_room80": lambda: exp_run_room(a, 80),
             "run_room300": lambda: exp_run_room(a, 300), "run_kitti07": lambda: exp_run_kitti07(a),
             "mapping": lambda: exp_mapping(a), "ros": lambda: exp_ros(a)}
    names = [e for e in a.exp.split(",") if e]
    bad = [e for e in names if e not in table]
    if bad:
        ap.error(f"unknown experiment(s) {bad}; known: {', '.join(table)}")
    out = {"config": vars(a), "cpu_count": os.cpu_count(), "load_avg_1m_start": os.getloadavg()[0]}

    def finish(o: dict) -> None:
        o["load_avg_1m_end"] = os.getloadavg()[0]
    return run_experiments([(n, table[n]) for n in names], out, log, finish)


if __name__ == "__main__":
    raise SystemExit(main())
