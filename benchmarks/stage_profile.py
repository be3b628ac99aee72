"""Where the time of a `vings run` goes, per stage and step. Last line: one JSON object.

Runs the offline runner (`vings_core.pipeline.SlamRunner`, the code `vings run` runs) with the step
timers of `vings_core.profiling` on, over one or more recordings, and prints the table per run
(tracking: flow, motion-only BA, window BA, pose system, depth uncertainty; mapping: render, loss,
backward, optimiser step, scores, densify, pose refinement; I/O: reading frames, writing outputs;
evaluation renders). Steps nest: `tracking / frame (total)` holds the tracking steps, `mapping /
keyframe (total)` the mapping steps.

    python benchmarks/stage_profile.py                       # synthetic room, 80 frames, defaults
    python benchmarks/stage_profile.py --source ../shared/data/kitti07_160 --max-frames 60
    python benchmarks/stage_profile.py --sync                # mapper inline (no concurrency)

Without `--source` it generates the synthetic scene (`--scene`, `--frames`, seed 0) in a temporary
folder first (not timed).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path


def profile_run(source_path: Path, out: Path, sync: bool, max_frames: int, params: str | None) -> dict:
    """One profiled run: metrics and the step table."""
    from vings_core.io.base import SourceOptions
    from vings_core.pipeline import RunConfig, SlamRunner, open_working_source
    from vings_core.profiling import PROFILE

    cfg = RunConfig(sync=sync)
    opts = SourceOptions(max_frames=max_frames or None)
    src = open_working_source(source_path, opts, cfg.width, cfg.height)
    runner = SlamRunner(src, out, params_file=params, run_cfg=cfg, progress=False)
    PROFILE.enable()
    try:
        metrics = runner.run()
    finally:
        PROFILE.disable()
    rows = PROFILE.table(metrics.get("wall_s"))
    cam = src.calibration.camera
    return {"source": str(source_path), "resolution": [cam.width, cam.height], "sync": sync,
            "frames": metrics["frames"], "keyframes": metrics["keyframes"], "wall_s": metrics["wall_s"],
            "fps": metrics["fps"], "ate_sim3_m": metrics.get("ate_sim3_m"),
            "psnr_keyframes_db": metrics.get("psnr_keyframes_db"), "peak_rss_mb": metrics.get("peak_rss_mb"),
            "steps": rows}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--source", action="append", help="recording (repeatable); default: a synthetic scene")
    ap.add_argument("--scene", default="room", help="synthetic scene without --source (room, street)")
    ap.add_argument("--frames", type=int, default=80, help="frames of the synthetic scene")
    ap.add_argument("--size", default="376x240", help="WxH of the synthetic scene")
    ap.add_argument("--max-frames", type=int, default=0, help="frames read of each source (0 = all)")
    ap.add_argument("--sync", action="store_true", help="map each keyframe before the next frame")
    ap.add_argument("--params", default=None, help="params file (default: the built-in defaults)")
    args = ap.parse_args(argv)
    from vings_core.profiling import format_table

    with tempfile.TemporaryDirectory() as tmp:
        sources = [Path(s) for s in (args.source or [])]
        if not sources:
            from vings_core.sim import generate
            sources = [Path(tmp) / args.scene]
            w, h = (int(v) for v in args.size.lower().split("x"))
            generate(args.scene, sources[0], frames=args.frames, width=w, height=h, seed=0, mcap=False)
        runs = []
        for i, src in enumerate(sources):
            t0 = time.perf_counter()
            r = profile_run(src, Path(tmp) / f"out{i}", args.sync, args.max_frames, args.params)
            r["total_s"] = time.perf_counter() - t0
            runs.append(r)
            print(f"## {src} ({r['resolution'][0]}x{r['resolution'][1]}, {r['frames']} frames, "
                  f"{r['keyframes']} keyframes, {r['wall_s']:.1f} s, {r['fps']:.2f} FPS)", file=sys.stderr)
            print(format_table(r["steps"]), file=sys.stderr)
    print(json.dumps({"benchmark": "stage_profile", "cores": os.cpu_count(), "runs": runs}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
