"""A tiny ray-cast test scene for the front end's tests and examples (not the simulator).

A textured box room (half extents ``room``) with one textured cube inside; exact depth. The
simulator proper is :mod:`vings_core.sim`; this exists so the front-end tests need nothing else.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..types import CameraModel


@dataclass
class BoxScene:
    room: np.ndarray          #: (3,) half extents of the room (m), centred at the origin
    cube_center: np.ndarray   #: (3,)
    cube_half: float
    textures: np.ndarray      #: (12, S, S) float32 grey textures (6 room walls, 6 cube faces)
    tex_scale: float          #: texture pixels per metre


def make_box_scene(seed: int = 0, room=(4.0, 2.0, 4.0), cube_center=(0.6, 0.5, 2.0),
                   cube_half: float = 0.5, size: int = 512, tex_scale: float = 64.0) -> BoxScene:
    """Random multi-octave noise textures (contrast at several scales, no repetition)."""
    rng = np.random.default_rng(seed)
    tex = np.zeros((12, size, size), np.float32)
    for k in range(12):
        acc = np.zeros((size, size), np.float32)
        for octave, amp in ((8, 1.0), (32, 0.6), (128, 0.35)):
            n = rng.random((octave, octave)).astype(np.float32)
            acc += amp * cv2.resize(n, (size, size), interpolation=cv2.INTER_CUBIC)
        acc = (acc - acc.min()) / (acc.max() - acc.min() + 1e-9)
        tex[k] = 30 + 200 * acc
    return BoxScene(np.asarray(room, float), np.asarray(cube_center, float), float(cube_half), tex,
                    tex_scale)


def _sample(tex: np.ndarray, u: np.ndarray, v: np.ndarray, scale: float) -> np.ndarray:
    S = tex.shape[0]
    u = np.nan_to_num(u, posinf=0.0, neginf=0.0)
    v = np.nan_to_num(v, posinf=0.0, neginf=0.0)
    x = np.mod(u * scale, S - 1).astype(np.float32)
    y = np.mod(v * scale, S - 1).astype(np.float32)
    return cv2.remap(tex, x, y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)


def render_box(scene: BoxScene, cam: CameraModel, T_wc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(grey uint8 (H, W), z-depth float32 (H, W) m)`` of ``scene`` seen from ``T_wc``."""
    H, W = cam.height, cam.width
    ys, xs = np.mgrid[0:H, 0:W].astype(np.float64)
    rays_c = np.stack([(xs - cam.cx) / cam.fx, (ys - cam.cy) / cam.fy, np.ones_like(xs)], -1)
    R, o = T_wc[:3, :3], T_wc[:3, 3]
    dirs = rays_c @ R.T                                    # z-depth = t for these unnormalised rays
    best_t = np.full((H, W), np.inf)
    face = np.full((H, W), -1)
    with np.errstate(divide="ignore", invalid="ignore"):
        for ax in range(3):                                # room walls (inside)
            for sgn in (-1, 1):
                t = (sgn * scene.room[ax] - o[ax]) / dirs[..., ax]
                ok = (t > 1e-6) & (t < best_t)
                best_t = np.where(ok, t, best_t)
                face = np.where(ok, 2 * ax + (sgn > 0), face)
        c, hf = scene.cube_center, scene.cube_half         # cube (outside): slab test
        t0 = (c - hf - o) / dirs
        t1 = (c + hf - o) / dirs
        tmin = np.minimum(t0, t1)
        tmax = np.maximum(t0, t1)
        tn = tmin.max(-1)
        tf = tmax.min(-1)
        hit = (tn <= tf) & (tn > 1e-6) & (tn < best_t)
        ax_hit = tmin.argmax(-1)
        best_t = np.where(hit, tn, best_t)
        sgn_hit = np.take_along_axis(dirs, ax_hit[..., None], -1)[..., 0] < 0
        face = np.where(hit, 6 + 2 * ax_hit + sgn_hit, face)
    p = o + dirs * best_t[..., None]
    img = np.zeros((H, W), np.float32)
    for f in range(12):
        m = face == f
        if not m.any():
            continue
        ax = (f % 6) // 2
        a, b = [k for k in range(3) if k != ax]
        img[m] = _sample(scene.textures[f], p[..., a], p[..., b], scene.tex_scale)[m]
    return np.clip(img + 0.5, 0, 255).astype(np.uint8), best_t.astype(np.float32)


def orbit_trajectory(n: int, radius: float = 0.6, height: float = 0.0, look_at=(0.0, 0.3, 2.5),
                     arc: float = 1.2) -> np.ndarray:
    """``(n, 4, 4)`` camera poses ``T_wc`` moving on an arc, looking at ``look_at`` (m)."""
    poses = np.zeros((n, 4, 4))
    target = np.asarray(look_at, float)
    for k, a in enumerate(np.linspace(-arc / 2, arc / 2, n)):
        pos = np.array([radius * np.sin(a), height + 0.1 * np.sin(2 * a), -1.5 + radius * (1 - np.cos(a))])
        zc = target - pos
        zc /= np.linalg.norm(zc)
        xc = np.cross([0.0, 1.0, 0.0], zc)
        xc /= np.linalg.norm(xc)
        yc = np.cross(zc, xc)
        poses[k, :3, :3] = np.stack([xc, yc, zc], 1)
        poses[k, :3, 3] = pos
        poses[k, 3, 3] = 1
    return poses
