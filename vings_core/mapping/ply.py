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

import numpy as np

from ..errors import InputError
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


def write_ply(path: str | os.PathLike, gm: GaussianMap) -> int:
    """Write ``gm`` as a viewer-compatible binary PLY, atomically; returns the number of splats
    written. Gaussians with a non-finite value or a zero quaternion are left out (with a warning):
    viewers break on NaN bounds or normalise the quaternion to NaN."""
    names = ply_property_names(gm.sh_degree)
    data = gaussians_to_ply_array(gm)
    q = gm.quats.detach().cpu()
    ok = np.isfinite(data).all(1) & (q.norm(dim=-1) > 0).numpy()
    if not ok.all():
        log.warning("%s: %d of %d Gaussians left out (non-finite values or a zero quaternion)",
                    path, int((~ok).sum()), len(ok))
        data = data[ok]
    data = np.ascontiguousarray(data.astype("<f4"))
    header = ["ply", "format binary_little_endian 1.0", "comment VINGS-ROS 2DGS map (surfels: scale_2 is tiny)",
              f"element vertex {len(data)}"] + [f"property float {p}" for p in names] + ["end_header"]
    head = ("\n".join(header) + "\n").encode("ascii")

    def _w(tmp: str) -> None:
        with open(tmp, "wb") as f:
            f.write(head)
            f.write(data.tobytes())
    atomic_write(path, _w)
    return len(data)


def read_ply(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Read a binary little-endian PLY vertex element into ``{property: (N,) array}``."""
    with open(path, "rb") as f:
        raw = f.read()
    end = raw.find(b"end_header\n")
    if not raw.startswith(b"ply") or end < 0:
        raise InputError(f"{path}: not a PLY file (no 'ply' magic or no end_header)")
    lines = raw[:end].decode("ascii", errors="replace").splitlines()
    if "format binary_little_endian 1.0" not in lines:
        raise InputError(f"{path}: only binary_little_endian PLY is supported")
    n = None
    props: list[tuple[str, str]] = []
    types = {"float": "<f4", "float32": "<f4", "double": "<f8", "uchar": "u1", "int": "<i4", "uint": "<u4"}
    in_vertex = False
    for ln in lines:
        t = ln.split()
        if not t:
            continue
        if t[0] == "element":
            in_vertex = t[1] == "vertex"
            if in_vertex:
                n = int(t[2])
        elif t[0] == "property" and in_vertex:
            if t[1] not in types:
                raise InputError(f"{path}: unsupported property type {t[1]!r}")
            props.append((t[2], types[t[1]]))
    if n is None:
        raise InputError(f"{path}: no vertex element")
    dt = np.dtype(props)
    body = raw[end + len(b"end_header\n"):]
    if len(body) < n * dt.itemsize:
        raise InputError(f"{path}: truncated ({len(body)} bytes for {n} vertices of {dt.itemsize})")
    arr = np.frombuffer(body[: n * dt.itemsize], dtype=dt, count=n)
    return {name: arr[name].copy() for name, _ in props}
