"""The dynamic eraser's message: a keyframe's dynamic mask (``eraser_node`` -> ``mapper_node``,
``frontend_node``). A standard ``sensor_msgs/Image``.

Dynamic mask: ``/vings/keyframe/dynamic_mask``, ``sensor_msgs/Image``, one per keyframe the eraser
processed (the mask of a keyframe without moving objects is all 0, and is sent too: the mapper
waits for it):

================================  ==============================================================
field                             content
================================  ==============================================================
``header.stamp``                  the keyframe's image stamp (its identity on every keyframe topic)
``header.frame_id``               the camera frame
``encoding``                      ``mono8``: 255 = dynamic (a moving object), 0 = static; on input
                                  every value > 127 is dynamic
``width``, ``height``             the keyframe's working resolution (the keyframe packet's camera)
``step``, ``is_bigendian``        ``width`` (no row padding; padding is honoured on input), 0
================================  ==============================================================

The pixels are those of ``vings_core.eraser.mask_io`` (``masks/kf_<stamp>.png`` of ``vings run``).
"""
from __future__ import annotations

from typing import Any

import numpy as np
from sensor_msgs.msg import Image

from vings_core.eraser.mask_io import mask_to_mono8, mono8_to_mask
from vings_core.errors import InputError

from .image import array_to_msg, msg_to_image
from .stamps import header_ns
from .topics import CAMERA_FRAME, DYNAMIC_MASK_TOPIC


def mask_to_msg(mask: Any, stamp_ns: int, frame_id: str = CAMERA_FRAME,
                where: str = DYNAMIC_MASK_TOPIC) -> Image:
    """``(H, W)`` bool mask (True = dynamic; numpy or torch) of keyframe ``stamp_ns`` -> ``mono8``
    Image (255 where True)."""
    m = mask.detach().cpu().numpy() if hasattr(mask, "detach") else np.asarray(mask)
    if m.ndim != 2 or m.dtype != np.bool_:
        raise InputError(f"{where}: a dynamic mask is a bool (H, W) array, got {m.dtype} {m.shape}")
    if m.shape[0] < 1 or m.shape[1] < 1:
        raise InputError(f"{where}: a dynamic mask needs at least one pixel, got {m.shape}")
    return array_to_msg(mask_to_mono8(m), int(stamp_ns), frame_id, where)


def msg_to_mask(msg: Image, where: str = DYNAMIC_MASK_TOPIC) -> tuple[int, np.ndarray]:
    """``mono8`` Image -> ``(stamp_ns, (H, W) bool mask)``; anything else (another encoding, an
    empty image, a bad size) raises :class:`InputError` naming ``where``."""
    stamp = header_ns(msg.header, f"{where}.header")
    if str(msg.encoding) != "mono8":
        raise InputError(f"{where}: a dynamic mask is mono8, got encoding {msg.encoding!r}")
    if int(msg.width) < 1 or int(msg.height) < 1:
        raise InputError(f"{where}: a dynamic mask needs at least one pixel, got "
                         f"{int(msg.width)}x{int(msg.height)}")
    img = msg_to_image(msg, where)
    try:
        return stamp, mono8_to_mask(img, where)
    except ValueError as e:
        raise InputError(str(e)) from None


__all__ = ["DYNAMIC_MASK_TOPIC", "mask_to_msg", "msg_to_mask"]
