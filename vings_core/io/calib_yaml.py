"""Calibration YAML files: read several common layouts, write the VINGS one.

Readable layouts (detected from the keys):

* **VINGS** (what :func:`save_calibration_yaml` writes, = ``Calibration.to_dict()``): ``camera:
  {width, height, fx, fy, cx, cy, distortion_model, distortion}``, ``T_bc`` (4x4, cam0-to-body),
  ``gyro_noise_density``, ``gyro_random_walk``, ``accel_noise_density``, ``accel_random_walk``,
  ``imu_rate_hz``, ``has_imu``, ``gravity``.
* **EuRoC/ASL** ``sensor.yaml``: ``intrinsics [fu, fv, cu, cv]``, ``resolution [w, h]``,
  ``distortion_model`` (``radial-tangential`` | ``equidistant`` | ``none``),
  ``distortion_coefficients``, ``T_BS: {data: 16 values}`` (sensor-to-body).
* **Kalibr** camchain: ``cam0: {intrinsics, resolution, distortion_model, distortion_coeffs,
  T_cam_imu}`` (``T_cam_imu`` is IMU-to-camera, inverted here), plus Kalibr/EuRoC IMU noise keys
  (``gyroscope_noise_density`` ...) anywhere at the top level or under ``imu0``.
* **ROS camera_info** YAML: ``image_width``, ``image_height``, ``camera_matrix: {data}``,
  ``distortion_model`` (``plumb_bob`` | ``rational_polynomial`` | ``equidistant``),
  ``distortion_coefficients: {data}``.
* **ORB-SLAM** settings: ``Camera.fx`` / ``Camera1.fx`` ..., ``Camera.k1`` ..., ``Camera.width``,
  ``Camera.type: KannalaBrandt8`` (equidistant), ``IMU.T_b_c1`` (cam-to-body), ``IMU.NoiseGyro`` ...

OpenCV's ``%YAML:1.0`` header and ``!!opencv-matrix`` tags are accepted. Errors name the file and key.
"""
from __future__ import annotations

import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional

import numpy as np
import yaml

from ..errors import InputError
from ..geometry import check_rigid_pose
from ..types import Calibration, CameraModel
from ..util import atomic_write_text, describe_yaml_error, read_utf8_text

# Published intrinsics of the TUM RGB-D Kinects (TUM RGB-D benchmark web page "File Formats ->
# Intrinsic Camera Calibration of the Kinect"; ORB-SLAM2 ships the same in TUM1/2/3.yaml). 640x480.
PRESETS: dict[str, CameraModel] = {
    "tum-fr1": CameraModel(640, 480, 517.3, 516.5, 318.6, 255.3, "radtan",
                           np.array([0.2624, -0.9531, -0.0054, 0.0026, 1.1633])),
    "tum-fr2": CameraModel(640, 480, 520.9, 521.0, 325.1, 249.7, "radtan",
                           np.array([0.2312, -0.7849, -0.0033, -0.0001, 0.9172])),
    "tum-fr3": CameraModel(640, 480, 535.4, 539.2, 320.1, 247.6, "none"),
}

_NOISE_KEYS = {
    "gyro_noise_density": ("gyro_noise_density", "gyroscope_noise_density", "IMU.NoiseGyro"),
    "gyro_random_walk": ("gyro_random_walk", "gyroscope_random_walk", "IMU.GyroWalk"),
    "accel_noise_density": ("accel_noise_density", "accelerometer_noise_density", "IMU.NoiseAcc"),
    "accel_random_walk": ("accel_random_walk", "accelerometer_random_walk", "IMU.AccWalk"),
}


@dataclass
class CalibParts:
    """What a calibration file provided (``None`` where it said nothing)."""

    camera: Optional[CameraModel] = None
    T_bc: Optional[np.ndarray] = None
    noise: dict = field(default_factory=dict)
    imu_rate_hz: Optional[float] = None
    has_imu: Optional[bool] = None
    gravity: Optional[float] = None

    def to_calibration(self, camera: Optional[CameraModel] = None) -> Calibration:
        cam = camera if camera is not None else self.camera
        kw: dict[str, Any] = dict(self.noise)
        if self.imu_rate_hz is not None:
            kw["imu_rate_hz"] = float(self.imu_rate_hz)
        if self.has_imu is not None:
            kw["has_imu"] = bool(self.has_imu)
        if self.gravity is not None:
            kw["gravity"] = float(self.gravity)
        return Calibration(camera=cam, T_bc=self.T_bc if self.T_bc is not None else np.eye(4),
                           T_bc_known=self.T_bc is not None, **kw)


