"""`vings eval`: trajectory accuracy (ATE Sim(3)/SE(3), scale, RPE) and image quality (PSNR/SSIM,
LPIPS with a local weights file).

    vings eval EST.tum --gt GT [--json] [--plots DIR] [--max-dt-ms 10] [--gt-frame camera|body] [--calib FILE]
    vings eval --images RENDERS_DIR REFERENCE_DIR [--lpips-weights FILE] [--json]

EST is a TUM file of cam0 poses or a run output folder (its trajectory.tum). GT is a TUM file (cam0
poses unless ``--gt-frame body``, which needs ``--calib`` for T_bc) or any dataset path
``vings_core.io.open_source`` reads (its ground truth is mapped to cam0 with the dataset's T_bc).
With ``--json`` the last line of stdout is one JSON object.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any, Optional

from vings_core.errors import InputError

DATASET_SUFFIXES = {".bag", ".mcap", ".db3", ".yaml", ".yml", ".sqlite3"}
IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".ppm", ".bmp", ".tif", ".tiff"}


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "eval", help="evaluate a trajectory (ATE, scale, RPE) and/or renders (PSNR, SSIM, LPIPS)",
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("estimate", nargs="?", help="estimated trajectory: TUM file (cam0 T_wc) or run "
                   "output folder holding trajectory.tum")
    p.add_argument("--gt", help="ground truth: TUM file or dataset path (EuRoC/TUM/KITTI folder, bag, MCAP)")
    p.add_argument("--gt-frame", choices=("camera", "body"), default=None,
                   help="what GT poses describe (TUM default: camera; datasets: as the loader says)")
    p.add_argument("--calib", help="calibration YAML giving T_bc (for --gt-frame body; for datasets "
                   "it overrides the calibration the source carries)")
    p.add_argument("--image-topic", help="bag/MCAP image topic (datasets only)")
    p.add_argument("--gt-topic", help="bag/MCAP ground-truth topic (datasets only)")
    p.add_argument("--imu-topic", help="bag/MCAP IMU topic, when it has several (datasets only)")
    p.add_argument("--camera-info-topic", help="bag/MCAP CameraInfo topic (datasets only)")
    p.add_argument("--max-dt-ms", type=float, default=10.0,
                   help="max time offset (ms) between an estimate stamp and ground truth (default 10)")
    p.add_argument("--no-interpolate", action="store_true",
                   help="use the nearest GT sample only (no SLERP interpolation of denser GT)")
    p.add_argument("--rpe-lengths", help="comma-separated RPE segment lengths in metres "
                   "(default: chosen from the path length, see docs/evaluation.md)")
    p.add_argument("--rpe-no-scale", action="store_true",
                   help="do not correct the estimate's scale (Sim(3)) before RPE")
    p.add_argument("--write-metrics", action="store_true",
                   help="when ESTIMATE is a run folder, merge ATE/scale/RPE into its metrics.json")
    p.add_argument("--plots", metavar="DIR", help="write trajectory.png, error.png and rpe.png (docs/report.md) to DIR")
    p.add_argument("--images", nargs=2, metavar=("RENDERS_DIR", "REFERENCE_DIR"),
                   help="PSNR/SSIM between images of the same file name in two folders")
    p.add_argument("--lpips-weights", help="local LPIPS state-dict file (enables LPIPS for --images)")
    p.add_argument("--json", action="store_true", help="print one JSON object as the last line")
    p.set_defaults(func=run)


# ------------------------------------------------------------------------------- trajectories


def _resolve_estimate(arg: str) -> tuple[Path, Optional[Path]]:
    from vings_core.eval.output import TRAJECTORY_FILE

    p = Path(arg)
    if p.is_dir():
        t = p / TRAJECTORY_FILE
        if not t.is_file():
            raise InputError(f"{p}: folder has no {TRAJECTORY_FILE} (expected a run output folder)")
        return t, p
    if not p.exists():
        raise InputError(f"{p}: estimated trajectory not found")
    return p, None


def _t_bc_from_calib(path: str):
    from vings_core.io.calib_yaml import read_calibration_parts

    if not Path(path).is_file():
        raise InputError(f"{path}: calibration file not found")
    parts = read_calibration_parts(path)
    if parts.T_bc is None:
        raise InputError(f"{path}: calibration gives no camera-to-body extrinsic (T_bc)")
    return parts.T_bc


def load_ground_truth(gt_arg: str, gt_frame: Optional[str] = None, calib: Optional[str] = None,
                      image_topic: Optional[str] = None, gt_topic: Optional[str] = None,
                      imu_topic: Optional[str] = None, camera_info_topic: Optional[str] = None):
    """Ground truth as cam0 ``T_wc``: returns ``(Trajectory, info dict)``."""
    from vings_core.trajectory_io import read_tum

    p = Path(gt_arg)
    if not p.exists():
        raise InputError(f"{p}: ground truth not found")
    if p.is_file() and p.suffix.lower() not in DATASET_SUFFIXES:
        try:
            traj = read_tum(p)
        except InputError as e:
            if "got 12" in str(e):  # KITTI poses.txt: no stamps in the file itself
                raise InputError(f"{e} (a KITTI poses file? pass the sequence folder with times.txt "
                                 "and calib.txt as --gt)") from None
            raise
        frame = gt_frame or "camera"
        if calib and gt_frame is None:
            print(f"vings eval: warning: --calib has no effect on {p.name}: a TUM file is taken as "
                  "camera poses; pass --gt-frame body if it holds body (IMU) poses", file=sys.stderr)
        if frame == "body":
            if not calib:
                raise InputError(f"{p}: --gt-frame body needs --calib FILE giving T_bc")
            traj = traj.right_multiply(_t_bc_from_calib(calib))
        return traj, {"ground_truth": str(p), "gt_source": "tum", "gt_frame": frame}
    try:
        from vings_core.io import open_source
        from vings_core.io.base import SourceOptions
    except ImportError as e:
        raise InputError(f"{p}: reading ground truth from a dataset needs vings_core.io.open_source "
                         f"({e})") from None
    src = open_source(str(p), SourceOptions(image_topic=image_topic, gt_topic=gt_topic, calib_file=calib,
                                            imu_topic=imu_topic, camera_info_topic=camera_info_topic))
    if src.ground_truth is None or len(src.ground_truth) == 0:
        raise InputError(f"{p}: dataset has no ground truth")
    if gt_frame is not None:
        src.gt_frame = gt_frame
    traj = src.gt_camera_trajectory()
    return traj, {"ground_truth": str(p), "gt_source": src.kind, "gt_frame": src.gt_frame}


def _parse_lengths(text: Optional[str]) -> Optional[list[float]]:
    if text is None:
        return None
    try:
        vals = [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise InputError(f"--rpe-lengths: expected comma-separated metres, got {text!r}") from None
    if not vals or any(not (0 < v < float("inf")) for v in vals):
        raise InputError(f"--rpe-lengths: lengths must be positive and finite, got {text!r}")
    return vals


def eval_trajectory_cli(args: argparse.Namespace) -> dict:
    from vings_core.eval.output import TRAJECTORY_METRIC_KEYS, RunOutput
    from vings_core.eval.traj import evaluate_trajectory
    from vings_core.trajectory_io import read_tum

    if not args.gt:
        raise InputError("--gt is required to evaluate a trajectory (TUM file or dataset path)")
    if not (0 <= args.max_dt_ms <= 1e9):    # 1e6 s: beyond any recording; int64 ns stay far from overflow
        raise InputError(f"--max-dt-ms must be in [0, 1e9] ms, got {args.max_dt_ms}")
    est_path, run_dir = _resolve_estimate(args.estimate)
    est = read_tum(est_path)
    gt, info = load_ground_truth(args.gt, args.gt_frame, args.calib, args.image_topic, args.gt_topic,
                                 args.imu_topic, args.camera_info_topic)
    res = evaluate_trajectory(est, gt, max_dt_ns=int(round(args.max_dt_ms * 1e6)),
                              rpe_lengths_m=_parse_lengths(args.rpe_lengths),
                              interpolate=not args.no_interpolate,
                              rpe_correct_scale=not args.rpe_no_scale)
    out = {"estimate": str(est_path), **info, **res}
    if args.plots:
        from vings_core.report.build import trajectory_plots
        from vings_core.util import atomic_write_bytes
        d = Path(args.plots)
        if d.exists() and not d.is_dir():
            raise InputError(f"--plots {d}: exists and is not a folder")
        written = []
        for name, png in trajectory_plots(est, gt, res.get("rpe")).items():
            atomic_write_bytes(d / name, png)
            written.append(str(d / name))
        out["plots"] = written
    if args.write_metrics:
        if run_dir is None:
            raise InputError("--write-metrics needs ESTIMATE to be a run output folder")
        RunOutput(run_dir).update_metrics({k: res[k] for k in TRAJECTORY_METRIC_KEYS})
        out["metrics_written"] = str(RunOutput(run_dir).metrics_path)
    return out


# ------------------------------------------------------------------------------------- images


def _read_image(path: Path):
    import cv2
    import numpy as np

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise InputError(f"{path}: cannot read image")
    if img.dtype == np.uint16:
        img = img.astype(np.float64) / 65535.0
    elif img.dtype != np.uint8:
        raise InputError(f"{path}: unsupported image dtype {img.dtype}")
    if img.ndim == 3:
        img = img[..., :3][..., ::-1]  # BGR(A) -> RGB
        if img.shape[2] != 3:
            raise InputError(f"{path}: expected 1, 3 or 4 channels, got {img.shape[2]}")
    return np.ascontiguousarray(img)


def eval_images(dir_a: str, dir_b: str, lpips_weights: Optional[str] = None) -> dict:
    """Mean PSNR/SSIM (and LPIPS with a weights file) over images with the same stem in both folders."""
    import numpy as np

    from vings_core.eval.image import psnr, ssim
    from vings_core.eval.output import RUN_RENDER_PREFIX

    a, b = Path(dir_a), Path(dir_b)
    for d in (a, b):
        if not d.is_dir():
            raise InputError(f"{d}: image folder not found")

    def listing(d: Path) -> dict:
        out: dict = {}
        for f in sorted(d.iterdir()):
            if f.suffix.lower() in IMAGE_SUFFIXES:
                # the runner's renders are kf_<stamp>.png; recordings name frames <stamp>.png
                key = f.stem[len(RUN_RENDER_PREFIX):] if f.stem.startswith(RUN_RENDER_PREFIX) else f.stem
                if key in out:     # which one would be compared must not depend on the sort order
                    raise InputError(f"{d}: {out[key].name} and {f.name} share the name "
                                     f"{key!r}; keep one image per name")
                out[key] = f
        return out

    la, lb = listing(a), listing(b)
    common = sorted(set(la) & set(lb))
    if not common:
        raise InputError(f"no images with the same name in {a} ({len(la)} images) and {b} "
                         f"({len(lb)} images)")
    lp = None
    if lpips_weights:
        from vings_core.eval.lpips import load_lpips
        lp = load_lpips(lpips_weights)
    per = []
    for name in common:
        ia, ib = _read_image(la[name]), _read_image(lb[name])
        if ia.shape != ib.shape:
            raise InputError(f"{la[name]} has shape {ia.shape} but {lb[name]} has {ib.shape}")
        rec = {"name": name, "psnr_db": psnr(ia, ib), "ssim": ssim(ia, ib)}
        if lp is not None:
            rec["lpips"] = lp.distance(ia, ib)
        per.append(rec)
    ps = np.array([r["psnr_db"] for r in per])
    finite = ps[np.isfinite(ps)]  # identical images have PSNR inf: counted, left out of the mean
    return {
        "images": len(per),
        "psnr_db": float(finite.mean()) if len(finite) else None,
        "identical_images": int(len(ps) - len(finite)),
        "ssim": float(np.mean([r["ssim"] for r in per])),
        "lpips": float(np.mean([r["lpips"] for r in per])) if lp is not None else None,
        "only_in_first": len(set(la) - set(lb)), "only_in_second": len(set(lb) - set(la)),
        "per_image": [{k: (None if isinstance(v, float) and not math.isfinite(v) else v)
                       for k, v in r.items()} for r in per],
    }


# ---------------------------------------------------------------------------------------- run


def _fmt(v: Any, unit: str = "", prec: int = 4) -> str:
    return "n/a" if v is None else f"{v:.{prec}g}{unit}"


def _print_human(out: dict) -> None:
    if "ate_sim3_m" in out:
        print(f"estimate:       {out['estimate']} ({out['estimate_poses']} poses)")
        print(f"ground truth:   {out['ground_truth']} ({out['gt_source']}, {out['gt_frame']} frame, "
              f"{out['gt_poses']} poses)")
        print(f"matched poses:  {out['matched_poses']} ({out['interpolated_poses']} interpolated, "
              f"max dt {out['max_match_dt_ms']:.3g} ms), {out['duration_s']:.2f} s, "
              f"GT path {out['path_length_m']:.2f} m")
        print(f"ATE Sim(3):     {_fmt(out['ate_sim3_m'], ' m')} RMSE (scale {out['sim3_scale']:.6g})")
        print(f"ATE SE(3):      {_fmt(out['ate_se3_m'], ' m')} RMSE")
        r = out["rpe"]
        if r is None:
            print("RPE:            n/a (path too short for any segment length)")
        else:
            print(f"RPE:            {r['trans_pct']:.4g} % , {r['rot_deg_per_m']:.4g} deg/m "
                  f"(mean over {r['pairs']} pairs{', scale-corrected' if r['scale_corrected'] else ''})")
            for L, v in r["per_length"].items():
                print(f"  {L:>5} m:      {v['trans_pct']:.4g} %, {v['rot_deg_per_m']:.4g} deg/m "
                      f"({v['pairs']} pairs)")
        if "metrics_written" in out:
            print(f"metrics:        updated {out['metrics_written']}")
    if "images" in out:
        im = out["images"]
        print(f"images:         {im['images']} pairs: PSNR {_fmt(im['psnr_db'], ' dB')}, "
              f"SSIM {_fmt(im['ssim'])}, LPIPS {_fmt(im['lpips'])}"
              + (f" ({im['identical_images']} identical, PSNR inf, left out of the mean)"
                 if im["identical_images"] else ""))


def run(args: argparse.Namespace) -> int:
    if args.estimate is None and args.images is None:
        raise InputError("nothing to evaluate: give an estimated trajectory (with --gt) and/or "
                         "--images RENDERS_DIR REFERENCE_DIR")
    if args.lpips_weights and not args.images:
        raise InputError("--lpips-weights needs --images")
    out: dict = {}
    if args.estimate is not None:
        out.update(eval_trajectory_cli(args))
    if args.images:
        out["images"] = eval_images(args.images[0], args.images[1], args.lpips_weights)
    if args.json:
        print(json.dumps(out, allow_nan=False))
    else:
        _print_human(out)
    return 0
