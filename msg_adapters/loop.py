"""The loop closer's messages: render requests and replies between ``loop_closer_node`` and
``mapper_node``, and the accepted loop constraints. Standard ``common_interfaces`` messages only.

Render request: ``/vings/render/request``, ``geometry_msgs/PoseStamped`` (loop closer -> mapper)

================================  ==============================================================
field                             content
================================  ==============================================================
``header.stamp``                  the request id, as a time in ns (> 0; the requester numbers its
                                  requests upwards from its start time)
``header.frame_id``               ``<world frame>[;older_than=<ns>][;width=<W>;height=<H>;fx=<fx>;``
                                  ``fy=<fy>;cx=<cx>;cy=<cy>]``: ``older_than`` (an integer): render
                                  only the Gaussians whose keyframe ID(g) has a stamp < ``<ns>``
                                  (absent: every Gaussian); the pinhole camera to render with
                                  (undistorted; absent: the mapper's keyframe camera); numbers
                                  written with Python's ``repr`` (exact)
``pose``                          ``T_wc`` of the camera to render from, in the world frame
================================  ==============================================================

Render reply: three ``sensor_msgs/Image`` (mapper -> loop closer), every one stamped with the
request id (``header.stamp``), ``header.frame_id`` = the camera frame, at the request's camera (or
the mapper's keyframe camera):

==============================  =========================================================
topic                           content
==============================  =========================================================
/vings/render/reply/color       ``32FC3``: RGB in [0, 1], float32 (``rgb8`` accepted too)
/vings/render/reply/depth       ``32FC1``: expected z-depth in metres, 0 where empty
/vings/render/reply/alpha       ``32FC1``: accumulated opacity in [0, 1]
==============================  =========================================================

A reply whose three images are 0 x 0 says "no map to render" (no keyframe mapped yet): the
requester need not wait for its timeout.

Loop constraint: ``/vings/loop/constraints``, ``nav_msgs/Path``, one message per accepted loop
(loop closer -> users):

=====================================  =========================================================
field                                  content
=====================================  =========================================================
``header.stamp``                       the newer keyframe's stamp
``header.frame_id``                    the world frame
``poses[0]``                           the older keyframe: ``header.stamp`` its stamp,
                                       ``header.frame_id`` the world frame, ``pose`` its ``T_wc``
                                       after the loop's correction
``poses[1]``                           the loop measurement: ``header.stamp`` the newer keyframe's
                                       stamp, ``pose`` = ``poses[0].pose * T_on`` (rigid part): where
                                       the loop puts the newer camera, so ``T_on``'s rotation and
                                       translation are ``inverse(poses[0]) * poses[1]``;
                                       ``header.frame_id`` = ``<world frame>;scale=<s>;key=value;...``:
                                       ``scale`` is ``T_on``'s scale (1 for an SE(3) graph), then the
                                       verdict figures (below)
=====================================  =========================================================

``T_on = [[s R, t], [0, 1]]`` is the pose of the newer keyframe in the older keyframe's camera frame,
``t`` in the older keyframe's units (vings_core/loop/verify.py). Figures in ``poses[1].header.frame_id``
(numbers written with Python's ``repr``, so they read back exactly; words for the rest):
``matches``, ``with_depth``, ``inliers`` (PnP), ``pnp_scale``, ``render_l1``, ``coverage``,
``distance``, ``bow_score``, ``sources`` (``radius``/``retrieval``, joined by ``+``), ``graph``
(``sim3``/``se3``), ``moved`` (keyframes corrected), ``newer_shift``, ``newer_scale``,
``error_before``, ``error_after`` (the pose graph's). RViz's Path display draws each loop as a
segment from the older keyframe to the measured newer camera (it uses the Path's frame only).
"""
from __future__ import annotations

import array
import re
from dataclasses import dataclass, field
from typing import Any, Optional, Union

import numpy as np
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Path
from sensor_msgs.msg import Image

from vings_core.errors import InputError
from vings_core.geometry import np_pose_inverse, sim3, sim3_scale
from vings_core.types import CameraModel

from .image import float_image_to_msg, msg_to_float_image, msg_to_image, uint8_to_rgb_float
from .pose import matrix_to_pose, pose_to_matrix
from .stamps import header_ns, make_header
from .topics import CAMERA_FRAME, WORLD_FRAME

