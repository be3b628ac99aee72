"""KITTI odometry folders (one sequence).

Layout (``PATH`` is the sequence folder, e.g. ``dataset/sequences/06``)::

    image_0/ | image_l/ | image_2/  000000.png ...  (first found is used; image_0/_l = left gray)
    times.txt      one time [s] per frame (if missing: 10 Hz from 0, with a warning)
    calib.txt      3x4 projection matrices P0..P3, one per line, with or without "P0:" labels
    poses.txt | poses/NN.txt | ../../poses/NN.txt   row-major 3x4 [R|t] of camera 0 (optional)

Images are rectified (no distortion). Ground truth is the pose of camera 0 in the frame of camera 0
at frame 0; with ``image_2`` it is moved to camera 2 using P2's baseline from ``calib.txt`` (also
when ``--calib`` gives the intrinsics). ``gt_frame == 'camera'``.
There is no IMU.
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import numpy as np

from ..errors import InputError
from ..types import Calibration, CameraModel
from .base import SourceOptions
from .calib_yaml import read_calibration_parts
from .common import FileFramesSource, check_size, read_table
from .image_codec import read_image_file

IMAGE_DIRS = (("image_0", 0), ("image_l", 0), ("image_2", 2))


def kitti_image_dir(path: Path) -> Optional[tuple[Path, int]]:
    for name, cam in IMAGE_DIRS:
        if (path / name).is_dir():
            return path / name, cam
    return None


def _numbers(text: str, path: Path, ln: int) -> np.ndarray:
    """The whitespace-separated numbers of ``text`` (line ``ln`` of ``path``); an
    :class:`InputError` naming that line when one is not a number."""
    try:
        return np.array([float(x) for x in text.split()])
    except ValueError:
        raise InputError(f"{path}:{ln}: not a list of numbers") from None


def read_kitti_calib(path: Path) -> dict[int, np.ndarray]:
    """``calib.txt`` -> {camera index: 3x4 P}; lines labelled ``P<i>:`` or unlabelled (line i)."""
    if not path.is_file():
        raise InputError(f"{path}: KITTI calib.txt not found")
    out: dict[int, np.ndarray] = {}
    unlabelled = 0
    for ln, line in enumerate(path.read_text().splitlines(), 1):
        line = line.strip()
        if not line:
            continue
        label = None
        if ":" in line:
            label, line = line.split(":", 1)
            label = label.strip()
        v = _numbers(line, path, ln)
        if label is None:
            key = unlabelled
            unlabelled += 1
        elif len(label) == 2 and label[0] == "P" and label[1].isdigit():
            key = int(label[1])
        else:
            continue  # Tr:, R0_rect: ...
        if v.size != 12:
            raise InputError(f"{path}:{ln}: P{key} needs 12 numbers, got {v.size}")
        out[key] = v.reshape(3, 4)
    if not out:
        raise InputError(f"{path}: no projection matrices found")
    return out


def read_kitti_poses(path: Path) -> np.ndarray:
    """Poses file -> (N, 4, 4) float64."""
    rows = []
    for ln, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip():
            continue
        v = _numbers(line, path, ln)
        if v.size == 13:  # some copies put the time in front
            v = v[1:]
        if v.size != 12:
            raise InputError(f"{path}:{ln}: expected 12 numbers (row-major 3x4), got {v.size}")
        T = np.eye(4)
        T[:3, :] = v.reshape(3, 4)
        rows.append(T)
    if not rows:
        raise InputError(f"{path}: no poses")
    return np.stack(rows)


def find_kitti_poses(path: Path) -> Optional[Path]:
    seq = path.resolve().name
    cands = [path / "poses.txt", path / "poses" / f"{seq}.txt", path.parent.parent / "poses" / f"{seq}.txt"]
    for c in cands:
        if c.is_file():
            return c
    pdir = path / "poses"
    if pdir.is_dir():
        txt = sorted(pdir.glob("*.txt"))
        if len(txt) == 1:
            return txt[0]
    return None


def _numbered_images(img_dir: Path) -> tuple[list[Path], np.ndarray]:
    """The ``.png``/``.jpg`` images of ``img_dir`` and their frame numbers (int64).

    KITTI names frames by their number (000123.png): times.txt and the poses file have one line per
    frame number, so a subset of the images (or a gap) is paired by number, not position. Images
    are ordered by number (2.png before 10.png when the names are not zero-padded); when any name
    is not a number, by name, numbered by position."""
    files = sorted(p for p in img_dir.iterdir() if p.suffix.lower() in (".png", ".jpg"))
    if not files:
        raise InputError(f"{img_dir}: no images")
    numbers = [int(p.stem) if p.stem.isdigit() else None for p in files]
    by_number = all(n is not None for n in numbers)
    if by_number:
        files, numbers = zip(*sorted(zip(files, numbers), key=lambda fn: fn[1]))
        files, numbers = list(files), list(numbers)
    return files, np.array(numbers if by_number else range(len(files)), dtype=np.int64)


class KittiSource(FileFramesSource):
    """KITTI odometry sequence loader (see the module doc)."""

    def __init__(self, path: str | Path, options: Optional[SourceOptions] = None) -> None:
        super().__init__(Path(path), "kitti", options)
        if not self.path.is_dir():
            raise InputError(f"{self.path}: KITTI folder not found")
        found = kitti_image_dir(self.path)
        if found is None:
            raise InputError(f"{self.path}: no image_0/, image_l/ or image_2/ folder")
        img_dir, cam = found
        self.camera_index = cam
        files, idx = _numbered_images(img_dir)
        times = self.path / "times.txt"
        st, files, idx = self._frame_times(times, files, idx)
        self._set_frames(st, files, str(times))
        P_cam = self._set_kitti_camera(img_dir, cam, files)
        pose_file = find_kitti_poses(self.path)
        if pose_file is not None:
            if cam != 0 and P_cam is None:
                P_cam = self._lever_arm_camera(cam)
            self._set_kitti_gt(pose_file, idx, st, cam, P_cam)

    def _frame_times(self, times: Path, files: list[Path], idx: np.ndarray
                     ) -> tuple[np.ndarray, list[Path], np.ndarray]:
        """Stamps (ns) of the images numbered ``idx`` from ``times`` (s; 10 Hz from 0 when it is
        missing, warned), with the images and numbers that have one."""
        if not times.is_file():
            self._warn(f"{times} not found: assuming 10 Hz frames from t = 0")
            return idx * 100_000_000, files, idx
        st, _, _ = read_table(times, 1, "frame times (times.txt)", stamp_in_seconds=True)
        if len(st) == 0:
            raise InputError(f"{times}: no time stamps")
        line = self._line_index(idx, len(st), times, "times")
        keep = line < len(st)
        if not keep.any():
            raise InputError(f"{times}: {len(st)} times, none for the images numbered "
                             f"{int(idx.min())}..{int(idx.max())}")
        if not keep.all():
            self._warn(f"{times}: {len(st)} times; the {int((~keep).sum())} image(s) numbered "
                       f"{int(idx[~keep][0])} and above have none and are left out")
            files = [f for f, k in zip(files, keep) if k]
            idx, line = idx[keep], line[keep]
        return st[line], files, idx

    def _set_kitti_camera(self, img_dir: Path, cam: int, files: list[Path]) -> Optional[np.ndarray]:
        """Install the camera of ``img_dir`` (camera ``cam``): from ``--calib``, else ``P<cam>`` of
        calib.txt, sized by the first image. Returns that 3x4 P (None with ``--calib``)."""
        first = read_image_file(self._files[0] if self._files else files[0])
        h, w = first.shape[:2]
        if self.options.calib_file:
            parts = read_calibration_parts(self.options.calib_file)
            if parts.camera is None:
                raise InputError(f"{self.options.calib_file}: no camera calibration in this file")
            raw = check_size(parts.camera, w, h, str(files[0]), self._warn)
            calib = parts.to_calibration(raw)
            P_cam = None     # the lever arm to camera 0 (ground truth): from calib.txt, if needed
        else:
            Ps = read_kitti_calib(self.path / "calib.txt")
            if cam not in Ps:
                raise InputError(f"{self.path / 'calib.txt'}: no P{cam} for {img_dir.name}/")
            P_cam = Ps[cam]
            raw = CameraModel(w, h, P_cam[0, 0], P_cam[1, 1], P_cam[0, 2], P_cam[1, 2])
            calib = Calibration(camera=raw)
        calib.has_imu = False
        self._set_camera(raw, calib)
        return P_cam

    def _set_kitti_gt(self, pose_file: Path, idx: np.ndarray, st: np.ndarray, cam: int,
                      P_cam: Optional[np.ndarray]) -> None:
        """Ground truth ``T_w_cam`` of the images numbered ``idx`` (stamps ``st``, ns) from
        ``pose_file`` (camera 0), moved to camera ``cam`` by the baseline of ``P_cam`` if given."""
        poses = read_kitti_poses(pose_file)
        pidx = self._line_index(idx, len(poses), pose_file, "poses")
        has = pidx < len(poses)
        if not has.all():
            self._warn(f"{pose_file}: {len(poses)} poses; no ground truth for the "
                       f"{int((~has).sum())} frame(s) numbered {int(pidx[~has][0])} and above")
        all_st = np.asarray(st)[has]
        poses = poses[pidx[has]]
        if P_cam is not None and cam != 0:
            # x_cam = x_cam0 + t with t = K^-1 P[:, 3]: T_cam0_cam = [I | -t]
            t = np.linalg.solve(P_cam[:, :3], P_cam[:, 3])
            T0c = np.eye(4)
            T0c[:3, 3] = -t
            poses = poses @ T0c
        self._set_gt(all_st, poses, str(pose_file), "camera")

    def _line_index(self, idx: np.ndarray, n_lines: int, path: Path, what: str) -> np.ndarray:
        """Line of ``path`` (times / poses: one line per frame number) for each image number
        ``idx``: the number itself; when the file does not even reach the first image's number (it
        was cut to the subset), the number less the first one if their span fits, else the image's
        position if the file has one line per image; both warned. Lines past the file mean no time /
        pose for that image (the caller's business)."""
        if not len(idx) or idx.min() < n_lines:
            return idx
        if idx.max() - idx.min() < n_lines:
            self._warn(f"{path}: {n_lines} {what} for images numbered {int(idx.min())}..{int(idx.max())}: "
                       f"line 0 taken as image {int(idx.min())} (a file cut to the subset)")
            return idx - idx.min()
        if n_lines == len(idx):
            self._warn(f"{path}: {n_lines} {what} for images numbered up to {int(idx.max())}: "
                       f"paired by position (one line per image)")
            return np.arange(n_lines, dtype=np.int64)
        return idx

    def _lever_arm_camera(self, cam: int) -> Optional[np.ndarray]:
        """P of camera ``cam`` from the sequence's calib.txt when ``--calib`` gave the intrinsics
        (only its baseline is used, to move the camera-0 ground truth); None, with a warning, when
        calib.txt is missing, unreadable or has no such P."""
        path = self.path / "calib.txt"
        P = None
        try:
            P = read_kitti_calib(path).get(cam) if path.is_file() else None
        except InputError as e:
            self._warn(f"{e}")
        if P is None:
            self._warn(f"{path}: no P{cam} to move the camera-0 ground truth to camera {cam}: it stays "
                       f"at camera 0 (~6 cm off on KITTI)")
        return P
