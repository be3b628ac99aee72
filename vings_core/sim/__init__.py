"""Synthetic photo-textured scenes with exact ground truth (the `vings sim` generator).

Public API:

* :func:`make_scene` (``'room'`` or ``'street'``) -> :class:`Scene`
* :func:`render_view` (exact ray-caster: RGB, z-depth, dynamic mask)
* :func:`generate` (EuRoC/ASL folder + ROS 2 MCAP)
* :func:`simulate_imu` (IMU at 200 Hz from the trajectory's derivatives)

See docs/sim.md. Nothing is compiled at import time (numba kernels compile, and are cached, on first
use).
"""
from __future__ import annotations

from typing import Optional

import numpy as np

from ..types import CameraModel
from .raycast import RenderOutput, raycast, raycast_reference
from .scene import SCENES, T_BC_DEFAULT, MovingBox, Scene, default_camera, make_scene


def render_view(scene: Scene, camera: CameraModel, T_wc: np.ndarray, t: float = 0.0,
                antialias: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ray-cast ``scene`` from camera pose ``T_wc`` (4x4 camera-to-world, optical frame) at time ``t``
    (s; places the moving objects).

    Returns ``(rgb uint8 (H, W, 3), depth float32 (H, W) z-depth in m (0 where no surface: sky),
    mask bool (H, W) True where a moving object is seen)``. Distortion in ``camera`` is ignored.
    """
    out = raycast(scene.quads_at(t), scene.atlas, camera, T_wc, sky=scene.sky, antialias=antialias)
    return out.rgb, out.depth, out.mask


def render_view_full(scene: Scene, camera: CameraModel, T_wc: np.ndarray, t: float = 0.0,
                     antialias: bool = True) -> RenderOutput:
    """Like :func:`render_view` but returns the full :class:`RenderOutput` (hit quad ids, hit
    coordinates)."""
    return raycast(scene.quads_at(t), scene.atlas, camera, T_wc, sky=scene.sky, antialias=antialias)


def __getattr__(name: str):
    # lazy: generate/imu pull in file writers, keep `import vings_core.sim` light
    if name in ("generate", "build_scene", "load_summary"):
        from . import sequence as _s
        return getattr(_s, name)
    if name in ("simulate_imu", "ImuNoise"):
        from . import imu as _i
        return getattr(_i, name)
    raise AttributeError(f"module 'vings_core.sim' has no attribute {name!r}")


__all__ = ["SCENES", "T_BC_DEFAULT", "MovingBox", "RenderOutput", "Scene", "build_scene",
           "default_camera", "generate", "load_summary", "make_scene", "raycast", "raycast_reference", "render_view",
           "render_view_full", "simulate_imu", "ImuNoise"]
