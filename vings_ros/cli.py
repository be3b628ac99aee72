"""The `vings` command: ``vings <subcommand> ...``.

Each subcommand lives in ``vings_ros/commands/<name>.py`` and exposes ``register(subparsers)``, which
adds its parser and sets ``func`` to a callable ``(args) -> int``. Heavy imports happen inside the
subcommand, so ``vings --help`` is fast. A :class:`~vings_core.errors.VingsError` is printed as a
one-line error (exit 2), never as a traceback.
"""
from __future__ import annotations

import argparse
import importlib
import sys
from typing import Optional, Sequence

SUBCOMMANDS = ("sim", "info", "eval", "run", "report", "replay", "launch")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="vings", description="VINGS-ROS: monocular (visual-inertial) "
                                "2D Gaussian-splatting SLAM. Run `vings <command> --help`.")
    p.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = p.add_subparsers(dest="command", metavar="<command>")
    for name in SUBCOMMANDS:
        try:
            mod = importlib.import_module(f"vings_ros.commands.{name}")
        except ModuleNotFoundError as e:
            if e.name == f"vings_ros.commands.{name}":
                continue  # not delivered yet
            raise
        mod.register(sub)
    return p


def main(argv: Optional[Sequence[str]] = None) -> int:
    from vings_core.errors import VingsError
    from vings_core.util import setup_logging

    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 1
    setup_logging(args.verbose)
    try:
        return int(args.func(args) or 0)
    except VingsError as e:
        print(f"vings {args.command}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"vings {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