def distortion_model_name(name: str, where: str) -> str:
    """Map the many spellings of distortion models to ``none``/``radtan``/``equidistant``."""
    n = str(name).strip().lower().replace("_", "-")
    if n in ("radial-tangential", "radtan", "plumb-bob", "rational-polynomial", "pinhole-radtan",
             "brown", "opencv"):
        return "radtan"
    if n in ("equidistant", "equi", "fisheye", "kannala-brandt", "kannalabrandt8",
             "pinhole-equi", "kb4"):
        return "equidistant"
    if n in ("none", "", "pinhole", "rectified"):
        return "none"
    raise InputError(f"{where}: unknown distortion model {name!r} (expected radial-tangential, "
                     f"plumb_bob, rational_polynomial, equidistant or none)")


def camera_info_intrinsics(K: Any, width: int, height: int, roi: tuple, binning: tuple,
                           where: str) -> tuple[int, int, float, float, float, float]:
    """Intrinsics of the *published image* from a ``sensor_msgs/CameraInfo`` (REP-104): ``K``
    (row-major 3x3) and ``width x height`` describe the full sensor; the image is the region of
    interest ``roi = (x_offset, y_offset, width, height)`` (0 size = whole sensor), binned by
    ``binning = (bx, by)`` (0 = 1). Same formulas as image_geometry.PinholeCameraModel. Returns
    ``(width, height, fx, fy, cx, cy)``; a K that is not an upper-triangular pinhole matrix
    (e.g. written column-major) is an :class:`InputError` naming ``where``."""
    K = np.asarray(K, dtype=np.float64).reshape(3, 3)
    if not np.all(np.isfinite(K)):
        raise InputError(f"{where}: field k holds non-finite values")
    if K[1, 0] != 0 or K[2, 0] != 0 or K[2, 1] != 0 or K[2, 2] != 1:
        raise InputError(f"{where}: field k must be row-major [fx, s, cx, 0, fy, cy, 0, 0, 1], "
                         f"got {K.reshape(-1).tolist()} (column-major?)")
    if K[0, 1] != 0:
        raise InputError(f"{where}: field k has skew {K[0, 1]}; cameras with skew are not "
                         f"supported")
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    bx, by = max(int(binning[0]), 1), max(int(binning[1]), 1)
    x0, y0 = int(roi[0]), int(roi[1])
    rw = int(roi[2]) or width
    rh = int(roi[3]) or height
    if x0 + rw > width or y0 + rh > height:
        raise InputError(f"{where}: roi {rw}x{rh}+{x0}+{y0} exceeds the {width}x{height} sensor")
    if (bx, by, x0, y0, rw, rh) != (1, 1, 0, 0, width, height):
        width, height = rw // bx, rh // by
        # image_geometry's formulas, so every ROS consumer of this CameraInfo agrees: exact for
        # image_proc's decimation (output pixel j = sensor pixel b j); for hardware binning that
        # averages b x b blocks the centre would be (cx - x0 + 0.5) / b - 0.5, a quarter pixel away
        fx, fy, cx, cy = fx / bx, fy / by, (cx - x0) / bx, (cy - y0) / by
    return width, height, float(fx), float(fy), float(cx), float(cy)


#: image_transport suffixes after the image topic's own name (``/cam/image_rect/compressed``)
TRANSPORT_SUFFIXES = ("compressed", "compressedDepth", "theora", "zstd", "ffmpeg", "h264")


def _topic_names(topic) -> list[str]:
    """The names of a topic without its image-transport suffixes."""
    parts = [p for p in str(topic).split("/") if p]
    while parts and parts[-1] in TRANSPORT_SUFFIXES:
        parts.pop()
    return parts


def camera_topic(topic: str) -> str:
    """The topic without its image-transport suffix (``/cam/image_raw/compressed`` -> ``/cam/image_raw``)."""
    return "/" + "/".join(_topic_names(topic))


def topic_namespace(topic: str) -> str:
    """The camera namespace of an image or CameraInfo topic: the topic without its transport
    suffix and last name (``/stereo/left/image_raw/compressed`` -> ``/stereo/left``)."""
    return "/" + "/".join(_topic_names(topic)[:-1])


def is_rectified_topic(topic: Optional[str]) -> bool:
    """ROS naming: ``image_rect`` / ``image_rect_color`` / ``image_rect_raw`` (image_proc, RealSense)
    carry rectified images, also behind a transport suffix (``.../image_rect/compressed``)."""
    if not topic:
        return False
    parts = _topic_names(topic)
    return bool(parts) and parts[-1].startswith("image_rect")


