"""Exact ray-caster of textured quads (numba, parallel over screen tiles).

One ray per pixel centre gives the exact z-depth, the hit quad and the dynamic-object mask. Colour is
the quad's photo texture sampled with anisotropic trilinear mip filtering (footprint from exact ray
differentials), and pixels on a silhouette edge (hit id differs from a neighbour) are re-shaded with
2x2 supersampling, so images look like a real camera's (no texture aliasing, soft edges).

Speed: quads are culled per view (back faces, outside the frustum, behind the near plane), sorted by
their nearest z and binned into 16x16-pixel screen tiles; a ray stops as soon as its hit is nearer
than the next quad's nearest z. Nothing here is shared with the Gaussian rasterizer.

:func:`raycast_reference` is the slow, obvious numpy version (loop over quads, vectorised over
pixels) the kernel is tested against.
"""
from __future__ import annotations

from dataclasses import dataclass

import numba as nb
import numpy as np

from ..geometry import check_rigid_pose
from ..types import CameraModel
from .quads import QuadSet
from .textures import LEVEL_OFFSETS, LEVELS, SIZE, TextureAtlas

TILE = 16
NEAR = 0.02          # m: nearest visible z-depth
MAX_ANISO = 4
SKY_HORIZON = np.array([205.0, 214.0, 224.0])
SKY_ZENITH = np.array([112.0, 150.0, 204.0])


@dataclass
class RenderOutput:
    """``rgb`` uint8 (H, W, 3); ``depth`` float32 (H, W) z-depth in m (0 where no surface);
    ``mask`` bool (H, W) True on moving objects; ``prim`` int32 (H, W) index of the hit quad in the
    rendered QuadSet (-1 for sky); ``uv`` float64 (H, W, 2) hit coordinates (a, b) on that quad (m)."""

    rgb: np.ndarray
    depth: np.ndarray
    mask: np.ndarray
    prim: np.ndarray
    uv: np.ndarray


# --------------------------------------------------------------------------------------- kernels


@nb.njit(cache=True)
def _prepare(O, U, V, N, E, R_wc, t_wc, fx, fy, cx, cy, W, H, near, bbox, zmin):
    """Per quad: screen bbox (x0, y0, x1, y1 inclusive, or x0 > x1 if culled) and nearest z-depth."""
    M = O.shape[0]
    Rcw = R_wc.T
    tcw = -(Rcw @ t_wc)
    px = np.empty(8)
    py = np.empty(8)
    pz = np.empty(8)
    cz = np.empty(4)
    cxv = np.empty(4)
    cyv = np.empty(4)
    for k in range(M):
        bbox[k, 0] = 1
        bbox[k, 2] = 0
        # back face: camera centre on the back side of the plane
        s = 0.0
        for i in range(3):
            s += N[k, i] * (t_wc[i] - O[k, i])
        if s <= 0.0:
            continue
        for j in range(4):
            a = E[k, 0] if (j == 1 or j == 2) else 0.0
            b = E[k, 1] if (j == 2 or j == 3) else 0.0
            x = O[k, 0] + a * U[k, 0] + b * V[k, 0]
            y = O[k, 1] + a * U[k, 1] + b * V[k, 1]
            z = O[k, 2] + a * U[k, 2] + b * V[k, 2]
            cxv[j] = Rcw[0, 0] * x + Rcw[0, 1] * y + Rcw[0, 2] * z + tcw[0]
            cyv[j] = Rcw[1, 0] * x + Rcw[1, 1] * y + Rcw[1, 2] * z + tcw[1]
            cz[j] = Rcw[2, 0] * x + Rcw[2, 1] * y + Rcw[2, 2] * z + tcw[2]
        # clip the polygon against z >= near (Sutherland-Hodgman, one plane)
        n = 0
        for j in range(4):
            j2 = (j + 1) % 4
            in1 = cz[j] >= near
            in2 = cz[j2] >= near
            if in1:
                px[n] = cxv[j]
                py[n] = cyv[j]
                pz[n] = cz[j]
                n += 1
            if in1 != in2:
                f = (near - cz[j]) / (cz[j2] - cz[j])
                px[n] = cxv[j] + f * (cxv[j2] - cxv[j])
                py[n] = cyv[j] + f * (cyv[j2] - cyv[j])
                pz[n] = near
                n += 1
        if n == 0:
            continue
        u0 = 1e30
        u1 = -1e30
        v0 = 1e30
        v1 = -1e30
        zm = 1e30
        for j in range(n):
            u = fx * px[j] / pz[j] + cx
            v = fy * py[j] / pz[j] + cy
            u0 = min(u0, u)
            u1 = max(u1, u)
            v0 = min(v0, v)
            v1 = max(v1, v)
            zm = min(zm, pz[j])
        # one pixel of margin for sub-pixel samples and rounding
        x0 = max(int(np.floor(u0)) - 1, 0)
        x1 = min(int(np.ceil(u1)) + 1, W - 1)
        y0 = max(int(np.floor(v0)) - 1, 0)
        y1 = min(int(np.ceil(v1)) + 1, H - 1)
        if x0 > x1 or y0 > y1:
            continue
        bbox[k, 0] = x0
        bbox[k, 1] = y0
        bbox[k, 2] = x1
        bbox[k, 3] = y1
        zmin[k] = zm