RENDER_REQUEST_TOPIC = "/vings/render/request"
RENDER_REPLY_COLOR_TOPIC = "/vings/render/reply/color"
RENDER_REPLY_DEPTH_TOPIC = "/vings/render/reply/depth"
RENDER_REPLY_ALPHA_TOPIC = "/vings/render/reply/alpha"
#: the reply's parts and their topics
REPLY_PARTS = ("color", "depth", "alpha")
REPLY_TOPICS = {"color": RENDER_REPLY_COLOR_TOPIC, "depth": RENDER_REPLY_DEPTH_TOPIC,
                "alpha": RENDER_REPLY_ALPHA_TOPIC}
LOOP_CONSTRAINTS_TOPIC = "/vings/loop/constraints"

#: key of the render bound in a request's frame_id
OLDER_THAN_KEY = "older_than"
#: keys of the render camera in a request's frame_id (all or none)
CAMERA_KEYS = ("width", "height", "fx", "fy", "cx", "cy")
#: figures of a constraint written in ``poses[1].header.frame_id``, in this order
CONSTRAINT_FIGURES = ("matches", "with_depth", "inliers", "pnp_scale", "render_l1", "coverage", "distance",
                      "bow_score", "sources", "graph", "moved", "newer_shift", "newer_scale",
                      "error_before", "error_after")

_WORD = re.compile(r"^[A-Za-z_][A-Za-z0-9_+\-.]*$")
_INT = re.compile(r"^[+-]?[0-9]+$")


# ----------------------------------------------------------------------------- key=value frames


def _format_value(v: Any, where: str) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        return repr(float(v))
    s = str(v)
    if not _WORD.match(s) or s in ("true", "false"):
        raise InputError(f"{where}: value {s!r} cannot travel in a frame_id (a number or a word of "
                         f"letters, digits, _ + - .)")
    return s


def _parse_value(s: str) -> Union[int, float, str, bool]:
    if s in ("true", "false"):
        return s == "true"
    if _INT.match(s):
        return int(s)
    try:
        return float(s)
    except ValueError:
        return s


def _frame_with_keys(frame: str, values: dict, where: str) -> str:
    if not frame or ";" in frame or "=" in frame:
        raise InputError(f"{where}: frame id {frame!r} must be non-empty without ';' or '='")
    parts = [frame]
    for k, v in values.items():
        if v is None:
            continue
        if not _WORD.match(k):
            raise InputError(f"{where}: key {k!r} is not a word")
        parts.append(f"{k}={_format_value(v, f'{where}.{k}')}")
    return ";".join(parts)


def _split_frame(frame_id: str, where: str) -> tuple[str, dict]:
    """``<frame>;k=v;...`` -> ``(frame, {k: value})``."""
    head, *rest = str(frame_id).split(";")
    if not head or "=" in head:
        raise InputError(f"{where}: {frame_id!r} does not start with a frame id")
    out: dict = {}
    for item in rest:
        k, sep, v = item.partition("=")
        if not sep or not k or not v:
            raise InputError(f"{where}: {item!r} in {frame_id!r} is not key=value")
        if k in out:
            raise InputError(f"{where}: key {k!r} given twice in {frame_id!r}")
        out[k] = _parse_value(v)
    return head, out


# ------------------------------------------------------------------------------ render request


@dataclass
class RenderRequest:
    """``request_id`` > 0; ``T_wc`` 4x4 rigid camera-to-world; ``older_than``: render only the
    Gaussians whose keyframe stamp is below it (None: all); ``camera``: the undistorted pinhole
    camera to render with (None: the mapper's keyframe camera)."""

    request_id: int
    T_wc: np.ndarray
    older_than: Optional[int] = None
    camera: Optional[CameraModel] = None


def render_request_to_msg(req: RenderRequest, frame_id: str = WORLD_FRAME) -> PoseStamped:
    """Request -> ``geometry_msgs/PoseStamped`` (table in the module docstring)."""
    where = RENDER_REQUEST_TOPIC
    if int(req.request_id) <= 0:
        raise InputError(f"{where}: request id must be > 0, got {req.request_id}")
    keys: dict = {} if req.older_than is None else {OLDER_THAN_KEY: int(req.older_than)}
    cam = req.camera
    if cam is not None:
        if cam.is_distorted:
            raise InputError(f"{where}: the render camera must be undistorted, got {cam.distortion_model!r}")
        keys.update(width=int(cam.width), height=int(cam.height), fx=float(cam.fx), fy=float(cam.fy),
                    cx=float(cam.cx), cy=float(cam.cy))
    return PoseStamped(header=make_header(int(req.request_id), _frame_with_keys(frame_id, keys, where), where),
                       pose=matrix_to_pose(np.asarray(req.T_wc, np.float64), f"{where}.pose"))


