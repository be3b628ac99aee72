"""TUM RGB-D folders (also the Bonn RGB-D Dynamic dataset, same layout).

Layout::

    rgb.txt           "timestamp[s] filename" per line (filename relative to the folder)
    groundtruth.txt   "timestamp[s] tx ty tz qx qy qz qw" (optional) - pose of the CAMERA
    depth.txt         "timestamp[s] filename" of 16-bit PNGs, depth [m] = value / 5000 (optional)
    accelerometer.txt ignored (accelerometer only, no gyroscope: not usable as an IMU)

Calibration (the folder does not carry one), in this order: ``SourceOptions.calib_file`` (a YAML
file in any layout :mod:`calib_yaml` reads, or a preset name ``tum-fr1``/``tum-fr2``/``tum-fr3``);
a ``calib.yaml``/``calibration.yaml``/``camera.yaml`` in the folder; the published Kinect intrinsics
when the folder name says ``freiburg1``/``2``/``3`` (with a warning). Otherwise an InputError.
"""
from __future__ import annotations

import re
from pathlib import Path
from typing import Optional

import numpy as np

from ..errors import InputError
from ..geometry import np_quat_to_rotmat
from .base import SourceOptions
from .calib_yaml import PRESETS, CalibParts, read_calibration_parts
from .common import FileFramesSource, check_size, order_stamps, read_table
from .image_codec import read_image_file

CALIB_NAMES = ("calib.yaml", "calibration.yaml", "camera.yaml")
DEPTH_SCALE = 5000.0  # TUM: 16-bit PNG value / 5000 = metres
ASSOC_MAX_NS = 20_000_000  # TUM associate.py default: 0.02 s


def resolve_calibration(path: Path, calib_file: Optional[str], warn) -> CalibParts:
    """Calibration of a TUM-style folder (see the module doc)."""
    if calib_file:
        if str(calib_file).lower() in PRESETS:
            return CalibParts(camera=PRESETS[str(calib_file).lower()])
        return read_calibration_parts(calib_file)
    for name in CALIB_NAMES:
        if (path / name).is_file():
            return read_calibration_parts(path / name)
    m = re.search(r"freiburg([123])", path.resolve().name)
    if m:
        key = f"tum-fr{m.group(1)}"
        warn(f"{path}: no calibration file; using the published {key} Kinect intrinsics "
             f"(folder name says freiburg{m.group(1)}); pass --calib FILE to override")
        return CalibParts(camera=PRESETS[key])
    raise InputError(f"{path}: TUM RGB-D folder has no calibration: pass --calib FILE (a YAML "
                     f"calibration) or --calib tum-fr1|tum-fr2|tum-fr3, or put "
                     f"{'/'.join(CALIB_NAMES)} in the folder")


class TumSource(FileFramesSource):
    """TUM RGB-D / Bonn folder loader. Ground truth is of the camera: ``gt_frame == 'camera'``."""

    def __init__(self, path: str | Path, options: Optional[SourceOptions] = None) -> None:
        super().__init__(Path(path), "tum", options)
        if not self.path.is_dir():
            raise InputError(f"{self.path}: TUM RGB-D folder not found")
        rgb = self.path / "rgb.txt"
        st, _, rows = read_table(rgb, 2, "image list (rgb.txt)", stamp_in_seconds=True, n_numeric=0)
        files = [self.path / r[1] for r in rows]
        exists = np.array([f.is_file() for f in files], dtype=bool)
        if len(files) and not exists.any():
            raise InputError(f"{rgb}: none of the {len(files)} listed images exist (first: {files[0]})")
        if not exists.all():
            miss = [str(f) for f, e in zip(files, exists) if not e]
            self._warn(f"{rgb}: {len(miss)} listed image file(s) missing, skipped (first: {miss[0]})")
            st = st[exists]
            files = [f for f, e in zip(files, exists) if e]
        if len(files) == 0:
            self._warn(f"{rgb}: no images listed")
        self._set_frames(st, files, str(rgb))

        parts = resolve_calibration(self.path, self.options.calib_file, self._warn)
        if parts.camera is None:
            raise InputError(f"{self.options.calib_file}: no camera calibration in this file")
        raw = parts.camera
        if len(self._stamps):
            first = read_image_file(self._files[0])
            raw = check_size(raw, first.shape[1], first.shape[0], str(self._files[0]), self._warn)
        parts.has_imu = False
        self._set_camera(raw, parts.to_calibration(raw))
        self._read_gt(self.path / "groundtruth.txt")
        self._read_depth(self.path / "depth.txt")

    def _read_gt(self, f: Path) -> None:
        if not f.is_file():
            return
        st, v, _ = read_table(f, 8, "ground truth", stamp_in_seconds=True)
        if len(st) == 0:
            self._warn(f"{f}: no ground-truth rows")
            return
        q = v[:, 3:7]
        n = np.linalg.norm(q, axis=1)
        if np.any(n < 1e-6):
            raise InputError(f"{f}: zero quaternion in data row {int(np.argmax(n < 1e-6)) + 1}")
        T = np.tile(np.eye(4), (len(st), 1, 1))
        T[:, :3, :3] = np_quat_to_rotmat(q / n[:, None])
        T[:, :3, 3] = v[:, 0:3]
        self._set_gt(st, T, str(f), "camera")

    def _read_depth(self, f: Path) -> None:
        self._depth_st = np.zeros(0, dtype=np.int64)
        self._depth_files: list[Path] = []
        if not f.is_file():
            return
        st, _, rows = read_table(f, 2, "depth list (depth.txt)", stamp_in_seconds=True, n_numeric=0)
        idx = order_stamps(st, str(f), self._warn)
        self._depth_st = st[idx]
        self._depth_files = [self.path / rows[i][1] for i in idx]

    def depth_file(self, stamp_ns: int) -> Optional[Path]:
        """Depth PNG nearest in time to ``stamp_ns`` (within 20 ms), or None."""
        if len(self._depth_st) == 0:
            return None
        i = int(np.searchsorted(self._depth_st, stamp_ns))
        cands = [j for j in (i - 1, i) if 0 <= j < len(self._depth_st)]
        j = min(cands, key=lambda k: abs(int(self._depth_st[k]) - int(stamp_ns)))
        if abs(int(self._depth_st[j]) - int(stamp_ns)) > ASSOC_MAX_NS:
            return None
        return self._depth_files[j]

    def gt_depth(self, stamp_ns: int) -> Optional[np.ndarray]:
        """Sensor depth (value / 5000 m) associated by time (<= 20 ms), at the working resolution.

        This is the RGB-D sensor's depth (the usual reference for TUM), not a perfect ground truth.
        """
        f = self.depth_file(stamp_ns)
        if f is None:
            return None
        d = read_image_file(f)
        if d.ndim != 2 or d.dtype != np.uint16:
            raise InputError(f"{f}: depth image must be a 16-bit single-channel PNG, got "
                             f"{d.dtype} {d.shape}")
        if d.shape != (self.raw_camera.height, self.raw_camera.width):
            raise InputError(f"{f}: depth image is {d.shape[1]}x{d.shape[0]}, expected "
                             f"{self.raw_camera.width}x{self.raw_camera.height}")
        return self._undist(d.astype(np.float32) / DEPTH_SCALE, nearest=True)

    def _extra_info(self) -> dict:
        return {"has_depth": len(self._depth_st) > 0, "has_mask": False}
