"""Bird's-eye view of a 2D Gaussian map (``bev.png``): the surfels seen orthographically from above.

"Above" is the run's up direction (:func:`view_basis`): the world's ``+z`` when the run is
visual-inertial (the world frame is gravity-aligned once the IMU alignment is accepted), otherwise
the normal of the best-fit plane of the camera path, signed to agree with the cameras' up vectors
(``-y`` of the optical frame); a nearly straight path (no plane), or one whose plane is more than
45 degrees from the cameras' mean up vector (a path curving in 3D), takes that mean up vector.

Each surfel is a disc of its larger standard deviation (at least one pixel, at most
``max_radius_px``) filled with its DC colour; a pixel shows the highest surfel covering it.
Surfels above the camera path's highest point are left out (ceilings, tree canopies, upper
facades hide what the camera moved through) and so are nearly transparent ones.
:func:`splat_bev` is the vectorised kernel, :func:`splat_bev_reference` its slow, obvious
reference (tested against each other).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from enum import Enum
from pathlib import Path

import numpy as np

from ..errors import InputError

SH_C0 = 0.28209479177387814
#: the path plane's normal is taken for "up" only within 45 degrees of the cameras' mean up vector
PLANE_UP_COS = math.cos(math.radians(45.0))
BACKGROUND = np.array([255, 255, 255], np.uint8)


class UpSource(Enum):
    """Where the view's up direction came from."""

    GRAVITY = "gravity"                 # visual-inertial: world +z
    PATH_PLANE = "path-plane"           # normal of the camera path's best-fit plane
    CAMERA_UP = "camera-up"             # the cameras' mean up vector (path without a plane)


@dataclass
class Surfels:
    """What the view needs of each Gaussian: ``means`` ``(N, 3)`` world (run units), ``rgb``
    ``(N, 3)`` in [0, 1], ``opacity`` ``(N,)`` in [0, 1], ``radius`` ``(N,)`` larger standard
    deviation (run units)."""

    means: np.ndarray
    rgb: np.ndarray
    opacity: np.ndarray
    radius: np.ndarray

    def __len__(self) -> int:
        return len(self.means)


@dataclass
class ViewBasis:
    """Rows ``e1, e2, up`` (orthonormal, right-handed) of the view: plane coordinates are
    ``(e1 . p, e2 . p)``, height ``up . p``."""

    R: np.ndarray
    source: UpSource

    def plane(self, p: np.ndarray) -> np.ndarray:
        return np.asarray(p, np.float64) @ self.R[:2].T

    def height(self, p: np.ndarray) -> np.ndarray:
        return np.asarray(p, np.float64) @ self.R[2]


@dataclass
class BevImage:
    """``rgb`` ``(H, W, 3)`` uint8 (row 0 at the largest ``e2``); ``extent`` ``(x0, x1, y0, y1)``
    plane coordinates of the image's edges (matplotlib's ``imshow(extent=...)``); ``px`` the pixel
    size (run units); ``metric`` whether the units are metres (then a scale bar is drawn)."""

    rgb: np.ndarray
    extent: tuple[float, float, float, float]
    px: float
    basis: ViewBasis
    metric: bool
    surfels_drawn: int


def surfels_from_ply(path: str | Path) -> Surfels:
    """The surfels of a ``map.ply`` (docs/mapping.md layout: logit opacity, log scales, DC SH)."""
    from ..mapping.ply import read_ply
    v = read_ply(path)
    need = ("x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1")
    missing = [k for k in need if k not in v]
    if missing:
        raise InputError(f"{path}: not a Gaussian map (vertex properties {', '.join(missing)} missing)")
    means = np.stack([v["x"], v["y"], v["z"]], 1).astype(np.float64)
    rgb = np.clip(np.stack([v["f_dc_0"], v["f_dc_1"], v["f_dc_2"]], 1) * SH_C0 + 0.5, 0, 1)
    op = 1.0 / (1.0 + np.exp(-np.asarray(v["opacity"], np.float64)))
    rad = np.exp(np.maximum(v["scale_0"], v["scale_1"]).astype(np.float64))
    ok = np.isfinite(means).all(1) & np.isfinite(rgb).all(1) & np.isfinite(op) & np.isfinite(rad)
    return Surfels(means[ok], rgb[ok], op[ok], rad[ok])