def rectified_camera_matrix(P: Any, where: str) -> np.ndarray:
    """Camera matrix of rectified images (``image_rect``): ``P[:3, :3]`` of their CameraInfo (its K
    and D describe the raw sensor). :class:`InputError` when P is not set."""
    P = np.asarray(P, dtype=np.float64).reshape(3, 4)
    if not (np.all(np.isfinite(P)) and P[0, 0] > 0 and P[1, 1] > 0):
        raise InputError(f"{where}: the image topic carries rectified images but field p (the "
                         f"projection matrix) is not set; give the camera with --calib")
    return P[:3, :3].copy()


def make_camera(width: Any, height: Any, fx: Any, fy: Any, cx: Any, cy: Any, model: str,
                coeffs: Any, where: str) -> CameraModel:
    """Build a :class:`CameraModel`, turning bad values into an :class:`InputError` naming ``where``."""
    try:
        d = np.asarray(coeffs if coeffs is not None else [], dtype=np.float64).reshape(-1)
        if model == "radtan" and d.size not in (0, 4, 5, 8, 12, 14):
            raise ValueError(f"radial-tangential needs 4, 5 or 8 coefficients, got {d.size}")
        if model == "equidistant" and d.size != 4:
            raise ValueError(f"equidistant needs 4 coefficients k1..k4, got {d.size}")
        if model == "radtan" and d.size > 5 and not np.any(d[5:]):
            d = d[:5]
        if model != "none" and not np.any(d):
            model, d = "none", np.zeros(0)
        if model == "none":
            d = np.zeros(0)
        vals = [float(v) for v in (fx, fy, cx, cy)]
        if not np.all(np.isfinite(vals)):
            raise ValueError("non-finite intrinsics")
        return CameraModel(int(width), int(height), *vals, distortion_model=model, distortion=d)
    except (TypeError, ValueError) as e:
        raise InputError(f"{where}: invalid camera calibration: {e}") from None


