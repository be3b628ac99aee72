"""Raw image buffers <-> numpy arrays, shared by the bag loader, the MCAP writer and msg_adapters.

No ROS imports: a ``sensor_msgs/Image`` is described by its ``data`` bytes, ``encoding``, ``width``,
``height``, ``step`` (bytes per row, >= width * bytes per pixel) and ``is_bigendian``.

Decoded arrays follow the :mod:`vings_core.types` conventions: colour is ``(H, W, 3)`` **RGB**
(``bgr8``/``bgra8``/``rgba8``/bayer/yuv are converted), single-channel is ``(H, W)`` in the
encoding's dtype (``uint8``, ``uint16``, ``float32`` ...). Bad buffers raise
:class:`~vings_core.errors.InputError` naming ``where`` (file, topic, stamp).
"""
from __future__ import annotations

from typing import Union

import numpy as np

from ..errors import InputError

# encoding -> (channels, numpy dtype, post-processing)
_ENCODINGS: dict[str, tuple[int, str, str]] = {
    "mono8": (1, "u1", ""), "8UC1": (1, "u1", ""), "8SC1": (1, "i1", ""),
    "mono16": (1, "u2", ""), "16UC1": (1, "u2", ""), "16SC1": (1, "i2", ""),
    "32SC1": (1, "i4", ""), "32FC1": (1, "f4", ""), "64FC1": (1, "f8", ""),
    "rgb8": (3, "u1", ""), "bgr8": (3, "u1", "bgr"), "8UC3": (3, "u1", "bgr"),
    "rgba8": (4, "u1", "drop_alpha"), "bgra8": (4, "u1", "bgra"), "8UC4": (4, "u1", "bgra"),
    "rgb16": (3, "u2", ""), "bgr16": (3, "u2", "bgr"),
    "rgba16": (4, "u2", "drop_alpha"), "bgra16": (4, "u2", "bgra"),
    "bayer_rggb8": (1, "u1", "bayer"), "bayer_bggr8": (1, "u1", "bayer"),
    "bayer_gbrg8": (1, "u1", "bayer"), "bayer_grbg8": (1, "u1", "bayer"),
    "yuv422": (2, "u1", "uyvy"), "uyvy": (2, "u1", "uyvy"),
    "yuv422_yuy2": (2, "u1", "yuyv"), "yuyv": (2, "u1", "yuyv"),
}

SUPPORTED_ENCODINGS = tuple(_ENCODINGS)


_BAYER_8 = ("bayer_rggb8", "bayer_bggr8", "bayer_gbrg8", "bayer_grbg8")


def _bayer_code(encoding: str) -> int:
    import cv2
    # ROS names the top-left 2x2 pattern; OpenCV names the pattern starting at pixel (1, 1).
    return {"bayer_rggb8": cv2.COLOR_BayerBG2RGB, "bayer_bggr8": cv2.COLOR_BayerRG2RGB,
            "bayer_gbrg8": cv2.COLOR_BayerGR2RGB, "bayer_grbg8": cv2.COLOR_BayerGB2RGB}[encoding]


def decode_image(data: Union[bytes, bytearray, memoryview, np.ndarray], encoding: str, width: int,
                 height: int, step: int, where: str = "image", is_bigendian: bool = False) -> np.ndarray:
    """Decode a raw ``sensor_msgs/Image`` buffer into an array (RGB for colour, see module doc).

    Raises :class:`InputError` naming ``where`` for an unknown encoding, a wrong byte count or a
    ``step`` shorter than a row.
    """
    if encoding not in _ENCODINGS:
        raise InputError(f"{where}: unknown image encoding {encoding!r} "
                         f"(supported: {', '.join(SUPPORTED_ENCODINGS)})")
    ch, dt, post = _ENCODINGS[encoding]
    width, height, step = int(width), int(height), int(step)
    if width <= 0 or height <= 0:
        raise InputError(f"{where}: image size {width}x{height} is empty")
    buf = np.frombuffer(data, dtype=np.uint8) if not isinstance(data, np.ndarray) \
        else np.ascontiguousarray(data).reshape(-1).view(np.uint8)
    itemsize = np.dtype(dt).itemsize
    row = width * ch * itemsize
    if step == 0:
        step = row
    if step < row:
        raise InputError(f"{where}: step {step} bytes is shorter than one row of {width} px "
                         f"{encoding} ({row} bytes)")
    if buf.size < step * (height - 1) + row:
        raise InputError(f"{where}: image data has {buf.size} bytes, expected {step * height} "
                         f"(step {step} x height {height}, {encoding} {width}x{height})")
    if buf.size > step * height:
        raise InputError(f"{where}: image data has {buf.size} bytes, more than step {step} x "
                         f"height {height} = {step * height} ({encoding} {width}x{height})")
    if buf.size < step * height:  # last row unpadded: pad so every row has ``step`` bytes
        buf = np.concatenate([buf, np.zeros(step * height - buf.size, np.uint8)])
    rows = buf.reshape(height, step)[:, :row]
    dtype = np.dtype(dt).newbyteorder(">" if is_bigendian else "<")
    arr = np.ascontiguousarray(rows).view(dtype).reshape(height, width, ch)
    arr = arr.astype(np.dtype(dt).newbyteorder("="), copy=False)
    if post == "bgr":
        arr = arr[..., ::-1]
    elif post == "bgra":
        arr = arr[..., 2::-1]
    elif post == "drop_alpha":
        arr = arr[..., :3]
    elif post in ("bayer", "uyvy", "yuyv"):
        import cv2
        if width % 2 or (post == "bayer" and height % 2):
            raise InputError(f"{where}: a {encoding} image needs an even "
                             f"{'width and height' if post == 'bayer' else 'width'}, got "
                             f"{width}x{height}")
        try:
            if post == "bayer":
                arr = cv2.cvtColor(arr[..., 0], _bayer_code(encoding))
            else:
                code = cv2.COLOR_YUV2RGB_UYVY if post == "uyvy" else cv2.COLOR_YUV2RGB_YUY2
                arr = cv2.cvtColor(arr, code)
        except cv2.error as e:
            raise InputError(f"{where}: cannot convert the {encoding} {width}x{height} image to RGB "
                             f"({str(e).strip().splitlines()[-1]})") from None
    if arr.ndim == 3 and arr.shape[2] == 1:
        arr = arr[..., 0]
    return np.ascontiguousarray(arr)


