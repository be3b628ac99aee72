"""Lens undistortion and resizing to the working resolution, in one remap.

Radial-tangential models use ``cv2.initUndistortRectifyMap``; equidistant (fisheye) models use
``cv2.fisheye.initUndistortRectifyMap``. The undistorted pinhole camera keeps the principal point
and the fx:fy ratio and scales the focal length so that every output pixel sees valid input
(:func:`undistorted_camera`), then it is scaled to the working size with
:meth:`CameraModel.scaled` (pixel-centre convention, as ``cv2.remap`` uses).
"""
from __future__ import annotations

from typing import Optional

import numpy as np

from ..errors import ConfigError, InputError
from ..types import CameraModel


def working_size(width: int, height: int, want_w: Optional[int], want_h: Optional[int]) -> tuple[int, int]:
    """Working resolution: native when both are ``None``; one given keeps the aspect ratio."""
    for name, v in (("width", want_w), ("height", want_h)):
        if v is not None and int(v) <= 0:
            raise ConfigError(f"working {name} must be positive, got {v}")
    if want_w is None and want_h is None:
        return int(width), int(height)
    if want_w is not None and want_h is not None:
        return int(want_w), int(want_h)
    if want_w is not None:
        return int(want_w), max(1, int(round(height * int(want_w) / width)))
    return max(1, int(round(width * int(want_h) / height))), int(want_h)


def distort_pixels(raw: CameraModel, xy: np.ndarray) -> np.ndarray:
    """Project normalised pinhole coordinates ``xy`` (N, 2) through ``raw`` (with its distortion)
    to pixel coordinates (N, 2) of the stored image."""
    import cv2
    pts = np.concatenate([xy, np.ones((len(xy), 1))], axis=1).reshape(-1, 1, 3).astype(np.float64)
    z = np.zeros(3)
    if raw.distortion_model == "equidistant":
        uv, _ = cv2.fisheye.projectPoints(pts, z, z, raw.K, raw.distortion[:4].reshape(4, 1))
    else:
        D = raw.distortion if raw.distortion_model == "radtan" else np.zeros(4)
        uv, _ = cv2.projectPoints(pts, z, z, raw.K, D)
    return uv.reshape(-1, 2)


def undistorted_camera(raw: CameraModel) -> CameraModel:
    """The pinhole model (same size, same principal point, same fx:fy ratio) of the undistorted image.

    The focal lengths are ``s * (fx, fy)`` with the smallest ``s`` (widest view) for which every
    pixel on the output border samples inside the stored image, so frames have no black borders.
    """
    if not raw.is_distorted:
        return raw.undistorted()
    W, H = raw.width, raw.height
    u = np.arange(W, dtype=np.float64)
    v = np.arange(H, dtype=np.float64)
    border = np.concatenate([np.stack([u, np.zeros(W)], 1), np.stack([u, np.full(W, H - 1.0)], 1),
                             np.stack([np.zeros(H), v], 1), np.stack([np.full(H, W - 1.0), v], 1)])

    def valid(s: float) -> bool:
        xy = (border - [raw.cx, raw.cy]) / [s * raw.fx, s * raw.fy]
        uv = distort_pixels(raw, xy)
        # bilinear sampling needs both neighbours inside: [0, W-1] x [0, H-1]
        return bool(np.all(np.isfinite(uv)) and np.all(uv >= 0.0) and np.all(uv[:, 0] <= W - 1.0)
                    and np.all(uv[:, 1] <= H - 1.0))

    lo, hi = 0.25, 1.0
    while not valid(hi) and hi < 16:
        lo, hi = hi, hi * 2
    if not valid(hi):
        return raw.undistorted()
    if valid(lo):
        return CameraModel(W, H, lo * raw.fx, lo * raw.fy, raw.cx, raw.cy)
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        lo, hi = (lo, mid) if valid(mid) else (mid, hi)
    return CameraModel(W, H, hi * raw.fx, hi * raw.fy, raw.cx, raw.cy)


#: OpenCV's remap works on images below 32767 px per side (SHRT_MAX)
REMAP_MAX_SIDE = 32767


class Undistorter:
    """Maps stored images (``raw`` camera) to delivered frames (``self.camera``).

    ``width``/``height``: working resolution (see :func:`working_size`). ``undistort=False`` only
    resizes and keeps the distortion model (scaled). Maps are built once.
    """

    def __init__(self, raw: CameraModel, width: Optional[int] = None, height: Optional[int] = None,
                 undistort: bool = True) -> None:
        import cv2
        self.raw = raw
        out_w, out_h = working_size(raw.width, raw.height, width, height)
        self.out_size = (out_w, out_h)
        self._maps = None
        self._post_resize = False
        if undistort and raw.is_distorted:
            if max(raw.width, raw.height) >= REMAP_MAX_SIDE:
                raise InputError(f"camera {raw.width}x{raw.height}: distorted images of {REMAP_MAX_SIDE} px "
                                 f"or more per side cannot be undistorted (OpenCV remap limit); "
                                 f"undistort them beforehand")
            rect = undistorted_camera(raw)
            self.camera = rect.scaled(out_w, out_h)
            # For strong down-sampling remap at native size, then area-average.
            self._post_resize = out_w < raw.width / 2 or out_h < raw.height / 2
            target = rect if self._post_resize else self.camera
            size = (target.width, target.height)
            if raw.distortion_model == "equidistant":
                m1, m2 = cv2.fisheye.initUndistortRectifyMap(
                    raw.K, raw.distortion[:4].reshape(4, 1), np.eye(3), target.K, size, cv2.CV_32FC1)
            else:
                m1, m2 = cv2.initUndistortRectifyMap(raw.K, raw.distortion, np.eye(3), target.K, size,
                                                     cv2.CV_32FC1)
            self._maps = (m1, m2)
        else:
            base = raw.undistorted() if (undistort or not raw.is_distorted) else raw
            self.camera = base.scaled(out_w, out_h) if (out_w, out_h) != (raw.width, raw.height) \
                else base

    @property
    def is_identity(self) -> bool:
        return self._maps is None and self.out_size == (self.raw.width, self.raw.height)

    def __call__(self, img: np.ndarray, nearest: bool = False) -> np.ndarray:
        """Undistort and resize ``img`` (``(H, W)`` or ``(H, W, C)`` at the raw size).

        ``nearest``: nearest-neighbour sampling (for depth maps and masks); otherwise bilinear
        (area averaging when shrinking).
        """
        import cv2
        if self.is_identity:
            return img
        src = img
        if src.dtype == np.bool_:
            src = src.astype(np.uint8)
        interp = cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR
        if self._maps is not None:
            src = cv2.remap(src, self._maps[0], self._maps[1], interp,
                            borderMode=cv2.BORDER_REPLICATE)
            if not self._post_resize:
                return src.astype(img.dtype) if img.dtype == np.bool_ else src
        if (src.shape[1], src.shape[0]) != self.out_size:
            shrink = self.out_size[0] < src.shape[1]
            # INTER_NEAREST_EXACT samples the source pixel nearest the output pixel's centre (plain
            # INTER_NEAREST takes floor(j s): a 0.25-0.5 px shift against the frames and intrinsics)
            src = cv2.resize(src, self.out_size, interpolation=cv2.INTER_NEAREST_EXACT if nearest else
                             (cv2.INTER_AREA if shrink else cv2.INTER_LINEAR))
        return src.astype(img.dtype) if img.dtype == np.bool_ else src
