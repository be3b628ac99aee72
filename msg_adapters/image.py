"""``sensor_msgs/Image`` <-> numpy (camera images, 32FC1 depth / variance images).

All pixel work goes through the shared codec :mod:`vings_core.io.image_codec` (``decode_image`` /
``encode_image``), so bag files and live topics are decoded by the same vectorised code: colour
comes out RGB, ``step`` padding and ``is_bigendian`` are honoured, bad sizes and unknown encodings
raise :class:`InputError` naming the topic. Float images follow REP-118: ``32FC1`` (metres for
depth) and, on input, ``16UC1`` depth in millimetres.

``Image.data`` is filled with an ``array.array('B')`` (one memcpy): a list or a ``bytes`` object
would make rclpy check every byte in Python.
"""
from __future__ import annotations

import array
from typing import Any, Optional

import numpy as np
from sensor_msgs.msg import Image

from vings_core.errors import InputError
from vings_core.io.image_codec import FrameConverter, decode_image, encode_image
from vings_core.types import CameraModel, Frame

from .stamps import header_ns, make_header

#: encodings read as float images, with the factor to metres (REP-118 16UC1 depth is in mm)
FLOAT_ENCODINGS = {"32FC1": 1.0, "64FC1": 1.0, "16UC1": 1e-3}


def _byte_array(buf: Any) -> array.array:
    """``array.array('B')`` holding a copy of any C-contiguous bytes-like object (one memcpy)."""
    out = array.array("B")
    out.frombytes(buf if isinstance(buf, (bytes, bytearray)) else memoryview(buf).cast("B"))
    return out


def _as_numpy(img: Any) -> np.ndarray:
    if hasattr(img, "detach"):  # torch tensor
        img = img.detach().cpu().numpy()
    return np.asarray(img)


def _decode(msg: Image, where: str) -> np.ndarray:
    return decode_image(np.frombuffer(msg.data, dtype=np.uint8), str(msg.encoding),
                        int(msg.width), int(msg.height), int(msg.step), where,
                        is_bigendian=bool(msg.is_bigendian))


def array_to_msg(img: Any, stamp_ns: int, frame_id: str, where: str = "image") -> Image:
    """Any array the codec encodes (uint8 mono/RGB/RGBA, uint16, float32 (H, W), ...) -> Image."""
    a = _as_numpy(img)
    try:
        encoding, step, data = encode_image(np.ascontiguousarray(a))
    except InputError as e:
        raise InputError(f"{where}: {e}") from None
    msg = Image(header=make_header(stamp_ns, frame_id, where), height=int(a.shape[0]),
                width=int(a.shape[1]), encoding=encoding, is_bigendian=0, step=int(step))
    msg.data = _byte_array(data)
    return msg


# ------------------------------------------------------------------------------ camera images


def image_to_msg(img: Any, stamp_ns: int, frame_id: str, where: str = "image") -> Image:
    """uint8 ``(H, W, 3)`` RGB -> ``rgb8``, uint8 ``(H, W)`` -> ``mono8`` Image."""
    a = _as_numpy(img)
    if a.dtype != np.uint8 or not (a.ndim == 2 or (a.ndim == 3 and a.shape[2] == 3)):
        raise InputError(f"{where}: camera images must be uint8 (H, W) or (H, W, 3), got "
                         f"{a.dtype} {a.shape}")
    return array_to_msg(a, stamp_ns, frame_id, where)


def msg_to_image(msg: Image, where: str = "image") -> np.ndarray:
    """Image -> array as decoded by the codec: ``(H, W, 3)`` RGB or ``(H, W)``, in the encoding's
    dtype (uint8 for the 8-bit encodings)."""
    return _decode(msg, where)


def msg_to_frame(msg: Image, camera: CameraModel, where: str = "image",
                 converter: Optional[FrameConverter] = None) -> Frame:
    """Image + the camera model describing it -> :class:`Frame` (uint8; sizes must agree).

    Non-8-bit encodings (mono16, 32FC1, ...) need a ``converter`` (one
    :class:`~vings_core.io.image_codec.FrameConverter` per stream, so the mapping to 8 bit stays
    fixed over time); see :class:`FrameDecoder`.
    """
    img = _decode(msg, where)
    if img.dtype != np.uint8:
        if converter is None:
            raise InputError(f"{where}: encoding {msg.encoding!r} gives {img.dtype} pixels; camera "
                             f"frames need 8 bit (use a FrameDecoder / FrameConverter)")
        img = converter(img)
    if (img.shape[1], img.shape[0]) != (camera.width, camera.height):
        raise InputError(f"{where}: image is {img.shape[1]}x{img.shape[0]} but the camera model "
                         f"(camera_info / calibration) is {camera.width}x{camera.height}")
    return Frame(stamp_ns=header_ns(msg.header, f"{where}.header"), image=img, camera=camera)


