"""A dynamic mask on disk and on the wire: mono8, 255 = dynamic, 0 = static, the working resolution
(``masks/kf_<stamp>.png`` of the output contract; ``/vings/keyframe/dynamic_mask``)."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from ..errors import InputError


def mask_to_mono8(mask: np.ndarray) -> np.ndarray:
    """``(H, W)`` bool -> uint8 (255 where True)."""
    return np.where(np.asarray(mask, dtype=bool), 255, 0).astype(np.uint8)


def mono8_to_mask(img: np.ndarray, what: str = "mask") -> np.ndarray:
    """uint8 ``(H, W)`` -> bool (True where > 127). Other shapes or types: ValueError naming ``what``."""
    a = np.asarray(img)
    if a.ndim != 2 or a.dtype != np.uint8:
        raise ValueError(f"{what}: expected a mono8 (H, W) uint8 image, got {a.dtype} {a.shape}")
    return a > 127


def encode_mask_png(mask: np.ndarray) -> bytes:
    """PNG bytes of a mask (mono8)."""
    ok, buf = cv2.imencode(".png", mask_to_mono8(mask))
    if not ok:
        raise ValueError("PNG encoding of a mask failed")
    return buf.tobytes()


def read_mask_png(path: str | Path) -> np.ndarray:
    """A mask PNG (``masks/kf_<stamp>.png``) as ``(H, W)`` bool; InputError naming the file when it
    is missing or not a mono8 image."""
    p = Path(path)
    img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise InputError(f"{p}: missing or not a PNG image")
    try:
        return mono8_to_mask(img, str(p))
    except ValueError as e:
        raise InputError(str(e)) from None
