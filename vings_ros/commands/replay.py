"""``vings replay SOURCE``: publish a recording on the live input topics (see vings_ros/replay.py)."""
from __future__ import annotations

import argparse
import json
import signal
import sys


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "replay", help="publish a recording on /camera/image_raw, /camera/camera_info, /imu/data, /clock",
        description="Publish a recording (EuRoC/TUM/KITTI folder, ROS 1/2 bag, MCAP) on the VINGS input "
        "topics with its original stamps, and /clock at sensor time. With --wait-for-graph each image "
        "waits for the front end's acknowledgement on /vings/frontend/processed (std_msgs/Header "
        "with the image's stamp), so no frame is dropped however slow the graph is. Uses the "
        "shared-memory Fast DDS profile unless VINGS_DDS=udp.")
    p.add_argument("source", help="dataset folder, .bag, .mcap or ROS 2 bag folder")
    p.add_argument("--rate", type=float, default=1.0,
                   help="playback speed as a multiple of real time; 0 = as fast as possible (default 1)")
    p.add_argument("--topics", default="", metavar="KEY=TOPIC,...",
                   help="output topic names, keys image, camera_info, imu, clock, processed "
                   "(default image=/camera/image_raw,camera_info=/camera/camera_info,imu=/imu/data,"
                   "clock=/clock,processed=/vings/frontend/processed)")
    p.add_argument("--wait-for-graph", action="store_true",
                   help="back-pressure: wait for the front end's acknowledgement of every image")
    p.add_argument("--ack-timeout", type=float, default=60.0, metavar="S",
                   help="seconds to wait for one acknowledgement before failing (default 60)")
    p.add_argument("--respawn-wait", type=float, default=30.0, metavar="S",
                   help="with --wait-for-graph: seconds to wait for a front end that went away (vings "
                   "launch respawns it) before failing; the image it lost is sent again (default 30; "
                   "0: fail at once)")
    p.add_argument("--startup-timeout", type=float, default=30.0, metavar="S",
                   help="seconds to wait at start for subscribers (default 30; with --wait-for-graph "
                   "not finding them is an error, otherwise a warning)")
    p.add_argument("--no-wait", action="store_true",
                   help="start publishing at once, without waiting for subscribers")
    p.add_argument("--loop", action="store_true",
                   help="start again at the end (original stamps: /clock jumps back); stop with Ctrl-C")
    p.add_argument("--loop-shift", action="store_true",
                   help="with --loop: shift every pass's stamps past the previous pass's, so a graph "
                   "that drops stamps that do not increase (the VINGS front end) processes every pass")
    p.add_argument("--start", type=float, default=0.0, metavar="S",
                   help="skip the frames of the first S seconds (from the first frame)")
    p.add_argument("--duration", type=float, default=None, metavar="D",
                   help="publish only the frames of D seconds (after --start)")
    p.add_argument("--imu-lead", type=float, default=1.0, metavar="S",
                   help="also publish the IMU samples of S seconds before the first frame "
                   "(default 1); IMU after the last frame is never published")
    p.add_argument("--no-clock", action="store_true", help="do not publish /clock")
    p.add_argument("--camera-frame", default=None,
                   help="frame_id of images and camera_info (default camera_optical_frame)")
    p.add_argument("--imu-frame", default=None, help="frame_id of IMU messages (default imu_link)")
    p.add_argument("--domain-id", type=int, default=None, help="ROS_DOMAIN_ID (default: environment)")
    p.add_argument("--publish-log", metavar="CSV", default=None,
                   help="write 'stamp_ns,publish_wall_ns' of every image (publish-to-output latency)")
    p.add_argument("--json", action="store_true", help="print the final statistics as JSON on stdout")
    from .info import add_source_arguments
    add_source_arguments(p)
    p.set_defaults(func=run)


def _sigterm(signum, frame):  # a launcher's SIGTERM stops like Ctrl-C: clean DDS shutdown
    raise KeyboardInterrupt


def run(args: argparse.Namespace) -> int:
    from vings_core.io import open_source

    from ..replay import ReplayOptions, Replayer, parse_topics
    from ..ros_env import apply_ros_environment
    from .info import source_options

    opts = ReplayOptions(rate=args.rate, topics=parse_topics(args.topics),
                         wait_for_graph=args.wait_for_graph, wait_subscribers=not args.no_wait,
                         startup_timeout_s=args.startup_timeout, ack_timeout_s=args.ack_timeout,
                         respawn_wait_s=args.respawn_wait,
                         loop=args.loop, loop_shift=args.loop_shift, start_s=args.start, duration_s=args.duration,
                         imu_lead_s=args.imu_lead,
                         publish_clock=not args.no_clock, publish_log=args.publish_log)
    if args.camera_frame:
        opts.camera_frame = args.camera_frame
    if args.imu_frame:
        opts.imu_frame = args.imu_frame
    opts.validate()
    source = open_source(args.source, source_options(args))
    for w in getattr(source, "warnings", []) or []:
        print(f"replay: note: {w}", file=sys.stderr)
    apply_ros_environment(domain_id=args.domain_id)
    if signal.getsignal(signal.SIGTERM) is signal.SIG_DFL:
        signal.signal(signal.SIGTERM, _sigterm)
    stats = Replayer(source, opts).run()
    print(stats.summary(), file=sys.stderr, flush=True)
    if args.json:
        print(json.dumps(stats.as_dict()), flush=True)
    if stats.interrupted and not args.loop:
        return 130
    return 0
