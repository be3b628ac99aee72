"""Plain data contracts exchanged by every stage of VINGS-ROS.

Conventions (see docs/data_contracts.md):

* Time stamps are ``int`` nanoseconds on the sensor clock. A keyframe is identified by the stamp of
  its image, everywhere (in memory, in files and on ROS topics).
* Poses are 4x4 homogeneous ``float64`` matrices. ``T_ab`` maps points expressed in frame ``b`` into
  frame ``a`` (so ``T_wc`` is camera-to-world, the camera's pose in the world).
* Camera frame: optical convention, x right, y down, z forward (REP-103 ``*_optical_frame``).
* Body frame: the IMU frame. ``T_bc`` is camera-to-body (EuRoC's ``T_BS`` of cam0).
* Images: ``uint8`` arrays, ``(H, W, 3)`` RGB or ``(H, W)`` mono, at the working resolution.
* Depth is metric z-depth along the optical axis in metres; ``0`` marks an invalid pixel.
"""
from __future__ import annotations

import enum
from dataclasses import dataclass, field, replace
from typing import Any, Optional

import numpy as np
import torch

DISTORTION_MODELS = ("none", "radtan", "equidistant")


def _as_int(v: Any, what: str) -> int:
    """``v`` (int or numpy integer) as a Python int; ValueError naming ``what`` otherwise (a float
    nanosecond stamp has already lost precision)."""
    if isinstance(v, bool) or not isinstance(v, (int, np.integer)):
        raise ValueError(f"{what} must be an integer, got {v!r} ({type(v).__name__})")
    return int(v)


@dataclass
class CameraModel:
    """Pinhole intrinsics at a given resolution, with optional lens distortion.

    ``fx, fy, cx, cy`` are in pixels of an image ``width`` x ``height``. ``distortion`` holds
    ``(k1, k2, p1, p2[, k3])`` for ``radtan`` (OpenCV plumb_bob) or ``(k1, k2, k3, k4)`` for
    ``equidistant`` (OpenCV fisheye); it is empty for ``none``. After undistortion by the I/O layer
    frames carry a model with ``distortion_model == "none"``.
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    distortion_model: str = "none"
    distortion: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def __post_init__(self) -> None:
        if self.distortion_model not in DISTORTION_MODELS:
            raise ValueError(f"unknown distortion model {self.distortion_model!r}; "
                             f"expected one of {DISTORTION_MODELS}")
        self.distortion = np.asarray(self.distortion, dtype=np.float64).reshape(-1)
        if not np.all(np.isfinite(self.distortion)):
            # a NaN coefficient would undistort every frame to black without a word
            raise ValueError(f"camera distortion coefficients must be finite, got "
                             f"{self.distortion.tolist()}")
        for name in ("width", "height"):       # 640.0 from a YAML file is 640; 640.5 is an error
            v = getattr(self, name)
            try:
                whole = not isinstance(v, bool) and float(v).is_integer()
            except (TypeError, ValueError):
                whole = False
            if not whole:
                raise ValueError(f"camera {name} must be a whole number of pixels, got {v!r}")
            setattr(self, name, int(v))
        for name in ("fx", "fy", "cx", "cy"):
            try:
                v = float(getattr(self, name))
            except (TypeError, ValueError):
                v = float("nan")
            if not np.isfinite(v):
                raise ValueError(f"camera {name} must be a finite number, got {getattr(self, name)!r}")
            # a plain float: numpy scalars (from a K matrix) are not JSON-serialisable, and a map
            # checkpoint or metrics file would fail to write long after the camera was built
            setattr(self, name, v)
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"camera size must be positive, got {self.width}x{self.height}")
        if not (self.fx > 0 and self.fy > 0):
            raise ValueError(f"focal lengths must be positive, got fx={self.fx}, fy={self.fy}")

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, CameraModel):
            return NotImplemented
        return (self.width, self.height, self.fx, self.fy, self.cx, self.cy, self.distortion_model) == \
            (other.width, other.height, other.fx, other.fy, other.cx, other.cy, other.distortion_model) \
            and np.array_equal(self.distortion, other.distortion)

    @property
    def K(self) -> np.ndarray:
        """3x3 intrinsic matrix (float64)."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def is_distorted(self) -> bool:
        return self.distortion_model != "none" and bool(np.any(self.distortion != 0))

    def scaled(self, width: int, height: int) -> "CameraModel":
        """The same camera resampled to ``width`` x ``height`` (pixel-centre convention).

        Distortion coefficients act on normalised coordinates and are unchanged.
        """
        sx, sy = width / self.width, height / self.height
        return replace(self, width=int(width), height=int(height), fx=self.fx * sx, fy=self.fy * sy,
                       cx=(self.cx + 0.5) * sx - 0.5, cy=(self.cy + 0.5) * sy - 0.5,
                       distortion=self.distortion.copy())

    def undistorted(self) -> "CameraModel":
        """This model with the distortion removed (same intrinsics)."""
        return replace(self, distortion_model="none", distortion=np.zeros(0))

    def to_dict(self) -> dict:
        return {"width": self.width, "height": self.height, "fx": self.fx, "fy": self.fy,
                "cx": self.cx, "cy": self.cy, "distortion_model": self.distortion_model,
                "distortion": [float(v) for v in self.distortion]}

    @staticmethod
    def from_dict(d: dict) -> "CameraModel":
        return CameraModel(width=int(d["width"]), height=int(d["height"]), fx=float(d["fx"]),
                           fy=float(d["fy"]), cx=float(d["cx"]), cy=float(d["cy"]),
                           distortion_model=d.get("distortion_model", "none"),
                           distortion=np.asarray(d.get("distortion", []), dtype=np.float64))


