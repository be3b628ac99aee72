"""``visualization_msgs/MarkerArray`` for RViz: keyframe frustums and the trajectory line.

Frustum geometry is computed for all keyframes at once in numpy: each frustum is 8 line segments
(4 from the optical centre to the image corners at ``scale`` metres depth, 4 around the image
rectangle) in one ``LINE_LIST`` marker. The trajectory is one ``LINE_STRIP``.
"""
from __future__ import annotations

from typing import Iterable, Sequence

import numpy as np
from builtin_interfaces.msg import Duration
from geometry_msgs.msg import Point
from std_msgs.msg import ColorRGBA
from visualization_msgs.msg import Marker, MarkerArray

from vings_core.errors import InputError
from vings_core.types import CameraModel

from .stamps import make_header
from .topics import WORLD_FRAME

Color = Sequence[float]  # (r, g, b, a) in [0, 1]


def frustum_segments(poses: np.ndarray, camera: CameraModel, scale: float = 0.2) -> np.ndarray:
    """Line-list endpoints ``(N * 16, 3)`` of the frustums of ``N`` poses ``T_wc`` (world frame).

    Corners are the image corners back-projected to depth ``scale`` (m).
    """
    T = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
    W, H = camera.width, camera.height
    u = np.array([0.0, W, W, 0.0]) - 0.5
    v = np.array([0.0, 0.0, H, H]) - 0.5
    corners = np.stack([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy,
                        np.ones(4)], axis=1) * scale                                # (4, 3)
    # 16 local endpoints: centre->corner i (8), corner i -> corner i+1 (8)
    centre = np.zeros((4, 3))
    local = np.empty((16, 3))
    local[0:8:2], local[1:8:2] = centre, corners
    local[8::2], local[9::2] = corners, np.roll(corners, -1, axis=0)
    world = local[None] @ T[:, :3, :3].transpose(0, 2, 1) + T[:, None, :3, 3]       # (N, 16, 3)
    return world.reshape(-1, 3)


def _points(xyz: np.ndarray) -> list:
    return [Point(x=p[0], y=p[1], z=p[2]) for p in np.asarray(xyz, np.float64).tolist()]


def _color(c: Color) -> ColorRGBA:
    if len(c) != 4:
        raise InputError(f"marker colour must be (r, g, b, a), got {c!r}")
    return ColorRGBA(r=float(c[0]), g=float(c[1]), b=float(c[2]), a=float(c[3]))


def _marker(kind: int, ns: str, marker_id: int, stamp_ns: int, frame_id: str, width: float,
            color: Color) -> Marker:
    m = Marker(header=make_header(stamp_ns, frame_id, f"markers/{ns}"), ns=ns, id=int(marker_id),
               type=kind, action=Marker.ADD, lifetime=Duration(sec=0, nanosec=0),
               frame_locked=False)
    m.pose.orientation.w = 1.0
    m.scale.x = float(width)
    m.color = _color(color)
    return m


def keyframe_frustums_marker(poses: np.ndarray, camera: CameraModel, stamp_ns: int,
                             frame_id: str = WORLD_FRAME, scale: float = 0.2,
                             width: float = 0.01, color: Color = (0.1, 0.6, 1.0, 1.0),
                             ns: str = "keyframes", marker_id: int = 0) -> Marker:
    """One LINE_LIST marker drawing every keyframe's frustum (poses ``T_wc`` in ``frame_id``)."""
    m = _marker(Marker.LINE_LIST, ns, marker_id, stamp_ns, frame_id, width, color)
    if len(np.asarray(poses).reshape(-1, 16)):
        m.points = _points(frustum_segments(poses, camera, scale))
    return m


def trajectory_marker(positions: np.ndarray, stamp_ns: int, frame_id: str = WORLD_FRAME,
                      width: float = 0.02, color: Color = (1.0, 0.5, 0.0, 1.0),
                      ns: str = "trajectory", marker_id: int = 0) -> Marker:
    """One LINE_STRIP through ``positions`` (N, 3) (m, in ``frame_id``)."""
    p = np.asarray(positions, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise InputError(f"trajectory marker: positions must be (N, 3), got {p.shape}")
    m = _marker(Marker.LINE_STRIP, ns, marker_id, stamp_ns, frame_id, width, color)
    m.points = _points(p)
    return m


def marker_array(markers: Iterable[Marker], clear: bool = True) -> MarkerArray:
    """MarkerArray; with ``clear`` a DELETEALL marker goes first so RViz drops stale markers."""
    out = []
    if clear:
        out.append(Marker(action=Marker.DELETEALL))
    out.extend(markers)
    return MarkerArray(markers=out)


def marker_points(marker: Marker) -> np.ndarray:
    """The marker's points as float64 (K, 3)."""
    return np.array([(p.x, p.y, p.z) for p in marker.points], dtype=np.float64).reshape(-1, 3)


__all__ = ["frustum_segments", "keyframe_frustums_marker", "trajectory_marker", "marker_array",
           "marker_points"]