def view_basis(T_wc: np.ndarray, gravity_aligned: bool) -> ViewBasis:
    """The view's axes for camera path ``T_wc`` ``(N, 4, 4)`` (camera-to-world). With
    ``gravity_aligned`` the up axis is the world's ``+z`` (visual-inertial runs); otherwise the
    path plane's normal (see the module doc). ``e1`` follows the path's main direction projected on
    the plane (the world's x axis when the path is a point)."""
    T = np.asarray(T_wc, np.float64).reshape(-1, 4, 4)
    cam_up = -T[:, :3, 1].mean(0) if len(T) else np.array([0.0, 0.0, 1.0])
    pos = T[:, :3, 3]
    main = np.array([1.0, 0.0, 0.0])
    if gravity_aligned:
        up, src = np.array([0.0, 0.0, 1.0]), UpSource.GRAVITY
        if len(pos) >= 2:
            main = np.linalg.svd(pos - pos.mean(0), full_matrices=False)[2][0]
    elif len(pos) >= 3:
        _, s, vt = np.linalg.svd(pos - pos.mean(0), full_matrices=False)
        main = vt[0]
        cu = cam_up / max(np.linalg.norm(cam_up), 1e-12)
        if s[0] > 0 and s[1] > 0.1 * s[0] and abs(vt[2] @ cu) > PLANE_UP_COS:
            up, src = vt[2], UpSource.PATH_PLANE
        else:   # a line (or a point), or a path curving out of the horizontal: the cameras' up
            up = cam_up - (cam_up @ main) * main if s[0] > 0 else cam_up
            src = UpSource.CAMERA_UP
    else:
        up, src = cam_up, UpSource.CAMERA_UP
    n = np.linalg.norm(up)
    up = up / n if n > 1e-12 else np.array([0.0, 0.0, 1.0])
    if src is UpSource.PATH_PLANE and up @ cam_up < 0:
        up = -up
    e1 = main - (main @ up) * up
    if np.linalg.norm(e1) < 1e-9:     # main direction along up: any horizontal axis
        e1 = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(up, e1)
    return ViewBasis(np.stack([e1, e2, up]), src)


def _grid(uv: np.ndarray, path_uv: np.ndarray, size_px: int) -> tuple[float, float, float, int, int]:
    """Image frame: ``(x0, y1, px, W, H)`` covering the 1st-99th percentile of the surfels and
    the whole camera path, 5 % margin, longest side ``size_px``."""
    pts = [path_uv] if len(path_uv) else []
    if len(uv):
        pts.append(np.percentile(uv, [1, 99], axis=0))
    if not pts:
        return -1.0, 1.0, 2.0 / size_px, size_px, size_px
    allp = np.concatenate(pts)
    lo, hi = allp.min(0), allp.max(0)
    span = np.maximum(hi - lo, 1e-6)
    lo, hi = lo - 0.05 * span.max(), hi + 0.05 * span.max()
    px = float((hi - lo).max() / size_px)
    W = max(1, int(math.ceil((hi[0] - lo[0]) / px)))
    H = max(1, int(math.ceil((hi[1] - lo[1]) / px)))
    return float(lo[0]), float(lo[1] + H * px), px, W, H


def _select(s: Surfels, basis: ViewBasis, path_pos: np.ndarray, min_opacity: float) -> np.ndarray:
    """Surfels drawn: opaque enough and not above the path's highest point (unless that would
    leave under 1 % of them: then the up axis is not what the map's layout suggests, keep all)."""
    keep = s.opacity >= min_opacity
    if len(path_pos):
        below = keep & (basis.height(s.means) <= basis.height(path_pos).max())
        if below.sum() >= 0.01 * keep.sum():
            keep = below
    return np.nonzero(keep)[0]


