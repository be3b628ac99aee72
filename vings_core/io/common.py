"""Helpers shared by the loaders: time-stamp repair, text tables, the loader base class."""
from __future__ import annotations

import logging
from pathlib import Path
from typing import Callable, Iterator, Optional

import numpy as np

from ..errors import InputError
from ..types import Calibration, CameraModel, Frame, ImuSample, Trajectory
from .base import BadFramePolicy, Source, SourceOptions
from .image_codec import FrameConverter, read_image_file
from .undistort import Undistorter

log = logging.getLogger("vings.io")


def order_stamps(stamps: np.ndarray, what: str, warn: Callable[[str], None]) -> np.ndarray:
    """Indices that put ``stamps`` in strictly increasing order.

    Negative stamps are refused (dropped: no clock gives them), out-of-order entries are sorted
    (stable) and duplicated stamps dropped (the first one in file order is kept); each is reported
    through ``warn`` naming ``what`` and the count.
    """
    stamps = np.asarray(stamps, dtype=np.int64)
    neg = stamps < 0
    if neg.any():
        warn(f"{what}: {int(neg.sum())} negative time stamp(s) refused (dropped)")
        pos = np.nonzero(~neg)[0]
        return pos[order_stamps(stamps[pos], what, warn)]
    n = len(stamps)
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    back = int(np.count_nonzero(np.diff(stamps) < 0))
    order = np.argsort(stamps, kind="stable")
    s = stamps[order]
    keep = np.ones(n, dtype=bool)
    keep[1:] = s[1:] != s[:-1]
    dups = int(n - keep.sum())
    if back:
        warn(f"{what}: {back} time stamp(s) out of order; sorted {n} entries by time")
    if dups:
        warn(f"{what}: {dups} duplicated time stamp(s); dropped, keeping the first of each")
    return order[keep]


def late_entries(arrival: np.ndarray, window: int) -> np.ndarray:
    """Bool mask of entries a reorder buffer of ``window`` entries cannot deliver in order.

    ``arrival[k]``: position in the file of the ``k``-th entry in time order. Reading the file in
    order and delivering in time order, an entry that arrives while ``window`` later-stamped ones
    already wait cannot be waited for any longer: it is marked (dropped), and the ones behind it go
    on. Replaying this mask while reading keeps at most ``window`` entries pending.
    """
    n = len(arrival)
    dropped = np.zeros(n, dtype=bool)
    arrived = np.zeros(n, dtype=bool)
    nxt = 0
    pending = 0
    for k in np.argsort(np.asarray(arrival), kind="stable").tolist():
        if k < nxt:
            continue            # passed over already (marked dropped when it blocked)
        arrived[k] = True
        pending += 1
        while True:
            while nxt < n and (arrived[nxt] or dropped[nxt]):
                pending -= int(arrived[nxt])
                nxt += 1
            if pending <= window:
                break
            dropped[nxt] = True     # the entry everything waits for is too late
            nxt += 1
    return dropped


def read_table(path: Path, min_cols: int, what: str, sep: Optional[str] = None,
               stamp_in_seconds: bool = False, n_numeric: Optional[int] = None
               ) -> tuple[np.ndarray, np.ndarray, list[list[str]]]:
    """Read a text table with a time stamp in column 0 (``#``/``%`` comments and blank lines skipped;
    the first remaining line may be a header without ``#``).

    Returns ``(stamps_ns int64 (N,), values float64 (N, n_numeric), raw_rows)`` where the values are
    columns ``1 .. n_numeric`` (default ``min_cols - 1``). Stamps are integer nanoseconds, or seconds
    (``stamp_in_seconds``) converted exactly. Bad rows raise :class:`InputError` naming the file and
    line.
    """
    from ..trajectory_io import str_to_stamp_ns

    if n_numeric is None:
        n_numeric = min_cols - 1
    if not path.is_file():
        raise InputError(f"{path}: {what} file not found")
    stamps: list[int] = []
    vals: list[list[float]] = []
    rows: list[list[str]] = []
    first = True
    with open(path, "r", errors="replace") as f:
        for ln, line in enumerate(f, 1):
            line = line.strip()
            if not line or line.startswith("#") or line.startswith("%"):
                continue
            parts = [p.strip() for p in (line.split(sep) if sep else line.replace(",", " ").split())]
            parts = [p for p in parts if p != ""]
            try:
                if len(parts) < min_cols:
                    raise InputError(f"{path}:{ln}: expected at least {min_cols} columns, got {len(parts)}")
                try:
                    st = str_to_stamp_ns(parts[0]) if stamp_in_seconds else int(parts[0])
                    v = [float(p) for p in parts[1:1 + n_numeric]]
                except ValueError:
                    raise InputError(f"{path}:{ln}: not a number in {parts[:1 + n_numeric]}") from None
            except InputError:
                if first and not _is_number(parts[0]):
                    first = False
                    continue  # a header line without '#'
                raise
            first = False
            if not np.all(np.isfinite(v)):
                raise InputError(f"{path}:{ln}: non-finite value")
            stamps.append(st)
            vals.append(v)
            rows.append(parts)
    return (np.asarray(stamps, dtype=np.int64),
            np.asarray(vals, dtype=np.float64).reshape(len(vals), n_numeric), rows)