def _matrix(v: Any, n: int, where: str, key: str) -> np.ndarray:
    if isinstance(v, dict):
        v = v.get("data")
    try:
        a = np.asarray(v, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise InputError(f"{where}: {key} is not a list of numbers") from None
    if a.size != n * n:
        raise InputError(f"{where}: {key} must hold {n * n} values, got {a.size}")
    return a.reshape(n, n)


def _rigid(T: np.ndarray, where: str, key: str) -> np.ndarray:
    """The 4x4 ``T`` read from ``key`` if it is a rigid transform (to 1e-3), else InputError."""
    return check_rigid_pose(T, f"{where}: {key}", tol=1e-3, error=InputError)


def read_yaml_doc(path: str | os.PathLike) -> dict:
    """Load a YAML mapping, accepting OpenCV's ``%YAML:1.0`` header and ``!!opencv-matrix`` tags."""
    path = Path(path)
    if not path.is_file():
        hint = (f" (the presets {', '.join(PRESETS)} apply to TUM RGB-D folders only)"
                if str(path).lower() in PRESETS else "")
        raise InputError(f"{path}: calibration file not found{hint}")
    text = read_utf8_text(path, "calibration file", InputError)
    text = re.sub(r"^%YAML[: ]?1\.\d.*$", "", text, flags=re.M)
    text = text.replace("!!opencv-matrix", "")
    try:
        doc = yaml.safe_load(text)
    except yaml.YAMLError as e:
        raise InputError(f"{path}: {describe_yaml_error(e)}") from None
    if not isinstance(doc, dict):
        raise InputError(f"{path}: expected a YAML mapping at the top level")
    return doc


def parse_calibration(doc: dict, where: str, image_topic: Optional[str] = None) -> CalibParts:
    """Interpret a calibration mapping in any of the layouts of the module doc. A Kalibr camchain
    with several cameras gives the one whose ``rostopic`` is ``image_topic`` (cam0 without a
    topic; an InputError when none matches)."""
    parts = CalibParts()
    _parse_imu_parts(doc, parts, where)
    if "T_bc" in doc:                                             # VINGS (also without camera)
        parts.T_bc = _rigid(_matrix(doc["T_bc"], 4, where, "T_bc"), where, "T_bc")
    for layout in (_vings_camera, _kalibr_camera_parts, _asl_camera, _camera_info_camera, _orbslam_camera):
        if layout(doc, parts, where, image_topic):
            return parts
    if "T_BS" in doc:  # an IMU-only ASL sensor.yaml: T_BS is IMU-to-body (kept by the caller)
        return parts
    if parts.noise or parts.T_bc is not None:
        return parts
    raise InputError(f"{where}: no camera calibration found (expected a VINGS 'camera:' block, "
                     f"EuRoC 'intrinsics', Kalibr 'cam0', ROS 'camera_matrix' or ORB-SLAM "
                     f"'Camera.fx' keys)")


def _parse_imu_parts(doc: dict, parts: CalibParts, where: str) -> None:
    """IMU noise, rate, presence and gravity, from the top level or an ``imu0`` / ``imu`` block."""
    flat = dict(doc)
    for sub in ("imu0", "imu"):
        if isinstance(doc.get(sub), dict):
            flat = {**doc[sub], **flat}
    for name, keys in _NOISE_KEYS.items():
        for k in keys:
            if k in flat and flat[k] is not None:
                try:
                    parts.noise[name] = float(flat[k])
                except (TypeError, ValueError):
                    raise InputError(f"{where}: {k} must be a number, got {flat[k]!r}") from None
                break
    for k in ("imu_rate_hz", "update_rate", "IMU.Frequency"):
        if k in flat and isinstance(flat[k], (int, float)):
            parts.imu_rate_hz = float(flat[k])
            break
    if "has_imu" in doc:
        parts.has_imu = bool(doc["has_imu"])
    if "gravity" in doc and isinstance(doc["gravity"], (int, float)):
        parts.gravity = float(doc["gravity"])


def _vings_camera(doc: dict, parts: CalibParts, where: str, image_topic: Optional[str]) -> bool:
    """VINGS ``camera:`` block."""
    if not isinstance(doc.get("camera"), dict):
        return False
    c = doc["camera"]
    missing = [k for k in ("width", "height", "fx", "fy", "cx", "cy") if k not in c]
    if missing:
        raise InputError(f"{where}: camera block lacks {', '.join(missing)}")
    model = distortion_model_name(c.get("distortion_model", "none"), where)
    parts.camera = make_camera(c["width"], c["height"], c["fx"], c["fy"], c["cx"], c["cy"],
                               model, c.get("distortion", []), where)
    return True


def _kalibr_camera_parts(doc: dict, parts: CalibParts, where: str, image_topic: Optional[str]) -> bool:
    """Kalibr camchain (``cam0``, ...; the camera of ``image_topic``)."""
    if not isinstance(doc.get("cam0"), dict):
        return False
    name = _kalibr_camera(doc, where, image_topic)
    c = doc[name]
    parts.camera = _camera_from_asl(c, where, coeff_key="distortion_coeffs")
    if "T_cam_imu" in c:
        T = _rigid(_matrix(c["T_cam_imu"], 4, where, f"{name}.T_cam_imu"), where, f"{name}.T_cam_imu")
        parts.T_bc = np.linalg.inv(T)
    return True


def _asl_camera(doc: dict, parts: CalibParts, where: str, image_topic: Optional[str]) -> bool:
    """EuRoC/ASL ``sensor.yaml`` (``intrinsics``, ``T_BS``)."""
    if "intrinsics" not in doc:
        return False
    parts.camera = _camera_from_asl(doc, where, coeff_key="distortion_coefficients")
    if "T_BS" in doc:
        parts.T_bc = _rigid(_matrix(doc["T_BS"], 4, where, "T_BS"), where, "T_BS")
    return True


def _camera_info_camera(doc: dict, parts: CalibParts, where: str, image_topic: Optional[str]) -> bool:
    """ROS camera_info YAML (``camera_matrix``)."""
    if "camera_matrix" not in doc:
        return False
    K = _matrix(doc["camera_matrix"], 3, where, "camera_matrix")
    model = distortion_model_name(doc.get("distortion_model", "plumb_bob"), where)
    d = doc.get("distortion_coefficients", [])
    d = d.get("data", []) if isinstance(d, dict) else d
    for k in ("image_width", "image_height"):
        if k not in doc:
            raise InputError(f"{where}: camera_info YAML lacks {k}")
    parts.camera = make_camera(doc["image_width"], doc["image_height"], K[0, 0], K[1, 1],
                               K[0, 2], K[1, 2], model, d, where)
    return True


def _orbslam_camera(doc: dict, parts: CalibParts, where: str, image_topic: Optional[str]) -> bool:
    """ORB-SLAM settings (``Camera.fx`` / ``Camera1.fx``, ``Tbc``)."""
    pre = next((p for p in ("Camera1.", "Camera.") if f"{p}fx" in doc), None)
    if pre is None:
        return False
    equi = str(doc.get("Camera.type", "")).strip('"').lower() in ("kannalabrandt8", "fisheye")
    names = ("k1", "k2", "k3", "k4") if equi else ("k1", "k2", "p1", "p2", "k3")
    d = [float(doc.get(f"{pre}{n}", 0.0)) for n in names]
    w = doc.get("Camera.width", doc.get(f"{pre}width"))
    h = doc.get("Camera.height", doc.get(f"{pre}height"))
    if w is None or h is None:
        raise InputError(f"{where}: ORB-SLAM settings lack Camera.width/Camera.height")
    parts.camera = make_camera(w, h, doc[f"{pre}fx"], doc.get(f"{pre}fy", doc[f"{pre}fx"]),
                               doc[f"{pre}cx"], doc[f"{pre}cy"],
                               "equidistant" if equi else "radtan", d, where)
    for k in ("IMU.T_b_c1", "Tbc"):
        if k in doc:
            parts.T_bc = _rigid(_matrix(doc[k], 4, where, k), where, k)
    return True


def _camera_from_asl(c: dict, where: str, coeff_key: str) -> CameraModel:
    try:
        fu, fv, cu, cv = [float(v) for v in c["intrinsics"]]
    except (KeyError, TypeError, ValueError):
        raise InputError(f"{where}: 'intrinsics' must be [fu, fv, cu, cv]") from None
    res = c.get("resolution")
    if not (isinstance(res, (list, tuple)) and len(res) == 2):
        raise InputError(f"{where}: 'resolution' must be [width, height]")
    model = distortion_model_name(c.get("distortion_model", "radial-tangential"), where)
    if str(c.get("camera_model", "pinhole")).lower() not in ("pinhole",):
        raise InputError(f"{where}: camera_model {c.get('camera_model')!r} is not supported "
                         f"(only pinhole)")
    return make_camera(res[0], res[1], fu, fv, cu, cv, model, c.get(coeff_key, []), where)


def _kalibr_camera(doc: dict, where: str, image_topic: Optional[str]) -> str:
    """The ``camN`` block of a Kalibr camchain for ``image_topic`` (see :func:`parse_calibration`)."""
    cams = sorted((k for k in doc if re.fullmatch(r"cam\d+", str(k)) and isinstance(doc[k], dict)),
                  key=lambda k: int(k[3:]))
    if not image_topic or len(cams) == 1:
        return "cam0"
    hit = [k for k in cams if _topic_names(doc[k].get("rostopic", "")) == _topic_names(image_topic)]
    if len(hit) != 1:
        topics = ", ".join(f"{k}: {doc[k].get('rostopic', '?')}" for k in cams)
        raise InputError(f"{where}: camchain has {len(cams)} cameras ({topics}); none is for the "
                         f"image topic {image_topic}")
    return hit[0]


def read_calibration_parts(path: str | os.PathLike, image_topic: Optional[str] = None) -> CalibParts:
    """Whatever a calibration YAML provides (camera may be ``None`` for an IMU-only file);
    ``image_topic``: picks the camera of a multi-camera Kalibr camchain."""
    return parse_calibration(read_yaml_doc(path), str(path), image_topic)


def load_calibration_yaml(path: str | os.PathLike) -> Calibration:
    """Read a calibration YAML (any layout of the module doc) into a :class:`Calibration`.

    ``camera`` is the model of the stored images (distortion kept); ``T_bc`` is identity when the
    file gives no extrinsic; IMU noise falls back to the :class:`Calibration` defaults.
    """
    parts = read_calibration_parts(path)
    if parts.camera is None:
        raise InputError(f"{path}: no camera calibration in this file")
    return parts.to_calibration()


def format_calibration_yaml(calib: Calibration) -> str:
    d = calib.to_dict()
    head = ("# VINGS-ROS calibration (vings_core.io.calib_yaml). camera: cam0 intrinsics in pixels of\n"
            "# width x height; T_bc: cam0-to-body (IMU) 4x4; IMU noise in continuous time\n"
            "# (rad/s/sqrt(Hz), rad/s^2/sqrt(Hz), m/s^2/sqrt(Hz), m/s^3/sqrt(Hz)).\n")
    return head + yaml.safe_dump(d, sort_keys=False, default_flow_style=None, width=120)


def save_calibration_yaml(path: str | os.PathLike, calib: Calibration) -> None:
    """Write ``calib`` in the VINGS layout, atomically; :func:`load_calibration_yaml` reads it back."""
    atomic_write_text(path, format_calibration_yaml(calib))