def encode_image(img: np.ndarray) -> tuple[str, int, bytes]:
    """Array -> ``(encoding, step, data)`` for a ``sensor_msgs/Image`` (little-endian, no padding).

    ``uint8 (H, W)`` -> ``mono8``; ``uint8 (H, W, 3)`` RGB -> ``rgb8``; ``uint8 (H, W, 4)`` ->
    ``rgba8``; ``uint16 (H, W)`` -> ``16UC1``; ``uint16 (H, W, 3)`` -> ``rgb16``; ``float32 (H, W)``
    -> ``32FC1``.
    """
    img = np.asarray(img)
    table = {("u1", 1): "mono8", ("u1", 3): "rgb8", ("u1", 4): "rgba8", ("u2", 1): "16UC1",
             ("u2", 3): "rgb16", ("f4", 1): "32FC1", ("f8", 1): "64FC1", ("i2", 1): "16SC1"}
    ch = 1 if img.ndim == 2 else (img.shape[2] if img.ndim == 3 else -1)
    key = (img.dtype.kind + str(img.dtype.itemsize), ch)
    if key not in table:
        raise InputError(f"cannot encode an image of dtype {img.dtype} and shape {img.shape} "
                         f"(expected uint8 mono/RGB/RGBA, uint16 mono/RGB or float32 mono)")
    enc = table[key]
    le = img.astype(img.dtype.newbyteorder("<"), copy=False)
    data = np.ascontiguousarray(le).tobytes()
    return enc, int(img.shape[1] * ch * img.dtype.itemsize), data


def decode_compressed(data: Union[bytes, bytearray, memoryview, np.ndarray], fmt: str,
                      where: str = "image") -> np.ndarray:
    """Decode a ``sensor_msgs/CompressedImage`` (JPEG/PNG/...) with OpenCV; colour comes back RGB.

    ``fmt`` is the message's ``format`` field (``jpeg``, ``png``, ``rgb8; jpeg compressed bgr8``,
    ...). ``compressedDepth`` streams are not supported. A buffer OpenCV cannot decode raises
    :class:`InputError` naming ``where``.
    """
    import cv2
    if "compresseddepth" in fmt.lower().replace(" ", ""):
        raise InputError(f"{where}: compressedDepth images are not supported (format {fmt!r})")
    buf = np.frombuffer(data, dtype=np.uint8) if not isinstance(data, np.ndarray) \
        else np.ascontiguousarray(data).reshape(-1).view(np.uint8)
    if buf.size == 0:
        raise InputError(f"{where}: compressed image is empty (format {fmt!r})")
    img = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)
    if img is None:
        raise InputError(f"{where}: corrupt compressed image: OpenCV could not decode "
                         f"{buf.size} bytes (format {fmt!r})")
    # compressed_image_transport compresses a Bayer image as the raw mosaic ("bayer_rggb8; png
    # compressed "): demosaic it, as decode_image does for a raw Image
    source_enc = fmt.split(";")[0].strip().lower() if ";" in fmt else ""
    pattern = source_enc[:10] + "8"           # bayer_rggb8 / bayer_rggb16: one OpenCV code
    if pattern in _BAYER_8:
        if img.ndim != 2 or img.shape[0] % 2 or img.shape[1] % 2:
            raise InputError(f"{where}: a {source_enc} compressed image must decode to one channel of "
                             f"even width and height, got shape {img.shape} (format {fmt!r})")
        return cv2.cvtColor(img, _bayer_code(pattern))
    return bgr_to_rgb(img)


