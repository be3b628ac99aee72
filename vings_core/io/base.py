"""The one interface every sensor-data source implements.

A :class:`Source` is a recording on one clock: camera frames, IMU samples, a calibration and optional
ground truth. Frames come out undistorted and resized to the working resolution (the calibration's
camera model describes them); IMU samples are in the body frame.
"""
from __future__ import annotations

import enum
import heapq
from abc import ABC, abstractmethod
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Optional, Union

import numpy as np

from ..errors import InputError
from ..types import Calibration, Frame, ImuSample, Trajectory


class BadFramePolicy(str, enum.Enum):
    """What reading does with a frame it cannot decode."""

    SKIP = "skip"       # skip it, count it (Source.bad_frames), warn
    ABORT = "abort"     # stop with an InputError naming the frame


@dataclass
class SourceOptions:
    """How a source delivers frames.

    ``width``/``height``: working resolution (None keeps the native size; one of them alone keeps
    the aspect ratio). ``undistort``: remove lens distortion. ``image_topic``/``imu_topic``/
    ``camera_info_topic``: for bags, chosen by name (None = detect). ``calib_file``: YAML calibration
    overriding what the source carries. ``max_frames``: stop after this many frames (None = all).
    ``on_bad_frame``: a frame that cannot be decoded (corrupt file, wrong size or encoding) is
    skipped and counted (:class:`BadFramePolicy` ``skip``, the default, as the nodes do) or ends
    the reading with an :class:`InputError` (``abort``).
    """

    width: Optional[int] = None
    height: Optional[int] = None
    undistort: bool = True
    image_topic: Optional[str] = None
    imu_topic: Optional[str] = None
    camera_info_topic: Optional[str] = None
    gt_topic: Optional[str] = None
    calib_file: Optional[str] = None
    max_frames: Optional[int] = None
    on_bad_frame: "BadFramePolicy" = None      # type: ignore[assignment]  (None: BadFramePolicy.SKIP)

    def __post_init__(self) -> None:
        self.on_bad_frame = BadFramePolicy(self.on_bad_frame or BadFramePolicy.SKIP)


class Source(ABC):
    """A time-ordered recording. Subclasses fill the attributes in ``__init__`` and implement
    :meth:`frames` and :meth:`imu_samples`.

    Attributes:
        path: where it was read from.
        kind: loader name (``euroc``, ``tum``, ``kitti``, ``bag``, ``mcap``).
        calibration: rig calibration; ``calibration.camera`` describes the delivered frames.
        raw_camera: the camera model of the stored images (before undistortion/resize).
        ground_truth: optional trajectory; ``gt_frame`` tells whether its poses are ``T_w_body``
            (``"body"``) or ``T_w_cam0`` (``"camera"``).
        warnings: human-readable notes on what the loader repaired (e.g. sorted IMU samples).
    """

    path: Path
    kind: str
    calibration: Calibration
    raw_camera: Optional[object]
    ground_truth: Optional[Trajectory] = None
    gt_frame: str = "body"
    warnings: list

    @abstractmethod
    def frame_stamps(self) -> np.ndarray:
        """int64 (N,) stamps (ns) of the frames :meth:`frames` yields, strictly increasing."""

    @abstractmethod
    def frames(self) -> Iterator[Frame]:
        """Frames in time order, undistorted and at the working resolution."""

    @abstractmethod
    def imu_samples(self) -> list[ImuSample]:
        """IMU samples in time order (empty list when the source has no IMU)."""

    def gt_depth(self, stamp_ns: int) -> Optional[np.ndarray]:
        """Ground-truth metric z-depth (float32, working resolution) for a frame, if available."""
        return None

    def gt_mask(self, stamp_ns: int) -> Optional[np.ndarray]:
        """Ground-truth dynamic-object mask (bool, working resolution) for a frame, if available."""
        return None

    def gt_camera_trajectory(self) -> Optional[Trajectory]:
        """Ground truth as cam0 ``T_wc`` (body ground truth right-multiplied by ``T_bc``).

        Raises ``InputError`` when the ground truth is of the body but no extrinsic ``T_bc`` is
        known (mapping through an assumed identity would put the lever arm into every metric)."""
        if self.ground_truth is None:
            return None
        if self.gt_frame == "camera":
            return self.ground_truth
        if not self.calibration.T_bc_known:
            raise InputError(f"{self.path}: the ground truth is of the body (IMU) frame, but the recording "
                             f"gives no camera-to-body extrinsic T_bc to map it to cam0; give one with "
                             f"--calib FILE (or, for 'vings eval', --gt-frame camera if it holds camera poses)")
        return self.ground_truth.right_multiply(self.calibration.T_bc)

    def stream(self) -> Iterator[Union[Frame, ImuSample]]:
        """Frames and IMU samples merged in time order (IMU first on equal stamps)."""
        imu = ((s.stamp_ns, 0, i, s) for i, s in enumerate(self.imu_samples()))
        frm = ((f.stamp_ns, 1, i, f) for i, f in enumerate(self.frames()))
        for _, _, _, item in heapq.merge(imu, frm, key=lambda x: (x[0], x[1], x[2])):
            yield item

    def info(self) -> dict:
        """Summary: frames, IMU samples, rates, resolution, calibration, ground-truth span."""
        fs = self.frame_stamps()
        imu = self.imu_samples()
        ist = np.array([s.stamp_ns for s in imu], dtype=np.int64)

        def rate(st: np.ndarray) -> Optional[float]:
            return float((len(st) - 1) / ((st[-1] - st[0]) * 1e-9)) if len(st) > 1 and st[-1] > st[0] else None

        gt = self.ground_truth
        cam = self.calibration.camera
        raw = self.raw_camera
        out = {
            "path": str(self.path), "kind": self.kind,
            "frames": int(len(fs)),
            "frame_rate_hz": rate(fs),
            "first_stamp_ns": int(fs[0]) if len(fs) else None,
            "last_stamp_ns": int(fs[-1]) if len(fs) else None,
            "duration_s": float((fs[-1] - fs[0]) * 1e-9) if len(fs) > 1 else 0.0,
            "imu_samples": int(len(ist)),
            "imu_rate_hz": rate(ist),
            "resolution": [cam.width, cam.height] if cam is not None else None,
            "native_resolution": [raw.width, raw.height] if raw is not None else None,
            "calibration": self.calibration.to_dict(),
            "ground_truth": None if gt is None or len(gt) == 0 else {
                "poses": int(len(gt)), "frame": self.gt_frame,
                "first_stamp_ns": int(gt.stamps_ns[0]), "last_stamp_ns": int(gt.stamps_ns[-1]),
                "duration_s": float((gt.stamps_ns[-1] - gt.stamps_ns[0]) * 1e-9),
                "path_length_m": gt.path_length(),
            },
            "warnings": list(self.warnings),
        }
        return out
