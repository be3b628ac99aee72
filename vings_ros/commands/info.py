"""``vings info PATH``: what a recording holds (frames, IMU, rates, resolution, calibration, GT)."""
from __future__ import annotations

import argparse
import json

from .argtypes import image_side, int_at_least


def add_source_arguments(p: argparse.ArgumentParser) -> None:
    """The options of :class:`vings_core.io.SourceOptions` (shared by commands that open data)."""
    g = p.add_argument_group("input")
    g.add_argument("--image-topic", help="bag image topic (default: the only Image/CompressedImage topic)")
    g.add_argument("--imu-topic", help="bag IMU topic (default: the only Imu topic)")
    g.add_argument("--camera-info-topic", help="bag CameraInfo topic (default: detected)")
    g.add_argument("--gt-topic", help="bag ground-truth pose topic (default: /ground_truth/pose if present)")
    g.add_argument("--calib", metavar="FILE", help="calibration YAML overriding the recording's "
                   "(EuRoC/Kalibr/ROS camera_info/ORB-SLAM/VINGS layouts; or tum-fr1|tum-fr2|tum-fr3)")
    g.add_argument("--width", type=image_side, help="working width in pixels (default: native)")
    g.add_argument("--height", type=image_side, help="working height in pixels (default: native)")
    g.add_argument("--no-undistort", action="store_true", help="keep lens distortion")
    g.add_argument("--max-frames", type=int_at_least(1), help="use at most this many frames")
    g.add_argument("--on-bad-frame", choices=("skip", "abort"), default="skip",
                   help="a frame that cannot be decoded: skip and count it (default, as the nodes do) or stop")


def source_options(args: argparse.Namespace):
    from vings_core.io import SourceOptions
    return SourceOptions(width=args.width, height=args.height, undistort=not args.no_undistort,
                         image_topic=args.image_topic, imu_topic=args.imu_topic,
                         camera_info_topic=args.camera_info_topic, gt_topic=args.gt_topic,
                         calib_file=args.calib, max_frames=args.max_frames,
                         on_bad_frame=getattr(args, "on_bad_frame", "skip"))


def register(subparsers) -> None:
    p = subparsers.add_parser("info", help="summarise a recording (EuRoC, TUM, KITTI, bag, MCAP)",
                              description="Print what a recording holds: frames, IMU samples, "
                              "rates, resolution, calibration and ground-truth span.")
    p.add_argument("path", help="dataset folder, .bag, .mcap or ROS 2 bag folder")
    p.add_argument("--json", action="store_true", help="print JSON (Source.info()) instead of text")
    p.add_argument("--check", action="store_true",
                   help="decode every frame and report those that cannot be decoded (exit 1 if any)")
    add_source_arguments(p)
    p.set_defaults(func=run)


def _fmt_rate(v) -> str:
    return f"{v:.3f} Hz" if v else "-"


def format_info(info: dict) -> str:
    """Human-readable summary of ``Source.info()``."""
    lines = [f"{info['path']}  [{info['kind']}{' - ' + info['format'] if info.get('format') else ''}]"]
    lines.append(f"  frames      : {info['frames']}  rate {_fmt_rate(info['frame_rate_hz'])}  "
                 f"duration {info['duration_s']:.3f} s")
    if info["frames"]:
        lines.append(f"                first {info['first_stamp_ns']} ns, last {info['last_stamp_ns']} ns")
    if info.get("resolution"):
        nat = info.get("native_resolution")
        lines.append(f"  resolution  : {info['resolution'][0]}x{info['resolution'][1]}"
                     + (f" (native {nat[0]}x{nat[1]})" if nat and nat != info["resolution"] else ""))
    lines.append(f"  IMU samples : {info['imu_samples']}  rate {_fmt_rate(info['imu_rate_hz'])}"
                 + (f"  duration {info['imu_duration_s']:.3f} s" if info["imu_samples"] else ""))
    cal = info.get("calibration")
    if cal and cal.get("camera"):
        c = cal["camera"]
        lines.append(f"  camera      : fx {c['fx']:.3f} fy {c['fy']:.3f} cx {c['cx']:.3f} cy {c['cy']:.3f} "
                     f"distortion {c['distortion_model']}"
                     + (f" {c['distortion']}" if c["distortion"] else ""))
        t = cal["T_bc"]
        lines.append(f"  T_bc        : translation [{t[0][3]:.4f}, {t[1][3]:.4f}, {t[2][3]:.4f}] m"
                     + ("  (identity)" if all(abs(t[i][j] - (i == j)) < 1e-12 for i in range(4)
                                          for j in range(4)) else ""))
        if cal.get("has_imu"):
            lines.append(f"  IMU noise   : gyro {cal['gyro_noise_density']:.4g} rad/s/sqrt(Hz), walk "
                         f"{cal['gyro_random_walk']:.4g}; accel {cal['accel_noise_density']:.4g} "
                         f"m/s^2/sqrt(Hz), walk {cal['accel_random_walk']:.4g}")
    else:
        lines.append("  camera      : none")
        if cal and cal.get("has_imu"):
            lines.append(f"  IMU noise   : gyro {cal['gyro_noise_density']:.4g} rad/s/sqrt(Hz), walk "
                         f"{cal['gyro_random_walk']:.4g}; accel {cal['accel_noise_density']:.4g} "
                         f"m/s^2/sqrt(Hz), walk {cal['accel_random_walk']:.4g}")
    if info.get("calibration_from"):
        lines.append(f"  calibration : from {info['calibration_from']}")
    gt = info.get("ground_truth")
    if gt:
        lines.append(f"  ground truth: {gt['poses']} poses of the {gt['frame']}, {gt['duration_s']:.3f} s, "
                     f"path {gt['path_length_m']:.3f} m")
    else:
        lines.append("  ground truth: none")
    if info.get("topics_used"):
        used = ", ".join(f"{k} {v}" for k, v in info["topics_used"].items() if v)
        lines.append(f"  topics used : {used or 'none'}")
    if info.get("topics"):
        lines.append("  topics      :")
        for name, t in sorted(info["topics"].items()):
            lines.append(f"    {name}  {t['type']}  {t['count']} msgs")
    for extra in ("has_depth", "has_mask"):
        if info.get(extra):
            lines.append(f"  {extra.replace('has_', ''):<12}: yes")
    for w in info.get("warnings", []):
        lines.append(f"  warning     : {w}")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    from vings_core.io import open_source
    from vings_core.util import _json_default

    src = open_source(args.path, source_options(args))
    info = src.info()
    if args.check:
        decoded = sum(1 for _ in src.frames())
        bad = list(getattr(src, "bad_frames", []))
        info["check"] = {"frames_decoded": decoded, "frames_bad": len(bad), "bad": bad}
    if args.json:
        print(json.dumps(info, indent=2, default=_json_default))
    else:
        print(format_info(info))
        if args.check:
            c = info["check"]
            print(f"  check       : {c['frames_decoded']} frames decoded, {c['frames_bad']} could not be")
            for b in c["bad"][:20]:
                print(f"                {b}")
            if len(c["bad"]) > 20:
                print(f"                ... and {len(c['bad']) - 20} more")
    return 1 if args.check and info["check"]["frames_bad"] else 0