@dataclass
class Frame:
    """One camera image.

    ``stamp_ns``: capture time (ns). ``image``: ``uint8`` ``(H, W, 3)`` RGB or ``(H, W)`` mono at
    ``camera``'s resolution. ``camera``: the model the image is expressed in.
    """

    stamp_ns: int
    image: np.ndarray
    camera: CameraModel

    @property
    def is_color(self) -> bool:
        return self.image.ndim == 3 and self.image.shape[2] == 3

    def rgb(self) -> np.ndarray:
        """The image as ``(H, W, 3)`` uint8 RGB (mono replicated)."""
        if self.is_color:
            return self.image
        img = self.image if self.image.ndim == 2 else self.image[..., 0]
        return np.repeat(img[..., None], 3, axis=2)

    def gray(self) -> np.ndarray:
        """The image as ``(H, W)`` uint8 luminance (BT.601 weights)."""
        if self.image.ndim == 2:
            return self.image
        if self.image.shape[2] == 1:
            return self.image[..., 0]
        w = np.array([0.299, 0.587, 0.114], dtype=np.float32)
        return np.clip(self.image.astype(np.float32) @ w + 0.5, 0, 255).astype(np.uint8)


@dataclass
class ImuSample:
    """One IMU reading in the body (IMU) frame.

    ``gyro``: angular rate, rad/s, shape (3,). ``accel``: specific force (gravity included, so about
    +9.81 m/s^2 upward at rest), m/s^2, shape (3,).
    """

    stamp_ns: int
    gyro: np.ndarray
    accel: np.ndarray