@nb.njit(cache=True)
def _bin_tiles(order, bbox, ntx, nty, tile):
    """CSR lists of quads (in ``order``, i.e. by nearest z) overlapping each screen tile."""
    nt = ntx * nty
    counts = np.zeros(nt + 1, np.int64)
    for idx in range(order.shape[0]):
        k = order[idx]
        for ty in range(bbox[k, 1] // tile, bbox[k, 3] // tile + 1):
            for tx in range(bbox[k, 0] // tile, bbox[k, 2] // tile + 1):
                counts[ty * ntx + tx + 1] += 1
    start = np.cumsum(counts)
    fill = start[:-1].copy()
    items = np.empty(start[-1], np.int64)
    for idx in range(order.shape[0]):
        k = order[idx]
        for ty in range(bbox[k, 1] // tile, bbox[k, 3] // tile + 1):
            for tx in range(bbox[k, 0] // tile, bbox[k, 2] // tile + 1):
                t = ty * ntx + tx
                items[fill[t]] = k
                fill[t] += 1
    return start, items


@nb.njit(cache=True, inline="always")
def _trace(ox, oy, oz, dx, dy, dz, items, i0, i1, O, U, V, N, E, zmin, near):
    """Nearest hit of ray ``o + t d`` (t = z-depth since d_cam.z = 1) among ``items[i0:i1]``."""
    best = 1e300
    hit = -1
    ha = 0.0
    hb = 0.0
    for ii in range(i0, i1):
        k = items[ii]
        if zmin[k] >= best:
            break
        den = N[k, 0] * dx + N[k, 1] * dy + N[k, 2] * dz
        if den >= 0.0:
            continue
        rx = O[k, 0] - ox
        ry = O[k, 1] - oy
        rz = O[k, 2] - oz
        t = (N[k, 0] * rx + N[k, 1] * ry + N[k, 2] * rz) / den
        if t < near or t >= best:
            continue
        qx = t * dx - rx
        qy = t * dy - ry
        qz = t * dz - rz
        a = U[k, 0] * qx + U[k, 1] * qy + U[k, 2] * qz
        if a < 0.0 or a > E[k, 0]:
            continue
        b = V[k, 0] * qx + V[k, 1] * qy + V[k, 2] * qz
        if b < 0.0 or b > E[k, 1]:
            continue
        best = t
        hit = k
        ha = a
        hb = b
    return hit, best, ha, hb


@nb.njit(cache=True, inline="always")
def _bilinear(tex, k, level, s, t, out):
    """Add bilinear sample of mip ``level`` at texture coords (s, t) (repeats; t up) to out[0:3]."""
    size = SIZE >> level
    off = LEVEL_OFFSETS[level]
    x = s * size - 0.5
    y = -t * size - 0.5
    xf = np.floor(x)
    yf = np.floor(y)
    wx = x - xf
    wy = y - yf
    x0 = int(xf) % size
    y0 = int(yf) % size
    x1 = (x0 + 1) % size
    y1 = (y0 + 1) % size
    w00 = (1 - wx) * (1 - wy)
    w10 = wx * (1 - wy)
    w01 = (1 - wx) * wy
    w11 = wx * wy
    i00 = off + y0 * size + x0
    i10 = off + y0 * size + x1
    i01 = off + y1 * size + x0
    i11 = off + y1 * size + x1
    for c in range(3):
        out[c] += (w00 * tex[k, i00, c] + w10 * tex[k, i10, c] + w01 * tex[k, i01, c]
                   + w11 * tex[k, i11, c])


@nb.njit(cache=True, inline="always")
def _shade(k, a, b, t, dx, dy, dz, exx, exy, exz, eyx, eyy, eyz, fscale,
           U, V, N, tex_id, tile, offs, tint, tex, out):
    """Colour (0..255 floats, into out) of quad k at (a, b): anisotropic trilinear mip filtering.

    The footprint uses exact ray differentials on the plane: dP/dx = t (e_x - d (n.e_x)/(n.d)),
    e_x = R_wc[:, 0] / fx (and y likewise), scaled by ``fscale`` (0.5 for 2x2 sub-samples).
    """
    den = N[k, 0] * dx + N[k, 1] * dy + N[k, 2] * dz
    nex = (N[k, 0] * exx + N[k, 1] * exy + N[k, 2] * exz) / den
    ney = (N[k, 0] * eyx + N[k, 1] * eyy + N[k, 2] * eyz) / den
    px = t * fscale * (exx - dx * nex)
    py = t * fscale * (exy - dy * nex)
    pz = t * fscale * (exz - dz * nex)
    qx = t * fscale * (eyx - dx * ney)
    qy = t * fscale * (eyy - dy * ney)
    qz = t * fscale * (eyz - dz * ney)
    su = SIZE / tile[k, 0]
    sv = SIZE / tile[k, 1]
    # footprint axes in texels
    ax = (U[k, 0] * px + U[k, 1] * py + U[k, 2] * pz) * su
    ay = (V[k, 0] * px + V[k, 1] * py + V[k, 2] * pz) * sv
    bx = (U[k, 0] * qx + U[k, 1] * qy + U[k, 2] * qz) * su
    by = (V[k, 0] * qx + V[k, 1] * qy + V[k, 2] * qz) * sv
    la = np.sqrt(ax * ax + ay * ay)
    lb = np.sqrt(bx * bx + by * by)
    if la >= lb:
        major = la
        minor = lb
        mx = ax
        my = ay
    else:
        major = lb
        minor = la
        mx = bx
        my = by
    # anisotropic taps along the major axis (none when magnifying: footprint under one texel)
    nsamp = 1
    if major > 1.0:
        if minor > 1e-12:
            nsamp = int(min(np.ceil(major / minor - 1e-3), np.ceil(major), MAX_ANISO))
        else:
            nsamp = MAX_ANISO
    if nsamp < 1:
        nsamp = 1
    lod = np.log2(max(major / nsamp, 1e-12))
    if lod < 0.0:
        lod = 0.0
    if lod > LEVELS - 1:
        lod = LEVELS - 1.0
    l0 = int(np.floor(lod))
    l1 = min(l0 + 1, LEVELS - 1)
    wl = lod - l0
    s0 = (a + offs[k, 0]) / tile[k, 0]
    t0 = (b + offs[k, 1]) / tile[k, 1]
    acc0 = np.zeros(3)
    acc1 = np.zeros(3)
    tid = tex_id[k]
    for i in range(nsamp):
        f = (i + 0.5) / nsamp - 0.5
        s = s0 + f * mx / SIZE
        tt = t0 + f * my / SIZE
        _bilinear(tex, tid, l0, s, tt, acc0)
        if wl > 0.0:
            _bilinear(tex, tid, l1, s, tt, acc1)
    for c in range(3):
        out[c] = ((1.0 - wl) * acc0[c] + wl * acc1[c]) / nsamp * tint[k, c]


@nb.njit(cache=True, inline="always")
def _sky(dx, dy, dz, out):
    n = np.sqrt(dx * dx + dy * dy + dz * dz)
    e = max(dz / n, 0.0)
    e = np.sqrt(e)
    out[0] = (1 - e) * 205.0 + e * 112.0
    out[1] = (1 - e) * 214.0 + e * 150.0
    out[2] = (1 - e) * 224.0 + e * 204.0


@nb.njit(cache=True, parallel=True)
def _render_tiles(start, items, O, U, V, N, E, zmin, tex_id, tile, offs, tint, obj, tex,
                  R_wc, t_wc, fx, fy, cx, cy, W, H, ntx, near, sky,
                  rgb, depth, mask, prim, uv):
    """Pass 1: one ray per pixel centre -> depth, hit id, hit coords, colour."""
    nt = start.shape[0] - 1
    ox = t_wc[0]
    oy = t_wc[1]
    oz = t_wc[2]
    exx = R_wc[0, 0] / fx
    exy = R_wc[1, 0] / fx
    exz = R_wc[2, 0] / fx
    eyx = R_wc[0, 1] / fy
    eyy = R_wc[1, 1] / fy
    eyz = R_wc[2, 1] / fy
    for ti in nb.prange(nt):
        ty = ti // ntx
        tx = ti - ty * ntx
        i0 = start[ti]
        i1 = start[ti + 1]
        col = np.zeros(3)
        for y in range(ty * TILE, min((ty + 1) * TILE, H)):
            yn = (y - cy) / fy
            for x in range(tx * TILE, min((tx + 1) * TILE, W)):
                xn = (x - cx) / fx
                dx = R_wc[0, 0] * xn + R_wc[0, 1] * yn + R_wc[0, 2]
                dy = R_wc[1, 0] * xn + R_wc[1, 1] * yn + R_wc[1, 2]
                dz = R_wc[2, 0] * xn + R_wc[2, 1] * yn + R_wc[2, 2]
                k, t, a, b = _trace(ox, oy, oz, dx, dy, dz, items, i0, i1, O, U, V, N, E,
                                    zmin, near)
                prim[y, x] = k
                if k < 0:
                    depth[y, x] = 0.0
                    mask[y, x] = False
                    if sky:
                        _sky(dx, dy, dz, col)
                    else:
                        col[0] = 0.0
                        col[1] = 0.0
                        col[2] = 0.0
                else:
                    depth[y, x] = t
                    mask[y, x] = obj[k] >= 0
                    uv[y, x, 0] = a
                    uv[y, x, 1] = b
                    _shade(k, a, b, t, dx, dy, dz, exx, exy, exz, eyx, eyy, eyz, 1.0,
                           U, V, N, tex_id, tile, offs, tint, tex, col)
                for c in range(3):
                    rgb[y, x, c] = col[c]


@nb.njit(cache=True, parallel=True)
def _antialias_edges(start, items, O, U, V, N, E, zmin, tex_id, tile, offs, tint, tex,
                     R_wc, t_wc, fx, fy, cx, cy, W, H, ntx, near, sky, prim, rgb_in, rgb_out):
    """Pass 2: pixels whose hit id differs from a 4-neighbour get the mean of 2x2 sub-samples."""
    ox = t_wc[0]
    oy = t_wc[1]
    oz = t_wc[2]
    exx = R_wc[0, 0] / fx
    exy = R_wc[1, 0] / fx
    exz = R_wc[2, 0] / fx
    eyx = R_wc[0, 1] / fy
    eyy = R_wc[1, 1] / fy
    eyz = R_wc[2, 1] / fy
    for y in nb.prange(H):
        col = np.zeros(3)
        acc = np.zeros(3)
        for x in range(W):
            k0 = prim[y, x]
            edge = ((x > 0 and prim[y, x - 1] != k0) or (x < W - 1 and prim[y, x + 1] != k0)
                    or (y > 0 and prim[y - 1, x] != k0) or (y < H - 1 and prim[y + 1, x] != k0))
            if not edge:
                for c in range(3):
                    rgb_out[y, x, c] = rgb_in[y, x, c]
                continue
            ti = (y // TILE) * ntx + (x // TILE)
            i0 = start[ti]
            i1 = start[ti + 1]
            for c in range(3):
                acc[c] = 0.0
            for sj in range(2):
                for si in range(2):
                    xn = (x - 0.25 + 0.5 * si - cx) / fx
                    yn = (y - 0.25 + 0.5 * sj - cy) / fy
                    dx = R_wc[0, 0] * xn + R_wc[0, 1] * yn + R_wc[0, 2]
                    dy = R_wc[1, 0] * xn + R_wc[1, 1] * yn + R_wc[1, 2]
                    dz = R_wc[2, 0] * xn + R_wc[2, 1] * yn + R_wc[2, 2]
                    k, t, a, b = _trace(ox, oy, oz, dx, dy, dz, items, i0, i1, O, U, V, N, E,
                                        zmin, near)
                    if k < 0:
                        if sky:
                            _sky(dx, dy, dz, col)
                        else:
                            col[0] = 0.0
                            col[1] = 0.0
                            col[2] = 0.0
                    else:
                        _shade(k, a, b, t, dx, dy, dz, exx, exy, exz, eyx, eyy, eyz, 0.5,
                               U, V, N, tex_id, tile, offs, tint, tex, col)
                    for c in range(3):
                        acc[c] += col[c]
            for c in range(3):
                rgb_out[y, x, c] = 0.25 * acc[c]


# --------------------------------------------------------------------------------------- driver


def _check_pose(T_wc: np.ndarray) -> np.ndarray:
    """``T_wc`` as a float64 4x4 rigid transform (to 1e-6); ValueError otherwise."""
    if np.shape(T_wc) != (4, 4):
        raise ValueError(f"T_wc must be a finite 4x4 matrix, got shape {np.shape(T_wc)}")
    return check_rigid_pose(T_wc, "T_wc", tol=1e-6, error=ValueError)


def raycast(quads: QuadSet, atlas: TextureAtlas, camera: CameraModel, T_wc: np.ndarray,
            sky: bool = True, antialias: bool = True) -> RenderOutput:
    """Render ``quads`` seen by a pinhole ``camera`` at pose ``T_wc`` (camera-to-world, optical
    frame). Distortion in ``camera`` is ignored (the simulator renders ideal pinhole images)."""
    T = _check_pose(T_wc)
    W, H = int(camera.width), int(camera.height)
    R_wc = np.ascontiguousarray(T[:3, :3])
    t_wc = np.ascontiguousarray(T[:3, 3])
    M = len(quads)
    bbox = np.zeros((M, 4), np.int64)
    zmin = np.full(M, np.inf)
    O = np.ascontiguousarray(quads.origin, dtype=np.float64)
    U = np.ascontiguousarray(quads.u, dtype=np.float64)
    V = np.ascontiguousarray(quads.v, dtype=np.float64)
    N = np.ascontiguousarray(quads.normal, dtype=np.float64)
    E = np.ascontiguousarray(quads.extent, dtype=np.float64)
    if M:
        _prepare(O, U, V, N, E, R_wc, t_wc, float(camera.fx), float(camera.fy), float(camera.cx),
                 float(camera.cy), W, H, NEAR, bbox, zmin)
    vis = np.nonzero(bbox[:, 0] <= bbox[:, 2])[0]
    order = vis[np.argsort(zmin[vis], kind="stable")].astype(np.int64)
    ntx = (W + TILE - 1) // TILE
    nty = (H + TILE - 1) // TILE
    start, items = _bin_tiles(order, bbox, ntx, nty, TILE)
    rgb_f = np.empty((H, W, 3), np.float32)
    depth = np.empty((H, W), np.float32)
    mask = np.empty((H, W), np.bool_)
    prim = np.empty((H, W), np.int32)
    uv = np.zeros((H, W, 2), np.float64)
    tex_id = np.ascontiguousarray(quads.tex, dtype=np.int64)
    tile = np.ascontiguousarray(quads.tile, dtype=np.float64)
    offs = np.ascontiguousarray(quads.offset, dtype=np.float64)
    tint = np.ascontiguousarray(quads.tint, dtype=np.float64)
    obj = np.ascontiguousarray(quads.obj, dtype=np.int64)
    args = (float(camera.fx), float(camera.fy), float(camera.cx), float(camera.cy), W, H, ntx,
            NEAR, bool(sky))
    _render_tiles(start, items, O, U, V, N, E, zmin, tex_id, tile, offs, tint, obj, atlas.data,
                  R_wc, t_wc, *args, rgb_f, depth, mask, prim, uv)
    if antialias:
        out = np.empty_like(rgb_f)
        _antialias_edges(start, items, O, U, V, N, E, zmin, tex_id, tile, offs, tint, atlas.data,
                         R_wc, t_wc, *args, prim, rgb_f, out)
        rgb_f = out
    rgb = np.clip(np.rint(rgb_f), 0, 255).astype(np.uint8)
    return RenderOutput(rgb=rgb, depth=depth, mask=mask, prim=prim, uv=uv)


def raycast_reference(quads: QuadSet, camera: CameraModel, T_wc: np.ndarray):
    """Slow, obvious reference: nearest hit of the pixel-centre ray against every quad.

    Returns ``(depth float64 (H, W) z-depth m (0 = none), prim int (H, W) (-1 = none),
    uv float64 (H, W, 2))``. No culling, no sorting, no tiles.
    """
    T = _check_pose(T_wc)
    W, H = camera.width, camera.height
    ys, xs = np.mgrid[0:H, 0:W].astype(np.float64)
    d_c = np.stack([(xs - camera.cx) / camera.fx, (ys - camera.cy) / camera.fy, np.ones_like(xs)], -1)
    d = d_c @ T[:3, :3].T                      # world ray directions with camera z = 1
    o = T[:3, 3]
    best = np.full((H, W), np.inf)
    prim = np.full((H, W), -1, np.int64)
    uv = np.zeros((H, W, 2))
    for k in range(len(quads)):
        n = quads.normal[k]
        den = d @ n
        with np.errstate(divide="ignore", invalid="ignore"):
            t = ((quads.origin[k] - o) @ n) / den
        p = o + t[..., None] * d - quads.origin[k]
        a = p @ quads.u[k]
        b = p @ quads.v[k]
        ok = ((den < 0) & (t >= NEAR) & (t < best) & (a >= 0) & (a <= quads.extent[k, 0])
              & (b >= 0) & (b <= quads.extent[k, 1]))
        best[ok] = t[ok]
        prim[ok] = k
        uv[ok, 0] = a[ok]
        uv[ok, 1] = b[ok]
    depth = np.where(np.isfinite(best), best, 0.0)
    return depth, prim, uv