def bgr_to_rgb(img: np.ndarray) -> np.ndarray:
    """OpenCV channel order (BGR/BGRA) -> RGB; single-channel arrays pass through as ``(H, W)``."""
    if img.ndim == 3 and img.shape[2] == 1:
        return img[..., 0]
    if img.ndim == 3 and img.shape[2] == 3:
        return np.ascontiguousarray(img[..., ::-1])
    if img.ndim == 3 and img.shape[2] == 4:
        return np.ascontiguousarray(img[..., 2::-1])
    return img


def read_image_file(path) -> np.ndarray:
    """Read an image file (PNG/JPEG/...) keeping its bit depth; colour as RGB.

    Raises :class:`InputError` naming the file when it is missing or cannot be decoded.
    """
    import os

    import cv2
    p = os.fspath(path)
    if not os.path.isfile(p):
        raise InputError(f"{p}: image file not found")
    img = cv2.imread(p, cv2.IMREAD_UNCHANGED)
    if img is None:
        raise InputError(f"{p}: corrupt or unreadable image file (OpenCV could not decode it)")
    return bgr_to_rgb(img)


class FrameConverter:
    """Turns decoded images of any supported dtype into ``uint8`` frames, with ONE fixed mapping per
    stream (chosen from the first image) so that brightness stays consistent over time.

    ``uint8``: unchanged. Integer 16-bit: shifted right by ``bits - 8`` where ``bits`` is the
    sensor depth (8, 10, 12, 14 or 16) that holds the first non-black image's maximum (so 10/12-bit
    cameras are not dark, and a dim first image still leaves headroom up to its depth). Float:
    values in [0, 1] are scaled by 255, otherwise by ``255 / max`` of the first non-black image.
    Colour 16-bit likewise. All-black images (a camera starting up) do not fix the mapping. Notes,
    and a warning the first time a later image saturates the chosen mapping, go to ``warn``.
    """

    def __init__(self, where: str, warn=None) -> None:
        self.where = where
        self.warn = warn
        self._shift: int | None = None
        self._scale: float | None = None
        self._clip_warned = False

    def __call__(self, img: np.ndarray) -> np.ndarray:
        if img.dtype == np.uint8:
            return img
        if img.dtype.kind in "ui" and img.dtype.itemsize > 1:
            mx = int(img.max()) if img.size else 0
            if self._shift is None:
                if mx <= 0:
                    return np.zeros(img.shape, np.uint8)    # black: decide on a later image
                # rounded up to a sensor depth (10/12/14/16 bit): a dim first image (exposure still
                # settling) must not fix a shift that saturates every later, brighter one
                need = int(mx).bit_length()
                bits = next(b for b in (8, 10, 12, 14, 16, 32, 64) if b >= need)
                self._shift = bits - 8
                self._note(f"{self.where}: {img.dtype} images converted to 8 bit by a right shift of "
                           f"{self._shift} bits (chosen from the first non-black image, max {mx})")
            elif mx >> self._shift > 255:
                self._warn_clip(f"max {mx} > {(256 << self._shift) - 1}")
            out = np.clip(img.astype(np.int64) >> self._shift, 0, 255)
            return out.astype(np.uint8)
        if img.dtype.kind == "f":
            finite = img[np.isfinite(img)]
            mx = float(finite.max()) if finite.size else 0.0
            if self._scale is None:
                if mx <= 0.0:
                    return np.zeros(img.shape, np.uint8)    # black: decide on a later image
                self._scale = 255.0 if mx <= 1.0 else 255.0 / mx
                self._note(f"{self.where}: float images converted to 8 bit by a scale of "
                           f"{self._scale:.6g} (chosen from the first non-black image, max {mx:.6g})")
            elif mx * self._scale > 255.5:
                self._warn_clip(f"max {mx:.6g} > {255.0 / self._scale:.6g}")
            out = np.nan_to_num(img.astype(np.float32) * self._scale, nan=0.0, posinf=255, neginf=0)
            return np.clip(out + 0.5, 0, 255).astype(np.uint8)
        if img.dtype.kind == "i" and img.dtype.itemsize == 1:
            return np.clip(img.astype(np.int16), 0, 127).astype(np.uint8) * 2
        raise InputError(f"{self.where}: images of dtype {img.dtype} cannot be used as camera frames")

    def _warn_clip(self, detail: str) -> None:
        if not self._clip_warned:
            self._clip_warned = True
            self._note(f"{self.where}: an image is brighter than the 8-bit mapping chosen from the "
                       f"first images ({detail}): bright pixels saturate (reported once)")

    def _note(self, msg: str) -> None:
        if self.warn is not None:
            self.warn(msg)
