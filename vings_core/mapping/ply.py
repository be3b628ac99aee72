"""``map.ply`` in the layout common 3DGS viewers load (INRIA 3DGS / SuperSplat / gsplat exporters).

Binary little-endian PLY, one ``vertex`` per Gaussian with float32 properties::

    x y z nx ny nz f_dc_0 f_dc_1 f_dc_2 f_rest_0 .. f_rest_{3(K-1)-1} opacity
    scale_0 scale_1 scale_2 rot_0 rot_1 rot_2 rot_3

* positions in the world frame (m); ``nx ny nz`` the surfel normal (3DGS writes zeros; viewers
  ignore it);
* ``f_dc_*``: DC SH band; ``f_rest_*``: higher bands channel-major (all R coefficients, then G, then
  B), as 3DGS stores ``features_rest.transpose(1, 2)``;
* ``opacity``: logit; ``scale_*``: log standard deviations; a 2D surfel has two, the third is tiny
  (``min(scale_0, scale_1) + log(1e-3)``) so that 3D viewers draw a flat disc;
* ``rot_*``: unit quaternion in ``(w, x, y, z)`` order (viewers' convention; the map stores xyzw).

This file is for viewing; the lossless checkpoint is :meth:`Mapper.save_checkpoint`.
"""
from __future__ import annotations

import math
import os
from typing import Callable, Iterable, Optional

import numpy as np

from ..errors import InputError, VingsError
from ..util import atomic_write, log
from .gaussians import GaussianMap

FLAT_LOG_RATIO = math.log(1e-3)


def ply_property_names(sh_degree: int) -> list[str]:
    k = (sh_degree + 1) ** 2
    names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    names += [f"f_rest_{i}" for i in range(3 * (k - 1))]
    names += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    return names


def gaussians_to_ply_array(gm: GaussianMap) -> np.ndarray:
    """(N, P) float32 rows in :func:`ply_property_names` order."""
    n = len(gm)
    q = gm.quats.detach().cpu().double()
    q = q / q.norm(dim=-1, keepdim=True).clamp_min(1e-30)
    normals = gm.normals().detach().cpu().numpy()
    sh = gm.sh.detach().cpu().numpy()
    rest = sh[:, 1:, :].transpose(0, 2, 1).reshape(n, 3 * (sh.shape[1] - 1))
    ls = gm.log_scales.detach().cpu().numpy()
    third = ls.min(1, keepdims=True) + FLAT_LOG_RATIO
    cols = [gm.means.detach().cpu().numpy(), normals, sh[:, 0, :], rest,
            gm.opacity_logits.detach().cpu().numpy()[:, None], ls, third,
            q[:, [3, 0, 1, 2]].numpy()]
    # explicit widths: reshape(n, -1) is ambiguous for an empty map (n = 0)
    return np.concatenate([c.astype(np.float32).reshape(n, int(np.prod(c.shape[1:])))
                           for c in cols], 1)


def _finite_rows(gm: GaussianMap) -> tuple[np.ndarray, np.ndarray]:
    """``(rows, ok)``: the PLY rows of ``gm`` and the mask of those a viewer can draw (finite values,
    non-zero quaternion)."""
    data = gaussians_to_ply_array(gm)
    ok = np.isfinite(data).all(1) & (gm.quats.detach().cpu().norm(dim=-1) > 0).numpy()
    return data, ok


