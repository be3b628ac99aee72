"""`vings sim`: render a synthetic photo-textured sequence (EuRoC/ASL folder + ROS 2 MCAP)."""
from __future__ import annotations

import argparse
import json

from .argtypes import image_side, int_at_least


def _interval(text: str) -> tuple[float, float]:
    """``T0:T1`` seconds, 0 <= T0 < T1."""
    try:
        a, b = (float(v) for v in text.split(":"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected T0:T1 in seconds (e.g. 2:3), got {text!r}") from None
    if not (0 <= a < b < float("inf")):
        raise argparse.ArgumentTypeError(f"need 0 <= T0 < T1, got {text!r}")
    return a, b


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "sim", help="generate a synthetic sequence (room or street) with exact ground truth",
        description="Ray-cast a photo-textured scene along a smooth trajectory and write an "
                    "EuRoC/ASL folder (images, 200 Hz IMU, body ground truth, depth, dynamic masks) "
                    "plus a ROS 2 MCAP. Prints a JSON summary (also saved as OUT/sim.json).",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--scene", choices=("room", "street"), default="room",
                   help="room: indoor handheld motion; street: driving on a city grid")
    p.add_argument("--out", required=True, help="output folder (replaced if it holds an earlier "
                   "simulator output)")
    p.add_argument("--frames", type=int, default=None,
                   help="camera frames (default: room 300; street: the whole route)")
    p.add_argument("--length-m", type=float, default=None,
                   help="street route length in metres (default 400; >= 50)")
    p.add_argument("--loop", action="store_true",
                   help="street: closed route that ends exactly at its start")
    p.add_argument("--retrace", type=float, default=None, metavar="F",
                   help="street, with --loop: after closing the loop, drive fraction F (0 < F <= 1) "
                        "of it again over the same lanes (a second pass; sim.json 'revisit' gives its times)")
    p.add_argument("--route", choices=("handheld", "return", "oneway"), default=None,
                   help="room: handheld (default) wanders around; return walks a lap of the room and "
                        "ends at the start pose; oneway turns round at one end of the room and walks "
                        "to the other, never re-seeing its first views")
    p.add_argument("--dynamic", action="store_true", help="add moving objects (and their masks)")
    p.add_argument("--fps", type=float, default=20.0, help="camera rate (Hz, divides 200)")
    p.add_argument("--width", type=image_side, default=376, help="image width (px)")
    p.add_argument("--height", type=image_side, default=240, help="image height (px)")
    p.add_argument("--seed", type=int_at_least(0), default=0, help="seed of scene, motion and IMU noise (>= 0)")
    p.add_argument("--no-noise", action="store_true", help="exact IMU: no noise, zero biases")
    p.add_argument("--no-mcap", action="store_true", help="skip the ROS 2 MCAP")
    p.add_argument("--slow-start", type=float, default=0.0, metavar="S",
                   help="start from rest and reach the scene's own speed after S seconds")
    p.add_argument("--speed-factor", type=float, default=1.0, metavar="F",
                   help="play the motion F times faster (street at 2.5: 21-29 m/s, highway speed)")
    p.add_argument("--blind", type=_interval, default=None, metavar="T0:T1",
                   help="lens covered from T0 to T1 seconds after the first frame (black images)")
    p.add_argument("--imu-rate", type=float, default=200.0, metavar="HZ",
                   help="IMU rate (Hz, divides 200)")
    p.add_argument("--imu-td", type=float, default=0.0, metavar="S",
                   help="camera-IMU time offset: readings stamped t + S (t_imu = t_cam + td)")
    p.add_argument("--imu-drop", type=float, default=0.0, metavar="F",
                   help="fraction of IMU readings dropped at random")
    p.add_argument("--imu-gap", type=_interval, action="append", default=[], metavar="T0:T1",
                   help="no IMU readings from T0 to T1 seconds after the first frame (repeatable)")
    p.add_argument("--progress", action="store_true", help="show a progress bar")
    p.set_defaults(func=run)


def run(args) -> int:
    from vings_core.sim import generate, load_summary
    from vings_core.sim.sequence import ImuStreamOptions

    out = generate(args.scene, args.out, frames=args.frames, width=args.width, height=args.height,
                   seed=args.seed, dynamic=args.dynamic, loop=args.loop, length_m=args.length_m,
                   mcap=not args.no_mcap, fps=args.fps, noise=not args.no_noise,
                   progress=args.progress, blind=args.blind, slow_start_s=args.slow_start,
                   speed_factor=args.speed_factor, retrace=args.retrace, route=args.route,
                   imu=ImuStreamOptions(args.imu_rate, args.imu_td, args.imu_drop, tuple(args.imu_gap)))
    print(json.dumps(load_summary(out), indent=2))
    return 0