def _is_number(s: str) -> bool:
    try:
        float(s)
        return True
    except ValueError:
        return False


def imu_from_arrays(stamps: np.ndarray, gyro: np.ndarray, accel: np.ndarray) -> list[ImuSample]:
    return [ImuSample(int(s), g.copy(), a.copy()) for s, g, a in zip(stamps, gyro, accel)]


def check_size(raw: CameraModel, actual_w: int, actual_h: int, where: str,
               warn: Callable[[str], None]) -> CameraModel:
    """Reconcile a calibration's size with the images': equal -> as is; same aspect -> scaled with
    a warning; otherwise an :class:`InputError`."""
    if (raw.width, raw.height) == (actual_w, actual_h):
        return raw
    if abs(raw.width / raw.height - actual_w / actual_h) < 1e-3:
        warn(f"{where}: calibration is for {raw.width}x{raw.height} but the images are "
             f"{actual_w}x{actual_h}; intrinsics scaled")
        return raw.scaled(actual_w, actual_h)
    raise InputError(f"{where}: calibration is for {raw.width}x{raw.height} but the images are "
                     f"{actual_w}x{actual_h} (different aspect ratio)")


def calibration_dict(c: Optional[Calibration]) -> Optional[dict]:
    """``Calibration.to_dict()``, None for no calibration (``camera`` is None when camera-less)."""
    return None if c is None else c.to_dict()


