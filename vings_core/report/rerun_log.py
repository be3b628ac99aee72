"""Live 3D log of a run for the rerun viewer (``vings run --rerun FILE.rrd``; docs/report.md).

The rerun SDK is an optional extra (``pip install .[viz]``), imported only when a log is asked for;
without it :class:`RerunLog` raises a :class:`~vings_core.errors.ConfigError` saying how to install
it. Entities (world frame ``world`` in the run's units; the camera in the optical convention,
x right, y down, z forward):

=====================================  ======================================  ===============
entity                                 archetype                               logged
=====================================  ======================================  ===============
``world/camera``                       ``Transform3D`` (``T_wc``)              every posed frame
``world/camera/image``                 ``Pinhole``                             once (static)
``world/camera/image/rgb``             ``EncodedImage`` (JPEG)                 every frame
``world/keyframes/render``             ``EncodedImage`` (JPEG)                 every keyframe
``world/keyframes/depth``              ``DepthImage`` (m)                      every keyframe
``world/trajectory``                   ``LineStrips3D`` (keyframe positions)   every keyframe
``world/map``                          ``Points3D`` (Gaussian centres, colour) every ``map_every`` keyframes
=====================================  ======================================  ===============

Timelines: ``stamp`` (the image stamp, a timestamp) and ``frame`` (the frame's index). Safe from
two threads (tracking and mapper): rerun's time is per thread and its stream is thread-safe.
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import numpy as np

from ..errors import ConfigError, InputError
from ..types import CameraModel

JPEG_QUALITY = 80


def _rerun():
    try:
        import rerun as rr
    except ImportError:
        raise ConfigError("--rerun needs the rerun SDK, an optional extra: pip install '.[viz]' "
                          "(or pip install rerun-sdk)") from None
    return rr


class RerunLog:
    """Writes one ``.rrd`` file (module doc). ``camera``: the pinhole (or later, :meth:`set_camera`);
    ``map_every``: keyframes between map point clouds (:meth:`want_points`); ``map_points``: at
    most this many Gaussian centres per cloud. ``recording_id``: the same id in several files makes
    the viewer merge them into one recording."""

    def __init__(self, path: str | Path, camera: Optional[CameraModel] = None, map_every: int = 5,
                 map_points: int = 50_000, recording_id: Optional[str] = None) -> None:
        rr = _rerun()
        self.rr = rr
        self.path = Path(path)
        if self.path.suffix != ".rrd":
            raise InputError(f"--rerun {self.path}: the file must end in .rrd")
        if self.path.is_dir():
            raise InputError(f"--rerun {self.path}: is a folder")
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise InputError(f"--rerun {self.path}: cannot create its folder ({e.strerror or e})") from None
        self.rec = rr.RecordingStream("vings", recording_id=recording_id)
        self.rec.save(str(self.path))
        self.map_every, self.map_points = int(map_every), int(map_points)
        self.keyframes: list[np.ndarray] = []
        self.camera: Optional[CameraModel] = None
        self.rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        if camera is not None:
            self.set_camera(camera)

    def set_camera(self, camera: CameraModel) -> None:
        """Log the pinhole (static) once."""
        if self.camera is not None:
            return
        self.camera = camera
        K = np.array([[camera.fx, 0, camera.cx], [0, camera.fy, camera.cy], [0, 0, 1]], np.float64)
        self.rec.log("world/camera/image", self.rr.Pinhole(image_from_camera=K, width=camera.width,
                                                           height=camera.height,
                                                           camera_xyz=self.rr.ViewCoordinates.RDF), static=True)

    def _time(self, stamp_ns: int, index: Optional[int] = None) -> None:
        self.rec.set_time("stamp", timestamp=np.datetime64(int(stamp_ns), "ns"))
        if index is not None:
            self.rec.set_time("frame", sequence=int(index))

    def _jpeg(self, rgb: np.ndarray):
        import cv2
        img = np.asarray(rgb)
        if img.dtype != np.uint8:
            img = (np.clip(img, 0, 1) * 255).round().astype(np.uint8)
        if img.ndim == 2:
            img = np.repeat(img[..., None], 3, axis=2)
        ok, buf = cv2.imencode(".jpg", np.ascontiguousarray(img[..., ::-1]), [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
        return self.rr.EncodedImage(contents=buf.tobytes(), media_type="image/jpeg")

    def pose(self, stamp_ns: int, T_wc: np.ndarray, index: Optional[int] = None) -> None:
        """The camera's pose ``T_wc`` at ``stamp_ns``."""
        self._time(stamp_ns, index)
        T = np.asarray(T_wc, np.float64)
        self.rec.log("world/camera", self.rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]))

    def image(self, stamp_ns: int, rgb: np.ndarray, index: Optional[int] = None) -> None:
        """The camera's image (uint8 RGB or grey) at ``stamp_ns``."""
        self._time(stamp_ns, index)
        self.rec.log("world/camera/image/rgb", self._jpeg(rgb))

    def frame(self, index: int, stamp_ns: int, T_wc: Optional[np.ndarray], rgb: np.ndarray) -> None:
        """A frame: its pose (when posed) and its image."""
        if T_wc is not None:
            self.pose(stamp_ns, T_wc, index)
        self.image(stamp_ns, rgb, index)

    def render(self, stamp_ns: int, color: np.ndarray, depth: Optional[np.ndarray]) -> None:
        """The map rendered at a keyframe's pose: colour (float [0, 1] or uint8) and depth (m)."""
        self._time(stamp_ns)
        self.rec.log("world/keyframes/render", self._jpeg(color))
        if depth is not None:
            self.rec.log("world/keyframes/depth", self.rr.DepthImage(np.asarray(depth, np.float32), meter=1.0))

    def keyframe_path(self, stamp_ns: int, positions: np.ndarray) -> None:
        """The keyframe path ``(K, 3)`` as of ``stamp_ns``."""
        self._time(stamp_ns)
        self.rec.log("world/trajectory", self.rr.LineStrips3D([np.asarray(positions, np.float64)],
                                                               colors=[[255, 140, 0]]))

    def points(self, stamp_ns: int, xyz: np.ndarray, rgb: np.ndarray) -> None:
        """Map points ``(M, 3)`` with colours (float [0, 1] or uint8)."""
        if not len(xyz):
            return
        self._time(stamp_ns)
        c = np.asarray(rgb)
        c = c / 255.0 if c.dtype == np.uint8 else np.clip(c, 0, 1)
        self.rec.log("world/map", self.rr.Points3D(np.asarray(xyz, np.float32), colors=c, radii=0.005))

    def keyframe(self, stamp_ns: int, T_wc: np.ndarray, render: Optional[dict],
                 points: Optional[tuple[np.ndarray, np.ndarray]] = None) -> None:
        """A mapped keyframe (``vings run``): the render at its pose (``color``, ``depth``), the
        keyframe path so far, and the map's points when given (see :meth:`want_points`)."""
        self.keyframes.append(np.asarray(T_wc, np.float64)[:3, 3].copy())
        if render is not None:
            self.render(stamp_ns, render["color"], render["depth"])
        self.keyframe_path(stamp_ns, np.stack(self.keyframes))
        if points is not None:
            self.points(stamp_ns, *points)

    def want_points(self) -> bool:
        """Whether the next keyframe logs the map's points."""
        return len(self.keyframes) % max(self.map_every, 1) == 0

    def close(self) -> None:
        """Flush and close the file."""
        self.rec.flush()
        try:
            self.rec.disconnect()
        except AttributeError:
            pass
