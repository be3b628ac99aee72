"""Register the package in the ament index of a prefix, as a colcon/ament install would, so that ROS
tools find it: ``python -m vings_ros.ament_install [PREFIX]`` (default: the running Python's prefix,
the virtual environment; ``make install`` runs it).

Writes under ``PREFIX``:

* ``share/ament_index/resource_index/packages/vings_ros`` (the marker ``ament_index_python`` looks
  for on ``AMENT_PREFIX_PATH``);
* ``share/vings_ros/package.xml`` and ``share/vings_ros/params/*.yaml``;
* ``lib/vings_ros/<node>`` for every node of :mod:`vings_ros.registry`: an executable that runs the
  node with this Python (where ``ros2 run vings_ros <node>`` looks).

Every file is written atomically; running it again replaces them (nothing else is touched).
"""
from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import Optional

from vings_core.util import atomic_write_bytes, atomic_write_text

from . import registry

PACKAGE = "vings_ros"
REPO = Path(__file__).resolve().parent.parent


def _source_file(rel: str) -> Path:
    """A file of the package's source tree (editable install) or of its installed share folder."""
    for base in (REPO, Path(sys.prefix) / "share" / PACKAGE):
        if (base / rel).is_file():
            return base / rel
    raise FileNotFoundError(f"{rel} not found in {REPO} or {Path(sys.prefix) / 'share' / PACKAGE}")


def install(prefix: Optional[str | os.PathLike] = None) -> list[Path]:
    """Write the ament index entries and node executables under ``prefix`` (module doc); returns
    the paths written."""
    prefix = Path(prefix or sys.prefix).resolve()
    out = []
    marker = prefix / "share" / "ament_index" / "resource_index" / "packages" / PACKAGE
    atomic_write_text(marker, "")
    out.append(marker)
    share = prefix / "share" / PACKAGE
    atomic_write_bytes(share / "package.xml", _source_file("package.xml").read_bytes())
    out.append(share / "package.xml")
    params = REPO / "params"
    for y in sorted(params.glob("*.yaml")) if params.is_dir() else []:
        atomic_write_bytes(share / "params" / y.name, y.read_bytes())
        out.append(share / "params" / y.name)
    for spec in registry.NODES:
        exe = prefix / "lib" / PACKAGE / spec.name
        atomic_write_text(exe, f"#!{sys.executable}\n# {spec.name} of {PACKAGE} (ros2 run {PACKAGE} {spec.name})\n"
                               f"import sys\nfrom {spec.module} import main\nsys.exit(main())\n")
        exe.chmod(0o755)
        out.append(exe)
    return out


def main(argv: Optional[list[str]] = None) -> int:
    args = list(sys.argv[1:] if argv is None else argv)
    if len(args) > 1 or (args and args[0].startswith("-")):
        print("usage: python -m vings_ros.ament_install [PREFIX]", file=sys.stderr)
        return 2
    paths = install(args[0] if args else None)
    print(f"{PACKAGE}: registered in the ament index of {Path(args[0] if args else sys.prefix).resolve()} "
          f"({len(paths)} files; add it to AMENT_PREFIX_PATH)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