@dataclass
class Calibration:
    """Sensor rig calibration.

    ``camera``: cam0 model at the working resolution (after undistortion ``distortion_model='none'``);
    ``None`` for IMU-only recordings (no image topic).
    ``T_bc``: cam0-to-body 4x4. IMU noise in continuous time: ``gyro_noise_density`` rad/s/sqrt(Hz),
    ``gyro_random_walk`` rad/s^2/sqrt(Hz), ``accel_noise_density`` m/s^2/sqrt(Hz),
    ``accel_random_walk`` m/s^3/sqrt(Hz). ``imu_rate_hz`` is nominal; ``has_imu`` is False for
    camera-only sources. ``gravity`` is the magnitude in m/s^2. ``T_bc_known`` is False when no
    source of the calibration gave the extrinsic (``T_bc`` then holds the identity as a default that
    nobody measured: body ground truth cannot be mapped to cam0 through it).
    """

    camera: Optional[CameraModel]
    T_bc: np.ndarray = field(default_factory=lambda: np.eye(4))
    gyro_noise_density: float = 1.6968e-4
    gyro_random_walk: float = 1.9393e-5
    accel_noise_density: float = 2.0e-3
    accel_random_walk: float = 3.0e-3
    imu_rate_hz: float = 200.0
    has_imu: bool = False
    gravity: float = 9.81
    T_bc_known: bool = True

    def __post_init__(self) -> None:
        self.T_bc = np.asarray(self.T_bc, dtype=np.float64).reshape(4, 4)

    def to_dict(self) -> dict:
        return {"camera": self.camera.to_dict() if self.camera is not None else None, "T_bc": self.T_bc.tolist(),
                "gyro_noise_density": self.gyro_noise_density,
                "gyro_random_walk": self.gyro_random_walk,
                "accel_noise_density": self.accel_noise_density,
                "accel_random_walk": self.accel_random_walk, "imu_rate_hz": self.imu_rate_hz,
                "has_imu": self.has_imu, "gravity": self.gravity, "T_bc_known": self.T_bc_known}

    @staticmethod
    def from_dict(d: dict) -> "Calibration":
        kw = {k: d[k] for k in ("gyro_noise_density", "gyro_random_walk", "accel_noise_density",
                                "accel_random_walk", "imu_rate_hz", "has_imu", "gravity", "T_bc_known") if k in d}
        cam = d.get("camera")
        return Calibration(camera=CameraModel.from_dict(cam) if cam else None,
                           T_bc=np.asarray(d.get("T_bc", np.eye(4)), dtype=np.float64), **kw)


@dataclass
class Trajectory:
    """A sequence of stamped poses. ``stamps_ns``: int64 (N,). ``poses``: float64 (N, 4, 4).

    What the poses mean is stated by whoever makes the trajectory; VINGS outputs are cam0
    camera-to-world ``T_wc``.
    """

    stamps_ns: np.ndarray
    poses: np.ndarray

    def __post_init__(self) -> None:
        self.stamps_ns = np.asarray(self.stamps_ns, dtype=np.int64).reshape(-1)
        self.poses = np.asarray(self.poses, dtype=np.float64).reshape(-1, 4, 4)
        if len(self.stamps_ns) != len(self.poses):
            raise ValueError(f"trajectory has {len(self.stamps_ns)} stamps but "
                             f"{len(self.poses)} poses")

    @staticmethod
    def from_poses(poses: dict[int, np.ndarray]) -> "Trajectory":
        """The ``{stamp_ns: 4x4 pose}`` mapping in stamp order (empty mapping: empty trajectory)."""
        st = sorted(int(s) for s in poses)
        return Trajectory(np.array(st, np.int64),
                          np.stack([poses[s] for s in st]) if st else np.zeros((0, 4, 4)))

    def __len__(self) -> int:
        return len(self.stamps_ns)

    @property
    def positions(self) -> np.ndarray:
        return self.poses[:, :3, 3]

    def path_length(self) -> float:
        """Sum of distances between consecutive positions (m)."""
        if len(self) < 2:
            return 0.0
        return float(np.linalg.norm(np.diff(self.positions, axis=0), axis=1).sum())

    def right_multiply(self, T: np.ndarray) -> "Trajectory":
        """Poses ``P @ T`` (e.g. body ground truth ``T_wb`` to camera with ``T_bc``)."""
        return Trajectory(self.stamps_ns.copy(), self.poses @ np.asarray(T, dtype=np.float64))

    def slice_time(self, t0_ns: int, t1_ns: int) -> "Trajectory":
        m = (self.stamps_ns >= t0_ns) & (self.stamps_ns <= t1_ns)
        return Trajectory(self.stamps_ns[m], self.poses[m])