def write_ply(path: str | os.PathLike, gm: GaussianMap | Callable[[], Iterable[GaussianMap]],
              sh_degree: Optional[int] = None) -> int:
    """Write Gaussians as a viewer-compatible binary PLY, atomically; returns the number of splats
    written. ``gm``: one map, or a function returning an iterable of maps written one after the
    other (called twice: once to count, once to write, so a large map is never gathered in memory;
    ``sh_degree`` then gives the layout). Gaussians with a non-finite value or a zero quaternion
    are left out (with a warning): viewers break on NaN bounds or normalise the quaternion to NaN."""
    if isinstance(gm, GaussianMap):
        parts: Callable[[], Iterable[GaussianMap]] = lambda: (gm,)
        sh_degree = gm.sh_degree
    else:
        parts = gm
        if sh_degree is None:
            raise ValueError("write_ply: sh_degree is required with an iterable of maps")
    names = ply_property_names(sh_degree)
    total = bad = 0
    for part in parts():
        ok = _finite_rows(part)[1]
        total += int(ok.sum())
        bad += int((~ok).sum())
    if bad:
        log.warning("%s: %d of %d Gaussians left out (non-finite values or a zero quaternion)",
                    path, bad, total + bad)
    header = ["ply", "format binary_little_endian 1.0", "comment VINGS-ROS 2DGS map (surfels: scale_2 is tiny)",
              f"element vertex {total}"] + [f"property float {p}" for p in names] + ["end_header"]
    head = ("\n".join(header) + "\n").encode("ascii")

    def _w(tmp: str) -> None:
        written = 0
        with open(tmp, "wb") as f:
            f.write(head)
            for part in parts():
                data, ok = _finite_rows(part)
                data = np.ascontiguousarray(data[ok].astype("<f4"))
                f.write(data.tobytes())
                written += len(data)
        if written != total:     # a passive chunk file lost between the two passes (reported)
            raise VingsError(f"{path}: the map changed while it was written ({written} Gaussians "
                             f"written, {total} counted); not replaced")
    atomic_write(path, _w)
    return total


_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "<i2", "int16": "<i2",
              "ushort": "<u2", "uint16": "<u2", "int": "<i4", "int32": "<i4", "uint": "<u4", "uint32": "<u4",
              "float": "<f4", "float32": "<f4", "double": "<f8", "float64": "<f8"}


def read_ply(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Read the ``vertex`` element of a binary little-endian PLY into ``{property: (N,) array}``.

    Elements before ``vertex`` (e.g. a compressed splat file's ``chunk``) are skipped by their byte
    size; a list property before or in ``vertex`` (variable size) or a malformed header is an
    :class:`InputError` naming the file and the header line."""
    try:
        with open(path, "rb") as f:
            raw = f.read()
    except OSError as e:
        raise InputError(f"{path}: cannot read PLY file: {e.strerror or e}") from None
    end = raw.find(b"end_header\n")
    if not raw.startswith(b"ply") or end < 0:
        raise InputError(f"{path}: not a PLY file (no 'ply' magic or no end_header)")
    lines = raw[:end].decode("ascii", errors="replace").splitlines()
    if "format binary_little_endian 1.0" not in lines:
        raise InputError(f"{path}: only binary_little_endian PLY is supported")
    elements: list[tuple[str, int, list[tuple[str, str]]]] = []   # (name, count, [(prop, dtype)])
    for no, ln in enumerate(lines, 1):
        t = ln.split()
        if not t or t[0] in ("ply", "format", "comment", "obj_info"):
            continue
        if t[0] == "element":
            if len(t) != 3 or not t[2].isdigit():
                raise InputError(f"{path}: header line {no} {ln!r}: expected 'element NAME COUNT'")
            elements.append((t[1], int(t[2]), []))
        elif t[0] == "property":
            if not elements:
                raise InputError(f"{path}: header line {no} {ln!r}: property before any element")
            if t[1:2] == ["list"]:
                raise InputError(f"{path}: header line {no} {ln!r}: list properties are not supported")
            if len(t) != 3 or t[1] not in _PLY_TYPES:
                raise InputError(f"{path}: header line {no} {ln!r}: expected 'property TYPE NAME' "
                                 f"with TYPE one of {sorted(_PLY_TYPES)}")
            elements[-1][2].append((t[2], _PLY_TYPES[t[1]]))
        else:
            raise InputError(f"{path}: header line {no} {ln!r}: unknown keyword {t[0]!r}")
    offset = end + len(b"end_header\n")
    for name, n, props in elements:
        try:
            dt = np.dtype(props)
        except (TypeError, ValueError) as e:          # e.g. a property named twice
            raise InputError(f"{path}: element {name!r}: {e}") from None
        if name != "vertex":
            offset += n * dt.itemsize
            continue
        body = raw[offset:]
        if len(body) < n * dt.itemsize:
            raise InputError(f"{path}: truncated ({len(body)} bytes for {n} vertices of {dt.itemsize})")
        arr = np.frombuffer(body[: n * dt.itemsize], dtype=dt, count=n)
        return {p: arr[p].copy() for p, _ in props}
    raise InputError(f"{path}: no vertex element")
