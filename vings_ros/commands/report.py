"""`vings report`: draw ``report.html`` for an existing run (docs/report.md).

    vings report OUT_DIR [--gt GT] [--out FILE]
    vings report RECORDING.mcap [--out-dir DIR] [--gt GT]

OUT_DIR is a `vings run` output folder: the report is drawn from its files (``bev.png`` is drawn
from ``map.ply`` when absent). RECORDING.mcap is a recording of `vings launch --record`: its
trajectory (``/vings/odometry``), keyframe poses, keyframe images, renders and masks are first
written as an output folder (``--out-dir``, default ``<recording>_report/``), then drawn. GT (a TUM
file of cam0 poses or any dataset path `vings eval --gt` takes) adds the ground truth where the
folder has none.
"""
from __future__ import annotations

import argparse
from pathlib import Path

from vings_core.errors import InputError


def register(sub) -> None:
    p = sub.add_parser("report", help="draw report.html for a run output folder or a `vings launch --record` MCAP",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("path", help="`vings run` output folder, or an MCAP recording of `vings launch --record`")
    p.add_argument("--gt", help="ground truth: TUM file (cam0) or dataset path (as `vings eval --gt`)")
    p.add_argument("--out", help="report file (default: report.html in the output folder)")
    p.add_argument("--out-dir", help="for a recording: the output folder to write (default: <recording>_report)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from vings_core.report import build_report

    from .eval import load_ground_truth
    path = Path(args.path)
    if not path.exists():
        raise InputError(f"{path}: not found (give a `vings run` output folder or a .mcap recording)")
    gt = load_ground_truth(args.gt)[0] if args.gt else None
    if path.is_file():
        if path.suffix.lower() != ".mcap":
            raise InputError(f"{path}: not a folder or an .mcap recording")
        from vings_core.report.recording import recording_to_folder
        folder = Path(args.out_dir) if args.out_dir else path.with_name(path.stem + "_report")
        summary = recording_to_folder(path, folder)
        print(f"vings report: {path.name}: {summary}")
    else:
        if args.out_dir:
            raise InputError("--out-dir is for a recording; an output folder is drawn in place (--out FILE)")
        folder = path
    out = build_report(folder, out_path=args.out, gt=gt, write_bev_png=True)
    print(f"report: {out}")
    return 0
