"""Format detection and :func:`open_source`, the one entry point to every loader."""
from __future__ import annotations

import os
from pathlib import Path
from typing import Optional

from ..errors import InputError
from .base import Source, SourceOptions
from .euroc import find_mav0
from .kitti import kitti_image_dir

FORMATS = ("euroc", "tum", "kitti", "bag", "mcap")


def detect_format(path: str | os.PathLike) -> str:
    """``euroc`` | ``tum`` | ``kitti`` | ``bag`` (ROS 1 .bag, ROS 2 folder/.db3) | ``mcap``.

    Raises :class:`InputError` naming the path and what was looked for when nothing matches.
    """
    p = Path(path)
    if not p.exists():
        raise InputError(f"{p}: no such file or folder")
    if p.is_file():
        suf = p.suffix.lower()
        if suf == ".mcap":
            return "mcap"
        if suf in (".bag", ".db3"):
            return "bag"
        if p.name == "metadata.yaml":
            return "bag"
        raise InputError(f"{p}: unknown file type {suf or '(no suffix)'!r}: expected a .bag, .mcap "
                         f"or .db3 file, or a dataset folder (EuRoC, TUM RGB-D, KITTI, ROS 2 bag)")
    if (p / "metadata.yaml").is_file():
        return "bag"
    if find_mav0(p) is not None:
        return "euroc"
    if (p / "rgb.txt").is_file():
        return "tum"
    if kitti_image_dir(p) is not None and any((p / n).is_file() for n in ("calib.txt", "times.txt")):
        return "kitti"
    bags = sorted(list(p.glob("*.mcap")) + list(p.glob("*.bag")) + list(p.glob("*.db3")))
    if len(bags) == 1:
        return "mcap" if bags[0].suffix == ".mcap" else "bag"
    if len(bags) > 1:
        raise InputError(f"{p}: folder holds several recordings ({', '.join(b.name for b in bags)}); "
                         f"pass one of them")
    raise InputError(f"{p}: not a recognised recording: expected an EuRoC/ASL folder (mav0/cam0/), a "
                     f"TUM RGB-D folder (rgb.txt), a KITTI sequence (image_0|image_l|image_2 + "
                     f"calib.txt/times.txt), a ROS 2 bag folder (metadata.yaml), or a .bag/.mcap file")


def open_source(path: str | os.PathLike, options: Optional[SourceOptions] = None) -> Source:
    """Open any supported recording (format auto-detected, see :func:`detect_format`)."""
    p = Path(path)
    fmt = detect_format(p)
    if p.is_file() and p.name == "metadata.yaml":
        p = p.parent
    if fmt == "euroc":
        from .euroc import EurocSource
        return EurocSource(p, options)
    if fmt == "tum":
        from .tum import TumSource
        return TumSource(p, options)
    if fmt == "kitti":
        from .kitti import KittiSource
        return KittiSource(p, options)
    from .bag import BagSource
    if p.is_dir() and not (p / "metadata.yaml").is_file():
        bags = sorted(list(p.glob("*.mcap")) + list(p.glob("*.bag")) + list(p.glob("*.db3")))
        p = bags[0]
    return BagSource(p, options)