@dataclass
class Keyframe:
    """A keyframe delivered by the front end to the mapper (and on ROS topics).

    * ``stamp_ns``: image stamp, the keyframe's identity.
    * ``image``: float32 ``(H, W, 3)`` RGB in [0, 1] at the working resolution.
    * ``T_wc``: float64 4x4 camera-to-world.
    * ``depth``: float32 ``(H, W)`` metric z-depth (m), 0 where invalid.
    * ``inv_depth_var``: float32 ``(H, W)`` variance of inverse depth (1/m^2), the paper's
      Sigma_d^-1 block; large where uncertain.
    * ``valid``: bool ``(H, W)``: depth usable for mapping.
    * ``camera``: undistorted model at the working resolution.
    * ``index``: running keyframe number (informational; identity is the stamp).
    * ``dynamic``: bool ``(H, W)``, True where the dynamic eraser found a moving object (kept out
      of every mapping loss and of new Gaussians), or None (no mask).
    """

    stamp_ns: int
    image: torch.Tensor
    T_wc: torch.Tensor
    depth: torch.Tensor
    inv_depth_var: torch.Tensor
    valid: torch.Tensor
    camera: CameraModel
    index: int = -1
    dynamic: Optional[torch.Tensor] = None

    def __post_init__(self) -> None:
        self.stamp_ns = _as_int(self.stamp_ns, "Keyframe.stamp_ns")
        self.index = _as_int(self.index, "Keyframe.index")
        self.T_wc = torch.as_tensor(self.T_wc, dtype=torch.float64).reshape(4, 4)
        H, W = self.camera.height, self.camera.width
        if self.dynamic is not None:
            self.dynamic = torch.as_tensor(self.dynamic).to(torch.bool)
        for name in ("image", "depth", "inv_depth_var", "valid", "dynamic"):
            t = getattr(self, name)
            if t is not None and tuple(t.shape[:2]) != (H, W):
                raise ValueError(f"Keyframe.{name} has shape {tuple(t.shape)}, expected ({H}, {W}, ...)"
                                 f" from the camera model")


class TrackState(str, enum.Enum):
    """Tracking state of the visual front end (and of each frame it posed).

    * ``WAITING``: no map segment yet; waiting for enough parallax to initialise one.
    * ``TRACKING``: the frame was posed against the keyframe window.
    * ``LOST``: tracking failed; the pose is the last good one.
    * ``INERTIAL``: posed from the IMU alone (visual-inertial front end): propagated through a
      vision outage, or held at a standstill before the visual initialisation (a frame state; the
      front end's own state is then ``LOST`` or ``WAITING``).

    A ``str`` subclass: a member equals, hashes and prints (``str``, f-strings, ``%s``,
    ``json.dumps``) as its value, so ``TrackState.TRACKING == "tracking"``.
    """

    WAITING = "waiting"
    TRACKING = "tracking"
    LOST = "lost"
    INERTIAL = "inertial"

    def __str__(self) -> str:
        return self.value

    def __format__(self, spec: str) -> str:
        return format(self.value, spec)


#: frame states that carry a pose estimate (published as odometry, written to trajectory.tum)
POSED_STATES = (TrackState.TRACKING, TrackState.INERTIAL)


@dataclass
class PoseEstimate:
    """Front-end output for one frame: ``T_wc`` (cam0-to-world) with a 6x6 covariance of the
    left-multiplied tangent ``[rho (m), phi (rad)]`` (``None`` if unknown), a tracking state
    (:class:`TrackState`; its string value is accepted) and whether the frame became a keyframe."""

    stamp_ns: int
    T_wc: np.ndarray
    covariance: Optional[np.ndarray] = None
    state: TrackState = TrackState.TRACKING
    is_keyframe: bool = False

    def __post_init__(self) -> None:
        self.state = TrackState(self.state)
