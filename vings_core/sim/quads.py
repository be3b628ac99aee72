"""Scene geometry as one-sided textured rectangles ("quads").

A quad is the rectangle ``origin + a*u + b*v`` for ``0 <= a <= extent[0]``, ``0 <= b <= extent[1]``
(metres), with orthonormal ``u``, ``v`` and ``normal = u x v``. It is visible only from the side its
normal points to (boxes have outward normals, the room's walls inward ones). Texture coordinates are
``((a + offset[0]) / tile[0], (b + offset[1]) / tile[1])`` in texture repeats, so ``tile`` is the
metric size of one copy of the photograph; the image's up direction is ``+v``.

``obj`` is ``-1`` for static geometry and the index of the moving object otherwise (masks are
``obj >= 0``). ``tint`` multiplies the texture (it also carries a fixed per-face shading so box faces
are told apart; shading does not depend on the view, so the scene is Lambertian).
"""
from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Sequence

import numpy as np


@dataclass
class QuadSet:
    origin: np.ndarray   # (M, 3) float64, world (m)
    u: np.ndarray        # (M, 3) float64 unit
    v: np.ndarray        # (M, 3) float64 unit
    normal: np.ndarray   # (M, 3) float64 unit, u x v
    extent: np.ndarray   # (M, 2) float64 (m)
    tex: np.ndarray      # (M,) int32 texture index in the atlas
    tile: np.ndarray     # (M, 2) float64 metres per texture repeat
    offset: np.ndarray   # (M, 2) float64 metres
    tint: np.ndarray     # (M, 3) float64 RGB multiplier
    obj: np.ndarray      # (M,) int32, -1 static, else moving-object index

    def __len__(self) -> int:
        return int(self.origin.shape[0])

    @staticmethod
    def empty() -> "QuadSet":
        z3 = np.zeros((0, 3))
        z2 = np.zeros((0, 2))
        return QuadSet(z3, z3.copy(), z3.copy(), z3.copy(), z2, np.zeros(0, np.int32), z2.copy(),
                       z2.copy(), z3.copy(), np.zeros(0, np.int32))

    @staticmethod
    def concat(parts: Sequence["QuadSet"]) -> "QuadSet":
        parts = [p for p in parts if len(p)]
        if not parts:
            return QuadSet.empty()
        if len(parts) == 1:
            return parts[0]
        return QuadSet(**{f.name: np.concatenate([getattr(p, f.name) for p in parts])
                          for f in fields(QuadSet)})

    def transformed(self, R: np.ndarray, t: np.ndarray) -> "QuadSet":
        """The quads moved by the rigid motion ``x -> R x + t``."""
        return QuadSet(origin=self.origin @ R.T + t, u=self.u @ R.T, v=self.v @ R.T,
                       normal=self.normal @ R.T, extent=self.extent, tex=self.tex, tile=self.tile,
                       offset=self.offset, tint=self.tint, obj=self.obj)

    def corners(self) -> np.ndarray:
        """(M, 4, 3) corners: origin, +u, +u+v, +v."""
        o = self.origin
        du = self.u * self.extent[:, :1]
        dv = self.v * self.extent[:, 1:]
        return np.stack([o, o + du, o + du + dv, o + dv], axis=1)


def make_quads(origin, u, v, extent, tex, tile, offset, tint, obj=-1) -> QuadSet:
    """QuadSet from per-quad lists; ``normal`` is computed as ``u x v``."""
    origin = np.asarray(origin, np.float64).reshape(-1, 3)
    u = np.asarray(u, np.float64).reshape(-1, 3)
    v = np.asarray(v, np.float64).reshape(-1, 3)
    u = u / np.linalg.norm(u, axis=1, keepdims=True)
    v = v / np.linalg.norm(v, axis=1, keepdims=True)
    m = origin.shape[0]
    if np.max(np.abs(np.einsum("ij,ij->i", u, v)), initial=0.0) > 1e-9:
        raise ValueError("quad axes u and v must be orthogonal")
    return QuadSet(origin=origin, u=u, v=v, normal=np.cross(u, v),
                   extent=np.broadcast_to(np.asarray(extent, np.float64), (m, 2)).copy(),
                   tex=np.broadcast_to(np.asarray(tex, np.int32), (m,)).copy(),
                   tile=np.broadcast_to(np.asarray(tile, np.float64), (m, 2)).copy(),
                   offset=np.broadcast_to(np.asarray(offset, np.float64), (m, 2)).copy(),
                   tint=np.broadcast_to(np.asarray(tint, np.float64), (m, 3)).copy(),
                   obj=np.broadcast_to(np.asarray(obj, np.int32), (m,)).copy())


# Per-face shading (view-independent) by face normal: a soft light from above and one side.
_LIGHT = np.array([0.35, 0.55, 0.76])


def face_shade(normal: np.ndarray) -> np.ndarray:
    """(M,) shading factor in [0.62, 1.0] from a fixed light direction (Lambertian, no view term)."""
    return 0.62 + 0.38 * np.clip((np.asarray(normal) @ _LIGHT + 1.0) / 2.0, 0.0, 1.0)


def box_quads(center, size, yaw: float, tex: Sequence[int] | int, tile: float,
              rng: np.random.Generator, tint=(1.0, 1.0, 1.0), obj: int = -1,
              bottom: bool = False, inward: bool = False) -> QuadSet:
    """Quads of a box of ``size`` (sx, sy, sz) m centred at ``center``, rotated by ``yaw`` about z.

    Faces in order +x, -x, +y, -y, +z (top), [-z (bottom)]; side faces have ``v`` up so photographs
    stand upright. ``tex`` is one texture index or one per face. ``inward`` flips every face to look
    inside (a room). Texture offsets are drawn from ``rng`` so faces do not repeat in phase.
    """
    c = np.asarray(center, np.float64)
    h = 0.5 * np.asarray(size, np.float64)
    ez = np.array([0.0, 0.0, 1.0])
    normals = [np.array([1.0, 0, 0]), np.array([-1.0, 0, 0]), np.array([0, 1.0, 0]),
               np.array([0, -1.0, 0]), ez.copy()]
    if bottom:
        normals.append(-ez)
    O, U, V, E = [], [], [], []
    for n in normals:
        if abs(n[2]) > 0.5:
            vax = np.array([1.0, 0, 0])
        else:
            vax = ez
        nn = -n if inward else n
        uax = np.cross(vax, nn)
        hn = float(np.abs(n) @ h)
        hu = float(np.abs(uax) @ h)
        hv = float(np.abs(vax) @ h)
        O.append(n * hn - uax * hu - vax * hv)
        U.append(uax)
        V.append(vax)
        E.append((2 * hu, 2 * hv))
    nf = len(normals)
    texs = np.broadcast_to(np.asarray(tex, np.int32), (nf,))
    cy, sy = np.cos(yaw), np.sin(yaw)
    R = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
    q = make_quads(O, U, V, E, texs, (tile, tile), rng.uniform(0, tile, size=(nf, 2)), tint, obj)
    q = q.transformed(R, c)
    q.tint = q.tint * face_shade(q.normal)[:, None]
    return q