def msg_to_render_request(msg: PoseStamped, where: str = RENDER_REQUEST_TOPIC) -> RenderRequest:
    """``PoseStamped`` -> request; a malformed one raises :class:`InputError` naming the field."""
    rid = header_ns(msg.header, f"{where}.header")
    if rid <= 0:
        raise InputError(f"{where}.header.stamp: the request id must be > 0, got {rid}")
    at = f"{where}.header.frame_id"
    _, keys = _split_frame(msg.header.frame_id, at)
    unknown = set(keys) - {OLDER_THAN_KEY, *CAMERA_KEYS}
    if unknown:
        raise InputError(f"{at}: unknown key(s) {sorted(unknown)}; expected {OLDER_THAN_KEY}, "
                         f"{', '.join(CAMERA_KEYS)}")
    older = keys.get(OLDER_THAN_KEY)
    if older is not None and (isinstance(older, bool) or not isinstance(older, int)):
        raise InputError(f"{at}: {OLDER_THAN_KEY} must be an integer stamp (ns), got {older!r}")
    cam = None
    given = [k for k in CAMERA_KEYS if k in keys]
    if given:
        if len(given) != len(CAMERA_KEYS):
            raise InputError(f"{at}: the render camera needs all of {', '.join(CAMERA_KEYS)}, got "
                             f"{', '.join(given)}")
        w, h = keys["width"], keys["height"]
        nums = [keys[k] for k in ("fx", "fy", "cx", "cy")]
        if any(isinstance(v, bool) or not isinstance(v, int) or v < 1 for v in (w, h)) or \
                any(isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v) for v in nums) \
                or not (nums[0] > 0 and nums[1] > 0):
            raise InputError(f"{at}: render camera width/height must be integers >= 1 and fx, fy > 0, cx, cy "
                             f"finite numbers, got {[keys[k] for k in CAMERA_KEYS]}")
        cam = CameraModel(int(w), int(h), *(float(v) for v in nums))
    return RenderRequest(rid, pose_to_matrix(msg.pose, f"{where}.pose"), older, cam)


# ------------------------------------------------------------------------------- render reply


@dataclass
class RenderReply:
    """A reply: ``color`` (H, W, 3) float32 in [0, 1], ``depth`` (H, W) metres, ``alpha`` (H, W);
    all None for the "no map to render" reply (:attr:`empty`)."""

    request_id: int
    color: Optional[np.ndarray] = None
    depth: Optional[np.ndarray] = None
    alpha: Optional[np.ndarray] = None

    @property
    def empty(self) -> bool:
        return self.color is None

    def as_dict(self) -> Optional[dict]:
        """``{"color", "depth", "alpha"}`` as ``Mapper.render`` gives them (None when empty)."""
        return None if self.empty else {"color": self.color, "depth": self.depth, "alpha": self.alpha}


def color32_to_msg(img: Any, stamp_ns: int, frame_id: str, where: str = "image") -> Image:
    """float ``(H, W, 3)`` RGB -> ``32FC3`` Image (little-endian, ``step = 12 W``): exact."""
    a = np.asarray(img)
    if a.ndim != 3 or a.shape[2] != 3 or not np.issubdtype(a.dtype, np.number):
        raise InputError(f"{where}: a 32FC3 image needs a numeric (H, W, 3) array, got {a.dtype} {a.shape}")
    a = np.ascontiguousarray(a, dtype="<f4")
    msg = Image(header=make_header(stamp_ns, frame_id, where), height=int(a.shape[0]), width=int(a.shape[1]),
                encoding="32FC3", is_bigendian=0, step=int(a.shape[1]) * 12)
    data = array.array("B")
    data.frombytes(a.tobytes())
    msg.data = data
    return msg


def msg_to_color32(msg: Image, where: str = "image") -> np.ndarray:
    """``32FC3`` (either byte order, row padding honoured) or ``rgb8`` Image -> float32 (H, W, 3)."""
    enc = str(msg.encoding)
    if enc == "rgb8":
        return uint8_to_rgb_float(msg_to_image(msg, where))
    if enc != "32FC3":
        raise InputError(f"{where}: encoding {enc!r} is not supported here; expected 32FC3 or rgb8")
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    buf = np.frombuffer(msg.data, np.uint8)
    if step < 12 * w or buf.size != step * h:
        raise InputError(f"{where}: data holds {buf.size} bytes but step {step} x height {h} = {step * h} "
                         f"(step must be >= 12 x width {w})")
    rows = buf.reshape(h, step)[:, :12 * w] if h else np.zeros((0, 12 * w), np.uint8)
    dt = np.dtype(">f4" if msg.is_bigendian else "<f4")
    return np.ascontiguousarray(rows).view(dt).reshape(h, w, 3).astype(np.float32)


