"""Keyframe packets: one :class:`vings_core.types.Keyframe` <-> five messages with the same stamp.

=======================  ====================  ================================================
topic                    type                  content
=======================  ====================  ================================================
/vings/keyframe/image    sensor_msgs/Image     rgb8 (``Keyframe.image`` * 255, rounded)
/vings/keyframe/depth    sensor_msgs/Image     32FC1 z-depth (m), 0 where ``valid`` is False
/vings/keyframe/inv_depth_var  Image           32FC1 variance of inverse depth (1/m^2)
/vings/keyframe/pose     geometry_msgs/PoseStamped  ``T_wc`` in ``map``
/vings/keyframe/camera_info    CameraInfo      the (undistorted) working-resolution camera
=======================  ====================  ================================================

Every part carries the keyframe's image stamp, which is the keyframe's identity. On the way back
``valid = depth > 0``. No message_filters wheel exists here, so :class:`KeyframeAssembler` pairs the
parts by stamp.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Optional

import numpy as np
import torch
from geometry_msgs.msg import PoseStamped
from sensor_msgs.msg import CameraInfo, Image

from vings_core.errors import InputError
from vings_core.types import CameraModel, Keyframe

from .camera_info import camera_info_to_camera, camera_to_camera_info
from .image import (float_image_to_msg, image_to_msg, msg_to_float_image, msg_to_image,
                    rgb_float_to_uint8, uint8_to_rgb_float)
from .pose import matrix_to_pose_stamped, pose_stamped_to_matrix
from .stamps import header_ns
from .topics import (CAMERA_FRAME, KEYFRAME_DEPTH_TOPIC, KEYFRAME_IMAGE_TOPIC, KEYFRAME_INFO_TOPIC,
                     KEYFRAME_POSE_TOPIC, KEYFRAME_VAR_TOPIC, WORLD_FRAME)

PARTS = ("image", "depth", "inv_depth_var", "pose", "camera_info")
PART_TOPICS = {"image": KEYFRAME_IMAGE_TOPIC, "depth": KEYFRAME_DEPTH_TOPIC,
               "inv_depth_var": KEYFRAME_VAR_TOPIC, "pose": KEYFRAME_POSE_TOPIC,
               "camera_info": KEYFRAME_INFO_TOPIC}


@dataclass
class KeyframeMessages:
    image: Image
    depth: Image
    inv_depth_var: Image
    pose: PoseStamped
    camera_info: CameraInfo

    def as_dict(self) -> dict:
        return {p: getattr(self, p) for p in PARTS}


def keyframe_to_msgs(kf: Keyframe, camera_frame: str = CAMERA_FRAME,
                     world_frame: str = WORLD_FRAME) -> KeyframeMessages:
    """The five messages of a keyframe, all stamped with ``kf.stamp_ns``."""
    s = int(kf.stamp_ns)
    valid = kf.valid.detach().cpu().numpy().astype(bool)
    depth = kf.depth.detach().cpu().numpy().astype(np.float32, copy=True)
    depth[~valid] = 0.0
    return KeyframeMessages(
        image=image_to_msg(rgb_float_to_uint8(kf.image), s, camera_frame, PART_TOPICS["image"]),
        depth=float_image_to_msg(depth, s, camera_frame, PART_TOPICS["depth"]),
        inv_depth_var=float_image_to_msg(kf.inv_depth_var, s, camera_frame,
                                         PART_TOPICS["inv_depth_var"]),
        pose=matrix_to_pose_stamped(kf.T_wc.detach().cpu().numpy(), s, world_frame,
                                    PART_TOPICS["pose"]),
        camera_info=camera_to_camera_info(kf.camera, s, camera_frame,
                                          PART_TOPICS["camera_info"]))


def msgs_to_keyframe(image: Image, depth: Image, inv_depth_var: Image, pose: PoseStamped,
                     camera_info: Optional[CameraInfo] = None,
                     camera: Optional[CameraModel] = None, index: int = -1) -> Keyframe:
    """Five parts (or four plus a known ``camera``) -> Keyframe; stamps and sizes must agree."""
    parts = {"image": image, "depth": depth, "inv_depth_var": inv_depth_var, "pose": pose}
    if camera_info is not None:
        parts["camera_info"] = camera_info
    stamps = {k: header_ns(m.header, f"{PART_TOPICS[k]}.header") for k, m in parts.items()}
    s = stamps["image"]
    if any(v != s for v in stamps.values()):
        raise InputError(f"keyframe parts have different stamps: {stamps}")
    if camera_info is not None:
        camera = camera_info_to_camera(camera_info, PART_TOPICS["camera_info"])
    if camera is None:
        raise InputError("keyframe: no camera model (neither camera_info nor a calibration)")
    if camera.is_distorted:
        raise InputError(f"{PART_TOPICS['camera_info']}: keyframes must be undistorted, got "
                         f"distortion_model {camera.distortion_model!r}")
    img = msg_to_image(image, PART_TOPICS["image"])
    if img.dtype != np.uint8:
        raise InputError(f"{PART_TOPICS['image']}: keyframe images must be 8-bit (mono8/rgb8/bgr8), "
                         f"got encoding {image.encoding!r}")
    d = msg_to_float_image(depth, PART_TOPICS["depth"])
    var = msg_to_float_image(inv_depth_var, PART_TOPICS["inv_depth_var"])
    for k, a in (("image", img), ("depth", d), ("inv_depth_var", var)):
        if (a.shape[1], a.shape[0]) != (camera.width, camera.height):
            raise InputError(f"{PART_TOPICS[k]}: image is {a.shape[1]}x{a.shape[0]} but the "
                             f"keyframe camera is {camera.width}x{camera.height}")
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=2)
    _, T = pose_stamped_to_matrix(pose, PART_TOPICS["pose"])
    if bool((var < 0).any()):
        raise InputError(f"{PART_TOPICS['inv_depth_var']}: {int((var < 0).sum())} negative variances "
                         f"(a variance is >= 0; use inf or NaN for unknown)")
    var = np.where(np.isnan(var), np.float32(np.inf), var)    # NaN = unknown, the mapper's inf
    valid = np.isfinite(d) & (d > 0)
    d = np.where(valid, d, np.float32(0.0))
    return Keyframe(stamp_ns=s, image=torch.from_numpy(uint8_to_rgb_float(img)),
                    T_wc=torch.from_numpy(T), depth=torch.from_numpy(d),
                    inv_depth_var=torch.from_numpy(var), valid=torch.from_numpy(valid),
                    camera=camera, index=int(index))


class KeyframeAssembler:
    """Collects keyframe parts arriving on separate topics and yields complete keyframes.

    ``add(part, msg)`` returns the :class:`Keyframe` once every required part of its stamp is
    there. Each topic is delivered in order (one reliable writer), so when the packet of stamp
    ``s`` completes, older incomplete packets can no longer complete: they are discarded and
    counted in ``dropped``. At most ``max_pending`` incomplete packets are held (oldest evicted).
    With a fixed ``camera`` the camera_info part is not required.
    """

    def __init__(self, camera: Optional[CameraModel] = None, max_pending: int = 8) -> None:
        self.camera = camera
        self.max_pending = int(max_pending)
        self.required = tuple(p for p in PARTS if not (camera is not None and p == "camera_info"))
        self._pending: dict[int, dict[str, Any]] = {}
        self.dropped = 0
        self.completed = 0

    @property
    def pending(self) -> int:
        return len(self._pending)

    def add(self, part: str, msg: Any) -> Optional[Keyframe]:
        if part not in PARTS:
            raise InputError(f"keyframe: unknown part {part!r}; expected one of {PARTS}")
        if part not in self.required:
            return None
        s = header_ns(msg.header, f"{PART_TOPICS[part]}.header")
        slot = self._pending.setdefault(s, {})
        slot[part] = msg
        if len(slot) < len(self.required):
            while len(self._pending) > self.max_pending:
                del self._pending[min(self._pending)]
                self.dropped += 1
            return None
        del self._pending[s]
        stale = [t for t in self._pending if t < s]
        for t in stale:
            del self._pending[t]
        self.dropped += len(stale)
        self.completed += 1
        return msgs_to_keyframe(slot["image"], slot["depth"], slot["inv_depth_var"],
                                slot["pose"], slot.get("camera_info"), camera=self.camera)


__all__ = ["PARTS", "PART_TOPICS", "KeyframeMessages", "keyframe_to_msgs", "msgs_to_keyframe",
           "KeyframeAssembler"]
