"""Numba CPU kernels of the 2DGS rasterizer (forward, sample-based backward, binning, reductions).

Every kernel is ``cache=True`` and compiled on first call (nothing at import). Kernels are generic
over float32 / float64: the dtype follows the ``params`` array, and every constant comes from the
``cst`` array (:func:`make_consts`) so float32 arithmetic never silently widens to float64.

Per-Gaussian record (``params``, ``(N, 16)``): ``M`` (3x3 ray-splat transform, row-major, see
:mod:`.project`), opacity, rgb, camera-frame normal. For pixel centre ``(x, y)`` (OpenCV convention:
pixel column ``j`` has ``x = j``) the splat coordinates are ``(u, v, 1) ~ h_u x h_v`` with
``h_u = x M_2 - M_0`` and ``h_v = y M_2 - M_1`` (``M_r`` = row r), as in 2DGS; the kernels evaluate
that cross product from precomputed, centred line coordinates (see :func:`preprocess`). Then

* ``rho3 = u^2 + v^2`` (3D branch; valid when the cross product is not degenerate and the hit
  point's camera z exceeds ``near``), hit depth ``z = M_2 . (u, v, 1)``;
* ``rho2 = 2 |(x, y) - mean2d|^2`` (screen-space low-pass filter, sigma = sqrt(2)/2 px);
* the smaller of the two is used (``G = max(G3, G2)`` as in 2DGS), with the centre depth
  ``M[2,2]`` as depth in the low-pass case; ``alpha = min(0.99, o exp(-rho/2))``, skipped when
  ``< 1/255``; compositing stops before a Gaussian that would take ``T`` below ``1e-4`` (see ``T_MIN``).

Work is split in 16x16 tiles (``prange`` over tiles; callers set a parallel chunk size of one
tile, see :func:`tile_parallel`, so uneven tiles balance dynamically). Inside a tile
the loop is Gaussian-outer / pixel-inner and each Gaussian only visits the pixels of its exact
screen bounding box, so tiny splats cost a few pixel evaluations instead of 256. Per-Gaussian
results (scores, gradients) are written to one row per (tile, Gaussian) pair of a Gaussian-major
buffer, so tiles never race, and then reduced per Gaussian in parallel (:func:`reduce_pairs`).
"""
from __future__ import annotations

import math

import numba
import numpy as np
from numba import njit, prange

from .intrinsics import ctz64, prefetch_at, prefetch_row, prefetch_w

TILE = 16
TILE_PIX = TILE * TILE
ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.99
# compositing stops before a Gaussian that would take T below 1e-4 (3DGS/gsplat); the threshold sits
# a hair below 1e-4 because two clamped splats leave exactly (1 - ALPHA_MAX)^2 = 1e-4, which float32
# rounds below and float64 above: a boundary that common must not depend on the precision
T_MIN = 1e-4 * (1.0 - 1e-5)
DIST_NEAR = 0.2     # 2DGS's depth mapping for the distortion term
DIST_FAR = 100.0
BBOX_PAD = 1e-2     # px, guards the exact bounding box against rounding
NPARAM = 16
NGRAD = 16          # gradient record: dL/dM (9), dL/dopacity, dL/drgb (3), dL/dnormal (3)
AUX = 16            # per-Gaussian auxiliary record (see preprocess)
NSTAT = 3           # per-pair forward stats: sum(alpha T), pixels touched, sum(L alpha T)
PREFETCH = 3        # tile-list entries ahead whose records the tile kernels prefetch

class tile_parallel:
    """Context manager: parallel regions launched inside use dynamic chunks of one iteration."""

    def __enter__(self):
        self._old = numba.set_parallel_chunksize(1)
        return self

    def __exit__(self, *exc):
        numba.set_parallel_chunksize(self._old)
        return False


# indices into the constants array
_ZERO, _ONE, _HALF, _TWO, _AMIN, _AMAX, _TMIN, _NEAR, _FAR, _DA, _DN, _LN255, _PAD = range(13)


def make_consts(dtype, near: float, far: float) -> np.ndarray:
    """Constants of the kernels in the working dtype (see module docstring)."""
    return np.array([0.0, 1.0, 0.5, 2.0, ALPHA_MIN, ALPHA_MAX, T_MIN, near, far,
                     DIST_FAR / (DIST_FAR - DIST_NEAR), DIST_NEAR, math.log(255.0), BBOX_PAD],
                    dtype=dtype)


# ------------------------------------------------------------------------------ per-Gaussian set-up


EXACT_MIN_TILES = 3  # boxes over this many tiles get exact per-row coverage (see _row_span)
SPAN_MARGIN = 1.0    # px added on both sides of an exact row span (rounding guard)


@njit(cache=True, inline="always", error_model="numpy")
def _row_span(aux, g, y, x0, x1):
    """Pixels ``[xl, xr]`` (inclusive, inside ``[x0, x1]``; ``xl > xr``: none) of pixel row ``y``
    where Gaussian ``g`` can reach ``rho <= rho_cut``, i.e. ``alpha >= 1/255``.

    A superset, exact up to ``SPAN_MARGIN``: the union of the 3D footprint (``c0^2 + c1^2 <=
    rho_cut c2^2`` with ``c = (x - mx) A - (y - my) B + C``: a quadratic in ``x`` per row) and the
    low-pass disc ``2 (dx^2 + dy^2) <= rho_cut``, as the hull of the two. A splat seen at a grazing
    angle projects to a thin slanted ellipse whose axis-aligned box is mostly empty; one near the
    camera (hyperbolic footprint) gets the whole image as its box, but only part of each row."""
    mx = float(aux[g, 0])
    my = float(aux[g, 1])
    k2 = float(aux[g, 2])
    dy = float(y) - my
    a0 = float(aux[g, 4])
    a1 = float(aux[g, 5])
    a2 = float(aux[g, 6])
    e0 = float(aux[g, 10]) - dy * float(aux[g, 7])
    e1 = float(aux[g, 11]) - dy * float(aux[g, 8])
    e2 = float(aux[g, 12]) - dy * float(aux[g, 9])
    X0 = x0 - mx
    X1 = x1 - mx
    lo = np.inf
    hi = -np.inf
    r2 = 0.5 * k2 - dy * dy
    if r2 >= 0.0:
        r = np.sqrt(r2)
        lo = -r
        hi = r
    al = a0 * a0 + a1 * a1 - k2 * a2 * a2
    be = a0 * e0 + a1 * e1 - k2 * a2 * e2
    ga = e0 * e0 + e1 * e1 - k2 * e2 * e2
    eps = 1e-9 * (a0 * a0 + a1 * a1 + k2 * a2 * a2)
    if al > eps:
        disc = be * be - al * ga
        if disc >= 0.0:
            sq = np.sqrt(disc)
            lo = min(lo, (-be - sq) / al)
            hi = max(hi, (-be + sq) / al)
    elif al < -eps:
        disc = be * be - al * ga
        if disc > 0.0:
            sq = np.sqrt(disc)
            ra = (-be + sq) / al
            rb = (-be - sq) / al
            rmin = min(ra, rb)
            rmax = max(ra, rb)
            if X0 <= rmin:       # f <= 0 outside (rmin, rmax)
                lo = min(lo, X0)
                hi = max(hi, min(rmin, X1))
            if X1 >= rmax:
                lo = min(lo, max(rmax, X0))
                hi = max(hi, X1)
        else:                    # f < 0 everywhere (or NaN: keep the whole row)
            lo = X0
            hi = X1
    else:                        # (near-)parabolic: keep the whole row
        lo = X0
        hi = X1
    if not (lo <= hi):
        return x0 + 1, x0
    lo = max(lo - SPAN_MARGIN, X0 - 1.0)
    hi = min(hi + SPAN_MARGIN, X1 + 1.0)
    xl = max(x0, int(np.ceil(mx + lo)))
    xr = min(x1, int(np.floor(mx + hi)))
    return xl, xr