def _empty_image(stamp_ns: int, frame_id: str, encoding: str, where: str) -> Image:
    return Image(header=make_header(stamp_ns, frame_id, where), height=0, width=0, encoding=encoding,
                 is_bigendian=0, step=0)


def render_reply_to_msgs(request_id: int, out: Optional[dict], frame_id: str = CAMERA_FRAME) -> dict:
    """A render (``Mapper.render``'s dict, ``color``/``depth``/``alpha`` used; None: no map) ->
    ``{part: Image}`` stamped with the request id."""
    rid = int(request_id)
    if out is None:
        return {p: _empty_image(rid, frame_id, "32FC3" if p == "color" else "32FC1", REPLY_TOPICS[p])
                for p in REPLY_PARTS}
    return {"color": color32_to_msg(out["color"], rid, frame_id, RENDER_REPLY_COLOR_TOPIC),
            "depth": float_image_to_msg(out["depth"], rid, frame_id, RENDER_REPLY_DEPTH_TOPIC),
            "alpha": float_image_to_msg(out["alpha"], rid, frame_id, RENDER_REPLY_ALPHA_TOPIC)}


def msgs_to_render_reply(color: Image, depth: Image, alpha: Image) -> RenderReply:
    """The three parts -> reply; ids and sizes must agree (all 0 x 0: the empty reply)."""
    msgs = {"color": color, "depth": depth, "alpha": alpha}
    ids = {p: header_ns(m.header, f"{REPLY_TOPICS[p]}.header") for p, m in msgs.items()}
    rid = ids["color"]
    if any(v != rid for v in ids.values()):
        raise InputError(f"render reply parts have different request ids: {ids}")
    sizes = {p: (int(m.width), int(m.height)) for p, m in msgs.items()}
    if len(set(sizes.values())) != 1:
        raise InputError(f"render reply {rid}: parts have different sizes {sizes}")
    if sizes["color"][0] == 0 or sizes["color"][1] == 0:
        return RenderReply(rid)
    c = msg_to_color32(color, RENDER_REPLY_COLOR_TOPIC)
    d = msg_to_float_image(depth, RENDER_REPLY_DEPTH_TOPIC)
    a = msg_to_float_image(alpha, RENDER_REPLY_ALPHA_TOPIC)
    return RenderReply(rid, c, d, a)


class RenderReplyAssembler:
    """Pairs the three reply parts by request id (they travel on three topics); ``add(part, msg)``
    returns the :class:`RenderReply` once complete. At most ``max_pending`` incomplete replies are
    held (the oldest ids evicted and counted in ``dropped``)."""

    def __init__(self, max_pending: int = 8) -> None:
        self.max_pending = int(max_pending)
        self._pending: dict[int, dict[str, Image]] = {}
        self.dropped = 0

    @property
    def pending(self) -> int:
        return len(self._pending)

    def add(self, part: str, msg: Image) -> Optional[RenderReply]:
        if part not in REPLY_PARTS:
            raise InputError(f"render reply: unknown part {part!r}; expected one of {REPLY_PARTS}")
        rid = header_ns(msg.header, f"{REPLY_TOPICS[part]}.header")
        slot = self._pending.setdefault(rid, {})
        slot[part] = msg
        if len(slot) < len(REPLY_PARTS):
            while len(self._pending) > self.max_pending:
                del self._pending[min(self._pending)]
                self.dropped += 1
            return None
        del self._pending[rid]
        return msgs_to_render_reply(slot["color"], slot["depth"], slot["alpha"])


# ---------------------------------------------------------------------------- loop constraints


@dataclass
class LoopConstraint:
    """An accepted loop: keyframe stamps ``older`` < ``newer``; ``T_on`` the 4x4 similarity of the
    newer keyframe in the older one's camera frame; ``T_wc_older`` the older keyframe's (rigid)
    pose after the correction; ``figures``: the verdict figures (numbers or words)."""

    older: int
    newer: int
    T_on: np.ndarray
    T_wc_older: np.ndarray
    figures: dict = field(default_factory=dict)

    @property
    def scale(self) -> float:
        return sim3_scale(self.T_on)


