"""EuRoC / ASL folders (``mav0/``), as written by the EuRoC MAV dataset and ``vings sim``.

Layout (``PATH`` is the folder holding ``mav0/``, or ``mav0`` itself)::

    mav0/cam0/data.csv                 #timestamp [ns],filename
    mav0/cam0/data/<ns>.png            8-bit mono or colour (16-bit is shifted to 8 bit)
    mav0/cam0/sensor.yaml              intrinsics, distortion, resolution, T_BS (cam0-to-body)
    mav0/imu0/data.csv                 t[ns], gyro xyz [rad/s], accel xyz [m/s^2]   (optional)
    mav0/imu0/sensor.yaml              noise densities / random walks, rate_hz, T_BS
    mav0/state_groundtruth_estimate0/data.csv   t[ns], p xyz [m], q wxyz, ...  (body GT, optional)
    mav0/depth0/data/<ns>.npy          float32 z-depth [m] at cam0 resolution (optional)
    mav0/mask0/data/<ns>.png           uint8, 255 = dynamic object (optional)
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import numpy as np

from ..errors import InputError
from ..geometry import np_quat_to_rotmat
from .base import SourceOptions
from .calib_yaml import CalibParts, parse_calibration, read_calibration_parts, read_yaml_doc
from .common import FileFramesSource, check_size, read_table
from .image_codec import read_image_file


def find_mav0(path: Path) -> Optional[Path]:
    """The ``mav0`` folder of an EuRoC sequence at ``path`` (or ``None``)."""
    path = Path(path)
    if (path / "mav0" / "cam0").is_dir():
        return path / "mav0"
    if path.name == "mav0" and (path / "cam0").is_dir():
        return path
    if (path / "cam0" / "data.csv").is_file() or (path / "cam0" / "data").is_dir():
        return path
    return None


class EurocSource(FileFramesSource):
    """EuRoC/ASL folder loader (see the module doc). GT is of the body: ``gt_frame == 'body'``."""

    def __init__(self, path: str | Path, options: Optional[SourceOptions] = None) -> None:
        super().__init__(Path(path), "euroc", options)
        if not self.path.exists():
            raise InputError(f"{self.path}: EuRoC folder not found")
        mav0 = find_mav0(self.path)
        if mav0 is None:
            raise InputError(f"{self.path}: not an EuRoC/ASL folder (no mav0/cam0/)")
        self.mav0 = mav0
        cam_dir = mav0 / "cam0"
        self._read_frames(cam_dir)
        imu_parts = self._read_imu(mav0 / "imu0")
        raw, parts = self._read_calibration(cam_dir, imu_parts)
        if len(self._stamps):
            first = read_image_file(self._files[0])
            raw = check_size(raw, first.shape[1], first.shape[0], str(self._files[0]), self._warn)
        self._set_camera(raw, parts.to_calibration(raw))
        self._read_gt(mav0 / "state_groundtruth_estimate0")
        self._depth_dir = mav0 / "depth0" / "data"
        self._mask_dir = mav0 / "mask0" / "data"

    # -- parts -----------------------------------------------------------------------------------
    def _read_frames(self, cam_dir: Path) -> None:
        csv = cam_dir / "data.csv"
        data_dir = cam_dir / "data"
        if csv.is_file():
            stamps, _, rows = read_table(csv, 2, "cam0 image list", sep=",", n_numeric=0)
            files = [data_dir / r[1] for r in rows]
        elif data_dir.is_dir():
            found = sorted(p for p in data_dir.iterdir() if p.suffix.lower() in (".png", ".jpg")
                           and p.stem.isdigit())
            if not found:
                raise InputError(f"{data_dir}: no images named <stamp_ns>.png and no {csv}")
            self._warn(f"{csv} not found: using the {len(found)} image file names as time stamps")
            stamps = np.array([int(p.stem) for p in found], dtype=np.int64)
            files = found
        else:
            raise InputError(f"{cam_dir}: neither data.csv nor data/ found")
        exists = np.array([f.is_file() for f in files], dtype=bool)
        if not exists.all():
            miss = [str(f) for f, e in zip(files, exists) if not e]
            if not exists.any():
                raise InputError(f"{csv}: none of the {len(files)} listed images exist "
                                 f"(first: {miss[0]})")
            self._warn(f"{csv}: {len(miss)} listed image file(s) missing, skipped (first: {miss[0]})")
            stamps = stamps[exists]
            files = [f for f, e in zip(files, exists) if e]
        if len(files) == 0:
            self._warn(f"{csv}: no images listed")
        self._set_frames(stamps, files, f"{csv}")

    def _read_imu(self, imu_dir: Path) -> CalibParts:
        parts = CalibParts()
        csv = imu_dir / "data.csv"
        self._T_b_imu = np.eye(4)
        if (imu_dir / "sensor.yaml").is_file():
            doc = read_yaml_doc(imu_dir / "sensor.yaml")
            parts = parse_calibration(doc, str(imu_dir / "sensor.yaml"))
            if "T_BS" in doc:
                from .calib_yaml import _matrix, _rigid
                w = str(imu_dir / "sensor.yaml")
                self._T_b_imu = _rigid(_matrix(doc["T_BS"], 4, w, "T_BS"), w, "T_BS")
            if isinstance(doc.get("rate_hz"), (int, float)):
                parts.imu_rate_hz = float(doc["rate_hz"])
        if csv.is_file():
            st, v, _ = read_table(csv, 7, "IMU")
            if len(st) == 0:
                self._warn(f"{csv}: no IMU samples")
            self._set_imu(st, v[:, 0:3], v[:, 3:6], str(csv))
            parts.has_imu = len(self._imu_st) > 0
            if parts.imu_rate_hz is None:
                parts.imu_rate_hz = self._imu_rate()
        else:
            parts.has_imu = False
        return parts

    def _read_calibration(self, cam_dir: Path, imu_parts: CalibParts):
        yaml_path = cam_dir / "sensor.yaml"
        parts = CalibParts()
        if yaml_path.is_file():
            parts = read_calibration_parts(yaml_path)
        camera = parts.camera
        T_bc = parts.T_bc
        if T_bc is not None and not np.allclose(self._T_b_imu, np.eye(4)):
            T_bc = np.linalg.inv(self._T_b_imu) @ T_bc  # body of VINGS = IMU frame
        merged = CalibParts(camera=camera, T_bc=T_bc, noise=dict(imu_parts.noise),
                            imu_rate_hz=imu_parts.imu_rate_hz, has_imu=imu_parts.has_imu)
        if self.options.calib_file:
            o = read_calibration_parts(self.options.calib_file)
            merged.camera = o.camera or merged.camera
            merged.T_bc = o.T_bc if o.T_bc is not None else merged.T_bc
            merged.noise.update(o.noise)
        if merged.camera is None:
            raise InputError(f"{yaml_path}: camera calibration not found (give one with --calib FILE)")
        if merged.has_imu and not merged.noise:
            self._warn(f"{self.mav0 / 'imu0' / 'sensor.yaml'}: no IMU noise parameters; using the "
                       f"defaults (EuRoC ADIS16448)")
        return merged.camera, merged

    def _read_gt(self, gt_dir: Path) -> None:
        csv = gt_dir / "data.csv"
        if not csv.is_file():
            return
        st, v, _ = read_table(csv, 8, "ground truth")
        if len(st) == 0:
            self._warn(f"{csv}: no ground-truth rows")
            return
        q_wxyz = v[:, 3:7]
        n = np.linalg.norm(q_wxyz, axis=1)
        if np.any(n < 1e-6):
            raise InputError(f"{csv}: zero quaternion in row {int(np.argmax(n < 1e-6)) + 1}")
        q_xyzw = np.concatenate([q_wxyz[:, 1:4], q_wxyz[:, :1]], axis=1) / n[:, None]
        T = np.tile(np.eye(4), (len(st), 1, 1))
        T[:, :3, :3] = np_quat_to_rotmat(q_xyzw)
        T[:, :3, 3] = v[:, 0:3]
        # GT is of the sensor S of state_groundtruth_estimate0 (T_BS, identity in EuRoC); map to IMU.
        T_bs = np.eye(4)
        if (gt_dir / "sensor.yaml").is_file():
            doc = read_yaml_doc(gt_dir / "sensor.yaml")
            if "T_BS" in doc:
                from .calib_yaml import _matrix, _rigid
                w = str(gt_dir / "sensor.yaml")
                T_bs = _rigid(_matrix(doc["T_BS"], 4, w, "T_BS"), w, "T_BS")
        if not (np.allclose(T_bs, np.eye(4)) and np.allclose(self._T_b_imu, np.eye(4))):
            T = T @ np.linalg.inv(T_bs) @ self._T_b_imu
        self._set_gt(st, T, str(csv), "body")

    # -- optional ground-truth images ------------------------------------------------------------
    def _raw_size(self) -> tuple[int, int]:
        return self.raw_camera.width, self.raw_camera.height

    def gt_depth(self, stamp_ns: int) -> Optional[np.ndarray]:
        """``mav0/depth0/data/<stamp>.npy`` (float32 z-depth, m) at the working resolution, or None."""
        f = self._depth_dir / f"{int(stamp_ns)}.npy"
        if not f.is_file():
            return None
        try:
            d = np.load(f, allow_pickle=False)
        except Exception as e:  # noqa: BLE001 - any numpy failure means a bad file
            raise InputError(f"{f}: cannot read depth map: {e}") from None
        w, h = self._raw_size()
        if d.shape != (h, w):
            raise InputError(f"{f}: depth map has shape {d.shape}, expected ({h}, {w}) like cam0")
        return self._undist(np.ascontiguousarray(d, dtype=np.float32), nearest=True)

    def gt_mask(self, stamp_ns: int) -> Optional[np.ndarray]:
        """``mav0/mask0/data/<stamp>.png`` (255 = dynamic) as bool at the working resolution, or None."""
        f = self._mask_dir / f"{int(stamp_ns)}.png"
        if not f.is_file():
            return None
        m = read_image_file(f)
        if m.ndim == 3:
            m = m[..., 0]
        w, h = self._raw_size()
        if m.shape != (h, w):
            raise InputError(f"{f}: mask has shape {m.shape}, expected ({h}, {w}) like cam0")
        return self._undist(np.ascontiguousarray(m > 127), nearest=True)

    def _extra_info(self) -> dict:
        return {"has_depth": self._depth_dir.is_dir() and any(self._depth_dir.glob("*.npy")),
                "has_mask": self._mask_dir.is_dir() and any(self._mask_dir.glob("*.png"))}