@njit(cache=True, inline="always")
def _exact_tiles(bbox, g):
    """Whether Gaussian ``g``'s tiles come from exact row spans (box over >= EXACT_MIN_TILES)."""
    return (bbox[g, 1] // TILE - bbox[g, 0] // TILE + 1) * (bbox[g, 3] // TILE - bbox[g, 2] // TILE + 1) \
        >= EXACT_MIN_TILES


@njit(cache=True, inline="always")
def _band_spans(aux, bbox, g, ty, spans):
    """Row spans of Gaussian ``g`` in tile row ``ty`` (rows clipped to its box) into ``spans[r]``
    (``r`` = row - ty * TILE; rows outside the box get empty spans). Returns the band's hull
    ``(xl, xr)`` (``xl > xr``: empty)."""
    x0 = bbox[g, 0]
    x1 = bbox[g, 1]
    hl = x1 + 1
    hr = x0
    for r in range(TILE):
        y = ty * TILE + r
        if y < bbox[g, 2] or y > bbox[g, 3]:
            spans[r, 0] = 1
            spans[r, 1] = 0
            continue
        xl, xr = _row_span(aux, g, y, x0, x1)
        spans[r, 0] = xl
        spans[r, 1] = xr
        if xl <= xr:
            hl = min(hl, xl)
            hr = max(hr, xr)
    if hl > hr:
        return 1, 0
    return hl, hr


@njit(cache=True, inline="always")
def _band_tiles(aux, bbox, g, ty, exact, spans):
    """Inclusive range ``(txa, txb)`` of tile columns Gaussian ``g`` touches in tile row ``ty``
    (``txb < txa``: none): its box's, or with ``exact`` those its row spans reach (the spans are
    left in ``spans`` for the caller)."""
    if not exact:
        return bbox[g, 0] // TILE, bbox[g, 1] // TILE
    hl, hr = _band_spans(aux, bbox, g, ty, spans)
    if hl > hr:
        return 0, -1
    return hl // TILE, hr // TILE


@njit(parallel=True, cache=True, error_model="numpy")
def preprocess(params, cst, width, height, aux, bbox, radii, ntiles):
    """Cull, and compute per Gaussian its pixel bounding box and tile count.

    Culled: centre depth outside ``(near, far)``, opacity below 1/255, or any non-finite value in
    the record (so a NaN/zero quaternion or NaN/inf scale, opacity or colour draws nothing and gets
    zero gradients). ``aux[i]`` (16 values): ``mean2d_x, mean2d_y, rho_cut, 0`` where ``rho_cut = 2 ln(255 o)`` is
    the largest ``rho`` with ``alpha >= 1/255``, then the splat's homogeneous line coordinates
    about its projected centre ``(mx, my)``: with ``M0' = M_0 - mx M_2``, ``M1' = M_1 - my M_2``,
    ``A = M1' x M_2``, ``B = M0' x M_2``, ``C = M0' x M1'`` (each 3), the ray-splat cross product
    at pixel ``(x, y)`` is ``c = (x - mx) A - (y - my) B + C`` (exactly ``h_u x h_v``); computed in
    float64 and centred so that float32 keeps its precision. ``bbox[i] = (x0, x1, y0, y1)`` inclusive pixel ranges (empty
    when culled), ``radii[i]`` the half extent in px (0 when culled), ``ntiles[i]`` the number of
    16x16 tiles the splat touches (0 when culled; for boxes over ``EXACT_MIN_TILES`` or more tiles
only the tiles its row spans reach, :func:`_row_span`). Exact: the 3D part is the axis-aligned box of the
    projected ellipse ``u^2 + v^2 = rho_cut`` (dual conic ``M diag(k2,k2,-1) M^T``), the low-pass part
    a disc of radius ``sqrt(ln(255 o))`` around the projected centre. A splat whose cut-off disc
    reaches behind the camera plane gets the whole image.
    """
    near = cst[_NEAR]
    far = cst[_FAR]
    amin = cst[_AMIN]
    zero = cst[_ZERO]
    pad = cst[_PAD]
    wf = cst[_ONE] * width
    hf = cst[_ONE] * height
    n = params.shape[0]
    for i in prange(n):
        radii[i] = 0
        ntiles[i] = 0
        bbox[i, 0] = 0
        bbox[i, 1] = -1
        bbox[i, 2] = 0
        bbox[i, 3] = -1
        for c in range(AUX):
            aux[i, c] = zero
        m0 = params[i, 0]
        m1 = params[i, 1]
        m2 = params[i, 2]
        m3 = params[i, 3]
        m4 = params[i, 4]
        m5 = params[i, 5]
        m6 = params[i, 6]
        m7 = params[i, 7]
        m8 = params[i, 8]
        o = params[i, 9]
        if not (m8 > near and m8 < far and o >= amin):
            continue
        # a non-finite record (zero or NaN quaternion, NaN/inf scale, opacity or colour) is culled:
        # its NaN would otherwise run through every pixel's transmittance and every gradient
        chk = zero
        for c in range(NPARAM):
            chk += params[i, c]
        if not (chk - chk == zero):
            continue
        lk = np.log(o) + cst[_LN255]
        if lk < zero:
            lk = zero
        k2 = lk + lk
        mx = m2 / m8
        my = m5 / m8
        rl = np.sqrt(lk)
        xmin = mx - rl
        xmax = mx + rl
        ymin = my - rl
        ymax = my + rl
        rad = rl
        d22 = k2 * (m6 * m6 + m7 * m7) - m8 * m8
        if d22 < -1e-6 * m8 * m8:
            d00 = k2 * (m0 * m0 + m1 * m1) - m2 * m2
            d02 = k2 * (m0 * m6 + m1 * m7) - m2 * m8
            d11 = k2 * (m3 * m3 + m4 * m4) - m5 * m5
            d12 = k2 * (m3 * m6 + m4 * m7) - m5 * m8
            ecx = d02 / d22
            ecy = d12 / d22
            hx2 = ecx * ecx - d00 / d22
            hy2 = ecy * ecy - d11 / d22
            hx = np.sqrt(hx2) if hx2 > zero else zero
            hy = np.sqrt(hy2) if hy2 > zero else zero
            xmin = min(xmin, ecx - hx)
            xmax = max(xmax, ecx + hx)
            ymin = min(ymin, ecy - hy)
            ymax = max(ymax, ecy + hy)
            rad = max(rad, max(hx, hy))
        else:
            xmin = -wf
            xmax = wf + wf
            ymin = -hf
            ymax = hf + hf
            rad = max(wf, hf)
        if not (xmax + pad >= zero and ymax + pad >= zero and xmin - pad <= wf - 1
                and ymin - pad <= hf - 1):
            continue  # off-screen (or NaN)
        x0 = 0 if xmin - pad <= zero else int(np.ceil(xmin - pad))
        x1 = width - 1 if xmax + pad >= wf - 1 else int(np.floor(xmax + pad))
        y0 = 0 if ymin - pad <= zero else int(np.ceil(ymin - pad))
        y1 = height - 1 if ymax + pad >= hf - 1 else int(np.floor(ymax + pad))
        if x0 > x1 or y0 > y1:
            continue
        bbox[i, 0] = x0
        bbox[i, 1] = x1
        bbox[i, 2] = y0
        bbox[i, 3] = y1
        radii[i] = int(np.ceil(min(rad, wf + hf)))
        ntiles[i] = (x1 // TILE - x0 // TILE + 1) * (y1 // TILE - y0 // TILE + 1)
        aux[i, 0] = mx
        aux[i, 1] = my
        aux[i, 2] = k2
        # line coordinates, in float64
        fm0 = float(m0)
        fm1 = float(m1)
        fm2 = float(m2)
        fm3 = float(m3)
        fm4 = float(m4)
        fm5 = float(m5)
        fm6 = float(m6)
        fm7 = float(m7)
        fm8 = float(m8)
        fmx = fm2 / fm8
        fmy = fm5 / fm8
        u0 = fm0 - fmx * fm6
        u1 = fm1 - fmx * fm7
        u2 = fm2 - fmx * fm8
        v0 = fm3 - fmy * fm6
        v1 = fm4 - fmy * fm7
        v2 = fm5 - fmy * fm8
        aux[i, 4] = v1 * fm8 - v2 * fm7
        aux[i, 5] = v2 * fm6 - v0 * fm8
        aux[i, 6] = v0 * fm7 - v1 * fm6
        aux[i, 7] = u1 * fm8 - u2 * fm7
        aux[i, 8] = u2 * fm6 - u0 * fm8
        aux[i, 9] = u0 * fm7 - u1 * fm6
        aux[i, 10] = u1 * v2 - u2 * v1
        aux[i, 11] = u2 * v0 - u0 * v2
        aux[i, 12] = u0 * v1 - u1 * v0
        if _exact_tiles(bbox, i):
            # tiles the footprint really touches (a slanted or near-camera splat covers few of its box's)
            spans = np.empty((TILE, 2), np.int64)
            cnt = 0
            for ty in range(y0 // TILE, y1 // TILE + 1):
                txa, txb = _band_tiles(aux, bbox, i, ty, True, spans)
                cnt += txb - txa + 1
            ntiles[i] = cnt
            if cnt == 0:
                radii[i] = 0
                bbox[i, 0] = 0
                bbox[i, 1] = -1
                bbox[i, 2] = 0
                bbox[i, 3] = -1


@njit(cache=True)
def radix_argsort_u32(keys):
    """Stable argsort of ``uint32`` keys (3 passes of 11 bits). Positive float32 depths viewed as
    ``uint32`` sort in the same order as the floats."""
    n = keys.shape[0]
    idx = np.arange(n).astype(np.int64)
    tmp = np.empty(n, np.int64)
    k = keys.copy()
    ktmp = np.empty_like(k)
    for shift in (0, 11, 22):
        count = np.zeros(2049, np.int64)
        for i in range(n):
            count[((k[i] >> shift) & 2047) + 1] += 1
        for b in range(2048):
            count[b + 1] += count[b]
        for i in range(n):
            b = (k[i] >> shift) & 2047
            pos = count[b]
            count[b] = pos + 1
            tmp[pos] = idx[i]
            ktmp[pos] = k[i]
        idx, tmp = tmp, idx
        k, ktmp = ktmp, k
    return idx


@njit(parallel=True, cache=True, error_model="numpy")
def bin_tiles(order, bbox, aux, ntiles, width, height, nchunk):
    """Bin depth-sorted Gaussians into 16x16 tiles, keeping the depth order inside each tile.

    ``order``: visible Gaussian ids sorted front to back. Returns ``tile_off (T+1)``, ``gids (P)``
    (the Gaussians of tile ``t`` are ``gids[tile_off[t]:tile_off[t+1]]``), ``xstart (N+1)``,
    ``gslot (P)`` and ``pbox (P)``. Tile-list entry ``j`` writes its per-pair results to row
    ``gslot[j]`` of a buffer of ``N + xstart[N]`` rows: the first tile of Gaussian ``g`` writes
    row ``g`` itself, its other tiles the extra rows ``N + xstart[g] .. N + xstart[g+1] - 1``, so
    :func:`reduce_pairs` leaves the per-Gaussian sums in rows ``0..N-1`` in place and only touches
    the Gaussians that span several tiles. ``pbox[j]``: the entry's screen box clipped to its tile,
    in tile-local pixels, packed as bytes ``x0 | x1 << 8 | y0 << 16 | y1 << 24`` (the tile kernels
    read it in tile-list order instead of fetching the scattered ``bbox`` row). Gaussians with
    exact coverage (:func:`_exact_tiles`) get only the tiles their row spans reach, and per tile
    the box of the spans' pixels inside it (an empty box ``1 | 0 | 1 << 16 | 0`` when none).
    """
    tiles_x = (width + TILE - 1) // TILE
    tiles_y = (height + TILE - 1) // TILE
    ntile = tiles_x * tiles_y
    nv = order.shape[0]
    n = ntiles.shape[0]
    xstart = np.empty(n + 1, np.int64)
    xstart[0] = 0
    npair = 0
    for g in range(n):
        xstart[g + 1] = xstart[g] + max(ntiles[g] - 1, 0)
        npair += ntiles[g]
    cb = np.empty(nchunk + 1, np.int64)
    for c in range(nchunk + 1):
        cb[c] = (nv * c) // nchunk
    counts = np.zeros((nchunk, ntile), np.int64)
    for c in prange(nchunk):
        spans = np.empty((TILE, 2), np.int64)
        for s in range(cb[c], cb[c + 1]):
            g = order[s]
            exact = _exact_tiles(bbox, g)
            for ty in range(bbox[g, 2] // TILE, bbox[g, 3] // TILE + 1):
                txa, txb = _band_tiles(aux, bbox, g, ty, exact, spans)
                for tx in range(txa, txb + 1):
                    counts[c, ty * tiles_x + tx] += 1
    tile_off = np.empty(ntile + 1, np.int64)
    cursor = np.empty((nchunk, ntile), np.int64)
    run = 0
    for t in range(ntile):
        tile_off[t] = run
        for c in range(nchunk):
            cursor[c, t] = run
            run += counts[c, t]
    tile_off[ntile] = run
    gids = np.empty(npair, np.int32)
    gslot = np.empty(npair, np.int64)
    pbox = np.empty(npair, np.uint32)
    for c in prange(nchunk):
        spans = np.empty((TILE, 2), np.int64)
        for s in range(cb[c], cb[c + 1]):
            g = order[s]
            k = g
            bx0 = bbox[g, 0]
            bx1 = bbox[g, 1]
            by0 = bbox[g, 2]
            by1 = bbox[g, 3]
            exact = _exact_tiles(bbox, g)
            for ty in range(by0 // TILE, by1 // TILE + 1):
                ly0 = max(by0 - ty * TILE, 0)
                ly1 = min(by1 - ty * TILE, TILE - 1)
                txa, txb = _band_tiles(aux, bbox, g, ty, exact, spans)
                for tx in range(txa, txb + 1):
                    lx0 = max(bx0 - tx * TILE, 0)
                    lx1 = min(bx1 - tx * TILE, TILE - 1)
                    if exact:
                        # box of the row spans' pixels inside this tile
                        ex0 = TILE
                        ex1 = -1
                        ey0 = TILE
                        ey1 = -1
                        for r in range(TILE):
                            a = max(spans[r, 0] - tx * TILE, 0)
                            b = min(spans[r, 1] - tx * TILE, TILE - 1)
                            if a <= b:
                                ex0 = min(ex0, a)
                                ex1 = max(ex1, b)
                                ey0 = min(ey0, r)
                                ey1 = max(ey1, r)
                        if ex1 < 0:
                            lx0, lx1, ey0, ey1 = 1, 0, 1, 0
                        else:
                            lx0, lx1 = ex0, ex1
                        ly0 = ey0
                        ly1 = ey1
                    t = ty * tiles_x + tx
                    pos = cursor[c, t]
                    cursor[c, t] = pos + 1
                    gids[pos] = g
                    gslot[pos] = k
                    pbox[pos] = lx0 | (lx1 << 8) | (ly0 << 16) | (ly1 << 24)
                    k = n + xstart[g] if k == g else k + 1
    return tile_off, gids, xstart, gslot, pbox


@njit(parallel=True, cache=True)
def reduce_pairs(buf, used, xstart, ntiles, out):
    """Per-Gaussian sums of the per-pair rows (row layout: :func:`bin_tiles`).

    Row ``g`` of ``out`` (``(N, k)``; may be ``buf`` itself: in place) becomes the sum of Gaussian
    ``g``'s rows of ``buf`` (row ``g``, then its extra rows ``N + xstart[g] ...``) that have
    ``used[q] != 0`` (every row when ``used`` is empty); rows not used are never read, so they may
    hold garbage. Gaussians without tiles get zeros."""
    n = ntiles.shape[0]
    k = buf.shape[1]
    every = used.shape[0] == 0
    for g in prange(n):
        if ntiles[g] == 0 or not (every or used[g] != 0):
            for c in range(k):
                out[g, c] = 0
        else:
            for c in range(k):
                out[g, c] = buf[g, c]
        for q in range(n + xstart[g], n + xstart[g + 1]):
            if every or used[q] != 0:
                for c in range(k):
                    out[g, c] += buf[q, c]


# ------------------------------------------------------------------------------ forward


@njit(cache=True, inline="always")
def _prefetch_pair(params, aux, rows, g, q):
    """Prefetch Gaussian ``g``'s parameter and auxiliary records and per-pair output row ``q``."""
    prefetch_row(params, g)
    prefetch_at(params, g, NPARAM - 1)
    prefetch_row(aux, g)
    prefetch_at(aux, g, 12)
    prefetch_w(rows, q)


@njit(parallel=True, cache=True, error_model="numpy")
def forward_tiles(params, aux, pbox, tile_off, gids, gslot, cst, width, height, xs, ys, bg, loss,
                  has_loss, out_rgb, out_depth, out_normal, out_alpha, out_dist, out_T, out_last,
                  out_count, out_d1, out_d2, pair_stats, pmask, tile_evals):
    """Front-to-back compositing of every tile. Fills the per-pixel outputs, the saved state of
    the backward pass (final ``T``, number of tile-list entries up to the last contributor,
    distortion accumulators ``sum w m`` and ``sum w m^2``, and ``pmask (P, 4)``: per tile-list
    entry the 256-bit mask of the tile's pixels it was composited into, bit ``p`` of word
    ``p >> 6`` for tile pixel ``p = 16 ly + lx``), per-pair stats and per-tile counts of evaluated
    pixel-Gaussian pairs."""
    tiles_x = (width + TILE - 1) // TILE
    tiles_y = (height + TILE - 1) // TILE
    zero = cst[_ZERO]
    one = cst[_ONE]
    half = cst[_HALF]
    two = cst[_TWO]
    amin = cst[_AMIN]
    amax = cst[_AMAX]
    tmin = cst[_TMIN]
    near = cst[_NEAR]
    da = cst[_DA]
    dn = cst[_DN]
    for t in prange(tiles_x * tiles_y):
        tx = t % tiles_x
        ty = t // tiles_x
        px0 = tx * TILE
        py0 = ty * TILE
        px1 = min(px0 + TILE, width) - 1
        py1 = min(py0 + TILE, height) - 1
        npix = (px1 - px0 + 1) * (py1 - py0 + 1)
        T = np.ones(TILE_PIX, params.dtype)
        acc = np.zeros((TILE_PIX, 11), params.dtype)  # rgb 3, depth, normal 3, dist, d1, d2, -
        last = np.zeros(TILE_PIX, np.int32)
        pcount = np.zeros(TILE_PIX, np.int32)
        done = np.zeros(TILE_PIX, np.uint8)
        fm = np.zeros(4, np.uint64)
        bit1 = np.uint64(1)
        ndone = 0
        evals = 0
        start = tile_off[t]
        end = tile_off[t + 1]
        j = start
        while j < end:
            if ndone == npix:
                break
            if j + PREFETCH < end:
                _prefetch_pair(params, aux, pair_stats, gids[j + PREFETCH], gslot[j + PREFETCH])
            g = gids[j]
            m0 = params[g, 0]
            m1 = params[g, 1]
            m2 = params[g, 2]
            m3 = params[g, 3]
            m4 = params[g, 4]
            m5 = params[g, 5]
            m6 = params[g, 6]
            m7 = params[g, 7]
            m8 = params[g, 8]
            o = params[g, 9]
            cr = params[g, 10]
            cg = params[g, 11]
            cb = params[g, 12]
            n0 = params[g, 13]
            n1 = params[g, 14]
            n2 = params[g, 15]
            mx = aux[g, 0]
            my = aux[g, 1]
            kcut = aux[g, 2]
            aa0 = aux[g, 4]
            aa1 = aux[g, 5]
            aa2 = aux[g, 6]
            bb0 = aux[g, 7]
            bb1 = aux[g, 8]
            bb2 = aux[g, 9]
            cc0 = aux[g, 10]
            cc1 = aux[g, 11]
            cc2 = aux[g, 12]
            mm8 = da * (one - dn / m8)
            pb = pbox[j]
            x0 = px0 + (pb & 255)
            x1 = px0 + ((pb >> 8) & 255)
            y0 = py0 + ((pb >> 16) & 255)
            y1 = py0 + (pb >> 24)
            sw = zero
            se = zero
            cnt = 0
            for w4 in range(4):
                fm[w4] = 0
            for y in range(y0, y1 + 1):
                dy = ys[y] - my
                dy2 = dy * dy
                # c = h_u x h_v = (x - mx) A - (y - my) B + C  (line coordinates, see preprocess)
                ey0 = cc0 - dy * bb0
                ey1 = cc1 - dy * bb1
                ey2 = cc2 - dy * bb2
                prow = (y - py0) * TILE - px0
                for x in range(x0, x1 + 1):
                    p = prow + x
                    if done[p]:
                        continue
                    evals += 1
                    dx = xs[x] - mx
                    rho = two * (dx * dx + dy2)
                    # (u, v) = (c0, c1) / c2; hit z = q / c2. Decide the branch without dividing:
                    # 3D when u^2+v^2 < rho (s < rho c2^2) and z > near (q c2 > near c2^2).
                    c0 = dx * aa0 + ey0
                    c1 = dx * aa1 + ey1
                    c2 = dx * aa2 + ey2
                    s = c0 * c0 + c1 * c1
                    c22 = c2 * c2
                    q = m6 * c0 + m7 * c1 + m8 * c2
                    use3 = s < rho * c22 and q * c2 > near * c22
                    r = zero
                    if use3:
                        r = one / (c22 * q)
                        rho = s * q * r
                    if rho > kcut:
                        continue
                    alpha = o * np.exp(-half * rho)
                    if alpha > amax:
                        alpha = amax
                    if alpha < amin:
                        continue
                    tp = T[p]
                    nt = tp * (one - alpha)
                    if nt < tmin:
                        done[p] = 1
                        ndone += 1
                        continue
                    w = alpha * tp
                    if use3:
                        depth = q * q * c2 * r
                        mm = da * (one - dn * (c2 * c22 * r))
                    else:
                        depth = m8
                        mm = mm8
                    acc[p, 0] += w * cr
                    acc[p, 1] += w * cg
                    acc[p, 2] += w * cb
                    acc[p, 3] += w * depth
                    acc[p, 4] += w * n0
                    acc[p, 5] += w * n1
                    acc[p, 6] += w * n2
                    acc[p, 7] += w * (mm * mm * (one - tp) + acc[p, 9] - two * mm * acc[p, 8])
                    acc[p, 8] += w * mm
                    acc[p, 9] += w * mm * mm
                    T[p] = nt
                    last[p] = j - start + 1
                    pcount[p] += 1
                    fm[p >> 6] |= bit1 << np.uint64(p & 63)
                    sw += w
                    cnt += 1
                    if has_loss:
                        se += w * loss[y, x]
            q = gslot[j]
            pair_stats[q, 0] = sw
            pair_stats[q, 1] = cnt
            pair_stats[q, 2] = se
            for w4 in range(4):
                pmask[j, w4] = fm[w4]
            j += 1
        while j < end:  # Gaussians behind the point where every pixel terminated
            q = gslot[j]
            pair_stats[q, 0] = zero
            pair_stats[q, 1] = zero
            pair_stats[q, 2] = zero
            for w4 in range(4):
                pmask[j, w4] = 0
            j += 1
        tile_evals[t] = evals
        for y in range(py0, py1 + 1):
            for x in range(px0, px1 + 1):
                p = (y - py0) * TILE + (x - px0)
                tp = T[p]
                out_rgb[y, x, 0] = acc[p, 0] + tp * bg[0]
                out_rgb[y, x, 1] = acc[p, 1] + tp * bg[1]
                out_rgb[y, x, 2] = acc[p, 2] + tp * bg[2]
                out_depth[y, x] = acc[p, 3]
                out_normal[y, x, 0] = acc[p, 4]
                out_normal[y, x, 1] = acc[p, 5]
                out_normal[y, x, 2] = acc[p, 6]
                out_alpha[y, x] = one - tp
                out_dist[y, x] = acc[p, 7]
                out_T[y, x] = tp
                out_last[y, x] = last[p]
                out_count[y, x] = pcount[p]
                out_d1[y, x] = acc[p, 8]
                out_d2[y, x] = acc[p, 9]


# ------------------------------------------------------------------------------ backward


@njit(parallel=True, cache=True, error_model="numpy")
def select_pixels(score, ratio, out_sel):
    """Per 16x16 tile, mark the ``ceil(ratio * n)`` pixels of highest ``score`` (ties: lower
    row-major index first; a NaN score ranks below every number). ``ratio >= 1`` marks every
    pixel, a ratio so small that ``ceil(ratio * n)`` is 0 none."""
    height, width = score.shape
    tiles_x = (width + TILE - 1) // TILE
    tiles_y = (height + TILE - 1) // TILE
    for t in prange(tiles_x * tiles_y):
        tx = t % tiles_x
        ty = t // tiles_x
        px0 = tx * TILE
        py0 = ty * TILE
        px1 = min(px0 + TILE, width)
        py1 = min(py0 + TILE, height)
        n = (px1 - px0) * (py1 - py0)
        k = int(np.ceil(ratio * n - 1e-9))
        if k <= 0:
            for y in range(py0, py1):
                for x in range(px0, px1):
                    out_sel[y, x] = 0
            continue
        if k >= n:
            for y in range(py0, py1):
                for x in range(px0, px1):
                    out_sel[y, x] = 1
            continue
        vals = np.empty(n, np.float64)
        q = 0
        for y in range(py0, py1):
            for x in range(px0, px1):
                v = -score[y, x]
                # NaN last (as +inf): a NaN threshold would select no pixel of the tile
                vals[q] = v if v == v else np.inf
                out_sel[y, x] = 0
                q += 1
        # k-th best score by quickselect, then the strictly better pixels and, in row-major
        # order, as many ties as needed (same result as a stable sort, O(n))
        thr = np.partition(vals.copy(), k - 1)[k - 1]
        taken = 0
        for q in range(n):
            if vals[q] < thr:
                taken += 1
        tw = px1 - px0
        for q in range(n):
            v = vals[q]
            if v < thr or (v == thr and taken < k):
                if v == thr:
                    taken += 1
                out_sel[py0 + q // tw, px0 + q % tw] = 1


@njit(parallel=True, cache=True, error_model="numpy")
def backward_tiles(params, aux, pmask, tile_off, gids, gslot, cst, width, height, xs, ys, bg, T_final,
                   last, d1, d2, g_rgb, g_depth, g_normal, g_alpha, g_dist, sel, pair_grad,
                   pair_used, tile_evals):
    """Back-to-front pass over the selected pixels (``sel != 0``) of every tile.

    Rebuilds ``T`` from the saved final transmittance (``T_i = T_{i+1} / (1 - alpha_i)``) and keeps
    per pixel ``R = sum_{k>i} w_k g_k + T_N bg.dL/dC``, so ``dL/dalpha_i = T_i g_i - R / (1 -
    alpha_i)`` where ``g_i`` gathers the colour, depth, normal, alpha and distortion terms. For each
    (tile, Gaussian) pair the sum over the tile's selected pixels of dL/d(M, opacity, rgb, normal)
    goes to row ``gslot[j]`` of ``pair_grad``; every alpha is recomputed with the forward's exact
    expressions. ``pair_used[gslot[j]]`` is set to 1 when the pair touched a selected pixel, else
    to 0 and its ``pair_grad`` row is left unwritten (:func:`reduce_pairs` skips it).

    Work is proportional to the selected pixels: each pair visits exactly the set bits of its
    forward mask ``pmask[j]`` (the pixels it was composited into) ANDed with the tile's selected
    pixels, and a pair left with none is skipped at once (no record loaded). The records of the
    pair a few *visited* pairs ahead, and its gradient row, are prefetched, so the scattered
    per-Gaussian memory does not stall every pair.
    """
    tiles_x = (width + TILE - 1) // TILE
    tiles_y = (height + TILE - 1) // TILE
    zero = cst[_ZERO]
    one = cst[_ONE]
    half = cst[_HALF]
    two = cst[_TWO]
    amax = cst[_AMAX]
    near = cst[_NEAR]
    da = cst[_DA]
    dn = cst[_DN]
    bit1 = np.uint64(1)
    for t in prange(tiles_x * tiles_y):
        tx = t % tiles_x
        ty = t // tiles_x
        px0 = tx * TILE
        py0 = ty * TILE
        px1 = min(px0 + TILE, width) - 1
        py1 = min(py0 + TILE, height) - 1
        start = tile_off[t]
        end = tile_off[t + 1]
        # per-pixel state: T, R (= sum_{k>i} w_k g_k + T_N bg.dC), loss grads, totals
        st = np.empty((TILE_PIX, 16), params.dtype)
        smask = np.zeros(4, np.uint64)
        maxlast = 0
        for y in range(py0, py1 + 1):
            for x in range(px0, px1 + 1):
                lp = last[y, x]
                if sel[y, x] == 0 or lp == 0:
                    continue  # not selected, or nothing composited here
                if lp > maxlast:
                    maxlast = lp
                p = (y - py0) * TILE + (x - px0)
                smask[p >> 6] |= bit1 << np.uint64(p & 63)
                tf = T_final[y, x]
                st[p, 0] = tf
                st[p, 1] = tf * (bg[0] * g_rgb[y, x, 0] + bg[1] * g_rgb[y, x, 1]
                                 + bg[2] * g_rgb[y, x, 2])
                st[p, 2] = g_rgb[y, x, 0]
                st[p, 3] = g_rgb[y, x, 1]
                st[p, 4] = g_rgb[y, x, 2]
                st[p, 5] = g_depth[y, x]
                st[p, 6] = g_normal[y, x, 0]
                st[p, 7] = g_normal[y, x, 1]
                st[p, 8] = g_normal[y, x, 2]
                st[p, 9] = g_alpha[y, x]
                st[p, 10] = g_dist[y, x]
                st[p, 11] = one - tf        # A_tot
                st[p, 12] = d1[y, x]        # sum w m
                st[p, 13] = d2[y, x]        # sum w m^2
        s0 = smask[0]
        s1m = smask[1]
        s2m = smask[2]
        s3m = smask[3]
        # entries behind the last contributor of every selected pixel touch none of them
        for j in range(start + maxlast, end):
            pair_used[gslot[j]] = 0
        # pass 1: the entries (back to front) whose mask meets a selected pixel; sampling leaves
        # many pairs with none, so the prefetch below runs PREFETCH *visited* pairs ahead
        visit = np.empty(maxlast, np.int64)
        masks = np.empty((maxlast, 4), np.uint64)
        nv = 0
        for j in range(start + maxlast - 1, start - 1, -1):
            a0 = pmask[j, 0] & s0
            a1 = pmask[j, 1] & s1m
            a2 = pmask[j, 2] & s2m
            a3 = pmask[j, 3] & s3m
            if (a0 | a1 | a2 | a3) == 0:
                pair_used[gslot[j]] = 0
                continue
            pair_used[gslot[j]] = 1
            visit[nv] = j
            masks[nv, 0] = a0
            masks[nv, 1] = a1
            masks[nv, 2] = a2
            masks[nv, 3] = a3
            nv += 1
        for k in range(min(PREFETCH, nv)):
            _prefetch_pair(params, aux, pair_grad, gids[visit[k]], gslot[visit[k]])
        evals = 0
        for k in range(nv):
            if k + PREFETCH < nv:
                jp = visit[k + PREFETCH]
                _prefetch_pair(params, aux, pair_grad, gids[jp], gslot[jp])
            j = visit[k]
            q = gslot[j]
            g = gids[j]
            m0 = params[g, 0]
            m1 = params[g, 1]
            m2 = params[g, 2]
            m3 = params[g, 3]
            m4 = params[g, 4]
            m5 = params[g, 5]
            m6 = params[g, 6]
            m7 = params[g, 7]
            m8 = params[g, 8]
            o = params[g, 9]
            cr = params[g, 10]
            cg = params[g, 11]
            cb = params[g, 12]
            n0 = params[g, 13]
            n1 = params[g, 14]
            n2 = params[g, 15]
            mx = aux[g, 0]
            my = aux[g, 1]
            aa0 = aux[g, 4]
            aa1 = aux[g, 5]
            aa2 = aux[g, 6]
            bb0 = aux[g, 7]
            bb1 = aux[g, 8]
            bb2 = aux[g, 9]
            cc0 = aux[g, 10]
            cc1 = aux[g, 11]
            cc2 = aux[g, 12]
            # centred rows M0' = M_0 - mx M_2, M1' = M_1 - my M_2: h_u = (x-mx) M_2 - M0', etc.
            u0 = m0 - mx * m6
            u1 = m1 - mx * m7
            u2 = m2 - mx * m8
            w0 = m3 - my * m6
            w1 = m4 - my * m7
            w2 = m5 - my * m8
            im8 = one / m8
            gm0 = zero
            gm1 = zero
            gm2 = zero
            gm3 = zero
            gm4 = zero
            gm5 = zero
            gm6 = zero
            gm7 = zero
            gm8 = zero
            go = zero
            gcr = zero
            gcg = zero
            gcb = zero
            gn0 = zero
            gn1 = zero
            gn2 = zero
            for w in range(4):
                bits = masks[k, w]
                while bits != 0:
                    p = (w << 6) | int(ctz64(bits))
                    bits &= bits - bit1
                    evals += 1
                    xf = xs[px0 + (p & 15)]
                    yf = ys[py0 + (p >> 4)]
                    dx = xf - mx
                    dy = yf - my
                    rho = two * (dx * dx + dy * dy)
                    # c = h_u x h_v = (x - mx) A - (y - my) B + C, same expressions as the forward
                    c0 = dx * aa0 + (cc0 - dy * bb0)
                    c1 = dx * aa1 + (cc1 - dy * bb1)
                    c2 = dx * aa2 + (cc2 - dy * bb2)
                    s = c0 * c0 + c1 * c1
                    c22 = c2 * c2
                    qz = m6 * c0 + m7 * c1 + m8 * c2
                    use3 = s < rho * c22 and qz * c2 > near * c22
                    r = zero
                    if use3:
                        r = one / (c22 * qz)
                        rho = s * qz * r
                    # the forward composited this pixel, so rho <= rho_cut and alpha >= 1/255 here
                    gauss = np.exp(-half * rho)
                    alpha = o * gauss
                    clamped = alpha > amax
                    if clamped:
                        alpha = amax
                    om = one - alpha
                    ti = st[p, 0] / om
                    wt = alpha * ti
                    dcr = st[p, 2]
                    dcg = st[p, 3]
                    dcb = st[p, 4]
                    ddep = st[p, 5]
                    dn0 = st[p, 6]
                    dn1 = st[p, 7]
                    dn2 = st[p, 8]
                    ddist = st[p, 10]
                    atot = st[p, 11]
                    s1 = st[p, 12]
                    s2 = st[p, 13]
                    if use3:
                        ic = c2 * qz * r
                        u = c0 * ic
                        v = c1 * ic
                        depth = qz * ic
                        invd = c2 * c22 * r
                    else:
                        ic = zero
                        u = zero
                        v = zero
                        depth = m8
                        invd = im8
                    mm = da * (one - dn * invd)
                    gk = (dcr * cr + dcg * cg + dcb * cb + ddep * depth + dn0 * n0 + dn1 * n1
                          + dn2 * n2 + st[p, 9] + ddist * (mm * mm * atot - two * mm * s1 + s2))
                    dl_dalpha = ti * gk - st[p, 1] / om
                    st[p, 1] += wt * gk
                    st[p, 0] = ti
                    gcr += wt * dcr
                    gcg += wt * dcg
                    gcb += wt * dcb
                    gn0 += wt * dn0
                    gn1 += wt * dn1
                    gn2 += wt * dn2
                    dl_ddepth = wt * ddep + ddist * two * wt * (mm * atot - s1) * (da * dn * invd * invd)
                    dl_drho = zero
                    if not clamped:
                        go += gauss * dl_dalpha
                        dl_drho = -half * gauss * o * dl_dalpha
                    if use3:
                        dl_du = dl_drho * two * u + dl_ddepth * m6
                        dl_dv = dl_drho * two * v + dl_ddepth * m7
                        gm6 += dl_ddepth * u
                        gm7 += dl_ddepth * v
                        gm8 += dl_ddepth
                        e0 = dl_du * ic
                        e1 = dl_dv * ic
                        e2 = -(dl_du * u + dl_dv * v) * ic
                        hu0 = dx * m6 - u0
                        hu1 = dx * m7 - u1
                        hu2 = dx * m8 - u2
                        hv0 = dy * m6 - w0
                        hv1 = dy * m7 - w1
                        hv2 = dy * m8 - w2
                        # c = h_u x h_v:  dL/dh_u = h_v x e,  dL/dh_v = e x h_u
                        fu0 = hv1 * e2 - hv2 * e1
                        fu1 = hv2 * e0 - hv0 * e2
                        fu2 = hv0 * e1 - hv1 * e0
                        fv0 = e1 * hu2 - e2 * hu1
                        fv1 = e2 * hu0 - e0 * hu2
                        fv2 = e0 * hu1 - e1 * hu0
                        gm0 -= fu0
                        gm1 -= fu1
                        gm2 -= fu2
                        gm3 -= fv0
                        gm4 -= fv1
                        gm5 -= fv2
                        gm6 += xf * fu0 + yf * fv0
                        gm7 += xf * fu1 + yf * fv1
                        gm8 += xf * fu2 + yf * fv2
                    else:
                        # rho = 2 |(x,y) - (m2/m8, m5/m8)|^2, depth = m8
                        gmx = -two * two * dx * dl_drho
                        gmy = -two * two * dy * dl_drho
                        gm2 += gmx * im8
                        gm5 += gmy * im8
                        gm8 += dl_ddepth - (gmx * mx + gmy * my) * im8
            pair_grad[q, 0] = gm0
            pair_grad[q, 1] = gm1
            pair_grad[q, 2] = gm2
            pair_grad[q, 3] = gm3
            pair_grad[q, 4] = gm4
            pair_grad[q, 5] = gm5
            pair_grad[q, 6] = gm6
            pair_grad[q, 7] = gm7
            pair_grad[q, 8] = gm8
            pair_grad[q, 9] = go
            pair_grad[q, 10] = gcr
            pair_grad[q, 11] = gcg
            pair_grad[q, 12] = gcb
            pair_grad[q, 13] = gn0
            pair_grad[q, 14] = gn1
            pair_grad[q, 15] = gn2
        tile_evals[t] = evals


# ------------------------------------------------------------------------------ projection


@njit(parallel=True, cache=True, error_model="numpy")
def project_fwd(means, quats, scales, opac, colors, Rcw, tcw, fx, fy, cx, cy, out, sign):
    """Per-Gaussian record ``out (N, 16)`` (see :mod:`.project`): ray-splat transform
    ``M = K [R_cw R e0 s_u | R_cw R e1 s_v | R_cw p + t_cw]``, opacity, rgb, camera-frame normal
    facing the camera (``sign[i]`` = +-1, the flip applied). Same maths as
    :func:`.project.project_surfels` (its torch reference)."""
    n = means.shape[0]
    for i in prange(n):
        qx = quats[i, 0]
        qy = quats[i, 1]
        qz = quats[i, 2]
        qw = quats[i, 3]
        qn = np.sqrt(qx * qx + qy * qy + qz * qz + qw * qw)
        x = qx / qn
        y = qy / qn
        z = qz / qn
        w = qw / qn
        r00 = 1 - 2 * (y * y + z * z)
        r01 = 2 * (x * y - z * w)
        r02 = 2 * (x * z + y * w)
        r10 = 2 * (x * y + z * w)
        r11 = 1 - 2 * (x * x + z * z)
        r12 = 2 * (y * z - x * w)
        r20 = 2 * (x * z - y * w)
        r21 = 2 * (y * z + x * w)
        r22 = 1 - 2 * (x * x + y * y)
        su = scales[i, 0]
        sv = scales[i, 1]
        # camera-frame tangent axes (scaled), normal and centre
        tu0 = (Rcw[0, 0] * r00 + Rcw[0, 1] * r10 + Rcw[0, 2] * r20) * su
        tu1 = (Rcw[1, 0] * r00 + Rcw[1, 1] * r10 + Rcw[1, 2] * r20) * su
        tu2 = (Rcw[2, 0] * r00 + Rcw[2, 1] * r10 + Rcw[2, 2] * r20) * su
        tv0 = (Rcw[0, 0] * r01 + Rcw[0, 1] * r11 + Rcw[0, 2] * r21) * sv
        tv1 = (Rcw[1, 0] * r01 + Rcw[1, 1] * r11 + Rcw[1, 2] * r21) * sv
        tv2 = (Rcw[2, 0] * r01 + Rcw[2, 1] * r11 + Rcw[2, 2] * r21) * sv
        nn0 = Rcw[0, 0] * r02 + Rcw[0, 1] * r12 + Rcw[0, 2] * r22
        nn1 = Rcw[1, 0] * r02 + Rcw[1, 1] * r12 + Rcw[1, 2] * r22
        nn2 = Rcw[2, 0] * r02 + Rcw[2, 1] * r12 + Rcw[2, 2] * r22
        px = means[i, 0]
        py = means[i, 1]
        pz = means[i, 2]
        pc0 = Rcw[0, 0] * px + Rcw[0, 1] * py + Rcw[0, 2] * pz + tcw[0]
        pc1 = Rcw[1, 0] * px + Rcw[1, 1] * py + Rcw[1, 2] * pz + tcw[1]
        pc2 = Rcw[2, 0] * px + Rcw[2, 1] * py + Rcw[2, 2] * pz + tcw[2]
        out[i, 0] = fx * tu0 + cx * tu2
        out[i, 1] = fx * tv0 + cx * tv2
        out[i, 2] = fx * pc0 + cx * pc2
        out[i, 3] = fy * tu1 + cy * tu2
        out[i, 4] = fy * tv1 + cy * tv2
        out[i, 5] = fy * pc1 + cy * pc2
        out[i, 6] = tu2
        out[i, 7] = tv2
        out[i, 8] = pc2
        out[i, 9] = opac[i]
        out[i, 10] = colors[i, 0]
        out[i, 11] = colors[i, 1]
        out[i, 12] = colors[i, 2]
        sg = -1.0 if nn0 * pc0 + nn1 * pc1 + nn2 * pc2 > 0 else 1.0
        sign[i] = sg
        out[i, 13] = nn0 * sg
        out[i, 14] = nn1 * sg
        out[i, 15] = nn2 * sg


@njit(parallel=True, cache=True, error_model="numpy")
def project_bwd(means, quats, scales, sign, dpar, Rcw, fx, fy, cx, cy, want_pose, d_means,
                d_quats, d_scales, d_opac, d_rgb, d_pose):
    """Chain rule of :func:`project_fwd`: from ``dpar = dL/d record (N, 16)`` to dL/d means,
    quats (through the normalisation), scales, opacities ``d_opac (N,)`` and colours ``d_rgb
    (N, 3)`` (record columns 9 and 10-12, copied), and per-Gaussian contributions to dL/dR_cw (9,
    row-major) and dL/dt_cw (3) in ``d_pose (N, 12)`` when ``want_pose``. Gaussians whose
    geometric gradient (``dL/dM``, ``dL/dnormal``) is zero (culled, or no selected pixel) get zeros
    without the chain rule."""
    n = means.shape[0]
    for i in prange(n):
        d_opac[i] = dpar[i, 9]
        d_rgb[i, 0] = dpar[i, 10]
        d_rgb[i, 1] = dpar[i, 11]
        d_rgb[i, 2] = dpar[i, 12]
        active = False
        for c in range(9):
            if dpar[i, c] != 0:
                active = True
        for c in range(13, 16):
            if dpar[i, c] != 0:
                active = True
        if not active:
            for c in range(3):
                d_means[i, c] = 0
            for c in range(4):
                d_quats[i, c] = 0
            d_scales[i, 0] = 0
            d_scales[i, 1] = 0
            if want_pose:
                for c in range(12):
                    d_pose[i, c] = 0
            continue
        qx = quats[i, 0]
        qy = quats[i, 1]
        qz = quats[i, 2]
        qw = quats[i, 3]
        qn = np.sqrt(qx * qx + qy * qy + qz * qz + qw * qw)
        x = qx / qn
        y = qy / qn
        z = qz / qn
        w = qw / qn
        r00 = 1 - 2 * (y * y + z * z)
        r01 = 2 * (x * y - z * w)
        r02 = 2 * (x * z + y * w)
        r10 = 2 * (x * y + z * w)
        r11 = 1 - 2 * (x * x + z * z)
        r12 = 2 * (y * z - x * w)
        r20 = 2 * (x * z - y * w)
        r21 = 2 * (y * z + x * w)
        r22 = 1 - 2 * (x * x + y * y)
        su = scales[i, 0]
        sv = scales[i, 1]
        # dL/dA where A = [tu | tv | p_c] (columns) and M = K A
        dm0 = dpar[i, 0]
        dm1 = dpar[i, 1]
        dm2 = dpar[i, 2]
        dm3 = dpar[i, 3]
        dm4 = dpar[i, 4]
        dm5 = dpar[i, 5]
        dm6 = dpar[i, 6]
        dm7 = dpar[i, 7]
        dm8 = dpar[i, 8]
        dtu0 = fx * dm0
        dtu1 = fy * dm3
        dtu2 = cx * dm0 + cy * dm3 + dm6
        dtv0 = fx * dm1
        dtv1 = fy * dm4
        dtv2 = cx * dm1 + cy * dm4 + dm7
        dpc0 = fx * dm2
        dpc1 = fy * dm5
        dpc2 = cx * dm2 + cy * dm5 + dm8
        sg = sign[i]
        dn0 = dpar[i, 13] * sg
        dn1 = dpar[i, 14] * sg
        dn2 = dpar[i, 15] * sg
        # Rc = R_cw R: columns Rc0 = tu / su, Rc1 = tv / sv, Rc2 = n
        rc00 = Rcw[0, 0] * r00 + Rcw[0, 1] * r10 + Rcw[0, 2] * r20
        rc10 = Rcw[1, 0] * r00 + Rcw[1, 1] * r10 + Rcw[1, 2] * r20
        rc20 = Rcw[2, 0] * r00 + Rcw[2, 1] * r10 + Rcw[2, 2] * r20
        rc01 = Rcw[0, 0] * r01 + Rcw[0, 1] * r11 + Rcw[0, 2] * r21
        rc11 = Rcw[1, 0] * r01 + Rcw[1, 1] * r11 + Rcw[1, 2] * r21
        rc21 = Rcw[2, 0] * r01 + Rcw[2, 1] * r11 + Rcw[2, 2] * r21
        d_scales[i, 0] = dtu0 * rc00 + dtu1 * rc10 + dtu2 * rc20
        d_scales[i, 1] = dtv0 * rc01 + dtv1 * rc11 + dtv2 * rc21
        # dL/dRc columns
        g00 = dtu0 * su
        g10 = dtu1 * su
        g20 = dtu2 * su
        g01 = dtv0 * sv
        g11 = dtv1 * sv
        g21 = dtv2 * sv
        g02 = dn0
        g12 = dn1
        g22 = dn2
        # dL/dR = R_cw^T dL/dRc
        G00 = Rcw[0, 0] * g00 + Rcw[1, 0] * g10 + Rcw[2, 0] * g20
        G10 = Rcw[0, 1] * g00 + Rcw[1, 1] * g10 + Rcw[2, 1] * g20
        G20 = Rcw[0, 2] * g00 + Rcw[1, 2] * g10 + Rcw[2, 2] * g20
        G01 = Rcw[0, 0] * g01 + Rcw[1, 0] * g11 + Rcw[2, 0] * g21
        G11 = Rcw[0, 1] * g01 + Rcw[1, 1] * g11 + Rcw[2, 1] * g21
        G21 = Rcw[0, 2] * g01 + Rcw[1, 2] * g11 + Rcw[2, 2] * g21
        G02 = Rcw[0, 0] * g02 + Rcw[1, 0] * g12 + Rcw[2, 0] * g22
        G12 = Rcw[0, 1] * g02 + Rcw[1, 1] * g12 + Rcw[2, 1] * g22
        G22 = Rcw[0, 2] * g02 + Rcw[1, 2] * g12 + Rcw[2, 2] * g22
        # through R(q_hat), then the normalisation q_hat = q / |q|
        gx = 2 * (y * (G01 + G10) + z * (G02 + G20) + w * (G21 - G12) - 2 * x * (G11 + G22))
        gy = 2 * (x * (G01 + G10) + z * (G12 + G21) + w * (G02 - G20) - 2 * y * (G00 + G22))
        gz = 2 * (x * (G02 + G20) + y * (G12 + G21) + w * (G10 - G01) - 2 * z * (G00 + G11))
        gw = 2 * (x * (G21 - G12) + y * (G02 - G20) + z * (G10 - G01))
        dot = gx * x + gy * y + gz * z + gw * w
        iq = 1 / qn
        d_quats[i, 0] = (gx - x * dot) * iq
        d_quats[i, 1] = (gy - y * dot) * iq
        d_quats[i, 2] = (gz - z * dot) * iq
        d_quats[i, 3] = (gw - w * dot) * iq
        # p_c = R_cw p + t_cw
        d_means[i, 0] = Rcw[0, 0] * dpc0 + Rcw[1, 0] * dpc1 + Rcw[2, 0] * dpc2
        d_means[i, 1] = Rcw[0, 1] * dpc0 + Rcw[1, 1] * dpc1 + Rcw[2, 1] * dpc2
        d_means[i, 2] = Rcw[0, 2] * dpc0 + Rcw[1, 2] * dpc1 + Rcw[2, 2] * dpc2
        if want_pose:
            px = means[i, 0]
            py = means[i, 1]
            pz = means[i, 2]
            # dL/dR_cw = dL/dRc R^T + dL/dp_c p^T
            d_pose[i, 0] = g00 * r00 + g01 * r01 + g02 * r02 + dpc0 * px
            d_pose[i, 1] = g00 * r10 + g01 * r11 + g02 * r12 + dpc0 * py
            d_pose[i, 2] = g00 * r20 + g01 * r21 + g02 * r22 + dpc0 * pz
            d_pose[i, 3] = g10 * r00 + g11 * r01 + g12 * r02 + dpc1 * px
            d_pose[i, 4] = g10 * r10 + g11 * r11 + g12 * r12 + dpc1 * py
            d_pose[i, 5] = g10 * r20 + g11 * r21 + g12 * r22 + dpc1 * pz
            d_pose[i, 6] = g20 * r00 + g21 * r01 + g22 * r02 + dpc2 * px
            d_pose[i, 7] = g20 * r10 + g21 * r11 + g22 * r12 + dpc2 * py
            d_pose[i, 8] = g20 * r20 + g21 * r21 + g22 * r22 + dpc2 * pz
            d_pose[i, 9] = dpc0
            d_pose[i, 10] = dpc1
            d_pose[i, 11] = dpc2
