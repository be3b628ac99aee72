"""`vings launch`: start the VINGS node graph (front end + mapper + loop closer + eraser [+ recorder]) as
processes."""
from __future__ import annotations

import argparse
from pathlib import Path


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "launch", help="start the node graph (frontend_node, mapper_node, loop_closer_node, eraser_node) "
                       "as processes",
        description="Start frontend_node, mapper_node, loop_closer_node and eraser_node (and with "
                    "--record a recorder) as separate "
                    "processes with the shipped Fast DDS shared-memory profile, report a node that "
                    "dies, and stop everything cleanly on Ctrl-C. Feed it with `vings replay` or a "
                    "live camera publishing /camera/image_raw + /camera/camera_info.")
    p.add_argument("--params", metavar="FILE", help="ROS 2 params YAML (default: params/vings.yaml "
                   "of the package)")
    p.add_argument("--record", metavar="OUT.mcap", help="record every output topic to this MCAP file")
    p.add_argument("--rerun", metavar="OUT.rrd", help="log poses, keyframe images, renders, depth and map "
                   "points for the rerun viewer (rerun_node; optional extra: pip install '.[viz]')")
    p.add_argument("--use-sim-time", action="store_true",
                   help="nodes follow /clock (set this when replaying a recording)")
    p.add_argument("--domain-id", type=int, default=None, help="ROS_DOMAIN_ID for the graph")
    p.add_argument("--checkpoint", metavar="FILE",
                   help="mapper checkpoint: resumed from at start if it exists, written periodically "
                        "and on shutdown (overrides mapper_node.checkpoint_path); the loop closer's "
                        "database goes beside it as FILE.loop (loop_closer_node.checkpoint_path), the "
                        "front end's window and poses as FILE.frontend (frontend_node.checkpoint_path)")
    p.add_argument("--no-mapper", action="store_true", help="leave the mapper out (front end alone)")
    p.add_argument("--no-loop", action="store_true",
                   help="leave the loop closer out (loop.enabled false: no loop closure, no retrain)")
    p.add_argument("--no-eraser", action="store_true",
                   help="leave the dynamic eraser out (eraser.enabled false: no masks, the mapper "
                        "does not wait for them)")
    p.add_argument("--backpressure", action="store_true",
                   help="front end queue policy 'backpressure' (use with `vings replay --wait-for-graph`)")
    p.add_argument("--no-imu", action="store_true",
                   help="visual-only front end: do not fuse the IMU (vio.enabled false)")
    p.add_argument("--nodes", metavar="NAME,...",
                   help="start only these nodes (registry names, e.g. mapper_node on a second host; "
                        "default: frontend_node, mapper_node, loop_closer_node, eraser_node)")
    p.add_argument("-p", "--param", action="append", default=[], metavar="SECTION.KEY=VALUE",
                   help="override one parameter of every node, e.g. -p mapping.iters_per_keyframe=20")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from vings_core.errors import ConfigError

    from ..launch import Launcher, LaunchOptions, default_nodes
    from ..params import default_params_file

    extra = {}
    for item in args.param:
        key, sep, val = item.partition("=")
        if not sep or "." not in key:
            raise ConfigError(f"-p {item!r}: expected SECTION.KEY=VALUE")
        extra[key] = val
    if args.backpressure:
        extra["frontend_node.queue_policy"] = "backpressure"
    if args.no_imu:
        extra["vio.enabled"] = "false"
    if args.no_loop:
        extra["loop.enabled"] = "false"
    if args.no_eraser:
        extra["eraser.enabled"] = "false"
    if args.checkpoint:
        extra.setdefault("frontend_node.checkpoint_path", str(Path(args.checkpoint).resolve()) + ".frontend")
    if args.checkpoint and not args.no_loop:
        extra.setdefault("loop_closer_node.checkpoint_path", str(Path(args.checkpoint).resolve()) + ".loop")
    left_out = {n for n, off in (("mapper_node", args.no_mapper), ("loop_closer_node", args.no_loop),
                                 ("eraser_node", args.no_eraser)) if off}
    nodes = tuple(n for n in default_nodes() if n not in left_out) if left_out else None
    if args.nodes:
        nodes = tuple(n.strip() for n in args.nodes.split(",") if n.strip() and n.strip() not in left_out)
        if not nodes:
            raise ConfigError(f"--nodes {args.nodes!r}: no node left to start")
        from .. import registry
        known = [n.name for n in registry.NODES]
        bad = [n for n in nodes if n not in known]
        if bad:
            raise ConfigError(f"--nodes: unknown node(s) {', '.join(bad)}; known: {', '.join(known)}")
    opt = LaunchOptions(params_file=args.params or str(default_params_file()), record=args.record, rerun=args.rerun,
                        use_sim_time=args.use_sim_time, domain_id=args.domain_id,
                        checkpoint=args.checkpoint, extra_params=extra, nodes=nodes)
    return Launcher(opt).run()