def _pixels(s: Surfels, idx: np.ndarray, basis: ViewBasis, x0: float, y1: float, px: float,
            max_radius_px: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Centre pixel ``(col, row)`` and disc radius (pixels) of surfels ``idx``."""
    uv = basis.plane(s.means[idx])
    col = np.floor((uv[:, 0] - x0) / px).astype(np.int64)
    row = np.floor((y1 - uv[:, 1]) / px).astype(np.int64)
    r = np.clip(np.round(s.radius[idx] / px), 0, max_radius_px).astype(np.int64)
    return col, row, r


@dataclass
class _Layout:
    """What the kernel and its reference share: the view, the surfels drawn (``idx``), the image
    frame and each drawn surfel's centre pixel, disc radius and height."""

    basis: ViewBasis
    idx: np.ndarray
    x0: float
    y1: float
    px: float
    W: int
    H: int
    col: np.ndarray
    row: np.ndarray
    r: np.ndarray
    h: np.ndarray


def _layout(s: Surfels, T_wc: np.ndarray, gravity_aligned: bool, size_px: int, max_radius_px: int,
            min_opacity: float) -> _Layout:
    basis = view_basis(T_wc, gravity_aligned)
    path = np.asarray(T_wc, np.float64).reshape(-1, 4, 4)[:, :3, 3]
    idx = _select(s, basis, path, min_opacity)
    x0, y1, px, W, H = _grid(basis.plane(s.means[idx]), basis.plane(path), size_px)
    col, row, r = _pixels(s, idx, basis, x0, y1, px, max_radius_px)
    return _Layout(basis, idx, x0, y1, px, W, H, col, row, r, basis.height(s.means[idx]))


def splat_bev(s: Surfels, T_wc: np.ndarray, gravity_aligned: bool, metric: bool = False,
              size_px: int = 1024, max_radius_px: int = 3, min_opacity: float = 0.3,
              chunk: int = 1 << 20) -> BevImage:
    """The map from above (see the module doc), vectorised: each surfel's disc as integer pixel
    offsets within its radius, one z-buffer pass (sort by pixel, then height) per chunk."""
    v = _layout(s, T_wc, gravity_aligned, size_px, max_radius_px, min_opacity)
    basis, idx, x0, y1, px, W, H, col, row, r, h = (v.basis, v.idx, v.x0, v.y1, v.px, v.W, v.H, v.col, v.row,
                                                    v.r, v.h)
    best_h = np.full(H * W, -np.inf)
    best_i = np.full(H * W, -1, np.int64)
    for k in range(max_radius_px + 1):
        dy, dx = np.mgrid[-k:k + 1, -k:k + 1]
        disc = dx ** 2 + dy ** 2 <= k * k
        dx, dy = dx[disc], dy[disc]
        sel = np.nonzero(r == k)[0]
        step = max(1, chunk // len(dx))
        for a in range(0, len(sel), step):
            g = sel[a:a + step]
            cc = (col[g, None] + dx[None]).ravel()
            rr = (row[g, None] + dy[None]).ravel()
            gi = np.repeat(g, len(dx))
            ok = (cc >= 0) & (cc < W) & (rr >= 0) & (rr < H)
            pix, gi = rr[ok] * W + cc[ok], gi[ok]
            # highest surfel per pixel; equal heights: the later surfel
            order = np.lexsort((gi, h[gi], pix))
            pix, gi = pix[order], gi[order]
            last = np.r_[pix[1:] != pix[:-1], True]
            pix, gi = pix[last], gi[last]
            better = (h[gi] > best_h[pix]) | ((h[gi] == best_h[pix]) & (gi > best_i[pix]))
            best_h[pix[better]] = h[gi[better]]
            best_i[pix[better]] = gi[better]
    img = np.tile(BACKGROUND, (H * W, 1))
    hit = best_i >= 0
    img[hit] = np.round(s.rgb[idx[best_i[hit]]] * 255).astype(np.uint8)
    rgb = img.reshape(H, W, 3)
    if metric:
        draw_scale_bar(rgb, px)
    return BevImage(rgb, (x0, x0 + W * px, y1 - H * px, y1), px, basis, metric, int(len(idx)))


def splat_bev_reference(s: Surfels, T_wc: np.ndarray, gravity_aligned: bool, size_px: int = 1024,
                        max_radius_px: int = 3, min_opacity: float = 0.3) -> np.ndarray:
    """Slow reference of :func:`splat_bev` (no scale bar): every surfel, every pixel of its disc,
    kept when higher than what the pixel holds (equal heights: the later surfel)."""
    v = _layout(s, T_wc, gravity_aligned, size_px, max_radius_px, min_opacity)
    idx, W, H, col, row, r, h = v.idx, v.W, v.H, v.col, v.row, v.r, v.h
    img = np.tile(BACKGROUND, (H, W, 1))
    zbuf = np.full((H, W), -np.inf)
    for j in range(len(idx)):
        k = int(r[j])
        for dy in range(-k, k + 1):
            for dx in range(-k, k + 1):
                c, rr = col[j] + dx, row[j] + dy
                if dx * dx + dy * dy <= k * k and 0 <= c < W and 0 <= rr < H and h[j] >= zbuf[rr, c]:
                    zbuf[rr, c] = h[j]
                    img[rr, c] = np.round(s.rgb[idx[j]] * 255).astype(np.uint8)
    return img


def draw_scale_bar(rgb: np.ndarray, px_m: float) -> None:
    """A scale bar (1, 2 or 5 x 10^k m, about a fifth of the width) in the bottom-left corner."""
    import cv2
    H, W = rgb.shape[:2]
    target = 0.2 * W * px_m
    k = math.floor(math.log10(target)) if target > 0 else 0
    length = max((m * 10.0 ** k for m in (1, 2, 5) if m * 10.0 ** k <= target), default=10.0 ** k)
    n = max(1, int(round(length / px_m)))
    x0, y0 = max(4, W // 40), H - max(8, H // 30)
    th = max(2, H // 200)
    cv2.rectangle(rgb, (x0 - 2, y0 - 6 * th - 14), (x0 + n + 2, y0 + th + 2), (255, 255, 255), -1)
    cv2.rectangle(rgb, (x0, y0), (x0 + n, y0 + th), (0, 0, 0), -1)
    label = f"{length:g} m"
    cv2.putText(rgb, label, (x0, y0 - 2 * th), cv2.FONT_HERSHEY_SIMPLEX, max(0.4, W / 2000), (0, 0, 0), 1,
                cv2.LINE_AA)


def write_bev(path: str | Path, bev: BevImage) -> None:
    """``bev.png`` (atomic)."""
    import cv2

    from ..util import atomic_write_bytes
    ok, buf = cv2.imencode(".png", cv2.cvtColor(bev.rgb, cv2.COLOR_RGB2BGR))
    if not ok:
        raise InputError(f"{path}: could not encode the bird's-eye view")
    atomic_write_bytes(path, buf.tobytes())
