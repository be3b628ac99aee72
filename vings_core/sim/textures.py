"""Photo textures for the synthetic scenes: real photographs shipped with scikit-image.

Every texture is a square ``SIZE x SIZE`` RGB image with a full mip pyramid (box-filtered 2x2
averages, wrap-around), stored as one ``uint8`` array ``(ntex, PYR_TEXELS, 3)`` so a numba kernel can
sample it trilinearly. Textures tile (wrap) in both directions; a quad says how many metres one tile
covers, so the texel size is metric and texture stays visible at every distance.

Grey-level photographs (brick, grass, gravel, ...) are tinted so that scenes are colourful. "facade_*"
textures overlay a window grid on a photograph for the street scene's building blocks.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

SIZE = 512
LEVELS = int(np.log2(SIZE)) + 1          # 512, 256, ..., 1
LEVEL_OFFSETS = np.cumsum([0] + [(SIZE >> l) ** 2 for l in range(LEVELS)]).astype(np.int64)
PYR_TEXELS = int(LEVEL_OFFSETS[-1])

# name -> (skimage.data function, tint RGB (for grey photographs; colour ones use (1, 1, 1)))
_PHOTOS: dict[str, tuple[str, tuple[float, float, float]]] = {
    "astronaut": ("astronaut", (1.0, 1.0, 1.0)),
    "coffee": ("coffee", (1.0, 1.0, 1.0)),
    "chelsea": ("chelsea", (1.0, 1.0, 1.0)),
    "rocket": ("rocket", (1.0, 1.0, 1.0)),
    "hubble": ("hubble_deep_field", (1.0, 1.0, 1.0)),
    "ihc": ("immunohistochemistry", (1.0, 1.0, 1.0)),
    "retina": ("retina", (1.0, 1.0, 1.0)),
    "motorcycle": ("stereo_motorcycle", (1.0, 1.0, 1.0)),
    "brick": ("brick", (1.0, 0.62, 0.48)),
    "grass": ("grass", (0.55, 0.85, 0.45)),
    "gravel": ("gravel", (0.85, 0.8, 0.72)),
    "camera": ("camera", (0.95, 0.95, 1.0)),
    "moon": ("moon", (1.0, 0.95, 0.85)),
    "text": ("text", (0.95, 0.92, 0.8)),
    "page": ("page", (0.95, 0.95, 0.9)),
    "coins": ("coins", (0.9, 0.8, 0.55)),
    "clock": ("clock", (0.8, 0.9, 1.0)),
    "asphalt": ("gravel", (0.42, 0.42, 0.45)),
}
_FACADE_BASES = ("astronaut", "coffee", "chelsea", "rocket", "motorcycle", "brick", "camera", "ihc")

TEXTURE_NAMES: tuple[str, ...] = tuple(_PHOTOS) + tuple(f"facade_{b}" for b in _FACADE_BASES)


@dataclass
class TextureAtlas:
    """All textures with their mip pyramids.

    ``data``: uint8 ``(ntex, PYR_TEXELS, 3)``; level ``l`` of texture ``k`` is the ``(SIZE>>l)^2``
    row-major block starting at ``LEVEL_OFFSETS[l]``. ``names[k]`` names texture ``k``.
    """

    data: np.ndarray
    names: tuple[str, ...]

    def index(self, name: str) -> int:
        return self.names.index(name)

    def level(self, k: int, l: int) -> np.ndarray:
        """Mip level ``l`` of texture ``k`` as uint8 ``(s, s, 3)``."""
        s = SIZE >> l
        return self.data[k, LEVEL_OFFSETS[l]:LEVEL_OFFSETS[l] + s * s].reshape(s, s, 3)


def _load_photo(fn_name: str) -> np.ndarray:
    """The photograph as float32 RGB in [0, 1], centre-cropped to a square, resized to SIZE."""
    import cv2
    import skimage.data

    img = getattr(skimage.data, fn_name)()
    if isinstance(img, tuple):          # stereo_motorcycle -> (left, right, disparity)
        img = img[0]
    img = np.asarray(img)
    if img.dtype == bool:
        img = img.astype(np.float32)
    elif img.dtype == np.uint8:
        img = img.astype(np.float32) / 255.0
    else:
        img = img.astype(np.float32)
        img = (img - img.min()) / max(float(img.max() - img.min()), 1e-6)
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=2)
    img = img[..., :3]
    h, w = img.shape[:2]
    s = min(h, w)
    y0, x0 = (h - s) // 2, (w - s) // 2
    img = img[y0:y0 + s, x0:x0 + s]
    if s != SIZE:
        interp = cv2.INTER_AREA if s > SIZE else cv2.INTER_CUBIC
        img = cv2.resize(np.ascontiguousarray(img), (SIZE, SIZE), interpolation=interp)
    return np.clip(img, 0.0, 1.0).astype(np.float32)


def _facade(base: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A building facade tile: the photograph as wall, with a 3 x 3 grid of darker glass windows."""
    yy, xx = np.mgrid[0:SIZE, 0:SIZE].astype(np.float32) / SIZE
    cell = 1.0 / 3.0
    fx, fy = (xx % cell) / cell, (yy % cell) / cell
    win = (fx > 0.22) & (fx < 0.78) & (fy > 0.25) & (fy < 0.8)
    frame = (fx > 0.19) & (fx < 0.81) & (fy > 0.22) & (fy < 0.83) & ~win
    glass = np.array([0.25, 0.32, 0.42], np.float32) + 0.1 * rng.random(3, dtype=np.float32)
    wall = 0.35 + 0.65 * base
    out = wall.copy()
    out[win] = 0.55 * glass + 0.45 * base[win] * 0.6
    out[frame] = 0.85
    return np.clip(out, 0.0, 1.0)


def _pyramid(img: np.ndarray) -> np.ndarray:
    """uint8 (PYR_TEXELS, 3) mip pyramid of a float (SIZE, SIZE, 3) image in [0, 1]."""
    out = np.empty((PYR_TEXELS, 3), np.float32)
    cur = img.astype(np.float32)
    for l in range(LEVELS):
        s = SIZE >> l
        out[LEVEL_OFFSETS[l]:LEVEL_OFFSETS[l] + s * s] = cur.reshape(s * s, 3)
        if s > 1:
            cur = 0.25 * (cur[0::2, 0::2] + cur[1::2, 0::2] + cur[0::2, 1::2] + cur[1::2, 1::2])
    return np.clip(np.round(out * 255.0), 0, 255).astype(np.uint8)


@functools.lru_cache(maxsize=1)
def load_atlas() -> TextureAtlas:
    """Build (once per process) the atlas of every texture in :data:`TEXTURE_NAMES`."""
    photos: dict[str, np.ndarray] = {}
    for name, (fn, tint) in _PHOTOS.items():
        photos[name] = _load_photo(fn) * np.asarray(tint, np.float32)
    rng = np.random.default_rng(1234)
    imgs = [photos[n] for n in _PHOTOS]
    imgs += [_facade(photos[b], rng) for b in _FACADE_BASES]
    data = np.stack([_pyramid(im) for im in imgs])
    data.setflags(write=False)
    return TextureAtlas(data=data, names=TEXTURE_NAMES)
