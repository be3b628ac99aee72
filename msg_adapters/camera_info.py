"""``sensor_msgs/CameraInfo`` <-> :class:`vings_core.types.CameraModel`.

Distortion models (ROS ``sensor_msgs/distortion_models`` names):

* ``none``        <-> ``plumb_bob`` with ``D = 0`` (what rectified drivers publish),
* ``radtan``      <-> ``plumb_bob`` ``(k1, k2, p1, p2, k3)`` (a 4-term model gets ``k3 = 0``),
* ``equidistant`` <-> ``equidistant`` ``(k1, k2, k3, k4)``.

On input ``rational_polynomial`` is accepted when its extra terms ``k4..k6`` are zero, an empty
model with empty ``D`` means no distortion, and binning / ROI are applied as in image_geometry
(the returned model describes the image that is actually published). ``K == 0`` means an
uncalibrated camera (REP-104) and is refused.
"""
from __future__ import annotations

import numpy as np
from sensor_msgs.msg import CameraInfo, RegionOfInterest

from vings_core.errors import InputError
from vings_core.io.calib_yaml import camera_info_intrinsics, rectified_camera_matrix
from vings_core.types import CameraModel

from .stamps import make_header


def camera_to_camera_info(camera: CameraModel, stamp_ns: int, frame_id: str,
                          where: str = "camera_info") -> CameraInfo:
    """CameraInfo for images described by ``camera`` (R = I, P = [K | 0], no binning / ROI)."""
    d = np.asarray(camera.distortion, dtype=np.float64).reshape(-1)
    if camera.distortion_model == "none":
        model, d = "plumb_bob", np.zeros(5)
    elif camera.distortion_model == "radtan":
        if len(d) not in (4, 5):
            raise InputError(f"{where}: radtan distortion needs 4 or 5 coefficients "
                             f"(k1, k2, p1, p2[, k3]), got {len(d)}")
        model, d = "plumb_bob", np.concatenate([d, np.zeros(5 - len(d))])
    else:  # equidistant
        if len(d) != 4:
            raise InputError(f"{where}: equidistant distortion needs 4 coefficients, got {len(d)}")
        model = "equidistant"
    K = camera.K
    P = np.zeros((3, 4))
    P[:, :3] = K
    msg = CameraInfo(header=make_header(stamp_ns, frame_id, where), height=int(camera.height),
                     width=int(camera.width), distortion_model=model)
    msg.d = [float(v) for v in d]
    msg.k = K.reshape(-1)
    msg.r = np.eye(3).reshape(-1)
    msg.p = P.reshape(-1)
    msg.binning_x = 0
    msg.binning_y = 0
    msg.roi = RegionOfInterest()
    return msg


def camera_info_to_camera(msg: CameraInfo, where: str = "camera_info",
                          rectified: bool = False) -> CameraModel:
    """CameraInfo -> CameraModel of the published image (InputError naming the bad field).
    ``rectified``: the image topic carries rectified images (``image_rect``, see
    :func:`vings_core.io.calib_yaml.is_rectified_topic`): the camera is then ``P[:3, :3]`` without
    distortion, as the bag reader does."""
    width, height = int(msg.width), int(msg.height)
    if width <= 0 or height <= 0:
        raise InputError(f"{where}: width/height {width}x{height} must be positive")
    K = rectified_camera_matrix(msg.p, where) if rectified else \
        np.asarray(msg.k, dtype=np.float64).reshape(3, 3)
    if not np.all(np.isfinite(K)):
        raise InputError(f"{where}: field k holds non-finite values")
    fx, fy = K[0, 0], K[1, 1]
    if not (fx > 0 and fy > 0):
        raise InputError(f"{where}: field k has fx={fx}, fy={fy}; the camera is uncalibrated "
                         f"(REP-104: K = 0) or K is invalid")
    d = np.zeros(0) if rectified else np.asarray(msg.d, dtype=np.float64).reshape(-1)
    if not np.all(np.isfinite(d)):
        raise InputError(f"{where}: field d holds non-finite values")
    name = "none" if rectified else str(msg.distortion_model).strip().lower()
    if (name in ("", "none") and not np.any(d)) or d.size == 0:
        # no coefficients at all means no distortion whatever the model says (image_geometry)
        model, coeffs = "none", np.zeros(0)
    elif name in ("plumb_bob", "radtan", "radial_tangential", "rational_polynomial"):
        if name == "rational_polynomial" and np.any(d[5:]):
            raise InputError(f"{where}: distortion_model 'rational_polynomial' with k4..k6 != 0 "
                             f"is not supported (use plumb_bob or rectify upstream)")
        if len(d) < 4 or (name != "rational_polynomial" and len(d) > 5):
            raise InputError(f"{where}: distortion_model {msg.distortion_model!r} needs 4-5 "
                             f"coefficients in d, got {len(d)}")
        coeffs = d[:5]
        model = "radtan" if np.any(coeffs) else "none"
    elif name in ("equidistant", "fisheye"):
        if len(d) != 4:
            raise InputError(f"{where}: distortion_model 'equidistant' needs 4 coefficients in d, "
                             f"got {len(d)}")
        coeffs = d
        model = "equidistant" if np.any(coeffs) else "none"
    else:
        raise InputError(f"{where}: distortion_model {msg.distortion_model!r} is not supported "
                         f"(plumb_bob, equidistant, rational_polynomial with k4..k6 = 0)")
    if model == "none":
        coeffs = np.zeros(0)

    roi = msg.roi
    width, height, fx, fy, cx, cy = camera_info_intrinsics(
        K, width, height, (roi.x_offset, roi.y_offset, roi.width, roi.height),
        (msg.binning_x, msg.binning_y), where)
    try:
        return CameraModel(width=width, height=height, fx=float(fx), fy=float(fy), cx=float(cx),
                           cy=float(cy), distortion_model=model, distortion=coeffs)
    except ValueError as e:
        raise InputError(f"{where}: {e}") from None


__all__ = ["camera_to_camera_info", "camera_info_to_camera"]