class LoaderSource(Source):
    """Base of the VINGS loaders: options, warnings, the image pipeline and IMU storage.

    ``calibration`` is always a :class:`Calibration`; its ``camera`` is ``None`` only for recordings
    without a camera (e.g. an IMU-only bag), which deliver no frames.
    """

    def __init__(self, path: Path, kind: str, options: Optional[SourceOptions]) -> None:
        self.path = Path(path)
        self.kind = kind
        self.options = options or SourceOptions()
        self.bad_frames: list[str] = []     # frames skipped as undecodable (on_bad_frame skip)
        self.warnings: list[str] = []
        self.ground_truth: Optional[Trajectory] = None
        self.gt_frame = "body"
        self.raw_camera: Optional[CameraModel] = None
        self.calibration: Optional[Calibration] = None  # type: ignore[assignment]
        self._undist: Optional[Undistorter] = None
        self._imu_st = np.zeros(0, dtype=np.int64)
        self._imu_g = np.zeros((0, 3))
        self._imu_a = np.zeros((0, 3))
        self._imu_cache: Optional[list[ImuSample]] = None
        self._converter = FrameConverter(str(self.path), self._warn)
        if self.options.max_frames is not None and int(self.options.max_frames) < 0:
            from ..errors import ConfigError
            raise ConfigError(f"max_frames must be >= 0, got {self.options.max_frames}")

    # -- helpers ---------------------------------------------------------------------------------
    def _warn(self, msg: str) -> None:
        if msg not in self.warnings:
            log.warning(msg)
            self.warnings.append(msg)

    def _limit(self, n: int) -> int:
        m = self.options.max_frames
        return n if m is None else min(n, int(m))

    def _set_camera(self, raw: CameraModel, calib_extra: Calibration) -> None:
        """Install the raw camera and the delivered calibration (working resolution)."""
        self.raw_camera = raw
        o = self.options
        self._undist = Undistorter(raw, o.width, o.height, o.undistort)
        d = calib_extra.to_dict()
        d["camera"] = self._undist.camera.to_dict()
        self.calibration = Calibration.from_dict(d)

    def _set_imu(self, stamps: np.ndarray, gyro: np.ndarray, accel: np.ndarray, what: str) -> None:
        idx = order_stamps(stamps, what, self._warn)
        self._imu_st = np.asarray(stamps, dtype=np.int64)[idx]
        self._imu_g = np.asarray(gyro, dtype=np.float64).reshape(-1, 3)[idx]
        self._imu_a = np.asarray(accel, dtype=np.float64).reshape(-1, 3)[idx]
        self._imu_cache = None

    def _imu_rate(self) -> Optional[float]:
        if len(self._imu_st) < 2:
            return None
        dt = np.median(np.diff(self._imu_st)) * 1e-9
        return float(1.0 / dt) if dt > 0 else None

    def _set_gt(self, stamps: np.ndarray, poses: np.ndarray, what: str, frame: str) -> None:
        idx = order_stamps(stamps, what, self._warn)
        if len(idx) == 0:
            self._warn(f"{what}: no ground-truth poses")
            return
        self.ground_truth = Trajectory(np.asarray(stamps)[idx], np.asarray(poses)[idx])
        self.gt_frame = frame

    def _frame(self, decode: Callable[[], np.ndarray], stamp: int, where: str) -> Optional[Frame]:
        """The frame ``decode()`` gives, delivered (:meth:`_deliver`); one that cannot be decoded
        or has the wrong size is skipped and counted in :attr:`bad_frames` (None), or, with
        ``on_bad_frame`` ``abort``, ends the reading (its :class:`InputError`)."""
        try:
            return self._deliver(decode(), stamp, where)
        except InputError as e:
            if self.options.on_bad_frame is BadFramePolicy.ABORT:
                raise
            self.bad_frames.append(str(e))
            self._warn(f"frame skipped (bad frame {len(self.bad_frames)}): {e}")
            return None

    def _deliver(self, img: np.ndarray, stamp: int, where: str) -> Frame:
        """Convert to uint8, check the size, undistort and resize."""
        assert self._undist is not None and self.raw_camera is not None
        img = self._converter(img)
        h, w = img.shape[:2]
        if (w, h) != (self.raw_camera.width, self.raw_camera.height):
            raise InputError(f"{where}: image is {w}x{h} but the calibration/first image is "
                             f"{self.raw_camera.width}x{self.raw_camera.height}")
        out = self._undist(img)
        return Frame(int(stamp), out, self.calibration.camera)

    # -- Source API --------------------------------------------------------------------------------
    def imu_samples(self) -> list[ImuSample]:
        if self._imu_cache is None:
            self._imu_cache = imu_from_arrays(self._imu_st, self._imu_g, self._imu_a)
        return list(self._imu_cache)

    def imu_arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """IMU as arrays: stamps int64 (N,), gyro (N, 3) rad/s, accel (N, 3) m/s^2 (body frame)."""
        return self._imu_st.copy(), self._imu_g.copy(), self._imu_a.copy()

    def gt_camera_trajectory(self) -> Optional[Trajectory]:
        if self.calibration is None and self.gt_frame != "camera":
            return None           # a recording without any calibration: no T_bc at all
        return super().gt_camera_trajectory()

    def info(self) -> dict:
        if self.calibration is not None and self.calibration.camera is not None:
            out = super().info()
        else:  # a camera-less recording (e.g. an IMU-only bag): calibration.camera is None
            st = self._imu_st
            gt = self.ground_truth
            rate = (float((len(st) - 1) / ((st[-1] - st[0]) * 1e-9))
                    if len(st) > 1 and st[-1] > st[0] else None)
            out = {
                "path": str(self.path), "kind": self.kind, "frames": 0, "frame_rate_hz": None,
                "first_stamp_ns": None, "last_stamp_ns": None, "duration_s": 0.0,
                "imu_samples": int(len(st)), "imu_rate_hz": rate, "resolution": None,
                "native_resolution": None, "calibration": calibration_dict(self.calibration),
                "ground_truth": None if gt is None or len(gt) == 0 else {
                    "poses": int(len(gt)), "frame": self.gt_frame,
                    "first_stamp_ns": int(gt.stamps_ns[0]), "last_stamp_ns": int(gt.stamps_ns[-1]),
                    "duration_s": float((gt.stamps_ns[-1] - gt.stamps_ns[0]) * 1e-9),
                    "path_length_m": gt.path_length()},
                "warnings": list(self.warnings),
            }
        st = self._imu_st
        out["imu_first_stamp_ns"] = int(st[0]) if len(st) else None
        out["imu_last_stamp_ns"] = int(st[-1]) if len(st) else None
        out["imu_duration_s"] = float((st[-1] - st[0]) * 1e-9) if len(st) > 1 else 0.0
        out.update(self._extra_info())
        return out

    def _extra_info(self) -> dict:
        return {}


class FileFramesSource(LoaderSource):
    """A loader whose frames are image files listed with their stamps."""

    def __init__(self, path: Path, kind: str, options: Optional[SourceOptions]) -> None:
        super().__init__(path, kind, options)
        self._stamps = np.zeros(0, dtype=np.int64)
        self._files: list[Path] = []

    def _set_frames(self, stamps: np.ndarray, files: list[Path], what: str) -> None:
        idx = order_stamps(stamps, what, self._warn)
        idx = idx[: self._limit(len(idx))]
        self._stamps = np.asarray(stamps, dtype=np.int64)[idx]
        self._files = [files[i] for i in idx]

    def frame_stamps(self) -> np.ndarray:
        return self._stamps.copy()

    def frames(self) -> Iterator[Frame]:
        for s, f in zip(self._stamps, self._files):
            fr = self._frame(lambda f=f: read_image_file(f), int(s), str(f))
            if fr is not None:
                yield fr

    def frame_files(self) -> list[Path]:
        """The image file of each delivered frame (same order as :meth:`frame_stamps`)."""
        return list(self._files)