class FrameDecoder:
    """Stateful Image -> Frame for one topic: keeps one FrameConverter so 16-bit / float cameras
    are mapped to 8 bit the same way for the whole stream. ``warnings`` collects its notes."""

    def __init__(self, where: str = "image") -> None:
        self.where = where
        self.warnings: list[str] = []
        self._conv = FrameConverter(where, warn=self.warnings.append)

    def __call__(self, msg: Image, camera: CameraModel) -> Frame:
        return msg_to_frame(msg, camera, self.where, self._conv)


def frame_to_msg(frame: Frame, frame_id: str, where: str = "image") -> Image:
    """A :class:`Frame` as an Image with the frame's exact stamp."""
    return image_to_msg(frame.image, frame.stamp_ns, frame_id, where)


# ------------------------------------------------------------------------------- float images


def float_image_to_msg(img: Any, stamp_ns: int, frame_id: str, where: str = "image") -> Image:
    """numeric ``(H, W)`` -> ``32FC1`` Image (``step = 4 W``). NaN / inf pass through."""
    a = _as_numpy(img)
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[..., 0]
    if a.ndim != 2 or not (np.issubdtype(a.dtype, np.number) or a.dtype == np.bool_):
        raise InputError(f"{where}: a 32FC1 image needs a numeric (H, W) array, got "
                         f"{a.dtype} {a.shape}")
    return array_to_msg(a.astype(np.float32, copy=False), stamp_ns, frame_id, where)


def msg_to_float_image(msg: Image, where: str = "image", allow_mm_depth: bool = False) -> np.ndarray:
    """``32FC1`` (or ``64FC1``) Image -> float32 ``(H, W)``.

    With ``allow_mm_depth`` a REP-118 ``16UC1`` depth image in millimetres is accepted and returned
    in metres (0 stays 0 = invalid).
    """
    enc = str(msg.encoding)
    if enc not in FLOAT_ENCODINGS or (enc == "16UC1" and not allow_mm_depth):
        ok = "32FC1, 64FC1 or 16UC1 (mm)" if allow_mm_depth else "32FC1 or 64FC1"
        raise InputError(f"{where}: encoding {enc!r} is not supported here; expected {ok}")
    out = _decode(msg, where).astype(np.float32)
    if enc == "16UC1":
        out /= np.float32(1000.0)    # exact mm -> m (x 1e-3 gave 1500 mm -> 1.5000001 m)
    return out


def msg_to_depth(msg: Image, where: str = "depth") -> np.ndarray:
    """Depth Image (``32FC1`` m or ``16UC1`` mm, REP-118) -> float32 metres, 0 where invalid.

    Non-finite and negative values become 0 (the vings_core convention for invalid depth).
    """
    d = msg_to_float_image(msg, where, allow_mm_depth=True)
    d[~np.isfinite(d) | (d < 0)] = 0.0
    return d


def stamp_of(msg: Image, where: str = "image") -> int:
    """The exact header stamp (ns) of an Image."""
    return header_ns(msg.header, f"{where}.header")


def rgb_float_to_uint8(img: Any) -> np.ndarray:
    """float RGB in [0, 1] -> uint8 (round to nearest, clipped). Exact inverse of ``u8 / 255``."""
    a = _as_numpy(img).astype(np.float32, copy=False)
    return np.clip(np.rint(a * 255.0), 0, 255).astype(np.uint8)


def uint8_to_rgb_float(img: np.ndarray) -> np.ndarray:
    """uint8 -> float32 in [0, 1]."""
    return np.asarray(img, dtype=np.float32) / np.float32(255.0)


__all__ = ["array_to_msg", "image_to_msg", "msg_to_image", "msg_to_frame", "FrameDecoder",
           "frame_to_msg", "float_image_to_msg", "msg_to_float_image", "msg_to_depth", "stamp_of",
           "rgb_float_to_uint8", "uint8_to_rgb_float", "FLOAT_ENCODINGS"]
