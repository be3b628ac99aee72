"""`vings run SOURCE --out DIR`: the offline SLAM runner (front end + 2DGS mapper)."""
from __future__ import annotations

import argparse
import json
import sys

from .info import add_source_arguments, source_options


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "run", help="run SLAM offline on a recording and write the output folder",
        description="Run the front end and the 2D Gaussian mapper on any recording the I/O layer "
                    "reads (EuRoC/TUM/KITTI folders, ROS 1/2 bags, MCAP). Writes trajectory.tum, "
                    "keyframes.tum, map.ply, checkpoint.pt, metrics.json and renders/ to --out.")
    p.add_argument("source", help="dataset folder, .bag, .mcap or ROS 2 bag folder")
    p.add_argument("--out", required=True, help="output folder (created; files are replaced atomically)")
    p.add_argument("--params", metavar="FILE", help="ROS 2 params YAML (the file the nodes read)")
    p.add_argument("--gt-poses", action="store_true",
                   help="map with ground-truth poses and depth (sources that have both)")
    p.add_argument("--sync", action="store_true",
                   help="deterministic: the mapper finishes each keyframe before tracking goes on")
    p.add_argument("--no-imu", action="store_true",
                   help="visual-only: do not fuse the IMU even when the recording has one (vio.enabled false)")
    p.add_argument("--no-loop", action="store_true",
                   help="no loop closure (loop.enabled false), e.g. for ablations")
    p.add_argument("--no-eraser", action="store_true",
                   help="no dynamic eraser (eraser.enabled false): no masks, e.g. for ablations")
    p.add_argument("--no-report", action="store_true",
                   help="no report.html / bev.png at the end (run.report false; the report's data are written)")
    p.add_argument("--rerun", metavar="FILE.rrd",
                   help="log poses, images, renders, depth and map points for the rerun viewer "
                        "(optional extra: pip install '.[viz]')")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--json", action="store_true", help="print metrics.json as one JSON line at the end")
    p.add_argument("--profile", action="store_true",
                   help="time every stage and step (docs/performance.md); writes profile.json and prints the table")
    add_source_arguments(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from vings_core.config import ConfigError
    from vings_core.pipeline import RunConfig, SlamRunner, open_working_source
    from vings_core.profiling import PROFILE, format_table

    from ..node_common import check_params_file

    if not str(args.out).strip():
        raise ConfigError("--out: give an output folder (an empty path would write into the current folder)")
    # every section (the nodes' too) before any work: a typo fails at once
    from vings_core.config import load_section
    from vings_core.vio.config import ViConfig
    cfg = check_params_file(args.params)["run"] if args.params else RunConfig()
    vio_cfg = load_section(ViConfig, "vio", args.params)
    vio_cfg.enabled = vio_cfg.enabled and not args.no_imu
    from vings_core.loop import LoopConfig
    loop_cfg = load_section(LoopConfig, "loop", args.params)
    loop_cfg.enabled = loop_cfg.enabled and not args.no_loop
    from vings_core.eraser import EraserConfig
    eraser_cfg = load_section(EraserConfig, "eraser", args.params)
    eraser_cfg.enabled = eraser_cfg.enabled and not args.no_eraser
    cfg.sync = cfg.sync or args.sync
    cfg.gt_poses = cfg.gt_poses or args.gt_poses
    cfg.report = cfg.report and not args.no_report
    source = open_working_source(args.source, source_options(args), cfg.width, cfg.height)
    for w in source.warnings:
        print(f"vings run: warning: {w}", file=sys.stderr)
    runner = SlamRunner(source, args.out, params_file=args.params, run_cfg=cfg, progress=not args.no_progress,
                        vio_cfg=vio_cfg, loop_cfg=loop_cfg, eraser_cfg=eraser_cfg, rerun_path=args.rerun)
    if args.profile:
        PROFILE.enable()
    metrics = runner.run()
    if args.profile:
        rows = PROFILE.table(metrics.get("wall_s"))
        runner.out.write_json("profile.json", {"wall_s": metrics.get("wall_s"), "steps": rows})
        print(format_table(rows))
    print(f"outputs in {runner.out.out_dir}: trajectory.tum keyframes.tum map.ply checkpoint.pt "
          f"metrics.json "
          f"{'loops.json ' if runner.loop is not None else ''}renders/"
          f"{' masks/' if runner.eraser is not None else ''}"
          f"{' report.html bev.png' if cfg.report else ''} timeline.jsonl run.json views/"
          f"{'' if args.rerun is None else ' and ' + args.rerun}")
    if args.json:
        print(json.dumps(metrics))
    else:
        for k, v in metrics.items():
            if k != "rpe":
                print(f"  {k:18s} {v}")
    return 0