def constraint_from_record(older: int, newer: int, T_on: np.ndarray, T_wc_older: np.ndarray,
                           record: dict) -> LoopConstraint:
    """A constraint with the figures of the loop closer's accepted record (``LoopCloser.records``
    entry, with its ``correction``)."""
    corr = record.get("correction") or {}
    fig: dict = {"pnp_scale": record.get("scale")}
    for k in ("matches", "with_depth", "inliers", "render_l1", "coverage", "distance", "bow_score"):
        fig[k] = record.get(k)
    fig["sources"] = "+".join(record.get("sources") or []) or None
    for k in ("graph", "moved", "newer_shift", "newer_scale", "error_before", "error_after"):
        fig[k] = corr.get(k)
    fig = {k: fig[k] for k in CONSTRAINT_FIGURES if fig.get(k) is not None
           and not (isinstance(fig[k], float) and not np.isfinite(fig[k]))}
    return LoopConstraint(int(older), int(newer), np.asarray(T_on, np.float64),
                          np.asarray(T_wc_older, np.float64), fig)


def loop_constraint_to_path(c: LoopConstraint, frame_id: str = WORLD_FRAME) -> Path:
    """Constraint -> ``nav_msgs/Path`` (table in the module docstring)."""
    where = LOOP_CONSTRAINTS_TOPIC
    s = sim3_scale(c.T_on)
    if not (np.isfinite(c.T_on).all() and s > 0):
        raise InputError(f"{where}: T_on is not a finite similarity")
    R = c.T_on[:3, :3] / s
    rigid = sim3(R, c.T_on[:3, 3], 1.0)
    T0 = np.asarray(c.T_wc_older, np.float64)
    keys = {"scale": float(s), **{k: c.figures[k] for k in CONSTRAINT_FIGURES if k in c.figures},
            **{k: v for k, v in c.figures.items() if k not in CONSTRAINT_FIGURES and k != "scale"}}
    msg = Path(header=make_header(int(c.newer), frame_id, where))
    msg.poses.append(PoseStamped(header=make_header(int(c.older), frame_id, f"{where}.poses[0]"),
                                 pose=matrix_to_pose(T0, f"{where}.poses[0].pose")))
    msg.poses.append(PoseStamped(header=make_header(int(c.newer), _frame_with_keys(frame_id, keys, where),
                                                    f"{where}.poses[1]"),
                                 pose=matrix_to_pose(T0 @ rigid, f"{where}.poses[1].pose")))
    return msg


def path_to_loop_constraint(msg: Path, where: str = LOOP_CONSTRAINTS_TOPIC) -> LoopConstraint:
    """``nav_msgs/Path`` from ``/vings/loop/constraints`` -> constraint; :class:`InputError` naming
    the field when malformed."""
    if len(msg.poses) != 2:
        raise InputError(f"{where}.poses: a loop constraint has 2 poses, got {len(msg.poses)}")
    newer = header_ns(msg.header, f"{where}.header")
    older = header_ns(msg.poses[0].header, f"{where}.poses[0].header")
    n1 = header_ns(msg.poses[1].header, f"{where}.poses[1].header")
    if n1 != newer:
        raise InputError(f"{where}.poses[1].header.stamp: {n1} is not the newer keyframe {newer}")
    _, keys = _split_frame(msg.poses[1].header.frame_id, f"{where}.poses[1].header.frame_id")
    s = keys.pop("scale", None)
    if isinstance(s, bool) or not isinstance(s, (int, float)) or not (np.isfinite(s) and s > 0):
        raise InputError(f"{where}.poses[1].header.frame_id: scale must be a number > 0, got {s!r}")
    T0 = pose_to_matrix(msg.poses[0].pose, f"{where}.poses[0].pose")
    T1 = pose_to_matrix(msg.poses[1].pose, f"{where}.poses[1].pose")
    rel = np_pose_inverse(T0) @ T1
    return LoopConstraint(older, newer, sim3(rel[:3, :3], rel[:3, 3], float(s)), T0, keys)


__all__ = ["RENDER_REQUEST_TOPIC", "RENDER_REPLY_COLOR_TOPIC", "RENDER_REPLY_DEPTH_TOPIC",
           "RENDER_REPLY_ALPHA_TOPIC", "REPLY_PARTS", "REPLY_TOPICS", "LOOP_CONSTRAINTS_TOPIC",
           "CONSTRAINT_FIGURES", "RenderRequest", "render_request_to_msg", "msg_to_render_request",
           "RenderReply", "color32_to_msg", "msg_to_color32", "render_reply_to_msgs", "msgs_to_render_reply",
           "RenderReplyAssembler", "LoopConstraint", "constraint_from_record", "loop_constraint_to_path",
           "path_to_loop_constraint"]
