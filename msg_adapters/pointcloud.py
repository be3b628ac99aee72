"""``sensor_msgs/PointCloud2`` <-> numpy points with colour.

Written clouds are unorganised (``height = 1``) with fields ``x, y, z`` (FLOAT32) and ``rgb``
(FLOAT32 holding the packed ``0x00RRGGBB`` bits: the PCL / RViz convention), ``point_step = 16``.
Reading accepts any field layout, byte order, padding and organised clouds, ``rgb`` or ``rgba``
stored as FLOAT32 or UINT32; all through a numpy structured dtype (no per-point Python).
"""
from __future__ import annotations

import sys
from typing import Any, Optional

import numpy as np
from sensor_msgs.msg import PointCloud2, PointField

from vings_core.errors import InputError

from .image import _as_numpy, _byte_array
from .stamps import make_header
from .topics import WORLD_FRAME

_DTYPES = {PointField.INT8: "i1", PointField.UINT8: "u1", PointField.INT16: "i2",
           PointField.UINT16: "u2", PointField.INT32: "i4", PointField.UINT32: "u4",
           PointField.FLOAT32: "f4", PointField.FLOAT64: "f8"}
_NATIVE_BIG = sys.byteorder == "big"


def pack_rgb(rgb: np.ndarray) -> np.ndarray:
    """uint8 (N, 3) -> uint32 (N,) ``0x00RRGGBB``."""
    c = rgb.astype(np.uint32)
    return (c[:, 0] << 16) | (c[:, 1] << 8) | c[:, 2]


def unpack_rgb(packed: np.ndarray) -> np.ndarray:
    """uint32 (N,) ``0x??RRGGBB`` -> uint8 (N, 3)."""
    p = packed.astype(np.uint32)
    return np.stack([(p >> 16) & 255, (p >> 8) & 255, p & 255], axis=1).astype(np.uint8)


def points_to_pointcloud2(xyz: Any, rgb: Optional[Any] = None, stamp_ns: int = 0,
                          frame_id: str = WORLD_FRAME, where: str = "points") -> PointCloud2:
    """(N, 3) positions (m, in ``frame_id``) and optional colours -> PointCloud2.

    ``rgb``: uint8 (N, 3), or float (N, 3) in [0, 1] (rounded to uint8).
    """
    p = _as_numpy(xyz)
    if p.ndim != 2 or p.shape[1] != 3:
        raise InputError(f"{where}: positions must be (N, 3), got {p.shape}")
    n = p.shape[0]
    fields = [PointField(name=c, offset=4 * i, datatype=PointField.FLOAT32, count=1)
              for i, c in enumerate("xyz")]
    names, formats = ["x", "y", "z"], ["f4", "f4", "f4"]
    if rgb is not None:
        c = _as_numpy(rgb)
        if c.shape != (n, 3):
            raise InputError(f"{where}: colours must be ({n}, 3) like the positions, got {c.shape}")
        if c.dtype.kind in "iu" and c.dtype != np.uint8:     # integer colours are 0..255 already
            if c.size and (c.min() < 0 or c.max() > 255):
                raise InputError(f"{where}: integer colours must lie in 0..255, got "
                                 f"[{c.min()}, {c.max()}]")
            c = c.astype(np.uint8)
        elif c.dtype != np.uint8:                            # floats in [0, 1]
            c = np.clip(np.rint(c.astype(np.float32) * 255.0), 0, 255).astype(np.uint8)
        fields.append(PointField(name="rgb", offset=12, datatype=PointField.FLOAT32, count=1))
        names.append("rgb")
        formats.append("u4")  # the bits of a float32, written as uint32
    rec = np.empty(n, dtype=np.dtype({"names": names, "formats": formats}))
    rec["x"], rec["y"], rec["z"] = p[:, 0], p[:, 1], p[:, 2]
    if rgb is not None:
        rec["rgb"] = pack_rgb(c)
    step = rec.dtype.itemsize
    msg = PointCloud2(header=make_header(stamp_ns, frame_id, where), height=1, width=n,
                      fields=fields, is_bigendian=_NATIVE_BIG, point_step=step, row_step=step * n,
                      is_dense=bool(np.all(np.isfinite(p))))
    msg.data = _byte_array(rec)
    return msg


def pointcloud2_to_points(msg: PointCloud2, where: str = "points"
                          ) -> tuple[np.ndarray, Optional[np.ndarray]]:
    """PointCloud2 -> (float32 (N, 3) positions, uint8 (N, 3) colours or None).

    Needs FLOAT32/FLOAT64 ``x, y, z``; colour from ``rgb`` / ``rgba`` when present.
    """
    h, w = int(msg.height), int(msg.width)
    step, row_step = int(msg.point_step), int(msg.row_step)
    order = ">" if msg.is_bigendian else "<"
    by_name = {f.name: f for f in msg.fields}
    for c in "xyz":
        if c not in by_name:
            raise InputError(f"{where}: fields lack {c!r} (have {sorted(by_name)})")
    names, formats, offsets = [], [], []
    for name in ("x", "y", "z", "rgb", "rgba"):
        f = by_name.get(name)
        if f is None:
            continue
        if f.datatype not in _DTYPES:
            raise InputError(f"{where}: field {name!r} has unknown datatype {f.datatype}")
        code = _DTYPES[f.datatype]
        if name in "xyz" and code not in ("f4", "f8"):
            raise InputError(f"{where}: field {name!r} must be FLOAT32 or FLOAT64, got {code}")
        if name in ("rgb", "rgba"):
            if np.dtype(code).itemsize != 4:
                raise InputError(f"{where}: field {name!r} must be 4 bytes (FLOAT32/UINT32)")
            code = "u4"  # reinterpret the packed bits
        if int(f.offset) + np.dtype(code).itemsize > step:
            raise InputError(f"{where}: field {name!r} at offset {f.offset} exceeds "
                             f"point_step {step}")
        names.append(name)
        formats.append(order + code)
        offsets.append(int(f.offset))
    if h < 0 or w < 0 or (h * w > 0 and row_step < w * step):
        raise InputError(f"{where}: row_step {row_step} < width {w} x point_step {step}")
    if len(msg.data) != row_step * h:
        raise InputError(f"{where}: data holds {len(msg.data)} bytes but row_step {row_step} x "
                         f"height {h} = {row_step * h}")
    dt = np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": step})
    raw = np.frombuffer(msg.data, dtype=np.uint8)
    if h * w == 0:
        return np.zeros((0, 3), np.float32), (np.zeros((0, 3), np.uint8)
                                              if len(names) > 3 else None)
    rows = raw.reshape(h, row_step)[:, : w * step]
    rec = np.ascontiguousarray(rows).view(dt).reshape(-1)
    xyz = np.stack([rec["x"], rec["y"], rec["z"]], axis=1).astype(np.float32)
    rgb = None
    cname = "rgb" if "rgb" in names else ("rgba" if "rgba" in names else None)
    if cname is not None:
        rgb = unpack_rgb(rec[cname])
    return xyz, rgb


__all__ = ["points_to_pointcloud2", "pointcloud2_to_points", "pack_rgb", "unpack_rgb"]
